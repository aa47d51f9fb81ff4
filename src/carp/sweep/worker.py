"""How sweep workers share one study: claiming grid points, retrying trials of dead workers, heartbeats.

Workers: any number of sweep processes, each in its own workspace, may work on one study at once through its RDB
storage (SQLite on one machine, PostgreSQL across machines). Each repeatedly takes up a queued retry, or claims an
untried grid point in the database (:mod:`carp.sweep.claims`) and creates a trial with that point's params
(:func:`next_trial`); no two workers run the same point, and at most ``num_trials`` points are ever claimed, so the
budget holds across workers and across restarts.

Retries: a worker killed mid-trial leaves that trial ``RUNNING``; once its heartbeat (:class:`Heartbeat`) is older
than the grace period (2 heartbeats) another worker (or the restarted one) marks it ``FAIL``
(:func:`fail_abandoned_trials`) and ``RetryHeartbeatStaleTrialCallback`` queues a copy with the same params, which
the next free worker takes up, moving the point's claim to it. A trial stopped by Ctrl-C is marked ``FAIL``, tagged
``interrupted`` and queued again the same way before the worker exits (:func:`queue_retry`). A trial is retried at
most ``MAX_RETRIES`` times.
"""

import logging
import random
import threading
import time
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import optuna
from optuna.distributions import CategoricalDistribution
from optuna.exceptions import ExperimentalWarning, UpdateFinishedTrialError
from optuna.storages import RDBStorage, RetryHeartbeatStaleTrialCallback, fail_stale_trials
from optuna.trial import FrozenTrial, TrialState
from sqlalchemy.exc import IntegrityError, OperationalError, ProgrammingError, SQLAlchemyError

from carp.config.experiments import SweepConfig
from carp.sweep.claims import ClaimLostError, ClaimStore
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
# Set on a trial whose worker lost its point's claim before the trial started; it never ran and does not count.
CLAIM_LOST_ATTR = "carp_claim_lost"
# Seeds the order in which workers claim grid points: a budget smaller than the grid gets a spread-out sample of it
# rather than the first schedules, and every worker uses the same order.
CLAIM_ORDER_SEED = 0
SCHEMA_ATTEMPTS = 5


@contextmanager
def experimental_api() -> Iterator[None]:
    """Silence Optuna's experimental-feature warnings (heartbeats, retries) for deliberate uses."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ExperimentalWarning)
        yield


def grace_seconds(config: SweepConfig) -> float:
    """How old a heartbeat (or a claim without a trial) must be before its worker is taken for dead."""
    return 2 * config.heartbeat_seconds


def search_distributions(config: SweepConfig) -> dict[str, CategoricalDistribution]:
    """The study's two categorical params: scale schedule labels and codebook sizes."""
    return {
        SCALES_PARAM: CategoricalDistribution(scale_choices(config)),
        CODEBOOK_PARAM: CategoricalDistribution(codebook_choices(config)),
    }


def open_storage(config: SweepConfig) -> RDBStorage:
    """The study's storage with heartbeats and the retry of trials whose heartbeat went stale."""
    for attempt in range(SCHEMA_ATTEMPTS):
        try:
            with experimental_api():
                storage = RDBStorage(
                    config.storage,
                    heartbeat_interval=config.heartbeat_seconds,
                    grace_period=grace_seconds(config),
                    heartbeat_stale_trial_callback=RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRIES),
                )
            break
        except (IntegrityError, OperationalError, ProgrammingError) as error:
            # Workers started together on an empty database all create Optuna's tables; PostgreSQL rejects all but
            # the first CREATE (a duplicate in its catalog), SQLite reports "table ... already exists". The tables
            # exist then; opening the storage again works. Other operational errors (no such file) are not a race.
            schema_race = not isinstance(error, OperationalError) or "already exists" in str(error)
            if not schema_race or attempt + 1 == SCHEMA_ATTEMPTS:
                raise
            time.sleep(1.0 + random.random())
    return storage


def trial_settings(trial: FrozenTrial) -> TrialSettings | None:
    """The grid point of a trial, ``None`` when its params were never set."""
    if SCALES_PARAM in trial.params and CODEBOOK_PARAM in trial.params:
        return TrialSettings(parse_schedule_label(trial.params[SCALES_PARAM]), int(trial.params[CODEBOOK_PARAM]))
    return None


def retried_trial_numbers(trials: Sequence[FrozenTrial]) -> set[int]:
    """Numbers of failed trials that a later trial retries (they do not count against the budget)."""
    retried: set[int] = set()
    with experimental_api():
        for trial in trials:
            retried.update(RetryHeartbeatStaleTrialCallback.retry_history(trial))
    return retried


def claim_order(config: SweepConfig) -> list[TrialSettings]:
    """The grid in the order workers claim it: a fixed shuffle, the same in every worker."""
    points = all_settings(config)
    return random.Random(CLAIM_ORDER_SEED).sample(points, len(points))


def claim_existing_trials(study: optuna.Study, claims: ClaimStore) -> None:
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


def next_trial(study: optuna.Study, config: SweepConfig, claims: ClaimStore) -> optuna.Trial | None:
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
    point = claims.claim(list(by_key), config.num_trials, stale_seconds=grace_seconds(config))
    if point is None:
        return None
    settings = by_key[point]
    with experimental_api():
        template = optuna.trial.create_trial(
            state=TrialState.RUNNING,
            params={SCALES_PARAM: schedule_label(settings.scales), CODEBOOK_PARAM: settings.codebook_size},
            distributions=search_distributions(config),
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
        return next_trial(study, config, claims)
    return trial


def queue_retry(study: optuna.Study, trial: optuna.Trial) -> None:
    """Queue a copy of `trial`, which its own worker has just failed, for the next free worker."""
    with experimental_api():
        RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRIES)(study, study._storage.get_trial(trial._trial_id))


class Heartbeat:
    """Marks a trial alive in the storage every ``interval_seconds`` while the block runs (from a thread)."""

    def __init__(self, storage: RDBStorage, trial_id: int, interval_seconds: float) -> None:
        self.storage = storage
        self.trial_id = trial_id
        self.interval_seconds = interval_seconds
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name=f"heartbeat-{trial_id}", daemon=True)

    def __enter__(self) -> "Heartbeat":
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


def fail_abandoned_trials(study: optuna.Study, tracker: SweepTracker | None) -> None:
    """Fail (and queue again) trials whose worker stopped sending heartbeats; close their MLflow runs."""
    running = {
        trial.number: trial.user_attrs.get("mlflow_run_id")
        for trial in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
    }
    if not running:
        return
    with experimental_api():
        fail_stale_trials(study)
    for trial in study.get_trials(deepcopy=False, states=(TrialState.FAIL,)):
        # A trial its own worker failed carries the reason (or `interrupted`) and had its run closed by that worker.
        if trial.number in running and not trial.user_attrs.get("error") and not trial.user_attrs.get("interrupted"):
            logger.info("trial %d lost its worker (no heartbeat); marked failed", trial.number)
            run_id = running[trial.number]
            if tracker is not None and run_id:
                tracker.end_trial(run_id, "FAIL")
