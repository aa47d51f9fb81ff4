"""Image windows: the source frames of each window, read from only the chunks they lie in."""

from collections.abc import MutableMapping
from pathlib import Path

import numpy as np
import pytest
import zarr

from carp.data.image_windows import ImageWindowReader, episode_images
from carp.data.ingest import BUFFER_DIRNAME, ingest_demonstrations
from carp.data.rendering import RenderSettings
from carp.data.replay_buffer import FRAMES_PER_CHUNK, ReplayBuffer
from carp.data.windows import make_windows, window_row_indices
from tests.conftest import IMAGE_KEYS, write_synthetic_file

PROPRIOCEPTION_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
LENGTHS = (30, 25, 40, 20)
HORIZON, OBS_STEPS, ACTION_STEPS = 16, 2, 8


class CountingStore(MutableMapping):
    """A zarr store that records every key read through it."""

    def __init__(self, inner: MutableMapping) -> None:
        self.inner = inner
        self.reads: list[str] = []

    def __getitem__(self, key):
        self.reads.append(key)
        return self.inner[key]

    def __setitem__(self, key, value):
        self.inner[key] = value

    def __delitem__(self, key):
        del self.inner[key]

    def __iter__(self):
        return iter(self.inner)

    def __len__(self):
        return len(self.inner)

    def __contains__(self, key):
        return key in self.inner


@pytest.fixture(scope="module")
def image_buffer(tmp_path_factory) -> tuple[Path, list]:
    """An image replay buffer of 4 demos with 8 x 8 noise images, and the source episodes."""
    folder = tmp_path_factory.mktemp("image-windows")
    episodes = write_synthetic_file(folder / "raw.hdf5", lengths=LENGTHS, image_size=8)
    ingest_demonstrations(
        folder / "raw.hdf5", folder / "processed", PROPRIOCEPTION_KEYS, camera_settings=RenderSettings(image_size=8)
    )
    return folder / "processed" / BUFFER_DIRNAME, episodes


def test_windows_hold_the_source_frames_proprioception_and_actions(image_buffer):
    root, episodes = image_buffer
    reader = ImageWindowReader(root, HORIZON, OBS_STEPS, ACTION_STEPS)
    buffer = ReplayBuffer.load(root)
    rows = window_row_indices(buffer.episode_ends, HORIZON, OBS_STEPS - 1, ACTION_STEPS - 1)
    assert len(reader) == len(rows)
    indices = np.array([0, 7, len(rows) - 1, 40, 7, 60])  # repeats and any order
    windows = reader.read(indices)

    source = {key: np.concatenate([episode.obs[key] for episode in episodes]) for key in IMAGE_KEYS}
    assert windows.images.shape == (len(indices), OBS_STEPS, len(IMAGE_KEYS), 3, 8, 8)
    assert windows.images.dtype == np.uint8 and windows.images.flags["C_CONTIGUOUS"]
    for n, window in enumerate(indices):
        for t in range(OBS_STEPS):
            for camera, key in enumerate(IMAGE_KEYS):
                np.testing.assert_array_equal(
                    windows.images[n, t, camera], source[key][rows[window, t]].transpose(2, 0, 1)
                )
    # The first window of an episode pads by repeating its first frame.
    np.testing.assert_array_equal(windows.images[0, 0], windows.images[0, 1])
    obs, actions = make_windows(buffer, HORIZON, OBS_STEPS, ACTION_STEPS)
    np.testing.assert_array_equal(windows.proprioception, obs[indices])
    np.testing.assert_array_equal(windows.actions, actions[indices])
    eef = np.concatenate([episode.obs["robot0_eef_pos"] for episode in episodes])
    np.testing.assert_allclose(windows.proprioception[:, :, :3], eef[rows[indices, :OBS_STEPS]], atol=1e-6)


