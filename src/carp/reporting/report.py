"""The run report: ``report.md`` and a self-contained ``report.html`` built from the pipeline's metrics files.

Both documents come from one list of sections (text, tables as DataFrames, PNG figures), so they never disagree.
The HTML embeds its figures as base64 data URIs and carries no scripts, fonts or stylesheets from the network, so
it reads offline.
"""

import base64
import html
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from carp.evaluation.metrics import wilson_interval  # noqa: E402
from carp.outputs import MULTITASK_SUFFIX  # noqa: E402
from carp.reporting import (
    claims,  # noqa: E402
    comparison,  # noqa: E402
    verdict_text,  # noqa: E402
    verdicts,  # noqa: E402
)
from carp.reporting.figures import finish_figure  # noqa: E402
from carp.reporting.image_grid import save_frame_grid  # noqa: E402
from carp.reporting.runs import Runs
from carp.tokenizer.task_metrics import task_errors  # noqa: E402


@dataclass
class Section:
    """One report section: a title, paragraphs, tables and figures in that order."""

    title: str
    paragraphs: list[str] = field(default_factory=list)
    tables: list[pd.DataFrame] = field(default_factory=list)
    figures: list[Path] = field(default_factory=list)
    code: str = ""


@dataclass
class ReportInputs:
    """Everything a report is made of (all optional except the evaluation metrics).

    Attributes:
        evaluation: task -> policy family -> evaluation metrics dict (``reports/eval/<task>/<policy>/seed<seed>.json``;
            pooled over the seeds with `runs`).
        tokenizer_metrics: tokenizer reconstruction metrics (``reports/tokenizer/metrics.json``).
        tokenizer_history: per-epoch tokenizer losses.
        policy_histories: task -> policy family -> per-epoch losses (and CARP's token accuracies); their
            ``epoch_seconds`` sum to the training wall time of the comparison table.
        reconstruction_figure: raw vs reconstructed actions PNG.
        camera_frames: task -> obs key -> (T, H, W, 3) uint8 frames of one demo, for runs on camera images; the
            report draws a grid of them per task to check by eye that the rendered observations look right.
        videos: task -> the evaluation's recorded episodes as GIFs (``eval.video``), shown under each task.
        runs: task -> policy family -> training seed -> that seed's summary and test episodes
            (`carp.reporting.runs.RunResults`); with it the report adds the per-seed tables, the paired
            comparisons with their verdicts, the steps-to-success curves and the paper's claims. `evaluation` then
            holds each family's figures pooled over its seeds (`carp.reporting.runs.pooled_metrics`).
        multitask: task -> policy family -> the evaluation metrics of that family's multi-task policy (one policy
            trained over every task of the run) on the task, pooled over its seeds like `evaluation`
            (``reports/eval/<task>/<policy>-multitask/``); the report sets it next to the single-task policy of the
            same family where `evaluation` has one.
        multitask_runs: task -> policy family -> training seed -> the multi-task policy's results on the task, like
            `runs`; with it the report compares each multi-task policy with the family's single-task policy on the
            same episodes (difference over training seeds, verdict) and gives its task measures.
        max_steps: task -> episode step limit (the curves' horizon).
        demo_notes: task -> where its demos came from, when that limits the comparison with the paper (scripted
            demos where the paper trained on human ones); shown under the task's policies.
        reference_notes: task -> which of its evaluations came from other runs (``comparison.references``); shown
            under the task's policies.
        margin: equivalence margin of the verdicts, in success rate.
        alpha: family-wise significance level of all the report's verdicts (one correction over them).
        min_seeds: training seeds per family a family verdict needs.
        sweep_trials: the Optuna sweep's trials table, when a sweep ran.
        versions: package -> version (robosuite, mujoco, torch, ...).
        git_commit: commit the pipeline ran at.
        params_yaml: the params file's text.
    """

    evaluation: Mapping[str, Mapping[str, Mapping]]
    tokenizer_metrics: Mapping | None = None
    tokenizer_history: pd.DataFrame | None = None
    policy_histories: Mapping[str, Mapping[str, pd.DataFrame]] = field(default_factory=dict)
    reconstruction_figure: Path | None = None
    camera_frames: Mapping[str, Mapping[str, np.ndarray]] = field(default_factory=dict)
    videos: Mapping[str, Sequence[Path]] = field(default_factory=dict)
    runs: Mapping[str, Mapping[str, "Runs"]] = field(default_factory=dict)
    multitask: Mapping[str, Mapping[str, Mapping]] = field(default_factory=dict)
    multitask_runs: Mapping[str, Mapping[str, "Runs"]] = field(default_factory=dict)
    max_steps: Mapping[str, int] = field(default_factory=dict)
    demo_notes: Mapping[str, str] = field(default_factory=dict)
    reference_notes: Mapping[str, str] = field(default_factory=dict)
    margin: float = 0.05
    alpha: float = 0.05
    min_seeds: int = verdicts.DEFAULT_MIN_SEEDS
    sweep_trials: pd.DataFrame | None = None
    versions: Mapping[str, str] = field(default_factory=dict)
    git_commit: str = "unknown"
    params_yaml: str = ""


