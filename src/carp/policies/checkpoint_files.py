"""Reading a policy checkpoint file into a policy, with every problem as one `CheckpointError` line naming the file.

The rebuilding is the caller's: `carp.policies.registry.load_policy` dispatches on the family a checkpoint names, a
family's own `load` rebuilds its own kind. Neither this module nor the families need the registry to read a file.
"""

from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from carp.policies.base import Policy
from carp.training.checkpoint import CheckpointError, one_line, read_checkpoint


def read_policy(
    path: Path, rebuild: Callable[[dict[str, Any]], Policy], map_location: str | torch.device = "cpu"
) -> Policy:
    """The policy `rebuild` makes of the checkpoint at `path`, in evaluation mode on `map_location`.

    Raises:
        FileNotFoundError: no file at `path`.
        CheckpointError: the file is truncated or corrupt, or `rebuild` finds it of another format version or family,
            incomplete, or with parts that do not fit together; the message is one line that starts with `path`.
    """
    checkpoint = read_checkpoint(Path(path), weights_only=True)
    try:
        # A checkpoint is read for inference: every module in evaluation mode, so the camera crops are centred.
        return rebuild(checkpoint).train(False).to(map_location)
    except KeyError as error:
        raise CheckpointError(f"{path}: policy checkpoint lacks the entry {error}") from error
    except (AttributeError, RuntimeError, TypeError, ValueError) as error:
        raise CheckpointError(f"{path}: {one_line(error)}") from error
