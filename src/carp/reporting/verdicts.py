"""Verdicts on pairs of policy families: what a report may claim, and the family-wise error it claims it at.

A family verdict ("carp better", "on par within ±5 points") is a statement about the recipes, so its unit is the
training seed (`carp.reporting.seed_inference`): the difference of two families is the mean over paired training
seeds of each seed pair's difference on the same initial states, with a t interval over seeds. A pair with fewer
training seeds than ``min_seeds`` gets no family verdict: "not decided (n training seeds)", and its figures are
reported per network (one trained network of each family, McNemar's test and Newcombe's interval on their shared
episodes), which says how those networks compare and nothing more.

Multiplicity: every pair with enough seeds contributes two hypotheses, "no difference" (two-sided t test; rejected,
the leader is "better") and "the difference is at least the margin" (two one-sided tests; rejected, the two are "on
par"). All of a report's hypotheses (every pair, task and study size) go into one step-down correction in which the
two hypotheses of a pair count once, since they cannot both be true (`seed_inference.step_down_adjust`). The test
that decides each verdict is therefore inside the correction, and the family-wise error of all verdicts a report
states is at most alpha.
"""

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from carp.reporting.seed_inference import SeedLevelEstimate, seed_level_estimate, seeds_to_decide, step_down_adjust
from carp.reporting.statistics import (
    Interval,
    KaplanMeierCurve,
    McNemarResult,
    as_outcomes,
    kaplan_meier,
    mcnemar_exact,
    newcombe_paired_difference,
)
from carp.reporting.verdict_text import (
    disagreement_text,
    interval_bounds,
    networks_text,
    seeds_text,
    summary_text,
)

DEFAULT_MIN_SEEDS = 3
"""Training seeds per family a family verdict needs unless the params say otherwise (never fewer than 2)."""


@dataclass(frozen=True)
class NetworkComparison:
    """One trained network of each family (a training seed pair) on the same initial states.

    Attributes:
        first_seed: the first family's training seed.
        second_seed: the second family's training seed.
        episodes: paired episodes.
        first_rate: the first network's success share over them.
        second_rate: the second network's.
        difference: Newcombe's paired interval of the two networks' difference (first minus second).
        mcnemar: exact McNemar test of the two networks.
    """

    first_seed: int
    second_seed: int
    episodes: int
    first_rate: float
    second_rate: float
    difference: Interval
    mcnemar: McNemarResult


@dataclass(frozen=True)
class PairComparison:
    """Everything a report prints for one pair of families on one task; differences are first minus second.

    Attributes:
        first: name of the first family.
        second: name of the second family.
        seeds: paired training seeds used.
        episodes: paired episodes per seed pair (the shared initial states).
        shared_states: every seed pair ran the same initial states (crossed design).
        first_seed_rates: the first family's success share per paired training seed, in pairing order.
        second_seed_rates: the second family's, paired with ``first_seed_rates``.
        first_rate: the first family's mean over its paired seeds of the per-seed success share.
        second_rate: the second family's.
        estimate: the seed-level estimate of the family difference; None with fewer than 2 seed pairs.
        difference: the family difference with its t interval over training seeds at ``level``; None with fewer
            than 2 seed pairs.
        equivalence_difference: the same at 1 - 2 ``alpha`` (the two one-sided tests); None likewise.
        p_value: two-sided p of "no difference" over training seeds; None below ``min_seeds``.
        equivalence_p_value: p of "the difference is at least the margin"; None below ``min_seeds``.
        adjusted_p_value: ``p_value`` after the report-wide correction (``decide_pairs``); None likewise.
        adjusted_equivalence_p_value: ``equivalence_p_value`` after it; None likewise.
        networks: each seed pair's network comparison.
        seeds_needed: training seeds per family after which a verdict becomes likely at this estimate; None when
            not estimable or already decided.
        first_steps_curve: Kaplan-Meier curve of the first family's steps to success (seeds pooled, descriptive).
        second_steps_curve: the same for the second family.
        min_seeds: training seeds a family verdict needs.
        level: confidence level of ``difference`` and the network intervals.
        alpha: family-wise significance level of the verdicts.
        margin: equivalence margin, as a share.
        verdict: ``"<first> better"``, ``"<second> better"``, ``"on par within ±<m> points"``, ``"not decided"``
            or ``"not decided (<n> training seeds)"``.
        explanation: sentences with the numbers behind the verdict.
        pairing_note: how training seeds and episodes were paired when not one to one; empty otherwise.
    """

    first: str
    second: str
    seeds: int
    episodes: int
    shared_states: bool
    first_seed_rates: tuple[float, ...]
    second_seed_rates: tuple[float, ...]
    first_rate: float
    second_rate: float
    estimate: SeedLevelEstimate | None
    difference: Interval | None
    equivalence_difference: Interval | None
    p_value: float | None
    equivalence_p_value: float | None
    adjusted_p_value: float | None
    adjusted_equivalence_p_value: float | None
    networks: tuple[NetworkComparison, ...]
    seeds_needed: int | None
    first_steps_curve: KaplanMeierCurve | None
    second_steps_curve: KaplanMeierCurve | None
    min_seeds: int
    level: float
    alpha: float
    margin: float
    verdict: str
    explanation: str
    pairing_note: str

    @property
    def decidable(self) -> bool:
        """Whether the pair has the training seeds a family verdict needs."""
        return self.seeds >= self.min_seeds


