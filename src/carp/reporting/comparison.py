"""The report's comparison of policy families: per-seed results, family figures, paired verdicts, the paper's claims.

Every number comes from `carp.reporting.statistics` (episode-level figures of single networks),
`carp.reporting.seed_inference` (family-level figures over training seeds) and `carp.reporting.verdicts`; this module
only arranges the evaluations (task -> family -> training seed -> summary and test episodes) into what those functions
take and into tables and figures. Episodes pair across families by their episode seed (the same initial state), and
training seeds pair by number.
"""

import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from itertools import combinations
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from scipy import stats  # noqa: E402

from carp.reporting import statistics, verdicts  # noqa: E402
from carp.reporting.figures import finish_figure  # noqa: E402
from carp.reporting.seed_inference import seed_level_estimate  # noqa: E402


@dataclass(frozen=True)
class RunResults:
    """One training seed's evaluation of one family on one task.

    Attributes:
        metrics: the evaluation summary (``reports/eval/<task>/<family>/seed<seed>.json``).
        episodes: the test episodes (``seed<seed>_episodes.csv``): at least ``seed``, ``success`` and ``steps``.
    """

    metrics: Mapping[str, Any]
    episodes: pd.DataFrame


Runs = Mapping[int, RunResults]
"""Training seed -> that seed's results, for one family on one task."""

PAPER_CLAIMS = (
    ("CARP's success is on par with DP-C", "carp", "diffusion_unet", "on par"),
    ("CARP's success is better than next-token's", "carp", "next_token", "better"),
)
"""(claim, family, rival, what the paper says of the pair) for the success claims a run can check."""

PRECISION_CLAIMS = (
    ("CARP's insertion precision is comparable to DP-C's", "carp", "diffusion_unet", "insertion_offset_mm"),
)
"""(claim, family, rival, per-episode measure) for the precision claims (CARP's Tables 4-5): lower is more precise."""

EPISODE_RECORD_COLUMNS = frozenset({"seed", "success", "steps", "seconds", "chunks", "chunk_ms_median", "error"})
"""Columns every episodes table has; any other numeric column is a task's own per-episode measure."""

SPEED_CLAIMS = (
    ("CARP is about 10x faster per chunk than DP-C", "carp", "diffusion_unet"),
    ("CARP is faster per chunk than DP-T", "carp", "diffusion_transformer"),
)
"""(claim, family, slower rival) for the inference-speed claims: the rival's latency over the family's."""


def outcomes_by_seed(runs: Runs, episode_seeds: Sequence[int] | None = None) -> dict[int, np.ndarray]:
    """Training seed -> (N,) bool test successes ordered by episode seed, restricted to `episode_seeds` if given."""
    return _episode_column(runs, "success", bool, episode_seeds)


def steps_by_seed(runs: Runs, episode_seeds: Sequence[int] | None = None) -> dict[int, np.ndarray]:
    """Training seed -> (N,) int steps of each test episode, in the order of `outcomes_by_seed`."""
    return _episode_column(runs, "steps", np.int64, episode_seeds)


def _episode_column(runs: Runs, column: str, dtype, episode_seeds: Sequence[int] | None) -> dict[int, np.ndarray]:
    """Training seed -> one column of its test episodes, ordered by episode seed (optionally only `episode_seeds`)."""
    values = {}
    for seed, run in sorted(runs.items()):
        episodes = run.episodes.sort_values("seed")
        if episode_seeds is not None:
            episodes = episodes[episodes["seed"].isin(episode_seeds)]
        values[seed] = episodes[column].to_numpy(dtype=dtype)
    return values


EVALUATION_SUMMARY_PATTERN = re.compile(r"seed(\d+)\.json")
"""File name of one training seed's evaluation summary in an evaluation directory (``seed<k>.json``)."""


def read_run_results(summary: Path) -> RunResults:
    """One evaluation summary (``seed<k>.json``) and the test episodes beside it (``seed<k>_episodes.csv``)."""
    summary = Path(summary)
    return RunResults(json.loads(summary.read_text()), pd.read_csv(summary.with_name(f"{summary.stem}_episodes.csv")))


