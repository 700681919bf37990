"""Latest-value inputs of one agent, filled from raw payloads and read once per tick.

`InputGate.offer(key, payload, now)` is what a Zenoh callback calls: it decodes, checks and keeps the
newest value per key (and every UWB range set since the last tick, up to MAX_RANGE_SETS: a module ranges at
its own rate, and each set is a measurement at its own time), never blocks on I/O and never raises; every refusal is counted by reason (and the
last few reasons kept for the log). `snapshot(now)` turns what is fresh into the tick's `TickInputs`.

What is refused, in the order it is checked (the cheap checks come before decoding):
- a key the agent does not read (`unexpected_key`; a share to another vessel too), a share from a vessel
  whose liveliness token is not live (`unknown_sender`: a share alone never makes a neighbour), a new sender
  beyond MAX_PEERS (`too_many_peers`); shares of both formats are judged alike, one stamp mark per sender;
- more than `max_rate` messages per second on one key, with bursts of `burst` (`rate_limited`, a token
  bucket per key, so a flood costs a dictionary look-up per message and no decoding);
- an undecodable or invalid payload (`malformed`: wrong types, NaN, inf, values beyond the contract's
  physical limits, covariances that are not symmetric positive semi-definite, more than 2 MiB, ...), and a
  sender that is not the vessel of the key (`sender_mismatch`);
- a stamp further than `max_age` in the past (`stale`) or `max_future` ahead (`future`) of the agent's clock;
- a stamp not newer than the last one accepted from that sender on that key (`duplicate_or_reordered`).

When a tick reads its inputs (`snapshot`), own odometry older than the one the last tick used, or that moved
faster than MAX_SPEED (1 km/s) from it, is left out of that tick (`implausible_motion`): the core's own
velocity is the difference of the two.

More: docs/reliability.md §4, `agent/shell/gate.py`.
"""

from __future__ import annotations

import math
import statistics
import threading
import time
from collections import Counter, deque
from collections.abc import Callable

import numpy as np

from agent.contract import (
    CLOCK_SOURCE_SENSORS,
    MAX_PEERS,
    MAX_SENSOR_STAGGER,
    MAX_SPEED,
    TOPICS,
    VEHICLE_TOPIC,
    Bearing,
    Clock,
    Odometry,
    Ranges,
    ReceivedShare,
    Sonar,
    VehicleState,
    decode,
    nanoseconds,
    seconds,
    share_key,
    vessel_of,
)
from agent.core.records import Share, TickInputs
from agent.shell.translate import odometry_reading, share_from_message

OWN_TOPICS = ("sensor/odom", "sensor/uwb", "sensor/bearing", "sensor/sonar")
OWN_KEYS = (*OWN_TOPICS, VEHICLE_TOPIC)   # the vehicle's state too: kept for the status, awaited by no tick
ALWAYS_COUNTED = ("stale", "malformed", "shares_missing")   # refusals an operator watches (usv_op.layout)
DETAIL_CHARS = 200   # of a refusal's detail kept in `recent_reasons` (a key or a reason may be long)
MAX_RANGE_SETS = 32  # UWB range sets kept between two ticks (a module ranging at up to 300 Hz), the oldest dropped
OFFSET_WINDOW = 64   # messages judging a source's clock (1.6 s of own sensors, 6 s of a neighbour's shares)
OFFSET_MIN = 16      # messages of a source before its clock is judged at all
OFFSET_SPREAD = 0.1  # s: the largest median absolute deviation of a source's offsets for a correction
OFFSET_SETTLE = 0.05  # s: a correction in force moves only when the median moved further than this
MAX_CORRECTION = 3600.0  # s: a sensor clock more than an hour off is alarmed, never corrected: it is no clock


class TokenBucket:
    """At most `rate` events per second on average and `burst` at once."""

    __slots__ = ("burst", "last", "rate", "tokens")

    def __init__(self, rate: float, burst: float, now: float) -> None:
        self.rate, self.burst, self.tokens, self.last = rate, burst, burst, now

    def take(self, now: float) -> bool:
        self.tokens = min(self.burst, self.tokens + (now - self.last) * self.rate)
        self.last = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


