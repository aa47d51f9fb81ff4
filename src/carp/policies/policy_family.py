"""What a policy family is to the rest of carp: `PolicyFamily`, the object each family's `family` module defines.

Apart from the registry, which names every family's module, so that the families can define themselves without
importing the table that imports them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from carp.policies.base import Policy


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

    @property
    def tokenizer_kinds(self) -> tuple[str, ...] | None:
        """The tokenizer kinds whose tokens the family's policy predicts, or None for a family that declares none.

        Declared by the config class's `TOKENIZER_KINDS` (checked when the params load); a family that declares
        none trains beside carp_msvq's tokenizer only.
        """
        return getattr(self.config_class, "TOKENIZER_KINDS", None)
