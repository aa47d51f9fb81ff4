import math
import re

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from carp.evaluation import metrics
from carp.evaluation.metrics import Z_95, wilson_interval
from carp.reporting.statistics import (
    Interval,
    compare_means,
    compare_pair,
    comparison_table,
    decide_pairs,
    effective_episodes,
    episodes_to_decide,
    holm_adjust,
    intraclass_correlation,
    kaplan_meier,
    logrank,
    mcnemar_exact,
    newcombe_paired_difference,
    paired_seed_interval,
    paired_two_level_bootstrap,
    seed_permutation_test,
    two_level_bootstrap,
    z_value,
)


def paired_table(both: int, first_only: int, second_only: int, neither: int) -> tuple[np.ndarray, np.ndarray]:
    """Paired outcomes with the given cell counts of the 2x2 table."""
    first = np.array([True] * (both + first_only) + [False] * (second_only + neither))
    second = np.array([True] * both + [False] * first_only + [True] * second_only + [False] * neither)
    return first, second


def simulate_families(
    rng: np.random.Generator,
    seeds: int,
    episodes: int,
    first_mean: float,
    second_mean: float,
    seed_concentration: float | None = None,
    shared_difficulty: float = 0.5,
) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """Outcomes of two families on shared initial states.

    Each initial state has a difficulty u ~ U(0, 1); an episode reuses it with probability ``shared_difficulty``
    (else draws its own), and succeeds when it is below the training seed's rate. So both families succeed on the
    same states more often than by chance, and each family's expected rate is its seed rate: the family mean, or a
    Beta draw with that mean and concentration ``seed_concentration`` when training seeds vary.
    """
    difficulty = rng.random(episodes)
    outcomes: tuple[dict[int, np.ndarray], dict[int, np.ndarray]] = ({}, {})
    for seed in range(seeds):
        for family, mean in zip(outcomes, (first_mean, second_mean)):
            rate = mean
            if seed_concentration is not None:
                rate = rng.beta(mean * seed_concentration, (1 - mean) * seed_concentration)
            latent = np.where(rng.random(episodes) < shared_difficulty, difficulty, rng.random(episodes))
            family[seed] = latent < rate
    return outcomes


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


def test_seed_permutation_test_smallest_p_values_and_a_hand_case():
    assert seed_permutation_test([0.9, 0.95, 1.0], [0.1, 0.2, 0.3]) == pytest.approx(0.1)
    assert seed_permutation_test([0.9, 0.95, 1.0, 0.97], [0.1, 0.2, 0.3, 0.4]) == pytest.approx(2 / 70)
    # 2 vs 2: the six splits give |differences| 0.2, 0.2, 0.1, 0.1, 0, 0; the observed 0.2 is matched twice.
    assert seed_permutation_test([0.9, 0.8], [0.7, 0.6]) == pytest.approx(2 / 6)
    assert seed_permutation_test([0.5, 0.5, 0.5], [0.5, 0.5]) == 1.0
    assert seed_permutation_test([0.9], [0.1, 0.2]) is None
    # 10 vs 10 is past enumeration: random splits, still about 2 / C(20, 10) and never 0.
    sampled = seed_permutation_test(np.linspace(0.8, 0.9, 10), np.linspace(0.1, 0.2, 10))
    assert 0 < sampled < 1e-3


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


def test_episodes_to_decide_connor_and_equivalence_by_hand():
    # Connor: (1.959964 * sqrt(0.2) + 0.841621 * sqrt(0.2 - 0.01))^2 / 0.01 = (0.876523 + 0.366856)^2 / 0.01 = 154.6.
    assert episodes_to_decide(0.9, 0.8, 0.2) == 155
    # d = 0: TOST (1.644854 + 1.281552)^2 * 0.2 / 0.05^2 = 685.1.
    assert episodes_to_decide(0.8, 0.8, 0.2, margin=0.05) == 686
    # A tiny difference asks for the (smaller) equivalence count, not Connor's 1.96^2 * 0.2 / 1e-6 scale.
    assert episodes_to_decide(0.801, 0.8, 0.2, margin=0.05) < 1000
    assert episodes_to_decide(0.8, 0.8, 0.0) is None
    with pytest.raises(ValueError, match="discordant"):
        episodes_to_decide(0.9, 0.5, 0.1)