def referenced_runs(eval_dir: Path, tasks: Sequence[str]) -> dict[str, dict[str, dict[int, RunResults]]]:
    """Every evaluation of `tasks` in another run's evaluation directory: task -> label -> training seed -> results.

    Args:
        eval_dir: that run's ``reports/eval`` (``<task>/<label>/seed<k>.json`` with its episodes beside it; a label
            is a family, or ``<family>-multitask`` for a multi-task policy).
        tasks: the tasks to read; a task the directory lacks gives nothing.

    Raises:
        FileNotFoundError: `eval_dir` is not a directory, or a summary has no episodes file beside it.
    """
    eval_dir = Path(eval_dir)
    if not eval_dir.is_dir():
        raise FileNotFoundError(f"{eval_dir}: no such evaluation directory")
    found: dict[str, dict[str, dict[int, RunResults]]] = {}
    for task in tasks:
        task_dir = eval_dir / task
        for label_dir in sorted(path for path in task_dir.iterdir() if path.is_dir()) if task_dir.is_dir() else ():
            for summary in sorted(label_dir.iterdir()):
                matched = EVALUATION_SUMMARY_PATTERN.fullmatch(summary.name)
                if matched is None:
                    continue
                if not summary.with_name(f"{summary.stem}_episodes.csv").is_file():
                    raise FileNotFoundError(f"{summary}: no {summary.stem}_episodes.csv beside it")
                runs = found.setdefault(task, {}).setdefault(label_dir.name, {})
                runs[int(matched.group(1))] = read_run_results(summary)
    return found


def merge_runs(
    own: Mapping[str, Mapping[str, Runs]], referenced: Mapping[str, Mapping[str, Runs]], source: str
) -> dict[str, dict[str, dict[int, RunResults]]]:
    """Both runs' evaluations (task -> label -> training seed -> results), the training seeds of a label added up.

    Raises:
        ValueError: both have the same training seed of a label on a task; the message names `source`, the task,
            the label and the seed.
    """
    merged = {task: {label: dict(runs) for label, runs in labels.items()} for task, labels in own.items()}
    for task, labels in referenced.items():
        for label, runs in labels.items():
            mine = merged.setdefault(task, {}).setdefault(label, {})
            for seed, run in runs.items():
                if seed in mine:
                    raise ValueError(f"{source}: {task}/{label} training seed {seed} is already in the report")
                mine[seed] = run
    return merged


def add_referenced_runs(
    own: Mapping[str, Mapping[str, Runs]],
    references: Mapping[str, Path],
    tasks: Sequence[str],
    params_key: str = "comparison.references",
) -> tuple[dict[str, dict[str, dict[int, RunResults]]], dict[str, str]]:
    """The run's evaluations with those of other runs added (`comparison.references`), and what came from where.

    Args:
        own: the run's own evaluations, task -> label -> training seed -> results.
        references: name (as the params give it) -> that run's evaluation directory (:func:`referenced_runs`).
        tasks: the run's tasks; other tasks of a reference are left out.
        params_key: the param that names the references, for the sentences.

    Returns:
        The merged evaluations (:func:`merge_runs`) and, per task with referenced evaluations, a sentence naming
        each referenced label, its training seeds and where they came from.

    Raises:
        FileNotFoundError, ValueError: from :func:`referenced_runs` and :func:`merge_runs`.
    """
    merged = {task: dict(labels) for task, labels in own.items()}
    sources: dict[str, list[str]] = {}
    for name, eval_dir in references.items():
        referenced = referenced_runs(eval_dir, tasks)
        merged = merge_runs(merged, referenced, name)
        for task, labels in referenced.items():
            sources.setdefault(task, []).extend(
                f"{label} (training seeds {', '.join(map(str, sorted(runs)))}) from {name}"
                for label, runs in labels.items()
            )
    notes = {task: f"Evaluations of other runs ({params_key}): {'; '.join(found)}." for task, found in sources.items()}
    return merged, notes


def split_multitask(
    runs: Mapping[str, Mapping[str, Runs]], suffix: str
) -> tuple[dict[str, dict[str, Runs]], dict[str, dict[str, Runs]]]:
    """Single-task and multi-task evaluations apart: labels ending in `suffix` are a family's multi-task policy.

    Returns:
        task -> family -> runs of the single-task policies, and task -> family -> runs of the multi-task ones (the
        family named without `suffix`; a task without any is left out).
    """
    single = {
        task: {label: seeds for label, seeds in labels.items() if not label.endswith(suffix)}
        for task, labels in runs.items()
    }
    multi = {
        task: {label.removesuffix(suffix): seeds for label, seeds in labels.items() if label.endswith(suffix)}
        for task, labels in runs.items()
    }
    return single, {task: families for task, families in multi.items() if families}


