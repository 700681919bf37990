"""The operator's mission commands in the agent: judged as they arrive, applied at a tick boundary.

A command comes on `mission/all` (every vessel) or `mission/<id>` (one vessel; the agent sees the others'
too, so that one addressed to a vessel nobody knows is refused, not lost in silence). It is refused, counted
and answered when it is malformed, stale or ahead of the agent's clock (the same window as every input),
replayed (its `seq` not above the last one judged from its sender), or addressed to an unknown vessel; a
`set` whose values the controller's parameters refuse, or that asks for a circle the fleet cannot fly
(agent/core/mission_limits.py), is refused when applied. Nothing is half-applied: a `set` is checked whole
before anything changes. Accepted commands wait for the next tick, which applies them in order before it
runs the core:
- `hold`: the tick commands STOP (as the watchdog would) until `resume` or `start`; the core still runs, so
  the estimates stay current;
- `set`: from that tick on, the radius, yaw rate and/or direction (r*, and omega*'s size and sign) move to
  the new ones at a bounded rate (mission_limits.toward; docs/operator.md).
Every judgement is an acknowledgement (`MissionAck`); the status carries the latest one of each sender, and
the log gets every one.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from collections.abc import Callable

from pydantic import ValidationError

from agent.config import updated
from agent.contract import (
    MAX_STAMP_NS,
    MISSION_ALL,
    MISSION_PREFIX,
    MissionAck,
    MissionCommand,
    decode,
    seconds,
)
from agent.core.mission_limits import infeasible, toward
from agent.core.params import AgentParams

MAX_SENDERS = 8      # operators remembered (their last seq and ack); the oldest is forgotten beyond
MAX_PENDING = 64     # accepted commands waiting for the next tick; more is a flood, refused


class MissionOrders:
    """The mission commands of one agent. `offer` runs on Zenoh's threads, `apply` on the tick thread."""

    def __init__(self, vessel: str, max_age: float, max_future: float, count: Callable[[str, str], None]) -> None:
        self.vessel = vessel
        self.max_age, self.max_future = max_age, max_future
        self._count = count
        self.held = False
        self._lock = threading.Lock()
        self._pending: list[tuple[MissionCommand, int]] = []   # and when each came (agent time, ns)
        self._last_seq: OrderedDict[str, int] = OrderedDict()
        self._acks: OrderedDict[str, MissionAck] = OrderedDict()
        self._goal: tuple[float, float] | None = None     # (r*, omega*) of the last set, until reached
        # For the log, drained by the tick: (command, answer, when it came).
        self._judged: list[tuple[MissionCommand | None, MissionAck, int]] = []

    def offer(self, key: str, payload: bytes, now: float | None, now_ns: int, known: Callable[[], frozenset]) -> bool:
        """Judge one payload received on `key` at agent time `now` (None: no clock to judge stamps by);
        True if it waits for the next tick."""
        parts = str(key).split("/")
        target = parts[1] if len(parts) == 2 and parts[0] == MISSION_PREFIX else None
        message, reason = decode(MissionCommand, payload)
        if message is None:
            return self._refuse(None, now_ns, "malformed", reason, who=_who(payload))
        if target is None:
            return self._refuse(message, now_ns, "unexpected_key", f"key {key}")
        if target not in (MISSION_ALL, self.vessel):
            if target not in known():
                return self._refuse(message, now_ns, "unknown_vessel", f"no vessel {target!r} is alive")
            return False   # another vessel's: not ours to judge
        stamp = seconds(message.stamp_ns)
        if now is not None and stamp < now - self.max_age:
            return self._refuse(message, now_ns, "stale", f"stamped {now - stamp:.3f} s ago")
        if now is not None and stamp > now + self.max_future:
            return self._refuse(message, now_ns, "future", f"stamped {stamp - now:.3f} s ahead")
        with self._lock:
            last = self._last_seq.get(message.sender)
            if last is not None and message.seq <= last:
                return self._refuse(message, now_ns, "replayed", f"seq {message.seq} not after {last}", locked=True)
            if len(self._pending) >= MAX_PENDING:
                return self._refuse(message, now_ns, "flood", f"{MAX_PENDING} commands wait already", locked=True)
            self._remember(self._last_seq, message.sender, message.seq)
            self._pending.append((message, now_ns))
        return True

    def apply(self, params: AgentParams, stamp_ns: int, vessels: int = 1) -> AgentParams:
        """The commands that came since the last tick, in order, at the tick stamped `stamp_ns`, by a vessel
        that knows `vessels` alive (itself included); the parameters to tick with. A `set` the fleet cannot
        fly is refused (agent/core/mission_limits.py); an accepted one becomes the goal that r* and omega*
        move towards, a tick at a time."""
        with self._lock:
            pending, self._pending = self._pending, []
        for message, received in pending:
            reason, kind = "", "refused"
            if message.command == "hold":
                self.held = True
            elif message.command in ("resume", "start"):
                self.held = False
            else:
                # A set changes the goal (the circle being moved to, if any): what it leaves out stays.
                radius, rate = self._goal or (params.control.radius, params.control.yaw_rate)
                radius = radius if message.radius is None else message.radius
                # omega*'s sign is the direction (agent/core/params.py): the size and the sign are set apart.
                size = abs(rate) if message.yaw_rate is None else message.yaw_rate
                clockwise = rate < 0 if message.direction is None else message.direction == "cw"
                rate = -size if clockwise else size
                try:
                    updated(params, control=updated(params.control, radius=radius, yaw_rate=rate))
                    reason = infeasible(radius, rate, vessels, params.control) or ""
                    kind = "infeasible"
                except (ValidationError, ValueError) as error:
                    reason = f"the controller refuses it: {' '.join(str(error).split())[:200]}"
                if not reason:
                    self._goal = (radius, rate)
            if reason:
                self._refuse(message, stamp_ns, kind, reason, received=received)
            else:
                self._ack(message, MissionAck(sender=message.sender, seq=message.seq, command=message.command,
                                              applied=True, stamp_ns=stamp_ns), received)
        if self._goal is not None:
            control = params.control
            radius, rate = toward(control.radius, control.yaw_rate, self._goal, params.dt, control)
            params = updated(params, control=updated(control, radius=radius, yaw_rate=rate))
            if (radius, rate) == self._goal:
                self._goal = None
        return params

    def acks(self) -> list[MissionAck]:
        """The latest acknowledgement of each sender (at most MAX_SENDERS), oldest first."""
        with self._lock:
            return list(self._acks.values())

    def judged(self) -> list[tuple[MissionCommand | None, MissionAck, int]]:
        """Every judgement since the last call: the command (None if it could not be read), the answer, and
        when the command came (agent time, ns)."""
        with self._lock:
            judged, self._judged = self._judged, []
        return judged

    def reset(self) -> None:
        """A new mission (the simulation restarted): no hold, nothing pending; senders' seqs are kept."""
        with self._lock:
            self._pending.clear()
            self.held = False
            self._goal = None

    # ----- internals -----
    def _refuse(self, message: MissionCommand | None, stamp_ns: int, kind: str, reason: str,
                locked: bool = False, who: tuple[str, int, str] = ("?", 0, "?"), received: int | None = None) -> bool:
        """Count and answer a refusal; `who` names an unreadable command's sender, seq and command as far
        as they could be read, so that its sender learns why."""
        self._count(f"mission_{kind}", f"mission: {reason}")
        sender, seq, command = (message.sender, message.seq, message.command) if message is not None else who
        ack = MissionAck(sender=sender, seq=seq, command=command, applied=False, reason=f"{kind}: {reason}"[:300],
                         stamp_ns=max(0, stamp_ns))
        self._ack(message, ack, stamp_ns if received is None else received, locked)
        return False

    def _ack(self, message: MissionCommand | None, ack: MissionAck, received: int, locked: bool = False) -> None:
        if locked:
            self._record(message, ack, received)
        else:
            with self._lock:
                self._record(message, ack, received)

    def _record(self, message: MissionCommand | None, ack: MissionAck, received: int) -> None:
        self._remember(self._acks, ack.sender, ack)
        if len(self._judged) < MAX_PENDING * 4:
            self._judged.append((message, ack, max(0, received)))

    @staticmethod
    def _remember(table: OrderedDict, sender: str, value) -> None:
        table[sender] = value
        table.move_to_end(sender)
        while len(table) > MAX_SENDERS:
            table.popitem(last=False)


def _who(payload: bytes) -> tuple[str, int, str]:
    """(sender, seq, command) of a payload the contract refused, as far as they read as such; "?" and 0 where
    not."""
    try:
        fields = json.loads(payload)   # not orjson: this must read the NaN that the contract refused
    except (ValueError, TypeError, RecursionError):
        return "?", 0, "?"
    if not isinstance(fields, dict):
        return "?", 0, "?"
    sender, seq, command = fields.get("sender"), fields.get("seq"), fields.get("command")
    return (sender[:64] if isinstance(sender, str) else "?",
            seq if isinstance(seq, int) and 0 <= seq <= MAX_STAMP_NS else 0,
            command[:16] if isinstance(command, str) else "?")
