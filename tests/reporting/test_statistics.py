import math

import numpy as np
import pytest
from scipy import stats

from carp.evaluation import metrics
from carp.evaluation.metrics import Z_95, wilson_interval
from carp.reporting.statistics import (
    compare_means,
    effective_episodes,
    holm_adjust,
    intraclass_correlation,
    kaplan_meier,
    logrank,
    mcnemar_exact,
    newcombe_paired_difference,
    z_value,
)


def paired_table(both: int, first_only: int, second_only: int, neither: int) -> tuple[np.ndarray, np.ndarray]:
    """Paired outcomes with the given cell counts of the 2x2 table."""
    first = np.array([True] * (both + first_only) + [False] * (second_only + neither))
    second = np.array([True] * both + [False] * first_only + [True] * second_only + [False] * neither)
    return first, second


# Known values.


def test_wilson_interval_moved_and_still_importable_from_metrics():
    # Newcombe (1998), "Two-sided confidence intervals for the single proportion", example 81/263: 0.2553 to 0.3662.
    low, high = wilson_interval(81, 263)
    assert (low, high) == pytest.approx((0.2553, 0.3662), abs=1e-4)
    assert metrics.wilson_interval is wilson_interval
    assert z_value(0.95) == pytest.approx(Z_95, abs=1e-12)
    assert z_value(0.90) == pytest.approx(1.6448536269514722, abs=1e-12)
    with pytest.raises(ValueError, match="level"):
        z_value(1.0)


def test_mcnemar_exact_matches_the_hand_computed_binomial_tail():
    # b = 10, c = 2: two-sided P = 2 * (C(12,0) + C(12,1) + C(12,2)) / 2^12 = 2 * 79 / 4096.
    result = mcnemar_exact(*paired_table(30, 10, 2, 8))
    assert (result.first_only, result.second_only) == (10, 2)
    assert result.p_value == pytest.approx(158 / 4096, rel=1e-12)
    assert mcnemar_exact(*paired_table(2, 10, 2, 0)).p_value == pytest.approx(result.p_value)  # concordant don't count
    assert mcnemar_exact(*paired_table(5, 2, 10, 3)).p_value == pytest.approx(result.p_value)  # symmetric
    assert mcnemar_exact(*paired_table(7, 0, 0, 3)).p_value == 1.0
    with pytest.raises(ValueError, match="same length"):
        mcnemar_exact(np.ones(3, bool), np.ones(4, bool))


