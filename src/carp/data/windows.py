"""Training windows with the time convention of Diffusion Policy (docs/architecture.md, "Time convention").

A window covers ``H`` consecutive steps starting ``To - 1`` steps before the current step: the policy sees
obs[0:To] and predicts actions[0:H], of which actions[To-1 : To-1+Ta] are executed. Windows may start up to ``To - 1``
steps before an episode and end up to ``Ta - 1`` steps after it; missing steps repeat the first/last step (edge
padding), so every real step is the "current step" of some window and every executed action is supervised.
"""

import numpy as np

from carp.data.replay_buffer import ReplayBuffer


def window_row_indices(
    episode_ends: np.ndarray, horizon: int, pad_before: int, pad_after: int, episodes: np.ndarray | None = None
) -> np.ndarray:
    """Buffer rows of every window, edge-padded by clamping to the episode's first/last row.

    Args:
        episode_ends: (E,) exclusive end row per episode.
        horizon: ``H``, window length.
        pad_before: steps a window may start before its episode (``To - 1``).
        pad_after: steps a window may run past its episode's end (``Ta - 1``).
        episodes: optional indices of the episodes to use (default all).

    Returns:
        (N, H) int64 row indices; window n covers rows ``indices[n]``.
    """
    starts = np.concatenate([[0], episode_ends[:-1]])
    selected = np.arange(len(episode_ends)) if episodes is None else np.asarray(episodes)
    windows = []
    offsets = np.arange(horizon)
    for index in selected:
        begin, end = int(starts[index]), int(episode_ends[index])
        length = end - begin
        last_start = max(length - horizon + pad_after, -pad_before)
        relative = np.arange(-pad_before, last_start + 1)[:, None] + offsets[None, :]  # (n, H)
        windows.append(begin + np.clip(relative, 0, length - 1))
    if not windows:
        return np.zeros((0, horizon), dtype=np.int64)
    return np.concatenate(windows).astype(np.int64)


def make_windows(
    buffer: ReplayBuffer, horizon: int, obs_steps: int, action_steps: int, split: str = "all"
) -> tuple[np.ndarray, np.ndarray]:
    """Gather (obs, action) windows from a replay buffer.

    Args:
        buffer: the replay buffer.
        horizon: ``H``.
        obs_steps: ``To``.
        action_steps: ``Ta``.
        split: ``train`` (episodes not held out), ``valid`` (held out) or ``all``.

    Returns:
        obs (N, To, Do) and actions (N, H, A), raw (not normalized).
    """
    if split not in ("train", "valid", "all"):
        raise ValueError(f"split must be train, valid or all, got {split!r}")
    episodes = np.arange(buffer.num_episodes)
    if split == "train":
        episodes = episodes[~buffer.valid_episodes]
    elif split == "valid":
        episodes = episodes[buffer.valid_episodes]
    rows = window_row_indices(buffer.episode_ends, horizon, obs_steps - 1, action_steps - 1, episodes)
    return buffer.obs[rows[:, :obs_steps]], buffer.action[rows]
