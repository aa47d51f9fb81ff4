"""The data-efficiency study (CARP supplementary Fig. 5): success against the number of demos, per family.

Each size is one DVC experiment of the whole pipeline with ``data.subset_size`` set to it and ``data.num_demos`` set to
the largest size, so that collection runs once (DVC keeps its output) and every size ingests a nested subset of the
same file (`carp.data.subsets`), identical for every family. After each experiment its evaluation files (each
training seed's summary and test episodes) are copied into ``<output>/size<N>/``; a size whose copy is complete is
not run again, so an interrupted study resumes where it stopped. The study's report then shows each family's curve
with its band over training seeds and, per size, the paired verdicts of the families, all sizes under one correction.
"""

import json
import logging
import os
import shutil
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from carp.reporting import verdicts as verdicts_module  # noqa: E402
from carp.reporting.claims import find_pair, oriented_verdict
from carp.reporting.comparison import decide_groups, family_pairs, family_rate, family_rate_cells
from carp.reporting.document import Section, write_sections
from carp.reporting.figures import finish_figure  # noqa: E402
from carp.reporting.runs import RunResults, Runs, add_referenced_runs, outcomes_by_seed, referenced_runs

logger = logging.getLogger(__name__)

EXPERIMENT_PREFIX = "data-efficiency"
COMPLETE_MARKER = "complete.json"
CLAIM_FAMILY = "carp"
"""The family of the paper's data-efficiency claim: higher success than every baseline at every demo count."""

Evaluations = Mapping[str, Mapping[str, Runs]]
"""task -> family -> training seed -> results: what one size's experiment evaluated."""


@dataclass(frozen=True)
class StudyLayout:
    """What every experiment of the study trains and evaluates (the workspace's params at the study's start)."""

    tasks: tuple[str, ...]
    policies: tuple[str, ...]
    seeds: tuple[int, ...]


def experiment_overrides(size: int, sizes: Sequence[int]) -> list[str]:
    """The `dvc exp run -S` values of one size: the subset, and the largest size as the collected demos."""
    return [f"data.num_demos={max(sizes)}", f"data.subset_size={size}"]


def summary_path(eval_dir: Path, task: str, policy: str, seed: int) -> Path:
    """``<eval_dir>/<task>/<policy>/seed<seed>.json``, the evaluate stage's summary (its episodes beside it)."""
    return Path(eval_dir) / task / policy / f"seed{seed}.json"


def harvest(eval_dir: Path, point_dir: Path, layout: StudyLayout, size: int) -> None:
    """Copy the evaluation of every (task, family, seed) into `point_dir`, then mark it complete, atomically.

    Raises:
        FileNotFoundError: the experiment left an evaluation file missing.
    """
    staging = point_dir.with_name(f".{point_dir.name}.tmp")
    shutil.rmtree(staging, ignore_errors=True)
    for task in layout.tasks:
        for policy in layout.policies:
            for seed in layout.seeds:
                summary = summary_path(eval_dir, task, policy, seed)
                for source in (summary, summary.with_name(f"{summary.stem}_episodes.csv")):
                    if not source.exists():
                        raise FileNotFoundError(f"{source}: the experiment of size {size} left no evaluation here")
                    target = staging / source.relative_to(eval_dir)
                    target.parent.mkdir(parents=True, exist_ok=True)
                    shutil.copyfile(source, target)
    (staging / COMPLETE_MARKER).write_text(json.dumps({"size": size, **asdict(layout)}, indent=2) + "\n")
    shutil.rmtree(point_dir, ignore_errors=True)
    os.replace(staging, point_dir)


def is_complete(point_dir: Path, layout: StudyLayout, size: int) -> bool:
    """Whether `point_dir` holds a finished copy of this size's evaluation for this layout."""
    marker = Path(point_dir) / COMPLETE_MARKER
    if not marker.exists():
        return False
    recorded = json.loads(marker.read_text())
    expected = json.loads(json.dumps({"size": size, **asdict(layout)}))
    return recorded == expected


def load_point(point_dir: Path, layout: StudyLayout) -> dict[str, dict[str, dict[int, RunResults]]]:
    """One size's evaluations as the report's comparison reads them.

    Every family and training seed the folder holds for the layout's tasks, at least the layout's own (which
    `is_complete` checked), so a folder extended by hand with more seeds reports them all.
    """
    return referenced_runs(Path(point_dir), layout.tasks)


