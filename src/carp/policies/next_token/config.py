"""Config of the next-token autoregressive family: one frozen dataclass, validated at construction.

It is the family's params section (`next_token`) and what its checkpoint stores; the token choice at evaluation is
the separate section `inference.next_token` (:class:`NextTokenInference`). The transformer's defaults are CARP's
(`carp.policies.carp.config.CarpConfig`), so that the two families differ only in how many tokens a step predicts.
Shapes that come from the data and the tokenizer (`Do`, `To`, `A`, scales, `V`) are passed to the model separately;
loop settings shared by every family (epochs, batch size, checkpoints, seed) are the `training` section.
"""

from dataclasses import dataclass, field
from typing import Any

from carp.config import TASK_NAMES, ConfigError, _require

SECTION = "next_token"


def _require_positive_int(name: str, value: Any, section: str = SECTION) -> None:
    _require(
        isinstance(value, int) and not isinstance(value, bool) and value >= 1,
        f"{section}.{name}",
        value,
        "must be an integer >= 1",
    )


@dataclass(frozen=True)
class NextTokenConfig:
    """The next-token transformer (`carp.policies.next_token.transformer`) and its optimizer.

    Attributes:
        depth: Transformer blocks; an integer >= 1.
        width: ``D``, token and conditioning width; an integer >= 1 divisible by ``num_heads``.
        num_heads: Attention heads per block; an integer >= 1 that divides ``width``.
        mlp_ratio: Hidden width of each feed-forward layer as a multiple of ``width``; a number > 0.
        dropout: Dropout probability of attention weights and residual branches during training; a number in [0, 1).
        learning_rate: Peak AdamW learning rate, reached after a linear warm-up and followed by a cosine decay to 1%
            of the peak; a number > 0.
        weight_decay: AdamW weight decay of the weight matrices (biases and embeddings are not decayed); a number
            >= 0.
        warmup_steps: Optimizer steps of linear learning-rate warm-up; an integer >= 0.
        use_ema: Keep an exponential moving average of the weights during training and save it instead of the raw
            weights; true or false.
        ema_decay: Decay of the moving average per optimizer step, used only with ``use_ema``; a number in (0, 1).
    """

    depth: int = 8
    width: int = 64
    num_heads: int = 8
    mlp_ratio: float = 4.0
    dropout: float = 0.0
    learning_rate: float = 1e-3
    weight_decay: float = 0.05
    warmup_steps: int = 100
    use_ema: bool = False
    ema_decay: float = 0.999

    def __post_init__(self) -> None:
        for name in ("depth", "width", "num_heads"):
            _require_positive_int(name, getattr(self, name))
        _require(
            self.width % self.num_heads == 0, f"{SECTION}.num_heads", self.num_heads, f"must divide width={self.width}"
        )
        _require(self.mlp_ratio > 0, f"{SECTION}.mlp_ratio", self.mlp_ratio, "must be > 0")
        _require(0.0 <= self.dropout < 1.0, f"{SECTION}.dropout", self.dropout, "must be in [0, 1)")
        _require(self.learning_rate > 0, f"{SECTION}.learning_rate", self.learning_rate, "must be > 0")
        _require(self.weight_decay >= 0, f"{SECTION}.weight_decay", self.weight_decay, "must be >= 0")
        _require(
            isinstance(self.warmup_steps, int) and self.warmup_steps >= 0,
            f"{SECTION}.warmup_steps",
            self.warmup_steps,
            "must be an integer >= 0",
        )
        _require(isinstance(self.use_ema, bool), f"{SECTION}.use_ema", self.use_ema, "must be true or false")
        _require(0.0 < self.ema_decay < 1.0, f"{SECTION}.ema_decay", self.ema_decay, "must be in (0, 1)")

    @property
    def hidden_width(self) -> int:
        """Hidden width of the feed-forward layers."""
        return round(self.width * self.mlp_ratio)


@dataclass(frozen=True)
class NextTokenInference:
    """How evaluation chooses the next-token policy's tokens; decoding only, so a change reruns evaluation.

    Attributes:
        top_k: 1 takes the most likely token (greedy); k > 1 draws among the k most likely ones, with draws seeded
            per episode. An integer between 1 and ``codebook_size``.
        top_k_per_task: Task -> token choice when evaluating that task, overriding ``top_k``; each an integer between
            1 and ``codebook_size``, tasks among lift, can and square.
    """

    top_k: int = 1
    top_k_per_task: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        key = f"inference.{SECTION}"
        _require_positive_int("top_k", self.top_k, key)
        for task, top_k in self.top_k_per_task.items():
            _require(task in TASK_NAMES, f"{key}.top_k_per_task.{task}", task, f"task must be one of {TASK_NAMES}")
            _require(top_k >= 1, f"{key}.top_k_per_task.{task}", top_k, "must be >= 1 (1 = greedy)")

    def settings_for(self, task: str) -> dict[str, Any]:
        """Keyword arguments of `NextTokenPolicy.configure_inference` when evaluating `task`."""
        return {"top_k": self.top_k_per_task.get(task, self.top_k)}

    def check_with(self, params: Any) -> None:
        """Refuse a token choice above the vocabulary (`params.codebook_size`)."""
        for task, top_k in [(None, self.top_k), *self.top_k_per_task.items()]:
            if top_k > params.codebook_size:
                name = f"inference.{SECTION}.top_k" + (f"_per_task.{task}" if task else "")
                raise ConfigError(f"{name}={top_k!r}: must be <= codebook_size = {params.codebook_size}")


SECTIONS = (NextTokenConfig, NextTokenInference)
"""The registry's view of this module: the `next_token` and `inference.next_token` sections."""
