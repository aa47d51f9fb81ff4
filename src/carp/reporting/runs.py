"""The evaluations a report compares: per task, family and training seed, the summary and the test episodes.

Read from `reports/eval/<task>/<family>/seed<seed>.json` and its `_episodes.csv`, merged with referenced folders, and
turned into the arrays the statistics take. Episodes pair across families by their episode seed (the same initial
state), and training seeds pair by number.
"""

import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from carp.reporting import statistics


@dataclass(frozen=True)
class RunResults:
    """One training seed's evaluation of one family on one task.

    Attributes:
        metrics: the evaluation summary (``reports/eval/<task>/<family>/seed<seed>.json``).
        episodes: the test episodes (``seed<seed>_episodes.csv``): at least ``seed``, ``success`` and ``steps``.
    """

    metrics: Mapping[str, Any]
    episodes: pd.DataFrame


Runs = Mapping[int, RunResults]
"""Training seed -> that seed's results, for one family on one task."""


EPISODE_RECORD_COLUMNS = frozenset({"seed", "success", "steps", "seconds", "chunks", "chunk_ms_median", "error"})
"""Columns every episodes table has; any other numeric column is a task's own per-episode measure."""


def outcomes_by_seed(runs: Runs, episode_seeds: Sequence[int] | None = None) -> dict[int, np.ndarray]:
    """Training seed -> (N,) bool test successes ordered by episode seed, restricted to `episode_seeds` if given."""
    return _episode_column(runs, "success", bool, episode_seeds)


def steps_by_seed(runs: Runs, episode_seeds: Sequence[int] | None = None) -> dict[int, np.ndarray]:
    """Training seed -> (N,) int steps of each test episode, in the order of `outcomes_by_seed`."""
    return _episode_column(runs, "steps", np.int64, episode_seeds)


def _episode_column(runs: Runs, column: str, dtype, episode_seeds: Sequence[int] | None) -> dict[int, np.ndarray]:
    """Training seed -> one column of its test episodes, ordered by episode seed (optionally only `episode_seeds`)."""
    values = {}
    for seed, run in sorted(runs.items()):
        episodes = run.episodes.sort_values("seed")
        if episode_seeds is not None:
            episodes = episodes[episodes["seed"].isin(episode_seeds)]
        values[seed] = episodes[column].to_numpy(dtype=dtype)
    return values


EVALUATION_SUMMARY_PATTERN = re.compile(r"seed(\d+)\.json")
"""File name of one training seed's evaluation summary in an evaluation directory (``seed<k>.json``)."""


def read_run_results(summary: Path) -> RunResults:
    """One evaluation summary (``seed<k>.json``) and the test episodes beside it (``seed<k>_episodes.csv``)."""
    summary = Path(summary)
    return RunResults(json.loads(summary.read_text()), pd.read_csv(summary.with_name(f"{summary.stem}_episodes.csv")))


def referenced_runs(eval_dir: Path, tasks: Sequence[str]) -> dict[str, dict[str, dict[int, RunResults]]]:
    """Every evaluation of `tasks` in another run's evaluation directory: task -> label -> training seed -> results.

    Args:
        eval_dir: that run's ``reports/eval`` (``<task>/<label>/seed<k>.json`` with its episodes beside it; a label
            is a family, or ``<family>-multitask`` for a multi-task policy).
        tasks: the tasks to read; a task the directory lacks gives nothing.

    Raises:
        FileNotFoundError: `eval_dir` is not a directory, or a summary has no episodes file beside it.
    """
    eval_dir = Path(eval_dir)
    if not eval_dir.is_dir():
        raise FileNotFoundError(f"{eval_dir}: no such evaluation directory")
    found: dict[str, dict[str, dict[int, RunResults]]] = {}
    for task in tasks:
        task_dir = eval_dir / task
        for label_dir in sorted(path for path in task_dir.iterdir() if path.is_dir()) if task_dir.is_dir() else ():
            for summary in sorted(label_dir.iterdir()):
                matched = EVALUATION_SUMMARY_PATTERN.fullmatch(summary.name)
                if matched is None:
                    continue
                if not summary.with_name(f"{summary.stem}_episodes.csv").is_file():
                    raise FileNotFoundError(f"{summary}: no {summary.stem}_episodes.csv beside it")
                runs = found.setdefault(task, {}).setdefault(label_dir.name, {})
                runs[int(matched.group(1))] = read_run_results(summary)
    return found


def merge_runs(
    own: Mapping[str, Mapping[str, Runs]], referenced: Mapping[str, Mapping[str, Runs]], source: str
) -> dict[str, dict[str, dict[int, RunResults]]]:
    """Both runs' evaluations (task -> label -> training seed -> results), the training seeds of a label added up.

    Raises:
        ValueError: both have the same training seed of a label on a task; the message names `source`, the task,
            the label and the seed.
    """
    merged = {task: {label: dict(runs) for label, runs in labels.items()} for task, labels in own.items()}
    for task, labels in referenced.items():
        for label, runs in labels.items():
            mine = merged.setdefault(task, {}).setdefault(label, {})
            for seed, run in runs.items():
                if seed in mine:
                    raise ValueError(f"{source}: {task}/{label} training seed {seed} is already in the report")
                mine[seed] = run
    return merged


