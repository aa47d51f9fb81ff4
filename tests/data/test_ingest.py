import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from carp.data.ingest import BUFFER_DIRNAME, NORMALIZATION_FILENAME, ingest_demonstrations
from carp.data.normalizer import load_normalizers
from carp.data.replay_buffer import ReplayBuffer
from carp.data.robomimic_io import DatasetError
from carp.data.rotation import rot6d_to_absolute_actions
from carp.data.subsets import nested_subset
from carp.data.windows import make_windows
from tests.conftest import OBS_KEYS, OBS_WIDTHS, write_synthetic_file
from tests.reliability.corrupt_files import CORRUPT_FILES, corrupt_file, expected_message


def test_ingest_builds_buffer_with_episode_boundaries_and_exact_actions(tmp_path):
    raw = tmp_path / "raw.hdf5"
    episodes = write_synthetic_file(raw, lengths=(30, 25, 40, 20))
    output = tmp_path / "processed"
    summary = ingest_demonstrations(raw, output, OBS_KEYS)
    buffer = ReplayBuffer.load(output / BUFFER_DIRNAME)

    assert summary.episodes == 4 and summary.steps == 115 and summary.action_dim == 10
    np.testing.assert_array_equal(buffer.episode_ends, [30, 55, 95, 115])
    np.testing.assert_array_equal(buffer.valid_episodes, [False, False, False, True])  # mask/valid = last demo
    assert buffer.obs.shape == (115, sum(OBS_WIDTHS.values()))
    assert buffer.attrs["obs_widths"] == [OBS_WIDTHS[key] for key in OBS_KEYS]
    _, third_actions = buffer.episode(2)
    np.testing.assert_allclose(
        rot6d_to_absolute_actions(third_actions.astype(np.float64)), episodes[2].actions, atol=1e-5
    )
    np.testing.assert_allclose(buffer.obs[55:95, :10], episodes[2].obs["object"], atol=1e-6)


def test_the_output_is_the_same_bytes_wherever_the_file_lies_when_its_source_is_named(tmp_path):
    # A project copied elsewhere ingests its demos to the same bytes, so DVC finds every later stage up to date.
    outputs = []
    for place in ("here", "elsewhere/deeper"):
        raw = tmp_path / place / "data/raw/lift.hdf5"
        raw.parent.mkdir(parents=True)
        write_synthetic_file(raw, lengths=(30, 25, 40, 20))
        output = tmp_path / place / "processed"
        summary = ingest_demonstrations(raw, output, OBS_KEYS, source_name="data/raw/lift.hdf5")
        assert summary.source == "data/raw/lift.hdf5"
        outputs.append({p.relative_to(output): p.read_bytes() for p in sorted(output.rglob("*")) if p.is_file()})
    assert outputs[0] == outputs[1]
    assert ReplayBuffer.load(tmp_path / "here/processed" / BUFFER_DIRNAME).attrs["source"] == "data/raw/lift.hdf5"
    # Unnamed, the source is the path as given.
    unnamed = ingest_demonstrations(tmp_path / "here/data/raw/lift.hdf5", tmp_path / "unnamed", OBS_KEYS)
    assert unnamed.source == str(tmp_path / "here/data/raw/lift.hdf5")


def test_ingested_windows_normalize_to_unit_range_and_back(tmp_path, synthetic_file):
    output = tmp_path / "processed"
    ingest_demonstrations(synthetic_file, output, OBS_KEYS)
    normalizers = load_normalizers(output / NORMALIZATION_FILENAME)
    buffer = ReplayBuffer.load(output / BUFFER_DIRNAME)
    obs, actions = make_windows(buffer, horizon=16, obs_steps=2, action_steps=8)
    normalized = normalizers["action"].normalize(actions.astype(np.float64))
    assert normalized.min() >= -1.0 - 1e-9 and normalized.max() <= 1.0 + 1e-9
    np.testing.assert_allclose(normalized.reshape(-1, 10).max(axis=0), 1.0, atol=1e-9)
    np.testing.assert_allclose(normalizers["action"].unnormalize(normalized), actions, atol=1e-5)
    assert obs.shape[1:] == (2, 19)


def test_delta_actions_are_kept_as_they_are(tmp_path, synthetic_file):
    ingest_demonstrations(synthetic_file, tmp_path / "out", OBS_KEYS, controller="delta")
    buffer = ReplayBuffer.load(tmp_path / "out" / BUFFER_DIRNAME)
    with h5py.File(synthetic_file) as handle:
        np.testing.assert_allclose(buffer.action[:30], handle["data/demo_0/actions"][()], atol=1e-6)


