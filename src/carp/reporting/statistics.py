"""Intervals, tests and verdicts for comparing policy families on the same evaluation episodes.

Families are evaluated on one list of episode seeds (initial states) per task, for one or more training seeds each, so
episode ``i`` of a training seed pairs across families. This module turns such outcomes into the numbers a report
prints: paired intervals and tests over episodes, a two-level bootstrap over training seeds and episodes, the
clustering of success within a training seed, steps-to-success curves, and a verdict per pair of families.

Sources (formulas re-derived from the papers, not copied from any implementation):
    - Wilson (1927): score interval of one proportion.
    - Newcombe (1998), "Improved confidence intervals for the difference between binomial proportions based on
      paired data", Statistics in Medicine 17:2635-2650, method 10 (Wilson margins, continuity-corrected phi).
    - McNemar (1947), exact form: a binomial test on the discordant pairs.
    - Holm (1979): step-down family-wise adjustment.
    - Ridout, Demetrio & Firth (1999), "Estimating intraclass correlation for binary data", Biometrics 55:137-148:
      the ANOVA estimator of the intra-class correlation; Kish (1965): design effect 1 + (m - 1) rho.
    - Davison & Hinkley (1997), section 3.8: bootstrap of hierarchical data by resampling clusters, then units.
    - Connor (1987), "Sample size for testing differences in proportions for the paired-sample design", Biometrics
      43:207-211; Chow, Shao & Wang (2008), "Sample Size Calculations in Clinical Research", equivalence (TOST).
    - Kaplan & Meier (1958) and the log-rank test, through ``scipy.stats.ecdf`` and ``scipy.stats.logrank``.
    - Hayes & Moulton, "Cluster Randomised Trials": a t interval on cluster-level summaries when clusters are few.
    - Phipson & Smyth (2010), "Permutation p-values should never be zero": sampled permutations count the observed.

Deviations:
    - The episode level of the bootstrap draws the per-seed counts of each outcome cell from a multinomial instead of
      drawing episode indices; for binary outcomes both have the same distribution, and the draw costs O(cells).
    - ``episodes_to_decide`` returns the smaller of the superiority (Connor) and equivalence (TOST) sample sizes, the
      episodes after which either verdict becomes likely at the observed rates.
    - A verdict also asks the Student-t interval over training seeds (``paired_seed_interval``): the percentile
      bootstrap over 3 seeds covers far below its level (see ``decide_pairs``).

Limits: the same initial states recur for every training seed, but episodes of different training seeds are
treated as independent draws, as are states within a seed. A family-by-state interaction (states that only one
family finds hard) therefore narrows every interval here; more distinct episode seeds, not more training seeds,
shrink it.
"""

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
from scipy import stats

# The evaluate stage's own interval and quantile: kept in carp.evaluation so that the report's statistics are no
# dependency of the evaluations (a change here reruns the report alone).
from carp.evaluation.metrics import wilson_interval

# The seed permutation test enumerates every split up to this many (9 seeds against 9 is C(18, 9) = 48,620, a few
# tens of milliseconds) and draws this many random splits beyond, where enumeration would take seconds.
_MAX_PERMUTATION_SPLITS = 50_000

# Differences of per-seed mean rates computed in different summation orders agree to ~1e-15; ties within this are
# ties, so the observed split always counts as at least as extreme as itself.
_TIE_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Interval:
    """A point estimate with a two-sided confidence interval, all on the same scale (shares, not points)."""

    estimate: float
    low: float
    high: float

    def inside(self, margin: float) -> bool:
        """Whether the whole interval lies strictly within (-margin, +margin)."""
        return -margin < self.low and self.high < margin


@dataclass(frozen=True)
class McNemarResult:
    """Exact McNemar test of two paired binary outcomes.

    Attributes:
        first_only: pairs where only the first succeeded.
        second_only: pairs where only the second succeeded.
        p_value: exact two-sided p-value; 1.0 when no pair is discordant.
    """

    first_only: int
    second_only: int
    p_value: float


@dataclass(frozen=True)
class KaplanMeierCurve:
    """Cumulative share of episodes that succeeded by each step, as a right-continuous step function.

    Attributes:
        steps: (S,) int64, increasing: 0, then every step at which some episode succeeded, then ``max_steps`` unless
            the last success happened there.
        success_share: (S,) float64, the share succeeded by (and including) each of ``steps``; 0 at step 0.
    """

    steps: np.ndarray
    success_share: np.ndarray

    def share_at(self, steps: np.ndarray | Sequence[int] | int) -> np.ndarray:
        """The curve at arbitrary steps (steps >= 0); float64 of the shape of ``steps``."""
        positions = np.searchsorted(self.steps, np.asarray(steps), side="right") - 1
        return self.success_share[np.clip(positions, 0, None)]


