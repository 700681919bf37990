"""The architecture as rules on imports, read from the source with `ast` (every import: at the top, inside a
function, under `if TYPE_CHECKING`, relative ones, and `importlib.import_module` of a constant name).

- `agent.core` is the pure per-vessel core: no transport, log format, plotting, threads, sockets or
  processes (zenoh, mcap, matplotlib, threading, socket, subprocess), none of the agent process around it
  (agent.shell, agent.runtime, agent.contract), and nothing of the packages built on it.
- The contract, configuration, angles and the covariance check they share (agent.cholesky) take nothing of
  the core or the shell: a bridge that loads them loads no part of the agent's computation.
- `driver_bridge` and `usv_op` (the operator's station) take from `agent` only what every process of the fleet shares: the wire contract
  (agent.contract), typed configuration (agent.config), angles (agent.angles) and the runtime
  (agent.runtime: Zenoh session settings, the vessel-process command line, MCAP logs).
- `sim_bridge` takes the same, plus the core's pure vocabulary that its scenario and world model share with
  the in-process runner (lab.harness.runner), so that both build a mission the same way: the parameters
  (agent.core.params), the per-tick records (agent.core.records), the builder of a vessel's core and
  initial estimates (agent.core.build) and the range noise the world samples and the filters assume
  (agent.core.range_noise). Never the agent process (agent.shell).
- `boat` (hull presets, thrusters, the inner loop), shared by the sim bridge and the driver bridge, imports
  from the project only `agent.config` and `agent.angles` and itself; `agent` never imports it.
- The ROS 2 libraries of the `ros2` extra (rosbags; mcap_ros2, the tests' decoder) are imported by
  `mission_log.ros2_export` only: no process of the fleet needs them.
- The `driver` extra's libraries stay at the boat's edge: pyserial's `serial` and `pynmeagps` are imported by
  `driver_bridge` alone, pymavlink by the MAVLink link (driver_bridge.mavlink_link) and the ArduPilot stand-in
  (sim_bridge.ardupilot_standin) alone. The agent, the rest of the simulator, the lab, the logs and the
  operator's station install and run without them.
- The `field` extra's pymap3d (latitude and longitude to metres) is imported by `mission_log.local_frame`
  alone: the simulator's GNSS and the scoring of a field trial go through it.
- No agent reads the GNSS truth: outside `agent.contract`, which defines them, no module of `agent` names
  GnssFix, gnss_truth_key or GNSS_TRUTH_TOPIC, nor writes a string with `truth/` in it (a key), and none of
  the key expressions the agent subscribes to matches `usv/<id>/truth/gnss`.
- Layers: `mission_log` and `sim_bridge` never import `lab`; `mission_log` never imports `sim_bridge`;
  nothing outside `lab` imports `lab` (the tests may); `agent` imports none of sim_bridge, driver_bridge, lab,
  mission_log, usv_deploy.

No import circles, inside a package or between packages: the graph of modules, from every import above,
has no cycle (a function-level or TYPE_CHECKING import too: it is a dependency all the same).

A failure names each offending file, line and import statement, or each circle's modules and lines.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("agent", "boat", "sim_bridge", "driver_bridge", "lab", "mission_log", "usv_deploy", "usv_op")

CORE_FORBIDDEN = ("zenoh", "mcap", "matplotlib", "threading", "socket", "subprocess",
                  "agent.shell", "agent.runtime", "agent.contract",
                  "boat", "sim_bridge", "driver_bridge", "lab", "mission_log", "usv_deploy", "usv_op")
OURS = PACKAGES
BOAT_ALLOWED = ("agent.config", "agent.angles", "boat")
ROS2_LIBRARIES = ("rosbags", "mcap_ros2")
ROS2_EXPORT = "mission_log.ros2_export"
SHARED_FROM_AGENT = ("agent.contract", "agent.config", "agent.angles", "agent.runtime")
CORE_VOCABULARY = ("agent.core.params", "agent.core.records", "agent.core.build", "agent.core.range_noise")
# pyproject.toml's `driver` extra, by import name: the only modules that may import each library.
DRIVER_LIBRARIES = {"serial": ("driver_bridge",), "pynmeagps": ("driver_bridge",),
                    "pymavlink": ("driver_bridge.mavlink_link", "sim_bridge.ardupilot_standin")}
FIELD_LIBRARY, FIELD_USER = "pymap3d", "mission_log.local_frame"
GNSS_TRUTH_NAMES = ("GnssFix", "gnss_truth_key", "GNSS_TRUTH_TOPIC")


@dataclass(frozen=True)
class Import:
    module: str      # the importing module, e.g. sim_bridge.world
    path: Path       # its file, relative to the repository
    line: int
    target: str      # the imported module, resolved: `from agent import contract` -> agent.contract
    statement: str   # the source of the import, for the message

    def __str__(self) -> str:
        return f"{self.path}:{self.line} imports {self.target} (`{self.statement}`)"


def within(name: str, prefix: str) -> bool:
    """Is module `name` the module or package `prefix`, or inside it? Everything is within ""."""
    return prefix == "" or name == prefix or name.startswith(prefix + ".")


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(source: str, module: str, is_package: bool, known: set[str],
               path: Path = Path("<source>")) -> list[Import]:
    """Every import in `source` (the code of `module`), with relative imports resolved and `from X import Y`
    read as X.Y where X.Y is a module of `known`."""
    lines = source.splitlines()
    found = []

    def add(node: ast.AST, target: str) -> None:
        statement = " ".join(line.strip() for line in lines[node.lineno - 1:node.end_lineno])
        found.append(Import(module, path, node.lineno, target, statement))

    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(node, alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                origin = ".".join(base + ([node.module] if node.module else []))
            else:
                origin = node.module or ""
            for alias in node.names:
                add(node, f"{origin}.{alias.name}" if f"{origin}.{alias.name}" in known else origin)
        elif (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
              and isinstance(node.args[0].value, str) and _is_dynamic_import(node.func)):
            add(node, node.args[0].value)
    return sorted(found, key=lambda f: f.line)


def _is_dynamic_import(func: ast.expr) -> bool:
    """importlib.import_module(...), import_module(...) or __import__(...)."""
    name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
    return name in ("import_module", "__import__")


def scan(root: Path = ROOT, packages: Iterable[str] = PACKAGES) -> list[Import]:
    files = sorted(path for package in packages for path in (root / package).rglob("*.py")
                   if "__pycache__" not in path.parts)
    known = {module_name(path, root) for path in files}
    return [found for path in files
            for found in imports_of(path.read_text(encoding="utf-8"), module_name(path, root),
                                    path.name == "__init__.py", known, path.relative_to(root))]


def circles(imports: list[Import]) -> list[list[Import]]:
    """One cycle of imports (as the imports that close it, in order) for each strongly connected set of
    modules of more than one; the graph's nodes are the modules that import, its edges one import each."""
    edges: dict[str, dict[str, Import]] = {}
    for found in imports:
        edges.setdefault(found.module, {})
    for found in imports:
        if found.target in edges and found.target != found.module:
            edges[found.module].setdefault(found.target, found)
    # Tarjan's strongly connected components, iteratively (no recursion limit on a long chain).
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[set[str]] = []
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, successors = work[-1]
            successor = next(successors, None)
            if successor is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = set()
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.add(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        components.append(component)
            elif successor not in index:
                index[successor] = low[successor] = len(index)
                stack.append(successor)
                on_stack.add(successor)
                work.append((successor, iter(sorted(edges[successor]))))
            elif successor in on_stack:
                low[node] = min(low[node], index[successor])
    return [_cycle_through(min(component), component, edges) for component in components]


def _cycle_through(start: str, component: set[str], edges: dict[str, dict[str, Import]]) -> list[Import]:
    """The shortest cycle from `start` back to itself inside `component` (breadth first)."""
    came_from: dict[str, Import] = {}
    frontier = [start]
    while frontier:
        following = []
        for node in frontier:
            for target, found in sorted(edges[node].items()):
                if target == start:
                    path = [found]
                    while path[0].module != start:
                        path.insert(0, came_from[path[0].module])
                    return path
                if target in component and target not in came_from:
                    came_from[target] = found
                    following.append(target)
        frontier = following
    raise AssertionError(f"{start} is in a strongly connected set but on no cycle")


def describe(cycle: list[Import]) -> str:
    names = " -> ".join([cycle[0].module, *(found.target for found in cycle)])
    return names + "\n" + "\n".join(f"    {found}" for found in cycle)


@pytest.fixture(scope="module")
def imports() -> list[Import]:
    return scan()


def broken(imports: list[Import], importer: str, allowed, rule: str) -> None:
    """Fail, naming each offender, unless each import of a module in `importer` passes `allowed(target)`."""
    offending = [found for found in imports if within(found.module, importer) and not allowed(found.target)]
    if offending:
        pytest.fail(f"{rule}, but:\n" + "\n".join(f"  {found}" for found in offending), pytrace=False)


# ----- the rules -----
def test_the_core_is_pure(imports):
    broken(imports, "agent.core", lambda target: not any(within(target, name) for name in CORE_FORBIDDEN),
           f"agent.core imports none of {', '.join(CORE_FORBIDDEN)}")


@pytest.mark.parametrize("importer", ["agent.contract", "agent.cholesky", "agent.config", "agent.angles"])
def test_what_a_bridge_takes_from_agent_takes_nothing_of_the_core_or_the_shell(imports, importer):
    broken(imports, importer, lambda target: not (within(target, "agent.core") or within(target, "agent.shell")),
           f"{importer} imports nothing of agent.core or agent.shell (a bridge loads it alone)")


@pytest.mark.parametrize("importer", ["driver_bridge", "usv_op"])
def test_the_driver_bridge_and_the_operator_take_only_the_shared_modules_from_agent(imports, importer):
    broken(imports, importer,
           lambda target: not within(target, "agent") or any(within(target, n) for n in SHARED_FROM_AGENT),
           f"{importer} imports from agent only {', '.join(SHARED_FROM_AGENT)}")


def test_the_sim_bridge_takes_the_shared_modules_and_the_core_vocabulary_from_agent(imports):
    allowed = SHARED_FROM_AGENT + CORE_VOCABULARY
    broken(imports, "sim_bridge",
           lambda target: not within(target, "agent") or any(within(target, name) for name in allowed),
           f"sim_bridge imports from agent only {', '.join(allowed)} (and never agent.shell)")


def test_the_boat_takes_only_config_and_angles(imports):
    broken(imports, "boat",
           lambda target: not any(within(target, name) for name in OURS)
           or any(within(target, name) for name in BOAT_ALLOWED),
           f"boat imports from the project only {', '.join(BOAT_ALLOWED)}")


@pytest.mark.parametrize("importer, forbidden", [
    ("mission_log", ("lab", "sim_bridge")),
    ("sim_bridge", ("lab",)),
    ("boat", ("zenoh", "mcap", "matplotlib", "threading", "socket", "subprocess")),
    ("agent", ("boat", "sim_bridge", "driver_bridge", "lab", "mission_log", "usv_deploy", "usv_op")),
])
def test_the_layers(imports, importer, forbidden):
    broken(imports, importer, lambda target: not any(within(target, name) for name in forbidden),
           f"{importer} imports none of {', '.join(forbidden)}")


def test_only_the_ros2_export_imports_the_ros2_libraries(imports):
    others = [found for found in imports if found.module != ROS2_EXPORT]
    broken(others, "", lambda target: not any(within(target, name) for name in ROS2_LIBRARIES),
           f"only {ROS2_EXPORT} imports {', '.join(ROS2_LIBRARIES)}")


@pytest.mark.parametrize("library, users", DRIVER_LIBRARIES.items())
def test_only_the_driver_bridge_imports_the_driver_extras_libraries(imports, library, users):
    others = [found for found in imports if not any(within(found.module, user) for user in users)]
    broken(others, "", lambda target: not within(target, library),
           f"only {' and '.join(users)} may import {library} (the `driver` extra)")


def test_only_the_local_frame_imports_the_field_extras_library(imports):
    others = [found for found in imports if found.module != FIELD_USER]
    broken(others, "", lambda target: not within(target, FIELD_LIBRARY),
           f"only {FIELD_USER} may import {FIELD_LIBRARY} (the `field` extra)")


def truth_readers(source: str, path: str) -> list[str]:
    """Where `source` names the GNSS truth or writes a key with `truth/` in it: "path:line what"."""
    found = []
    for node in ast.walk(ast.parse(source)):
        name = (node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute)
                else node.name if isinstance(node, ast.alias) else None)
        if name is not None and name.split(".")[-1] in GNSS_TRUTH_NAMES:
            found.append(f"{path}:{node.lineno} names {name}")
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and "truth/" in node.value:
            found.append(f"{path}:{node.lineno} writes {node.value[:60]!r}")
    return found


