import json
import subprocess
import sys

import numpy as np
import pyarrow.parquet as pq
import pytest

from carp.data.demo_sources import import_demos
from carp.data.lerobot.export import export_lerobot
from carp.data.lerobot.reader import read_lerobot_demonstrations
from carp.data.lerobot.videos import decode_episode
from carp.data.lerobot.writer import write_lerobot_dataset
from carp.data.robomimic_io import read_demonstrations, write_demonstrations
from carp.data.robomimic_schema import DatasetError
from tests.conftest import OBS_KEYS, write_synthetic_file
from tests.data.lerobot.fixtures import FIXTURES
from tests.fixtures.lerobot.make_carp_export import CAMERA_KEY, write_source

EXPORT = FIXTURES / "carp-export"


def assert_same_demos(expected, actual, obs_keys=OBS_KEYS):
    assert actual.names == expected.names and actual.masks == expected.masks
    assert actual.env_args == expected.env_args
    for ours, theirs in zip(expected.episodes, actual.episodes, strict=True):
        assert np.array_equal(theirs.actions, ours.actions)
        assert np.array_equal(theirs.states, ours.states)
        assert np.array_equal(theirs.rewards, ours.rewards) and np.array_equal(theirs.dones, ours.dones)
        for key in obs_keys:
            assert np.array_equal(theirs.obs[key], ours.obs[key])
        assert {key: theirs.attrs[key] for key in ours.attrs} == ours.attrs


def test_export_then_import_round_trips_the_demos_exactly(tmp_path):
    source = tmp_path / "lift.hdf5"
    write_synthetic_file(source)
    summary = export_lerobot(source, tmp_path / "lift", staging_dir=tmp_path / "staging")
    assert (summary.episodes, summary.frames, summary.fps) == (4, 115, 20)
    assert list((tmp_path / "staging").iterdir()) == []
    back = tmp_path / "back.hdf5"
    import_demos(tmp_path / "lift", back, OBS_KEYS, action_dim=7, env_name="Lift")
    assert_same_demos(read_demonstrations(source, OBS_KEYS), read_demonstrations(back, OBS_KEYS))


def test_episodes_spread_over_several_data_files_read_back_the_same(tmp_path):
    source = tmp_path / "lift.hdf5"
    write_synthetic_file(source, lengths=(5, 6, 7, 8, 9))
    demos = read_demonstrations(source, OBS_KEYS)
    write_lerobot_dataset(demos, tmp_path / "lift", fps=20, state_keys=OBS_KEYS, task_text="lift", episodes_per_file=2)
    files = sorted(path.name for path in (tmp_path / "lift" / "data" / "chunk-000").iterdir())
    assert files == ["file-000.parquet", "file-001.parquet", "file-002.parquet"]
    assert_same_demos(demos, read_lerobot_demonstrations(tmp_path / "lift", OBS_KEYS))


def test_observation_state_concatenates_the_state_keys(tmp_path):
    source = tmp_path / "lift.hdf5"
    write_synthetic_file(source, lengths=(5, 6))
    demos = read_demonstrations(source, OBS_KEYS)
    write_lerobot_dataset(demos, tmp_path / "lift", fps=20, state_keys=OBS_KEYS, task_text="lift")
    state = read_lerobot_demonstrations(tmp_path / "lift", ["state"]).episodes[1].obs["state"]
    assert np.array_equal(state, np.concatenate([demos.episodes[1].obs[key] for key in OBS_KEYS], axis=1))
    info = json.loads((tmp_path / "lift" / "meta" / "info.json").read_text())
    assert info["features"]["observation.state"]["names"][:2] == ["object_0", "object_1"]
    assert info["splits"] == {"train": "0:1", "valid": "1:2"}


