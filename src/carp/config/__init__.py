"""Typed, validated configuration: ``params.yaml`` loads into frozen dataclasses, one per section.

Every problem is reported at load time as a :class:`ConfigError` whose message names the dotted key
(``carp.learning_rate``), the offending value and the constraint. Unknown keys are errors, so a typo in
``dvc exp run -S`` fails loudly instead of silently training with a default.

The library never reads ``params.yaml`` itself: the pipeline scripts call :func:`load_params` and pass the typed
sections to library functions. One module per section (`checks` holds the rules they share, `params` the whole
file); this package re-exports them for the pipeline, tests and users. Modules inside the library import the
section module they need, so that a section never imports the whole params (and, through it, the families'
sections).
"""

from carp.config.checks import (
    CONTROLLERS,
    EVAL_BACKENDS,
    IMAGE_KEY_SUFFIX,
    OBSERVATION_KINDS,
    REGISTRY_URI_PREFIX,
    SELECTION_RULES,
    SET_BY_PIPELINE,
    SWEEP_PRUNERS,
    TRAINING_PRECISIONS,
    ConfigError,
    _require,
    require_optimizer_settings,
    require_positive_int,
    require_registry_alias,
)
from carp.config.data import DataConfig
from carp.config.evaluation import EvalConfig
from carp.config.experiments import ComparisonConfig, StudyConfig, SweepConfig, TrackingConfig
from carp.config.image_encoder import (
    CHANNELS_PER_GROUP,
    LIGHT_BASE_CHANNELS,
    STANDARD_BASE_CHANNELS,
    ImageEncoderConfig,
)
from carp.config.loading import flatten_params, load_params, params_from_dict, params_to_dict
from carp.config.params import FAMILY_SECTIONS, Params
from carp.config.serving import ServingConfig
from carp.config.tokenizer import TokenizerConfig
from carp.config.training import TrainingConfig
from carp.policies.sections import family_sections
from carp.tasks import TASK_NAMES

__all__ = [
    "CHANNELS_PER_GROUP",
    "CONTROLLERS",
    "ComparisonConfig",
    "ServingConfig",
    "ConfigError",
    "DataConfig",
    "EVAL_BACKENDS",
    "EvalConfig",
    "FAMILY_SECTIONS",
    "IMAGE_KEY_SUFFIX",
    "ImageEncoderConfig",
    "LIGHT_BASE_CHANNELS",
    "OBSERVATION_KINDS",
    "Params",
    "REGISTRY_URI_PREFIX",
    "SELECTION_RULES",
    "SET_BY_PIPELINE",
    "STANDARD_BASE_CHANNELS",
    "SWEEP_PRUNERS",
    "StudyConfig",
    "SweepConfig",
    "TASK_NAMES",
    "TRAINING_PRECISIONS",
    "TokenizerConfig",
    "TrackingConfig",
    "TrainingConfig",
    "_require",
    "family_sections",
    "flatten_params",
    "load_params",
    "params_from_dict",
    "params_to_dict",
    "require_optimizer_settings",
    "require_positive_int",
    "require_registry_alias",
]