class StampOffsets:
    """How far each source's stamps run from the agent's clock: the offsets stamp - now of its last
    OFFSET_WINDOW messages judged by their stamp, accepted or refused (a source is this vessel's sensors,
    `CLOCK_SOURCE_SENSORS`, or one neighbour's shares). The median is robust: a few late, early or forged
    stamps do not move it, and it follows a clock that changes within half a window.

    A source's clock disagrees with the agent's (`alarms`) when at least OFFSET_MIN offsets are in and their
    median is outside the window [-max_age, max_future]: most of its messages are refused for their stamp.
    For the own sensors, which come from one driver and one clock, `correction` then says how far to take
    their stamps back, once the offsets are also consistent (median absolute deviation within OFFSET_SPREAD):
    the vessel then runs on its sensors mapped onto the agent's clock instead of standing still (up to
    MAX_CORRECTION). This gives a spoofer of the sensor keys nothing it did not have: a forged message stamped
    now is taken anyway; with TLS only the driver may publish them."""

    def __init__(self, max_age: float, max_future: float) -> None:
        self.max_age, self.max_future = max_age, max_future
        self._offsets: dict[str, deque[float]] = {}
        self.applied = 0.0     # s: the correction in force on the own sensors' stamps
        self.corrected = 0     # own sensor messages whose stamp was corrected
        self._sensors_outside = 0   # offsets of the own sensors' window outside [-max_age, max_future]

    def observe(self, source: str, offset: float) -> None:
        window = self._offsets.get(source)
        if window is None:
            window = self._offsets[source] = deque(maxlen=OFFSET_WINDOW)
        if source != CLOCK_SOURCE_SENSORS:
            window.append(offset)
            return
        if len(window) == OFFSET_WINDOW and self.outside(window[0]):
            self._sensors_outside -= 1      # the oldest, which the append drops
        window.append(offset)
        self._sensors_outside += self.outside(offset)
        # A median outside the window needs at least half the offsets outside it: short of that, with no
        # correction in force, `_settle` would leave none, and its median (on every sensor message, on the
        # path from a tick's sensors to its command) is not worth taking.
        if self.applied or 2 * self._sensors_outside >= len(window):
            self._settle()

    def median(self, source: str) -> float | None:
        """The median offset of `source` once OFFSET_MIN offsets are in, else None."""
        window = self._offsets.get(source)
        # The standard library's median (sort, middle or mean of the two middle): numpy's numbers, without
        # its per-call cost, which was most of the gate's CPU with a window taken on every sensor message.
        return statistics.median(window) if window is not None and len(window) >= OFFSET_MIN else None

    def heard(self, source: str) -> int:
        """Messages of `source` in the window (at most OFFSET_WINDOW)."""
        return len(self._offsets.get(source, ()))

    def outside(self, offset: float | None) -> bool:
        return offset is not None and not -self.max_age <= offset <= self.max_future

    def _settle(self) -> None:
        """The own sensors' correction: their median offset while it is outside the window and consistent,
        else none; moved only by more than OFFSET_SETTLE, so that corrected stamps keep their order."""
        median = self.median(CLOCK_SOURCE_SENSORS)
        window = self._offsets[CLOCK_SOURCE_SENSORS]
        if (not self.outside(median) or abs(median) > MAX_CORRECTION
                or statistics.median(abs(offset - median) for offset in window) > OFFSET_SPREAD):
            self.applied = 0.0
        elif abs(median - self.applied) > OFFSET_SETTLE:
            self.applied = median

    def shift(self, source: str, delta: float) -> None:
        """The clock of `source` stepped by `delta` against the agent's: what was measured of it moves too."""
        window = self._offsets.get(source)
        if window is not None:
            self._offsets[source] = window = deque((offset + delta for offset in window), maxlen=OFFSET_WINDOW)
            if source == CLOCK_SOURCE_SENSORS:
                self._sensors_outside = sum(map(self.outside, window))
                self._settle()

    def forget(self, source: str) -> None:
        self._offsets.pop(source, None)
        if source == CLOCK_SOURCE_SENSORS:
            self._sensors_outside = 0

    def clear(self) -> None:
        self._offsets.clear()
        self.applied = 0.0
        self._sensors_outside = 0

    def alarms(self) -> list[tuple[str, float]]:
        """(source, median offset) of every source whose clock disagrees with the agent's, sensors first."""
        found = [(source, median) for source in self._offsets if self.outside(median := self.median(source))]
        return sorted(found, key=lambda item: (item[0] != CLOCK_SOURCE_SENSORS, item[0]))


