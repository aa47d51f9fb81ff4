import re

import numpy as np
import pandas as pd
import pytest

from carp.reporting.calibration import Regime, simulate_run
from carp.reporting.verdict_text import pairs_table
from carp.reporting.verdicts import compare_pair, decide_pairs, decide_pairs_and_tests


def paired_table(both: int, first_only: int, second_only: int, neither: int) -> tuple[np.ndarray, np.ndarray]:
    """Paired outcomes with the given cell counts of the 2x2 table."""
    first = np.array([True] * (both + first_only) + [False] * (second_only + neither))
    second = np.array([True] * both + [False] * first_only + [True] * second_only + [False] * neither)
    return first, second


def two_families(rates: tuple[float, float], seeds: int, episodes: int, seed: int = 0, **regime):
    outcomes, _ = simulate_run(Regime(rates, seeds, episodes, **regime), np.random.default_rng(seed))
    return outcomes


def test_one_training_seed_never_yields_a_family_verdict():
    # 190 against 100 of 200: the two networks differ beyond doubt, the families are not compared.
    first, second = paired_table(100, 90, 0, 10)
    for min_seeds in (2, 3):
        comparison = compare_pair("carp", {0: first}, "diffusion_unet", {0: second}, min_seeds=min_seeds)
        assert comparison.verdict == "not decided (1 training seed)"
        assert comparison.difference is None and comparison.p_value is None
        assert "compare the trained networks, not the families" in comparison.explanation
        network = comparison.networks[0]
        assert network.mcnemar.first_only == 90 and network.mcnemar.p_value < 1e-20
        decided = decide_pairs([comparison], margin=0.05)[0]
        assert decided.verdict == "not decided (1 training seed)" and decided.adjusted_p_value is None


def test_fewer_seeds_than_the_rule_needs_is_said_with_the_count():
    outcomes = two_families((0.95, 0.4), 2, 200)
    comparison = compare_pair("a", outcomes[0], "b", outcomes[1], min_seeds=3)
    assert comparison.verdict == "not decided (2 training seeds)"
    assert comparison.difference is not None  # the interval over 2 seeds is printed, no verdict drawn from it
    with pytest.raises(ValueError, match="min_seeds"):
        compare_pair("a", outcomes[0], "b", outcomes[1], min_seeds=1)


def test_a_clear_family_difference_over_three_seeds_is_decided():
    outcomes = two_families((0.95, 0.5), 3, 100, seed_spread=0.03)
    comparison = compare_pair("carp", outcomes[0], "diffusion_unet", outcomes[1])
    assert comparison.verdict == "carp better"
    assert (comparison.seeds, comparison.episodes) == (3, 100)
    assert comparison.difference.low > 0 and comparison.p_value < 0.05
    assert comparison.first_rate == pytest.approx(np.mean(comparison.first_seed_rates))
    assert "means over 3 training seeds" in comparison.explanation and "is better" in comparison.explanation
    assert len(comparison.networks) == 3 and comparison.pairing_note == ""


def test_seeds_that_disagree_block_what_the_pooled_episodes_would_call():
    # Seed 0 carries the whole difference: pooled over 600 episodes McNemar would say p < 1e-6.
    first = {0: np.ones(200, bool), 1: np.array([True] * 150 + [False] * 50), 2: np.array([True] * 150 + [False] * 50)}
    second = {0: np.array([True] * 100 + [False] * 100), 1: first[1].copy(), 2: first[2].copy()}
    comparison = compare_pair("a", first, "b", second)
    assert comparison.difference.low < 0 < comparison.difference.high
    assert comparison.verdict == "not decided"
    needed = re.search(r"about (\d+) training seeds per family would likely decide", comparison.explanation)
    assert needed is not None and int(needed.group(1)) > 3
    first[1][:60] = False  # now seed 1 points the other way
    assert "disagree in sign" in compare_pair("a", first, "b", second).explanation


def test_equivalence_is_decided_over_seeds_with_many_episodes():
    outcomes = two_families((0.8, 0.8), 8, 1000, seed_spread=0.0, shared_states=False)
    comparison = compare_pair("a", outcomes[0], "b", outcomes[1], margin=0.1)
    assert comparison.verdict == "on par within ±10 points"
    assert comparison.equivalence_difference.inside(0.1) and comparison.equivalence_p_value < 0.05
    assert "90% interval over training seeds" in comparison.explanation


