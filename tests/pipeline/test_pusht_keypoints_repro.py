"""End to end on Push-T from a dataset in ``lerobot/pusht_keypoints``' layout (the paper's Push-T demonstrations as
LeRobot publishes them): with ``data.raw_files.pusht`` naming it, `dvc repro` derives carp's observations and states
from the T's polygon vertices at collect, ingests, trains and evaluates in simulation, and a second run does
nothing."""

import json
import sys

import h5py
import numpy as np
import pytest

from tests.pipeline.workspace import make_workspace, run, stages_run

pytestmark = pytest.mark.slow

PARAMS = {
    "tasks": ["pusht"],
    "policies": ["carp"],
    "data": {"raw_files": {"pusht": "tests/fixtures/lerobot/pusht-keypoints"}},
    "eval": {"max_steps": {"pusht": 30}},
}


def test_push_t_keypoints_dataset_trains_and_evaluates_and_a_second_run_does_nothing(tmp_path):
    workspace = make_workspace(tmp_path / "carp", PARAMS)
    first = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert first.returncode == 0, first.stderr[-3000:]
    assert {"collect@pusht", "ingest@pusht"} <= stages_run(first.stdout)
    with h5py.File(workspace / "data/raw/pusht.hdf5", "r") as raw:
        demo = raw["data/demo_0"]
        assert demo["obs/block_keypoints"].shape[1] == 18 and demo["obs/agent_pos"].shape[1] == 2
        assert demo["states"].shape[1] == 5
        assert json.loads(raw["data"].attrs["env_args"])["env_name"] == "gym_pusht/PushT-v0"
        assert np.isfinite(demo["states"][()]).all()
    processed = json.loads((workspace / "data/processed/pusht/summary.json").read_text())
    assert (processed["obs_dim"], processed["action_dim"], processed["episodes"]) == (20, 2, 3)
    summary = json.loads((workspace / "reports/eval/pusht/carp/seed0.json").read_text())
    assert summary["max_reward_episodes"] == 2 and 0.0 <= summary["max_reward_mean"] <= 1.0
    assert (workspace / "reports/report.md").exists()
    assert stages_run(run([sys.executable, "-m", "dvc", "repro"], workspace).stdout) == {"check_inputs"}
