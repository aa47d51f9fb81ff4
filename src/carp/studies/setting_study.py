"""Studies of one tokenizer setting: the number of scales K (supplementary Fig. 10) and the codebook size V.

A point of the study is one DVC experiment of the whole pipeline with the setting changed (``-S scales=[1,2,3]`` or
``-S codebook_size=256``) and everything else as the workspace's params say. After each experiment its evaluation
files, its tokenizer's metrics and the tokenizer itself are copied into ``<output>/<point>/``, and the demos are
replayed open loop through that tokenizer (`carp.studies.point_replay`); a point whose copy is complete is not run
again, so an interrupted study resumes, and folders of the same study run in other clones (``study.references``)
join the report at every point. The report shows, per task, each family's success against the setting with its band
over training seeds, the tokenizer's error, code usage and perplexity, its replay success and the latency per chunk,
and each point's
verdict against the reference point (the workspace's own setting), all points under one correction. The scales study
also checks the paper's reading of Fig. 10: fewer than 4 scales tokenize too coarsely, and 5 or 6 add nothing.
"""

import json
import os
import shutil
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from carp.reporting import verdicts  # noqa: E402
from carp.reporting.claims import oriented_verdict
from carp.reporting.comparison import decide_groups, family_rate, family_rate_cells
from carp.reporting.document import Section, write_sections
from carp.reporting.figures import finish_figure  # noqa: E402
from carp.reporting.runs import Runs, merge_runs, outcomes_by_seed, referenced_runs
from carp.studies.data_efficiency import COMPLETE_MARKER, Evaluations  # noqa: E402
from carp.studies.point_replay import TOKENIZER_FOLDER, read_replay, replay_cell

TOKENIZER_METRICS = "tokenizer_metrics.json"
EVAL_FOLDER = "eval"


@dataclass(frozen=True)
class SettingStudy:
    """One study: the param it varies, the values it tries and the value the others are compared with.

    Attributes:
        name: the study's name (``scales`` or ``codebook``), also its folder under ``reports/studies``.
        key: the param set by ``dvc exp run -S`` (``scales`` or ``codebook_size``).
        values: the points, in the order of the report's axis.
        reference: the value every other point is compared with; one of `values`.
    """

    name: str
    key: str
    values: tuple[Any, ...]
    reference: Any

    def __post_init__(self) -> None:
        if self.reference not in self.values:
            raise ValueError(f"study {self.name}: the reference {self.reference!r} is not one of its points")

    def folder(self, value: Any) -> str:
        """The point's folder and experiment suffix, e.g. ``K3`` for scales [1, 2, 3] or ``V256``."""
        return f"K{len(value)}" if self.key == "scales" else f"V{value}"

    def label(self, value: Any) -> str:
        """The point as the report names it, e.g. ``K=3 [1, 2, 3]`` or ``V=256``."""
        return f"K={len(value)} {list(value)}" if self.key == "scales" else f"V={value}"

    def axis(self, value: Any) -> float:
        """The point's position on the report's x axis: K, or V."""
        return float(len(value)) if self.key == "scales" else float(value)

    def overrides(self, value: Any) -> list[str]:
        """The `dvc exp run -S` value that makes the point."""
        shown = "[" + ",".join(map(str, value)) + "]" if self.key == "scales" else str(value)
        return [f"{self.key}={shown}"]


def scales_study(schedules: Sequence[Sequence[int]], reference: Sequence[int]) -> SettingStudy:
    """The scales study over `schedules`, against the workspace's `reference` schedule."""
    return SettingStudy("scales", "scales", tuple(tuple(s) for s in schedules), tuple(reference))


def codebook_study(sizes: Sequence[int], reference: int) -> SettingStudy:
    """The codebook study over `sizes`, against the workspace's `reference` size."""
    return SettingStudy("codebook", "codebook_size", tuple(sizes), reference)


