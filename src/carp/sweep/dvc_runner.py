"""The sweep's `ExperimentRunner` (`carp.sweep.study`): trials run with DVC in a project workspace.

A trial first sets its values in the params file and reproduces only `train_tokenizer` (for the pruning check), with
the same override code as `dvc exp run -S`, so the experiment that follows finds the tokenizer cached. Then `dvc exp
run -n <name> -S ... evaluate` runs the trainings and evaluations, with the trial's evaluation settings
(:data:`TRIAL_EVAL_OVERRIDES`: validation episodes only, the best-validated checkpoint; and the sweep's count of
validation episodes), and the experiment is pushed to a git remote when one is given. While it runs, the evaluate
stages append each validated candidate to a progress file that this runner follows (`carp.evaluation.progress`), so
the sweep can prune the trial before its later candidates and evaluations run. The confirmation's experiments run
the same stages with :data:`CONFIRMATION_EVAL_OVERRIDES` and the confirmation's training seeds. DVC's own output
goes straight to this process's stdout and stderr.
"""

import json
import logging
import subprocess
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from dvc.utils.hydra import apply_overrides

from carp.evaluation.progress import PROGRESS_VARIABLE, ProgressFile, ValidatedCandidate
from carp.reporting.runs import read_run_results
from carp.sweep.confirmation import LabelledRuns
from carp.sweep.outcome import ExperimentResult
from carp.sweep.space import TrialSettings, schedule_label
from carp.sweep.study import ExperimentFailedError, ExperimentStoppedError

logger = logging.getLogger(__name__)

TOKENIZER_ERROR_KEY = "rmse_percent_range/mean"
"""The tokenizer metric a trial is pruned on and reports: reconstruction RMSE in % of range, mean over dimensions."""

TRIAL_EVAL_OVERRIDES = {"run_test": False, "selection": "best_validation"}
"""``eval`` settings of every trial: no test episode, the checkpoint with the best validation success."""
CONFIRMATION_EVAL_OVERRIDES = {"run_test": True, "selection": "best_validation"}
"""``eval`` settings of the confirmation: the trials' checkpoint choice, then that checkpoint on the test seeds."""
EVALUATION_TARGET = "evaluate"
"""The stages an experiment runs (with everything upstream): the report and registration are left out."""
POLL_SECONDS = 1.0
"""How often the progress file is read while an experiment runs."""


def eval_arguments(overrides: Mapping[str, object]) -> list[str]:
    """``-S`` values that set ``eval`` keys, e.g. ``{"run_test": False}`` -> ``["eval.run_test=false"]``."""
    return [
        f"eval.{key}={str(value).lower() if isinstance(value, bool) else value}" for key, value in overrides.items()
    ]


