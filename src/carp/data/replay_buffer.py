"""Replay buffer: one zarr (v2 format) store per task with episodes concatenated along time.

Layout::

    <root>/data/obs            (N, Do) float32  low-dim obs keys concatenated in params order
    <root>/data/action         (N, A)  float32  policy actions (10-D absolute or 7-D delta)
    <root>/meta/episode_ends   (E,)    int64    exclusive end row of each episode
    <root>/meta/valid_episodes (E,)    bool     held out for validation metrics
    attrs: obs_keys, obs_widths, controller, source file, env_args, demo names

zarr 2 is used deliberately: its ``DirectoryStore`` API is stable and the arrays are small (a few MB), so one chunk
of a few thousand rows per array keeps random window sampling to a single read.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

# Rows per chunk: large enough that a whole task usually fits in one or two chunks.
ROWS_PER_CHUNK = 4096


@dataclass
class ReplayBuffer:
    """In-memory view of a replay buffer.

    Attributes:
        obs: (N, Do) observations.
        action: (N, A) actions.
        episode_ends: (E,) exclusive end row of each episode.
        valid_episodes: (E,) True for held-out episodes.
        attrs: metadata (obs keys and widths, controller, env_args, ...).
    """

    obs: np.ndarray
    action: np.ndarray
    episode_ends: np.ndarray
    valid_episodes: np.ndarray
    attrs: dict

    @property
    def num_episodes(self) -> int:
        """E."""
        return int(self.episode_ends.shape[0])

    @property
    def episode_starts(self) -> np.ndarray:
        """(E,) first row of each episode."""
        return np.concatenate([[0], self.episode_ends[:-1]]).astype(np.int64)

    def episode(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(obs (T, Do), action (T, A)) of one episode."""
        start, end = int(self.episode_starts[index]), int(self.episode_ends[index])
        return self.obs[start:end], self.action[start:end]

    def save(self, root: Path) -> None:
        """Write the zarr store at ``root`` (which must not exist yet)."""
        group = zarr.open_group(str(root), mode="w-")
        for name, values in (("data/obs", self.obs), ("data/action", self.action)):
            group.create_dataset(
                name, data=values.astype(np.float32), chunks=(ROWS_PER_CHUNK, values.shape[1]), compressor=None
            )
        group.create_dataset("meta/episode_ends", data=self.episode_ends.astype(np.int64))
        group.create_dataset("meta/valid_episodes", data=self.valid_episodes.astype(bool))
        group.attrs.update(self.attrs)

    @classmethod
    def load(cls, root: Path) -> "ReplayBuffer":
        """Read a store written by :meth:`save` into memory."""
        if not Path(root).exists():
            raise FileNotFoundError(f"{root}: replay buffer not found (run the ingest stage)")
        group = zarr.open_group(str(root), mode="r")
        return cls(
            obs=group["data/obs"][:],
            action=group["data/action"][:],
            episode_ends=group["meta/episode_ends"][:],
            valid_episodes=group["meta/valid_episodes"][:],
            attrs=dict(group.attrs),
        )
