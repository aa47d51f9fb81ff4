import json
import re

import numpy as np
import pyarrow as pa
import pytest

from carp.data.lerobot.reader import read_lerobot_demonstrations
from carp.data.robomimic_schema import DatasetError
from tests.data.lerobot.fixtures import (
    ENV_ARGS,
    FIXTURES,
    LENGTHS,
    OBS_KEYS,
    TASKS,
    VERSIONS,
    data_file,
    edit_info,
    edit_rows,
    episode_rows,
    fixture_copy,
    inputs,
    with_field_type,
    without_field,
)


def read(root, **overrides):
    settings = {"obs_keys": OBS_KEYS, "action_dim": 2, "env_args": ENV_ARGS, **overrides}
    return read_lerobot_demonstrations(root, **settings)


@pytest.mark.parametrize("version", VERSIONS)
def test_episodes_hold_exactly_what_lerobots_writer_was_given(version):
    demos = read(FIXTURES / version)
    given = inputs(version)
    assert demos.names == ["demo_0", "demo_1", "demo_2"]
    assert [episode.length for episode in demos.episodes] == list(LENGTHS)
    for index, episode in enumerate(demos.episodes):
        assert np.array_equal(episode.actions, given[f"action_{index}"])
        assert np.array_equal(episode.obs["state"], given[f"observation.state_{index}"])
        assert np.array_equal(episode.obs["environment_state"], given[f"observation.environment_state_{index}"])
        assert np.array_equal(episode.rewards, given[f"next.reward_{index}"][:, 0])
        assert np.array_equal(episode.dones, given[f"next.done_{index}"][:, 0])
        assert episode.states is None
        assert json.loads(episode.attrs["lerobot_tasks"]) == [TASKS[index % 2]]
        assert episode.attrs["lerobot_episode_index"] == index
    assert demos.attrs["lerobot_tasks"] == list(TASKS)
    assert demos.attrs["lerobot_codebase_version"] == version and demos.attrs["lerobot_fps"] == 10
    assert demos.env_args == ENV_ARGS
    assert demos.masks == {"train": demos.names}  # LeRobot's writer puts every episode in its "train" split


@pytest.mark.parametrize("version", VERSIONS)
def test_a_split_selects_episodes(tmp_path, version):
    root = fixture_copy(version, tmp_path)
    edit_info(root, lambda info: info["splits"].update(train="0:2", valid="2:3"))
    demos = read(root, filter_key="train")
    assert demos.names == ["demo_0", "demo_1"] and demos.masks["valid"] == ["demo_2"]


def _set_step(rows, episode, step, key, value):
    episode_rows(rows, episode)[step][key] = value


def _drop_step(rows, episode, step):
    rows.remove(episode_rows(rows, episode)[step])


