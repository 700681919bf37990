"""Shared fixtures and helpers, and which tests are `slow`.

The `slow` marker (registered in pyproject.toml) is for two kinds of test. Those that wait on the world
outside the test process: they start processes (the fleet's, or a command line in a child Python), open
Zenoh sessions, or watch real time go by. And in-process integration runs that take seconds each: fleet
simulations of tens of seconds over several seeds or variants, Monte Carlo campaigns, a lab command run end
to end (bench, compare, replay, plots). Unit checks (a kernel against closed forms, one component's
invariants over random inputs) stay fast even at a second or two. `make test-fast` (`pytest -m "not slow"`,
on every core) leaves the slow ones out and runs in under a minute on 2 cores; `make test` (what CI runs)
runs everything. A test is slow when one of these holds, and only then:

1. it carries the mark itself: `@pytest.mark.slow`, or `pytestmark = pytest.mark.slow` for a whole module.
   This is the way for every new test;
2. it uses a fixture named in SLOW_FIXTURES (a fixture that runs the fleet's processes);
3. its module, or the test itself, is named in SLOW_MODULES / SLOW_TESTS below: the modules that do not
   (yet) mark themselves. A name in SLOW_TESTS that its module no longer defines is an error at
   collection, so a rename cannot quietly move a slow test into the fast suite.

Helpers for tests (import them with `from conftest import ...`):
- `wait_until(predicate, timeout)`: poll a condition up to a deadline instead of sleeping and hoping;
- `free_ports(n)`: n distinct TCP ports for listeners a test must name in advance (see sim_bridge.fleet);
- `bridge_counts(text)`: the numbers of the sim bridge's closing line, parsed exactly.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from sim_bridge.fleet import Fleet, free_port

SCENARIO = (Path(__file__).parent / "data" / "short_scenario.yaml").read_text()

# Rule 2: fixtures that start the fleet's processes.
SLOW_FIXTURES = {"fleet_run"}
# Rule 3: whole modules that start processes or open Zenoh sessions and carry no mark of their own ...
SLOW_MODULES = {
    "test_node.py": "the agent process and its Zenoh session on loopback",
}
# ... and single tests of otherwise fast modules.
SLOW_TESTS = {
    "test_mcap_log.py": {"test_a_process_killed_hard_loses_at_most_the_last_second"},   # 2.5 s of a child
    "test_usv_log.py": {"test_the_log_of_an_agent_killed_with_sigkill_is_read_up_to_its_last_chunk"},
}


@pytest.hookimpl(tryfirst=True)   # before `-m` deselects anything
def pytest_collection_modifyitems(config, items) -> None:
    checked = set()
    for item in items:
        module = item.path.name
        if module in SLOW_TESTS and module not in checked:
            checked.add(module)
            missing = sorted(name for name in SLOW_TESTS[module] if not hasattr(item.module, name))
            if missing:
                raise pytest.UsageError(f"tests/conftest.py SLOW_TESTS names {', '.join(missing)} in "
                                        f"{module}, which defines no such test: update the list (or mark "
                                        "the test there)")
        if (module in SLOW_MODULES or item.originalname in SLOW_TESTS.get(module, ())
                or SLOW_FIXTURES & set(getattr(item, "fixturenames", ()))):
            item.add_marker(pytest.mark.slow)


# ----- helpers -----
def wait_until(predicate: Callable[[], object], timeout: float = 10.0, interval: float = 0.02) -> bool:
    """Poll `predicate` until it holds or `timeout` seconds have passed: True as soon as it holds, else what
    a last look says. Use it as `assert wait_until(...)`, or `assert not wait_until(...)` to watch for
    something that must not happen during `timeout` (that fails as soon as it happens)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval)
    return bool(predicate())


def free_ports(count: int) -> list[int]:
    """`count` distinct ports free on loopback now, for listeners a test must name in advance (the port of
    one side of a link). sim_bridge.fleet.free_port picks outside the kernel's range for outgoing
    connections, so no client socket takes one in the meantime; drawing them together keeps them apart."""
    ports: list[int] = []
    while len(ports) < count:
        port = free_port()
        if port not in ports:
            ports.append(port)
    return ports


BRIDGE_LINE = re.compile(r"usv-sim: (?P<ticks>\d+) ticks, (?P<missed>\d+) missed commands, "
                         r"(?P<watchdog>\d+) watchdog stops, (?P<refused>\d+) refused")


def bridge_counts(text: str) -> dict[str, int]:
    """{'ticks', 'missed', 'watchdog', 'refused'} of the sim bridge's closing line in its console output
    (a whole number each, never a substring match: '0 missed commands' is also in '10 missed commands')."""
    found = BRIDGE_LINE.findall(text)
    assert len(found) == 1, f"one closing line of the sim bridge expected, {len(found)} in:\n{text[-2000:]}"
    return dict(zip(("ticks", "missed", "watchdog", "refused"), map(int, found[0]), strict=True))


# ----- fixtures -----
@pytest.fixture
def short_scenario(tmp_path):
    """A scenario file: three vessels, 12 s, an island out of the way."""
    path = tmp_path / "short.yaml"
    path.write_text(SCENARIO)
    return path


@pytest.fixture(scope="session")
def fleet_run(tmp_path_factory):
    """(run folder, scenario file) of a lockstep run of the short scenario, made once for all tests."""
    folder = tmp_path_factory.mktemp("fleet")
    scenario = folder / "short.yaml"
    scenario.write_text(SCENARIO)
    fleet = Fleet(scenario, None, folder / "runs")
    return fleet.run(timeout=240), scenario
