"""evaluate stage: models/policy/<task>/<policy>/seed<seed>/ -> reports/eval/<task>/<policy>/seed<seed>*.

With validation episodes (`eval.validation_episodes`) every candidate policy of the run (the final one and its
snapshots) runs on the validation seeds first; `eval.selection` then fixes one, and only that one runs on the test
seeds. Writes the summary `seed<seed>.json`, the test episodes `seed<seed>_episodes.csv` and the validation episodes
`seed<seed>_validation.csv` (empty without validation).

With `eval.run_test: false` (the sweep's trials) no test episode runs: the summary holds the selected candidate's
validation figures (`validation_score`, `validation_success_rate`, `test_episodes: 0`) and the episodes table is
empty. When the environment names a progress file (`carp.evaluation.progress`), each candidate's validation is
appended to it as it finishes, and the stage stops with an error once a stop file appears beside it.

With --multitask (the evaluate_multitask stage) it evaluates the family's multi-task policy,
models/policy/multitask/<policy>/seed<seed>/, on --task, with that task's statistics and task id, and writes
reports/eval/<task>/<policy>-multitask/seed<seed>*.

A task without a simulator (`carp.tasks.offline`) has no episodes to roll out: its policies are scored by their
action errors on the held-out episodes instead (`offline_evaluation.py`), into the same files.
"""

import argparse
import os
import tempfile
from pathlib import Path

import pandas as pd
from evaluation_support import episode_runner
from offline_evaluation import evaluate_offline
from stage_support import (
    EVAL_VIDEO_DIR,
    PROCESSED_DIR,
    camera_settings,
    evaluation_report,
    fail,
    mlflow_stage,
    policy_stage_args,
    setup_logging,
    stage_policy_paths,
)

from carp.config import Params
from carp.data.dataset import load_task_windows
from carp.evaluation.progress import PROGRESS_VARIABLE, ProgressFile, ValidatedCandidate, ValidationStopped
from carp.evaluation.runner import buffer_latency, episodes_table, write_episode_videos
from carp.evaluation.selection import (
    AVERAGED_POLICY_NAME,
    evaluate_as_configured,
    find_candidates,
    save_averaged_policy,
    validation_only_summary,
)
from carp.outputs import write_json
from carp.policies.registry import load_policy
from carp.tasks.base import OFFLINE, ROLLOUTS
from carp.training.checkpoint import CheckpointError


def main() -> None:
    setup_logging()
    args, params = policy_stage_args(__doc__)
    evaluations = {ROLLOUTS: evaluate_in_simulation, OFFLINE: evaluate_offline}
    evaluations[params.task(args.task).evaluation](args, params)


