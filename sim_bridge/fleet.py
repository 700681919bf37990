"""`usv-fleet run SCENARIO`: the sim bridge and one agent per vessel as separate OS processes on loopback.

It writes each process's settings into a run folder, starts the bridge (lockstep) and the agents, waits
for the mission to end, stops the agents with SIGTERM (they finish their logs), and then computes the
paper's metrics from the logs alone: the bridge's ground truth against what each agent logged it believed.
The folder ends up with every MCAP log, `metrics.json`, `summary.md` and `trajectories.png`.

Ports: each agent listens on port 0, so the OS picks a free port as the agent binds it (the others learn it
from Zenoh's gossip). Only the sim bridge's port must be known in advance, by the launcher and the agents
that connect to it; `free_port()` draws it, and if another process binds it before the bridge does (the
bridge then exits at start-up with "Address already in use") the launcher starts the bridge again on
another port. Any process that exits on its own during the mission fails the launch, naming it.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import signal
import socket
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import yaml
import zenoh

from agent.config import ConfigError
from agent.contract import CLOCK_KEY, Clock, decode, seconds
from agent.runtime.zenoh_session import ZenohSettings, zenoh_config
from mission_log.metrics import truth_metrics
from mission_log.plots import plot_run
from mission_log.reader import load_run
from sim_bridge.scenario import initial_estimates, select_scenario
from sim_bridge.world import World, streams

AGENT_LISTEN = "tcp/127.0.0.1:0"   # port 0: the OS picks a free one as the agent binds it
PORT_TAKEN = "Address already in use"
BRIDGE_ATTEMPTS = 3                # starts of the sim bridge, each on a fresh port, before the launch fails
FIRST_PORT = 20000                 # free_port() draws from [FIRST_PORT, the first port for outgoing connections)
_PORTS = random.SystemRandom()     # not the `random` module's state, which a caller may have seeded


def free_port() -> int:
    """A TCP port free on loopback now, for a listener that binds it later (its clients must know it first).

    Another process may bind it in between. To make that rare the port is drawn outside the kernel's range
    for outgoing connections (/proc/sys/net/ipv4/ip_local_port_range), from which every connecting socket of
    the machine takes its local port: those cannot take it, only listeners that choose their own port can.
    Where that range is unknown or leaves no room, the OS picks (from that range)."""
    end = _first_outgoing_port()
    if end is not None and end - FIRST_PORT >= 1000:
        for _ in range(100):
            port = _PORTS.randrange(FIRST_PORT, end)
            with socket.socket() as probe:
                try:
                    probe.bind(("127.0.0.1", port))
                except OSError:
                    continue
                return port
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _first_outgoing_port() -> int | None:
    """The first port of the kernel's range of local ports for outgoing connections; None where unknown."""
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


