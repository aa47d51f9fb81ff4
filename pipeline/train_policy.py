"""train_policy stage: a task's processed data + the referenced tokenizer -> models/policy/<task>/<policy>/policy.pt.

With `training.num_processes` above 1 the script checks its inputs, then starts itself again as that many processes
under torchrun (`carp.training.distributed`); rank 0 logs to MLflow and writes the outputs, the others only train.
"""

import argparse
import logging
import os
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from stage_support import (
    CHECKPOINT_DIR,
    PROCESSED_DIR,
    TOKENIZER_DIR,
    TOKENIZER_REF,
    fail,
    mlflow_stage,
    policy_dir,
    policy_report_dir,
    policy_stage_args,
    select_device,
    setup_logging,
    write_history,
    write_json,
)

from carp.config import Params
from carp.data.dataset import TaskWindows, load_task_windows
from carp.evaluation.offline import held_out_action_errors
from carp.policies.base import Policy
from carp.policies.context import PolicyContext
from carp.policies.registry import train_policy
from carp.tokenizer.artifact import (
    TokenizerArtifact,
    TokenizerMismatchError,
    check_compatible,
    load_tokenizer_artifact,
)
from carp.tracking.registry import TokenizerReference
from carp.training import distributed
from carp.training.checkpoint import CheckpointError
from carp.training.loop import PolicyTrainingData
from carp.training.runtime import precision_name, resolve_precision

TORCHRUN_VARIABLES = ("RANK", "LOCAL_RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT")


def torchrun_variables() -> dict[str, str] | None:
    """What torchrun tells a process it started (rank, world size, rendezvous store), or None outside torchrun."""
    found = {name: os.environ[name] for name in TORCHRUN_VARIABLES if name in os.environ}
    return found if len(found) == len(TORCHRUN_VARIABLES) else None


@dataclass(frozen=True)
class StageInputs:
    """The checked inputs of the stage: the tokenizer reference and artifact and the task's windows."""

    reference: TokenizerReference
    artifact: TokenizerArtifact
    windows: TaskWindows


def load_inputs(args: argparse.Namespace, params: Params) -> StageInputs:
    """Read and check the tokenizer and the task's windows; exit with one `error:` line if they do not fit."""
    reference = TokenizerReference.load(TOKENIZER_REF)
    try:
        # models/tokenizer holds the referenced tokenizer whatever its source (train_tokenizer fetches registered ones).
        artifact = load_tokenizer_artifact(TOKENIZER_DIR, expected_sha256=reference.sha256, recorded_in=TOKENIZER_REF)
        check_compatible(artifact, params.action_space, params.scales, params.codebook_size)
    except (CheckpointError, TokenizerMismatchError, FileNotFoundError) as error:
        fail(str(error))
    data = params.data
    windows = load_task_windows(PROCESSED_DIR / args.task, data.action_horizon, data.obs_steps, data.action_steps)
    return StageInputs(reference, artifact, windows)


def launch_processes(args: argparse.Namespace, num_processes: int, device: torch.device) -> None:
    """Run this stage again as `num_processes` torchrun processes and wait for them."""
    if device.type == "cuda" and torch.cuda.device_count() < num_processes:
        fail(
            f"{args.params}: training.num_processes={num_processes}: one CUDA device per process, "
            f"{torch.cuda.device_count()} visible"
        )
    # The processes' math libraries share the cores too (torchrun would give each one thread).
    os.environ.setdefault("OMP_NUM_THREADS", str(distributed.cpu_threads_per_process(num_processes)))
    logging.getLogger("torch.distributed").setLevel(logging.WARNING)
    logging.getLogger("carp.pipeline").info("training on %d processes (torchrun)", num_processes)
    try:
        distributed.run_processes(Path(__file__), sys.argv[1:], num_processes)
    except distributed.ProcessesFailed as error:
        fail(str(error))


