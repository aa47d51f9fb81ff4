"""What a policy trains from: one task's windows or every task's, each labelled with its task.

Both kinds give the training windows, the policy's context, the epochs and the held-out errors (`PolicyInputs`), so
that one path (`carp.training.task_policy`) trains either.
"""

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol

import torch

from carp.config.data import DataConfig
from carp.config.image_encoder import ImageEncoderConfig
from carp.config.tokenizer_kinds import DEFAULT_TOKENIZER_KIND
from carp.config.training import TrainingConfig
from carp.data.dataset import (
    TaskWindows,
    load_multitask_windows,
    load_task_windows,
    stack_task_windows,
    task_obs_widths,
)
from carp.data.image_windows import ImageWindowReader
from carp.data.ingest import BUFFER_DIRNAME
from carp.data.obs_padding import padded_layout
from carp.evaluation.offline import held_out_action_errors
from carp.policies.base import Policy
from carp.policies.context import MsvqLayout, PolicyContext
from carp.policies.tasks import DEFAULT_TASK_EMBEDDING_DIM, PolicyTasks
from carp.serving.protocol import SERVING_METADATA_KEY, ProtocolError, training_protocol
from carp.tasks import task_for_env_args
from carp.tokenizer.artifact import TokenizerArtifact, TokenizerMismatchError, check_compatible, load_tokenizer_artifact
from carp.tokenizer.kinds.artifact import KindArtifact, is_kind_artifact, load_kind_artifact
from carp.tokenizer.kinds.base import read_kind_file
from carp.tracking.registry import TokenizerReference
from carp.training.loop import PolicyTrainingData

IMAGE_PRELOAD_LIMIT_BYTES = 4 << 30
"""Decoded camera frames a training split may hold in memory (per split); larger splits are read per batch."""


class PolicyInputs(Protocol):
    """What a policy trains from, one task's windows or several tasks': the one seam of the training path."""

    reference: TokenizerReference
    artifact: TokenizerArtifact | KindArtifact

    @property
    def label(self) -> str:
        """The task, or the tasks joined, for log lines."""

    def training_data(self, data: DataConfig, tracking_run_id: str | None) -> tuple[PolicyTrainingData, PolicyContext]:
        """The normalized training windows and the policy's context (metadata, normalizers, tasks)."""

    def epochs(self, training: TrainingConfig, family: str) -> int:
        """Epochs `family` trains on these inputs (`TrainingConfig.epochs_for`)."""

    def held_out_errors(self, policy: Policy, data: DataConfig) -> dict[str, float]:
        """The trained policy's action errors on the held-out windows (`carp.evaluation.offline`)."""


@dataclass(frozen=True)
class TaskPolicyInputs:
    """What a task's policy is trained from: the tokenizer reference and artifact and the task's windows.

    Attributes:
        task: the task's name, stored in the checkpoint's metadata.
        reference: the tokenizer reference file's content.
        artifact: the referenced tokenizer.
        windows: the task's low-dim windows (the proprioception with cameras), training and held-out.
        image_encoder: the camera encoder's settings of an image policy; None for state observations.
        train_images: the camera images of `windows`' training windows, in the same order; None for state.
        valid_images: the same for the held-out windows.
        msvq_layout: the params' carp_msvq scales and codebook size (`PolicyContext.msvq_layout`); None without params.
    """

    task: str
    reference: TokenizerReference
    artifact: TokenizerArtifact | KindArtifact
    windows: TaskWindows
    image_encoder: ImageEncoderConfig | None = None
    train_images: ImageWindowReader | None = None
    valid_images: ImageWindowReader | None = None
    msvq_layout: MsvqLayout | None = None

    @property
    def label(self) -> str:
        """The task."""
        return self.task

    def training_data(self, data: DataConfig, tracking_run_id: str | None) -> tuple[PolicyTrainingData, PolicyContext]:
        """The task's normalized training windows and the policy context of its training."""
        windows = self.windows
        # The task's own statistics, as the tokenizer saw every training task's actions (carp.tokenizer.artifact).
        obs_normalizer, action_normalizer = windows.obs_normalizer, windows.action_normalizer
        train_data = PolicyTrainingData(
            obs=torch.as_tensor(obs_normalizer.normalize(windows.train_obs), dtype=torch.float32),
            actions=torch.as_tensor(action_normalizer.normalize(windows.train_actions), dtype=torch.float32),
            images=None if self.train_images is None else self.train_images.images,
        )
        context = PolicyContext(
            obs_normalizer=obs_normalizer,
            action_normalizer=action_normalizer,
            obs_steps=data.obs_steps,
            action_horizon=data.action_horizon,
            tokenizer_artifact=self.artifact,
            metadata={
                "task": self.task,
                "tokenizer": asdict(self.reference),
                "mlflow_run_id": tracking_run_id,
                # What a robot sends and executes, so that `carp serve` needs only the checkpoint.
                SERVING_METADATA_KEY: training_protocol(
                    data, windows.buffer.attrs, self.image_encoder, _control_frequency(windows.buffer.attrs)
                ),
            },
            image_encoder=self.image_encoder,
            msvq_layout=self.msvq_layout,
        )
        return train_data, context

    def epochs(self, training: TrainingConfig, family: str) -> int:
        """The task's epochs for `family`."""
        return training.epochs_for(self.task, family)

    def held_out_errors(self, policy: Policy, data: DataConfig) -> dict[str, float]:
        """Errors on the task's held-out windows."""
        valid_images = None if self.valid_images is None else self.valid_images.images
        windows = self.windows
        return held_out_action_errors(
            policy, windows.valid_obs, windows.valid_actions, data.obs_steps, data.action_steps, images=valid_images
        )