def add_referenced_runs(
    own: Mapping[str, Mapping[str, Runs]],
    references: Mapping[str, Path],
    tasks: Sequence[str],
    params_key: str = "comparison.references",
) -> tuple[dict[str, dict[str, dict[int, RunResults]]], dict[str, str]]:
    """The run's evaluations with those of other runs added (`comparison.references`), and what came from where.

    Args:
        own: the run's own evaluations, task -> label -> training seed -> results.
        references: name (as the params give it) -> that run's evaluation directory (:func:`referenced_runs`).
        tasks: the run's tasks; other tasks of a reference are left out.
        params_key: the param that names the references, for the sentences.

    Returns:
        The merged evaluations (:func:`merge_runs`) and, per task with referenced evaluations, a sentence naming
        each referenced label, its training seeds and where they came from.

    Raises:
        FileNotFoundError, ValueError: from :func:`referenced_runs` and :func:`merge_runs`.
    """
    merged = {task: dict(labels) for task, labels in own.items()}
    sources: dict[str, list[str]] = {}
    for name, eval_dir in references.items():
        referenced = referenced_runs(eval_dir, tasks)
        merged = merge_runs(merged, referenced, name)
        for task, labels in referenced.items():
            sources.setdefault(task, []).extend(
                f"{label} (training seeds {', '.join(map(str, sorted(runs)))}) from {name}"
                for label, runs in labels.items()
            )
    notes = {task: f"Evaluations of other runs ({params_key}): {'; '.join(found)}." for task, found in sources.items()}
    return merged, notes


def split_multitask(
    runs: Mapping[str, Mapping[str, Runs]], suffix: str
) -> tuple[dict[str, dict[str, Runs]], dict[str, dict[str, Runs]]]:
    """Single-task and multi-task evaluations apart: labels ending in `suffix` are a family's multi-task policy.

    Returns:
        task -> family -> runs of the single-task policies, and task -> family -> runs of the multi-task ones (the
        family named without `suffix`; a task without any is left out).
    """
    single = {
        task: {label: seeds for label, seeds in labels.items() if not label.endswith(suffix)}
        for task, labels in runs.items()
    }
    multi = {
        task: {label.removesuffix(suffix): seeds for label, seeds in labels.items() if label.endswith(suffix)}
        for task, labels in runs.items()
    }
    return single, {task: families for task, families in multi.items() if families}


def pooled_metrics(runs: Runs) -> dict[str, Any]:
    """One family's metrics over its training seeds, in the keys of a single evaluation summary.

    Successes and episodes add up; the mean episode length is over every episode; latencies and the policy's facts
    are the median over seeds (the same network at every seed). ``seeds`` counts the training seeds.
    """
    summaries = [run.metrics for _, run in sorted(runs.items())]
    pooled: dict[str, Any] = dict(summaries[0])
    episodes = sum(int(summary["episodes"]) for summary in summaries)
    successes = sum(int(summary["successes"]) for summary in summaries)
    low, high = statistics.wilson_interval(successes, episodes)
    pooled.update(
        episodes=episodes,
        successes=successes,
        success_rate=successes / episodes,
        success_rate_ci_low=low,
        success_rate_ci_high=high,
        crashed_episodes=sum(int(summary.get("crashed_episodes", 0)) for summary in summaries),
        mean_episode_steps=float(np.mean(np.concatenate([run.episodes["steps"].to_numpy() for run in runs.values()]))),
        seeds=len(summaries),
    )
    if all("repaired_chunks" in summary for summary in summaries):
        repaired = sum(int(summary["repaired_chunks"]) for summary in summaries)
        predicted = sum(int(summary["predicted_chunks"]) for summary in summaries)
        pooled.update(repaired_chunks=repaired, predicted_chunks=predicted, repaired_chunk_rate=repaired / predicted)
    for key in summaries[0]:
        if "latency" in key and key.endswith(("_median", "_p90")):
            pooled[key] = float(np.median([summary[key] for summary in summaries if key in summary]))
    return pooled


def measure_columns(task_runs: Mapping[str, Runs]) -> list[str]:
    """The task's per-episode measures (e.g. Square's ``insertion_offset_mm``) found in its episodes tables."""
    columns: list[str] = []
    for runs in task_runs.values():
        for run in runs.values():
            for column in run.episodes.columns:
                numeric = pd.api.types.is_numeric_dtype(run.episodes[column])
                if column not in EPISODE_RECORD_COLUMNS and numeric and column not in columns:
                    columns.append(column)
    return columns


def pooled_measure(runs: Runs, column: str) -> np.ndarray:
    """One family's values of a per-episode measure over all its seeds' test episodes (NaN where not measured)."""
    frames = [run.episodes[column] for run in runs.values() if column in run.episodes]
    return np.concatenate([frame.to_numpy(dtype=float) for frame in frames]) if frames else np.array([])