@dataclass(frozen=True)
class PairComparison:
    """Everything the report prints for one pair of families on one task.

    Differences are first minus second, as shares in [-1, 1].

    Attributes:
        first: name of the first family.
        second: name of the second family.
        episodes: paired episodes used, over all paired training seeds.
        seeds: paired training seeds used.
        first_rate: the first family's success share over the paired episodes.
        second_rate: the second family's success share over the paired episodes.
        difference: Newcombe's paired interval at ``level`` over all paired episodes.
        bootstrap_difference: the paired two-level bootstrap interval at ``level``; it carries training-seed spread.
        equivalence_difference: Newcombe's interval at 1 - 2 ``alpha`` (the two one-sided tests of equivalence).
        equivalence_bootstrap_difference: the paired two-level bootstrap interval at 1 - 2 ``alpha``.
        seed_difference: Student-t interval at ``level`` of the mean per-seed difference (``paired_seed_interval``);
            None with one seed pair.
        first_seed_rates: the first family's success share per paired training seed, in pairing order.
        second_seed_rates: the second family's, paired with ``first_seed_rates``.
        mcnemar: exact McNemar test over all paired episodes.
        seed_p_value: permutation test of per-seed success rates; None with fewer than 2 seeds per family.
        logrank_p_value: log-rank test of steps to success; None when steps were not given.
        first_steps_curve: Kaplan-Meier curve of the first family's steps to success; None without steps.
        second_steps_curve: the same for the second family.
        adjusted_p_value: Holm-adjusted McNemar p-value over every pair that ``decide_pairs`` saw.
        level: confidence level of ``difference`` and ``bootstrap_difference``.
        alpha: significance level of the verdict.
        margin: equivalence margin of the verdict, as a share.
        verdict: ``"<first> better"``, ``"<second> better"``, ``"on par within ±<m> points"`` or ``"not decided"``.
        explanation: one sentence with the numbers behind the verdict.
        pairing_note: how training seeds and episodes were paired when not one to one; empty otherwise.
    """

    first: str
    second: str
    episodes: int
    seeds: int
    first_rate: float
    second_rate: float
    difference: Interval
    bootstrap_difference: Interval
    equivalence_difference: Interval
    equivalence_bootstrap_difference: Interval
    seed_difference: Interval | None
    first_seed_rates: tuple[float, ...]
    second_seed_rates: tuple[float, ...]
    mcnemar: McNemarResult
    seed_p_value: float | None
    logrank_p_value: float | None
    first_steps_curve: KaplanMeierCurve | None
    second_steps_curve: KaplanMeierCurve | None
    adjusted_p_value: float
    level: float
    alpha: float
    margin: float
    verdict: str
    explanation: str
    pairing_note: str


def z_value(level: float) -> float:
    """Two-sided standard normal quantile of a confidence level (0.95 -> 1.95996...)."""
    _check_open_unit("level", level)
    return float(stats.norm.ppf(0.5 + level / 2.0))


def newcombe_paired_difference(first: np.ndarray, second: np.ndarray, level: float = 0.95) -> Interval:
    """Newcombe's (1998) method 10 interval for the difference of two paired success shares.

    The Wilson intervals of the two margins are combined by "square and add", corrected for the correlation of the
    paired outcomes by phi. As Newcombe defines it, phi's numerator ad - bc is reduced by n / 2 when it exceeds n / 2
    and set to 0 when it lies in [0, n / 2] (a continuity correction that never flips its sign), and phi is 0 when a
    margin is empty (zero denominator).

    Args:
        first: (N,) bool, the first family's outcome per episode.
        second: (N,) bool, the second family's outcome on the same episodes, in the same order.
        level: confidence level in (0, 1).

    Returns:
        estimate = mean(first) - mean(second), with bounds clipped to [-1, 1].
    """
    first, second = _paired_outcomes(first, second)
    episodes = first.size
    both = int(np.sum(first & second))
    first_only = int(np.sum(first & ~second))
    second_only = int(np.sum(~first & second))
    neither = episodes - both - first_only - second_only
    z = z_value(level)
    first_rate = (both + first_only) / episodes
    second_rate = (both + second_only) / episodes
    first_low, first_high = wilson_interval(both + first_only, episodes, z)
    second_low, second_high = wilson_interval(both + second_only, episodes, z)
    phi = _newcombe_phi(both, first_only, second_only, neither)
    below_first, above_first = first_rate - first_low, first_high - first_rate
    below_second, above_second = second_rate - second_low, second_high - second_rate
    # The lower bound of the difference pairs the first margin's lower distance with the second's upper one, and the
    # other way round for the upper bound; |phi| <= 1 keeps both radicands >= 0 up to rounding.
    lower_radicand = below_first**2 - 2.0 * phi * below_first * above_second + above_second**2
    upper_radicand = above_first**2 - 2.0 * phi * above_first * below_second + below_second**2
    estimate = first_rate - second_rate
    low = estimate - math.sqrt(max(0.0, lower_radicand))
    high = estimate + math.sqrt(max(0.0, upper_radicand))
    return Interval(estimate, max(-1.0, low), min(1.0, high))


def mcnemar_exact(first: np.ndarray, second: np.ndarray) -> McNemarResult:
    """Exact two-sided McNemar test: a binomial test of the first-only count among discordant pairs at 1/2.

    Args:
        first: (N,) bool, the first family's outcome per episode.
        second: (N,) bool, the second family's outcome on the same episodes.
    """
    first, second = _paired_outcomes(first, second)
    first_only = int(np.sum(first & ~second))
    second_only = int(np.sum(~first & second))
    if first_only + second_only == 0:
        return McNemarResult(0, 0, 1.0)
    p_value = stats.binomtest(first_only, first_only + second_only, 0.5).pvalue
    return McNemarResult(first_only, second_only, float(p_value))


def holm_adjust(p_values: Sequence[float]) -> list[float]:
    """Holm's (1979) step-down adjusted p-values, in the input order.

    The i-th smallest of m p-values is multiplied by m - i + 1; a running maximum keeps the adjusted values in the
    order of the raw ones, and they are capped at 1. Rejecting where adjusted < alpha controls the family-wise error.
    """
    raw = np.asarray(p_values, dtype=np.float64)
    if raw.ndim != 1 or np.any(np.isnan(raw)) or np.any((raw < 0) | (raw > 1)):
        raise ValueError(f"p-values must be a flat sequence of numbers in [0, 1], got {p_values!r}")
    count = raw.size
    order = np.argsort(raw, kind="stable")
    scaled = (count - np.arange(count)) * raw[order]
    adjusted = np.empty(count)
    adjusted[order] = np.minimum(1.0, np.maximum.accumulate(scaled))
    return adjusted.tolist()


