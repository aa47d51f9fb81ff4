"""A LeRobotDataset folder named in `data.raw_files` goes through check_inputs, collect and ingest like a robomimic
file: carp's demos exported as a LeRobotDataset ingest to the same replay buffer (the same windows) as the file."""

import json
import sys

import numpy as np
import pytest
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