class Fleet:
    """The processes of one simulated mission on loopback: the sim bridge (lockstep by default, or real time)
    and one agent per vessel.

    `run()` starts the bridge and the agents of the vessels there at the start, then follows the sim clock:
    it starts a joining vessel's agent when the sim reaches its `join_time` (the bridge waits for it), and
    kills a leaving vessel's agent with SIGKILL at its `leave_time`, as a vessel lost at sea. When the
    bridge has finished, the agents get SIGTERM and finish their logs. `on_time(fleet, sim_seconds)` lets a
    caller act during the mission (tests kill an agent with it); it is called on each sim clock message, from
    Zenoh's thread, so it must be quick and must not call Zenoh.
    """

    def __init__(self, scenario_path: Path, variant: str | None, out: Path, seed: int | None = None,
                 mode: str = "lockstep") -> None:
        self.name, self.scenario = select_scenario(scenario_path, variant)
        self.folder = out / f"{scenario_path.stem}-{self.name}-{datetime.now(UTC):%Y%m%dT%H%M%S%f}"
        self.folder.mkdir(parents=True, exist_ok=False)
        self.mode, self.seed = mode, seed
        self.bridge_cmd = [sys.executable, "-m", "sim_bridge", "--scenario", str(scenario_path), "--variant",
                           self.name, "--config", str(self.folder / "bridge.yaml")]
        self.bridge_cmd += ["--seed", str(seed)] if seed is not None else []
        self.bridge_port = 0
        self._write_settings(free_port())
        self.bridge: subprocess.Popen | None = None
        self.agents: dict[str, subprocess.Popen] = {}
        self.killed: dict[str, float] = {}        # vessel -> sim time (s) when its agent was killed
        self.peak_memory: dict[str, float] = {}   # MB of resident memory at its highest, per process
        self._logs: list = []
        self._sim_time = -math.inf

    def _write_settings(self, bridge_port: int) -> None:
        """bridge.yaml and each agent-<id>.yaml, for a sim bridge listening on `bridge_port`."""
        self.bridge_port = bridge_port
        (self.folder / "bridge.yaml").write_text(yaml.safe_dump({
            "mode": self.mode, "zenoh": {"listen": [f"tcp/127.0.0.1:{bridge_port}"]},
            "log": str(self.folder / "sim.mcap")}))
        for vessel, settings in agent_configs(self.scenario, self.seed, self.folder, lambda v: {
                "listen": [AGENT_LISTEN], "connect": [f"tcp/127.0.0.1:{bridge_port}"]}).items():
            (self.folder / f"agent-{vessel}.yaml").write_text(yaml.safe_dump(settings))

    def _start(self, name: str, command: list[str]) -> subprocess.Popen:
        handle = (self.folder / f"{name}.log").open("w")
        self._logs.append(handle)
        return subprocess.Popen(command, stdout=handle, stderr=subprocess.STDOUT)

    def start_agent(self, vessel: str) -> None:
        self.agents[vessel] = self._start(f"agent-{vessel}", [
            sys.executable, "-m", "agent", "--vessel", vessel, "--config", str(self.folder / f"agent-{vessel}.yaml")])

    def kill(self, vessel: str) -> None:
        """SIGKILL a vessel's agent: no goodbye, its liveliness token vanishes with its session."""
        self._note_memory()
        self.killed[vessel] = self._sim_time   # first: the polling loop must never see it dead and not killed
        self.agents[vessel].kill()

    def run(self, timeout: float = 600.0, on_time=None) -> Path:
        """Run the mission; the run folder. RuntimeError (saying which process and where its log is) when a
        process fails: the sim bridge cannot start or exits with an error, or an agent exits on its own."""

        def on_clock(sample) -> None:
            message, _ = decode(Clock, sample.payload.to_bytes())
            if message is not None:
                self._sim_time = max(self._sim_time, seconds(message.stamp_ns))
                if on_time is not None:
                    # Here rather than in the polling loop: in lockstep the sim runs ahead of any poll.
                    on_time(self, self._sim_time)

        deadline = time.monotonic() + timeout
        try:
            with self._start_bridge(on_clock, deadline):
                dt = self.scenario.world.dt
                pending = {v.id: v for v in self.scenario.world.vessels}
                leaving = {v.id: v.leave_time for v in self.scenario.world.vessels if v.leave_time is not None}
                print(f"usv-fleet: the sim bridge and {sum(v.join_time == 0 for v in pending.values())} agents "
                      f"starting; run folder {self.folder}", file=sys.stderr)
                while self.bridge.poll() is None:
                    if time.monotonic() > deadline:
                        raise TimeoutError(f"the mission did not end within {timeout:.0f} s")
                    self._check_agents()
                    now = self._sim_time
                    for vessel in [v for v, spec in pending.items() if spec.join_time <= max(now, 0.0) + dt + 1e-9]:
                        self.start_agent(vessel)
                        del pending[vessel]
                    for vessel in [v for v, t in leaving.items() if now >= t - 1e-9 and v in self.agents]:
                        self.kill(vessel)
                        del leaving[vessel]
                    self._note_memory()
                    time.sleep(0.02)
                if self.bridge.returncode != 0:
                    raise RuntimeError(self._exited("the sim bridge", "bridge", self.bridge.returncode))
                self._check_agents()
        finally:
            self._stop()
        for vessel, process in self.agents.items():
            if vessel not in self.killed and process.returncode != 0:
                raise RuntimeError(self._exited(f"the agent of vessel {vessel}", f"agent-{vessel}",
                                                process.returncode, "when told to stop"))
        return self.folder

    def _start_bridge(self, on_clock, deadline: float):
        """Start the sim bridge and return the launcher's session (sim clock subscribed) once it reaches it.
        A bridge whose port was taken in the meantime is started again on a fresh port."""
        attempt = 1
        while True:
            self.bridge = self._start("bridge", self.bridge_cmd)
            session = zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{self.bridge_port}"])))
            try:
                session.declare_subscriber(CLOCK_KEY, on_clock)
                if self._wait_for_bridge(session, deadline):
                    return session
            except BaseException:
                session.close()
                raise
            session.close()
            log = self.folder / "bridge.log"
            failure = self._exited("the sim bridge", "bridge", self.bridge.returncode, "at start-up")
            if PORT_TAKEN not in log.read_text(errors="replace"):
                raise RuntimeError(failure)
            if attempt == BRIDGE_ATTEMPTS:
                raise RuntimeError(f"{failure}; its port was taken {attempt} times in a row")
            log.rename(self.folder / f"bridge-attempt{attempt}.log")
            taken = self.bridge_port
            self._write_settings(free_port())
            attempt += 1
            print(f"usv-fleet: port {taken} was taken before the sim bridge could listen on it; starting it "
                  f"again on port {self.bridge_port}", file=sys.stderr)

    def _wait_for_bridge(self, session, deadline: float) -> bool:
        """Start no agent before this session reaches the bridge: Zenoh retries a connection with a growing
        delay, and a launcher that connects late misses the sim clock of the mission's first seconds.
        False if the bridge exits first."""
        while not list(session.info.peers_zid()):
            if self.bridge.poll() is not None:
                return False
            if time.monotonic() > deadline:
                raise TimeoutError("the launcher could not reach the sim bridge")
            time.sleep(0.01)
        return True

    def _check_agents(self) -> None:
        """An agent runs until the launcher stops or kills it: one that exits on its own fails the launch."""
        for vessel, process in self.agents.items():
            if vessel not in self.killed and process.poll() is not None:
                raise RuntimeError(self._exited(f"the agent of vessel {vessel}", f"agent-{vessel}",
                                                process.returncode, "during the mission"))

    def _exited(self, who: str, name: str, code: int | None, when: str = "") -> str:
        """`who` exited with `code` `when`, with the last line of its console log and where that log is."""
        log = self.folder / f"{name}.log"
        try:
            lines = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.strip()]
        except OSError:
            lines = []
        last = f": {lines[-1]}" if lines else ""
        return f"{who} exited with code {code}{' ' + when if when else ''}{last} (see {log})"

    def _note_memory(self) -> None:
        for name, process in [("bridge", self.bridge), *((f"agent-{v}", p) for v, p in self.agents.items())]:
            if process is not None and process.poll() is None:
                peak = _peak_resident_mb(process.pid)
                if peak is not None:
                    self.peak_memory[name] = max(self.peak_memory.get(name, 0.0), peak)

    def _stop(self) -> None:
        self._note_memory()
        processes = [p for p in [*self.agents.values(), self.bridge] if p is not None]
        for process in processes:
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        for process in processes:
            try:
                process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        for handle in self._logs:
            handle.close()
        (self.folder / "memory.json").write_text(json.dumps(
            {"peak_resident_mb": dict(sorted(self.peak_memory.items()))}, indent=2))