def seed_permutation_test(first_rates: Sequence[float], second_rates: Sequence[float]) -> float | None:
    """Two-sided permutation test of the difference of mean per-training-seed success rates.

    Every split of the pooled seeds into groups of the original sizes is enumerated; the p-value is the share of
    splits whose absolute difference of means is at least the observed one. The split count bounds the smallest
    reachable p: 2 / C(6, 3) = 0.1 for 3 seeds against 3, 2 / C(8, 4) = 0.029 for 4 against 4. Beyond 50,000 splits
    (more than 9 seeds against 9) 50,000 random splits are drawn with a fixed seed instead, and the observed split is
    counted once more so the estimate is never 0 (Phipson & Smyth 2010).

    Args:
        first_rates: (n1,) per-seed success rates of the first family.
        second_rates: (n2,) per-seed success rates of the second family.

    Returns:
        The p-value, or None when either family has fewer than 2 seeds (no spread to compare against).
    """
    first = np.asarray(first_rates, dtype=np.float64)
    second = np.asarray(second_rates, dtype=np.float64)
    if first.ndim != 1 or second.ndim != 1:
        raise ValueError("per-seed rates must be flat sequences")
    if first.size < 2 or second.size < 2:
        return None
    pooled = np.concatenate([first, second])
    observed = abs(first.mean() - second.mean())
    exact = math.comb(pooled.size, first.size) <= _MAX_PERMUTATION_SPLITS
    if exact:
        first_groups = np.array(list(itertools.combinations(range(pooled.size), first.size)))  # (splits, n1)
    else:
        orders = np.tile(np.arange(pooled.size), (_MAX_PERMUTATION_SPLITS, 1))
        first_groups = np.random.default_rng(0).permuted(orders, axis=1)[:, : first.size]  # (splits, n1)
    first_sums = pooled[first_groups].sum(axis=1)
    differences = first_sums / first.size - (pooled.sum() - first_sums) / second.size
    extreme = int(np.sum(np.abs(differences) >= observed - _TIE_TOLERANCE))
    if exact:
        return extreme / first_groups.shape[0]
    return (extreme + 1) / (first_groups.shape[0] + 1)


def paired_seed_interval(
    first_rates: Sequence[float], second_rates: Sequence[float], level: float = 0.95
) -> Interval | None:
    """Student-t interval of the mean per-seed difference of success rates over paired training seeds.

    The analysis of cluster-level summaries for few clusters (Hayes & Moulton, "Cluster Randomised Trials"): each
    seed pair contributes one difference, whose spread holds both seed-to-seed and episode noise, and k - 1 degrees
    of freedom price in how little k seeds say about that spread. With 3 seeds the t quantile is 4.30 against the
    normal 1.96, which a percentile bootstrap over 3 seeds cannot know.

    Args:
        first_rates: (k,) per-seed success rates of the first family.
        second_rates: (k,) success rates of the second family, the i-th seed paired with the first's i-th.
        level: confidence level in (0, 1).

    Returns:
        The mean difference (first minus second) with its interval, or None with fewer than 2 seed pairs.
    """
    differences = np.asarray(first_rates, dtype=np.float64) - np.asarray(second_rates, dtype=np.float64)
    if differences.ndim != 1:
        raise ValueError("per-seed rates must be flat sequences of the same length")
    _check_open_unit("level", level)
    if differences.size < 2:
        return None
    mean = float(differences.mean())
    half_width = stats.t.ppf(0.5 + level / 2.0, differences.size - 1) * differences.std(ddof=1)
    half_width /= math.sqrt(differences.size)
    return Interval(mean, max(-1.0, mean - half_width), min(1.0, mean + half_width))


def intraclass_correlation(successes: Sequence[int], trials: Sequence[int]) -> float:
    """Intra-class correlation of success within training seeds (ANOVA estimator, Ridout et al. 1999).

    Under a beta-binomial model each training seed has its own success rate; rho is the share of outcome variance
    that is between seeds. The ANOVA estimator is (MSB - MSW) / (MSB + (n0 - 1) MSW) with the between- and
    within-seed mean squares of the 0/1 outcomes and n0 the size-weighted mean seed size.

    Args:
        successes: (k,) successes per training seed.
        trials: (k,) episodes per training seed, each >= 1.

    Returns:
        rho clipped to [0, 1]; 0.0 for a single seed, when every seed has one episode, or when every episode has the
        same outcome (no variance to split).
    """
    success_counts = np.asarray(successes, dtype=np.float64)
    trial_counts = np.asarray(trials, dtype=np.float64)
    if success_counts.shape != trial_counts.shape or success_counts.ndim != 1:
        raise ValueError("successes and trials must be flat sequences of the same length")
    if np.any(trial_counts < 1) or np.any(success_counts < 0) or np.any(success_counts > trial_counts):
        raise ValueError("each seed needs trials >= 1 and 0 <= successes <= trials")
    seeds = success_counts.size
    total = trial_counts.sum()
    if seeds < 2 or total == seeds:
        return 0.0
    between_sum = np.sum(success_counts**2 / trial_counts) - success_counts.sum() ** 2 / total
    within_sum = success_counts.sum() - np.sum(success_counts**2 / trial_counts)
    between_mean_square = between_sum / (seeds - 1)
    within_mean_square = within_sum / (total - seeds)
    mean_seed_size = (total - np.sum(trial_counts**2) / total) / (seeds - 1)
    denominator = between_mean_square + (mean_seed_size - 1.0) * within_mean_square
    if denominator <= 0:
        return 0.0
    return float(np.clip((between_mean_square - within_mean_square) / denominator, 0.0, 1.0))


def effective_episodes(total_episodes: int, episodes_per_seed: float, icc: float) -> float:
    """Independent episodes worth as much as ``total_episodes`` clustered in seeds: N / (1 + (m - 1) rho) (Kish).

    Args:
        total_episodes: N, all episodes over all training seeds.
        episodes_per_seed: m, episodes per training seed (a mean when seeds differ), >= 1.
        icc: rho in [0, 1], e.g. from ``intraclass_correlation``.
    """
    if total_episodes < 0 or episodes_per_seed < 1 or not 0.0 <= icc <= 1.0:
        raise ValueError(
            f"need total >= 0, per seed >= 1, icc in [0, 1]; got {total_episodes}, {episodes_per_seed}, {icc}"
        )
    return total_episodes / (1.0 + (episodes_per_seed - 1.0) * icc)