def pooled_metrics(runs: Runs) -> dict[str, Any]:
    """One family's metrics over its training seeds, in the keys of a single evaluation summary.

    Successes and episodes add up; the mean episode length is over every episode; latencies and the policy's facts
    are the median over seeds (the same network at every seed). ``seeds`` counts the training seeds.
    """
    summaries = [run.metrics for _, run in sorted(runs.items())]
    pooled: dict[str, Any] = dict(summaries[0])
    episodes = sum(int(summary["episodes"]) for summary in summaries)
    successes = sum(int(summary["successes"]) for summary in summaries)
    low, high = statistics.wilson_interval(successes, episodes)
    pooled.update(
        episodes=episodes,
        successes=successes,
        success_rate=successes / episodes,
        success_rate_ci_low=low,
        success_rate_ci_high=high,
        crashed_episodes=sum(int(summary.get("crashed_episodes", 0)) for summary in summaries),
        mean_episode_steps=float(np.mean(np.concatenate([run.episodes["steps"].to_numpy() for run in runs.values()]))),
        seeds=len(summaries),
    )
    for key in summaries[0]:
        if "latency" in key and key.endswith(("_median", "_p90")):
            pooled[key] = float(np.median([summary[key] for summary in summaries if key in summary]))
    return pooled


def seed_table(task_runs: Mapping[str, Runs]) -> pd.DataFrame:
    """One row per (family, training seed): the selected checkpoint and its confirmed test success.

    With validation episodes the Diffusion-Policy-style validation figures stand next to it, with the gap between them.
    """
    rows = []
    for family, runs in task_runs.items():
        for seed, run in sorted(runs.items()):
            metrics = run.metrics
            successes, episodes = int(metrics["successes"]), int(metrics["episodes"])
            low, high = statistics.wilson_interval(successes, episodes)
            validation = "validation_max_success_rate" in metrics
            candidates = metrics.get("candidates", 1)
            checkpoint = f"epoch {metrics.get('selected_epoch', '-')} of {candidates} candidates"
            if "averaged_checkpoints" in metrics:
                checkpoint = (
                    f"mean of the last {int(metrics['averaged_checkpoints'])} of {candidates} candidates "
                    f"(to epoch {metrics['selected_epoch']})"
                )
            rows.append(
                {
                    "policy": family,
                    "seed": seed,
                    "checkpoint": checkpoint,
                    "test success": f"{successes}/{episodes}",
                    "test rate": f"{100 * successes / episodes:.1f}% ({100 * low:.1f}-{100 * high:.1f}%)",
                    "validation max": _percent(metrics.get("validation_max_success_rate")) if validation else "-",
                    "validation top-k mean": (
                        f"{_percent(metrics['validation_top_k_mean_success_rate'])} "
                        f"(k={int(metrics['validation_top_k'])})"
                        if validation
                        else "-"
                    ),
                    "max - test": (
                        f"{100 * metrics['validation_max_test_gap']:+.1f} points"
                        if "validation_max_test_gap" in metrics
                        else "-"
                    ),
                }
            )
    return pd.DataFrame(rows)


def family_rate(runs: Runs, level: float = 0.95) -> "statistics.Interval | None":
    """A family's success rate over its training seeds with its t interval (`seed_level_estimate`); None below 2 seeds.

    The seeds ran the same initial states (the episodes shared by all of them are used), so the interval carries the
    states' shared difficulty as well as the spread between seeds.
    """
    outcomes = list(outcomes_by_seed(runs, _shared_episode_seeds(runs, {})).values())
    if len(outcomes) < 2 or not outcomes[0].size:
        return None
    return seed_level_estimate([values.astype(float) for values in outcomes], shared_states=True).interval(level)


