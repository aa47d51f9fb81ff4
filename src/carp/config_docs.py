"""The params reference page (``docs/params.md``), generated from the docstrings of the config dataclasses.

Each section of :mod:`carp.config` documents every one of its fields in its Google-style ``Attributes:`` section:
meaning, unit, range and the constraints the field takes part in. This module reads those sections and renders one
Markdown page with every key of ``params.yaml``, its type and default; ``tools/params_docs.py`` writes or checks the
page (``make docs``, ``make lint``), and a test keeps every field documented and the committed page current.
"""

import dataclasses
import inspect
import re
import types
import typing
from typing import Any

import yaml

from carp.config import Params

_ENTRY = re.compile(r"^(\w+):\s*(.*)$")


def field_descriptions(cls: type) -> dict[str, str]:
    """Field name -> description from the ``Attributes:`` section of a dataclass's docstring (empty if none).

    Entries are indented one level below ``Attributes:`` (``name: text``); deeper-indented lines continue the
    entry before them; the section ends at the first line indented no deeper than ``Attributes:`` itself.
    """
    lines = inspect.cleandoc(cls.__doc__ or "").splitlines()
    descriptions: dict[str, str] = {}
    try:
        start = next(index for index, line in enumerate(lines) if line.strip() == "Attributes:")
    except StopIteration:
        return descriptions
    section_indent = _indent(lines[start])
    entry_indent = None
    current = None
    for line in lines[start + 1 :]:
        if not line.strip():
            continue
        indent = _indent(line)
        if indent <= section_indent:
            break
        entry_indent = indent if entry_indent is None else entry_indent
        match = _ENTRY.match(line.strip())
        if indent == entry_indent and match:
            current = match.group(1)
            descriptions[current] = match.group(2)
        elif current is not None:
            descriptions[current] = f"{descriptions[current]} {line.strip()}".strip()
    return descriptions


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip())


def config_sections(root: type = Params) -> list[tuple[str, type]]:
    """(dotted prefix, dataclass) of `root` and of every section dataclass below it, in field order."""
    sections = [("", root)]
    hints = typing.get_type_hints(root)
    for field in dataclasses.fields(root):
        if dataclasses.is_dataclass(hints[field.name]):
            sections.extend((f"{field.name}.{prefix}", cls) for prefix, cls in config_sections(hints[field.name]))
    return sections


def documentation_problems(root: type = Params) -> list[str]:
    """Dotted keys of fields without a description, and descriptions that name no field; empty when all is well."""
    problems = []
    for prefix, cls in config_sections(root):
        descriptions = field_descriptions(cls)
        names = [field.name for field in dataclasses.fields(cls)]
        problems += [
            f"{prefix}{name}: no description in {cls.__name__}'s docstring"
            for name in names
            if not descriptions.get(name)
        ]
        problems += [
            f"{prefix}{name}: described in {cls.__name__}'s docstring but not a field of it"
            for name in descriptions
            if name not in names
        ]
    return problems


def params_reference(root: type = Params) -> str:
    """The Markdown page documenting every key of ``params.yaml``.

    Raises:
        ValueError: a field has no description (the message lists every such key).
    """
    problems = documentation_problems(root)
    if problems:
        raise ValueError("undocumented params:\n" + "\n".join(problems))
    lines = [
        "# Parameters",
        "",
        "<!-- Generated from the docstrings of src/carp/config.py by `make docs`; edit those, not this page. -->",
        "",
        "Every key of `params.yaml`, with its type and default. The params are validated when a stage loads them:",
        "an unknown key, a wrong type or a broken constraint stops the stage with one line that names the key, the",
        "value and the rule, e.g. `error: params.yaml: codebook_size=1: must be >= 2`.",
    ]
    defaults = _defaults(root())
    for prefix, cls in config_sections(root):
        descriptions = field_descriptions(cls)
        hints = typing.get_type_hints(cls)
        title = f"`{prefix.rstrip('.')}`" if prefix else "Top level"
        summary = inspect.cleandoc(cls.__doc__ or "").splitlines()[0]
        lines += ["", f"## {title}", "", summary, ""]
        for field in dataclasses.fields(cls):
            key = f"{prefix}{field.name}"
            if dataclasses.is_dataclass(hints[field.name]):
                lines.append(f"- `{key}`: {descriptions[field.name]} See [`{key}`](#{key}).")
                continue
            kind, default = _type_name(hints[field.name]), _yaml_value(defaults[key])
            lines.append(f"- `{key}` ({kind}, default `{default}`): {descriptions[field.name]}")
    # The docstrings quote code reStructuredText-style (``x``); Markdown takes single backticks.
    return "\n".join(lines).replace("``", "`") + "\n"


def _defaults(params: Any, prefix: str = "") -> dict[str, Any]:
    values = {}
    for field in dataclasses.fields(params):
        value = getattr(params, field.name)
        if dataclasses.is_dataclass(value):
            values.update(_defaults(value, f"{prefix}{field.name}."))
        else:
            values[f"{prefix}{field.name}"] = value
    return values


def _type_name(hint: Any) -> str:
    origin, arguments = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        inner = [argument for argument in arguments if argument is not type(None)]
        return f"{_type_name(inner[0])} or null"
    if origin is tuple:
        return f"list of {_plural(_type_name(arguments[0]))}"
    if origin is dict:
        return f"mapping of task to {_type_name(arguments[1])}"
    return {int: "integer", float: "number", str: "string", bool: "true or false"}[hint]


def _plural(name: str) -> str:
    return name.replace("list of", "lists of", 1) if name.startswith("list of") else f"{name}s"


def _yaml_value(value: Any) -> str:
    text = yaml.safe_dump(_plain(value), default_flow_style=True, sort_keys=False, width=1000)
    return text.strip().removesuffix("...").strip()  # a scalar's document ends with "..."


def _plain(value: Any) -> Any:
    if isinstance(value, tuple | list):
        return [_plain(item) for item in value]
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    return value
