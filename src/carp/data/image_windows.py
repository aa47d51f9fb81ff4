"""Image observation windows, read lazily from an image replay buffer (layout in :mod:`carp.data.replay_buffer`).

Windows follow :mod:`carp.data.windows` (same rows, same edge padding); only the observation steps ``To`` carry
images. The low-dim arrays (proprioception, actions) are small and held in memory; the images stay on disk and a
batch reads, for each camera, the union of its windows' frames with one orthogonal selection, which decodes only the
chunks (a few frames each) holding those frames.
"""

from collections.abc import MutableMapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr
from einops import rearrange

from carp.data.windows import window_row_indices

SPLITS = ("train", "valid", "all")


@dataclass(frozen=True)
class ImageWindows:
    """A batch of windows.

    Attributes:
        images: (N, To, cameras, 3, H, W) uint8 RGB images, cameras in the buffer's ``image_keys`` order.
        proprioception: (N, To, Dp) float32 low-dim observations (the buffer's ``obs``), raw.
        actions: (N, H, A) float32 actions, raw.
    """

    images: np.ndarray
    proprioception: np.ndarray
    actions: np.ndarray


class ImageWindowReader:
    """Windows of an image replay buffer, indexed ``0 .. len - 1``.

    Args:
        store: the ``replay.zarr`` folder, or any zarr 2 store holding it (e.g. a wrapper that counts reads).
        horizon: ``H``, window length.
        obs_steps: ``To``, observation steps per window.
        action_steps: ``Ta``, executed actions per window (sets the padding after an episode's end).
        split: ``train`` (episodes not held out), ``valid`` (held out) or ``all``.
        preload_limit_bytes: when the split's observation frames, decoded, take at most this many bytes, they are
            decoded once into memory and batches index them; otherwise (and with 0) every batch reads its frames
            from the store. Training reads every window once per epoch, where a per-batch read of scattered chunks
            costs about as much as the encoder's step on a CPU; a single pass over the split's chunks is far cheaper.

    Raises:
        ValueError: an unknown split, or a buffer without images (ingested with ``observations: state``).
    """

    def __init__(
        self,
        store: Path | MutableMapping,
        horizon: int,
        obs_steps: int,
        action_steps: int,
        split: str = "all",
        preload_limit_bytes: int = 0,
    ) -> None:
        if split not in SPLITS:
            raise ValueError(f"split={split!r}: must be one of {SPLITS}")
        group = zarr.open_group(str(store) if isinstance(store, Path) else store, mode="r")
        if "image_keys" not in group.attrs:
            raise ValueError(f"{store}: replay buffer holds no images (ingest it with observations: image)")
        self.image_keys: tuple[str, ...] = tuple(group.attrs["image_keys"])
        self.image_size = int(group.attrs["image_size"])
        self.obs_steps = obs_steps
        self._images = [group[f"data/{key}"] for key in self.image_keys]
        self._proprioception = group["data/obs"][:]
        self._actions = group["data/action"][:]
        episode_ends = group["meta/episode_ends"][:]
        held_out = group["meta/valid_episodes"][:]
        episodes = np.arange(len(episode_ends))
        if split != "all":
            episodes = episodes[held_out] if split == "valid" else episodes[~held_out]
        self.rows = window_row_indices(episode_ends, horizon, obs_steps - 1, action_steps - 1, episodes)  # (N, H)
        # Decoded frames of the split (cameras x (U, H, W, 3)) and each buffer row's position among them.
        self._preloaded: list[np.ndarray] | None = None
        self._preloaded_position: np.ndarray | None = None
        frames = np.unique(self.rows[:, :obs_steps])
        frame_bytes = sum(int(np.prod(array.shape[1:])) * array.dtype.itemsize for array in self._images)
        if preload_limit_bytes > 0 and len(frames) * frame_bytes <= preload_limit_bytes:
            self._preloaded = [array.get_orthogonal_selection(frames) for array in self._images]
            self._preloaded_position = np.full(self._images[0].shape[0], -1, dtype=np.int64)
            self._preloaded_position[frames] = np.arange(len(frames))

    @property
    def preloaded(self) -> bool:
        """Whether the split's frames were decoded into memory (see ``preload_limit_bytes``)."""
        return self._preloaded is not None

    def __len__(self) -> int:
        return int(self.rows.shape[0])

    def images(self, window_indices: np.ndarray) -> np.ndarray:
        """The camera images of some windows' observation steps.

        Args:
            window_indices: (N,) int indices into ``0 .. len - 1``, any order, repeats allowed.

        Returns:
            (N, To, cameras, 3, H, W) uint8 RGB images, in the order of ``window_indices``.
        """
        obs_rows = self.rows[np.asarray(window_indices, dtype=np.int64), : self.obs_steps]  # (N, To)
        if self._preloaded is not None:
            positions = self._preloaded_position[obs_rows]  # (N, To)
            images = np.stack([frames[positions] for frames in self._preloaded], axis=2)  # (N, To, cameras, H, W, 3)
            return np.ascontiguousarray(rearrange(images, "n t c h w rgb -> n t c rgb h w"))
        frames, inverse = np.unique(obs_rows, return_inverse=True)
        # Orthogonal selection reads each chunk holding a selected frame once; sorted unique rows keep it in order.
        per_camera = [array.get_orthogonal_selection(frames) for array in self._images]  # cameras x (U, H, W, 3)
        images = np.stack(per_camera, axis=1)[inverse.reshape(obs_rows.shape)]  # (N, To, cameras, H, W, 3)
        return np.ascontiguousarray(rearrange(images, "n t c h w rgb -> n t c rgb h w"))

    def read(self, window_indices: np.ndarray) -> ImageWindows:
        """Images, proprioception and actions of some windows.

        Args:
            window_indices: (N,) int indices into ``0 .. len - 1``, any order, repeats allowed.

        Returns:
            The windows, in the order of ``window_indices``.
        """
        rows = self.rows[np.asarray(window_indices, dtype=np.int64)]  # (N, H)
        return ImageWindows(
            images=self.images(window_indices),
            proprioception=self._proprioception[rows[:, : self.obs_steps]],
            actions=self._actions[rows],
        )


def episode_images(store: Path | MutableMapping, episode: int = 0) -> dict[str, np.ndarray]:
    """Every camera's frames of one episode of a replay buffer, or an empty dict for a buffer without images.

    Args:
        store: the ``replay.zarr`` folder or a zarr 2 store holding it.
        episode: index of the episode.

    Returns:
        obs key (``<camera>_image``) -> (T, H, W, 3) uint8 upright RGB frames, in the buffer's camera order.
    """
    group = zarr.open_group(str(store) if isinstance(store, Path) else store, mode="r")
    if "image_keys" not in group.attrs:
        return {}
    ends = group["meta/episode_ends"][:]
    start, end = (int(ends[episode - 1]) if episode > 0 else 0), int(ends[episode])
    return {key: group[f"data/{key}"][start:end] for key in group.attrs["image_keys"]}


__all__ = ["ImageWindowReader", "ImageWindows", "episode_images"]