@dataclass(frozen=True)
class MultiTaskPolicyInputs:
    """What a multi-task policy is trained from: the tokenizer reference and artifact and every task's windows.

    Attributes:
        reference: the tokenizer reference file's content.
        artifact: the referenced tokenizer (shared by the tasks).
        windows: task -> its low-dim windows, in task-id order, checked to agree (`carp.data.dataset`).
        task_embedding_dim: width of the learned task embedding the policy is conditioned on.
        msvq_layout: the params' carp_msvq scales and codebook size (`PolicyContext.msvq_layout`); None without params.
    """

    reference: TokenizerReference
    artifact: TokenizerArtifact | KindArtifact
    windows: dict[str, TaskWindows]
    task_embedding_dim: int = DEFAULT_TASK_EMBEDDING_DIM
    msvq_layout: MsvqLayout | None = None

    @property
    def tasks(self) -> tuple[str, ...]:
        """Task names in task-id order."""
        return tuple(self.windows)

    @property
    def label(self) -> str:
        """The tasks, joined."""
        return "+".join(self.tasks)

    def training_data(self, data: DataConfig, tracking_run_id: str | None) -> tuple[PolicyTrainingData, PolicyContext]:
        """Every task's training windows, each labelled with its task id, and the multi-task policy's context.

        Each task's windows are normalized with that task's own statistics (`carp.policies.tasks`); the policy is
        conditioned on the task through the observation encoder's task embedding. Its selected task is the first.
        """
        windows = self.windows
        obs, actions, task_ids = stack_task_windows(windows, "train")
        train_data = PolicyTrainingData(
            obs=torch.as_tensor(obs), actions=torch.as_tensor(actions), task_ids=torch.as_tensor(task_ids)
        )
        obs_widths = task_obs_widths(windows)
        paddings = padded_layout(obs_widths)
        tasks = PolicyTasks(
            self.tasks,
            {
                task: paddings[task].pad_normalizer(task_windows.obs_normalizer)
                for task, task_windows in windows.items()
            },
            {task: task_windows.action_normalizer for task, task_windows in windows.items()},
            self.task_embedding_dim,
            obs_widths=obs_widths,
        )
        first = windows[self.tasks[0]]
        context = PolicyContext(
            obs_normalizer=tasks.obs_normalizers[self.tasks[0]],
            action_normalizer=first.action_normalizer,
            obs_steps=data.obs_steps,
            action_horizon=data.action_horizon,
            tokenizer_artifact=self.artifact,
            tasks=tasks,
            metadata={
                "tokenizer": asdict(self.reference),
                "mlflow_run_id": tracking_run_id,
                # The tasks' observation keys agree (checked when their windows were loaded), so one protocol serves
                # every task; `carp serve --task` picks the task, whose own key widths the policy's tasks record.
                SERVING_METADATA_KEY: training_protocol(
                    data, first.buffer.attrs, control_frequency_hz=_control_frequency(first.buffer.attrs)
                ),
            },
            msvq_layout=self.msvq_layout,
        )
        return train_data, context

    def epochs(self, training: TrainingConfig, family: str) -> int:
        """The most epochs any of the tasks would get alone."""
        return max(training.epochs_for(task, family) for task in self.tasks)

    def held_out_errors(self, policy: Policy, data: DataConfig) -> dict[str, float]:
        """Each task's errors on its own held-out windows with its own statistics, as `<task>/<error>`."""
        errors: dict[str, float] = {}
        for task, windows in self.windows.items():
            policy.select_task(task)
            task_errors = held_out_action_errors(
                policy, windows.valid_obs, windows.valid_actions, data.obs_steps, data.action_steps
            )
            errors |= {f"{task}/{name}": value for name, value in task_errors.items()}
        policy.select_task(self.tasks[0])
        return errors


