"""Summary statistics of an evaluation: success rate with a Wilson score interval, episode lengths, latency."""

import math
from collections.abc import Sequence

import numpy as np

# Two-sided 95% normal quantile.
Z_95 = 1.959963984540054


def wilson_interval(successes: int, trials: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (better than the normal interval near 0 and 1).

    Args:
        successes: number of successes, 0 <= successes <= trials.
        trials: number of trials; 0 gives the uninformative (0, 1).
        z: normal quantile of the confidence level (1.96 for 95%).

    Returns:
        (lower, upper) bounds in [0, 1].
    """
    if not 0 <= successes <= trials:
        raise ValueError(f"successes={successes} must lie in [0, trials={trials}]")
    if trials == 0:
        return 0.0, 1.0
    proportion = successes / trials
    denominator = 1.0 + z * z / trials
    center = (proportion + z * z / (2 * trials)) / denominator
    half_width = z * math.sqrt(proportion * (1 - proportion) / trials + z * z / (4 * trials * trials)) / denominator
    return max(0.0, center - half_width), min(1.0, center + half_width)


def latency_summary(seconds: Sequence[float], prefix: str) -> dict[str, float]:
    """Median and p90 in milliseconds, keyed ``<prefix>_ms_median`` / ``<prefix>_ms_p90`` (NaN when empty)."""
    values = np.asarray(seconds, dtype=np.float64) * 1000.0
    if values.size == 0:
        return {f"{prefix}_ms_median": float("nan"), f"{prefix}_ms_p90": float("nan")}
    return {f"{prefix}_ms_median": float(np.median(values)), f"{prefix}_ms_p90": float(np.percentile(values, 90))}
