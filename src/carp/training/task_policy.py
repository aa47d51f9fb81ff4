"""A policy of one family trained with the referenced tokenizer, on one task's windows or on several tasks'.

A multi-task policy trains on every task's windows, each labelled with its task.

The work of the `train_policy` stage: `load_task_policy_inputs` reads and checks what it trains from,
`train_task_policy` trains (every process of a multi-process run calls it), and `train_and_write_task_policy` trains
inside a tracking run, measures the held-out action errors and writes the checkpoint, history and metrics (the one
process that writes outputs). A distilled family (one that declares a teacher family, e.g. `consistency_policy`)
trains its teacher first, in the same stage (`train_task_teacher`): the teacher's resumable state lives in
`<checkpoint_dir>/teacher`, so a rerun whose teacher is unchanged (its params section, the loop's settings and the
data) finds the teacher's training finished and only distils, and the teacher is written beside the policy as
`teacher.pt`. `load_multitask_policy_inputs`, `train_multitask_policy` and `train_and_write_multitask_policy` do the
same for a multi-task policy (of a family without a teacher).
"""

import logging
import shutil
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from carp.config.data import DataConfig
from carp.config.image_encoder import ImageEncoderConfig
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
from carp.outputs import write_history, write_json
from carp.policies.base import Policy
from carp.policies.context import PolicyContext
from carp.policies.registry import get_family, train_policy
from carp.policies.tasks import DEFAULT_TASK_EMBEDDING_DIM, PolicyTasks
from carp.serving.protocol import SERVING_METADATA_KEY, ProtocolError, training_protocol
from carp.tokenizer.artifact import TokenizerArtifact, check_compatible, load_tokenizer_artifact
from carp.tracking.registry import TokenizerReference
from carp.training.loop import CHECKPOINT_NAME, SNAPSHOT_DIRNAME, PolicyTrainingData, snapshot_path

if TYPE_CHECKING:
    from carp.tracking.runs import StageRun

logger = logging.getLogger(__name__)

TEACHER_DIRNAME = "teacher"
"""The teacher's resumable state goes into this folder of the student's checkpoint directory."""

TEACHER_FILENAME = "teacher.pt"
"""A distilled family's trained teacher is written beside its `policy.pt` under this name."""

FINAL_METRICS = ("loss", "token_accuracy")
"""Per-epoch metrics whose last value is also reported as `final_<name>` (a family that has them)."""


IMAGE_PRELOAD_LIMIT_BYTES = 4 << 30
"""Decoded camera frames a training split may hold in memory (per split); larger splits are read per batch."""


@dataclass(frozen=True)
class TaskPolicyInputs:
    """What a task's policy is trained from: the tokenizer reference and artifact and the task's windows.

    Attributes:
        reference: the tokenizer reference file's content.
        artifact: the referenced tokenizer.
        windows: the task's low-dim windows (the proprioception with cameras), training and held-out.
        image_encoder: the camera encoder's settings of an image policy; None for state observations.
        train_images: the camera images of `windows`' training windows, in the same order; None for state.
        valid_images: the same for the held-out windows.
    """

    reference: TokenizerReference
    artifact: TokenizerArtifact
    windows: TaskWindows
    image_encoder: ImageEncoderConfig | None = None
    train_images: ImageWindowReader | None = None
    valid_images: ImageWindowReader | None = None


@dataclass(frozen=True)
class TaskPolicyOutputs:
    """Where a trained policy and its reports go.

    Attributes:
        checkpoint: the policy file (`policy.pt`), read by evaluation; the kept snapshots go beside it into
            `snapshots/` (`carp.training.loop.snapshot_path`).
        report_dir: receives `history.csv` (one row per epoch) and `metrics.json` (held-out errors, final values).
    """

    checkpoint: Path
    report_dir: Path


