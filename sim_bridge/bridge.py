"""The sim bridge process: the world model behind the agents' Zenoh contract.

Each tick it publishes every live vessel's sensors (odometry, ranges, bearing, sonar) and then `sim/clock`,
takes the commands, and steps the world. Lockstep mode waits for a command of this tick from every live
agent (a liveliness token), up to a timeout that counts as a missed command; real-time mode steps every
dt of wall time. A command watchdog stops a vessel (zero surge, zero yaw rate) whose latest command is
older than `watchdog` seconds of sim time, as a real driver bridge must. Ground truth goes to an MCAP log.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from agent.contract import (
    CLOCK_KEY, LIVELINESS, Bearing, Clock, Cmd, Odometry, Ranges, Sonar, decode, encode, every, key,
    nanoseconds, seconds, vessel_of,
)
from agent.node import ZenohSettings, zenoh_config
from agent.params import ConfigError, PositiveFloat, StrictModel, load_yaml
from agent.tick_io import STOP, Command
from sim_bridge.scenario import Scenario, select_scenario
from sim_bridge.world import World


class BridgeSettings(StrictModel):
    mode: Literal["lockstep", "realtime"] = "lockstep"
    command_timeout: PositiveFloat = Field(2.0, description="lockstep: wall seconds to wait for a tick's commands")
    watchdog: PositiveFloat = Field(0.5, description="a vessel with no command this recent (sim s) stops")
    startup_timeout: PositiveFloat = Field(30.0, description="wall seconds to wait for the first agents")
    zenoh: ZenohSettings = ZenohSettings()
    log: str | None = Field(None, description="MCAP file of the ground truth")


class SimBridge:
    def __init__(self, scenario: Scenario, settings: BridgeSettings, seed: int | None = None) -> None:
        self.scenario = scenario
        self.settings = settings
        sequence = np.random.SeedSequence(scenario.seed if seed is None else seed)
        self.world = World(scenario.world, np.random.default_rng(sequence.spawn(1)[0]))
        self.alive: set[str] = set()
        self.commands: dict[str, Cmd] = {}
        self.missed_commands = 0
        self.watchdog_stops = 0
        self.rejected = 0
        self.ticks = 0
        self.stopping = threading.Event()
        self._lock = threading.Lock()
        self._arrived = threading.Condition(self._lock)
        self._seq: dict[str, int] = {}
        self.log = None
        if settings.log:
            from agent.mcap_log import McapLog

            self.log = McapLog(settings.log, metadata={"scenario": scenario.name, "mode": settings.mode})

    # ----- callbacks -----
    def _on_command(self, sample) -> None:
        vessel = vessel_of(str(sample.key_expr))
        message, _ = decode(Cmd, sample.payload.to_bytes())
        with self._arrived:
            if message is None or message.sender != vessel:
                self.rejected += 1
                return
            previous = self.commands.get(vessel)
            if previous is None or message.stamp_ns >= previous.stamp_ns:
                self.commands[vessel] = message
            self._arrived.notify_all()

    def _on_liveliness(self, sample) -> None:
        import zenoh

        vessel = vessel_of(str(sample.key_expr))
        if vessel is None:
            return
        with self._arrived:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(vessel)
            else:
                self.alive.discard(vessel)
            self._arrived.notify_all()

    # ----- the loop -----
    def run(self) -> None:
        import zenoh

        steps = int(round(self.scenario.duration / self.scenario.world.dt)) + 1
        with zenoh.open(zenoh_config(self.settings.zenoh)) as session:
            commands = session.declare_subscriber(every("cmd"), self._on_command)
            watcher = session.liveliness().declare_subscriber(every(LIVELINESS), self._on_liveliness, history=True)
            self._wait_for_agents()
            start = time.monotonic()
            for k in range(steps):
                if self.stopping.is_set():
                    break
                now = self.world.time
                stamp = nanoseconds(now)
                self._publish_sensors(session, stamp)
                session.put(CLOCK_KEY, encode(Clock(stamp_ns=stamp, seq=k)))
                if self.settings.mode == "lockstep":
                    self._wait_for_commands(stamp)
                else:
                    self.stopping.wait(max(0.0, start + (k + 1) * self.scenario.world.dt - time.monotonic()))
                self._log_truth(stamp)
                self.world.step(self._commands_now(now))
                self.ticks += 1
            commands.undeclare()
            watcher.undeclare()
        if self.log is not None:
            self.log.close()

    def _wait_for_agents(self) -> None:
        """Before tick 0, wait until every vessel present at the start has an agent alive."""
        deadline = time.monotonic() + self.settings.startup_timeout
        with self._arrived:
            while not self.stopping.is_set() and not set(self.world.live()) <= self.alive:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return
                self._arrived.wait(remaining)

    def _publish_sensors(self, session, stamp: int) -> None:
        for vessel, reading in self.world.sense().items():
            odometry = reading.odometry
            session.put(key(vessel, "sensor/odom"), encode(Odometry(
                stamp_ns=stamp, seq=self._next(vessel, "odom"), sender=vessel,
                position=tuple(float(v) for v in odometry.position), heading=float(odometry.heading))))
            session.put(key(vessel, "sensor/uwb"), encode(Ranges(
                stamp_ns=stamp, seq=self._next(vessel, "uwb"), sender=vessel,
                ranges={peer: float(r) for peer, r in reading.ranges.items()})))
            bearing = None
            if reading.bearing is not None:
                unit = np.asarray(reading.bearing, dtype=float)
                bearing = tuple(float(v) for v in unit / np.hypot(*unit))  # the contract carries a unit vector
            session.put(key(vessel, "sensor/bearing"), encode(Bearing(
                stamp_ns=stamp, seq=self._next(vessel, "bearing"), sender=vessel, bearing=bearing)))
            session.put(key(vessel, "sensor/sonar"), encode(Sonar(
                stamp_ns=stamp, seq=self._next(vessel, "sonar"), sender=vessel,
                points=[tuple(float(v) for v in p) for p in reading.obstacle_points])))

    def _wait_for_commands(self, stamp: int) -> None:
        deadline = time.monotonic() + self.settings.command_timeout
        with self._arrived:
            while not self.stopping.is_set():
                waiting = [v for v in self.world.live() if v in self.alive
                           and (v not in self.commands or self.commands[v].stamp_ns < stamp)]
                if not waiting:
                    return
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self.missed_commands += len(waiting)
                    return
                self._arrived.wait(remaining)

    def _commands_now(self, now: float) -> dict[str, Command]:
        commands = {}
        with self._lock:
            for vessel in self.world.live():
                message = self.commands.get(vessel)
                if message is None or now - seconds(message.stamp_ns) > self.settings.watchdog:
                    commands[vessel] = STOP
                    self.watchdog_stops += 1
                else:
                    commands[vessel] = Command(message.surge, message.yaw_rate)
        return commands

    def _log_truth(self, stamp: int) -> None:
        if self.log is None:
            return
        truth = self.world.truth()
        self.log.log("/truth", {
            "time": truth.time,
            "vessels": {v: {"position": [float(x) for x in p], "heading": float(truth.headings[v])}
                        for v, p in truth.positions.items()},
            "target": [float(x) for x in truth.target_position],
            "target_velocity": [float(x) for x in truth.target_velocity],
        }, stamp)

    def _next(self, vessel: str, stream: str) -> int:
        name = f"{vessel}/{stream}"
        value = self._seq.get(name, 0)
        self._seq[name] = value + 1
        return value


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="usv-sim", description="The sim bridge: the world behind the agents.")
    parser.add_argument("--scenario", required=True, type=Path, help="scenario YAML (configs/scenarios/...)")
    parser.add_argument("--variant", default=None, help="variant of the file (default: the first)")
    parser.add_argument("--config", default=None, help="bridge settings YAML (BridgeSettings)")
    parser.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    args = parser.parse_args(argv)
    try:
        _, scenario = select_scenario(args.scenario, args.variant)
        settings = load_yaml(BridgeSettings, args.config) if args.config else BridgeSettings()
    except ConfigError as error:
        print(f"usv-sim: {error}", file=sys.stderr)
        return 2
    bridge = SimBridge(scenario, settings, args.seed)

    def stop(signum, frame):  # noqa: ARG001
        bridge.stopping.set()

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    bridge.run()
    print(f"usv-sim: {bridge.ticks} ticks, {bridge.missed_commands} missed commands, "
          f"{bridge.watchdog_stops} watchdog stops, {bridge.rejected} refused", file=sys.stderr)
    return 0