def two_level_bootstrap(
    outcomes_by_seed: Sequence[np.ndarray], level: float = 0.95, resamples: int = 4000, seed: int = 0
) -> Interval:
    """Percentile bootstrap of the mean over training seeds of the per-seed success rate.

    Each resample draws training seeds with replacement, then episodes with replacement within each drawn seed
    (with one seed, episodes only), so the interval carries both seed-to-seed and episode-to-episode spread.

    Args:
        outcomes_by_seed: k arrays, each (n_s,) bool, one training seed's episode outcomes; n_s >= 1 may differ.
        level: confidence level in (0, 1).
        resamples: bootstrap resamples.
        seed: seed of the resampling generator.

    Returns:
        estimate: mean of the observed per-seed rates; low, high: percentile bounds.
    """
    outcomes = [_outcomes(values, "outcomes_by_seed") for values in outcomes_by_seed]
    if not outcomes:
        raise ValueError("two_level_bootstrap needs at least one training seed")
    episodes = np.array([values.size for values in outcomes])
    successes = np.array([values.sum() for values in outcomes])
    cell_shares = np.stack([successes / episodes, 1.0 - successes / episodes], axis=1)  # (k, 2)
    draws = _bootstrap_seed_means(cell_shares, episodes, np.array([1.0, 0.0]), resamples, seed)
    return _percentile_interval(float(np.mean(successes / episodes)), draws, level)


def paired_two_level_bootstrap(
    first_by_seed: Sequence[np.ndarray],
    second_by_seed: Sequence[np.ndarray],
    level: float = 0.95,
    resamples: int = 4000,
    seed: int = 0,
) -> Interval:
    """Percentile bootstrap of the difference of two families' seed-mean success rates, keeping both pairings.

    Training seeds pair by index (the i-th seed of each family), episodes by position within a seed (the same
    initial state). A resample draws seed indices jointly, then the same episode indices for both families.

    Args:
        first_by_seed: k arrays, each (n_s,) bool, the first family's outcomes per training seed.
        second_by_seed: k arrays, each (n_s,) bool, the second family's outcomes, same lengths as the first's.
        level: confidence level in (0, 1).
        resamples: bootstrap resamples.
        seed: seed of the resampling generator.

    Returns:
        estimate: observed difference of seed means (first minus second); low, high: percentile bounds.
    """
    estimate, draws = _paired_bootstrap_draws(first_by_seed, second_by_seed, resamples, seed)
    return _percentile_interval(estimate, draws, level)


@dataclass(frozen=True)
class MeanComparison:
    """Two samples of a continuous per-episode measure (e.g. an insertion offset in mm) side by side.

    Attributes:
        first_mean: mean of the first sample.
        second_mean: mean of the second sample.
        first_variance: sample variance (n - 1) of the first.
        second_variance: sample variance (n - 1) of the second.
        difference: first mean minus second mean, with Welch's t interval.
        p_value: Welch's two-sided t-test of equal means.
        variance_p_value: Brown-Forsythe (median-centred Levene) test of equal variances; None when a sample has
            fewer than 3 values (with 2, both deviations from the median are equal, so the test degenerates to p = 0).
    """

    first_mean: float
    second_mean: float
    first_variance: float
    second_variance: float
    difference: Interval
    p_value: float
    variance_p_value: float | None


def compare_means(first: np.ndarray, second: np.ndarray, level: float = 0.95) -> MeanComparison | None:
    """Welch's comparison of two samples' means, and a test of their variances; NaNs are left out.

    Args:
        first: (N1,) float measurements.
        second: (N2,) float measurements.
        level: confidence level of the difference's interval.

    Returns:
        None when either sample has fewer than 2 finite values.
    """
    first = np.asarray(first, dtype=np.float64)
    second = np.asarray(second, dtype=np.float64)
    first, second = first[np.isfinite(first)], second[np.isfinite(second)]
    if first.size < 2 or second.size < 2:
        return None
    test = stats.ttest_ind(first, second, equal_var=False)
    interval = test.confidence_interval(confidence_level=level)
    return MeanComparison(
        first_mean=float(first.mean()),
        second_mean=float(second.mean()),
        first_variance=float(first.var(ddof=1)),
        second_variance=float(second.var(ddof=1)),
        difference=Interval(float(first.mean() - second.mean()), float(interval.low), float(interval.high)),
        p_value=float(test.pvalue),
        variance_p_value=(
            float(stats.levene(first, second, center="median").pvalue) if min(first.size, second.size) >= 3 else None
        ),
    )


def kaplan_meier(steps: np.ndarray, success: np.ndarray, max_steps: int) -> KaplanMeierCurve:
    """Kaplan-Meier curve of steps to success: failed episodes are right-censored at the step they stopped.

    Args:
        steps: (N,) int, steps each episode ran, in [1, max_steps].
        success: (N,) bool, whether the episode succeeded (at its last step).
        max_steps: the episode horizon; the curve ends there.

    Returns:
        The cumulative success share as a step function (see ``KaplanMeierCurve``); all zeros without successes,
        reaching 1 when no episode failed.
    """
    step_counts = np.asarray(steps)
    succeeded = _outcomes(success, "success")
    if step_counts.shape != succeeded.shape or not np.issubdtype(step_counts.dtype, np.integer):
        raise ValueError("steps must be integers of the same shape as success")
    if step_counts.size == 0:
        raise ValueError("kaplan_meier needs at least one episode")
    if np.any(step_counts < 1) or np.any(step_counts > max_steps):
        raise ValueError(f"steps must lie in [1, max_steps={max_steps}]")
    event_steps = np.unique(step_counts[succeeded])
    shares = np.zeros(0)
    if event_steps.size:
        censored = stats.CensoredData(uncensored=step_counts[succeeded], right=step_counts[~succeeded])
        shares = 1.0 - stats.ecdf(censored).sf.evaluate(event_steps)
    curve_steps = np.concatenate([[0], event_steps]).astype(np.int64)
    curve_shares = np.concatenate([[0.0], shares])
    if curve_steps[-1] < max_steps:
        curve_steps = np.append(curve_steps, max_steps)
        curve_shares = np.append(curve_shares, curve_shares[-1])
    return KaplanMeierCurve(curve_steps, curve_shares)


