"""Family name -> its config, model builder and loader, and `load_policy`, which dispatches on `policy_type`.

Each family's folder has a `config` module with its params sections and a `family` module that defines its
:class:`PolicyFamily` (the two Diffusion Policy families share one folder). The table below names the `family`
modules, one line per family; `carp.policies.sections` names the `config` modules, so that loading the params imports
only those, never torch or the models. Both import on first use. `family_names` and `get_sections` are the sections
table's, kept here for the callers that use the registry alone.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from carp.policies.base import POLICY_FORMAT_VERSION, Policy
from carp.policies.sections import (
    family_names,
    module_attribute,
    register_sections,
    unregister_sections,
)
from carp.policies.sections import get_sections as get_sections  # the registry's callers look sections up here too

if TYPE_CHECKING:
    import torch

FAMILY_MODULES = {
    "carp": "carp.policies.carp.family:FAMILY",
    "diffusion_unet": "carp.policies.diffusion.family:UNET_FAMILY",
    "diffusion_transformer": "carp.policies.diffusion.family:TRANSFORMER_FAMILY",
    "next_token": "carp.policies.next_token.family:FAMILY",
    "vq_bet": "carp.policies.vq_bet.family:FAMILY",
    "edm_unet": "carp.policies.consistency.family:TEACHER_FAMILY",
    "consistency_policy": "carp.policies.consistency.family:STUDENT_FAMILY",
}
"""One entry per family: registry name -> `module:attribute` of its :class:`PolicyFamily`. The family's params
sections are the other half of the table (`carp.policies.sections.SECTION_MODULES`), under the same names."""

_registered: dict[str, PolicyFamily] = {}


@dataclass(frozen=True)
class PolicyFamily:
    """A policy family as the rest of carp sees it.

    Attributes:
        name: registry name, stored as `policy_type` in every checkpoint and used as the params section name.
        config_class: frozen dataclass of the family's params section `<name>` (its model and optimizer).
        inference_class: frozen dataclass of the `inference.<name>` section, read by evaluation only; its
            `settings_for(task)` gives the keyword arguments of the policy's `configure_inference`.
        build: `build(config, context)` -> an untrained :class:`~carp.policies.base.Policy` sized by `config` and
            by a :class:`~carp.policies.context.PolicyContext` (the data's shapes, normalizers, tokenizer).
        from_checkpoint: rebuilds a policy from a checkpoint dict, loading weights strictly; raises KeyError,
            ValueError, RuntimeError or TypeError on a checkpoint that does not fit.
        train: `train(config, run)` -> the trained policy in eval mode, given a :class:`TrainingRun`: builds the
            policy and runs the resumable loop on it (the shared loop, through :meth:`TrainingRun.train_with_loss`);
            see :func:`train_policy`.
    """

    name: str
    config_class: type
    inference_class: type
    build: Callable[..., Policy]
    from_checkpoint: Callable[[dict[str, Any]], Policy]
    train: Callable[..., Policy]

    @property
    def teacher(self) -> str | None:
        """The family whose trained policy this family's training distils, or None.

        Declared by the config class's `TEACHER` (the params section trained first); given to `train` as
        :attr:`TrainingRun.teacher`. None for a family trained from the data alone.
        """
        return getattr(self.config_class, "TEACHER", None)


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
            self.data,
            recipe,
            self.training,
            self.checkpoint_dir,
            identity | {"observations": observations},
            self.epochs,
            self.device,
            self.on_epoch_end,
            prepare_data=prepare_data,
            training_step=training_step,
        )


def get_family(name: str) -> PolicyFamily:
    """The family registered under `name`.

    Raises:
        KeyError: no such family; the message lists the known ones.
    """
    if name in _registered:
        return _registered[name]
    if name not in FAMILY_MODULES:
        raise KeyError(f"unknown policy family {name!r} (known: {', '.join(family_names())})")
    family = module_attribute(FAMILY_MODULES[name])
    _registered[name] = family
    return family


def register_family(family: PolicyFamily) -> None:
    """Add a family defined outside `FAMILY_MODULES` (e.g. in a test); re-registering a name replaces it."""
    _registered[family.name] = family
    register_sections(family.name, family.config_class, family.inference_class)


def build_policy(name: str, config: Any, context: Any) -> Policy:
    """An untrained policy of family `name`, sized by its `config` and a `carp.policies.context.PolicyContext`."""
    return get_family(name).build(config, context)


def train_policy(
    name: str,
    config: Any,
    training: Any,
    context: Any,
    data: Any,
    checkpoint_dir: Path,
    device: str | torch.device = "cpu",
    epochs: int | None = None,
    on_epoch_end: Callable[[int, dict[str, float]], None] | None = None,
    teacher: Policy | None = None,
) -> Policy:
    """Train a policy of family `name`, resuming from `checkpoint_dir` when a run of the same setup left a state.

    Args:
        name: registered family.
        config: the family's params section.
        training: see :class:`TrainingRun`, whose fields the remaining arguments are.
        context: see :class:`TrainingRun`.
        data: see :class:`TrainingRun`.
        checkpoint_dir: see :class:`TrainingRun`.
        device: see :class:`TrainingRun`.
        epochs: see :class:`TrainingRun`.
        on_epoch_end: see :class:`TrainingRun`.
        teacher: see :class:`TrainingRun`; required by a family that declares a `teacher`.

    Returns:
        The trained policy in eval mode on the CPU.
    """
    run = TrainingRun(training, context, data, Path(checkpoint_dir), device, epochs, on_epoch_end, teacher)
    return get_family(name).train(config, run).to("cpu").train(False)


def unregister_family(name: str) -> None:
    """Forget a family added by :func:`register_family` (built-in families stay)."""
    if name not in FAMILY_MODULES:
        _registered.pop(name, None)
        unregister_sections(name)


def policy_from_checkpoint(checkpoint: Any) -> Policy:
    """Rebuild the policy a checkpoint dict holds, through the family named by its `policy_type`, in eval mode.

    Raises:
        ValueError: not a dict, another format version, or an unknown `policy_type`.
        KeyError, RuntimeError, TypeError: raised by the family's loader for a checkpoint that does not fit.
    """
    version = checkpoint.get("format_version") if isinstance(checkpoint, dict) else None
    if version != POLICY_FORMAT_VERSION:
        raise ValueError(
            f"policy checkpoint has format_version {version!r}, this code reads version {POLICY_FORMAT_VERSION}"
        )
    policy_type = checkpoint.get("policy_type")
    try:
        family = get_family(policy_type)
    except KeyError as error:
        raise ValueError(f"policy_type={policy_type!r}: {error.args[0]}") from None
    # A checkpoint is read for inference: every module in evaluation mode, so the camera crops are centred.
    return family.from_checkpoint(checkpoint).train(False)


def load_policy(path: Path, map_location: str | torch.device = "cpu") -> Policy:
    """Read any family's checkpoint onto `map_location`.

    Raises:
        FileNotFoundError: no file at `path`.
        CheckpointError: the file is truncated or corrupt, of another format version, of an unknown family,
            incomplete, or its parts do not fit together; the message is one line that starts with `path`.
    """
    from carp.training.checkpoint import CheckpointError, one_line, read_checkpoint

    checkpoint = read_checkpoint(Path(path), weights_only=True)
    try:
        return policy_from_checkpoint(checkpoint).to(map_location)
    except KeyError as error:
        raise CheckpointError(f"{path}: policy checkpoint lacks the entry {error}") from error
    except (AttributeError, RuntimeError, TypeError, ValueError) as error:
        raise CheckpointError(f"{path}: {one_line(error)}") from error


def average_policies(paths: Sequence[Path]) -> Policy:
    """One policy whose weights are the mean of the checkpoints' at `paths` (checkpoint averaging).

    The checkpoints must be snapshots of one training run: the same family and shapes. Floating-point weights and
    buffers are averaged (in float64, then cast back); other entries (index tables, counters) must be equal. The
    policy's metadata is the first checkpoint's.

    Raises:
        ValueError: no path, or checkpoints whose entries do not match.
        CheckpointError: a checkpoint cannot be read (see `load_policy`).
    """
    import torch

    if not paths:
        raise ValueError("there is no checkpoint to average")
    policies = [load_policy(path) for path in paths]
    first = policies[0]
    states = [policy.state_dict() for policy in policies]
    averaged = {}
    for name, value in states[0].items():
        values = []
        for path, state in zip(paths, states, strict=True):
            other = state.get(name)
            if other is None or other.shape != value.shape or other.dtype != value.dtype:
                raise ValueError(f"{path}: entry {name!r} does not match {paths[0]}'s; average snapshots of one run")
            values.append(other)
        if value.is_floating_point():
            averaged[name] = torch.stack([other.double() for other in values]).mean(dim=0).to(value.dtype)
        elif any(not torch.equal(other, value) for other in values[1:]):
            raise ValueError(f"entry {name!r} differs between the checkpoints; only floating-point weights average")
        else:
            averaged[name] = value
    first.load_state_dict(averaged)
    return first
