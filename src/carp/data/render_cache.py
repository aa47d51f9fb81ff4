"""Rendered demos kept on disk until their ingestion finishes, so an interrupted ingestion resumes where it stopped.

Rendering a task's demos takes minutes to tens of minutes on a CPU, and the ingested buffer only appears, atomically,
when every demo is done. Each demo's frames are therefore saved as soon as they are rendered, under a key that digests
everything the frames depend on: the demos' stored states and models, the render settings, and the rendering code and
MuJoCo version. A rerun with the same key reads the saved demos instead of rendering them again; anything else
(another file, other settings, changed rendering code) gets a key of its own, and the entries of other keys are
removed when a cache is opened. The ingestion removes the cache once its output is in place.

Each entry is written under a temporary name and renamed, so a process killed while saving leaves no truncated entry;
an entry that cannot be read, or holds other shapes than expected, is rendered again.
"""

import hashlib
import json
import logging
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from importlib.metadata import version
from pathlib import Path

import numpy as np

from carp.data import rendering
from carp.data.rendering import RenderSettings
from carp.data.staging import remove_path
from carp.outputs import atomic_path

logger = logging.getLogger(__name__)


def render_key(env_args: Mapping, demos: Sequence[tuple[Mapping, np.ndarray]], settings: RenderSettings) -> str:
    """A digest of everything a demo file's rendered frames depend on.

    Args:
        env_args: the file's ``env_args``.
        demos: per demo, its attributes (model or seed) and its (T, S) stored states, in file order.
        settings: cameras, image size and render flags.
    """
    digest = hashlib.sha256()
    header = {"env_args": env_args, "settings": asdict(settings), "mujoco": version("mujoco")}
    digest.update(json.dumps(header, sort_keys=True, default=str).encode())
    digest.update(Path(rendering.__file__).read_bytes())
    for attrs, states in demos:
        digest.update(json.dumps(dict(attrs), sort_keys=True, default=str).encode())
        states = np.ascontiguousarray(states, dtype=np.float64)
        digest.update(str(states.shape).encode())
        digest.update(states.tobytes())
    return digest.hexdigest()[:16]


class RenderCache:
    """The rendered demos of one key, in ``root/<key>/<demo index>.npz``.

    Opening a cache removes the entries of every other key under ``root``: they belong to an ingestion whose input or
    settings have since changed, and would never be read again.
    """

    def __init__(self, root: Path, key: str, settings: RenderSettings) -> None:
        self.root = Path(root)
        self.directory = self.root / key
        self.settings = settings
        if self.root.is_dir():
            for entry in self.root.iterdir():
                if entry != self.directory:
                    remove_path(entry)
        self.directory.mkdir(parents=True, exist_ok=True)

    def load(self, index: int, steps: int) -> dict[str, np.ndarray] | None:
        """Demo ``index``'s frames, obs key -> (steps, size, size, 3) uint8, or ``None`` when not saved intact."""
        path = self._path(index)
        if not path.exists():
            return None
        size = self.settings.image_size
        try:
            with np.load(path) as saved:
                images = {key: saved[key] for key in self.settings.image_keys}
        except (OSError, KeyError, ValueError, zipfile.BadZipFile):
            return None
        if any(image.shape != (steps, size, size, 3) or image.dtype != np.uint8 for image in images.values()):
            return None
        return images

    def save(self, index: int, images: Mapping[str, np.ndarray]) -> None:
        """Save demo ``index``'s frames (obs key -> (T, size, size, 3) uint8) under a temporary name, then rename."""
        with atomic_path(self._path(index)) as temporary, open(temporary, "wb") as handle:
            np.savez_compressed(handle, **images)

    def saved_count(self) -> int:
        """How many demos have an entry (intact or not)."""
        return sum(1 for path in self.directory.glob("*.npz"))

    def remove(self) -> None:
        """Remove the whole cache root, every key included."""
        remove_path(self.root)

    def _path(self, index: int) -> Path:
        return self.directory / f"{index:06d}.npz"


__all__ = ["RenderCache", "render_key"]
