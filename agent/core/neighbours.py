"""One neighbour as vessel i sees it: the relative position filter and the bookkeeping that feeds it.

A range to j measured at time s can only be used once j's cumulative odometry around s has arrived (in
its share, typically one tick later). The track keeps short histories of both vessels' odometry and of the
ranges, each at its own stamp, and runs the filter over the ranges in time order: each range's time gets
both vessels' positions interpolated from the samples around it (at most `max_gap` apart), so the stamps
of ranges, of i's odometry and of j's need not meet. A range waits (up to `wait`) for j's odometry of its
time; one that comes after the filter has moved past its time, or whose time falls in a gap of an odometry
history, cannot be used and is counted. The filter state refers to the last range used (`epoch`). For
control, the estimate is carried from the epoch to the current time with i's odometry, j's odometry as far
as it is known, and j's commanded velocity for the rest. In the lockstep simulation every stamp is a tick,
the interpolation meets the samples exactly, and nothing is approximated.

The pair state is p_ij of (10); the odometry differences are (5) and (11), the range pairing (12), (13),
(14), the prediction (15). Beside the filter, the track keeps the spread of the relative path at the range
epochs, what (41) asks of the motion (`observability.py`); it is bookkeeping and changes no estimate.
"""

from __future__ import annotations

import bisect
import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from agent.core.antenna import ZERO, antenna_offset, arm_vector
from agent.core.checks import CheckedShare
from agent.core.estimators import RelativePositionEstimator, make_relative_estimator
from agent.core.estimators.base import UpdateOutcome
from agent.core.observability import PathSpread, verdict
from agent.core.params import FleetParams, RelativeEstimationParams
from agent.core.records import Share


def stamp_key(stamp: float) -> int:
    """Histories are keyed by the stamp in microseconds, so stamps computed two ways still meet."""
    return int(round(stamp * 1e6))


@dataclass(frozen=True)
class NeighbourPrior:
    """An initial estimate of p_ij at a stamp (the paper's p^_ij,0 ~ N(p_ij,0, P_ij,0) at t = 0)."""

    position: np.ndarray
    covariance: np.ndarray
    stamp: float | None = 0.0     # None: at the vessel's first tick (deployment knowledge given at launch)


class History:
    """Values by stamp (keyed in microseconds), keeping the most recent `size` stamps. Positions are kept as
    (x, y) float tuples, not arrays: every tick reads several of them per neighbour in floats."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._values: dict[int, object] = {}
        self._keys: list[int] | None = []      # sorted keys, rebuilt when a put comes out of order

    def put(self, stamp: float, value: object) -> None:
        self.put_key(stamp_key(stamp), value)

    def put_key(self, key: int, value: object) -> None:
        """`put` for a caller that has the stamp's key already (`store_ranges`, once for all its ranges)."""
        values, keys = self._values, self._keys     # (locals: two puts per neighbour and tick)
        if keys is not None and key not in values:
            if keys and key < keys[-1]:
                self._keys = keys = None            # out of order: sorted again on the next read
            else:
                keys.append(key)
        values[key] = value
        excess = len(values) - self.size
        if excess > 0:
            if keys is None:
                keys = self.keys()
            if excess == 1:                         # the usual put once full: no list for it
                del values[keys[0]]
            else:
                for old in keys[:excess]:
                    del values[old]
            # Trimmed in place (still sorted, no sort on the next read): a new list per put would be one more
            # object per neighbour and tick for the garbage collector to walk.
            del keys[:excess]

    def get(self, key: int):
        return self._values.get(key)

    def pop(self, key: int) -> None:
        if self._values.pop(key, None) is not None:
            self._keys = None

    def keys(self) -> list[int]:
        if self._keys is None:
            self._keys = sorted(self._values)
        return self._keys

    def keys_after(self, key: int) -> list[int]:
        keys = self.keys()
        return keys[bisect.bisect_right(keys, key):]

    def latest(self) -> int | None:
        keys = self.keys()
        return keys[-1] if keys else None

    def kept(self) -> bool:
        """Whether any value is kept (`latest() is not None` without the keys' sort)."""
        return bool(self._values)

    def at(self, key: int, max_gap: int) -> tuple[tuple[float, float] | None, str]:
        """The (x, y) value at `key`: the sample itself, or the straight line between the samples around it
        when they are at most `max_gap` apart. (None, why) otherwise: "later" (no sample at or after it yet),
        "before" (older than every sample kept) or "gap" (the samples around it are too far apart)."""
        value = self._values.get(key)
        if value is not None:
            return value, ""
        keys = self.keys()
        index = bisect.bisect_left(keys, key)
        if index == len(keys):
            return None, "later"
        if index == 0:
            return None, "before"
        before, after = keys[index - 1], keys[index]
        if after - before > max_gap:
            return None, "gap"
        fraction = (key - before) / (after - before)
        (lx, ly), (hx, hy) = self._values[before], self._values[after]
        # numpy's low + fraction * (high - low), element by element
        return (lx + fraction * (hx - lx), ly + fraction * (hy - ly)), ""

    def items(self) -> list[tuple[int, object]]:
        return [(key, self._values[key]) for key in self.keys()]

    def last_values(self, count: int) -> list:
        """The values of the last `count` stamps (fewer if fewer are kept), oldest first."""
        values = self._values
        return [values[key] for key in self.keys()[-count:]]

    def restore(self, pairs) -> None:
        """Take back what `items` gave (agent/core/snapshot.py)."""
        self._values = dict(pairs)
        self._keys = None


