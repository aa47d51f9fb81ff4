"""Summary statistics of an evaluation: success rate with its interval, episode lengths, latency, task measures.

The success rate gets a Wilson score interval, a task's per-episode measures their mean and variance. The report's
comparisons of families (``carp.reporting.statistics``) build on the same interval.
"""

import math
from collections.abc import Mapping, Sequence

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
    # At 0 (or all) successes the bound is exactly 0 (or 1); rounding would put it a hair above (or below).
    lower = 0.0 if successes == 0 else max(0.0, center - half_width)
    upper = 1.0 if successes == trials else min(1.0, center + half_width)
    return lower, upper


def latency_summary(seconds: Sequence[float], prefix: str) -> dict[str, float]:
    """Median and p90 in milliseconds, keyed ``<prefix>_ms_median`` / ``<prefix>_ms_p90`` (NaN when empty)."""
    values = np.asarray(seconds, dtype=np.float64) * 1000.0
    if values.size == 0:
        return {f"{prefix}_ms_median": float("nan"), f"{prefix}_ms_p90": float("nan")}
    return {f"{prefix}_ms_median": float(np.median(values)), f"{prefix}_ms_p90": float(np.percentile(values, 90))}


def summarize_episodes(
    successes: Sequence[bool],
    steps: Sequence[int],
    crashed: Sequence[bool],
    prediction_seconds: Sequence[float],
    decoding_seconds: Sequence[float],
) -> dict[str, float]:
    """The metrics of one task's evaluation (the keys of ``reports/eval/<task>/<policy>/seed<seed>.json``).

    Args:
        successes: per episode, whether the env's success check fired.
        steps: per episode, steps taken.
        crashed: per episode, whether it ended in an exception.
        prediction_seconds: per chunk, coarse-to-fine prediction time (batch 1).
        decoding_seconds: per chunk, token -> action decoding time (batch 1).
    """
    episodes = len(successes)
    successful = int(sum(bool(s) for s in successes))
    lower, upper = wilson_interval(successful, episodes)
    return {
        "episodes": episodes,
        "successes": successful,
        "success_rate": successful / episodes if episodes else float("nan"),
        "success_rate_ci_low": lower,
        "success_rate_ci_high": upper,
        "mean_episode_steps": float(np.mean(steps)) if episodes else float("nan"),
        "crashed_episodes": int(sum(bool(c) for c in crashed)),
        **latency_summary(prediction_seconds, "latency_predict"),
        **latency_summary(decoding_seconds, "latency_decode"),
    }


def task_score(summary: Mapping[str, float], score_measure: str | None) -> float:
    """A task's headline score from an evaluation summary, NaN when no episode measured it.

    The mean of the task's score measure where it has one (Push-T: DP's mean over episodes of the highest reward),
    else the success rate, which is an arm task's score too (its sparse reward is 1 exactly on success).
    """
    if score_measure is None:
        return float(summary["success_rate"])
    return float(summary.get(f"{score_measure}_mean", float("nan")))


def measure_summary(measures: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """Per task measure, over the episodes that measured it (a finite value): mean, variance and their count.

    Keys ``<name>_mean``, ``<name>_variance`` (the sample variance, n - 1) and ``<name>_episodes``, for every name
    found in any episode; the mean is NaN without a value and the variance NaN with fewer than two.

    Args:
        measures: per episode, its task measures (`EpisodeResult.task_measures`; empty for a task without any).
    """
    summary: dict[str, float] = {}
    for name in dict.fromkeys(name for episode in measures for name in episode):
        values = np.array([episode.get(name, np.nan) for episode in measures], dtype=np.float64)
        values = values[np.isfinite(values)]
        summary[f"{name}_mean"] = float(values.mean()) if values.size else float("nan")
        summary[f"{name}_variance"] = float(values.var(ddof=1)) if values.size > 1 else float("nan")
        summary[f"{name}_episodes"] = int(values.size)
    return summary
