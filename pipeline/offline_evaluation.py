"""The evaluate stage on a task without a simulator: action errors on the held-out episodes instead of rollouts.

Writes the same files as a rollout evaluation, so that `dvc.yaml` declares one set for every task:
`seed<seed>.json` (the errors of `carp.evaluation.offline.offline_evaluation`, with ``evaluation: offline``),
`seed<seed>_episodes.csv` (one row per held-out episode) and `seed<seed>_validation.csv` (empty: no candidate is
chosen by rollouts, the final policy is scored).
"""

import argparse

import pandas as pd
from stage_support import PROCESSED_DIR, evaluation_report, fail, mlflow_stage, stage_policy_paths

from carp.config import Params
from carp.data.ingest import BUFFER_DIRNAME
from carp.data.replay_buffer import ReplayBuffer
from carp.evaluation.offline import OFFLINE_EPISODE_COLUMNS, offline_evaluation
from carp.outputs import write_json
from carp.policies.registry import load_policy
from carp.tasks.base import OFFLINE
from carp.training.checkpoint import CheckpointError
from carp.training.runtime import seed_everything


def evaluate_offline(args: argparse.Namespace, params: Params) -> None:
    """Score the final policy of `args` (task, family, seed, --multitask) on its task's held-out episodes."""
    data = params.data
    run_dir, _, label = stage_policy_paths(args)
    try:
        policy = load_policy(run_dir / "policy.pt")
        policy.select_task(args.task)
    except (CheckpointError, FileNotFoundError, ValueError) as error:
        fail(str(error))
    policy.configure_inference(**params.inference_settings(args.policy, args.task))
    buffer = ReplayBuffer.load(PROCESSED_DIR / args.task / BUFFER_DIRNAME)
    # Families that draw (a diffusion policy's noise, CARP's top-k) give the same errors on every run.
    seed_everything(params.eval.seed)
    try:
        summary, episodes = offline_evaluation(
            policy,
            buffer,
            data.action_horizon,
            data.obs_steps,
            data.action_steps,
            params.action_format.dimension_names,
        )
    except ValueError as error:
        fail(f"{PROCESSED_DIR / args.task}: {args.task} has no simulator and is scored offline, but {error}")
    summary |= {"evaluation": OFFLINE, "selection": "final", "training_seed": args.seed}
    report = evaluation_report(args.task, label, args.seed)
    write_json(report, summary)
    episodes_file = report.with_name(f"{report.stem}_episodes.csv")
    pd.DataFrame(episodes, columns=OFFLINE_EPISODE_COLUMNS).to_csv(episodes_file, index=False)
    validation_file = report.with_name(f"{report.stem}_validation.csv")
    pd.DataFrame(columns=["epoch", *OFFLINE_EPISODE_COLUMNS]).to_csv(validation_file, index=False)
    stage = "evaluate_multitask" if args.multitask else "evaluate"
    tags = {"carp.policy_type": args.policy, "carp.training_seed": str(args.seed), "carp.evaluation": OFFLINE}
    with mlflow_stage(params, f"{stage}@{args.task}-{args.policy}-{args.seed}", args.task, tags) as run:
        run.log_metrics(summary)
        run.log_artifact(episodes_file)
    print(
        f"{args.task} {label} seed {args.seed}: no simulator, scored offline on {summary['held_out_episodes']} "
        f"held-out episodes: action RMSE {summary['action_rmse']:.4f} over the chunk, "
        f"{summary['executed_action_rmse']:.4f} over its executed rows"
    )
