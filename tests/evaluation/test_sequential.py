import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import betaln
from scipy.stats import binom

from carp.evaluation.sequential import log_e_value, run_duel, sequential_verdict


def test_the_e_value_is_the_uniform_mixture_likelihood_ratio_against_a_fair_split():
    assert log_e_value(0, 0) == 0.0
    # One discordant episode says nothing: 2 * B(2, 1) = 1.
    assert math.exp(log_e_value(1, 0)) == pytest.approx(1.0)
    # Ten of ten discordant episodes to one side: 2**10 / 11.
    assert math.exp(log_e_value(10, 0)) == pytest.approx(1024 / 11)
    # By hand: 2**4 * B(4, 2) = 16 * (3! 1!) / 5! = 0.8, and symmetric in the two counts.
    assert math.exp(log_e_value(3, 1)) == pytest.approx(0.8)
    assert log_e_value(3, 1) == pytest.approx(log_e_value(1, 3))
    # Numerically against the integral of p**k (1-p)**(n-k) over [0, 1], times 2**n.
    integral, _ = quad(lambda p: p**17 * (1 - p) ** 5, 0.0, 1.0, epsabs=1e-14)
    assert math.exp(log_e_value(17, 5)) == pytest.approx(2**22 * integral, rel=1e-6)
    with pytest.raises(ValueError, match="discordant counts must be >= 0"):
        log_e_value(-1, 2)


def test_a_verdict_counts_the_discordant_episodes_and_names_the_winner_only_past_one_over_alpha():
    first = [True] * 8 + [True, False]
    second = [False] * 8 + [True, False]
    verdict = sequential_verdict("carp", first, "dp", second, alpha=0.05, max_episodes=100)
    assert (verdict.first_only, verdict.second_only, verdict.episodes) == (8, 0, 10)
    assert verdict.e_value == pytest.approx(256 / 9)  # 28.4 >= 20
    assert verdict.verdict == "carp better" and verdict.finished
    assert "carp better after 10 of at most 100 episodes" in verdict.explanation
    # Seven to none stays below 20 (16): not decided, and not finished while episodes remain.
    short = sequential_verdict("carp", first[1:], "dp", second[1:], alpha=0.05, max_episodes=100)
    assert short.e_value == pytest.approx(16.0) and short.verdict == "not decided" and not short.finished
    assert "not decided yet" in short.explanation
    out = sequential_verdict("carp", first[1:], "dp", second[1:], alpha=0.05, max_episodes=9)
    assert out.finished and "not decided in 9 episodes" in out.explanation
    flipped = sequential_verdict("dp", second, "carp", first, alpha=0.05, max_episodes=100)
    assert flipped.verdict == "carp better"
    with pytest.raises(ValueError, match="one shape"):
        sequential_verdict("a", [True], "b", [True, False], alpha=0.05, max_episodes=10)
    with pytest.raises(ValueError, match="alpha must be in"):
        sequential_verdict("a", [True], "b", [True], alpha=1.0, max_episodes=10)


def _simulated_e_paths(first_rate, second_rate, duels, episodes, round_episodes, generator):
    """(duels, rounds) e-values after each round of simulated duels with independent outcomes per side."""
    first = generator.random((duels, episodes)) < first_rate
    second = generator.random((duels, episodes)) < second_rate
    first_only = np.cumsum(first & ~second, axis=1)[:, round_episodes - 1 :: round_episodes]
    second_only = np.cumsum(second & ~first, axis=1)[:, round_episodes - 1 :: round_episodes]
    return np.exp((first_only + second_only) * math.log(2.0) + betaln(first_only + 1, second_only + 1))


def test_stopping_whenever_the_test_decides_keeps_the_false_positive_rate_at_alpha():
    generator = np.random.default_rng(0)
    for rate in (0.5, 0.8):
        e_values = _simulated_e_paths(rate, rate, duels=4000, episodes=300, round_episodes=10, generator=generator)
        # Looking after each of 30 rounds and stopping at the first crossing.
        false_positives = np.mean((e_values >= 20).any(axis=1))
        assert false_positives <= 0.05 + 3 * math.sqrt(0.05 * 0.95 / 4000), (rate, false_positives)
    # Testing a fixed-sample exact McNemar p-value after every round instead would exceed alpha: the reason for E.
    first = generator.random((2000, 300)) < 0.7
    second = generator.random((2000, 300)) < 0.7
    only_first = np.cumsum(first & ~second, axis=1)[:, 9::10]
    discordant = only_first + np.cumsum(second & ~first, axis=1)[:, 9::10]
    tail = np.minimum(binom.cdf(only_first, discordant, 0.5), binom.sf(only_first - 1, discordant, 0.5))
    peeking = np.mean((np.minimum(1.0, 2 * tail) < 0.05).any(axis=1))
    assert peeking > 0.1


def test_a_clear_difference_stops_after_a_fraction_of_the_episodes():
    generator = np.random.default_rng(1)
    e_values = _simulated_e_paths(0.95, 0.6, duels=2000, episodes=300, round_episodes=10, generator=generator)
    crossed = e_values >= 20
    assert crossed.any(axis=1).mean() > 0.99
    first_round = crossed.argmax(axis=1)[crossed.any(axis=1)]
    assert np.median((first_round + 1) * 10) <= 60


def test_a_duel_runs_rounds_until_decided_and_resumes_without_running_a_seed_twice():
    seeds = list(range(1000, 1100))
    asked = []

    def run_round(batch):
        asked.append(batch)
        # The first policy wins every seed divisible by 3, the second none; both succeed elsewhere.
        return [True] * len(batch), [seed % 3 != 0 for seed in batch]

    verdict, first, second = run_duel("a", "b", run_round, seeds, round_episodes=5, alpha=0.05, show_progress=False)
    assert verdict.verdict == "a better" and verdict.first_only >= 8 and verdict.second_only == 0
    assert sum(map(len, asked)) == verdict.episodes == len(first) == len(second) < len(seeds)
    assert [seed for batch in asked for seed in batch] == seeds[: verdict.episodes]
    assert verdict.rounds == len(asked)

    # Interrupted after two rounds, then resumed from those episodes: only the seeds after them run.
    asked.clear()
    done = (first[:10], second[:10])
    resumed, first_again, _ = run_duel(
        "a", "b", run_round, seeds, round_episodes=5, alpha=0.05, done=done, show_progress=False
    )
    assert asked[0][0] == seeds[10] and resumed == verdict.__class__(**{**vars(verdict), "rounds": resumed.rounds})
    assert first_again == first

    # Two equal policies run out of seeds undecided.
    tie, _, _ = run_duel(
        "a", "b", lambda b: ([True] * len(b), [True] * len(b)), seeds[:30], 7, 0.05, show_progress=False
    )
    assert tie.verdict == "not decided" and tie.finished and tie.episodes == 30 and tie.rounds == 5
    with pytest.raises(ValueError, match="must pair up"):
        run_duel("a", "b", run_round, seeds, 5, 0.05, done=([True], []), show_progress=False)