def family_rate_cells(runs: Runs, level: float = 0.95) -> dict[str, int | str]:
    """Table cells of one family: its training seeds, each seed's rate and the family rate with its interval."""
    rate = family_rate(runs, level)
    seed_rates = [values.mean() for values in outcomes_by_seed(runs).values()]
    return {
        "seeds": len(runs),
        "per seed": ", ".join(f"{100 * seed_rate:.1f}%" for seed_rate in seed_rates),
        f"family rate, {level:.0%} interval over seeds": (
            f"{100 * rate.estimate:.1f}% ({100 * rate.low:.1f}-{100 * rate.high:.1f}%)"
            if rate is not None
            else f"{100 * seed_rates[0]:.1f}% (n/a, 1 training seed)"
        ),
    }


def family_table(task_runs: Mapping[str, Runs], level: float = 0.95) -> pd.DataFrame:
    """One row per family: its rate over training seeds with the family interval, and the networks' own figures.

    The family's rate is the mean over training seeds with a t interval over seeds (n/a with one seed: one network
    says nothing about the spread of its recipe). The pooled rate with its Wilson interval, the between-seed
    intra-class correlation and the effective episodes describe the trained networks, not the family.
    """
    rows = []
    for family, runs in task_runs.items():
        outcomes = list(outcomes_by_seed(runs).values())
        successes = [int(values.sum()) for values in outcomes]
        trials = [len(values) for values in outcomes]
        total = sum(trials)
        low, high = statistics.wilson_interval(sum(successes), total)
        rate = family_rate(runs, level)
        icc = statistics.intraclass_correlation(successes, trials)
        effective = statistics.effective_episodes(total, total / len(trials), icc)
        rows.append(
            {
                "policy": family,
                "seeds": len(trials),
                "episodes": total,
                f"family rate, {level:.0%} interval over seeds": (
                    f"{100 * rate.estimate:.1f}% ({100 * rate.low:.1f}-{100 * rate.high:.1f}%)"
                    if rate is not None
                    else f"{100 * np.mean([s / n for s, n in zip(successes, trials)]):.1f}% (n/a, 1 training seed)"
                ),
                "per seed": ", ".join(f"{100 * s / n:.0f}%" for s, n in zip(successes, trials)),
                "networks pooled (Wilson)": f"{100 * sum(successes) / total:.1f}% ({100 * low:.1f}-{100 * high:.1f}%)",
                "between-seed ICC": f"{icc:.3f}",
                "effective episodes": f"{effective:.0f}",
            }
        )
    return pd.DataFrame(rows)


def measure_columns(task_runs: Mapping[str, Runs]) -> list[str]:
    """The task's per-episode measures (e.g. Square's ``insertion_offset_mm``) found in its episodes tables."""
    columns: list[str] = []
    for runs in task_runs.values():
        for run in runs.values():
            for column in run.episodes.columns:
                numeric = pd.api.types.is_numeric_dtype(run.episodes[column])
                if column not in EPISODE_RECORD_COLUMNS and numeric and column not in columns:
                    columns.append(column)
    return columns


def pooled_measure(runs: Runs, column: str) -> np.ndarray:
    """One family's values of a per-episode measure over all its seeds' test episodes (NaN where not measured)."""
    frames = [run.episodes[column] for run in runs.values() if column in run.episodes]
    return np.concatenate([frame.to_numpy(dtype=float) for frame in frames]) if frames else np.array([])


def measure_table(task_runs: Mapping[str, Runs]) -> pd.DataFrame:
    """Per family and task measure: episodes measured, mean with its t interval, variance (as CARP's Tables 4-5)."""
    rows = []
    for column in measure_columns(task_runs):
        for family, runs in task_runs.items():
            values = pooled_measure(runs, column)
            values = values[np.isfinite(values)]
            if values.size == 0:
                rows.append({"measure": column, "policy": family, "episodes measured": 0})
                continue
            half = (
                float(stats.t.ppf(0.975, values.size - 1) * values.std(ddof=1) / np.sqrt(values.size))
                if values.size > 1
                else float("nan")
            )
            rows.append(
                {
                    "measure": column,
                    "policy": family,
                    "episodes measured": int(values.size),
                    "mean": f"{values.mean():.2f} (+-{half:.2f})",
                    "variance": f"{values.var(ddof=1):.2f}" if values.size > 1 else "-",
                }
            )
    return pd.DataFrame(rows)


