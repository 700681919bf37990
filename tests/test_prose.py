"""Prose stays where it belongs: short module docstrings, one-line config field descriptions.

The developers' guide: a module docstring is at most 25 lines (what the module holds and its contract; reasons
and measurements go to docs/), and a config field description fits on one line (at most 110 characters).
Descriptions are read twice: from the source (every `description=` string literal given to a `Field` call,
implicitly concatenated pieces joined as Python joins them) and from the pydantic models themselves (every
model class defined in these packages and reachable from their modules' namespaces, through its bases and
the types of its fields), so a description assembled at run time is caught too.
"""

import ast
import importlib
import inspect
import typing
from pathlib import Path

from pydantic import BaseModel

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("agent", "boat", "sim_bridge", "driver_bridge", "lab", "mission_log", "usv_deploy", "usv_op")
MAX_DOCSTRING_LINES = 25
MAX_DESCRIPTION_CHARS = 110


def _sources():
    for package in PACKAGES:
        yield from sorted((ROOT / package).rglob("*.py"))


def _relative(path):
    return Path(path).resolve().relative_to(ROOT).as_posix()


def _runs_at_import(tree):
    """True for a script module (a bare call or raise at top level): importing it would run it."""
    return any(isinstance(node, ast.Raise)
               or (isinstance(node, ast.Expr) and isinstance(node.value, ast.Call)) for node in tree.body)


def _module_name(path):
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _docstring_offenders():
    offenders = []
    for path in _sources():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        doc = ast.get_docstring(tree)
        if doc is None:
            continue
        lines = len(doc.splitlines())
        if lines > MAX_DOCSTRING_LINES:
            offenders.append(f"{_relative(path)}:{tree.body[0].lineno} module docstring has {lines} lines")
    return offenders


def _literal_description_offenders():
    offenders = []
    for path in _sources():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if not isinstance(node, ast.Call):
                continue
            called = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", None)
            if called != "Field":
                continue
            for keyword in node.keywords:
                value = keyword.value
                # Adjacent literals ("a" "b") are already one Constant in the tree, as Python joins them.
                if keyword.arg != "description" or not isinstance(value, ast.Constant):
                    continue
                if isinstance(value.value, str) and len(value.value) > MAX_DESCRIPTION_CHARS:
                    offenders.append(f"{_relative(path)}:{value.lineno} description has {len(value.value)} "
                                     "characters")
    return offenders


def _models():
    """Every pydantic model class defined in these packages reachable from their modules' namespaces."""
    found, stack = set(), []
    for path in _sources():
        if path.name == "__main__.py" or _runs_at_import(ast.parse(path.read_text(encoding="utf-8"))):
            continue
        module = importlib.import_module(_module_name(path))
        stack.extend(value for value in vars(module).values() if inspect.isclass(value))
    while stack:
        cls = stack.pop()
        if cls in found or not (inspect.isclass(cls) and issubclass(cls, BaseModel)) or cls is BaseModel:
            continue
        found.add(cls)
        stack.extend(cls.__mro__[1:])
        for field in cls.model_fields.values():
            stack.extend(_classes_in(field.annotation))
    return {cls for cls in found if cls.__module__.split(".")[0] in PACKAGES}


def _classes_in(annotation):
    if inspect.isclass(annotation):
        yield annotation
    for argument in typing.get_args(annotation):
        yield from _classes_in(argument)


def _field_line(cls, name):
    path = inspect.getsourcefile(cls)
    start = inspect.getsourcelines(cls)[1]
    tree = ast.parse(Path(path).read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if (isinstance(node, ast.ClassDef) and node.name == cls.__name__
                and node.lineno <= start <= node.end_lineno):
            for statement in node.body:
                if isinstance(statement, ast.AnnAssign) and getattr(statement.target, "id", None) == name:
                    return f"{_relative(path)}:{statement.lineno}"
    return f"{_relative(path)}:{start}"


def _model_description_offenders():
    offenders = set()
    for cls in _models():
        own = cls.__dict__.get("__annotations__", {})
        for name, field in cls.model_fields.items():
            if name not in own or field.description is None:
                continue  # an inherited field is reported once, at the class that declares it
            if len(field.description) > MAX_DESCRIPTION_CHARS:
                offenders.add(f"{_field_line(cls, name)} {cls.__name__}.{name} description has "
                              f"{len(field.description)} characters")
    return sorted(offenders)


def test_module_docstrings_are_short():
    offenders = _docstring_offenders()
    assert not offenders, (f"{len(offenders)} module docstrings over {MAX_DOCSTRING_LINES} lines "
                           "(move reasons and measurements to docs/):\n" + "\n".join(offenders))


def test_field_descriptions_in_the_source_fit_on_one_line():
    offenders = _literal_description_offenders()
    assert not offenders, (f"{len(offenders)} Field descriptions over {MAX_DESCRIPTION_CHARS} characters "
                           "(move the reason to a comment or docs/):\n" + "\n".join(offenders))


def test_model_field_descriptions_fit_on_one_line():
    offenders = _model_description_offenders()
    assert not offenders, (f"{len(offenders)} model field descriptions over {MAX_DESCRIPTION_CHARS} "
                           "characters (move the reason to a comment or docs/):\n" + "\n".join(offenders))


def test_the_model_walk_sees_the_config_models():
    """The walk must reach the models it is meant to check, or the test above could pass on nothing."""
    names = {f"{cls.__module__}.{cls.__qualname__}" for cls in _models()}
    for expected in ("agent.core.params.AgentParams", "agent.shell.settings.NodeSettings",
                     "sim_bridge.world.SeaConfig", "agent.contract.Status"):
        assert expected in names
