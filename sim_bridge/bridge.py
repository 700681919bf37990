"""The sim bridge process: the world model behind the agents' Zenoh contract.

Each tick it publishes every live vessel's sensors (odometry, ranges, bearing, sonar) and then `sim/clock`,
takes the commands, and steps the world. Lockstep mode waits for the command and the status of this tick
from every live agent (a liveliness token), up to a timeout that counts as a missed command; a vessel that
joins the world makes the tick wait for its agent as the first tick waits for everyone's. Real-time mode
steps every dt of wall time. A command watchdog stops a vessel (zero surge, zero yaw rate) whose latest
command arrived more than `watchdog` seconds ago by the bridge's own clock (sim time; wall time in the sea
mode), whatever stamp the agent wrote, as a real driver bridge must. A command stamped more than
`max_command_skew` from the bridge's clock (a status: ahead of it) is refused and counted.

The sea mode (a scenario's `world.sea`, real-time mode only) behaves like boats at sea, for agents on the
wall clock (`clock: wall`). Sim time 0 is the wall time `epoch_ns`. The world moves in short steps
(`sea.step_ms`, 10 ms by default; `sea_world`): each takes the latest commands (so a command acts within a
step of its arrival, as thrusters do), and `SeaSensors` gives every measurement of the step, each at its own
time, from the world interpolated between the step's ends. A small scheduler (one heap, on the bridge's
thread) publishes each message when its latency has passed, stamped in its vessel's own clock. The truth is
logged and `sim/clock` goes out once per tick (dt), for the launcher; wall-clock agents do not read the
clock, and the radio is not simulated (no packet loss). Vessels in `autopilots` are driven through MAVLink
stand-ins, which relay this world (sim_bridge/autopilot_relay.py).

The bridge also plays the radio between the vessels: each clock message says which shares of the tick
before each agent gets now (`lost_shares`: the scenario's packet loss, by a hash of the run's seed), so the
same messages are lost in every run with the same seed. Ground truth goes to an MCAP log.
"""

from __future__ import annotations

import argparse
import heapq
import itertools
import sys
import threading
import time
from contextlib import nullcontext
from pathlib import Path
from typing import Literal

import orjson
import zenoh
from pydantic import Field

from agent.config import ConfigError, PositiveFloat, StrictModel, load_yaml
from agent.contract import (
    CLOCK_KEY,
    LIVELINESS,
    MAX_SENSOR_STAGGER,
    TRUTH_KEY,
    Bearing,
    Clock,
    Cmd,
    Odometry,
    Ranges,
    Sonar,
    Status,
    decode,
    encode,
    every,
    key,
    vessel_of,
)
from agent.core.records import STOP, Command
from agent.runtime import foxglove
from agent.runtime.log_schema import BridgeSummary, CommandLatency, LoggedTruth
from agent.runtime.mcap_log import LogRotation, McapLog
from agent.runtime.process import guard_stderr, stop_on_signals
from agent.runtime.zenoh_session import ZenohSettings, open_session, zenoh_config
from sim_bridge.autopilot_relay import DRIVE_ALL, Drive, drives_command, pose_key
from sim_bridge.gnss_ptys import GnssPtys, SimulatedGnss
from sim_bridge.scenario import Scenario, select_scenario
from sim_bridge.world import Frame, Measurement, SeaSensors, World, lost_shares, sea_steps, sea_world, streams


