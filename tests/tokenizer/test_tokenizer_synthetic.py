import numpy as np

from carp.tokenizer.synthetic import min_max_bounds, sliding_windows, synthetic_action_episodes


def test_episodes_look_like_absolute_pick_and_place_actions():
    episodes = synthetic_action_episodes(3, seed=5)
    assert len(episodes) == 3
    for episode in episodes:
        assert episode.dtype == np.float32 and episode.shape[1] == 10 and 70 <= episode.shape[0] <= 200
        assert set(np.unique(episode[:, 9]).tolist()) == {-1.0, 1.0}
        first, second = episode[:, 3:6], episode[:, 6:9]
        assert np.allclose(np.linalg.norm(first, axis=1), 1, atol=1e-5)
        assert np.allclose(np.linalg.norm(second, axis=1), 1, atol=1e-5)
        assert np.allclose((first * second).sum(axis=1), 0, atol=1e-5)
        assert np.abs(np.diff(episode[:, :3], axis=0)).max() < 0.1, "positions move smoothly"
    again = synthetic_action_episodes(3, seed=5)
    assert all(np.array_equal(a, b) for a, b in zip(episodes, again, strict=True))


def test_other_action_widths_end_with_a_gripper():
    episode = synthetic_action_episodes(1, action_dim=3, seed=0)[0]
    assert episode.shape[1] == 3
    assert set(np.unique(episode[:, 2]).tolist()) == {-1.0, 1.0}


def test_sliding_windows_pad_at_episode_edges():
    episode = np.arange(10, dtype=np.float32)[:, None]
    windows = sliding_windows([episode], horizon=4, pad_before=1, pad_after=2)
    assert windows.shape == (10 + 1 + 2 - 4 + 1, 4, 1)
    assert windows[0, :, 0].tolist() == [0, 0, 1, 2]
    assert windows[-1, :, 0].tolist() == [8, 9, 9, 9]
    low, high = min_max_bounds(windows)
    assert low.tolist() == [0.0] and high.tolist() == [9.0]
