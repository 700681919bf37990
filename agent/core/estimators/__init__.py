"""Relative position estimators between vessels (Sec. III-A) and the target tracker (Sec. III-B)."""

from __future__ import annotations

import numpy as np

from agent.core.estimators.akf import AKF
from agent.core.estimators.base import Diagnostics, RelativePositionEstimator, UpdateOutcome
from agent.core.estimators.huber_rls import HuberRLS
from agent.core.estimators.kf import KF
from agent.core.estimators.mckf import MCKF
from agent.core.estimators.plkf import PLKF, BearingOutcome
from agent.core.estimators.raw_range import RawRange
from agent.core.estimators.rls import RLS
from agent.core.params import RelativeEstimationParams

ESTIMATORS: dict[str, type[RelativePositionEstimator]] = {
    cls.name: cls for cls in (RLS, HuberRLS, KF, AKF, MCKF, RawRange)
}


def make_relative_estimator(
    params: RelativeEstimationParams,
    position: np.ndarray | tuple[float, float],
    covariance: np.ndarray | None = None,
    dt: float = 0.1,
    name: str | None = None,
) -> RelativePositionEstimator:
    """The estimator named by `name` (default: params.estimator), started at `position`."""
    return ESTIMATORS[name or params.estimator](params, position, covariance, dt)


__all__ = [
    "AKF",
    "ESTIMATORS",
    "KF",
    "MCKF",
    "PLKF",
    "RLS",
    "BearingOutcome",
    "Diagnostics",
    "HuberRLS",
    "RawRange",
    "RelativePositionEstimator",
    "UpdateOutcome",
    "make_relative_estimator",
]
