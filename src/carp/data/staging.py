"""Temporary outputs: built under a per-process name in a staging folder, then renamed into place.

The staging folder is chosen by the caller. A pipeline must pick one outside every path a stage declares as a
dependency (DVC hashes everything inside a dependency folder, so a leftover of a killed process there would land in
``dvc.lock``) and on the same filesystem as the outputs, so that the final ``os.replace`` is atomic. A process killed
before its cleanup ran leaves its entry behind; the next staging in that folder removes entries of processes that no
longer exist.
"""

import logging
import os
import re
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

logger = logging.getLogger(__name__)

# `.<name>.<pid>.tmp`: the pid tells whether the process that owns an entry is still running.
_ENTRY = re.compile(r"\.(?P<name>.+)\.(?P<pid>\d+)\.tmp")


@contextmanager
def staged(directory: Path, name: str) -> Iterator[Path]:
    """A temporary path ``directory/.<name>.<pid>.tmp`` for building ``name``; removed on exit if still there.

    The caller writes a file or folder at the yielded path and moves it to its final place with ``os.replace``.
    ``directory`` is created if missing, and leftovers of dead processes in it are removed first.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    remove_stale_entries(directory)
    path = directory / f".{name}.{os.getpid()}.tmp"
    remove_path(path)
    try:
        yield path
    finally:
        remove_path(path)


def remove_stale_entries(directory: Path) -> list[Path]:
    """Remove the staging entries in ``directory`` whose process has exited; returns what was removed."""
    removed = []
    for path in sorted(Path(directory).iterdir()) if Path(directory).is_dir() else []:
        match = _ENTRY.fullmatch(path.name)
        if match is not None and not _process_exists(int(match["pid"])):
            remove_path(path)
            logger.info("removed %s, left behind by process %s", path, match["pid"])
            removed.append(path)
    return removed


def _process_exists(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's live process
    return True


def remove_path(path: Path) -> None:
    """Remove a file, link or folder tree if it exists."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)
