"""Offline scores of a policy on held-out episodes: root mean squared errors overall, on the executed rows, per horizon
step, per action dimension and per episode, against values computed by hand."""

import numpy as np
import pytest

from carp.data.replay_buffer import ReplayBuffer
from carp.evaluation.offline import chunk_errors, held_out_action_errors, offline_evaluation


class ConstantPolicy:
    """Predicts the same chunk for every window: (B, To, Do) -> (B, H, A)."""

    def __init__(self, chunk: np.ndarray):
        self.chunk = chunk
        self.windows = 0

    def predict_action(self, obs: np.ndarray) -> np.ndarray:
        self.windows += len(obs)
        return np.broadcast_to(self.chunk, (len(obs), *self.chunk.shape)).copy()


def test_chunk_errors_have_known_values():
    # Two windows, H = 3, A = 2; the error is 1 everywhere but row 1, dimension 1 of the second window (3).
    actions = np.zeros((2, 3, 2))
    predicted = np.ones((2, 3, 2))
    predicted[1, 1, 1] = 3.0
    errors = chunk_errors(predicted, actions, obs_steps=2, action_steps=1, dimension_names=("x", "y"))
    assert errors["action_rmse"] == pytest.approx(np.sqrt((11 + 9) / 12))
    assert errors["executed_action_rmse"] == pytest.approx(np.sqrt((3 + 9) / 4))  # row To - 1 = 1 only
    assert [errors[f"step_rmse/{step}"] for step in range(3)] == pytest.approx([1.0, np.sqrt(12 / 4), 1.0])
    assert errors["dimension_rmse/x"] == pytest.approx(1.0)
    assert errors["dimension_rmse/y"] == pytest.approx(np.sqrt((5 + 9) / 6))
    assert set(errors) == {"action_rmse", "executed_action_rmse", "dimension_rmse/x", "dimension_rmse/y"} | {
        f"step_rmse/{step}" for step in range(3)
    }
    with pytest.raises(ValueError, match="must be"):
        chunk_errors(predicted[:, :2], actions, 2, 1)


def buffer_of(lengths, valid, action_value) -> ReplayBuffer:
    """Episodes of `lengths` steps with constant actions per episode (`action_value[e]`), obs = the step index."""
    steps = sum(lengths)
    actions = np.concatenate([np.full((length, 2), value) for length, value in zip(lengths, action_value)])
    return ReplayBuffer(
        obs=np.arange(steps, dtype=np.float64)[:, None],
        action=actions,
        episode_ends=np.cumsum(lengths),
        valid_episodes=np.array(valid),
        attrs={},
    )


def test_offline_evaluation_scores_only_the_held_out_episodes_every_window_once():
    buffer = buffer_of([5, 6, 4], [False, True, True], [100.0, 1.0, 3.0])
    policy = ConstantPolicy(np.zeros((4, 2)))
    summary, episodes = offline_evaluation(policy, buffer, horizon=4, obs_steps=2, action_steps=2, dimension_names="xy")
    # Windows start To - 1 = 1 step early and end once their executed rows (1 and 2) reach the last step: starts -1
    # to length - 3, length - 1 windows.
    assert [row["windows"] for row in episodes] == [5, 3] and policy.windows == 8
    assert [(row["episode"], row["steps"]) for row in episodes] == [(1, 6), (2, 4)]
    assert [row["action_rmse"] for row in episodes] == pytest.approx([1.0, 3.0])
    # Pooled over the 8 windows: 5 with squared error 1, 3 with 9; the training episode (100) never counts.
    assert summary["action_rmse"] == pytest.approx(np.sqrt((5 + 27) / 8))
    assert summary["dimension_rmse/x"] == summary["dimension_rmse/y"] == pytest.approx(summary["action_rmse"])
    assert (summary["held_out_episodes"], summary["held_out_windows"]) == (2, 8)
    # The same windows' errors as the training stages log.
    windows = np.array([[0, 0, 1, 2]])
    assert held_out_action_errors(policy, buffer.obs[windows[:, :2]], buffer.action[windows], 2, 2) == {
        "valid_action_rmse": pytest.approx(100.0),
        "valid_executed_action_rmse": pytest.approx(100.0),
    }


def test_no_held_out_episode_is_refused():
    buffer = buffer_of([5, 6], [False, False], [1.0, 1.0])
    with pytest.raises(ValueError, match="no held-out episode to score"):
        offline_evaluation(ConstantPolicy(np.zeros((4, 2))), buffer, 4, 2, 2, "xy")
