"""The operator's mission commands in the agent: judged as they arrive, applied at a tick boundary.

A command comes on `mission/all` (every vessel) or `mission/<id>` (one vessel; the agent sees the others'
too, so that one addressed to a vessel nobody knows is refused, not lost in silence). It is refused, counted
and answered when it is malformed, stale or ahead of the agent's clock (the same window as every input),
replayed (its sender, session and seq already judged within the window), one too many of its sender (a
flood, or a new sender while the table is full of senders heard within the window: `MissionOrders`), or
addressed to an unknown vessel; a `set` whose values the controller's parameters refuse, or that asks for a
circle the fleet cannot fly (agent/core/mission_limits.py), is refused when applied. Nothing is half-applied:
a `set` is checked whole before anything changes. Accepted commands wait for the next tick, which applies
them in order before it runs the core:
- `hold`: the tick commands STOP (as the watchdog would) until `resume` or `start`; the core still runs, so
  the estimates stay current;
- `set`: from that tick on, the radius, yaw rate and/or direction (r*, and omega*'s size and sign) move to
  the new ones at a bounded rate (mission_limits.toward; docs/operator.md).
Every judgement is an acknowledgement (`MissionAck`); the statuses carry the latest one of each sender (eight
a status, those not yet carried first), and the log gets every one (refusals up to a bound a tick).
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict, deque
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
    nanoseconds,
    seconds,
)
from agent.core.mission_limits import infeasible, toward
from agent.core.params import AgentParams

MAX_SENDERS = 256         # senders remembered; beyond, the least recently heard goes if idle within the window
MAX_IDS_PER_SENDER = 64   # a sender's commands remembered within the window; more in one window is a flood
MAX_PENDING_PER_SENDER = 16   # a sender's commands waiting for a tick; more is a flood (a hold always goes)
DRAIN_PER_TICK = 32       # commands a tick applies at least, in rounds of one per sender, whole rounds
STATUS_ACKS = 8           # answers a status carries (Status.mission): those not yet shown first
MAX_LOGGED = 256          # refusals a tick logs at most (each is counted in the health all the same)


class Sender:
    """What one sender's commands leave behind: the ids (session, seq) of those accepted, with their stamps,
    for as long as a replay of them could still pass the stamp window, and those waiting for a tick."""

    __slots__ = ("ids", "newest", "pending")

    def __init__(self) -> None:
        self.ids: dict[tuple[str, int], int] = {}   # (session, seq) -> stamp_ns, in the order accepted
        self.newest = -1                              # the latest stamp among `ids` (ns)
        self.pending: deque[tuple[int, MissionCommand, int]] = deque()   # (arrival number, command, when)

    def expire(self, low_ns: int, high_ns: int) -> None:
        """Forget the ids whose stamps lie outside [low_ns, high_ns], the window around the clock: a replay of
        one is refused as stale (or future) before its id is looked at."""
        if self.newest < low_ns:
            self.ids.clear()
        else:
            self.ids = {i: s for i, s in self.ids.items() if low_ns <= s <= high_ns}
        self.newest = max(self.ids.values(), default=-1)

    def idle(self, low_ns: int | None) -> bool:
        """Nothing waits and no id is within the window (None: no clock; only an empty record is idle)."""
        return not self.pending and (not self.ids if low_ns is None else self.newest < low_ns)


class MissionOrders:
    """The mission commands of one agent. `offer` runs on Zenoh's threads, `apply` on the tick thread.

    Replays are judged by the stamp window and the sender's sessions, never by a high-water mark that outlives
    them: a command is one (sender, session, seq), remembered while its stamp is within the window (after that
    a replay of it is stale), and within a session the seqs must grow (a reordered pair is not applied the
    wrong way round). So a seq of 2^63 - 1 blocks one session of one sender until its stamp leaves the window
    (1.5 s) and nothing else, and a sender that starts again with a new session (usv-op: one per invocation)
    may count its seqs from anywhere. The table of senders
    is bounded (MAX_SENDERS); a new sender takes the place of the least recently heard one only if that one has
    no command within the window, else it is refused (`too_many_senders`): new senders never push out one that
    spoke within the window, whose replays must still be refused. Each sender has its own queue
    (MAX_PENDING_PER_SENDER) and the tick drains the queues in rounds, one command of each sender a round: a
    flood from one sender fills its own queue and delays nobody else's command. A `hold` is never refused for a
    full queue: it takes the place of its sender's oldest waiting command (refused as `flood`)."""

    def __init__(self, vessel: str, max_age: float, max_future: float, count: Callable[[str, str], None]) -> None:
        self.vessel = vessel
        self.max_age, self.max_future = max_age, max_future
        self._count = count
        self.held = False
        self._lock = threading.Lock()
        self._senders: OrderedDict[str, Sender] = OrderedDict()   # least recently heard first
        self._arrivals = 0
        self._acks: OrderedDict[str, MissionAck] = OrderedDict()
        self._unshown: OrderedDict[str, None] = OrderedDict()   # senders whose latest answer no status carried
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
        window = (None if now is None
                  else (nanoseconds(now - self.max_age), nanoseconds(now + self.max_future)))
        with self._lock:
            sender = self._sender(message.sender, window)
            if sender is None:
                return self._refuse(message, now_ns, "too_many_senders",
                                    f"{MAX_SENDERS} senders heard within {self.max_age:g} s", locked=True)
            self._senders.move_to_end(message.sender)
            if window is not None:
                sender.expire(*window)
            ident = (message.session, message.seq)
            last = max((seq for session, seq in sender.ids if session == message.session), default=None)
            if last is not None and message.seq <= last:
                where = f" in session {message.session}" if message.session else ""
                return self._refuse(message, now_ns, "replayed", f"seq {message.seq} not after {last}{where}",
                                    locked=True)
            hold = message.command == "hold"
            if len(sender.ids) >= MAX_IDS_PER_SENDER and not hold:
                return self._refuse(message, now_ns, "flood",
                                    f"{MAX_IDS_PER_SENDER} commands of {message.sender!r} within the window",
                                    locked=True)
            if len(sender.pending) >= MAX_PENDING_PER_SENDER:
                if not hold:
                    return self._refuse(message, now_ns, "flood",
                                        f"{MAX_PENDING_PER_SENDER} commands of {message.sender!r} wait already",
                                        locked=True)
                _, dropped, received = sender.pending.popleft()
                self._refuse(dropped, now_ns, "flood", "dropped for a later hold of its sender", locked=True,
                             received=received)
            if len(sender.ids) >= MAX_IDS_PER_SENDER:   # a hold: the oldest id goes (a flood in its own name)
                del sender.ids[next(iter(sender.ids))]
            sender.ids[ident] = message.stamp_ns
            sender.newest = max(sender.newest, message.stamp_ns)
            self._arrivals += 1
            sender.pending.append((self._arrivals, message, now_ns))
        return True

    def _sender(self, name: str, window: tuple[int, int] | None) -> Sender | None:
        """The record of `name`, made if new; None if the table is full of senders heard within the window."""
        sender = self._senders.get(name)
        if sender is not None:
            return sender
        if len(self._senders) >= MAX_SENDERS:
            oldest_name, oldest = next(iter(self._senders.items()))
            if window is not None:
                oldest.expire(*window)
            if not oldest.idle(None if window is None else window[0]):
                return None
            del self._senders[oldest_name]
        sender = self._senders[name] = Sender()
        return sender

    def _drain(self) -> list[tuple[MissionCommand, int]]:
        """The commands this tick applies, in the order they came: rounds of one command of each sender with
        one waiting, until DRAIN_PER_TICK are taken (a round is always finished)."""
        taken: list[tuple[int, MissionCommand, int]] = []
        waiting = [s for s in self._senders.values() if s.pending]
        while waiting and len(taken) < DRAIN_PER_TICK:
            taken += [s.pending.popleft() for s in waiting]
            waiting = [s for s in waiting if s.pending]
        taken.sort(key=lambda item: item[0])
        return [(message, received) for _, message, received in taken]

    def apply(self, params: AgentParams, stamp_ns: int, vessels: int = 1) -> AgentParams:
        """The commands that came since the last tick, in order, at the tick stamped `stamp_ns`, by a vessel
        that knows `vessels` alive (itself included); the parameters to tick with. A `set` the fleet cannot
        fly is refused (agent/core/mission_limits.py); an accepted one becomes the goal that r* and omega*
        move towards, a tick at a time."""
        with self._lock:
            pending = self._drain()
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
        """What a status carries: the latest answer of up to STATUS_ACKS senders, oldest first; those no status
        carried yet come first, so that a storm of senders cannot keep an answer out of every status."""
        with self._lock:
            unshown = sorted(self._unshown, key=lambda name: not self._acks[name].applied)   # applied first
            chosen = unshown[:STATUS_ACKS]
            for name in chosen:
                del self._unshown[name]
            for name in reversed(self._acks):
                if len(chosen) >= STATUS_ACKS:
                    break
                if name not in chosen:
                    chosen.append(name)
            return sorted((self._acks[name] for name in chosen), key=lambda ack: ack.stamp_ns)

    def judged(self) -> list[tuple[MissionCommand | None, MissionAck, int]]:
        """Every judgement since the last call: the command (None if it could not be read), the answer, and
        when the command came (agent time, ns)."""
        with self._lock:
            judged, self._judged = self._judged, []
        return judged

    def reset(self) -> None:
        """A new mission (the simulation restarted): no hold, nothing pending; senders' ids are kept (those
        outside the new clock's window go when their sender is next heard)."""
        with self._lock:
            for sender in self._senders.values():
                sender.pending.clear()
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
        self._acks[ack.sender] = ack
        self._acks.move_to_end(ack.sender)
        self._unshown[ack.sender] = None
        self._unshown.move_to_end(ack.sender)
        if len(self._acks) > MAX_SENDERS:
            # The oldest refusal goes first: a storm of refused senders does not push out an applied answer.
            refused = (name for name, a in self._acks.items() if not a.applied)
            forgotten = next(refused, next(iter(self._acks)))
            del self._acks[forgotten]
            self._unshown.pop(forgotten, None)
        # Refusals are logged up to a bound a tick (a flood's); what is applied, always.
        if ack.applied or len(self._judged) < MAX_LOGGED:
            self._judged.append((message, ack, max(0, received)))


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
