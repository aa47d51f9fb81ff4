import functools

import numpy as np
import pytest

from carp.evaluation.sources import ChunkEnsemble, PolicySource, executed_actions
from carp.policies.base import TimedPrediction
from carp.policies.registry import load_policy
from carp.tasks.arms.task import ABSOLUTE_ACTIONS, DELTA_ACTIONS
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


def test_the_ensemble_averages_every_chunk_covering_a_step_with_acts_weights():
    ensemble = ChunkEnsemble(m=0.0)
    first = np.array([[0.0], [10.0], [20.0]])  # predicted at step 0: steps 0, 1, 2
    second = np.array([[13.0], [23.0], [33.0]])  # at step 1: steps 1, 2, 3
    third = np.array([[26.0], [36.0], [46.0]])  # at step 2
    np.testing.assert_allclose(ensemble.act(first), [0.0])
    np.testing.assert_allclose(ensemble.act(second), [(10.0 + 13.0) / 2])
    np.testing.assert_allclose(ensemble.act(third), [(20.0 + 23.0 + 26.0) / 3])
    fourth = np.array([[39.0], [49.0], [59.0]])  # the first chunk no longer covers step 3
    np.testing.assert_allclose(ensemble.act(fourth), [(33.0 + 36.0 + 39.0) / 3])
    weighted = ChunkEnsemble(m=1.0)
    weighted.act(first)
    weights = np.exp([0.0, -1.0])
    np.testing.assert_allclose(weighted.act(second), [(weights @ [10.0, 13.0]) / weights.sum()])
    weighted.reset()
    np.testing.assert_allclose(weighted.act(second), [13.0])  # a new episode starts with no chunk
    with pytest.raises(ValueError, match="ensemble m must be >= 0, got -0.5"):
        ChunkEnsemble(-0.5)


class _ChunkPolicy:
    """Stands in for a policy: the k-th chunk it predicts is k everywhere, rows counting up by 100."""

    def __init__(self) -> None:
        self.calls = 0

    def configure_inference(self) -> None:
        pass

    def predict_action_timed(self, obs, task_index=None, generator=None):
        chunk = self.calls + 100.0 * np.arange(6)[:, None] * np.ones((1, 3))  # (H = 6, A = 3)
        self.calls += 1
        return TimedPrediction(actions=chunk[None], prediction_seconds=0.0, decoding_seconds=0.0, model_calls=1)


def test_an_ensembling_source_predicts_every_step_and_executes_one_averaged_action():
    policy = _ChunkPolicy()
    source = PolicySource(lambda: policy, DELTA_ACTIONS, obs_steps=2, action_steps=4, ensemble_m=0.0)
    source.reset(env=None, seed=0)
    history = np.zeros((2, 3))
    executed = [source.act(history, env=None)[0] for _ in range(3)]
    assert all(actions.shape == (1, 3) for actions in executed) and policy.calls == 3
    # Step 2: chunk 0's row 1 + 2 (= 300), chunk 1's row 1 + 1 (= 201), chunk 2's row 1 (= 102); rows from To - 1 = 1.
    np.testing.assert_allclose(executed[2][0], np.full(3, (300.0 + 201.0 + 102.0) / 3))
    plain = PolicySource(lambda: _ChunkPolicy(), DELTA_ACTIONS, obs_steps=2, action_steps=4)
    assert plain.act(history, env=None)[0].shape == (4, 3)
