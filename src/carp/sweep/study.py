"""The Optuna study: sample a grid point, train its tokenizer, prune or run the whole experiment, record it.

Resuming: the study lives in an SQLite (RDB) storage with heartbeats. A sweep killed mid-trial leaves that trial
``RUNNING``; once its heartbeat is older than the grace period (2 heartbeats) the storage marks it ``FAIL`` and
``RetryHeartbeatStaleTrialCallback`` (formerly ``RetryFailedTrialCallback``) queues a copy with the same params,
which the resumed sweep runs first. A trial stopped by Ctrl-C is marked ``FAIL`` by Optuna itself; it is tagged
``interrupted`` and queued again the same way. The budget counts finished trials (complete, pruned, failed) but not
failed trials that were retried, so ``num_trials`` holds across any number of resumes.

Trials run one at a time: each owns the workspace (params, outputs, ``dvc.lock``) while it runs.
"""

import logging
import time
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import optuna
from optuna.distributions import CategoricalDistribution
from optuna.exceptions import ExperimentalWarning
from optuna.storages import RDBStorage, RetryHeartbeatStaleTrialCallback, fail_stale_trials
from optuna.trial import FrozenTrial, TrialState

from carp.config import SweepConfig
from carp.sweep.outcome import (
    ExperimentResult,
    TrialRecord,
    best_record,
    best_tokenizer_error,
    should_prune,
    write_best_params,
    write_trials_csv,
)
from carp.sweep.space import (
    CODEBOOK_PARAM,
    SCALES_PARAM,
    TrialSettings,
    all_settings,
    codebook_choices,
    parse_schedule_label,
    scale_choices,
)
from carp.sweep.tracking import SweepTracker

logger = logging.getLogger(__name__)

# A trial killed again and again (e.g. it always runs out of memory) is given up after this many retries.
MAX_RETRIES = 2
PARENT_RUN_ATTR = "mlflow_parent_run_id"
TRIALS_FILE = "trials.csv"
BEST_PARAMS_FILE = "best_params.txt"
SAMPLER_SEED = 0


class ExperimentFailedError(RuntimeError):
    """An experiment (or its tokenizer stage) exited with an error; the trial fails and the sweep goes on."""


class SweepStateError(RuntimeError):
    """The stored study cannot be continued as asked (other search space, or another sweep is running it)."""


class ExperimentRunner(Protocol):
    """Runs the pipeline for one trial's settings (the sweep's only contact with DVC)."""

    def train_tokenizer(self, name: str, settings: TrialSettings) -> float:
        """Bring the pipeline up to the trained tokenizer; return its reconstruction RMSE (% of range).

        ``name`` is the experiment name the trial will use if it is not pruned.
        """
        ...

    def run_experiment(self, name: str, settings: TrialSettings) -> ExperimentResult:
        """Run the whole pipeline as an experiment called ``name``; return its metrics."""
        ...


@dataclass(frozen=True)
class SweepResult:
    """What a call of :func:`run_sweep` leaves behind.

    Attributes:
        records: every trial of the study so far, by number.
        best: the best completed trial (see :mod:`carp.sweep.outcome` for the ordering), if any.
        finished_trials: trials that count against the budget.
    """

    records: list[TrialRecord]
    best: TrialRecord | None
    finished_trials: int


def experiment_name(study_name: str, number: int) -> str:
    """DVC experiment name of a trial, e.g. ``sweep-carp-sweep-t3``."""
    return f"sweep-{study_name}-t{number}"


def run_sweep(
    config: SweepConfig,
    runner: ExperimentRunner,
    report_directory: Path,
    tracker: SweepTracker | None = None,
) -> SweepResult:
    """Run (or resume) the study until ``config.num_trials`` trials finished or the grid is exhausted.

    Args:
        config: the sweep section; ``config.storage`` must already be an absolute URL (e.g. ``sqlite:////abs/x.db``).
        runner: runs one trial's pipeline.
        report_directory: receives ``trials.csv`` and ``best_params.txt`` (rewritten after every trial).
        tracker: MLflow parent/child runs; ``None`` records nothing in MLflow.

    Raises:
        SweepStateError: the stored study has another search space, or another live sweep is running one of its
            trials.
    """
    study = _load_study(config)
    _check_search_space(study, config)
    _recover_interrupted_trials(study, config, tracker)

    parent_run_id = None
    if tracker is not None:
        parent_run_id = tracker.open_study(
            config.study_name,
            study.user_attrs.get(PARENT_RUN_ATTR),
            {
                "study_name": config.study_name,
                "scale_schedules": str(scale_choices(config)),
                "codebook_sizes": str(codebook_choices(config)),
                "prune_factor": str(config.prune_factor),
            },
        )
        study.set_user_attr(PARENT_RUN_ATTR, parent_run_id)

    def write_reports() -> SweepResult:
        trials = study.get_trials(deepcopy=False)
        records = [trial_record(trial) for trial in trials]
        result = SweepResult(records, best_record(records), finished_trial_count(trials))
        write_trials_csv(records, report_directory / TRIALS_FILE)
        write_best_params(result.best, report_directory / BEST_PARAMS_FILE)
        return result

    remaining = remaining_trials(study.get_trials(deepcopy=False), config)
    logger.info("study %s: %d trial(s) to run (budget %d)", config.study_name, remaining, config.num_trials)
    objective = _Objective(config, runner, tracker, parent_run_id)
    try:
        if remaining > 0:
            with _experimental_api():
                study.optimize(
                    objective,
                    n_trials=remaining,
                    catch=(ExperimentFailedError,),
                    callbacks=[lambda study, trial: write_reports()],
                )
    except BaseException:
        # Ctrl-C or a bug: the reports and the parent run still show where the sweep stopped.
        write_reports()
        if tracker is not None and parent_run_id is not None:
            tracker.interrupt_study(parent_run_id)
        raise
    result = write_reports()
    if tracker is not None and parent_run_id is not None:
        tracker.close_study(parent_run_id, result.best, result.finished_trials)
    return result


