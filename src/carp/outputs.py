"""Small output files of the pipeline's stages (metrics JSON, per-epoch CSV), each written atomically.

Every file is written to a hidden temporary sibling and renamed into place, so an interrupted stage leaves either
the previous file or the new one, never a partial one. pandas is imported where it is used, so that stages which
write no CSV do not pay for importing it.
"""

import json
import os
from pathlib import Path

MULTITASK_SUFFIX = "-multitask"
"""Appended to a family's name to name its multi-task policy (``carp-multitask``) in evaluation paths and reports."""


def write_json(path: Path, payload: dict) -> None:
    """Write `payload` as indented JSON with sorted keys to `path` (parents created)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(json.dumps(payload, indent=2, sort_keys=True))
    os.replace(temporary, path)


def write_history(path: Path, history: list[dict]) -> None:
    """Write per-epoch metrics as CSV; no epochs (a tokenizer fetched, not trained) gives just an ``epoch`` header."""
    import pandas as pd

    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    pd.DataFrame(history, columns=None if history else ["epoch"]).to_csv(temporary, index=False)
    os.replace(temporary, path)
