"""The rules every params section checks with, and the named choices of its fields.

A leaf of the configuration: the policy families' own sections import these checks too.
"""

import re
from typing import Any

CONTROLLERS = ("absolute", "delta")
EVAL_BACKENDS = ("onnxruntime", "torch")
TRAINING_PRECISIONS = ("auto", "float32", "bfloat16")
OBSERVATION_KINDS = ("state", "image")
SELECTION_RULES = ("final", "best_validation", "lowest_loss", "average_last")
SWEEP_PRUNERS = ("successive_halving", "hyperband", "none")
SET_BY_PIPELINE = "set_by_pipeline"
"""Field metadata of a setting that the pipeline derives for each run and that ``params.yaml`` must not hold."""
REGISTRY_URI_PREFIX = "models:/"
# robomimic names a camera's images obs/<camera>_image (as carp.data.robomimic_schema does).
IMAGE_KEY_SUFFIX = "_image"


class ConfigError(ValueError):
    """A params file that does not match the schema or breaks a constraint."""


def _require(condition: bool, key: str, value: Any, constraint: str) -> None:
    if not condition:
        raise ConfigError(f"{key}={value!r}: {constraint}")


def require_registry_alias(key: str, alias: Any) -> None:
    """Refuse at `key` an alias the MLflow registry would refuse or reserve (the one rule for every alias carp sets).

    An alias is letters, digits, ``_`` and ``-`` (MLflow's characters), not ``latest`` in any case (MLflow's moving
    pointer), not ``v<digits>`` (MLflow's version aliases) and not starting with a digit (a version number).
    """
    _require(isinstance(alias, str) and bool(alias), key, alias, "must be set")
    _require(
        re.fullmatch(r"[\w-]+", alias) is not None,
        key,
        alias,
        "may only contain letters, digits, '_' and '-' (the MLflow registry's alias characters)",
    )
    _require(
        alias.lower() != "latest" and not alias[:1].isdigit() and re.fullmatch(r"[vV]\d+", alias) is None,
        key,
        alias,
        "'latest', 'v<digits>' and names starting with a digit are reserved by the MLflow registry",
    )


def require_positive_int(key: str, value: Any) -> None:
    """Refuse anything but an integer >= 1 at `key` (a bool or a whole float such as 8.0 included)."""
    _require(
        isinstance(value, int) and not isinstance(value, bool) and value >= 1, key, value, "must be an integer >= 1"
    )


def require_bool(key: str, value: Any) -> None:
    """Refuse anything but true or false at `key` (a 0 or 1 included)."""
    _require(isinstance(value, bool), key, value, "must be true or false")


def require_optimizer_settings(section: str, config: Any) -> None:
    """Check the optimizer fields every policy family's section has, naming them under `section`.

    Args:
        section: the params section, e.g. `carp` or `diffusion_unet`.
        config: a family config with `learning_rate`, `weight_decay`, `warmup_steps` and `use_ema`.
    """
    _require(config.learning_rate > 0, f"{section}.learning_rate", config.learning_rate, "must be > 0")
    _require(config.weight_decay >= 0, f"{section}.weight_decay", config.weight_decay, "must be >= 0")
    _require(
        isinstance(config.warmup_steps, int) and not isinstance(config.warmup_steps, bool) and config.warmup_steps >= 0,
        f"{section}.warmup_steps",
        config.warmup_steps,
        "must be an integer >= 0",
    )
    require_bool(f"{section}.use_ema", config.use_ema)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _distinct_paths(key: str, paths: Any) -> tuple[str, ...]:
    """`paths` as a tuple, refused at `key` unless every entry is a non-empty string named once."""
    listed = list(paths)
    _require(all(isinstance(path, str) and path for path in listed), key, listed, "must be non-empty paths")
    _require(len(set(listed)) == len(listed), key, listed, "must name each once")
    return tuple(listed)


def _positive_training_fields(section: Any, name: str) -> None:
    _require(section.epochs >= 1, f"{name}.epochs", section.epochs, "must be >= 1")
    _require(section.batch_size >= 1, f"{name}.batch_size", section.batch_size, "must be >= 1")
    _require(section.learning_rate > 0, f"{name}.learning_rate", section.learning_rate, "must be > 0")
    _require(section.weight_decay >= 0, f"{name}.weight_decay", section.weight_decay, "must be >= 0")
    _require(section.checkpoint_every >= 1, f"{name}.checkpoint_every", section.checkpoint_every, "must be >= 1")
