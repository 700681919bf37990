"""The agent process of one vessel: its parts wired to one Zenoh session, and the tick loop around the core's `step`.

Subscriber callbacks only hand payloads to the input gate (gate.py), the mission orders (mission.py) or the
sim clock, and return: no Zenoh calls, no blocking. The tick runs on sim time (one per `sim/clock` message; it
first takes the neighbours' shares the simulated radio delivers, waiting for them in lockstep) or on a monotonic
timer every `dt`, whose overruns are counted. A tick applies the operator's orders, takes the gate's snapshot
as the peer table vets it (peers.py), calls the core, publishes (publish.py) and logs (recorder.py); a tick that
fails commands STOP (failures.py). While no sim clock comes, a heartbeat status goes out every HEARTBEAT s; a
clock that starts again from 0 is a new mission: the gate forgets the old timeline (at once, in the callback),
the core is rebuilt from the initial estimates, the log goes on in a new file. SIGINT and SIGTERM stop it.
"""

from __future__ import annotations

import os
import sys
import threading
import time

import zenoh

from agent.contract import (
    CLOCK_KEY,
    FLEET_PREFIX,
    LIVELINESS,
    MISSION_PREFIX,
    Clock,
    every,
    key,
    nanoseconds,
    seconds,
    shares_for,
    vessel_of,
)
from agent.core.build import InitialEstimates, initial_state
from agent.core.records import STOP, TickInputs, TickOutput
from agent.core.state import VesselState
from agent.core.step import decide
from agent.runtime.process import startup_error, stop_on_signals, vessel_process
from agent.runtime.zenoh_session import SessionError, open_session
from agent.shell.failures import TickFailures, check_command
from agent.shell.gate import InputGate
from agent.shell.mission import MissionOrders
from agent.shell.peers import RANGED_WITHIN, PeerTable
from agent.shell.publish import Outbox, declare_publishers, health
from agent.shell.recorder import Recorder
from agent.shell.settings import NodeSettings
from agent.shell.startup import SensorWatch, StartupError, check_id_free
from agent.shell.ticker import HEARTBEAT, Ticker


def yield_cpu() -> None:
    """Let another thread that is ready to run on this CPU run first (no-op where the OS has no sched_yield)."""
    if hasattr(os, "sched_yield"):
        os.sched_yield()


