"""The verdict rules and intervals against simulated families with known truth (CI-sized; the benchmark
``benchmarks/verdict_calibration.py`` runs the full table with many more runs).

Each cell simulates runs of a regime (`carp.reporting.calibration`) and checks, with a fixed random seed:
the share of runs with a false "better" and the family-wise share with any wrong verdict are at most alpha plus two
Monte-Carlo standard errors; "on par" at a true difference just beyond the margin likewise; and each printed interval
covers its truth at least at its level minus two standard errors.
"""

import math

import numpy as np
import pytest

from carp.reporting.calibration import Regime, run_cell

ALPHA = 0.05
LEVEL = 0.95


def upper_bound(share: float, runs: int) -> float:
    return share + 2 * math.sqrt(share * (1 - share) / runs)


def lower_bound(share: float, runs: int) -> float:
    return share - 2 * math.sqrt(share * (1 - share) / runs)


EQUAL_FAMILY_CELLS = [
    # (regime, runs): 1-10 seeds, 50-500 episodes, spread 0-10 points, shared state difficulty with and without a
    # family-by-state effect, distinct states per seed, 2-6 families.
    (Regime((0.7, 0.7), seeds=1, episodes=200, seed_spread=0.05), 300),
    (Regime((0.7, 0.7), seeds=2, episodes=50, seed_spread=0.10, state_share=0.3), 300),
    (Regime((0.7, 0.7), seeds=3, episodes=200, seed_spread=0.05, state_share=0.3, family_state_share=0.2), 400),
    (Regime((0.9, 0.9), seeds=3, episodes=50, seed_spread=0.05), 300),
    (Regime((0.7, 0.7), seeds=5, episodes=500, seed_spread=0.0, state_share=0.3, family_state_share=0.2), 300),
    (Regime((0.7, 0.7), seeds=10, episodes=200, seed_spread=0.10, state_share=0.3, family_state_share=0.2), 300),
    (Regime((0.7, 0.7), seeds=5, episodes=200, seed_spread=0.05, shared_states=False), 300),
    (Regime((0.7,) * 4, seeds=3, episodes=200, seed_spread=0.05, state_share=0.3, family_state_share=0.2), 150),
    (Regime((0.7,) * 6, seeds=5, episodes=50, seed_spread=0.10), 100),
]


@pytest.mark.parametrize(("regime", "runs"), EQUAL_FAMILY_CELLS, ids=[f"cell{index}" for index in range(9)])
def test_equal_families_are_rarely_called_different_and_intervals_cover(regime, runs):
    cell = run_cell(regime, runs, alpha=ALPHA, level=LEVEL, seed=11)
    assert cell.false_better / runs <= upper_bound(ALPHA, runs)
    assert cell.any_verdict_error / runs <= upper_bound(ALPHA, runs)
    if regime.seeds < 3:
        assert cell.family_verdicts == 0  # too few training seeds for any family verdict
    if regime.seeds >= 2:
        assert cell.rate_covered / cell.rate_intervals >= lower_bound(LEVEL, runs)
        assert cell.difference_covered / cell.difference_intervals >= lower_bound(LEVEL, runs)
    assert cell.network_covered / cell.network_intervals >= lower_bound(LEVEL, runs)


@pytest.mark.parametrize(
    "regime",
    [
        Regime((0.7, 0.755), seeds=10, episodes=500, seed_spread=0.0),
        Regime((0.7, 0.755), seeds=5, episodes=500, seed_spread=0.02, state_share=0.3, family_state_share=0.2),
    ],
)
def test_a_difference_just_beyond_the_margin_is_rarely_called_on_par(regime):
    runs = 400
    cell = run_cell(regime, runs, margin=0.05, alpha=ALPHA, seed=12)
    assert cell.false_on_par / runs <= upper_bound(ALPHA, runs)
    assert cell.difference_covered / cell.difference_intervals >= lower_bound(LEVEL, runs)


def test_a_large_difference_is_found_with_enough_seeds():
    # The rules are not merely silent: 15 points over 5 seeds of 200 episodes is called nearly always.
    runs = 100
    cell = run_cell(Regime((0.85, 0.7), seeds=5, episodes=200, seed_spread=0.03), runs, seed=13)
    assert cell.family_verdicts / cell.pairs >= 0.9 and cell.false_better == 0


def test_simulated_seeds_have_the_family_rate_as_their_mean():
    from carp.reporting.calibration import simulate_run

    generator = np.random.default_rng(0)
    rates = [
        simulate_run(Regime((0.9, 0.3), seeds=4, episodes=500, seed_spread=0.1, state_share=0.5), generator)[1]
        for _ in range(300)
    ]
    assert np.mean([run[0] for run in rates]) == pytest.approx(0.9, abs=0.005)
    assert np.mean([run[1] for run in rates]) == pytest.approx(0.3, abs=0.01)