def test_a_batch_reads_only_the_chunks_holding_its_frames(image_buffer):
    root, _ = image_buffer
    store = CountingStore(zarr.DirectoryStore(str(root)))
    reader = ImageWindowReader(store, HORIZON, OBS_STEPS, ACTION_STEPS)
    store.reads.clear()
    indices = np.array([3, 60, 61])
    reader.read(indices)
    frames = np.unique(reader.rows[indices, :OBS_STEPS])
    expected = {f"data/{key}/{chunk}.0.0.0" for key in IMAGE_KEYS for chunk in np.unique(frames // FRAMES_PER_CHUNK)}
    image_reads = [key for key in store.reads if "_image/" in key and not key.endswith((".zarray", ".zattrs"))]
    assert sorted(image_reads) == sorted(expected)  # each needed chunk once, no other chunk


@pytest.mark.parametrize("split", ["train", "valid", "all"])
def test_preloaded_frames_give_the_same_windows_and_the_batches_read_nothing(image_buffer, split):
    root, _ = image_buffer
    lazy = ImageWindowReader(root, HORIZON, OBS_STEPS, ACTION_STEPS, split=split)
    store = CountingStore(zarr.DirectoryStore(str(root)))
    preloaded = ImageWindowReader(store, HORIZON, OBS_STEPS, ACTION_STEPS, split=split, preload_limit_bytes=1 << 20)
    assert preloaded.preloaded and not lazy.preloaded
    store.reads.clear()
    indices = np.random.default_rng(0).integers(0, len(lazy), 50)  # repeats and any order
    images = preloaded.images(indices)
    assert not [key for key in store.reads if "_image/" in key]  # served from memory
    np.testing.assert_array_equal(images, lazy.images(indices))
    assert images.flags["C_CONTIGUOUS"]


def test_a_split_larger_than_the_preload_limit_is_read_per_batch(image_buffer):
    root, _ = image_buffer
    frame_bytes = len(IMAGE_KEYS) * 8 * 8 * 3
    reader = ImageWindowReader(root, HORIZON, OBS_STEPS, ACTION_STEPS, preload_limit_bytes=frame_bytes * 10)
    assert len(np.unique(reader.rows[:, :OBS_STEPS])) > 10 and not reader.preloaded


def test_splits_follow_the_held_out_episodes(image_buffer):
    root, _ = image_buffer
    buffer = ReplayBuffer.load(root)
    for split in ("train", "valid"):
        obs, _ = make_windows(buffer, HORIZON, OBS_STEPS, ACTION_STEPS, split=split)
        reader = ImageWindowReader(root, HORIZON, OBS_STEPS, ACTION_STEPS, split=split)
        assert len(reader) == len(obs) > 0
        np.testing.assert_array_equal(reader.read(np.arange(len(reader))).proprioception, obs)


def test_state_buffer_and_unknown_split_are_refused(tmp_path, synthetic_file, image_buffer):
    ingest_demonstrations(synthetic_file, tmp_path / "state", PROPRIOCEPTION_KEYS)
    with pytest.raises(ValueError, match="replay buffer holds no images"):
        ImageWindowReader(tmp_path / "state" / BUFFER_DIRNAME, HORIZON, OBS_STEPS, ACTION_STEPS)
    with pytest.raises(ValueError, match="split='test': must be one of"):
        ImageWindowReader(image_buffer[0], HORIZON, OBS_STEPS, ACTION_STEPS, split="test")


def test_episode_images_are_one_demos_frames_and_empty_without_cameras(image_buffer, tmp_path):
    root, episodes = image_buffer
    for index in (0, 2):
        frames = episode_images(root, index)
        assert list(frames) == list(IMAGE_KEYS)
        for key in IMAGE_KEYS:
            np.testing.assert_array_equal(frames[key], episodes[index].obs[key])
    write_synthetic_file(tmp_path / "raw.hdf5")
    ingest_demonstrations(tmp_path / "raw.hdf5", tmp_path / "processed", PROPRIOCEPTION_KEYS)
    assert episode_images(tmp_path / "processed" / BUFFER_DIRNAME) == {}
