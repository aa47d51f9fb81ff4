"""Config of the next-token autoregressive family: one frozen dataclass, validated at construction.

It is the family's params section (`next_token`) and what its checkpoint stores. The transformer's defaults are
CARP's (`carp.config.PolicyConfig`), so that the two families differ only in how many tokens a step predicts. Shapes
that come from the data and the tokenizer (`Do`, `To`, `A`, scales, `V`) are passed to the model separately; loop
settings shared by every family (epochs, batch size, checkpoints, seed) are left to the training loop's section.
"""

from dataclasses import dataclass
from typing import Any

from carp.config import _require

SECTION = "next_token"


def _require_positive_int(name: str, value: Any) -> None:
    _require(
        isinstance(value, int) and not isinstance(value, bool) and value >= 1,
        f"{SECTION}.{name}",
        value,
        "must be an integer >= 1",
    )


@dataclass(frozen=True)
class NextTokenConfig:
    """The next-token transformer (`carp.policies.next_token.transformer`) and its optimizer.

    Attributes:
        depth: transformer blocks, integer >= 1.
        width: `D`, token and conditioning width, integer >= 1.
        num_heads: attention heads, integer >= 1 dividing `width`.
        mlp_ratio: feed-forward hidden width relative to `width`, > 0.
        dropout: dropout on attention weights and residual branches in training, in [0, 1).
        learning_rate: peak AdamW learning rate, > 0.
        weight_decay: AdamW weight decay, >= 0.
        warmup_steps: optimizer steps of linear learning-rate warmup, integer >= 0.
        use_ema: evaluate an exponential moving average of the weights.
        ema_decay: decay of that average, in (0, 1).
        top_k: token choice at inference: 1 takes the most likely token, k > 1 draws among the k most likely;
            integer >= 1 (and at most the codebook size, checked at generation).
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
    top_k: int = 1

    def __post_init__(self) -> None:
        for name in ("depth", "width", "num_heads", "top_k"):
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
