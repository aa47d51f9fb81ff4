"""The Optuna study: claim a grid point, train its tokenizer, prune or run the experiment, record it; then confirm.

A trial never runs a test episode: its experiment evaluates on the validation seeds only (``eval.run_test: false``,
``eval.selection: best_validation``), reporting each candidate's validation to Optuna's pruner as it finishes
(:mod:`carp.sweep.pruning`). When every trial is finished, one worker trains the selected settings and the default
ones on ``sweep.confirm_seeds`` and compares them on the test seeds (:mod:`carp.sweep.confirmation`);
``best_params.txt`` and the MLflow parent run record that verdict beside the winner's validation figures.

Any number of sweep processes, each in its own workspace, may work on one study at once through its RDB storage;
how they share it (claimed grid points, retries of trials whose worker died, heartbeats) is
:mod:`carp.sweep.worker`'s. A worker with nothing left to claim waits until no trial of the study is running or
queued (another worker's trial may still fail and be retried), so every worker ends with the whole study in its
reports. The budget counts finished trials (complete, pruned, failed) but not failed trials that were retried.

Within a workspace trials run one at a time: each owns the workspace (params, outputs, ``dvc.lock``) while it runs.
"""

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import optuna
from optuna.trial import FrozenTrial, TrialState

from carp.config.experiments import SweepConfig
from carp.evaluation.progress import ValidatedCandidate
from carp.sweep.claims import ClaimStore
from carp.sweep.confirmation import ConfirmationPlan, ConfirmationResult, LabelledRuns, confirm
from carp.sweep.outcome import (
    ExperimentResult,
    TrialRecord,
    best_record,
    best_tokenizer_error,
    should_prune,
    write_trials_csv,
)
from carp.sweep.pruning import ValidationCurve, make_pruner
from carp.sweep.space import (
    CODEBOOK_PARAM,
    SCALES_PARAM,
    TrialSettings,
    codebook_choices,
    parse_schedule_label,
    scale_choices,
)
from carp.sweep.tracking import SweepTracker
from carp.sweep.worker import (
    CLAIM_LOST_ATTR,
    CLAIM_ORDER_SEED,
    Heartbeat,
    claim_existing_trials,
    fail_abandoned_trials,
    next_trial,
    open_storage,
    queue_retry,
    retried_trial_numbers,
    search_distributions,
    trial_settings,
)

logger = logging.getLogger(__name__)

PARENT_RUN_ATTR = "mlflow_parent_run_id"
TRIALS_FILE = "trials.csv"
BEST_PARAMS_FILE = "best_params.txt"
# The workspace that runs the confirmation (first writer wins), and its lines once done, kept with the study.
CONFIRMATION_WORKER_KEY = "confirmation_worker"
CONFIRMATION_ATTR = "confirmation"


class ExperimentFailedError(RuntimeError):
    """An experiment (or its tokenizer stage) exited with an error; the trial fails and the sweep goes on."""


class ExperimentStoppedError(RuntimeError):
    """An experiment stopped because the sweep's pruner asked it to (the trial is pruned)."""


class SweepStateError(RuntimeError):
    """The stored study cannot be continued as asked (another search space)."""


class ExperimentRunner(Protocol):
    """Runs the pipeline for one trial's settings (the sweep's only contact with DVC)."""

    def train_tokenizer(self, name: str, settings: TrialSettings) -> float:
        """Bring the pipeline up to the trained tokenizer; return its reconstruction RMSE (% of range).

        ``name`` is the experiment name the trial will use if it is not pruned.
        """
        ...

    def run_experiment(
        self, name: str, settings: TrialSettings, on_validated: Callable[[ValidatedCandidate], bool]
    ) -> ExperimentResult:
        """Run the trial as an experiment called ``name``, on the validation seeds only; return its metrics.

        ``on_validated`` gets each candidate's validation as it finishes and returns whether to stop; a stopped
        experiment raises :class:`ExperimentStoppedError`.
        """
        ...

    def run_confirmation(self, name: str, settings: TrialSettings, seeds: Sequence[int]) -> LabelledRuns:
        """Train ``settings`` once per training seed as the experiment ``name`` and evaluate on the test seeds."""
        ...


@dataclass(frozen=True)
class SweepResult:
    """What a call of :func:`run_sweep` leaves behind.

    Attributes:
        records: every trial of the study so far, by number.
        best: the best completed trial (see :mod:`carp.sweep.outcome` for the ordering), if any.
        finished_trials: trials that count against the budget.
        confirmation: the lines that say how the best trial's settings fared on the test seeds (see
            :meth:`ConfirmationResult.lines`), or why there is no confirmation yet.
    """

    records: list[TrialRecord]
    best: TrialRecord | None
    finished_trials: int
    confirmation: tuple[str, ...] = ()

    def summary_lines(self, config: SweepConfig) -> list[str]:
        """What a worker prints when it is done: trials by state, and how to reproduce (and fetch) the best one."""
        states: dict[str, int] = {}
        for record in self.records:
            states[record.state] = states.get(record.state, 0) + 1
        lines = [f"study {config.study_name}: {self.finished_trials}/{config.num_trials} trials finished {states}"]
        best = self.best
        if best is not None and best.settings is not None:
            lines.append(
                f"best: trial {best.number} ({best.dvc_experiment}), validation score {best.objective:.3f}, "
                f"validation success {100 * best.validation_success_rate:.1f}%, latency "
                f"{best.latency_ms:.2f} ms; reproduce with: dvc exp run {best.settings.command_line()}"
            )
            if config.git_remote:
                name = best.dvc_experiment
                lines.append(f"in any workspace: dvc exp pull {config.git_remote} {name} && dvc exp apply {name}")
        lines.extend(self.confirmation)
        return lines


