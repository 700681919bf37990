"""The interface every inter-vessel relative position estimator offers, and the prediction they share.

For the pair (i, j), state p_ij = p_i - p_j in R^2, (10):
- `predict(displacement)` moves the state by the relative displacement delta~_ij of (13) over one odometry
  interval, (15), and accumulates it since the last range epoch;
- `update(range_prev, range_now)` corrects with a range pair (the subclass's measurement model);
  `update_between` with ranges between antennas off the hulls' centres (the raw-range filter's model);
- `position`, `covariance`, `moments`, `diagnostics` read; `reset`, `assimilate`, `mark_range_epoch`,
  `export_state` / `restore_state` (agent/core/snapshot.py) manage it.
Inputs are checked before they touch the state: a non-finite displacement, or a range that is non-finite,
negative or beyond `max_range`, is refused, counted, and leaves the state as it was.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass, field
from typing import ClassVar

import numpy as np

from agent.core.estimators.pseudolinear import is_positive_definite
from agent.core.estimators.registry import EstimatorParams, RelativeEstimationParams


@dataclass(frozen=True, slots=True)
class UpdateOutcome:
    """What one update did. `innovation` is z - delta^T p^-; `innovation_variance` is delta^T P^- delta + R_z
    (for RLS, with unit noise), so innovation^2 / innovation_variance is the normalised innovation squared."""

    accepted: bool
    reason: str = ""
    iterations: int = 0
    innovation: float = 0.0
    innovation_variance: float = 0.0
    weight: float = 1.0
    noise_scale: float = 1.0


# The slots' setters of UpdateOutcome's fields, in their order (`accepted_outcome`)
_OUTCOME_SLOTS = tuple(UpdateOutcome.__dict__[name].__set__ for name in UpdateOutcome.__slots__)


def accepted_outcome(iterations: int, innovation: float, innovation_variance: float, weight: float,
                     reason: str = "") -> UpdateOutcome:
    """`UpdateOutcome(accepted=True, reason=reason, iterations=..., innovation=..., innovation_variance=...,
    weight=..., noise_scale=1.0)`, the same object, built by setting its slots directly: the frozen
    dataclass's __init__ (object.__setattr__ per field, keywords) cost 2 us, once per range and pair."""
    outcome = object.__new__(UpdateOutcome)
    accepted_, reason_, iterations_, innovation_, variance_, weight_, scale_ = _OUTCOME_SLOTS
    accepted_(outcome, True)
    reason_(outcome, reason)
    iterations_(outcome, iterations)
    innovation_(outcome, innovation)
    variance_(outcome, innovation_variance)
    weight_(outcome, weight)
    scale_(outcome, 1.0)
    return outcome


REJECTED_RANGE = "range is not finite, is negative or exceeds max_range"
REJECTED_NUMERICS = "update produced a non-finite or indefinite state"


def _real(value: object) -> float:
    """The value as a float if it is a real number (not a string or a bool), else NaN."""
    if type(value) is float:        # the usual case, several times per pair update: no isinstance chain
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        return math.nan
    return float(value)


def _as_range(value: object, limit: float) -> float:
    """The value as a valid range in [0, limit], or NaN when it is not one."""
    r = _real(value)
    return r if 0.0 <= r <= limit else math.nan


@dataclass(slots=True)
class Diagnostics:
    predictions: int = 0
    updates: int = 0
    rejected: int = 0
    last: UpdateOutcome = field(default_factory=lambda: UpdateOutcome(accepted=False, reason="no update yet"))


