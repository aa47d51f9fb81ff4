"""Where a task's demonstrations come from, as a small record whose content changes exactly when the source does.

DVC cannot template a dependency on ``data.raw_files[task]`` (a path held in a params mapping), so the collect stage
depends on this record instead: the ``check_inputs`` stage rewrites it on every ``dvc repro`` and ``dvc exp run``,
and its bytes change when, and only when, the user's file changes (its sha256) or the source kind does. A replaced
file at the same path therefore reruns collect and everything downstream, and an unchanged one reruns nothing.
"""

import hashlib
from pathlib import Path

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


def describe_source(task: str, user_file: str | None, project_root: Path) -> dict:
    """The record of one task's demonstration source.

    Args:
        task: task name, e.g. ``lift``.
        user_file: the ``data.raw_files`` entry of the task (relative to ``project_root`` or absolute), or ``None``
            for scripted collection.
        project_root: directory that relative paths refer to.

    Returns:
        ``{"task", "source": "scripted"}``, or ``{"task", "source": "file", "path", "sha256", "bytes"}``.

    Raises:
        SourceError: the user's file is missing, not a regular file or unreadable (the message names the key).
    """
    if user_file is None:
        return {"task": task, "source": "scripted"}
    key = f"data.raw_files.{task}={user_file!r}"
    path = (Path(project_root) / user_file).resolve()
    if not path.exists():
        raise SourceError(f"{key}: file not found ({path})")
    if not path.is_file():
        raise SourceError(f"{key}: not a regular file ({path})")
    try:
        sha256 = file_sha256(path)
    except OSError as error:
        raise SourceError(f"{key}: cannot be read ({error.strerror or error})") from None
    return {"task": task, "source": "file", "path": user_file, "sha256": sha256, "bytes": path.stat().st_size}