def load_task_policy_inputs(
    task_dir: Path,
    tokenizer_dir: Path,
    reference_path: Path,
    data: DataConfig,
    action_space: str,
    scales: tuple[int, ...],
    codebook_size: int,
    image_encoder: ImageEncoderConfig | None = None,
) -> TaskPolicyInputs:
    """Read the referenced tokenizer and the task's windows, checking that the tokenizer fits the params.

    With `image_encoder`, the windows' camera images are opened too (they stay on disk; each batch reads its own).

    Args:
        task_dir: the task's processed data (`data/processed/<task>`).
        tokenizer_dir: the referenced tokenizer, whatever its source (a registered one is fetched there first).
        reference_path: the tokenizer reference file; the artifact's sha256 must equal the one it records.
        data: windowing (`H`, `To`, `Ta`).
        action_space: the params' action space, which the tokenizer must have been trained in.
        scales: the params' scale schedule, which the tokenizer must use.
        codebook_size: the params' `V`, which the tokenizer must use.
        image_encoder: the camera encoder's settings of an image policy (its cameras and image size must be the
            ones the buffer stores); None for state observations.

    Raises:
        FileNotFoundError: a file is missing.
        CheckpointError: the tokenizer is corrupt or not the referenced one.
        TokenizerMismatchError: the tokenizer does not fit the params.
        ValueError: the buffer does not record its observation keys and widths (ingested before they were
            recorded: the message names the buffer and the missing attribute), holds no images, or other cameras or
            another image size than `image_encoder`.
    """
    reference = TokenizerReference.load(reference_path)
    artifact = load_tokenizer_artifact(tokenizer_dir, expected_sha256=reference.sha256, recorded_in=reference_path)
    check_compatible(artifact, action_space, scales, codebook_size)
    windows = load_task_windows(task_dir, data.action_horizon, data.obs_steps, data.action_steps)
    try:
        # Checked before any training: the trained checkpoint records this protocol, and an old buffer that cannot
        # give it should stop the stage at its start with one line, not after the epochs.
        training_protocol(data, windows.buffer.attrs, image_encoder)
    except ProtocolError as error:
        raise ValueError(f"{Path(task_dir) / BUFFER_DIRNAME}: {error}") from None
    if image_encoder is None:
        return TaskPolicyInputs(reference, artifact, windows)
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
    return TaskPolicyInputs(reference, artifact, windows, image_encoder, readers["train"], readers["valid"])


def train_task_policy(
    family: str,
    family_config: Any,
    training: TrainingConfig,
    data: DataConfig,
    inputs: TaskPolicyInputs,
    task: str,
    checkpoint_dir: Path,
    device: torch.device,
    tracking_run_id: str | None = None,
    on_epoch_end: Callable[[int, dict[str, float]], None] | None = None,
    teacher: Policy | None = None,
) -> Policy:
    """Train a policy of `family` on the task's training windows, resuming from `checkpoint_dir` when it can.

    Args:
        family: registered policy family.
        family_config: the family's params section.
        training: the shared training loop's settings (its epochs for `task`).
        data: `To` and `H`; with the windows' replay buffer, the serving protocol stored in the checkpoint's metadata
            (`carp.serving.protocol`).
        inputs: see :func:`load_task_policy_inputs`.
        task: the task's name, stored in the checkpoint's metadata.
        checkpoint_dir: resumable training states of this (task, family) pair.
        device: where training runs (a process's own device in a multi-process run).
        tracking_run_id: the tracking run that logs this training, stored in the checkpoint's metadata.
        on_epoch_end: called with (epoch, metrics) after every epoch on the process that reports.
        teacher: the trained policy of the family's teacher family (a distilled family, see
            :func:`train_task_teacher`); None otherwise.

    Returns:
        The trained policy in eval mode on the CPU.
    """
    train_data, context = _training_inputs(data, inputs, task, tracking_run_id)
    return train_policy(
        family,
        family_config,
        training,
        context,
        train_data,
        checkpoint_dir,
        device=device,
        epochs=training.epochs_for(task, family),
        on_epoch_end=on_epoch_end,
        teacher=teacher,
    )


def train_task_teacher(
    family: str,
    teacher_config: Any,
    training: TrainingConfig,
    data: DataConfig,
    inputs: TaskPolicyInputs,
    task: str,
    checkpoint_dir: Path,
    device: torch.device,
    on_epoch_end: Callable[[int, dict[str, float]], None] | None = None,
) -> Policy | None:
    """The trained teacher of a distilled `family`, trained (or found trained) in `<checkpoint_dir>/teacher`.

    The teacher trains in the shared resumable loop, whose state resumes only for the same teacher (its params
    section, the loop's settings, the data): a finished state of the same teacher is reused without training, any
    other is trained over. Its metadata holds no tracking run, so the same teacher saves to the same bytes.

    Args:
        family: registered policy family; None is returned unless it declares a teacher family.
        teacher_config: the teacher family's params section.
        training: see :func:`train_task_policy` (the teacher's epochs are its own family's for `task`).
        data: see :func:`train_task_policy`.
        inputs: see :func:`train_task_policy`.
        task: see :func:`train_task_policy`.
        checkpoint_dir: the student's resumable states; the teacher's go into its `teacher` folder.
        device: see :func:`train_task_policy`.
        on_epoch_end: called with (epoch, metrics) after every teacher epoch on the process that reports.

    Returns:
        The trained teacher in eval mode on the CPU, or None for a family without a teacher.
    """
    teacher_family = get_family(family).teacher
    if teacher_family is None:
        return None
    teacher_dir = Path(checkpoint_dir) / TEACHER_DIRNAME
    state = teacher_dir / CHECKPOINT_NAME
    before = state.stat().st_mtime_ns if state.exists() else None
    train_data, context = _training_inputs(data, inputs, task, tracking_run_id=None)
    teacher = train_policy(
        teacher_family,
        teacher_config,
        training,
        context,
        train_data,
        teacher_dir,
        device=device,
        epochs=training.epochs_for(task, teacher_family),
        on_epoch_end=on_epoch_end,
    )
    if before is not None and state.exists() and state.stat().st_mtime_ns == before:
        logger.info("reused the trained %s teacher of %s from %s (no epoch trained)", teacher_family, family, state)
    else:
        logger.info("trained the %s teacher of %s in %s", teacher_family, family, teacher_dir)
    return teacher


