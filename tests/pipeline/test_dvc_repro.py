"""End to end: `dvc repro` on tiny params in a temporary copy of the repository, then a second run is a no-op."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]

TINY_PARAMS = {
    "scales": [1, 2, 4],
    "codebook_size": 16,
    "data": {"num_demos": 3},
    "tokenizer": {"epochs": 2, "batch_size": 64, "checkpoint_every": 1},
    "policy": {"epochs": 2, "depth": 1, "width": 16, "num_heads": 2, "batch_size": 64, "warmup_steps": 2},
    "eval": {"episodes": 2, "workers": 2, "max_steps": {"lift": 40, "can": 40, "square": 40}},
}


def _merge(base: dict, override: dict) -> dict:
    merged = dict(base)
    for key, value in override.items():
        merged[key] = _merge(base[key], value) if isinstance(value, dict) and key in base else value
    return merged


def _run(command: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    return subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)


@pytest.mark.slow
def test_dvc_repro_runs_every_stage_and_second_run_is_a_no_op(tmp_path):
    workspace = tmp_path / "carp"
    tracked = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, capture_output=True, text=True)
    for name in tracked.stdout.split():
        source = REPO / name
        if source.is_file() and not name.startswith(("data/", "models/", "reports/")):
            (workspace / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, workspace / name)
    params = yaml.safe_load((workspace / "params.yaml").read_text())
    (workspace / "params.yaml").write_text(yaml.safe_dump(_merge(params, TINY_PARAMS), sort_keys=False))
    for command in (
        ["git", "init", "-q"],
        ["git", "add", "-A"],
        ["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "tiny"],
    ):
        assert _run(command, workspace).returncode == 0

    first = _run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert first.returncode == 0, first.stderr[-3000:]

    for output in (
        "data/raw/lift.hdf5",
        "data/processed/lift/replay.zarr",
        "data/processed/lift/normalization.json",
        "models/tokenizer/tokenizer.pt",
        "models/tokenizer_ref.json",
        "models/policy/lift/policy.pt",
        "reports/tokenizer/metrics.json",
        "reports/tokenizer/reconstruction.png",
        "reports/policy/lift/metrics.json",
        "reports/eval/lift.json",
        "reports/eval/lift_episodes.csv",
        "reports/report.md",
        "reports/report.html",
    ):
        assert (workspace / output).exists(), output
    evaluation = json.loads((workspace / "reports/eval/lift.json").read_text())
    assert evaluation["episodes"] == 2 and 0 <= evaluation["success_rate"] <= 1
    assert evaluation["latency_predict_ms_median"] > 0
    reference = json.loads((workspace / "models/tokenizer_ref.json").read_text())
    assert reference["name"] == "carp-tokenizer-panda-abs10" and reference["alias"] == "default"
    assert (workspace / "mlflow.db").exists()
    assert "## Success rate" in (workspace / "reports/report.md").read_text()

    second = _run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "Running stage" not in second.stdout
    status = _run([sys.executable, "-m", "dvc", "status"], workspace)
    assert "up to date" in status.stdout, status.stdout
