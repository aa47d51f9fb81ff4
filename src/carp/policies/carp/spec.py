"""What the coarse-to-fine transformer is sized by: CARP's params section plus the shapes of the data and tokenizer."""

from dataclasses import asdict, dataclass, field
from typing import Any

from carp.policies.carp.config import CarpConfig

POLICY_TYPE = "carp"
"""The family's registry name, stored as `policy_type` in its checkpoints and exported graphs."""

ARCHITECTURE_FIELDS = ("depth", "width", "num_heads", "mlp_ratio", "dropout")
"""`CarpConfig` fields that checkpoints written before the spec held the whole section stored beside the shapes."""


def _require_positive_int(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"PolicySpec.{name} must be a positive integer, got {value!r}")


@dataclass(frozen=True)
class PolicySpec:
    """Shape and size of a :class:`~carp.policies.carp.transformer.CoarseToFineTransformer`.

    The architecture is the `carp` params section itself (`config`, validated there); the other fields come from the
    data and the tokenizer. The last four shape fields repeat the tokenizer's spec;
    :class:`~carp.policies.carp.policy.CarpPolicy` checks that they match.

    Attributes:
        obs_dim: `F`, observation features per step the transformer is conditioned on (not the flattened `To * F`):
            `Do` for state observations, camera features and proprioception for images, plus a multi-task policy's
            task embedding (`carp.policies.observations`).
        obs_steps: `To`, observation steps the policy conditions on.
        action_dim: `A`, action dimensions (one tokenizer and one vocabulary each).
        scales: `(s_1, ..., s_K)`, tokens per dimension at each scale, strictly increasing.
        latent_channels: `C`, channels of the tokenizer latent (input width of scales k > 1).
        codebook_size: `V`, vocabulary size per dimension.
        config: CARP's params section: depth, width `D`, heads, feed-forward ratio and dropout of the transformer
            (and the optimizer settings it was trained with).
    """

    obs_dim: int
    obs_steps: int
    action_dim: int
    scales: tuple[int, ...]
    latent_channels: int
    codebook_size: int
    config: CarpConfig = field(default_factory=CarpConfig)

    def __post_init__(self) -> None:
        # Lists arrive from YAML/JSON; the frozen spec keeps a hashable tuple.
        object.__setattr__(self, "scales", tuple(self.scales))
        for name in ("obs_dim", "obs_steps", "action_dim", "latent_channels"):
            _require_positive_int(name, getattr(self, name))
        if isinstance(self.codebook_size, bool) or not isinstance(self.codebook_size, int) or self.codebook_size < 2:
            raise ValueError(f"PolicySpec.codebook_size must be an integer >= 2, got {self.codebook_size!r}")
        if not self.scales:
            raise ValueError("PolicySpec.scales must not be empty")
        for scale in self.scales:
            _require_positive_int("scales[...]", scale)
        if any(later <= earlier for earlier, later in zip(self.scales, self.scales[1:], strict=False)):
            raise ValueError(f"PolicySpec.scales must be strictly increasing, got {self.scales}")
        if not isinstance(self.config, CarpConfig):
            raise ValueError(f"PolicySpec.config must be a CarpConfig, got {type(self.config).__name__}")

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
        """Input width of the conditioning projection: `To * F`."""
        return self.obs_steps * self.obs_dim

    def to_dict(self) -> dict[str, Any]:
        """Plain-types view for checkpoints and tracking (scales as a list, the config as a dict)."""
        values = asdict(self)
        values["scales"] = list(self.scales)
        return values

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "PolicySpec":
        """Inverse of :meth:`to_dict`; unknown keys are errors.

        Also reads the flat form of older checkpoints, whose architecture fields sat beside the shapes without the
        rest of the section; their optimizer settings are then the section's defaults. Older specs also held
        `num_tasks` (0 for every single-task policy; the task embedding now lives in the observation encoder).

        Raises:
            ValueError: unknown keys, or a spec whose transformer embedded the task itself (num_tasks > 0).
        """
        values = dict(values)
        if values.pop("num_tasks", 0) != 0:
            raise ValueError(
                "PolicySpec.num_tasks > 0: a multi-task transformer of an earlier format, which this code no longer "
                "reads (the task embedding is the observation encoder's now); train it again"
            )
        legacy = {name: values.pop(name) for name in ARCHITECTURE_FIELDS if name in values}
        unknown = set(values) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown PolicySpec keys: {sorted(unknown)}")
        if legacy and "config" in values:
            raise ValueError(f"PolicySpec keys {sorted(legacy)} belong in its config")
        config = CarpConfig(**values.pop("config", legacy))
        return cls(**values, config=config)