def test_no_agent_module_reads_the_gnss_truth():
    files = sorted(path for path in (ROOT / "agent").rglob("*.py") if "__pycache__" not in path.parts)
    assert len(files) > 20 and ROOT / "agent" / "shell" / "node.py" in files
    found = [where for path in files if path != ROOT / "agent" / "contract.py"
             for where in truth_readers(path.read_text(encoding="utf-8"), str(path.relative_to(ROOT)))]
    assert not found, "no agent module reads the GNSS truth, but:\n" + "\n".join(found)


def test_the_truth_check_finds_a_made_up_reader():
    source = ("from agent.contract import GnssFix\nimport agent.contract as c\n"
              "k = c.gnss_truth_key('1')\nsession.declare_subscriber('usv/*/truth/**', on)\n")
    found = truth_readers(source, "x.py")
    assert [where.split(" ", 1)[0] for where in found] == ["x.py:1", "x.py:3", "x.py:4"], found


def test_no_key_the_agent_subscribes_to_matches_the_gnss_truth():
    """The agent's subscriptions (agent/shell/node.py: its own sensors, the shares to it in both formats, mission commands, the
    sim clock and the liveliness tokens), as zenoh key expressions, against the truth key."""
    import zenoh

    from agent.contract import (
        CLOCK_KEY,
        FLEET_PREFIX,
        LIVELINESS,
        MISSION_PREFIX,
        every,
        gnss_truth_key,
        shares_for,
    )
    source = (ROOT / "agent" / "shell" / "node.py").read_text(encoding="utf-8")
    subscribed = ['f"{FLEET_PREFIX}/{self.id}/sensor/*"', "shares_for(self.id)", 'every("share")',
                  'f"{MISSION_PREFIX}/*"', "CLOCK_KEY", "every(LIVELINESS)"]
    assert source.count("declare_subscriber(") == len(subscribed), "a subscription was added: list it here"
    assert all(f"declare_subscriber({expression}" in source for expression in subscribed)
    vessel = "1"
    expressions = [f"{FLEET_PREFIX}/{vessel}/sensor/*", shares_for(vessel), every("share"), f"{MISSION_PREFIX}/*",
                   CLOCK_KEY, every(LIVELINESS)]
    truth = zenoh.KeyExpr(gnss_truth_key(vessel))
    assert not [e for e in expressions if zenoh.KeyExpr(e).intersects(truth)]
    assert zenoh.KeyExpr(f"{FLEET_PREFIX}/*/**").intersects(truth)   # the check can see a match