def main() -> None:
    setup_logging()
    args, params = policy_stage_args(__doc__)
    num_processes = params.training.num_processes
    launched = torchrun_variables()
    if launched is not None and int(launched["WORLD_SIZE"]) != num_processes:
        fail(
            f"{args.params}: training.num_processes={num_processes}: torchrun started {launched['WORLD_SIZE']} "
            "processes; run the stage without torchrun, it starts its own"
        )
    inputs = load_inputs(args, params)
    device = select_device(params)
    if launched is None and num_processes > 1:
        launch_processes(args, num_processes, device)
        return
    rank = 0
    if launched is not None:
        distributed.end_with_launcher()
        rank = int(launched["RANK"])
        if rank != 0:
            logging.getLogger().setLevel(logging.WARNING)
        device = distributed.start_process_group(
            rank, num_processes, int(launched["LOCAL_RANK"]), launched["MASTER_ADDR"], int(launched["MASTER_PORT"]),
            device,
        )  # fmt: skip
    try:
        if rank == 0:
            train_and_write(args, params, inputs, device)
        else:
            train(args, params, inputs, device, mlflow_run_id=None, on_epoch_end=None)
    finally:
        distributed.stop_process_group()


def train(
    args: argparse.Namespace,
    params: Params,
    inputs: StageInputs,
    device: torch.device,
    mlflow_run_id: str | None,
    on_epoch_end: Callable[[int, dict[str, float]], None] | None,
) -> Policy:
    """The trained policy of this stage (every process of a multi-process run calls it)."""
    data, windows = params.data, inputs.windows
    # The task's own statistics, as the tokenizer saw every training task's actions (carp.tokenizer.artifact).
    obs_normalizer, action_normalizer = windows.obs_normalizer, windows.action_normalizer
    train_data = PolicyTrainingData(
        obs=torch.as_tensor(obs_normalizer.normalize(windows.train_obs), dtype=torch.float32),
        actions=torch.as_tensor(action_normalizer.normalize(windows.train_actions), dtype=torch.float32),
    )
    context = PolicyContext(
        obs_normalizer=obs_normalizer,
        action_normalizer=action_normalizer,
        obs_steps=data.obs_steps,
        action_horizon=data.action_horizon,
        tokenizer_artifact=inputs.artifact,
        metadata={"task": args.task, "tokenizer": asdict(inputs.reference), "mlflow_run_id": mlflow_run_id},
    )
    return train_policy(
        args.policy,
        params.family_config(args.policy),
        params.training,
        context,
        train_data,
        CHECKPOINT_DIR / "policy" / args.task / args.policy,
        device=device,
        epochs=params.training.epochs_for(args.task),
        on_epoch_end=on_epoch_end,
    )


def train_and_write(args: argparse.Namespace, params: Params, inputs: StageInputs, device: torch.device) -> None:
    """Train in an MLflow run, evaluate on the held-out windows and write the stage's outputs (rank 0)."""
    data, windows = params.data, inputs.windows
    precision = precision_name(resolve_precision(params.training.precision, device))
    history: list[dict] = []
    tags = {
        "carp.tokenizer": inputs.reference.uri,
        "carp.training_precision": precision,
        "carp.policy_type": args.policy,
    }
    stage = f"train_policy@{args.task}-{args.policy}"
    with mlflow_stage(params, stage, args.task, tags) as run:

        def log_epoch(epoch: int, metrics: dict[str, float]) -> None:
            history.append({"epoch": epoch + 1, **metrics})
            run.log_metrics(metrics, step=epoch + 1)

        policy = train(args, params, inputs, device, run.run_id, log_epoch)
        held_out = held_out_action_errors(
            policy, windows.valid_obs, windows.valid_actions, data.obs_steps, data.action_steps
        )
        run.log_metrics(held_out)
        checkpoint = policy_dir(args.task, args.policy) / "policy.pt"
        checkpoint.parent.mkdir(parents=True, exist_ok=True)
        policy.save(checkpoint)
        report_dir = policy_report_dir(args.task, args.policy)
        write_history(report_dir / "history.csv", history)
        last = history[-1]
        final = {f"final_{key}": last[key] for key in ("loss", "token_accuracy") if key in last}
        write_json(report_dir / "metrics.json", {**held_out, **final})
        run.log_artifact(checkpoint, "checkpoint")
    print(
        f"{args.task} {args.policy}: final loss {final['final_loss']:.4f}, held-out action RMSE "
        f"{held_out.get('valid_action_rmse', float('nan')):.4f}"
    )


if __name__ == "__main__":
    main()
