"""What an agent publishes: each tick the command, then the share, then the status; a heartbeat status between.

The command goes first: it is what the thrusters wait for (sensor to command), and building the share costs
more than the command. The status goes last: once a bridge has it, the share is on its way (the sim bridge's
radio reads `Status.shared`). A share the contract refuses (an estimate beyond its limits) is not sent, and
counted. The status is built in one place (`Outbox.status`) for a tick and for a heartbeat; if the tick's
record does not fit the contract (a non-finite estimate), the status goes without it.
"""

from __future__ import annotations

import sys
from collections.abc import Callable

import zenoh

from agent.contract import SHARE_FORMAT, Cmd, Status, WeakestPair, encode, encode_per_pair, key, share_key
from agent.core.observability import MIRROR_AMBIGUOUS, UNOBSERVABLE
from agent.core.records import Command, Share, TickRecord
from agent.shell.translate import message_from_share

Health = Callable[[TickRecord | None], dict[str, int]]


def declare_publishers(session, vessel: str, sim: bool, share_format: int = SHARE_FORMAT) -> dict:
    """The agent's publishers on `session`: command, status and share (one to all in share format 1, one per
    receiver in format 2). On sim time nothing may be dropped by Zenoh (the simulated radio decides what is
    lost, and lockstep waits for every message); at sea a late command or share is worth less than a new one.
    The command goes express, at real-time priority."""
    congestion = zenoh.CongestionControl.BLOCK if sim else zenoh.CongestionControl.DROP
    # Our own subscription to every vessel's share (format 1) would hand ours straight back to us.
    share_options = {"congestion_control": congestion, "allowed_destination": zenoh.Locality.REMOTE}
    return {
        "cmd": session.declare_publisher(key(vessel, "cmd"), express=True, priority=zenoh.Priority.REAL_TIME,
                                         congestion_control=congestion),
        "share": PairPublishers(session, vessel, share_options) if share_format == 2
        else session.declare_publisher(share_key(vessel), **share_options),
        "status": session.declare_publisher(key(vessel, "status"), congestion_control=congestion)}


class PairPublishers:
    """Share format 2: a publisher on `usv/<vessel>/share/<j>` for each receiver j, declared when j is first
    sent to and undeclared when a share goes out without it (its liveliness token went away)."""

    def __init__(self, session, vessel: str, options: dict) -> None:
        self.session, self.vessel, self.options = session, vessel, options
        self.publishers: dict[str, object] = {}

    def put_each(self, payloads: dict[str, bytes]) -> None:
        for receiver in [j for j in self.publishers if j not in payloads]:
            self.publishers.pop(receiver).undeclare()
        for receiver, payload in payloads.items():
            publisher = self.publishers.get(receiver)
            if publisher is None:
                publisher = self.publishers[receiver] = self.session.declare_publisher(
                    share_key(self.vessel, receiver), **self.options)
            publisher.put(payload)


class Outbox:
    """One agent's streams on the wire (`cmd`, `share`, `status`): their seqs and what could not be sent.
    `publishers` maps each stream to something with `put(bytes)`."""

    def __init__(self, vessel: str) -> None:
        self.vessel = vessel
        self.seq = {"cmd": 0, "share": 0, "status": 0}
        self.shares_unsent = 0
        self.last_shared = False   # the last tick's share went out (a heartbeat repeats it)

    def command(self, publishers, stamp: int, command: Command) -> tuple[Cmd, bytes]:
        message = Cmd(stamp_ns=stamp, seq=self._next("cmd"), sender=self.vessel,
                      surge=float(command.surge), yaw_rate=float(command.yaw_rate))
        wire = encode(message)
        publishers["cmd"].put(wire)
        return message, wire

    def share(self, publishers, share: Share | None, receivers=()) -> bool:
        """Publish the tick's share, if it has one the contract takes, to all (format 1: `publishers["share"]`
        has `put`) or to each of `receivers` and each vessel it has an estimate of (format 2: `put_each`);
        whether it went out. In format 2 the same `seq` goes to every receiver: it counts the sender's shares."""
        shared = False
        if share is not None:
            try:
                message = message_from_share(share, self.seq["share"])
                out = publishers["share"]
                if hasattr(out, "put_each"):
                    out.put_each(encode_per_pair(message, sorted({*receivers, *message.neighbours})))
                else:
                    out.put(encode(message))
                self._next("share")
                shared = True
            except Exception as error:  # noqa: BLE001  (an estimate beyond the contract's limits: not sent, counted)
                self.shares_unsent += 1
                if self.shares_unsent == 1:
                    print(f"usv-agent {self.vessel}: a share not sent (the contract refuses it): "
                          f"{' '.join(str(error).split())[:300]}", file=sys.stderr)
        self.last_shared = shared
        return shared

    def status(self, publishers, stamp: int, command: tuple[float, float], record: TickRecord | None,
               peers: list[str], health: Health, view: dict, ticked: bool = True) -> tuple[Status, bytes]:
        """Publish the status of a tick at `stamp` (its record None if the core gave none), or of no tick
        (`ticked` False: a heartbeat); `view` is what it says for the operator (held, radius, mission, clocks)."""
        seq = self._next("status")
        try:
            status = self._status(stamp, seq, command, record, peers, health, view, ticked)
        except Exception:  # noqa: BLE001  (a non-finite estimate: the status goes without it)
            if record is None:
                raise
            status = self._status(stamp, seq, command, None, peers, health, view, ticked)
        wire = encode(status)
        publishers["status"].put(wire)
        return status, wire

    def _status(self, stamp, seq, command, record, peers, health, view, ticked) -> Status:
        return Status(
            stamp_ns=stamp, seq=seq, sender=self.vessel, phase=record.phase if record is not None else 0.0,
            command=command, shared=self.last_shared, peers=peers, ticked=ticked,
            target=None if record is None or record.target_state is None
            else tuple(float(v) for v in record.target_state),
            health=health(record), weakest_pair=weakest_pair(record), **view)

    def counts(self) -> dict[str, int]:
        return {"shares_unsent": self.shares_unsent}

    def _next(self, stream: str) -> int:
        value = self.seq[stream]
        self.seq[stream] += 1
        return value


def health(record: TickRecord | None, gate, peers, *parts) -> dict[str, int]:
    """The status's counters: the core's of this tick (and its pairs whose relative motion leaves them short of
    observable: gauges, not counts), the input gate's refusals by reason and the shares it was handed (and
    their bytes), the peer table's, and each of the shell's `parts`' `counts()`."""
    health = dict(record.health if record is not None else {})
    if record is not None:
        verdicts = [n.observability for n in record.neighbours.values()]
        health.update(pairs_mirror_ambiguous=verdicts.count(MIRROR_AMBIGUOUS),
                      pairs_unobservable=verdicts.count(UNOBSERVABLE))
    health.update({f"rejected_{k}": v for k, v in gate.rejected.items()})
    health.update(gate.received)
    health.update(peers.counted(), peers_withheld=len(peers.withheld()), peers_unproven=len(peers.unproven()))
    for part in parts:
        health.update(part.counts())
    health.update(clock_corrected=gate.offsets.corrected)
    return health


def weakest_pair(record: TickRecord | None) -> WeakestPair | None:
    """The pair of this tick whose relative path is narrowest (smallest eigenvalue of its spread, (41)), or None
    without a record or a pair."""
    if record is None or not record.neighbours:
        return None
    j, n = min(record.neighbours.items(), key=lambda item: (item[1].excitation[0], item[0]))
    return WeakestPair(neighbour=j, excitation=float(n.excitation[0]), observability=n.observability)