def _training_inputs(
    data: DataConfig, inputs: TaskPolicyInputs, task: str, tracking_run_id: str | None
) -> tuple[PolicyTrainingData, PolicyContext]:
    """The normalized training windows and the policy context of a task's training."""
    windows = inputs.windows
    # The task's own statistics, as the tokenizer saw every training task's actions (carp.tokenizer.artifact).
    obs_normalizer, action_normalizer = windows.obs_normalizer, windows.action_normalizer
    train_data = PolicyTrainingData(
        obs=torch.as_tensor(obs_normalizer.normalize(windows.train_obs), dtype=torch.float32),
        actions=torch.as_tensor(action_normalizer.normalize(windows.train_actions), dtype=torch.float32),
        images=None if inputs.train_images is None else inputs.train_images.images,
    )
    context = PolicyContext(
        obs_normalizer=obs_normalizer,
        action_normalizer=action_normalizer,
        obs_steps=data.obs_steps,
        action_horizon=data.action_horizon,
        tokenizer_artifact=inputs.artifact,
        metadata={
            "task": task,
            "tokenizer": asdict(inputs.reference),
            "mlflow_run_id": tracking_run_id,
            # What a robot sends and executes, so that `carp serve` needs only the checkpoint.
            SERVING_METADATA_KEY: training_protocol(data, windows.buffer.attrs, inputs.image_encoder),
        },
        image_encoder=inputs.image_encoder,
    )
    return train_data, context


def publish_snapshots(source_dir: Path, output_dir: Path, epochs: Sequence[int], final_epoch: int) -> list[Path]:
    """Copy the training's kept snapshots of `epochs` into the stage's output, leaving out the final epoch's.

    The final policy is written as `policy.pt` itself, so its snapshot would be a second copy of it.

    Raises:
        FileNotFoundError: a snapshot the training should have kept is missing.
    """
    copied = []
    for epoch in epochs:
        if epoch == final_epoch:
            continue
        source = snapshot_path(source_dir, epoch)
        if not source.exists():
            raise FileNotFoundError(f"{source}: the policy snapshot of epoch {epoch} is missing (train again)")
        target = snapshot_path(output_dir, epoch)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, target)
        copied.append(target)
    return copied