IMAGE_MEDIA_TYPES = {".png": "image/png", ".gif": "image/gif"}
"""Media type of each kind of figure the HTML embeds (plots are PNG, rollout videos animated GIF)."""

CONTROL_STEPS = 400
"""Control steps of the Table-1-style inference budget for a task carp does not know (the paper's supplementary
table 1: 400 steps, the arm tasks' episode limit)."""


def budget_steps(task: str) -> int:
    """Control steps of `task`'s inference budget: its protocol's episode limit (arms 400, Push-T 300)."""
    from carp.tasks import TASK_NAMES, get_task

    return get_task(task).default_max_steps if task in TASK_NAMES else CONTROL_STEPS


def comparison_table(
    evaluations: Mapping[str, Mapping], histories: Mapping[str, pd.DataFrame] | None = None
) -> pd.DataFrame:
    """One task's row per policy family: success with its 95% Wilson interval, latency, model calls, size, backend.

    Args:
        evaluations: policy family -> that family's evaluation metrics on the task.
        histories: policy family -> its training history; the ``epoch_seconds`` sum is the training wall time.
    """
    rows = []
    for policy, metrics in evaluations.items():
        successes, episodes = int(metrics["successes"]), int(metrics["episodes"])
        lower, upper = wilson_interval(successes, episodes)
        history = (histories or {}).get(policy)
        seconds = float(history["epoch_seconds"].sum()) if history is not None and "epoch_seconds" in history else None
        rows.append(
            {
                "policy": policy,
                "inference": metrics.get("inference") or token_choice(metrics.get("top_k")),
                "success": f"{successes}/{episodes}",
                "rate": f"{100 * successes / episodes:.1f}%",
                "95% interval": f"{100 * lower:.1f}-{100 * upper:.1f}%",
                "crashed": int(metrics.get("crashed_episodes", 0)),
                "predict ms (median / p90)": _pair(metrics, "latency_predict_ms"),
                "decode ms (median / p90)": _pair(metrics, "latency_decode_ms"),
                "model calls": _integer(metrics.get("model_calls_per_chunk")),
                "parameters": _integer(metrics.get("num_parameters")),
                "training": "-" if seconds is None else f"{seconds / 60:.1f} min",
                "backend": metrics.get("backend", "-"),
            }
        )
    return pd.DataFrame(rows)


def success_table(evaluation: Mapping[str, Mapping[str, Mapping]]) -> pd.DataFrame:
    """One row per (task, policy): successes, rate, 95% Wilson interval, mean episode length, inference setting."""
    rows = []
    for task, policies in evaluation.items():
        for policy, metrics in policies.items():
            successes, episodes = int(metrics["successes"]), int(metrics["episodes"])
            lower, upper = wilson_interval(successes, episodes)
            rows.append(
                {
                    "task": task,
                    "policy": policy,
                    "success": f"{successes}/{episodes}",
                    "rate": f"{100 * successes / episodes:.1f}%",
                    "95% interval": f"{100 * lower:.1f}-{100 * upper:.1f}%",
                    "mean steps": f"{metrics.get('mean_episode_steps', float('nan')):.0f}",
                    "crashed": int(metrics.get("crashed_episodes", 0)),
                    "decoding": metrics.get("inference") or token_choice(metrics.get("top_k")),
                }
            )
    return pd.DataFrame(rows)


