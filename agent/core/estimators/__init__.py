"""Relative position estimators between vessels (Sec. III-A); the target tracker (Sec. III-B) is plkf.py.

Every module of this package that defines an estimator registers it (registry.py); `estimator_names()` lists
them and `make_relative_estimator` builds one by name.
"""

from __future__ import annotations

import numpy as np

from agent.core.estimators.akf import AKF
from agent.core.estimators.base import Diagnostics, RelativePositionEstimator, UpdateOutcome
from agent.core.estimators.huber_rls import HuberRLS
from agent.core.estimators.kf import KF
from agent.core.estimators.mckf import MCKF
from agent.core.estimators.raw_range import RawRange
from agent.core.estimators.registry import (
    EstimatorParams,
    RelativeEstimationParams,
    estimator_class,
    estimator_names,
    register,
)
from agent.core.estimators.rls import RLS


def make_relative_estimator(
    params: RelativeEstimationParams,
    position: np.ndarray | tuple[float, float],
    covariance: np.ndarray | None = None,
    dt: float = 0.1,
    name: str | None = None,
) -> RelativePositionEstimator:
    """The estimator named by `name` (default: the configured one, params.estimator), started at `position`;
    it takes its own parameters from `params` if they are configured there, else its defaults."""
    return estimator_class(name or params.estimator.name)(params, position, covariance, dt)


__all__ = [
    "AKF",
    "KF",
    "MCKF",
    "RLS",
    "Diagnostics",
    "EstimatorParams",
    "HuberRLS",
    "RawRange",
    "RelativeEstimationParams",
    "RelativePositionEstimator",
    "UpdateOutcome",
    "estimator_class",
    "estimator_names",
    "make_relative_estimator",
    "register",
]
