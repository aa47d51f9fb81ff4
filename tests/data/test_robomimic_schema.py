import os
import re
import subprocess
import sys

import h5py
import numpy as np
import pytest

from carp.data.robomimic_io import DatasetError, import_demonstrations, read_demonstrations, write_demonstrations
from tests.conftest import IMAGE_KEYS, OBS_KEYS, write_synthetic_file
from tests.reliability.corrupt_files import CORRUPT_FILES, corrupt_file, expected_message


@pytest.mark.parametrize("name", sorted(CORRUPT_FILES))
def test_every_damage_is_one_line_naming_file_demo_and_key(tmp_path, name):
    path = tmp_path / "raw.hdf5"
    with corrupt_file(name, path) as case, pytest.raises(DatasetError) as error:
        read_demonstrations(path, case.obs_keys, action_dim=7)
    text = str(error.value)
    assert text.startswith(expected_message(case, path)), text
    assert case.problem in text and "\n" not in text


@pytest.mark.parametrize(
    "name", ["obs widths differ between demos", "action overflows float32", "truncated", "image of floats"]
)
def test_import_refuses_before_copying_and_keeps_the_destination(tmp_path, name):
    destination = tmp_path / "raw" / "lift.hdf5"
    destination.parent.mkdir()
    destination.write_bytes(b"previous")
    staging = tmp_path / "staging"
    with corrupt_file(name, tmp_path / "user.hdf5") as case, pytest.raises(DatasetError, match=re.escape(case.problem)):
        import_demonstrations(tmp_path / "user.hdf5", destination, case.obs_keys, action_dim=7, staging_dir=staging)
    assert destination.read_bytes() == b"previous"
    assert not staging.exists() or not list(staging.iterdir())


def test_import_copies_a_valid_file_byte_for_byte(tmp_path):
    source = tmp_path / "user.hdf5"
    write_synthetic_file(source)
    destination = tmp_path / "raw" / "lift.hdf5"
    demos = import_demonstrations(source, destination, OBS_KEYS, action_dim=7, staging_dir=tmp_path / "staging")
    assert demos.names == ["demo_0", "demo_1", "demo_2", "demo_3"]
    assert destination.read_bytes() == source.read_bytes()
    assert list((tmp_path / "staging").iterdir()) == []


def test_camera_images_are_read_as_stored(tmp_path):
    path = tmp_path / "raw.hdf5"
    episodes = write_synthetic_file(path, image_size=84)
    demos = read_demonstrations(path, (*OBS_KEYS, *IMAGE_KEYS), action_dim=7)
    for episode, written in zip(demos.episodes, episodes, strict=True):
        for key in IMAGE_KEYS:
            assert episode.obs[key].dtype == np.uint8 and episode.obs[key].shape == (episode.length, 84, 84, 3)
            assert np.array_equal(episode.obs[key], written.obs[key])
        assert episode.obs["object"].dtype == np.float64 and episode.obs["object"].shape == (episode.length, 10)


def test_every_mask_is_checked_whichever_filter_key_is_used(tmp_path):
    path = tmp_path / "raw.hdf5"
    write_synthetic_file(path)
    with h5py.File(path, "r+") as handle:
        handle.create_dataset("mask/extra", data=np.array([b"demo_1", b"demo_7"]))
    for filter_key in (None, "train"):
        with pytest.raises(DatasetError, match=r"mask 'mask/extra': names demo 'demo_7', which does not exist"):
            read_demonstrations(path, OBS_KEYS, filter_key=filter_key)


def test_filter_key_errors_name_the_mask(tmp_path):
    path = tmp_path / "raw.hdf5"
    write_synthetic_file(path)
    with pytest.raises(DatasetError, match=r"filter key 'mask/test' not found \(masks: \['train', 'valid'\]\)"):
        read_demonstrations(path, OBS_KEYS, filter_key="test")
    with h5py.File(path, "r+") as handle:
        handle.create_dataset("mask/none", data=np.array([], dtype="S"))
    with pytest.raises(DatasetError, match=r"filter key 'mask/none' lists no demos"):
        read_demonstrations(path, OBS_KEYS, filter_key="none")


def test_values_at_the_float32_limit_are_kept(tmp_path):
    path = tmp_path / "raw.hdf5"
    write_synthetic_file(path)
    with h5py.File(path, "r+") as handle:
        handle["data/demo_1/obs/object"][0, 0] = 1e19  # its square, 1e38, still fits float32
    demos = read_demonstrations(path, OBS_KEYS)
    assert demos.episodes[1].obs["object"][0, 0] == 1e19


def test_a_file_left_open_without_file_locking_is_still_one_line(tmp_path):
    # With HDF5_USE_FILE_LOCKING=FALSE (set on some clusters) a reader sees whatever the writer has flushed so far.
    path = tmp_path / "raw.hdf5"
    with corrupt_file("held open for writing", path):
        reader = subprocess.run(
            [
                sys.executable,
                "-c",
                "import sys; from carp.data.robomimic_io import read_demonstrations as r; r(sys.argv[1], ['object'])",
                str(path),
            ],
            env={**os.environ, "HDF5_USE_FILE_LOCKING": "FALSE"},
            capture_output=True,
            text=True,
        )
    last = reader.stderr.strip().splitlines()[-1]
    assert last.startswith(f"carp.data.robomimic_schema.DatasetError: {path}: "), reader.stderr


def test_a_valid_mask_listing_every_demo_is_refused(tmp_path):
    path = tmp_path / "raw.hdf5"
    episodes = write_synthetic_file(path)
    names = [f"demo_{index}" for index in range(len(episodes))]
    env_args = {"env_name": "Lift", "type": 1, "env_kwargs": {"robots": ["Panda"]}}
    write_demonstrations(path, episodes, env_args, masks={"train": names, "valid": names})
    message = r"mask 'mask/valid': lists all 4 demos in the file, leaving none to train on"
    with pytest.raises(DatasetError, match=message):
        read_demonstrations(path, OBS_KEYS)
    with pytest.raises(DatasetError, match=r"lists all 4 demos selected by 'mask/train', leaving none"):
        read_demonstrations(path, OBS_KEYS, filter_key="train")
    # Training on the held-out demos themselves is an explicit choice.
    assert read_demonstrations(path, OBS_KEYS, filter_key="valid").names == names
