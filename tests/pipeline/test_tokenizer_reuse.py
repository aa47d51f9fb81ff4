"""Walkthrough: a tokenizer registered from Lift and Can demos serves a Square policy without any tokenizer training.

The walkthrough starts from a copy of the shared arm pipeline (its Lift demos stand) without its MLflow store, so the
store holds this walkthrough's runs alone."""

import json

import pytest
import torch
import yaml

from carp.tracking.runs import find_runs
from tests.pipeline.shared_workspaces import copy_pipeline
from tests.pipeline.workspace import dvc, run


def _set_params(workspace, change) -> None:
    path = workspace / "params.yaml"
    params = yaml.safe_load(path.read_text())
    change(params)
    path.write_text(yaml.safe_dump(params, sort_keys=False))


@pytest.mark.slow
def test_square_policy_reuses_a_tokenizer_registered_on_lift_and_can(lift_pipeline, tmp_path):
    variation = {"tasks": ["lift", "can"], "policies": ["carp"], "eval": {"episodes": 1, "workers": 1}}
    workspace = copy_pipeline(lift_pipeline, tmp_path, variation, tracking=False)
    first = run(dvc("repro", "register_tokenizer"), workspace)
    assert first.returncode == 0, first.stderr[-3000:]
    reference = json.loads((workspace / "models/tokenizer_ref.json").read_text())
    assert reference["name"] == "carp-tokenizer-panda-abs10"
    assert json.loads((workspace / "models/tokenizer/tokenizer.json").read_text())["tasks"] == ["lift", "can"]
    training_state = workspace / "checkpoints/tokenizer"
    state_before = {p.name: p.stat().st_mtime_ns for p in training_state.iterdir()}

    uri = f"models:/{reference['name']}@{reference['alias']}"

    def reuse(params):
        params["tasks"] = ["square"]
        params["tokenizer"]["source"] = uri

    _set_params(workspace, reuse)
    # The walkthrough of docs/pipeline.md: Square's data, then everything downstream of the registry stage;
    # train_tokenizer is not even visited.
    data = run(dvc("repro", "collect@square", "ingest@square"), workspace)
    assert data.returncode == 0, data.stderr[-3000:]
    second = run(dvc("repro", "--downstream", "register_tokenizer"), workspace)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "Running stage 'train_tokenizer'" not in second.stdout + data.stdout
    assert "Running stage 'train_policy@square-carp-0'" in second.stdout

    # The registered weights were used as they are: same hash, same registry version, trained on lift and can.
    metadata = json.loads((workspace / "models/tokenizer/tokenizer.json").read_text())
    assert metadata["sha256"] == reference["sha256"] and metadata["tasks"] == ["lift", "can"]
    reused = json.loads((workspace / "models/tokenizer_ref.json").read_text())
    assert (reused["version"], reused["sha256"]) == (reference["version"], reference["sha256"])
    # No tokenizer training happened: the training state is untouched and the stage's run logged no epochs.
    assert {p.name: p.stat().st_mtime_ns for p in training_state.iterdir()} == state_before
    tracking = f"sqlite:///{workspace / 'mlflow.db'}"
    runs = [r for r in find_runs(tracking, "carp-tokenizer") if r["run_name"] == "train_tokenizer"]
    assert len(runs) == 1 and runs[0]["metrics"].get("train_loss") is not None  # only the Lift+Can training

    # A plain `dvc repro` also trains nothing: train_tokenizer then only fetches and measures the registered version.
    third = run(dvc("repro"), workspace)
    assert third.returncode == 0, third.stderr[-3000:]
    runs = [r for r in find_runs(tracking, "carp-tokenizer") if r["run_name"] == "train_tokenizer"]
    assert runs[0]["tags"]["carp.tokenizer_source"] == uri
    assert "train_loss" not in runs[0]["metrics"] and "rmse_percent_range.mean" in runs[0]["metrics"]
    assert json.loads((workspace / "models/tokenizer/tokenizer.json").read_text())["sha256"] == reference["sha256"]
    assert {p.name: p.stat().st_mtime_ns for p in training_state.iterdir()} == state_before
    # The Square policy was trained against it and evaluated.
    evaluation = json.loads((workspace / "reports/eval/square/carp/seed0.json").read_text())
    assert evaluation["episodes"] == 1
    checkpoint_metadata = torch.load(workspace / "models/policy/square/carp/seed0/policy.pt", weights_only=True)
    assert checkpoint_metadata["metadata"]["tokenizer"]["sha256"] == reference["sha256"]

    # A registered tokenizer that does not fit the params is refused with the differing field named.
    _set_params(workspace, lambda params: params.update(codebook_size=32))
    refused = run(dvc("repro"), workspace)
    assert refused.returncode != 0
    assert "tokenizer codebook_size is 16 but the params ask for 32" in refused.stderr