def multitask_table(
    multitask: Mapping[str, Mapping[str, Mapping]], evaluation: Mapping[str, Mapping[str, Mapping]]
) -> pd.DataFrame:
    """One row per (task, family) of a multi-task policy: its success and that of the family's single-task policy.

    Each success is given as successes/episodes and rate with its 95% Wilson interval; "-" where the run has no
    single-task policy of that family on the task.

    Args:
        multitask: task -> family -> the multi-task policy's evaluation metrics on the task.
        evaluation: task -> family -> the single-task policies' evaluation metrics.
    """
    rows = []
    for task, families in multitask.items():
        for policy, metrics in families.items():
            single = evaluation.get(task, {}).get(policy)
            multi_success, multi_interval = _success_and_interval(metrics)
            single_success, single_interval = ("-", "-") if single is None else _success_and_interval(single)
            rows.append(
                {
                    "task": task,
                    "policy": policy,
                    "multi-task success": multi_success,
                    "multi-task 95% interval": multi_interval,
                    "single-task success": single_success,
                    "single-task 95% interval": single_interval,
                }
            )
    return pd.DataFrame(rows)


def _success_and_interval(metrics: Mapping) -> tuple[str, str]:
    successes, episodes = int(metrics["successes"]), int(metrics["episodes"])
    lower, upper = wilson_interval(successes, episodes)
    return f"{successes}/{episodes} ({100 * successes / episodes:.1f}%)", f"{100 * lower:.1f}-{100 * upper:.1f}%"


def token_choice(top_k: float | None) -> str:
    """How an evaluation chose tokens: "greedy", "top-<k> draws", or "-" for metrics that predate the record."""
    if top_k is None:
        return "-"
    return "greedy" if int(top_k) == 1 else f"top-{int(top_k)} draws"


def latency_table(evaluation: Mapping[str, Mapping[str, Mapping]]) -> pd.DataFrame:
    """Per (task, policy): per-chunk latency (ms) of prediction and decoding, at batch 1 in rollouts and batched.

    For an image policy, "encoder median" is the camera encoder's share of the prediction ("-" for state policies),
    so the latency without the encoder is the prediction minus it.
    """
    rows = []
    for task, policies in evaluation.items():
        for policy, metrics in policies.items():
            for setting, prefix in (("batch 1 (rollouts)", "latency"), ("batched", "batched_latency")):
                if f"{prefix}_predict_ms_median" not in metrics:
                    continue
                batch = metrics.get("batched_latency_batch_size", "") if prefix == "batched_latency" else 1
                backend = metrics.get("backend", "-") if prefix == "latency" else "torch"
                rows.append(
                    {
                        "task": task,
                        "policy": policy,
                        "setting": f"{setting}" + (f", B={batch}" if prefix == "batched_latency" else ""),
                        "backend": backend,
                        "predict median": f"{metrics[f'{prefix}_predict_ms_median']:.2f}",
                        "predict p90": f"{metrics[f'{prefix}_predict_ms_p90']:.2f}",
                        "decode median": f"{metrics[f'{prefix}_decode_ms_median']:.2f}",
                        "decode p90": f"{metrics[f'{prefix}_decode_ms_p90']:.2f}",
                        "encoder median": _milliseconds(metrics.get(f"{prefix}_encode_ms_median")),
                    }
                )
    return pd.DataFrame(rows)


