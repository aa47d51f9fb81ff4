"""The words and tables of the verdicts: rates, differences and p-values as a report prints them.

Apart from the rules (`carp.reporting.verdicts`), which decide; this module only formats what they decided.
"""

from collections.abc import Sequence
from typing import TYPE_CHECKING

import pandas as pd

from carp.reporting.statistics import Interval

if TYPE_CHECKING:
    from carp.reporting.verdicts import PairComparison


def summary_text(comparison: "PairComparison", difference_p: float, equivalence_p: float) -> str:
    """The family rates, the difference with its interval over seeds and both corrected p-values."""
    design = "the same" if comparison.shared_states else "distinct"
    return (
        f"{comparison.first} {comparison.first_rate:.1%} vs {comparison.second} {comparison.second_rate:.1%} "
        f"(means over {comparison.seeds} training seeds, {comparison.episodes} episodes each on {design} initial "
        f"states): difference {signed_points(comparison.difference.estimate)} points, {comparison.level:.0%} "
        f"interval over training seeds {interval_bounds(comparison.difference)}, "
        f"corrected {p_phrase(difference_p)} for a difference and {p_phrase(equivalence_p)} for equivalence"
    )


def disagreement_text(comparison: "PairComparison") -> str:
    """A clause for the explanation when the seed pairs' differences point both ways, else nothing."""
    differences = [first - second for first, second in zip(comparison.first_seed_rates, comparison.second_seed_rates)]
    if any(value > 0 for value in differences) and any(value < 0 for value in differences):
        return "the training seeds disagree in sign; "
    return ""


def networks_text(comparison: "PairComparison") -> str:
    """Each seed pair's networks in one clause: rates, Newcombe interval, McNemar p (uncorrected, networks only)."""
    parts = [
        f"seed {network.first_seed}"
        + (f"/{network.second_seed}" if network.second_seed != network.first_seed else "")
        + f": {network.first_rate:.1%} vs {network.second_rate:.1%}, "
        f"{interval_bounds(network.difference)}, McNemar {p_phrase(network.mcnemar.p_value)}"
        for network in comparison.networks
    ]
    return f"Per network pair ({comparison.level:.0%} intervals, uncorrected): " + "; ".join(parts)


def pairs_table(comparisons: Sequence["PairComparison"]) -> pd.DataFrame:
    """One row per pair of families, every cell a human-readable string; differences in percentage points."""
    rows = []
    for comparison in comparisons:
        level = f"{comparison.level:.0%}"
        rows.append(
            {
                "comparison": f"{comparison.first} vs {comparison.second}",
                "training seeds": str(comparison.seeds),
                "episodes per seed": str(comparison.episodes),
                "success (mean over seeds)": f"{comparison.first_rate:.1%} vs {comparison.second_rate:.1%}",
                f"difference, {level} interval over seeds (points)": (
                    interval_text(comparison.difference) if comparison.difference is not None else "n/a"
                ),
                "corrected p: difference / equivalence": (
                    f"{p_text(comparison.adjusted_p_value)} / {p_text(comparison.adjusted_equivalence_p_value)}"
                ),
                "networks per seed pair: difference (McNemar p)": "; ".join(
                    f"{signed_points(network.difference.estimate)} ({p_text(network.mcnemar.p_value)})"
                    for network in comparison.networks
                ),
                "verdict": comparison.verdict,
                "note": comparison.pairing_note,
            }
        )
    return pd.DataFrame(rows)


def seeds_text(seeds: int) -> str:
    """`n training seeds`, singular for one."""
    return "1 training seed" if seeds == 1 else f"{seeds} training seeds"


def signed_points(share: float) -> str:
    """A share as signed percentage points with one decimal."""
    return f"{100.0 * share:+.1f}"


def interval_bounds(interval: Interval) -> str:
    """An interval's bounds in signed points: `low to high`."""
    return f"{signed_points(interval.low)} to {signed_points(interval.high)}"


def interval_text(interval: Interval) -> str:
    """An interval as `estimate [low, high]` in signed points."""
    return f"{signed_points(interval.estimate)} [{signed_points(interval.low)}, {signed_points(interval.high)}]"


def p_phrase(p_value: float) -> str:
    """`p = ...` for a sentence, with four digits near alpha."""
    # Four digits between 0.01 and 0.1, so a p just below alpha does not print as alpha itself.
    if p_value < 1e-4:
        return "p < 0.0001"
    return f"p = {p_value:.4g}" if 0.01 <= p_value < 0.1 else f"p = {p_value:.2g}"


def p_text(p_value: float | None) -> str:
    """A p-value for a table cell; `n/a` for none."""
    if p_value is None:
        return "n/a"
    return "<0.0001" if p_value < 1e-4 else f"{p_value:.2g}"
