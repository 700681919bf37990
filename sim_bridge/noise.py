"""The world's sensor noise beside the range noise, and what a harness tells the filters of the range noise.

The range noise (7), (8), a calibrated mixture and the plain Gaussian are one family, `RangeNoise`
(agent/core/range_noise.py), which the filters share. Here:
- `IsotropicGaussianNoise`: N(0, R I_2); the bearing noise (9) and the displacement noise (5).
- `FilterNoise`, a harness's one statement of which range noise its filters assume: the world's ("world":
  R_z's range variance is its variance, the raw-range estimator's density its mixture and, for the
  log-normal (8), its exact density in tracking) or the agent parameters' own ("configured").
- `assumed_relative`: the relative-estimation parameters of filters that assume a given range noise.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from agent.config import NonNegativeFloat, StrictModel, updated
from agent.core.params import RelativeEstimationParams
from agent.core.range_noise import LogNormalNoise, RangeNoise, Shape, as_shape

FilterNoise = Literal["world", "configured"]
FILTER_NOISE_DESCRIPTION = ("'world': the filters assume the world's range noise (R_z, raw_range's density); "
                            "'configured': agent.relative's")


class IsotropicGaussianNoise(StrictModel):
    """2-D noise N(0, variance * I_2): bearing noise (9) and displacement noise (5)."""

    kind: Literal["isotropic_gaussian"] = "isotropic_gaussian"
    variance: NonNegativeFloat

    def sample(self, rng: np.random.Generator, shape: Shape = ()) -> np.ndarray:
        return rng.normal(0.0, math.sqrt(self.variance), size=as_shape(shape) + (2,))


def assumed_relative(relative: RelativeEstimationParams, noise: RangeNoise, variance_scale: float = 1.0,
                     estimator: str | None = None) -> RelativeEstimationParams:
    """`relative` for filters that assume `noise`: R_z's range variance its total variance (x variance_scale)
    and, if `estimator` (default: the configured one) is raw_range, raw_range's density: the noise's mixture
    for the batch fix and, for the log-normal (8), its exact density for tracking. Another estimator keeps
    its parameters."""
    params = updated(relative, range_variance=noise.total_variance * variance_scale)
    if (estimator or params.estimator.name) != "raw_range":
        return params
    exact = noise if isinstance(noise, LogNormalNoise) else None
    return params.selecting(updated(params.params_of("raw_range"), noise_components=noise.mixture(),
                                    tracking_lognormal=exact))
