"""`benchmarks/gpu_check.sh` where there is no GPU: one error line and nothing created; its parts that need none."""

import importlib.util
import subprocess
from pathlib import Path

import pandas as pd
import pytest
import torch

from carp.config import load_params

REPO_ROOT = Path(__file__).resolve().parents[1]


def _gpu_check():
    spec = importlib.util.spec_from_file_location("gpu_check", REPO_ROOT / "benchmarks" / "gpu_check.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.skipif(torch.cuda.is_available(), reason="the check runs for real where CUDA is available")
def test_without_cuda_the_check_stops_with_one_line_and_creates_nothing(tmp_path):
    workspace = tmp_path / "workspace"
    completed = subprocess.run(
        ["bash", str(REPO_ROOT / "benchmarks" / "gpu_check.sh"), "--workspace", str(workspace)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert completed.returncode == 1
    assert completed.stderr.startswith("error: gpu_check: no CUDA device is visible to torch ")
    assert len(completed.stderr.strip().splitlines()) == 1 and completed.stdout == ""
    assert not workspace.exists()


def test_the_check_workspace_holds_the_sources_and_valid_params_for_cuda(tmp_path):
    gpu_check = _gpu_check()
    gpu_check.make_workspace(tmp_path, gpu_check.check_params(["carp", "next_token"], epochs=3, num_processes=2))
    params = load_params(tmp_path / "params.yaml")
    assert (params.device, params.tasks, params.policies) == ("cuda", ("lift",), ("carp", "next_token"))
    assert (params.tokenizer.epochs, params.training.epochs, params.training.num_processes) == (3, 3, 2)
    assert params.data.num_demos == 10 and params.eval.episodes == 8
    default = load_params(REPO_ROOT / "params.yaml")
    assert params.family_config("carp") == default.family_config("carp") and params.scales == default.scales
    assert (tmp_path / "dvc.yaml").exists() and (tmp_path / "pipeline" / "train_policy.py").exists()
    assert not (tmp_path / "data").exists() and (tmp_path / ".git").is_dir()


def test_step_time_leaves_out_the_first_epoch_and_divides_by_the_steps(tmp_path):
    history = tmp_path / "history.csv"
    # 1000 windows per epoch, batch 64: 16 steps; the first epoch pays for start-up.
    pd.DataFrame(
        {
            "epoch": [1, 2, 3, 4],
            "epoch_seconds": [9.0, 0.32, 0.16, 0.16],
            "samples_per_second": [1000 / 9, 3125, 6250, 6250],
        }
    ).to_csv(history, index=False)
    summary = _gpu_check().training_summary(history, batch_size=64)
    assert summary["steps_per_epoch"] == 16 and summary["epochs"] == 4
    assert summary["step_ms"] == pytest.approx(10.0)
    assert summary["windows_per_second"] == pytest.approx(6250)