def write_best_params(best: TrialRecord | None, confirmation: Sequence[str], path: Path) -> None:
    """Write the best trial's ``-S`` arguments on the first line, then the confirmation as ``#`` lines.

    No file before a best exists. The first line alone is ready for ``dvc exp run`` (``head -n 1``).
    """
    if best is None or best.settings is None:
        path.unlink(missing_ok=True)
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{line}\n" for line in [best.settings.command_line(), *(f"# {c}" for c in confirmation)]))


def experiment_name(study_name: str, number: int) -> str:
    """DVC experiment name of a trial, e.g. ``sweep-carp-sweep-t3``."""
    return f"sweep-{study_name}-t{number}"


def run_sweep(
    config: SweepConfig,
    runner: ExperimentRunner,
    report_directory: Path,
    tracker: SweepTracker | None = None,
    confirmation: ConfirmationPlan | None = None,
) -> SweepResult:
    """Work on the study until its budget is spent or its grid exhausted and no trial of it runs or waits; confirm.

    Other workers may work on the same study at the same time (each with its own runner and workspace).

    Args:
        config: the sweep section; ``config.storage`` must already be an absolute URL (e.g. ``sqlite:////abs/x.db``).
        runner: runs one trial's pipeline.
        report_directory: receives ``trials.csv`` and ``best_params.txt`` (rewritten after every trial), and the
            confirmation's evaluations under ``confirmation/``.
        tracker: MLflow parent/child runs; ``None`` records nothing in MLflow.
        confirmation: how to confirm the best trial on the test seeds once every trial is finished; ``None``
            confirms nothing (``best_params.txt`` then says so).

    Raises:
        SweepStateError: the stored study has another search space.
    """
    study, study_id = _load_study(config)
    _check_search_space(study, config)
    claims = ClaimStore(config.storage, study_id)
    try:
        return _work(study, config, claims, runner, report_directory, tracker, confirmation)
    finally:
        claims.close()


def _work(
    study: optuna.Study,
    config: SweepConfig,
    claims: ClaimStore,
    runner: ExperimentRunner,
    report_directory: Path,
    tracker: SweepTracker | None,
    confirmation: ConfirmationPlan | None,
) -> SweepResult:
    claim_existing_trials(study, claims)
    parent_run_id = None
    if tracker is not None:
        parent_run_id = _open_parent_run(study, config, claims, tracker)

    def write_reports(confirmed: Sequence[str] = ("not confirmed on the test seeds yet",)) -> SweepResult:
        trials = study.get_trials(deepcopy=False)
        records = [trial_record(trial) for trial in trials]
        result = SweepResult(records, best_record(records), finished_trial_count(trials), tuple(confirmed))
        write_trials_csv(records, report_directory / TRIALS_FILE)
        write_best_params(result.best, result.confirmation, report_directory / BEST_PARAMS_FILE)
        return result

    logger.info(
        "study %s: %d of %d budgeted point(s) claimed", config.study_name, len(claims.claims()), config.num_trials
    )
    objective = _Objective(config, runner, tracker, parent_run_id)
    waiting_for: list[int] = []
    try:
        while True:
            fail_abandoned_trials(study, tracker)
            trial = next_trial(study, config, claims)
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
        best = write_reports().best
        confirmed, lines = _confirm(study, claims, config, runner, report_directory, best, confirmation)
    except BaseException:
        # Ctrl-C, a failed confirmation or a bug: the reports and the parent run still show where the sweep stopped.
        write_reports()
        if tracker is not None and parent_run_id is not None:
            tracker.interrupt_study(parent_run_id)
        raise
    result = write_reports(lines)
    if tracker is not None and parent_run_id is not None:
        tracker.close_study(parent_run_id, result.best, result.finished_trials, confirmed, lines)
    return result


def _confirm(
    study: optuna.Study,
    claims: ClaimStore,
    config: SweepConfig,
    runner: ExperimentRunner,
    report_directory: Path,
    best: TrialRecord | None,
    plan: ConfirmationPlan | None,
) -> tuple[ConfirmationResult | None, list[str]]:
    """Run (or resume) the confirmation when this worker owns it; otherwise the lines another worker stored."""
    if best is None or best.settings is None:
        return None, ["no completed trial to confirm"]
    if plan is None:
        return None, ["not confirmed on the test seeds (the sweep ran without a confirmation)"]
    owner = claims.setdefault(CONFIRMATION_WORKER_KEY, plan.worker)
    if owner != plan.worker:
        stored = study.user_attrs.get(CONFIRMATION_ATTR) or {}
        if stored.get("settings") == best.settings.command_line():
            return None, list(stored["lines"])
        logger.info("the confirmation runs in the workspace %s; this worker leaves it there", owner)
        return None, [f"not confirmed here: the confirmation runs in the workspace {owner}"]
    result = confirm(best, plan, config.study_name, runner.run_confirmation, report_directory)
    lines = result.lines()
    study.set_user_attr(CONFIRMATION_ATTR, {"settings": best.settings.command_line(), "lines": lines})
    return result, lines