def _milliseconds(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def inference_budget_lines(evaluation: Mapping[str, Mapping[str, Mapping]]) -> list[str]:
    """Table-1-style lines: per (task, policy), total inference time over the task's episode limit (`budget_steps`).

    A chunk is predicted every ``action_steps`` (Ta) control steps, so N steps take ``ceil(N / Ta)`` chunks at
    the median batch-1 latency of prediction plus decoding (the camera encoder included for image policies). The
    cameras an image policy sees are rendered at every control step; that time is given apart.
    """
    lines = []
    for task, policies in evaluation.items():
        steps = budget_steps(task)
        for policy, metrics in policies.items():
            if "latency_predict_ms_median" not in metrics or "action_steps" not in metrics:
                continue
            chunks = -(-steps // int(metrics["action_steps"]))
            chunk_ms = metrics["latency_predict_ms_median"] + metrics["latency_decode_ms_median"]
            lines.append(
                f"{task}, {policy} ({metrics.get('inference', '-')}, {metrics.get('backend', '-')}): "
                f"{chunks * chunk_ms / 1000:.2f} s of inference over {steps} control steps "
                f"({chunks} chunks of {chunk_ms:.2f} ms)"
                + (
                    f", {metrics['latency_encode_ms_median']:.2f} ms of each in the camera encoder"
                    if "latency_encode_ms_median" in metrics
                    else ""
                )
                + (
                    f"; rendering the cameras: {steps * metrics['render_step_ms_median'] / 1000:.2f} s "
                    f"({metrics['render_step_ms_median']:.2f} ms per step)"
                    if "render_step_ms_median" in metrics
                    else ""
                )
            )
    return lines


def plot_success_against_latency(evaluation: Mapping[str, Mapping[str, Mapping]], path: Path) -> Path:
    """Success rate (with its 95% interval) against batch-1 latency per chunk on a log axis; one point per pair."""
    figure, axis = plt.subplots(figsize=(6, 3.6))
    for task, policies in evaluation.items():
        for policy, metrics in policies.items():
            if "latency_predict_ms_median" not in metrics:
                continue
            successes, episodes = int(metrics["successes"]), int(metrics["episodes"])
            lower, upper = wilson_interval(successes, episodes)
            rate = successes / episodes
            latency = metrics["latency_predict_ms_median"] + metrics["latency_decode_ms_median"]
            axis.errorbar(
                [latency],
                [100 * rate],
                yerr=[[100 * (rate - lower)], [100 * (upper - rate)]],
                fmt="o",
                capsize=3,
                label=f"{task}: {policy}",
            )
    axis.set_xscale("log")
    axis.set_xlabel("latency per chunk at batch 1 (ms, log scale)")
    axis.set_ylabel("success rate (%)")
    axis.set_ylim(0, 105)
    return finish_figure(figure, axis, path)


def _pair(metrics: Mapping, prefix: str) -> str:
    if f"{prefix}_median" not in metrics:
        return "-"
    return f"{metrics[f'{prefix}_median']:.2f} / {metrics[f'{prefix}_p90']:.2f}"


def _integer(value: float | None) -> str:
    return "-" if value is None else f"{int(value):,}"


TOKENIZER_COLUMNS = {
    "rmse": "RMSE",
    "rmse_percent_range": "RMSE % of range",
    "max_error": "max error",
    "usage/all_scales": "code usage",
    "perplexity": "perplexity",
}


def tokenizer_table(metrics: Mapping[str, float]) -> pd.DataFrame:
    """Per-dimension rows from flat tokenizer metrics keyed ``<metric>/<dimension>``."""
    # Aggregates ("mean", "max") are summarized in the text, not listed as dimensions.
    dimensions = [
        key.split("/", 1)[1] for key in metrics if key.startswith("rmse/") and key not in ("rmse/mean", "rmse/max")
    ]
    rows = []
    for dimension in dimensions:
        row = {"dimension": dimension}
        for key, label in TOKENIZER_COLUMNS.items():
            value = metrics.get(f"{key}/{dimension}")
            row[label] = "" if value is None else f"{value:.4g}"
        rows.append(row)
    return pd.DataFrame(rows)


def tokenizer_task_table(metrics: Mapping[str, float]) -> pd.DataFrame:
    """One row per task of a tokenizer measured on several tasks (`carp.tokenizer.task_metrics`); empty otherwise."""
    rows = []
    for task, own in task_errors(metrics).items():
        dimensions = [key.split("/", 1)[1] for key in own if key.startswith("rmse_percent_range/")]
        worst = max(
            (name for name in dimensions if name not in ("mean", "max")),
            key=lambda name: own[f"rmse_percent_range/{name}"],
        )
        rows.append(
            {
                "task": task,
                "RMSE % of range (mean)": f"{own['rmse_percent_range/mean']:.3g}",
                "worst dimension": f"{worst} ({own[f'rmse_percent_range/{worst}']:.3g}%)",
                "max error": f"{own['max_error/max']:.4g}",
            }
        )
    return pd.DataFrame(rows)


def plot_curves(history: pd.DataFrame, columns: Sequence[str], title: str, path: Path, log_scale: bool = True) -> Path:
    """Plot per-epoch columns of a history table to a PNG."""
    figure, axis = plt.subplots(figsize=(6, 3.2))
    for column in columns:
        if column in history:
            axis.plot(history["epoch"], history[column], label=column)
    axis.set_xlabel("epoch")
    axis.set_title(title)
    if log_scale and (history[[c for c in columns if c in history]] > 0).all().all():
        axis.set_yscale("log")
    return finish_figure(figure, axis, path)


def plot_sweep(trials: pd.DataFrame, path: Path) -> Path:
    """Validation success against the number of scales K, one line per codebook size (the paper's ablation on K)."""
    figure, axis = plt.subplots(figsize=(5, 3.2))
    for size, group in trials.groupby("codebook_size"):
        ordered = group.sort_values("num_scales")
        axis.plot(ordered["num_scales"], 100 * ordered["validation_success_rate"], marker="o", label=f"V={size}")
    axis.set_xlabel("number of scales K")
    axis.set_ylabel("validation success rate (%)")
    axis.set_ylim(0, 105)
    return finish_figure(figure, axis, path)


def build_sections(inputs: ReportInputs, figures_dir: Path) -> list[Section]:
    """Assemble the report's sections; figures are written into ``figures_dir``."""
    sections = [
        Section(
            f"Policies on {task}",
            paragraphs=[
                "Episodes with fixed seeds disjoint from the collection seeds, the same for every policy; success is "
                "the env's own check, with its 95% Wilson interval. Latency per chunk at batch 1 in the rollouts, "
                "split into prediction and decoding; model calls are the sequential network calls per chunk "
                "(K scales, L tokens or N denoising steps); the backend ran the rollouts.",
                *([inputs.demo_notes[task]] if task in inputs.demo_notes else []),
                *([inputs.reference_notes[task]] if task in inputs.reference_notes else []),
            ],
            tables=[comparison_table(policies, inputs.policy_histories.get(task))],
        )
        for task, policies in inputs.evaluation.items()
        if policies
    ]
    decided = decide_verdicts(inputs)
    if inputs.multitask:
        sections.append(multitask_section(inputs, decided))
    if inputs.runs:
        sections += comparison_sections(inputs, decided, figures_dir)
    sections += [
        Section(
            "Success rate",
            paragraphs=[
                "Episodes with fixed seeds disjoint from the collection seeds; success is the env's own check."
            ],
            tables=[success_table(inputs.evaluation)],
            figures=[plot_success_against_latency(inputs.evaluation, figures_dir / "success_vs_latency.png")],
        ),
        Section(
            "Inference latency per chunk (ms)",
            paragraphs=[
                "Prediction is everything up to the family's decoding step (CARP: the coarse-to-fine token "
                "prediction; a diffusion policy: the denoising loop); decoding turns the prediction into actions. "
                "Rollouts run one environment per worker with the backend named in each row (CARP: the exported "
                "ONNX graphs on ONNX Runtime unless `eval.backend` is torch; the baselines: PyTorch in inference "
                "mode); the batched rows are the PyTorch policies.",
                *inference_budget_lines(inputs.evaluation),
            ],
            tables=[latency_table(inputs.evaluation)],
        ),
    ]
    if inputs.camera_frames:
        sections.append(
            Section(
                "Camera images",
                paragraphs=[
                    "Evenly spaced frames of each task's first demo as stored for the policy (before its crop): the "
                    "scene, the objects and the gripper should be visible and upright."
                ],
                figures=[
                    save_frame_grid(frames, figures_dir / f"cameras_{task}.png", title=task)
                    for task, frames in inputs.camera_frames.items()
                ],
            )
        )
    if any(inputs.videos.values()):
        sections.append(
            Section(
                "Rollout videos",
                paragraphs=[
                    "The first evaluation episodes of each policy from the agent-view camera, every second control "
                    "step; the file names give the task, the policy and the episode's seed."
                ],
                figures=[Path(video) for videos in inputs.videos.values() for video in videos],
            )
        )
    tokenizer = Section("Action tokenizer")
    if inputs.tokenizer_metrics:
        metrics = inputs.tokenizer_metrics
        tokenizer.paragraphs.append(
            "Reconstruction of held-out windows in original action units: mean RMSE "
            f"{metrics.get('rmse_percent_range/mean', float('nan')):.2f}% of each dimension's range, "
            f"worst error {metrics.get('max_error/max', float('nan')):.4f}."
        )
        tokenizer.tables.append(tokenizer_table(metrics))
        per_task = tokenizer_task_table(metrics)
        if not per_task.empty:
            tokenizer.paragraphs.append(
                "The tokenizer is shared by the tasks; each task's held-out windows alone, relative to its own ranges:"
            )
            tokenizer.tables.append(per_task)
    if inputs.reconstruction_figure and Path(inputs.reconstruction_figure).exists():
        tokenizer.figures.append(Path(inputs.reconstruction_figure))
    if tokenizer.paragraphs or tokenizer.figures:
        sections.append(tokenizer)

    curves = Section("Training curves")
    if inputs.tokenizer_history is not None and not inputs.tokenizer_history.empty:
        columns = [c for c in inputs.tokenizer_history.columns if c.endswith("loss")]
        curves.figures.append(
            plot_curves(inputs.tokenizer_history, columns, "tokenizer", figures_dir / "tokenizer_curves.png")
        )
    for task, histories in inputs.policy_histories.items():
        for policy, history in histories.items():
            if history.empty:
                continue
            name = f"{task}_{policy}"
            columns = [c for c in history.columns if c.endswith("loss")]
            curves.figures.append(
                plot_curves(history, columns, f"{policy} ({task})", figures_dir / f"policy_{name}_loss.png")
            )
            accuracy = [c for c in history.columns if c.startswith("token_accuracy")]
            if accuracy:
                curves.figures.append(
                    plot_curves(
                        history,
                        accuracy,
                        f"token accuracy, {policy} ({task})",
                        figures_dir / f"policy_{name}_acc.png",
                        False,
                    )
                )
    if curves.figures:
        sections.append(curves)

    if inputs.sweep_trials is not None and not inputs.sweep_trials.empty:
        sweep = Section("Sweep over scales and codebook size", tables=[inputs.sweep_trials])
        if {"num_scales", "codebook_size", "validation_success_rate"} <= set(inputs.sweep_trials.columns):
            sweep.figures.append(plot_sweep(inputs.sweep_trials, figures_dir / "sweep_scales.png"))
        sections.append(sweep)

    versions = ", ".join(f"{name} {version}" for name, version in inputs.versions.items())
    sections.append(
        Section(
            "Provenance",
            paragraphs=[f"git commit `{inputs.git_commit}`", f"versions: {versions}"],
            code=inputs.params_yaml,
        )
    )
    return sections


def multitask_section(inputs: ReportInputs, decided: "ReportVerdicts") -> Section:
    """Each multi-task policy beside its family's single-task policy per task, with paired verdicts and task measures.

    The verdicts set each multi-task policy against its single-task policy and against the other families' multi-task
    policies; the paper's claims are checked on the multi-task policies as on the single-task families.
    """
    section = Section(
        "Multi-task",
        paragraphs=[
            "One policy per family trained over every task of the run, told the task by a learned task "
            "embedding, evaluated on each task on the same episode seeds as the single-task policies; next "
            "to it the single-task policy of the same family on that task. Successes are pooled over the "
            "training seeds, with their 95% Wilson intervals."
        ],
        tables=[multitask_table(inputs.multitask, inputs.evaluation)],
    )
    pairs = [(task, pair) for task, task_pairs in decided.multitask.items() for pair in task_pairs]
    if pairs:
        section.paragraphs.append(
            "Each multi-task policy against its single-task policy, and the multi-task policies of different families "
            "against each other, on the episodes they share, tested as the pairs of families are (one correction over "
            f"every verdict of the report at alpha {inputs.alpha}; "
            f'"on par" means within +-{100 * inputs.margin:.0f} points).'
        )
        section.paragraphs += [f"{task}, {pair.verdict}: {pair.explanation}" for task, pair in pairs]
        table = verdict_text.pairs_table([pair for _, pair in pairs])
        table.insert(0, "task", [task for task, _ in pairs])
        section.tables.append(table)
    for task, families in inputs.multitask_runs.items():
        measures = comparison.measure_table({family + MULTITASK_SUFFIX: runs for family, runs in families.items()})
        if not measures.empty:
            section.paragraphs.append(f"The multi-task policies' own measures on {task} (as in the task's comparison).")
            section.tables.append(measures)
    claims_rows = claims.claims_table(
        inputs.multitask_runs,
        decided.multitask,
        decided.multitask_precision,
        alpha=inputs.alpha,
        suffix=MULTITASK_SUFFIX,
    )
    if not claims_rows.empty:
        section.paragraphs.append(
            "The paper's claims checked on the multi-task policies (its Table 4 sets a multi-task CARP against a "
            "multi-task diffusion policy), as for the single-task families."
        )
        section.tables.append(claims_rows)
    return section


@dataclass(frozen=True)
class ReportVerdicts:
    """Every verdict a report states, decided under one correction (`decide_verdicts`).

    Attributes:
        single_task: task -> the single-task families' decided pairs.
        multitask: task -> the multi-task policies' decided pairs.
        single_task_precision: the single-task families' precision tests, corrected.
        multitask_precision: the multi-task policies' precision tests, corrected.
    """

    single_task: Mapping[str, Sequence[verdicts.PairComparison]]
    multitask: Mapping[str, Sequence[verdicts.PairComparison]]
    single_task_precision: Sequence[claims.PrecisionTest]
    multitask_precision: Sequence[claims.PrecisionTest]


def decide_verdicts(inputs: ReportInputs) -> ReportVerdicts:
    """The report's single-task and multi-task pairs and precision claims, decided under one correction."""
    groups = [
        (list(inputs.runs), comparison.family_pairs(inputs.runs)),
        (list(inputs.multitask_runs), comparison.multitask_pairs(inputs.runs, inputs.multitask_runs, MULTITASK_SUFFIX)),
    ]
    single_tests = claims.precision_tests(inputs.runs, inputs.min_seeds)
    multitask_tests = claims.precision_tests(inputs.multitask_runs, inputs.min_seeds)
    (single, multi), tests = comparison.decide_report(
        groups, single_tests + multitask_tests, inputs.margin, inputs.alpha, min_seeds=inputs.min_seeds
    )
    return ReportVerdicts(single, multi, tests[: len(single_tests)], tests[len(single_tests) :])


def comparison_sections(inputs: ReportInputs, decided: ReportVerdicts, figures_dir: Path) -> list[Section]:
    """The comparison sections: per task the seeds, families, paired verdicts and steps to success; then the claims."""
    margin_points = 100 * inputs.margin
    sections = []
    for task, task_runs in inputs.runs.items():
        if not task_runs:
            continue
        section = Section(
            f"Comparison on {task}",
            paragraphs=[
                "Each training seed's selected checkpoint, confirmed once on the test seeds. With validation "
                "episodes, the best validation success over the candidates (what selecting on the test seeds would "
                "report, as Diffusion Policy and robomimic do) and the mean of the best few stand next to it; the gap "
                "is the optimism that selection on the test seeds would have added.",
                "Each family over its training seeds: the family's rate is the mean over seeds with a t interval over "
                "seeds that also carries the difficulty of the shared initial states (from 2 seeds; one network says "
                "nothing about its recipe's spread). The pooled rate with its Wilson interval, the between-seed "
                "intra-class correlation and the effective episodes describe the trained networks, not the family.",
            ],
            tables=[comparison.seed_table(task_runs), comparison.family_table(task_runs)],
        )
        pairs = decided.single_task.get(task, [])
        if pairs:
            section.paragraphs.append(
                "Pairs of families on the same episode seeds, training seeds paired by number. The training seed is "
                "the unit of a family verdict: the difference is the mean over seed pairs of each pair's difference, "
                "with a t interval over seeds; a pair with fewer than "
                f"{inputs.min_seeds} training seeds gets no family verdict. Every verdict of the report is tested "
                f"inside one step-down correction at alpha {inputs.alpha} (each pair's test of a difference and its "
                f'two one-sided tests of equivalence). "On par" means the 90% interval lies within '
                f"+-{margin_points:.0f} points. The per-network column (McNemar on each seed pair's episodes, "
                "uncorrected) describes the trained networks only."
            )
            section.paragraphs += [f"{pair.verdict}: {pair.explanation}" for pair in pairs]
            section.tables.append(verdict_text.pairs_table(pairs))
        measures = comparison.measure_table(task_runs)
        if not measures.empty:
            section.paragraphs.append(
                "The task's own per-episode measures over every test episode that took them (Square: the horizontal "
                "distance in mm between the nut's and the peg's centres at their first contact, as in CARP's Tables "
                "4-5, lower is more precise; Push-T: max_reward, the episode's highest reward, whose mean is "
                "Diffusion Policy's score): the mean with its 95% t interval and the variance."
            )
            section.tables.append(measures)
        max_steps = inputs.max_steps.get(task)
        if max_steps:
            section.figures.append(
                comparison.plot_steps_to_success(
                    task_runs, max_steps, figures_dir / f"steps_to_success_{task}.png", f"steps to success ({task})"
                )
            )
        sections.append(section)
    claims_rows = claims.claims_table(
        inputs.runs, decided.single_task, decided.single_task_precision, alpha=inputs.alpha
    )
    if not claims_rows.empty:
        sections.append(
            Section(
                "The paper's claims on this run",
                paragraphs=[
                    "Each claim of the CARP paper that this run's families can check, with the verdict of the paired "
                    "comparison, the latency ratio or the precision measure behind it."
                ],
                tables=[claims_rows],
            )
        )
    return sections


def render_markdown(sections: Sequence[Section], title: str, base_dir: Path) -> str:
    """Markdown with figures referenced by paths relative to ``base_dir``."""
    lines = [f"# {title}", ""]
    for section in sections:
        lines += [f"## {section.title}", ""]
        for paragraph in section.paragraphs:
            lines += [paragraph, ""]
        for table in section.tables:
            lines += [table.to_markdown(index=False, disable_numparse=True), ""]
        for figure in section.figures:
            lines += [f"![{figure.stem}]({os.path.relpath(figure, base_dir)})", ""]
        if section.code:
            lines += ["```yaml", section.code.rstrip(), "```", ""]
    return "\n".join(lines)


def render_html(sections: Sequence[Section], title: str) -> str:
    """Self-contained HTML: inline CSS, figures as data URIs, no external resources."""
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title>",
        "<style>body{font-family:sans-serif;max-width:60em;margin:2em auto;padding:0 1em}"
        "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}"
        "img{max-width:100%}pre{background:#f6f6f6;padding:1em;overflow:auto}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
    ]
    for section in sections:
        parts.append(f"<h2>{html.escape(section.title)}</h2>")
        parts += [f"<p>{html.escape(paragraph).replace('`', '')}</p>" for paragraph in section.paragraphs]
        parts += [table.to_html(index=False, border=0) for table in section.tables]
        for figure in section.figures:
            encoded = base64.b64encode(Path(figure).read_bytes()).decode()
            media_type = IMAGE_MEDIA_TYPES[Path(figure).suffix.lower()]
            parts.append(f"<img alt='{html.escape(figure.stem)}' src='data:{media_type};base64,{encoded}'>")
        if section.code:
            parts.append(f"<pre>{html.escape(section.code)}</pre>")
    parts.append("</body></html>")
    return "\n".join(parts)


def write_report(inputs: ReportInputs, output_dir: Path, title: str = "carp report") -> tuple[Path, Path]:
    """Write ``report.md``, ``report.html`` and ``figures/`` into ``output_dir``; returns the two document paths."""
    output_dir = Path(output_dir)
    figures_dir = output_dir / "figures"
    figures_dir.mkdir(parents=True, exist_ok=True)
    return write_sections(build_sections(inputs, figures_dir), output_dir, title)


def write_sections(sections: Sequence[Section], output_dir: Path, title: str) -> tuple[Path, Path]:
    """Write `sections` as ``report.md`` and ``report.html`` into ``output_dir``, atomically; returns the two paths."""
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    markdown_path, html_path = output_dir / "report.md", output_dir / "report.html"
    for path, text in (
        (markdown_path, render_markdown(sections, title, output_dir)),
        (html_path, render_html(sections, title)),
    ):
        temporary = path.with_name(f".{path.name}.tmp")
        temporary.write_text(text)
        os.replace(temporary, path)
    return markdown_path, html_path
