"""Episode-level statistics of trained networks: intervals, paired tests, clustering and steps to success.

Everything here describes the networks that were evaluated, on the episodes they ran: the Wilson interval of one
network's rate, Newcombe's interval and McNemar's test of two networks on the same initial states, the intra-class
correlation of success within training seeds, Welch's comparison of a per-episode measure, and Kaplan-Meier curves of
steps to success. Statements about a policy *family* take the training seed as their unit and live in
`carp.reporting.seed_inference` and `carp.reporting.verdicts`.

Sources (formulas re-derived from the papers, not copied from any implementation):
    - Wilson (1927): score interval of one proportion.
    - Newcombe (1998), "Improved confidence intervals for the difference between binomial proportions based on
      paired data", Statistics in Medicine 17:2635-2650, method 10 (Wilson margins, continuity-corrected phi).
    - McNemar (1947), exact form: a binomial test on the discordant pairs.
    - Holm (1979): step-down family-wise adjustment.
    - Ridout, Demetrio & Firth (1999), "Estimating intraclass correlation for binary data", Biometrics 55:137-148:
      the ANOVA estimator of the intra-class correlation; Kish (1965): design effect 1 + (m - 1) rho.
    - Kaplan & Meier (1958) and the log-rank test, through ``scipy.stats.ecdf`` and ``scipy.stats.logrank``.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

# The evaluate stage's own interval and quantile: kept in carp.evaluation so that the report's statistics are no
# dependency of the evaluations (a change here reruns the report alone).
from carp.evaluation.metrics import wilson_interval


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
    succeeded = as_outcomes(success, "success")
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
        succeeded = as_outcomes(success, "success")
        if step_counts.shape != succeeded.shape or step_counts.size == 0:
            raise ValueError("steps and success must be non-empty and of the same shape")
        samples.append(stats.CensoredData(uncensored=step_counts[succeeded], right=step_counts[~succeeded]))
        any_success = any_success or bool(succeeded.any())
    if not any_success:
        return 1.0
    return float(stats.logrank(samples[0], samples[1], alternative="two-sided").pvalue)


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
    first, second = as_outcomes(first, "first"), as_outcomes(second, "second")
    if first.shape != second.shape:
        raise ValueError(f"paired outcomes need the same length, got {first.size} and {second.size}")
    if first.size == 0:
        raise ValueError("paired outcomes are empty")
    return first, second


def as_outcomes(values: np.ndarray | Sequence[bool], name: str) -> np.ndarray:
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
