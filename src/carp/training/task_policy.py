"""A policy of one family trained with the referenced tokenizer, on one task's windows or on several tasks'.

The work of the `train_policy` and `train_multitask` stages. What a policy trains from is its inputs: one task's
windows (`load_task_policy_inputs`) or every task's, each labelled with its task (`load_multitask_policy_inputs`);
both give the training windows, the policy's context, the epochs and the held-out errors, so that one path trains
either. What to train is a `PolicyTrainingRequest` (the family, its sections, the loop's settings, where the
resumable state lives and the device). `train_requested_policy` trains (every process of a multi-process run calls
it) and `train_and_write` trains inside a tracking run, measures the held-out action errors and writes the
checkpoint, history and metrics (the one process that writes outputs). A distilled family (one that declares a
teacher family, e.g. `consistency_policy`) trains its teacher first, in the same stage (`train_teacher`): the
teacher's resumable state lives in `<checkpoint_dir>/teacher`, so a rerun whose teacher is unchanged (its params
section, the loop's settings and the data) finds the teacher's training finished and only distils, and the teacher is
written beside the policy as `teacher.pt`.
"""

import logging
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from carp.config.data import DataConfig
from carp.config.training import TrainingConfig
from carp.outputs import write_history, write_json
from carp.policies.base import Policy
from carp.policies.registry import get_family, train_policy
from carp.training.loop import CHECKPOINT_NAME, SNAPSHOT_DIRNAME, snapshot_path
from carp.training.policy_inputs import PolicyInputs  # noqa: E402

if TYPE_CHECKING:
    from carp.tracking.runs import StageRun

logger = logging.getLogger(__name__)

TEACHER_DIRNAME = "teacher"
"""The teacher's resumable state goes into this folder of the student's checkpoint directory."""

TEACHER_FILENAME = "teacher.pt"
"""A distilled family's trained teacher is written beside its `policy.pt` under this name."""

FINAL_METRICS = ("loss", "token_accuracy")
"""Per-epoch metrics whose last value is also reported as `final_<name>` (a family that has them)."""


@dataclass(frozen=True)
class PolicyTrainingRequest:
    """What to train: a family with its params sections, the loop's settings, where and on what device.

    Attributes:
        family: registered policy family.
        family_config: the family's params section.
        training: the shared training loop's settings (its epochs per task and family).
        data: `To`, `H` and `Ta`; with the windows' replay buffer, the serving protocol stored in the checkpoint's
            metadata (`carp.serving.protocol`).
        checkpoint_dir: resumable training states of this policy (a teacher's go into its `teacher` folder).
        device: where training runs (a process's own device in a multi-process run).
        teacher_config: the teacher family's params section of a distilled family; None for other families.
    """

    family: str
    family_config: Any
    training: TrainingConfig
    data: DataConfig
    checkpoint_dir: Path
    device: torch.device
    teacher_config: Any = None


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


def train_requested_policy(
    request: PolicyTrainingRequest,
    inputs: PolicyInputs,
    tracking_run_id: str | None = None,
    on_epoch_end: Callable[[int, dict[str, float]], None] | None = None,
    teacher: Policy | None = None,
) -> Policy:
    """Train the requested policy on `inputs`' training windows, resuming from its checkpoint folder when it can.

    Args:
        request: what to train, where and on what device.
        inputs: one task's windows or several tasks' (`load_task_policy_inputs`, `load_multitask_policy_inputs`).
        tracking_run_id: the tracking run that logs this training, stored in the checkpoint's metadata.
        on_epoch_end: called with (epoch, metrics) after every epoch on the process that reports.
        teacher: the trained policy of the family's teacher family (a distilled family, see :func:`train_teacher`);
            None otherwise.

    Returns:
        The trained policy in eval mode on the CPU.
    """
    train_data, context = inputs.training_data(request.data, tracking_run_id)
    return train_policy(
        request.family,
        request.family_config,
        request.training,
        context,
        train_data,
        request.checkpoint_dir,
        device=request.device,
        epochs=inputs.epochs(request.training, request.family),
        on_epoch_end=on_epoch_end,
        teacher=teacher,
    )


