"""Loading the processed data of one or more tasks into training windows."""

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carp.data.ingest import BUFFER_DIRNAME, NORMALIZATION_FILENAME
from carp.data.normalizer import MinMaxNormalizer, load_normalizers
from carp.data.obs_padding import padded_layout
from carp.data.replay_buffer import ReplayBuffer
from carp.data.windows import make_windows


@dataclass
class TaskWindows:
    """Raw (not normalized) windows of one task, split into training and held-out episodes.

    Attributes:
        train_obs: (N, To, Do) observations.
        train_actions: (N, H, A) actions.
        valid_obs: (M, To, Do) held-out observations.
        valid_actions: (M, H, A) held-out actions.
        obs_normalizer: the task's obs statistics.
        action_normalizer: the task's action statistics.
        buffer: the replay buffer the windows came from.
    """

    train_obs: np.ndarray
    train_actions: np.ndarray
    valid_obs: np.ndarray
    valid_actions: np.ndarray
    obs_normalizer: MinMaxNormalizer
    action_normalizer: MinMaxNormalizer
    buffer: ReplayBuffer


def load_task_windows(processed_dir: Path, horizon: int, obs_steps: int, action_steps: int) -> TaskWindows:
    """Windows of one task's ``data/processed/<task>/`` directory (see :mod:`carp.data.ingest`)."""
    processed_dir = Path(processed_dir)
    buffer = ReplayBuffer.load(processed_dir / BUFFER_DIRNAME)
    normalizers = load_normalizers(processed_dir / NORMALIZATION_FILENAME)
    train_obs, train_actions = make_windows(buffer, horizon, obs_steps, action_steps, split="train")
    valid_obs, valid_actions = make_windows(buffer, horizon, obs_steps, action_steps, split="valid")
    return TaskWindows(
        train_obs, train_actions, valid_obs, valid_actions, normalizers["obs"], normalizers["action"], buffer
    )


def check_tasks_agree(windows: Mapping[str, TaskWindows]) -> None:
    """Refuse tasks whose observations or actions differ in layout: one multi-task policy sees them all alike.

    The first task is the reference; every other must have the same low-dim obs keys in the same order, the same
    controller, and actions of the same width. A key may differ in width between tasks (Lift's 10-wide `object`
    against Can's 14): the policy pads each to its widest task's width (`carp.data.obs_padding`).

    Raises:
        ValueError: naming the task, the key and both values.
    """
    names = list(windows)
    reference_task = names[0]
    reference = windows[reference_task]
    for task in names[1:]:
        own = windows[task]
        for key in ("obs_keys", "controller"):
            ours, theirs = reference.buffer.attrs.get(key), own.buffer.attrs.get(key)
            if ours != theirs:
                raise ValueError(f"task {task!r}: {key} {theirs!r} differs from task {reference_task!r}'s {ours!r}")
        if own.buffer.action.shape[1] != reference.buffer.action.shape[1]:
            raise ValueError(
                f"task {task!r}: actions have {own.buffer.action.shape[1]} dimensions, task {reference_task!r}'s have "
                f"{reference.buffer.action.shape[1]}"
            )


def task_obs_widths(windows: Mapping[str, TaskWindows]) -> dict[str, tuple[int, ...]]:
    """Each task's features per obs key (the replay buffer's `obs_widths`), in task-id order."""
    return {task: tuple(int(width) for width in own.buffer.attrs["obs_widths"]) for task, own in windows.items()}


def load_multitask_windows(
    processed_dirs: Mapping[str, Path], horizon: int, obs_steps: int, action_steps: int
) -> dict[str, TaskWindows]:
    """Windows of every task of a multi-task policy, in task-id order, checked to agree (:func:`check_tasks_agree`).

    Args:
        processed_dirs: task -> its ``data/processed/<task>/`` directory, in the order of the task ids.
        horizon: `H`.
        obs_steps: `To`.
        action_steps: `Ta`.
    """
    windows = {
        task: load_task_windows(directory, horizon, obs_steps, action_steps)
        for task, directory in processed_dirs.items()
    }
    check_tasks_agree(windows)
    return windows


def stack_task_windows(windows: Mapping[str, TaskWindows], split: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One split of several tasks' windows, each normalized with its own task's statistics, and their task ids.

    Every window comes from one episode of one task (`carp.data.windows`), so stacking the tasks' windows never
    makes one that straddles two demos or two tasks. Tasks whose obs keys differ in width are padded to the widest
    (`carp.data.obs_padding.padded_layout`): a padded column is 0, as the task's statistics would normalize it.

    Args:
        windows: task -> its windows, in task-id order.
        split: ``train`` or ``valid``.

    Returns:
        obs (N, To, Do) (padded) and actions (N, H, A) float32 normalized, task ids (N,) int64 (the tasks' positions).
    """
    if split not in ("train", "valid"):
        raise ValueError(f"split must be train or valid, got {split!r}")
    paddings = padded_layout(task_obs_widths(windows))
    obs, actions, task_ids = [], [], []
    for task_id, (task, task_windows) in enumerate(windows.items()):
        task_obs = getattr(task_windows, f"{split}_obs")
        obs.append(paddings[task].pad(task_windows.obs_normalizer.normalize(task_obs).astype(np.float32)))
        actions.append(task_windows.action_normalizer.normalize(getattr(task_windows, f"{split}_actions")))
        task_ids.append(np.full(len(task_obs), task_id, dtype=np.int64))
    return np.concatenate(obs), np.concatenate(actions).astype(np.float32), np.concatenate(task_ids)
