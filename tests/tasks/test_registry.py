"""The task seam: every registered task resolves by name and by the env_args of its files, and its action format maps
stored actions to the policy's and back."""

import subprocess
import sys

import numpy as np
import pytest

from carp.tasks import TASK_NAMES, get_task, task_for_env_args
from carp.tasks.arms.task import ABSOLUTE_ACTIONS, DELTA_ACTIONS
from carp.tasks.pusht.task import MaxReward


def test_every_task_is_found_by_name_and_by_the_env_args_it_writes():
    assert set(TASK_NAMES) == {"lift", "can", "square", "stack", "nut_assembly", "stack_three", "threading", "pusht"}
    for name in TASK_NAMES:
        task = get_task(name)
        assert task.name == name
        assert task_for_env_args(task.make_env_args("absolute")) is task
    assert get_task("pusht").make_env_args("absolute")["env_name"] == "gym_pusht/PushT-v0"


def test_the_names_are_listed_without_importing_a_task_or_its_simulator():
    script = (
        "import sys\n"
        "from carp.tasks import TASK_NAMES\n"
        "assert len(TASK_NAMES) == 8\n"
        "loaded = [name for name in sys.modules if name.startswith(('robosuite', 'mujoco', 'gym_pusht', 'pymunk'))]\n"
        "tasks = [name for name in sys.modules if name.startswith('carp.tasks.') and name != 'carp.tasks.base']\n"
        "print(loaded, tasks)\n"
    )
    completed = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert completed.stdout.strip() == "[] []"


def test_unknown_tasks_and_envs_are_refused_naming_them():
    known = r"\['lift', 'can', 'square', 'stack', 'nut_assembly', 'stack_three', 'threading', 'pusht'\]"
    with pytest.raises(ValueError, match=rf"unknown task 'peg_in_hole'; expected one of {known}"):
        get_task("peg_in_hole")
    with pytest.raises(ValueError, match="env_args name env 'PegInHole', which no task runs"):
        task_for_env_args({"env_name": "PegInHole"})
    with pytest.raises(ValueError, match="pusht: controller 'delta': the agent takes absolute targets only"):
        get_task("pusht").action_format("delta")


def test_absolute_arm_actions_round_trip_through_the_policys_10_d_form():
    rng = np.random.default_rng(0)
    axis = rng.normal(size=(5, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    stored = np.concatenate(
        [rng.normal(size=(5, 3)), axis * rng.uniform(0.1, 3.0, size=(5, 1)), rng.choice([-1.0, 1.0], size=(5, 1))],
        axis=1,
    )
    policy = ABSOLUTE_ACTIONS.to_policy(stored)
    assert policy.shape == (5, ABSOLUTE_ACTIONS.policy_dim) == (5, 10)
    np.testing.assert_allclose(ABSOLUTE_ACTIONS.to_env(policy), stored, atol=1e-9)
    np.testing.assert_array_equal(DELTA_ACTIONS.to_env(DELTA_ACTIONS.to_policy(stored)), stored)
    pusht_actions = get_task("pusht").action_format("absolute")
    targets = rng.uniform(0, 512, size=(4, 2))
    assert (pusht_actions.space, pusht_actions.stored_dim, pusht_actions.policy_dim) == ("pusht-abs2", 2, 2)
    np.testing.assert_array_equal(pusht_actions.to_env(pusht_actions.to_policy(targets)), targets)


class _Rewarded:
    def __init__(self, reward: float) -> None:
        self.value = reward

    def reward(self) -> float:
        return self.value


def test_the_push_t_score_is_the_highest_reward_of_the_steps_not_the_initial_state():
    measure = MaxReward()
    env = _Rewarded(0.9)
    measure.reset(env)  # DP scores the rewards its steps return; a good initial state counts for nothing
    for step, reward in enumerate((0.2, 0.7, 0.4), start=1):
        env.value = reward
        measure.observe(env, step)
    assert measure.values() == {"max_reward": 0.7}
