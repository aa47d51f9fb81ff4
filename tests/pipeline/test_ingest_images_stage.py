"""The ingest stage script with `data.observations: image`: a robomimic image file ingests; a bad one is refused."""

import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
import zarr

from tests.conftest import IMAGE_KEYS, write_synthetic_file
from tests.pipeline.workspace import dvc, make_workspace, run

pytestmark = pytest.mark.slow

IMAGE_SIZE = 8


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    data = {"observations": "image", "image_size": IMAGE_SIZE}
    return make_workspace(tmp_path_factory.mktemp("ingest-images"), {"data": data})


def _ingest(workspace: Path):
    return run([sys.executable, "pipeline/ingest.py", "--task", "lift"], workspace, timeout=300)


def test_image_file_ingests_with_its_images_and_proprioception_only(workspace):
    raw = workspace / "data" / "raw" / "lift.hdf5"
    episodes = write_synthetic_file(raw, image_size=IMAGE_SIZE)
    completed = _ingest(workspace)
    assert completed.returncode == 0, completed.stderr
    assert f"lift: images agentview_image, robot0_eye_in_hand_image at {IMAGE_SIZE} px" in completed.stdout
    group = zarr.open_group(str(workspace / "data" / "processed" / "lift" / "replay.zarr"), mode="r")
    assert group.attrs["obs_keys"] == ["robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"]
    for key in IMAGE_KEYS:
        np.testing.assert_array_equal(group[f"data/{key}"][:], np.concatenate([e.obs[key] for e in episodes]))


def test_wrong_image_dtype_is_one_error_line_with_key_and_shape_and_nothing_is_written(workspace):
    raw = workspace / "data" / "raw" / "lift.hdf5"
    output = workspace / "data" / "processed" / "lift"
    write_synthetic_file(raw, image_size=IMAGE_SIZE)
    with h5py.File(raw, "r+") as handle:
        del handle["data/demo_0/obs/agentview_image"]
        handle["data/demo_0/obs/agentview_image"] = np.zeros((30, IMAGE_SIZE, IMAGE_SIZE, 3), np.float64)
    before = sorted(path.relative_to(output) for path in output.rglob("*")) if output.exists() else None
    completed = _ingest(workspace)
    errors = [line for line in completed.stderr.splitlines() if line.startswith("error:")]
    assert completed.returncode == 1 and "Traceback" not in completed.stderr and len(errors) == 1, completed.stderr
    assert errors[0].startswith(
        f"error: {raw.resolve()}: demo 'demo_0': obs key 'agentview_image': shape=(30, 8, 8, 3), dtype=float64"
    ), errors[0]
    after = sorted(path.relative_to(output) for path in output.rglob("*")) if output.exists() else None
    assert after == before  # an earlier output stays as it was
    assert list(workspace.glob("data/.staging/.*")) == []


def test_image_settings_of_a_state_run_rerun_ingest_alone_with_an_identical_output(tmp_path):
    workspace = make_workspace(tmp_path, {"data": {"num_demos": 2}})
    assert run(dvc("repro", "ingest@lift"), workspace, timeout=600).returncode == 0
    before = yaml.safe_load((workspace / "dvc.lock").read_text())["stages"]["ingest@lift"]["outs"]
    params = yaml.safe_load((workspace / "params.yaml").read_text())
    params["data"].update(cameras=["agentview"], image_size=32, proprioception_keys=["robot0_eef_pos"])
    (workspace / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    status = run(dvc("status", "ingest@lift"), workspace)
    assert "modified:           data.cameras" in status.stdout, status.stdout
    assert run(dvc("repro", "ingest@lift"), workspace, timeout=600).returncode == 0
    after = yaml.safe_load((workspace / "dvc.lock").read_text())["stages"]["ingest@lift"]["outs"]
    assert after == before  # same directory hash: train_tokenizer and every later stage stay cached