def logrank(
    first_steps: np.ndarray, first_success: np.ndarray, second_steps: np.ndarray, second_success: np.ndarray
) -> float:
    """Two-sided log-rank p-value comparing steps to success; failures are right-censored at their step count.

    Args:
        first_steps: (N1,) int, steps each of the first family's episodes ran.
        first_success: (N1,) bool, whether each succeeded.
        second_steps: (N2,) int, the same for the second family.
        second_success: (N2,) bool.

    Returns:
        The p-value; 1.0 when neither family has a success (the curves are identical at zero).
    """
    samples, any_success = [], False
    for steps, success in ((first_steps, first_success), (second_steps, second_success)):
        step_counts = np.asarray(steps)
        succeeded = _outcomes(success, "success")
        if step_counts.shape != succeeded.shape or step_counts.size == 0:
            raise ValueError("steps and success must be non-empty and of the same shape")
        samples.append(stats.CensoredData(uncensored=step_counts[succeeded], right=step_counts[~succeeded]))
        any_success = any_success or bool(succeeded.any())
    if not any_success:
        return 1.0
    return float(stats.logrank(samples[0], samples[1], alternative="two-sided").pvalue)


def episodes_to_decide(
    first_rate: float,
    second_rate: float,
    discordant_share: float,
    alpha: float = 0.05,
    power: float = 0.8,
    margin: float = 0.05,
) -> int | None:
    """Paired episodes per family after which a verdict becomes likely, if the observed rates are the true ones.

    For a difference d != 0: Connor's (1987) McNemar sample size
    n = (z_{1-alpha/2} sqrt(psi) + z_{power} sqrt(psi - d^2))^2 / d^2 with psi the discordant share.
    For |d| < margin: the two one-sided tests of equivalence at ``margin`` under the normal approximation with the
    per-pair variance psi - d^2, n = (z_{1-alpha} + z) ^ 2 (psi - d^2) / (margin - |d|)^2, with z = z_{power} for
    d != 0 and z_{(1+power)/2} for d = 0 (Chow, Shao & Wang 2008). The smaller of the applicable counts is returned,
    so a tiny difference asks for the equivalence count rather than an enormous superiority one.

    Args:
        first_rate: observed success share of the first family.
        second_rate: observed success share of the second family.
        discordant_share: psi, the share of episodes where exactly one family succeeded (>= |d|).
        alpha: significance level (two-sided for the difference, per side for equivalence).
        power: probability of reaching the verdict.
        margin: equivalence margin as a share, > 0.

    Returns:
        The episode count rounded up, or None when psi = 0: with no discordant episode there is no estimate of the
        per-pair variance, and d = 0 with zero variance would claim that no episode at all is needed.
    """
    for name, value in (
        ("first_rate", first_rate),
        ("second_rate", second_rate),
        ("discordant_share", discordant_share),
    ):
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"{name}={value} must lie in [0, 1]")
    _check_open_unit("alpha", alpha)
    _check_open_unit("power", power)
    if margin <= 0:
        raise ValueError(f"margin={margin} must be > 0")
    difference = first_rate - second_rate
    if abs(difference) < 1e-12:
        difference = 0.0
    if abs(difference) > discordant_share + 1e-12:
        raise ValueError(f"a difference of {difference:.4f} needs a discordant share >= |d|, got {discordant_share}")
    if discordant_share == 0:
        return None
    variance = max(0.0, discordant_share - difference**2)
    counts = []
    if difference != 0:
        z_alpha = stats.norm.ppf(1.0 - alpha / 2.0)
        z_power = stats.norm.ppf(power)
        counts.append((z_alpha * math.sqrt(discordant_share) + z_power * math.sqrt(variance)) ** 2 / difference**2)
    if abs(difference) < margin:
        z_power = stats.norm.ppf(power if difference != 0 else (1.0 + power) / 2.0)
        counts.append((stats.norm.ppf(1.0 - alpha) + z_power) ** 2 * variance / (margin - abs(difference)) ** 2)
    return max(1, math.ceil(min(counts)))