def run_study(
    sizes: Sequence[int],
    layout: StudyLayout,
    eval_dir: Path,
    output_dir: Path,
    run_experiment: Callable[[str, list[str]], None],
) -> dict[int, Evaluations]:
    """Run every size not yet complete as an experiment, copy its evaluation, and load them all.

    Args:
        sizes: the demo counts, increasing.
        layout: tasks, families and training seeds of the workspace.
        eval_dir: the workspace's ``reports/eval``.
        output_dir: the study's folder; ``size<N>/`` per size.
        run_experiment: runs the pipeline as a named experiment with `-S` overrides (e.g. ``dvc exp run``) and
            raises when it fails.

    Returns:
        size -> that size's evaluations.
    """
    points = {}
    for size in sizes:
        point_dir = Path(output_dir) / f"size{size}"
        if is_complete(point_dir, layout, size):
            logger.info("size %d: evaluated already (%s)", size, point_dir)
        else:
            run_experiment(f"{EXPERIMENT_PREFIX}-{size}", experiment_overrides(size, sizes))
            harvest(Path(eval_dir), point_dir, layout, size)
        points[size] = load_point(point_dir, layout)
    return points


def add_referenced_studies(
    points: Mapping[int, Evaluations], references: Mapping[str, Path], tasks: Sequence[str]
) -> tuple[dict[int, Evaluations], dict[str, str]]:
    """Every size's evaluations with the families of other runs of the study added (``study.references``).

    Args:
        points: size -> the study's own evaluations (:func:`run_study`).
        references: name (as the params give it) -> that study's folder, holding a finished ``size<N>/`` per size.
        tasks: the study's tasks; other tasks of a reference are left out.

    Returns:
        The merged points and, per task with referenced families, a sentence naming each and where it came from.

    Raises:
        FileNotFoundError: a reference lacks a finished copy of one of the sizes (or an episodes file).
        ValueError: a training seed of a family on a task is in the study and in a reference, or in two.
    """
    merged: dict[int, Evaluations] = {}
    notes: dict[str, str] = {}
    for size, evaluations in points.items():
        size_dirs = {}
        for name, folder in references.items():
            size_dir = Path(folder) / f"size{size}"
            if not (size_dir / COMPLETE_MARKER).is_file():
                raise FileNotFoundError(f"{size_dir}: no finished evaluation of {size} demos in {name}")
            size_dirs[name] = size_dir
        merged[size], size_notes = add_referenced_runs(evaluations, size_dirs, tasks, "study.references")
        for task, note in size_notes.items():
            notes.setdefault(task, note)
    return merged, notes


def plot_success_against_demos(points: Mapping[int, Evaluations], task: str, path: Path) -> Path:
    """Each family's mean success over seeds against the demo count, with its 95% band over training seeds.

    A size with a single training seed has its point but no band (one network says nothing about the spread).
    """
    figure, axis = plt.subplots(figsize=(6, 3.4))
    sizes = sorted(points)
    for family in points[sizes[0]][task]:
        means, bands = [], []
        for size in sizes:
            runs = points[size][task][family]
            means.append(100 * float(np.mean([values.mean() for values in outcomes_by_seed(runs).values()])))
            interval = family_rate(runs)
            if interval is not None:
                bands.append((size, 100 * interval.low, 100 * interval.high))
        line = axis.plot(sizes, means, marker="o", label=family)[0]
        if bands:
            band_sizes, lows, highs = zip(*bands)
            axis.fill_between(band_sizes, lows, highs, color=line.get_color(), alpha=0.2)
    axis.set_xlabel("demos")
    axis.set_ylabel("success rate (%)")
    axis.set_ylim(0, 105)
    axis.set_title(f"data efficiency ({task})")
    return finish_figure(figure, axis, path)