def test_filter_key_selects_demos(tmp_path, synthetic_file):
    summary = ingest_demonstrations(synthetic_file, tmp_path / "out", OBS_KEYS, filter_key="train")
    assert summary.episodes == 3


def test_a_subset_keeps_the_nested_demos_in_file_order(tmp_path):
    raw = tmp_path / "raw.hdf5"
    write_synthetic_file(raw, lengths=(30, 25, 40, 20, 35, 22))
    names = [f"demo_{index}" for index in range(6)]
    ingest_demonstrations(raw, tmp_path / "out", OBS_KEYS, subset_size=3, subset_seed=4)
    buffer = ReplayBuffer.load(tmp_path / "out" / BUFFER_DIRNAME)
    assert buffer.attrs["demo_names"] == nested_subset(names, 3, seed=4)
    assert len(buffer.episode_ends) == 3
    with pytest.raises(DatasetError, match="holds 6 demos, fewer than a subset of 7"):
        ingest_demonstrations(raw, tmp_path / "out", OBS_KEYS, subset_size=7)


def _mutate(path: Path, change) -> None:
    with h5py.File(path, "r+") as handle:
        change(handle)


@pytest.mark.parametrize("name", sorted(CORRUPT_FILES))
def test_bad_input_names_file_demo_and_key_and_writes_nothing(tmp_path, name):
    raw = tmp_path / "raw.hdf5"
    output = tmp_path / "processed"
    with corrupt_file(name, raw) as case, pytest.raises(DatasetError) as error:
        ingest_demonstrations(raw, output, case.obs_keys, staging_dir=tmp_path / "staging")
    text = str(error.value)
    assert text.startswith(expected_message(case, raw)) and case.problem in text and "\n" not in text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw.hdf5"]


def test_camera_images_are_refused_by_the_low_dim_buffer_and_nothing_is_written(tmp_path):
    raw = tmp_path / "raw.hdf5"
    write_synthetic_file(raw, image_size=8)
    with pytest.raises(DatasetError) as error:
        ingest_demonstrations(raw, tmp_path / "processed", (*OBS_KEYS, "agentview_image"), staging_dir=tmp_path / "s")
    assert str(error.value) == (
        f"{raw}: obs keys ['agentview_image']: camera images are not stored in the low-dimensional replay buffer; "
        "list only low-dimensional obs keys"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw.hdf5"]


def test_missing_file_is_named(tmp_path):
    with pytest.raises(DatasetError, match=r"missing.hdf5: file not found"):
        ingest_demonstrations(tmp_path / "missing.hdf5", tmp_path / "processed", OBS_KEYS)
    assert list(tmp_path.iterdir()) == []


def test_staging_stays_outside_the_output_folder_and_clears_dead_leftovers(tmp_path, synthetic_file):
    processed, staging = tmp_path / "processed", tmp_path / "staging"
    finished = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(finished.stdout)
    staging.mkdir()
    (staging / f".can.{dead_pid}.tmp").mkdir()
    (staging / f".lift.{os.getppid()}.tmp").mkdir()  # a live process's: kept
    ingest_demonstrations(synthetic_file, processed / "lift", OBS_KEYS, staging_dir=staging)
    assert sorted(p.name for p in processed.iterdir()) == ["lift"]
    assert sorted(p.name for p in staging.iterdir()) == [f".lift.{os.getppid()}.tmp"]


def test_failed_ingest_keeps_previous_output_intact(tmp_path, synthetic_file):
    output = tmp_path / "processed"
    ingest_demonstrations(synthetic_file, output, OBS_KEYS)
    before = json.loads((output / "summary.json").read_text())
    _mutate(synthetic_file, lambda h: h["data/demo_0/actions"].__setitem__((0, 0), np.nan))
    with pytest.raises(DatasetError):
        ingest_demonstrations(synthetic_file, output, OBS_KEYS)
    assert json.loads((output / "summary.json").read_text()) == before


def test_a_subset_inside_mask_valid_is_refused_not_split_another_way(tmp_path, synthetic_file):
    # Seed 2 keeps demo_3 alone, the one demo mask/valid lists: nothing would be left to train on.
    with pytest.raises(DatasetError, match=r"mask 'mask/valid': lists all 1 demos in the file, leaving none"):
        ingest_demonstrations(synthetic_file, tmp_path / "out", OBS_KEYS, subset_size=1, subset_seed=2)
    assert not (tmp_path / "out").exists()
