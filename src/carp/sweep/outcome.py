"""What a trial produced, how trials are ranked and pruned, and the sweep's trials table.

Every figure of a trial comes from the *validation* seeds (``eval.validation_seed`` on): the trial's evaluation
selects each run's checkpoint on them (``best_validation``) and runs no test episode (``eval.run_test: false``), so
that choosing settings never looks at the test seeds, which stay for the confirmation (:mod:`carp.sweep.confirmation`).

Ranking: the objective is the selected checkpoints' validation score (mean over the evaluated runs), maximized: each
task's headline score (`carp.evaluation.metrics.task_score`), which is the success rate on the arm tasks and DP's mean
maximum reward on Push-T, where a short training rarely finishes an episode but its coverage still tells trials
apart. Scores are means over small episode counts, so ties are common; among tied trials the higher validation
success rate wins, then the lower inference latency, then the earlier trial. Optuna itself only sees the score (a
single objective keeps its samplers, pruners and ``best_trial`` simple); :func:`best_record` applies the full
ordering. The best of many trials is an optimistic estimate of its own settings (the winner's curse); the
confirmation measures it again on the test seeds.

Pruning: the tokenizer is trained first; a trial whose tokenizer reconstruction error is more than
``prune_factor`` times the best error seen so far in the study stops before the (costly) policy training. Later,
Optuna's pruner may stop it from its snapshots' validation scores (:mod:`carp.sweep.pruning`).
"""

import csv
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from carp.outputs import atomic_path
from carp.sweep.space import TrialSettings, schedule_label

TRIALS_COLUMNS = (
    "trial",
    "state",
    "scales",
    "num_scales",
    "codebook_size",
    "validation_score",
    "validation_success_rate",
    "latency_ms",
    "pareto",
    "validated_candidates",
    "tokenizer_rmse_percent",
    "dvc_experiment",
)
"""``pareto``: true for a completed trial that no other completed trial beats on both validation score and latency
(:func:`pareto_front`); ``validated_candidates``: the candidates whose validation the trial reported to the pruner."""


@dataclass(frozen=True)
class ExperimentResult:
    """Metrics of one fully run trial experiment, all from the validation seeds.

    Attributes:
        validation_success_rate: the selected checkpoints' validation success rate in [0, 1], mean over the
            evaluated runs (tasks x policies x training seeds).
        latency_ms: median inference latency per action chunk (prediction + decoding) in the validation episodes,
            mean over the runs.
        tokenizer_rmse_percent: tokenizer reconstruction RMSE in percent of each dimension's range, mean over
            dimensions (``rmse_percent_range/mean`` of ``reports/tokenizer/metrics.json``).
        validation_score: the selected checkpoints' validation score in [0, 1], mean over the runs (the objective);
            None: the validation success rate.
    """

    validation_success_rate: float
    latency_ms: float
    tokenizer_rmse_percent: float
    validation_score: float | None = None

    @property
    def objective(self) -> float:
        """What the sweep maximizes: the validation score."""
        return self.validation_success_rate if self.validation_score is None else self.validation_score


@dataclass(frozen=True)
class TrialRecord:
    """One trial as the reports see it; metrics are ``None`` where the trial never got that far.

    Attributes:
        number: Optuna trial number.
        state: Optuna state name (``COMPLETE``, ``PRUNED``, ``FAIL``, ``RUNNING``, ``WAITING``).
        settings: the trial's params, ``None`` before they were sampled.
        validation_success_rate: see :class:`ExperimentResult`.
        latency_ms: see :class:`ExperimentResult`.
        tokenizer_rmse_percent: see :class:`ExperimentResult`.
        dvc_experiment: name of the trial's DVC experiment (only completed trials have one).
        validation_score: see :class:`ExperimentResult`.
        validated_candidates: how many candidates' validations the trial reported to the pruner.
    """

    number: int
    state: str
    settings: TrialSettings | None
    validation_success_rate: float | None = None
    latency_ms: float | None = None
    tokenizer_rmse_percent: float | None = None
    dvc_experiment: str = ""
    validation_score: float | None = None
    validated_candidates: int = 0

    @property
    def objective(self) -> float | None:
        """What the sweep maximizes: the validation score (the validation success rate for a record that has none)."""
        return self.validation_success_rate if self.validation_score is None else self.validation_score


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
    """Sort key, best first: higher validation score, then higher validation success, lower latency, earlier trial."""
    assert record.objective is not None and record.validation_success_rate is not None and record.latency_ms is not None
    return (-record.objective, -record.validation_success_rate, record.latency_ms, record.number)


def completed_records(records: Iterable[TrialRecord]) -> list[TrialRecord]:
    """The completed trials that carry the figures ranking needs."""
    return [
        record
        for record in records
        if record.state == "COMPLETE" and record.validation_success_rate is not None and record.latency_ms is not None
    ]


def best_record(records: Iterable[TrialRecord]) -> TrialRecord | None:
    """The best completed trial under :func:`ranking_key`, ``None`` before any trial completed."""
    return min(completed_records(records), key=ranking_key, default=None)


def pareto_front(records: Iterable[TrialRecord]) -> list[TrialRecord]:
    """The completed trials that no other completed trial beats on validation score and latency per chunk at once.

    A trial is beaten when another scores at least as high and is at least as fast, and strictly better on one of
    the two. The front is read from the finished trials; the Optuna study itself keeps one objective.
    """
    complete = completed_records(records)

    def beaten(record: TrialRecord) -> bool:
        assert record.objective is not None and record.latency_ms is not None
        return any(
            other.objective >= record.objective
            and other.latency_ms <= record.latency_ms
            and (other.objective > record.objective or other.latency_ms < record.latency_ms)
            for other in complete
            if other.objective is not None and other.latency_ms is not None
        )

    return sorted((record for record in complete if not beaten(record)), key=ranking_key)


def write_trials_csv(records: Sequence[TrialRecord], path: Path) -> None:
    """Write ``trials.csv`` (columns :data:`TRIALS_COLUMNS`, one row per trial, empty cells for missing values)."""
    rows = []
    front = {record.number for record in pareto_front(records)}
    for record in sorted(records, key=lambda record: record.number):
        settings = record.settings
        rows.append(
            {
                "trial": record.number,
                "state": record.state,
                "scales": schedule_label(settings.scales) if settings else "",
                "num_scales": settings.num_scales if settings else "",
                "codebook_size": settings.codebook_size if settings else "",
                "validation_score": _cell(record.objective),
                "validation_success_rate": _cell(record.validation_success_rate),
                "latency_ms": _cell(record.latency_ms),
                "pareto": record.number in front,
                "validated_candidates": record.validated_candidates,
                "tokenizer_rmse_percent": _cell(record.tokenizer_rmse_percent),
                "dvc_experiment": record.dvc_experiment,
            }
        )
    with atomic_path(path) as temporary, temporary.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=TRIALS_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)


def _cell(value: float | None) -> str | float:
    return "" if value is None else value
