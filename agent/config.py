"""Typed configuration shared by every process: strict models, YAML files, one-line errors.

Every model forbids unknown keys, so a misspelt key in a YAML file is an error rather than a silently
ignored setting. `load_yaml` turns a file into a model and reports the first bad field together with the
file it came from, in one line a user can act on.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegativeFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]


class StrictModel(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class ConfigError(ValueError):
    """A configuration file could not be turned into parameters; the message says where and why."""


M = TypeVar("M", bound=BaseModel)


def updated(model: M, **changes: object) -> M:
    """A copy of `model` with `changes`, validated like a fresh one (pydantic's model_copy is not)."""
    data = model.model_dump()
    data.update({key: value.model_dump() if isinstance(value, BaseModel) else value
                 for key, value in changes.items()})
    return type(model).model_validate(data)


def describe_validation_error(error: ValidationError, source: str) -> str:
    """One line naming the source, the dotted field path and what is wrong with it."""
    first = error.errors()[0]
    field = ".".join(str(part) for part in first["loc"]) or "<top level>"
    if first["type"] == "extra_forbidden":
        problem = "unknown key"
    else:
        problem = first["msg"]
    more = len(error.errors()) - 1
    suffix = f" (and {more} more problem{'s' if more > 1 else ''})" if more else ""
    shown = first.get("input")
    value = f" (got {shown!r})" if first["type"] != "extra_forbidden" and not isinstance(shown, dict) else ""
    return f"{source}: field '{field}': {problem}{value}{suffix}"


def parse_mapping(model: type[M], data: object, source: str) -> M:
    """Validate an already-loaded mapping; `source` names where it came from in error messages."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping of keys to values, got {type(data).__name__}")
    try:
        return model.model_validate(data)
    except ValidationError as error:
        raise ConfigError(describe_validation_error(error, source)) from None


def read_yaml(path: str | Path) -> object:
    """The parsed content of a YAML file, or ConfigError naming the file (and line) on any problem."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise ConfigError(f"{path}: cannot read: {error.strerror or error}") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f" line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise ConfigError(f"{path}:{where} not valid YAML: {getattr(error, 'problem', error)}") from None


def load_yaml(model: type[M], path: str | Path) -> M:
    """Read a YAML file into `model`, raising ConfigError with the file and field on any problem."""
    return parse_mapping(model, read_yaml(path), str(path))


def yaml_scalar(value: object) -> str:
    """A value as a YAML 1.1 scalar that PyYAML reads back as the same type."""
    if value is None:
        return "null"
    if isinstance(value, float):
        text = repr(value)
        # YAML 1.1 (PyYAML) reads 1e-06 as a string: a float needs a dot before its exponent.
        if "e" in text and "." not in text:
            mantissa, exponent = text.split("e")
            text = f"{mantissa}.0e{exponent}"
        return text
    if isinstance(value, tuple):
        return "[" + ", ".join(yaml_scalar(v) for v in value) + "]"
    return str(value)


def commented_yaml(model: BaseModel, indent: int = 0) -> str:
    """The model as YAML, each field followed by its description as a comment (for showing a config)."""
    lines = []
    for name, info in type(model).model_fields.items():
        value = getattr(model, name)
        pad = "  " * indent
        if isinstance(value, BaseModel):
            lines.append(f"{pad}{name}:")
            lines.append(commented_yaml(value, indent + 1))
        else:
            comment = f"  # {info.description}" if info.description else ""
            lines.append(f"{pad}{name}: {yaml_scalar(value)}{comment}")
    return "\n".join(lines)


def deep_merge(base: dict, override: dict) -> dict:
    """`override` onto `base`, recursing into mappings; lists and values replace, and so does a tagged
    mapping whose `kind` changes (a log-normal noise model shares no field with a mixture)."""
    merged = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict) and value.get(
                "kind", merged[key].get("kind")) == merged[key].get("kind"):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged
