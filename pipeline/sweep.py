"""Optuna sweep over scale schedules and codebook sizes; every trial is a `dvc exp run` in this workspace.

    python pipeline/sweep.py [--trials N] [--params params.yaml]

Reads the `sweep` section (and `tasks`) of the params file, runs trials one at a time until the budget
(`sweep.num_trials`, or --trials) counts that many finished trials in the study's storage, and writes
reports/sweep/trials.csv and reports/sweep/best_params.txt. Killed or interrupted, it resumes where it stopped.
Each trial first sets its values in params.yaml and reproduces only `train_tokenizer` (for the pruning check),
then runs `dvc exp run -n sweep-<study>-t<number> -S scales=... -S codebook_size=...`, which skips the stages
already done, and pushes that experiment to `sweep.git_remote` when one is set. The workspace is left holding the
last trial's params and outputs.

Several workers: start this same command in several workspaces (clones of one commit, on any machines) whose
`sweep.storage` names one PostgreSQL database; they share the study, each grid point runs once, and the budget
holds across them (docs/several-machines.md). One sweep at a time per workspace.
"""

import argparse
import dataclasses
import fcntl
import json
import logging
import os
import subprocess
import sys
from pathlib import Path

from dvc.utils.hydra import apply_overrides
from stage_support import (
    PROJECT_DIR,
    REPORTS_DIR,
    TOKENIZER_REPORT_DIR,
    evaluation_report,
    fail,
    git_commit,
    load,
    project_root,
    setup_logging,
    tracking_uri,
)

from carp.sweep.outcome import ExperimentResult
from carp.sweep.space import TrialSettings
from carp.sweep.study import ExperimentFailedError, SweepStateError, run_sweep
from carp.sweep.tracking import SweepTracker
from carp.tracking.runs import resolve_tracking_uri

logger = logging.getLogger("carp.pipeline.sweep")

TOKENIZER_ERROR_KEY = "rmse_percent_range/mean"


class DvcExperimentRunner:
    """Runs trials with DVC in the project workspace (the files the stages read and write)."""

    def __init__(self, tasks: tuple[str, ...], policies: tuple[str, ...], git_remote: str) -> None:
        self.tasks = tasks
        self.policies = policies
        self.git_remote = git_remote

    def train_tokenizer(self, name: str, settings: TrialSettings) -> float:
        # The same override code as `dvc exp run -S`, so the experiment that follows finds the tokenizer cached.
        apply_overrides(str(PROJECT_DIR / "params.yaml"), settings.set_arguments())
        # DVC sets DVC_EXP_NAME only under `dvc exp run`; this stage belongs to the trial's experiment, so its
        # MLflow run gets the same tag.
        self._dvc("repro", "train_tokenizer", environment={**os.environ, "DVC_EXP_NAME": name})
        return float(_read_json(TOKENIZER_REPORT_DIR / "metrics.json")[TOKENIZER_ERROR_KEY])

    def run_experiment(self, name: str, settings: TrialSettings) -> ExperimentResult:
        overrides = [part for argument in settings.set_arguments() for part in ("-S", argument)]
        self._dvc("exp", "run", "--name", name, *overrides)
        if self.git_remote:
            self._push(name)
        # Averaged over every evaluated (task, policy) pair; the sweep's axes are the tokenizer's, so it is meant for
        # the token-predicting families (the default `policies: [carp]`).
        evaluations = [_read_json(evaluation_report(task, policy)) for task in self.tasks for policy in self.policies]
        return ExperimentResult(
            success_rate=sum(e["success_rate"] for e in evaluations) / len(evaluations),
            latency_ms=sum(e["latency_predict_ms_median"] + e["latency_decode_ms_median"] for e in evaluations)
            / len(evaluations),
            tokenizer_rmse_percent=float(_read_json(TOKENIZER_REPORT_DIR / "metrics.json")[TOKENIZER_ERROR_KEY]),
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
        # DVC's own output goes straight to this process's stdout/stderr; a failed stage fails the trial only.
        completed = subprocess.run(command, cwd=PROJECT_DIR, env=environment)
        if completed.returncode != 0:
            raise ExperimentFailedError(f"`dvc {' '.join(arguments)}` exited with status {completed.returncode}")


def _read_json(path: Path) -> dict:
    return json.loads(path.read_text())


def _hold_workspace_lock() -> object:
    """Lock the workspace for this sweep (released when the process exits); fail if another sweep holds it.

    Workers share a study, not a workspace: each trial rewrites params.yaml and the outputs in place.
    """
    path = PROJECT_DIR / ".dvc" / "tmp" / "sweep.lock"
    path.parent.mkdir(parents=True, exist_ok=True)
    handle = path.open("w")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        fail(f"{path}: another sweep is running in this workspace; start each sweep worker in its own clone")
    return handle


def main() -> None:
    setup_logging()
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--params", type=Path, default=PROJECT_DIR / "params.yaml")
    parser.add_argument("--trials", type=int, default=None, help="total trial budget (default: sweep.num_trials)")
    args = parser.parse_args()
    params = load(args.params)
    if args.trials is not None and args.trials < 1:
        fail(f"--trials={args.trials}: must be at least 1")
    if project_root() != PROJECT_DIR:
        fail("run the sweep in the project workspace, not inside a DVC temporary workspace")
    lock = _hold_workspace_lock()
    config = dataclasses.replace(
        params.sweep,
        storage=resolve_tracking_uri(params.sweep.storage, project_root()),
        num_trials=args.trials or params.sweep.num_trials,
    )
    tracker = SweepTracker(
        tracking_uri(params),
        experiment_name=f"{params.tracking.experiment_prefix}-sweep",
        tags={"carp.git_commit": git_commit()},
    )
    try:
        runner = DvcExperimentRunner(params.tasks, params.policies, config.git_remote)
        result = run_sweep(config, runner, REPORTS_DIR / "sweep", tracker)
    except SweepStateError as error:
        fail(str(error))
    finally:
        lock.close()
    states = {}
    for record in result.records:
        states[record.state] = states.get(record.state, 0) + 1
    print(f"study {config.study_name}: {result.finished_trials}/{config.num_trials} trials finished {states}")
    if result.best is not None and result.best.settings is not None:
        print(
            f"best: trial {result.best.number} ({result.best.dvc_experiment}), success "
            f"{100 * result.best.success_rate:.1f}%, latency {result.best.latency_ms:.2f} ms; "
            f"reproduce with: dvc exp run {result.best.settings.command_line()}"
        )
        if config.git_remote:
            name = result.best.dvc_experiment
            print(f"in any workspace: dvc exp pull {config.git_remote} {name} && dvc exp apply {name}")
    print(f"wrote {(REPORTS_DIR / 'sweep').relative_to(PROJECT_DIR)}/trials.csv and best_params.txt")


if __name__ == "__main__":
    main()