def family_pairs(evaluations: Mapping[str, Mapping[str, Runs]]) -> list[tuple[str, str, Runs, str, Runs]]:
    """Every pair of families on every task: (task, first, its runs, second, its runs)."""
    return [
        (task, first, task_runs[first], second, task_runs[second])
        for task, task_runs in evaluations.items()
        for first, second in combinations(task_runs, 2)
    ]


def multitask_pairs(
    single_task: Mapping[str, Mapping[str, Runs]], multitask: Mapping[str, Mapping[str, Runs]], suffix: str
) -> list[tuple[str, str, Runs, str, Runs]]:
    """Each multi-task policy against its family's single-task policy, then every pair of multi-task policies.

    On every task: a family's multi-task policy against its single-task policy where the task has one, multi-task
    first, then every pair of multi-task policies of different families (the comparison of the paper's Table 4), in
    the order of `multitask`'s families; each named by its family and `suffix`.
    """
    against_single = [
        (task, family + suffix, runs, family, single_task[task][family])
        for task, families in multitask.items()
        for family, runs in families.items()
        if family in single_task.get(task, {})
    ]
    between_families = [
        (task, first + suffix, families[first], second + suffix, families[second])
        for task, families in multitask.items()
        for first, second in combinations(families, 2)
    ]
    return against_single + between_families


def decide_groups(
    groups: Sequence[tuple[Sequence[str], Sequence[tuple[str, str, Runs, str, Runs]]]],
    margin: float,
    alpha: float,
    level: float = 0.95,
    min_seeds: int = verdicts.DEFAULT_MIN_SEEDS,
) -> list[dict[str, list["verdicts.PairComparison"]]]:
    """Compare several groups of pairs with one correction over all of them (`decide_report` without other tests).

    Args:
        groups: (tasks, pairs) per group, e.g. the single-task families and the multi-task policies of one report, or
            each size of a study; pairs as `family_pairs` gives them.
        margin: equivalence margin of the verdicts, in success rate.
        alpha: family-wise significance level over every verdict of every group.
        level: confidence level of the intervals.
        min_seeds: training seeds per family a family verdict needs.

    Returns:
        Per group, task -> its pairs' comparisons with verdicts, in the order of the pairs.
    """
    return decide_report(groups, (), margin, alpha, level, min_seeds)[0]


def decide_report(
    groups: Sequence[tuple[Sequence[str], Sequence[tuple[str, str, Runs, str, Runs]]]],
    tests: Sequence["PrecisionTest"],
    margin: float,
    alpha: float,
    level: float = 0.95,
    min_seeds: int = verdicts.DEFAULT_MIN_SEEDS,
) -> tuple[list[dict[str, list["verdicts.PairComparison"]]], list["PrecisionTest"]]:
    """Every verdict a report states under one correction: the groups' success pairs and the precision tests.

    Args:
        groups: as for `decide_groups`.
        tests: the report's precision tests (`precision_tests`); those without a p-value (too few seeds) stay out of
            the correction.
        margin: equivalence margin of the verdicts, in success rate.
        alpha: family-wise significance level over every pair's verdict and every test.
        level: confidence level of the intervals.
        min_seeds: training seeds per family a family verdict needs.

    Returns:
        Per group, task -> its decided pairs; and the tests with their adjusted p-values, in their input order.
    """
    compared = [[(pair[0], _compare(pair, margin, alpha, level, min_seeds)) for pair in pairs] for _, pairs in groups]
    decidable = [test for test in tests if test.p_value is not None]
    decided_pairs, adjusted = verdicts.decide_pairs_and_tests(
        [pair for group in compared for _, pair in group],
        [test.p_value for test in decidable if test.p_value is not None],
        margin=margin,
        alpha=alpha,
    )
    decided = iter(decided_pairs)
    results = []
    for (tasks, _), group in zip(groups, compared):
        by_task: dict[str, list[verdicts.PairComparison]] = {task: [] for task in tasks}
        for task, _ in group:
            by_task.setdefault(task, []).append(next(decided))
        results.append(by_task)
    adjusted_by_test = {id(test): value for test, value in zip(decidable, adjusted)}
    corrected = [replace(test, adjusted_p_value=adjusted_by_test.get(id(test))) for test in tests]
    return results, corrected