class InputGate:
    def __init__(self, vessel_id: str, max_age: float = 1.0, max_future: float = 0.5,
                 known_peers: Callable[[], set[str] | frozenset[str]] | None = None, keep_reasons: int = 20,
                 hold_shares: bool = False, max_rate: float | None = 1000.0, burst: float | None = None,
                 max_held: int = 16, monotonic: Callable[[], float] = time.monotonic) -> None:
        self.id = vessel_id
        self.hold_shares = hold_shares
        self.max_age = max_age
        self.max_future = max_future
        self.known_peers = known_peers
        self.max_rate = max_rate
        self.burst = burst if burst is not None else (max_rate if max_rate is not None else None)
        self.max_held = max_held
        self._monotonic = monotonic
        # Present from the start at 0: the status's health carries them, and a plot of an absent field is empty.
        self.rejected: Counter[str] = Counter(dict.fromkeys(ALWAYS_COUNTED, 0))
        self.accepted: Counter[str] = Counter()
        self.received: Counter[str] = Counter(shares_received=0, share_bytes_received=0)
        self.recent_reasons: deque[str] = deque(maxlen=keep_reasons)
        self._lock = threading.Lock()
        self._arrival = threading.Condition(self._lock)
        self._ready: Callable[[], bool] | None = None   # what the tick waiting in deliver_shares waits for
        self._held: dict[tuple[str, int], Share] = {}   # (sender, stamp_ns) -> share awaiting the clock
        self._held_count: Counter[str] = Counter()       # sender -> shares held
        self._delivered_through: int | None = None
        self._latest: dict[str, object] = {}
        self._shares: dict[str, Share] = {}
        self._last_stamp: dict[tuple[str, str], int] = {}   # (topic, sender) -> stamp_ns of the last accepted
        self._senders: set[str] = set()                    # share senders with any state here
        self._buckets: dict[str, TokenBucket] = {}
        self._bearing_used: int | None = None   # stamp_ns of the bearing message the last tick used
        self._range_sets: deque[Ranges] = deque(maxlen=MAX_RANGE_SETS)   # UWB messages since the last tick
        self._used_odometry = None            # the OdometryReading the last snapshot gave the tick
        self.offsets = StampOffsets(max_age, max_future)   # how far each source's clock runs from ours
        self._ranged: dict[str, float] = {}   # vessel id -> stamp (s) of the last accepted range to it

    # ----- the callback side -----
    def offer(self, key: str, payload: bytes | bytearray | memoryview, now: float | None) -> bool:
        """Decode and keep one payload received on `key` at agent time `now` (None: no clock to judge stamps
        by); False if refused."""
        try:
            return self._offer(str(key), payload, now)
        except Exception as error:  # noqa: BLE001  (the gate must never take the agent down, whatever arrives)
            return self._refuse("internal", f"{key}: {type(error).__name__}: {error}")

    def _offer(self, key: str, payload, now: float | None) -> bool:
        vessel = vessel_of(key)
        topic = key.split("/", 2)[2] if vessel is not None else ""
        per_pair = topic.startswith("share/")
        if per_pair:   # format 2: a share to one receiver, usv/<sender>/share/<receiver>
            if topic != f"share/{self.id}":
                return self._refuse("unexpected_key", key)
            topic = "share"
        model = TOPICS.get(topic)
        if topic == "share" and vessel == self.id:
            return False  # our own share, echoed by a subscription to every vessel's
        if model is None or topic not in (*OWN_KEYS, "share") or topic in OWN_KEYS and vessel != self.id:
            return self._refuse("unexpected_key", key)
        if topic == "share":
            with self._lock:   # what the shares cost on the wire (status: shares_received, share_bytes_received)
                self.received["shares_received"] += 1
                self.received["share_bytes_received"] += len(payload)
            if self.known_peers is not None and vessel not in self.known_peers():
                return self._refuse("unknown_sender", f"{key}: no liveliness token")
            if vessel not in self._senders:
                with self._lock:
                    if len(self._senders) >= MAX_PEERS:
                        return self._refuse("too_many_peers", key, locked=True)
                    self._senders.add(vessel)
        if self.max_rate is not None:
            bucket = self._buckets.get(key)
            if bucket is None:
                bucket = self._buckets.setdefault(key, TokenBucket(self.max_rate, self.burst, self._monotonic()))
            if not bucket.take(self._monotonic()):
                return self._refuse("rate_limited", key)
        message, reason = decode(ReceivedShare if topic == "share" else model, payload)
        if message is None:
            return self._refuse("malformed", f"{key}: {reason}")
        mine = None
        if topic == "share":
            mine, reason = message.estimate_for(self.id)
            if per_pair and len(message.neighbours) > (self.id in message.neighbours):
                reason = "ShareMessage: neighbours: a share to one receiver carries other vessels' estimates"
            if reason:
                return self._refuse("malformed", f"{key}: {reason}")
        if message.sender != vessel:
            return self._refuse("sender_mismatch", f"{key}: sender {message.sender!r}")
        if now is not None:
            message = self._on_clock_of(topic, message, now)
        stamp = seconds(message.stamp_ns)
        if now is not None and stamp < now - self.max_age:
            return self._refuse("stale", f"{key}: {now - stamp:.3f} s old")
        if now is not None and stamp > now + self.max_future:
            return self._refuse("future", f"{key}: {stamp - now:.3f} s ahead")
        with self._lock:
            mark = (topic, message.sender)
            last = self._last_stamp.get(mark)
            # A mark the clock has left behind by more than max_future (a clock stepped back) blocks nothing.
            if (now is not None and last is not None and message.stamp_ns <= last
                    and seconds(last) <= now + self.max_future):
                return self._refuse("duplicate_or_reordered",
                                    f"{key}: stamp {message.stamp_ns} not after {last}", locked=True)
            if now is not None:
                self._last_stamp[mark] = message.stamp_ns
            if topic == "share" and self.hold_shares:
                # Without a clock to judge by (a restarted simulation's first shares can come before its
                # clock) a share is held: `reset` keeps it if it belongs to the new timeline.
                if (now is not None and self._delivered_through is not None
                        and message.stamp_ns <= self._delivered_through):
                    return self._refuse("late_share", f"{key}: stamp {message.stamp_ns} already delivered",
                                        locked=True)
                held = (message.sender, message.stamp_ns)
                if held not in self._held:   # one share per sender and stamp: a second one is a repeat
                    if self._held_count[message.sender] >= self.max_held:
                        return self._refuse("held_full", f"{key}: {self.max_held} shares held already",
                                            locked=True)
                    self._held[held] = self._share(message, mine)
                    self._held_count[message.sender] += 1
                self._wake()
            elif topic == "share":
                self._shares[message.sender] = self._share(message, mine)
            else:
                self._latest[topic] = message
                if isinstance(message, Ranges):
                    self._note_ranged(message)
                    if len(self._range_sets) == MAX_RANGE_SETS:
                        self.rejected["range_sets_dropped"] += 1   # the oldest, which the deque drops
                    self._range_sets.append(message)
                self._wake()
            self.accepted[topic] += 1
        return True

    def _wake(self) -> None:
        """After an arrival (caller holds the lock): wake the tick waiting in `deliver_shares` only if what it
        waits for is now all in. A wake-up for nothing costs a switch of threads, which on a boat's single core
        is time taken from the Zenoh thread delivering the next message (a tick's four sensors, or in lockstep
        its n - 1 shares)."""
        if self._ready is None or self._ready():
            self._arrival.notify_all()

    def _on_clock_of(self, topic: str, message, now: float):
        """Measure the offset of the message's stamp from `now` for its source; an own sensor message comes
        back with its stamp corrected while the sensors' clock is consistently outside the window (the
        correction in force: `StampOffsets`), else as it came."""
        own = topic in OWN_KEYS
        with self._lock:
            source = CLOCK_SOURCE_SENSORS if own else message.sender
            self.offsets.observe(source, seconds(message.stamp_ns) - now)
            correction = self.offsets.applied if own else 0.0
            if correction:
                self.offsets.corrected += 1
        if not correction:
            return message
        return message.model_copy(update={"stamp_ns": message.stamp_ns - nanoseconds(correction)})

    def clock_stepped(self, delta: float) -> None:
        """This computer's clock stepped by `delta` s against the agent's timeline (which holds on across the
        step, `WallTimeline`): the own sensors, stamped by a driver on this computer's clock, step with it, so
        their correction does at once; the neighbours' clocks did not step."""
        with self._lock:
            self.offsets.shift(CLOCK_SOURCE_SENSORS, delta)

    def clock_alarms(self) -> list[tuple[str, float]]:
        """Every source whose clock disagrees with the agent's: (source, median offset s), sensors first."""
        with self._lock:
            return self.offsets.alarms()

    def _note_ranged(self, message: Ranges) -> None:
        """Remember when our UWB module last ranged to each id (evidence that such a vessel is out there, for
        agent/shell/peers.py); bounded: beyond 2 * MAX_PEERS ids, the MAX_PEERS last ranged are kept."""
        stamp = seconds(message.stamp_ns)
        for peer in message.ranges:
            self._ranged[peer] = stamp
        if len(self._ranged) > 2 * MAX_PEERS:
            newest = sorted(self._ranged.items(), key=lambda item: item[1])[-MAX_PEERS:]
            self._ranged = dict(newest)

    def vehicle(self) -> VehicleState | None:
        """The autopilot's latest state its driver published (None: none came); for the status only."""
        with self._lock:
            return self._latest.get(VEHICLE_TOPIC)

    def ranged_within(self, peer: str, now: float | None, within: float) -> bool:
        """Whether our UWB module ranged to `peer` within `within` s of `now` (None: at all)."""
        stamp = self._ranged.get(peer)
        return stamp is not None and (now is None or abs(now - stamp) <= within)

    def _plausible(self, reading, now: float) -> bool:
        """Own odometry the tick may use: not older than the one the last tick used, and no faster than
        MAX_SPEED from it (within `max_age`). The core differences successive odometry into its own velocity:
        a position a metre away stamped a nanosecond after the last (a forged stamp just inside the window)
        would make that 1e9 m/s and send the target estimate to 1e7 m. A last one now further ahead than
        `max_future` (the clock stepped back) no longer counts."""
        last = self._used_odometry
        if last is None or last.stamp > now + self.max_future:
            return True
        interval = reading.stamp - last.stamp
        if interval < 0:
            return False
        if interval == 0 or interval > self.max_age:
            return True
        (x, y), (last_x, last_y) = reading.position, last.position
        return math.hypot(x - last_x, y - last_y) <= MAX_SPEED * interval

    def _share(self, message: ReceivedShare, mine) -> Share:
        """The share as the tick reads it: of the sender's estimates of its neighbours, only its estimate of
        this vessel (`mine`, checked; the only one the core uses: reciprocal fusion), so a held share costs a few
        hundred bytes whatever the sender put in it (up to MAX_PEERS entries)."""
        return share_from_message(message, {} if mine is None else {self.id: mine})

    def _known_ranges(self, ranges: dict[str, float], shares: dict[str, Share]) -> dict[str, float]:
        """Ranges to peers alive (liveliness) or heard from (a share); a UWB module may still range to a
        vessel whose agent is gone, and such a range has no odometry to pair with."""
        if self.known_peers is None:
            return dict(ranges)
        alive = self.known_peers()
        unknown = [peer for peer in ranges if peer not in alive and peer not in shares]
        if not unknown:
            return dict(ranges)
        with self._lock:
            self.rejected["unknown_peer"] += len(unknown)
            self.recent_reasons.append(f"ranges to unknown peers {sorted(unknown)[:5]}")
        return {p: r for p, r in ranges.items() if p in alive or p in shares}

    def _refuse(self, reason: str, detail: str, locked: bool = False) -> bool:
        if locked:
            self.rejected[reason] += 1
            self.recent_reasons.append(f"{reason}: {detail[:DETAIL_CHARS]}")
        else:
            with self._lock:
                self.rejected[reason] += 1
                self.recent_reasons.append(f"{reason}: {detail[:DETAIL_CHARS]}")
        return False

    def count(self, reason: str, detail: str) -> None:
        """Count a refusal decided elsewhere (the node's judgement of the sim clock)."""
        self._refuse(reason, detail)

    # ----- sessions and restarts -----
    def forget(self, vessel: str) -> None:
        """A neighbour's liveliness session ended (its token went away) or a new one began (a token declared
        again): drop its share, what is held of it, its freshness marks and its rate bucket."""
        with self._lock:
            self._shares.pop(vessel, None)
            for held in [k for k in self._held if k[0] == vessel]:
                del self._held[held]
            self._held_count.pop(vessel, None)
            for mark in [k for k in self._last_stamp if k[1] == vessel]:
                del self._last_stamp[mark]
            self._buckets.pop(share_key(vessel), None)
            self._buckets.pop(share_key(vessel, self.id), None)
            self._senders.discard(vessel)
            self.offsets.forget(vessel)

    def reset(self, now_ns: int) -> None:
        """The simulation restarted and its clock is now at `now_ns`: every freshness mark goes, and so does
        whatever belongs to the old timeline (shares delivered or held, sensors stamped outside the window
        around `now_ns`); what already belongs to the new one (a tick's sensors that came before its clock)
        stays."""
        low, high = now_ns - int(self.max_age * 1e9), now_ns + int(self.max_future * 1e9)
        with self._arrival:
            self._last_stamp.clear()
            self.offsets.clear()
            self._held = {k: share for k, share in self._held.items() if low <= k[1] <= high}
            self._held_count = Counter(sender for sender, _ in self._held)
            self._shares.clear()
            self._latest = {t: m for t, m in self._latest.items() if low <= m.stamp_ns <= high}
            self._range_sets = deque((m for m in self._range_sets if low <= m.stamp_ns <= high), maxlen=MAX_RANGE_SETS)
            self._bearing_used = None
            self._used_odometry = None
            self._delivered_through = None
            self._arrival.notify_all()

    # ----- the tick side -----
    def deliver_for(self, clock: Clock, share_wait: float, dt: float) -> None:
        """Sim time: take the shares of the tick before that `clock` (the sim's radio) delivers to this vessel,
        once this tick's own sensors are in; in lockstep first wait (up to `share_wait`) for those shares too.
        In real time only the own sensors are worth a wait, bounded by three quarters of `dt`: the bridge
        publishes them within `MAX_SENSOR_STAGGER` (half) of dt after the clock (its `stagger`,
        sim_bridge/bridge.py), and a vessel whose sensors never come still answers before the world's next step.
        Each neighbour's newest share that has come is taken, late or not, unless the radio lost it: at sea a late
        share is still the neighbour's latest word."""
        wait = share_wait if clock.lockstep else (MAX_SENSOR_STAGGER + 0.25) * dt
        sensed = clock.vessels is not None and self.id in clock.vessels
        lost = None if clock.lockstep else {sender for sender, to in clock.lost if to == self.id}
        self.deliver_shares(clock.previous_ns, clock.delivered_to(self.id), wait, clock.stamp_ns if sensed else None,
                            wait_for_shares=clock.lockstep, lost=lost)

    def deliver_shares(self, stamp_ns: int | None, senders: set[str] | None, wait: float = 0.0,
                       sensors_ns: int | None = None, wait_for_shares: bool = True,
                       lost: set[str] | None = None) -> set[str]:
        """Make the held shares stamped `stamp_ns` from `senders` (None: from anyone) this agent's latest, and
        drop every other held share that old. With `wait` > 0, first wait up to that many seconds for this
        vessel's sensors stamped `sensors_ns` and (if `wait_for_shares`) for all of `senders` to arrive: the
        network may bring a tick's messages in any order. Returns the senders still missing.

        `lost` given (sim time in real time): the network, not the clock, decides what is in time. From each
        sender, its newest held share stamped up to `stamp_ns` becomes its latest, unless that is its share of
        `stamp_ns` and the sender is in `lost` (the simulated radio's loss); `senders` is not asked. A share
        that came after its tick, or is stamped off the clock's ticks (its sender ticked on older odometry, or
        skipped a clock), is late, not lost: taken only when stamped exactly `stamp_ns`, a loaded fleet went
        over a second without shares, dropped its neighbours and started cold (docs/fleet.md §6)."""
        deadline = time.monotonic() + wait
        with self._arrival:
            def absent() -> set[str]:
                if stamp_ns is None or senders is None or lost is not None:
                    return set()
                return {j for j in senders if (j, stamp_ns) not in self._held}

            def sensors_in() -> bool:
                return sensors_ns is None or all(
                    topic in self._latest and self._latest[topic].stamp_ns >= sensors_ns for topic in OWN_TOPICS)

            def ready() -> bool:
                return sensors_in() and not (wait_for_shares and absent())

            self._ready = ready
            try:
                while not ready() and (remaining := deadline - time.monotonic()) > 0:
                    self._arrival.wait(remaining)
            finally:
                self._ready = None
            if wait > 0 and not sensors_in():
                self.rejected["sensors_missing"] += 1
            missing = absent()
            if stamp_ns is None:
                return missing
            if missing and wait_for_shares:
                self.rejected["shares_missing"] += len(missing)
            if lost is not None:
                self._deliver_newest(stamp_ns, lost)
                return missing
            for (sender, stamp), share in list(self._held.items()):
                if stamp == stamp_ns and (senders is None or sender in senders):
                    self._shares[sender] = share
                if stamp <= stamp_ns:
                    del self._held[(sender, stamp)]
                    self._held_count[sender] -= 1
                    if self._held_count[sender] <= 0:
                        del self._held_count[sender]
            self._delivered_through = max(stamp_ns, self._delivered_through or 0)
        return missing

    def _deliver_newest(self, stamp_ns: int, lost: set[str]) -> None:
        """`deliver_shares` in real time; the caller holds the lock. The marks let a sender's stamps only go
        up, and what is delivered leaves the held shares, so a held share is always newer than its sender's
        latest. `_delivered_through` stays: a share that comes after its tick is still the sender's newest.

        A sender's first share is its oldest one instead (the later ones stay held for the next tick): a pair
        filter starts from the deployment estimate at its stamp, and needs the neighbour's odometry of that
        time. Agents that all stalled after their first tick (a loaded machine) otherwise met with shares
        0.7 s later and found their deployment estimates stale."""
        chosen: dict[str, tuple[int, Share]] = {}
        for (sender, stamp), share in sorted(self._held.items(), key=lambda item: item[0][1]):
            if stamp > stamp_ns or stamp == stamp_ns and sender in lost:
                continue
            if sender not in self._shares and sender in chosen:
                continue    # a first contact: its oldest share is taken, the later ones wait
            chosen[sender] = (stamp, share)
        for (sender, stamp) in list(self._held):
            if stamp <= stamp_ns and (sender in self._shares or stamp <= chosen.get(sender, (stamp_ns,))[0]
                                      or stamp == stamp_ns and sender in lost):
                del self._held[(sender, stamp)]
                self._held_count[sender] -= 1
                if self._held_count[sender] <= 0:
                    del self._held_count[sender]
        for sender, (_, share) in chosen.items():
            self._shares[sender] = share

    def snapshot(self, now: float) -> TickInputs:
        """This tick's inputs: the freshest odometry and sonar, the bearing if not used before, every range set
        received since the last tick, and the latest shares. Only what is stamped within
        [now - max_age, now + max_future] is used."""
        with self._lock:
            latest = dict(self._latest)
            shares = dict(self._shares)
            range_sets = list(self._range_sets)
            self._range_sets.clear()
            # A bearing is a measurement at its stamp: it is used by one tick only (so is each range set).
            message = latest.get("sensor/bearing")
            if message is not None and self._bearing_used == message.stamp_ns:
                latest["sensor/bearing"] = None
            elif message is not None:
                self._bearing_used = message.stamp_ns
        odometry = latest.get("sensor/odom")

        def fresh(message) -> bool:
            return message is not None and -self.max_future <= now - seconds(message.stamp_ns) <= self.max_age

        reading = odometry_reading(odometry) if isinstance(odometry, Odometry) and fresh(odometry) else None
        if reading is not None and not self._plausible(reading, now):
            self._refuse("implausible_motion", f"odometry at {reading.stamp:.9f} s: older than the last used, or "
                         f"faster than {MAX_SPEED:g} m/s from it")
            reading = None
        if reading is not None:
            self._used_odometry = reading
        tick_time = reading.stamp if reading is not None else now
        # Each set at its own time, oldest first (a sender's stamps only go up: the marks see to it).
        sets = [(seconds(m.stamp_ns), known) for m in range_sets
                if fresh(m) and (known := self._known_ranges(m.ranges, shares))]
        range_stamp, ranges = sets.pop() if sets else (None, {})
        if range_stamp == tick_time:   # measured at the tick (lockstep sim): the core reads None as `time`
            range_stamp = None
        bearing = latest.get("sensor/bearing")
        sonar = latest.get("sensor/sonar")
        return TickInputs(
            time=tick_time,
            odometry=reading,
            ranges=ranges,
            range_stamp=range_stamp,
            earlier_ranges=tuple(sets),
            shares=shares,
            bearing=np.array(bearing.bearing) if isinstance(bearing, Bearing) and fresh(bearing)
            and bearing.bearing is not None else None,
            obstacle_points=np.array(sonar.points, dtype=float).reshape(-1, 2)
            if isinstance(sonar, Sonar) and fresh(sonar) else None,
        )