def _peak_resident_mb(pid: int) -> float | None:
    """Peak resident memory of a live process (Linux /proc VmHWM), in MB; None where unavailable."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        return None
    return None


def launch(scenario_path: Path, variant: str | None, out: Path, seed: int | None,
           timeout: float = 600.0) -> Path:
    """Run the fleet and analyse its logs; returns the run folder."""
    fleet = Fleet(scenario_path, variant, out, seed)
    folder = fleet.run(timeout)
    analyse(folder, fleet.scenario.agent_params().control.radius)
    return folder


def agent_configs(scenario, seed: int | None, folder: Path, zenoh) -> dict[str, dict]:
    """Each vessel's agent settings (NodeSettings as a mapping) for a simulated mission: sim clock, the
    scenario's parameters and initial estimates, its log in `folder`, and `zenoh(vessel)` as its Zenoh section
    (loopback peers for the launcher, clients of a router in tests/test_multihost.py)."""
    agent_params = scenario.agent_params().model_dump(mode="json")
    starts = initial_settings(scenario, seed)
    return {v.id: {"clock": "sim", "zenoh": zenoh(v.id), "log": str(folder / f"agent-{v.id}.mcap"),
                   "agent": agent_params, "initial": starts.get(v.id, {})}
            for v in scenario.world.vessels}


def initial_settings(scenario, seed: int | None) -> dict[str, dict]:
    """Each agent's starting estimates, drawn as the in-process runner draws them (for the vessels there
    at the start; a later joiner starts from its first bearing and its neighbours' shares)."""
    random = streams(scenario.seed if seed is None else seed)
    world = World(scenario.world, random.world)
    return {v: start.model_dump(mode="json")
            for v, start in initial_estimates(scenario, world.truth(), random.initial).items()}


