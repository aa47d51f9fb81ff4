"""The sweep's `ExperimentRunner` (`carp.sweep.study`): trials run with DVC in a project workspace.

A trial first sets its values in the params file and reproduces only `train_tokenizer` (for the pruning check), with
the same override code as `dvc exp run -S`, so the experiment that follows finds the tokenizer cached. Then `dvc exp
run -n <name> -S ...` runs the rest, and the experiment is pushed to a git remote when one is given. DVC's own output
goes straight to this process's stdout and stderr.
"""

import json
import logging
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

from dvc.utils.hydra import apply_overrides

from carp.sweep.outcome import ExperimentResult
from carp.sweep.space import TrialSettings
from carp.sweep.study import ExperimentFailedError

logger = logging.getLogger(__name__)

TOKENIZER_ERROR_KEY = "rmse_percent_range/mean"
"""The tokenizer metric a trial is pruned on and reports: reconstruction RMSE in % of range, mean over dimensions."""


class DvcExperimentRunner:
    """Runs trials with DVC in a workspace (the files the stages read and write)."""

    def __init__(
        self,
        workspace: Path,
        tokenizer_metrics: Path,
        evaluation_reports: Sequence[Path],
        git_remote: str,
        environment: Mapping[str, str],
    ) -> None:
        """Runner of one workspace.

        Args:
            workspace: the project directory; its `params.yaml` receives each trial's values.
            tokenizer_metrics: the `train_tokenizer` stage's metrics JSON.
            evaluation_reports: the evaluation summary JSON of every evaluated (task, policy, training seed) run.
            git_remote: where experiments are pushed; empty pushes nothing.
            environment: the variables the tokenizer stage runs with, to which the trial's `DVC_EXP_NAME` is added.
        """
        self.workspace = Path(workspace)
        self.tokenizer_metrics = Path(tokenizer_metrics)
        self.evaluation_reports = tuple(Path(path) for path in evaluation_reports)
        self.git_remote = git_remote
        self.environment = dict(environment)

    def train_tokenizer(self, name: str, settings: TrialSettings) -> float:
        """Set the trial's values in `params.yaml` and reproduce `train_tokenizer`; its RMSE (% of range)."""
        apply_overrides(str(self.workspace / "params.yaml"), settings.set_arguments())
        # DVC sets DVC_EXP_NAME only under `dvc exp run`; this stage belongs to the trial's experiment, so its
        # MLflow run gets the same tag.
        self._dvc("repro", "train_tokenizer", environment={**self.environment, "DVC_EXP_NAME": name})
        return float(_read_json(self.tokenizer_metrics)[TOKENIZER_ERROR_KEY])

    def run_experiment(self, name: str, settings: TrialSettings) -> ExperimentResult:
        """Run the trial as the DVC experiment `name` (pushed when a remote is set); its evaluation metrics."""
        overrides = [part for argument in settings.set_arguments() for part in ("-S", argument)]
        self._dvc("exp", "run", "--name", name, *overrides)
        if self.git_remote:
            self._push(name)
        # Averaged over every evaluated (task, policy) pair; the sweep's axes are the tokenizer's, so it is meant for
        # the token-predicting families (the default `policies: [carp]`).
        evaluations = [_read_json(path) for path in self.evaluation_reports]
        return ExperimentResult(
            # Summaries written before evaluation recorded the task's score have the success rate as their score.
            score=sum(e.get("score", e["success_rate"]) for e in evaluations) / len(evaluations),
            success_rate=sum(e["success_rate"] for e in evaluations) / len(evaluations),
            latency_ms=sum(e["latency_predict_ms_median"] + e["latency_decode_ms_median"] for e in evaluations)
            / len(evaluations),
            tokenizer_rmse_percent=float(_read_json(self.tokenizer_metrics)[TOKENIZER_ERROR_KEY]),
        )

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
