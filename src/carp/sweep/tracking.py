"""MLflow side of a sweep: one parent run per study, one child run per trial (``mlflow.parentRunId``).

Uses ``MlflowClient`` with explicit run ids instead of the fluent API: the parent run stays open for the whole
sweep (and is reopened on resume) while child runs come and go, and the stage scripts that each trial's
``dvc exp run`` starts open their own runs in other processes.
"""

import logging
import math
import random
import time
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

from mlflow import MlflowClient
from mlflow.exceptions import MlflowException

from carp.sweep.outcome import TrialRecord
from carp.sweep.space import TrialSettings, schedule_label
from carp.tracking.runs import ensure_experiment

if TYPE_CHECKING:
    from carp.sweep.confirmation import ConfirmationResult

logger = logging.getLogger(__name__)

# Optuna trial state -> MLflow run status.
RUN_STATUS = {"COMPLETE": "FINISHED", "PRUNED": "KILLED", "FAIL": "FAILED"}
# Sweep workers that share a study close its parent run (and a dead worker's trial run) at about the same moment.
# MLflow's SQL store writes a new tag by an INSERT after a look-up, so two writers of one tag can collide on its
# primary key; the loser's second attempt finds the tag and updates it.
SHARED_RUN_ATTEMPTS = 3


class SweepTracker:
    """Writes a study's runs to one MLflow experiment.

    Args:
        tracking_uri: absolute tracking URI (the project's store).
        experiment_name: e.g. ``carp-sweep``.
        tags: added to every run, e.g. ``{"carp.git_commit": ...}``.
    """

    def __init__(self, tracking_uri: str, experiment_name: str, tags: Mapping[str, str]) -> None:
        self.client = MlflowClient(tracking_uri=tracking_uri)
        self.experiment_id = ensure_experiment(tracking_uri, experiment_name)
        self.tags = dict(tags)

    def open_study(self, study_name: str, existing_run_id: str | None, description: Mapping[str, str]) -> str:
        """Reopen the study's parent run, or create it (with ``description`` as params) when there is none.

        Returns:
            The parent run's id, to be kept with the study so a resumed sweep finds it.
        """
        if existing_run_id is not None:
            try:
                self.client.update_run(existing_run_id, status="RUNNING")
                return existing_run_id
            except MlflowException:
                logger.warning("parent run %s of study %s is gone; starting a new one", existing_run_id, study_name)
        run = self.client.create_run(
            self.experiment_id, run_name=study_name, tags={**self.tags, "carp.sweep_study": study_name}
        )
        for key, value in description.items():
            self.client.log_param(run.info.run_id, key, value)
        return run.info.run_id

    def discard_run(self, run_id: str) -> None:
        """Delete a parent run that lost the race to become the study's (another worker's run is used instead)."""
        self.client.delete_run(run_id)

    def start_trial(self, parent_run_id: str, study_name: str, number: int, settings: TrialSettings) -> str:
        """Create the trial's child run with its params; returns its id."""
        run = self.client.create_run(
            self.experiment_id,
            run_name=f"trial-{number}",
            tags={
                **self.tags,
                "mlflow.parentRunId": parent_run_id,
                "carp.sweep_study": study_name,
                "carp.trial_number": str(number),
                "carp.trial_state": "RUNNING",
            },
        )
        run_id = run.info.run_id
        self.client.log_param(run_id, "scales", schedule_label(settings.scales))
        self.client.log_param(run_id, "num_scales", settings.num_scales)
        self.client.log_param(run_id, "codebook_size", settings.codebook_size)
        return run_id

    def log_trial_metrics(self, run_id: str, metrics: Mapping[str, float | None], step: int = 0) -> None:
        """Log the finite metrics among ``metrics`` at ``step``."""
        for key, value in metrics.items():
            if value is not None and math.isfinite(value):
                self.client.log_metric(run_id, key, value, step=step)

    def end_trial(self, run_id: str, state: str, dvc_experiment: str = "") -> None:
        """Close a child run with the trial's final state (a tag and the matching run status)."""

        def end() -> None:
            self.client.set_tag(run_id, "carp.trial_state", state)
            if dvc_experiment:
                self.client.set_tag(run_id, "carp.dvc_experiment", dvc_experiment)
            self.client.set_terminated(run_id, status=RUN_STATUS.get(state, "FAILED"))

        _shared_write(end)

    def close_study(
        self,
        parent_run_id: str,
        best: TrialRecord | None,
        finished_trials: int,
        confirmation: "ConfirmationResult | None" = None,
        confirmation_lines: Sequence[str] = (),
    ) -> None:
        """Record the best trial and its confirmation on the parent run and mark it finished (a resume reopens it).

        The best trial's figures are validation figures (``best_validation_*``); the confirmation's test figures
        (``confirmed_test_success_rate``, ``default_test_success_rate``) and verdicts (tags
        ``carp.confirmation_verdict.<label>``) sit beside them, with its lines in the tag ``carp.confirmation``.
        """
        _shared_write(lambda: self._close_study(parent_run_id, best, finished_trials, confirmation, confirmation_lines))

    def _close_study(
        self,
        parent_run_id: str,
        best: TrialRecord | None,
        finished_trials: int,
        confirmation: "ConfirmationResult | None",
        confirmation_lines: Sequence[str],
    ) -> None:
        self.client.set_tag(parent_run_id, "carp.finished_trials", str(finished_trials))
        if confirmation_lines:
            self.client.set_tag(parent_run_id, "carp.confirmation", "\n".join(confirmation_lines))
        if confirmation is not None:
            self.log_trial_metrics(parent_run_id, confirmation.metrics())
            for label, verdict in confirmation.verdicts().items():
                self.client.set_tag(parent_run_id, f"carp.confirmation_verdict.{label}", verdict)
        if best is not None and best.settings is not None:
            self.client.set_tag(parent_run_id, "carp.best_trial", str(best.number))
            self.client.set_tag(parent_run_id, "carp.best_params", best.settings.command_line())
            self.client.set_tag(parent_run_id, "carp.best_dvc_experiment", best.dvc_experiment)
            self.log_trial_metrics(
                parent_run_id,
                {
                    "best_validation_score": best.objective,
                    "best_validation_success_rate": best.validation_success_rate,
                    "best_latency_ms": best.latency_ms,
                    "best_tokenizer_rmse_percent": best.tokenizer_rmse_percent,
                },
            )
        self.client.set_terminated(parent_run_id, status="FINISHED")

    def interrupt_study(self, parent_run_id: str) -> None:
        """Mark the parent run killed (a resume reopens it)."""
        self.client.set_terminated(parent_run_id, status="KILLED")


def _shared_write(write: Callable[[], None]) -> None:
    """Run an idempotent write to a run that other workers may write at the same moment (see SHARED_RUN_ATTEMPTS)."""
    for attempt in range(SHARED_RUN_ATTEMPTS):
        try:
            write()
            return
        except MlflowException:
            if attempt + 1 == SHARED_RUN_ATTEMPTS:
                raise
            logger.info("a run was written by another worker at the same moment; writing again")
            time.sleep(random.random())
