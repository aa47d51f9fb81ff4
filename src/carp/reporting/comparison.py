"""The report's comparison of policy families: per-seed and family tables, the pairs and their one correction.

Every number comes from `carp.reporting.statistics` (episode-level figures of single networks),
`carp.reporting.seed_inference` (family-level figures over training seeds) and `carp.reporting.verdicts`; this module
arranges the evaluations (`carp.reporting.runs`) into what those functions take, decides every verdict of a report
at once (`decide_report`, the paper's precision claims of `carp.reporting.claims` included) and draws the tables and
figures.
"""

from collections.abc import Mapping, Sequence
from dataclasses import replace
from itertools import combinations
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from scipy import stats  # noqa: E402

from carp.reporting import statistics, verdicts  # noqa: E402
from carp.reporting.claims import PrecisionTest  # noqa: E402
from carp.reporting.figures import finish_figure  # noqa: E402
from carp.reporting.runs import Runs, measure_columns, outcomes_by_seed, pooled_measure, steps_by_seed  # noqa: E402
from carp.reporting.seed_inference import seed_level_estimate  # noqa: E402


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


def _percent(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f}%"
