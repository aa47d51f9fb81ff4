"""The Optuna study: claim a grid point, train its tokenizer, prune or run the whole experiment, record it.

Workers: any number of sweep processes, each in its own workspace, may work on one study at once through its RDB
storage (SQLite on one machine, PostgreSQL across machines). Each repeatedly takes up a queued retry, or claims an
untried grid point in the database (:mod:`carp.sweep.claims`) and creates a trial with that point's params; no two
workers run the same point, and at most ``num_trials`` points are ever claimed, so the budget holds across workers and
across restarts. A worker with nothing left to claim waits until no trial of the study is running or queued (another
worker's trial may still fail and be retried), so every worker ends with the whole study in its reports.

Retries: a worker killed mid-trial leaves that trial ``RUNNING``; once its heartbeat is older than the grace period
(2 heartbeats) another worker (or the restarted one) marks it ``FAIL`` and ``RetryHeartbeatStaleTrialCallback``
queues a copy with the same params, which the next free worker takes up, moving the point's claim to it. A trial
stopped by Ctrl-C is marked ``FAIL``, tagged ``interrupted`` and queued again the same way before the worker exits.
The budget counts finished trials (complete, pruned, failed) but not failed trials that were retried.

Within a workspace trials run one at a time: each owns the workspace (params, outputs, ``dvc.lock``) while it runs.
"""

import logging
import random
import threading
import time
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import optuna
from optuna.distributions import CategoricalDistribution
from optuna.exceptions import ExperimentalWarning, UpdateFinishedTrialError
from optuna.storages import RDBStorage, RetryHeartbeatStaleTrialCallback, fail_stale_trials
from optuna.trial import FrozenTrial, TrialState
from sqlalchemy.exc import IntegrityError, ProgrammingError, SQLAlchemyError

from carp.config import SweepConfig
from carp.sweep.claims import ClaimLostError, ClaimStore
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
    point_key,
    scale_choices,
    schedule_label,
)
from carp.sweep.tracking import SweepTracker

logger = logging.getLogger(__name__)

# A trial killed again and again (e.g. it always runs out of memory) is given up after this many retries.
MAX_RETRIES = 2
PARENT_RUN_ATTR = "mlflow_parent_run_id"
# Set on a trial whose worker lost its point's claim before the trial started; it never ran and does not count.
CLAIM_LOST_ATTR = "carp_claim_lost"
TRIALS_FILE = "trials.csv"
BEST_PARAMS_FILE = "best_params.txt"
# Seeds the order in which workers claim grid points: a budget smaller than the grid gets a spread-out sample of it
# rather than the first schedules, and every worker uses the same order.
CLAIM_ORDER_SEED = 0
SCHEMA_ATTEMPTS = 5


class ExperimentFailedError(RuntimeError):
    """An experiment (or its tokenizer stage) exited with an error; the trial fails and the sweep goes on."""


class SweepStateError(RuntimeError):
    """The stored study cannot be continued as asked (another search space)."""


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
    """Work on the study until its budget is spent or its grid exhausted and no trial of it runs or waits.

    Other workers may work on the same study at the same time (each with its own runner and workspace).

    Args:
        config: the sweep section; ``config.storage`` must already be an absolute URL (e.g. ``sqlite:////abs/x.db``).
        runner: runs one trial's pipeline.
        report_directory: receives ``trials.csv`` and ``best_params.txt`` (rewritten after every trial).
        tracker: MLflow parent/child runs; ``None`` records nothing in MLflow.

    Raises:
        SweepStateError: the stored study has another search space.
    """
    study, study_id = _load_study(config)
    _check_search_space(study, config)
    claims = ClaimStore(config.storage, study_id)
    try:
        return _work(study, config, claims, runner, report_directory, tracker)
    finally:
        claims.close()


