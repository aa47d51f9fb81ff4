"""Family name -> its params sections: the light half of the family table, which loading the params needs.

Each family's folder has a `config` module with its params sections (a config class and an inference class); this
table names it, one line per family, and imports it on first use. It never imports a family's model code: the other
half of the table, `carp.policies.registry.FAMILY_MODULES`, names the modules that build, train and load policies, so
that validating a params file stays below the policies, the training loop and torch.
"""

import importlib
from typing import Any

SECTION_MODULES = {
    "carp": "carp.policies.carp.config:SECTIONS",
    "diffusion_unet": "carp.policies.diffusion.config:UNET_SECTIONS",
    "diffusion_transformer": "carp.policies.diffusion.config:TRANSFORMER_SECTIONS",
    "next_token": "carp.policies.next_token.config:SECTIONS",
    "vq_bet": "carp.policies.vq_bet.config:SECTIONS",
    "edm_unet": "carp.policies.consistency.config:TEACHER_SECTIONS",
    "consistency_policy": "carp.policies.consistency.config:STUDENT_SECTIONS",
}
"""Registry name -> `module:attribute` of the family's (config class, inference class)."""

_registered: dict[str, tuple[type, type]] = {}


def family_names() -> tuple[str, ...]:
    """Registered family names, built-in ones first."""
    return tuple(SECTION_MODULES) + tuple(name for name in _registered if name not in SECTION_MODULES)


def get_sections(name: str) -> tuple[type, type]:
    """(config class, inference class) of family `name`, without importing its model code.

    Raises:
        KeyError: no such family; the message lists the known ones.
    """
    if name in _registered:
        return _registered[name]
    if name not in SECTION_MODULES:
        raise KeyError(f"unknown policy family {name!r} (known: {', '.join(family_names())})")
    return module_attribute(SECTION_MODULES[name])


def family_sections() -> dict[str, tuple[type, type]]:
    """Registered family -> (config class of its section, class of its `inference.<family>` section)."""
    return {name: get_sections(name) for name in family_names()}


def teacher_of(name: str) -> str | None:
    """The family whose trained policy family `name` distils (its config class's `TEACHER`), or None."""
    return getattr(get_sections(name)[0], "TEACHER", None)


def register_sections(name: str, config_class: type, inference_class: type) -> None:
    """Add the sections of a family defined outside `SECTION_MODULES` (`carp.policies.registry.register_family`)."""
    _registered[name] = (config_class, inference_class)


def unregister_sections(name: str) -> None:
    """Forget the sections added by :func:`register_sections` (built-in families stay)."""
    if name not in SECTION_MODULES:
        _registered.pop(name, None)


def module_attribute(path: str) -> Any:
    """The attribute a `module:attribute` path names, its module imported."""
    module, attribute = path.split(":")
    return getattr(importlib.import_module(module), attribute)
