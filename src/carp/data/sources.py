"""Where a task's demonstrations come from, as a small record whose content changes exactly when the source does.

DVC cannot template a dependency on ``data.raw_files[task]`` (a path held in a params mapping), so the collect stage
depends on this record instead: the ``check_inputs`` stage rewrites it on every ``dvc repro`` and ``dvc exp run``,
and its bytes change when, and only when, the user's file changes (its sha256) or the source kind does. A replaced
file at the same path therefore reruns collect and everything downstream, and an unchanged one reruns nothing.
A LeRobotDataset folder (:mod:`carp.data.lerobot`) is recorded the same way, its sha256 taken over the relative path
and the bytes of every file in it, so that a changed, added or removed file reruns collect as well. Collect decodes
its videos for the cameras of an image run, so the record of such a folder also holds the cameras and image size.
"""

import hashlib
from collections.abc import Sequence
from pathlib import Path

from carp.data.lerobot import is_lerobot_dataset

# Large robomimic image files are read in blocks so hashing never holds a whole file in memory.
HASH_BLOCK_BYTES = 1 << 20


class SourceError(ValueError):
    """A user's demonstration file that cannot be read."""


def file_sha256(path: Path) -> str:
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(HASH_BLOCK_BYTES):
            digest.update(block)
    return digest.hexdigest()


def folder_sha256(root: Path) -> tuple[str, int, int]:
    """Hex sha256 over the sorted relative paths and bytes of every file under ``root``; with the files and bytes."""
    digest = hashlib.sha256()
    files = sorted(path for path in Path(root).rglob("*") if path.is_file())
    for path in files:
        relative = path.relative_to(root).as_posix().encode()
        digest.update(len(relative).to_bytes(8, "little") + relative)
        digest.update(bytes.fromhex(file_sha256(path)))
    return digest.hexdigest(), len(files), sum(path.stat().st_size for path in files)


def describe_source(
    task: str, user_file: str | None, project_root: Path, cameras: Sequence[str] = (), image_size: int | None = None
) -> dict:
    """The record of one task's demonstration source.

    Args:
        task: task name, e.g. ``lift``.
        user_file: the ``data.raw_files`` entry of the task (relative to ``project_root`` or absolute), or ``None``
            for scripted collection.
        project_root: directory that relative paths refer to.
        cameras: the cameras of an image run (``()`` for state); recorded for a LeRobotDataset folder, whose videos
            collect decodes for them.
        image_size: side of the camera images in pixels, recorded with ``cameras``.

    Returns:
        ``{"task", "source": "scripted"}``, ``{"task", "source": "file", "path", "sha256", "bytes"}``, or for a
        LeRobotDataset folder ``{"task", "source": "lerobot", "path", "sha256", "files", "bytes"}`` (plus
        ``"cameras"`` and ``"image_size"`` when ``cameras`` are given).

    Raises:
        SourceError: the user's file is missing, neither a regular file nor a LeRobotDataset folder, or unreadable
            (the message names the key).
    """
    if user_file is None:
        return {"task": task, "source": "scripted"}
    key = f"data.raw_files.{task}={user_file!r}"
    path = (Path(project_root) / user_file).resolve()
    if not path.exists():
        raise SourceError(f"{key}: file not found ({path})")
    if is_lerobot_dataset(path):
        try:
            sha256, files, size = folder_sha256(path)
        except OSError as error:
            raise SourceError(f"{key}: cannot be read ({error.strerror or error})") from None
        record = {"task": task, "source": "lerobot", "path": user_file, "sha256": sha256, "files": files, "bytes": size}
        if cameras:
            record.update(cameras=list(cameras), image_size=image_size)
        return record
    if not path.is_file():
        raise SourceError(f"{key}: not a regular file nor a LeRobotDataset folder (meta/info.json) ({path})")
    try:
        sha256 = file_sha256(path)
    except OSError as error:
        raise SourceError(f"{key}: cannot be read ({error.strerror or error})") from None
    return {"task": task, "source": "file", "path": user_file, "sha256": sha256, "bytes": path.stat().st_size}
