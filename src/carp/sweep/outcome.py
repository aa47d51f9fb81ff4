"""What a trial produced, how trials are ranked and pruned, and the sweep's two report files.

Ranking: the objective is the evaluation score (mean over tasks), maximized: each task's headline score
(`carp.evaluation.metrics.task_score`), which is the success rate on the arm tasks and DP's mean maximum reward on
Push-T, where a short training rarely finishes an episode but its coverage still tells trials apart. Scores are
means over small episode counts, so ties are common; among tied trials the higher success rate wins, then the lower
inference latency, then the earlier trial. Optuna itself only sees the score (a single objective keeps its samplers
and ``best_trial`` simple); :func:`best_record` applies the full ordering.

Pruning: the tokenizer is trained first; a trial whose tokenizer reconstruction error is more than
``prune_factor`` times the best error seen so far in the study stops before the (costly) policy training.
"""

import csv
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from carp.sweep.space import TrialSettings, schedule_label

TRIALS_COLUMNS = (
    "trial",
    "state",
    "scales",
    "num_scales",
    "codebook_size",
    "score",
    "success_rate",
    "latency_ms",
    "tokenizer_rmse_percent",
    "dvc_experiment",
)


@dataclass(frozen=True)
class ExperimentResult:
    """Metrics of one fully run experiment.

    Attributes:
        success_rate: evaluation success rate in [0, 1], mean over the pipeline's tasks.
        latency_ms: median inference latency per action chunk (prediction + decoding), mean over tasks.
        tokenizer_rmse_percent: tokenizer reconstruction RMSE in percent of each dimension's range, mean over
            dimensions (``rmse_percent_range/mean`` of ``reports/tokenizer/metrics.json``).
        score: the evaluation score in [0, 1], mean over the pipeline's tasks (the objective); None: the success rate.
    """

    success_rate: float
    latency_ms: float
    tokenizer_rmse_percent: float
    score: float | None = None

    @property
    def objective(self) -> float:
        """What the sweep maximizes: the score."""
        return self.success_rate if self.score is None else self.score


@dataclass(frozen=True)
class TrialRecord:
    """One trial as the reports see it; metrics are ``None`` where the trial never got that far.

    Attributes:
        number: Optuna trial number.
        state: Optuna state name (``COMPLETE``, ``PRUNED``, ``FAIL``, ``RUNNING``, ``WAITING``).
        settings: the trial's params, ``None`` before they were sampled.
        dvc_experiment: name of the trial's DVC experiment (only completed trials have one).
    """

    number: int
    state: str
    settings: TrialSettings | None
    success_rate: float | None = None
    latency_ms: float | None = None
    tokenizer_rmse_percent: float | None = None
    dvc_experiment: str = ""
    score: float | None = None

    @property
    def objective(self) -> float | None:
        """What the sweep maximizes: the score (the success rate for a record that has none)."""
        return self.success_rate if self.score is None else self.score


def should_prune(tokenizer_error: float, best_error: float | None, prune_factor: float) -> bool:
    """Whether a trial stops after its tokenizer.

    Args:
        tokenizer_error: this trial's reconstruction RMSE (% of range); NaN (a diverged tokenizer) always prunes.
        best_error: lowest error of the study's other trials, ``None`` when this is the first.
        prune_factor: tolerated ratio to the best error (> 1).
    """
    if math.isnan(tokenizer_error):
        return True
    return best_error is not None and tokenizer_error > prune_factor * best_error


def best_tokenizer_error(records: Iterable[TrialRecord], exclude_number: int | None = None) -> float | None:
    """Lowest finite tokenizer error among the records (any state), ``None`` when there is none."""
    errors = [
        record.tokenizer_rmse_percent
        for record in records
        if record.number != exclude_number
        and record.tokenizer_rmse_percent is not None
        and not math.isnan(record.tokenizer_rmse_percent)
    ]
    return min(errors, default=None)


def ranking_key(record: TrialRecord) -> tuple[float, float, float, int]:
    """Sort key, best first: higher score, then higher success, then lower latency, then earlier trial."""
    assert record.objective is not None and record.success_rate is not None and record.latency_ms is not None
    return (-record.objective, -record.success_rate, record.latency_ms, record.number)


def best_record(records: Iterable[TrialRecord]) -> TrialRecord | None:
    """The best completed trial under :func:`ranking_key`, ``None`` before any trial completed."""
    complete = [
        record
        for record in records
        if record.state == "COMPLETE" and record.success_rate is not None and record.latency_ms is not None
    ]
    return min(complete, key=ranking_key, default=None)


def write_trials_csv(records: Sequence[TrialRecord], path: Path) -> None:
    """Write ``trials.csv`` (columns :data:`TRIALS_COLUMNS`, one row per trial, empty cells for missing values)."""
    rows = []
    for record in sorted(records, key=lambda record: record.number):
        settings = record.settings
        rows.append(
            {
                "trial": record.number,
                "state": record.state,
                "scales": schedule_label(settings.scales) if settings else "",
                "num_scales": settings.num_scales if settings else "",
                "codebook_size": settings.codebook_size if settings else "",
                "score": _cell(record.objective),
                "success_rate": _cell(record.success_rate),
                "latency_ms": _cell(record.latency_ms),
                "tokenizer_rmse_percent": _cell(record.tokenizer_rmse_percent),
                "dvc_experiment": record.dvc_experiment,
            }
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    with temporary.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=TRIALS_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    os.replace(temporary, path)


def write_best_params(record: TrialRecord | None, path: Path) -> None:
    """Write the best trial's ``-S`` arguments (one line, ready for ``dvc exp run``); no file before a best exists."""
    if record is None or record.settings is None:
        path.unlink(missing_ok=True)
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(record.settings.command_line() + "\n")


def _cell(value: float | None) -> str | float:
    return "" if value is None else value