class SimClock:
    """The sim/clock an agent on sim time runs on, judged message by message (`offer`).

    The sim bridge's clock advances by one tick per message. So a clock ahead of the last one by at most
    `max_jump` seconds is the next tick; one behind by at most that much is a duplicate, a reordered message,
    or the genuine clock catching up with a forged one a little ahead (`clock_reordered`: refused, and the
    agent waits until the clock passes its last tick). A clock further away either way is a discontinuity:
    the simulation restarted (its clock starts again from 0), or a stray or forged clock. It is taken as a
    restart
    - at once, when it goes back and the clock had been silent for `silence` wall seconds before it (a
      restarted sim bridge takes seconds to come back, and starts again from 0);
    - or when `confirm` discontinuous clocks continue each other (a new timeline that keeps going; up to
      MAX_CHAINS such timelines are followed at once, so clocks of other kinds in between do not hide it);
    otherwise it is refused (`clock_jump`). So one clock of 2^62 ns can neither freeze the agent (the next
    genuine clock continues the old timeline) nor restart it, one a little ahead holds it back for at most
    `max_jump`, and a restarted simulation is always followed."""

    MAX_CHAINS = 8

    def __init__(self, dt: float, max_jump: float = 1.0, confirm: int = 3, silence: float = 1.0,
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        self.tick_ns = round(dt * 1e9)
        self.max_jump_ns = max(round(max_jump * 1e9), 2 * self.tick_ns)   # a tick is never a jump
        self.confirm = confirm
        self.silence = silence
        self._monotonic = monotonic
        self._lock = threading.Lock()
        self.latest = None          # the newest accepted Clock
        self._heard = 0.0           # monotonic time it was accepted
        self._chains: list[list] = []   # [last discontinuous clock of a timeline, clocks in it], newest last

    def offer(self, message) -> str:
        """'first', 'tick' or 'restart' when `message` becomes the clock; else the reason it is refused."""
        with self._lock:
            now = self._monotonic()
            if self.latest is None:
                return self._accept(message, now, "first")
            step = message.stamp_ns - self.latest.stamp_ns
            if 0 < step <= self.max_jump_ns:
                return self._accept(message, now, "tick")
            if step < -self.tick_ns and now - self._heard >= self.silence:
                return self._accept(message, now, "restart")
            if -self.max_jump_ns <= step <= 0:
                return "clock_reordered"
            for chain in self._chains:
                if 0 < message.stamp_ns - chain[0].stamp_ns <= self.max_jump_ns:
                    chain[0], chain[1] = message, chain[1] + 1
                    self._chains.remove(chain)
                    self._chains.append(chain)
                    break
            else:
                self._chains.append([message, 1])
                del self._chains[:-self.MAX_CHAINS]
            if self._chains[-1][1] >= self.confirm:
                return self._accept(message, now, "restart")
            return "clock_jump"

    def _accept(self, message, now: float, verdict: str) -> str:
        self.latest, self._heard = message, now
        self._chains.clear()
        return verdict

    def silent(self) -> bool:
        """No clock yet, or none for `silence` wall seconds."""
        with self._lock:
            return self.latest is None or self._monotonic() - self._heard >= self.silence
