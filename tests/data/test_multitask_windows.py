"""Multi-task windows: task labels survive into the training windows, and no window straddles two demos or tasks."""

import numpy as np
import pytest

from carp.data.dataset import TaskWindows, check_tasks_agree, stack_task_windows, task_obs_widths
from carp.data.normalizer import MinMaxNormalizer
from carp.data.replay_buffer import ReplayBuffer
from carp.data.windows import make_windows

HORIZON, OBS_STEPS, ACTION_STEPS = 4, 2, 2


def _task_windows(task_code: int, lengths: list[int], widths=(2, 1), valid: list[bool] | None = None) -> TaskWindows:
    """Episodes whose every value encodes (task, episode): task_code * 1000 + episode * 100 + step."""
    rows = [task_code * 1000 + episode * 100 + step for episode, length in enumerate(lengths) for step in range(length)]
    codes = np.asarray(rows, dtype=np.float64)[:, None]
    buffer = ReplayBuffer(
        obs=np.repeat(codes, sum(widths), axis=1),
        action=np.repeat(codes, 3, axis=1),
        episode_ends=np.cumsum(lengths),
        valid_episodes=np.asarray(valid or [False] * len(lengths)),
        attrs={
            "obs_keys": ["object", "robot0_eef_pos"][: len(widths)],
            "obs_widths": list(widths),
            "controller": "abs",
        },
    )
    split = {name: make_windows(buffer, HORIZON, OBS_STEPS, ACTION_STEPS, split=name) for name in ("train", "valid")}
    # Identity statistics ([-1, 1] -> [-1, 1]) keep the codes readable after normalization.
    identity = MinMaxNormalizer(-np.ones(sum(widths)), np.ones(sum(widths)))
    action_identity = MinMaxNormalizer(-np.ones(3), np.ones(3))
    return TaskWindows(*split["train"], *split["valid"], identity, action_identity, buffer)


def test_task_labels_survive_and_no_window_straddles_two_demos_or_tasks():
    windows = {"lift": _task_windows(1, [5, 3, 6]), "can": _task_windows(2, [4, 7], valid=[False, True])}
    obs, actions, task_ids = stack_task_windows(windows, "train")
    expected_count = len(windows["lift"].train_obs) + len(windows["can"].train_obs)
    assert obs.shape == (expected_count, OBS_STEPS, 3) and actions.shape == (expected_count, HORIZON, 3)
    assert obs.dtype == actions.dtype == np.float32 and task_ids.dtype == np.int64
    # Each window's every observation and action row belongs to one episode of one task, the task of its label.
    window_codes = np.concatenate([obs.reshape(len(obs), -1), actions.reshape(len(actions), -1)], axis=1) // 100
    assert (window_codes == window_codes[:, :1]).all()
    np.testing.assert_array_equal(window_codes[:, 0] // 10, task_ids + 1)
    np.testing.assert_array_equal(
        np.bincount(task_ids), [len(windows["lift"].train_obs), len(windows["can"].train_obs)]
    )
    # The held-out episode of can gives the held-out windows, labelled as can's.
    _, _, valid_ids = stack_task_windows(windows, "valid")
    assert set(valid_ids.tolist()) == {1}


def test_each_task_is_normalized_with_its_own_statistics():
    lift, can = _task_windows(1, [5]), _task_windows(2, [5])
    can = TaskWindows(
        can.train_obs,
        can.train_actions,
        can.valid_obs,
        can.valid_actions,
        MinMaxNormalizer(np.full(3, 2000.0), np.full(3, 2004.0)),
        MinMaxNormalizer(np.full(3, 2000.0), np.full(3, 2004.0)),
        can.buffer,
    )
    obs, actions, task_ids = stack_task_windows({"lift": lift, "can": can}, "train")
    assert obs[task_ids == 0].min() >= 1000  # identity statistics
    assert obs[task_ids == 1].min() >= -1 and obs[task_ids == 1].max() <= 1  # can's own [2000, 2004]
    assert actions[task_ids == 1].min() >= -1 and actions[task_ids == 1].max() <= 1


def test_tasks_whose_observation_keys_or_actions_differ_are_refused_naming_task_and_key():
    with pytest.raises(ValueError, match="task 'can': obs_keys \\['object'\\] differs from task 'lift''s"):
        check_tasks_agree({"lift": _task_windows(1, [5]), "can": _task_windows(2, [5], widths=(2,))})
    check_tasks_agree({"lift": _task_windows(1, [5]), "can": _task_windows(2, [6, 4])})
    # A key of another width is padded, not refused.
    check_tasks_agree({"lift": _task_windows(1, [5]), "can": _task_windows(2, [5], widths=(4, 1))})


def test_a_narrower_task_is_zero_padded_per_key_to_the_widest_layout():
    lift, can = _task_windows(1, [5, 3]), _task_windows(2, [6], widths=(4, 1))
    windows = {"lift": lift, "can": can}
    assert task_obs_widths(windows) == {"lift": (2, 1), "can": (4, 1)}
    obs, _, task_ids = stack_task_windows(windows, "train")
    assert obs.shape[-1] == 5  # object 4 + eef 1
    lift_obs, can_obs = obs[task_ids == 0], obs[task_ids == 1]
    # Lift's two object features fill the key's first columns, then two zeros, then its eef feature.
    np.testing.assert_array_equal(lift_obs[..., [2, 3]], 0.0)
    np.testing.assert_array_equal(lift_obs[..., [0, 1, 4]], lift.train_obs.astype(np.float32))
    np.testing.assert_array_equal(can_obs, can.train_obs.astype(np.float32))
