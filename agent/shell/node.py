"""The agent process of one vessel: a thin Zenoh shell around the core's `step`.

One Zenoh session (peer mode, explicit endpoints, multicast scouting off unless configured). Subscriber
callbacks only hand payloads to the `InputGate` (no Zenoh calls, no blocking). The tick runs on sim time
(one tick per `sim/clock` message) or on a monotonic 10 Hz timer whose overruns are counted; each tick
takes the gate's snapshot, calls the pure core, and publishes the share, the command (express, real-time
priority) and the status. On sim time the clock message also says which neighbours' shares of the tick
before the simulated radio delivers; in lockstep the tick waits (bounded) for those to arrive. Neighbours
are discovered and forgotten through their liveliness tokens.
SIGINT and SIGTERM stop it cleanly.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
import time

import zenoh

from agent.contract import (
    CLOCK_KEY,
    LIVELINESS,
    Clock,
    Cmd,
    Status,
    decode,
    encode,
    every,
    key,
    message_from_share,
    nanoseconds,
    seconds,
    vessel_of,
)
from agent.core.build import initial_state
from agent.core.snapshot import state_to_json
from agent.core.state import VesselState
from agent.core.step import step
from agent.runtime.log_schema import CoreState
from agent.runtime.mcap_log import McapLog
from agent.runtime.process import vessel_process
from agent.runtime.zenoh_session import open_session
from agent.shell.gate import OWN_TOPICS, InputGate
from agent.shell.settings import NodeSettings
from agent.shell.tick_log import TickLogger, log_topic


class AgentNode:
    def __init__(self, vessel_id: str, settings: NodeSettings, state: VesselState | None = None) -> None:
        self.id = vessel_id
        self.settings = settings
        self.params = settings.agent
        self.state = state or initial_state(vessel_id, settings.agent, settings.initial)
        self.live_peers: set[str] = set()
        self.gate = InputGate(vessel_id, max_age=settings.max_input_age, known_peers=lambda: set(self.live_peers),
                              hold_shares=settings.clock == "sim")
        self.ticks = 0
        self.overruns = 0
        self.stopping = threading.Event()
        self._clock_lock = threading.Lock()
        self._clock: Clock | None = None   # the newest sim/clock message
        self._sim_tick = threading.Event()
        self._seq = {"cmd": 0, "share": 0, "status": 0}
        self.log = None
        self.log_errors = 0
        if settings.log:
            # The settings go in whole: with the logged inputs they are all `usv-log replay` needs.
            start = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
            self.log = McapLog(settings.log.replace("{vessel}", vessel_id).replace("{start}", start),
                               metadata={"vessel": vessel_id, "clock": settings.clock,
                                         "settings": settings.model_dump_json()})
            self.tick_log = TickLogger(self.log, vessel_id, settings.agent.control.radius)

    # ----- clock -----
    def now(self) -> float:
        current = self._input_time()
        return 0.0 if current is None else current

    def _input_time(self) -> float | None:
        """The time to judge an input's stamp by; None on sim time before the first clock (nothing to judge
        by yet: an agent started mid-mission gets its first tick's sensors before that tick's clock)."""
        if self.settings.clock == "sim":
            clock = self._latest_clock()
            return None if clock is None else seconds(clock.stamp_ns)
        return time.time()

    def _latest_clock(self) -> Clock | None:
        with self._clock_lock:
            return self._clock

    # ----- callbacks: hand over and return -----
    def _on_input(self, sample) -> None:
        self.gate.offer(str(sample.key_expr), sample.payload.to_bytes(), self._input_time())

    def _on_clock(self, sample) -> None:
        message, _ = decode(Clock, sample.payload.to_bytes())
        if message is None:
            self.gate.rejected["malformed_clock"] += 1
            return
        with self._clock_lock:
            if self._clock is not None and message.stamp_ns <= self._clock.stamp_ns:
                return
            self._clock = message
        self._sim_tick.set()

    def _on_liveliness(self, sample) -> None:
        peer = vessel_of(str(sample.key_expr))
        if peer is None or peer == self.id:
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self.live_peers.add(peer)
        else:
            self.live_peers.discard(peer)
            self.gate.forget(peer)

    # ----- the loop -----
    def run(self, max_ticks: int | None = None) -> None:
        """Tick until stopped (or `max_ticks`); the log is finished however the loop ends, an exception
        included, so that the file holds every tick up to the failure."""
        with self.log if self.log is not None else contextlib.nullcontext():
            self._run(max_ticks)

    def _run(self, max_ticks: int | None) -> None:
        with open_session(self.settings.zenoh) as session:
            subscribers = [session.declare_subscriber(key(self.id, t), self._on_input) for t in OWN_TOPICS]
            subscribers.append(session.declare_subscriber(every("share"), self._on_input))
            if self.settings.clock == "sim":
                subscribers.append(session.declare_subscriber(CLOCK_KEY, self._on_clock))
            token = session.liveliness().declare_token(key(self.id, LIVELINESS))
            watcher = session.liveliness().declare_subscriber(every(LIVELINESS), self._on_liveliness, history=True)
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
            deadline = started = time.monotonic()
            cpu_started = time.process_time()
            while not self.stopping.is_set() and (max_ticks is None or self.ticks < max_ticks):
                clock = None
                if self.settings.clock == "sim":
                    if not self._sim_tick.wait(timeout=0.1):
                        if self.ticks == 0:
                            self._heartbeat(publishers)
                        continue
                    self._sim_tick.clear()
                    clock = self._latest_clock()
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
                if self.ticks == 0:  # what the run costs from its first tick, not the wait before it
                    started, cpu_started = time.monotonic(), time.process_time()
                self._tick(publishers, clock)
            self._log_summary(time.monotonic() - started, time.process_time() - cpu_started)
            token.undeclare()
            watcher.undeclare()
            for subscriber in subscribers:
                subscriber.undeclare()

    def _log_summary(self, wall_seconds: float, cpu_seconds: float) -> None:
        """The run as a whole: what the process cost (all its threads, Zenoh's included) and what it refused."""
        if self.log is None:
            return
        try:
            self.tick_log.summary(nanoseconds(self.now()), ticks=self.ticks, overruns=self.overruns,
                                  refused=self.gate.rejected, loop_seconds=wall_seconds, cpu_seconds=cpu_seconds)
        except Exception:  # noqa: BLE001  (the summary must not stop a clean shutdown)
            self.log_errors += 1

    def _heartbeat(self, publishers) -> None:
        """Before the first sim tick: a status that says who this agent sees, so that the sim bridge starts
        only once the fleet's links are up (and no tick's messages fall into a gap)."""
        publishers["status"].put(encode(Status(
            stamp_ns=nanoseconds(self.now()), seq=self._next("status"), sender=self.id, phase=0.0,
            command=(0.0, 0.0), peers=sorted(self.live_peers), ticked=False)))

    def _deliver_shares(self, clock: Clock) -> None:
        """Sim time: take the shares of the tick before that the sim's radio delivers to this vessel, once this
        tick's own sensors are in; in lockstep, first wait (bounded) for those shares too."""
        # In real time only this tick's own sensors are worth a short wait (they were published just before
        # the clock); a late share is the radio's loss, as it would be at sea.
        wait = self.settings.share_wait if clock.lockstep else 0.25 * self.settings.agent.dt
        sensed = clock.vessels is not None and self.id in clock.vessels
        self.gate.deliver_shares(clock.previous_ns, clock.delivered_to(self.id), wait,
                                 clock.stamp_ns if sensed else None, wait_for_shares=clock.lockstep)

    def _tick(self, publishers, clock: Clock | None = None) -> None:
        """One tick: on sim time `clock` is the sim/clock message it answers, on wall time None."""
        if clock is not None:
            self._deliver_shares(clock)
        now = self.now() if clock is None else seconds(clock.stamp_ns)
        inputs = self.gate.snapshot(now)
        self.state, output = step(self.params, self.state, inputs)
        stamp = nanoseconds(now)
        # The share goes first: once the bridge has this tick's status, the share is on its way.
        if output.share is not None:
            publishers["share"].put(encode(message_from_share(output.share, self._next("share"))))
        command = Cmd(stamp_ns=stamp, seq=self._next("cmd"), sender=self.id, surge=output.command.surge,
                      yaw_rate=output.command.yaw_rate)
        wire = {"cmd": encode(command)}
        publishers["cmd"].put(wire["cmd"])
        record = output.record
        health = dict(record.health if record is not None else {})
        health.update({f"rejected_{k}": v for k, v in self.gate.rejected.items()})
        health["overruns"] = self.overruns
        health["log_errors"] = self.log_errors
        status = Status(
            stamp_ns=stamp, seq=self._next("status"), sender=self.id,
            phase=record.phase if record is not None else 0.0,
            command=(output.command.surge, output.command.yaw_rate), shared=output.share is not None,
            peers=sorted(self.live_peers),
            target=None if record is None or record.target_state is None
            else tuple(float(v) for v in record.target_state),
            health=health,
        )
        wire["status"] = encode(status)
        publishers["status"].put(wire["status"])
        if self.log is not None:
            try:
                self.tick_log.tick(stamp, inputs, output, command, status, wire)
                every = self.settings.snapshot_every
                if every and self.ticks % every == 0:
                    # After this tick: replay can start at the next one (agent/core/snapshot.py).
                    self.log.log(log_topic(self.id, "state"), state_to_json(self.state), stamp,
                                 schema=CoreState)
            except Exception as error:  # a full disk or a bad value must not stop the vessel's control
                self.log_errors += 1
                if self.log_errors == 1:
                    print(f"usv-agent {self.id}: logging failed: {type(error).__name__}: {error}", file=sys.stderr)
        self.ticks += 1

    def _next(self, stream: str) -> int:
        value = self._seq[stream]
        self._seq[stream] += 1
        return value


def main(argv: list[str] | None = None) -> int:
    started = vessel_process("usv-agent", "The onboard agent of one vessel.", NodeSettings, argv, lambda parser:
                             parser.add_argument("--ticks", type=int, default=None,
                                                 help="stop after this many ticks (tests)"))
    if isinstance(started, int):
        return started
    args, settings = started
    node = AgentNode(args.vessel, settings)

    def stop(signum, frame):  # noqa: ARG001
        node.stopping.set()

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    node.run(max_ticks=args.ticks)
    print(f"usv-agent {args.vessel}: stopped after {node.ticks} ticks, {node.overruns} overruns, "
          f"refused {dict(node.gate.rejected)}", file=sys.stderr)
    return 0