# name -> (damage(root, version), the file the message names (relative to the root; "data" for the episode's data
# file), the problem it states)
DAMAGES = {
    "unsupported version": (
        lambda root, version: edit_info(root, lambda info: info.update(codebase_version="v1.6")),
        "meta/info.json",
        "key 'codebase_version'='v1.6': carp reads LeRobot",
    ),
    "fps not positive": (
        lambda root, version: edit_info(root, lambda info: info.update(fps=0)),
        "meta/info.json",
        "key 'fps'=0: expected a positive number",
    ),
    "obs feature missing": (
        lambda root, version: edit_info(root, lambda info: info["features"].pop("observation.environment_state")),
        "meta/info.json",
        "obs key 'environment_state': no feature 'environment_state' or 'observation.environment_state'",
    ),
    "action width": (
        lambda root, version: edit_info(root, lambda info: info["features"]["action"].update(shape=[3])),
        "meta/info.json",
        "feature 'action': shape=[3]: expected [2]",
    ),
    "camera feature as obs key": (
        lambda root, version: edit_info(root, lambda info: info["features"]["observation.state"].update(dtype="image")),
        "meta/info.json",
        "feature 'observation.state': dtype='image': camera features are not read",
    ),
    "total frames contradict the index": (
        lambda root, version: edit_info(root, lambda info: info.update(total_frames=35)),
        "meta/info.json",
        "key 'total_frames'=35: the episode index lists 36",
    ),
    "split names a missing episode": (
        lambda root, version: edit_info(root, lambda info: info["splits"].update(valid="2:5")),
        "meta/info.json",
        "key 'splits.valid'='2:5': names episode 3",
    ),
    "valid split lists every episode": (
        lambda root, version: edit_info(root, lambda info: info["splits"].update(valid="0:3")),
        "",
        "mask 'mask/valid': lists all 3 demos in the file, leaving none to train on",
    ),
    "action column dtype": (
        lambda root, version: edit_rows(
            data_file(root, 1), lambda rows: None, with_field_type(data_file(root, 1), "action", pa.list_(pa.float64()))
        ),
        "data",
        "key 'action': dtype=float64: info.json declares float32",
    ),
    "action row too short": (
        lambda root, version: edit_rows(
            data_file(root, 1),
            lambda rows: _set_step(rows, 1, 4, "action", [1.0]),
            with_field_type(data_file(root, 1), "action", pa.list_(pa.float32())),
        ),
        "data",
        "episode 1: step 4: key 'action': holds 1 values, info.json's shape is [2]",
    ),
    "action value missing": (
        lambda root, version: edit_rows(
            data_file(root, 1),
            lambda rows: _set_step(rows, 1, 3, "action", None),
            with_field_type(data_file(root, 1), "action", pa.list_(pa.float32())),
        ),
        "data",
        "episode 1: step 3: key 'action': value missing (null)",
    ),
    "action not finite": (
        lambda root, version: edit_rows(
            data_file(root, 1), lambda rows: _set_step(rows, 1, 2, "action", [float("nan"), 0.0])
        ),
        "data",
        "episode 1: key 'action': step 2, column 0: value=nan: not a finite float32 number",
    ),
    "a frame dropped": (
        lambda root, version: edit_rows(data_file(root, 1), lambda rows: _drop_step(rows, 1, 5)),
        "data",
        "episode 1: key 'episode_index': 8 frames, the episode index lists length 9",
    ),
    "timestamp gap": (
        lambda root, version: edit_rows(data_file(root, 2), lambda rows: _set_step(rows, 2, 6, "timestamp", 0.65)),
        "data",
        "episode 2: key 'timestamp': step 6: value=0.65 s follows 0.5 s, a gap of 0.15 s where fps=10 needs 0.1 s",
    ),
    "frame index out of order": (
        lambda root, version: edit_rows(data_file(root, 2), lambda rows: _set_step(rows, 2, 3, "frame_index", 7)),
        "data",
        "episode 2: key 'frame_index': step 3: value=7: expected 3",
    ),
    "frames of an unlisted episode": (
        lambda root, version: edit_rows(data_file(root, 2), lambda rows: _set_step(rows, 2, 14, "episode_index", 7)),
        "data",
        "episode 7: key 'episode_index': frames of an episode the index does not place in this file",
    ),
    "unknown task index": (
        lambda root, version: edit_rows(data_file(root, 0), lambda rows: _set_step(rows, 0, 2, "task_index", 5)),
        "data",
        "episode 0: key 'task_index': step 2: value=5: not in the task table",
    ),
    "column missing": (
        lambda root, version: edit_rows(
            data_file(root, 0),
            lambda rows: [row.pop("timestamp") for row in rows],
            without_field(data_file(root, 0), "timestamp"),
        ),
        "data",
        "key 'timestamp': column missing",
    ),
    "data file unreadable": (
        lambda root, version: data_file(root, 0).write_bytes(b"not parquet"),
        "data",
        "cannot be read as Parquet",
    ),
}


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("name", sorted(DAMAGES))
def test_every_damage_is_one_line_naming_file_episode_and_key(tmp_path, version, name):
    damage, where, problem = DAMAGES[name]
    root = fixture_copy(version, tmp_path)
    damage(root, version)
    with pytest.raises(DatasetError) as error:
        read(root)
    text = str(error.value)
    assert "\n" not in text and problem in text, text
    if where == "data":
        assert re.match(rf"{re.escape(str(root))}/data/chunk-000/[a-z_0-9-]+\.parquet: ", text), text
    else:
        assert text.startswith(f"{(root / where).as_posix().rstrip('/')}: "), text


def test_a_missing_episode_file_is_named(tmp_path):
    root = fixture_copy("v2.1", tmp_path)
    data_file(root, 1).unlink()
    with pytest.raises(DatasetError, match=r"episode_000001\.parquet: file not found"):
        read(root)


def test_a_malformed_episode_index_line_is_named(tmp_path):
    root = fixture_copy("v2.1", tmp_path)
    path = root / "meta" / "episodes.jsonl"
    path.write_text(path.read_text() + "{not json\n")
    with pytest.raises(DatasetError, match=r"meta/episodes\.jsonl: line 4: not JSON"):
        read(root)