def harvest_point(
    eval_dir: Path,
    tokenizer_metrics: Path,
    point_dir: Path,
    layout_marker: Mapping[str, Any],
    value: Any,
    tokenizer_dir: Path | None = None,
) -> None:
    """Copy one point's evaluations (every summary with its episodes), tokenizer metrics and tokenizer, then mark it.

    `tokenizer_dir` (the workspace's ``models/tokenizer``) is copied to ``<point>/tokenizer`` when it exists, so that
    the point's replay can be measured, or measured again, from the point folder alone.

    The copy is made beside `point_dir` and renamed into place, so a point is either complete or absent.

    Raises:
        FileNotFoundError: an evaluation the layout names, or the tokenizer's metrics, is missing.
    """
    staging = point_dir.with_name(f".{point_dir.name}.tmp")
    shutil.rmtree(staging, ignore_errors=True)
    for task in layout_marker["tasks"]:
        for policy in layout_marker["policies"]:
            for seed in layout_marker["seeds"]:
                summary = Path(eval_dir) / task / policy / f"seed{seed}.json"
                for source in (summary, summary.with_name(f"seed{seed}_episodes.csv")):
                    if not source.exists():
                        raise FileNotFoundError(f"{source}: the experiment of {value!r} left no evaluation here")
                    target = staging / EVAL_FOLDER / source.relative_to(eval_dir)
                    target.parent.mkdir(parents=True, exist_ok=True)
                    shutil.copyfile(source, target)
    if not Path(tokenizer_metrics).exists():
        raise FileNotFoundError(f"{tokenizer_metrics}: the experiment of {value!r} left no tokenizer metrics")
    shutil.copyfile(tokenizer_metrics, staging / TOKENIZER_METRICS)
    if tokenizer_dir is not None and Path(tokenizer_dir).is_dir():  # absent when the pipeline reused a tokenizer
        shutil.copytree(tokenizer_dir, staging / TOKENIZER_FOLDER)
    marker = {"value": _plain(value), **layout_marker}
    (staging / COMPLETE_MARKER).write_text(json.dumps(marker, indent=2) + "\n")
    shutil.rmtree(point_dir, ignore_errors=True)
    os.replace(staging, point_dir)


def is_complete(point_dir: Path, layout_marker: Mapping[str, Any], value: Any) -> bool:
    """Whether `point_dir` holds a finished copy of this point for this layout."""
    marker = Path(point_dir) / COMPLETE_MARKER
    if not marker.exists():
        return False
    expected = json.loads(json.dumps({"value": _plain(value), **layout_marker}))
    return json.loads(marker.read_text()) == expected


@dataclass(frozen=True)
class StudyPoint:
    """One point's evaluations (task -> family -> seed -> results), its tokenizer's metrics and its replay figures."""

    evaluations: Evaluations
    tokenizer_metrics: Mapping[str, float]
    replay: Mapping[str, Mapping[str, int]] = dataclass_field(default_factory=dict)


def load_point(point_dir: Path, tasks: Sequence[str]) -> StudyPoint:
    """A point folder's evaluations of `tasks` (whichever families and seeds it holds), tokenizer metrics and replay."""
    point_dir = Path(point_dir)
    evaluations = referenced_runs(point_dir / EVAL_FOLDER, tasks)
    metrics = json.loads((point_dir / TOKENIZER_METRICS).read_text())
    return StudyPoint(evaluations, metrics, read_replay(point_dir))


def run_points(
    study: SettingStudy,
    layout_marker: Mapping[str, Any],
    eval_dir: Path,
    tokenizer_metrics: Path,
    output_dir: Path,
    run_experiment: Callable[[str, list[str]], None],
    tokenizer_dir: Path | None = None,
    replay: Callable[[Path], object] | None = None,
) -> list[Any]:
    """Run every point not yet complete as an experiment and copy what it produced; return the points run now.

    Args:
        study: the study.
        layout_marker: tasks, policies and seeds of the workspace (what every point trains and evaluates).
        eval_dir: the workspace's ``reports/eval``.
        tokenizer_metrics: the workspace's ``reports/tokenizer/metrics.json``.
        output_dir: the study's folder; one sub-folder per point.
        run_experiment: runs the pipeline as a named experiment with `-S` overrides and raises when it fails.
        tokenizer_dir: the workspace's tokenizer folder, copied into each point (see `harvest_point`).
        replay: called with each complete point's folder, this run's and earlier ones' (it measures what is missing:
            `carp.studies.point_replay.replay_point`).
    """
    ran = []
    for value in study.values:
        point_dir = Path(output_dir) / study.folder(value)
        if not is_complete(point_dir, layout_marker, value):
            run_experiment(f"{study.name}-{study.folder(value)}", study.overrides(value))
            harvest_point(eval_dir, tokenizer_metrics, point_dir, layout_marker, value, tokenizer_dir)
            ran.append(value)
        if replay is not None:
            replay(point_dir)
    return ran


def load_study(study: SettingStudy, folders: Sequence[Path], tasks: Sequence[str]) -> dict[Any, list[StudyPoint]]:
    """Each point's parts from the study folders (the workspace's own, then references); a point none has is absent."""
    points: dict[Any, list[StudyPoint]] = {}
    for value in study.values:
        for folder in folders:
            point_dir = Path(folder) / study.folder(value)
            if (point_dir / COMPLETE_MARKER).is_file():
                points.setdefault(value, []).append(load_point(point_dir, tasks))
    return points


