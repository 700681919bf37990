"""Recursive least squares on the pseudo-linear measurement (12), with exponential forgetting.

The least-squares relative localisation of Nguyen et al. (IEEE T-RO vol. 36 no. 2, 2020, the paper's [26]):
the relative position is carried forward by the measured displacement (15) and corrected by exponentially
weighted RLS on z = delta^T p. Unlike the Kalman filters it knows nothing of the noise level: every equation
has unit weight, and the forgetting factor lambda discounts old equations. Its matrix P is the inverse of the
weighted information (not a covariance in m^2); it starts from the same P_ij,0 as the Kalman filters.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from agent.core.estimators.base import UpdateOutcome
from agent.core.estimators.pseudolinear_estimator import PseudoLinearEstimator
from agent.core.estimators.registry import EstimatorParams, register


class RlsParams(EstimatorParams):
    name: Literal["rls"] = "rls"
    forgetting_factor: float = Field(0.99, gt=0, le=1, description="lambda of exponentially weighted RLS")


def rls_correct(
    px: float, py: float, p11: float, p12: float, p22: float,
    dx: float, dy: float, z: float, forgetting: float, weight: float = 1.0,
) -> tuple[float, float, float, float, float, float, float]:
    """One weighted RLS step with forgetting factor lambda and equation weight w:

        K = w P phi / (lambda + w phi^T P phi),  p+ = p + K (z - phi^T p),  P+ = (P - K phi^T P) / lambda.

    Returns (px+, py+, p11+, p12+, p22+, innovation, phi^T P phi + 1).
    """
    hx = p11 * dx + p12 * dy
    hy = p12 * dx + p22 * dy
    spread = dx * hx + dy * hy
    denominator = forgetting + weight * spread
    kx, ky = weight * hx / denominator, weight * hy / denominator
    innovation = z - (dx * px + dy * py)
    return (
        px + kx * innovation,
        py + ky * innovation,
        (p11 - kx * hx) / forgetting,
        (p12 - kx * hy) / forgetting,
        (p22 - ky * hy) / forgetting,
        innovation,
        spread + 1.0,
    )


@register
class RLS(PseudoLinearEstimator):
    """Exponentially weighted recursive least squares (Nguyen et al. 2020)."""

    name = "rls"
    Params = RlsParams
    table_order = 1

    def _inflate(self, variance: float) -> None:
        """RLS has no process-noise model: its P only changes through forgetting (the state still moves by
        (15), the covariance step of (15) is left out)."""

    def _correct(self, z: float, dx: float, dy: float, rz: float) -> UpdateOutcome:
        if dx == 0.0 and dy == 0.0:
            # No excitation: the equation carries no information, and forgetting would only wind P up.
            return UpdateOutcome(accepted=True, innovation=z, innovation_variance=1.0)
        (self._px, self._py, self._p11, self._p12, self._p22, innovation, s) = rls_correct(
            self._px, self._py, self._p11, self._p12, self._p22, dx, dy, z,
            self.params.forgetting_factor,
        )
        return UpdateOutcome(accepted=True, iterations=1, innovation=innovation, innovation_variance=s)
