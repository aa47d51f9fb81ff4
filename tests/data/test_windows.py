import numpy as np
import pytest

from carp.data.normalizer import MinMaxNormalizer
from carp.data.replay_buffer import ReplayBuffer
from carp.data.windows import make_windows, window_row_indices


def test_windows_pad_at_episode_edges_and_never_cross_episodes():
    ends = np.array([5, 12])
    rows = window_row_indices(ends, horizon=4, pad_before=1, pad_after=2)
    # Episode 0 (rows 0..4): starts -1..(5-4+2)=3 -> 5 windows; episode 1 (rows 5..11): starts -1..5 -> 7 windows.
    assert rows.shape == (12, 4)
    np.testing.assert_array_equal(rows[0], [0, 0, 1, 2])  # first step repeated
    np.testing.assert_array_equal(rows[4], [3, 4, 4, 4])  # last step repeated
    np.testing.assert_array_equal(rows[5], [5, 5, 6, 7])
    np.testing.assert_array_equal(rows[-1], [10, 11, 11, 11])
    episode_of_row = np.searchsorted(ends, rows, side="right")
    assert np.all(episode_of_row == episode_of_row[:, :1])


def test_current_steps_cover_the_episode_as_in_diffusion_policy():
    # The "current step" (index To-1 of a window) runs from the first step to T - H + Ta - 1 + To - 1, so every
    # action that a rollout executes from a non-terminal state is supervised.
    length, horizon, obs_steps, action_steps = 40, 16, 2, 8
    rows = window_row_indices(np.array([length]), horizon, obs_steps - 1, action_steps - 1)
    current = rows[:, obs_steps - 1]
    last_current = length - horizon + (action_steps - 1) + (obs_steps - 1)
    np.testing.assert_array_equal(current, np.arange(last_current + 1))
    # A short episode still yields one fully padded window instead of none.
    short = window_row_indices(np.array([3]), horizon, obs_steps - 1, action_steps - 1)
    np.testing.assert_array_equal(short, [[0, 0, 1, 2] + [2] * 12])


def test_make_windows_splits_by_held_out_episode():
    obs = np.arange(24, dtype=np.float32).reshape(12, 2)
    action = -np.arange(36, dtype=np.float32).reshape(12, 3)
    buffer = ReplayBuffer(obs, action, np.array([5, 12]), np.array([False, True]), attrs={})
    train_obs, train_actions = make_windows(buffer, horizon=4, obs_steps=2, action_steps=3, split="train")
    valid_obs, valid_actions = make_windows(buffer, horizon=4, obs_steps=2, action_steps=3, split="valid")
    assert train_obs.shape == (5, 2, 2) and train_actions.shape == (5, 4, 3)
    assert train_actions.max() > -15.0 and valid_actions.min() <= -15.0  # rows 5.. belong to episode 1 only
    assert valid_obs.shape[0] == 7
    with pytest.raises(ValueError, match="split must be"):
        make_windows(buffer, 4, 2, 3, split="test")


def test_normalizer_maps_to_unit_interval_and_back():
    rng = np.random.default_rng(0)
    values = rng.normal(size=(100, 4)) * [1.0, 10.0, 0.01, 0.0] + [0.0, 5.0, -2.0, 3.0]
    normalizer = MinMaxNormalizer.fit(values)
    normalized = normalizer.normalize(values)
    np.testing.assert_allclose(normalized[:, :3].min(axis=0), -1.0, atol=1e-12)
    np.testing.assert_allclose(normalized[:, :3].max(axis=0), 1.0, atol=1e-12)
    np.testing.assert_allclose(normalized[:, 3], 0.0)  # constant feature
    np.testing.assert_allclose(normalizer.unnormalize(normalized), values, atol=1e-9)
    stray = normalized.copy()
    stray[:, 3] = 0.7  # a model's output on the constant feature
    np.testing.assert_allclose(normalizer.unnormalize(stray)[:, 3], 3.0)
    restored = MinMaxNormalizer.from_dict(normalizer.to_dict())
    np.testing.assert_allclose(restored.unnormalize(normalized), values, atol=1e-9)


def test_normalizer_works_on_tensors_with_dtype_kept():
    import torch

    normalizer = MinMaxNormalizer(minimum=np.array([0.0, -1.0]), maximum=np.array([2.0, 1.0]))
    values = torch.tensor([[1.0, 0.5], [2.0, -1.0]], dtype=torch.float32)
    normalized = normalizer.normalize(values)
    assert normalized.dtype == torch.float32
    torch.testing.assert_close(normalized, torch.tensor([[0.0, 0.5], [1.0, -1.0]]))
    torch.testing.assert_close(normalizer.unnormalize(normalized), values)


@pytest.mark.parametrize(
    "column, message",
    [
        ([0.0, np.inf], r"feature 1: minimum=.*maximum=inf"),
        ([-3e38, 3e38], r"feature 1: minimum=-3e\+38, maximum=3e\+38: the statistics or their range are not finite"),
        ([0.0, 1e39], r"feature 1: minimum=0.0, maximum=1e\+39"),
    ],
)
def test_normalizer_refuses_statistics_not_finite_in_float32(column, message):
    values = np.stack([np.zeros(2), np.asarray(column)], axis=1)  # (2, 2): feature 1 holds the bad column
    with pytest.raises(ValueError, match=message):
        MinMaxNormalizer.fit(values)
