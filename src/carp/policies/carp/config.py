"""CARP's params sections: `carp` (the coarse-to-fine transformer and its optimizer) and `inference.carp`.

The two are split so that DVC can tell them apart: `train_policy` tracks `carp`, `evaluate` tracks `inference.carp`,
and a change of the token choice re-evaluates without retraining. The epochs, batch size, checkpoints, seed and
precision of the training loop are the shared `training` section (`carp.config.TrainingConfig`).
"""

from dataclasses import dataclass, field
from typing import Any, ClassVar

from carp.config.checks import ConfigError, _require, require_optimizer_settings, require_positive_int

SECTION = "carp"
ATTENTION_SETTINGS = ("auto", "masked", "blockwise")
"""Values of `carp.attention`: the kernels of `carp.policies.carp.attention`, or auto (timed when training starts)."""


@dataclass(frozen=True)
class TransformerConfig:
    """The AdaLN transformer of the token families and its optimizer: what the CARP and next-token sections share.

    Attributes:
        depth: Transformer blocks; an integer >= 1.
        width: ``D``, width of every token; an integer >= 1, divisible by ``num_heads``.
        num_heads: Attention heads per block; an integer >= 1 that divides ``width``.
        mlp_ratio: Hidden width of each block's feed-forward layer as a multiple of ``width``; a number > 0.
        dropout: Dropout probability of the attention weights and of both residual branches during training; a
            number in [0, 1). Above 0, attention on the CPU leaves PyTorch's fused kernel for one that materializes
            and samples every attention weight, which about doubles a training step of the default transformer.
        learning_rate: Peak AdamW learning rate, reached after ``warmup_steps`` of linear warm-up and followed by a
            cosine decay to 1% of the peak; a number > 0.
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

    SECTION: ClassVar[str] = SECTION

    def __post_init__(self) -> None:
        section = self.SECTION
        for name in ("depth", "width", "num_heads"):
            require_positive_int(f"{section}.{name}", getattr(self, name))
        _require(
            self.width % self.num_heads == 0, f"{section}.num_heads", self.num_heads, f"must divide width={self.width}"
        )
        _require(self.mlp_ratio > 0, f"{section}.mlp_ratio", self.mlp_ratio, "must be > 0")
        _require(0.0 <= self.dropout < 1.0, f"{section}.dropout", self.dropout, "must be in [0, 1)")
        require_optimizer_settings(section, self)
        _require(0.0 < self.ema_decay < 1.0, f"{section}.ema_decay", self.ema_decay, "must be in (0, 1)")

    @property
    def hidden_width(self) -> int:
        """Hidden width of the feed-forward layers."""
        return round(self.width * self.mlp_ratio)


@dataclass(frozen=True)
class CarpConfig(TransformerConfig):
    """The coarse-to-fine transformer (docs/architecture.md, "Coarse-to-fine transformer") and its optimizer.

    Attributes:
        attention: Kernel of the block-causal attention in training: ``masked`` (one fused kernel over the dense
            mask), ``blockwise`` (one unmasked product per scale) or ``auto`` (training steps with each timed when a
            fresh run starts, blockwise kept only when at least 10% faster; a resumed run keeps its kernel;
            `carp.policies.carp.attention`). Both compute the same values to float rounding, so runs that time the
            kernels differently differ in the last bits; a pinned kernel makes every run take the same one.
            Inference uses neither.
    """

    attention: str = "auto"

    # The next-scale transformer reads the per-dimension multi-scale layout (a codebook per dimension, scales of
    # A * s_k tokens) and the tokenizer's latents for teacher forcing; joint_msvq has one codebook over all
    # dimensions and no per-dimension latents, so only carp_msvq fits.
    TOKENIZER_KINDS: ClassVar[tuple[str, ...]] = ("carp_msvq",)

    def __post_init__(self) -> None:
        super().__post_init__()
        section = self.SECTION
        _require(
            self.attention in ATTENTION_SETTINGS,
            f"{section}.attention",
            self.attention,
            f"must be one of {ATTENTION_SETTINGS}",
        )


@dataclass(frozen=True)
class CarpInference:
    """How evaluation chooses CARP's tokens; decoding only, so a change reruns evaluation, not training.

    Attributes:
        top_k: 1 takes the most likely token (greedy); k > 1 draws among the k most likely ones, with draws seeded
            per episode so results reproduce. An integer between 1 and ``codebook_size``.
        top_k_per_task: Task -> token choice when evaluating that task, overriding ``top_k``; each an integer between
            1 and ``codebook_size``, tasks registered (``carp.tasks``) or
            listed in ``tasks``.
    """

    top_k: int = 1
    top_k_per_task: dict[str, int] = field(default_factory=dict)

    SECTION: ClassVar[str] = SECTION

    def __post_init__(self) -> None:
        key = f"inference.{self.SECTION}"
        require_positive_int(f"{key}.top_k", self.top_k)
        for task, top_k in self.top_k_per_task.items():
            _require(top_k >= 1, f"{key}.top_k_per_task.{task}", top_k, "must be >= 1 (1 = greedy)")

    def settings_for(self, task: str) -> dict[str, Any]:
        """Keyword arguments of the policy's `configure_inference` when evaluating `task`."""
        return {"top_k": self.top_k_per_task.get(task, self.top_k)}

    def check_with(self, params: Any) -> None:
        """Refuse a token choice above the vocabulary (`params.codebook_size`) or for a task the params do not know."""
        key = f"inference.{self.SECTION}"
        for task in self.top_k_per_task:
            params.require_known_task(f"{key}.top_k_per_task.{task}", task)
        entries = [(f"{key}.top_k", self.top_k)] + [
            (f"{key}.top_k_per_task.{task}", top_k) for task, top_k in self.top_k_per_task.items()
        ]
        for name, top_k in entries:
            if top_k > params.codebook_size:
                raise ConfigError(f"{name}={top_k!r}: must be <= codebook_size = {params.codebook_size}")


SECTIONS = (CarpConfig, CarpInference)
"""The registry's view of this module: the `carp` section and the `inference.carp` section."""