def trial_record(trial: FrozenTrial) -> TrialRecord:
    """Flatten an Optuna trial (params and the user attrs the objective sets) into a :class:`TrialRecord`."""
    settings = None
    if SCALES_PARAM in trial.params and CODEBOOK_PARAM in trial.params:
        settings = TrialSettings(parse_schedule_label(trial.params[SCALES_PARAM]), int(trial.params[CODEBOOK_PARAM]))
    attrs = trial.user_attrs
    return TrialRecord(
        number=trial.number,
        state=trial.state.name,
        settings=settings,
        success_rate=attrs.get("success_rate"),
        latency_ms=attrs.get("latency_ms"),
        tokenizer_rmse_percent=attrs.get("tokenizer_rmse_percent"),
        dvc_experiment=attrs.get("dvc_experiment") or "",
    )


def retried_trial_numbers(trials: Sequence[FrozenTrial]) -> set[int]:
    """Numbers of failed trials that a later trial retries (they do not count against the budget)."""
    retried: set[int] = set()
    with _experimental_api():
        for trial in trials:
            retried.update(RetryHeartbeatStaleTrialCallback.retry_history(trial))
    return retried


def finished_trial_count(trials: Sequence[FrozenTrial]) -> int:
    """Complete, pruned and failed trials, leaving out failed trials that were queued again."""
    retried = retried_trial_numbers(trials)
    finished = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL)
    return sum(1 for trial in trials if trial.state in finished and trial.number not in retried)


def remaining_trials(trials: Sequence[FrozenTrial], config: SweepConfig) -> int:
    """Trials still to run: the budget left, but no more than the grid points not tried yet plus queued retries."""
    retried = retried_trial_numbers(trials)
    tried = {
        record.settings
        for trial in trials
        if trial.state.is_finished() and trial.number not in retried
        for record in [trial_record(trial)]
        if record.settings is not None
    }
    waiting = sum(1 for trial in trials if trial.state == TrialState.WAITING)
    untried = len(set(all_settings(config)) - tried)
    return max(0, min(config.num_trials - finished_trial_count(trials), untried + waiting))


