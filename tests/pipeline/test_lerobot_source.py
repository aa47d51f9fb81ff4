"""A LeRobotDataset folder named in `data.raw_files` goes through check_inputs, collect and ingest like a robomimic
file. carp's Lift demos exported as a LeRobotDataset ingest to byte-identical processed data (the same windows and
statistics), so every later stage sees the inputs of the run from the file: the same training curve and the same
evaluation, episode by episode."""

import json
import sys

import pandas as pd
import pytest
import yaml

from carp.data.lerobot.export import export_lerobot
from tests.conftest import write_synthetic_file
from tests.pipeline.shared_workspaces import copy_pipeline
from tests.pipeline.workspace import make_workspace, run, stages_run

pytestmark = pytest.mark.slow


def repro(workspace, *targets):
    result = run([sys.executable, "-m", "dvc", "repro", *targets], workspace)
    assert result.returncode == 0, result.stderr[-3000:]
    return stages_run(result.stdout)


def set_raw_file(workspace, task, path):
    params_file = workspace / "params.yaml"
    params = yaml.safe_load(params_file.read_text())
    params["data"]["raw_files"][task] = path
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))


def stage_outputs(workspace, stage):
    """The md5 of each output `dvc.lock` records for a stage: what the stages after it depend on."""
    lock = yaml.safe_load((workspace / "dvc.lock").read_text())
    return {out["path"]: out["md5"] for out in lock["stages"][stage]["outs"]}


def test_lift_exported_as_a_lerobot_dataset_ingests_to_the_same_bytes_as_its_file(tmp_path):
    workspace = make_workspace(tmp_path / "carp", {"data": {"raw_files": {"lift": "own/lift.hdf5"}}})
    write_synthetic_file(workspace / "own/lift.hdf5", lengths=(30, 25, 40, 20))
    export_lerobot(workspace / "own/lift.hdf5", workspace / "own/lift")
    assert repro(workspace, "ingest@lift") == {"check_inputs", "collect@lift", "ingest@lift"}
    from_file = stage_outputs(workspace, "ingest@lift")

    set_raw_file(workspace, "lift", "own/lift")
    assert repro(workspace, "ingest@lift") == {"check_inputs", "collect@lift", "ingest@lift"}
    assert stage_outputs(workspace, "ingest@lift") == from_file
    assert repro(workspace, "ingest@lift") == {"check_inputs"}  # a second run does nothing
    record = json.loads((workspace / "data" / "inputs" / "lift.json").read_text())
    assert record["source"] == "lerobot" and record["files"] == 6


# Columns that measure time, not behaviour: they differ between any two runs.
TIMING_COLUMNS = {"epoch_seconds", "samples_per_second", "seconds", "chunk_ms_median"}


def behaviour(csv_path):
    frame = pd.read_csv(csv_path)
    return frame.drop(columns=[column for column in frame.columns if column in TIMING_COLUMNS])


def test_the_lift_pipeline_from_its_lerobot_export_trains_and_evaluates_as_from_its_file(lift_pipeline, tmp_path):
    """carp's own Lift demos, run through every stage from the HDF5 file (a copy of the shared arm pipeline), then
    exported as a LeRobotDataset: the ingest outputs are the same bytes, and training and evaluation run again from
    the export (forced) give the same training curve and the same outcome in every test episode."""
    workspace = copy_pipeline(lift_pipeline, tmp_path)
    history = workspace / "reports/policy/lift/carp/seed0/history.csv"
    episodes = workspace / "reports/eval/lift/carp/seed0_episodes.csv"
    from_file = {"ingest": stage_outputs(workspace, "ingest@lift"), "history": behaviour(history),
                 "episodes": behaviour(episodes)}  # fmt: skip

    export_lerobot(workspace / "data/raw/lift.hdf5", workspace / "own/lift")
    set_raw_file(workspace, "lift", "own/lift")
    assert repro(workspace) == {"check_inputs", "collect@lift", "ingest@lift"}  # the same inputs downstream
    assert stage_outputs(workspace, "ingest@lift") == from_file["ingest"]
    for stage in ("train_policy@lift-carp-0", "evaluate@lift-carp-0"):
        forced = run([sys.executable, "-m", "dvc", "repro", "--force", "--single-item", stage], workspace)
        assert forced.returncode == 0, forced.stderr[-3000:]
        assert stages_run(forced.stdout) == {stage}
    pd.testing.assert_frame_equal(behaviour(history), from_file["history"])
    pd.testing.assert_frame_equal(behaviour(episodes), from_file["episodes"])
    assert len(from_file["episodes"]) == 2 and {"success", "steps"} <= set(from_file["episodes"].columns)


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

    from_v3 = stage_outputs(workspace, "ingest@pusht")
    set_raw_file(workspace, "pusht", "tests/fixtures/lerobot/pusht-v2.1")
    second = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert second.returncode == 0, second.stderr[-3000:]
    assert stages_run(second.stdout) == {"check_inputs", "collect@pusht", "ingest@pusht"}, second.stdout[-3000:]
    assert stage_outputs(workspace, "ingest@pusht") == from_v3
    record = json.loads((workspace / "data/inputs/pusht.json").read_text())
    assert record["source"] == "lerobot" and record["path"].endswith("pusht-v2.1")
