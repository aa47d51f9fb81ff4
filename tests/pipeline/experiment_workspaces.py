"""Shared by the experiment and sweep end-to-end tests: a template workspace with ingested tiny demos, its copies,
and readers of what experiments, MLflow and Optuna recorded.

`tests/pipeline/conftest.py` builds the template once per test module (`template`); every test works in its own
copy, so experiments, MLflow and Optuna stores never mix between tests.
"""

import json
import shutil
import sys
from pathlib import Path

import optuna
import yaml
from mlflow import MlflowClient

from tests.pipeline.workspace import dvc, make_workspace, run

SWEEP = {
    "study_name": "tiny",
    "num_trials": 2,
    "scale_schedules": [[1, 4], [1, 2, 4]],
    "codebook_sizes": [8, 16],
    "heartbeat_seconds": 1,
}
# Generous bounds for a loaded two-core machine; the waits end as soon as their condition holds.
TRIAL_TIMEOUT_SECONDS = 900


def copy_workspace(template: Path, directory: Path, sweep: dict | None = None, tracking: dict | None = None) -> Path:
    workspace = directory / "carp"
    # The template's MLflow store records absolute artifact locations inside the template: start a fresh one.
    shutil.copytree(template, workspace, symlinks=True, ignore=shutil.ignore_patterns("mlflow.db", "mlartifacts"))
    if sweep is not None:
        params = yaml.safe_load((workspace / "params.yaml").read_text())
        params["sweep"].update(sweep)
        params["tracking"].update(tracking or {})
        (workspace / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
        for command in (["git", "add", "params.yaml"], ["git", "commit", "-qm", "sweep settings"]):
            assert run(command, workspace).returncode == 0
    return workspace


def head(workspace: Path) -> str:
    return run(["git", "rev-parse", "HEAD"], workspace).stdout.strip()


def experiments(workspace: Path) -> dict[str, dict]:
    """`dvc exp show --json` as experiment name -> {params, metrics} of params.yaml and the metrics files."""
    shown = run(dvc("exp", "show", "--json"), workspace)
    assert shown.returncode == 0, shown.stderr
    found = {}
    for baseline in json.loads(shown.stdout):
        for experiment in baseline.get("experiments") or []:
            data = experiment["revs"][0]["data"]
            metrics = {}
            for values in data["metrics"].values():
                metrics.update(values["data"])
            found[experiment["name"]] = {"params": data["params"]["params.yaml"]["data"], "metrics": metrics}
    return found


def mlflow_runs(workspace: Path) -> list:
    client = MlflowClient(tracking_uri=f"sqlite:///{workspace / 'mlflow.db'}")
    return client.search_runs([experiment.experiment_id for experiment in client.search_experiments()])


def study_trials(workspace: Path) -> list:
    return optuna.load_study(study_name="tiny", storage=f"sqlite:///{workspace / 'optuna.db'}").get_trials()


def sweep_command() -> list[str]:
    return [sys.executable, "pipeline/sweep.py"]


def build_template(directory: Path) -> Path:
    """A repository copy in `directory` whose tiny demos are collected and ingested and committed."""
    workspace = make_workspace(directory / "carp")
    for command in (dvc("repro", "ingest"), ["git", "add", "-A"], ["git", "commit", "-qm", "tiny demos"]):
        completed = run(command, workspace)
        assert completed.returncode == 0, completed.stderr[-3000:]
    return workspace
