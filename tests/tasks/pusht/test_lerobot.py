"""Push-T from ``lerobot/pusht_keypoints``: the block pose fitted to LeRobot's polygon vertices, the observations and
states derived from it, the replay of an episode from its first state, and the one-line refusals.

The fixture (``tests/fixtures/lerobot/pusht-keypoints``, written by LeRobot's own writer) holds three of carp's expert
demos in that layout; ``pusht-keypoints.npz`` beside it keeps what carp recorded for them."""

import math
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from carp.data.demo_sources import import_demos
from carp.data.robomimic_io import read_demonstrations
from carp.data.robomimic_schema import DatasetError
from carp.tasks import get_task
from carp.tasks.pusht import env as pusht
from carp.tasks.pusht.lerobot import (
    AGENT_STATE,
    ENVIRONMENT_STATE,
    PushTKeypoints,
    block_vertices,
    check_replays,
    fit_block_poses,
    vertices_in_workspace,
)
from tests.data.lerobot.fixtures import FIXTURES, edit_rows

KEYPOINTS = FIXTURES / "pusht-keypoints"
OBS_KEYS = tuple(pusht.OBSERVATION_DIMS)
PUSHT = get_task("pusht")
# Float32 storage of coordinates below 512 rounds each by at most 3e-5 px.
FLOAT32_PX = 1e-4


@pytest.fixture(scope="module")
def recorded():
    """What carp recorded for the fixture's demos: ``states_<e>`` (T, 5), ``block_keypoints_<e>``, ...."""
    with np.load(FIXTURES / "pusht-keypoints.npz") as data:
        return dict(data)


def import_pusht(source, destination, adapter=PUSHT.lerobot_adapter):
    """Import as the collect stage does for Push-T: DP's keys, 2-D actions, the task's adapter."""
    return import_demos(
        source, destination, OBS_KEYS, action_dim=2, env_name=pusht.ENV_NAME, env_args=pusht.make_env_args,
        adapter=adapter,
    )  # fmt: skip


def gym_pusht_vertices(pose):
    """(8, 2) as LeRobot's converter computes them: gym-pusht's add_tee at the pose, then get_keypoints."""
    import pymunk
    from gym_pusht.envs.pusht import PushTEnv

    _, shapes = PushTEnv.add_tee(pymunk.Space(), list(pose[:2]), float(pose[2]))
    return PushTEnv.get_keypoints(shapes)


def test_the_fit_inverts_gym_pushts_vertices_at_any_pose():
    rng = np.random.default_rng(0)
    poses = np.column_stack([rng.uniform(0, 512, size=(20, 2)), rng.uniform(-10, 10, size=20)])
    vertices = np.stack([gym_pusht_vertices(pose).reshape(-1) for pose in poses])
    assert np.allclose(vertices.reshape(-1, 8, 2), [vertices_in_workspace(pose) for pose in poses], atol=1e-9)
    fit = fit_block_poses(vertices)
    assert fit.residuals.max() < 1e-9
    assert np.allclose(fit.poses[:, :2], poses[:, :2], atol=1e-9)
    assert np.all((fit.poses[:, 2] >= 0) & (fit.poses[:, 2] < 2 * math.pi))
    assert np.allclose(fit.poses[:, 2], np.mod(poses[:, 2], 2 * math.pi), atol=1e-9)
    # pymunk orders each rectangle's vertices itself: the crossbar's corners, then the stem's.
    assert block_vertices()[:4, 1].max() == 30 and block_vertices()[4:, 1].max() == 120


def test_the_derived_pose_and_keypoints_equal_carps_own(tmp_path, recorded):
    destination = tmp_path / "pusht.hdf5"
    import_pusht(KEYPOINTS, destination)
    demos = read_demonstrations(destination, OBS_KEYS, action_dim=2, env_name=pusht.ENV_NAME)
    assert demos.names == ["demo_0", "demo_1", "demo_2"] and demos.env_args == pusht.make_env_args()
    for index, episode in enumerate(demos.episodes):
        states = recorded[f"states_{index}"]
        assert episode.states.shape == states.shape
        assert np.allclose(episode.states[:, :4], states[:, :4], atol=FLOAT32_PX)
        turn = np.angle(np.exp(1j * (episode.states[:, 4] - states[:, 4])))
        assert np.abs(turn).max() < 1e-6
        assert np.all((episode.states[:, 4] >= 0) & (episode.states[:, 4] < 2 * math.pi))
        for key in OBS_KEYS:
            assert np.allclose(episode.obs[key], recorded[f"{key}_{index}"], atol=FLOAT32_PX), key
        assert np.allclose(episode.actions, recorded[f"action_{index}"].astype(np.float64))