def compare_pair(
    first_name: str,
    first_by_seed: Mapping[int, np.ndarray],
    second_name: str,
    second_by_seed: Mapping[int, np.ndarray],
    *,
    first_steps_by_seed: Mapping[int, np.ndarray] | None = None,
    second_steps_by_seed: Mapping[int, np.ndarray] | None = None,
    max_steps: int | None = None,
    shared_states: bool = True,
    min_seeds: int = DEFAULT_MIN_SEEDS,
    margin: float = 0.05,
    alpha: float = 0.05,
    level: float = 0.95,
) -> PairComparison:
    """Compare two families on one task, as if this were the only pair of the report (``decide_pairs`` corrects).

    Training seeds with the same number pair first; the remaining ones pair by sorted position (said in
    ``pairing_note``), and seeds left over are not used. Within a seed pair, episodes pair by position (the same
    initial state) and are truncated to the shorter list.

    Args:
        first_name: name of the first family.
        first_by_seed: training seed -> (m,) bool outcomes over the task's episode seeds, in their shared order.
        second_name: name of the second family.
        second_by_seed: the same for the second family.
        first_steps_by_seed: training seed -> (m,) int steps per episode, for the steps-to-success curves.
        second_steps_by_seed: the same for the second family.
        max_steps: episode horizon for the curves; the largest step seen when None.
        shared_states: whether every seed pair ran the same initial states (True in carp's evaluations).
        min_seeds: training seeds per family a family verdict needs; >= 2.
        margin: equivalence margin as a share (0.05 = 5 points).
        alpha: significance level; the equivalence interval is at 1 - 2 alpha.
        level: confidence level of the printed intervals.

    Raises:
        ValueError: no training seed pairs, no episode pairs, only one family's steps, or ``min_seeds`` < 2.
    """
    _check_settings(min_seeds, margin, alpha, level)
    if (first_steps_by_seed is None) != (second_steps_by_seed is None):
        raise ValueError("give steps for both families or for neither")
    seed_pairs, note = _pair_seeds(first_name, first_by_seed, second_name, second_by_seed)
    first_runs, second_runs, used_pairs, first_steps, second_steps = [], [], [], [], []
    truncated, empty = False, []
    for first_seed, second_seed in seed_pairs:
        first_values = as_outcomes(first_by_seed[first_seed], first_name)
        second_values = as_outcomes(second_by_seed[second_seed], second_name)
        length = min(first_values.size, second_values.size)
        truncated |= first_values.size != second_values.size
        if length == 0:
            empty.append(f"{first_seed} with {second_seed}")
            continue
        first_runs.append(first_values[:length])
        second_runs.append(second_values[:length])
        used_pairs.append((first_seed, second_seed))
        if first_steps_by_seed is not None and second_steps_by_seed is not None:
            first_steps.append(_steps_of(first_steps_by_seed, first_seed, first_values.size, first_name)[:length])
            second_steps.append(_steps_of(second_steps_by_seed, second_seed, second_values.size, second_name)[:length])
    if not first_runs:
        raise ValueError(f"{first_name} and {second_name} share no evaluated episode: nothing to compare")
    if shared_states and len({run.size for run in first_runs}) > 1:
        # A crossed design needs one set of states; seeds that ran more keep the common leading ones.
        shortest = min(run.size for run in first_runs)
        first_runs = [run[:shortest] for run in first_runs]
        second_runs = [run[:shortest] for run in second_runs]
        first_steps = [steps[:shortest] for steps in first_steps]
        second_steps = [steps[:shortest] for steps in second_steps]
        truncated = True
    if truncated:
        note = _join_notes(note, "episodes truncated to the shorter list of each seed pair")
    if empty:
        note = _join_notes(note, f"seed pairs without episodes left out: {', '.join(empty)}")
    networks = tuple(
        NetworkComparison(
            first_seed=first_seed,
            second_seed=second_seed,
            episodes=int(first.size),
            first_rate=float(first.mean()),
            second_rate=float(second.mean()),
            difference=newcombe_paired_difference(first, second, level),
            mcnemar=mcnemar_exact(first, second),
        )
        for (first_seed, second_seed), first, second in zip(used_pairs, first_runs, second_runs)
    )
    estimate = (
        seed_level_estimate(
            [first.astype(float) - second.astype(float) for first, second in zip(first_runs, second_runs)],
            shared_states=shared_states,
            value_range=(-1.0, 1.0),
        )
        if len(first_runs) >= 2
        else None
    )
    decidable = len(first_runs) >= min_seeds
    curves = _steps_curves(first_runs, second_runs, first_steps, second_steps, max_steps)
    comparison = PairComparison(
        first=first_name,
        second=second_name,
        seeds=len(first_runs),
        episodes=min(run.size for run in first_runs),
        shared_states=shared_states,
        first_seed_rates=tuple(float(run.mean()) for run in first_runs),
        second_seed_rates=tuple(float(run.mean()) for run in second_runs),
        first_rate=float(np.mean([run.mean() for run in first_runs])),
        second_rate=float(np.mean([run.mean() for run in second_runs])),
        estimate=estimate,
        difference=estimate.interval(level) if estimate is not None else None,
        equivalence_difference=estimate.interval(1.0 - 2.0 * alpha) if estimate is not None else None,
        p_value=estimate.p_value() if decidable and estimate is not None else None,
        equivalence_p_value=estimate.equivalence_p_value(margin) if decidable and estimate is not None else None,
        adjusted_p_value=None,
        adjusted_equivalence_p_value=None,
        networks=networks,
        seeds_needed=None,
        first_steps_curve=curves[0],
        second_steps_curve=curves[1],
        min_seeds=min_seeds,
        level=level,
        alpha=alpha,
        margin=margin,
        verdict="",
        explanation="",
        pairing_note=note,
    )
    return _with_verdict(comparison, comparison.p_value, comparison.equivalence_p_value, groups=1)


