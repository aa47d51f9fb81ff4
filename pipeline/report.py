"""report stage: every metrics file -> reports/report.md and a self-contained reports/report.html."""

import json
from importlib.metadata import version

import pandas as pd
from stage_support import (
    EVAL_VIDEO_DIR,
    PROCESSED_DIR,
    PROJECT_DIR,
    REPORTS_DIR,
    TOKENIZER_REPORT_DIR,
    evaluation_report,
    fail,
    git_commit,
    load,
    multitask_label,
    parse_args,
    policy_report_dir,
    setup_logging,
)

from carp.data.image_windows import episode_images
from carp.data.ingest import BUFFER_DIRNAME
from carp.evaluation.runner import episode_videos
from carp.outputs import MULTITASK_SUFFIX
from carp.reporting.report import ReportInputs, write_report
from carp.reporting.runs import add_referenced_runs, pooled_metrics, read_run_results, split_multitask
from carp.tasks import get_task
from carp.tasks.base import OFFLINE

SWEEP_TRIALS = REPORTS_DIR / "sweep" / "trials.csv"


def main() -> None:
    setup_logging()
    args = parse_args(__doc__)
    params = load(args.params)
    tokenizer_history = TOKENIZER_REPORT_DIR / "history.csv"
    own_labels = (*params.policies, *map(multitask_label, params.multitask))
    # A task without a simulator has offline summaries, no rollout episodes (`carp.reporting.offline`).
    offline_tasks = [task for task in params.tasks if params.task(task).evaluation == OFFLINE]
    rollout_tasks = [task for task in params.tasks if task not in offline_tasks]
    offline = {
        task: {
            label: {seed: json.loads(evaluation_report(task, label, seed).read_text()) for seed in params.seeds}
            for label in own_labels
        }
        for task in offline_tasks
    }
    runs = {
        task: {
            label: {seed: read_run_results(evaluation_report(task, label, seed)) for seed in params.seeds}
            for label in own_labels
        }
        for task in rollout_tasks
    }
    for task in rollout_tasks:
        for label in own_labels:
            for seed in params.seeds:
                if runs[task][label][seed].metrics.get("test_episodes") == 0:
                    fail(
                        f"{evaluation_report(task, label, seed)}: evaluated without test episodes "
                        f"(eval.run_test: false); set eval.run_test: true to report"
                    )
    try:
        references = {name: PROJECT_DIR / name for name in params.comparison.references}
        runs, reference_notes = add_referenced_runs(runs, references, rollout_tasks)
    except (OSError, ValueError) as error:
        fail(f"{args.params}: comparison.references: {error}")
    single_task, multitask = split_multitask(runs, MULTITASK_SUFFIX)
    # The training curves of each family's first seed; the others' histories sit beside them.
    first_seed = params.seeds[0]
    inputs = ReportInputs(
        evaluation={
            task: {policy: pooled_metrics(seed_runs) for policy, seed_runs in task_runs.items()}
            for task, task_runs in single_task.items()
        },
        runs=single_task,
        multitask={
            task: {policy: pooled_metrics(seed_runs) for policy, seed_runs in families.items()}
            for task, families in multitask.items()
        },
        multitask_runs=multitask,
        offline=offline,
        max_steps={task: params.max_steps_for(task) for task in params.tasks},
        demo_notes={task: scripted_demo_note(task) for task in params.tasks if task not in params.data.raw_files},
        reference_notes=reference_notes,
        margin=params.comparison.margin,
        alpha=params.comparison.alpha,
        min_seeds=params.comparison.min_seeds,
        tokenizer_metrics=_json_or_none(TOKENIZER_REPORT_DIR / "metrics.json"),
        tokenizer_history=pd.read_csv(tokenizer_history) if tokenizer_history.exists() else None,
        policy_histories={
            task: {
                policy: pd.read_csv(policy_report_dir(task, policy, first_seed) / "history.csv")
                for policy in params.policies
                if (policy_report_dir(task, policy, first_seed) / "history.csv").exists()
            }
            for task in params.tasks
        },
        reconstruction_figure=TOKENIZER_REPORT_DIR / "reconstruction.png",
        camera_frames={
            task: frames for task in params.tasks if (frames := episode_images(PROCESSED_DIR / task / BUFFER_DIRNAME))
        },
        videos={
            task: [
                video
                for policy in (*params.policies, *map(multitask_label, params.multitask))
                for seed in params.seeds
                for video in episode_videos(EVAL_VIDEO_DIR, f"{task}_{policy}-{seed}")
            ]
            for task in params.tasks
        },
        sweep_trials=pd.read_csv(SWEEP_TRIALS) if SWEEP_TRIALS.exists() else None,
        versions={
            name: version(name) for name in ("robosuite", "mujoco", "gym-pusht", "pymunk", "torch", "dvc", "mlflow")
        },
        git_commit=git_commit(),
        params_yaml=args.params.read_text(),
    )
    title = f"carp report: {', '.join(params.tasks)} ({', '.join(own_labels)})"
    markdown, html = write_report(inputs, REPORTS_DIR, title=title)
    print(f"wrote {markdown.relative_to(PROJECT_DIR)} and {html.relative_to(PROJECT_DIR)}")


def scripted_demo_note(task: str) -> str:
    """The caveat of a task trained on carp's scripted demos instead of the paper's."""
    spec = get_task(task)
    return (
        f"The {task} demos are scripted by carp's expert ({spec.expert_name}), not {spec.paper_demos}: success rates "
        "and scores are not directly comparable with the paper's."
    )


def _json_or_none(path):
    return json.loads(path.read_text()) if path.exists() else None


if __name__ == "__main__":
    main()
