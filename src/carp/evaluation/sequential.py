"""Anytime-valid comparison of two policies evaluated in rounds on the same episode seeds, stopped once decided.

A fixed-size comparison (`carp.reporting.statistics`) spends every episode it planned, even when the first rounds
already separate two policies. Here both policies run round after round on shared seeds, and after every round a
test whose error rate holds at *any* stopping time decides whether to go on.

The test is McNemar's in sequential form. Only discordant episodes (one policy succeeded, the other failed) carry
information on which is better; under the null hypothesis that neither is, each discordant episode is the first
policy's with probability 1/2, whatever the two success rates are. Against that null, the likelihood ratio of the
discordant sequence averaged over a uniform prior on that probability,

    E_n = 2**n * B(k + 1, n - k + 1)      (n discordant episodes, k of them the first policy's, B the beta function),

is a nonnegative martingale with E_0 = 1 under the null, so by Ville's inequality P(E_n >= 1/alpha for some n) <=
alpha: stopping the first time E_n reaches 1/alpha, after any number of looks, keeps the false-positive rate at
alpha. The price is power: at a fixed size, the fixed-sample McNemar test decides somewhat sooner than this one
would at that size; the saving is on pairs that differ clearly, which stop after a fraction of the episodes.

An undecided duel that ran out of episodes says so; it does not claim the two are on par (equivalence at a margin
is the fixed-size comparison's job, on the report's full episode sets).
"""

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.special import betaln
from tqdm.auto import tqdm


def log_e_value(first_only: int, second_only: int) -> float:
    """Log E of the mixture test for `first_only` and `second_only` discordant episodes (see the module docstring).

    0 (E = 1) with no discordant episode; grows with the imbalance between the two counts.
    """
    if first_only < 0 or second_only < 0:
        raise ValueError(f"discordant counts must be >= 0, got {first_only} and {second_only}")
    return (first_only + second_only) * math.log(2.0) + float(betaln(first_only + 1, second_only + 1))


@dataclass(frozen=True)
class SequentialVerdict:
    """Where a duel stands after the episodes run so far.

    Attributes:
        first, second: the two policies' names.
        episodes: paired episodes run (both policies on each seed).
        max_episodes: the most the duel may run.
        rounds: rounds run.
        first_successes, second_successes: successes of each policy over `episodes`.
        first_only, second_only: discordant episodes won by the first / by the second policy alone.
        e_value: the test's E after the last round.
        alpha: the false-positive rate it holds at any stopping time.
        verdict: ``"<first> better"``, ``"<second> better"`` or ``"not decided"``.
        finished: decided, or out of episodes.
    """

    first: str
    second: str
    episodes: int
    max_episodes: int
    rounds: int
    first_successes: int
    second_successes: int
    first_only: int
    second_only: int
    e_value: float
    alpha: float
    verdict: str
    finished: bool

    @property
    def explanation(self) -> str:
        """One sentence with the numbers behind the verdict."""
        rates = (
            f"{self.first} {self.first_successes}/{self.episodes} vs {self.second} {self.second_successes}/"
            f"{self.episodes} on the same seeds, discordant {self.first_only} / {self.second_only}, "
            f"E = {self.e_value:.3g} (decides at {1 / self.alpha:.3g})"
        )
        if self.verdict != "not decided":
            return f"{self.verdict} after {self.episodes} of at most {self.max_episodes} episodes: {rates}."
        if self.finished:
            return f"not decided in {self.episodes} episodes: {rates}; more episodes or a fixed-size comparison."
        return f"not decided yet after {self.episodes} episodes: {rates}."