def test_only_the_lab_imports_the_lab(imports):
    outside = [found for found in imports if not within(found.module, "lab")]
    broken(outside, "", lambda target: not within(target, "lab"), "nothing outside lab imports lab")


def test_no_import_circles(imports):
    found = circles(imports)
    if found:
        pytest.fail("no module imports itself through others, but:\n" + "\n".join(map(describe, found)),
                    pytrace=False)


# ----- the scan itself -----
def test_the_scan_reads_every_package(imports):
    """Every package has modules with imports, and the imports the tree is known to have are seen: the
    rules above cannot pass by reading nothing."""
    assert {found.module.split(".")[0] for found in imports} == set(PACKAGES)
    seen = {(found.module, found.target) for found in imports}
    assert ("driver_bridge.node", "zenoh") in seen                    # a process imports its transport
    assert ("sim_bridge.fleet", "mission_log.metrics") in seen        # the launcher computes the metrics
    assert ("usv_deploy.cli", "usv_deploy.certs") in seen             # inside a function (cryptography)
    assert ("usv_op.cli", "agent.contract") in seen                   # the operator speaks the contract
    assert ("sim_bridge.hull", "boat.inner_loop") in seen             # the simulator runs the boat's loop
    assert (ROS2_EXPORT, "rosbags.rosbag2") in seen                   # inside a function (the ros2 extra)
    assert ("driver_bridge.serial_port", "serial") in seen            # inside a function (the driver extra)
    assert ("driver_bridge.mavlink_link", "pymavlink") in seen        # inside a function (the driver extra)
    assert (FIELD_USER, FIELD_LIBRARY) in seen                        # inside a function (the field extra)