def analyse(folder: Path, radius: float) -> dict:
    """The paper's metrics from the run folder's logs; writes metrics.json, summary.md and the figures of
    `usv-log plot` (trajectories.png, errors.png, ranges.png)."""
    run = load_run(folder)
    result = truth_metrics(run, radius)
    (folder / "metrics.json").write_text(json.dumps(result, indent=2))
    figures = plot_run(run, folder, radius)
    settling = result["settling_time"]
    lines = [f"# Fleet run {folder.name}", "",
             f"{len(result['vessels'])} vessels, {result['ticks']} ticks, r* = {radius} m", "",
             "| mean e_ij (m) | mean e_io (m) | mean e_c (m) | settling time (s) |", "|---|---|---|---|",
             (f"| {result['mean_e_ij']:.3f} | {result['mean_e_io']:.3f} | {result['mean_e_c']:.3f} | "
             f"{'never' if settling is None else f'{settling:.1f}'} |"), "",
             ("Computed from the logs alone: `sim.mcap` (ground truth) and `agent-<id>.mcap` (what each believed). "
             "`usv-log summary|metrics|plot` on this folder says more."), "",
             *(f"![{path.stem}]({path.name})" for path in figures)]
    (folder / "summary.md").write_text("\n".join(lines) + "\n")
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="usv-fleet", description="Run a simulated fleet as separate processes.")
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="the sim bridge and one agent process per vessel")
    run.add_argument("scenario", type=Path, help="scenario YAML, e.g. configs/scenarios/table2_estimators.yaml")
    run.add_argument("--variant", default=None, help="variant of the file (default: the first)")
    run.add_argument("--out", type=Path, default=Path("runs"), help="parent of the run folder")
    run.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    args = parser.parse_args(argv)
    started = time.monotonic()
    try:
        folder = launch(args.scenario, args.variant, args.out, args.seed)
    except ConfigError as error:
        print(f"usv-fleet: {error}", file=sys.stderr)
        return 2
    except (RuntimeError, TimeoutError) as error:
        print(f"usv-fleet: {error}", file=sys.stderr)
        return 1
    print((folder / "summary.md").read_text())
    print(f"usv-fleet: run folder {folder} ({time.monotonic() - started:.1f} s)", file=sys.stderr)
    return 0
