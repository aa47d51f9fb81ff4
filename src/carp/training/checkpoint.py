"""Atomic, versioned checkpoints: training states shared by the tokenizer and policy trainers, and strict reading.

A training state holds everything needed to continue a run bit-for-bit: model, optimizer and LR-scheduler state, the
number of completed epochs with their metrics, the random-number-generator states of torch, numpy and Python, and
metadata (architecture, settings, data hash) that must equal the new run's before it resumes. Files are written to a
temporary sibling and moved into place with `os.replace`, so an interruption leaves either the previous checkpoint or
the new one, never half a file.

A state that cannot be used (truncated or corrupt, another format version, parts that do not fit the model) is
discarded with a one-line warning and its stage starts over: a training state only saves time, and its loss must
never stop the pipeline until someone deletes `checkpoints/` by hand.
"""

import logging
import random
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from carp.outputs import atomic_path

logger = logging.getLogger(__name__)

TRAINING_STATE_FORMAT_VERSION = 1
_TRAINING_STATE_KEYS = ("format_version", "epoch", "model", "optimizer", "scheduler", "rng", "metadata", "history")


class CheckpointError(ValueError):
    """A checkpoint file this code cannot use; the message is one line that names the file."""


class CheckpointFormatError(CheckpointError):
    """A checkpoint was written in another format version."""


def one_line(error: BaseException) -> str:
    """The message of an exception on one line (PyTorch's load errors span several); its type when it has none."""
    return " ".join(str(error).split()) or type(error).__name__


