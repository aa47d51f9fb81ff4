import json

import h5py
import numpy as np
import pytest

from carp import simulation
from carp.data.collect import CollectionError, collect_demonstrations, run_expert_episode
from carp.data.experts import make_expert
from carp.data.robomimic_io import read_demonstrations
from carp.data.rotation import absolute_to_rot6d_actions, rot6d_to_absolute_actions

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
    assert demos.env_args == simulation.make_env_args("lift")
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
    env = simulation.make_env(simulation.make_env_args("lift"))
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


def test_collection_noise_moves_the_arm_but_records_the_experts_commands(lift_demo_collection):
    path, summary = lift_demo_collection
    clean = read_demonstrations(path, DEFAULT_OBS_KEYS, action_dim=7).episodes[0]
    env = simulation.make_env(simulation.make_env_args("lift"))
    try:
        expert = make_expert("lift", env)
        noisy, success = run_expert_episode(
            env, expert, summary.seeds[0], max_steps=300, noise_m=0.01, rng=np.random.default_rng(0)
        )
    finally:
        env.close()
    assert success
    # Same start; the first command is the expert's (its commanded pose starts at the measured pose).
    np.testing.assert_allclose(noisy.obs["robot0_eef_pos"][0], clean.obs["robot0_eef_pos"][0], atol=1e-9)
    np.testing.assert_allclose(noisy.actions[0], clean.actions[0], atol=1e-9)
    # Over the first second, before the two runs drift apart in time, the arm is off the clean path by about the
    # noise level (std 1 cm per axis), not by a lost grasp.
    deviation = np.linalg.norm(noisy.obs["robot0_eef_pos"][:20] - clean.obs["robot0_eef_pos"][:20], axis=1)
    assert 0.002 < deviation.max() < 0.05, deviation.max()
    # Recorded commands move smoothly (no 1 cm jumps): the noise is executed, not stored.
    command_steps = np.linalg.norm(np.diff(noisy.actions[:, :3], axis=0), axis=1)
    assert command_steps.max() < 0.02, command_steps.max()


def test_collection_noise_needs_a_generator():
    with pytest.raises(ValueError, match="noise_m > 0 needs a random generator"):
        run_expert_episode(env=None, expert=None, seed=0, max_steps=1, noise_m=0.01)
