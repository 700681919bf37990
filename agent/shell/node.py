"""The agent process of one vessel: a thin Zenoh shell around the core's `step`.

One Zenoh session (peer mode, explicit endpoints, multicast scouting off unless configured). Subscriber
callbacks only hand payloads to the `InputGate` (no Zenoh calls, no blocking). The tick runs on sim time
(one tick per `sim/clock` message) or on a monotonic 10 Hz timer whose overruns are counted; each tick
takes the gate's snapshot, calls the pure core, and publishes the share, the command (express, real-time
priority) and the status. On sim time the clock message also says which neighbours' shares of the tick
before the simulated radio delivers; in lockstep the tick waits (bounded) for those to arrive. Neighbours
are discovered and forgotten through their liveliness tokens, and only a vessel with a live token counts
as one; the table of tokens is bounded and ranked by evidence, and an id that comes back proves itself
before its shares steer this vessel (agent/shell/peers.py). SIGINT and SIGTERM stop it cleanly.

What it survives:
- Any exception in a tick (`_tick`): counted (`tick_errors`), told on stderr and logged on `/<id>/errors`
  with the tick's inputs (the first of each kind, then at most one every `ERROR_REPEAT` seconds), and the
  tick commands STOP. The core's state is kept (one bad tick usually leaves it usable); after
  `rebuild_after` failed ticks in a row it is rebuilt with no initial estimates (the deployment's are stale
  by then), as a vessel joining late starts. A command that is not finite or not within the controller's
  limits (U_v, U_omega_c + omega*) is refused the same way: STOP goes out instead.
- The sim bridge going away and coming back (`SimClock`): while no clock comes for `clock_timeout`, the
  agent sends a heartbeat status every 0.1 s and judges no stamps; when the new clock starts again from 0,
  the gate forgets the old timeline and the core is rebuilt from the node's initial estimates: a restarted
  simulation is a new mission. Its ticks go to a new log file (`<name>-mission2.mcap`, ...), so each file
  replays on its own.
- A second agent with its vessel id: at start-up it looks for the id's liveliness token for `id_check`
  seconds and refuses to start (one line, exit 2) if another agent holds it.
"""

from __future__ import annotations

import contextlib
import math
import sys
import threading
import time
import traceback
from pathlib import Path

import zenoh

from agent.contract import (
    CLOCK_KEY,
    CLOCK_SOURCE_SENSORS,
    FLEET_PREFIX,
    LIVELINESS,
    MISSION_PREFIX,
    Clock,
    ClockOffset,
    Cmd,
    Status,
    WeakestPair,
    decode,
    encode,
    every,
    key,
    message_from_share,
    nanoseconds,
    seconds,
    vessel_of,
)
from agent.core.build import InitialEstimates, initial_state
from agent.core.observability import MIRROR_AMBIGUOUS, UNOBSERVABLE
from agent.core.records import STOP, Command, TickInputs, TickOutput
from agent.core.snapshot import state_to_json
from agent.core.state import VesselState
from agent.core.step import step
from agent.runtime.log_schema import CoreState
from agent.runtime.mcap_log import McapLog
from agent.runtime.process import startup_error, stop_on_signals, vessel_process
from agent.runtime.zenoh_session import SessionError, open_session
from agent.shell.gate import OWN_TOPICS, InputGate, SimClock
from agent.shell.mission import MissionOrders
from agent.shell.peers import RANGED_WITHIN, PeerTable
from agent.shell.reaction import ReactionTimes
from agent.shell.settings import NodeSettings
from agent.shell.tick_log import TickLogger, log_topic
from agent.shell.wall_clock import WallTimeline

HEARTBEAT = 0.1        # s between heartbeat statuses while there is no clock
ERROR_REPEAT = 10.0    # s: a kind of tick error already told is told again at most this often
MAX_ERROR_KINDS = 64   # kinds of tick error remembered (each a place in the code; more is a storm)
LIMIT_SLACK = 1e-9     # relative: a command this far beyond a limit is rounding, not a fault
MAX_MISSION_LOGS = 20  # log files of one run at most (one per sim restart): a forged clock cannot fill the disk


class StartupError(RuntimeError):
    """The agent cannot start (its log cannot be written, its vessel id is taken): one line says why."""


class CommandOutOfLimits(ValueError):
    """The core's command is not finite or beyond the controller's saturation limits."""