def read_checkpoint(path: Path, weights_only: bool) -> Any:
    """`torch.load` onto the CPU, turning a truncated or corrupt file into one `CheckpointError`.

    Args:
        path: the file.
        weights_only: PyTorch's restricted unpickler (tensors and plain containers only); False only for files this
            project writes into its own directories.

    Raises:
        FileNotFoundError: no file at `path`.
        CheckpointError: the file exists but cannot be read as a checkpoint.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        return torch.load(path, map_location="cpu", weights_only=weights_only)
    except Exception as error:  # noqa: BLE001 - torch.load reports a damaged archive as RuntimeError, EOFError,
        # KeyError or UnpicklingError depending on where the damage is; all of them mean the same to the user.
        reason = one_line(error).split(". ")[0]  # PyTorch appends advice on its own internals after the first sentence
        raise CheckpointError(
            f"{path}: not a readable checkpoint, truncated or corrupt ({type(error).__name__}: {reason})"
        ) from error


def atomic_torch_save(payload: Any, path: Path) -> None:
    """`torch.save` to a temporary file in the same directory, then atomically rename it to `path`.

    The payload is written through a file object: given a path, torch names the archive's records after the file,
    here the temporary name with its process id, so that the same payload would save to different bytes per run.
    """
    with atomic_path(path) as temporary, open(temporary, "wb") as handle:
        torch.save(payload, handle)


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
    metadata: dict[str, Any],
    history: list[dict[str, float]],
) -> None:
    """Atomically write a training state.

    Args:
        path: destination file.
        model: the trained module.
        optimizer: its optimizer.
        scheduler: its LR scheduler, or None.
        epoch: number of completed epochs (training resumes at this epoch index).
        metadata: plain values describing the run (architecture, settings, data hash); a later run resumes only
            from a state whose metadata equals its own.
        history: metrics of the `epoch` completed epochs, one dict per epoch, reported again on resuming.
    """
    if len(history) != epoch:
        raise ValueError(f"a training state after {epoch} epochs needs {epoch} epochs of history, got {len(history)}")
    payload = {
        "format_version": TRAINING_STATE_FORMAT_VERSION,
        "epoch": epoch,
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "scheduler": scheduler.state_dict() if scheduler is not None else None,
        "rng": _rng_states(),
        "metadata": metadata,
        "history": list(history),
    }
    atomic_torch_save(payload, path)


def read_training_state(path: Path) -> dict[str, Any]:
    """The payload of a training state, after checking that it is readable, of this format version and complete.

    Raises:
        FileNotFoundError: no file at `path`.
        CheckpointError: unreadable, another format version (`CheckpointFormatError`), or parts missing.
    """
    # weights_only=False: the payload holds numpy and Python RNG states, which are not plain tensors. The file is
    # one this project wrote into its own checkpoint directory.
    payload = read_checkpoint(path, weights_only=False)
    version = payload.get("format_version") if isinstance(payload, dict) else None
    if version != TRAINING_STATE_FORMAT_VERSION:
        raise CheckpointFormatError(
            f"{path}: training state has format_version {version!r}, this code reads version "
            f"{TRAINING_STATE_FORMAT_VERSION}"
        )
    missing = [key for key in _TRAINING_STATE_KEYS if key not in payload]
    if missing:
        raise CheckpointError(f"{path}: training state lacks {', '.join(missing)}")
    types = {"metadata": dict, "history": list, "epoch": int}
    if not all(isinstance(payload[key], expected) for key, expected in types.items()):
        raise CheckpointError(f"{path}: training state's metadata, history or epoch has the wrong type")
    if len(payload["history"]) != payload["epoch"]:
        raise CheckpointError(
            f"{path}: training state after {payload['epoch']} epochs holds {len(payload['history'])} epochs of history"
        )
    return payload


def _check_model_state(path: Path, saved: dict[str, torch.Tensor], model: nn.Module) -> None:
    # Checked before anything is loaded: `load_state_dict(strict=True)` copies the matching tensors before it
    # reports the others, which would leave a half-restored model to start over from.
    expected = {name: tuple(value.shape) for name, value in model.state_dict().items()}
    found = {name: tuple(value.shape) for name, value in saved.items()}
    if found != expected:
        differing = sorted(set(found) ^ set(expected)) or sorted(n for n in expected if found[n] != expected[n])
        raise CheckpointError(f"{path}: model parameters do not fit this model ({', '.join(differing[:3])})")


def _remove_stale_temporaries(path: Path) -> None:
    # A process killed inside `atomic_torch_save` leaves its temporary sibling behind; only one run trains into a
    # checkpoint directory at a time, so every temporary found at the start of a run is such a leftover.
    for temporary in path.parent.glob(f".{path.name}.*.tmp"):
        temporary.unlink(missing_ok=True)


def resume_training_state(
    path: Path,
    metadata: dict[str, Any],
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: torch.optim.lr_scheduler.LRScheduler | None,
    on_epoch_end: Callable[[int, dict[str, float]], None] | None = None,
) -> tuple[int, list[dict[str, float]]]:
    """Continue from the training state at `path` if it was written by a run of the same setup.

    A matching state restores model (strictly), optimizer, scheduler and RNG states, and every stored epoch's
    metrics are passed to `on_epoch_end` again, so a resumed run reports every epoch (a finished run reports them
    all and trains no further). A state of another setup is ignored (and later overwritten); a state that cannot be
    used is deleted. Both cases log one warning naming the file, and leave model, optimizer and RNGs untouched, so
    that training starts over exactly as a fresh run.

    Args:
        path: the training state file; need not exist.
        metadata: the new run's metadata, compared with the stored one.
        model: restored in place.
        optimizer: restored in place.
        scheduler: restored in place, or None.
        on_epoch_end: called as `on_epoch_end(epoch, metrics)` for each stored epoch (0-based).

    Returns:
        The number of completed epochs (0 = start over) and their metrics.
    """
    path = Path(path)
    _remove_stale_temporaries(path)
    if not path.exists():
        return 0, []
    try:
        payload = read_training_state(path)
        stored = payload["metadata"]
        if stored != metadata:
            differing = sorted(key for key in {*metadata, *stored} if metadata.get(key) != stored.get(key))
            logger.warning(
                "ignoring %s: it was written for another setup (different %s); training starts over",
                path,
                ", ".join(differing),
            )
            return 0, []
        _check_model_state(path, payload["model"], model)
        if (payload["scheduler"] is None) != (scheduler is None):
            raise CheckpointError(f"{path}: scheduler state {'missing' if scheduler else 'unexpected'}")
        try:
            # The optimizer validates the saved parameter groups before it changes anything.
            optimizer.load_state_dict(payload["optimizer"])
        except ValueError as error:
            raise CheckpointError(f"{path}: optimizer state does not fit ({one_line(error)})") from error
    except CheckpointError as error:
        logger.warning("discarding training state %s; training starts over", error)
        path.unlink(missing_ok=True)
        return 0, []
    if scheduler is not None:
        scheduler.load_state_dict(payload["scheduler"])
    model.load_state_dict(payload["model"], strict=True)
    _restore_rng_states(payload["rng"])
    history = list(payload["history"])
    if on_epoch_end is not None:
        for epoch, metrics in enumerate(history):
            on_epoch_end(epoch, metrics)
    return int(payload["epoch"]), history