def test_connor_count_gives_the_stated_power_in_simulation():
    # At 155 pairs with 15% first-only and 5% second-only, an exact McNemar at 0.05 should reject about 80% of the
    # time; the exact test is a little conservative (about 77% here), so 0.72-0.88 (1000 runs: binomial sd 0.013).
    rng = np.random.default_rng(2)
    first_only, second_only, _ = rng.multinomial(155, [0.15, 0.05, 0.80], size=1000).T
    # The exact two-sided binomial test at 1/2 is twice the smaller tail, as mcnemar_exact computes through scipy.
    p_values = np.minimum(
        1.0, 2.0 * stats.binom.cdf(np.minimum(first_only, second_only), first_only + second_only, 0.5)
    )
    assert mcnemar_exact(*paired_table(0, first_only[0], second_only[0], 0)).p_value == pytest.approx(p_values[0])
    assert 0.72 <= np.mean(p_values < 0.05) <= 0.88


def test_paired_seed_interval_matches_scipy_paired_t():
    first, second = [0.82, 0.75, 0.9, 0.7], [0.7, 0.72, 0.8, 0.71]
    interval = paired_seed_interval(first, second, level=0.9)
    expected = stats.ttest_rel(first, second).confidence_interval(confidence_level=0.9)
    assert (interval.low, interval.high) == pytest.approx((expected.low, expected.high))
    assert interval.estimate == pytest.approx(np.mean(first) - np.mean(second))
    assert paired_seed_interval([0.8], [0.7]) is None


def test_two_level_bootstrap_estimate_and_determinism():
    runs = [np.array([True] * 8 + [False] * 2), np.array([True] * 3 + [False] * 7), np.ones(20, bool)]
    interval = two_level_bootstrap(runs, resamples=2000, seed=3)
    assert interval.estimate == pytest.approx((0.8 + 0.3 + 1.0) / 3)
    assert interval.low < interval.estimate < interval.high
    assert two_level_bootstrap(runs, resamples=2000, seed=3) == interval
    single = two_level_bootstrap([runs[0]], resamples=4000)
    wilson = wilson_interval(8, 10)
    assert single.high - single.low == pytest.approx(wilson[1] - wilson[0], abs=0.15)
    with pytest.raises(ValueError):
        two_level_bootstrap([])


def test_paired_two_level_bootstrap_pairs_episodes_and_seeds():
    runs = [np.array([True, False, True, True]), np.array([False, False, True, True, True])]
    same = paired_two_level_bootstrap(runs, [run.copy() for run in runs], resamples=500)
    assert same == Interval(0.0, 0.0, 0.0)  # identical pairs: every resample differs by exactly 0
    shifted = paired_two_level_bootstrap(runs, [np.zeros(4, bool), np.zeros(5, bool)], resamples=2000)
    assert shifted.estimate == pytest.approx((0.75 + 0.6) / 2)
    assert 0 < shifted.low < shifted.estimate < shifted.high <= 1
    with pytest.raises(ValueError, match="same number of episodes"):
        paired_two_level_bootstrap(runs, [np.zeros(4, bool), np.zeros(4, bool)])


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


def test_two_level_bootstrap_coverage_with_varying_seeds_and_its_few_seed_limit():
    # Seed rates Beta(8, 2) (mean 0.8, sd 12 points), 400 runs (binomial sd about 1.3%). With 10 seeds of 50 episodes
    # the percentile bootstrap covers about 92% in longer simulations; 0.88-0.98 allows 3 sd. With 3 seeds of 200
    # episodes it covers about 75%: it sees the spread of 3 values and nothing of their k - 1 degrees of freedom.
    # The across-seed t interval on the same 3 seeds still covers about 93%; this is why decide_pairs asks both.
    rng = np.random.default_rng(2)
    truth, runs = 0.8, 400
    covered_ten = covered_three = covered_t = 0
    for run in range(runs):
        rates = rng.beta(8.0, 2.0, size=10)
        ten = two_level_bootstrap([rng.random(50) < rate for rate in rates], resamples=1000, seed=run)
        covered_ten += ten.low <= truth <= ten.high
        three_seeds = [rng.random(200) < rate for rate in rates[:3]]
        three = two_level_bootstrap(three_seeds, resamples=1000, seed=run)
        covered_three += three.low <= truth <= three.high
        t_interval = paired_seed_interval([outcome.mean() for outcome in three_seeds], [0.0] * 3)
        covered_t += t_interval.low <= truth <= t_interval.high
    assert 0.88 <= covered_ten / runs <= 0.98
    assert covered_three / runs <= 0.85
    assert covered_t / runs >= 0.89