def _work(
    study: optuna.Study,
    config: SweepConfig,
    claims: ClaimStore,
    runner: ExperimentRunner,
    report_directory: Path,
    tracker: SweepTracker | None,
) -> SweepResult:
    _claim_existing_trials(study, claims)
    parent_run_id = None
    if tracker is not None:
        parent_run_id = _open_parent_run(study, config, claims, tracker)

    def write_reports() -> SweepResult:
        trials = study.get_trials(deepcopy=False)
        records = [trial_record(trial) for trial in trials]
        result = SweepResult(records, best_record(records), finished_trial_count(trials))
        write_trials_csv(records, report_directory / TRIALS_FILE)
        write_best_params(result.best, report_directory / BEST_PARAMS_FILE)
        return result

    logger.info(
        "study %s: %d of %d budgeted point(s) claimed", config.study_name, len(claims.claims()), config.num_trials
    )
    objective = _Objective(config, runner, tracker, parent_run_id)
    waiting_for: list[int] = []
    try:
        while True:
            _fail_stale_trials(study, tracker)
            trial = _next_trial(study, config, claims)
            if trial is None:
                busy = [
                    t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING, TrialState.WAITING))
                ]
                if not busy:
                    break
                if busy != waiting_for:
                    logger.info("nothing left to claim; waiting for trial(s) %s of other workers", busy)
                    waiting_for = busy
                time.sleep(config.heartbeat_seconds)
                continue
            waiting_for = []
            _run_trial(study, trial, objective, config)
            write_reports()
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
    attrs = trial.user_attrs
    return TrialRecord(
        number=trial.number,
        state=trial.state.name,
        settings=trial_settings(trial),
        success_rate=attrs.get("success_rate"),
        latency_ms=attrs.get("latency_ms"),
        tokenizer_rmse_percent=attrs.get("tokenizer_rmse_percent"),
        dvc_experiment=attrs.get("dvc_experiment") or "",
    )


def trial_settings(trial: FrozenTrial) -> TrialSettings | None:
    """The grid point of a trial, ``None`` when its params were never set."""
    if SCALES_PARAM in trial.params and CODEBOOK_PARAM in trial.params:
        return TrialSettings(parse_schedule_label(trial.params[SCALES_PARAM]), int(trial.params[CODEBOOK_PARAM]))
    return None


def retried_trial_numbers(trials: Sequence[FrozenTrial]) -> set[int]:
    """Numbers of failed trials that a later trial retries (they do not count against the budget)."""
    retried: set[int] = set()
    with _experimental_api():
        for trial in trials:
            retried.update(RetryHeartbeatStaleTrialCallback.retry_history(trial))
    return retried


def finished_trial_count(trials: Sequence[FrozenTrial]) -> int:
    """Complete, pruned and failed trials, leaving out failed trials that were queued again or never ran a point."""
    retried = retried_trial_numbers(trials)
    finished = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL)
    return sum(
        1
        for trial in trials
        if trial.state in finished
        and trial.number not in retried
        and trial_settings(trial) is not None
        and not trial.system_attrs.get(CLAIM_LOST_ATTR)
    )


def claim_order(config: SweepConfig) -> list[TrialSettings]:
    """The grid in the order workers claim it: a fixed shuffle, the same in every worker."""
    points = all_settings(config)
    return random.Random(CLAIM_ORDER_SEED).sample(points, len(points))