def decide_pairs(comparisons: Sequence[PairComparison], margin: float, alpha: float = 0.05) -> list[PairComparison]:
    """Correct every pair's tests over the whole report, then give each pair its verdict.

    A family is "better" when its pair's adjusted p of "no difference" is below ``alpha``; the two are "on par within
    ±margin" when the adjusted p of "the difference is at least the margin" is below ``alpha``; both at once reads
    "better" (the difference is real but smaller than the margin, which the explanation says). Pairs with fewer than
    ``min_seeds`` training seeds are "not decided (n training seeds)" and take no part in the correction.

    Args:
        comparisons: results of ``compare_pair``, all computed at this ``alpha``.
        margin: equivalence margin as a share.
        alpha: family-wise significance level over every verdict of ``comparisons``.

    Returns:
        The comparisons in the same order with adjusted p-values, ``margin``, ``verdict`` and ``explanation``.
    """
    return decide_pairs_and_tests(comparisons, (), margin, alpha)[0]


def decide_pairs_and_tests(
    comparisons: Sequence[PairComparison], other_p_values: Sequence[float], margin: float, alpha: float = 0.05
) -> tuple[list[PairComparison], list[float]]:
    """``decide_pairs`` with further single-hypothesis tests of the same report under the same correction.

    Every claim a report states from a rejection must share the family-wise level, so tests that are not success
    pairs (e.g. a precision claim's test of two families' mean measures) join the correction, each as its own group.

    Args:
        comparisons: as for ``decide_pairs``.
        other_p_values: raw p-values of the other tests.
        margin: equivalence margin as a share.
        alpha: family-wise significance level over the pairs' verdicts and the other tests together.

    Returns:
        The decided comparisons (as ``decide_pairs``) and the other tests' adjusted p-values, in their input order.
    """
    for comparison in comparisons:
        if not math.isclose(comparison.alpha, alpha):
            raise ValueError(
                f"{comparison.first} vs {comparison.second} was compared at alpha={comparison.alpha}, not {alpha}: "
                "its equivalence interval would not match"
            )
    rescored = [_at_margin(comparison, margin) for comparison in comparisons]
    p_values, groups = [], []
    for index, comparison in enumerate(rescored):
        if comparison.decidable:
            p_values += [comparison.p_value, comparison.equivalence_p_value]
            groups += [index, index]
    p_values += list(other_p_values)
    groups += [len(rescored) + index for index in range(len(other_p_values))]
    adjusted = step_down_adjust(p_values, groups)
    pair_adjusted = iter(adjusted[: len(adjusted) - len(other_p_values)])
    hypotheses = max(1, len(set(groups)))
    decided = []
    for comparison in rescored:
        if comparison.decidable:
            difference_p, equivalence_p = next(pair_adjusted), next(pair_adjusted)
        else:
            difference_p = equivalence_p = None
        decided.append(_with_verdict(comparison, difference_p, equivalence_p, hypotheses))
    return decided, adjusted[len(adjusted) - len(other_p_values) :]


