"""Pseudo-linear maximum-correntropy Kalman filter, Sec. III-A steps 3-6, (16), (17), (18), (19), (20), (21).

Follows Chen et al., "Maximum correntropy Kalman filter" (Automatica 2017), the paper's [33], applied to the
scalar pseudo-linear measurement (12).
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field

from agent.config import PositiveFloat
from agent.core.estimators.base import UpdateOutcome, accepted_outcome
from agent.core.estimators.pseudolinear import joseph
from agent.core.estimators.pseudolinear_estimator import PseudoLinearEstimator
from agent.core.estimators.registry import EstimatorParams, register

# Lower bound on the prior kernel weights: a weight of 0 would make P-bar infinite. 1e-12 caps the prior
# inflation at 1e12, which already means "ignore the prior in that direction".
MIN_PRIOR_WEIGHT = 1e-12


class MckfParams(EstimatorParams):
    """Maximum-correntropy update, Sec. III-A steps 3-5."""

    name: Literal["mckf"] = "mckf"
    bandwidths: tuple[PositiveFloat, PositiveFloat, PositiveFloat] = Field(
        (9999.0, 9999.0, 0.8), description="Gaussian kernel bandwidths [sigma1, sigma2, sigma3] (Table I)"
    )
    tolerance: PositiveFloat = Field(1e-6, description="stopping threshold iota of (20) (Table I)")
    max_iterations: int = Field(10, ge=1, le=1000, description="L_max (Table I)")


def mckf_correct(
    px: float, py: float, p11: float, p12: float, p22: float,
    dx: float, dy: float, z: float, rz: float,
    sigma1: float, sigma2: float, sigma3: float, tolerance: float, max_iterations: int,
) -> tuple[float, float, float, float, float, int, float]:
    """One MCKF correction of the prior (p^-, P^-) with z = delta^T p + mu_z, Var mu_z = rz.

    (16) B_p B_p^T = P^- (Cholesky, lower), B_z = sqrt(R_z).
    (17) B = diag(B_p, B_z): block diagonal, so B^-1 is applied block by block and B is never formed.
    (18) D = B^-1 [p^-; z], W = B^-1 [I; delta^T], so w = D - W p^(s-1) is
         [B_p^-1 (p^- - p^(s-1)); (z - delta^T p^(s-1)) / B_z].
    (19) p^(s) = p^- + K-bar (z - delta^T p^-), with
         K-bar = P-bar delta (delta^T P-bar delta + R-bar)^-1, P-bar = B_p C_p^-1 B_p^T,
         R-bar = B_z C_z^-1 B_z^T, C = diag(G_sigma_l(w_l)), G_sigma(w) = exp(-w^2 / (2 sigma^2)).
    (20) stop when |p^(s) - p^(s-1)| / |p^(s-1)| <= iota, or after L_max iterations.
    (21) P^+ = (I - K-bar delta^T) P^- (I - K-bar delta^T)^T + K-bar R_z K-bar^T (Joseph form).

    R-bar = R_z / c3 is folded into the gain as K-bar = c3 P-bar delta / (c3 delta^T P-bar delta + R_z), which
    stays finite when the kernel weight c3 underflows to 0 (the measurement is then ignored).

    Returns (px+, py+, p11+, p12+, p22+, iterations, c3), c3 being the final measurement weight.
    """
    l11 = math.sqrt(p11)
    l21 = p12 / l11
    l22 = math.sqrt(p22 - l21 * l21)
    bz = math.sqrt(rz)
    innovation = z - (dx * px + dy * py)
    two_s1, two_s2, two_s3 = 2.0 * sigma1 * sigma1, 2.0 * sigma2 * sigma2, 2.0 * sigma3 * sigma3
    qx, qy = px, py  # p^(0) = p^-
    kx = ky = 0.0
    c3 = 1.0
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        w1 = (px - qx) / l11
        w2 = ((py - qy) - l21 * w1) / l22
        w3 = (z - dx * qx - dy * qy) / bz
        c1 = max(math.exp(-w1 * w1 / two_s1), MIN_PRIOR_WEIGHT)
        c2 = max(math.exp(-w2 * w2 / two_s2), MIN_PRIOR_WEIGHT)
        c3 = math.exp(-w3 * w3 / two_s3)
        b11 = p11 / c1
        b12 = p12 / c1
        b22 = l21 * l21 / c1 + l22 * l22 / c2
        hx = b11 * dx + b12 * dy
        hy = b12 * dx + b22 * dy
        denominator = c3 * (dx * hx + dy * hy) + rz
        kx = c3 * hx / denominator
        ky = c3 * hy / denominator
        nx = px + kx * innovation
        ny = py + ky * innovation
        change = math.hypot(nx - qx, ny - qy)
        previous = math.hypot(qx, qy)
        qx, qy = nx, ny
        # (20); the relative test needs a non-zero previous iterate, else fall back to an absolute one.
        if change <= tolerance * (previous if previous > 0.0 else 1.0):
            break
    q11, q12, q22 = joseph(p11, p12, p22, kx, ky, dx, dy, rz)
    return qx, qy, q11, q12, q22, iterations, c3


@register
class MCKF(PseudoLinearEstimator):
    """Maximum-correntropy Kalman filter on the pseudo-linear range measurement (12); the paper's method:
    prediction (15) in the base class, correction (16), (17), (18), (19), (20), (21) in `mckf_correct`."""

    name = "mckf"
    Params = MckfParams
    table_order = 5

    def _correct(self, z: float, dx: float, dy: float, rz: float) -> UpdateOutcome:
        p = self.params
        px, py, p11, p12, p22 = self._px, self._py, self._p11, self._p12, self._p22
        innovation = z - (dx * px + dy * py)
        innovation_variance = dx * (p11 * dx + p12 * dy) + dy * (p12 * dx + p22 * dy) + rz
        (self._px, self._py, self._p11, self._p12, self._p22, iterations, weight) = mckf_correct(
            px, py, p11, p12, p22, dx, dy, z, rz, *p.bandwidths, p.tolerance, p.max_iterations
        )
        return accepted_outcome(iterations, innovation, innovation_variance, weight)