class AgentNode:
    def __init__(self, vessel_id: str, settings: NodeSettings, state: VesselState | None = None) -> None:
        self.id = vessel_id
        self.settings = settings
        self.params = settings.agent
        self.state = state or initial_state(vessel_id, settings.agent, settings.initial)
        self._live_view: frozenset[str] = frozenset()   # what the gate reads from Zenoh's threads
        self.peers = PeerTable(lambda peer: self.gate.ranged_within(peer, self._input_time(), RANGED_WITHIN))
        self.gate = InputGate(vessel_id, max_age=settings.max_input_age, max_future=settings.max_input_future,
                              known_peers=lambda: self._live_view, hold_shares=settings.clock == "sim",
                              max_rate=settings.max_input_rate)
        self.clock = SimClock(settings.agent.dt, settings.max_clock_jump, settings.clock_confirm,
                              settings.clock_timeout)
        vessel_clock = settings.vessel_clock
        system = time.time if vessel_clock is None else lambda: vessel_clock.read(time.time_ns())
        self.timeline = WallTimeline(system, on_step=self._clock_stepped)
        self._clocks_told: dict[str, float] = {}   # source -> the offset last told on stderr
        self.orders = MissionOrders(vessel_id, settings.max_input_age, settings.max_input_future, self.gate.count)
        self.ticks = 0
        self.overruns = 0
        self.tick_errors = 0
        self.core_rebuilds = 0
        self.sim_restarts = 0
        self.shares_unsent = 0
        self.core_seconds = 0.0   # tick thread CPU inside the core's step since the first tick
        self.reaction = ReactionTimes()
        self.reaction_cpu = ReactionTimes()    # the tick thread's CPU from its tick's start to the command's put
        self._triggered: float | None = None   # monotonic time the tick to come was triggered (clock or timer)
        self.stopping = threading.Event()
        self._sim_tick = threading.Event()
        self._restart_pending = False
        self._failed_in_a_row = 0
        self._error_kinds: dict[str, list] = {}   # kind -> [count, monotonic time last told]
        self._last_shared = False
        self._id_seen = False     # another agent's token with our id, seen before we declared ours
        self._seq = {"cmd": 0, "share": 0, "status": 0}
        self.log = None          # opened by `run` once the vessel id is known to be free (`open_log`)
        self.tick_log = None
        self.log_errors = 0
        self._restarts_told = -math.inf

    def open_log(self) -> None:
        """The MCAP log of this mission, if the settings name one: the settings go in whole (with the logged
        inputs they are all `usv-log replay` needs). After a sim restart, a new file: `<name>-mission<n>.mcap`.
        StartupError (one line) if it cannot be written. `run` opens it only after the id check, so that an
        agent refused for a taken id never truncates the log of the agent that has it."""
        if not self.settings.log:
            if not self.sim_restarts:
                print(f"usv-agent {self.id}: no MCAP log: the settings name none (log: FILE, e.g. "
                      "agent-{vessel}-{start}.mcap, records the mission for usv-log)", file=sys.stderr)
            return
        start = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        path = Path(self.settings.log.replace("{vessel}", self.id).replace("{start}", start))
        metadata = {"vessel": self.id, "clock": self.settings.clock, "settings": self.settings.model_dump_json()}
        if self.sim_restarts:
            path = path.with_name(f"{path.stem}-mission{self.sim_restarts + 1}{path.suffix}")
            metadata["mission"] = str(self.sim_restarts + 1)
        try:
            self.log = McapLog(path, metadata=metadata, rotation=self.settings.log_rotation,
                               announce=lambda line: print(f"usv-agent {self.id}: {line}", file=sys.stderr))
        except OSError as error:
            raise StartupError(f"cannot write its log {path}: {error.strerror or error}") from None
        self.tick_log = TickLogger(self.log, self.id, self.settings.agent.control.radius)

    # ----- clock -----
    def now(self) -> float:
        """The agent's time: the latest sim clock (0 before the first), or the system clock."""
        if self.settings.clock == "sim":
            latest = self.clock.latest
            return 0.0 if latest is None else seconds(latest.stamp_ns)
        return self.timeline.read()

    def _input_time(self) -> float | None:
        """The time to judge an input's stamp by; None on sim time while there is no clock to judge by: before
        the first (an agent started mid-mission gets its first tick's sensors before that tick's clock), and
        while the clock is silent (a restarted sim bridge publishes its first sensors before its clock)."""
        if self.settings.clock == "sim":
            if self.clock.silent():
                return None
            return seconds(self.clock.latest.stamp_ns)
        return self.timeline.read()

    def _clock_stepped(self, delta: float) -> None:
        """This computer's clock stepped (`WallTimeline`): the agent's time holds on, the own sensors' stamps
        (this computer's clock) are taken back by the step, and the operator is told."""
        self.gate.clock_stepped(delta)
        print(f"usv-agent {self.id}: this computer's clock stepped {'back' if delta < 0 else 'forward'} "
              f"{abs(delta):.3f} s (against the monotonic clock; {self.timeline.steps} steps so far): the "
              f"agent keeps its time continuous with the fleet's and takes its sensors' stamps "
              f"{abs(delta):.3f} s {'forward' if delta < 0 else 'back'}", file=sys.stderr)

    def _clock_alarms(self) -> list[ClockOffset]:
        """The clocks that disagree with the agent's, for the status; each told on stderr once (again when it
        moves by more than a tenth of a second, or is over)."""
        alarms = [ClockOffset(source=source, offset=offset) for source, offset in self.gate.clock_alarms()]
        now = {alarm.source: alarm.offset for alarm in alarms}
        for source, offset in now.items():
            told = self._clocks_told.get(source)
            if told is None or abs(told - offset) > 0.1:
                self._clocks_told[source] = offset
                print(f"usv-agent {self.id}: {clock_alarm_words(source, offset)}", file=sys.stderr)
        for source in [s for s in self._clocks_told if s not in now]:
            del self._clocks_told[source]
            whose = "sensor" if source == CLOCK_SOURCE_SENSORS else f"vessel {source}"
            print(f"usv-agent {self.id}: the {whose} clock agrees with this computer's again",
                  file=sys.stderr)
        return alarms

    def _latest_clock(self) -> Clock | None:
        return self.clock.latest

    # ----- callbacks: hand over and return -----
    def _on_input(self, sample) -> None:
        self.gate.offer(str(sample.key_expr), sample.payload.to_bytes(), self._input_time())

    def _on_mission(self, sample) -> None:
        try:
            self.orders.offer(str(sample.key_expr), sample.payload.to_bytes(), self._input_time(),
                              nanoseconds(self.now()), lambda: self._live_view)
        except Exception as error:  # noqa: BLE001  (a callback must never raise into Zenoh)
            self.gate.count("internal", f"mission: {type(error).__name__}: {error}")

    def _on_clock(self, sample) -> None:
        arrived = time.monotonic()
        try:
            message, reason = decode(Clock, sample.payload.to_bytes())
            if message is None:
                self.gate.count("malformed_clock", reason)
                return
            verdict = self.clock.offer(message)
            if verdict == "restart":
                # Now, on this thread: the new timeline's shares may come before the tick thread wakes.
                self.gate.reset(message.stamp_ns)
                self._restart_pending = True
            elif verdict not in ("first", "tick"):
                self.gate.count(verdict, f"sim/clock: stamp {message.stamp_ns}")
                return
            self._triggered = arrived
            self._sim_tick.set()
        except Exception as error:  # noqa: BLE001  (a callback must never raise into Zenoh)
            self.gate.count("internal", f"sim/clock: {type(error).__name__}: {error}")

    def _on_liveliness(self, sample) -> None:
        peer = vessel_of(str(sample.key_expr))
        if peer is None:
            return
        if peer == self.id:
            if sample.kind == zenoh.SampleKind.PUT:
                self._id_seen = True   # ours once we have declared it; before that, another agent's
            return
        if sample.kind == zenoh.SampleKind.PUT:
            if peer in self._live_view:
                return
            admitted, evicted = self.peers.declare(peer)
            for other in evicted:
                self.gate.forget(other)
            if not admitted:
                self.gate.count("too_many_peers", f"liveliness: {peer}")
                return
            self.gate.forget(peer)   # a new liveliness session: nothing of an earlier one counts
        else:
            self.peers.undeclare(peer)
            self.gate.forget(peer)
        self._live_view = self.peers.live()

    # ----- the loop -----
    def run(self, max_ticks: int | None = None) -> None:
        """Tick until stopped (or `max_ticks`); the log is finished however the loop ends, an exception
        included, so that the file holds every tick up to the failure."""
        try:
            self._run(max_ticks)
        finally:
            if self.log is not None:
                self.log.close()

    def _run(self, max_ticks: int | None) -> None:
        with open_session(self.settings.zenoh) as session:
            watcher = session.liveliness().declare_subscriber(every(LIVELINESS), self._on_liveliness, history=True)
            self._check_id_free(session)
            if self.log is None:
                self.open_log()
            # One subscriber for all four sensors: each subscriber is a thread of zenoh-python's, and a message
            # handed across threads costs more CPU than decoding it (docs/results/runtime_benchmark.md).
            subscribers = [session.declare_subscriber(f"{FLEET_PREFIX}/{self.id}/sensor/*", self._on_input),
                           session.declare_subscriber(every("share"), self._on_input),
                           session.declare_subscriber(f"{MISSION_PREFIX}/*", self._on_mission)]
            if self.settings.clock == "sim":
                subscribers.append(session.declare_subscriber(CLOCK_KEY, self._on_clock))
            token = session.liveliness().declare_token(key(self.id, LIVELINESS))
            # On sim time nothing may be dropped by Zenoh (the simulated radio decides what is lost, and
            # lockstep waits for every message); at sea a late command or share is worth less than a new one.
            congestion = (zenoh.CongestionControl.BLOCK if self.settings.clock == "sim"
                          else zenoh.CongestionControl.DROP)
            publishers = {
                "cmd": session.declare_publisher(key(self.id, "cmd"), express=True, priority=zenoh.Priority.REAL_TIME,
                                                 congestion_control=congestion),
                # Our own subscription to every vessel's share would hand ours straight back to us.
                "share": session.declare_publisher(key(self.id, "share"), congestion_control=congestion,
                                                   allowed_destination=zenoh.Locality.REMOTE),
                "status": session.declare_publisher(key(self.id, "status"), congestion_control=congestion),
            }
            period = self.settings.agent.dt
            deadline = started = opened = time.monotonic()
            cpu_started = time.process_time()
            sensors_told = False
            while not self.stopping.is_set() and (max_ticks is None or self.ticks < max_ticks):
                try:
                    if not sensors_told and time.monotonic() - opened >= self.settings.no_sensor_warning:
                        sensors_told = True
                        with contextlib.suppress(Exception):   # a word to the operator is not worth the vessel
                            self._tell_if_no_sensors()
                    clock = None
                    if self.settings.clock == "sim":
                        if not self._sim_tick.wait(timeout=HEARTBEAT):
                            if self.ticks == 0 or self.clock.silent():
                                self._heartbeat(publishers)
                            continue
                        self._sim_tick.clear()
                        clock = self._latest_clock()
                        if self._restart_pending:
                            self._restart()
                        if clock.vessels is not None and self.id not in clock.vessels:
                            # The sim says this vessel is not (or no longer) in the world: no tick, and the shares
                            # held for that tick are dropped, not hoarded.
                            self.gate.deliver_shares(clock.previous_ns, set())
                            continue
                    else:
                        deadline += period
                        delay = deadline - time.monotonic()
                        if delay > 0:
                            self.stopping.wait(delay)
                        else:
                            self.overruns += 1
                            deadline = time.monotonic()  # do not try to catch up a backlog of ticks
                        self._triggered = time.monotonic()
                    if self.ticks == 0:  # what the run costs from its first tick, not the wait before it
                        started, cpu_started, self.core_seconds = time.monotonic(), time.process_time(), 0.0
                    self._tick(publishers, clock)
                except Exception as error:  # noqa: BLE001  (whatever one pass of the loop meets, the loop goes on)
                    self._tick_failed(error, None, 0)
                    self.stopping.wait(HEARTBEAT)
            self._log_summary(time.monotonic() - started, time.process_time() - cpu_started)
            # Finished before Zenoh is: whatever happens to the process while its session closes, the log
            # is whole.
            if self.log is not None:
                self.log.close()
            token.undeclare()
            watcher.undeclare()
            for subscriber in subscribers:
                subscriber.undeclare()

    def _check_id_free(self, session) -> None:
        """StartupError if another agent holds this vessel's liveliness token: two agents commanding one
        vessel would alternate on its `cmd`. Looks for `id_check` seconds, for the links to other peers come
        up in that time (a router answers at once)."""
        deadline = time.monotonic() + self.settings.id_check
        alive = key(self.id, LIVELINESS)
        while True:
            taken = self._id_seen or any(reply.ok is not None for reply in session.liveliness().get(alive, timeout=0.2))
            if taken:
                raise StartupError(
                    f"vessel id {self.id} is taken: another agent holds the liveliness token {alive} (if that "
                    "agent was just stopped hard, its token lasts until its session times out, about 10 s)")
            if time.monotonic() >= deadline:
                return
            self.stopping.wait(min(0.1, max(0.0, deadline - time.monotonic())))

    def _tell_if_no_sensors(self) -> None:
        """One line on stderr if no own sensor message has come since start-up (a vessel id no bridge
        publishes for commands STOP for ever otherwise, silently); if they come but their stamps are refused,
        that instead, with how far their clock runs from ours."""
        if any(self.gate.accepted[topic] for topic in OWN_TOPICS):
            return
        if self.gate.offsets.heard(CLOCK_SOURCE_SENSORS):
            offset = self.gate.offsets.median(CLOCK_SOURCE_SENSORS)
            why = "" if offset is None else f": {clock_alarm_words(CLOCK_SOURCE_SENSORS, offset)}"
            refused = {k: v for k, v in self.gate.rejected.items() if k in ("stale", "future")}
            print(f"usv-agent {self.id}: sensor messages arrive but none was taken in "
                  f"{self.settings.no_sensor_warning:g} s{why} (refused {refused}); commanding STOP until "
                  "they are", file=sys.stderr)
            return
        clock = self._latest_clock()
        if self.settings.clock == "sim" and clock is None:
            print(f"usv-agent {self.id}: no sim/clock in {self.settings.no_sensor_warning:g} s: this agent ticks "
                  "on sim time (clock: sim) and no simulation is running (start usv-sim, or clock: wall on a "
                  "boat); commanding STOP until one does", file=sys.stderr)
            return
        world = ""
        if clock is not None and clock.vessels is not None and self.id not in clock.vessels:
            world = f"; the sim clock lists vessels {', '.join(clock.vessels[:10]) or 'none'}, not {self.id}"
        print(f"usv-agent {self.id}: no sensor data on {FLEET_PREFIX}/{self.id}/sensor/* in "
              f"{self.settings.no_sensor_warning:g} s: no bridge publishes for vessel {self.id}{world}; "
              f"commanding STOP until one does", file=sys.stderr)

    def _restart(self) -> None:
        """The simulation restarted (a new timeline of sim/clock): a new mission. The gate has already
        forgotten the old timeline (in `_on_clock`); the core is rebuilt from the node's initial estimates and
        the ticks go to a new log file."""
        self._restart_pending = False
        self.sim_restarts += 1
        self.orders.reset()
        self.params = self.settings.agent   # a new mission starts from the configured circle
        self.state = initial_state(self.id, self.params, self.settings.initial)
        self._failed_in_a_row = 0
        if self.sim_restarts <= 3 or time.monotonic() - self._restarts_told >= ERROR_REPEAT:
            self._restarts_told = time.monotonic()
            print(f"usv-agent {self.id}: the simulation restarted (sim/clock began a new timeline at "
                  f"{seconds(self.clock.latest.stamp_ns):.3f} s; {self.sim_restarts} restarts so far): starting "
                  "the mission again", file=sys.stderr)
        if self.log is not None and self.sim_restarts < MAX_MISSION_LOGS:
            self._log_summary(0.0, 0.0)
            self.log.close()
            self.log = None
            try:
                self.open_log()
            except StartupError as error:
                self.log_errors += 1
                print(f"usv-agent {self.id}: no log for the new mission: {error}", file=sys.stderr)
        elif self.log is not None and self.sim_restarts == MAX_MISSION_LOGS:
            print(f"usv-agent {self.id}: {MAX_MISSION_LOGS} restarts of the simulation: the next missions go on in "
                  f"{self.log.path.name}", file=sys.stderr)

    def _log_summary(self, wall_seconds: float, cpu_seconds: float) -> None:
        """The run as a whole: what the process cost (all its threads, Zenoh's included) and what it refused."""
        if self.log is None:
            return
        try:
            self.tick_log.summary(nanoseconds(self.now()), ticks=self.ticks, overruns=self.overruns,
                                  refused=self.gate.rejected, loop_seconds=wall_seconds, cpu_seconds=cpu_seconds,
                                  core_cpu_seconds=self.core_seconds, reaction_ms=self.reaction.summary(),
                                  reaction_cpu_ms=self.reaction_cpu.summary())
        except Exception:  # noqa: BLE001  (the summary must not stop a clean shutdown)
            self.log_errors += 1

    def _heartbeat(self, publishers) -> None:
        """While there is no clock (before the first sim tick, or while the sim bridge is gone): a status that
        says this agent is up and who it sees, so that a sim bridge starts (again) only once the fleet's links
        are up. It is stamped 0, not with a tick's time: a restarted bridge's clock starts again from 0, and a
        heartbeat stamped later would hide the new ticks' statuses from it. `shared` repeats the last tick's,
        so that a heartbeat taken for the status of a tick at 0 says the same about its share."""
        try:
            publishers["status"].put(encode(Status(
                stamp_ns=0, seq=self._next("status"), sender=self.id, phase=0.0, command=(0.0, 0.0),
                shared=self._last_shared, peers=sorted(self._live_view), ticked=False,
                health=self._health(None), **self._operator_view())))
        except Exception as error:  # noqa: BLE001  (a heartbeat lost is not worth the process)
            self._tick_failed(error, None, 0)

    def _deliver_shares(self, clock: Clock) -> None:
        """Sim time: take the shares of the tick before that the sim's radio delivers to this vessel, once this
        tick's own sensors are in; in lockstep, first wait (bounded) for those shares too. In real time, each
        neighbour's newest share up to the tick before (`InputGate.deliver_shares`, `lost`)."""
        # In real time only this tick's own sensors are worth a short wait (they were published just before
        # the clock), and each neighbour's newest share that has come is taken, late or not, unless the radio
        # lost it: at sea a late share is still the neighbour's latest word.
        wait = self.settings.share_wait if clock.lockstep else 0.25 * self.settings.agent.dt
        sensed = clock.vessels is not None and self.id in clock.vessels
        lost = None if clock.lockstep else {sender for sender, to in clock.lost if to == self.id}
        self.gate.deliver_shares(clock.previous_ns, clock.delivered_to(self.id), wait,
                                 clock.stamp_ns if sensed else None, wait_for_shares=clock.lockstep,
                                 lost=lost)

    def _tick(self, publishers, clock: Clock | None = None) -> None:
        """One tick: on sim time `clock` is the sim/clock message it answers, on wall time None. Whatever
        fails in it, the tick publishes a command (STOP if the core did not give a sound one) and a status."""
        tick_cpu = time.thread_time()
        now = self.now() if clock is None else seconds(clock.stamp_ns)
        stamp = nanoseconds(now)
        inputs = None
        self.params = self.orders.apply(self.params, stamp, vessels=len(self._live_view) + 1)
        try:
            if clock is not None:
                self._deliver_shares(clock)
            inputs = self.peers.vet(self.gate.snapshot(now))   # a vessel id come back proves itself first
            core_started = time.thread_time()
            self.state, output = step(self.params, self.state, inputs)
            self.peers.learn(inputs, output.record)
            self.core_seconds += time.thread_time() - core_started
            self._check_command(output.command)
            self._failed_in_a_row = 0
            if self.orders.held:   # the operator's hold: STOP, as the watchdog would; the core keeps estimating
                output = TickOutput(STOP, output.share, output.record)
        except Exception as error:  # noqa: BLE001  (one bad tick must not take the vessel's control down)
            output = TickOutput(STOP, None, None)
            self._tick_failed(error, inputs, stamp)
        # The command goes first: it is what the thrusters wait for (sensor to command), and building the share
        # costs more than the command. The status goes last: once the bridge has it, the share is on its way.
        # The driver judges a command by its own clock: on the wall clock, stamped in it (the agent's time
        # plus the correction its sensors' stamps need; the same unless the driver's clock is off or this
        # one stepped).
        driver_stamp = stamp if clock is not None else nanoseconds(now + self.gate.offsets.applied)
        command = Cmd(stamp_ns=driver_stamp, seq=self._next("cmd"), sender=self.id,
                      surge=float(output.command.surge), yaw_rate=float(output.command.yaw_rate))
        wire = {"cmd": encode(command)}
        publishers["cmd"].put(wire["cmd"])
        self.reaction_cpu.add(time.thread_time() - tick_cpu)
        if self._triggered is not None:
            self.reaction.add(time.monotonic() - self._triggered)
        shared = False
        if output.share is not None:
            try:
                publishers["share"].put(encode(message_from_share(output.share, self._seq["share"])))
                self._next("share")
                shared = True
            except Exception as error:  # noqa: BLE001  (an estimate beyond the contract's limits: not sent, counted)
                self.shares_unsent += 1
                if self.shares_unsent == 1:
                    print(f"usv-agent {self.id}: a share not sent (the contract refuses it): "
                          f"{' '.join(str(error).split())[:300]}", file=sys.stderr)
        self._last_shared = shared
        record = output.record
        try:
            status = Status(
                stamp_ns=stamp, seq=self._seq["status"], sender=self.id,
                phase=record.phase if record is not None else 0.0,
                command=(command.surge, command.yaw_rate), shared=shared,
                peers=sorted(self._live_view),
                target=None if record is None or record.target_state is None
                else tuple(float(v) for v in record.target_state),
                health=self._health(record), weakest_pair=weakest_pair(record),
                **self._operator_view(),
            )
        except Exception:  # noqa: BLE001  (a non-finite estimate: the status goes without it)
            status = Status(stamp_ns=stamp, seq=self._seq["status"], sender=self.id, phase=0.0,
                            command=(command.surge, command.yaw_rate), shared=shared, peers=sorted(self._live_view),
                            health=self._health(None), **self._operator_view())
        self._next("status")
        wire["status"] = encode(status)
        publishers["status"].put(wire["status"])
        if self.log is not None:
            try:
                logged = inputs if inputs is not None else TickInputs(time=now, odometry=None)
                self.tick_log.tick(stamp, logged, output, command, status, wire)
                for order, ack, received in self.orders.judged():
                    self.tick_log.mission(stamp, order, ack, received)
                every = self.settings.snapshot_every
                if every and self.ticks % every == 0:
                    # After this tick: replay can start at the next one (agent/core/snapshot.py).
                    self.log.log(log_topic(self.id, "state"), state_to_json(self.state), stamp,
                                 schema=CoreState)
            except Exception as error:  # noqa: BLE001  (a bad value must not stop the vessel's control)
                # A write error (a full disk) is not raised: the log counts it, says so and resumes by itself.
                self.log_errors += 1
                if self.log_errors == 1:
                    print(f"usv-agent {self.id}: logging failed: {type(error).__name__}: {error}", file=sys.stderr)
        self.ticks += 1

    @property
    def limits(self) -> tuple[float, float]:
        """U_v and U_omega_c + |omega*| of the parameters ticking now (a mission `set` changes omega*)."""
        control = self.params.control
        return control.max_speed, control.max_correction_yaw_rate + abs(control.yaw_rate)

    def _operator_view(self) -> dict:
        """What every status says for the operator: a hold in force, the circle steered to, the answers."""
        return {"held": self.orders.held, "radius": self.params.control.radius, "mission": self.orders.acks(),
                "clocks": self._clock_alarms()}

    def _check_command(self, command: Command) -> None:
        """CommandOutOfLimits unless the command is finite and within U_v and U_omega_c + omega* (formation.py's
        `surge_and_yaw_rate` never gives more; this is the shell's own guard on what goes to the thrusters)."""
        max_surge, max_yaw_rate = self.limits
        surge, yaw_rate = float(command.surge), float(command.yaw_rate)
        if not (math.isfinite(surge) and math.isfinite(yaw_rate)
                and abs(surge) <= max_surge * (1 + LIMIT_SLACK) and abs(yaw_rate) <= max_yaw_rate * (1 + LIMIT_SLACK)):
            raise CommandOutOfLimits(f"command ({surge!r} m/s, {yaw_rate!r} rad/s) beyond "
                                     f"({max_surge:g} m/s, {max_yaw_rate:g} rad/s)")

    def _tick_failed(self, error: Exception, inputs: TickInputs | None, stamp: int) -> None:
        """Count a failed tick; tell it (stderr, and `/<id>/errors` with its inputs) the first time for its kind
        and then at most every ERROR_REPEAT s; rebuild the core after `rebuild_after` failures in a row."""
        self.tick_errors += 1
        self._failed_in_a_row += 1
        kind = error_kind(error)
        now = time.monotonic()
        entry = self._error_kinds.get(kind)
        if entry is None and len(self._error_kinds) < MAX_ERROR_KINDS:
            entry = self._error_kinds[kind] = [0, -math.inf]
        tell = entry is not None and now - entry[1] >= ERROR_REPEAT
        if entry is not None:
            entry[0] += 1
        if tell:
            entry[1] = now
            text = f"{type(error).__name__}: {error}"[:500]
            print(f"usv-agent {self.id}: tick at {seconds(stamp):.3f} s failed ({kind}, {entry[0]} so far): {text}; "
                  "commanding STOP", file=sys.stderr)
            if self.log is not None:
                try:
                    self.tick_log.error(stamp, kind, text, entry[0], inputs)
                except Exception:  # noqa: BLE001
                    self.log_errors += 1
        if self._failed_in_a_row >= self.settings.rebuild_after:
            # The same failure tick after tick: the state is beyond use. Start again as a late joiner does;
            # the deployment's initial estimates are stale by now.
            self.state = initial_state(self.id, self.params, InitialEstimates())
            self.core_rebuilds += 1
            self._failed_in_a_row = 0
            print(f"usv-agent {self.id}: {self.settings.rebuild_after} failed ticks in a row: core rebuilt "
                  f"({self.core_rebuilds} so far)", file=sys.stderr)

    def _health(self, record) -> dict[str, int]:
        health = dict(record.health if record is not None else {})
        if record is not None:
            # This tick's pairs whose relative motion leaves them short of observable (gauges, not counts).
            verdicts = [n.observability for n in record.neighbours.values()]
            health.update(pairs_mirror_ambiguous=verdicts.count(MIRROR_AMBIGUOUS),
                          pairs_unobservable=verdicts.count(UNOBSERVABLE))
        health.update({f"rejected_{k}": v for k, v in self.gate.rejected.items()})
        health.update(self.peers.counted(), peers_withheld=len(self.peers.withheld()),
                      peers_unproven=len(self.peers.unproven()))
        log = self.log
        health.update(overruns=self.overruns,
                      log_errors=self.log_errors + (log.errors if log is not None else 0),
                      tick_errors=self.tick_errors, core_rebuilds=self.core_rebuilds,
                      sim_restarts=self.sim_restarts, shares_unsent=self.shares_unsent,
                      # 1 while the log is suspended (its disk full): the messages it drops are counted here.
                      log_suspended=int(log is not None and log.suspended),
                      log_dropped=log.dropped if log is not None else 0,
                      clock_steps=self.timeline.steps, clock_stepped_ms=round(self.timeline.stepped * 1e3),
                      clock_corrected=self.gate.offsets.corrected)
        return health

    def _next(self, stream: str) -> int:
        value = self._seq[stream]
        self._seq[stream] += 1
        return value


