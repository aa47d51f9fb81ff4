"""Ingestion of camera images: read from a robomimic image file, rendered from states, refused when malformed."""

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import zarr

from carp.data.camera_images import plan_images
from carp.data.ingest import BUFFER_DIRNAME, ingest_demonstrations
from carp.data.rendering import RenderSettings, offscreen_backend
from carp.data.replay_buffer import FRAMES_PER_CHUNK, ReplayBuffer
from carp.data.robomimic_io import DatasetError
from tests.conftest import IMAGE_KEYS, OBS_WIDTHS, write_synthetic_file

PROPRIOCEPTION_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
IMAGE_SIZE = 8


def _ingest(raw: Path, output: Path, image_size: int = IMAGE_SIZE, **kwargs):
    return ingest_demonstrations(
        raw,
        output,
        PROPRIOCEPTION_KEYS,
        staging_dir=output.parent / "staging",
        camera_settings=RenderSettings(image_size=image_size),
        **kwargs,
    )


def test_robomimic_image_file_ingests_its_images_chunked_and_compressed(tmp_path):
    raw = tmp_path / "raw.hdf5"
    episodes = write_synthetic_file(raw, image_size=IMAGE_SIZE)
    summary = _ingest(raw, tmp_path / "processed")

    root = tmp_path / "processed" / BUFFER_DIRNAME
    buffer = ReplayBuffer.load(root)
    group = zarr.open_group(str(root), mode="r")
    assert summary.obs_dim == sum(OBS_WIDTHS[key] for key in PROPRIOCEPTION_KEYS) == buffer.obs.shape[1]
    assert buffer.attrs["obs_keys"] == list(PROPRIOCEPTION_KEYS)  # no object pose with images
    assert buffer.attrs["image_keys"] == list(IMAGE_KEYS) and buffer.attrs["image_size"] == IMAGE_SIZE
    assert buffer.attrs["image_sources"] == {key: "file" for key in IMAGE_KEYS}
    for key in IMAGE_KEYS:
        images = group[f"data/{key}"]
        assert images.dtype == np.uint8 and images.chunks == (FRAMES_PER_CHUNK, IMAGE_SIZE, IMAGE_SIZE, 3)
        assert images.compressor is not None
        np.testing.assert_array_equal(images[:], np.concatenate([episode.obs[key] for episode in episodes]))
    np.testing.assert_allclose(
        buffer.obs[30:55, 3:7], episodes[1].obs["robot0_eef_quat"], atol=1e-6
    )  # proprioception keeps the params order: eef pos (3), eef quat (4), gripper (2)


def test_cameras_the_file_does_not_store_are_planned_for_rendering_with_the_same_settings(tmp_path):
    raw = tmp_path / "raw.hdf5"
    write_synthetic_file(raw, image_size=IMAGE_SIZE)
    with h5py.File(raw, "r+") as handle:
        for demo in ("demo_0", "demo_1", "demo_2", "demo_3"):
            del handle[f"data/{demo}/obs/robot0_eye_in_hand_image"]
    settings = RenderSettings(image_size=IMAGE_SIZE, shadows=True)
    plan = plan_images(raw, ["demo_0", "demo_3"], settings)
    assert plan.stored_keys == ("agentview_image",)
    assert plan.rendered == RenderSettings(cameras=("robot0_eye_in_hand",), image_size=IMAGE_SIZE, shadows=True)
    assert plan.sources(settings) == {"agentview_image": "file", "robot0_eye_in_hand_image": "rendered"}
    assert plan_images(raw, ["demo_0"], RenderSettings(cameras=("agentview",))).rendered is None


def _replace(path: Path, demo: str, key: str, values: np.ndarray) -> None:
    with h5py.File(path, "r+") as handle:
        del handle[f"data/{demo}/obs/{key}"]
        handle[f"data/{demo}/obs/{key}"] = values


@pytest.mark.parametrize(
    ("values", "expected"),
    [
        (np.zeros((25, 8, 8, 3), np.float32), "shape=(25, 8, 8, 3), dtype=float32: expected uint8 RGB images"),
        (np.zeros((25, 8, 8), np.uint8), "shape=(25, 8, 8), dtype=uint8: expected uint8 RGB images"),
        (np.zeros((25, 6, 6, 3), np.uint8), "shape=(25, 6, 6, 3): image size differs from demo 'demo_0'"),
    ],
    ids=["float-dtype", "no-channels", "size-differs"],
)
def test_malformed_images_are_refused_in_one_line_naming_key_and_shape_and_nothing_is_written(
    tmp_path, values, expected
):
    raw = tmp_path / "raw.hdf5"
    write_synthetic_file(raw, image_size=IMAGE_SIZE)
    _replace(raw, "demo_1", "agentview_image", values)
    with pytest.raises(DatasetError) as error:
        _ingest(raw, tmp_path / "processed")
    message = str(error.value)
    assert message.startswith(f"{raw}: demo 'demo_1': obs key 'agentview_image'") and "\n" not in message
    assert expected in message
    assert sorted(path.name for path in tmp_path.iterdir()) == ["raw.hdf5"]  # no output, no staging leftover


def test_images_of_another_size_than_configured_are_refused_not_resized(tmp_path):
    raw = tmp_path / "raw.hdf5"
    write_synthetic_file(raw, image_size=IMAGE_SIZE)
    with pytest.raises(DatasetError) as error:
        _ingest(raw, tmp_path / "processed", image_size=IMAGE_SIZE + 2)
    assert str(error.value) == (
        f"{raw}: demo 'demo_0': obs key 'agentview_image': shape=(30, 8, 8, 3): expected (T, 10, 10, 3), "
        "the configured image size; images are not resized"
    )
    assert sorted(path.name for path in tmp_path.iterdir()) == ["raw.hdf5"]