def trial_record(trial: FrozenTrial) -> TrialRecord:
    """Flatten an Optuna trial (params and the user attrs the objective sets) into a :class:`TrialRecord`."""
    attrs = trial.user_attrs
    return TrialRecord(
        number=trial.number,
        state=trial.state.name,
        settings=trial_settings(trial),
        validation_success_rate=attrs.get("validation_success_rate"),
        validation_score=attrs.get("validation_score"),
        latency_ms=attrs.get("latency_ms"),
        tokenizer_rmse_percent=attrs.get("tokenizer_rmse_percent"),
        dvc_experiment=attrs.get("dvc_experiment") or "",
        validated_candidates=attrs.get("validated_candidates") or 0,
    )


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


def _run_trial(study: optuna.Study, trial: optuna.Trial, objective: "_Objective", config: SweepConfig) -> None:
    """Run the objective with heartbeats and record the outcome; an interrupted trial is queued again."""
    with Heartbeat(study._storage, trial._trial_id, config.heartbeat_seconds):
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
            queue_retry(study, trial)
            raise
        except BaseException:
            study.tell(trial, state=TrialState.FAIL)
            raise
        study.tell(trial, value)


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
        for key in (
            "tokenizer_rmse_percent",
            "validation_score",
            "validation_success_rate",
            "validated_candidates",
            "latency_ms",
            "dvc_experiment",
            "interrupted",
            "error",
        ):
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
        curve = ValidationCurve()

        def on_validated(candidate: ValidatedCandidate) -> bool:
            step, value = curve.add(candidate)
            trial.report(value, step)
            trial.set_user_attr("validated_candidates", step)
            self._log(run_id, {"validation_curve": value}, step)
            return trial.should_prune()

        try:
            result = self.runner.run_experiment(name, settings, on_validated)
        except ExperimentStoppedError as stopped:
            raise optuna.TrialPruned(
                f"{self.config.pruner} pruner after {curve.steps} validated candidate(s): {stopped}"
            ) from stopped
        trial.set_user_attr("dvc_experiment", name)
        trial.set_user_attr("validation_score", result.objective)
        trial.set_user_attr("validation_success_rate", result.validation_success_rate)
        trial.set_user_attr("latency_ms", result.latency_ms)
        trial.set_user_attr("tokenizer_rmse_percent", result.tokenizer_rmse_percent)
        self._log(
            run_id,
            {
                "validation_score": result.objective,
                "validation_success_rate": result.validation_success_rate,
                "latency_ms": result.latency_ms,
                "tokenizer_rmse_percent": result.tokenizer_rmse_percent,
            },
        )
        return result.objective, "COMPLETE", name

    def _log(self, run_id: str | None, metrics: dict[str, float], step: int = 0) -> None:
        if self.tracker is not None and run_id is not None:
            self.tracker.log_trial_metrics(run_id, metrics, step)

    def _end_run(self, run_id: str | None, state: str, dvc_experiment: str = "") -> None:
        if self.tracker is not None and run_id is not None:
            self.tracker.end_trial(run_id, state, dvc_experiment)


def _load_study(config: SweepConfig) -> tuple[optuna.Study, int]:
    storage = open_storage(config)
    study = optuna.create_study(
        study_name=config.study_name,
        storage=storage,
        # Never consulted: every trial is created with the params of the point its worker claimed.
        sampler=optuna.samplers.RandomSampler(seed=CLAIM_ORDER_SEED),
        pruner=make_pruner(config),
        direction="maximize",
        load_if_exists=True,
    )
    return study, storage.get_study_id_from_name(config.study_name)


def _check_search_space(study: optuna.Study, config: SweepConfig) -> None:
    expected = search_distributions(config)
    for trial in study.get_trials(deepcopy=False):
        for name, distribution in trial.distributions.items():
            if expected.get(name) != distribution:
                raise SweepStateError(
                    f"study '{config.study_name}' was created with {name} choices {list(distribution.choices)}, "
                    f"params now give {list(expected[name].choices) if name in expected else 'none'}; "
                    "use a new sweep.study_name for a new search space"
                )


def _open_parent_run(study: optuna.Study, config: SweepConfig, claims: ClaimStore, tracker: SweepTracker) -> str:
    """The study's MLflow parent run: one for all workers, created by whichever worker gets there first."""
    description = {
        "study_name": config.study_name,
        "scale_schedules": str(scale_choices(config)),
        "codebook_sizes": str(codebook_choices(config)),
        "prune_factor": str(config.prune_factor),
        "pruner": config.pruner,
        "confirm_seeds": str(list(config.confirm_seeds)),
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
