"""Push-T's env: DP's keypoints and their definition, the seeded reset in this and another process, reward and
success on hand-placed states, the step limit, rendering and the refusal of bad input."""

import json
import math
import multiprocessing
import re
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

from carp.tasks.pusht import env as pusht

FAR_FROM_GOAL = (400.0, 450.0, math.pi)  # stem pointing up, in the lower right corner, clear of the goal and walls
AGENT_AWAY = (50.0, 50.0)


@pytest.fixture(scope="module")
def env():
    environment = pusht.make_env(pusht.make_env_args(), render_size=96)
    yield environment
    environment.close()


def pairwise_distances(points: np.ndarray) -> np.ndarray:
    return np.linalg.norm(points[:, None] - points[None], axis=-1)


def keypoints(observation: dict[str, np.ndarray]) -> np.ndarray:
    return observation["block_keypoints"].reshape(9, 2)


def test_stored_keypoints_are_the_farthest_point_samples_of_the_drawn_t():
    recomputed = pusht.farthest_point_block_keypoints()
    np.testing.assert_allclose(recomputed, pusht.BLOCK_KEYPOINTS, rtol=0, atol=1e-9)
    # They spread over the T: crossbar ends (x = +-60 at the top), stem foot (y = 120), none twice.
    assert pusht.BLOCK_KEYPOINTS[:, 0].min() < -59 and pusht.BLOCK_KEYPOINTS[:, 0].max() > 59
    assert pusht.BLOCK_KEYPOINTS[:, 1].max() > 119
    distances = pairwise_distances(pusht.BLOCK_KEYPOINTS)
    assert distances[~np.eye(9, dtype=bool)].min() > 20


def test_keypoints_move_rigidly_with_the_block(env):
    reference_distances = pairwise_distances(pusht.BLOCK_KEYPOINTS)
    observations = [env.reset(100000), env.reset_to_state(pusht.reset_state_for_pose(AGENT_AWAY, pusht.GOAL_POSE))]
    env.reset(100000)
    start = env.state()
    for _ in range(30):  # drive the agent through the block's position: it gets pushed and turned
        env.step(start[2:4])
    observations.append(env.observation())
    assert np.abs(env.state()[2:] - start[2:]).max() > 1.0  # the block moved, so the last pose is a new one

    for observation in observations:
        assert observation["block_keypoints"].shape == (18,) and observation["agent_pos"].shape == (2,)
        np.testing.assert_allclose(pairwise_distances(keypoints(observation)), reference_distances, atol=1e-9)
    # Fixed in the simulated block's own frame: pymunk maps them to the same points as the observation does.
    block = env._simulation.block
    expected = np.array([block.local_to_world(tuple(point)) for point in pusht.BLOCK_KEYPOINTS])
    np.testing.assert_allclose(keypoints(observations[-1]), expected, atol=1e-9)
    np.testing.assert_array_equal(observations[-1]["agent_pos"], env.state()[:2])
    vector = env.observation_vector()
    assert vector.shape == (pusht.OBSERVATION_DIM,) == (20,)
    np.testing.assert_array_equal(vector, np.concatenate([observations[-1]["block_keypoints"], env.state()[:2]]))


def initial_state_and_observation(seed: int) -> tuple[np.ndarray, np.ndarray]:
    environment = pusht.make_env(pusht.make_env_args())
    environment.reset(seed)
    return environment.state(), environment.observation_vector()


def test_a_seed_gives_the_same_initial_state_every_time_and_in_another_process(env):
    seed = 100003
    env.reset(seed)
    first_state, first_observation = env.state(), env.observation_vector()
    env.reset(5)
    for _ in range(5):
        env.step(np.array([256.0, 256.0]))
    env.reset(seed)
    np.testing.assert_array_equal(env.state(), first_state)
    np.testing.assert_array_equal(env.observation_vector(), first_observation)
    # An evaluation worker is a spawned process that imports everything afresh.
    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
        worker_state, worker_observation = pool.submit(initial_state_and_observation, seed).result(timeout=120)
    np.testing.assert_array_equal(worker_state, first_state)
    np.testing.assert_array_equal(worker_observation, first_observation)
    env.reset(seed + 1)
    assert not np.array_equal(env.state(), first_state)


@pytest.mark.parametrize("seed", [100000, 100001, 0])
def test_reset_follows_diffusion_policys_draws(env, seed):
    draws = np.random.RandomState(seed)  # DP's runner: five scalar draws in this order
    agent = [draws.randint(50, 450), draws.randint(50, 450)]
    block = [draws.randint(100, 400), draws.randint(100, 400)]
    angle = draws.randn() * 2 * np.pi - np.pi
    np.testing.assert_array_equal(pusht.reset_state(seed), [*agent, *block, angle])

    env.reset(seed)
    state = env.state()
    np.testing.assert_array_equal(state[:2], agent)
    assert state[4] == angle
    # Position first, then the angle, which turns the block about its centre of gravity: that point stays where the
    # drawn position put it.
    center_of_gravity = np.array(pusht.BLOCK_CENTER_OF_GRAVITY)
    np.testing.assert_array_equal(env._simulation.block.center_of_gravity, center_of_gravity)
    cos, sin = math.cos(angle), math.sin(angle)
    turned = np.array([[cos, -sin], [sin, cos]]) @ center_of_gravity
    np.testing.assert_allclose(state[2:4] + turned, np.add(block, center_of_gravity), atol=1e-9)