def train_and_write_task_policy(
    family: str,
    family_config: Any,
    training: TrainingConfig,
    data: DataConfig,
    inputs: TaskPolicyInputs,
    task: str,
    checkpoint_dir: Path,
    device: torch.device,
    outputs: TaskPolicyOutputs,
    run: "StageRun",
    teacher_config: Any = None,
) -> dict[str, float]:
    """Train as :func:`train_task_policy` does, logging to `run`, then evaluate and write the outputs.

    Every epoch's metrics go to `run` and to the history; the held-out action errors (raw units, see
    `carp.evaluation.offline`) to `run` and, with the last epoch's loss and token accuracy, to `metrics.json`; the
    checkpoint becomes an artifact of `run`.

    Args:
        family: see :func:`train_task_policy`.
        family_config: see :func:`train_task_policy`.
        training: see :func:`train_task_policy`.
        data: see :func:`train_task_policy`; also `Ta` of the held-out errors.
        inputs: see :func:`train_task_policy`.
        task: see :func:`train_task_policy`.
        checkpoint_dir: see :func:`train_task_policy`.
        device: see :func:`train_task_policy`.
        outputs: where the checkpoint and the reports go.
        run: the tracking run of this training.
        teacher_config: the teacher family's params section of a distilled family (see :func:`train_task_teacher`,
            whose epochs go to `run` as `teacher_<metric>`); None for other families.

    Returns:
        The metrics written to `metrics.json`: held-out errors (none without held-out windows) and `final_*` values.
    """
    history: list[dict] = []

    def log_epoch(epoch: int, metrics: dict[str, float]) -> None:
        history.append({"epoch": epoch + 1, **metrics})
        run.log_metrics(metrics, step=epoch + 1)

    def log_teacher_epoch(epoch: int, metrics: dict[str, float]) -> None:
        run.log_metrics({f"teacher_{name}": value for name, value in metrics.items()}, step=epoch + 1)

    windows = inputs.windows
    teacher = train_task_teacher(
        family, teacher_config, training, data, inputs, task, checkpoint_dir, device, log_teacher_epoch
    )
    policy = train_task_policy(
        family, family_config, training, data, inputs, task, checkpoint_dir, device, run.run_id, log_epoch, teacher
    )
    valid_images = None if inputs.valid_images is None else inputs.valid_images.images
    held_out = held_out_action_errors(
        policy, windows.valid_obs, windows.valid_actions, data.obs_steps, data.action_steps, images=valid_images
    )
    run.log_metrics(held_out)
    outputs.checkpoint.parent.mkdir(parents=True, exist_ok=True)
    policy.save(outputs.checkpoint)
    if teacher is not None:
        teacher.save(outputs.checkpoint.parent / TEACHER_FILENAME)
    publish_snapshots(
        Path(checkpoint_dir) / SNAPSHOT_DIRNAME,
        outputs.checkpoint.parent / SNAPSHOT_DIRNAME,
        training.snapshot_epochs(training.epochs_for(task, family)),
        final_epoch=len(history),
    )
    write_history(outputs.report_dir / "history.csv", history)
    last = history[-1]
    final = {f"final_{key}": last[key] for key in FINAL_METRICS if key in last}
    metrics = {**held_out, **final}
    write_json(outputs.report_dir / "metrics.json", metrics)
    run.log_artifact(outputs.checkpoint, "checkpoint")
    return metrics


@dataclass(frozen=True)
class MultiTaskPolicyInputs:
    """What a multi-task policy is trained from: the tokenizer reference and artifact and every task's windows.

    Attributes:
        reference: the tokenizer reference file's content.
        artifact: the referenced tokenizer (shared by the tasks).
        windows: task -> its low-dim windows, in task-id order, checked to agree (`carp.data.dataset`).
    """

    reference: TokenizerReference
    artifact: TokenizerArtifact
    windows: dict[str, TaskWindows]

    @property
    def tasks(self) -> tuple[str, ...]:
        """Task names in task-id order."""
        return tuple(self.windows)


def load_multitask_policy_inputs(
    task_dirs: dict[str, Path],
    tokenizer_dir: Path,
    reference_path: Path,
    data: DataConfig,
    action_space: str,
    scales: tuple[int, ...],
    codebook_size: int,
) -> MultiTaskPolicyInputs:
    """Read the referenced tokenizer and every task's windows, as :func:`load_task_policy_inputs` does for one.

    Args:
        task_dirs: task -> its processed data, in task-id order (at least two tasks).
        tokenizer_dir: see :func:`load_task_policy_inputs`.
        reference_path: see :func:`load_task_policy_inputs`.
        data: see :func:`load_task_policy_inputs`.
        action_space: see :func:`load_task_policy_inputs`.
        scales: see :func:`load_task_policy_inputs`.
        codebook_size: see :func:`load_task_policy_inputs`.

    Raises:
        ValueError: fewer than two tasks, or tasks whose observations or actions differ (naming task and key).
        FileNotFoundError, CheckpointError, TokenizerMismatchError: as :func:`load_task_policy_inputs`.
    """
    if len(task_dirs) < 2:
        raise ValueError(f"a multi-task policy needs at least two tasks, got {list(task_dirs)}")
    reference = TokenizerReference.load(reference_path)
    artifact = load_tokenizer_artifact(tokenizer_dir, expected_sha256=reference.sha256, recorded_in=reference_path)
    check_compatible(artifact, action_space, scales, codebook_size)
    windows = load_multitask_windows(task_dirs, data.action_horizon, data.obs_steps, data.action_steps)
    return MultiTaskPolicyInputs(reference, artifact, windows)


def multitask_epochs(training: TrainingConfig, tasks: Sequence[str], family: str) -> int:
    """Epochs of a multi-task policy: the most that any of its tasks would get alone (`TrainingConfig.epochs_for`)."""
    return max(training.epochs_for(task, family) for task in tasks)