def _next_trial(study: optuna.Study, config: SweepConfig, claims: ClaimStore) -> optuna.Trial | None:
    """A queued retry taken up by this worker, else a new trial on a freshly claimed point, else ``None``."""
    storage = study._storage
    for waiting in study.get_trials(deepcopy=False, states=(TrialState.WAITING,)):
        # Optuna moves a trial from WAITING to RUNNING under a row lock and reports whether this call did it, so
        # exactly one worker takes up each queued retry.
        try:
            if not storage.set_trial_state_values(waiting._trial_id, TrialState.RUNNING):
                continue
        except UpdateFinishedTrialError:
            continue
        storage.record_heartbeat(waiting._trial_id)
        trial = optuna.Trial(study, waiting._trial_id)
        history = waiting.system_attrs.get("retry_history") or []
        point = claims.transfer(history[-1], waiting.number) if history else None
        settings = trial_settings(waiting)
        if point is None and settings is not None:
            claims.record(point_key(settings), waiting.number)
        if settings is None:
            # Queued from a trial that died before it had a point: it has nothing to rerun.
            trial.set_user_attr("error", "queued without a grid point")
            study.tell(trial, state=TrialState.FAIL)
            continue
        logger.info("trial %d retries trial %d", waiting.number, history[-1] if history else -1)
        return trial

    by_key = {point_key(settings): settings for settings in claim_order(config)}
    point = claims.claim(list(by_key), config.num_trials, stale_seconds=_grace_seconds(config))
    if point is None:
        return None
    settings = by_key[point]
    with _experimental_api():
        template = optuna.trial.create_trial(
            state=TrialState.RUNNING,
            params={SCALES_PARAM: schedule_label(settings.scales), CODEBOOK_PARAM: settings.codebook_size},
            distributions=_distributions(config),
        )
    trial_id = storage.create_new_trial(claims.study_id, template_trial=template)
    storage.record_heartbeat(trial_id)
    trial = optuna.Trial(study, trial_id)
    try:
        claims.assign(point, trial.number)
    except ClaimLostError as error:
        logger.warning("%s", error)
        storage.set_trial_system_attr(trial_id, CLAIM_LOST_ATTR, True)
        trial.set_user_attr("error", str(error))
        study.tell(trial, state=TrialState.FAIL)
        return _next_trial(study, config, claims)
    return trial


def _run_trial(study: optuna.Study, trial: optuna.Trial, objective: "_Objective", config: SweepConfig) -> None:
    """Run the objective with heartbeats and record the outcome; an interrupted trial is queued again."""
    with _Heartbeat(study._storage, trial._trial_id, config.heartbeat_seconds):
        try:
            value = objective(trial)
        except optuna.TrialPruned as pruned:
            logger.info("trial %d pruned: %s", trial.number, pruned)
            study.tell(trial, state=TrialState.PRUNED)
            return
        except ExperimentFailedError as error:
            logger.warning("trial %d failed: %s", trial.number, error)
            trial.set_user_attr("error", str(error))
            study.tell(trial, state=TrialState.FAIL)
            return
        except KeyboardInterrupt:
            study.tell(trial, state=TrialState.FAIL)
            # Queued by this worker alone, before it exits, so that exactly one copy waits for the next worker.
            with _experimental_api():
                RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRIES)(
                    study, study._storage.get_trial(trial._trial_id)
                )
            raise
        except BaseException:
            study.tell(trial, state=TrialState.FAIL)
            raise
        study.tell(trial, value)


