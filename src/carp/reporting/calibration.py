"""Simulated families with known truth, to check that the report's verdicts and intervals keep their promises.

A simulated run trains ``seeds`` networks per family and evaluates each on ``episodes`` initial states, like carp's
evaluate stages, with three sources of variation that real runs have:

- **Training seeds.** Seed s of family f succeeds at rate ``p_fs = p_f + u_fs``, u_fs normal with sd
  ``seed_spread``, clipped symmetrically at ``±min(p_f, 1 - p_f)`` so that the mean over seeds stays exactly p_f.
- **Shared state difficulty.** Each episode succeeds when a uniform latent value falls below p_fs. With probability
  ``state_share`` that latent is the state's own (the same for every family and seed: a state hard for one is hard
  for all), with probability ``family_state_share`` it is the family's own for that state (the same for every seed of
  the family, independent across families: a family-by-state interaction), otherwise it is fresh. Every latent is
  uniform, so the success probability of an episode of seed s is exactly p_fs whatever the mix, and the family's
  true rate is exactly p_f.
- **Design.** With ``shared_states`` every seed runs the same states (carp's evaluations); otherwise each seed pair
  draws its own.

:func:`run_cell` simulates many runs of a regime and counts what the verdict rules and intervals did; the test suite
runs CI-sized cells (``tests/reporting/test_calibration.py``) and ``benchmarks/verdict_calibration.py`` the full
table.
"""

import math
from dataclasses import dataclass
from itertools import combinations

import numpy as np
from scipy import stats

from carp.reporting.seed_inference import seed_level_estimate
from carp.reporting.statistics import wilson_interval
from carp.reporting.verdicts import compare_pair, decide_pairs


@dataclass(frozen=True)
class Regime:
    """One cell of the calibration table: the truth and the design of a simulated run.

    Attributes:
        rates: (F,) true success rate of each family, each in (0, 1).
        seeds: training seeds per family, >= 1.
        episodes: initial states per seed, >= 1.
        seed_spread: sd of the per-seed true rates around the family's, as a share.
        state_share: probability that an episode's outcome follows the state's shared difficulty.
        family_state_share: probability that it follows the family's own difficulty of that state.
        shared_states: whether every seed runs the same initial states.
    """

    rates: tuple[float, ...]
    seeds: int
    episodes: int
    seed_spread: float = 0.05
    state_share: float = 0.0
    family_state_share: float = 0.0
    shared_states: bool = True

    def __post_init__(self) -> None:
        if not all(0.0 < rate < 1.0 for rate in self.rates) or len(self.rates) < 1:
            raise ValueError(f"rates={self.rates}: need at least one, each in (0, 1)")
        if self.seeds < 1 or self.episodes < 1 or self.seed_spread < 0:
            raise ValueError(f"seeds={self.seeds}, episodes={self.episodes}, seed_spread={self.seed_spread}")
        if self.state_share < 0 or self.family_state_share < 0 or self.state_share + self.family_state_share > 1:
            raise ValueError("state_share and family_state_share must be >= 0 and add up to at most 1")


def simulate_run(
    regime: Regime, generator: np.random.Generator
) -> tuple[list[dict[int, np.ndarray]], list[np.ndarray]]:
    """One simulated run of every family's networks.

    Returns:
        Per family, training seed -> (episodes,) bool outcomes (column j is state j when states are shared), and per
        family the (seeds,) true success rates of its networks.
    """
    families, seeds, episodes = len(regime.rates), regime.seeds, regime.episodes
    state_rows = 1 if regime.shared_states else seeds
    state_latent = generator.random((state_rows, episodes))
    family_latent = generator.random((families, state_rows, episodes))
    runs, network_rates = [], []
    for family, rate in enumerate(regime.rates):
        bound = min(rate, 1.0 - rate)
        offsets = np.clip(generator.normal(0.0, regime.seed_spread, seeds), -bound, bound)
        outcomes = {}
        for seed in range(seeds):
            row = 0 if regime.shared_states else seed
            source = generator.random(episodes)
            latent = generator.random(episodes)
            from_state = source < regime.state_share
            from_family = ~from_state & (source < regime.state_share + regime.family_state_share)
            latent[from_state] = state_latent[row, from_state]
            latent[from_family] = family_latent[family, row, from_family]
            outcomes[seed] = latent < rate + offsets[seed]
        runs.append(outcomes)
        network_rates.append(rate + offsets)
    return runs, network_rates