def test_images_stored_in_some_demos_only_are_refused(tmp_path):
    raw = tmp_path / "raw.hdf5"
    write_synthetic_file(raw, image_size=IMAGE_SIZE)
    with h5py.File(raw, "r+") as handle:
        del handle["data/demo_2/obs/robot0_eye_in_hand_image"]
    with pytest.raises(DatasetError, match=r"demo 'demo_2'.*'robot0_eye_in_hand_image'"):
        _ingest(raw, tmp_path / "processed")
    assert sorted(path.name for path in tmp_path.iterdir()) == ["raw.hdf5"]


def test_missing_images_without_states_are_refused_before_rendering(tmp_path):
    raw = tmp_path / "raw.hdf5"
    write_synthetic_file(raw)
    with h5py.File(raw, "r+") as handle:
        del handle["data/demo_0/states"]
        handle["data/demo_0/states"] = np.zeros((30, 0))
    with pytest.raises(DatasetError) as error:
        _ingest(raw, tmp_path / "processed")
    assert str(error.value).startswith(
        f"{raw}: demo 'demo_0': key 'states': shape=(30, 0): no simulator states to render "
        "['agentview_image', 'robot0_eye_in_hand_image'] from"
    )
    assert sorted(path.name for path in tmp_path.iterdir()) == ["raw.hdf5"]


def _tree_digest(root: Path) -> dict[str, str]:
    return {
        str(path.relative_to(root)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(root.rglob("*"))
        if path.is_file()
    }


def test_state_ingestion_ignores_stored_images_and_writes_the_same_bytes(tmp_path):
    with_images, without_images = tmp_path / "with.hdf5", tmp_path / "without.hdf5"
    write_synthetic_file(with_images, image_size=IMAGE_SIZE)
    write_synthetic_file(without_images)
    obs_keys = tuple(OBS_WIDTHS)
    ingest_demonstrations(with_images, tmp_path / "a", obs_keys)
    ingest_demonstrations(without_images, tmp_path / "b", obs_keys)
    first, second = _tree_digest(tmp_path / "a"), _tree_digest(tmp_path / "b")
    # Only the source path recorded in the attributes and the summary differs.
    assert set(first) == set(second) and not any("image" in name for name in first)
    assert {name for name in first if first[name] != second[name]} == {
        f"{BUFFER_DIRNAME}/.zattrs",
        "summary.json",
    }
    attrs = json.loads((tmp_path / "a" / BUFFER_DIRNAME / ".zattrs").read_text())
    assert set(attrs) == {"obs_keys", "obs_widths", "controller", "source", "env_args", "demo_names"}


RENDER_SCRIPT = """
import sys
from pathlib import Path

import numpy as np

from carp.data.image_windows import ImageWindowReader
from carp.data.camera_images import plan_images, render_demos
from carp.data.ingest import BUFFER_DIRNAME, ingest_demonstrations
from carp.data.rendering import RenderSettings
from carp.data.robomimic_io import read_demonstrations

raw, output = Path(sys.argv[1]), Path(sys.argv[2])
settings = RenderSettings(image_size=int(sys.argv[3]))
ingest_demonstrations(
    raw, output, ["robot0_eef_pos"], camera_settings=settings, valid_fraction=0.0, render_workers=2
)
reader = ImageWindowReader(output / BUFFER_DIRNAME, horizon=1, obs_steps=1, action_steps=1)
windows = reader.read(np.arange(len(reader)))
demos = read_demonstrations(raw, ["robot0_eef_pos"])
direct = render_demos(demos.env_args, [(e.attrs, e.states) for e in demos.episodes], settings)
np.savez(
    output.parent / "frames.npz",
    ingested=windows.images[:, 0],
    **{key: np.concatenate([images[key] for images in direct]) for key in settings.image_keys},
)
"""


@pytest.mark.slow
def test_ingestion_renders_missing_cameras_from_the_stored_states(tmp_path, lift_demo_collection):
    raw, _ = lift_demo_collection
    size = 32
    output = tmp_path / "processed"
    # mujoco reads MUJOCO_GL when first imported, so rendering runs in a fresh interpreter.
    completed = subprocess.run(
        [sys.executable, "-c", RENDER_SCRIPT, str(raw), str(output), str(size)],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "MUJOCO_GL": offscreen_backend()},
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    attrs = json.loads((output / BUFFER_DIRNAME / ".zattrs").read_text())
    assert attrs["image_sources"] == {key: "rendered" for key in IMAGE_KEYS} and attrs["image_size"] == size
    frames = np.load(tmp_path / "frames.npz")
    ingested = frames["ingested"]  # (N, cameras, 3, H, W)
    assert ingested.shape[1:] == (2, 3, size, size) and ingested.dtype == np.uint8
    for camera, key in enumerate(IMAGE_KEYS):
        # Every demo's frames, in buffer order, are the renderer's frames of its stored states, though two worker
        # processes rendered them.
        np.testing.assert_array_equal(ingested[:, camera].transpose(0, 2, 3, 1), frames[key])
        assert (ingested[0, camera] != ingested[-1, camera]).any()  # the scene changes over a demo
        assert np.unique(ingested[0, camera].reshape(3, -1), axis=1).shape[1] > 10  # a rendered scene, not blank
