"""Hyper-parameters of the coarse-to-fine transformer, validated at construction."""

from dataclasses import asdict, dataclass
from typing import Any

TASK_EMBEDDING_DIM = 3
"""Width of the learned per-task embedding concatenated to the observation features (CARP's multi-task setting)."""


def _require_positive_int(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"PolicySpec.{name} must be a positive integer, got {value!r}")


@dataclass(frozen=True)
class PolicySpec:
    """Shape and size of a :class:`~carp.policies.carp.transformer.CoarseToFineTransformer`.

    The last four fields repeat the tokenizer's spec; :class:`~carp.policies.carp.policy.CarpPolicy` checks that they
    match.

    Attributes:
        obs_dim: `Do`, low-dim observation features per step (not the flattened `To * Do`).
        obs_steps: `To`, observation steps the policy conditions on.
        action_dim: `A`, action dimensions (one tokenizer and one vocabulary each).
        scales: `(s_1, ..., s_K)`, tokens per dimension at each scale, strictly increasing.
        latent_channels: `C`, channels of the tokenizer latent (input width of scales k > 1).
        codebook_size: `V`, vocabulary size per dimension.
        num_tasks: 0 for a single-task policy; otherwise the number of task indices, each with a learned
            `TASK_EMBEDDING_DIM`-wide embedding concatenated to the observation features.
        depth: number of transformer blocks.
        width: `D`, token and conditioning width.
        num_heads: `Nh`, attention heads; must divide `width`.
        mlp_ratio: hidden width of the feed-forward layer relative to `width`.
        dropout: dropout on attention weights and on the residual branches during training.
    """

    obs_dim: int
    obs_steps: int
    action_dim: int
    scales: tuple[int, ...]
    latent_channels: int
    codebook_size: int
    num_tasks: int = 0
    depth: int = 8
    width: int = 64
    num_heads: int = 8
    mlp_ratio: float = 4.0
    dropout: float = 0.0

    def __post_init__(self) -> None:
        # Lists arrive from YAML/JSON; the frozen spec keeps a hashable tuple.
        object.__setattr__(self, "scales", tuple(self.scales))
        for name in ("obs_dim", "obs_steps", "action_dim", "latent_channels", "depth", "width", "num_heads"):
            _require_positive_int(name, getattr(self, name))
        if isinstance(self.num_tasks, bool) or not isinstance(self.num_tasks, int) or self.num_tasks < 0:
            raise ValueError(f"PolicySpec.num_tasks must be a non-negative integer, got {self.num_tasks!r}")
        if isinstance(self.codebook_size, bool) or not isinstance(self.codebook_size, int) or self.codebook_size < 2:
            raise ValueError(f"PolicySpec.codebook_size must be an integer >= 2, got {self.codebook_size!r}")
        if not self.scales:
            raise ValueError("PolicySpec.scales must not be empty")
        for scale in self.scales:
            _require_positive_int("scales[...]", scale)
        if any(later <= earlier for earlier, later in zip(self.scales, self.scales[1:], strict=False)):
            raise ValueError(f"PolicySpec.scales must be strictly increasing, got {self.scales}")
        if self.width % self.num_heads != 0:
            raise ValueError(f"PolicySpec.width ({self.width}) must be divisible by num_heads ({self.num_heads})")
        if not self.mlp_ratio > 0:
            raise ValueError(f"PolicySpec.mlp_ratio must be positive, got {self.mlp_ratio!r}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"PolicySpec.dropout must be in [0, 1), got {self.dropout!r}")

    @property
    def num_scales(self) -> int:
        """`K`, the number of scales."""
        return len(self.scales)

    @property
    def sequence_length(self) -> int:
        """`L = A * sum(s_k)`, tokens per action chunk."""
        return self.action_dim * sum(self.scales)

    @property
    def condition_features(self) -> int:
        """Input width of the conditioning projection: `To * Do` plus the task embedding if multi-task."""
        task_features = TASK_EMBEDDING_DIM if self.num_tasks > 0 else 0
        return self.obs_steps * self.obs_dim + task_features

    @property
    def hidden_width(self) -> int:
        """Hidden width of the feed-forward layers."""
        return round(self.width * self.mlp_ratio)

    def to_dict(self) -> dict[str, Any]:
        """Plain-types view for checkpoints and tracking (scales as a list)."""
        values = asdict(self)
        values["scales"] = list(self.scales)
        return values

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "PolicySpec":
        """Inverse of :meth:`to_dict`; unknown keys are errors."""
        unknown = set(values) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown PolicySpec keys: {sorted(unknown)}")
        return cls(**values)
