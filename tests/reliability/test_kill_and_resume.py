"""`kill -9` of a stage mid-way, then the stage again: the result is the uninterrupted run's, and no debris is left.

One tiny workspace for the module, a copy of the shared demos workspace (``lift_demos``): `dvc repro evaluate@lift`
gives the uninterrupted results; then each stage is started again by hand (its dvc.yaml command), its whole process
group is killed with SIGKILL once it has written something a rerun could pick up (the first training state, the
exported ONNX graphs), and it is run once more.

A training state truncated by hand is discarded with one warning, and its stage trains from the first epoch.

What a rerun repeats exactly: weights, metrics and per-epoch losses of both training stages, and every episode of the
evaluation. What it cannot: wall-clock columns (`epoch_seconds`, `samples_per_second`, episode `seconds`, latency
percentiles) and the MLflow run id stored in the policy's metadata (the rerun is another run). Training resumes from
its last state (the log says from which epoch); evaluation keeps no state and runs every episode again.
"""

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pandas as pd
import pytest
import torch

from tests.pipeline.shared_workspaces import copy_pipeline
from tests.pipeline.workspace import dvc, tool_env

TOKENIZER_EPOCHS = 12
POLICY_EPOCHS = 12
PARAMS = {
    "tokenizer": {"epochs": TOKENIZER_EPOCHS, "checkpoint_every": 1},
    "training": {"epochs": POLICY_EPOCHS, "checkpoint_every": 1},
    "eval": {"episodes": 4, "workers": 2, "video": False},
    # The reference and the killed runs each start fresh; `auto` could time the attention kernels differently in
    # each, and the two kernels round differently.
    "carp": {"attention": "masked"},
}
TIMING_COLUMNS = {"epoch_seconds", "samples_per_second", "seconds", "chunk_ms_median"}
REFERENCE_OUTPUTS = (
    "models/tokenizer/tokenizer.pt",
    "models/tokenizer/tokenizer.json",
    "reports/tokenizer/metrics.json",
    "reports/tokenizer/history.csv",
    "models/policy/lift/carp/seed0/policy.pt",
    "reports/policy/lift/carp/seed0/metrics.json",
    "reports/policy/lift/carp/seed0/history.csv",
    "reports/eval/lift/carp/seed0.json",
    "reports/eval/lift/carp/seed0_episodes.csv",
)


def _env(temp_directory: Path) -> dict[str, str]:
    # The stages' own temp directory, so that leftovers of a killed evaluation can be looked for there.
    return {**tool_env(), "TMPDIR": str(temp_directory), "GOMP_SPINCOUNT": "5000"}


