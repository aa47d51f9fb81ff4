"""`train_policy` with `training.num_processes: 2`: the unchanged stage command starts itself again under torchrun,
two gloo processes train, and rank 0 alone logs to MLflow and writes the outputs. The stage runs in a copy of the
shared arm pipeline, whose demos stand."""

import os
import subprocess
import sys

import pandas as pd
import pytest
import yaml
from mlflow import MlflowClient

from carp.policies.registry import load_policy
from tests.pipeline.shared_workspaces import copy_pipeline
from tests.pipeline.workspace import REPO, dvc, run

EPOCHS = 3
PARAMS = {
    "policies": ["diffusion_transformer"],
    "diffusion_transformer": {"num_layers": 1, "num_heads": 2, "width": 16, "num_train_steps": 10, "warmup_steps": 2},
    "inference": {"diffusion_transformer": {"sampler": "ddim", "num_inference_steps": 2}},
    "training": {"epochs": EPOCHS, "num_processes": 2},
}
STAGE = "train_policy@lift-diffusion_transformer-0"


@pytest.mark.slow
def test_two_processes_train_the_stage_and_rank_0_alone_logs_and_writes(lift_pipeline, tmp_path):
    workspace = copy_pipeline(lift_pipeline, tmp_path, PARAMS)
    completed = run(dvc("repro", STAGE), workspace, timeout=1200)
    assert completed.returncode == 0, completed.stderr[-3000:]
    assert "training on 2 processes (torchrun)" in completed.stderr
    client = MlflowClient(tracking_uri=f"sqlite:///{workspace / 'mlflow.db'}")
    experiments = [experiment.experiment_id for experiment in client.search_experiments()]
    runs = client.search_runs(experiments, filter_string=f"tags.`carp.dvc_stage` = '{STAGE}'")
    assert len(runs) == 1 and runs[0].info.status == "FINISHED"
    assert runs[0].data.params["training.num_processes"] == "2"
    losses = client.get_metric_history(runs[0].info.run_id, "loss")
    assert sorted(metric.step for metric in losses) == list(range(1, EPOCHS + 1))
    history = pd.read_csv(workspace / "reports/policy/lift/diffusion_transformer/seed0/history.csv")
    assert list(history["epoch"]) == list(range(1, EPOCHS + 1))
    policy = load_policy(workspace / "models/policy/lift/diffusion_transformer/seed0/policy.pt")
    assert policy.metadata["mlflow_run_id"] == runs[0].info.run_id
    state = workspace / "checkpoints/policy/lift/diffusion_transformer/seed0/training_state.pt"
    assert state.exists() and not list(state.parent.glob("*.tmp"))

    again = run(dvc("repro", STAGE), workspace)
    assert again.returncode == 0 and f"Running stage '{STAGE}'" not in again.stdout


@pytest.mark.slow
def test_a_stage_started_by_another_torchrun_is_refused_in_one_line(tmp_path):
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["training"]["num_processes"] = 2
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    torchrun = {"RANK": "0", "LOCAL_RANK": "0", "WORLD_SIZE": "3", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": "1"}
    completed = subprocess.run(
        [sys.executable, str(REPO / "pipeline/train_policy.py"), "--params", str(tmp_path / "params.yaml"), "--task",
         "lift", "--policy", "carp", "--seed", "0"],
        env={**os.environ, **torchrun}, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert completed.returncode == 1
    assert completed.stderr.strip().splitlines()[-1] == (
        f"error: {tmp_path / 'params.yaml'}: training.num_processes=2: torchrun started 3 processes; run the stage "
        "without torchrun, it starts its own"
    )
    assert "Traceback" not in completed.stderr
