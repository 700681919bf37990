"""Multi-host: the shore router, the sim bridge and two agents, each in its own Linux network namespace.

The router's namespace sits in the middle, with one veth pair (its own /30) to each of the others, so the
sim bridge and the agents can reach the router and nothing else: as Zenoh clients every message between
them goes through it, as it will between boats and the shore. A short lockstep mission must complete with
every tick answered, and give the same commands as the in-process runner.

Needs Linux, iproute2 and root (or CAP_SYS_ADMIN + CAP_NET_ADMIN); skipped with the reason elsewhere.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("zenoh")

pytestmark = pytest.mark.slow   # network namespaces, a router, the bridge and agents as processes

ROOT = Path(__file__).resolve().parents[1]
PORT = 7447
VESSELS = ("1", "2")
MISSION_TIMEOUT = 45.0    # wall seconds from the router's start to the sim bridge's exit
STOP_TIMEOUT = 10.0       # wall seconds for a process to stop after SIGTERM
COMMAND_TIMEOUT = 5.0     # wall seconds for each `ip` call

# The tests' short mission (tests/data/short_scenario.yaml) with two vessels for 5 s.
_SHORT = yaml.safe_load((Path(__file__).parent / "data" / "short_scenario.yaml").read_text())
_SHORT["base"].update(duration=5.0)
_SHORT["base"]["world"]["vessels"] = _SHORT["base"]["world"]["vessels"][:2]
SCENARIO = yaml.safe_dump(_SHORT)


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    result = subprocess.run(["ip", *args], check=False, capture_output=True, text=True,
                            timeout=COMMAND_TIMEOUT)
    if check and result.returncode != 0:
        raise RuntimeError(f"`ip {' '.join(args)}` failed ({result.returncode}): {result.stderr.strip()}")
    return result


def _why_not_supported() -> str | None:
    """None where namespaces, veth links and `ip netns exec` all work here; else why not."""
    if not sys.platform.startswith("linux"):
        return f"network namespaces need Linux (this is {sys.platform})"
    if shutil.which("ip") is None:
        return "no `ip` command (iproute2) on PATH"
    # No uid check of our own: a non-root user with CAP_SYS_ADMIN and CAP_NET_ADMIN may do it; the probe says.
    who = "" if os.geteuid() == 0 else f" (running as uid {os.geteuid()}, not root)"
    probe = f"usvt{os.getpid()}-probe"
    try:
        steps = [("netns", "add", probe),
                 ("-n", probe, "link", "add", "p0", "type", "veth", "peer", "name", "p1"),
                 ("netns", "exec", probe, "true")]
        for step in steps:
            result = _ip(*step, check=False)
            if result.returncode != 0:
                return (f"`ip {' '.join(step)}` is not allowed here{who} (exit {result.returncode}): "
                        f"{result.stderr.strip() or '(no stderr)'}")
        return None
    except (OSError, subprocess.TimeoutExpired) as error:
        return f"probing `ip netns` failed: {type(error).__name__}: {error}"
    finally:
        try:
            _ip("netns", "del", probe, check=False)
        except (OSError, subprocess.TimeoutExpired):
            pass


class Net:
    """Four namespaces: `router` in the middle, joined to `sim`, `a1`, `a2` by one veth pair each.

    `address[name]` is the router's address on the link to `name`, the endpoint that side connects to."""

    def __init__(self, prefix: str) -> None:
        self.names = {role: f"{prefix}-{role}" for role in ("router", "sim", "a1", "a2")}
        self.address: dict[str, str] = {}
        self.processes: list[subprocess.Popen] = []
        self._handles: list = []

    def create(self) -> None:
        for ns in self.names.values():
            _ip("netns", "add", ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        router = self.names["router"]
        for subnet, role in enumerate(("sim", "a1", "a2"), start=1):
            # The pair is made inside the router's namespace and one end moved out: interface names never
            # touch the root namespace, so parallel runs cannot clash.
            inner, outer = f"r-{role}", "eth0"
            _ip("-n", router, "link", "add", inner, "type", "veth", "peer", "name", outer,
                "netns", self.names[role])
            _ip("-n", router, "addr", "add", f"10.77.{subnet}.1/30", "dev", inner)
            _ip("-n", router, "link", "set", inner, "up")
            _ip("-n", self.names[role], "addr", "add", f"10.77.{subnet}.2/30", "dev", outer)
            _ip("-n", self.names[role], "link", "set", outer, "up")
            self.address[role] = f"10.77.{subnet}.1"

    def traffic(self, role: str) -> tuple[int, int]:
        """(received, sent) bytes on the router's side of the link to `role`."""
        shown = _ip("-j", "-s", "-n", self.names["router"], "link", "show", "dev", f"r-{role}").stdout
        (link,) = json.loads(shown)
        return link["stats64"]["rx"]["bytes"], link["stats64"]["tx"]["bytes"]

    def start(self, role: str, args: list[str], log: Path) -> subprocess.Popen:
        """`python -m ...` inside the role's namespace, stdout and stderr to `log`."""
        handle = log.open("w")
        self._handles.append(handle)
        env = {k: v for k, v in os.environ.items() if k != "ZENOH_CONFIG"}   # ours, not the caller's
        env["PYTHONUNBUFFERED"] = "1"
        process = subprocess.Popen(["ip", "netns", "exec", self.names[role], sys.executable, *args],
                                   stdout=handle, stderr=subprocess.STDOUT, cwd=ROOT, env=env)
        self.processes.append(process)
        return process

    def destroy(self) -> None:
        """Kill what is left (ours, then anything else still inside our namespaces), delete the namespaces
        (their veths go with them)."""
        for process in self.processes:
            if process.poll() is None:
                process.kill()
        for process in self.processes:
            try:
                process.wait(timeout=STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                pass
        existing = set(_ip("netns", "list", check=False).stdout.split())
        for ns in self.names.values():
            if ns not in existing:
                continue
            for pid in _ip("netns", "pids", ns, check=False).stdout.split():
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            _ip("netns", "del", ns, check=False)
        for handle in self._handles:
            handle.close()


@pytest.fixture
def net():
    reason = _why_not_supported()
    if reason is not None:
        pytest.skip(f"multi-host test needs network namespaces: {reason}")
    topology = Net(f"usvt{os.getpid()}")
    try:
        topology.create()
        yield topology
    finally:
        topology.destroy()
        left = set(_ip("netns", "list", check=False).stdout.split()) & set(topology.names.values())
        assert not left, f"namespaces left behind: {sorted(left)}"


def _report(logs: dict[str, Path], limit: int = 4000) -> str:
    """Every process's console output (the tail of it), for an assertion message."""
    parts = []
    for name, path in logs.items():
        text = path.read_text(errors="replace") if path.exists() else "(no output file)"
        if len(text) > limit:
            text = "..." + text[-limit:]
        parts.append(f"----- {name} ({path.name}) -----\n{text.rstrip() or '(empty)'}")
    return "\n" + "\n".join(parts)


def _wait_for_line(process: subprocess.Popen, log: Path, pattern: str, deadline: float) -> bool:
    while time.monotonic() < deadline:
        if pattern in log.read_text(errors="replace"):
            return True
        if process.poll() is not None:
            return False
        time.sleep(0.05)
    return False


def _stop(process: subprocess.Popen) -> int | None:
    """SIGTERM, then wait; None if it did not stop in time (the fixture kills it)."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
    try:
        return process.wait(timeout=STOP_TIMEOUT)
    except subprocess.TimeoutExpired:
        return None


def test_router_bridge_and_agents_in_separate_namespaces_complete_a_mission(tmp_path, net):
    from agent.runtime.mcap_log import read_messages
    from lab.harness.runner import run
    from mission_log.reader import read_log
    from sim_bridge.fleet import agent_configs
    from sim_bridge.scenario import select_scenario

    scenario_path = tmp_path / "multihost.yaml"
    scenario_path.write_text(SCENARIO)
    variant, scenario = select_scenario(scenario_path, None)
    ticks = round(scenario.duration / scenario.world.dt) + 1

    # Each process's settings, as the fleet launcher writes them, but as clients of the router.
    def client(role: str) -> dict:
        return {"mode": "client", "connect": [f"tcp/{net.address[role]}:{PORT}"]}

    (tmp_path / "bridge.yaml").write_text(yaml.safe_dump({
        "mode": "lockstep", "zenoh": client("sim"), "log": str(tmp_path / "sim.mcap"),
        "startup_timeout": 20.0}))
    for vessel, settings in agent_configs(scenario, None, tmp_path, lambda v: client(f"a{v}")).items():
        (tmp_path / f"agent-{vessel}.yaml").write_text(yaml.safe_dump(settings))

    logs = {"router": tmp_path / "router.log", "bridge": tmp_path / "bridge.log",
            **{f"agent {v}": tmp_path / f"agent-{v}.log" for v in VESSELS}}
    deadline = time.monotonic() + MISSION_TIMEOUT
    router = net.start("router", ["-m", "usv_deploy", "router", "--listen", f"tcp/0.0.0.0:{PORT}"],
                       logs["router"])
    # Clients give up when no router answers their first connection, so the router goes first.
    assert _wait_for_line(router, logs["router"], "usv-router: running as", deadline), (
        f"the router did not come up (exit code {router.poll()})" + _report(logs))
    agents = {v: net.start(f"a{v}", ["-m", "agent", "--vessel", v, "--config",
                                     str(tmp_path / f"agent-{v}.yaml")], logs[f"agent {v}"]) for v in VESSELS}
    bridge = net.start("sim", ["-m", "sim_bridge", "--scenario", str(scenario_path), "--variant", variant,
                               "--config", str(tmp_path / "bridge.yaml")], logs["bridge"])
    # Until the bridge is done; an agent gone before it is a failure now, not after the bridge's start-up
    # timeout (the fixture kills what is left).
    early = None
    while bridge.poll() is None and time.monotonic() < deadline:
        early = next((v for v, p in agents.items() if p.poll() is not None), None)
        if early is not None:
            break
        time.sleep(0.05)
    assert early is None, (f"agent {early} exited (code {agents[early].returncode}) before the mission ended"
                           + _report(logs))
    bridge_code = bridge.poll()
    if bridge_code is None:   # a hang: on SIGTERM the bridge still prints how far it got
        _stop(bridge)
    agent_codes = {v: _stop(p) for v, p in agents.items()}
    router_code = _stop(router)
    traffic = {role: net.traffic(role) for role in ("sim", "a1", "a2")}

    assert bridge_code is not None, f"the mission did not end within {MISSION_TIMEOUT:.0f} s" + _report(logs)
    assert bridge_code == 0, f"the sim bridge exited with code {bridge_code}" + _report(logs)
    # A vessel whose agent never came up is not "missed" (the bridge waits only for live agents) but
    # stopped by the watchdog every tick: both counts must be 0.
    line = re.search(r"usv-sim: (\d+) ticks, (\d+) missed commands, (\d+) watchdog stops",
                     logs["bridge"].read_text())
    assert line is not None, "no summary line from the sim bridge" + _report(logs)
    assert tuple(map(int, line.groups())) == (ticks, 0, 0), line[0] + _report(logs)
    (summary,) = [m for t, _, m in read_messages(tmp_path / "sim.mcap") if t == "/bridge/summary"]
    assert (summary["ticks"], summary["missed_commands"], summary["watchdog_stops"]) == (ticks, 0, 0), (
        f"/bridge/summary {summary}" + _report(logs))
    assert agent_codes == {v: 0 for v in VESSELS}, f"agents' exit codes {agent_codes}" + _report(logs)
    assert router_code == 0, f"the router's exit code {router_code}" + _report(logs)
    # The messages really crossed the links: every link carried the mission's traffic both ways.
    assert all(min(both) > 10_000 for both in traffic.values()), f"bytes (in, out) per link {traffic}"

    # Every tick the bridge logged has each agent's command, sent over the router.
    stamps = [stamp for stamp, _ in read_log(tmp_path / "sim.mcap").messages("/truth")]
    assert len(stamps) == ticks, f"{len(stamps)} ticks in sim.mcap" + _report(logs)
    trace = run(scenario)   # the in-process runner, same seed: lockstep over the router must repeat it
    for n, vessel in enumerate(trace.vessels):
        path = tmp_path / f"agent-{vessel}.mcap"
        assert path.is_file(), f"agent {vessel} left no log" + _report(logs)
        log = read_log(path)
        assert not log.unfinished, f"agent {vessel}'s log is unfinished" + _report(logs)
        commands = {stamp: (m["surge"], m["yaw_rate"]) for stamp, m in log.topic("cmd")}
        assert sorted(commands) == stamps, (
            f"agent {vessel} logged commands for {len(commands)} of {ticks} ticks" + _report(logs))
        np.testing.assert_allclose([commands[s] for s in stamps], trace.commands[:, n], rtol=0, atol=1e-9,
                                   err_msg=f"vessel {vessel}: commands differ from the in-process runner")