def _at_margin(comparison: PairComparison, margin: float) -> PairComparison:
    """The comparison with its equivalence p-value recomputed at `margin`."""
    _check_settings(comparison.min_seeds, margin, comparison.alpha, comparison.level)
    equivalence = comparison.estimate.equivalence_p_value(margin) if comparison.decidable else None
    return replace(comparison, margin=margin, equivalence_p_value=equivalence)


def _with_verdict(
    comparison: PairComparison,
    difference_p: float | None,
    equivalence_p: float | None,
    groups: int,
) -> PairComparison:
    """The comparison with its verdict and explanation at given adjusted p-values (see ``decide_pairs``).

    ``groups`` counts the correction's groups (pairs and other tests), whose count the strictest step divides by.
    """
    alpha, margin = comparison.alpha, comparison.margin
    margin_text = f"±{100.0 * margin:g} points"
    networks = networks_text(comparison)
    seeds_needed = None
    if not comparison.decidable:
        verdict = f"not decided ({seeds_text(comparison.seeds)})"
        explanation = (
            f"{seeds_text(comparison.seeds)} per family, fewer than the {comparison.min_seeds} a family verdict "
            f"needs: these figures compare the trained networks, not the families. {networks}."
        )
        return replace(comparison, verdict=verdict, explanation=explanation)
    assert difference_p is not None and equivalence_p is not None and comparison.estimate is not None
    summary = summary_text(comparison, difference_p, equivalence_p)
    better = difference_p < alpha
    equivalent = equivalence_p < alpha
    if better:
        leader = comparison.first if comparison.difference.estimate > 0 else comparison.second
        verdict = f"{leader} better"
        within = f", by less than {margin_text}" if equivalent else ""
        explanation = f"{summary}, so {leader} is better{within}."
    elif equivalent:
        verdict = f"on par within {margin_text}"
        explanation = (
            f"{summary}; the {1 - 2 * alpha:.0%} interval over training seeds "
            f"({interval_bounds(comparison.equivalence_difference)}) lies within {margin_text}, so the two are on par."
        )
    else:
        verdict = "not decided"
        # The correction's strictest step, so the count holds whichever rank this pair's p-value takes.
        seeds_needed = seeds_to_decide(comparison.estimate, margin, alpha / groups)
        outlook = (
            f"about {seeds_needed} training seeds per family would likely decide at this difference and spread"
            if seeds_needed is not None
            else "no number of training seeds up to 100 would likely decide at this difference and spread"
        )
        explanation = f"{summary}; {disagreement_text(comparison)}{outlook}."
    return replace(
        comparison,
        adjusted_p_value=difference_p,
        adjusted_equivalence_p_value=equivalence_p,
        seeds_needed=seeds_needed,
        verdict=verdict,
        explanation=f"{explanation} {networks}.",
    )