@pytest.fixture(scope="module")
def pipeline(lift_demos, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("kill-and-resume")
    workspace = copy_pipeline(lift_demos, root, PARAMS)  # its demos stand
    temp_directory = root / "system-tmp"
    temp_directory.mkdir()
    completed = subprocess.run(
        dvc("repro", "evaluate@lift-carp-0"),
        cwd=workspace,
        env=_env(temp_directory),
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    reference = root / "reference"
    for name in REFERENCE_OUTPUTS:
        (reference / name).parent.mkdir(parents=True, exist_ok=True)
        (reference / name).write_bytes((workspace / name).read_bytes())
    return {"workspace": workspace, "reference": reference, "tmp": temp_directory, "logs": root}


def _stage(pipeline: dict[str, Path], *arguments: str) -> subprocess.Popen:
    log = (pipeline["logs"] / f"{Path(arguments[0]).stem}-{time.monotonic_ns()}.log").open("w")
    return subprocess.Popen(
        [sys.executable, *arguments],
        cwd=pipeline["workspace"],
        env=_env(pipeline["tmp"]),
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,  # its own process group: the stage and the evaluation workers it spawns
    )


def _kill_when(process: subprocess.Popen, ready: Callable[[], bool], deadline_seconds: float = 600) -> None:
    """SIGKILL the process group of `process` as soon as `ready()` holds; it must still be running then."""
    deadline = time.monotonic() + deadline_seconds
    while not ready():
        assert process.poll() is None, f"the stage ended (exit {process.returncode}) before it could be killed"
        assert time.monotonic() < deadline, "the stage never got to the point where it is killed"
        time.sleep(0.01)
    os.killpg(process.pid, signal.SIGKILL)
    assert process.wait(timeout=60) == -signal.SIGKILL


def _rerun(pipeline: dict[str, Path], *arguments: str) -> str:
    process = _stage(pipeline, *arguments)
    assert process.wait(timeout=900) == 0, Path(process.args[-1]).name
    logs = sorted(pipeline["logs"].glob(f"{Path(arguments[0]).stem}-*.log"))
    return logs[-1].read_text()


def _training_epochs(state: Path) -> int:
    return torch.load(state, weights_only=False)["epoch"]


def _assert_same_tensors(expected: dict, actual: dict) -> None:
    assert expected.keys() == actual.keys()
    for name, value in expected.items():
        assert torch.equal(value, actual[name]), name


def _assert_same_table(expected: Path, actual: Path) -> None:
    expected_table, actual_table = pd.read_csv(expected), pd.read_csv(actual)
    assert list(expected_table.columns) == list(actual_table.columns)
    kept = [column for column in expected_table.columns if column not in TIMING_COLUMNS]
    pd.testing.assert_frame_equal(expected_table[kept], actual_table[kept], check_exact=True)


def _assert_no_leftover_temporaries(directory: Path) -> None:
    assert not [path.name for path in directory.rglob("*.tmp")]


@pytest.mark.slow
def test_train_tokenizer_killed_mid_way_resumes_to_the_uninterrupted_result(pipeline):
    workspace, reference = pipeline["workspace"], pipeline["reference"]
    state = workspace / "checkpoints/tokenizer/tokenizer_training_state.pt"
    state.unlink()
    process = _stage(pipeline, "pipeline/train_tokenizer.py")
    _kill_when(process, state.exists)
    killed_at = _training_epochs(state)
    assert 0 < killed_at < TOKENIZER_EPOCHS

    log = _rerun(pipeline, "pipeline/train_tokenizer.py")
    assert f"resuming tokenizer training from {state}" in log
    resumed = torch.load(workspace / "models/tokenizer/tokenizer.pt", weights_only=True)
    expected = torch.load(reference / "models/tokenizer/tokenizer.pt", weights_only=True)
    _assert_same_tensors(expected.pop("state_dict"), resumed.pop("state_dict"))
    assert resumed == expected
    for name in ("models/tokenizer/tokenizer.json", "reports/tokenizer/metrics.json"):
        assert json.loads((workspace / name).read_text()) == json.loads((reference / name).read_text()), name
    _assert_same_table(reference / "reports/tokenizer/history.csv", workspace / "reports/tokenizer/history.csv")
    _assert_no_leftover_temporaries(workspace / "checkpoints")


@pytest.mark.slow
def test_a_truncated_training_state_is_discarded_with_one_warning_and_the_stage_starts_over(pipeline):
    workspace, reference = pipeline["workspace"], pipeline["reference"]
    state = workspace / "checkpoints/tokenizer/tokenizer_training_state.pt"
    state.write_bytes(state.read_bytes()[: state.stat().st_size // 2])

    log = _rerun(pipeline, "pipeline/train_tokenizer.py")
    warnings = [line for line in log.splitlines() if "training state" in line]
    assert len(warnings) == 1 and f"discarding training state {state}: not a readable checkpoint" in warnings[0]
    assert warnings[0].endswith("training starts over") and "Traceback" not in log
    assert f"tokenizer epoch 1/{TOKENIZER_EPOCHS}" in log
    assert _training_epochs(state) == TOKENIZER_EPOCHS
    name = "models/tokenizer/tokenizer.json"
    assert json.loads((workspace / name).read_text()) == json.loads((reference / name).read_text())


@pytest.mark.slow
def test_train_policy_killed_mid_way_resumes_to_the_uninterrupted_result(pipeline):
    workspace, reference = pipeline["workspace"], pipeline["reference"]
    state = workspace / "checkpoints/policy/lift/carp/seed0/training_state.pt"
    state.unlink()
    process = _stage(pipeline, "pipeline/train_policy.py", "--task", "lift", "--policy", "carp", "--seed", "0")
    _kill_when(process, state.exists)
    killed_at = _training_epochs(state)
    assert 0 < killed_at < POLICY_EPOCHS

    log = _rerun(pipeline, "pipeline/train_policy.py", "--task", "lift", "--policy", "carp", "--seed", "0")
    assert f"resuming carp training from {state}" in log
    resumed = torch.load(workspace / "models/policy/lift/carp/seed0/policy.pt", weights_only=True)
    expected = torch.load(reference / "models/policy/lift/carp/seed0/policy.pt", weights_only=True)
    _assert_same_tensors(expected.pop("transformer_state"), resumed.pop("transformer_state"))
    _assert_same_tensors(expected["tokenizer"].pop("state_dict"), resumed["tokenizer"].pop("state_dict"))
    # The rerun is another MLflow run; everything else in the metadata is the same.
    assert resumed["metadata"].pop("mlflow_run_id") != expected["metadata"].pop("mlflow_run_id")
    assert resumed == expected
    name = "reports/policy/lift/carp/seed0/metrics.json"
    assert json.loads((workspace / name).read_text()) == json.loads((reference / name).read_text())
    history = "reports/policy/lift/carp/seed0/history.csv"
    _assert_same_table(reference / history, workspace / history)
    _assert_no_leftover_temporaries(workspace / "checkpoints")


@pytest.mark.slow
def test_evaluate_killed_mid_way_runs_again_to_the_same_episodes_and_leaves_no_onnx_folder(pipeline):
    workspace, reference, temp_directory = pipeline["workspace"], pipeline["reference"], pipeline["tmp"]
    outputs = workspace / "reports/eval/lift/carp"
    for name in ("seed0.json", "seed0_episodes.csv"):
        (outputs / name).unlink()

    def graphs_exported() -> bool:
        return any(temp_directory.glob("carp-onnx-*/decoding.onnx"))

    process = _stage(pipeline, "pipeline/evaluate.py", "--task", "lift", "--policy", "carp", "--seed", "0")
    _kill_when(process, graphs_exported)
    left_behind = sorted(temp_directory.glob("carp-onnx-*"))
    assert len(left_behind) == 1, "the killed evaluation's folder is still there until the next evaluation"
    assert not (outputs / "seed0.json").exists() and not (outputs / "seed0_episodes.csv").exists()

    _rerun(pipeline, "pipeline/evaluate.py", "--task", "lift", "--policy", "carp", "--seed", "0")
    assert not list(temp_directory.glob("carp-onnx-*")), "no ONNX folder outlives the evaluations"
    _assert_same_table(reference / "reports/eval/lift/carp/seed0_episodes.csv", outputs / "seed0_episodes.csv")
    summary = "reports/eval/lift/carp/seed0.json"
    resumed, expected = (json.loads((path / summary).read_text()) for path in (workspace, reference))
    assert {key: value for key, value in resumed.items() if "latency" not in key} == {
        key: value for key, value in expected.items() if "latency" not in key
    }
    assert resumed["episodes"] == 4
