import functools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from carp.evaluation.rollout import evaluate_episodes, run_episode
from carp.evaluation.sources import ExpertSource
from carp.tasks import get_task
from carp.tasks.arms import simulation

LIFT = get_task("lift")
OBS_KEYS = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")


class CrashingSource:
    """Holds still, and raises on one seed's third decision."""

    def __init__(self, crash_seed: int) -> None:
        self.crash_seed = crash_seed
        self.decisions = 0

    def reset(self, env, seed: int) -> None:
        self.decisions = 0

    def act(self, history, env):
        self.decisions += 1
        if self.decisions == 3 and getattr(env, "_carp_test_seed", None) == self.crash_seed:
            raise RuntimeError("policy blew up")
        site = env.sim.data.site_xpos[env.robots[0].eef_site_id["right"]]
        matrix = env.sim.data.site_xmat[env.robots[0].eef_site_id["right"]].reshape(3, 3)
        hold = np.concatenate([site, Rotation.from_matrix(matrix).as_rotvec(), [-1.0]])
        return np.repeat(hold[None], 8, axis=0), None


@pytest.fixture(scope="module")
def lift_env():
    env = simulation.make_env(get_task("lift").make_env_args("absolute"))
    yield env
    env.close()


@pytest.mark.slow
def test_scripted_expert_through_the_runner_reaches_its_known_success(lift_env):
    seeds = [1000, 1001, 1002]
    results = [run_episode(LIFT, lift_env, ExpertSource("lift"), seed, OBS_KEYS, 2, 400) for seed in seeds]
    assert [r.success for r in results] == [True, True, True]
    assert all(0 < r.steps < 400 and r.error == "" for r in results)


@pytest.mark.slow
def test_crash_inside_an_episode_is_a_recorded_failure(lift_env):
    source = CrashingSource(crash_seed=7)
    lift_env._carp_test_seed = 7
    crashed = run_episode(LIFT, lift_env, source, 7, OBS_KEYS, 2, 100)
    lift_env._carp_test_seed = 8
    survived = run_episode(LIFT, lift_env, source, 8, OBS_KEYS, 2, 40)
    assert not crashed.success and crashed.error == "RuntimeError: policy blew up" and crashed.steps == 16
    assert not survived.success and survived.error == "" and survived.steps == 40


@pytest.mark.slow
def test_parallel_workers_match_in_process_results():
    env_args = get_task("lift").make_env_args("absolute")
    seeds = [2000, 2001]
    parallel = evaluate_episodes(env_args, functools.partial(ExpertSource, "lift"), seeds, OBS_KEYS, 2, 400, workers=2)
    serial = evaluate_episodes(env_args, functools.partial(ExpertSource, "lift"), seeds, OBS_KEYS, 2, 400, workers=1)
    assert [r.seed for r in parallel] == seeds
    assert [(r.success, r.steps) for r in parallel] == [(r.success, r.steps) for r in serial]
    assert all(r.success for r in parallel)
