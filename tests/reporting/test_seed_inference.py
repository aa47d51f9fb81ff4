import math

import numpy as np
import pytest
from scipy import stats

from carp.reporting.seed_inference import seed_level_estimate, seed_mean_interval, seeds_to_decide, step_down_adjust


def test_nested_design_is_the_paired_t_over_seed_means():
    generator = np.random.default_rng(0)
    runs = [generator.random(100) < rate for rate in (0.6, 0.7, 0.8, 0.75)]
    estimate = seed_level_estimate([run.astype(float) for run in runs], shared_states=False)
    means = np.array([run.mean() for run in runs])
    assert estimate.estimate == pytest.approx(means.mean())
    assert estimate.standard_error == pytest.approx(means.std(ddof=1) / 2)
    expected = stats.ttest_1samp(means, 0.0).confidence_interval(0.9)
    interval = estimate.interval(0.9)
    assert (interval.low, interval.high) == pytest.approx((expected.low, expected.high))
    assert estimate.p_value() == pytest.approx(stats.ttest_1samp(means, 0.0).pvalue)


def test_shared_states_add_the_states_difficulty_the_seed_spread_cannot_show():
    # Every seed ran the same 10 states and they split the same way: the seed means agree exactly, yet a new draw of
    # states would move all of them together.
    state_outcomes = np.array([1, 1, 1, 1, 1, 1, 0, 0, 0, 0], float)
    seeds = [state_outcomes.copy() for _ in range(3)]
    shared = seed_level_estimate(seeds, shared_states=True)
    # The two-way moments: no seed spread, no residual, state means with variance 0.2667 over 10 states.
    assert shared.standard_error == pytest.approx(math.sqrt(state_outcomes.var(ddof=1) / 10))
    nested = seed_level_estimate(seeds, shared_states=False)
    assert nested.standard_error < shared.standard_error


def test_the_floor_keeps_equal_seeds_from_a_zero_width_interval():
    # Three seeds of the same rate on distinct states: the sample spread is 0, the floor is the episodes' own noise.
    seeds = [np.array([1.0] * 25 + [0.0] * 25) for _ in range(3)]
    estimate = seed_level_estimate(seeds, shared_states=False)
    floor = math.sqrt(3 * np.var(np.array([1.0] * 26 + [0.0] * 26)) / 52 / 9)
    assert estimate.standard_error == pytest.approx(floor)
    interval = estimate.interval(0.95)
    assert interval.high - interval.low > 0.2
    # All successes still has a width, and the interval stays inside [0, 1].
    perfect = seed_level_estimate([np.ones(50)] * 3, shared_states=True).interval(0.95)
    assert perfect.high == 1.0 and perfect.low < 0.97


def test_equivalence_p_is_below_alpha_exactly_when_the_1_minus_2_alpha_interval_is_inside_the_margin():
    generator = np.random.default_rng(1)
    for _ in range(50):
        differences = [generator.choice([-1.0, 0.0, 1.0], 200, p=[0.1, 0.8, 0.1]) for _ in range(5)]
        estimate = seed_level_estimate(differences, shared_states=False, value_range=(-1.0, 1.0))
        inside = estimate.interval(0.9).inside(0.05)
        assert (estimate.equivalence_p_value(0.05) < 0.05) == inside


def test_a_family_estimate_needs_two_seeds_and_matching_states():
    with pytest.raises(ValueError, match=">= 2 training seeds"):
        seed_level_estimate([np.ones(5)], shared_states=True)
    with pytest.raises(ValueError, match="same episodes"):
        seed_level_estimate([np.ones(5), np.ones(4)], shared_states=True)
    with pytest.raises(ValueError, match="no episodes"):
        seed_level_estimate([np.ones(5), np.ones(0)], shared_states=False)


def test_seeds_to_decide_grows_as_the_difference_shrinks():
    big = seed_level_estimate([np.full(100, 0.2), np.full(100, 0.0), np.full(100, 0.1)], shared_states=False)
    small = seed_level_estimate([np.full(100, 0.05), np.full(100, -0.05), np.full(100, 0.03)], shared_states=False)
    assert seeds_to_decide(big, 0.05, 0.05) < seeds_to_decide(small, 0.05, 0.05)
    # A huge spread around no difference within 100 seeds decides nothing.
    wild = seed_level_estimate([np.full(10, 0.9), np.full(10, -0.9), np.full(10, 0.0)], shared_states=False)
    assert seeds_to_decide(wild, 0.01, 0.05, most=5) is None


def test_step_down_counts_a_pair_once_and_is_holm_with_one_hypothesis_per_group():
    # Holm: 0.005 * 4, 0.01 * 3, 0.03 * 2, 0.04 * 1, running max.
    assert step_down_adjust([0.01, 0.04, 0.03, 0.005], [0, 1, 2, 3]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    # Two pairs of two hypotheses: at most two can be true, so the smallest is doubled, not quadrupled; a rejected
    # hypothesis leaves its pair's other one possibly true, so the factor stays 2 until a pair is used up.
    # Sorted: 0.001 (pair 0) x 2, 0.01 (pair 1) x 2, 0.02 (pair 0) x 2, 0.3 (pair 1) x 1.
    adjusted = step_down_adjust([0.001, 0.02, 0.01, 0.3], [0, 0, 1, 1])
    assert adjusted == pytest.approx([0.002, 0.04, 0.02, 0.3])
    assert step_down_adjust([], []) == []
    with pytest.raises(ValueError, match="groups"):
        step_down_adjust([0.1], [0, 1])


def test_a_continuous_per_seed_figure_gets_the_t_interval_over_its_seeds():
    # Seeds 1, 2, 3: mean 2, sd 1, t(0.975; 2) = 4.3027, half-width 4.3027 / sqrt(3) = 2.4841.
    interval = seed_mean_interval([1.0, 2.0, 3.0])
    assert (interval.estimate, interval.low, interval.high) == pytest.approx((2.0, -0.48414, 4.48414), abs=1e-5)
    expected = stats.ttest_1samp([0.3, 0.5, 0.4, 0.9], 0.0).confidence_interval(0.9)
    interval = seed_mean_interval([0.3, 0.5, 0.4, 0.9], level=0.9)
    assert (interval.low, interval.high) == pytest.approx((expected.low, expected.high))
    # An error is never below 0: the interval is clipped to the figure's range.
    assert seed_mean_interval([1.0, 2.0, 3.0], value_range=(0.0, math.inf)).low == 0.0
    for values in ([1.0], [1.0, float("nan")]):
        with pytest.raises(ValueError, match="two finite values or more"):
            seed_mean_interval(values)
