"""The report's section for a task without a simulator: no rollout, each family's action error on held-out episodes.

The evaluate stage scores such a task's policies offline (`carp.evaluation.offline.offline_evaluation`); this module
turns those summaries into tables with the statistics the rollout comparisons use: the training seed is the unit, a
family's figure is the mean over its seeds of each seed's error, with a Student-t interval over the seeds
(`carp.reporting.seed_inference.seed_mean_interval`) when it has two or more.
"""

import math
from collections.abc import Mapping

import pandas as pd

from carp.reporting.document import Section
from carp.reporting.seed_inference import seed_mean_interval

STEP_PREFIX = "step_rmse/"
DIMENSION_PREFIX = "dimension_rmse/"
ERRORS = {"executed_action_rmse": "executed rows", "action_rmse": "whole chunk"}
"""The summary's overall errors and their column names in the family table."""

OfflineRuns = Mapping[str, Mapping[int, Mapping]]
"""Policy label -> training seed -> that seed's offline evaluation summary (``reports/eval/<task>/<label>/...``)."""


def offline_section(task: str, runs: OfflineRuns, level: float = 0.95) -> Section:
    """The section of `task`: why no rollout ran, the families' errors, and their errors per dimension and step."""
    return Section(
        f"Offline evaluation on {task}",
        paragraphs=[
            f"No rollout was possible: {task} has no simulator carp knows (its demos are a LeRobotDataset), so it has "
            "no success rate. Each policy is scored instead by its predicted action chunks against the demonstrated "
            "ones on the held-out episodes, as a root mean squared error in the actions' units (lower is better). "
            "The executed rows are those a robot would run (rows To-1 to To-2+Ta of each chunk).",
            f"The unit is the training seed: a family's error is the mean over its seeds of each seed's error, and "
            f"its {100 * level:.0f}% interval is Student's t over the seeds (none with one seed). Every seed is "
            "scored on the same held-out episodes, so the interval is about the family's error on them. The other "
            "tables give the seed means per action dimension and per row of the chunk (horizon step).",
        ],
        tables=[
            offline_family_table(runs, level),
            offline_detail_table(runs, DIMENSION_PREFIX),
            offline_detail_table(runs, STEP_PREFIX),
        ],
    )


def offline_family_table(runs: OfflineRuns, level: float = 0.95) -> pd.DataFrame:
    """One row per policy: its seeds, held-out episodes, and each overall error's seed mean with its t interval."""
    rows = []
    for policy, by_seed in runs.items():
        summaries = [by_seed[seed] for seed in sorted(by_seed)]
        row = {
            "policy": policy,
            "seeds": len(summaries),
            "held-out episodes": int(summaries[0]["held_out_episodes"]),
        }
        for key, name in ERRORS.items():
            values = [float(summary[key]) for summary in summaries]
            row[f"RMSE, {name}"] = f"{sum(values) / len(values):.4g}"
            row[f"{100 * level:.0f}% interval, {name}"] = _interval(values, level)
        rows.append(row)
    return pd.DataFrame(rows)


def offline_detail_table(runs: OfflineRuns, prefix: str) -> pd.DataFrame:
    """One row per policy: the seed mean of every summary key starting with `prefix` (per dimension or per step)."""
    rows = []
    for policy, by_seed in runs.items():
        summaries = list(by_seed.values())
        keys = [key for key in summaries[0] if key.startswith(prefix)]
        if prefix == STEP_PREFIX:
            keys.sort(key=lambda key: int(key.removeprefix(prefix)))
        row = {"policy": policy}
        for key in keys:
            values = [float(summary[key]) for summary in summaries]
            row[key.removeprefix(prefix)] = f"{sum(values) / len(values):.4g}"
        rows.append(row)
    return pd.DataFrame(rows)


def _interval(values: list[float], level: float) -> str:
    if len(values) < 2:
        return "-"
    interval = seed_mean_interval(values, level, value_range=(0.0, math.inf))
    return f"{interval.low:.4g}-{interval.high:.4g}"
