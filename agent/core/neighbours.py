"""One neighbour as vessel i sees it: the relative position filter and the bookkeeping that feeds it.

A range to j measured at time s can only be used once j's cumulative odometry at s has arrived (in its
share, typically one tick later). The track therefore keeps short histories keyed by stamp and runs the
filter over every stamp at which both odometries are known, in order; the filter state always refers to
the last such stamp (`epoch`). Stamps whose share was lost are skipped, and the next usable stamp's
displacement covers the whole interval, because odometry is cumulative. For control, the estimate is
carried from the epoch to the current time with vessel i's own odometry and j's commanded velocity.

The pair state is p_ij of (10); the odometry differences are (5) and (11), the range pairing (12), (13),
(14), the prediction (15).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agent.core.estimators import RelativePositionEstimator, make_relative_estimator
from agent.core.estimators.base import UpdateOutcome
from agent.core.params import RelativeEstimationParams
from agent.core.records import Share


def stamp_key(stamp: float) -> int:
    """Histories are keyed by the stamp in microseconds, so stamps computed two ways still meet."""
    return int(round(stamp * 1e6))


@dataclass(frozen=True)
class NeighbourPrior:
    """An initial estimate of p_ij at a stamp (the paper's p^_ij,0 ~ N(p_ij,0, P_ij,0) at t = 0)."""

    position: np.ndarray
    covariance: np.ndarray
    stamp: float = 0.0


class History:
    """Values by stamp, keeping the most recent `size` stamps."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._values: dict[int, object] = {}

    def put(self, stamp: float, value: object) -> None:
        self._values[stamp_key(stamp)] = value
        if len(self._values) > self.size:
            for key in sorted(self._values)[: len(self._values) - self.size]:
                del self._values[key]

    def get(self, key: int):
        return self._values.get(key)

    def keys_after(self, key: int) -> list[int]:
        return sorted(k for k in self._values if k > key)

    def items(self) -> list[tuple[int, object]]:
        return sorted(self._values.items())

    def restore(self, pairs) -> None:
        """Take back what `items` gave (agent/core/snapshot.py)."""
        self._values = dict(pairs)


class NeighbourTrack:
    """Relative position of one neighbour j, estimated by one inter-vessel filter."""

    def __init__(self, neighbour: str, params: RelativeEstimationParams, dt: float, history: int) -> None:
        self.neighbour = neighbour
        self.params = params
        self.dt = dt
        self.odometry = History(history)   # j's cumulative odometry by stamp
        self.ranges = History(history)     # ranges to j measured by i, by stamp
        self.estimator: RelativePositionEstimator | None = None
        self.epoch: int | None = None      # stamp key the filter state refers to
        self.last_range: float | None = None
        self.share: Share | None = None    # latest share received
        self.last_heard = -math.inf
        self.first_heard = math.inf
        self.updates = 0
        self.rejected = 0
        self.last_iterations = 0
        self.outcomes: list[tuple[float, float, UpdateOutcome]] = []   # (stamp s, range m, outcome) of the last advance

    def receive(self, share: Share, now: float) -> None:
        """Keep j's odometry and what it shares; shares may repeat or arrive out of order."""
        self.odometry.put(share.odometry.stamp, np.asarray(share.odometry.position, dtype=float))
        if self.share is None or share.odometry.stamp >= self.share.odometry.stamp:
            self.share = share
        self.last_heard = max(self.last_heard, share.odometry.stamp)
        self.first_heard = min(self.first_heard, share.odometry.stamp)

    def start(self, prior: NeighbourPrior, own: History) -> bool:
        """Start the filter from `prior` once both odometries are known at or after its stamp.

        When j's odometry at exactly the prior's stamp was lost, the prior is carried to the first stamp at
        which both are known, moving j by its shared velocity (a small, rare approximation). The prior is
        the initial estimate of (10)."""
        key = stamp_key(prior.stamp)
        candidates = [k for k in self.odometry.keys_after(key - 1) if own.get(k) is not None]
        if not candidates:
            return False
        start = candidates[0]
        position = np.asarray(prior.position, dtype=float)
        if start != key:
            seconds = (start - key) * 1e-6
            own_before = own.get(key)
            own_moved = own.get(start) - own_before if own_before is not None else np.zeros(2)
            other_moved = np.asarray(self.share.velocity, dtype=float) * seconds if self.share else np.zeros(2)
            position = position + own_moved - other_moved
        self.estimator = make_relative_estimator(self.params, position, prior.covariance, dt=self.dt)
        self.epoch = start
        self.last_range = None
        range_now = self.ranges.get(start)
        if range_now is not None:
            self.estimator.mark_range_epoch()
            self.last_range = range_now
        return True

    def advance(self, own: History) -> None:
        """Run the filter over every stamp after the epoch at which both odometries are known: the relative
        displacement (5), (11) predicts (15), and each range paired with the previous one updates, (12), (13), (14)."""
        self.outcomes = []
        if self.estimator is None or self.epoch is None:
            return
        for key in self.odometry.keys_after(self.epoch):
            own_now, own_then = own.get(key), own.get(self.epoch)
            other_now, other_then = self.odometry.get(key), self.odometry.get(self.epoch)
            if own_now is None or own_then is None or other_then is None:
                continue
            displacement = (own_now - own_then) - (other_now - other_then)
            if not self.estimator.predict(displacement, intervals=(key - self.epoch) * 1e-6 / self.dt):
                continue
            self.epoch = key
            range_now = self.ranges.get(key)
            if range_now is None:
                continue
            if self.last_range is None:
                self.estimator.mark_range_epoch()
                self.last_range = range_now
                continue
            outcome = self.estimator.update(self.last_range, range_now)
            self.outcomes.append((key * 1e-6, range_now, outcome))
            self.last_iterations = outcome.iterations
            if outcome.accepted:
                self.last_range = range_now
                self.updates += 1
            else:
                self.rejected += 1

    def estimate_at(self, own: History, now: float) -> np.ndarray | None:
        """p^_ij at `now`: the filter's estimate carried forward by i's odometry and j's shared velocity, (2),
        as in (15)."""
        if self.estimator is None or self.epoch is None:
            return None
        key = stamp_key(now)
        own_now, own_then = own.get(key), own.get(self.epoch)
        position = self.estimator.position
        if key == self.epoch or own_now is None or own_then is None:
            return position
        other_moved = np.zeros(2)
        if self.share is not None:
            other_moved = np.asarray(self.share.velocity, dtype=float) * ((key - self.epoch) * 1e-6)
        return position + (own_now - own_then) - other_moved
