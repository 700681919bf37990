"""`usv-fleet run SCENARIO`: the sim bridge and one agent per vessel as separate OS processes on loopback.

It writes each process's settings into a run folder, starts the bridge (lockstep) and the agents, waits
for the mission to end, stops the agents with SIGTERM (they finish their logs), and then computes the
paper's metrics from the logs alone: the bridge's ground truth against what each agent logged it believed.
The folder ends up with every MCAP log, `metrics.json`, `summary.md` and `trajectories.png`.

A run cut short (interrupted, a process failed, the bridge ended early, the time ran out) still gets its
metrics and figures from the logs there are, and `summary.md` and `metrics.json` say plainly that it was cut
short: the ticks done of the ticks planned, and why.

Exit codes: 0, the run went to its end and every log and console is whole; 1, the run failed or was cut
short; 2, a bad scenario or setting; 3, the run went to its end but logs were lost (a process's log was
suspended by write errors, a console or a summary file could not be written in full; each said in a line);
128 + N, stopped by signal N.

More: docs/fleet.md §8, `sim_bridge/fleet.py`.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import json
import math
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from datetime import datetime, timezone
from pathlib import Path

import yaml
import zenoh

from agent.config import ConfigError, read_yaml
from agent.contract import (
    CLOCK_KEY,
    CLOCK_SOURCE_SENSORS,
    LIVELINESS,
    Clock,
    Status,
    decode,
    every,
    key,
    seconds,
)
from agent.runtime.mcap_log import part_path, read_messages
from agent.runtime.process import guard_stderr
from agent.runtime.zenoh_session import ZenohSettings, zenoh_config
from mission_log.metrics import circle_words, truth_metrics
from mission_log.plots import plot_run
from mission_log.reader import LogError, load_run
from sim_bridge import fleet_mavlink, gnss_ptys, simulated_gnss
from sim_bridge.console import TAIL_BYTES, Console
from sim_bridge.scenario import default_variant, initial_estimates, scenario_file, select_scenario, with_duration
from sim_bridge.world import SeaSensors, World, streams

SEA_LEAD = 10.0   # s from writing the settings to sim time 0 of a sea-mode run: time for every process to start
AGENT_LISTEN = "tcp/127.0.0.1:0"   # port 0: the OS picks a free one as the agent binds it
PORT_TAKEN = "Address already in use"
SIM_ID_CHECK = 0.2                 # s an agent of a simulated fleet looks for another agent with its id
BRIDGE_ATTEMPTS = 3                # starts of the sim bridge, each on a fresh port, before the launch fails
FIRST_PORT = 20000                 # free_port() draws from [FIRST_PORT, the first port for outgoing connections)
_PORTS = random.SystemRandom()     # not the `random` module's state, which a caller may have seeded
STOP_SECONDS = 10.0                # after SIGTERM, how long the launcher waits for its children before SIGKILL
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
MAX_PARTS = 10_000                 # parts of the bridge's log read for its ticks (numbered in 4 digits)
LOGS_LOST = 3                      # exit code: the run went to its end, but logs were lost (module docstring)

# Run before each child's own program: set the parent-death signal (Linux prctl PR_SET_PDEATHSIG = 1), so the
# kernel sends the child SIGTERM if the launcher dies, even by SIGKILL; then exec the program in the same
# process. A launcher that died before the guard was set is seen by the parent pid having changed.
ORPHAN_GUARD = """import ctypes, os, signal, sys
try:
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)
except (OSError, AttributeError):
    pass
if os.getppid() != int(sys.argv[1]):
    sys.exit(0)