def clock_alarm_words(source: str, offset: float) -> str:
    """One line on a clock that disagrees with the agent's: 'sensor clock 1.02 s ahead of this computer's'."""
    way = "ahead of" if offset > 0 else "behind"
    if source == CLOCK_SOURCE_SENSORS:
        back = "back" if offset > 0 else "forward"
        return (f"sensor clock {abs(offset):.2f} s {way} this computer's: beyond the input window, so the "
                f"sensors' stamps are taken {abs(offset):.2f} s {back} once consistent")
    return (f"vessel {source}'s clock {abs(offset):.2f} s {way} this computer's: its shares are refused as "
            f"{'future' if offset > 0 else 'stale'}")


def weakest_pair(record) -> WeakestPair | None:
    """The pair of this tick whose relative path is narrowest (smallest eigenvalue of its spread, (41)), or None
    without a record or a pair."""
    if record is None or not record.neighbours:
        return None
    j, n = min(record.neighbours.items(), key=lambda item: (item[1].excitation[0], item[0]))
    return WeakestPair(neighbour=j, excitation=float(n.excitation[0]), observability=n.observability)


def error_kind(error: BaseException) -> str:
    """An exception's kind: its type and the place in our code it was raised from (the innermost frame under
    agent/, else the innermost), e.g. `ValueError@agent/core/estimators/base.py:115`."""
    frames = traceback.extract_tb(error.__traceback__)
    ours = [f for f in frames if "/agent/" in f.filename.replace("\\", "/")]
    frame = (ours or frames or [None])[-1]
    if frame is None:
        return type(error).__name__
    path = frame.filename.replace("\\", "/")
    where = path[path.rfind("/agent/") + 1:] if "/agent/" in path else Path(path).name
    return f"{type(error).__name__}@{where}:{frame.lineno}"


def main(argv: list[str] | None = None) -> int:
    started = vessel_process("usv-agent", "The onboard agent of one vessel.", NodeSettings, argv, lambda parser:
                             parser.add_argument("--ticks", type=int, default=None,
                                                 help="stop after this many ticks (tests)"))
    if isinstance(started, int):
        return started
    args, settings = started
    node = AgentNode(args.vessel, settings)
    stop_on_signals(node.stopping)
    try:
        node.run(max_ticks=args.ticks)
    except (StartupError, SessionError) as error:
        return startup_error("usv-agent", args.vessel, error)
    print(f"usv-agent {args.vessel}: stopped after {node.ticks} ticks, {node.overruns} overruns, "
          f"{node.tick_errors} failed ticks, refused {dict(node.gate.rejected)}", file=sys.stderr)
    return 0
