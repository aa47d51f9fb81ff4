"""What the families' PyTorch policies share: normalization, timing conveniences, saving and torch deployment.

:class:`PolicyModule` implements the parts of the :class:`~carp.policies.base.Policy` protocol that do not depend on
the family: a family subclasses it and writes its network, `predict_action_timed`, `training_loss`,
`configure_inference`, `model_calls_per_chunk`, `description` and its checkpoint entries. :class:`TokenizedPolicy`
adds what the two token-predicting families (CARP and next-token) share on top: the frozen registered tokenizer,
the token choice (`top_k`) and the tokenizer's checkpoint entries. The protocol stays the seam: the
rest of carp types against `Policy`, never against these classes.
"""

import abc
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from carp.config.image_encoder import ImageEncoderConfig
from carp.data.normalizer import MinMaxNormalizer
from carp.policies.base import (
    POLICY_FORMAT_VERSION,
    TORCH_BACKEND,
    Deployment,
    check_observation_shape,
    count_parameters,
)
from carp.policies.carp.sampling import check_top_k
from carp.policies.observations import (
    as_image_tensor,
    build_observation_encoder,
    checkpoint_image_encoder,
    encoder_checkpoint,
    restore_observation_encoder,
)
from carp.policies.tasks import TASKS_METADATA_KEY, PolicyTasks, metadata_tasks
from carp.tokenizer.artifact import TokenizerArtifact
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from carp.training.checkpoint import atomic_torch_save


def check_policy_type(checkpoint: dict[str, Any], policy_type: str) -> None:
    """Raise ValueError unless `checkpoint` was written by family `policy_type`."""
    if checkpoint.get("policy_type") != policy_type:
        raise ValueError(f"policy_type={checkpoint.get('policy_type')!r}: not a {policy_type} checkpoint")


def checkpoint_normalizers(checkpoint: dict[str, Any]) -> tuple[MinMaxNormalizer, MinMaxNormalizer]:
    """The (observation, action) normalizers a checkpoint written by :meth:`PolicyModule.to_checkpoint` holds."""
    normalizers = checkpoint["normalizers"]
    return MinMaxNormalizer.from_dict(normalizers["obs"]), MinMaxNormalizer.from_dict(normalizers["action"])


def check_tokenizer_fit(pairs: dict[str, tuple[Any, Any]], label: str, what: str) -> None:
    """Raise ValueError naming every size a model and the tokenizer disagree on.

    Args:
        pairs: size name -> (the model's value, the tokenizer's value).
        label: what the model's values are called in the message (`policy`, `model`).
        what: the start of the message, e.g. `policy spec does not match the tokenizer spec`.
    """
    mismatched = {name: values for name, values in pairs.items() if values[0] != values[1]}
    if mismatched:
        details = ", ".join(
            f"{name}: {label} {ours} vs tokenizer {theirs}" for name, (ours, theirs) in mismatched.items()
        )
        raise ValueError(f"{what} ({details})")