def test_one_correction_over_every_pair_turns_a_marginal_win_into_not_decided():
    outcomes = two_families((0.85, 0.7), 3, 200, seed=28, seed_spread=0.03)
    marginal = compare_pair("a", outcomes[0], "b", outcomes[1])
    assert marginal.verdict == "a better" and 0.005 < marginal.p_value < 0.05 / 3
    equal = two_families((0.8, 0.8), 3, 100, seed=1)[0]
    nulls = [compare_pair(f"c{index}", equal, "d", equal) for index in range(20)]
    decided = decide_pairs([marginal, *nulls], margin=0.05)
    assert decided[0].verdict == "not decided"
    assert decided[0].adjusted_p_value == pytest.approx(min(1.0, 21 * marginal.p_value))
    assert [comparison.first for comparison in decided] == ["a", *(f"c{index}" for index in range(20))]
    # Two other pairs: the win survives a correction over three.
    assert decide_pairs([marginal, *nulls[:2]], margin=0.05)[0].verdict == "a better"
    # Pairs with too few seeds are outside the correction: they leave the marginal win alone.
    few = [compare_pair(f"e{index}", {0: equal[0]}, "d", {0: equal[0]}) for index in range(20)]
    assert decide_pairs([marginal, *few], margin=0.05)[0].verdict == "a better"


def test_other_tests_share_the_correction_with_the_pairs():
    outcomes = two_families((0.85, 0.7), 3, 200, seed=28, seed_spread=0.03)
    marginal = compare_pair("a", outcomes[0], "b", outcomes[1])
    assert 0.005 < marginal.p_value < 0.05 / 3
    # Two precision tests, one strong, one null: three groups, so the marginal win holds at 3x its p.
    pairs, adjusted = decide_pairs_and_tests([marginal], [0.001, 0.6], margin=0.05)
    assert pairs[0].verdict == "a better"
    assert pairs[0].adjusted_p_value == pytest.approx(2 * marginal.p_value)  # second step: two groups left
    # The null test's step still counts the pair's untested equivalence: two groups, 2 x 0.6 capped at 1.
    assert adjusted == pytest.approx([0.003, 1.0])
    # Twenty null tests beside it: the same win is no longer decided, as with twenty null pairs.
    pairs, adjusted = decide_pairs_and_tests([marginal], [0.5] * 20, margin=0.05)
    assert pairs[0].verdict == "not decided" and pairs[0].adjusted_p_value == pytest.approx(21 * marginal.p_value)
    assert len(adjusted) == 20 and min(adjusted) >= 0.5
    # Without other tests it is decide_pairs.
    assert decide_pairs_and_tests([marginal], [], margin=0.05)[0] == decide_pairs([marginal], margin=0.05)


def test_pairs_seeds_by_position_and_truncates_to_shared_states():
    first = {0: np.ones(10, bool), 1: np.ones(12, bool), 4: np.ones(10, bool)}
    second = {0: np.zeros(10, bool), 2: np.zeros(10, bool), 3: np.zeros(10, bool), 5: np.zeros(10, bool)}
    comparison = compare_pair("a", first, "b", second)
    assert (comparison.seeds, comparison.episodes) == (3, 10)
    assert "paired by sorted position: 1 with 2, 4 with 3" in comparison.pairing_note
    assert "b 5" in comparison.pairing_note and "truncated" in comparison.pairing_note


def test_steps_give_descriptive_curves_and_must_come_for_both():
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
    assert comparison.first_steps_curve.share_at(30) == pytest.approx(0.75)
    assert comparison.second_steps_curve.share_at(50) == pytest.approx(0.25)
    with pytest.raises(ValueError, match="both families"):
        compare_pair("a", first, "b", second, first_steps_by_seed={0: np.array([1, 2, 3, 4])})
    with pytest.raises(ValueError, match="no training seed"):
        compare_pair("a", {}, "b", {0: np.ones(3, bool)})
    with pytest.raises(ValueError, match="share no evaluated episode"):
        compare_pair("a", {0: np.ones(0, bool)}, "b", {0: np.ones(3, bool)})


def test_decide_pairs_refuses_another_alpha_and_the_table_is_strings():
    outcomes = two_families((0.9, 0.6), 3, 50)
    comparison = compare_pair("a", outcomes[0], "b", outcomes[1])
    with pytest.raises(ValueError, match="alpha"):
        decide_pairs([comparison], margin=0.05, alpha=0.01)
    one_seed = compare_pair("a", {0: outcomes[0][0]}, "b", {0: outcomes[1][0]})
    table = pairs_table(decide_pairs([comparison, one_seed], margin=0.05))
    assert isinstance(table, pd.DataFrame) and len(table) == 2
    assert all(isinstance(value, str) for value in table.to_numpy().ravel())
    assert table.loc[0, "comparison"] == "a vs b" and table.loc[0, "training seeds"] == "3"
    assert table.loc[1, "difference, 95% interval over seeds (points)"] == "n/a"
    assert table.loc[1, "corrected p: difference / equivalence"] == "n/a / n/a"
