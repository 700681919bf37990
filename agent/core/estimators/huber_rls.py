"""RLS with Huber-weighted residuals on (12): the robust least-squares baseline (the paper's [43] uses
Huber loss).

Each equation gets the Huber weight w = min(1, c s / |e|) of its prior residual e, where s is a robust
scale of recent residuals, 1.4826 * median |e| over the last `scale_window` updates (the MAD estimate of a
standard deviation, residuals being centred on zero). Weighted RLS with that w is one iteratively
reweighted least-squares step of the Huber M-estimator. Until five residuals are known the weight is 1.
"""

from __future__ import annotations

import statistics
from collections import deque
from typing import Literal

from pydantic import Field

from agent.config import PositiveFloat
from agent.core.estimators.base import UpdateOutcome
from agent.core.estimators.registry import EstimatorParams, register
from agent.core.estimators.rls import RLS, rls_correct

MAD_TO_SIGMA = 1.4826
MIN_RESIDUALS_FOR_SCALE = 5


class HuberRlsParams(EstimatorParams):
    name: Literal["huber_rls"] = "huber_rls"
    forgetting_factor: float = Field(0.99, gt=0, le=1, description="lambda of exponentially weighted RLS")
    threshold: PositiveFloat = Field(1.345, description="Huber constant c, in robust standard deviations")
    scale_window: int = Field(50, ge=5, le=10_000, description="residuals kept for the MAD scale estimate")


def huber_weight(residual: float, scale: float, threshold: float) -> float:
    """w(e) = 1 for |e| <= c s, else c s / |e|: the Huber loss's IRLS weight."""
    bound = threshold * scale
    magnitude = abs(residual)
    return 1.0 if magnitude <= bound else bound / magnitude


@register
class HuberRLS(RLS):
    """RLS whose every equation is down-weighted by the Huber weight of its residual."""

    name = "huber_rls"
    Params = HuberRlsParams
    table_order = 2

    def _reset_extra(self) -> None:
        self._residuals: deque[float] = deque(maxlen=self.params.scale_window)

    def _export_extra(self) -> dict:
        return {"residuals": list(self._residuals)}

    def _restore_extra(self, extra: dict) -> None:
        self._residuals.extend(float(r) for r in extra["residuals"])

    def _correct(self, z: float, dx: float, dy: float, rz: float) -> UpdateOutcome:
        if dx == 0.0 and dy == 0.0:
            return UpdateOutcome(accepted=True, innovation=z, innovation_variance=1.0)
        residual = z - (dx * self._px + dy * self._py)
        weight = 1.0
        if len(self._residuals) >= MIN_RESIDUALS_FOR_SCALE:
            scale = MAD_TO_SIGMA * statistics.median(abs(e) for e in self._residuals)
            if scale > 0.0:
                weight = huber_weight(residual, scale, self.params.threshold)
        self._residuals.append(residual)
        (self._px, self._py, self._p11, self._p12, self._p22, innovation, s) = rls_correct(
            self._px, self._py, self._p11, self._p12, self._p22, dx, dy, z,
            self.params.forgetting_factor, weight,
        )
        return UpdateOutcome(accepted=True, iterations=1, innovation=innovation, innovation_variance=s,
                             weight=weight)