class DvcExperimentRunner:
    """Runs trials with DVC in a workspace (the files the stages read and write)."""

    def __init__(
        self,
        workspace: Path,
        tokenizer_metrics: Path,
        evaluation_report: Callable[[str, str, int], Path],
        tasks: Sequence[str],
        policies: Sequence[str],
        seeds: Sequence[int],
        git_remote: str,
        environment: Mapping[str, str],
        validation_episodes: int,
    ) -> None:
        """Runner of one workspace.

        Args:
            workspace: the project directory; its `params.yaml` receives each trial's values.
            tokenizer_metrics: the `train_tokenizer` stage's metrics JSON.
            evaluation_report: (task, policy, training seed) -> that evaluation's summary JSON.
            tasks: the pipeline's tasks.
            policies: the pipeline's policy families.
            seeds: the trials' training seeds (set on every trial, so a confirmation's seeds never leak into one).
            git_remote: where experiments are pushed; empty pushes nothing.
            environment: the variables DVC runs with, to which a trial adds its `DVC_EXP_NAME` (tokenizer stage) or
                the progress file (experiment).
            validation_episodes: ``eval.validation_episodes`` of every trial and confirmation experiment
                (``sweep.validation_episodes``).
        """
        self.workspace = Path(workspace)
        self.tokenizer_metrics = Path(tokenizer_metrics)
        self.evaluation_report = evaluation_report
        self.tasks = tuple(tasks)
        self.policies = tuple(policies)
        self.seeds = tuple(seeds)
        self.git_remote = git_remote
        self.environment = dict(environment)
        self.validation_episodes = validation_episodes
        self.progress = ProgressFile(self.workspace / ".dvc" / "tmp" / "sweep" / "validation_progress.jsonl")

    def trial_eval_settings(self) -> dict[str, object]:
        """The ``eval`` keys a trial's experiment sets: no test episode, selection on the validation episodes."""
        return {**TRIAL_EVAL_OVERRIDES, "validation_episodes": self.validation_episodes}

    def confirmation_eval_settings(self) -> dict[str, object]:
        """The ``eval`` keys a confirmation experiment sets: the trials' selection, then the test seeds."""
        return {**CONFIRMATION_EVAL_OVERRIDES, "validation_episodes": self.validation_episodes}

    def train_tokenizer(self, name: str, settings: TrialSettings) -> float:
        """Set the trial's values in `params.yaml` and reproduce `train_tokenizer`; its RMSE (% of range)."""
        apply_overrides(str(self.workspace / "params.yaml"), settings.set_arguments())
        # DVC sets DVC_EXP_NAME only under `dvc exp run`; this stage belongs to the trial's experiment, so its
        # MLflow run gets the same tag.
        self._dvc("repro", "train_tokenizer", environment={**self.environment, "DVC_EXP_NAME": name})
        return float(_read_json(self.tokenizer_metrics)[TOKENIZER_ERROR_KEY])

    def run_experiment(
        self, name: str, settings: TrialSettings, on_validated: Callable[[ValidatedCandidate], bool]
    ) -> ExperimentResult:
        """Run the trial as the DVC experiment `name` (pushed when a remote is set); its validation metrics.

        Raises:
            ExperimentStoppedError: `on_validated` asked to stop and the experiment stopped before its end.
            ExperimentFailedError: a stage failed.
        """
        arguments = [
            *settings.set_arguments(),
            *eval_arguments(self.trial_eval_settings()),
            f"seeds={schedule_label(self.seeds)}",
        ]
        command = ["exp", "run", "--name", name, *_set_options(arguments), EVALUATION_TARGET]
        if self._dvc_followed(command, on_validated):
            raise ExperimentStoppedError(f"`dvc exp run --name {name}` stopped after the pruner's request")
        if self.git_remote:
            self._push(name)
        # Averaged over every evaluated (task, policy, seed) run; the sweep's axes are the tokenizer's, so it is meant
        # for the token-predicting families (the default `policies: [carp]`).
        evaluations = [
            _read_json(self.evaluation_report(task, policy, seed))
            for task in self.tasks
            for policy in self.policies
            for seed in self.seeds
        ]
        return ExperimentResult(
            validation_score=_mean(e["validation_score"] for e in evaluations),
            validation_success_rate=_mean(e["validation_success_rate"] for e in evaluations),
            latency_ms=_mean(e["latency_predict_ms_median"] + e["latency_decode_ms_median"] for e in evaluations),
            tokenizer_rmse_percent=float(_read_json(self.tokenizer_metrics)[TOKENIZER_ERROR_KEY]),
        )

    def run_confirmation(self, name: str, settings: TrialSettings, seeds: Sequence[int]) -> LabelledRuns:
        """Train `settings` with each of `seeds` as the DVC experiment `name` and evaluate on the test seeds.

        Returns:
            Label (the task, or ``<task>-<policy>`` with several policies) -> training seed -> its evaluation.
        """
        arguments = [
            *settings.set_arguments(),
            *eval_arguments(self.confirmation_eval_settings()),
            f"seeds={schedule_label(tuple(seeds))}",
        ]
        self._dvc("exp", "run", "--name", name, *_set_options(arguments), EVALUATION_TARGET)
        if self.git_remote:
            self._push(name)
        return {
            task if len(self.policies) == 1 else f"{task}-{policy}": {
                seed: read_run_results(self.evaluation_report(task, policy, seed)) for seed in seeds
            }
            for task in self.tasks
            for policy in self.policies
        }

    def _dvc_followed(self, arguments: Sequence[str], on_validated: Callable[[ValidatedCandidate], bool]) -> bool:
        """Run a dvc command while following the progress file; returns whether it stopped on request."""
        self.progress.clear()
        command = [sys.executable, "-m", "dvc", *arguments]
        logger.info("$ dvc %s", " ".join(arguments))
        offset = 0
        with subprocess.Popen(
            command, cwd=self.workspace, env={**self.environment, PROGRESS_VARIABLE: str(self.progress.path)}
        ) as process:
            while True:
                try:
                    returncode = process.wait(timeout=POLL_SECONDS)
                except subprocess.TimeoutExpired:
                    returncode = None
                validated, offset = self.progress.read(offset)
                for candidate in validated:
                    if not self.progress.stop_requested() and on_validated(candidate):
                        logger.info("pruned after %s, epoch %d", candidate.evaluation, candidate.epoch)
                        self.progress.request_stop()
                if returncode is not None:
                    break
        if returncode == 0:
            return False
        if self.progress.stop_requested():
            return True
        raise ExperimentFailedError(f"`dvc {' '.join(arguments)}` exited with status {returncode}")

    def _push(self, name: str) -> None:
        try:
            self._dvc("exp", "push", self.git_remote, name)
        except ExperimentFailedError as error:
            # The experiment ran and is kept here; an unreachable remote must not fail the trial.
            logger.warning("%s; push it later with: dvc exp push %s %s", error, self.git_remote, name)

    def _dvc(self, *arguments: str, environment: dict[str, str] | None = None) -> None:
        command = [sys.executable, "-m", "dvc", *arguments]
        logger.info("$ dvc %s", " ".join(arguments))
        # A failed stage fails the trial only.
        completed = subprocess.run(command, cwd=self.workspace, env=environment)
        if completed.returncode != 0:
            raise ExperimentFailedError(f"`dvc {' '.join(arguments)}` exited with status {completed.returncode}")


def _read_json(path: Path) -> dict:
    return json.loads(path.read_text())


def _set_options(arguments: Sequence[str]) -> list[str]:
    return [part for argument in arguments for part in ("-S", argument)]


def _mean(values) -> float:
    values = list(values)
    return sum(values) / len(values)
