"""Atomic, versioned training-state checkpoints shared by the tokenizer and policy trainers.

A training state holds everything needed to continue a run bit-for-bit: model, optimizer and LR-scheduler state, the
number of completed epochs, the random-number-generator states of torch, numpy and Python, and free-form metadata
(e.g. the architecture) that a trainer compares before resuming. Files are written to a temporary sibling and moved
into place with `os.replace`, so an interruption leaves either the previous checkpoint or the new one, never half a
file.
"""

import os
import random
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

TRAINING_STATE_FORMAT_VERSION = 1


class CheckpointFormatError(ValueError):
    """A checkpoint was written by an incompatible version of this code."""


def atomic_torch_save(payload: Any, path: Path) -> None:
    """`torch.save` to a temporary file in the same directory, then atomically rename it to `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        torch.save(payload, temporary)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def _rng_states() -> dict[str, Any]:
    states: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
    }
    if torch.cuda.is_available():
        states["cuda"] = torch.cuda.get_rng_state_all()
    return states


def _restore_rng_states(states: dict[str, Any]) -> None:
    torch.set_rng_state(states["torch"])
    np.random.set_state(states["numpy"])
    random.setstate(states["python"])
    if "cuda" in states and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(states["cuda"])


def save_training_state(
    path: Path,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: torch.optim.lr_scheduler.LRScheduler | None,
    epoch: int,
    metadata: dict[str, Any] | None = None,
    history: list[dict[str, float]] | None = None,
) -> None:
    """Atomically write a training state.

    Args:
        path: destination file.
        model: the trained module.
        optimizer: its optimizer.
        scheduler: its LR scheduler, or None.
        epoch: number of completed epochs (training resumes at this epoch index).
        metadata: plain values describing the run (architecture, settings) for `read_training_metadata`.
        history: metrics of the completed epochs, one dict per epoch, for `replay_history`.
    """
    payload = {
        "format_version": TRAINING_STATE_FORMAT_VERSION,
        "epoch": epoch,
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "scheduler": scheduler.state_dict() if scheduler is not None else None,
        "rng": _rng_states(),
        "metadata": metadata or {},
        "history": list(history or []),
    }
    atomic_torch_save(payload, path)


def _read(path: Path) -> dict[str, Any]:
    # weights_only=False: the payload holds numpy and Python RNG states, which are not plain tensors. The file is
    # one this project wrote into its own checkpoint directory.
    payload = torch.load(Path(path), map_location="cpu", weights_only=False)
    version = payload.get("format_version") if isinstance(payload, dict) else None
    if version != TRAINING_STATE_FORMAT_VERSION:
        raise CheckpointFormatError(
            f"{path}: training state has format_version {version!r}, this code reads version "
            f"{TRAINING_STATE_FORMAT_VERSION}; delete the checkpoint to start over"
        )
    return payload


def read_training_metadata(path: Path) -> dict[str, Any]:
    """Metadata stored with a training state (after checking its format version)."""
    return _read(path)["metadata"]


def replay_history(path: Path, on_epoch_end: Callable[[int, dict[str, float]], None] | None) -> list[dict[str, float]]:
    """Metrics of the epochs stored with the training state at `path`, each passed to `on_epoch_end` again.

    A resumed run thereby reports every epoch, not only those after the interruption; a run whose state already
    holds all its epochs reports them and trains no further. States written without a history give none.
    """
    history = list(_read(path).get("history", []))
    if on_epoch_end is not None:
        for epoch, metrics in enumerate(history):
            on_epoch_end(epoch, metrics)
    return history


def load_training_state(
    path: Path,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: torch.optim.lr_scheduler.LRScheduler | None,
) -> int:
    """Restore model (strictly), optimizer, scheduler and RNG states from `path`.

    Returns:
        The number of completed epochs stored in the checkpoint.

    Raises:
        CheckpointFormatError: the file has another format version.
        RuntimeError: the model's parameters do not match the checkpoint (strict loading).
    """
    payload = _read(path)
    model.load_state_dict(payload["model"], strict=True)
    optimizer.load_state_dict(payload["optimizer"])
    if scheduler is not None:
        if payload["scheduler"] is None:
            raise ValueError(f"{path}: checkpoint has no scheduler state but a scheduler was given")
        scheduler.load_state_dict(payload["scheduler"])
    _restore_rng_states(payload["rng"])
    return int(payload["epoch"])
