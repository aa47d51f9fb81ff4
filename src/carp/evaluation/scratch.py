"""Scratch directories of evaluations (the exported ONNX graphs) that do not outlive a killed process.

A `with` block removes its directory on exit, but a process killed with SIGKILL never gets there. Each directory
therefore holds a lock file that its process keeps locked (`flock`) while it lives; the kernel drops the lock when
the process dies, however it dies. Every new scratch directory first removes the directories of the same prefix whose
lock nobody holds. A lock, unlike a process id stored in the name, stays right when the id is reused by another
process or the temp directory is shared by processes that see different process ids (containers).
"""

import fcntl
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

SCRATCH_PREFIX = "carp-onnx-"
LOCK_NAME = ".owner.lock"


def _hold_lock(directory: Path) -> int:
    # Locked under a temporary name and then renamed, so that a lock file under LOCK_NAME is always one whose owner
    # holds, or held, the lock: a sweeping process never sees an unlocked lock of a directory being set up.
    temporary = directory / f"{LOCK_NAME}.tmp"
    descriptor = os.open(temporary, os.O_CREAT | os.O_WRONLY, 0o600)
    fcntl.flock(descriptor, fcntl.LOCK_EX)
    os.replace(temporary, directory / LOCK_NAME)
    return descriptor


def remove_abandoned_scratch(root: Path, prefix: str = SCRATCH_PREFIX) -> list[Path]:
    """Delete the scratch directories under `root` whose process has ended; returns them.

    A directory without a lock file (one being set up this instant, or one not made by `scratch_directory`) is left.
    """
    removed = []
    for directory in sorted(Path(root).glob(f"{prefix}*")):
        try:
            descriptor = os.open(directory / LOCK_NAME, os.O_RDONLY)
        except OSError:
            continue
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            continue  # held: that evaluation is running
        else:
            shutil.rmtree(directory, ignore_errors=True)
            removed.append(directory)
        finally:
            os.close(descriptor)
    return removed


@contextmanager
def scratch_directory(root: Path | None = None, prefix: str = SCRATCH_PREFIX) -> Iterator[Path]:
    """A new directory under `root` (default: the system temp directory), removed on exit or after a kill.

    Directories left by killed processes are removed first (`remove_abandoned_scratch`).
    """
    root = Path(root) if root is not None else Path(tempfile.gettempdir())
    remove_abandoned_scratch(root, prefix)
    directory = Path(tempfile.mkdtemp(prefix=prefix, dir=root))
    lock = _hold_lock(directory)
    try:
        yield directory
    finally:
        shutil.rmtree(directory, ignore_errors=True)
        os.close(lock)
