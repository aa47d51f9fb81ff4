"""train_policy stage: a task's processed data + the tokenizer -> models/policy/<task>/<policy>/seed<seed>/policy.pt.

With --multitask instead of --task (the train_multitask stage) it trains one policy over every task of the run, each
window labelled with its task: models/policy/multitask/<policy>/seed<seed>/policy.pt.

With `training.num_processes` above 1 the script checks its inputs, then starts itself again as that many processes
under torchrun (`carp.training.distributed`); rank 0 logs to MLflow and writes the outputs, the others only train.
"""

import logging
import os
import sys
from pathlib import Path

import torch
from stage_support import (
    CHECKPOINT_DIR,
    MULTITASK_DIRNAME,
    POLICY_DIR,
    PROCESSED_DIR,
    TOKENIZER_DIR,
    TOKENIZER_REF,
    fail,
    mlflow_stage,
    policy_stage_args,
    select_device,
    setup_logging,
    stage_policy_paths,
)

from carp.config.tokenizer_kinds import DEFAULT_TOKENIZER_KIND
from carp.policies.registry import get_family
from carp.tokenizer.artifact import TokenizerMismatchError
from carp.training import distributed
from carp.training.checkpoint import CheckpointError
from carp.training.policy_inputs import ReferencedTokenizer, load_multitask_policy_inputs, load_task_policy_inputs
from carp.training.runtime import precision_name, resolve_precision
from carp.training.task_policy import PolicyTrainingRequest, TaskPolicyOutputs, train_and_write, train_with_teacher

TORCHRUN_VARIABLES = ("RANK", "LOCAL_RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT")


def torchrun_variables() -> dict[str, str] | None:
    """What torchrun tells a process it started (rank, world size, rendezvous store), or None outside torchrun."""
    found = {name: os.environ[name] for name in TORCHRUN_VARIABLES if name in os.environ}
    return found if len(found) == len(TORCHRUN_VARIABLES) else None


def launch_processes(params_path: Path, num_processes: int, device: torch.device) -> None:
    """Run this stage again as `num_processes` torchrun processes and wait for them."""
    if device.type == "cuda" and torch.cuda.device_count() < num_processes:
        fail(
            f"{params_path}: training.num_processes={num_processes}: one CUDA device per process, "
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
    args, params = policy_stage_args(__doc__, task_or_multitask=True)
    num_processes = params.training.num_processes
    launched = torchrun_variables()
    if launched is not None and int(launched["WORLD_SIZE"]) != num_processes:
        fail(
            f"{args.params}: training.num_processes={num_processes}: torchrun started {launched['WORLD_SIZE']} "
            "processes; run the stage without torchrun, it starts its own"
        )
    try:
        # models/tokenizer holds the referenced tokenizer whatever its source (train_tokenizer fetches registered ones).
        # The kinds the family takes; a family that declares none trains beside carp_msvq only.
        kinds = get_family(args.policy).tokenizer_kinds or (DEFAULT_TOKENIZER_KIND,)
        tokenizer = ReferencedTokenizer(
            TOKENIZER_DIR, TOKENIZER_REF, params.action_space, params.scales, params.codebook_size, kinds
        )
        if args.multitask:
            task_dirs = {task: PROCESSED_DIR / task for task in params.tasks}
            inputs = load_multitask_policy_inputs(task_dirs, tokenizer, params.data)
        else:
            inputs = load_task_policy_inputs(
                PROCESSED_DIR / args.task, tokenizer, params.data, params.policy_image_encoder
            )
    except (CheckpointError, TokenizerMismatchError, FileNotFoundError, ValueError) as error:
        fail(str(error))
    device = select_device(params)
    if launched is None and num_processes > 1:
        launch_processes(args.params, num_processes, device)
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
    family_config = params.family_config(args.policy)
    # A distilled family trains its teacher first, in this stage, from the teacher family's own params section.
    teacher = get_family(args.policy).teacher
    teacher_config = None if teacher is None else params.family_config(teacher)
    training = params.training_for_seed(args.seed)
    model_dir, report_dir, _ = stage_policy_paths(args)
    checkpoint_dir = CHECKPOINT_DIR / "policy" / model_dir.relative_to(POLICY_DIR)
    request = PolicyTrainingRequest(
        args.policy, family_config, training, params.data, checkpoint_dir, device, teacher_config
    )  # fmt: skip
    trained = MULTITASK_DIRNAME if args.multitask else args.task
    try:
        if rank != 0:
            train_with_teacher(request, inputs)
            return
        tags = {
            "carp.tokenizer": inputs.reference.uri,
            "carp.training_precision": precision_name(resolve_precision(params.training.precision, device)),
            "carp.policy_type": args.policy,
            "carp.training_seed": str(args.seed),
        }
        outputs = TaskPolicyOutputs(model_dir / "policy.pt", report_dir)
        stage = f"train_multitask@{args.policy}-{args.seed}" if args.multitask else (
            f"train_policy@{args.task}-{args.policy}-{args.seed}"
        )  # fmt: skip
        with mlflow_stage(params, stage, trained, tags) as run:
            metrics = train_and_write(request, inputs, outputs, run)
    finally:
        distributed.stop_process_group()
    # A multi-task policy's held-out errors are per task (`<task>/valid_action_rmse`).
    errors = ", ".join(f"{key} {value:.4f}" for key, value in metrics.items() if key.endswith("valid_action_rmse"))
    print(f"{trained} {args.policy} seed {args.seed}: final loss {metrics['final_loss']:.4f}, held-out {errors or '-'}")


if __name__ == "__main__":
    main()