def test_decide_pairs_false_positives_for_equal_rates_with_varying_seeds():
    # 0.8 vs 0.8, 3 training seeds x 67 episodes, seed rates Beta with sd 9 points. "Better" is a false positive;
    # allowed up to alpha + 2.5 binomial sd (300 runs: sd 1.3%), i.e. 8%.
    rng = np.random.default_rng(3)
    runs, false_positives = 300, 0
    for run in range(runs):
        first, second = simulate_families(rng, 3, 67, 0.8, 0.8, seed_concentration=20.0)
        verdict = compare_pair("a", first, "b", second, resamples=1000, seed=run).verdict
        false_positives += verdict.endswith("better")
    assert false_positives / runs <= 0.08


def test_decide_pairs_finds_a_large_difference():
    rng = np.random.default_rng(4)
    runs, first_better = 100, 0
    for run in range(runs):
        first, second = simulate_families(rng, 4, 50, 0.9, 0.6)
        first_better += compare_pair("a", first, "b", second, resamples=1000, seed=run).verdict == "a better"
    assert first_better / runs >= 0.9


# compare_pair and decide_pairs.


def test_compare_pair_clear_winner():
    rng = np.random.default_rng(6)
    first, second = simulate_families(rng, 3, 100, 0.95, 0.5)
    comparison = compare_pair("carp", first, "diffusion_unet", second)
    assert comparison.verdict == "carp better"
    assert (comparison.episodes, comparison.seeds) == (300, 3)
    assert comparison.difference.low > 0 and comparison.bootstrap_difference.low > 0
    assert comparison.seed_difference.low > 0
    assert comparison.seed_p_value == pytest.approx(0.1)  # 3 seeds cannot go lower
    assert comparison.adjusted_p_value == comparison.mcnemar.p_value < 1e-6
    assert "carp 9" in comparison.explanation and "is better" in comparison.explanation
    assert comparison.pairing_note == ""


def test_compare_pair_equivalence_with_many_episodes():
    rng = np.random.default_rng(7)
    first, second = simulate_families(rng, 3, 1000, 0.8, 0.8, shared_difficulty=0.8)
    comparison = compare_pair("a", first, "b", second, margin=0.1)
    assert comparison.verdict == "on par within ±10 points"
    assert comparison.equivalence_difference.inside(0.1)
    assert "90% intervals" in comparison.explanation


def test_compare_pair_not_decided_names_an_episode_count():
    rng = np.random.default_rng(8)
    first, second = simulate_families(rng, 1, 30, 0.75, 0.7)
    comparison = compare_pair("a", first, "b", second)
    assert comparison.verdict == "not decided"
    needed = re.search(r"about (\d+) paired episodes per family", comparison.explanation)
    assert needed is not None and int(needed.group(1)) > 30
    assert "does not rank" in comparison.explanation
    assert comparison.seed_difference is None and comparison.seed_p_value is None


def test_disagreeing_seeds_block_a_verdict_the_pooled_episodes_would_give():
    # Seed 0 carries the whole difference: pooled McNemar is significant, the across-seed interval is not.
    first = {0: np.ones(200, bool), 1: np.array([True] * 150 + [False] * 50), 2: np.array([True] * 150 + [False] * 50)}
    second = {0: np.array([True] * 100 + [False] * 100), 1: first[1].copy(), 2: first[2].copy()}
    comparison = compare_pair("a", first, "b", second)
    assert comparison.mcnemar.p_value < 1e-6 and comparison.difference.low > 0
    assert comparison.seed_difference.low < 0
    assert comparison.verdict == "not decided"
    assert "the interval across 3 training seeds is wide, so more training seeds" in comparison.explanation


def test_seeds_pointing_both_ways_are_named_as_disagreeing():
    first = {0: np.ones(200, bool), 1: np.array([True] * 150 + [False] * 50)}
    second = {0: np.array([True] * 100 + [False] * 100), 1: np.array([True] * 160 + [False] * 40)}
    comparison = compare_pair("a", first, "b", second)
    assert comparison.verdict == "not decided"
    assert "the training seeds disagree, so more training seeds" in comparison.explanation


