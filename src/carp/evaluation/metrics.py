"""Summary statistics of an evaluation: success rate with a Wilson score interval, episode lengths, latency.

The interval itself lives in ``carp.evaluation.statistics``; it is imported here for this module's users.
"""

from collections.abc import Sequence

import numpy as np

from carp.evaluation.statistics import wilson_interval


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