def test_block_on_the_goal_is_a_success_with_full_reward(env):
    env.reset_to_state(pusht.reset_state_for_pose(AGENT_AWAY, pusht.GOAL_POSE))
    np.testing.assert_allclose(env.state()[2:], pusht.GOAL_POSE, atol=1e-9)
    assert env.coverage() == pytest.approx(1.0, abs=1e-9)
    assert env.reward() == 1.0 and env.is_success()
    step = env.step(np.array(AGENT_AWAY))  # the agent holds still
    assert step.coverage == pytest.approx(1.0, abs=1e-9)
    assert step.reward == 1.0 and step.success and step.done


def test_block_far_from_the_goal_earns_nothing(env):
    env.reset_to_state(pusht.reset_state_for_pose(AGENT_AWAY, FAR_FROM_GOAL))
    np.testing.assert_allclose(env.state()[2:], FAR_FROM_GOAL, atol=1e-9)
    assert env.coverage() == pytest.approx(0.0, abs=1e-9)
    assert env.reward() == pytest.approx(0.0, abs=1e-9) and not env.is_success()
    step = env.step(np.array(AGENT_AWAY))
    assert step.reward == pytest.approx(0.0, abs=1e-9) and not step.success and not step.done


@pytest.mark.parametrize(("coverage", "reward"), [(0.0, 0.0), (0.475, 0.5), (0.95, 1.0), (0.99, 1.0)])
def test_reward_is_coverage_over_the_threshold_clipped(coverage, reward):
    assert pusht.reward_for(coverage) == pytest.approx(reward)


def test_the_step_limit_ends_an_episode_at_300_steps(env):
    assert env.max_steps == pusht.MAX_STEPS == 300
    env.reset_to_state(pusht.reset_state_for_pose(AGENT_AWAY, FAR_FROM_GOAL))
    done = [env.step(np.array(AGENT_AWAY)).done for _ in range(300)]
    assert not any(done[:-1]) and done[-1] and env.steps == 300
    with pytest.raises(RuntimeError, match="step limit of 300"):
        env.step(np.array(AGENT_AWAY))
    env.reset(1)
    assert env.steps == 0 and not env.step(np.array(AGENT_AWAY)).done


@pytest.mark.parametrize("action", [np.zeros(7), np.zeros((1, 2)), np.float64(3.0)])
def test_an_action_of_the_wrong_shape_is_refused_naming_both_shapes(env, action):
    env.reset(2)
    state = env.state()
    with pytest.raises(ValueError, match=re.escape(f"shape (2,), got shape {np.shape(action)}")):
        env.step(action)
    np.testing.assert_array_equal(env.state(), state)
    assert env.steps == 0


def test_frames_render_offscreen_and_show_the_state(env):
    env.reset_to_state(pusht.reset_state_for_pose(AGENT_AWAY, pusht.GOAL_POSE))
    on_goal = env.render()
    env.step(np.array([300.0, 100.0]))
    with_target = env.render()  # the agent moved, and the target is drawn as a cross
    env.reset_to_state(pusht.reset_state_for_pose(AGENT_AWAY, FAR_FROM_GOAL))
    far = env.render()
    assert on_goal.shape == far.shape == (96, 96, 3) and on_goal.dtype == np.uint8
    assert (on_goal != far).any() and (on_goal != with_target).any()
    # A reset forgets the last episode's target: the first frame is that of a fresh env.
    fresh = pusht.PushTEnv(render_size=96)
    fresh.reset_to_state(pusht.reset_state_for_pose(AGENT_AWAY, FAR_FROM_GOAL))
    np.testing.assert_array_equal(fresh.render(), far)
    with pytest.raises(ValueError, match="at least 96 pixels, got 64"):
        pusht.PushTEnv(render_size=64)


def test_env_args_round_trip_through_json_and_other_envs_are_refused():
    env_args = json.loads(json.dumps(pusht.make_env_args()))
    assert env_args["env_name"] == "gym_pusht/PushT-v0" and env_args["env_version"] == "0.1.8"
    environment = pusht.make_env(env_args)
    np.testing.assert_array_equal(environment.reset(7)["agent_pos"], pusht.reset_state(7)[:2])
    with pytest.raises(ValueError, match="'Lift', not Push-T"):
        pusht.make_env({"env_name": "Lift", "type": 1, "env_kwargs": {}})