def test_two_seeds_in_the_same_direction_still_need_more_seeds():
    # Both seeds favour b, the episodes decide, but a t interval on one degree of freedom spans both signs.
    first = {0: np.array([True] * 185 + [False] * 15), 1: np.array([True] * 197 + [False] * 3)}
    second = {0: np.ones(200, bool), 1: np.ones(200, bool)}
    comparison = compare_pair("a", first, "b", second)
    assert comparison.mcnemar.p_value < 1e-4 and comparison.difference.high < 0
    assert comparison.seed_difference.low < 0 < comparison.seed_difference.high
    assert comparison.verdict == "not decided"
    assert "the interval across 2 training seeds is wide, so more training seeds" in comparison.explanation


def test_holm_over_many_pairs_turns_a_marginal_win_into_not_decided():
    marginal = compare_pair("a", {0: paired_table(70, 10, 2, 18)[0]}, "b", {0: paired_table(70, 10, 2, 18)[1]})
    assert marginal.verdict == "a better"  # alone: p = 0.039
    null_first, null_second = paired_table(80, 5, 5, 10)
    nulls = [compare_pair(f"c{index}", {0: null_first}, "d", {0: null_second}) for index in range(4)]
    decided = decide_pairs([marginal, *nulls], margin=0.05)
    assert decided[0].adjusted_p_value == pytest.approx(5 * 158 / 4096)
    assert decided[0].verdict == "not decided"
    assert [comparison.first for comparison in decided] == ["a", "c0", "c1", "c2", "c3"]
    assert decide_pairs([marginal], margin=0.05)[0].verdict == "a better"


def test_compare_pair_pairs_seeds_by_position_and_truncates_episodes():
    first = {0: np.ones(10, bool), 1: np.ones(12, bool), 4: np.ones(10, bool)}
    second = {0: np.zeros(10, bool), 2: np.zeros(10, bool), 3: np.zeros(10, bool), 5: np.zeros(10, bool)}
    comparison = compare_pair("a", first, "b", second)
    assert (comparison.seeds, comparison.episodes) == (3, 30)
    assert "paired by sorted position: 1 with 2, 4 with 3" in comparison.pairing_note
    assert "b 5" in comparison.pairing_note and "truncated" in comparison.pairing_note


def test_compare_pair_with_steps_gives_logrank_and_curves():
    first = {0: np.array([True, True, True, False])}
    second = {0: np.array([True, False, False, False])}
    comparison = compare_pair(
        "a",
        first,
        "b",
        second,
        first_steps_by_seed={0: np.array([10, 20, 30, 50])},
        second_steps_by_seed={0: np.array([40, 50, 50, 50])},
        max_steps=50,
    )
    assert 0 < comparison.logrank_p_value < 1
    assert comparison.first_steps_curve.share_at(30) == pytest.approx(0.75)
    assert comparison.second_steps_curve.share_at(50) == pytest.approx(0.25)
    with pytest.raises(ValueError, match="both families"):
        compare_pair("a", first, "b", second, first_steps_by_seed={0: np.array([1, 2, 3, 4])})


def test_compare_pair_refuses_what_does_not_pair():
    with pytest.raises(ValueError, match="no training seed"):
        compare_pair("a", {}, "b", {0: np.ones(3, bool)})
    with pytest.raises(ValueError, match="share no evaluated episode"):
        compare_pair("a", {0: np.ones(0, bool)}, "b", {0: np.ones(3, bool)})


def test_decide_pairs_refuses_another_alpha_and_table_is_strings():
    comparison = compare_pair("a", {0: paired_table(70, 10, 2, 18)[0]}, "b", {0: paired_table(70, 10, 2, 18)[1]})
    with pytest.raises(ValueError, match="alpha"):
        decide_pairs([comparison], margin=0.05, alpha=0.01)
    table = comparison_table(decide_pairs([comparison, comparison], margin=0.05))
    assert isinstance(table, pd.DataFrame) and len(table) == 2
    assert all(isinstance(value, str) for value in table.to_numpy().ravel())
    assert table.loc[0, "comparison"] == "a vs b"
    assert table.loc[0, "difference, 95% CI (points)"].startswith("+8.0 [")
    assert table.loc[0, "seed permutation p"] == "n/a"


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