def compare_families(
    evaluations: Mapping[str, Mapping[str, Runs]],
    margin: float,
    alpha: float,
    level: float = 0.95,
    min_seeds: int = verdicts.DEFAULT_MIN_SEEDS,
) -> dict[str, list["verdicts.PairComparison"]]:
    """Every pair of families on every task, compared on the episodes they share, corrected over all the pairs.

    Returns:
        task -> its pairs' comparisons, verdicts decided (`verdicts.decide_pairs`).
    """
    return decide_groups([(list(evaluations), family_pairs(evaluations))], margin, alpha, level, min_seeds)[0]


def compare_multitask(
    single_task: Mapping[str, Mapping[str, Runs]],
    multitask: Mapping[str, Mapping[str, Runs]],
    suffix: str,
    margin: float,
    alpha: float,
    level: float = 0.95,
    min_seeds: int = verdicts.DEFAULT_MIN_SEEDS,
) -> dict[str, list["verdicts.PairComparison"]]:
    """The multi-task pairs (`multitask_pairs`) alone, compared like `compare_families` and corrected over them."""
    pairs = multitask_pairs(single_task, multitask, suffix)
    return decide_groups([(list(multitask), pairs)], margin, alpha, level, min_seeds)[0]


def _compare(
    pair: tuple[str, str, Runs, str, Runs], margin: float, alpha: float, level: float, min_seeds: int
) -> "verdicts.PairComparison":
    """One (task, first, its runs, second, its runs) compared on the episode seeds every run of both shares."""
    _, first, first_runs, second, second_runs = pair
    shared = _shared_episode_seeds(first_runs, second_runs)
    return verdicts.compare_pair(
        first,
        outcomes_by_seed(first_runs, shared),
        second,
        outcomes_by_seed(second_runs, shared),
        first_steps_by_seed=steps_by_seed(first_runs, shared),
        second_steps_by_seed=steps_by_seed(second_runs, shared),
        min_seeds=min_seeds,
        margin=margin,
        alpha=alpha,
        level=level,
    )


def _shared_episode_seeds(first: Runs, second: Runs) -> list[int]:
    seeds = [set(run.episodes["seed"]) for run in (*first.values(), *second.values())]
    return sorted(set.intersection(*seeds))


def plot_steps_to_success(task_runs: Mapping[str, Runs], max_steps: int, path: Path, title: str) -> Path:
    """Kaplan-Meier curves: the share of episodes succeeded by each control step, per family (seeds pooled).

    A failure is censored at its last step, so two families with the same final success can still differ in how
    fast they get there.
    """
    figure, axis = plt.subplots(figsize=(6, 3.4))
    for family, runs in task_runs.items():
        steps = np.concatenate(list(steps_by_seed(runs).values()))
        success = np.concatenate(list(outcomes_by_seed(runs).values()))
        curve = statistics.kaplan_meier(steps, success, max_steps)
        axis.step(
            np.concatenate([[0], curve.steps]), 100 * np.concatenate([[0], curve.success_share]), where="post",
            label=family,
        )  # fmt: skip
    axis.set_xlim(0, max_steps)
    axis.set_ylim(0, 105)
    axis.set_xlabel("control step")
    axis.set_ylabel("episodes succeeded (%)")
    axis.set_title(title)
    return finish_figure(figure, axis, path)


def latency_ratio(slower: Runs, faster: Runs, level: float = 0.95, resamples: int = 4000, seed: int = 0):
    """How many times longer a chunk takes `slower` than `faster`, with a percentile bootstrap interval.

    The ratio of the median per-episode chunk latencies, resampled over episodes; None when an episode table lacks
    latencies.
    """
    samples = []
    for runs in (slower, faster):
        frames = [run.episodes for run in runs.values()]
        if not all("chunk_ms_median" in frame for frame in frames):
            return None
        values = np.concatenate([frame["chunk_ms_median"].to_numpy(dtype=float) for frame in frames])
        samples.append(values[np.isfinite(values)])
    if not all(len(values) for values in samples):
        return None
    generator = np.random.default_rng(seed)
    medians = [
        np.median(values[generator.integers(0, len(values), size=(resamples, len(values)))], axis=1)
        for values in samples
    ]
    ratios = medians[0] / medians[1]
    tail = 100 * (1 - level) / 2
    return statistics.Interval(
        float(np.median(samples[0]) / np.median(samples[1])),
        float(np.percentile(ratios, tail)),
        float(np.percentile(ratios, 100 - tail)),
    )