def compare_pair(
    first_name: str,
    first_by_seed: Mapping[int, np.ndarray],
    second_name: str,
    second_by_seed: Mapping[int, np.ndarray],
    *,
    first_steps_by_seed: Mapping[int, np.ndarray] | None = None,
    second_steps_by_seed: Mapping[int, np.ndarray] | None = None,
    max_steps: int | None = None,
    margin: float = 0.05,
    alpha: float = 0.05,
    level: float = 0.95,
    resamples: int = 4000,
    seed: int = 0,
) -> PairComparison:
    """Compare two families on one task: intervals, tests and a verdict as if this were the only pair.

    Training seeds with the same number pair first; the remaining ones pair by sorted position (said in
    ``pairing_note``), and seeds left over are not used. Within a seed pair, episodes pair by position and are
    truncated to the shorter list. Run ``decide_pairs`` over all pairs of a run to adjust for multiplicity.

    Args:
        first_name: name of the first family.
        first_by_seed: training seed -> (n_s,) bool outcomes over the task's episode seeds, in their shared order.
        second_name: name of the second family.
        second_by_seed: the same for the second family.
        first_steps_by_seed: training seed -> (n_s,) int steps per episode; with ``second_steps_by_seed`` enables the
            log-rank test and the Kaplan-Meier curves.
        second_steps_by_seed: the same for the second family.
        max_steps: episode horizon for the curves; the largest step seen when None.
        margin: equivalence margin as a share (0.05 = 5 points).
        alpha: significance level; the equivalence intervals are at 1 - 2 alpha.
        level: confidence level of the reported intervals.
        resamples: resamples of the two-level bootstrap.
        seed: seed of the bootstrap's generator.

    Raises:
        ValueError: when no training seed pairs, no episode pairs, or only one family's steps are given.
    """
    _check_open_unit("alpha", alpha)
    if (first_steps_by_seed is None) != (second_steps_by_seed is None):
        raise ValueError("give steps for both families or for neither")
    seed_pairs, note = _pair_seeds(first_name, first_by_seed, second_name, second_by_seed)
    first_runs, second_runs, first_steps, second_steps = [], [], [], []
    truncated, empty = False, []
    for first_seed, second_seed in seed_pairs:
        first_values = _outcomes(first_by_seed[first_seed], first_name)
        second_values = _outcomes(second_by_seed[second_seed], second_name)
        length = min(first_values.size, second_values.size)
        truncated |= first_values.size != second_values.size
        if length == 0:
            empty.append(f"{first_seed} with {second_seed}")
            continue
        first_runs.append(first_values[:length])
        second_runs.append(second_values[:length])
        if first_steps_by_seed is not None and second_steps_by_seed is not None:
            first_steps.append(_steps_of(first_steps_by_seed, first_seed, first_values.size, first_name)[:length])
            second_steps.append(_steps_of(second_steps_by_seed, second_seed, second_values.size, second_name)[:length])
    if not first_runs:
        raise ValueError(f"{first_name} and {second_name} share no evaluated episode: nothing to compare")
    if truncated:
        note = _join_notes(note, "episodes truncated to the shorter list of each seed pair")
    if empty:
        note = _join_notes(note, f"seed pairs without episodes left out: {', '.join(empty)}")
    first_all, second_all = np.concatenate(first_runs), np.concatenate(second_runs)
    mcnemar = mcnemar_exact(first_all, second_all)
    estimate, draws = _paired_bootstrap_draws(first_runs, second_runs, resamples, seed)
    steps_results = _steps_comparison(first_all, second_all, first_steps, second_steps, max_steps)
    first_seed_rates = tuple(float(run.mean()) for run in first_runs)
    second_seed_rates = tuple(float(run.mean()) for run in second_runs)
    comparison = PairComparison(
        first=first_name,
        second=second_name,
        episodes=int(first_all.size),
        seeds=len(first_runs),
        first_rate=float(first_all.mean()),
        second_rate=float(second_all.mean()),
        difference=newcombe_paired_difference(first_all, second_all, level),
        bootstrap_difference=_percentile_interval(estimate, draws, level),
        equivalence_difference=newcombe_paired_difference(first_all, second_all, 1.0 - 2.0 * alpha),
        equivalence_bootstrap_difference=_percentile_interval(estimate, draws, 1.0 - 2.0 * alpha),
        seed_difference=paired_seed_interval(first_seed_rates, second_seed_rates, level),
        first_seed_rates=first_seed_rates,
        second_seed_rates=second_seed_rates,
        mcnemar=mcnemar,
        seed_p_value=seed_permutation_test(first_seed_rates, second_seed_rates),
        logrank_p_value=steps_results[0],
        first_steps_curve=steps_results[1],
        second_steps_curve=steps_results[2],
        adjusted_p_value=mcnemar.p_value,
        level=level,
        alpha=alpha,
        margin=margin,
        verdict="",
        explanation="",
        pairing_note=note,
    )
    return _with_verdict(comparison, mcnemar.p_value, margin, comparisons=1)


def _seed_spread_text(comparison: PairComparison) -> str:
    """Why the across-seed interval blocks a verdict: seeds pointing both ways, or a spread too wide for so few."""
    differences = [first - second for first, second in zip(comparison.first_seed_rates, comparison.second_seed_rates)]
    if any(difference > 0 for difference in differences) and any(difference < 0 for difference in differences):
        return "the training seeds disagree"
    return f"the interval across {len(differences)} training seeds is wide"


def decide_pairs(comparisons: Sequence[PairComparison], margin: float, alpha: float = 0.05) -> list[PairComparison]:
    """Holm-adjust the McNemar p-values over every pair of a run, then give each pair its verdict.

    A family is "better" when the Holm-adjusted McNemar p is below ``alpha`` and the Newcombe, the two-level
    bootstrap and (with 2 or more seed pairs) the across-seed t intervals of the difference all exclude 0 on its
    side. The pair is "on par within ±margin" when the same three intervals at 1 - 2 alpha lie inside
    (-margin, +margin), the two one-sided tests of equivalence. Otherwise it is "not decided", and the explanation
    says what would likely decide: a number of paired episodes per family at the observed rates, or more training
    seeds when the episodes decide but the seeds disagree.

    The across-seed t interval is there because the percentile bootstrap over few seeds is too narrow: in
    simulation (0.8 against 0.8, 3 seeds of 67 episodes, seed rates Beta with sd 9 points) McNemar with Newcombe
    and the bootstrap alone called a winner in 14% of runs, with the t interval in 3%.

    Args:
        comparisons: results of ``compare_pair``, all computed at this ``alpha``.
        margin: equivalence margin as a share.
        alpha: family-wise significance level.

    Returns:
        The comparisons in the same order with ``adjusted_p_value``, ``margin``, ``verdict`` and ``explanation``
        filled in.
    """
    for comparison in comparisons:
        if not math.isclose(comparison.alpha, alpha):
            raise ValueError(
                f"{comparison.first} vs {comparison.second} was compared at alpha={comparison.alpha}, not {alpha}: "
                "its equivalence intervals would not match"
            )
    adjusted = holm_adjust([comparison.mcnemar.p_value for comparison in comparisons])
    return [
        _with_verdict(comparison, p_value, margin, comparisons=len(comparisons))
        for comparison, p_value in zip(comparisons, adjusted)
    ]