class _Heartbeat:
    """Marks a trial alive in the storage every ``interval_seconds`` while the block runs (from a thread)."""

    def __init__(self, storage: RDBStorage, trial_id: int, interval_seconds: float) -> None:
        self.storage = storage
        self.trial_id = trial_id
        self.interval_seconds = interval_seconds
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name=f"heartbeat-{trial_id}", daemon=True)

    def __enter__(self) -> "_Heartbeat":
        self.storage.record_heartbeat(self.trial_id)
        self._thread.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._stop.set()
        self._thread.join()

    def _beat(self) -> None:
        while not self._stop.wait(self.interval_seconds):
            try:
                self.storage.record_heartbeat(self.trial_id)
            except SQLAlchemyError as error:
                # A brief database outage must not end the trial; a long one lets the trial go stale and be retried.
                logger.warning("heartbeat of trial %s not recorded: %s", self.trial_id, error)


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
        for key in ("tokenizer_rmse_percent", "success_rate", "latency_ms", "dvc_experiment", "interrupted", "error"):
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
    """Silence Optuna's experimental-feature warnings (heartbeats, retries) for deliberate uses."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ExperimentalWarning)
        yield


def _grace_seconds(config: SweepConfig) -> float:
    """How old a heartbeat (or a claim without a trial) must be before its worker is taken for dead."""
    return 2 * config.heartbeat_seconds


def _distributions(config: SweepConfig) -> dict[str, CategoricalDistribution]:
    return {
        SCALES_PARAM: CategoricalDistribution(scale_choices(config)),
        CODEBOOK_PARAM: CategoricalDistribution(codebook_choices(config)),
    }


def _load_study(config: SweepConfig) -> tuple[optuna.Study, int]:
    for attempt in range(SCHEMA_ATTEMPTS):
        try:
            with _experimental_api():
                storage = RDBStorage(
                    config.storage,
                    heartbeat_interval=config.heartbeat_seconds,
                    grace_period=_grace_seconds(config),
                    heartbeat_stale_trial_callback=RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRIES),
                )
            break
        except (IntegrityError, ProgrammingError):
            # Workers started together on an empty database all create Optuna's tables; PostgreSQL rejects all but
            # the first CREATE (a duplicate in its catalog). The tables exist then; opening the storage again works.
            if attempt + 1 == SCHEMA_ATTEMPTS:
                raise
            time.sleep(1.0 + random.random())
    study = optuna.create_study(
        study_name=config.study_name,
        storage=storage,
        # Never consulted: every trial is created with the params of the point its worker claimed.
        sampler=optuna.samplers.RandomSampler(seed=CLAIM_ORDER_SEED),
        direction="maximize",
        load_if_exists=True,
    )
    return study, storage.get_study_id_from_name(config.study_name)


def _check_search_space(study: optuna.Study, config: SweepConfig) -> None:
    expected = _distributions(config)
    for trial in study.get_trials(deepcopy=False):
        for name, distribution in trial.distributions.items():
            if expected.get(name) != distribution:
                raise SweepStateError(
                    f"study '{config.study_name}' was created with {name} choices {list(distribution.choices)}, "
                    f"params now give {list(expected[name].choices) if name in expected else 'none'}; "
                    "use a new sweep.study_name for a new search space"
                )


def _claim_existing_trials(study: optuna.Study, claims: ClaimStore) -> None:
    """Claim the points of trials made without claims (a study started by an earlier version, or by hand)."""
    claimed = {claim.trial_number for claim in claims.claims()}
    latest: dict[str, int] = {}
    for trial in study.get_trials(deepcopy=False):
        settings = trial_settings(trial)
        if settings is not None and not trial.system_attrs.get(CLAIM_LOST_ATTR):
            latest[point_key(settings)] = trial.number
    for point, number in latest.items():
        if number not in claimed:
            claims.record(point, number)


def _open_parent_run(study: optuna.Study, config: SweepConfig, claims: ClaimStore, tracker: SweepTracker) -> str:
    """The study's MLflow parent run: one for all workers, created by whichever worker gets there first."""
    description = {
        "study_name": config.study_name,
        "scale_schedules": str(scale_choices(config)),
        "codebook_sizes": str(codebook_choices(config)),
        "prune_factor": str(config.prune_factor),
    }
    known = claims.get(PARENT_RUN_ATTR) or study.user_attrs.get(PARENT_RUN_ATTR)
    run_id = tracker.open_study(config.study_name, known, description)
    shared = claims.setdefault(PARENT_RUN_ATTR, run_id)
    if shared != run_id:  # another worker created one at the same moment and stored it first
        if run_id != known:
            tracker.discard_run(run_id)
        run_id = tracker.open_study(config.study_name, shared, description)
    study.set_user_attr(PARENT_RUN_ATTR, run_id)
    return run_id


def _fail_stale_trials(study: optuna.Study, tracker: SweepTracker | None) -> None:
    """Fail (and queue again) trials whose worker stopped sending heartbeats; close their MLflow runs."""
    running = {
        trial.number: trial.user_attrs.get("mlflow_run_id")
        for trial in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
    }
    if not running:
        return
    with _experimental_api():
        fail_stale_trials(study)
    for trial in study.get_trials(deepcopy=False, states=(TrialState.FAIL,)):
        # A trial its own worker failed carries the reason (or `interrupted`) and had its run closed by that worker.
        if trial.number in running and not trial.user_attrs.get("error") and not trial.user_attrs.get("interrupted"):
            logger.info("trial %d lost its worker (no heartbeat); marked failed", trial.number)
            run_id = running[trial.number]
            if tracker is not None and run_id:
                tracker.end_trial(run_id, "FAIL")