@dataclass(frozen=True)
class PrecisionTest:
    """One precision claim on one task: Welch's test of two families' per-seed mean measures (lower is more precise).

    Attributes:
        task, claim, family, rival, column: the claim (`PRECISION_CLAIMS`) and the task it is tested on.
        seed_means: (n_family,), (n_rival,) each training seed's mean of the measure over its measured episodes.
        networks: the pooled episode figures, stated as the networks' (they do not decide the claim).
        min_seeds: training seeds per family the test needs.
        p_value: Welch's p over training seeds; None with fewer than `min_seeds` seeds in either family.
        difference: family's mean minus rival's, over seeds (NaN without a p-value).
        interval: its 95% Welch interval, uncorrected (NaN without a p-value).
        adjusted_p_value: p after the report's correction (`decide_report`); None until then.
    """

    task: str
    claim: str
    family: str
    rival: str
    column: str
    seed_means: tuple[np.ndarray, np.ndarray]
    networks: str
    min_seeds: int
    p_value: float | None
    difference: float
    interval: tuple[float, float]
    adjusted_p_value: float | None = None


def precision_tests(
    evaluations: Mapping[str, Mapping[str, Runs]], min_seeds: int = verdicts.DEFAULT_MIN_SEEDS
) -> list[PrecisionTest]:
    """The precision claims a run can test, per task: families it trained with a measure its task takes."""
    tests = []
    for task, task_runs in evaluations.items():
        for claim, family, rival, column in PRECISION_CLAIMS:
            if family not in task_runs or rival not in task_runs or column not in measure_columns(task_runs):
                continue
            pooled = [pooled_measure(task_runs[name], column) for name in (family, rival)]
            pooled = [values[np.isfinite(values)] for values in pooled]
            if not all(values.size for values in pooled):
                continue
            networks = (
                f"{column} over the networks' measured episodes: {family} mean {pooled[0].mean():.2f} "
                f"({pooled[0].size} episodes), {rival} mean {pooled[1].mean():.2f} ({pooled[1].size} episodes)"
            )
            seed_means = (_seed_means(task_runs[family], column), _seed_means(task_runs[rival], column))
            p_value, difference, interval = None, float("nan"), (float("nan"), float("nan"))
            if min(means.size for means in seed_means) >= min_seeds:
                result = stats.ttest_ind(seed_means[0], seed_means[1], equal_var=False)
                low, high = result.confidence_interval(0.95)
                p_value = float(result.pvalue)
                difference = float(seed_means[0].mean() - seed_means[1].mean())
                interval = (float(low), float(high))
            tests.append(
                PrecisionTest(
                    task, claim, family, rival, column, seed_means, networks, min_seeds, p_value, difference, interval
                )
            )
    return tests


def claims_table(
    evaluations: Mapping[str, Mapping[str, Runs]],
    comparisons: Mapping[str, Sequence["verdicts.PairComparison"]],
    precision: Sequence[PrecisionTest] = (),
    alpha: float = 0.05,
    suffix: str = "",
) -> pd.DataFrame:
    """The paper's claims that this run can check, per task: the verdict and the numbers behind it.

    A success claim holds when the pair's family verdict says what the paper says ("on par" also holds when CARP comes
    out better), and is "not decided (n training seeds)" when the pair has too few seeds for a family verdict; a speed
    claim states the latency ratio with its interval and holds when the interval lies above 1; a precision claim
    holds when CARP's per-seed mean offset is lower and its test's p, corrected with the report's verdicts, is below
    `alpha`. Claims about families the run did not train, or measures its task lacks, are left out.

    Args:
        evaluations: task -> family -> runs.
        comparisons: task -> the pairs compared, each policy named by its family and `suffix`.
        precision: the precision tests of these evaluations, corrected (`decide_report`).
        alpha: family-wise significance level the verdicts were corrected at.
        suffix: appended to a family's name in `comparisons` (`carp.outputs.MULTITASK_SUFFIX` for the multi-task
            policies' claims).
    """
    rows = []
    for task, task_runs in evaluations.items():
        pairs = comparisons.get(task, ())
        rows += [{"task": task, **row} for row in _success_claims(pairs, suffix)]
        rows += [{"task": task, **_precision_claim(test, alpha)} for test in precision if test.task == task]
        rows += [{"task": task, **row} for row in _speed_claims(task_runs)]
    return pd.DataFrame(rows, columns=["task", "claim", "verdict", "evidence"])


