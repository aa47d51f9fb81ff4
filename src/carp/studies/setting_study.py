"""Studies of one setting: scales K (supplementary Fig. 10), codebook size V, tokenizer kind, tokenizer source.

The tokenizer studies' points are made by `carp.studies.tokenizer_studies`.

A point of the study is one DVC experiment of the whole pipeline with the setting changed (``-S scales=[1,2,3]``,
``-S codebook_size=256``, ``-S tokenizer.kind=fsq``) and everything else as the workspace's params say, less the
families that cannot take the point's setting. After each experiment its evaluation files, its tokenizer's metrics
and the tokenizer itself are copied into ``<output>/<point>/``, and the demos are replayed open loop through that
tokenizer (`carp.studies.point_replay`); a point whose copy is complete is not run again, so an interrupted study
resumes, and folders of the same study run in other clones (``study.references``) join the report at every point.
The report shows, per task, each family's success against the setting with its band over training seeds, the
tokenizer's error and the figures the study varies (code usage and perplexity, or rate), its replay success and the
latency per chunk, and each point's verdict against the reference point, all points under one correction. The scales
study also checks the paper's reading of Fig. 10: fewer than 4 scales tokenize too coarsely, and 5 or 6 add nothing.
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
from carp.reporting.runs import Runs, merge_runs, outcomes_by_seed, pooled_metrics, referenced_runs
from carp.studies.data_efficiency import COMPLETE_MARKER, Evaluations  # noqa: E402
from carp.studies.point_replay import TOKENIZER_FOLDER, nominal_rate, read_replay, replay_cell

TOKENIZER_METRICS = "tokenizer_metrics.json"
EVAL_FOLDER = "eval"
USAGE_NOTE = "Code usage is the share of the V codes used over all scales."


@dataclass(frozen=True)
class SettingStudy:
    """One study: the param it varies, the values it tries and the value the others are compared with.

    Attributes:
        name: the study's name (``scales``, ``codebook``, ``tokenizers`` or ``tokenizer_reuse``), also its folder
            under ``reports/studies``.
        key: the param set by ``dvc exp run -S`` (``scales``, ``codebook_size``, ``tokenizer.kind`` or
            ``tokenizer.source``).
        values: the points, in the order of the report's axis.
        reference: the value every other point is compared with; one of `values`.
        point_families: value -> the families trained at that point, for points that train fewer than the
            workspace's ``policies`` (a family that cannot take the point's setting); other points train them all.
        point_overrides: value -> further ``-S`` overrides of that point (the narrowed ``policies`` and the lists
            that must stay inside it).
        shared_overrides: ``-S`` overrides every point adds (e.g. the tasks of the tokenizer reuse study).
        note: a paragraph the report adds to every task's section (what the columns of this study mean).
    """

    name: str
    key: str
    values: tuple[Any, ...]
    reference: Any
    point_families: tuple[tuple[Any, tuple[str, ...]], ...] = ()
    point_overrides: tuple[tuple[Any, tuple[str, ...]], ...] = ()
    shared_overrides: tuple[str, ...] = ()
    note: str = ""

    def __post_init__(self) -> None:
        if self.reference not in self.values:
            raise ValueError(f"study {self.name}: the reference {self.reference!r} is not one of its points")

    @property
    def categorical(self) -> bool:
        """Whether the points are categories (tokenizer kinds, tokenizer sources) rather than numbers."""
        return self.key in ("tokenizer.kind", "tokenizer.source")

    @property
    def axis_name(self) -> str:
        """The x axis's title in the report's figure."""
        return {"scales": "scales K", "codebook_size": "codebook size V", "tokenizer.kind": "tokenizer kind"}.get(
            self.key, "tokenizer"
        )

    def folder(self, value: Any) -> str:
        """The point's folder and experiment suffix: ``K3`` for scales [1, 2, 3], ``V256``, ``fsq``, ``own``."""
        if self.key == "scales":
            return f"K{len(value)}"
        if self.key == "tokenizer.kind":
            return str(value)
        if self.key == "tokenizer.source":
            return "own" if value == "pipeline" else "reused"
        return f"V{value}"

    def label(self, value: Any) -> str:
        """The point as the report names it, e.g. ``K=3 [1, 2, 3]``, ``V=256``, ``fsq`` or ``reused tokenizer``."""
        if self.key == "scales":
            return f"K={len(value)} {list(value)}"
        if self.key == "tokenizer.kind":
            return str(value)
        if self.key == "tokenizer.source":
            return f"{self.folder(value)} tokenizer"
        return f"V={value}"

    def axis(self, value: Any) -> float:
        """The point's position on the report's x axis: K, V, or the point's index for categories."""
        if self.categorical:
            return float(self.values.index(value))
        return float(len(value)) if self.key == "scales" else float(value)

    def overrides(self, value: Any) -> list[str]:
        """The `dvc exp run -S` values that make the point."""
        shown = "[" + ",".join(map(str, value)) + "]" if self.key == "scales" else str(value)
        return [f"{self.key}={shown}", *dict(self.point_overrides).get(value, ()), *self.shared_overrides]

    def families(self, value: Any, policies: Sequence[str]) -> list[str]:
        """The families trained at the point: `policies` (the workspace's) unless the point narrows them."""
        return list(dict(self.point_families).get(value, policies))

    def point_marker(self, value: Any, layout_marker: Mapping[str, Any]) -> dict[str, Any]:
        """The workspace's layout with the point's own families: what the point trains and evaluates."""
        return {**layout_marker, "policies": self.families(value, layout_marker["policies"])}


