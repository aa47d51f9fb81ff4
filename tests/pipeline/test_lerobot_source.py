"""A LeRobotDataset folder named in `data.raw_files` goes through check_inputs, collect and ingest like a robomimic
file: carp's demos exported as a LeRobotDataset ingest to the same replay buffer (the same windows) as the file."""

import json
import sys

import numpy as np
import pytest
import yaml
import zarr

from carp.data.lerobot.export import export_lerobot
from tests.conftest import write_synthetic_file
from tests.pipeline.workspace import make_workspace, run, stages_run

pytestmark = pytest.mark.slow


def repro(workspace):
    result = run([sys.executable, "-m", "dvc", "repro", "ingest@lift"], workspace)
    assert result.returncode == 0, result.stderr[-3000:]
    return stages_run(result.stdout)


def test_an_exported_lerobot_dataset_ingests_to_the_same_buffer_as_its_file(tmp_path):
    runs = {}
    for source in ("own/lift.hdf5", "own/lift"):
        workspace = make_workspace(
            tmp_path / source.replace("/", "-").replace(".", "-"), {"data": {"raw_files": {"lift": source}}}
        )
        write_synthetic_file(workspace / "own/lift.hdf5", lengths=(30, 25, 40, 20))
        if source == "own/lift":
            export_lerobot(workspace / "own/lift.hdf5", workspace / "own/lift")
            (workspace / "own/lift.hdf5").unlink()
        assert repro(workspace) == {"check_inputs", "collect@lift", "ingest@lift"}
        assert repro(workspace) == {"check_inputs"}  # a second run does nothing
        runs[source] = workspace / "data" / "processed" / "lift"
    record = json.loads((tmp_path / "own-lift" / "data" / "inputs" / "lift.json").read_text())
    assert record["source"] == "lerobot" and record["files"] == 6
    ours, theirs = (zarr.open(str(runs[source] / "replay.zarr"), mode="r") for source in runs)
    for key in ("data/obs", "data/action", "meta/episode_ends", "meta/valid_episodes"):
        assert np.array_equal(ours[key][:], theirs[key][:]), key
    normalization = [json.loads((path / "normalization.json").read_text()) for path in runs.values()]
    assert normalization[0] == normalization[1]


PUSHT = {
    "tasks": ["pusht"],
    "policies": ["carp"],
    "data": {"raw_files": {"pusht": "tests/fixtures/lerobot/pusht-v3.0"}},
    "eval": {"max_steps": {"pusht": 30}},
}


def test_push_t_trains_and_evaluates_from_either_lerobot_version(tmp_path):
    """The v3.0 fixture (carp's export) runs every stage in simulation; the v2.1 fixture (LeRobot's own writer, the
    same frames) then reruns only the input stages, as its replay buffer is the same, so training and evaluation
    stand for both."""
    workspace = make_workspace(tmp_path / "carp", PUSHT)
    first = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert first.returncode == 0, first.stderr[-3000:]
    for output in (
        "models/policy/pusht/carp/seed0/policy.pt",
        "reports/eval/pusht/carp/seed0.json",
        "reports/report.md",
    ):
        assert (workspace / output).exists(), output
    processed = json.loads((workspace / "data/processed/pusht/summary.json").read_text())
    assert (processed["obs_dim"], processed["action_dim"], processed["episodes"]) == (20, 2, 3)
    summary = json.loads((workspace / "reports/eval/pusht/carp/seed0.json").read_text())
    assert summary["max_reward_episodes"] == 2 and 0.0 <= summary["max_reward_mean"] <= 1.0
    assert stages_run(run([sys.executable, "-m", "dvc", "repro"], workspace).stdout) == {"check_inputs"}

    params_file = workspace / "params.yaml"
    params = yaml.safe_load(params_file.read_text())
    params["data"]["raw_files"]["pusht"] = "tests/fixtures/lerobot/pusht-v2.1"
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))
    second = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert second.returncode == 0, second.stderr[-3000:]
    assert stages_run(second.stdout) == {"check_inputs", "collect@pusht", "ingest@pusht"}, second.stdout[-3000:]
    record = json.loads((workspace / "data/inputs/pusht.json").read_text())
    assert record["source"] == "lerobot" and record["path"].endswith("pusht-v2.1")