def test_the_scan_sees_every_kind_of_import():
    source = '''
import zenoh, numpy as np
import agent.shell.node as node
from agent import contract
from agent.core import not_a_module
from . import sibling
from ..runtime import mcap_log
from typing import TYPE_CHECKING
if TYPE_CHECKING:
    from matplotlib import pyplot
def later():
    import threading
    importlib.import_module("subprocess")
    __import__("socket")
'''
    known = {"agent.contract", "agent.core.sibling", "agent.runtime", "agent.runtime.mcap_log"}
    found = imports_of(source, "agent.core.example", False, known)
    assert [f.target for f in found] == [
        "zenoh", "numpy", "agent.shell.node", "agent.contract", "agent.core", "agent.core.sibling",
        "agent.runtime.mcap_log", "typing", "matplotlib", "threading", "subprocess", "socket"]
    assert str(found[3]) == "<source>:4 imports agent.contract (`from agent import contract`)"
    offender = r"agent.core imports none of.*but:\n  <source>:2 imports zenoh \(`import zenoh, numpy as np`\)"
    with pytest.raises(pytest.fail.Exception, match=offender):
        broken(found, "agent.core", lambda target: not any(within(target, n) for n in CORE_FORBIDDEN),
               f"agent.core imports none of {', '.join(CORE_FORBIDDEN)}")