def _control_frequency(buffer_attrs) -> int | None:
    """Control steps per second of the task whose demos the buffer holds (its ``env_args``); None without them."""
    env_args = buffer_attrs.get("env_args")
    return None if env_args is None else task_for_env_args(env_args).control_frequency_hz


@dataclass(frozen=True)
class ReferencedTokenizer:
    """The tokenizer a policy trains with: its files, and the params it must fit.

    Attributes:
        directory: the referenced tokenizer, whatever its source (a registered one is fetched there first).
        reference_path: the tokenizer reference file; the artifact's sha256 must equal the one it records.
        action_space: the params' action space, which the tokenizer must have been trained in.
        scales: the params' scale schedule, which a carp_msvq tokenizer must use.
        codebook_size: the params' `V`, which a carp_msvq tokenizer must use.
        kinds: the tokenizer kinds the trained family takes (`PolicyFamily.tokenizer_kinds`); carp_msvq only for a
            family that declares none.
    """

    directory: Path
    reference_path: Path
    action_space: str
    scales: tuple[int, ...]
    codebook_size: int
    kinds: tuple[str, ...] = (DEFAULT_TOKENIZER_KIND,)

    @property
    def msvq_layout(self) -> MsvqLayout:
        """The params' carp_msvq scales and codebook size, whatever the referenced tokenizer's kind."""
        return MsvqLayout(tuple(self.scales), self.codebook_size)

    def load(self) -> tuple[TokenizerReference, TokenizerArtifact | KindArtifact]:
        """The reference and the artifact, checked against each other and the params.

        Raises:
            FileNotFoundError: a file is missing.
            CheckpointError: the tokenizer is corrupt or not the referenced one.
            TokenizerMismatchError: the tokenizer does not fit the params, or is of a kind the family does not take.
        """
        reference = TokenizerReference.load(self.reference_path)
        if is_kind_artifact(self.directory):
            kind, _ = read_kind_file(self.directory)
            if kind not in self.kinds:
                # The carp family reads carp_msvq's module (spec, ids per dimension, scales); the families that
                # predict no tokens record the tokenizer they were trained beside as carp_msvq's artifact.
                raise TokenizerMismatchError(
                    f"{self.directory}: a {kind!r} tokenizer (tokenizer.kind); this policy family trains beside "
                    f"{' or '.join(self.kinds)} only (next_token takes any kind)"
                )
            artifact = load_kind_artifact(
                self.directory, expected_sha256=reference.sha256, recorded_in=str(self.reference_path)
            )
            if artifact.action_space != self.action_space:
                raise TokenizerMismatchError(
                    f"{self.directory}: action space is {artifact.action_space!r} in the tokenizer but the params ask "
                    f"for {self.action_space!r}"
                )
            return reference, artifact
        artifact = load_tokenizer_artifact(
            self.directory, expected_sha256=reference.sha256, recorded_in=self.reference_path
        )
        check_compatible(artifact, self.action_space, self.scales, self.codebook_size)
        return reference, artifact