def merged_evaluations(parts: Sequence[StudyPoint]) -> dict[str, dict[str, dict[int, Any]]]:
    """One point's evaluations from several folders; a family's training seed may come from one folder only."""
    merged: dict[str, dict[str, dict[int, Any]]] = {}
    for index, part in enumerate(parts):
        merged = merge_runs(merged, part.evaluations, f"study folder {index + 1} of the point")
    return merged


def study_sections(
    study: SettingStudy,
    points: Mapping[Any, Sequence[StudyPoint]],
    margin: float,
    alpha: float,
    figures_dir: Path,
    min_seeds: int = verdicts.DEFAULT_MIN_SEEDS,
) -> list[Section]:
    """Per task: success, tokenizer error, usage and latency against the setting, and each point against the reference.

    Every point's family is compared with the same family at the reference point on the episodes they share, all
    pairs of the study under one correction (`carp.reporting.comparison.decide_groups`).
    """
    values = [value for value in study.values if value in points]
    evaluations = {value: merged_evaluations(points[value]) for value in values}
    tokenizer = {value: points[value][0].tokenizer_metrics for value in values}
    replays = {value: next((part.replay for part in points[value] if part.replay), {}) for value in values}
    tasks = sorted({task for by_task in evaluations.values() for task in by_task})
    pairs, where = [], []
    if study.reference in evaluations:
        for value in values:
            if value == study.reference:
                continue
            for task in tasks:
                for family, runs in evaluations[value].get(task, {}).items():
                    reference_runs = evaluations[study.reference].get(task, {}).get(family)
                    if reference_runs:
                        pairs.append(
                            (task, f"{family} {study.label(value)}", runs, f"{family} {study.label(study.reference)}",
                             reference_runs)
                        )  # fmt: skip
                        where.append((value, task, family))
    decided = decide_groups([(tasks, pairs)], margin, alpha, min_seeds=min_seeds)[0] if pairs else {}
    verdict_of = {}
    counters = {task: 0 for task in tasks}
    for value, task, family in where:
        verdict_of[(value, task, family)] = decided[task][counters[task]]
        counters[task] += 1
    sections = []
    for task in tasks:
        rows = []
        for value in values:
            for family, runs in evaluations[value].get(task, {}).items():
                latency = _median_latency(runs)
                comparison = verdict_of.get((value, task, family))
                rows.append(
                    {
                        "point": study.label(value),
                        "policy": family,
                        **family_rate_cells(runs),
                        "tokenizer error (% of range)": _metric(tokenizer[value], "rmse_percent_range/mean", "{:.2f}"),
                        "code usage": _metric(tokenizer[value], "usage/all_scales/mean", "{:.0%}"),
                        "perplexity": _metric(tokenizer[value], "perplexity/mean", "{:.0f}"),
                        "demos replayed through the tokenizer": replay_cell(replays[value], task),
                        "latency per chunk (ms)": "-" if latency is None else f"{latency:.1f}",
                        f"against {study.label(study.reference)}": (
                            "reference" if value == study.reference else (comparison.verdict if comparison else "-")
                        ),
                    }
                )
        paragraphs = [
            f"Each point is one experiment with `{study.key}` set as named, everything else as the workspace's params; "
            "the family's rate is the mean over training seeds with its 95% t interval over seeds. Each point is "
            f"compared with the same family at {study.label(study.reference)} on the episodes they share, the "
            f"training seed as the unit (at least {min_seeds} seeds a side), all pairs of the study under one "
            "correction. The tokenizer's figures are on its held-out windows; code usage is the share of the V codes "
            "used over all scales; the replay column counts demos that still succeed when every executed chunk "
            "goes through the point's tokenizer open loop (nothing corrects an error once made).",
        ]
        paragraphs += [
            f"{comparison.verdict}: {comparison.explanation}"
            for (value, pair_task, _), comparison in verdict_of.items()
            if pair_task == task
        ]
        tables = [pd.DataFrame(rows)]
        if study.key == "scales":
            claims = scales_claims(verdict_of, task, study)
            if not claims.empty:
                tables.append(claims)
        sections.append(
            Section(
                f"{study.name.capitalize()} study on {task}",
                paragraphs=paragraphs,
                tables=tables,
                figures=[_plot(study, evaluations, tokenizer, task, figures_dir / f"{study.name}_{task}.png")],
            )
        )
    return sections