def test_an_episode_listed_twice_is_named(tmp_path):
    root = fixture_copy("v2.1", tmp_path)
    path = root / "meta" / "episodes.jsonl"
    lines = path.read_text().splitlines()
    path.write_text("\n".join([*lines, lines[0]]) + "\n")
    with pytest.raises(DatasetError, match=r"meta/episodes\.jsonl: episode 0: key 'episode_index': listed twice"):
        read(root)


def test_a_dataset_without_env_args_needs_the_tasks(tmp_path):
    with pytest.raises(DatasetError, match=r"meta/carp\.json: key 'env_args': missing, and no task names"):
        read(FIXTURES / "v3.0", env_args=None)
    with pytest.raises(DatasetError, match=r"env_name='PushT': this task's demos come from 'Lift'"):
        read(FIXTURES / "v3.0", env_name="Lift")


@pytest.mark.parametrize("version", VERSIONS)
def test_camera_frames_are_decoded_at_every_step_and_resized(version):
    demos = read(FIXTURES / version, cameras=("top",), image_size=32)
    given = inputs(version)
    for index, episode in enumerate(demos.episodes):
        images = episode.obs["top_image"]
        assert images.dtype == np.uint8 and images.shape == (LENGTHS[index], 32, 32, 3)
        # Flat colours: resizing keeps them, AV1 compression moves them by a few levels at most.
        colours = given[f"observation.images.top_{index}"][:, 0, 0].astype(int)
        assert np.abs(images.astype(int) - colours[:, None, None, :]).max() <= 4


def _shift_video_start(root, episode, seconds):
    path = root / "meta" / "episodes" / "chunk-000" / "file-000.parquet"
    key = "videos/observation.images.top/from_timestamp"
    edit_rows(path, lambda rows: rows[episode].update({key: rows[episode][key] + seconds}))


CAMERA_DAMAGES = {
    "video missing": (
        lambda root: [path.unlink() for path in (root / "videos").rglob("*.mp4")],
        r"\.mp4: episode 0: key 'observation\.images\.top': file not found",
    ),
    "video unreadable": (
        lambda root: [path.write_bytes(b"not a video") for path in (root / "videos").rglob("*.mp4")],
        r"\.mp4: episode 0: key 'observation\.images\.top': cannot be decoded",
    ),
}


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("name", sorted(CAMERA_DAMAGES))
def test_every_camera_damage_names_the_video_episode_and_key(tmp_path, version, name):
    damage, message = CAMERA_DAMAGES[name]
    root = fixture_copy(version, tmp_path)
    damage(root)
    with pytest.raises(DatasetError, match=message):
        read(root, cameras=("top",), image_size=32)


def test_a_video_that_disagrees_with_the_timestamps_is_refused(tmp_path):
    root = fixture_copy("v3.0", tmp_path)
    _shift_video_start(root, 1, 0.05)
    with pytest.raises(DatasetError, match=r"episode 1: key 'observation\.images\.top': step 0: no frame at 1\.25 s"):
        read(root, cameras=("top",), image_size=32)


def test_a_camera_must_be_a_video_feature(tmp_path):
    with pytest.raises(DatasetError, match=r"camera 'wrist': no feature 'observation\.images\.wrist' or"):
        read(FIXTURES / "v3.0", cameras=("wrist",))
    with pytest.raises(
        DatasetError, match=r"feature 'observation\.state': dtype='float32': cameras are read from video"
    ):
        read(FIXTURES / "v3.0", cameras=("state",))


def test_an_episode_index_without_its_video_columns_is_refused(tmp_path):
    root = fixture_copy("v3.0", tmp_path)
    path = root / "meta" / "episodes" / "chunk-000" / "file-000.parquet"
    key = "videos/observation.images.top/chunk_index"
    edit_rows(path, lambda rows: [row.pop(key) for row in rows], without_field(path, key))
    with pytest.raises(DatasetError, match=rf"file-000\.parquet: key '{key}': column missing"):
        read(root)


def test_a_malformed_carp_record_is_named(tmp_path):
    root = fixture_copy("v3.0", tmp_path)
    (root / "meta" / "carp.json").write_text(json.dumps({"env_args": ENV_ARGS, "attrs": [1]}))
    with pytest.raises(DatasetError, match=r"meta/carp\.json: key 'attrs'=\[1\]: expected an object"):
        read(root, env_args=None)
    (root / "meta" / "carp.json").write_text("{not json")
    with pytest.raises(DatasetError, match=r"meta/carp\.json: cannot be read as JSON"):
        read(root)