@dataclass
class CellResult:
    """What the rules did over the runs of one regime; shares are of runs (or of intervals, for coverage).

    Attributes:
        runs: simulated runs.
        false_better: runs where some pair whose true difference is within ``null_tolerance`` of zero was called
            "better" (either way), or a truly worse family was called better.
        false_on_par: runs where some pair whose true difference is beyond the margin was called "on par".
        any_verdict_error: runs with any wrong verdict of either kind (the family-wise error).
        rate_covered, rate_intervals: family-rate intervals that covered the true rate, and how many there were.
        difference_covered, difference_intervals: the same for the intervals of the pairs' differences.
        network_covered, network_intervals: the same for each network's own Wilson interval of its true rate.
        family_verdicts: pairs that got a family verdict ("better" or "on par").
        pairs: pairs compared.
    """

    runs: int = 0
    false_better: int = 0
    false_on_par: int = 0
    any_verdict_error: int = 0
    rate_covered: int = 0
    rate_intervals: int = 0
    difference_covered: int = 0
    difference_intervals: int = 0
    network_covered: int = 0
    network_intervals: int = 0
    family_verdicts: int = 0
    pairs: int = 0

    def share(self, name: str) -> tuple[float, float]:
        """A share and its Monte-Carlo standard error.

        `name` is an error count over runs (``false_better``, ``false_on_par``, ``any_verdict_error``) or a coverage
        (``rate``, ``difference``, ``network``: intervals that covered over intervals printed).
        """
        if name in ("rate", "difference", "network"):
            count, total = getattr(self, f"{name}_covered"), getattr(self, f"{name}_intervals")
        else:
            count, total = getattr(self, name), self.runs
        if not total:
            return float("nan"), float("nan")
        share = count / total
        return share, math.sqrt(max(share * (1.0 - share), 1.0 / total) / total)


def run_cell(
    regime: Regime,
    runs: int,
    *,
    margin: float = 0.05,
    alpha: float = 0.05,
    level: float = 0.95,
    min_seeds: int = 3,
    seed: int = 0,
) -> CellResult:
    """Simulate `runs` runs of `regime` and score every verdict and interval the report would print.

    A verdict "A better" is wrong when A's true rate is not above B's; "on par" is wrong when the true difference is
    at least the margin. Coverage counts the seed-level intervals of each family's rate and of each pair's difference
    (where there are at least 2 seeds), and each network's Wilson interval of its own rate.
    """
    generator = np.random.default_rng(seed)
    result = CellResult()
    names = [f"family{index}" for index in range(len(regime.rates))]
    truth = dict(zip(names, regime.rates))
    z = float(stats.norm.ppf(0.5 + level / 2.0))
    for _ in range(runs):
        outcomes, network_rates = simulate_run(regime, generator)
        compared = [
            compare_pair(
                names[first],
                outcomes[first],
                names[second],
                outcomes[second],
                shared_states=regime.shared_states,
                min_seeds=min_seeds,
                margin=margin,
                alpha=alpha,
                level=level,
            )
            for first, second in combinations(range(len(names)), 2)
        ]
        decided = decide_pairs(compared, margin=margin, alpha=alpha)
        wrong_better = wrong_on_par = False
        for pair in decided:
            true_difference = truth[pair.first] - truth[pair.second]
            result.pairs += 1
            if pair.verdict.endswith(" better") and not pair.verdict.startswith("not"):
                result.family_verdicts += 1
                leader_ahead = (
                    true_difference > 1e-12 if pair.verdict == f"{pair.first} better" else true_difference < -1e-12
                )
                wrong_better |= not leader_ahead
            elif pair.verdict.startswith("on par"):
                result.family_verdicts += 1
                wrong_on_par |= abs(true_difference) >= margin - 1e-12
            if pair.difference is not None:
                result.difference_intervals += 1
                result.difference_covered += pair.difference.low <= true_difference <= pair.difference.high
        result.runs += 1
        result.false_better += wrong_better
        result.false_on_par += wrong_on_par
        result.any_verdict_error += wrong_better or wrong_on_par
        for name, by_seed, rates in zip(names, outcomes, network_rates):
            if len(by_seed) >= 2:
                interval = seed_level_estimate(
                    [values.astype(float) for values in by_seed.values()], shared_states=regime.shared_states
                ).interval(level)
                result.rate_intervals += 1
                result.rate_covered += interval.low <= truth[name] <= interval.high
            for values, rate in zip(by_seed.values(), rates):
                low, high = wilson_interval(int(values.sum()), values.size, z)
                result.network_intervals += 1
                result.network_covered += low <= rate <= high
    return result


def default_regimes() -> list[Regime]:
    """The benchmark's table: carp's range of seeds, episodes, seed spreads, state effects and family counts.

    Equal families (false verdicts and coverage), a pair whose true difference is just beyond the margin (false "on
    par"), and a 15-point difference (how often the rules decide at all).
    """
    with_states = {"state_share": 0.3, "family_state_share": 0.2}
    return [
        *(Regime((0.7, 0.7), seeds, 200, 0.05, **with_states) for seeds in (1, 2, 3, 5, 10)),
        Regime((0.7, 0.7), 3, 50, 0.10),
        Regime((0.7, 0.7), 3, 500, 0.0, **with_states),
        Regime((0.7, 0.7), 3, 200, 0.10, state_share=0.3),
        Regime((0.7, 0.7), 3, 200, 0.05, shared_states=False),
        Regime((0.9, 0.9), 3, 50, 0.05),
        Regime((0.7,) * 4, 3, 200, 0.05, **with_states),
        Regime((0.7,) * 6, 5, 50, 0.10),
        Regime((0.7, 0.755), 10, 500, 0.0),
        Regime((0.7, 0.755), 5, 500, 0.02, **with_states),
        *(Regime((0.85, 0.7), seeds, 200, 0.05) for seeds in (3, 5, 10)),
    ]