def train_teacher(
    request: PolicyTrainingRequest,
    inputs: PolicyInputs,
    on_epoch_end: Callable[[int, dict[str, float]], None] | None = None,
) -> Policy | None:
    """The trained teacher of a distilled family, trained (or found trained) in `<checkpoint_dir>/teacher`.

    The teacher trains in the shared resumable loop, whose state resumes only for the same teacher (its params
    section, the loop's settings, the data): a finished state of the same teacher is reused without training, any
    other is trained over. Its metadata holds no tracking run, so the same teacher saves to the same bytes.

    Args:
        request: the student's request; its `teacher_config` is the teacher family's section.
        inputs: see :func:`train_requested_policy` (the teacher's epochs are its own family's).
        on_epoch_end: called with (epoch, metrics) after every teacher epoch on the process that reports.

    Returns:
        The trained teacher in eval mode on the CPU, or None for a family without a teacher.
    """
    teacher_family = get_family(request.family).teacher
    if teacher_family is None:
        return None
    teacher_dir = Path(request.checkpoint_dir) / TEACHER_DIRNAME
    state = teacher_dir / CHECKPOINT_NAME
    before = state.stat().st_mtime_ns if state.exists() else None
    train_data, context = inputs.training_data(request.data, tracking_run_id=None)
    teacher = train_policy(
        teacher_family,
        request.teacher_config,
        request.training,
        context,
        train_data,
        teacher_dir,
        device=request.device,
        epochs=inputs.epochs(request.training, teacher_family),
        on_epoch_end=on_epoch_end,
    )
    if before is not None and state.exists() and state.stat().st_mtime_ns == before:
        logger.info(
            "reused the trained %s teacher of %s from %s (no epoch trained)", teacher_family, request.family, state
        )
    else:
        logger.info("trained the %s teacher of %s in %s", teacher_family, request.family, teacher_dir)
    return teacher


def train_with_teacher(request: PolicyTrainingRequest, inputs: PolicyInputs) -> Policy:
    """The teacher first (for a distilled family), then the policy: what a process that writes nothing runs."""
    return train_requested_policy(request, inputs, teacher=train_teacher(request, inputs))


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


def train_and_write(
    request: PolicyTrainingRequest, inputs: PolicyInputs, outputs: TaskPolicyOutputs, run: "StageRun"
) -> dict[str, float]:
    """Train as :func:`train_with_teacher` does, logging to `run`, then evaluate and write the outputs.

    Every epoch's metrics go to `run` and to the history (a teacher's as `teacher_<metric>`, to `run` only); the
    held-out action errors (raw units, see `carp.evaluation.offline`; per task as `<task>/<error>` for a multi-task
    policy) to `run` and, with the last epoch's loss and token accuracy, to `metrics.json`; the checkpoint becomes an
    artifact of `run`.

    Returns:
        The metrics written to `metrics.json`: held-out errors (none without held-out windows) and `final_*` values.
    """
    history: list[dict] = []

    def log_epoch(epoch: int, metrics: dict[str, float]) -> None:
        history.append({"epoch": epoch + 1, **metrics})
        run.log_metrics(metrics, step=epoch + 1)

    def log_teacher_epoch(epoch: int, metrics: dict[str, float]) -> None:
        run.log_metrics({f"teacher_{name}": value for name, value in metrics.items()}, step=epoch + 1)

    teacher = train_teacher(request, inputs, log_teacher_epoch)
    policy = train_requested_policy(request, inputs, run.run_id, log_epoch, teacher)
    held_out = inputs.held_out_errors(policy, request.data)
    run.log_metrics(held_out)
    outputs.checkpoint.parent.mkdir(parents=True, exist_ok=True)
    policy.save(outputs.checkpoint)
    if teacher is not None:
        teacher.save(outputs.checkpoint.parent / TEACHER_FILENAME)
    publish_snapshots(
        Path(request.checkpoint_dir) / SNAPSHOT_DIRNAME,
        outputs.checkpoint.parent / SNAPSHOT_DIRNAME,
        request.training.snapshot_epochs(inputs.epochs(request.training, request.family)),
        final_epoch=len(history),
    )
    write_history(outputs.report_dir / "history.csv", history)
    last = history[-1]
    metrics = {**held_out, **{f"final_{key}": last[key] for key in FINAL_METRICS if key in last}}
    write_json(outputs.report_dir / "metrics.json", metrics)
    run.log_artifact(outputs.checkpoint, "checkpoint")
    return metrics
