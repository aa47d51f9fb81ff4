import json

import h5py
import numpy as np
import pytest

from carp.data.collect import CollectionError, collect_demonstrations
from carp.data.robomimic_io import read_demonstrations
from carp.data.rotation import absolute_to_rot6d_actions, rot6d_to_absolute_actions
from carp.tasks import get_task
from carp.tasks.arms import simulation

from .conftest import LIFT_DEMO_SEED

DEFAULT_OBS_KEYS = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")


def test_collected_lift_file_reads_back_with_aligned_keys(lift_demo_collection):
    path, summary = lift_demo_collection
    assert (summary.task, summary.kept) == ("lift", 2)
    assert summary.attempted >= 2 and summary.success_rate == pytest.approx(2 / summary.attempted)
    assert summary.seeds[0] >= LIFT_DEMO_SEED and summary.seconds > 0
    with h5py.File(path, "r") as handle:
        stored_keys = sorted(handle["data/demo_0/obs"].keys())
    assert {"object", "cube_pos", "robot0_joint_pos", "robot0_eef_quat_site"} <= set(stored_keys)
    demos = read_demonstrations(path, stored_keys, action_dim=7)
    assert demos.names == ["demo_0", "demo_1"]
    assert demos.env_args == get_task("lift").make_env_args("absolute")
    assert demos.attrs["expert"] == "lift_scripted" and demos.attrs["controller"] == "absolute"
    assert demos.attrs["kept"] == 2 and demos.attrs["attempted"] == summary.attempted
    assert json.loads(demos.attrs["seeds"]) == summary.seeds
    assert demos.attrs["robosuite_version"] == "1.5.2" and demos.attrs["mujoco_version"]
    for episode, seed in zip(demos.episodes, summary.seeds, strict=True):
        steps = episode.length
        assert 20 < steps < 150
        assert episode.attrs["seed"] == seed
        assert all(values.shape[0] == steps for values in episode.obs.values())
        assert episode.obs["object"].shape[1] == 10
        assert episode.states.shape[0] == steps and episode.states.shape[1] > 0
        assert episode.rewards.shape == (steps,) and episode.rewards[-1] == 1.0
        assert episode.dones.tolist() == [0] * (steps - 1) + [1]


def test_rot6d_round_trip_of_recorded_actions_replays_to_success(lift_demo_collection):
    path, _ = lift_demo_collection
    episode = read_demonstrations(path, DEFAULT_OBS_KEYS, action_dim=7).episodes[0]
    converted = rot6d_to_absolute_actions(absolute_to_rot6d_actions(episode.actions))
    np.testing.assert_allclose(converted, episode.actions, atol=1e-6)
    env = simulation.make_env(get_task("lift").make_env_args("absolute"))
    try:
        obs = simulation.reset_env(env, episode.attrs["seed"])
        np.testing.assert_allclose(obs["robot0_eef_pos"], episode.obs["robot0_eef_pos"][0], atol=1e-9)
        np.testing.assert_allclose(env.sim.get_state().flatten(), episode.states[0], atol=1e-9)
        successes = []
        for action in converted:
            env.step(action)
            successes.append(simulation.is_success(env))
    finally:
        env.close()
    assert any(successes)


def test_rejects_non_positive_demo_count(tmp_path):
    with pytest.raises(ValueError, match="num_demos must be positive"):
        collect_demonstrations("lift", num_demos=0, output_path=tmp_path / "x.hdf5", seed=0)
    with pytest.raises(ValueError, match="max_attempts"):
        collect_demonstrations("lift", num_demos=3, output_path=tmp_path / "x.hdf5", seed=0, max_attempts=2)


def test_impossible_budget_raises_and_writes_nothing(tmp_path):
    output = tmp_path / "lift.hdf5"
    # Five steps are far too few to lift the cube, so every episode fails.
    with pytest.raises(CollectionError, match=r"succeeded on 0 of 1 episodes \(0%\).*max_attempts=2"):
        collect_demonstrations("lift", num_demos=2, output_path=output, seed=0, max_steps=5, max_attempts=2)
    assert not output.exists()
