import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from carp.data.ingest import BUFFER_DIRNAME, NORMALIZATION_FILENAME, ingest_demonstrations
from carp.data.normalizer import load_normalizers
from carp.data.replay_buffer import ReplayBuffer
from carp.data.robomimic_io import DatasetError
from carp.data.rotation import rot6d_to_absolute_actions
from carp.data.windows import make_windows
from tests.conftest import OBS_KEYS, OBS_WIDTHS, write_synthetic_file


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


def _mutate(path: Path, change) -> None:
    with h5py.File(path, "r+") as handle:
        change(handle)


def _replace(handle, key, values):
    del handle[key]
    handle.create_dataset(key, data=values)


BAD_INPUTS = {
    "missing file": (None, "missing.hdf5: file not found"),
    "not hdf5": ("text", "not an HDF5 file"),
    "no data group": (lambda h: h.move("data", "stuff"), "missing group 'data'"),
    "missing obs key": (lambda h: h.__delitem__("data/demo_1/obs/object"), "demo 'demo_1': missing obs key 'object'"),
    "length mismatch": (
        lambda h: _replace(h, "data/demo_2/obs/robot0_eef_pos", np.zeros((39, 3))),
        "demo 'demo_2': obs key 'robot0_eef_pos' has 39 steps but 'actions' has 40",
    ),
    "empty demo": (
        lambda h: _replace(h, "data/demo_0/actions", np.zeros((0, 7))),
        "demo 'demo_0': key 'actions' is empty",
    ),
    "nan action": (
        lambda h: h["data/demo_3/actions"].__setitem__((4, 2), np.nan),
        "demo 'demo_3': key 'actions' holds NaN or inf (first at step 4)",
    ),
    "inf obs": (
        lambda h: h["data/demo_0/obs/robot0_eef_quat"].__setitem__((7, 0), np.inf),
        "demo 'demo_0': obs key 'robot0_eef_quat' holds NaN or inf (first at step 7)",
    ),
    "wrong action width": (
        lambda h: _replace(h, "data/demo_1/actions", np.zeros((25, 6))),
        "demo 'demo_1': key 'actions' has width 6, expected 7",
    ),
    "filter names missing demo": (
        lambda h: _replace(h, "mask/train", np.array([b"demo_0", b"demo_9"])),
        "filter key 'mask/train' names demo 'demo_9', which does not exist",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_names_file_demo_and_key_and_writes_nothing(tmp_path, case):
    raw = tmp_path / "raw.hdf5"
    write_synthetic_file(raw)
    change, message = BAD_INPUTS[case]
    if change is None:
        raw = tmp_path / "missing.hdf5"
    elif change == "text":
        raw.write_text("not a dataset")
    else:
        _mutate(raw, change)
    output = tmp_path / "processed"
    with pytest.raises(DatasetError) as error:
        ingest_demonstrations(raw, output, OBS_KEYS, filter_key="train" if "filter" in case else None)
    text = str(error.value)
    assert message in text and str(raw) in text and "\n" not in text
    assert not output.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw.hdf5"]


def test_failed_ingest_keeps_previous_output_intact(tmp_path, synthetic_file):
    output = tmp_path / "processed"
    ingest_demonstrations(synthetic_file, output, OBS_KEYS)
    before = json.loads((output / "summary.json").read_text())
    _mutate(synthetic_file, lambda h: h["data/demo_0/actions"].__setitem__((0, 0), np.nan))
    with pytest.raises(DatasetError):
        ingest_demonstrations(synthetic_file, output, OBS_KEYS)
    assert json.loads((output / "summary.json").read_text()) == before