class RelativePositionEstimator(ABC):
    """Base of every estimator of p_ij (10): the prediction (15) and the reading are shared, subclasses
    provide `update`. A subclass declares `name` and its own `Params` and is made selectable by `@register`
    (registry.py); `self.params` are its own parameters, `self.relative` those every estimator shares."""

    name: ClassVar[str] = ""
    Params: ClassVar[type[EstimatorParams]]
    table_order: ClassVar[float] = math.inf   # where it stands in lists and tables (the paper's Table II)

    def __init__(
        self,
        relative: RelativeEstimationParams,
        position: np.ndarray | tuple[float, float],
        covariance: np.ndarray | None = None,
        dt: float = 0.1,
    ) -> None:
        self.relative = relative
        self.params = relative.params_of(self.name)
        self.dt = dt
        self.reset(position, covariance)

    # ----- reading -----
    @property
    def position(self) -> np.ndarray:
        return np.array([self._px, self._py])

    @property
    def covariance(self) -> np.ndarray:
        return np.array([[self._p11, self._p12], [self._p12, self._p22]])

    def moments(self) -> tuple[float, float, float, float, float]:
        """(px, py, p11, p12, p22): `position` and `covariance` as plain floats, for callers that do their
        2-D algebra in floats (agent/core/cooperation.py) and need no arrays."""
        return self._px, self._py, self._p11, self._p12, self._p22

    @property
    def diagnostics(self) -> Diagnostics:
        return self._diag

    # ----- life cycle -----
    def reset(self, position: np.ndarray | tuple[float, float], covariance: np.ndarray | None = None) -> None:
        """Start again from `position` with `covariance` (default: initial_covariance * I)."""
        px, py = (float(v) for v in np.asarray(position, dtype=float).reshape(2))
        if covariance is None:
            p11 = p22 = self.relative.initial_covariance
            p12 = 0.0
        else:
            c = np.asarray(covariance, dtype=float).reshape(2, 2)
            p11, p12, p22 = float(c[0, 0]), 0.5 * float(c[0, 1] + c[1, 0]), float(c[1, 1])
        if not (math.isfinite(px) and math.isfinite(py) and is_positive_definite(p11, p12, p22)):
            raise ValueError("reset needs a finite position and a symmetric positive-definite covariance")
        self._px, self._py = px, py
        self._p11, self._p12, self._p22 = p11, p12, p22
        self._pair_dx = self._pair_dy = 0.0
        self._pair_steps = 0.0
        self._diag = Diagnostics()
        self._reset_extra()

    def assimilate(self, position: np.ndarray, covariance: np.ndarray) -> bool:
        """Replace the estimate by a fused one (e.g. with a neighbour's, by covariance intersection), keeping
        the range pairing and any adaptive state. Refused (False, counted) unless finite and SPD."""
        px, py = (float(v) for v in np.asarray(position, dtype=float).reshape(2))
        c = np.asarray(covariance, dtype=float).reshape(2, 2)
        p11, p12, p22 = float(c[0, 0]), 0.5 * float(c[0, 1] + c[1, 0]), float(c[1, 1])
        if not (math.isfinite(px) and math.isfinite(py) and is_positive_definite(p11, p12, p22)):
            self._diag.rejected += 1
            return False
        self._px, self._py, self._p11, self._p12, self._p22 = px, py, p11, p12, p22
        return True

    def mark_range_epoch(self) -> None:
        """Declare a range epoch without updating (the first range of a pair sequence)."""
        self._pair_dx = self._pair_dy = 0.0
        self._pair_steps = 0.0

    # ----- prediction -----
    def predict(self, displacement: np.ndarray | tuple[float, float], intervals: float = 1.0) -> bool:
        """Propagate by the measured relative displacement, (15):
        p^- = p^+ + delta~_ij, P^- = P^+ + R_delta_ij.

        `intervals` is the length of the odometry interval in sampling periods dt: the displacement noise
        R_delta_ij = R_delta_i + R_delta_j = 2 R_delta_i of (13) is per period and grows linearly with it
        (a random walk), which (15) with one period per step leaves implicit.
        """
        if (type(displacement) is tuple and len(displacement) == 2 and type(displacement[0]) is float
                and type(displacement[1]) is float):
            dx, dy = displacement       # already two floats (agent/core/neighbours.py): no conversion
        else:
            try:
                dx, dy = (float(v) for v in np.asarray(displacement, dtype=float).reshape(2))
            except (TypeError, ValueError):
                dx = dy = math.nan
        intervals = _real(intervals)
        if not (math.isfinite(dx) and math.isfinite(dy) and math.isfinite(intervals) and intervals >= 0):
            self._diag.rejected += 1
            return False
        self._px += dx
        self._py += dy
        self._pair_dx += dx
        self._pair_dy += dy
        self._pair_steps += intervals
        self._inflate(2.0 * self.relative.displacement_variance * intervals)
        self._diag.predictions += 1
        return True

    def _inflate(self, variance: float) -> None:
        """Add the displacement noise to the covariance; RLS overrides this (its P is not a covariance)."""
        self._p11 += variance
        self._p22 += variance

    # ----- correction -----
    @abstractmethod
    def update(self, range_prev: float, range_now: float) -> UpdateOutcome:
        """Correct with the range pair (r~_{k-1}, r~_k) and the displacement accumulated since r~_{k-1}
        (the range of the last accepted update, or of `mark_range_epoch`)."""

    def update_between(self, range_prev: float, range_now: float, offset_prev: tuple[float, float],
                       offset_now: tuple[float, float]) -> UpdateOutcome:
        """`update` with ranges measured between antennas: r~ = |p + delta| + noise, delta the antennas'
        offset at each range's time (agent/core/antenna.py). A filter whose model has no antennas (the paper's
        pseudo-linear five) ignores the offsets and corrects as `update` does."""
        return self.update(range_prev, range_now)

    def _settle(self, saved: tuple[float, ...], outcome: UpdateOutcome) -> UpdateOutcome:
        """After a correction: keep it if the state is finite and its covariance SPD, else put `saved` back
        and refuse the update; either way the update is counted and recorded."""
        if not (math.isfinite(self._px) and math.isfinite(self._py)
                and is_positive_definite(self._p11, self._p12, self._p22)):
            self._px, self._py, self._p11, self._p12, self._p22 = saved
            self._diag.rejected += 1
            return self._record(UpdateOutcome(accepted=False, reason=REJECTED_NUMERICS))
        self.mark_range_epoch()
        self._diag.updates += 1
        return self._record(outcome)

    def _record(self, outcome: UpdateOutcome) -> UpdateOutcome:
        self._diag.last = outcome
        return outcome

    def _reset_extra(self) -> None:
        """Subclasses with extra state (AKF, Huber-RLS, RawRange) clear it here."""

    # ----- saving and restoring (agent/core/snapshot.py) -----
    def export_state(self) -> dict:
        """Everything that changes between calls, as JSON-ready data."""
        diag = self._diag
        return {
            "name": self.name, "position": [self._px, self._py], "covariance": [self._p11, self._p12, self._p22],
            "pair": [self._pair_dx, self._pair_dy, self._pair_steps],
            "diagnostics": {"predictions": diag.predictions, "updates": diag.updates, "rejected": diag.rejected,
                            "last": asdict(diag.last)},
            "extra": self._export_extra(),
        }

    def restore_state(self, data: dict) -> None:
        """Take back what `export_state` gave; the extra state only from an estimator of the same kind."""
        self._px, self._py = (float(v) for v in data["position"])
        self._p11, self._p12, self._p22 = (float(v) for v in data["covariance"])
        self._pair_dx, self._pair_dy, self._pair_steps = (float(v) for v in data["pair"])
        diag = data["diagnostics"]
        self._diag = Diagnostics(diag["predictions"], diag["updates"], diag["rejected"], UpdateOutcome(**diag["last"]))
        self._reset_extra()
        if data["name"] == self.name:
            self._restore_extra(data["extra"])

    def _export_extra(self) -> dict:
        return {}

    def _restore_extra(self, extra: dict) -> None:
        """Subclasses with extra state take it back here."""
