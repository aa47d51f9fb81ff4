"""Replay buffer: one zarr (v2 format) store per task with episodes concatenated along time.

Layout::

    <root>/data/obs            (N, Do) float32  low-dim obs keys concatenated in params order
    <root>/data/action         (N, A)  float32  policy actions (10-D absolute or 7-D delta)
    <root>/data/<camera>_image (N, H, W, 3) uint8 camera images, only in an image buffer (attrs image_keys)
    <root>/meta/episode_ends   (E,)    int64    exclusive end row of each episode
    <root>/meta/valid_episodes (E,)    bool     held out for validation metrics
    attrs: obs_keys, obs_widths, controller, source file, env_args, demo names; in an image buffer also
           image_keys (camera order), image_size and image_sources (obs key -> "file" or "rendered")

zarr 2 is used deliberately: its ``DirectoryStore`` API is stable and the arrays are small (a few MB), so one chunk
of a few thousand rows per array keeps random window sampling to a single read. Images are the exception: a demo's
frames take megabytes, so they are stored in chunks of a few frames along time, compressed, and read lazily (see
:mod:`carp.data.image_windows`): sampling a window decodes only the chunks holding its frames, never an episode.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

# Rows per chunk: large enough that a whole task usually fits in one or two chunks.
ROWS_PER_CHUNK = 4096
# Image frames per chunk: a window reads To (1 or 2) consecutive frames, so a few frames per chunk keep the bytes
# decoded per window close to the bytes used, while each chunk stays large enough (tens of kB at 84 x 84) to
# compress well and to keep the number of files per demo moderate.
FRAMES_PER_CHUNK = 4
# zstd at a low level: rendered scenes (flat table, walls) compress several times over, and decoding a chunk costs
# far less than copying it to the policy; Blosc's byte shuffle does nothing for 1-byte pixels, so it is off.
IMAGE_COMPRESSOR = zarr.Blosc(cname="zstd", clevel=3, shuffle=zarr.Blosc.NOSHUFFLE)


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
    def create_image_array(cls, root: Path, key: str, steps: int, image_size: int) -> zarr.Array:
        """Add an empty (steps, image_size, image_size, 3) uint8 image array ``data/<key>`` to a saved store.

        Args:
            root: a store written by :meth:`save`.
            key: the obs key, ``<camera>_image``.
            steps: N, rows of the buffer.
            image_size: H = W in pixels.

        Returns:
            The array, open for writing, chunked by :data:`FRAMES_PER_CHUNK` frames and compressed.
        """
        group = zarr.open_group(str(root), mode="r+")
        return group.create_dataset(
            f"data/{key}",
            shape=(steps, image_size, image_size, 3),
            chunks=(FRAMES_PER_CHUNK, image_size, image_size, 3),
            dtype=np.uint8,
            compressor=IMAGE_COMPRESSOR,
        )

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