def test_the_export_is_what_lerobots_loader_read(tmp_path):
    """carp's export of the fixture's source equals ``carp-export/``, which LeRobot's own loader read."""
    source = tmp_path / "lift.hdf5"
    write_source(source)
    written = read_demonstrations(source, (*OBS_KEYS, CAMERA_KEY)).episodes
    export_lerobot(source, tmp_path / "export")
    committed = sorted(path.relative_to(EXPORT) for path in EXPORT.rglob("*") if path.is_file())
    assert committed == sorted(
        path.relative_to(tmp_path / "export") for path in (tmp_path / "export").rglob("*") if path.is_file()
    )
    for relative in committed:
        ours, theirs = tmp_path / "export" / relative, EXPORT / relative
        if relative.suffix == ".parquet":
            assert pq.read_table(ours).equals(pq.read_table(theirs)), relative
        elif relative.suffix == ".mp4":
            times = np.arange(15) / 20
            frames = [decode_episode(path, 0.0, times, (32, 32, 3), 32, "camera") for path in (ours, theirs)]
            assert np.abs(frames[0].astype(int) - frames[1].astype(int)).max() <= 2
        else:
            assert json.loads(ours.read_text()) == json.loads(theirs.read_text()), relative
    with np.load(FIXTURES / "carp-export-read.npz") as read:
        # LeRobot returns float features as float32 tensors; frames in episode order.
        actions = np.concatenate([episode.actions for episode in written])
        assert np.array_equal(read["action"], actions.astype(np.float32))
        objects = np.concatenate([episode.obs["object"] for episode in written])
        assert np.array_equal(read["observation.object"], objects.astype(np.float32))
        assert np.array_equal(read["episode_index"], np.repeat([0, 1, 2], [6, 5, 4]))
        assert set(read["task"].tolist()) == {"lift"}
        # Camera frames come back as float (C, H, W) in [0, 1], within a few levels of the compressed originals.
        images = np.concatenate([episode.obs[CAMERA_KEY] for episode in written]).transpose(0, 3, 1, 2) / 255
        assert np.abs(read["observation.images.agentview"] - images).max() <= 4 / 255


def test_a_mask_of_non_consecutive_demos_is_refused(tmp_path):
    source = tmp_path / "lift.hdf5"
    episodes = write_synthetic_file(source)
    names = [f"demo_{index}" for index in range(4)]
    env_args = {"env_name": "Lift", "type": 1, "env_kwargs": {"robots": ["Panda"]}}
    write_demonstrations(source, episodes, env_args, masks={"train": names[1:3], "valid": [names[0], names[3]]})
    with pytest.raises(DatasetError, match=r"mask 'mask/valid': its demos are not consecutive"):
        export_lerobot(source, tmp_path / "lift")
    assert not (tmp_path / "lift").exists()


def test_the_command_exports_and_refuses_with_one_error_line(tmp_path):
    source = tmp_path / "lift.hdf5"
    write_synthetic_file(source, lengths=(5, 6))
    command = [sys.executable, "-m", "carp.cli", "export-lerobot"]
    done = subprocess.run([*command, str(source), "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "2 episodes, 11 frames at 20 fps" in done.stdout
    assert (tmp_path / "out" / "meta" / "info.json").is_file()
    source.write_bytes(b"not hdf5")
    done = subprocess.run([*command, str(source), "--out", str(tmp_path / "bad")], capture_output=True, text=True)
    assert done.returncode == 1
    assert done.stderr.strip().splitlines()[-1] == f"error: {source}: not an HDF5 file"
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow
def test_scripted_lift_demos_round_trip_exactly(tmp_path, lift_demo_collection):
    source, _ = lift_demo_collection
    export_lerobot(source, tmp_path / "lift")
    back = tmp_path / "back.hdf5"
    import_demos(tmp_path / "lift", back, OBS_KEYS, action_dim=7, env_name="Lift")
    assert_same_demos(read_demonstrations(source, OBS_KEYS), read_demonstrations(back, OBS_KEYS))


def test_camera_images_round_trip_within_the_video_compression(tmp_path):
    source = tmp_path / "lift.hdf5"
    write_source(source)
    summary = export_lerobot(source, tmp_path / "lift")
    assert summary.cameras == ("agentview",)
    back = tmp_path / "back.hdf5"
    import_demos(tmp_path / "lift", back, OBS_KEYS, action_dim=7, cameras=("agentview",), image_size=32)
    ours, theirs = (read_demonstrations(path, (*OBS_KEYS, CAMERA_KEY)) for path in (source, back))
    assert_same_demos(ours, theirs)
    for original, decoded in zip(ours.episodes, theirs.episodes, strict=True):
        assert np.abs(decoded.obs[CAMERA_KEY].astype(int) - original.obs[CAMERA_KEY].astype(int)).max() <= 4


def test_an_odd_image_size_is_refused_before_anything_is_written(tmp_path):
    source = tmp_path / "lift.hdf5"
    write_synthetic_file(source, lengths=(5, 6), image_size=33)
    with pytest.raises(DatasetError, match=r"obs key 'agentview_image': image size 33 x 33: MP4 video \(4:2:0\)"):
        export_lerobot(source, tmp_path / "lift")
    assert not (tmp_path / "lift").exists()
