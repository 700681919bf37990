"""Adaptive Kalman filter: Sage-Husa estimation of the measurement noise, with a fading memory.

Variant: the Sage-Husa innovation-based estimator of the measurement-noise covariance (A. P. Sage and
G. W. Husa, "Adaptive filtering with unknown prior statistics", Joint Automatic Control Conference, 1969) in
its common fading-memory form, where the estimate at update k is the weighted mean

    R^_k = (1 - d_k) R^_{k-1} + d_k (e_k^2 - delta^T P^-_k delta),   d_k = (1 - b) / (1 - b^(k+1)),

e_k being the prior innovation and 0 < b < 1 the fading factor. Here R_z changes with the predicted range
(14), so what is estimated is the dimensionless scale alpha = R^ / R_z(model) on the modelled R_z; with a
constant range this is exactly the textbook estimator. The estimate is clamped to [min_scale, max_scale]
because the raw Sage-Husa estimate can go negative (the usual 'modified Sage-Husa' safeguard).
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from agent.config import PositiveFloat
from agent.core.estimators.base import UpdateOutcome
from agent.core.estimators.kf import kf_correct
from agent.core.estimators.pseudolinear_estimator import PseudoLinearEstimator
from agent.core.estimators.registry import EstimatorParams, register


class AkfParams(EstimatorParams):
    """Sage-Husa noise estimation with a fading memory."""

    name: Literal["akf"] = "akf"
    fading_factor: float = Field(0.98, gt=0, lt=1, description="b: weight of the past in the noise estimate")
    min_scale: PositiveFloat = Field(0.05, description="lower bound of the estimated noise scale")
    max_scale: PositiveFloat = Field(1e3, description="upper bound of the estimated noise scale")

    @model_validator(mode="after")
    def _ordered(self) -> AkfParams:
        if self.min_scale >= self.max_scale:
            raise ValueError("min_scale must be below max_scale")
        return self


def sage_husa_scale(previous: float, count: int, fading: float, innovation: float, prior_spread: float,
                    rz: float, lower: float, upper: float) -> float:
    """Next noise scale alpha_k after `count` previous updates (alpha_0 is the prior scale)."""
    d = (1.0 - fading) / (1.0 - fading ** (count + 1))
    raw = (innovation * innovation - prior_spread) / rz
    return min(max((1.0 - d) * previous + d * raw, lower), upper)


@register
class AKF(PseudoLinearEstimator):
    """Kalman filter on (12) whose measurement-noise level (the scale on R_z of (14)) is estimated online
    (Sage-Husa, fading memory); prediction (15) in the base class."""

    name = "akf"
    Params = AkfParams
    table_order = 4

    def _reset_extra(self) -> None:
        self._scale = 1.0
        self._count = 0

    def _export_extra(self) -> dict:
        return {"scale": self._scale, "count": self._count}

    def _restore_extra(self, extra: dict) -> None:
        self._scale, self._count = float(extra["scale"]), int(extra["count"])

    def _correct(self, z: float, dx: float, dy: float, rz: float) -> UpdateOutcome:
        p = self.params
        px, py, p11, p12, p22 = self._px, self._py, self._p11, self._p12, self._p22
        innovation = z - (dx * px + dy * py)
        prior_spread = dx * (p11 * dx + p12 * dy) + dy * (p12 * dx + p22 * dy)
        self._scale = sage_husa_scale(self._scale, self._count, p.fading_factor, innovation, prior_spread,
                                      rz, p.min_scale, p.max_scale)
        self._count += 1
        (self._px, self._py, self._p11, self._p12, self._p22, innovation, s) = kf_correct(
            px, py, p11, p12, p22, dx, dy, z, self._scale * rz
        )
        return UpdateOutcome(accepted=True, iterations=1, innovation=innovation, innovation_variance=s,
                             noise_scale=self._scale)
