"""What time it is for an agent, and when it ticks: once per sim/clock message, or on a monotonic timer.

- Sim time (`clock: sim`): the latest accepted sim/clock (`SimClock`, gate.py) is the time; stamps are not
  judged while there is none (before the first, and while it is silent: a restarted sim bridge publishes its
  first sensors before its clock). A clock that starts a new timeline is a restart of the simulation: the gate
  forgets the old timeline at once, on Zenoh's thread (the new timeline's shares may come before the tick
  thread wakes), and the tick thread starts a new mission (`restart_pending`).
- Wall clock (`clock: wall`): the system clock held continuous across a step (`WallTimeline`); a tick every
  `dt` on the monotonic clock, an overrun counted and no backlog caught up.
`triggered` is the monotonic time the tick to come was triggered (the clock's arrival or the timer's; in real
time on sim time the arrival of its own sensors when they come after the clock, `sensors_in`), from which the
agent's reaction times are measured (`answered`: to the command's put, reaction.py).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

from agent.contract import Clock, decode, seconds
from agent.shell.gate import InputGate, SimClock
from agent.shell.reaction import ReactionTimes
from agent.shell.settings import NodeSettings
from agent.shell.wall_clock import ClockAlarms, WallTimeline, step_words

HEARTBEAT = 0.1   # s: the longest wait for a sim clock (a heartbeat status goes out between, while there is none)
RESTARTS_TOLD = 3   # restarts of the simulation told each; after these, at most one every RESTART_REPEAT s
RESTART_REPEAT = 10.0


class Ticker:
    def __init__(self, settings: NodeSettings, gate: InputGate, stopping: threading.Event,
                 say: Callable[[str], None]) -> None:
        self.sim, self.dt = settings.clock == "sim", settings.agent.dt
        self.gate, self.stopping, self.say = gate, stopping, say
        self.clock = SimClock(settings.agent.dt, settings.max_clock_jump, settings.clock_confirm,
                              settings.clock_timeout)
        own = settings.vessel_clock
        self.timeline = WallTimeline(time.time if own is None else lambda: own.read(time.time_ns()),
                                     on_step=self._stepped)
        self.alarms = ClockAlarms(say)   # the clocks that disagree with ours, for the status
        self.overruns = 0
        self.triggered: float | None = None
        self.sensed: float | None = None   # monotonic time the latest own sensor message arrived
        # From a tick's trigger to its command's put: wall time, and the tick thread's CPU.
        self.reaction, self.reaction_cpu = ReactionTimes(), ReactionTimes()
        self.restart_pending = False
        self.restarts = 0
        self._restarts_told = -math.inf
        self.clocked = threading.Event()   # a clock came for the tick thread
        self._deadline: float | None = None

    def now(self) -> float:
        """The agent's time: the latest sim clock (0 before the first), or the system clock."""
        if self.sim:
            return 0.0 if self.clock.latest is None else seconds(self.clock.latest.stamp_ns)
        return self.timeline.read()

    def input_time(self) -> float | None:
        """The time to judge an input's stamp by; None on sim time while there is no clock to judge by."""
        if self.sim:
            return None if self.clock.silent() else seconds(self.clock.latest.stamp_ns)
        return self.timeline.read()

    def _stepped(self, delta: float) -> None:
        """This computer's clock stepped: the agent's time holds on, the own sensors' stamps (this computer's
        clock) are taken back by the step, and the operator is told."""
        self.gate.clock_stepped(delta)
        self.say(step_words(delta, self.timeline.steps))

    def offer(self, payload: bytes) -> None:
        """A sim/clock payload (Zenoh's thread): judged, and the tick thread woken if it is the clock; a refusal
        is counted by the gate. Never raises."""
        arrived = time.monotonic()
        try:
            message, reason = decode(Clock, payload)
            verdict = "malformed_clock" if message is None else self.clock.offer(message)
            if verdict == "restart":
                self.gate.reset(message.stamp_ns)
                self.restart_pending = True
            elif verdict not in ("first", "tick"):
                self.gate.count(verdict, reason or f"sim/clock: stamp {message.stamp_ns}")
                return
            self.triggered = arrived
            self.clocked.set()
        except Exception as error:  # noqa: BLE001  (a callback must never raise into Zenoh)
            self.gate.count("internal", f"sim/clock: {type(error).__name__}: {error}")

    def sensors_in(self) -> None:
        """Real time on sim time: the bridge sends the clock first and this vessel's sensors in its slot after
        it (sim_bridge/bridge.py `stagger`); the tick, which waited for them, was triggered by the last."""
        if self.sensed is not None and self.triggered is not None and self.sensed > self.triggered:
            self.triggered = self.sensed

    def answered(self, tick_cpu: float) -> None:
        """The tick's command went out; the tick thread's CPU time at its start was `tick_cpu`."""
        self.reaction_cpu.add(time.thread_time() - tick_cpu)
        if self.triggered is not None:
            self.reaction.add(time.monotonic() - self.triggered)

    def restarted(self) -> bool:
        """Whether the simulation restarted since the last tick (counted, and told: the first RESTARTS_TOLD,
        then at most one every RESTART_REPEAT s)."""
        if not self.restart_pending:
            return False
        self.restart_pending = False
        self.restarts += 1
        if self.restarts <= RESTARTS_TOLD or time.monotonic() - self._restarts_told >= RESTART_REPEAT:
            self._restarts_told = time.monotonic()
            self.say(f"the simulation restarted (sim/clock began a new timeline at "
                     f"{seconds(self.clock.latest.stamp_ns):.3f} s; {self.restarts} restarts so far): starting "
                     "the mission again")
        return True

    def counts(self) -> dict[str, int]:
        """For the status: timer overruns, steps of the system clock, simulation restarts."""
        return {"overruns": self.overruns, "sim_restarts": self.restarts, "clock_steps": self.timeline.steps,
                "clock_stepped_ms": round(self.timeline.stepped * 1e3)}

    def next_clock(self) -> Clock | None:
        """Sim time: the clock of the next tick, or None if none came within HEARTBEAT."""
        if not self.clocked.wait(timeout=HEARTBEAT):
            return None
        self.clocked.clear()
        return self.clock.latest

    def next_timer(self) -> None:
        """Wall clock: wait for the next tick of the timer."""
        self._deadline = (time.monotonic() if self._deadline is None else self._deadline) + self.dt
        delay = self._deadline - time.monotonic()
        if delay > 0:
            self.stopping.wait(delay)
        else:
            self.overruns += 1
            self._deadline = time.monotonic()   # do not try to catch up a backlog of ticks
        self.triggered = time.monotonic()
