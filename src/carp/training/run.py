"""What a family's `train` gets besides its own params section: `TrainingRun`, the context of one training run.

Beside the loop it hands the family to: the data, the shared loop's settings, where the resumable state lives, the
epoch callback and a distilled family's teacher.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from carp.policies.base import Policy

if TYPE_CHECKING:
    import torch


@dataclass(frozen=True)
class TrainingRun:
    """What a family's `train` gets besides its own params section.

    The data, the shared loop's settings, where the resumable state lives, and the epoch callback.

    Attributes:
        training: the shared loop settings (`carp.config.TrainingConfig`).
        context: the data's shapes, normalizers and tokenizer (`carp.policies.context.PolicyContext`); its metadata
            goes into the checkpoint.
        data: normalized windows (`carp.training.loop.PolicyTrainingData`).
        checkpoint_dir: where the resumable training state lives.
        device: training device ("auto", "cpu", "cuda", ...).
        epochs: passes over the windows; None takes `training.epochs`.
        on_epoch_end: called as `on_epoch_end(epoch, metrics)` after every epoch (0-based); `metrics` has at least
            `loss` and `epoch_seconds`.
        teacher: the trained policy of the family's `teacher` family; None for other families.
    """

    training: Any
    context: Any
    data: Any
    checkpoint_dir: Path
    device: str | torch.device = "cpu"
    epochs: int | None = None
    on_epoch_end: Callable[[int, dict[str, float]], None] | None = None
    teacher: Policy | None = None

    def train_with_loss(
        self,
        policy: Policy,
        recipe: Any,
        identity: dict[str, Any],
        prepare_data: Callable[[Any], Any] | None = None,
        training_step: Callable[[dict[str, Any]], Any] | None = None,
    ) -> Policy:
        """Train `policy` in the shared resumable loop (`carp.training.loop.train_with_loss`).

        Args:
            policy: the freshly built policy.
            recipe: its optimizer (`carp.training.loop.OptimizerRecipe`).
            identity: plain values that must match for a saved state to be resumed (family, config, shapes); the
                observation kind and camera encoder settings, and a multi-task policy's tasks, are added here for
                every family.
            prepare_data: the family's one-time derivation from the windows (e.g. their token targets), or None.
            training_step: the family's loss and metric sums of a batch; None trains on `policy.training_loss`.
        """
        from carp.training.loop import check_task_ids, train_with_loss

        check_task_ids(self.data, self.context.num_tasks)
        encoder = self.context.image_encoder
        observations = {"image_encoder": None if encoder is None else dataclasses.asdict(encoder)}
        tasks = self.context.tasks
        if tasks is not None:
            # The task order fixes the ids; the statistics are part of the windows' digest already.
            observations["tasks"] = {"names": list(tasks.names), "embedding_dim": tasks.embedding_dim}
        return train_with_loss(
            policy,
            self,
            recipe,
            identity | {"observations": observations},
            prepare_data=prepare_data,
            training_step=training_step,
        )
