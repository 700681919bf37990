"""The pseudo-linear update the paper's five estimators share, Sec. III-A (12), (13), (14).

`update(range_prev, range_now)` forms z of (13) from the range pair and the displacement accumulated since
`range_prev`'s epoch, and its noise variance R_z from (14), at the predicted ranges (the paper's choice) or
the measured ones (`relative.noise_ranges`); the subclass's `_correct` applies the measurement model (12),
z = delta^T p + mu_z, Var mu_z = R_z, to the state.
"""

from __future__ import annotations

import math
from abc import abstractmethod

from agent.core.estimators.base import REJECTED_RANGE, RelativePositionEstimator, UpdateOutcome, _as_range
from agent.core.estimators.pseudolinear import (
    equivalent_noise_variance,
    pseudo_measurement,
    range_pair_noise_variance,
)


class PseudoLinearEstimator(RelativePositionEstimator):
    """An estimator of p_ij corrected by the pseudo-linear measurement (12): RLS, Huber-RLS, KF, AKF, MCKF."""

    def update(self, range_prev: float, range_now: float) -> UpdateOutcome:
        """Correct with the range pair (r~_{k-1}, r~_k) and the displacement accumulated since r~_{k-1}:
        z of (13), its noise variance R_z from (14), then `_correct` on the measurement model (12)."""
        relative = self.relative
        limit = relative.max_range
        range_prev, range_now = _as_range(range_prev, limit), _as_range(range_now, limit)
        if math.isnan(range_prev) or math.isnan(range_now):
            self._diag.rejected += 1
            return self._record(UpdateOutcome(accepted=False, reason=REJECTED_RANGE))
        dx, dy = self._pair_dx, self._pair_dy
        z = pseudo_measurement(range_prev, range_now, dx, dy)
        displacement_variance = 2.0 * relative.displacement_variance * self._pair_steps
        if relative.noise_ranges == "measured":
            rz = range_pair_noise_variance(range_now, range_prev, relative.range_variance,
                                           displacement_variance)
        else:
            rz = equivalent_noise_variance(self._px, self._py, dx, dy, relative.range_variance,
                                           displacement_variance)
        saved = (self._px, self._py, self._p11, self._p12, self._p22)
        outcome = self._correct(z, dx, dy, rz)
        return self._settle(saved, outcome)

    @abstractmethod
    def _correct(self, z: float, dx: float, dy: float, rz: float) -> UpdateOutcome:
        """Apply the measurement (12), z = (dx, dy)^T p + mu_z, Var mu_z = rz, to the state in place."""
