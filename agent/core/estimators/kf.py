"""Kalman filter on the pseudo-linear range measurement (12): the plain, non-robust baseline."""

from __future__ import annotations

from typing import Literal

from agent.core.estimators.base import UpdateOutcome
from agent.core.estimators.pseudolinear import gain, joseph
from agent.core.estimators.pseudolinear_estimator import PseudoLinearEstimator
from agent.core.estimators.registry import EstimatorParams, register


class KfParams(EstimatorParams):
    """The KF has no parameters of its own: R_z (14) from relative.range_variance."""

    name: Literal["kf"] = "kf"


def kf_correct(
    px: float, py: float, p11: float, p12: float, p22: float, dx: float, dy: float, z: float, r: float
) -> tuple[float, float, float, float, float, float, float]:
    """Standard Kalman correction for (12), z = delta^T p + mu, Var mu = r, with the Joseph-form covariance
    of (21): the MCKF's (19) and (21) with every kernel weight 1.

    Returns (px+, py+, p11+, p12+, p22+, innovation, innovation variance).
    """
    kx, ky, s = gain(p11, p12, p22, dx, dy, r)
    innovation = z - (dx * px + dy * py)
    q11, q12, q22 = joseph(p11, p12, p22, kx, ky, dx, dy, r)
    return px + kx * innovation, py + ky * innovation, q11, q12, q22, innovation, s


@register
class KF(PseudoLinearEstimator):
    """Kalman filter on (12) with the same R_z (14) as the MCKF; prediction (15) in the base class."""

    name = "kf"
    Params = KfParams
    table_order = 3

    def _correct(self, z: float, dx: float, dy: float, rz: float) -> UpdateOutcome:
        (self._px, self._py, self._p11, self._p12, self._p22, innovation, s) = kf_correct(
            self._px, self._py, self._p11, self._p12, self._p22, dx, dy, z, rz
        )
        return UpdateOutcome(accepted=True, iterations=1, innovation=innovation, innovation_variance=s)
