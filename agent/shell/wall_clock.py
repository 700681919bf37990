"""The agent's time on the wall clock: the system clock, held continuous across a step.

A boat's computer keeps its clock with the fleet's by chrony or PTP, which slew it by microseconds a second;
a step (an NTP step, an operator's `date -s`, a GNSS time source coming back) moves it by seconds at once.
The agent's stamps are what its neighbours judge its shares by: followed blindly, a step back of 2 s makes
every share it sends 2 s stale to the others and every share it receives 2 s in its future, and the vessel is
cut off from its neighbours. So `WallTimeline` reads the system clock against the monotonic clock: it follows
every change of less than `max_step`, and holds its timeline across a larger one, counting the step and saying
how far the system clock now runs from it (`stepped`). The driver on the same computer stamps the sensors
with the stepped clock: the input gate's correction takes their stamps back by as much
(`InputGate.clock_stepped`).
When the system clock comes back within `max_step` of the timeline, the timeline follows it again.

`SimulatedVesselClock` is the sim's sea mode's model of one vessel's clock (`sim_bridge/world.py`
`VesselClock`, with which the sim bridge stamps that vessel's sensors): on a boat the driver and the agent
read the same computer's clock, so in the sea mode the agent reads its vessel's clock, not the host's.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from pydantic import Field

from agent.config import StrictModel
from agent.contract import CLOCK_SOURCE_SENSORS, MAX_STAMP_NS, ClockOffset

MAX_STEP = 0.2   # s: a change of the system clock against the monotonic clock beyond this is a step


class SimulatedVesselClock(StrictModel):
    """One vessel's clock in the sim's sea mode: c(t) = t + offset + drift t + the steps taken by t, at true
    time t = the host's clock - epoch (s). The sim bridge stamps the vessel's sensors with the same clock."""

    epoch_ns: int = Field(ge=0, le=MAX_STAMP_NS, description="the host's time of sim time 0 (ns since 1970)")
    offset: float = Field(0.0, ge=-1e6, le=1e6, allow_inf_nan=False, description="s")
    drift: float = Field(0.0, ge=-1e-2, le=1e-2, allow_inf_nan=False, description="s per s")
    steps: list[tuple[float, float]] = Field(
        default_factory=list, max_length=64,
        description="(sim time s, step s): the clock steps by that much at that time (NTP step, date -s)")

    def read(self, host_ns: int) -> float:
        """The vessel's clock (s since 1970) when the host's reads `host_ns`."""
        t = (host_ns - self.epoch_ns) * 1e-9
        stepped = sum(step for at, step in self.steps if at <= t)
        return (self.epoch_ns + round((t + self.offset + self.drift * t + stepped) * 1e9)) * 1e-9


class WallTimeline:
    """The agent's wall-clock time (s since 1970): `system`, held continuous across a step of it;
    `on_step(delta)` is called (on the reading thread) when a step of `delta` s is detected."""

    def __init__(self, system: Callable[[], float] = time.time,
                 monotonic: Callable[[], float] = time.monotonic, max_step: float = MAX_STEP,
                 on_step: Callable[[float], None] | None = None) -> None:
        self._system, self._monotonic, self.max_step, self._on_step = system, monotonic, max_step, on_step
        self._lock = threading.Lock()   # read from the tick thread and Zenoh's: a step is counted once
        self.anchor = system() - monotonic()   # timeline - monotonic
        self._seen = self.anchor               # system - monotonic at the last reading
        self.steps = 0                         # steps of the system clock detected
        self.last_step = 0.0                   # s: the latest of them (< 0: back)

    def read(self) -> float:
        with self._lock:
            monotonic = self._monotonic()
            seen = self._system() - monotonic
            step = seen - self._seen
            self._seen = seen
            if abs(seen - self.anchor) <= self.max_step:
                self.anchor = seen     # chrony's slewing, or the clock back with the timeline: follow it
            now = monotonic + self.anchor
            if abs(step) > self.max_step:
                self.steps += 1
                self.last_step = step
                if self._on_step is not None:
                    self._on_step(step)
            return now

    @property
    def stepped(self) -> float:
        """How far the system clock runs from the timeline now (s; 0 unless it stepped and stays stepped)."""
        return self._seen - self.anchor


def clock_alarm_words(source: str, offset: float) -> str:
    """One line on a clock that disagrees with the agent's: 'sensor clock 1.02 s ahead of this computer's'."""
    way = "ahead of" if offset > 0 else "behind"
    if source == CLOCK_SOURCE_SENSORS:
        back = "back" if offset > 0 else "forward"
        return (f"sensor clock {abs(offset):.2f} s {way} this computer's: beyond the input window, so the "
                f"sensors' stamps are taken {abs(offset):.2f} s {back} once consistent")
    return (f"vessel {source}'s clock {abs(offset):.2f} s {way} this computer's: its shares are refused as "
            f"{'future' if offset > 0 else 'stale'}")


def step_words(delta: float, steps: int) -> str:
    """One line on a step of this computer's clock (`WallTimeline`) and what the agent does about it."""
    return (f"this computer's clock stepped {'back' if delta < 0 else 'forward'} {abs(delta):.3f} s (against the "
            f"monotonic clock; {steps} steps so far): the agent keeps its time continuous with the fleet's and "
            f"takes its sensors' stamps {abs(delta):.3f} s {'forward' if delta < 0 else 'back'}")


class ClockAlarms:
    """The clocks that disagree with the agent's (the gate's `clock_alarms`), each told by `say` once, again
    when it moves by more than a tenth of a second, and when it is over."""

    def __init__(self, say: Callable[[str], None]) -> None:
        self.say = say
        self.told: dict[str, float] = {}   # source -> the offset last told

    def __call__(self, offsets: list[tuple[str, float]]) -> list[ClockOffset]:
        alarms = [ClockOffset(source=source, offset=offset) for source, offset in offsets]
        now = {alarm.source: alarm.offset for alarm in alarms}
        for source, offset in now.items():
            told = self.told.get(source)
            if told is None or abs(told - offset) > 0.1:
                self.told[source] = offset
                self.say(clock_alarm_words(source, offset))
        for source in [s for s in self.told if s not in now]:
            del self.told[source]
            self.say(f"the {'sensor' if source == CLOCK_SOURCE_SENSORS else f'vessel {source}'} clock agrees "
                     "with this computer's again")
        return alarms
