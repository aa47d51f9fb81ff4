"""What the experiment and sweep tests share: the sweep settings, a copy of the demos workspace, and readers of the
experiments, MLflow runs and Optuna trials a workspace holds."""

import json
import shutil
import sys
from pathlib import Path

import optuna
import yaml
from mlflow import MlflowClient

from carp.sweep.space import TrialSettings
from tests.pipeline.workspace import TINY_PARAMS, dvc, run

SWEEP = {
    "study_name": "tiny",
    "num_trials": 2,
    "scale_schedules": [[1, 4], [1, 2, 4]],
    # The workspace's own codebook_size (TINY_PARAMS) is off the grid, so the confirmation always has two arms.
    "codebook_sizes": [8, 32],
    "heartbeat_seconds": 1,
    # Candidates still report their validation through the progress file; no trial is stopped by chance.
    "pruner": "none",
    "validation_episodes": 2,
    # Two training seeds per arm, none of the trials' (seeds: [0]); comparison.min_seeds allows two (copy_workspace).
    "confirm_seeds": [1, 2],
}
DEFAULT_SETTINGS = TrialSettings(tuple(TINY_PARAMS["scales"]), TINY_PARAMS["codebook_size"])
TEST_SEEDS = range(100_000, 100_000 + TINY_PARAMS["eval"]["episodes"])  # eval.seed on, eval.episodes of them
VALIDATION_SEEDS = range(200_000, 200_000 + SWEEP["validation_episodes"])  # eval.validation_seed on
# Generous bounds for a loaded two-core machine; the waits end as soon as their condition holds.
TRIAL_TIMEOUT_SECONDS = 900


def copy_workspace(template: Path, directory: Path, sweep: dict | None = None, tracking: dict | None = None) -> Path:
    workspace = directory / "carp"
    # The template's MLflow store records absolute artifact locations inside the template: start a fresh one.
    shutil.copytree(template, workspace, symlinks=True, ignore=shutil.ignore_patterns("mlflow.db", "mlartifacts"))
    if sweep is not None:
        params = yaml.safe_load((workspace / "params.yaml").read_text())
        params["sweep"].update(sweep)
        params["comparison"]["min_seeds"] = len(params["sweep"]["confirm_seeds"])
        params["tracking"].update(tracking or {})
        (workspace / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
        for command in (["git", "add", "params.yaml"], ["git", "commit", "-qm", "sweep settings"]):
            assert run(command, workspace).returncode == 0
    return workspace


def head(workspace: Path) -> str:
    return run(["git", "rev-parse", "HEAD"], workspace).stdout.strip()


def experiments(workspace: Path) -> dict[str, dict]:
    """`dvc exp show --json` as experiment name -> {rev, params, metrics} of params.yaml and the metrics files."""
    shown = run(dvc("exp", "show", "--json"), workspace)
    assert shown.returncode == 0, shown.stderr
    found = {}
    for baseline in json.loads(shown.stdout):
        for experiment in baseline.get("experiments") or []:
            data = experiment["revs"][0]["data"]
            metrics = {}
            for values in data["metrics"].values():
                metrics.update(values["data"])
            found[experiment["name"]] = {
                "rev": experiment["revs"][0]["rev"],
                "params": data["params"]["params.yaml"]["data"],
                "metrics": metrics,
            }
    return found


def mlflow_runs(workspace: Path) -> list:
    client = MlflowClient(tracking_uri=f"sqlite:///{workspace / 'mlflow.db'}")
    return client.search_runs([experiment.experiment_id for experiment in client.search_experiments()])


def study_trials(workspace: Path) -> list:
    return optuna.load_study(study_name="tiny", storage=f"sqlite:///{workspace / 'optuna.db'}").get_trials()


def sweep_command() -> list[str]:
    return [sys.executable, "pipeline/sweep.py"]


def committed_file(workspace: Path, rev: str, path: str) -> str:
    """A file as an experiment's commit holds it (its uncached outputs, metrics and plots)."""
    shown = run(["git", "show", f"{rev}:{path}"], workspace)
    assert shown.returncode == 0, shown.stderr
    return shown.stdout


def comment_lines(best_params: str) -> list[str]:
    """The ``#`` lines of best_params.txt without their ``# ``."""
    return [line.removeprefix("# ") for line in best_params.splitlines()[1:]]
