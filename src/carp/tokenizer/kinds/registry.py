"""Tokenizer kind name -> the class that implements it, imported on first use; and loading any saved kind.

One line per kind in :data:`KIND_MODULES`; each class implements `carp.tokenizer.kinds.base.ActionTokenizer` and
has a ``load(directory)`` classmethod, and the kinds with a params section (`carp.config.tokenizer_kinds`, the
light half of this table, under the same names) a ``from_config(config, action_dim, action_horizon)`` one.
"""

import importlib
from pathlib import Path
from typing import Any

from carp.tokenizer.artifact import WEIGHTS_FILENAME as ARTIFACT_WEIGHTS_FILENAME
from carp.tokenizer.kinds.base import KIND_FILENAME, ActionTokenizer, read_kind_file

KIND_MODULES = {
    "carp_msvq": "carp.tokenizer.kinds.carp_msvq:CarpMsvqTokenizer",
    "binning": "carp.tokenizer.kinds.binning:BinningTokenizer",
    "fast": "carp.tokenizer.kinds.fast:FastTokenizer",
    "bspline": "carp.tokenizer.kinds.bspline:BSplineTokenizer",
    "fsq": "carp.tokenizer.kinds.fsq:FsqTokenizer",
    "joint_msvq": "carp.tokenizer.kinds.joint_msvq:JointMsvqTokenizer",
    "residual_vq": "carp.tokenizer.kinds.residual_vq:ResidualVqTokenizer",
}
"""Kind name -> `module:attribute` of its tokenizer class."""


def kind_names() -> tuple[str, ...]:
    """The registered kinds, the default (``carp_msvq``) first."""
    return tuple(KIND_MODULES)


def kind_class(kind: str) -> Any:
    """The tokenizer class of ``kind``.

    Raises:
        KeyError: no such kind; the message lists the known ones.
    """
    if kind not in KIND_MODULES:
        raise KeyError(f"unknown tokenizer kind {kind!r} (known: {', '.join(kind_names())})")
    module, attribute = KIND_MODULES[kind].split(":")
    return getattr(importlib.import_module(module), attribute)


def build_tokenizer(kind: str, config: Any, action_dim: int, action_horizon: int) -> ActionTokenizer:
    """An unfitted tokenizer of ``kind`` from its params section (`carp.config.tokenizer_kinds`)."""
    cls = kind_class(kind)
    if not hasattr(cls, "from_config"):
        raise ValueError(f"tokenizer kind {kind!r} is not built from a params section (it is trained by its stage)")
    return cls.from_config(config, action_dim, action_horizon)


def load_tokenizer(directory: Path) -> ActionTokenizer:
    """The tokenizer saved in ``directory``, of the kind its ``kind.json`` names.

    The ``train_tokenizer`` stage's folder (``models/tokenizer/``, `carp.tokenizer.artifact`) holds no ``kind.json``
    and is always a ``carp_msvq`` tokenizer.

    Raises:
        FileNotFoundError: the folder holds neither a kind file nor a tokenizer artifact.
        KeyError: the recorded kind is not registered.
    """
    directory = Path(directory)
    if not (directory / KIND_FILENAME).exists() and (directory / ARTIFACT_WEIGHTS_FILENAME).exists():
        return kind_class("carp_msvq").from_artifact(directory)
    kind, _ = read_kind_file(directory)
    return kind_class(kind).load(directory)