def train_multitask_policy(
    family: str,
    family_config: Any,
    training: TrainingConfig,
    data: DataConfig,
    inputs: MultiTaskPolicyInputs,
    checkpoint_dir: Path,
    device: torch.device,
    tracking_run_id: str | None = None,
    on_epoch_end: Callable[[int, dict[str, float]], None] | None = None,
    task_embedding_dim: int = DEFAULT_TASK_EMBEDDING_DIM,
) -> Policy:
    """Train one policy of `family` over every task's training windows, each labelled with its task id.

    Each task's windows are normalized with that task's own statistics (`carp.policies.tasks`); the policy is
    conditioned on the task through the observation encoder's task embedding. The policy's selected task is the
    first; see :func:`train_task_policy` for the other arguments.

    Returns:
        The trained policy in eval mode on the CPU.
    """
    windows = inputs.windows
    obs, actions, task_ids = stack_task_windows(windows, "train")
    train_data = PolicyTrainingData(
        obs=torch.as_tensor(obs), actions=torch.as_tensor(actions), task_ids=torch.as_tensor(task_ids)
    )
    obs_widths = task_obs_widths(windows)
    paddings = padded_layout(obs_widths)
    tasks = PolicyTasks(
        inputs.tasks,
        {task: paddings[task].pad_normalizer(task_windows.obs_normalizer) for task, task_windows in windows.items()},
        {task: task_windows.action_normalizer for task, task_windows in windows.items()},
        task_embedding_dim,
        obs_widths=obs_widths,
    )
    first = windows[inputs.tasks[0]]
    context = PolicyContext(
        obs_normalizer=tasks.obs_normalizers[inputs.tasks[0]],
        action_normalizer=first.action_normalizer,
        obs_steps=data.obs_steps,
        action_horizon=data.action_horizon,
        tokenizer_artifact=inputs.artifact,
        tasks=tasks,
        metadata={
            "tokenizer": asdict(inputs.reference),
            "mlflow_run_id": tracking_run_id,
            # The tasks' observation keys agree (checked when their windows were loaded), so one protocol serves every
            # task; `carp serve --task` picks the task, whose own key widths the policy's tasks record.
            SERVING_METADATA_KEY: training_protocol(data, first.buffer.attrs),
        },
    )
    return train_policy(
        family,
        family_config,
        training,
        context,
        train_data,
        checkpoint_dir,
        device=device,
        epochs=multitask_epochs(training, inputs.tasks, family),
        on_epoch_end=on_epoch_end,
    )


def train_and_write_multitask_policy(
    family: str,
    family_config: Any,
    training: TrainingConfig,
    data: DataConfig,
    inputs: MultiTaskPolicyInputs,
    checkpoint_dir: Path,
    device: torch.device,
    outputs: TaskPolicyOutputs,
    run: "StageRun",
    task_embedding_dim: int = DEFAULT_TASK_EMBEDDING_DIM,
) -> dict[str, float]:
    """Train as :func:`train_multitask_policy` does, then write the outputs as :func:`train_and_write_task_policy`.

    The held-out action errors are measured per task, on that task's held-out windows with its own statistics, and
    reported as `<task>/<error>`.
    """
    history: list[dict] = []

    def log_epoch(epoch: int, metrics: dict[str, float]) -> None:
        history.append({"epoch": epoch + 1, **metrics})
        run.log_metrics(metrics, step=epoch + 1)

    policy = train_multitask_policy(
        family,
        family_config,
        training,
        data,
        inputs,
        checkpoint_dir,
        device,
        run.run_id,
        log_epoch,
        task_embedding_dim,
    )
    held_out: dict[str, float] = {}
    for task, windows in inputs.windows.items():
        policy.select_task(task)
        errors = held_out_action_errors(
            policy, windows.valid_obs, windows.valid_actions, data.obs_steps, data.action_steps
        )
        held_out |= {f"{task}/{name}": value for name, value in errors.items()}
    policy.select_task(inputs.tasks[0])
    run.log_metrics(held_out)
    outputs.checkpoint.parent.mkdir(parents=True, exist_ok=True)
    policy.save(outputs.checkpoint)
    publish_snapshots(
        Path(checkpoint_dir) / SNAPSHOT_DIRNAME,
        outputs.checkpoint.parent / SNAPSHOT_DIRNAME,
        training.snapshot_epochs(multitask_epochs(training, inputs.tasks, family)),
        final_epoch=len(history),
    )
    write_history(outputs.report_dir / "history.csv", history)
    last = history[-1]
    metrics = {**held_out, **{f"final_{key}": last[key] for key in FINAL_METRICS if key in last}}
    write_json(outputs.report_dir / "metrics.json", metrics)
    run.log_artifact(outputs.checkpoint, "checkpoint")
    return metrics
