"""Sensor noise models of the paper, Sec. II-B.

Each model is a small frozen pydantic object: it validates its parameters, can be written in YAML with a
`kind` tag, and draws samples with `sample(rng, shape)` from a caller's seeded `numpy.random.Generator`,
so that every random number in an experiment flows from one seed.

Range noise (scalar per measurement):
- `GaussianMixtureNoise`, (7): (1 - eps) N(0, R) + eps N(0, R_outlier).
- `LogNormalNoise`, (8): ln(mu + r_s) ~ N(0, R), i.e. mu = exp(N(0, R)) - r_s. As written in the paper this
  noise is not zero-mean: its mean is exp(R / 2) - r_s (0.669 m for R = 0.7, r_s = 0.75). `mean` reports it.
- `GaussianNoise`: plain N(0, R), for tests and baselines.

Vector noise (last axis of size 2):
- `IsotropicGaussianNoise`: N(0, R I_2); the bearing noise (9) and the displacement noise (5).
"""

from __future__ import annotations

import math
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import Field

from agent.config import NonNegativeFloat, PositiveFloat, StrictModel

Shape = int | tuple[int, ...]


def _as_shape(shape: Shape) -> tuple[int, ...]:
    return (shape,) if isinstance(shape, int) else tuple(shape)


class GaussianNoise(StrictModel):
    """Zero-mean Gaussian range noise N(0, variance), for tests and baselines (not one of the paper's models;
    (7) with eps = 0)."""

    kind: Literal["gaussian"] = "gaussian"
    variance: NonNegativeFloat

    @property
    def mean(self) -> float:
        return 0.0

    @property
    def total_variance(self) -> float:
        return self.variance

    def sample(self, rng: np.random.Generator, shape: Shape = ()) -> np.ndarray:
        return rng.normal(0.0, math.sqrt(self.variance), size=_as_shape(shape))


class GaussianMixtureNoise(StrictModel):
    """Range noise (7): (1 - eps) N(0, R) + eps N(0, R_outlier)."""

    kind: Literal["gmm"] = "gmm"
    outlier_fraction: float = Field(ge=0, le=1, description="eps")
    variance: PositiveFloat = Field(description="R, nominal variance")
    outlier_variance: PositiveFloat = Field(description="R_outlier, variance of the outlier component")

    @property
    def mean(self) -> float:
        return 0.0

    @property
    def total_variance(self) -> float:
        eps = self.outlier_fraction
        return (1 - eps) * self.variance + eps * self.outlier_variance

    def sample(self, rng: np.random.Generator, shape: Shape = ()) -> np.ndarray:
        shape = _as_shape(shape)
        # Draw the component first, then both normals, so the stream layout does not depend on the outcome.
        is_outlier = rng.random(shape) < self.outlier_fraction
        standard = rng.standard_normal(shape)
        scale = np.where(is_outlier, math.sqrt(self.outlier_variance), math.sqrt(self.variance))
        return standard * scale


class LogNormalNoise(StrictModel):
    """Range noise (8): ln(mu + r_s) ~ N(0, R), implemented as written (it has a non-zero mean)."""

    kind: Literal["lognormal"] = "lognormal"
    log_variance: PositiveFloat = Field(description="R_mu_r, variance of ln(mu + r_s)")
    shift: NonNegativeFloat = Field(description="r_s, shift parameter")

    @property
    def mean(self) -> float:
        """E[mu] = exp(R / 2) - r_s: the bias this model puts on every range."""
        return math.exp(self.log_variance / 2) - self.shift

    @property
    def total_variance(self) -> float:
        """Var[mu] = (exp(R) - 1) exp(R), the variance of a log-normal with log-variance R."""
        return (math.exp(self.log_variance) - 1) * math.exp(self.log_variance)

    def sample(self, rng: np.random.Generator, shape: Shape = ()) -> np.ndarray:
        return np.exp(rng.normal(0.0, math.sqrt(self.log_variance), size=_as_shape(shape))) - self.shift


class IsotropicGaussianNoise(StrictModel):
    """2-D noise N(0, variance * I_2): bearing noise (9) and displacement noise (5)."""

    kind: Literal["isotropic_gaussian"] = "isotropic_gaussian"
    variance: NonNegativeFloat

    def sample(self, rng: np.random.Generator, shape: Shape = ()) -> np.ndarray:
        return rng.normal(0.0, math.sqrt(self.variance), size=_as_shape(shape) + (2,))


RangeNoise = Annotated[
    Union[GaussianNoise, GaussianMixtureNoise, LogNormalNoise], Field(discriminator="kind")
]