def scales_study(schedules: Sequence[Sequence[int]], reference: Sequence[int]) -> SettingStudy:
    """The scales study over `schedules`, against the workspace's `reference` schedule."""
    return SettingStudy("scales", "scales", tuple(tuple(s) for s in schedules), tuple(reference), note=USAGE_NOTE)


def codebook_study(sizes: Sequence[int], reference: int) -> SettingStudy:
    """The codebook study over `sizes`, against the workspace's `reference` size."""
    return SettingStudy("codebook", "codebook_size", tuple(sizes), reference, note=USAGE_NOTE)


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


def load_point(point_dir: Path, tasks: Sequence[str], rate: bool = False) -> StudyPoint:
    """A point folder's evaluations of `tasks` (whichever families and seeds it holds), tokenizer metrics and replay.

    With `rate`, a tokenizer whose metrics hold no rate (carp_msvq's) gets its nominal one from its copy.
    """
    point_dir = Path(point_dir)
    evaluations = referenced_runs(point_dir / EVAL_FOLDER, tasks)
    metrics = json.loads((point_dir / TOKENIZER_METRICS).read_text())
    if rate and "bits_per_chunk" not in metrics:
        metrics = {**nominal_rate(point_dir / TOKENIZER_FOLDER), **metrics}
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
        layout_marker: tasks, policies and seeds of the workspace (what every point trains and evaluates, less the
            families a point leaves out: `SettingStudy.point_marker`).
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
        marker = study.point_marker(value, layout_marker)
        if not is_complete(point_dir, marker, value):
            run_experiment(f"{study.name}-{study.folder(value)}", study.overrides(value))
            harvest_point(eval_dir, tokenizer_metrics, point_dir, marker, value, tokenizer_dir)
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
                points.setdefault(value, []).append(load_point(point_dir, tasks, study.key == "tokenizer.kind"))
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
                        **tokenizer_cells(study, tokenizer[value], task, runs),
                        "demos replayed through the tokenizer": replay_cell(replays[value], task),
                        "latency per chunk (ms)": "-" if latency is None else f"{latency:.1f}",
                        f"against {study.label(study.reference)}": (
                            "reference" if value == study.reference else (comparison.verdict if comparison else "-")
                        ),
                    }
                )
        paragraphs = [
            f"Each point is one experiment with `{study.key}` set as named, everything else as the workspace's params "
            "(a family that cannot take the point's setting is not trained there); the family's rate is the mean "
            "over training seeds with its 95% t interval over seeds. Each point is compared with the same family at "
            f"the reference point, {study.label(study.reference)}, on the episodes they share, the training seed as "
            f"the unit (at least {min_seeds} seeds a side), all pairs of the study under one correction. The "
            "tokenizer's figures are on its held-out windows (the error is the task's own where the tokenizer serves "
            "several tasks); the replay column counts demos that still succeed when every executed chunk goes "
            "through the point's tokenizer open loop (nothing corrects an error once made).",
            *([study.note] if study.note else []),
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
                f"{study.name.replace('_', ' ').capitalize()} study on {task}",
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
    style = "none" if study.categorical else "-"
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
        line = success_axis.plot(xs, means, marker="o", linestyle=style, label=family)[0]
        if bands:
            band_x, lows, highs = zip(*bands)
            if study.categorical:  # no line between categories: each point's band is its own bar
                success_axis.vlines(band_x, lows, highs, color=line.get_color(), alpha=0.4, linewidth=6)
            else:
                success_axis.fill_between(band_x, lows, highs, color=line.get_color(), alpha=0.2)
    errors = [
        (
            study.axis(v),
            tokenizer[v].get(f"task/{task}/rmse_percent_range/mean", tokenizer[v].get("rmse_percent_range/mean")),
        )
        for v in values
    ]
    errors = [(x, e) for x, e in errors if e is not None]
    if errors:
        error_axis.plot(*zip(*errors), marker="s", linestyle=style, color="black")
    if study.key == "codebook_size":
        success_axis.set_xscale("log", base=2)
        error_axis.set_xscale("log", base=2)
    if study.categorical:
        for axis in (success_axis, error_axis):
            axis.set_xticks([study.axis(v) for v in values], [study.label(v) for v in values], rotation=30)
    axis_name = study.axis_name
    success_axis.set(xlabel=axis_name, ylabel="success rate (%)", ylim=(0, 105), title=f"{study.name} ({task})")
    error_axis.set(xlabel=axis_name, ylabel="tokenizer error (% of range)", title="held-out reconstruction")
    figure.tight_layout()
    return finish_figure(figure, success_axis, path)


def tokenizer_cells(study: SettingStudy, metrics: Mapping[str, float], task: str, runs: Runs) -> dict[str, str]:
    """The point's tokenizer columns: its error on `task`, then the figures the study varies (usage, or rate)."""
    own_error = f"task/{task}/rmse_percent_range/mean"
    cells = {
        "tokenizer error (% of range)": _metric(
            metrics, own_error if own_error in metrics else "rmse_percent_range/mean", "{:.2f}"
        )
    }
    if study.key in ("scales", "codebook_size"):
        cells["code usage"] = _metric(metrics, "usage/all_scales/mean", "{:.0%}")
        cells["perplexity"] = _metric(metrics, "perplexity/mean", "{:.0f}")
    elif study.key == "tokenizer.kind":
        cells["bits per chunk"] = _metric(metrics, "bits_per_chunk", "{:.0f}")
        cells["tokens per chunk"] = _metric(metrics, "tokens_per_chunk/mean", "{:.1f}")
        cells["entropy (bits per chunk)"] = _metric(metrics, "entropy_bits_per_chunk", "{:.0f}")
        pooled = pooled_metrics(runs)
        rate = pooled.get("repaired_chunk_rate")
        cells["repaired chunks"] = "-" if rate is None else f"{100 * rate:.1f}%"
        # The network's size beside its rate: next_token.match_size keeps it near carp_msvq's at every kind.
        parameters = pooled.get("num_parameters")
        cells["parameters"] = "-" if parameters is None else f"{int(parameters):,}"
    return cells


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