class BridgeSettings(StrictModel):
    mode: Literal["lockstep", "realtime"] = "lockstep"
    command_timeout: PositiveFloat = Field(2.0, description="lockstep: wall seconds to wait for a tick's commands")
    watchdog: PositiveFloat = Field(
        0.5, description="a vessel whose latest command arrived longer ago than this (s, the bridge's clock) stops")
    # A status stamped further ahead is refused too; sim time, wall time in the sea mode.
    max_command_skew: PositiveFloat = Field(
        1.0, description="a command stamped further than this from the bridge's clock is refused and counted (s)")
    # usv-fleet run --vehicle mavlink: their odometry goes to the stand-in, their commands come from it
    autopilots: list[str] = Field([], description="vessels an ArduPilot stand-in drives (autopilot_relay.py)")
    # The bridge waits for it once the agents are ready; None: sim time 0 is the moment they are.
    epoch_ns: int | None = Field(
        None, ge=0, description="sea mode: the wall time of sim time 0 (ns since 1970); None: agents ready")
    startup_timeout: PositiveFloat = Field(30.0, description="wall seconds to wait for the first agents")
    zenoh: ZenohSettings = ZenohSettings()
    log: str | None = Field(None, description="MCAP file of the ground truth")
    log_rotation: LogRotation | None = Field(
        LogRotation(), description="start a new part of the log by size or time, keep a bounded total; null: "
                                   "one file")
    gnss: SimulatedGnss | None = Field(
        None, description="sea mode: each vessel's and the target's GGA into a pty a usv-driver reads")
    # The clock first, then each vessel's sensors in a slot of its own over this fraction of dt; 0: every vessel's
    # at once, before the clock. Boats sample on clocks of their own, and a laptop's agents woken at one instant
    # queue for its cores (12 agents on 2 cores: sensor-to-command p99 42-47 ms at once, 10-15 ms spread over
    # half of dt; docs/results/runtime_benchmark.md).
    stagger: float = Field(0.5, ge=0.0, le=MAX_SENSOR_STAGGER, allow_inf_nan=False,
                           description="real time: the fraction of dt the vessels' sensors are spread over")