def test_holm_adjust_hand_example():
    # Sorted: 0.005 * 4 = 0.02, 0.01 * 3 = 0.03, 0.03 * 2 = 0.06, 0.04 * 1 = 0.04 -> running max 0.06.
    assert holm_adjust([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm_adjust([0.3, 0.6]) == pytest.approx([0.6, 0.6])
    assert holm_adjust([0.9, 0.8, 0.7]) == [1.0, 1.0, 1.0]
    assert holm_adjust([]) == []
    with pytest.raises(ValueError, match="p-values"):
        holm_adjust([0.5, 1.5])


def newcombe_from_the_published_formula(a: int, b: int, c: int, d: int, z: float) -> tuple[float, float, float]:
    """Newcombe (1998) method 10, written from the paper's formulas with Wilson limits as roots of a quadratic."""
    n = a + b + c + d

    def score_limits(successes: int) -> tuple[float, float]:
        # Wilson limits solve (p_hat - p)^2 = z^2 p (1 - p) / n for p.
        p_hat = successes / n
        roots = np.roots([1 + z * z / n, -(2 * p_hat + z * z / n), p_hat * p_hat]).real
        return float(np.min(roots)), float(np.max(roots))

    p1, p2 = (a + b) / n, (a + c) / n
    l1, u1 = score_limits(a + b)
    l2, u2 = score_limits(a + c)
    product = (a + b) * (c + d) * (a + c) * (b + d)
    numerator = a * d - b * c
    corrected = numerator - n / 2 if numerator > n / 2 else (0 if numerator >= 0 else numerator)
    phi = corrected / math.sqrt(product) if product else 0.0
    lower = p1 - p2 - math.sqrt((p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2)
    upper = p1 - p2 + math.sqrt((u1 - p1) ** 2 - 2 * phi * (u1 - p1) * (p2 - l2) + (p2 - l2) ** 2)
    return p1 - p2, lower, upper


def test_newcombe_matches_a_published_value_and_the_formula():
    # Cavo et al. (2012) table [[59, 6], [16, 80]], as published for Newcombe's square-and-add interval by the
    # contingencytables R package (Fagerland, Lydersen & Laake 2017): -0.0621 (-0.1186 to -0.0046).
    interval = newcombe_paired_difference(*paired_table(59, 6, 16, 80))
    assert (interval.estimate, interval.low, interval.high) == pytest.approx((-0.0621, -0.1186, -0.0046), abs=1e-4)
    rng = np.random.default_rng(5)
    for _ in range(20):
        cells = rng.integers(0, 30, size=4)
        if cells.sum() == 0:
            continue
        for level in (0.9, 0.95):
            interval = newcombe_paired_difference(*paired_table(*cells), level=level)
            expected = newcombe_from_the_published_formula(*(int(cell) for cell in cells), z_value(level))
            assert (interval.estimate, interval.low, interval.high) == pytest.approx(expected, abs=1e-9)


@pytest.mark.parametrize(
    "cells", [(10, 0, 0, 10), (40, 5, 3, 2), (0, 7, 0, 0), (0, 0, 9, 0), (0, 4, 4, 0), (20, 0, 0, 0), (0, 3, 1, 6)]
)
def test_newcombe_basic_properties(cells):
    interval = newcombe_paired_difference(*paired_table(*cells))
    assert -1.0 <= interval.low <= interval.estimate <= interval.high <= 1.0
    assert interval.low < interval.high


def test_newcombe_symmetric_for_identical_and_for_balanced_discordant_outcomes():
    first = np.array([True] * 30 + [False] * 10)
    identical = newcombe_paired_difference(first, first.copy())
    assert identical.estimate == 0.0 and identical.low < 0 < identical.high
    assert identical.low == pytest.approx(-identical.high)
    balanced = newcombe_paired_difference(*paired_table(0, 4, 4, 0))  # phi = -1
    assert balanced.low == pytest.approx(-balanced.high)
    all_first = newcombe_paired_difference(np.ones(15, bool), np.zeros(15, bool))
    assert all_first.estimate == 1.0 and all_first.high == 1.0 and 0.0 < all_first.low < 1.0


def test_intraclass_correlation_known_cases():
    assert intraclass_correlation([10, 10, 10], [50, 50, 50]) == 0.0  # same rate: binomial spread only
    assert intraclass_correlation([0, 50, 50, 0], [50, 50, 50, 50]) == 1.0  # all-or-nothing seeds
    # By hand: MSB = 6.8 - 5 = 1.8, MSW = (10 - 6.8) / 18, n0 = 10 -> (1.8 - 0.1778) / (1.8 + 9 * 0.1778) = 0.4771.
    assert intraclass_correlation([2, 8], [10, 10]) == pytest.approx(1.62222222 / 3.4, abs=1e-7)
    assert intraclass_correlation([7], [10]) == 0.0
    assert intraclass_correlation([0, 0, 0], [10, 20, 5]) == 0.0
    assert intraclass_correlation([20, 5], [20, 5]) == 0.0
    with pytest.raises(ValueError, match="trials"):
        intraclass_correlation([11], [10])


def test_intraclass_correlation_recovers_the_beta_binomial_rho():
    # Beta(a, b) seed rates give rho = 1 / (a + b + 1) = 0.2 for Beta(2, 2); 2000 seeds pin it to about +-0.02.
    rng = np.random.default_rng(11)
    trials = np.full(2000, 20)
    successes = rng.binomial(trials, rng.beta(2.0, 2.0, size=2000))
    assert intraclass_correlation(successes, trials) == pytest.approx(0.2, abs=0.03)


def test_effective_episodes_formula():
    assert effective_episodes(200, 50, 0.1) == pytest.approx(200 / 5.9)
    assert effective_episodes(200, 50, 0.0) == 200
    assert effective_episodes(200, 50, 1.0) == pytest.approx(4.0)  # all-or-nothing seeds: one episode per seed
    with pytest.raises(ValueError):
        effective_episodes(200, 50, 1.5)


def test_kaplan_meier_hand_computed_case():
    # At risk 5, 4, 2 at the success steps 2, 3, 5 (the failure at step 3 is still at risk there):
    # survival 4/5, 4/5 * 3/4 = 3/5, 3/5 * 1/2 = 3/10 -> success shares 0.2, 0.4, 0.7.
    curve = kaplan_meier(np.array([2, 3, 3, 5, 6]), np.array([True, True, False, True, False]), max_steps=10)
    np.testing.assert_array_equal(curve.steps, [0, 2, 3, 5, 10])
    np.testing.assert_allclose(curve.success_share, [0.0, 0.2, 0.4, 0.7, 0.7])
    np.testing.assert_allclose(curve.share_at([0, 1, 2, 4, 5, 9, 10]), [0, 0, 0.2, 0.4, 0.7, 0.7, 0.7])


def test_kaplan_meier_without_successes_or_without_failures():
    never = kaplan_meier(np.array([10, 10, 10]), np.zeros(3, bool), max_steps=10)
    np.testing.assert_array_equal(never.steps, [0, 10])
    np.testing.assert_array_equal(never.success_share, [0.0, 0.0])
    always = kaplan_meier(np.array([4, 2, 4, 8]), np.ones(4, bool), max_steps=8)
    np.testing.assert_array_equal(always.steps, [0, 2, 4, 8])
    np.testing.assert_allclose(always.success_share, [0.0, 0.25, 0.75, 1.0])
    with pytest.raises(ValueError, match="max_steps"):
        kaplan_meier(np.array([11]), np.ones(1, bool), max_steps=10)


def test_logrank_matches_the_leukemia_remission_example():
    # Gehan's 6-MP against placebo remission times (Freireich et al. 1963): chi-square 16.79, p = 4.17e-5.
    drug_steps = np.array([6, 6, 6, 6, 7, 9, 10, 10, 11, 13, 16, 17, 19, 20, 22, 23, 25, 32, 32, 34, 35])
    drug_events = np.array([1, 1, 1, 0, 1, 0, 1, 0, 0, 1, 1, 0, 0, 0, 1, 1, 0, 0, 0, 0, 0], bool)
    placebo_steps = np.array([1, 1, 2, 2, 3, 4, 4, 5, 5, 8, 8, 8, 8, 11, 11, 12, 12, 15, 17, 22, 23])
    p_value = logrank(drug_steps, drug_events, placebo_steps, np.ones(21, bool))
    assert p_value == pytest.approx(stats.chi2.sf(16.792941, 1), rel=1e-5)
    assert p_value == pytest.approx(4.1688e-5, rel=1e-3)
    assert logrank(np.array([5, 5]), np.zeros(2, bool), np.array([5]), np.zeros(1, bool)) == 1.0


# Simulations (seeded; tolerances are binomial standard deviations of the run counts).


def test_newcombe_coverage_with_correlated_episode_difficulty():
    # 2000 runs of 200 paired episodes; the nominal 95% coverage has a binomial sd of 0.5% over 2000 runs, so 93-97%
    # is +-4 sd around it. Equal rates (0.8 vs 0.8) and a true difference (0.8 vs 0.7, second = 7/8 of first's rate).
    rng = np.random.default_rng(1)
    runs, episodes = 2000, 200
    difficulty = rng.beta(4.0, 1.0, size=(runs, episodes))  # mean 0.8
    first = rng.random((runs, episodes)) < difficulty
    second_equal = rng.random((runs, episodes)) < difficulty
    second_lower = rng.random((runs, episodes)) < 0.875 * difficulty
    for second, truth in ((second_equal, 0.0), (second_lower, 0.1)):
        intervals = [newcombe_paired_difference(first[run], second[run]) for run in range(runs)]
        coverage = np.mean([interval.low <= truth <= interval.high for interval in intervals])
        assert 0.93 <= coverage <= 0.97, (truth, coverage)


def test_compare_means_matches_welchs_formula_and_skips_missing_measurements():
    first = np.array([5.0, 6.0, 7.0, 8.0, np.nan])
    second = np.array([7.0, 9.0, 11.0, 13.0])
    result = compare_means(first, second)
    # Welch by hand: means 6.5 and 10, variances 5/3 and 20/3, standard error sqrt(5/12 + 20/12) = 1.4434.
    standard_error = math.sqrt((5 / 3) / 4 + (20 / 3) / 4)
    degrees = standard_error**4 / (((5 / 3) / 4) ** 2 / 3 + ((20 / 3) / 4) ** 2 / 3)
    t_value = -3.5 / standard_error
    assert result.first_mean == 6.5 and result.second_mean == 10.0
    assert result.first_variance == pytest.approx(5 / 3) and result.second_variance == pytest.approx(20 / 3)
    assert result.p_value == pytest.approx(2 * stats.t.sf(abs(t_value), degrees))
    half = stats.t.ppf(0.975, degrees) * standard_error
    assert (result.difference.low, result.difference.high) == pytest.approx((-3.5 - half, -3.5 + half))
    assert compare_means(np.array([1.0, np.nan]), second) is None
    # Two measurements a side: the median-centred variance test degenerates (equal deviations), so it is not given.
    pair = compare_means(np.array([10.0, 12.0]), np.array([15.0, 19.0]))
    assert pair is not None and pair.variance_p_value is None and pair.p_value > 0.05
    three = compare_means(np.array([10.0, 12.0, 11.0]), np.array([15.0, 19.0, 23.0]))
    expected = stats.levene([10.0, 12.0, 11.0], [15.0, 19.0, 23.0], center="median").pvalue
    assert three.variance_p_value == pytest.approx(expected)


def test_wilson_bounds_are_exactly_0_and_1_at_no_and_all_successes():
    # Rounding gave a lower bound of 7e-18 for 0 of 50, which made the report's error bars negative.
    assert wilson_interval(0, 50)[0] == 0.0 and wilson_interval(50, 50)[1] == 1.0
    assert 0.0 < wilson_interval(0, 50)[1] < 0.08 and 0.92 < wilson_interval(50, 50)[0] < 1.0
