"""What a family's builder gets from the data: shapes, normalizers, the tokenizer and metadata."""

from dataclasses import dataclass, field
from typing import Any

from carp.config import ImageEncoderConfig
from carp.data.normalizer import MinMaxNormalizer
from carp.policies.observations import observation_feature_dim
from carp.tokenizer.artifact import TokenizerArtifact


@dataclass(frozen=True)
class PolicyContext:
    """Everything a policy is sized by that does not come from its own params section.

    Attributes:
        obs_normalizer: min-max statistics of the `Do` low-dim observation features (the proprioception with cameras).
        action_normalizer: min-max statistics of the `A` action dimensions of the task.
        obs_steps: `To`.
        action_horizon: `H`.
        tokenizer_artifact: the registered tokenizer, for families that predict its tokens; None otherwise.
        num_tasks: 0 for a single-task policy, else the number of task indices.
        metadata: plain values stored in the checkpoint (task, tokenizer reference, tracking run).
        image_encoder: the camera encoder's settings for a policy that sees images; None for state observations.
    """

    obs_normalizer: MinMaxNormalizer
    action_normalizer: MinMaxNormalizer
    obs_steps: int
    action_horizon: int
    tokenizer_artifact: TokenizerArtifact | None = None
    num_tasks: int = 0
    metadata: dict[str, Any] = field(default_factory=dict)
    image_encoder: ImageEncoderConfig | None = None

    @property
    def obs_dim(self) -> int:
        """`Do`."""
        return self.obs_normalizer.num_features

    @property
    def feature_dim(self) -> int:
        """`F`, the per-step observation features the family's network is conditioned on (`Do` for state)."""
        return observation_feature_dim(self.obs_dim, self.image_encoder)

    @property
    def action_dim(self) -> int:
        """`A`."""
        return self.action_normalizer.num_features
