"""Reading a params file into :class:`~carp.config.params.Params`, and writing one back as plain values.

Every problem names the file and the dotted key; unknown keys are errors.
"""

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any

from ruamel.yaml import YAML, YAMLError

from carp.config.checks import SET_BY_PIPELINE, ConfigError
from carp.config.params import FAMILY_SECTIONS, Params
from carp.policies.sections import family_sections


def params_from_dict(raw: dict[str, Any]) -> Params:
    """Build validated :class:`Params` from a parsed YAML mapping.

    Raises:
        ConfigError: unknown key, wrong type or broken constraint; the message names the dotted key.
    """
    return _build(Params, raw, prefix="")


def load_params(path: Path | str = "params.yaml") -> Params:
    """Load and validate a params file.

    Raises:
        ConfigError: the file is missing, is not YAML, or does not validate (message names the file and key).
    """
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: params file not found")
    try:
        raw = _read_yaml(path.read_text()) or {}
    except YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML ({_yaml_problem(error)})") from None
    try:
        return params_from_dict(raw)
    except ConfigError as error:
        raise ConfigError(f"{path}: {error}") from None


def _read_yaml(text: str) -> Any:
    # DVC parses params.yaml with ruamel.yaml's YAML 1.2 safe loader. Reading it with the same loader makes every
    # value mean here what DVC hashed and `dvc exp run -S` wrote: `1e-3` is a float (PyYAML's YAML 1.1 reads a
    # string), `yes` is a string (YAML 1.1: true), and a repeated key is an error (PyYAML keeps the last one).
    return YAML(typ="safe").load(text)


def _yaml_problem(error: YAMLError) -> str:
    problem = getattr(error, "problem", None)
    mark = getattr(error, "problem_mark", None)
    if problem and mark is not None:
        return f"{problem} at line {mark.line + 1}, column {mark.column + 1}"
    return str(error).strip().splitlines()[0]


def params_to_dict(params: Params) -> dict[str, Any]:
    """Plain nested dict (lists instead of tuples) of validated params, shaped as ``params.yaml``.

    Each family's section comes out at the top level under its name, as it is written in the file; settings the
    pipeline sets per run (``training.seed``) are left out, as the file does not hold them.
    """
    values = _plain(dataclasses.asdict(params))
    for section_name, hint in typing.get_type_hints(Params).items():
        if dataclasses.is_dataclass(hint):
            for field_ in dataclasses.fields(hint):
                if field_.metadata.get(SET_BY_PIPELINE):
                    values[section_name].pop(field_.name)
    families = values.pop("families")
    return {**values, **families}


def flatten_params(params: Params) -> dict[str, str]:
    """Dotted-key view (``carp.depth`` -> ``"8"``) for MLflow params."""
    flat: dict[str, str] = {}

    def visit(prefix: str, value: Any) -> None:
        if isinstance(value, dict) and value:
            for key, inner in value.items():
                visit(f"{prefix}.{key}" if prefix else str(key), inner)
        else:
            flat[prefix] = str(value)

    visit("", params_to_dict(params))
    return flat


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {key: _plain(inner) for key, inner in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(inner) for inner in value]
    return value


def _build(cls: type, raw: Any, prefix: str) -> Any:
    section = prefix.rstrip(".") or "params"
    if not isinstance(raw, dict):
        raise ConfigError(f"{section}: expected a mapping, got {type(raw).__name__}")
    hints = typing.get_type_hints(cls)
    dynamic = [f.name for f in dataclasses.fields(cls) if f.metadata.get(FAMILY_SECTIONS)]
    known = {f.name for f in dataclasses.fields(cls) if f.name not in dynamic}
    values = {}
    if dynamic:
        raw, values = _build_family_sections(raw, prefix)
        named = known | set(family_sections()) | {"inference"}
    derived = {f.name for f in dataclasses.fields(cls) if f.metadata.get(SET_BY_PIPELINE)}
    for key in raw:
        if key in derived:
            raise ConfigError(
                f"{prefix}{key}={raw[key]!r}: set by the pipeline for each run, not in params.yaml"
                + (" (training seeds are the top-level list `seeds`, e.g. seeds: [0, 1, 2])" if key == "seed" else "")
            )
        if key not in known:
            names = ", ".join(sorted((named if dynamic else known) - derived))
            raise ConfigError(f"{prefix}{key}: unknown key (known: {names})")
    for name, value in raw.items():
        hint = hints[name]
        key = f"{prefix}{name}"
        if dataclasses.is_dataclass(hint):
            values[name] = _build(hint, value if value is not None else {}, prefix=f"{key}.")
        else:
            values[name] = _coerce(value, hint, key)
    return cls(**values)


def _build_family_sections(raw: dict, prefix: str) -> tuple[dict, dict[str, Any]]:
    """Split the family sections (`<family>:` and `inference: {<family>: ...}`) off `raw` and build them.

    Returns:
        The rest of `raw`, and `{"families": ..., "inference": ...}` with each family's built sections.
    """
    known = family_sections()
    rest = {key: value for key, value in raw.items() if key not in known and key != "inference"}
    families = {
        name: _build(classes[0], raw[name] if raw[name] is not None else {}, f"{prefix}{name}.")
        for name, classes in known.items()
        if name in raw
    }
    inference_raw = raw.get("inference") or {}
    if not isinstance(inference_raw, dict):
        raise ConfigError(f"{prefix}inference: expected a mapping, got {type(inference_raw).__name__}")
    for name in inference_raw:
        if name not in known:
            raise ConfigError(f"{prefix}inference.{name}: unknown policy family (known: {', '.join(known)})")
    inference = {
        name: _build(known[name][1], value if value is not None else {}, f"{prefix}inference.{name}.")
        for name, value in inference_raw.items()
    }
    return rest, {"families": families, "inference": inference}


def _coerce(value: Any, hint: Any, key: str) -> Any:
    origin = typing.get_origin(hint)
    arguments = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in arguments:
            return None
        inner = [argument for argument in arguments if argument is not type(None)]
        return _coerce(value, inner[0], key)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}={value!r}: expected a list")
        element = arguments[0]
        return tuple(_coerce(item, element, key) for item in value)
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{key}={value!r}: expected a mapping")
        key_type, value_type = arguments
        return {
            _coerce(inner_key, key_type, key): _coerce(inner, value_type, f"{key}.{inner_key}")
            for inner_key, inner in value.items()
        }
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}={value!r}: expected true or false")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}={value!r}: expected an integer")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}={value!r}: expected a number")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}={value!r}: expected a string")
        return value
    raise ConfigError(f"{key}: unsupported type {hint}")