def claims_table(
    verdicts: Mapping[int, Mapping[str, Sequence["verdicts_module.PairComparison"]]], task: str
) -> pd.DataFrame:
    """The paper's data-efficiency claim on `task`, against each other family of the study: one row per rival.

    The claim ("CARP outperforms the baseline with any number of demos") holds against a rival when the family verdict
    is "carp better" at every size: an intersection-union test, for which each size's verdict at alpha suffices (the
    study's verdicts are corrected over every size and pair, which only makes it stricter). It does not hold when the
    rival is better, or on par within the margin, at some size, and is not decided otherwise (a size with too few
    training seeds for a family verdict among them). Without carp in the study the table is empty.

    Args:
        verdicts: size -> task -> the size's pair comparisons (`compare_families`).
        task: the task of the rows.

    Returns:
        Columns claim, verdict and evidence (per size: both success rates and the pair's verdict).
    """
    sizes = sorted(verdicts)
    rivals = sorted(
        {family for pair in verdicts[sizes[0]].get(task, []) for family in (pair.first, pair.second)} - {CLAIM_FAMILY}
    )
    rows = []
    for rival in rivals:
        outcomes, evidence = [], []
        for size in sizes:
            pair = find_pair(verdicts[size].get(task, []), CLAIM_FAMILY, rival)
            if pair is None:
                break
            outcome = oriented_verdict(pair, CLAIM_FAMILY, rival)
            ours, theirs = pair.first_rate, pair.second_rate
            if pair.first != CLAIM_FAMILY:
                ours, theirs = theirs, ours
            outcomes.append(outcome)
            evidence.append(f"{size} demos: {100 * ours:.1f}% against {100 * theirs:.1f}%, {pair.verdict}")
        if len(outcomes) < len(sizes):
            continue
        if all(outcome == "better" for outcome in outcomes):
            verdict = "holds"
        elif any(outcome in ("worse", "on par") for outcome in outcomes):
            verdict = "does not hold"
        else:
            verdict = "not decided"
        rows.append(
            {
                "claim": f"CARP's success is higher than {rival}'s at every number of demos",
                "verdict": verdict,
                "evidence": "; ".join(evidence),
            }
        )
    return pd.DataFrame(rows, columns=["claim", "verdict", "evidence"])


def study_sections(
    points: Mapping[int, Evaluations],
    margin: float,
    alpha: float,
    figures_dir: Path,
    reference_notes: Mapping[str, str] | None = None,
    min_seeds: int = verdicts_module.DEFAULT_MIN_SEEDS,
) -> list[Section]:
    """Per task: the curves, a table of each family's success per size, and per size the paired verdicts.

    `reference_notes` (task -> sentence, :func:`add_referenced_studies`) says which families came from elsewhere.
    """
    sizes = sorted(points)
    tasks = list(points[sizes[0]])
    decided = decide_groups(
        [(list(points[size]), family_pairs(points[size])) for size in sizes], margin, alpha, min_seeds=min_seeds
    )
    verdicts = dict(zip(sizes, decided))
    sections = []
    for task in tasks:
        rows = []
        for size in sizes:
            for family, runs in points[size][task].items():
                rows.append({"demos": size, "policy": family, **family_rate_cells(runs)})
        claims = claims_table(verdicts, task)
        section = Section(
            f"Data efficiency on {task}",
            paragraphs=[
                "Each size trains every family on the same nested subset of one collected file (a smaller subset is "
                "part of every larger one); the band is the 95% t interval over training seeds of the family's rate "
                "(sizes with one seed have none). Verdicts per size pair the families on the same episode seeds with "
                f"the training seed as the unit (at least {min_seeds} seeds per family), under one correction over "
                "every size and pair of the study.",
                *([reference_notes[task]] if reference_notes and task in reference_notes else []),
                *(
                    []
                    if claims.empty
                    else [
                        "The second table checks the paper's data-efficiency claim against each baseline: it holds "
                        "only where CARP is better at every size."
                    ]
                ),
            ],
            tables=[pd.DataFrame(rows), *([] if claims.empty else [claims])],
            figures=[plot_success_against_demos(points, task, figures_dir / f"data_efficiency_{task}.png")],
        )
        for size in sizes:
            section.paragraphs += [
                f"{size} demos, {pair.verdict}: {pair.explanation}" for pair in verdicts[size].get(task, [])
            ]
        sections.append(section)
    return sections


def write_study_report(
    points: Mapping[int, Evaluations],
    margin: float,
    alpha: float,
    output_dir: Path,
    reference_notes: Mapping[str, str] | None = None,
    min_seeds: int = verdicts_module.DEFAULT_MIN_SEEDS,
) -> Path:
    """``<output_dir>/report.md`` and ``report.html`` of the study; returns the Markdown path."""
    sections = study_sections(points, margin, alpha, Path(output_dir) / "figures", reference_notes, min_seeds)
    markdown, _ = write_sections(sections, output_dir, "carp study: data efficiency")
    return markdown