def test_a_dataset_with_carps_keys_is_read_as_stored(tmp_path):
    """carp's own export holds block_keypoints and agent_pos: the adapter is not used."""
    with_adapter, without = tmp_path / "with.hdf5", tmp_path / "without.hdf5"
    import_pusht(FIXTURES / "pusht-v3.0", with_adapter)
    import_pusht(FIXTURES / "pusht-v3.0", without, adapter=None)
    first, second = (read_demonstrations(path, OBS_KEYS) for path in (with_adapter, without))
    for one, other in zip(first.episodes, second.episodes, strict=True):
        assert all(np.array_equal(one.obs[key], other.obs[key]) for key in OBS_KEYS)
        assert np.array_equal(one.states, other.states)


def test_the_task_offers_the_adapter():
    assert isinstance(PUSHT.lerobot_adapter, PushTKeypoints)
    assert PUSHT.lerobot_adapter.provides == OBS_KEYS


def test_the_replay_from_the_first_state_reaches_the_recorded_reward(tmp_path):
    destination = tmp_path / "pusht.hdf5"
    demos = import_pusht(KEYPOINTS, destination)
    checks = check_replays(demos)
    assert [check.episode for check in checks] == ["demo_0", "demo_1", "demo_2"]
    for check, episode in zip(checks, demos.episodes, strict=True):
        assert check.steps == len(episode.actions) and check.recorded_reward == episode.rewards.max()
        assert check.reached and check.replayed_reward >= check.recorded_reward
        assert check.largest_gap < 1e-3  # the same simulation, from float32-rounded states
    assert len(check_replays(demos, episodes=1)) == 1


def test_the_replay_command_prints_a_row_per_episode():
    result = subprocess.run(
        [sys.executable, "benchmarks/pusht_replay.py", str(KEYPOINTS), "--episodes", "2"],
        capture_output=True, text=True, env={**os.environ, "PYTHONPATH": "src"}, timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[1].startswith("demo_0") and lines[2].startswith("demo_1") and lines[1].endswith("yes")
    assert lines[-1].startswith("2/2 episodes reach")


def corrupt_vertex(root, episode, frame, coordinate, shift):
    data_file = root / "data" / "chunk-000" / "file-000.parquet"

    def edit(rows):
        row = [row for row in rows if row["episode_index"] == episode][frame]
        row[ENVIRONMENT_STATE][coordinate] += shift

    edit_rows(data_file, edit)
    return data_file


def test_a_corrupted_vertex_is_refused_in_one_line(tmp_path):
    root = tmp_path / "pusht_keypoints"
    shutil.copytree(KEYPOINTS, root)
    data_file = corrupt_vertex(root, episode=1, frame=7, coordinate=5, shift=2.0)
    destination = tmp_path / "pusht.hdf5"
    with pytest.raises(DatasetError) as raised:
        import_pusht(root, destination)
    message = str(raised.value)
    assert "\n" not in message and not destination.exists()
    assert message.startswith(f"{data_file}: episode 1: frame 7: key '{ENVIRONMENT_STATE}'")
    residual = float(message.split("fit residual ")[1].split(" px")[0])
    assert 0.5 < residual < 2.0


def test_the_image_only_layout_is_refused_naming_the_layout_that_works(tmp_path):
    """``lerobot/pusht`` holds the image and the agent position, no block pose."""
    destination = tmp_path / "pusht.hdf5"
    with pytest.raises(DatasetError) as raised:
        import_pusht(FIXTURES / "pusht-image", destination)
    message = str(raised.value)
    assert "\n" not in message and not destination.exists()
    assert f"feature '{ENVIRONMENT_STATE}': no such feature" in message
    assert "the layout that works: lerobot/pusht_keypoints" in message and AGENT_STATE in message