def scales_claims(
    verdict_of: Mapping[tuple[Any, str, str], "verdicts.PairComparison"], task: str, study: SettingStudy
) -> pd.DataFrame:
    """The paper's reading of Fig. 10, per family: fewer than 4 scales worse than 4, and 5 or 6 on par with 4.

    A claim holds when every point it names has that verdict against the reference, does not hold when one of them
    has the opposite verdict (better, or a real difference beyond the margin for "on par"), and is not decided
    otherwise. Only with the reference at K = 4.
    """
    if len(study.reference) != 4:
        return pd.DataFrame(columns=["policy", "claim", "verdict", "evidence"])
    rows = []
    families = sorted({family for (_, pair_task, family) in verdict_of if pair_task == task})
    for family in families:
        for claim, wanted, points in (
            ("fewer than 4 scales tokenize too coarsely (worse than 4)", "worse", lambda k: k < 4),
            ("5 and 6 scales add nothing (on par with 4)", "on par", lambda k: k > 4),
        ):
            found = [
                (value, comparison)
                for (value, pair_task, pair_family), comparison in verdict_of.items()
                if pair_task == task and pair_family == family and points(len(value))
            ]
            if not found:
                continue
            outcomes = [oriented_verdict(comparison, comparison.first, comparison.second) for _, comparison in found]
            if all(outcome == wanted for outcome in outcomes):
                verdict = "holds"
            elif any(outcome not in (wanted, "not decided") for outcome in outcomes):
                verdict = "does not hold"
            else:
                verdict = "not decided"
            evidence = "; ".join(f"{study.label(value)}: {comparison.verdict}" for value, comparison in found)
            rows.append({"policy": family, "claim": claim, "verdict": verdict, "evidence": evidence})
    return pd.DataFrame(rows, columns=["policy", "claim", "verdict", "evidence"])


def write_study_report(
    study: SettingStudy,
    points: Mapping[Any, Sequence[StudyPoint]],
    margin: float,
    alpha: float,
    output_dir: Path,
    min_seeds: int = verdicts.DEFAULT_MIN_SEEDS,
) -> Path:
    """``<output_dir>/report.md`` and ``report.html`` of the study; returns the Markdown path."""
    sections = study_sections(study, points, margin, alpha, Path(output_dir) / "figures", min_seeds)
    markdown, _ = write_sections(sections, output_dir, f"carp study: {study.name}")
    return markdown


def _plot(
    study: SettingStudy,
    evaluations: Mapping[Any, Evaluations],
    tokenizer: Mapping[Any, Mapping[str, float]],
    task: str,
    path: Path,
) -> Path:
    """Success (with its band over seeds) and the tokenizer's error against the setting, side by side."""
    figure, (success_axis, error_axis) = plt.subplots(1, 2, figsize=(9, 3.4))
    values = list(evaluations)
    families = sorted({family for by_task in evaluations.values() for family in by_task.get(task, {})})
    for family in families:
        xs, means, bands = [], [], []
        for value in values:
            runs = evaluations[value].get(task, {}).get(family)
            if not runs:
                continue
            xs.append(study.axis(value))
            means.append(100 * float(np.mean([o.mean() for o in outcomes_by_seed(runs).values()])))
            rate = family_rate(runs)
            if rate is not None:
                bands.append((study.axis(value), 100 * rate.low, 100 * rate.high))
        line = success_axis.plot(xs, means, marker="o", label=family)[0]
        if bands:
            band_x, lows, highs = zip(*bands)
            success_axis.fill_between(band_x, lows, highs, color=line.get_color(), alpha=0.2)
    errors = [(study.axis(v), tokenizer[v].get("rmse_percent_range/mean")) for v in values]
    errors = [(x, e) for x, e in errors if e is not None]
    if errors:
        error_axis.plot(*zip(*errors), marker="s", color="black")
    if study.key == "codebook_size":
        success_axis.set_xscale("log", base=2)
        error_axis.set_xscale("log", base=2)
    axis_name = "scales K" if study.key == "scales" else "codebook size V"
    success_axis.set(xlabel=axis_name, ylabel="success rate (%)", ylim=(0, 105), title=f"{study.name} ({task})")
    error_axis.set(xlabel=axis_name, ylabel="tokenizer error (% of range)", title="held-out reconstruction")
    figure.tight_layout()
    return finish_figure(figure, success_axis, path)


def _median_latency(runs: Runs) -> float | None:
    """Median over training seeds of the prediction plus decoding latency per chunk, ms; None without latencies."""
    totals = [
        run.metrics["latency_predict_ms_median"] + run.metrics.get("latency_decode_ms_median", 0.0)
        for run in runs.values()
        if "latency_predict_ms_median" in run.metrics
    ]
    return float(np.median(totals)) if totals else None


def _metric(metrics: Mapping[str, float], key: str, form: str) -> str:
    return form.format(metrics[key]) if key in metrics else "-"


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value