class AgentNode:
    def __init__(self, vessel_id: str, settings: NodeSettings, state: VesselState | None = None) -> None:
        self.id, self.settings, self.params = vessel_id, settings, settings.agent
        self.state = state or initial_state(vessel_id, settings.agent, settings.initial)
        self._live_view: frozenset[str] = frozenset()   # what the gate reads from Zenoh's threads
        self.peers = PeerTable(lambda peer: self.gate.ranged_within(peer, self.ticker.input_time(), RANGED_WITHIN))
        self.gate = InputGate(vessel_id, max_age=settings.max_input_age, max_future=settings.max_input_future,
                              known_peers=lambda: self._live_view, hold_shares=settings.clock == "sim",
                              max_rate=settings.max_input_rate)
        self.stopping = threading.Event()
        self.ticker = Ticker(settings, self.gate, self.stopping, self._say)
        self.orders = MissionOrders(vessel_id, settings.max_input_age, settings.max_input_future, self.gate.count)
        self.outbox, self.recorder = Outbox(vessel_id), Recorder(vessel_id, settings)
        self.failures = TickFailures(vessel_id, settings.rebuild_after)
        self.ticks = 0
        self.core_seconds = 0.0   # tick thread CPU inside the core's step since the first tick
        self._id_seen = False     # another agent's token with our id, seen before we declared ours

    def _say(self, line: str) -> None:
        print(f"usv-agent {self.id}: {line}", file=sys.stderr)

    # ----- callbacks: hand over and return -----
    def _on_input(self, sample) -> None:
        self.gate.offer(str(sample.key_expr), sample.payload.to_bytes(), self.ticker.input_time())

    def _on_sensor(self, sample) -> None:
        self.ticker.sensed = time.monotonic()
        self._on_input(sample)

    def _on_mission(self, sample) -> None:
        try:
            self.orders.offer(str(sample.key_expr), sample.payload.to_bytes(), self.ticker.input_time(),
                              nanoseconds(self.ticker.now()), lambda: self._live_view)
        except Exception as error:  # noqa: BLE001  (a callback must never raise into Zenoh)
            self.gate.count("internal", f"mission: {type(error).__name__}: {error}")

    def _on_clock(self, sample) -> None:
        self.ticker.offer(sample.payload.to_bytes())

    def _on_liveliness(self, sample) -> None:
        peer, put = vessel_of(str(sample.key_expr)), sample.kind == zenoh.SampleKind.PUT
        if peer == self.id:
            self._id_seen = self._id_seen or put   # ours once we have declared it; before that, another agent's
        elif peer is not None and self.peers.token(peer, put, self.gate):
            self._live_view = self.peers.live()

    # ----- the loop -----
    def run(self, max_ticks: int | None = None) -> None:
        """Tick until stopped (or `max_ticks`); the log is finished however the loop ends, an exception
        included, so that the file holds every tick up to the failure."""
        try:
            self._run(max_ticks)
        finally:
            self.recorder.close()

    def _run(self, max_ticks: int | None) -> None:
        sim = self.settings.clock == "sim"
        with open_session(self.settings.zenoh) as session:
            watcher = session.liveliness().declare_subscriber(every(LIVELINESS), self._on_liveliness, history=True)
            check_id_free(session, self.id, self.settings.id_check, lambda: self._id_seen, self.stopping)
            if self.recorder.log is None:
                self.recorder.open()
            # One subscriber for all four sensors: each subscriber is a thread of zenoh-python's, and a message
            # handed across threads costs more CPU than decoding it (docs/results/runtime_benchmark.md).
            subscribers = [session.declare_subscriber(f"{FLEET_PREFIX}/{self.id}/sensor/*", self._on_sensor),
                           session.declare_subscriber(shares_for(self.id), self._on_input),
                           # Format 1 senders (older agents; nothing comes here in a fleet of format 2).
                           session.declare_subscriber(every("share"), self._on_input),
                           session.declare_subscriber(f"{MISSION_PREFIX}/*", self._on_mission),
                           *([session.declare_subscriber(CLOCK_KEY, self._on_clock)] if sim else [])]
            token = session.liveliness().declare_token(key(self.id, LIVELINESS))
            publishers = declare_publishers(session, self.id, sim, self.settings.share_format)
            started = opened = time.monotonic()
            cpu_started = time.process_time()
            watch = SensorWatch(self._say, self.settings.no_sensor_warning, opened)
            while not self.stopping.is_set() and (max_ticks is None or self.ticks < max_ticks):
                try:
                    watch.check(time.monotonic(), self.id, self.gate, sim, self.ticker.clock.latest)
                    clock = self._next_sim_tick(publishers) if sim else self.ticker.next_timer()
                    if sim and clock is None:
                        continue
                    if self.ticks == 0:  # what the run costs from its first tick, not the wait before it
                        started, cpu_started, self.core_seconds = time.monotonic(), time.process_time(), 0.0
                    self._tick(publishers, clock)
                except Exception as error:  # noqa: BLE001  (whatever one pass of the loop meets, the loop goes on)
                    self._failed(error, None, 0)
                    self.stopping.wait(HEARTBEAT)
            self._log_summary(time.monotonic() - started, time.process_time() - cpu_started)
            # Finished before Zenoh is: whatever happens to the process while its session closes, the log is whole.
            self.recorder.close()
            for declared in (token, watcher, *subscribers):
                declared.undeclare()

    def _next_sim_tick(self, publishers) -> Clock | None:
        """The clock of the next tick, or None: none came (a heartbeat goes out while there is none), or the
        sim says this vessel is not in the world (the shares held for that tick are dropped, not hoarded)."""
        clock = self.ticker.next_clock()
        if clock is None and (self.ticks == 0 or self.ticker.clock.silent()):
            self._heartbeat(publishers)
        if clock is not None and self.ticker.restarted():
            self._restart()
        if clock is not None and clock.vessels is not None and self.id not in clock.vessels:
            self.gate.deliver_shares(clock.previous_ns, set())
            return None
        return clock

    def _tick(self, publishers, clock: Clock | None = None) -> None:
        """One tick: on sim time `clock` is the sim/clock message it answers, on wall time None. Whatever
        fails in it, the tick publishes a command (STOP if the core did not give a sound one) and a status."""
        tick_cpu = time.thread_time()
        now = self.ticker.now() if clock is None else seconds(clock.stamp_ns)
        stamp, inputs = nanoseconds(now), None
        self.params = self.orders.apply(self.params, stamp, vessels=len(self._live_view) + 1)
        try:
            if clock is not None:
                self.gate.deliver_for(clock, self.settings.share_wait, self.settings.agent.dt)
                if not clock.lockstep:
                    self.ticker.sensors_in()
            inputs = self.peers.vet(self.gate.snapshot(now))   # a vessel id come back proves itself first
            core_started = time.thread_time()
            self.state, decided, report = decide(self.params, self.state, inputs)
            self.core_seconds += time.thread_time() - core_started
            check_command(decided, self.params.control)
            if self.orders.held:   # the operator's hold: STOP, as the watchdog would; the core keeps estimating
                decided = STOP
        except Exception as error:  # noqa: BLE001  (one bad tick must not take the vessel's control down)
            decided, report = STOP, None
            self._failed(error, inputs, stamp)
        # The driver judges a command by its own clock: on the wall clock it is stamped in it (the agent's time
        # plus the correction its sensors' stamps need; the same unless the driver's clock is off or ours stepped).
        driver_stamp = stamp if clock is not None else nanoseconds(now + self.gate.offsets.applied)
        command, wire = self.outbox.command(publishers, driver_stamp, decided)
        self.ticker.answered(tick_cpu)
        # Zenoh's own thread sends the command: on a core of its own the agent lets it run now, not once this
        # thread has built the share, the status and the log (about 2 ms later on 1 tick in 10 before this:
        # docs/results/runtime_changes.md).
        yield_cpu()
        output = TickOutput(decided, None, None)
        if report is not None:   # the share and the record, which the command did not wait for
            try:
                core_started = time.thread_time()
                reported = report()
                self.core_seconds += time.thread_time() - core_started
                output = TickOutput(decided, reported.share, reported.record)
                self.failures.succeeded()
            except Exception as error:  # noqa: BLE001
                self._failed(error, inputs, stamp)
        if output.record is not None:
            try:   # what the next ticks vet a returning id by: after the command, which does not wait for it
                self.peers.learn(inputs, output.record)
            except Exception as error:  # noqa: BLE001
                self._failed(error, inputs, stamp)
        self.outbox.share(publishers, output.share, self._live_view)
        status, status_wire = self._status(publishers, stamp, (command.surge, command.yaw_rate), output.record)
        self.recorder.tick(stamp, inputs if inputs is not None else TickInputs(time=now, odometry=None), output,
                           command, status, {"cmd": wire, "status": status_wire}, self.orders.judged(), self.state,
                           self.ticks)
        self.ticks += 1

    def _status(self, publishers, stamp, command, record, ticked=True):
        view = {"held": self.orders.held, "radius": self.params.control.radius, "mission": self.orders.acks(),
                "clocks": self.ticker.alarms(self.gate.clock_alarms()), "vehicle": self.gate.vehicle()}
        return self.outbox.status(publishers, stamp, command, record, sorted(self._live_view), self._health,
                                  view, ticked)

    def _health(self, record) -> dict[str, int]:
        return health(record, self.gate, self.peers, self.ticker, self.recorder, self.failures, self.outbox)

    def _heartbeat(self, publishers) -> None:
        """While there is no clock: a status that says this agent is up and whom it sees, so that a sim bridge
        starts (again) only once the fleet's links are up. Stamped 0, not with a tick's time: a restarted
        bridge's clock starts again from 0, and a later stamp would hide the new ticks' statuses from it."""
        try:
            self._status(publishers, 0, (0.0, 0.0), None, ticked=False)
        except Exception as error:  # noqa: BLE001  (a heartbeat lost is not worth the process)
            self._failed(error, None, 0)

    def _failed(self, error: Exception, inputs: TickInputs | None, stamp: int) -> None:
        """The error policy (failures.py); a run of failed ticks rebuilds the core as a late joiner starts."""
        if self.failures.failed(error, stamp, lambda kind, text, count: self.recorder.error(stamp, kind, text,
                                                                                           count, inputs)):
            self.state = initial_state(self.id, self.params, InitialEstimates())

    def _restart(self) -> None:
        """The simulation restarted: a new mission, from the configured circle and the initial estimates, in a
        new log file."""
        self.orders.reset()
        self.params = self.settings.agent
        self.state = initial_state(self.id, self.params, self.settings.initial)
        self.failures.succeeded()
        self.recorder.next_mission(lambda: self._log_summary(0.0, 0.0))

    def _log_summary(self, wall_seconds: float, cpu_seconds: float) -> None:
        """The run as a whole: what the process cost (all its threads, Zenoh's included) and what it refused."""
        self.recorder.summary(nanoseconds(self.ticker.now()), ticks=self.ticks, overruns=self.ticker.overruns,
                              refused=self.gate.rejected, loop_seconds=wall_seconds, cpu_seconds=cpu_seconds,
                              core_cpu_seconds=self.core_seconds, reaction_ms=self.ticker.reaction.summary(),
                              reaction_cpu_ms=self.ticker.reaction_cpu.summary())


def main(argv: list[str] | None = None) -> int:
    started = vessel_process("usv-agent", "The onboard agent of one vessel.", NodeSettings, argv, lambda parser:
                             parser.add_argument("--ticks", type=int, default=None,
                                                 help="stop after this many ticks (tests)"), params_key="agent")
    if isinstance(started, int):
        return started
    args, settings = started
    node = AgentNode(args.vessel, settings)
    stop_on_signals(node.stopping)
    try:
        node.run(max_ticks=args.ticks)
    except (StartupError, SessionError) as error:
        return startup_error("usv-agent", args.vessel, error)
    print(f"usv-agent {args.vessel}: stopped after {node.ticks} ticks, {node.ticker.overruns} overruns, "
          f"{node.failures.total} failed ticks, refused {dict(node.gate.rejected)}", file=sys.stderr)
    return 0
