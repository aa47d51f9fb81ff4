"""The run report: ``report.md`` and a self-contained ``report.html`` built from the pipeline's metrics files.

Both documents come from one list of sections (text, tables as DataFrames, PNG figures), so they never disagree.
The HTML embeds its figures as base64 data URIs and carries no scripts, fonts or stylesheets from the network, so
it reads offline.
"""

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from carp.outputs import MULTITASK_SUFFIX  # noqa: E402
from carp.reporting import (
    claims,  # noqa: E402
    comparison,  # noqa: E402
    verdict_text,  # noqa: E402
    verdicts,  # noqa: E402
)
from carp.reporting.document import Section, write_sections  # noqa: E402
from carp.reporting.image_grid import save_frame_grid  # noqa: E402
from carp.reporting.offline import OfflineRuns, offline_section  # noqa: E402
from carp.reporting.report_tables import (  # noqa: E402
    comparison_table,
    inference_budget_lines,
    latency_table,
    multitask_table,
    plot_curves,
    plot_success_against_latency,
    plot_sweep,
    success_table,
    tokenizer_table,
    tokenizer_task_table,
)
from carp.reporting.runs import Runs


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
        offline: task -> policy label -> training seed -> the offline evaluation summary of a task without a
            simulator (`carp.reporting.offline`); such a task is in none of the rollout mappings above.
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
    offline: Mapping[str, OfflineRuns] = field(default_factory=dict)
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
    sections += [offline_section(task, runs) for task, runs in inputs.offline.items() if runs]
    decided = decide_verdicts(inputs)
    if inputs.multitask:
        sections.append(multitask_section(inputs, decided))
    if inputs.runs:
        sections += comparison_sections(inputs, decided, figures_dir)
    if any(inputs.evaluation.values()):  # a run whose tasks all lack a simulator has no rollouts to tabulate
        sections += rollout_summary_sections(inputs.evaluation, figures_dir)
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


def rollout_summary_sections(evaluation: Mapping[str, Mapping[str, Mapping]], figures_dir: Path) -> list[Section]:
    """Success rates and inference latency of every task's rollouts (task -> family -> pooled metrics)."""
    return [
        Section(
            "Success rate",
            paragraphs=[
                "Episodes with fixed seeds disjoint from the collection seeds; success is the env's own check."
            ],
            tables=[success_table(evaluation)],
            figures=[plot_success_against_latency(evaluation, figures_dir / "success_vs_latency.png")],
        ),
        Section(
            "Inference latency per chunk (ms)",
            paragraphs=[
                "Prediction is everything up to the family's decoding step (CARP: the coarse-to-fine token "
                "prediction; a diffusion policy: the denoising loop); decoding turns the prediction into actions. "
                "Rollouts run one environment per worker with the backend named in each row (CARP: the exported "
                "ONNX graphs on ONNX Runtime unless `eval.backend` is torch; the baselines: PyTorch in inference "
                "mode); the batched rows are the PyTorch policies.",
                *inference_budget_lines(evaluation),
            ],
            tables=[latency_table(evaluation)],
        ),
    ]


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


def write_report(inputs: ReportInputs, output_dir: Path, title: str = "carp report") -> tuple[Path, Path]:
    """Write ``report.md``, ``report.html`` and ``figures/`` into ``output_dir``; returns the two document paths."""
    output_dir = Path(output_dir)
    figures_dir = output_dir / "figures"
    figures_dir.mkdir(parents=True, exist_ok=True)
    return write_sections(build_sections(inputs, figures_dir), output_dir, title)
