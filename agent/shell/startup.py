"""What an agent checks as it starts: its vessel id free, and, a few seconds in, its own sensors arriving.

A second agent with the same vessel id would alternate with the first on the vessel's `cmd`: it looks for the
id's liveliness token for `id_check` seconds and refuses to start (StartupError, one line, exit 2) if another
agent holds it. A vessel id no bridge publishes for would command STOP for ever, silently: after
`no_sensor_warning` seconds without an own sensor message taken, one line on stderr says why (no bridge, no
simulation, or sensor stamps refused and how far their clock runs from the agent's), and again whenever the
reason changes while none is taken.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable

from agent.contract import CLOCK_SOURCE_SENSORS, FLEET_PREFIX, LIVELINESS, Clock, key
from agent.shell.gate import OWN_TOPICS, InputGate
from agent.shell.wall_clock import clock_alarm_words


class StartupError(RuntimeError):
    """The agent cannot start (its log cannot be written, its vessel id is taken): one line says why."""


def check_id_free(session, vessel: str, seconds: float, seen: Callable[[], bool], stopping: threading.Event) -> None:
    """StartupError if another agent holds `vessel`'s liveliness token (`seen()`: the liveliness subscriber met
    it). Looks for `seconds`, for the links to other peers come up in that time (a router answers at once)."""
    deadline = time.monotonic() + seconds
    alive = key(vessel, LIVELINESS)
    while True:
        if seen() or any(reply.ok is not None for reply in session.liveliness().get(alive, timeout=0.2)):
            raise StartupError(
                f"vessel id {vessel} is taken: another agent holds the liveliness token {alive} (if that "
                "agent was just stopped hard, its token lasts until its session times out, about 10 s)")
        if time.monotonic() >= deadline:
            return
        stopping.wait(min(0.1, max(0.0, deadline - time.monotonic())))


class SensorWatch:
    """Until an own sensor message is taken, says every `every` seconds why none is, when the reason differs from
    the one said last: an agent started before its simulation first says there is no sim/clock, then, once the
    clock runs, that no bridge publishes for its vessel. A word to the operator is not worth the vessel:
    whatever fails here is let go."""

    def __init__(self, say: Callable[[str], None], every: float, opened: float):
        self.say, self.every, self.opened = say, every, opened
        self.next_check, self.said, self.done = opened + every, None, False

    def check(self, now: float, vessel: str, gate: InputGate, sim: bool, clock: Clock | None) -> None:
        if self.done or now < self.next_check:
            return
        self.next_check = now + self.every
        with contextlib.suppress(Exception):
            reason = no_sensor_reason(vessel, gate, sim, clock)
            self.done = reason is None
            if reason is not None and reason != self.said:
                self.said = reason
                self.say(no_sensor_words(vessel, gate, sim, clock, round(now - self.opened, 1)))


def no_sensor_reason(vessel: str, gate: InputGate, sim: bool, clock: Clock | None) -> str | None:
    """Why no own sensor message was taken, in a word (None if one was): `refused`, `no clock`, or `no bridge`
    with the vessels the sim clock lists."""
    if any(gate.accepted[topic] for topic in OWN_TOPICS):
        return None
    if gate.offsets.heard(CLOCK_SOURCE_SENSORS):
        return "refused"
    if sim and clock is None:
        return "no clock"
    return f"no bridge {None if clock is None else clock.vessels}"


def no_sensor_words(vessel: str, gate: InputGate, sim: bool, clock: Clock | None, waited: float) -> str | None:
    """The line to tell when no own sensor message was taken in the first `waited` seconds, or None if one was;
    if they come but their stamps are refused, that instead, with how far their clock runs from ours."""
    reason = no_sensor_reason(vessel, gate, sim, clock)
    if reason is None:
        return None
    if reason == "refused":
        offset = gate.offsets.median(CLOCK_SOURCE_SENSORS)
        why = "" if offset is None else f": {clock_alarm_words(CLOCK_SOURCE_SENSORS, offset)}"
        refused = {k: v for k, v in gate.rejected.items() if k in ("stale", "future")}
        return (f"sensor messages arrive but none was taken in {waited:g} s{why} (refused {refused}); "
                "commanding STOP until they are")
    if reason == "no clock":
        return (f"no sim/clock in {waited:g} s: this agent ticks on sim time (clock: sim) and no simulation is "
                "running (start usv-sim, or clock: wall on a boat); commanding STOP until one does")
    world = ""
    if clock is not None and clock.vessels is not None and vessel not in clock.vessels:
        world = f"; the sim clock lists vessels {', '.join(clock.vessels[:10]) or 'none'}, not {vessel}"
    return (f"no sensor data on {FLEET_PREFIX}/{vessel}/sensor/* in {waited:g} s: no bridge publishes for vessel "
            f"{vessel}{world}; commanding STOP until one does")
