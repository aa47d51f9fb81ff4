"""train_tokenizer and register_tokenizer refuse a tokenizer that is not finite: one `error:` line, nothing written."""

import sys
from pathlib import Path

import pytest
import torch
from mlflow import MlflowClient

from carp.config import load_params
from carp.data.ingest import ingest_demonstrations
from carp.data.normalizer import load_normalizers
from carp.tokenizer.artifact import save_tokenizer_artifact
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from tests.conftest import OBS_KEYS, write_synthetic_file
from tests.pipeline.workspace import make_workspace, run

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    # A learning rate this large makes the first epoch's loss NaN (tests/training/test_tokenizer_trainer.py).
    root = make_workspace(tmp_path_factory.mktemp("nonfinite"), {"tokenizer": {"learning_rate": 1e10}})
    raw = root / "data" / "raw" / "lift.hdf5"
    write_synthetic_file(raw)
    ingest_demonstrations(raw, root / "data" / "processed" / "lift", OBS_KEYS)
    return root


def _one_error_line(completed) -> str:
    errors = [line for line in completed.stderr.splitlines() if line.startswith("error:")]
    assert completed.returncode == 1
    assert "Traceback" not in completed.stderr and len(errors) == 1, completed.stderr
    return errors[0]


def test_a_diverging_tokenizer_run_fails_and_writes_no_output(workspace):
    completed = run([sys.executable, "pipeline/train_tokenizer.py"], workspace, timeout=600)
    line = _one_error_line(completed)
    assert line.startswith("error: tokenizer training epoch 1/2: train_loss=nan: not finite"), line
    assert not (workspace / "models" / "tokenizer").exists()
    assert not list((workspace / "reports").glob("tokenizer/*"))


def test_a_tokenizer_with_a_non_finite_metric_is_not_registered(workspace):
    # A tokenizer saved before its metrics were checked, whose held-out error is inf.
    params = load_params(workspace / "params.yaml")
    tokenizer = params.tokenizer
    spec = TokenizerSpec(
        action_dim=params.action_format.policy_dim,
        action_horizon=params.data.action_horizon,
        scales=params.scales,
        codebook_size=params.codebook_size,
        latent_channels=tokenizer.latent_channels,
        base_channels=tokenizer.base_channels,
        channel_mult=tokenizer.channel_mult,
    )
    statistics = load_normalizers(workspace / "data" / "processed" / "lift" / "normalization.json")["action"]
    directory = workspace / "models" / "tokenizer"
    save_tokenizer_artifact(directory, MultiScaleActionTokenizer(spec), {"lift": statistics}, params.action_space)
    payload = torch.load(directory / "tokenizer.pt", weights_only=False)
    payload["metrics"] = {"rmse_percent_range/mean": float("inf")}
    torch.save(payload, directory / "tokenizer.pt")

    completed = run([sys.executable, "pipeline/register_tokenizer.py"], workspace, timeout=600)
    assert _one_error_line(completed) == (
        f"error: {directory / 'tokenizer.pt'}: metric rmse_percent_range/mean=inf: not finite (training diverged, "
        "or the data's range is too wide)"
    )
    assert not (workspace / "models" / "tokenizer_ref.json").exists()
    if (workspace / "mlflow.db").exists():
        client = MlflowClient(tracking_uri=f"sqlite:///{workspace / 'mlflow.db'}")
        assert client.search_registered_models() == []