def evaluate_in_simulation(args: argparse.Namespace, params: Params) -> None:
    """Roll the run's candidates out on the validation seeds, then the chosen one on the test seeds."""
    data, config = params.data, params.eval
    if config.video:
        # Headless offscreen rendering through EGL (Debian: libegl1, libegl-mesa0, libgl1-mesa-dri; `make render-deps`).
        # Worker processes are spawned after this point and inherit it.
        os.environ.setdefault("MUJOCO_GL", "egl")
    cameras = camera_settings(params)
    run_dir, training_report_dir, label = stage_policy_paths(args)
    history = training_report_dir / "history.csv"
    try:
        policy = load_policy(run_dir / "policy.pt")
        candidates = find_candidates(run_dir, pd.read_csv(history)["loss"].tolist())
    except (CheckpointError, FileNotFoundError, ValueError) as error:
        fail(str(error))
    if config.selection == "average_last" and config.average_last > len(candidates):
        fail(
            f"{args.params}: eval.average_last={config.average_last}: the training in {run_dir} kept "
            f"{len(candidates)} candidates (epochs {[candidate.epoch for candidate in candidates]}); keep more "
            "snapshots (training.snapshot_every, training.snapshot_last) or average fewer"
        )
    windows = load_task_windows(PROCESSED_DIR / args.task, data.action_horizon, data.obs_steps, data.action_steps)
    inference = params.inference_settings(args.policy, args.task)
    tags = {
        "carp.policy_run_id": policy.metadata.get("mlflow_run_id", ""),
        "carp.policy_type": args.policy,
        "carp.training_seed": str(args.seed),
        "carp.multitask": str(args.multitask).lower(),
    }
    stage = "evaluate_multitask" if args.multitask else "evaluate"
    with (
        mlflow_stage(params, f"{stage}@{args.task}-{args.policy}-{args.seed}", args.task, tags) as run,
        tempfile.TemporaryDirectory(prefix="carp-averaged-") as scratch,
    ):

        def average(candidates):
            # The averaged policy is evaluated, not kept: the snapshots it comes from are the stage's inputs.
            return save_averaged_policy(candidates, Path(scratch) / AVERAGED_POLICY_NAME)

        # Only the test episodes are recorded: they are the ones the report shows.
        run_episodes = episode_runner(
            params, args.task, args.policy, windows.buffer.attrs["env_args"], video_seeds=config.test_seeds()
        )
        try:
            evaluated = evaluate_as_configured(
                config,
                candidates,
                run_episodes,
                lambda outcome: [result.success for result in outcome[1]],
                average,
                progress_reporter(f"{args.task}/{label}/seed{args.seed}"),
            )
        except ValidationStopped as error:
            fail(f"{args.task} {label} seed {args.seed}: {error}")
        if evaluated.test is None:
            summary, results = validation_only_summary(evaluated.validation[evaluated.selection.chosen.epoch]), []
        else:
            summary, results = evaluated.test
        summary.update(evaluated.selection.validation_summary(config.validation_top_k))
        summary["selection"] = evaluated.selection.rule
        summary["candidates"] = len(candidates)
        summary["training_seed"] = args.seed
        if "validation_max_success_rate" in summary and config.run_test:
            summary["validation_max_test_gap"] = summary["validation_max_success_rate"] - summary["success_rate"]
        policy = load_policy(evaluated.tested)
        policy.select_task(args.task)
        policy.configure_inference(**inference)
        summary.update(
            buffer_latency(
                policy,
                windows,
                PROCESSED_DIR / args.task,
                data.action_horizon,
                data.obs_steps,
                data.action_steps,
                with_images=cameras is not None,
            )
        )
        report = evaluation_report(args.task, label, args.seed)
        report.parent.mkdir(parents=True, exist_ok=True)
        write_json(report, summary)
        episodes = report.with_name(f"{report.stem}_episodes.csv")
        (episodes_table(results) if results else pd.DataFrame(columns=EPISODE_COLUMNS)).to_csv(episodes, index=False)
        validation = report.with_name(f"{report.stem}_validation.csv")
        validation_table(evaluated.validation).to_csv(validation, index=False)
        run.log_metrics(summary)
        run.log_artifact(episodes)
        run.log_artifact(validation)
        for video in write_episode_videos(results, EVAL_VIDEO_DIR, f"{args.task}_{label}-{args.seed}"):
            run.log_artifact(video)
    if config.run_test:
        figures = (
            f"success {summary['successes']}/{summary['episodes']} ({100 * summary['success_rate']:.1f}%, 95% CI "
            f"{100 * summary['success_rate_ci_low']:.1f}-{100 * summary['success_rate_ci_high']:.1f}%)"
        )
    else:
        figures = (
            f"validation only (eval.run_test: false): success {100 * summary['validation_success_rate']:.1f}% "
            f"of {summary['validation_episodes']}, score {summary['validation_score']:.3f}"
        )
    print(
        f"{args.task} {label} seed {args.seed} (epoch {summary['selected_epoch']}, {config.selection}, "
        f"{summary['backend']}): {figures}, latency per chunk "
        f"{summary['latency_predict_ms_median']:.2f} ms predict + {summary['latency_decode_ms_median']:.2f} ms decode"
    )


EPISODE_COLUMNS = ["seed", "success", "steps", "seconds", "chunks", "chunk_ms_median", "error"]


def progress_reporter(evaluation: str):
    """The `on_validated` hook that writes each candidate's validation to the progress file the environment names.

    None when it names none (the pipeline outside a sweep).
    """
    path = os.environ.get(PROGRESS_VARIABLE)
    if not path:
        return None
    progress = ProgressFile(Path(path))

    def report(candidate, outcome) -> None:
        summary = outcome[0]
        progress.append(ValidatedCandidate(evaluation, candidate.epoch, summary["score"], summary["success_rate"]))
        if progress.stop_requested():
            raise ValidationStopped(f"stopped after epoch {candidate.epoch}'s validation: the sweep pruned the trial")

    return report


def validation_table(validation: dict) -> pd.DataFrame:
    """The validation episodes of every candidate: epoch, then the per-episode records."""
    frames = [episodes_table(results).assign(epoch=epoch) for epoch, (_, results) in sorted(validation.items())]
    columns = ["epoch", *EPISODE_COLUMNS]
    return pd.concat(frames, ignore_index=True)[columns] if frames else pd.DataFrame(columns=columns)


if __name__ == "__main__":
    main()
