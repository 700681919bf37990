"""Latest-value inputs of one agent, filled from raw payloads and read once per tick.

`InputGate.offer(key, payload, now)` is what a Zenoh callback calls: it decodes, checks and keeps the
newest value per key, never blocks on I/O and never raises; every refusal is counted by reason (and the
last few reasons kept for the log). `snapshot(now)` turns what is fresh into the tick's `TickInputs`.

What is refused: undecodable or invalid payloads (wrong types, NaN, inf, negative ranges, non-unit
bearings, ...), a sender that is not the vessel of the key, a `seq` not newer than the last accepted one
from that sender on that key (duplicates and reordered messages), stamps further than `max_age` in the
past or `max_future` ahead of the agent's clock, and ranges to peers the agent does not know.

On sim time the gate holds each share until the sim clock says whether the simulated radio delivers it
(`deliver_shares`), so a fleet over Zenoh uses exactly the shares the in-process runner uses.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from collections.abc import Callable

import numpy as np

from agent.contract import (
    TOPICS,
    Bearing,
    Odometry,
    Ranges,
    ShareMessage,
    Sonar,
    decode,
    odometry_reading,
    seconds,
    share_from_message,
    vessel_of,
)
from agent.core.records import Share, TickInputs

OWN_TOPICS = ("sensor/odom", "sensor/uwb", "sensor/bearing", "sensor/sonar")


class InputGate:
    def __init__(self, vessel_id: str, max_age: float = 1.0, max_future: float = 0.5,
                 known_peers: Callable[[], set[str]] | None = None, keep_reasons: int = 20,
                 hold_shares: bool = False) -> None:
        self.id = vessel_id
        self.hold_shares = hold_shares
        self.max_age = max_age
        self.max_future = max_future
        self.known_peers = known_peers
        self.rejected: Counter[str] = Counter()
        self.accepted: Counter[str] = Counter()
        self.recent_reasons: deque[str] = deque(maxlen=keep_reasons)
        self._lock = threading.Lock()
        self._arrival = threading.Condition(self._lock)
        self._held: dict[tuple[str, int], Share] = {}   # (sender, stamp_ns) -> share awaiting the clock
        self._delivered_through: int | None = None
        self._latest: dict[str, object] = {}
        self._shares: dict[str, Share] = {}
        self._last_seq: dict[tuple[str, str], int] = {}
        self._consumed: dict[str, int] = {}   # topic -> stamp_ns of the range/bearing message last used

    # ----- the callback side -----
    def offer(self, key: str, payload: bytes | bytearray | memoryview, now: float | None) -> bool:
        """Decode and keep one payload received on `key` at agent time `now` (None: no clock yet, so stamps
        are not judged); False if refused."""
        try:
            return self._offer(str(key), payload, now)
        except Exception as error:  # the gate must never take the agent down, whatever arrives
            return self._refuse("internal", f"{key}: {type(error).__name__}: {error}")

    def _offer(self, key: str, payload, now: float | None) -> bool:
        vessel = vessel_of(key)
        topic = key.split("/", 2)[2] if vessel is not None else ""
        model = TOPICS.get(topic)
        if topic == "share" and vessel == self.id:
            return False  # our own share, echoed by a subscription to every vessel's
        if model is None or topic in OWN_TOPICS and vessel != self.id:
            return self._refuse("unexpected_key", key)
        message, reason = decode(model, payload)
        if message is None:
            return self._refuse("malformed", f"{key}: {reason}")
        if message.sender != vessel:
            return self._refuse("sender_mismatch", f"{key}: sender {message.sender!r}")
        stamp = seconds(message.stamp_ns)
        if now is not None and stamp < now - self.max_age:
            return self._refuse("stale", f"{key}: {now - stamp:.3f} s old")
        if now is not None and stamp > now + self.max_future:
            return self._refuse("future", f"{key}: {stamp - now:.3f} s ahead")
        with self._lock:
            last = self._last_seq.get((key, message.sender))
            if last is not None and message.seq == 0 and last > 0:
                self.accepted["sender_restarted"] += 1  # a sender that restarts counts from 0 again
            elif last is not None and message.seq <= last:
                return self._refuse("duplicate_or_reordered", f"{key}: seq {message.seq} after {last}",
                                    locked=True)
            self._last_seq[(key, message.sender)] = message.seq
            if isinstance(message, ShareMessage) and self.hold_shares:
                if self._delivered_through is not None and message.stamp_ns <= self._delivered_through:
                    return self._refuse("late_share", f"{key}: stamp {message.stamp_ns} already delivered",
                                        locked=True)
                # One share per sender and stamp: a second one for the same odometry stamp is a repeat.
                self._held.setdefault((message.sender, message.stamp_ns), share_from_message(message))
                self._arrival.notify_all()
            elif isinstance(message, ShareMessage):
                self._shares[message.sender] = share_from_message(message)
            else:
                self._latest[topic] = message
                self._arrival.notify_all()
            self.accepted[topic] += 1
        return True

    def _known_ranges(self, ranges: dict[str, float], shares: dict[str, Share]) -> dict[str, float]:
        """Ranges to peers alive (liveliness) or heard from (a share); a UWB module may still range to a
        vessel whose agent is gone, and such a range has no odometry to pair with."""
        if self.known_peers is None:
            return dict(ranges)
        known = self.known_peers() | set(shares)
        unknown = [peer for peer in ranges if peer not in known]
        if unknown:
            with self._lock:
                self.rejected["unknown_peer"] += len(unknown)
                self.recent_reasons.append(f"ranges to unknown peers {sorted(unknown)[:5]}")
        return {p: r for p, r in ranges.items() if p in known}

    def _refuse(self, reason: str, detail: str, locked: bool = False) -> bool:
        if locked:
            self.rejected[reason] += 1
            self.recent_reasons.append(f"{reason}: {detail}")
        else:
            with self._lock:
                self.rejected[reason] += 1
                self.recent_reasons.append(f"{reason}: {detail}")
        return False

    # ----- the tick side -----
    def forget(self, vessel: str) -> None:
        """A neighbour left (its liveliness token went away): drop its share."""
        with self._lock:
            self._shares.pop(vessel, None)
            for seq_key in [k for k in self._last_seq if k[1] == vessel]:
                del self._last_seq[seq_key]

    def deliver_shares(self, stamp_ns: int | None, senders: set[str] | None, wait: float = 0.0,
                       sensors_ns: int | None = None, wait_for_shares: bool = True) -> set[str]:
        """Make the held shares stamped `stamp_ns` from `senders` (None: from anyone) this agent's latest, and
        drop every other held share that old. With `wait` > 0, first wait up to that many seconds for this
        vessel's sensors stamped `sensors_ns` and (if `wait_for_shares`) for all of `senders` to arrive: the
        network may bring a tick's messages in any order. Returns the senders still missing."""
        deadline = time.monotonic() + wait
        with self._arrival:
            def absent() -> set[str]:
                if stamp_ns is None or senders is None:
                    return set()
                return {j for j in senders if (j, stamp_ns) not in self._held}

            def sensors_in() -> bool:
                return sensors_ns is None or all(
                    topic in self._latest and self._latest[topic].stamp_ns >= sensors_ns for topic in OWN_TOPICS)

            def ready() -> bool:
                return sensors_in() and not (wait_for_shares and absent())

            while not ready() and (remaining := deadline - time.monotonic()) > 0:
                self._arrival.wait(remaining)
            if wait > 0 and not sensors_in():
                self.rejected["sensors_missing"] += 1
            missing = absent()
            if stamp_ns is None:
                return missing
            if missing and wait_for_shares:
                self.rejected["shares_missing"] += len(missing)
            for (sender, stamp), share in list(self._held.items()):
                if stamp == stamp_ns and (senders is None or sender in senders):
                    self._shares[sender] = share
                if stamp <= stamp_ns:
                    del self._held[(sender, stamp)]
            self._delivered_through = max(stamp_ns, self._delivered_through or 0)
        return missing

    def snapshot(self, now: float) -> TickInputs:
        """This tick's inputs: the freshest odometry and sonar, ranges and bearing not used before, and the
        latest shares."""
        with self._lock:
            latest = dict(self._latest)
            shares = dict(self._shares)
            # A range pair or a bearing is a measurement at its stamp: each is used by one tick only.
            for topic in ("sensor/uwb", "sensor/bearing"):
                message = latest.get(topic)
                if message is not None and self._consumed.get(topic) == message.stamp_ns:
                    latest[topic] = None
                elif message is not None:
                    self._consumed[topic] = message.stamp_ns
        odometry = latest.get("sensor/odom")
        fresh = lambda message: message is not None and now - seconds(message.stamp_ns) <= self.max_age  # noqa: E731
        reading = odometry_reading(odometry) if isinstance(odometry, Odometry) and fresh(odometry) else None
        tick_time = reading.stamp if reading is not None else now
        message = latest.get("sensor/uwb")
        usable = isinstance(message, Ranges) and fresh(message)
        ranges = self._known_ranges(message.ranges, shares) if usable else {}
        # The measurement's own time; None when it is the tick's (lockstep sim): the core reads None as `time`.
        range_stamp = seconds(message.stamp_ns) if usable and ranges else None
        if range_stamp == tick_time:
            range_stamp = None
        bearing = latest.get("sensor/bearing")
        sonar = latest.get("sensor/sonar")
        return TickInputs(
            time=tick_time,
            odometry=reading,
            ranges=ranges,
            range_stamp=range_stamp,
            shares=shares,
            bearing=np.array(bearing.bearing) if isinstance(bearing, Bearing) and fresh(bearing)
            and bearing.bearing is not None else None,
            obstacle_points=np.array(sonar.points, dtype=float).reshape(-1, 2)
            if isinstance(sonar, Sonar) and fresh(sonar) else None,
        )
