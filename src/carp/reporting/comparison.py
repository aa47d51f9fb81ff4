"""The report's comparison of policy families: per-seed results, pooled figures, paired verdicts, the paper's claims.

Every number comes from `carp.reporting.statistics`; this module only arranges the evaluations (task -> family ->
training seed -> summary and test episodes) into what those functions take and into tables and figures. Episodes pair
across families by their episode seed (the same initial state), and training seeds pair by number.
"""

import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from scipy import stats  # noqa: E402

from carp.reporting import statistics  # noqa: E402
from carp.reporting.figures import finish_figure  # noqa: E402


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

MULTITASK_SUFFIX = "-multitask"
"""Appended to a family's name to name its multi-task policy (``carp-multitask``) in evaluation paths and reports."""

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


def family_table(task_runs: Mapping[str, Runs], level: float = 0.95) -> pd.DataFrame:
    """One row per family: pooled and per-seed success, between-seed spread.

    The pooled rate with its Wilson interval, the mean over seeds with its two-level bootstrap interval, the
    between-seed intra-class correlation and the effective number of episodes.
    """
    rows = []
    for family, runs in task_runs.items():
        outcomes = list(outcomes_by_seed(runs).values())
        successes = [int(values.sum()) for values in outcomes]
        trials = [len(values) for values in outcomes]
        total = sum(trials)
        low, high = statistics.wilson_interval(sum(successes), total)
        mean = statistics.two_level_bootstrap(outcomes, level=level)
        icc = statistics.intraclass_correlation(successes, trials)
        effective = statistics.effective_episodes(total, total / len(trials), icc)
        rows.append(
            {
                "policy": family,
                "seeds": len(trials),
                "episodes": total,
                "pooled rate": f"{100 * sum(successes) / total:.1f}% ({100 * low:.1f}-{100 * high:.1f}%)",
                "mean over seeds": f"{100 * mean.estimate:.1f}% ({100 * mean.low:.1f}-{100 * mean.high:.1f}%)",
                "per seed": ", ".join(f"{100 * s / n:.0f}%" for s, n in zip(successes, trials)),
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


def compare_families(
    evaluations: Mapping[str, Mapping[str, Runs]], margin: float, alpha: float, level: float = 0.95
) -> dict[str, list["statistics.PairComparison"]]:
    """Every pair of families on every task, compared on the episodes they share, with Holm over all the pairs.

    Returns:
        task -> its pairs' comparisons, verdicts decided (`statistics.decide_pairs`).
    """
    pairs = [
        (task, first, task_runs[first], second, task_runs[second])
        for task, task_runs in evaluations.items()
        for first, second in combinations(task_runs, 2)
    ]
    return _decide(pairs, list(evaluations), margin, alpha, level)


def compare_multitask(
    single_task: Mapping[str, Mapping[str, Runs]],
    multitask: Mapping[str, Mapping[str, Runs]],
    suffix: str,
    margin: float,
    alpha: float,
    level: float = 0.95,
) -> dict[str, list["statistics.PairComparison"]]:
    """Each multi-task policy against its family's single-task policy, and against the other families' multi-task ones.

    On every task: a family's multi-task policy against its single-task policy where the task has one, then every pair
    of multi-task policies of different families (the comparison of the paper's Table 4). The pairs are compared like
    `compare_families` (episodes by episode seed, training seeds by number), with Holm's correction over every
    multi-task pair of the run, of both kinds.

    Args:
        single_task: task -> family -> runs of the single-task policies.
        multitask: task -> family -> runs of the family's multi-task policy on the task.
        suffix: appended to a family's name to name its multi-task policy in the comparisons (as `split_multitask`).
        margin: equivalence margin of the verdicts, in success rate.
        alpha: family-wise significance level (Holm over the multi-task pairs).
        level: confidence level of the intervals.

    Returns:
        task -> its comparisons, verdicts decided: the (multi-task, single-task) pairs first, multi-task first in each,
        then the pairs of multi-task policies in the order of `multitask`'s families.
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
    return _decide(against_single + between_families, list(multitask), margin, alpha, level)


def _decide(
    pairs: Sequence[tuple[str, str, Runs, str, Runs]], tasks: Sequence[str], margin: float, alpha: float, level: float
) -> dict[str, list["statistics.PairComparison"]]:
    """Compare each (task, first, its runs, second, its runs) on their shared episodes; Holm over all of them."""
    compared = []
    for task, first, first_runs, second, second_runs in pairs:
        shared = _shared_episode_seeds(first_runs, second_runs)
        comparison = statistics.compare_pair(
            first,
            outcomes_by_seed(first_runs, shared),
            second,
            outcomes_by_seed(second_runs, shared),
            first_steps_by_seed=steps_by_seed(first_runs, shared),
            second_steps_by_seed=steps_by_seed(second_runs, shared),
            margin=margin,
            alpha=alpha,
            level=level,
        )
        compared.append((task, comparison))
    decided = statistics.decide_pairs([comparison for _, comparison in compared], margin=margin, alpha=alpha)
    by_task: dict[str, list[statistics.PairComparison]] = {task: [] for task in tasks}
    for (task, _), comparison in zip(compared, decided):
        by_task[task].append(comparison)
    return by_task


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


def claims_table(
    evaluations: Mapping[str, Mapping[str, Runs]],
    comparisons: Mapping[str, Sequence["statistics.PairComparison"]],
    alpha: float = 0.05,
    suffix: str = "",
) -> pd.DataFrame:
    """The paper's claims that this run can check, per task: the verdict and the numbers behind it.

    A success claim holds when the paired verdict says what the paper says ("on par" also holds when CARP comes out
    better); a speed claim states the latency ratio with its interval and holds when the interval lies above 1; a
    precision claim compares the families' mean per-episode offset (Welch) and their variances, and holds when CARP's
    mean is lower at `alpha`. Claims about families the run did not train, or measures its task lacks, are left out.

    Args:
        evaluations: task -> family -> runs.
        comparisons: task -> the pairs compared, each policy named by its family and `suffix`.
        alpha: significance level of the precision claims.
        suffix: appended to a family's name in `comparisons` (`MULTITASK_SUFFIX` for the multi-task policies' claims).
    """
    rows = []
    for task, task_runs in evaluations.items():
        pairs = comparisons.get(task, ())
        rows += [{"task": task, **row} for row in _success_claims(pairs, suffix)]
        rows += [{"task": task, **row} for row in _precision_claims(task_runs, alpha)]
        rows += [{"task": task, **row} for row in _speed_claims(task_runs)]
    return pd.DataFrame(rows, columns=["task", "claim", "verdict", "evidence"])


def _success_claims(pairs: Sequence["statistics.PairComparison"], suffix: str) -> list[dict[str, str]]:
    rows = []
    for claim, family, rival, paper in PAPER_CLAIMS:
        comparison = find_pair(pairs, family + suffix, rival + suffix)
        if comparison is None:
            continue
        verdict = oriented_verdict(comparison, family + suffix, rival + suffix)
        holds = verdict in ("on par", "better") if paper == "on par" else verdict == "better"
        status = "holds" if holds else ("not decided" if verdict == "not decided" else "does not hold")
        rows.append({"claim": claim, "verdict": status, "evidence": comparison.explanation})
    return rows


def _precision_claims(task_runs: Mapping[str, Runs], alpha: float) -> list[dict[str, str]]:
    rows = []
    for claim, family, rival, column in PRECISION_CLAIMS:
        if family not in task_runs or rival not in task_runs or column not in measure_columns(task_runs):
            continue
        result = statistics.compare_means(
            pooled_measure(task_runs[family], column), pooled_measure(task_runs[rival], column)
        )
        if result is None:
            continue
        if result.p_value >= alpha:
            verdict, finding = "not decided", "no difference in the means detected"
        else:
            better = result.difference.estimate < 0
            verdict, finding = (
                ("holds" if better else "does not hold"),
                f"{family} {'more' if better else 'less'} precise",
            )
        variances = "n/a, too few episodes" if result.variance_p_value is None else f"{result.variance_p_value:.3g}"
        evidence = (
            f"{column}: {family} mean {result.first_mean:.2f}, variance {result.first_variance:.2f}; {rival} mean "
            f"{result.second_mean:.2f}, variance {result.second_variance:.2f}; {finding} (Welch p = "
            f"{result.p_value:.3g}, difference {result.difference.estimate:+.2f}, 95% interval "
            f"{result.difference.low:+.2f} to {result.difference.high:+.2f}; equal variances p = "
            f"{variances})"
        )
        rows.append({"claim": claim, "verdict": verdict, "evidence": evidence})
    return rows


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


def find_pair(comparisons: Sequence["statistics.PairComparison"], family: str, rival: str):
    """The comparison of `family` and `rival` in either order, or None when the run did not pair them."""
    for comparison in comparisons:
        if {comparison.first, comparison.second} == {family, rival}:
            return comparison
    return None


def oriented_verdict(comparison: "statistics.PairComparison", family: str, rival: str) -> str:
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