class _Objective:
    """One trial: tokenizer first (prune check), then the full experiment."""

    def __init__(
        self, config: SweepConfig, runner: ExperimentRunner, tracker: SweepTracker | None, parent_run_id: str | None
    ) -> None:
        self.config = config
        self.runner = runner
        self.tracker = tracker
        self.parent_run_id = parent_run_id

    def __call__(self, trial: optuna.Trial) -> float:
        settings = TrialSettings(
            parse_schedule_label(trial.suggest_categorical(SCALES_PARAM, scale_choices(self.config))),
            int(trial.suggest_categorical(CODEBOOK_PARAM, codebook_choices(self.config))),
        )
        # A retried trial inherits its predecessor's user attrs; start from a clean slate.
        for key in ("tokenizer_rmse_percent", "success_rate", "latency_ms", "dvc_experiment", "interrupted"):
            trial.set_user_attr(key, None)
        run_id = None
        if self.tracker is not None and self.parent_run_id is not None:
            run_id = self.tracker.start_trial(self.parent_run_id, self.config.study_name, trial.number, settings)
        trial.set_user_attr("mlflow_run_id", run_id)
        logger.info("trial %d: %s", trial.number, settings.command_line())
        try:
            value, state, name = self._run(trial, settings, run_id)
        except optuna.TrialPruned:
            self._end_run(run_id, "PRUNED")
            raise
        except KeyboardInterrupt:
            trial.set_user_attr("interrupted", True)
            self._end_run(run_id, "FAIL")
            raise
        except Exception:
            self._end_run(run_id, "FAIL")
            raise
        self._end_run(run_id, state, name)
        return value

    def _run(self, trial: optuna.Trial, settings: TrialSettings, run_id: str | None) -> tuple[float, str, str]:
        name = experiment_name(self.config.study_name, trial.number)
        error = self.runner.train_tokenizer(name, settings)
        trial.set_user_attr("tokenizer_rmse_percent", error)
        self._log(run_id, {"tokenizer_rmse_percent": error})
        others = [trial_record(other) for other in trial.study.get_trials(deepcopy=False)]
        best_error = best_tokenizer_error(others, exclude_number=trial.number)
        if should_prune(error, best_error, self.config.prune_factor):
            raise optuna.TrialPruned(
                f"tokenizer RMSE {error:.3g}% > {self.config.prune_factor} x best {best_error}% of the study"
            )
        result = self.runner.run_experiment(name, settings)
        trial.set_user_attr("dvc_experiment", name)
        trial.set_user_attr("success_rate", result.success_rate)
        trial.set_user_attr("latency_ms", result.latency_ms)
        trial.set_user_attr("tokenizer_rmse_percent", result.tokenizer_rmse_percent)
        self._log(
            run_id,
            {
                "success_rate": result.success_rate,
                "latency_ms": result.latency_ms,
                "tokenizer_rmse_percent": result.tokenizer_rmse_percent,
            },
        )
        return result.success_rate, "COMPLETE", name

    def _log(self, run_id: str | None, metrics: dict[str, float]) -> None:
        if self.tracker is not None and run_id is not None:
            self.tracker.log_trial_metrics(run_id, metrics)

    def _end_run(self, run_id: str | None, state: str, dvc_experiment: str = "") -> None:
        if self.tracker is not None and run_id is not None:
            self.tracker.end_trial(run_id, state, dvc_experiment)


@contextmanager
def _experimental_api() -> Iterator[None]:
    """Silence Optuna's experimental-feature warnings (heartbeats, retries, brute force) for deliberate uses."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ExperimentalWarning)
        yield


def _load_study(config: SweepConfig) -> optuna.Study:
    with _experimental_api():
        storage = RDBStorage(
            config.storage,
            heartbeat_interval=config.heartbeat_seconds,
            grace_period=2 * config.heartbeat_seconds,
            heartbeat_stale_trial_callback=RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRIES),
        )
        sampler = optuna.samplers.BruteForceSampler(seed=SAMPLER_SEED)
    return optuna.create_study(
        study_name=config.study_name,
        storage=storage,
        sampler=sampler,
        direction="maximize",
        load_if_exists=True,
    )


def _check_search_space(study: optuna.Study, config: SweepConfig) -> None:
    expected = {
        SCALES_PARAM: CategoricalDistribution(scale_choices(config)),
        CODEBOOK_PARAM: CategoricalDistribution(codebook_choices(config)),
    }
    for trial in study.get_trials(deepcopy=False):
        for name, distribution in trial.distributions.items():
            if expected.get(name) != distribution:
                raise SweepStateError(
                    f"study '{config.study_name}' was created with {name} choices {list(distribution.choices)}, "
                    f"params now give {list(expected[name].choices) if name in expected else 'none'}; "
                    "use a new sweep.study_name for a new search space"
                )


def _recover_interrupted_trials(study: optuna.Study, config: SweepConfig, tracker: SweepTracker | None) -> None:
    """Fail and queue again the trials that a killed or interrupted sweep left behind."""
    retried = retried_trial_numbers(study.get_trials(deepcopy=False))
    with _experimental_api():
        retry = RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRIES)
        for trial in study.get_trials(deepcopy=False, states=(TrialState.FAIL,)):
            if trial.user_attrs.get("interrupted") and trial.number not in retried:
                logger.info("trial %d was interrupted; queueing it again", trial.number)
                retry(study, trial)

    running = study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
    if not running:
        return
    # Heartbeats are written every `heartbeat_seconds`; a dead sweep's trial is stale after the grace period.
    grace_seconds = 2 * config.heartbeat_seconds
    logger.info(
        "trial(s) %s were left running; waiting up to %d s for their heartbeat to expire",
        [trial.number for trial in running],
        grace_seconds,
    )
    deadline = time.monotonic() + grace_seconds + 2 * config.heartbeat_seconds
    left_running_runs = [trial.user_attrs.get("mlflow_run_id") for trial in running]
    while True:
        with _experimental_api():
            fail_stale_trials(study)
        running = study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
        if not running:
            break
        if time.monotonic() > deadline:
            raise SweepStateError(
                f"trial(s) {[trial.number for trial in running]} of study '{config.study_name}' are still running "
                "with a fresh heartbeat: another sweep is working on this study (run one sweep per workspace)"
            )
        time.sleep(1.0)
    if tracker is not None:
        for run_id in left_running_runs:
            if run_id:
                tracker.end_trial(run_id, "FAIL")