def check_kind_horizon(artifact: TokenizerArtifact | KindArtifact, data: DataConfig) -> None:
    """Refuse a kind's tokenizer fitted on chunks of another `H` than the params' (carp_msvq's is checked with it).

    Raises:
        TokenizerMismatchError: names both horizons.
    """
    if isinstance(artifact, KindArtifact) and artifact.tokenizer.action_horizon != data.action_horizon:
        raise TokenizerMismatchError(
            f"data.action_horizon is {artifact.tokenizer.action_horizon} in the tokenizer but the params ask for "
            f"{data.action_horizon}"
        )


def load_task_policy_inputs(
    task_dir: Path,
    tokenizer: ReferencedTokenizer,
    data: DataConfig,
    image_encoder: ImageEncoderConfig | None = None,
    task: str | None = None,
) -> TaskPolicyInputs:
    """Read the referenced tokenizer and the task's windows, checking that the tokenizer fits the params.

    With `image_encoder`, the windows' camera images are opened too (they stay on disk; each batch reads its own).

    Args:
        task_dir: the task's processed data (`data/processed/<task>`).
        tokenizer: the referenced tokenizer and the params it must fit.
        data: windowing (`H`, `To`, `Ta`).
        image_encoder: the camera encoder's settings of an image policy (its cameras and image size must be the
            ones the buffer stores); None for state observations.
        task: the task's name, recorded in the policy's metadata; None takes the name of `task_dir`.

    Raises:
        FileNotFoundError, CheckpointError, TokenizerMismatchError: as `ReferencedTokenizer.load`.
        ValueError: the buffer does not record its observation keys and widths (ingested before they were
            recorded: the message names the buffer and the missing attribute), holds no images, or other cameras or
            another image size than `image_encoder`.
    """
    reference, artifact = tokenizer.load()
    check_kind_horizon(artifact, data)
    windows = load_task_windows(task_dir, data.action_horizon, data.obs_steps, data.action_steps)
    try:
        # Checked before any training: the trained checkpoint records this protocol, and an old buffer that cannot
        # give it should stop the stage at its start with one line, not after the epochs.
        training_protocol(data, windows.buffer.attrs, image_encoder)
    except ProtocolError as error:
        raise ValueError(f"{Path(task_dir) / BUFFER_DIRNAME}: {error}") from None
    task = Path(task_dir).name if task is None else task
    layout = tokenizer.msvq_layout
    if image_encoder is None:
        return TaskPolicyInputs(task, reference, artifact, windows, msvq_layout=layout)
    store = Path(task_dir) / BUFFER_DIRNAME
    readers = {
        split: ImageWindowReader(
            store, data.action_horizon, data.obs_steps, data.action_steps, split, IMAGE_PRELOAD_LIMIT_BYTES
        )
        for split in ("train", "valid")
    }
    stored = (readers["train"].image_keys, readers["train"].image_size)
    if stored != (image_encoder.image_keys, image_encoder.image_size):
        raise ValueError(
            f"{store}: stores images {list(stored[0])} at {stored[1]} px, the encoder expects "
            f"{list(image_encoder.image_keys)} at {image_encoder.image_size} px (ingest again)"
        )
    return TaskPolicyInputs(
        task, reference, artifact, windows, image_encoder, readers["train"], readers["valid"], msvq_layout=layout
    )


def load_multitask_policy_inputs(
    task_dirs: dict[str, Path], tokenizer: ReferencedTokenizer, data: DataConfig
) -> MultiTaskPolicyInputs:
    """Read the referenced tokenizer and every task's windows, as :func:`load_task_policy_inputs` does for one.

    Args:
        task_dirs: task -> its processed data, in task-id order (at least two tasks).
        tokenizer: see :func:`load_task_policy_inputs`.
        data: see :func:`load_task_policy_inputs`.

    Raises:
        ValueError: fewer than two tasks, or tasks whose observations or actions differ (naming task and key).
        FileNotFoundError, CheckpointError, TokenizerMismatchError: as :func:`load_task_policy_inputs`.
    """
    if len(task_dirs) < 2:
        raise ValueError(f"a multi-task policy needs at least two tasks, got {list(task_dirs)}")
    reference, artifact = tokenizer.load()
    check_kind_horizon(artifact, data)
    windows = load_multitask_windows(task_dirs, data.action_horizon, data.obs_steps, data.action_steps)
    return MultiTaskPolicyInputs(reference, artifact, windows, msvq_layout=tokenizer.msvq_layout)