def _check_settings(min_seeds: int, margin: float, alpha: float, level: float) -> None:
    if min_seeds < 2:
        raise ValueError(f"min_seeds={min_seeds} must be >= 2: one training seed says nothing about a family")
    if not 0.0 < margin < 1.0:
        raise ValueError(f"margin={margin} must lie in (0, 1)")
    for name, value in (("alpha", alpha), ("level", level)):
        if not 0.0 < value < 1.0:
            raise ValueError(f"{name}={value} must lie in (0, 1)")


def _pair_seeds(
    first_name: str, first_by_seed: Mapping[int, np.ndarray], second_name: str, second_by_seed: Mapping[int, np.ndarray]
) -> tuple[list[tuple[int, int]], str]:
    """Training seed pairs (same numbers, then the rest by sorted position) and a note on anything not one to one."""
    if not first_by_seed or not second_by_seed:
        empty = first_name if not first_by_seed else second_name
        raise ValueError(f"{empty} has no training seed: nothing to pair")
    common = sorted(set(first_by_seed) & set(second_by_seed))
    first_rest = sorted(set(first_by_seed) - set(common))
    second_rest = sorted(set(second_by_seed) - set(common))
    by_position = list(zip(first_rest, second_rest))
    note = ""
    if by_position:
        listed = ", ".join(f"{first} with {second}" for first, second in by_position)
        note = f"training seeds of {first_name} and {second_name} paired by sorted position: {listed}"
    unused = [f"{first_name} {seed}" for seed in first_rest[len(by_position) :]]
    unused += [f"{second_name} {seed}" for seed in second_rest[len(by_position) :]]
    if unused:
        note = _join_notes(note, f"unpaired training seeds left out: {', '.join(unused)}")
    return [(seed, seed) for seed in common] + by_position, note


def _steps_of(steps_by_seed: Mapping[int, np.ndarray], seed: int, episodes: int, name: str) -> np.ndarray:
    """One training seed's (m,) steps per episode, checked to match its outcomes."""
    if seed not in steps_by_seed:
        raise ValueError(f"{name}: no steps for training seed {seed}")
    steps = np.asarray(steps_by_seed[seed])
    if steps.shape != (episodes,):
        raise ValueError(f"{name}: training seed {seed} has {episodes} outcomes but steps of shape {steps.shape}")
    return steps


def _steps_curves(
    first_runs: list[np.ndarray],
    second_runs: list[np.ndarray],
    first_steps: list[np.ndarray],
    second_steps: list[np.ndarray],
    max_steps: int | None,
) -> tuple[KaplanMeierCurve | None, KaplanMeierCurve | None]:
    """Both families' Kaplan-Meier curves over their seeds' episodes, or Nones when no steps were given."""
    if not first_steps:
        return None, None
    first_counts, second_counts = np.concatenate(first_steps), np.concatenate(second_steps)
    horizon = max_steps if max_steps is not None else int(max(first_counts.max(), second_counts.max()))
    return (
        kaplan_meier(first_counts, np.concatenate(first_runs), horizon),
        kaplan_meier(second_counts, np.concatenate(second_runs), horizon),
    )


def _join_notes(first: str, second: str) -> str:
    return f"{first}; {second}" if first else second
