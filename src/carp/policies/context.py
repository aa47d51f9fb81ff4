"""What a family's builder gets from the data: shapes, normalizers, the tokenizer and metadata."""

from dataclasses import dataclass, field
from typing import Any

from carp.data.normalizer import MinMaxNormalizer
from carp.tokenizer.artifact import TokenizerArtifact


@dataclass(frozen=True)
class PolicyContext:
    """Everything a policy is sized by that does not come from its own params section.

    Attributes:
        obs_normalizer: min-max statistics of the `Do` observation features.
        action_normalizer: min-max statistics of the `A` action dimensions of the task.
        obs_steps: `To`.
        action_horizon: `H`.
        tokenizer_artifact: the registered tokenizer, for families that predict its tokens; None otherwise.
        num_tasks: 0 for a single-task policy, else the number of task indices.
        metadata: plain values stored in the checkpoint (task, tokenizer reference, tracking run).
    """

    obs_normalizer: MinMaxNormalizer
    action_normalizer: MinMaxNormalizer
    obs_steps: int
    action_horizon: int
    tokenizer_artifact: TokenizerArtifact | None = None
    num_tasks: int = 0
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def obs_dim(self) -> int:
        """`Do`."""
        return self.obs_normalizer.num_features

    @property
    def action_dim(self) -> int:
        """`A`."""
        return self.action_normalizer.num_features
