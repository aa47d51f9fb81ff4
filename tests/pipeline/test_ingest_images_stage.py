"""`data.observations: image` in the pipeline: a robomimic image file ingests, a bad one is refused, and an image run
trains and evaluates end to end."""

import json
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
import yaml
import zarr

from tests.conftest import IMAGE_KEYS, write_synthetic_file
from tests.pipeline.workspace import dvc, make_workspace, run, stages_run

pytestmark = pytest.mark.slow

IMAGE_SIZE = 8


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    data = {"observations": "image", "image_size": IMAGE_SIZE}
    image_encoder = {"crop_size": IMAGE_SIZE}  # the policies' crop fits the images
    return make_workspace(tmp_path_factory.mktemp("ingest-images"), {"data": data, "image_encoder": image_encoder})


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


def test_an_image_run_reproduces_end_to_end_and_a_second_run_does_nothing(tmp_path):
    # Collection renders nothing; ingest renders both cameras from the demos' states; every family stage of the
    # default pipeline then trains and evaluates with the camera encoder (light trunk, small images).
    params = {
        "data": {"observations": "image", "image_size": 40, "num_demos": 2},
        "image_encoder": {"crop_size": 36, "base_channels": 16, "num_keypoints": 4, "feature_dim": 8},
        "eval": {"video": True, "video_episodes": 1},
    }
    workspace = make_workspace(tmp_path / "carp", params)
    first = run(dvc("repro"), workspace, timeout=1500)
    assert first.returncode == 0, first.stderr[-3000:]
    group = zarr.open_group(str(workspace / "data" / "processed" / "lift" / "replay.zarr"), mode="r")
    assert list(group.attrs["image_keys"]) == list(IMAGE_KEYS) and group["data/agentview_image"].shape[1:] == (
        40,
        40,
        3,
    )
    checkpoint = torch.load(workspace / "models/policy/lift/carp/seed0/policy.pt", weights_only=False)
    assert checkpoint["observations"]["kind"] == "image"
    assert tuple(checkpoint["observations"]["image_encoder"]["cameras"]) == ("agentview", "robot0_eye_in_hand")
    evaluation = json.loads((workspace / "reports/eval/lift/carp/seed0.json").read_text())
    assert evaluation["episodes"] == 2 and evaluation["backend"] == "torch"  # the encoder runs in PyTorch
    assert evaluation["render_step_ms_median"] > 0 and evaluation["latency_predict_ms_median"] > 0
    assert evaluation["batched_latency_predict_ms_median"] > 0
    assert 0 < evaluation["latency_encode_ms_median"] < evaluation["latency_predict_ms_median"]
    report = (workspace / "reports/report.md").read_text()
    assert "## Success rate" in report and "## Camera images" in report
    assert (workspace / "reports/figures/cameras_lift.png").exists()
    assert "rendering the cameras:" in report
    assert "## Rollout videos" in report and "(eval/videos/lift_carp-0_seed100000.gif)" in report
    assert (workspace / "reports/eval/videos/lift_carp-0_seed100000.gif").stat().st_size > 0

    second = run(dvc("repro"), workspace, timeout=600)
    assert second.returncode == 0, second.stderr[-3000:]
    assert stages_run(second.stdout) == {"check_inputs"}, second.stdout


def test_an_image_runs_user_file_needs_the_proprioception_not_the_object_pose(tmp_path):
    data = {"observations": "image", "image_size": IMAGE_SIZE, "raw_files": {"lift": "user/lift.hdf5"}}
    workspace = make_workspace(tmp_path / "carp", {"data": data, "image_encoder": {"crop_size": IMAGE_SIZE}})
    user_file = workspace / "user" / "lift.hdf5"
    user_file.parent.mkdir()
    write_synthetic_file(user_file, image_size=IMAGE_SIZE)
    with h5py.File(user_file, "r+") as handle:
        for demo in handle["data"].values():
            del demo["obs/object"]
    collect = [sys.executable, "pipeline/collect.py", "--task", "lift"]
    copied = run(collect, workspace, timeout=300)
    assert copied.returncode == 0, copied.stderr
    assert (workspace / "data" / "raw" / "lift.hdf5").exists()
    # A state run reads the object's pose, and is refused by name.
    params = yaml.safe_load((workspace / "params.yaml").read_text())
    params["data"]["observations"] = "state"
    (workspace / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    refused = run(collect, workspace, timeout=300)
    errors = [line for line in refused.stderr.splitlines() if line.startswith("error:")]
    assert refused.returncode == 1 and len(errors) == 1 and "'object'" in errors[0], refused.stderr