class SimBridge:
    def __init__(self, scenario: Scenario, settings: BridgeSettings, seed: int | None = None) -> None:
        self.scenario = scenario
        self.settings = settings
        random = streams(scenario.seed if seed is None else seed)
        self.sea = None if scenario.world.sea is None else SeaSensors(scenario.world, random.sea)
        self.world = World(scenario.world if self.sea is None else sea_world(scenario.world), random.world)
        self.loss_seed = random.loss_seed
        if self.sea is not None and settings.autopilots:
            raise ConfigError(f"scenario {scenario.name!r} runs in the sea mode, which has no autopilot stand-ins")
        if self.sea is not None and settings.mode != "realtime":
            raise ConfigError(f"scenario {scenario.name!r} runs in the sea mode, which needs the real-time mode "
                              "(bridge setting mode: realtime) and agents on the wall clock")
        self.gnss = None
        if settings.gnss is not None:
            if self.sea is None:
                raise ConfigError("gnss: the simulated receivers need the sea mode (a scenario with world.sea): "
                                  "the driver stamps its fixes on the wall clock, which only the sea mode's agents read")
            try:
                self.gnss = GnssPtys(settings.gnss, scenario.seed if seed is None else seed)
            except OSError as error:
                raise ConfigError(f"gnss: cannot make the receivers' ptys: {error}") from None
        self.epoch_ns = settings.epoch_ns or 0   # wall time of sim time 0 in the sea mode (set at the start)
        self.alive: set[str] = set()
        self.commands: dict[str, Cmd] = {}
        self.statuses: dict[str, Status] = {}
        self.autopilots = set(settings.autopilots)
        self.drives: dict[str, Drive] = {}         # vessel -> its stand-in's latest Drive (autopilot_relay.py)
        self.drive_arrivals: dict[str, float] = {}   # vessel -> when it came, by _bridge_clock()
        self.missed_commands = 0
        self.startup_missing: set[str] = set()   # vessels whose agent was not ready when the bridge gave up waiting
        self.watchdog_stops = 0
        self.rejected = 0
        self.refused_stamps = 0            # commands (and statuses) refused for a stamp out of bounds
        self.arrivals: dict[str, float] = {}   # vessel -> when its kept command arrived, by _bridge_clock()
        self.ticks = 0
        self.loop_seconds = 0.0       # wall time from tick 0 to the end (after the agents' start-up)
        self.stopping = threading.Event()
        self._lock = threading.Lock()
        self._arrived = threading.Condition(self._lock)
        self._seq: dict[str, int] = {}
        self._publishers: dict[str, object] = {}
        self._next_scene = 0
        self._scene: foxglove.StaticScene | None = None
        self._radius = scenario.agent_params().control.radius   # r*, for the desired circle in the log
        # Sensor-to-command latency: wall time from publishing a vessel's sensors of the tick to its agent's command.
        self._tick_stamp: int | None = None
        self._sent: dict[str, float] = {}
        self._latency: dict[str, float] = {}
        self._waiting: set[str] | None = None   # vessels the tick in progress still waits for
        self.log = None
        if settings.log:
            # A write error (a full disk) suspends the log, said once on stderr; the simulation goes on.
            self.log = McapLog(settings.log, metadata={"scenario": scenario.name, "mode": settings.mode},
                               rotation=settings.log_rotation,
                               announce=lambda line: print(f"usv-sim: {line}", file=sys.stderr))

    # ----- callbacks -----
    def _on_command(self, sample) -> None:
        arrived = time.monotonic()
        message = self._keep(sample, Cmd, self.commands)
        if message is not None:
            with self._lock:
                sent = self._sent.get(message.sender)
                if message.stamp_ns == self._tick_stamp and message.sender not in self._latency and sent is not None:
                    self._latency[message.sender] = arrived - sent

    def _on_status(self, sample) -> None:
        self._keep(sample, Status, self.statuses)

    def _keep(self, sample, model, latest: dict):
        vessel = vessel_of(str(sample.key_expr))
        message, _ = decode(model, sample.payload.to_bytes())
        arrived = self._bridge_clock()
        with self._arrived:
            if message is None or message.sender != vessel:
                self.rejected += 1
                return None
            if not self._stamp_in_bounds(message):
                self.rejected += 1
                self.refused_stamps += 1
                return None
            previous = latest.get(vessel)
            # A latest one the vessel's clock has left behind (it stepped back past it) no longer holds newer
            # messages off: each is judged against the clock's window, as the agents' gate judges its marks.
            if previous is None or message.stamp_ns >= previous.stamp_ns or self._ahead(previous):
                latest[vessel] = message
                if model is Cmd:
                    self.arrivals[vessel] = arrived
            self._wake(vessel)
        return message

    def _wake(self, vessel: str) -> None:
        """While a tick waits for its answers, wake it once, when the last one is in (fewer context switches
        per tick); otherwise on every message (start-up waits on heartbeats). Caller holds the lock."""
        if self._waiting is None:
            self._arrived.notify_all()
        elif vessel in self._waiting and self._answered(vessel, self._tick_stamp):
            self._waiting.discard(vessel)
            if not self._waiting:
                self._arrived.notify_all()

    def _on_drive(self, sample) -> None:
        """A stand-in's Drive: what its vessel is driven at (kept per vessel; refused and counted if malformed,
        from another vessel, or for a vessel no stand-in drives)."""
        parts = str(sample.key_expr).split("/")
        message, _ = decode(Drive, sample.payload.to_bytes())
        with self._arrived:
            if message is None or message.sender != parts[2] or message.sender not in self.autopilots:
                self.rejected += 1
                return
            self.drives[message.sender] = message
            self.drive_arrivals[message.sender] = self._bridge_clock()
            self._wake(message.sender)

    def _bridge_clock(self) -> float:
        """The bridge's own time (s) that command arrivals are judged by: sim time, or in the sea mode the
        monotonic wall clock."""
        return time.monotonic() if self.sea is not None else self.world.time

    def _now_ns(self, message) -> int:
        """The clock a message is judged by: sim time, or in the sea mode the wall clock as its vessel reads
        it (a driver judges a command by its own clock: the vessel's, the agent's computer's, offset by the
        driver's own if it has one; a vessel whose clock is off is judged by it, as aboard)."""
        now_ns = self.world.time_ns if self.sea is None else time.time_ns()
        if self.sea is not None and self.epoch_ns and message.sender in self.sea.clocks:
            t = (now_ns - self.epoch_ns) * 1e-9
            now_ns = self.sea.stamp_ns(message.sender, t, self.epoch_ns, driver=isinstance(message, Cmd))
        return now_ns

    def _ahead(self, message) -> bool:
        """Stamped further than `max_command_skew` ahead of the clock it is judged by (`_now_ns`)."""
        return message.stamp_ns - self._now_ns(message) > self.settings.max_command_skew * 1e9

    def _stamp_in_bounds(self, message) -> bool:
        """A command stamped within `max_command_skew` of the bridge's clock (its sim time, or in the sea mode
        the wall clock as the vessel reads it); a status not further ahead. An absurd stamp (2^62 from a
        corrupt clock) would otherwise make a command look fresh forever, or hide every later one."""
        now_ns = self._now_ns(message)
        skew = self.settings.max_command_skew * 1e9
        ahead = message.stamp_ns - now_ns > skew
        return not ahead and (not isinstance(message, Cmd) or now_ns - message.stamp_ns <= skew)

    def _on_liveliness(self, sample) -> None:
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
        """The mission, tick by tick; the log is finished however the run ends, an exception included."""
        steps = int(round(self.scenario.duration / self.scenario.world.dt)) + 1
        try:
            with self.log if self.log is not None else nullcontext(), open_session(self.settings.zenoh) as session:
                subscribers = [session.declare_subscriber(every("cmd"), self._on_command),
                               session.declare_subscriber(every("status"), self._on_status),
                               *([session.declare_subscriber(DRIVE_ALL, self._on_drive)] if self.autopilots else [])]
                watcher = session.liveliness().declare_subscriber(every(LIVELINESS), self._on_liveliness,
                                                                  history=True)
                start, cpu_start = (self._run_sea if self.sea is not None else self._run_ticks)(session, steps)
                self.loop_seconds = time.monotonic() - start
                self._log_summary(time.process_time() - cpu_start)
                for entity in [*subscribers, watcher, *self._publishers.values()]:
                    entity.undeclare()
                self._publishers.clear()
        finally:
            if self.gnss is not None:
                self.gnss.close()

    def _run_ticks(self, session, steps: int) -> tuple[float, float]:
        """Lockstep or real time on sim stamps; (monotonic, CPU) time of tick 0."""
        start, cpu_start = time.monotonic(), time.process_time()
        previous_live: list[str] = []
        previous_stamp: int | None = None
        for k in range(steps):
            if self.stopping.is_set():
                break
            now, stamp, live = self.world.time, self.world.time_ns, self.world.live()
            joined = set(live) - set(previous_live)
            if joined and (k == 0 or self.settings.mode == "lockstep"):
                self._wait_for_agents(joined)
            if k == 0:  # the clock of the loop starts once the agents are up
                start, cpu_start = time.monotonic(), time.process_time()
            with self._lock:
                self._tick_stamp, self._sent, self._latency = stamp, {}, {}
            clock = encode(self._clock(k, stamp, previous_stamp, live, joined))
            if self.settings.mode == "realtime" and self.settings.stagger > 0.0:
                # The clock first: each agent then waits for its own sensors (agent/shell/gate.py deliver_for),
                # which come in their vessel's slot.
                self._publisher(session, CLOCK_KEY).put(clock)
                # Half a slot first: the clock's arrival in every agent is not the first vessel's sensors' wait.
                spacing = self.settings.stagger * self.scenario.world.dt / max(len(live), 1)
                self._publish_sensors(session, stamp, start + k * self.scenario.world.dt + 0.5 * spacing, spacing)
            else:
                self._publish_sensors(session, stamp)
                self._publisher(session, CLOCK_KEY).put(clock)
            if self.settings.mode == "lockstep":
                self._wait_for_answers(stamp)
            else:
                self.stopping.wait(max(0.0, start + (k + 1) * self.scenario.world.dt - time.monotonic()))
            self._log_tick(stamp)
            self._publish_truth(session, stamp)
            self.world.step(self._commands_now(now))
            self.ticks += 1
            previous_live, previous_stamp = live, stamp
        return start, cpu_start

    def _run_sea(self, session, steps: int) -> tuple[float, float]:
        """The sea mode, `steps` ticks: sim time t is wall time epoch + t. Each step of the world takes the
        latest commands and queues the step's measurements; until the next step the queue is published as they
        arrive. (monotonic, CPU) time of tick 0."""
        hold = self.scenario.world.sea.hold_ms * 1e-3
        m, dt = sea_steps(self.scenario.world), self.world.config.dt   # m steps of dt make a tick
        self._wait_for_agents(set(self.world.live()))
        start = self._start_epoch()
        cpu_start = time.process_time()
        if self.log is not None:
            self.log.log("/bridge/sea", {"epoch_ns": self.epoch_ns, "clocks": {
                v: {"offset_s": c.offset, "drift_ppm": c.drift * 1e6} for v, c in self.sea.clocks.items()}},
                self.epoch_ns)
        queue: list[tuple[float, int, Measurement]] = []
        order = itertools.count()     # ties in arrival keep the order of measurement
        previous_stamp: int | None = None
        for n in range(steps * m):
            if self.stopping.is_set():
                break
            stamp, live = self.world.time_ns, self.world.live()
            if n % m == 0:    # a tick
                self._publisher(session, CLOCK_KEY).put(encode(Clock(
                    stamp_ns=stamp, seq=n // m, previous_ns=previous_stamp, vessels=live)))
                self._log_tick(self.epoch_ns + stamp)
                self._publish_truth(session, self.epoch_ns + stamp)
                if self.gnss is not None:
                    self.gnss.emit(truth_record(self.world.truth()), self.epoch_ns + stamp)
                self.ticks += 1
                previous_stamp = stamp
            if self.world.time < hold - 1e-9:
                commands = {vessel: STOP for vessel in live}
            else:
                commands = self._commands_now(time.monotonic())
            before = Frame.of(self.world)
            self.world.step(commands)
            for measurement in self.sea.measure(before, Frame.of(self.world)):
                heapq.heappush(queue, (measurement.arrival, next(order), measurement))
            # Until the next step: each message as its time comes (one wait per message, no thread).
            end = (n + 1) * dt
            while not self.stopping.is_set():
                due = queue[0][0] if queue and queue[0][0] < end else end
                self.stopping.wait(max(0.0, start + due - time.monotonic()))
                if not queue or queue[0][0] >= end:
                    break
                self._publish_measurement(session, heapq.heappop(queue)[2])
        return start, cpu_start

    def _start_epoch(self) -> float:
        """Set `epoch_ns`, waiting for the configured one if it is still to come; the monotonic time of it.
        A configured epoch already past is replaced by now (deployment estimates stamped for it go stale)."""
        now_ns, now = time.time_ns(), time.monotonic()
        wanted = self.settings.epoch_ns
        if wanted is not None and wanted < now_ns:
            print(f"usv-sim: the agents were ready {(now_ns - wanted) * 1e-9:.2f} s after epoch_ns; sim time 0 is "
                  "now instead", file=sys.stderr)
            wanted = None
        self.epoch_ns = now_ns if wanted is None else wanted
        if self.settings.epoch_ns is not None:   # the agents' clocks count from the epoch they were given
            self.sea.lag = (self.epoch_ns - self.settings.epoch_ns) * 1e-9
        start = now + (self.epoch_ns - now_ns) * 1e-9
        self.stopping.wait(max(0.0, start - time.monotonic()))
        return start

    def _publish_measurement(self, session, measurement: Measurement) -> None:
        """One sea-mode message on its vessel's key, stamped in the vessel's clock; `seq` counts in the order of
        publication, as a driver numbers what it sends."""
        vessel, values = measurement.vessel, measurement.values
        stamp = self.epoch_ns + measurement.stamp_ns
        if measurement.sensor == "odometry":
            self._put(session, vessel, Odometry(
                stamp_ns=stamp, seq=self._next(vessel, "odom"), sender=vessel,
                position=tuple(float(v) for v in values["position"]), heading=float(values["heading"])))
            self._put(session, vessel, Sonar(stamp_ns=stamp, seq=self._next(vessel, "sonar"), sender=vessel,
                                             points=[tuple(float(v) for v in p) for p in values["points"]]))
        elif measurement.sensor == "uwb":
            self._put(session, vessel, Ranges(stamp_ns=stamp, seq=self._next(vessel, "uwb"), sender=vessel,
                                              ranges={peer: float(r) for peer, r in values["ranges"].items()}))
        else:
            bearing = values["bearing"]
            self._put(session, vessel, Bearing(stamp_ns=stamp, seq=self._next(vessel, "bearing"), sender=vessel,
                                               bearing=None if bearing is None else tuple(float(v) for v in bearing)))

    def _put(self, session, vessel: str, message) -> None:
        topic = {Odometry: "sensor/odom", Ranges: "sensor/uwb", Bearing: "sensor/bearing", Sonar: "sensor/sonar"}
        self._publisher(session, key(vessel, topic[type(message)])).put(encode(message))

    def _clock(self, k: int, stamp: int, previous_stamp: int | None, live: list[str], joined: set[str]) -> Clock:
        """Tick k, and which shares of tick k - 1 reach whom now (the runner's rule, `lost_shares`)."""
        with self._lock:
            senders = [j for j in live if previous_stamp is not None and j in self.statuses
                       and self.statuses[j].stamp_ns == previous_stamp and self.statuses[j].shared]
        lost = lost_shares(self.loss_seed, senders, live, joined, k, self.scenario.world.packet_loss)
        return Clock(stamp_ns=stamp, seq=k, previous_ns=previous_stamp, vessels=live, senders=senders, lost=lost,
                     lockstep=self.settings.mode == "lockstep")

    def _wait_for_agents(self, vessels: set[str]) -> None:
        """Wait until each of `vessels` (the ones there at the start, or a joiner) has an agent alive that
        sees every other live agent (its status says so): then the links a tick needs are all up."""
        deadline = time.monotonic() + self.settings.startup_timeout
        live = set(self.world.live())

        def ready(vessel: str) -> bool:
            status = self.statuses.get(vessel)
            return (vessel in self.alive and status is not None
                    and set(status.peers) >= (live & self.alive) - {vessel})

        with self._arrived:
            while not self.stopping.is_set() and not all(ready(v) for v in vessels):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    missing = sorted(v for v in vessels if not ready(v))
                    self.startup_missing.update(missing)
                    print(f"usv-sim: no agent ready for vessel(s) {', '.join(missing)} after "
                          f"{self.settings.startup_timeout:.0f} s; going on without (they will be stopped by the "
                          "watchdog)", file=sys.stderr)
                    return
                self._arrived.wait(remaining)

    def _publish_sensors(self, session, stamp: int, first: float | None = None, spacing: float = 0.0) -> None:
        """Every vessel's sensors of the tick stamped `stamp`; with `first`, the m-th vessel's not before
        `first` + m `spacing` (monotonic s). A vessel's messages are built first: its latency is timed from their
        puts, as a boat's from its driver's, not from the simulator's work of sensing and encoding."""
        for m, (vessel, reading) in enumerate(self.world.sense().items()):
            odometry = reading.odometry
            bearing = None if reading.bearing is None else tuple(float(v) for v in reading.bearing)
            pose = Odometry(stamp_ns=stamp, seq=self._next(vessel, "odom"), sender=vessel,
                            position=tuple(float(v) for v in odometry.position), heading=float(odometry.heading))
            puts = [(pose_key(vessel), pose)] if vessel in self.autopilots else []   # to its stand-in (its driver
            for topic, message in (                                                  # gives the agent odometry)
                    *((("sensor/odom", pose),) if vessel not in self.autopilots else ()),
                    ("sensor/uwb", Ranges(stamp_ns=stamp, seq=self._next(vessel, "uwb"), sender=vessel,
                                          ranges={peer: float(r) for peer, r in reading.ranges.items()})),
                    ("sensor/bearing", Bearing(stamp_ns=stamp, seq=self._next(vessel, "bearing"), sender=vessel,
                                               bearing=bearing)),
                    ("sensor/sonar", Sonar(stamp_ns=stamp, seq=self._next(vessel, "sonar"), sender=vessel,
                                           points=[tuple(float(v) for v in p) for p in reading.obstacle_points]))):
                puts.append((key(vessel, topic), message))
            payloads = [(self._publisher(session, key_expr), encode(message)) for key_expr, message in puts]
            if first is not None:
                self.stopping.wait(max(0.0, first + m * spacing - time.monotonic()))
            with self._lock:
                self._sent[vessel] = time.monotonic()
            for publisher, payload in payloads:
                publisher.put(payload)

    def _publisher(self, session, key_expr: str):
        """A declared publisher per key: a put on it skips the key's resolution a session.put repeats. It
        blocks rather than drops when the link is congested: the world model decides what is lost."""
        publisher = self._publishers.get(key_expr)
        if publisher is None:
            publisher = self._publishers[key_expr] = session.declare_publisher(
                key_expr, congestion_control=zenoh.CongestionControl.BLOCK)
        return publisher

    def _wait_for_answers(self, stamp: int) -> None:
        """Lockstep: wait for every live agent's command and status of this tick (the status comes after
        the agent's share, and says whether it shared)."""
        deadline = time.monotonic() + self.settings.command_timeout
        with self._arrived:
            try:
                while not self.stopping.is_set():
                    waiting = {v for v in self.world.live() if v in self.alive and not self._answered(v, stamp)}
                    if not waiting:
                        return
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        self.missed_commands += len(waiting)
                        return
                    self._waiting = waiting
                    self._arrived.wait(remaining)
            finally:
                self._waiting = None

    def _answered(self, vessel: str, stamp: int | None) -> bool:
        """The vessel's command and (ticked) status of the tick stamped `stamp` are in; caller holds the lock."""
        command, status = self.commands.get(vessel), self.statuses.get(vessel)
        return (stamp is not None and command is not None and status is not None and status.ticked
                and command.stamp_ns >= stamp and status.stamp_ns >= stamp
                and (vessel not in self.autopilots or drives_command(self.drives.get(vessel), command)))

    def _commands_now(self, now: float) -> dict[str, Command]:
        """Each live vessel's latest command, or a stop when it arrived more than `watchdog` before `now`
        (both by `_bridge_clock()`), or never. A vessel a stand-in drives goes as its latest Drive says."""
        commands = {}
        with self._lock:
            for vessel in self.world.live():
                if vessel in self.autopilots:
                    drive, arrived = self.drives.get(vessel), self.drive_arrivals.get(vessel, 0.0)
                    message = None if drive is None else Command(*drive.drive)
                else:
                    message, arrived = self.commands.get(vessel), self.arrivals.get(vessel, 0.0)
                if message is None or now - arrived > self.settings.watchdog:
                    commands[vessel] = STOP
                    self.watchdog_stops += 1
                else:
                    commands[vessel] = Command(message.surge, message.yaw_rate)
        return commands

    def _log_tick(self, stamp: int) -> None:
        if self.log is None:
            return
        with self._lock:
            latency = {v: round(value * 1e3, 4) for v, value in self._latency.items()}
        self.log.log("/bridge/command_latency", {"milliseconds": latency}, stamp, schema=CommandLatency)
        truth = self.world.truth()
        self._log_frames(stamp, truth)
        self.log.log("/truth", truth_record(truth), stamp, schema=LoggedTruth)

    def _publish_truth(self, session, stamp: int) -> None:
        """The ground truth on `sim/truth`, for the operator's live view (`usv-op view`): in real time only,
        where someone can watch; a lockstep run is for its logs, and saves the message."""
        if self.settings.mode == "realtime":
            record = {"stamp_ns": stamp, **truth_record(self.world.truth())}
            self._publisher(session, TRUTH_KEY).put(orjson.dumps(record))

    def _log_summary(self, cpu_seconds: float) -> None:
        """The run as a whole, once at the end (built as the model, so a wrong value fails here)."""
        if self.log is None:
            return
        self.log.log("/bridge/summary", BridgeSummary(
            ticks=self.ticks, loop_seconds=self.loop_seconds, cpu_seconds=cpu_seconds,
            missed_commands=self.missed_commands, startup_missing=sorted(self.startup_missing),
            watchdog_stops=self.watchdog_stops, refused=self.rejected), self.epoch_ns + self.world.time_ns)

    def _log_frames(self, stamp: int, truth) -> None:
        """Ground truth for Foxglove's 3D panel: the vessels and the target in the `world` frame and, once a
        second, the islands and the desired circle (agent/runtime/foxglove.py)."""
        links = foxglove.world_links(truth.positions, truth.headings, truth.target_position)
        self.log.log("/tf", foxglove.transforms(stamp, links), stamp, schema=foxglove.FrameTransforms)
        if stamp >= self._next_scene:
            self._next_scene = stamp + foxglove.SCENE_PERIOD_NS
            if self._scene is None:
                self._scene = foxglove.StaticScene([
                    *foxglove.target_entities(0, "target", self._radius, "target"),
                    *foxglove.island_entities(0, "world", self.scenario.world.islands)])
            self.log.log("/scene", self._scene.at(stamp), stamp, schema=foxglove.SceneUpdate)

    def _next(self, vessel: str, stream: str) -> int:
        name = f"{vessel}/{stream}"
        value = self._seq.get(name, 0)
        self._seq[name] = value + 1
        return value


def truth_record(truth) -> dict:
    """The ground truth of one tick as logged on `/truth` (LoggedTruth) and published on `sim/truth`."""
    return {
        "time": truth.time,
        "vessels": {v: {"position": [float(x) for x in p], "heading": float(truth.headings[v])}
                    for v, p in truth.positions.items()},
        "target": [float(x) for x in truth.target_position],
        "target_velocity": [float(x) for x in truth.target_velocity],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="usv-sim", description="The sim bridge: the world behind the agents.")
    parser.add_argument("--scenario", required=True, type=Path, help="scenario YAML (configs/scenarios/...)")
    parser.add_argument("--variant", default=None, help="variant of the file (default: the first)")
    parser.add_argument("--config", default=None, help="bridge settings YAML (BridgeSettings)")
    parser.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    args = parser.parse_args(argv)
    guard_stderr()
    try:
        _, scenario = select_scenario(args.scenario, args.variant)
        settings = load_yaml(BridgeSettings, args.config) if args.config else BridgeSettings()
        zenoh_config(settings.zenoh)   # a bad ZENOH_CONFIG file or override: one line now, not a traceback later
        bridge = SimBridge(scenario, settings, args.seed)
    except ConfigError as error:
        print(f"usv-sim: {error}", file=sys.stderr)
        return 2

    stop_on_signals(bridge.stopping)
    bridge.run()
    simulated = bridge.ticks * scenario.world.dt
    factor = simulated / bridge.loop_seconds if bridge.loop_seconds > 0 else float("nan")
    print(f"usv-sim: {bridge.ticks} ticks, {bridge.missed_commands} missed commands, "
          f"{bridge.watchdog_stops} watchdog stops, {bridge.rejected} refused "
          f"({bridge.refused_stamps} for their stamp); "
          f"{simulated:.1f} s simulated in {bridge.loop_seconds:.2f} s of wall time ({factor:.1f}x real time)"
          + (f"; no agent came for {', '.join(sorted(bridge.startup_missing))}" if bridge.startup_missing else "")
          + (f"; {bridge.log.dropped} log message(s) lost to write errors" if bridge.log and bridge.log.dropped else "")
          + (f"; GNSS sentences written {dict(bridge.gnss.written)}, dropped {dict(bridge.gnss.dropped)}"
             if bridge.gnss is not None else ""),
          file=sys.stderr)
    return 0