def _success_claims(pairs: Sequence["verdicts.PairComparison"], suffix: str) -> list[dict[str, str]]:
    rows = []
    for claim, family, rival, paper in PAPER_CLAIMS:
        comparison = find_pair(pairs, family + suffix, rival + suffix)
        if comparison is None:
            continue
        verdict = oriented_verdict(comparison, family + suffix, rival + suffix)
        holds = verdict in ("on par", "better") if paper == "on par" else verdict == "better"
        status = "holds" if holds else (comparison.verdict if verdict == "not decided" else "does not hold")
        rows.append({"claim": claim, "verdict": status, "evidence": comparison.explanation})
    return rows


def _precision_claim(test: PrecisionTest, alpha: float) -> dict[str, str]:
    """A precision test's row: not decided below its seed count, else by its corrected p and the sign."""
    if test.p_value is None:
        seeds = min(means.size for means in test.seed_means)
        return {
            "claim": test.claim,
            "verdict": f"not decided ({seeds} training seed{'s' if seeds != 1 else ''})",
            "evidence": f"{test.networks}; a family verdict needs {test.min_seeds} training seeds with measured "
            "episodes each",
        }
    if test.adjusted_p_value is None:
        raise ValueError(f"the precision test of {test.claim!r} on {test.task} was not corrected (decide_report)")
    if test.adjusted_p_value >= alpha:
        verdict, finding = "not decided", "no difference in the families' means detected"
    else:
        better = test.difference < 0
        verdict = "holds" if better else "does not hold"
        finding = f"{test.family} {'more' if better else 'less'} precise"
    low, high = test.interval
    evidence = (
        f"per-seed mean {test.column}: {test.family} {_listed(test.seed_means[0])}, {test.rival} "
        f"{_listed(test.seed_means[1])}; {finding} (Welch over training seeds p = {test.p_value:.3g}, corrected "
        f"{test.adjusted_p_value:.3g}; difference {test.difference:+.2f}, 95% interval {low:+.2f} to {high:+.2f}); "
        f"{test.networks}"
    )
    return {"claim": test.claim, "verdict": verdict, "evidence": evidence}


def _seed_means(runs: Runs, column: str) -> np.ndarray:
    """(k,) each training seed's mean of a per-episode measure over the episodes that took it; seeds with none out."""
    means = []
    for _, run in sorted(runs.items()):
        if column in run.episodes:
            values = run.episodes[column].to_numpy(dtype=float)
            values = values[np.isfinite(values)]
            if values.size:
                means.append(values.mean())
    return np.array(means)


def _listed(values: np.ndarray) -> str:
    return ", ".join(f"{value:.2f}" for value in values)


def _speed_claims(task_runs: Mapping[str, Runs]) -> list[dict[str, str]]:
    rows = []
    for claim, family, rival in SPEED_CLAIMS:
        if family not in task_runs or rival not in task_runs:
            continue
        ratio = latency_ratio(task_runs[rival], task_runs[family])
        if ratio is None:
            continue
        evidence = (
            f"{rival} takes {ratio.estimate:.1f}x as long per chunk as {family} at batch 1 (95% bootstrap interval "
            f"{ratio.low:.1f}-{ratio.high:.1f}x over episodes' median latencies)"
        )
        rows.append({"claim": claim, "verdict": "holds" if ratio.low > 1 else "does not hold", "evidence": evidence})
    return rows


def find_pair(comparisons: Sequence["verdicts.PairComparison"], family: str, rival: str):
    """The comparison of `family` and `rival` in either order, or None when the run did not pair them."""
    for comparison in comparisons:
        if {comparison.first, comparison.second} == {family, rival}:
            return comparison
    return None


def oriented_verdict(comparison: "verdicts.PairComparison", family: str, rival: str) -> str:
    """The pair's verdict from `family`'s side: "better", "worse", "on par" or "not decided"."""
    verdict = comparison.verdict
    if verdict.startswith("on par"):
        return "on par"
    if verdict == f"{family} better":
        return "better"
    if verdict == f"{rival} better":
        return "worse"
    return "not decided"


def _percent(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f}%"