def comparison_table(comparisons: Sequence[PairComparison]) -> pd.DataFrame:
    """One row per pair of families, every cell a human-readable string; differences in percentage points."""
    rows = []
    for comparison in comparisons:
        rows.append(
            {
                "comparison": f"{comparison.first} vs {comparison.second}",
                "paired episodes": str(comparison.episodes),
                "training seeds": str(comparison.seeds),
                "success": f"{comparison.first_rate:.1%} vs {comparison.second_rate:.1%}",
                f"difference, {comparison.level:.0%} CI (points)": _interval_text(comparison.difference),
                f"seed bootstrap, {comparison.level:.0%} CI (points)": _interval_text(comparison.bootstrap_difference),
                f"across seeds, {comparison.level:.0%} t CI (points)": (
                    _interval_text(comparison.seed_difference) if comparison.seed_difference is not None else "n/a"
                ),
                "McNemar p (only first / only second)": (
                    f"{_p_text(comparison.mcnemar.p_value)} "
                    f"({comparison.mcnemar.first_only} / {comparison.mcnemar.second_only})"
                ),
                "Holm p": _p_text(comparison.adjusted_p_value),
                "seed permutation p": _p_text(comparison.seed_p_value),
                "log-rank p": _p_text(comparison.logrank_p_value),
                "verdict": comparison.verdict,
                "note": comparison.pairing_note,
            }
        )
    return pd.DataFrame(rows)


def _with_verdict(comparison: PairComparison, adjusted_p: float, margin: float, comparisons: int) -> PairComparison:
    """The comparison with its verdict and explanation at a given adjusted p-value (see ``decide_pairs``)."""
    if margin <= 0:
        raise ValueError(f"margin={margin} must be > 0")
    alpha = comparison.alpha
    seed_equivalence = paired_seed_interval(comparison.first_seed_rates, comparison.second_seed_rates, 1 - 2 * alpha)
    intervals = [comparison.difference, comparison.bootstrap_difference, comparison.seed_difference]
    equivalence_intervals = [
        comparison.equivalence_difference,
        comparison.equivalence_bootstrap_difference,
        seed_equivalence,
    ]
    significant = adjusted_p < alpha
    first_ahead = significant and all(interval.low > 0 for interval in intervals if interval is not None)
    second_ahead = significant and all(interval.high < 0 for interval in intervals if interval is not None)
    equivalent = all(interval.inside(margin) for interval in equivalence_intervals if interval is not None)
    margin_text = f"±{100.0 * margin:g} points"
    summary = _summary_text(comparison, adjusted_p)
    if first_ahead or second_ahead:
        leader = comparison.first if first_ahead else comparison.second
        verdict = f"{leader} better"
        explanation = f"{summary}, so {leader} is better."
    elif equivalent:
        verdict = f"on par within {margin_text}"
        equivalence_text = ", ".join(
            _interval_bounds(interval) for interval in equivalence_intervals if interval is not None
        )
        explanation = (
            f"{summary}; the {1 - 2 * alpha:.0%} intervals ({equivalence_text}) lie within {margin_text}, "
            "so the two are on par."
        )
    else:
        verdict = "not decided"
        episodes_decide = significant and (comparison.difference.low > 0 or comparison.difference.high < 0)
        episodes_decide = episodes_decide or comparison.equivalence_difference.inside(margin)
        if episodes_decide and comparison.seeds > 1:
            outlook = f"{_seed_spread_text(comparison)}, so more training seeds rather than episodes would decide"
        else:
            needed = episodes_to_decide(
                comparison.first_rate,
                comparison.second_rate,
                (comparison.mcnemar.first_only + comparison.mcnemar.second_only) / comparison.episodes,
                # Holm's strictest step, so the count holds for whichever rank this pair's p-value takes.
                alpha=alpha / comparisons,
                margin=margin,
            )
            outlook = (
                f"about {needed} paired episodes per family would likely decide at these rates "
                "(more if training seeds vary)"
                if needed is not None
                else "no episode count can be estimated because no episode went differently"
            )
        explanation = f"{summary}; the data does not rank the two: {outlook}."
    return replace(comparison, adjusted_p_value=adjusted_p, margin=margin, verdict=verdict, explanation=explanation)


def _summary_text(comparison: PairComparison, adjusted_p: float) -> str:
    """The rates, the difference with its intervals and the p-values, as the first half of a sentence."""
    seeds = "1 training seed" if comparison.seeds == 1 else f"{comparison.seeds} training seeds"
    intervals = [
        f"{comparison.level:.0%} CI {_interval_bounds(comparison.difference)}",
        f"seed bootstrap {_interval_bounds(comparison.bootstrap_difference)}",
    ]
    if comparison.seed_difference is not None:
        intervals.append(f"across seeds {_interval_bounds(comparison.seed_difference)}")
    else:
        intervals.append("training-seed spread not measured")
    return (
        f"{comparison.first} {comparison.first_rate:.1%} vs {comparison.second} {comparison.second_rate:.1%} "
        f"over {comparison.episodes} paired episodes from {seeds}: difference "
        f"{_signed_points(comparison.difference.estimate)} points ({'; '.join(intervals)}), "
        f"McNemar {_p_phrase(comparison.mcnemar.p_value)} (Holm-adjusted {_p_phrase(adjusted_p)})"
    )


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
    """One training seed's (n_s,) steps per episode, checked to match its outcomes."""
    if seed not in steps_by_seed:
        raise ValueError(f"{name}: no steps for training seed {seed}")
    steps = np.asarray(steps_by_seed[seed])
    if steps.shape != (episodes,):
        raise ValueError(f"{name}: training seed {seed} has {episodes} outcomes but steps of shape {steps.shape}")
    return steps


def _steps_comparison(
    first_all: np.ndarray,
    second_all: np.ndarray,
    first_steps: list[np.ndarray],
    second_steps: list[np.ndarray],
    max_steps: int | None,
) -> tuple[float | None, KaplanMeierCurve | None, KaplanMeierCurve | None]:
    """Log-rank p-value and both Kaplan-Meier curves, or Nones when no steps were given."""
    if not first_steps:
        return None, None, None
    first_counts, second_counts = np.concatenate(first_steps), np.concatenate(second_steps)
    horizon = max_steps if max_steps is not None else int(max(first_counts.max(), second_counts.max()))
    return (
        logrank(first_counts, first_all, second_counts, second_all),
        kaplan_meier(first_counts, first_all, horizon),
        kaplan_meier(second_counts, second_all, horizon),
    )