def sequential_verdict(
    first: str,
    first_success: Sequence[bool],
    second: str,
    second_success: Sequence[bool],
    alpha: float,
    max_episodes: int,
    rounds: int = 1,
) -> SequentialVerdict:
    """The duel's state from both policies' outcomes on the same seeds, in order.

    Args:
        first: the first policy's name.
        first_success: (N,) its success per episode, in seed order.
        second: the second policy's name.
        second_success: (N,) its success on the same seeds, in the same order.
        alpha: false-positive rate, in (0, 1).
        max_episodes: the duel's cap; the verdict is final once N reaches it.
        rounds: rounds that produced the N episodes (reported only).
    """
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    first_outcomes, second_outcomes = np.asarray(first_success, bool), np.asarray(second_success, bool)
    if first_outcomes.shape != second_outcomes.shape or first_outcomes.ndim != 1:
        raise ValueError(f"paired outcomes must have one shape, got {first_outcomes.shape} and {second_outcomes.shape}")
    first_only = int(np.sum(first_outcomes & ~second_outcomes))
    second_only = int(np.sum(second_outcomes & ~first_outcomes))
    e_value = math.exp(log_e_value(first_only, second_only))
    decided = e_value >= 1 / alpha
    verdict = "not decided" if not decided else f"{first if first_only > second_only else second} better"
    return SequentialVerdict(
        first=first,
        second=second,
        episodes=len(first_outcomes),
        max_episodes=max_episodes,
        rounds=rounds,
        first_successes=int(first_outcomes.sum()),
        second_successes=int(second_outcomes.sum()),
        first_only=first_only,
        second_only=second_only,
        e_value=e_value,
        alpha=alpha,
        verdict=verdict,
        finished=decided or len(first_outcomes) >= max_episodes,
    )


RoundRunner = Callable[[list[int]], tuple[list[bool], list[bool]]]
"""Runs both policies on a round's episode seeds: seeds -> (first's successes, second's), in seed order."""


def run_duel(
    first: str,
    second: str,
    run_round: RoundRunner,
    seeds: Sequence[int],
    round_episodes: int,
    alpha: float,
    done: tuple[Sequence[bool], Sequence[bool]] = ((), ()),
    show_progress: bool = True,
) -> tuple[SequentialVerdict, list[bool], list[bool]]:
    """Evaluate two policies round by round on `seeds` until the test decides or the seeds run out.

    Args:
        first: the first policy's name.
        second: the second policy's name.
        run_round: runs both policies on a round's seeds (`RoundRunner`); persisting each round's episodes, so that an
            interrupted duel resumes, is its job.
        seeds: the episode seeds in the order the duel takes them; their number caps the duel.
        round_episodes: seeds per round (the test looks after each round); >= 1.
        alpha: the false-positive rate at any stopping time.
        done: outcomes on the first seeds already run (a resumed duel, or episodes an evaluation ran on these seeds),
            one list per policy of one length; they count as the first round.
        show_progress: show a tqdm bar over the seeds.

    Returns:
        The verdict after the last round, and each policy's outcomes on the seeds run, in order.
    """
    if round_episodes < 1:
        raise ValueError(f"round_episodes must be >= 1, got {round_episodes}")
    first_success, second_success = list(done[0]), list(done[1])
    if len(first_success) != len(second_success) or len(first_success) > len(seeds):
        raise ValueError(
            f"episodes already run must pair up within the {len(seeds)} seeds, got {len(first_success)} and "
            f"{len(second_success)}"
        )
    rounds = 1 if first_success else 0
    verdict = sequential_verdict(first, first_success, second, second_success, alpha, len(seeds), rounds)
    with tqdm(
        total=len(seeds),
        initial=len(first_success),
        desc=f"{first} vs {second}",
        unit="pair",
        disable=not show_progress,
    ) as progress:
        while not verdict.finished:
            batch = list(seeds[len(first_success) : len(first_success) + round_episodes])
            first_round, second_round = run_round(batch)
            if len(first_round) != len(batch) or len(second_round) != len(batch):
                raise ValueError(f"a round of {len(batch)} seeds returned {len(first_round)} and {len(second_round)}")
            first_success += map(bool, first_round)
            second_success += map(bool, second_round)
            rounds += 1
            verdict = sequential_verdict(first, first_success, second, second_success, alpha, len(seeds), rounds)
            progress.update(len(batch))
            progress.set_postfix(E=f"{verdict.e_value:.3g}")
    return verdict, first_success, second_success