@dataclass(frozen=True)
class PairTiming:
    """How ranges and the two odometry histories are matched in time (FleetParams)."""

    max_gap: float          # s: largest gap between two odometry samples a range's time may fall in
    wait: float             # s: how long a range waits for the neighbour's odometry of its time

    @classmethod
    def of(cls, fleet: FleetParams) -> PairTiming:
        return cls(fleet.max_odometry_gap, fleet.range_wait)


class NeighbourTrack:
    """Relative position of one neighbour j, estimated by one inter-vessel filter."""

    def __init__(self, neighbour: str, params: RelativeEstimationParams, dt: float, history: int,
                 timing: PairTiming) -> None:
        self.neighbour = neighbour
        self.params = params
        self.dt = dt
        self.timing = timing
        self.gap_key = stamp_key(timing.max_gap)     # timing.max_gap and timing.wait as stamp keys
        self.wait_key = stamp_key(timing.wait)
        self.observability = params.observability
        self.spread = PathSpread()         # the relative path at the range epochs, (41)
        self.odometry = History(history)   # j's cumulative odometry by its stamps, (x, y)
        self.ranges = History(history)     # ranges to j measured by i, by their stamps
        # j's antenna arm vector R(psi_j) a_j by its odometry's stamps, once a share has given an antenna
        self.arms = History(history)
        self.estimator: RelativePositionEstimator | None = None
        self.epoch: int | None = None      # stamp key the filter state refers to
        # i's and j's odometry at the epoch as (x, y) floats: every tick reads them in floats, several times
        self.epoch_own: tuple[float, float] | None = None
        self.epoch_other: tuple[float, float] | None = None
        self.last_range: float | None = None
        self.last_offset = ZERO            # delta_ij at last_range's time (antenna.py)
        self.share: Share | None = None    # latest share received
        # That share's estimate of our pair, checked and as floats (agent/core/checks.py pair_entry_floats);
        # (): it carries none.
        self.reciprocal: tuple[float, ...] = ()
        self.velocity: tuple[float, float] | None = None     # that share's velocity (2), checked, as floats
        self.last_heard = -math.inf
        self.first_heard = math.inf
        self.updates = 0
        self.rejected = 0
        self.last_iterations = 0
        # (stamp s, range m, outcome) of each update of the last advance: a tuple, which the tick's record
        # takes as it is (no copy, no list left behind for the garbage collector).
        self.outcomes: tuple[tuple[float, float, UpdateOutcome], ...] = ()
        # This tick's p^_ij and covariance at the epoch, our filter's fused with j's own (cooperation.py), as
        # the floats of `moments`; None: not fused this tick. Derived afresh every tick, never fed back into
        # the filter.
        self.fused: tuple[float, float, float, float, float] | None = None

    def moments(self) -> tuple[float, float, float, float, float]:
        """(px, py, p11, p12, p22) of `best`, in plain floats (for callers doing their 2-D algebra in floats)."""
        if self.fused is not None:
            return self.fused
        return self.estimator.moments()

    def best(self) -> tuple[np.ndarray, np.ndarray]:
        """p^_ij and its covariance at the epoch: fused with j's estimate if this tick could, else our filter's."""
        px, py, p11, p12, p22 = self.moments()
        return np.array([px, py]), np.array([[p11, p12], [p12, p22]])

    def best_trace(self) -> float:
        """trace of `best`'s covariance, without building the matrix."""
        _, _, p11, _, p22 = self.moments()
        return p11 + p22

    def receive(self, share: Share, now: float, checked: CheckedShare) -> None:
        """Keep j's odometry and what it shares; shares may repeat or arrive out of order. `checked` is what
        `checked_share` gave for the share."""
        stamp, (position, velocity, reciprocal) = share.odometry.stamp, checked
        self.odometry.put(stamp, position)
        if share.antenna is not None or self.arms.kept():
            self.arms.put(stamp, arm_vector(share.odometry.heading, share.antenna or ZERO))
        if self.share is None or stamp >= self.share.odometry.stamp:
            self.share, self.reciprocal, self.velocity = share, reciprocal, velocity
        if stamp > self.last_heard:        # max and min, without their calls (per neighbour and tick)
            self.last_heard = stamp
        if stamp < self.first_heard:
            self.first_heard = stamp

    def positions_at(self, own: History, key: int) -> tuple[tuple[float, float] | None,
                                                            tuple[float, float] | None, str]:
        """(i's odometry, j's odometry, why not) at stamp `key`, interpolated where needed."""
        mine, why_mine = own.at(key, self.gap_key)
        theirs, why_theirs = self.odometry.at(key, self.gap_key)
        if mine is None or theirs is None:
            reasons = {why_mine, why_theirs}
            return None, None, "later" if "later" in reasons else ("gap" if "gap" in reasons else "before")
        return mine, theirs, ""

    def ranges_with_motion(self, own: History, key: int) -> tuple[tuple[float, float], list] | None:
        """i's odometry at stamp key `key`, and each range kept whose time both odometries cover, as (range,
        i's motion, j's motion) since `key`, each motion (dx, dy) in floats: what carries a p_ij of that time to
        each range's (p_ij(t_k) = p_ij(t) + i's motion - j's motion). None when `key` itself is not covered."""
        mine_then, theirs_then, why = self.positions_at(own, key)
        if why:
            return None
        (ax, ay), (bx, by) = mine_then, theirs_then
        kept = []
        for k, measured in self.ranges.items():
            mine, theirs, why = self.positions_at(own, k)
            if not why:
                kept.append((measured, (mine[0] - ax, mine[1] - ay), (theirs[0] - bx, theirs[1] - by)))
        return mine_then, kept

    def start(self, prior: NeighbourPrior, own: History, own_arms: History | None = None) -> str:
        """Start the filter from `prior`, the initial estimate of (10), at its stamp: "started", "wait" (the
        odometry of that time has not all arrived), or "stale" (the prior's time is outside the odometry
        kept, so nothing can carry it to now)."""
        key = stamp_key(prior.stamp)
        position = np.asarray(prior.position, dtype=float)
        mine, theirs, why = self.positions_at(own, key)
        if why == "later":
            return "wait"
        if why:
            # The prior's time is just before the neighbour's first odometry (it started a little later,
            # or its clock runs ahead): carry the prior to the first time both are known, moving j by its
            # shared velocity, if that is within `max_gap`.
            first = next((k for k in self.odometry.keys_after(key) if k - key <= self.gap_key
                          and self.positions_at(own, k)[2] == ""), None)
            if first is None or self.velocity is None:
                return "stale"
            mine, theirs, _ = self.positions_at(own, first)
            mine_then = own.at(key, self.gap_key)[0]
            own_moved = np.zeros(2) if mine_then is None else np.subtract(mine, mine_then)
            position = position + own_moved - np.array(self.velocity) * ((first - key) * 1e-6)
            key = first
        self.estimator = make_relative_estimator(self.params, position, prior.covariance, dt=self.dt)
        self.epoch, self.epoch_own, self.epoch_other = key, mine, theirs
        self.last_range = None
        self.spread = PathSpread()
        range_now = self.ranges.get(key)
        if range_now is not None:
            self.estimator.mark_range_epoch()
            self.last_range = range_now
            self.last_offset = self.offset_at(own_arms, key) or ZERO
            self.spread.add(0.0, 0.0, 0.0, self.observability.window)
        return "started"

    def offset_at(self, own_arms: History | None, key: int) -> tuple[float, float] | None:
        """delta_ij at stamp `key` from both vessels' antenna arm vectors (antenna.py), each interpolated like
        the odometry (a missing one counts as 0); None when neither vessel has an antenna off its centre, so
        that the filter runs the centre-to-centre model (6) exactly as without antennas."""
        mine = None if own_arms is None or own_arms.latest() is None else own_arms.at(key, self.gap_key)[0]
        theirs = None if self.arms.latest() is None else self.arms.at(key, self.gap_key)[0]
        if mine is None and theirs is None:
            return None
        return antenna_offset(mine or ZERO, theirs or ZERO)

    def advance(self, own: History, now: int, unusable: Counter, own_arms: History | None = None) -> None:
        """Run the filter over the ranges after the epoch, in time order: the relative displacement (5), (11)
        between the epoch and the range's time predicts (15), and each range paired with the previous one
        updates, (12), (13), (14). Ranges that cannot be used are dropped and counted in `unusable` by
        reason ("unpaired": j's odometry of their time never came; "gap": an odometry gap around them).
        `now` is the tick's time as a stamp key (`stamp_key`), computed once for all the tracks."""
        self.outcomes = ()
        if self.estimator is None or self.epoch is None:
            return
        latest = self.odometry.latest()
        # Without antennas off the centres (the paper's fleets) no offset is looked up: the loop is as it was.
        arms = self.arms.kept() or (own_arms is not None and own_arms.kept())
        for key in self.ranges.keys_after(self.epoch):
            if latest is None or key > latest:
                mine, theirs, why = None, None, "later"     # what positions_at says, without asking
            else:
                mine, theirs, why = self.positions_at(own, key)
            if why == "later":
                if now - key <= self.wait_key:
                    break           # wait for the odometry of its time; later ranges wait behind it
                why = "unpaired"
            if why:
                self.ranges.pop(key)
                unusable["gap" if why == "before" else why] += 1
                continue
            range_now = self.ranges.get(key)
            # (5), (11) in plain floats: numpy's per-call overhead would be most of the cost of 2-vectors.
            (mx, my), (tx, ty) = mine, theirs
            (ox, oy), (ex, ey) = self.epoch_own, self.epoch_other
            displacement = ((mx - ox) - (tx - ex), (my - oy) - (ty - ey))
            if not self.estimator.predict(displacement, intervals=(key - self.epoch) * 1e-6 / self.dt):
                self.ranges.pop(key)
                continue
            self.spread.add(*displacement, (key - self.epoch) * 1e-6, self.observability.window)
            self.epoch, self.epoch_own, self.epoch_other = key, (mx, my), (tx, ty)
            offset = self.offset_at(own_arms, key) if arms else None
            if self.last_range is None:
                self.estimator.mark_range_epoch()
                self.last_range, self.last_offset = range_now, offset or ZERO
                continue
            if offset is None:
                outcome = self.estimator.update(self.last_range, range_now)
            else:
                outcome = self.estimator.update_between(self.last_range, range_now, self.last_offset, offset)
            self.outcomes += ((key * 1e-6, range_now, outcome),)    # usually one: () + (x,) is (x,) itself
            self.last_iterations = outcome.iterations
            if outcome.accepted:
                self.last_range, self.last_offset = range_now, offset or ZERO
                self.updates += 1
            else:
                self.rejected += 1

    def excitation(self) -> tuple[float, float, str]:
        """(lambda_min, lambda_max) of the relative path's spread over the window (m^2), and the verdict:
        observable, mirror-ambiguous or unobservable (`observability.py`)."""
        low, high = self.spread.eigenvalues()
        return low, high, verdict(low, high, self.observability.min_width)

    def estimate_at(self, own: History, now: int) -> np.ndarray | None:
        """p^_ij at `now` (a stamp key): the filter's estimate carried forward by i's odometry, j's odometry as
        far as it is known, and j's shared velocity (2) for the rest, as in (15)."""
        estimate = self.estimate_floats_at(own, now)
        return None if estimate is None else np.array(estimate)

    def estimate_floats_at(self, own: History, key: int) -> tuple[float, float] | None:
        """`estimate_at` as two plain floats."""
        if self.estimator is None or self.epoch is None:
            return None
        own_now = own.get(key)
        px, py, _, _, _ = self.moments()
        if key == self.epoch or own_now is None:
            return px, py
        # In plain floats, as numpy would do it element by element (2-vectors: the call overhead is the cost).
        mx = my = 0.0       # j's motion since the epoch
        latest = self.odometry.latest()
        known = latest if latest is not None and self.epoch < latest < key else self.epoch
        if known != self.epoch:
            (kx, ky), (ex, ey) = self.odometry.get(known), self.epoch_other
            mx, my = kx - ex, ky - ey
        if self.velocity is not None:
            (vx, vy), elapsed = self.velocity, (key - known) * 1e-6
            mx, my = mx + vx * elapsed, my + vy * elapsed
        (ix, iy), (ox, oy) = own_now, self.epoch_own
        return (px + (ix - ox)) - mx, (py + (iy - oy)) - my