class PolicyModule(nn.Module, abc.ABC):
    """Base of the PyTorch policies: normalizers, the observation encoder, metadata and the family-independent methods.

    Subclasses set `policy_type`, register their networks (trainable parameters are what `num_parameters` counts)
    and implement `family_checkpoint` plus the family-specific protocol methods. Their networks are conditioned on
    the (B, To, F) features of :attr:`observation_encoder` (`carp.policies.observations`): the normalized
    observations themselves for state policies (F = Do), camera features and proprioception with `image_encoder`,
    and for a multi-task policy (its metadata records :class:`~carp.policies.tasks.PolicyTasks`) the task
    embedding appended to every step.

    Args:
        obs_normalizer: min-max statistics of the `Do` low-dim observation features (a multi-task policy's: its
            selected task's).
        action_normalizer: min-max statistics of the `A` action dimensions (likewise).
        metadata: plain values stored in the checkpoint; its `tasks` entry makes the policy multi-task.
        feature_dim: `F`, the observation features per step the network expects (the task embedding included).
        action_dim: `A` the network predicts.
        image_encoder: the camera encoder's settings for an image policy; None for a state policy.

    Raises:
        ValueError: a normalizer has another number of features than the network expects.
    """

    policy_type: str

    def __init__(
        self,
        obs_normalizer: MinMaxNormalizer,
        action_normalizer: MinMaxNormalizer,
        metadata: dict[str, Any] | None,
        feature_dim: int,
        action_dim: int,
        image_encoder: ImageEncoderConfig | None = None,
    ) -> None:
        tasks = metadata_tasks(metadata)
        encoder = build_observation_encoder(
            obs_normalizer.num_features,
            image_encoder,
            0 if tasks is None else tasks.num_tasks,
            0 if tasks is None else tasks.embedding_dim,
        )
        if encoder.output_dim != feature_dim:
            cameras = "" if encoder.output_dim == obs_normalizer.num_features else f" (F = {encoder.output_dim})"
            raise ValueError(
                f"obs normalizer has {obs_normalizer.num_features} features{cameras}, the policy expects "
                f"{'Do' if image_encoder is None else 'F'} = {feature_dim}"
            )
        if action_normalizer.num_features != action_dim:
            raise ValueError(
                f"action normalizer has {action_normalizer.num_features} features, the policy predicts A = {action_dim}"
            )
        super().__init__()
        self.observation_encoder = encoder
        self.obs_normalizer = obs_normalizer
        self.action_normalizer = action_normalizer
        self.metadata = dict(metadata or {})
        self.tasks: PolicyTasks | None = tasks

    @property
    def num_tasks(self) -> int:
        """0 for a single-task policy, else the number of task ids."""
        return 0 if self.tasks is None else self.tasks.num_tasks

    def select_task(self, task: str) -> None:
        """Use `task`'s statistics and task id from now on (a multi-task policy; saving keeps the choice).

        Raises:
            ValueError: the policy was not trained on `task` (a single-task policy: on another one).
        """
        if self.tasks is None:
            trained = self.metadata.get("task")
            if trained is not None and trained != task:
                raise ValueError(f"this policy was trained on task {trained!r}, not on {task!r}")
            return
        self.tasks = self.tasks.with_selected(task)
        self.obs_normalizer = self.tasks.obs_normalizers[task]
        self.action_normalizer = self.tasks.action_normalizers[task]
        self.metadata[TASKS_METADATA_KEY] = self.tasks.to_dict()

    def task_ids(self, task_index: int | np.ndarray | torch.Tensor | None, batch_size: int) -> torch.Tensor | None:
        """(B,) long task ids on the policy's device, or None for a single-task policy.

        Args:
            task_index: one index for the whole batch, one per sample, or None: a multi-task policy's selected task.
            batch_size: `B`.

        Raises:
            ValueError: a task index for a single-task policy, neither one index nor `batch_size` of them, or an
                index outside [0, num_tasks).
        """
        if self.tasks is None:
            if task_index is not None:
                raise ValueError(f"a {self.policy_type} policy trained on one task takes no task index")
            return None
        if task_index is None:
            task_index = self.tasks.index(self.tasks.selected)
        task_ids = torch.as_tensor(task_index, dtype=torch.long, device=self.device).reshape(-1)
        if task_ids.numel() == 1:
            task_ids = task_ids.expand(batch_size)
        if task_ids.numel() != batch_size:
            raise ValueError(f"task_index must be one index or one per sample ({batch_size}), got {task_ids.numel()}")
        if not bool(((task_ids >= 0) & (task_ids < self.num_tasks)).all()):
            raise ValueError(f"task indices must be in [0, {self.num_tasks}), got {task_ids.tolist()}")
        return task_ids  # (B,)

    @property
    def device(self) -> torch.device:
        """Device of the weights."""
        return next(self.parameters()).device

    @property
    def num_parameters(self) -> int:
        """Trained parameters: those that require gradients (a frozen tokenizer is not counted)."""
        return count_parameters(self)

    def observation_features(
        self,
        obs: np.ndarray | torch.Tensor,
        obs_steps: int,
        images: np.ndarray | torch.Tensor | None = None,
        task_index: int | np.ndarray | torch.Tensor | None = None,
    ) -> torch.Tensor:
        """(B, To, F) features the network is conditioned on, from raw observations (and images), on its device.

        Args:
            obs: (B, To, Do) raw low-dim observations (numpy or torch); a multi-task policy also takes its selected
                task's own (B, To, Do_task) and pads them (`carp.data.obs_padding`).
            obs_steps: `To` the network expects.
            images: (B, To, cameras, 3, h, w) uint8 camera images for an image policy; None for a state policy.
            task_index: see :meth:`task_ids`. The observations are normalized with the selected task's statistics.

        Raises:
            ValueError: `obs` or `images` has another shape, images are missing or unexpected, or a bad task index.
        """
        observations = torch.as_tensor(obs, dtype=torch.float32).to(self.device)
        padding = None if self.tasks is None else self.tasks.padding()
        if padding is not None and padding.pads:
            # The selected task's own observations are padded; padded ones (training windows) pass as they are.
            if observations.shape[-1] == padding.input_dim:
                observations = padding.pad(observations)  # (B, To, Do_task) -> (B, To, Do)
            elif observations.shape[-1] != padding.output_dim:
                raise ValueError(
                    f"obs of task {self.tasks.selected!r} must have its own {padding.input_dim} features (or the "
                    f"padded {padding.output_dim}), got shape {tuple(observations.shape)}"
                )
        check_observation_shape(observations, obs_steps, self.obs_normalizer.num_features, "obs")
        normalized = self.obs_normalizer.normalize(observations)  # (B, To, Do)
        task_ids = self.task_ids(task_index, observations.shape[0])
        return self.observation_encoder(normalized, as_image_tensor(images, self.device), task_ids)

    def batch_features(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """(b, To, F) features of a training batch: its normalized `obs` (b, To, Do), its `images` and `task_ids`.

        Each window of a multi-task batch was normalized with its own task's statistics before training.
        """
        return self.observation_encoder(batch["obs"], batch.get("images"), batch.get("task_ids"))

    def predict_action(
        self,
        obs: np.ndarray | torch.Tensor,
        task_index: int | np.ndarray | torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        **settings: Any,
    ) -> np.ndarray:
        """(B, H, A) float32 raw actions; see the family's `predict_action_timed` (and its extra `settings`)."""
        return self.predict_action_timed(obs, task_index, generator, **settings).actions

    def deployment(self, checkpoint_path: Path, backend: str, directory: Path) -> Deployment:
        """PyTorch (inference mode) whatever `backend` asks; the report names the backend that ran.

        Workers load `checkpoint_path` again, as the caller loads any checkpoint (`Deployment.load` is None);
        `directory` is not used.
        """
        return Deployment(TORCH_BACKEND, None)

    @abc.abstractmethod
    def family_checkpoint(self) -> dict[str, Any]:
        """The family's own checkpoint entries (config or spec, shapes, weights); see :meth:`to_checkpoint`."""

    def to_checkpoint(self) -> dict[str, Any]:
        """Self-contained state: envelope, family entries, observation encoder, normalizer statistics, metadata."""
        return {
            "format_version": POLICY_FORMAT_VERSION,
            "policy_type": self.policy_type,
            **self.family_checkpoint(),
            **encoder_checkpoint(self.observation_encoder),
            "normalizers": {"obs": self.obs_normalizer.to_dict(), "action": self.action_normalizer.to_dict()},
            "metadata": self.metadata,
        }

    def save(self, path: Path) -> None:
        """Atomically write :meth:`to_checkpoint` to `path`."""
        atomic_torch_save(self.to_checkpoint(), Path(path))


class TokenizedPolicy(PolicyModule):
    """Base of the families that predict the registered tokenizer's tokens with a transformer (CARP, next-token).

    The tokenizer is frozen (eval mode, no gradients); the checkpoint embeds its artifact with the artifact's
    sha256, which loading recomputes, so a policy never decodes with a tokenizer other than the one it learned from.

    Args:
        tokenizer_artifact: the trained tokenizer with its training statistics and sha256; becomes :attr:`tokenizer`.
        transformer: the family's token transformer, already checked against the tokenizer by the subclass.
        obs_normalizer: min-max statistics of the `Do` observation features.
        action_normalizer: min-max statistics of the task's `A` action dimensions.
        metadata: plain values stored in the checkpoint.
        feature_dim: `F`, observation features per step the transformer expects.
        image_encoder: the camera encoder's settings for an image policy; None for a state policy.
    """

    def __init__(
        self,
        tokenizer_artifact: TokenizerArtifact,
        transformer: nn.Module,
        obs_normalizer: MinMaxNormalizer,
        action_normalizer: MinMaxNormalizer,
        metadata: dict[str, Any] | None,
        feature_dim: int,
        image_encoder: ImageEncoderConfig | None = None,
    ) -> None:
        action_dim = tokenizer_artifact.tokenizer.spec.action_dim
        super().__init__(obs_normalizer, action_normalizer, metadata, feature_dim, action_dim, image_encoder)
        self.tokenizer: MultiScaleActionTokenizer = tokenizer_artifact.tokenizer.eval().requires_grad_(False)
        self.tokenizer_artifact = tokenizer_artifact
        self.transformer = transformer.eval()
        self.top_k = 1

    def train(self, mode: bool = True) -> "TokenizedPolicy":
        """Switch the transformer's mode; the tokenizer stays frozen in eval mode."""
        super().train(mode)
        self.tokenizer.eval()
        return self

    def configure_inference(self, top_k: int = 1) -> None:
        """Token choice of later predictions: 1 = greedy; k > 1 draws among the k most likely tokens."""
        check_top_k(top_k, self.tokenizer.spec.codebook_size)
        self.top_k = top_k

    @property
    def description(self) -> str:
        """`greedy` or `top-<k>`, the token choice of predictions."""
        return "greedy" if self.top_k == 1 else f"top-{self.top_k}"

    @property
    def draws_random(self) -> bool:
        """Top-k choice with k > 1 draws; greedy does not."""
        return self.top_k > 1

    @classmethod
    def with_checkpoint_parts(cls, transformer: nn.Module, checkpoint: dict[str, Any]) -> "TokenizedPolicy":
        """A policy of this family around `transformer` (weights loaded) with the checkpoint's other parts.

        The tokenizer (checked against its recorded sha256), the normalizers, the metadata and the observation
        encoder with its weights come from `checkpoint`, as :meth:`to_checkpoint` wrote them. Subclasses take
        `(tokenizer_artifact, transformer, obs_normalizer, action_normalizer, metadata, image_encoder)`.
        """
        policy = cls(
            checkpoint_tokenizer(checkpoint),
            transformer,
            *checkpoint_normalizers(checkpoint),
            checkpoint["metadata"],
            checkpoint_image_encoder(checkpoint),
        )
        restore_observation_encoder(policy.observation_encoder, checkpoint)
        return policy

    def tokenizer_checkpoint(self) -> dict[str, Any]:
        """The checkpoint entries of the frozen tokenizer: its artifact and the artifact's sha256."""
        return {"tokenizer": self.tokenizer_artifact.to_payload(), "tokenizer_sha256": self.tokenizer_artifact.sha256}


def checkpoint_tokenizer(checkpoint: dict[str, Any]) -> TokenizerArtifact:
    """The tokenizer artifact a :class:`TokenizedPolicy` checkpoint embeds, checked against its recorded sha256.

    Raises:
        TokenizerMismatchError: the artifact does not hash to the recorded sha256.
    """
    return TokenizerArtifact.from_payload(
        checkpoint["tokenizer"], checkpoint["tokenizer_sha256"], "the policy (the tokenizer it was trained with)"
    )
