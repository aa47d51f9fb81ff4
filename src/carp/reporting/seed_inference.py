"""Inference about a policy *family* from a few trained networks: the training seed is the unit.

A family's success rate is a mean over two random draws: the training seed (which network the recipe produced) and
the initial state (which episode the simulator drew). A report that pools every seed's episodes and treats them as
independent measures the few networks it trained, not the family: with three seeds whose rates spread by a few
points, pooled intervals cover the family's rate far below their label. Here the estimate is the mean over training
seeds of each seed's mean, and its standard error comes from the seeds' own spread, with a Student-t quantile on
``seeds - 1`` degrees of freedom (the summary-statistics analysis of a design with few clusters).

Two refinements keep it honest with 2 to 10 seeds:

- **Shared initial states.** carp evaluates every training seed on the same episode seeds (a crossed design).
  Initial states that all of a family's networks find hard (or, for a difference, states that one family finds hard
  and the other does not) then move every seed's mean the same way, which the spread across seeds cannot show. The
  variance of the estimate is therefore estimated from the two-way layout (seeds x states) as
  ``s_seeds^2 / n + s_states^2 / m - MS_residual / (n m)``, the method-of-moments variance of a grand mean under
  random seed and state effects; with distinct states per seed (a nested design) it is ``s_seeds^2 / n``.
- **A floor.** With three seeds the sample spread is itself very noisy and can be zero (three seeds at 50/50); the
  variance never goes below what the episodes alone would give if seeds and states did not matter, computed with one
  pseudo-episode at each end of the value range (so 50/50 successes still has a width).

The degrees of freedom stay ``seeds - 1`` whatever the state term adds, which is conservative when the state term
dominates. ``tests/reporting/test_calibration.py`` checks the coverage and error rates these give against simulated
families with known truth, and ``benchmarks/verdict_calibration.py`` prints the full table.

Sources (formulas re-derived, not copied): Hayes & Moulton, "Cluster Randomised Trials" (t on cluster summaries when
clusters are few); Searle, Casella & McCulloch, "Variance Components" (expected mean squares of the two-way random
model); Schuirmann (1987) for the two one-sided tests of equivalence.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

from carp.reporting.statistics import Interval


@dataclass(frozen=True)
class SeedLevelEstimate:
    """A family-level mean (a success rate, or a difference of two families' rates) estimated over training seeds.

    Attributes:
        estimate: the mean over training seeds of each seed's mean over its episodes.
        standard_error: its estimated standard error (seed spread, the shared-state term and the floor).
        seeds: training seeds n (degrees of freedom n - 1).
        episodes_per_seed: the smallest number of episodes of a seed.
        shared_states: whether every seed ran the same initial states (the state term is in the error).
        low_bound, high_bound: the range the quantity can take (e.g. 0 and 1 for a rate); intervals are clipped to it.
    """

    estimate: float
    standard_error: float
    seeds: int
    episodes_per_seed: int
    shared_states: bool
    low_bound: float
    high_bound: float

    @property
    def degrees_of_freedom(self) -> int:
        """Student-t degrees of freedom of the interval and tests: seeds - 1."""
        return self.seeds - 1

    def interval(self, level: float) -> Interval:
        """Two-sided Student-t interval at `level`, clipped to the quantity's range."""
        _check_open_unit("level", level)
        half = float(stats.t.ppf(0.5 + level / 2.0, self.degrees_of_freedom)) * self.standard_error
        return Interval(
            self.estimate, max(self.low_bound, self.estimate - half), min(self.high_bound, self.estimate + half)
        )

    def p_value(self) -> float:
        """Two-sided p-value of the hypothesis that the quantity is 0 (for a difference: no difference)."""
        statistic = self.estimate / self.standard_error
        return float(min(1.0, 2.0 * stats.t.sf(abs(statistic), self.degrees_of_freedom)))

    def equivalence_p_value(self, margin: float) -> float:
        """p-value of the two one-sided tests that the quantity lies within (-margin, +margin).

        The larger of the p-values of "the quantity is <= -margin" and "the quantity is >= +margin"; below alpha
        exactly when the 1 - 2 alpha interval lies inside the margin.
        """
        if margin <= 0:
            raise ValueError(f"margin={margin} must be > 0")
        below = stats.t.sf((self.estimate + margin) / self.standard_error, self.degrees_of_freedom)
        above = stats.t.cdf((self.estimate - margin) / self.standard_error, self.degrees_of_freedom)
        return float(max(below, above))


def seed_level_estimate(
    values_by_seed: Sequence[np.ndarray],
    *,
    shared_states: bool,
    value_range: tuple[float, float] = (0.0, 1.0),
) -> SeedLevelEstimate:
    """Estimate a family-level mean from per-episode values grouped by training seed.

    Args:
        values_by_seed: one (m_s,) float array per training seed: a success (0/1) per episode for a rate, or the
            paired difference (-1, 0, 1) per episode for a difference of two families. With ``shared_states`` every
            array has the same length m and column j is the same initial state in every seed.
        shared_states: whether every seed ran the same initial states (crossed design); False for distinct states
            per seed (nested design).
        value_range: (low, high) the values can take: (0, 1) for successes, (-1, 1) for paired differences.

    Raises:
        ValueError: fewer than 2 seeds, an empty seed, or seeds of different lengths with ``shared_states``.
    """
    arrays = [np.asarray(values, dtype=np.float64).ravel() for values in values_by_seed]
    if len(arrays) < 2:
        raise ValueError(f"a family-level estimate needs >= 2 training seeds, got {len(arrays)}")
    if any(array.size == 0 for array in arrays):
        raise ValueError("a training seed has no episodes")
    low, high = value_range
    seeds = len(arrays)
    seed_means = np.array([array.mean() for array in arrays])
    variance = seed_means.var(ddof=1) / seeds
    episodes = min(array.size for array in arrays)
    if shared_states:
        if len({array.size for array in arrays}) != 1:
            raise ValueError("with shared states every training seed needs the same episodes")
        table = np.stack(arrays)  # (n, m)
        state_means = table.mean(axis=0)
        residual = table - seed_means[:, None] - state_means[None, :] + table.mean()
        residual_mean_square = (residual**2).sum() / ((seeds - 1) * (episodes - 1)) if episodes > 1 else 0.0
        if episodes > 1:
            variance += state_means.var(ddof=1) / episodes - residual_mean_square / (seeds * episodes)
    # What the episodes alone would give: each seed's sampling variance, with one pseudo-episode at each end of the
    # range so that a seed of all successes (or all ties) still counts as uncertain.
    floor = sum(np.var(np.concatenate([array, [low, high]])) / (array.size + 2) for array in arrays) / seeds**2
    return SeedLevelEstimate(
        estimate=float(seed_means.mean()),
        standard_error=math.sqrt(max(variance, floor)),
        seeds=seeds,
        episodes_per_seed=int(episodes),
        shared_states=shared_states,
        low_bound=low,
        high_bound=high,
    )


def seed_mean_interval(
    per_seed: Sequence[float], level: float = 0.95, value_range: tuple[float, float] = (-math.inf, math.inf)
) -> Interval:
    """The mean over training seeds of a continuous per-seed figure, with a Student-t interval over the seeds.

    The continuous counterpart of `seed_level_estimate` for a figure each seed gives once, measured on data every seed
    shares (a policy's action error on the task's held-out episodes): the estimate is the mean of the seeds' values,
    its standard error their sample standard deviation over ``sqrt(n)``, the quantile Student's t on ``n - 1``
    degrees of freedom. The shared data are fixed, so the interval is about the family's figure on them.

    Args:
        per_seed: one value per training seed, at least two.
        level: two-sided confidence level in (0, 1).
        value_range: the range the figure can take (an error: from 0); the interval is clipped to it.

    Raises:
        ValueError: fewer than two seeds, a value that is not finite, or a level outside (0, 1).
    """
    _check_open_unit("level", level)
    values = np.asarray(per_seed, dtype=np.float64)
    if values.ndim != 1 or len(values) < 2 or not np.isfinite(values).all():
        raise ValueError(f"a t interval over seeds needs two finite values or more, got {values.tolist()}")
    mean = float(values.mean())
    half = float(stats.t.ppf(0.5 + level / 2.0, len(values) - 1)) * float(values.std(ddof=1)) / math.sqrt(len(values))
    low, high = value_range
    return Interval(mean, float(max(low, mean - half)), float(min(high, mean + half)))


def seeds_to_decide(
    estimate: SeedLevelEstimate, margin: float, alpha: float, power: float = 0.8, most: int = 100
) -> int | None:
    """Training seeds per family after which a verdict on a difference becomes likely, if the estimate is the truth.

    The per-seed standard deviation is taken as observed (``standard_error * sqrt(seeds)``); a difference is likely
    decided at n seeds when ``(t_{1 - alpha/2} + t_power) * sd / sqrt(n) <= |estimate|`` and equivalence when
    ``(t_{1 - alpha} + t_{(1 + power)/2}) * sd / sqrt(n) <= margin - |estimate|`` (both on n - 1 degrees of
    freedom). None when neither happens within `most` seeds.
    """
    spread = estimate.standard_error * math.sqrt(estimate.seeds)
    size = abs(estimate.estimate)
    seeds = np.arange(2, most + 1)
    df = seeds - 1
    superiority = (stats.t.ppf(1 - alpha / 2, df) + stats.t.ppf(power, df)) * spread / np.sqrt(seeds)
    equivalence = (stats.t.ppf(1 - alpha, df) + stats.t.ppf((1 + power) / 2, df)) * spread / np.sqrt(seeds)
    enough = np.flatnonzero((superiority <= size) | (equivalence <= margin - size))
    return int(seeds[enough[0]]) if enough.size else None


def step_down_adjust(p_values: Sequence[float], groups: Sequence[int]) -> list[float]:
    """Holm's step-down adjusted p-values, sharpened by groups of which at most one hypothesis can be true.

    A pair of families carries two hypotheses: "no difference" and "the difference is at least the margin". They
    cannot both be true, so after any set of rejections the number of hypotheses that can still be true is the number
    of groups with a hypothesis left, not the number of hypotheses left (Shaffer 1986, method 1). With one hypothesis
    per group this is Holm's procedure. The family-wise error stays at alpha for every verdict derived from a
    rejection.

    Args:
        p_values: raw p-values.
        groups: the group of each p-value (e.g. the pair's index).

    Returns:
        Adjusted p-values in the input order, each in [0, 1].
    """
    if len(p_values) != len(groups):
        raise ValueError(f"{len(p_values)} p-values but {len(groups)} groups")
    order = sorted(range(len(p_values)), key=lambda index: p_values[index])
    remaining = {group: sum(1 for other in groups if other == group) for group in set(groups)}
    adjusted = [1.0] * len(p_values)
    running = 0.0
    for index in order:
        possible = sum(1 for count in remaining.values() if count > 0)
        running = max(running, min(1.0, possible * p_values[index]))
        adjusted[index] = running
        remaining[groups[index]] -= 1
    return adjusted


def _check_open_unit(name: str, value: float) -> None:
    if not 0.0 < value < 1.0:
        raise ValueError(f"{name}={value} must lie in (0, 1)")
