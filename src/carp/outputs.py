"""Writing files atomically (`atomic_path`, the one way carp replaces a file) and the stages' small output files.

Every file is written to a hidden temporary sibling and renamed into place, so an interrupted writer leaves either
the previous file or the new one, never a partial one. pandas is imported where it is used, so that stages which
write no CSV do not pay for importing it.
"""

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

MULTITASK_SUFFIX = "-multitask"
"""Appended to a family's name to name its multi-task policy (``carp-multitask``) in evaluation paths and reports."""


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """A temporary sibling of `path` to write; renamed onto `path` when the block ends, removed if it raises.

    The sibling is hidden and carries the process id, so two processes writing the same file never share it, and
    parents are created. Write through a file handle where a format records the file's name (``torch.save`` names its
    records after a path it is given), so that the same content gives the same bytes.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def write_text(path: Path, text: str) -> None:
    """Write `text` to `path` atomically."""
    with atomic_path(path) as temporary:
        temporary.write_text(text)


def write_json(path: Path, payload: dict) -> None:
    """Write `payload` as indented JSON with sorted keys to `path` (parents created)."""
    write_text(path, json.dumps(payload, indent=2, sort_keys=True))


def write_history(path: Path, history: list[dict]) -> None:
    """Write per-epoch metrics as CSV; no epochs (a tokenizer fetched, not trained) gives just an ``epoch`` header."""
    import pandas as pd

    with atomic_path(path) as temporary:
        pd.DataFrame(history, columns=None if history else ["epoch"]).to_csv(temporary, index=False)