os.execv(sys.argv[2], sys.argv[2:])
"""


class Interrupted(RuntimeError):
    """The launcher was told to stop (SIGTERM, SIGINT, SIGHUP); `signum` says by what."""

    def __init__(self, signum: int, message: str) -> None:
        super().__init__(message)
        self.signum = signum


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
    kills a leaving vessel's agent with SIGKILL at its `leave_time`, as a vessel lost at sea; `run(restarts=)`
    restarts a vessel's agent without initial estimates (`stop_for_restart`, `start_again`). When the
    bridge has finished, the agents get SIGTERM and finish their logs. `on_time(fleet, sim_seconds)` lets a
    caller act during the mission (tests kill an agent with it); it is called on each sim clock message, from
    Zenoh's thread, so it must be quick and must not call Zenoh.
    """

    def __init__(self, scenario_path: Path, variant: str | None, out: Path, seed: int | None = None,
                 mode: str = "lockstep", gnss: str | None = None, vehicle: str = "sim") -> None:
        self.name, self.scenario = select_scenario(scenario_path, variant)
        if gnss is not None and self.scenario.world.sea is None:
            raise ConfigError(f"--gnss: scenario {self.name!r} is not in the sea mode (world.sea): the drivers stamp "
                              "their fixes on the wall clock, which only the sea mode's agents read (e.g. sea_trial)")
        self.gnss = gnss
        if vehicle == "mavlink" and self.scenario.world.sea is not None:
            raise ConfigError(f"scenario {self.name!r} runs in the sea mode, which --vehicle mavlink does not have")
        self.vehicle = vehicle
        # --vehicle mavlink: each vessel's UDP port between its driver and its stand-in (fleet_mavlink.py)
        self.udp_ports = {v.id: free_port() for v in self.scenario.world.vessels} if vehicle == "mavlink" else {}
        self.boats: dict[str, subprocess.Popen] = {}   # name (standin-<id>, driver-<id>) -> its process
        self.killed_at: dict[str, float] = {}     # vessel -> monotonic s when its agent was killed
        self.folder = out / f"{scenario_path.stem}-{self.name}-{datetime.now(timezone.utc):%Y%m%dT%H%M%S%f}"
        self.folder.mkdir(parents=True, exist_ok=False)
        self.mode, self.seed = mode, seed
        self.bridge_cmd = [sys.executable, "-m", "sim_bridge", "--scenario", str(scenario_path), "--variant",
                           self.name, "--config", str(self.folder / "bridge.yaml")]
        self.bridge_cmd += ["--seed", str(seed)] if seed is not None else []
        self.bridge_port = 0
        self._write_settings(free_port())
        self.bridge: subprocess.Popen | None = None
        self.agents: dict[str, subprocess.Popen] = {}
        self.drivers: dict[str, subprocess.Popen] = {}   # --gnss: id -> its usv-driver (GNSS only)
        self.killed: dict[str, float] = {}        # vessel -> sim time (s) when its agent was killed
        self.restarted: dict[str, list[tuple[float, float]]] = {}   # vessel -> (stopped, started again) sim times (s)
        self.down: set[str] = set()               # vessels whose agent is stopped for a restart, not yet started again
        self.names: dict[str, str] = {}           # vessel -> its current agent's process name, once restarted
        self.peak_memory: dict[str, float] = {}   # MB of resident memory at its highest, per process
        self.pids: dict[str, int] = {}            # every child started, by name (processes.json)
        self.planned_ticks = round(self.scenario.duration / self.scenario.world.dt) + 1
        self.signals: list[int] = []              # stop signals received, in order (interrupt())
        self.hard_killed: list[str] = []          # children that needed SIGKILL after SIGTERM
        self.consoles: dict[str, Console] = {}    # name -> the console of that process
        self.unwritten: list[str] = []            # what could not be written, one line each (a full disk)
        self.logs_lost: list[str] = []            # processes whose MCAP log said it was suspended
        self._disk_told = False
        self._sim_time = -math.inf
        self.clock_alarms: dict[str, dict[str, float]] = {}   # vessel -> its latest alarm, {source: offset s}
        self.clock_steps: dict[str, int] = {}                  # vessel -> steps of its clock its agent saw

    def _write_settings(self, bridge_port: int) -> None:
        """bridge.yaml and each agent-<id>.yaml, for a sim bridge listening on `bridge_port`.

        A scenario with a `sea` section runs as at sea: the bridge in real time from a wall-clock epoch a
        few seconds ahead (time for every process to come up), the agents on the wall clock, and each
        vessel's deployment estimates stamped in its own clock in the middle of the hold at the start,
        when every vessel is still."""
        self.bridge_port = bridge_port
        bridge = {"mode": self.mode, "zenoh": {"listen": [f"tcp/127.0.0.1:{bridge_port}"]},
                  "log": str(self.folder / "sim.mcap")}
        sea = self.scenario.world.sea
        configs = agent_configs(self.scenario, self.seed, self.folder, lambda v: {
            "listen": [AGENT_LISTEN], "connect": [f"tcp/127.0.0.1:{bridge_port}"]})
        if sea is not None:
            epoch_ns = time.time_ns() + int(SEA_LEAD * 1e9)
            bridge.update(mode="realtime", epoch_ns=epoch_ns)
            at_sea(self.scenario, self.seed, epoch_ns, configs)
        if self.gnss is not None:
            bridge["gnss"] = self._gnss_settings(bridge_port)
        if self.udp_ports:
            bridge["autopilots"] = sorted(self.udp_ports)
            for vessel, udp in self.udp_ports.items():
                (self.folder / f"driver-{vessel}.yaml").write_text(yaml.safe_dump(
                    fleet_mavlink.driver_settings(bridge_port, udp, AGENT_LISTEN)))
        (self.folder / "bridge.yaml").write_text(yaml.safe_dump(bridge))
        for vessel, settings in configs.items():
            (self.folder / f"agent-{vessel}.yaml").write_text(yaml.safe_dump(settings))

    def _gnss_settings(self, bridge_port: int) -> dict:
        """--gnss: the bridge's receivers (a pty per vessel and the target tag, linked in the run folder) and a
        GNSS-only driver's settings per id (driver-<id>.yaml), each logging its fixes to gnss-<id>.mcap."""
        make = {"plain": simulated_gnss.plain, "rtk": simulated_gnss.rtk}[self.gnss]
        links = {}
        for owner in [*(v.id for v in self.scenario.world.vessels), gnss_ptys.TARGET]:
            links[owner] = str(self.folder / f"gnss-{owner}.tty")
            driver = {"zenoh": {"connect": [f"tcp/127.0.0.1:{bridge_port}"]},
                      "gnss": {"device": links[owner], "baud": 115_200, "log": str(self.folder / f"gnss-{owner}.mcap")}}
            (self.folder / f"driver-{owner}.yaml").write_text(yaml.safe_dump(driver))
        return {"receiver": make(gnss_ptys.ORIGIN).model_dump(mode="json"), "links": links}

    def start_drivers(self) -> None:
        """--gnss: a usv-driver per vessel and the target tag, reading the bridge's pty (made before it listens)."""
        for owner in self.scenario.world.vessels if self.gnss is not None else []:
            self._start_driver(owner.id)
        if self.gnss is not None:
            self._start_driver(gnss_ptys.TARGET)

    def _start_driver(self, owner: str) -> None:
        self.drivers[owner] = self._start(f"driver-{owner}", [
            sys.executable, "-m", "driver_bridge", "--vessel", owner, "--config",
            str(self.folder / f"driver-{owner}.yaml")])

    def _start(self, name: str, command: list[str]) -> subprocess.Popen:
        guarded = [sys.executable, "-c", ORPHAN_GUARD, str(os.getpid()), *command]
        process = subprocess.Popen(guarded, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        self.consoles[name] = Console(self.folder / f"{name}.log", process.stdout, self._console_failed,
                                      lambda line, name=name: self._log_suspended(name, line))
        self.pids[name] = process.pid
        self.write_file("processes.json", json.dumps({"launcher": os.getpid(), **self.pids}, indent=2))
        return process

    def write_file(self, name: str, text: str) -> bool:
        """`text` to `name` in the run folder; False, and a line in `unwritten`, if the disk refuses it."""
        unwritten: list[str] = []
        _save(self.folder / name, text, unwritten)
        if unwritten:
            self._disk_full(OSError(unwritten[0]))
            self.unwritten.extend(unwritten)
        return not unwritten

    def _disk_full(self, error: OSError) -> None:
        if not self._disk_told:
            self._disk_told = True
            print(f"usv-fleet: cannot write in the run folder {self.folder} ({type(error).__name__}: {error}): "
                  f"the run goes on; each console is kept in memory (its last {TAIL_BYTES // 1024} kB) until "
                  "there is room, and the processes' logs suspend and resume by themselves", file=sys.stderr)

    def _console_failed(self, name: str, error: OSError) -> None:
        self._disk_full(error)

    def _log_suspended(self, name: str, line: str) -> None:
        """A process said its MCAP log is suspended (once per process): repeated on the launcher's stderr,
        which is not on the run folder's disk."""
        self.logs_lost.append(name)
        print(f"usv-fleet: {name}: {line}", file=sys.stderr)

    def interrupt(self, signum: int) -> None:
        """Stop the run (a signal handler's job; safe from any thread): the launcher's loop stops every
        process and `run()` raises Interrupted. A second call makes the stop a SIGKILL at once."""
        self.signals.append(signum)

    def _check_interrupted(self) -> None:
        if self.signals:
            name = signal.Signals(self.signals[0]).name
            raise Interrupted(self.signals[0], f"interrupted by {name} at sim time {max(self._sim_time, 0.0):.1f} s")

    def start_agent(self, vessel: str) -> None:
        name = self._name(vessel)
        self.agents[vessel] = self._start(name, [
            sys.executable, "-m", "agent", "--vessel", vessel, "--config", str(self.folder / f"{name}.yaml")])

    def _name(self, vessel: str) -> str:
        """The name of a vessel's agent process, of its settings and console log: `agent-<id>`, and
        `agent-<id>-restart<n>` after its n-th restart."""
        return self.names.get(vessel, f"agent-{vessel}")

    def stop_for_restart(self, vessel: str, session) -> None:
        """Stop a vessel's agent for a restart (`start_again` starts the new one), as a boat whose computer
        restarts mid-mission; the bridge's watchdog stops the vessel meanwhile, as a driver's would.

        SIGTERM, not SIGKILL: the agent finishes its log and its liveliness token goes with it at once, so the
        new agent's start-up check that its id is free passes (after SIGKILL the token would last until its
        Zenoh session times out, about 10 s, and the new agent would refuse to start). An agent that has not
        stopped STOP_SECONDS after SIGTERM gets SIGKILL, and this waits until `session` no longer sees its
        token."""
        old, name = self.agents[vessel], self._name(vessel)
        self.down.add(vessel)      # first: the polling loop must not take its exit for a failure
        self.restarted.setdefault(vessel, []).append((self._sim_time, math.nan))
        old.send_signal(signal.SIGTERM)
        try:
            old.wait(timeout=STOP_SECONDS)
        except subprocess.TimeoutExpired:
            old.kill()
            old.wait()
            self.hard_killed.append(name)
            alive = key(vessel, LIVELINESS)
            deadline = time.monotonic() + 3 * STOP_SECONDS
            while any(reply.ok is not None for reply in session.liveliness().get(alive, timeout=0.2)):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the liveliness token of {name}, killed for its restart, never lapsed")
                time.sleep(0.1)
        else:
            if old.returncode != 0:
                raise RuntimeError(self._exited(f"the agent of vessel {vessel}", name, old.returncode,
                                                "when told to stop for its restart"))

    def start_again(self, vessel: str) -> None:
        """Start a new agent for a vessel whose agent `stop_for_restart` stopped, without initial estimates:
        its settings, `agent-<id>-restart<n>.yaml`, are the vessel's without the `initial` section (a restarted
        boat knows nothing of the fleet as it was at launch, and the deploy tooling writes none) and with the
        default look for a namesake, and it logs
        to `agent-<id>-restart<n>.mcap`, so the first log stays whole."""
        restarts = self.restarted[vessel]
        restarts[-1] = (restarts[-1][0], self._sim_time)
        settings = read_yaml(self.folder / f"agent-{vessel}.yaml")
        settings.pop("initial", None)
        # The full look for a namesake (the agent's default), not the launch's short one: here an agent with
        # this id has just been, and a restart that waits that second rejoins as the restart tests measured.
        settings.pop("id_check", None)
        self.names[vessel] = name = f"agent-{vessel}-restart{len(restarts)}"
        settings["log"] = str(self.folder / f"{name}.mcap")
        (self.folder / f"{name}.yaml").write_text(yaml.safe_dump(settings))
        self.start_agent(vessel)
        self.down.discard(vessel)

    def kill(self, vessel: str) -> None:
        """SIGKILL a vessel's agent: no goodbye, its liveliness token vanishes with its session."""
        self._note_memory()
        self.killed[vessel] = self._sim_time   # first: the polling loop must never see it dead and not killed
        self.killed_at[vessel] = time.monotonic()
        self.agents[vessel].kill()

    def _start_boats(self, deadline: float) -> None:
        """--vehicle mavlink: each vessel's stand-in and driver, and wait until every driver has its autopilot's
        heartbeat (its console says so), so that the agents' first ticks find the odometry flowing."""
        for vessel, udp in self.udp_ports.items():
            self.boats[f"standin-{vessel}"] = self._start(f"standin-{vessel}", fleet_mavlink.standin_command(
                self.bridge_port, udp, vessel, self.folder / f"standin-{vessel}.jsonl"))
            self.boats[f"driver-{vessel}"] = self._start(f"driver-{vessel}", fleet_mavlink.driver_command(
                vessel, self.folder / f"driver-{vessel}.yaml"))
        waiting = [f"driver-{vessel}" for vessel in self.udp_ports]
        while waiting:
            self._check_interrupted()
            self._check_agents()
            if time.monotonic() > deadline:
                raise TimeoutError(f"no autopilot link for {', '.join(waiting)}")
            for name in list(waiting):
                if fleet_mavlink.LINK_UP in self.consoles[name].text:
                    waiting.remove(name)
            time.sleep(0.05)

    def run(self, timeout: float = 600.0, on_time=None,
            restarts: dict[str, tuple[float, float]] | None = None) -> Path:
        """Run the mission; the run folder. RuntimeError (saying which process and where its log is) when a
        process fails: the sim bridge cannot start or exits with an error, or an agent exits on its own.

        `restarts`: vessel -> (stop, start) sim times (s): its agent is stopped at `stop` and a new one without
        initial estimates started at `start` (or as soon as the old one has stopped, if that is later). In
        lockstep the sim runs on while the new process starts (about 1.5 s of wall time, tens of seconds of
        sim time), so the vessel is without an agent for at least `start` - `stop`, never exactly that."""

        def on_clock(sample) -> None:
            message, _ = decode(Clock, sample.payload.to_bytes())
            if message is not None:
                self._sim_time = max(self._sim_time, seconds(message.stamp_ns))
                if on_time is not None:
                    # Here rather than in the polling loop: in lockstep the sim runs ahead of any poll.
                    on_time(self, self._sim_time)

        deadline = time.monotonic() + timeout
        try:
            with self._start_bridge(on_clock, deadline) as session:
                self._start_boats(deadline)
                dt = self.scenario.world.dt
                pending = {v.id: v for v in self.scenario.world.vessels}
                leaving = {v.id: v.leave_time for v in self.scenario.world.vessels if v.leave_time is not None}
                restarting = dict(restarts or {})
                self.start_drivers()
                print(f"usv-fleet: the sim bridge and {sum(v.join_time == 0 for v in pending.values())} agents "
                      f"starting{' with their GNSS drivers' if self.drivers else ''}; run folder {self.folder}",
                      file=sys.stderr)
                print(f"usv-fleet: watch and command the fleet from another terminal: usv-op --connect "
                      f"tcp/127.0.0.1:{self.bridge_port} status (or hold, resume, set radius=R, view)",
                      file=sys.stderr)
                while self.bridge.poll() is None:
                    self._check_interrupted()
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
                    for vessel, (stop, start) in list(restarting.items()):
                        if vessel in self.killed:
                            del restarting[vessel]
                        elif vessel in self.down:
                            if now >= start - 1e-9:
                                self.start_again(vessel)
                                del restarting[vessel]
                        elif vessel in self.agents and now >= stop - 1e-9:
                            self.stop_for_restart(vessel, session)
                    self._note_memory()
                    time.sleep(0.02)
                self._check_interrupted()   # a SIGINT from the terminal reaches the bridge too: it stops early
                if self.bridge.returncode != 0:
                    raise RuntimeError(self._exited("the sim bridge", "bridge", self.bridge.returncode))
                self._check_agents()
                done = self.ticks_done()
                if done is None or done < self.planned_ticks:
                    raise RuntimeError(self._exited(
                        "the sim bridge", "bridge", 0,
                        f"after {'an unknown number of' if done is None else done} of {self.planned_ticks} ticks"))
        finally:
            self._stop()
        for vessel, process in self.agents.items():
            if vessel not in self.killed and vessel not in self.down and process.returncode != 0:
                raise RuntimeError(self._exited(f"the agent of vessel {vessel}", self._name(vessel),
                                                process.returncode, "when told to stop"))
        return self.folder

    def _start_bridge(self, on_clock, deadline: float):
        """Start the sim bridge and return the launcher's session (sim clock subscribed) once it reaches it.
        A bridge whose port was taken in the meantime is started again on a fresh port."""
        attempt = 1
        while True:
            self.bridge = self._start("bridge", self.bridge_cmd)
            # Zenoh retries a failed connect only after a second: connect once the bridge is listening.
            self._wait_for_port(deadline)
            session = zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{self.bridge_port}"])))
            try:
                session.declare_subscriber(CLOCK_KEY, on_clock)
                session.declare_subscriber(every("status"), self._on_status)
                if self._wait_for_bridge(session, deadline):
                    return session
            except BaseException:
                session.close()
                raise
            session.close()
            log = self.folder / "bridge.log"
            console = self.consoles.pop("bridge")
            console.close()
            failure = self._exited("the sim bridge", "bridge", self.bridge.returncode, "at start-up", console)
            if PORT_TAKEN not in console.text:
                raise RuntimeError(failure)
            if attempt == BRIDGE_ATTEMPTS:
                raise RuntimeError(f"{failure}; its port was taken {attempt} times in a row")
            with contextlib.suppress(OSError):    # a console never written (a full disk) has no file
                log.rename(self.folder / f"bridge-attempt{attempt}.log")
            taken = self.bridge_port
            self._write_settings(free_port())
            attempt += 1
            print(f"usv-fleet: port {taken} was taken before the sim bridge could listen on it; starting it "
                  f"again on port {self.bridge_port}", file=sys.stderr)

    def _on_status(self, sample) -> None:
        """Note a clock alarm or a clock step an agent's status reports (from Zenoh's thread: quick, so a
        status that reports neither, as the agent encodes it, is not decoded: lockstep sends thousands a
        second)."""
        payload = sample.payload.to_bytes()
        if payload.endswith(b'"clocks":[]}') and b'"clock_steps":0,' in payload:
            return
        message, _ = decode(Status, payload)
        if message is None:
            return
        if message.clocks:
            self.clock_alarms[message.sender] = {alarm.source: alarm.offset for alarm in message.clocks}
        steps = message.health.get("clock_steps", 0)
        if steps:
            self.clock_steps[message.sender] = max(steps, self.clock_steps.get(message.sender, 0))

    def clocks_verdict(self) -> str | None:
        """One line on the clocks that disagreed during the run (`clock_verdict`); None if none did."""
        return clock_verdict(dict(self.clock_alarms), dict(self.clock_steps))

    def _wait_for_port(self, deadline: float) -> None:
        """Until the bridge's port takes a TCP connection, or the bridge has exited (its caller finds out)."""
        while self.bridge.poll() is None and time.monotonic() < deadline:
            self._check_interrupted()
            try:
                with socket.create_connection(("127.0.0.1", self.bridge_port), timeout=0.1):
                    return
            except OSError:
                time.sleep(0.01)

    def _wait_for_bridge(self, session, deadline: float) -> bool:
        """Start no agent before this session reaches the bridge: Zenoh retries a connection with a growing
        delay, and a launcher that connects late misses the sim clock of the mission's first seconds.
        False if the bridge exits first."""
        while not list(session.info.peers_zid()):
            self._check_interrupted()
            if self.bridge.poll() is not None:
                return False
            if time.monotonic() > deadline:
                raise TimeoutError("the launcher could not reach the sim bridge")
            time.sleep(0.01)
        return True

    def _check_agents(self) -> None:
        """An agent runs until the launcher stops or kills it: one that exits on its own fails the launch (so
        does a vessel's stand-in or driver)."""
        for name, process in self.boats.items():
            if process.poll() is not None:
                raise RuntimeError(self._exited(name, name, process.returncode, "during the mission"))
        for vessel, process in self.agents.items():
            if vessel not in self.killed and vessel not in self.down and process.poll() is not None:
                raise RuntimeError(self._exited(f"the agent of vessel {vessel}", self._name(vessel),
                                                process.returncode, "during the mission"))
        for owner, process in self.drivers.items():
            # the bridge's ptys go with it at the end: a driver that loses its receiver then has done its part
            if process.poll() is not None and self._sim_time < self.scenario.duration - 1e-6:
                raise RuntimeError(self._exited(f"the GNSS driver of {owner}", f"driver-{owner}",
                                                process.returncode, "during the mission"))

    def _exited(self, who: str, name: str, code: int | None, when: str = "",
                console: Console | None = None) -> str:
        """`who` exited with `code` `when`, with the last line of its console and where its log is."""
        console = console or self.consoles.get(name)
        if console is not None:
            console.drain()
        line = console.last_line if console is not None else ""
        last = f": {line}" if line else ""
        log = self.folder / f"{name}.log"
        return f"{who} exited with code {code}{' ' + when if when else ''}{last} (see {log})"

    def _note_memory(self) -> None:
        for name, process in [("bridge", self.bridge), *((self._name(v), p) for v, p in self.agents.items())]:
            if process is not None and process.poll() is None:
                peak = _peak_resident_mb(process.pid)
                if peak is not None:
                    self.peak_memory[name] = max(self.peak_memory.get(name, 0.0), peak)

    def ticks_done(self) -> int | None:
        """The ticks the sim bridge simulated, from its log (its closing summary, else its ground truth) or
        from the last sim clock the launcher saw, whichever says more (a log cut by a full disk says less);
        None with neither."""
        summary, truth = self._bridge_log()
        if summary is not None and isinstance(summary.get("ticks"), int):
            return summary["ticks"]
        clocked = None if self._sim_time < 0 else round(self._sim_time / self.scenario.world.dt) + 1
        known = [n for n in (truth, clocked) if n is not None]
        return max(known) if known else None

    def bridge_summary(self) -> dict | None:
        """The sim bridge's closing summary (ticks, loop_seconds, cpu_seconds, ...); None if it wrote none."""
        return self._bridge_log()[0]

    def _bridge_log(self) -> tuple[dict | None, int | None]:
        """(the closing summary or None, ground-truth records counted until it) of sim.mcap and its later
        parts; (None, None) without a readable log."""
        path = self.folder / "sim.mcap"
        truth, read = 0, False
        try:
            for part in range(MAX_PARTS):
                file = part_path(path, part)
                if not file.is_file():
                    if part == 0:
                        continue     # an empty first part (the disk full from the start) is deleted
                    break
                read = True
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")   # a bridge killed hard leaves an unfinished file: read it
                    for topic, _, message in read_messages(file):
                        if topic == "/bridge/summary":
                            return message, truth
                        truth += topic == "/truth"
        except (OSError, ValueError):
            return None, None
        return None, truth if read else None

    def _stop(self) -> None:
        """SIGTERM to every child still running; SIGKILL to those still running STOP_SECONDS later (or at
        once on a second stop signal); wait for all of them."""
        self._note_memory()
        processes = {name: p for name, p in [*((self._name(v), p) for v, p in self.agents.items()),
                                             *((f"driver-{v}", p) for v, p in self.drivers.items()),
                                             ("bridge", self.bridge)] if p is not None}
        # The vessels' stand-ins and drivers last, as aboard: each driver sees its agent go and holds the boat.
        signals = len(self.signals)
        for phase in (processes, self.boats):
            self._stop_phase(phase, signals)
        for console in self.consoles.values():
            unwritten = console.close()
            if unwritten is not None:
                self.unwritten.append(unwritten)
        peaks = {"peak_resident_mb": dict(sorted(self.peak_memory.items()))}
        self.write_file("memory.json", json.dumps(peaks, indent=2))


    def _stop_phase(self, processes: dict[str, subprocess.Popen], signals: int) -> None:
        """SIGTERM to each of `processes` still running; SIGKILL to those still running STOP_SECONDS later (or
        at once once more than `signals` stop signals came); wait for all of them."""
        for process in processes.values():
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + STOP_SECONDS
        while any(p.poll() is None for p in processes.values()):
            if time.monotonic() > deadline or len(self.signals) > signals:
                for name, process in processes.items():
                    if process.poll() is None:
                        process.kill()
                        self.hard_killed.append(name)
                        print(f"usv-fleet: {name} had not stopped {STOP_SECONDS:.0f} s after SIGTERM (or a second "
                              "signal came): killed", file=sys.stderr)
                break
            time.sleep(0.02)
        for process in processes.values():
            process.wait()

class ClocksDisagree(RuntimeError):
    """The mission ran, but a vessel's clocks disagreed: an agent raised the alarm in its status."""


def clock_verdict(alarms: dict[str, dict[str, float]], steps: dict[str, int]) -> str | None:
    """What the agents' clock alarms say, in one line naming each vessel and offset; None without any.

    `alarms`: reporting vessel -> {source: offset s} (source: its own sensors, or a neighbour whose shares it
    sees so far off); `steps`: vessel -> steps of its computer's clock its agent detected. Of two vessels that
    see each other's clock off, the one more vessels report is named (the odd one out); a tie names both."""
    parts = []
    for vessel in sorted(steps):
        parts.append(f"vessel {vessel}'s clock stepped ({steps[vessel]} step{'s' * (steps[vessel] > 1)})")
    for vessel, sources in sorted(alarms.items()):
        if CLOCK_SOURCE_SENSORS in sources:
            offset = sources[CLOCK_SOURCE_SENSORS]
            way = "ahead of" if offset > 0 else "behind"
            parts.append(f"vessel {vessel}'s sensor clock {abs(offset):.2f} s {way} its agent's")
    seen_by: dict[str, dict[str, float]] = {}
    for reporter, sources in alarms.items():
        for source, offset in sources.items():
            if source != CLOCK_SOURCE_SENSORS:
                seen_by.setdefault(source, {})[reporter] = offset
    for source, reporters in sorted(seen_by.items()):
        if any(len(seen_by.get(reporter, {})) > len(reporters) for reporter in reporters):
            continue   # it sees them off because they see it off, and more see them: they are the odd one out
        offset = float(sorted(reporters.values())[len(reporters) // 2])
        way = "ahead of" if offset > 0 else "behind"
        parts.append(f"vessel {source}'s clock {abs(offset):.2f} s {way} that of "
                     f"vessel{'s' * (len(reporters) > 1)} {', '.join(sorted(reporters))}")
    return f"the clocks disagree: {'; '.join(parts)}" if parts else None


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
           timeout: float = 600.0, mode: str = "lockstep", vehicle: str = "sim", on_time=None) -> Path:
    """Run the fleet and analyse its logs; returns the run folder. A run that fails is analysed as cut short
    (`summary.md` says so), then its error raised. --vehicle mavlink: `mavlink.json` too (fleet_mavlink.py)."""
    fleet = Fleet(scenario_path, variant, out, seed, mode=mode, vehicle=vehicle)
    try:
        folder = fleet.run(timeout, on_time=on_time)
    except (RuntimeError, TimeoutError) as error:
        analyse_cut_short(fleet, str(error))
        raise
    analyse(folder, fleet.planned_ticks)
    if vehicle == "mavlink":
        fleet_mavlink.figures(folder, fleet.killed_at)
    verdict = fleet.clocks_verdict()
    if verdict is not None:
        raise ClocksDisagree(f"{folder}: {verdict}")
    return folder


def agent_configs(scenario, seed: int | None, folder: Path, zenoh) -> dict[str, dict]:
    """Each vessel's agent settings (NodeSettings as a mapping) for a simulated mission: sim clock, the
    scenario's parameters and initial estimates, its log in `folder`, and `zenoh(vessel)` as its Zenoh section
    (loopback peers for the launcher, clients of a router in tests/test_multihost.py). The look for another
    agent with the vessel's id is short (`SIM_ID_CHECK`): these links are up within milliseconds, and the
    launcher gives every agent its own id; the default second is for a boat's radio links."""
    agent_params = scenario.agent_params().model_dump(mode="json")
    starts = initial_settings(scenario, seed)
    return {v.id: {"clock": "sim", "zenoh": zenoh(v.id), "log": str(folder / f"agent-{v.id}.mcap"),
                   "id_check": SIM_ID_CHECK, "agent": agent_params, "initial": starts.get(v.id, {})}
            for v in scenario.world.vessels}


def at_sea(scenario, seed: int | None, epoch_ns: int, configs: dict[str, dict]) -> None:
    """Turn `agent_configs` into a sea-mode run's, in place: each agent on the wall clock read through its
    vessel's clock (`vessel_clock`: offset, drift and steps, the clock the sim bridge stamps its sensors with:
    aboard, the agent and the driver share the computer's clock), and its deployment estimates stamped in
    that clock in the middle of the hold at the start, when every vessel is still."""
    sea = scenario.world.sea
    clocks = SeaSensors(scenario.world, streams(scenario.seed if seed is None else seed).sea).clocks
    for vessel, settings in configs.items():
        clock = clocks[vessel]
        settings["clock"] = "wall"
        settings["vessel_clock"] = {"epoch_ns": epoch_ns, "offset": clock.offset, "drift": clock.drift,
                                    "steps": [list(step) for step in clock.steps]}
        if settings["initial"]:
            settings["initial"]["stamp"] = clock.stamp_ns(sea.hold_ms * 1e-3 / 2, epoch_ns) * 1e-9


def initial_settings(scenario, seed: int | None) -> dict[str, dict]:
    """Each agent's starting estimates, drawn as the in-process runner draws them (for the vessels there
    at the start; a later joiner starts from its first bearing and its neighbours' shares)."""
    random = streams(scenario.seed if seed is None else seed)
    world = World(scenario.world, random.world)
    return {v: start.model_dump(mode="json")
            for v, start in initial_estimates(scenario, world.truth(), random.initial).items()}


def analyse(folder: Path, planned: int | None = None, cut_short: str | None = None,
            logs_lost: list[str] | None = None) -> dict:
    """The paper's metrics from the run folder's logs; writes metrics.json, summary.md and the figures of
    `usv-log plot` (trajectories.png, errors.png, ranges.png). `planned`: the ticks the scenario has;
    `cut_short`: why the run ended early (None: it did not), said first in the summary; `logs_lost`: the
    processes whose logs were suspended by write errors (a full disk), said next. NotWritten (after trying
    every file) if some cannot be written."""
    run = load_run(folder)
    if not run.has_truth:
        raise LogError(f"{folder}: no ground truth (the sim bridge's /truth) in the logs")
    result = truth_metrics(run)      # r* as in force at each moment, the operator's sets included
    # Ticks missing from logs cut by a full disk were simulated all the same (the launcher counts them on the
    # sim clock): the run is complete, its logs are not.
    complete = cut_short is None and (planned is None or result["ticks"] >= planned or bool(logs_lost))
    result.update({"ticks_planned": planned, "complete": complete, "cut_short": cut_short})
    if logs_lost:
        result["logs_lost"] = sorted(set(logs_lost))
    unwritten: list[str] = []
    _save(folder / "metrics.json", json.dumps(result, indent=2), unwritten)
    before = {path: path.stat().st_mtime_ns for path in folder.glob("*.png")}
    try:
        figures = plot_run(run, folder)
    except OSError as error:
        figures = []
        unwritten.append(f"the figures ({error.strerror or error})")
        for path in folder.glob("*.png"):      # no half-written figure left behind
            if before.get(path) != path.stat().st_mtime_ns:
                path.unlink(missing_ok=True)
    settling = result["settling_time"]
    lost = ([f"**Logs were lost to write errors (a full disk)**: the logs of {', '.join(result['logs_lost'])}"
             " were suspended for a while (their `/log/gap` records say what and when); the figures below "
             f"cover what was logged: {result['ticks']} of the {planned} ticks simulated.", ""]
            if logs_lost else [])
    said = (_cut_short_lines(result["ticks"], planned, cut_short)
            if cut_short is not None or not logs_lost else [])
    lines = [f"# Fleet run {folder.name}", "", *said, *lost,
             f"{len(result['vessels'])} vessels, {result['ticks']} ticks"
             + (f" of {planned} planned" if planned is not None else "") + f", {circle_words(result)}", "",
             "| mean e_ij (m) | mean e_io (m) | mean e_c (m) | settling time (s) |", "|---|---|---|---|",
             (f"| {result['mean_e_ij']:.3f} | {result['mean_e_io']:.3f} | {result['mean_e_c']:.3f} | "
             f"{'never' if settling is None else f'{settling:.1f}'} |"), "",
             ("Computed from the logs alone: `sim.mcap` (ground truth) and `agent-<id>.mcap` (what each believed). "
             "`usv-log summary|metrics|plot` on this folder says more."), "",
             *(f"![{path.stem}]({path.name})" for path in figures)]
    _save(folder / "summary.md", "\n".join(lines) + "\n", unwritten)
    if unwritten:
        raise NotWritten(f"{folder}: not written: {', '.join(unwritten)}", "\n".join(lines) + "\n")
    return result


class NotWritten(OSError):
    """Summary files of a run that could not be written (a full disk): which ones, and the summary's text."""

    def __init__(self, message: str, summary: str = "") -> None:
        super().__init__(message)
        self.summary = summary


def _save(path: Path, text: str, unwritten: list[str]) -> None:
    """`text` to `path`; on an OSError, the file's name and why in `unwritten` (and no partial file left)."""
    try:
        path.write_text(text)
    except OSError as error:
        unwritten.append(f"{path.name} ({error.strerror or error})")
        try:
            path.unlink(missing_ok=True)
        except OSError:
            pass


def _cut_short_lines(done: int | None, planned: int | None, reason: str | None) -> list[str]:
    """The summary's first words on a run that did not run to its end; none for one that did."""
    if reason is None and (planned is None or done is None or done >= planned):
        return []
    share = f" ({100 * done / planned:.0f} %)" if done is not None and planned else ""
    count = f"{'an unknown number of' if done is None else done} of {planned} ticks{share}"
    return [f"**This run was cut short: {count}.** {reason or 'The sim bridge ended early.'}", "",
            "Every figure below covers only the ticks done; it is not the scenario's result.", ""]


def analyse_cut_short(fleet: Fleet, reason: str) -> None:
    """Analyse a run that failed or was interrupted, from whatever logs it left; where they cannot be
    analysed, a summary.md and metrics.json that say so. Never raises for a bad or missing log."""
    try:
        analyse(fleet.folder, fleet.planned_ticks, reason, fleet.logs_lost)
    except NotWritten as error:
        fleet.unwritten.append(str(error).split(": not written: ", 1)[-1])
    except Exception as error:  # noqa: BLE001  (a cut-short run's logs may be anything; the reason must get out)
        done = fleet.ticks_done()
        fleet.write_file("metrics.json", json.dumps(
            {"ticks": done, "ticks_planned": fleet.planned_ticks, "complete": False, "cut_short": reason},
            indent=2))
        fleet.write_file("summary.md", "\n".join([
            f"# Fleet run {fleet.folder.name}", "", *_cut_short_lines(done, fleet.planned_ticks, reason),
            f"No metrics: the logs could not be analysed ({type(error).__name__}: {error})."]) + "\n")


def _ticks_said(fleet: Fleet) -> str:
    done = fleet.ticks_done()
    return f"{'an unknown number of' if done is None else done} of {fleet.planned_ticks} ticks"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="usv-fleet", description="Run a simulated fleet as separate processes.")
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="the sim bridge and one agent process per vessel")
    run.add_argument("scenario", help="a scenario file, or the name of one in configs/scenarios/ "
                                      "(e.g. table2_estimators, cold_start)")
    run.add_argument("--variant", default=None,
                     help="variant of the file (default: the first that runs the product's default estimator, "
                          "raw_range; else the first)")
    run.add_argument("--duration", type=float, default=None, help="simulated seconds (default: the scenario's)")
    run.add_argument("--out", type=Path, default=Path("runs"), help="parent of the run folder")
    run.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    run.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep",
                     help="lockstep: as fast as the processes go; realtime: sim time at the wall clock's pace "
                          "(time to watch and command the fleet with usv-op)")
    run.add_argument("--vehicle", choices=("sim", "mavlink"), default="sim",
                     help="sim: the sim bridge moves the vessels; mavlink: each through an ArduPilot stand-in and "
                          "a usv-driver over MAVLink (docs/boats.md)")
    run.add_argument("--gnss", choices=("plain", "rtk"), default=None,
                     help="sea mode: a simulated field trial: the bridge's GGA (1.5 m or 2 cm) into a usv-driver "
                          "per vessel and the target, whose GNSS logs `usv-log metrics RUN --truth gnss` scores")
    args = parser.parse_args(argv)
    guard_stderr()
    started = time.monotonic()
    try:
        path = scenario_file(args.scenario)
        if args.duration is not None and not args.duration > 0:
            raise ConfigError(f"--duration {args.duration:g}: give the simulated seconds, more than 0")
        if args.duration is not None:    # a copy of the file with its base's duration changed, named as it is
            scratch = tempfile.mkdtemp(prefix="usv-fleet-")
            atexit.register(shutil.rmtree, scratch, True)    # the bridge reads the copy until the end
            path = with_duration(path, scratch, args.duration)
        variant = args.variant if args.variant is not None else default_variant(path)
        fleet = Fleet(path, variant, args.out, args.seed, mode=args.mode, gnss=args.gnss, vehicle=args.vehicle)
    except ConfigError as error:
        print(f"usv-fleet: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        print(f"usv-fleet: cannot write the run's settings in {args.out}: {error.strerror or error}",
              file=sys.stderr)
        return 1
    for signum in STOP_SIGNALS:
        signal.signal(signum, lambda signum, frame: fleet.interrupt(signum))
    try:
        fleet.run()
        launched = time.monotonic() - started
    except (RuntimeError, TimeoutError) as error:
        stopped = f"the sim bridge and {len(fleet.agents)} agent(s)" + (
            f" ({', '.join(fleet.hard_killed)} with SIGKILL)" if fleet.hard_killed else "")
        print(f"usv-fleet: {error}; stopped {stopped}", file=sys.stderr)
        for signum in STOP_SIGNALS:   # the processes are gone: a stop signal now cuts the analysis short
            signal.signal(signum, _raise_interrupted)
        analyse_cut_short(fleet, str(error))
        _say_losses(fleet)
        print(f"usv-fleet: run folder {fleet.folder}: cut short after {_ticks_said(fleet)} "
              f"({time.monotonic() - started:.1f} s)", file=sys.stderr)
        return 128 + error.signum if isinstance(error, Interrupted) else 1
    # From here the processes are gone: a stop signal ends the analysis at once.
    for signum in STOP_SIGNALS:
        signal.signal(signum, _raise_interrupted)
    summary_text = ""
    try:
        analyse(fleet.folder, fleet.planned_ticks, logs_lost=fleet.logs_lost)
        summary_text = (fleet.folder / "summary.md").read_text()
    except Interrupted as error:
        print(f"usv-fleet: {error} during the analysis; run folder {fleet.folder} (all {fleet.planned_ticks} "
              "ticks ran; `usv-log` analyses it)", file=sys.stderr)
        return 128 + error.signum
    except NotWritten as error:      # the disk is still full: the summary goes to stdout only
        fleet.unwritten.append(str(error).split(": not written: ", 1)[-1])
        summary_text = error.summary
    except (LogError, OSError) as error:
        fleet.unwritten.append(f"the summary: the logs could not be analysed ({type(error).__name__}: "
                               f"{' '.join(str(error).split())[:300]})")
    print(summary_text)
    if fleet.vehicle == "mavlink":
        print(f"usv-fleet: MAVLink: {fleet_mavlink.say(fleet_mavlink.figures(fleet.folder, fleet.killed_at))}",
              file=sys.stderr)
    verdict = fleet.clocks_verdict()
    summary = fleet.bridge_summary() or {}
    if summary.get("loop_seconds"):
        simulated = summary["ticks"] * fleet.scenario.world.dt
        print(f"usv-fleet: {simulated:.1f} s of mission in {summary['loop_seconds']:.2f} s of ticks: "
              f"{simulated / summary['loop_seconds']:.1f}x real time ({simulated / launched:.1f}x with the start-up "
              f"and shut-down of the processes, {launched:.1f} s)", file=sys.stderr)
    print(f"usv-fleet: run folder {fleet.folder} ({time.monotonic() - started:.1f} s)", file=sys.stderr)
    lost = _say_losses(fleet)
    if verdict is not None:
        print(f"usv-fleet: the run fails: {verdict}", file=sys.stderr)
        return 1
    if lost:
        print(f"usv-fleet: the mission ran to its end but logs were lost (exit {LOGS_LOST})", file=sys.stderr)
        return LOGS_LOST
    return 0


def _say_losses(fleet: Fleet) -> bool:
    """One line for what the run lost to write errors (a full disk), if anything; True if it lost any."""
    if not fleet.unwritten and not fleet.logs_lost:
        return False
    said = []
    if fleet.logs_lost:
        said.append(f"the logs of {', '.join(sorted(set(fleet.logs_lost)))} were suspended by write errors "
                    "(each log's /log/gap records say what was lost)")
    if fleet.unwritten:
        said.append("not written: " + "; ".join(fleet.unwritten))
    print(f"usv-fleet: {'; '.join(said)}", file=sys.stderr)
    return True


def _raise_interrupted(signum, frame) -> None:
    raise Interrupted(signum, f"interrupted by {signal.Signals(signum).name}")

