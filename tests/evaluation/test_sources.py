import functools

import numpy as np

from carp.evaluation.sources import PolicySource, executed_actions
from carp.policies.registry import load_policy
from carp.tasks.robosuite_arms import ABSOLUTE_ACTIONS, DELTA_ACTIONS
from tests.policies.carp.factories import OBS_DIM, OBS_STEPS, tiny_policy


def test_executed_actions_take_the_rows_from_the_current_step_on():
    chunk = np.arange(16 * 3, dtype=np.float32).reshape(16, 3)  # (H, A), a delta-style action space
    executed = executed_actions(chunk, obs_steps=2, action_steps=8, action_format=DELTA_ACTIONS)
    assert executed.dtype == np.float64
    np.testing.assert_array_equal(executed, chunk[1:9])


def test_executed_actions_convert_absolute_rotations_to_the_controllers_axis_angle():
    identity_rot6d = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    chunk = np.array([[0.1 * step, 0.2, 0.3, *identity_rot6d, -1.0] for step in range(16)])  # (H, 10)
    executed = executed_actions(chunk, obs_steps=2, action_steps=8, action_format=ABSOLUTE_ACTIONS)
    assert executed.shape == (8, 7)
    np.testing.assert_allclose(executed[:, :3], chunk[1:9, :3])
    np.testing.assert_allclose(executed[:, 3:6], 0.0, atol=1e-12)
    np.testing.assert_array_equal(executed[:, 6], -1.0)


def test_sampling_depends_on_the_episode_seed_only(tmp_path):
    checkpoint = tmp_path / "policy.pt"
    tiny_policy().save(checkpoint)
    history = np.random.default_rng(0).normal(size=(OBS_STEPS, OBS_DIM))

    def first_chunk(source, seed):
        source.reset(env=None, seed=seed)
        return source.act(history, env=None)[0]

    load = functools.partial(load_policy, checkpoint)
    settings = dict(action_format=DELTA_ACTIONS, obs_steps=OBS_STEPS, action_steps=4, inference={"top_k": 8})
    fresh = PolicySource(load, **settings)
    used = PolicySource(load, **settings)
    draws_for_other_seeds = [first_chunk(used, seed) for seed in (11, 12, 13)]
    np.testing.assert_array_equal(first_chunk(fresh, 7), first_chunk(used, 7))
    assert any(not np.array_equal(draws, draws_for_other_seeds[0]) for draws in draws_for_other_seeds[1:])