def test_the_circle_check_finds_a_made_up_circle(tmp_path):
    """Three modules of two packages in a circle, one link inside a function, beside a module outside it:
    the check names the three and the lines that close it; without the inner import there is none."""
    (tmp_path / "alpha").mkdir()
    (tmp_path / "beta").mkdir()
    (tmp_path / "alpha" / "__init__.py").write_text("")
    (tmp_path / "beta" / "__init__.py").write_text("")
    (tmp_path / "alpha" / "first.py").write_text("import os\nfrom beta import second\n")
    (tmp_path / "beta" / "second.py").write_text("from . import third\n")
    (tmp_path / "beta" / "third.py").write_text("def late():\n    from alpha.first import thing\n")
    (tmp_path / "beta" / "apart.py").write_text("from alpha import first\n")   # into the circle, not on it
    found = circles(scan(tmp_path, ("alpha", "beta")))
    assert len(found) == 1
    assert [(f.module, f.target, f.line) for f in found[0]] == [
        ("alpha.first", "beta.second", 2), ("beta.second", "beta.third", 1), ("beta.third", "alpha.first", 2)]
    message = describe(found[0])
    assert message.startswith("alpha.first -> beta.second -> beta.third -> alpha.first\n")
    assert "beta/third.py:2 imports alpha.first (`from alpha.first import thing`)" in message
    (tmp_path / "beta" / "third.py").write_text("def late():\n    import os\n")
    assert circles(scan(tmp_path, ("alpha", "beta"))) == []


def test_the_circle_check_finds_a_circle_of_two_and_of_a_package_and_its_module(tmp_path):
    (tmp_path / "gamma").mkdir()
    (tmp_path / "gamma" / "__init__.py").write_text("from gamma.core import Thing\n")
    (tmp_path / "gamma" / "core.py").write_text("import gamma\n")
    (tmp_path / "gamma" / "left.py").write_text("from gamma import right\n")
    (tmp_path / "gamma" / "right.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                                 "    from gamma.left import Other\n")
    found = sorted([f.module for f in cycle] for cycle in circles(scan(tmp_path, ("gamma",))))
    assert found == [["gamma", "gamma.core"], ["gamma.left", "gamma.right"]]
