"""Loading the processed data of one or more tasks into training windows."""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carp.data.ingest import BUFFER_DIRNAME, NORMALIZATION_FILENAME
from carp.data.normalizer import MinMaxNormalizer, load_normalizers
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
