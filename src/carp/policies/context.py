"""What a family's builder gets from the data: shapes, normalizers, the tokenizer and metadata."""

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from carp.config.image_encoder import ImageEncoderConfig
from carp.data.normalizer import MinMaxNormalizer
from carp.policies.observations import observation_feature_dim
from carp.policies.tasks import TASKS_METADATA_KEY, PolicyTasks
from carp.tokenizer.artifact import TokenizerArtifact

if TYPE_CHECKING:
    from carp.tokenizer.kinds.artifact import KindArtifact


@dataclass(frozen=True)
class MsvqLayout:
    """The carp_msvq token grid the params ask for: what a family over another tokenizer kind may be sized against.

    Attributes:
        scales: `(s_1, ..., s_K)`, the params' scale schedule.
        codebook_size: `V`, the params' codes per action dimension.
    """

    scales: tuple[int, ...]
    codebook_size: int


@dataclass(frozen=True)
class PolicyContext:
    """Everything a policy is sized by that does not come from its own params section.

    Attributes:
        obs_normalizer: min-max statistics of the `Do` low-dim observation features (the proprioception with cameras);
            a multi-task policy's are its selected task's (see `tasks`).
        action_normalizer: min-max statistics of the `A` action dimensions of the task (likewise).
        obs_steps: `To`.
        action_horizon: `H`.
        tokenizer_artifact: the registered tokenizer, for families that predict its tokens (carp_msvq's artifact,
            or another kind's for a family that takes it); None otherwise.
        tasks: the tasks of a multi-task policy (with their statistics and the task embedding's width); None for a
            single-task policy. Recorded in `metadata`, through which every family's policy receives it.
        metadata: plain values stored in the checkpoint (task, tokenizer reference, tracking run; the tasks).
        image_encoder: the camera encoder's settings for a policy that sees images; None for state observations.
        msvq_layout: the params' carp_msvq scales and codebook size, which the next-token family sizes its network
            against over another kind (`next_token.match_size`); None where no params are at hand.
    """

    obs_normalizer: MinMaxNormalizer
    action_normalizer: MinMaxNormalizer
    obs_steps: int
    action_horizon: int
    tokenizer_artifact: "TokenizerArtifact | KindArtifact | None" = None
    tasks: PolicyTasks | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    image_encoder: ImageEncoderConfig | None = None
    msvq_layout: MsvqLayout | None = None

    def __post_init__(self) -> None:
        if self.tasks is not None:
            selected = self.tasks.selected
            ours = (self.obs_normalizer.to_dict(), self.action_normalizer.to_dict())
            if ours != (
                self.tasks.obs_normalizers[selected].to_dict(),
                self.tasks.action_normalizers[selected].to_dict(),
            ):
                raise ValueError(f"the context's statistics must be those of the selected task {selected!r}")
            object.__setattr__(self, "metadata", self.metadata | {TASKS_METADATA_KEY: self.tasks.to_dict()})

    @property
    def num_tasks(self) -> int:
        """0 for a single-task policy, else the number of task ids."""
        return 0 if self.tasks is None else self.tasks.num_tasks

    @property
    def obs_dim(self) -> int:
        """`Do`."""
        return self.obs_normalizer.num_features

    @property
    def feature_dim(self) -> int:
        """`F`, the per-step observation features the family's network is conditioned on (`Do` for state)."""
        task_features = 0 if self.tasks is None else self.tasks.embedding_dim
        return observation_feature_dim(self.obs_dim, self.image_encoder, task_features)

    @property
    def action_dim(self) -> int:
        """`A`."""
        return self.action_normalizer.num_features
