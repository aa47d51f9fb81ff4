"""Family name -> its config, model builder and loader, and `load_policy`, which dispatches on `policy_type`.

Each family's folder has a `config` module with its params sections and a `family` module that defines its
:class:`PolicyFamily` (the two Diffusion Policy families share one folder). The table below names the `family`
modules, one line per family; `carp.policies.sections` names the `config` modules, so that loading the params imports
only those, never torch or the models. Both import on first use. `family_names` and `get_sections` are the sections
table's, kept here for the callers that use the registry alone.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from carp.policies.base import POLICY_FORMAT_VERSION, Policy
from carp.policies.policy_family import PolicyFamily
from carp.policies.sections import (
    family_names,
    module_attribute,
    register_sections,
    unregister_sections,
)
from carp.policies.sections import get_sections as get_sections  # the registry's callers look sections up here too
from carp.training.run import TrainingRun

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
    """Read any family's checkpoint onto `map_location`, through the family its `policy_type` names.

    Raises:
        FileNotFoundError: no file at `path`.
        CheckpointError: the file is truncated or corrupt, of another format version, of an unknown family,
            incomplete, or its parts do not fit together; the message is one line that starts with `path`.
    """
    from carp.policies.checkpoint_files import read_policy

    return read_policy(Path(path), policy_from_checkpoint, map_location)


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