def _paired_bootstrap_draws(
    first_by_seed: Sequence[np.ndarray], second_by_seed: Sequence[np.ndarray], resamples: int, seed: int
) -> tuple[float, np.ndarray]:
    """Observed difference of seed means and its (resamples,) float64 bootstrap draws."""
    first = [_outcomes(values, "first_by_seed") for values in first_by_seed]
    second = [_outcomes(values, "second_by_seed") for values in second_by_seed]
    if not first or len(first) != len(second):
        raise ValueError(
            f"need the same number (>= 1) of training seeds per family, got {len(first)} and {len(second)}"
        )
    if any(a.size != b.size for a, b in zip(first, second)):
        raise ValueError("paired training seeds need the same number of episodes")
    episodes = np.array([values.size for values in first])
    first_only = np.array([np.sum(a & ~b) for a, b in zip(first, second)])
    second_only = np.array([np.sum(~a & b) for a, b in zip(first, second)])
    # Concordant episodes do not move the difference, so three cells suffice: first only, second only, the rest.
    cell_shares = np.stack([first_only, second_only, episodes - first_only - second_only], axis=1) / episodes[:, None]
    draws = _bootstrap_seed_means(cell_shares, episodes, np.array([1.0, -1.0, 0.0]), resamples, seed)
    return float(np.mean((first_only - second_only) / episodes)), draws


def _bootstrap_seed_means(
    cell_shares: np.ndarray, episodes: np.ndarray, cell_values: np.ndarray, resamples: int, seed: int
) -> np.ndarray:
    """Two-level bootstrap draws of the mean over seeds of a per-seed mean of episode values.

    Drawing n_s episodes with replacement from a seed and counting them per outcome cell is a multinomial draw with
    the seed's cell shares, so the episode level is sampled as counts directly.

    Args:
        cell_shares: (k, C) float64, share of each seed's episodes in each outcome cell; rows sum to 1.
        episodes: (k,) int, episodes per seed.
        cell_values: (C,) float64, the value an episode in each cell contributes.
        resamples: bootstrap resamples R >= 1.
        seed: seed of the generator.

    Returns:
        (R,) float64 draws.
    """
    if resamples < 1:
        raise ValueError(f"resamples={resamples} must be >= 1")
    rng = np.random.default_rng(seed)
    seeds = episodes.size
    if seeds == 1:
        drawn = np.zeros((resamples, 1), dtype=np.int64)
    else:
        drawn = rng.integers(0, seeds, size=(resamples, seeds))  # (R, k)
    counts = rng.multinomial(episodes[drawn], cell_shares[drawn])  # (R, k, C)
    per_seed = counts @ cell_values / episodes[drawn]  # (R, k)
    return per_seed.mean(axis=1)


def _percentile_interval(estimate: float, draws: np.ndarray, level: float) -> Interval:
    """Percentile interval of bootstrap draws around a given point estimate."""
    _check_open_unit("level", level)
    low, high = np.quantile(draws, [(1.0 - level) / 2.0, (1.0 + level) / 2.0])
    return Interval(estimate, float(low), float(high))


def _newcombe_phi(both: int, first_only: int, second_only: int, neither: int) -> float:
    """Newcombe's continuity-corrected phi of a paired 2x2 table (method 10); 0 when a margin is empty."""
    episodes = both + first_only + second_only + neither
    denominator = (both + first_only) * (second_only + neither) * (both + second_only) * (first_only + neither)
    if denominator == 0:
        return 0.0
    numerator = float(both * neither - first_only * second_only)
    if numerator > episodes / 2:
        numerator -= episodes / 2
    elif numerator >= 0:
        numerator = 0.0
    return numerator / math.sqrt(denominator)


def _paired_outcomes(first: np.ndarray, second: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both outcome arrays as (N,) bool, N >= 1, checked to pair."""
    first, second = _outcomes(first, "first"), _outcomes(second, "second")
    if first.shape != second.shape:
        raise ValueError(f"paired outcomes need the same length, got {first.size} and {second.size}")
    if first.size == 0:
        raise ValueError("paired outcomes are empty")
    return first, second


def _outcomes(values: np.ndarray | Sequence[bool], name: str) -> np.ndarray:
    """A flat bool array from bools or 0/1 numbers."""
    array = np.asarray(values)
    if array.ndim != 1:
        raise ValueError(f"{name}: outcomes must be one flat array per run, got shape {array.shape}")
    if array.dtype != np.bool_:
        if array.size and not np.all((array == 0) | (array == 1)):
            raise ValueError(f"{name}: outcomes must be booleans or 0/1")
        array = array.astype(bool)
    return array


def _check_open_unit(name: str, value: float) -> None:
    """Refuse a probability-like setting outside (0, 1)."""
    if not 0.0 < value < 1.0:
        raise ValueError(f"{name}={value} must lie in (0, 1)")


def _join_notes(first: str, second: str) -> str:
    return f"{first}; {second}" if first else second


def _points(share: float) -> str:
    return f"{100.0 * share:.1f}"


def _signed_points(share: float) -> str:
    return f"{100.0 * share:+.1f}"


def _interval_bounds(interval: Interval) -> str:
    return f"{_signed_points(interval.low)} to {_signed_points(interval.high)}"


def _interval_text(interval: Interval) -> str:
    return f"{_signed_points(interval.estimate)} [{_signed_points(interval.low)}, {_signed_points(interval.high)}]"


def _p_phrase(p_value: float) -> str:
    return "p < 0.0001" if p_value < 1e-4 else f"p = {p_value:.2g}"


def _p_text(p_value: float | None) -> str:
    if p_value is None:
        return "n/a"
    return "<0.0001" if p_value < 1e-4 else f"{p_value:.2g}"
