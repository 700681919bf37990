"""Typed configuration shared by every process: strict models, YAML files, one-line errors.

Every model forbids unknown keys, so a misspelt key in a YAML file is an error rather than a silently
ignored setting. `load_yaml` turns a file into a model and reports the first bad field together with the
file it came from, in one line a user can act on.

Every YAML file of the project (settings, scenarios, inventories, the launcher's own files) is read by
`read_yaml`, and every YAML text by `parse_yaml`, which bound what a file may cost before any of it is
used: a file larger than `MAX_YAML_BYTES` (1 MB; the largest file in configs/ is a few kB) is refused
before it is read, and a document whose aliases would expand it beyond `MAX_YAML_NODES` nodes (an alias
"bomb": a few hundred bytes that expand to billions of values in whatever walks the result) is refused
once composed, before anything is built from it; so is an alias that refers to itself. Each refusal is
one ConfigError naming the file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, TypeVar

import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, ValidationInfo

MAX_YAML_BYTES = 1_000_000     # a YAML file larger than this is refused before it is read
MAX_YAML_NODES = 200_000       # nor may its aliases expand it beyond this many nodes (scalars, lists, maps)

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
    named = first.get("ctx", {}).get("error")
    if isinstance(named, ConfigError):
        return str(named)   # a file named inside this one (InlineOrFile): its own line says where
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


def parse_mapping(model: type[M], data: object, source: str, folder: str | Path | None = None) -> M:
    """Validate an already-loaded mapping; `source` names where it came from in error messages, and a file
    it names (`InlineOrFile`) is found relative to `folder` (None: the working directory)."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping of keys to values, got {type(data).__name__}")
    try:
        return model.model_validate(data, context={"folder": folder})
    except ValidationError as error:
        raise ConfigError(describe_validation_error(error, source)) from None


def named_file(value: str | Path, folder: str | Path | None) -> Path:
    """The file a configuration names: as given if absolute, else relative to `folder` (the folder of the file
    that names it; None: the working directory)."""
    path = Path(value).expanduser()
    return path if path.is_absolute() or folder is None else Path(folder) / path


def InlineOrFile(model: type[BaseModel]) -> BeforeValidator:  # noqa: N802  (used as a type annotation)
    """For a field of type `model` (`Annotated[model, InlineOrFile(model)]`): the value is `model` inline, or the
    name of a YAML file of the same shape, read and checked as `model` (a fault in it is told in its own name)."""
    def read(value: object, info: ValidationInfo) -> object:
        if not isinstance(value, (str, Path)):
            return value
        return load_yaml(model, named_file(value, (info.context or {}).get("folder")))
    return BeforeValidator(read)


class _BoundedLoader(yaml.SafeLoader):
    """PyYAML's safe loader that refuses a document whose aliases expand it beyond `max_nodes` nodes.

    An alias is one node in the text but stands for the whole of what it refers to: `safe_load` shares it,
    but anything that walks the result (validation, a merge, a dump) walks it in full. The count is the
    document's size with every alias expanded, computed on the composed node graph (each node's size once,
    so the bomb itself costs nothing to measure), before a single value is constructed."""

    max_nodes = MAX_YAML_NODES

    def compose_document(self):
        node = super().compose_document()
        expanded_size(node, self.max_nodes)
        return node


class YamlTooLarge(yaml.YAMLError):
    """A YAML document beyond what the loader accepts; the message says why."""


def expanded_size(root, limit: int) -> int:
    """Nodes of the composed document `root` with every alias expanded; YamlTooLarge past `limit` or on a
    node that contains itself (a recursive alias)."""
    sizes: dict[int, int] = {}
    # Iterative post-order walk: a deep document must not hit Python's recursion limit.
    stack: list[tuple[object, bool]] = [(root, False)]
    open_nodes: set[int] = set()
    while stack:
        node, children_done = stack.pop()
        ident = id(node)
        if children_done:
            open_nodes.discard(ident)
            children = _children(node)
            size = 1 + sum(sizes[id(child)] for child in children)
            if size > limit:
                raise YamlTooLarge(f"its aliases expand it beyond {limit:,} values (an alias bomb?)")
            sizes[ident] = size
            continue
        if ident in sizes:
            continue
        if ident in open_nodes:
            raise YamlTooLarge("an alias refers to a node that contains it (a recursive alias)")
        open_nodes.add(ident)
        stack.append((node, True))
        stack.extend((child, False) for child in _children(node) if id(child) not in sizes)
    return sizes[id(root)]


def _children(node) -> list:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [part for pair in node.value for part in pair]
    return []


def parse_yaml(text: str, source: str) -> object:
    """The parsed content of YAML `text` (bounded as the module docstring says), or ConfigError naming
    `source` (and the line) on any problem."""
    try:
        return yaml.load(text, Loader=_BoundedLoader)  # noqa: S506  (a SafeLoader)
    except YamlTooLarge as error:
        raise ConfigError(f"{source}: refused: {error}") from None
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f" line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise ConfigError(f"{source}:{where} not valid YAML: {getattr(error, 'problem', error)}") from None
    except RecursionError:
        raise ConfigError(f"{source}: refused: nested too deeply") from None


def read_yaml(path: str | Path, max_bytes: int = MAX_YAML_BYTES) -> object:
    """The parsed content of a YAML file, or ConfigError naming the file (and line) on any problem. A file
    larger than `max_bytes` is refused before it is read."""
    path = Path(path)
    try:
        with path.open("rb") as handle:
            data = handle.read(max_bytes + 1)   # a file that grows while read is bounded all the same
    except OSError as error:
        raise ConfigError(f"{path}: cannot read: {error.strerror or error}") from None
    if len(data) > max_bytes:
        raise ConfigError(f"{path}: refused: larger than {max_bytes:,} bytes (the limit for a YAML file)")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise ConfigError(f"{path}: not UTF-8 text ({error.reason} at byte {error.start})") from None
    return parse_yaml(text, str(path))


def load_yaml(model: type[M], path: str | Path) -> M:
    """Read a YAML file into `model`, raising ConfigError with the file and field on any problem; a file it
    names is found relative to its folder."""
    return parse_mapping(model, read_yaml(path), str(path), Path(path).parent)


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
    mapping whose tag, `kind` or `name`, changes (a log-normal noise model shares no field with a mixture, nor
    the MCKF's parameters with raw_range's)."""
    merged = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict) and all(
                value.get(tag, merged[key].get(tag)) == merged[key].get(tag) for tag in ("kind", "name")):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged
