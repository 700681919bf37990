"""Range noise, one family: the world samples it, the filters assume it, the lab compares with it.

- `GaussianNoise`: N(0, R), for tests and baselines ((7) with eps = 0).
- `GaussianMixtureNoise`, (7): (1 - eps) N(0, R) + eps N(0, R_outlier).
- `MixtureNoise`: sum_k w_k N(m_k, v_k), what a calibration writes (`usv-lab fit-noise`, configs/uwb/) and the
  raw-range estimator's density (raw_range's `noise_components` are its components).
- `LogNormalNoise`, (8): ln(mu + r_s) ~ N(0, R), as written, so with mean exp(R / 2) - r_s.

Each is a frozen pydantic model with a `kind` tag (YAML), its `mean` and `total_variance`,
`sample(rng, shape)` from a caller's seeded Generator, and `mixture()`: the Gaussian mixture the raw-range estimator assumes
for it (exact for the Gaussian kinds; for the log-normal an EM fit, agent/core/mixture_fit.py, to 50,000 of
its samples drawn with seed 0: the same fit every time).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import Field, model_validator

from agent.config import NonNegativeFloat, PositiveFloat, StrictModel
from agent.core.mixture_fit import em_mixture

Shape = int | tuple[int, ...]
Components = tuple[tuple[float, float, float], ...]   # (weight, mean m, variance m^2) per component


def as_shape(shape: Shape) -> tuple[int, ...]:
    return (shape,) if isinstance(shape, int) else tuple(shape)


class GaussianNoise(StrictModel):
    """Zero-mean Gaussian range noise N(0, variance), for tests and baselines ((7) with eps = 0)."""

    kind: Literal["gaussian"] = "gaussian"
    variance: NonNegativeFloat

    @property
    def mean(self) -> float:
        return 0.0

    @property
    def total_variance(self) -> float:
        return self.variance

    def sample(self, rng: np.random.Generator, shape: Shape = ()) -> np.ndarray:
        return rng.normal(0.0, math.sqrt(self.variance), size=as_shape(shape))

    def mixture(self) -> Components:
        """One component, its variance floored at 1e-8 (a density needs one)."""
        return ((1.0, 0.0, max(self.variance, 1e-8)),)


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
        shape = as_shape(shape)
        # Draw the component first, then both normals, so the stream layout does not depend on the outcome.
        is_outlier = rng.random(shape) < self.outlier_fraction
        standard = rng.standard_normal(shape)
        scale = np.where(is_outlier, math.sqrt(self.outlier_variance), math.sqrt(self.variance))
        return standard * scale

    def mixture(self) -> Components:
        eps = self.outlier_fraction
        return ((1.0 - eps, 0.0, self.variance), (eps, 0.0, self.outlier_variance))


class MixtureNoise(StrictModel):
    """sum_k w_k N(m_k, v_k), weights normalised: a calibrated sensor's range noise."""

    kind: Literal["mixture"] = "mixture"
    components: tuple[tuple[PositiveFloat, float, PositiveFloat], ...] = Field(
        min_length=1, max_length=8, description="(weight, mean m, variance m^2) per component")

    @model_validator(mode="after")
    def _finite(self) -> MixtureNoise:
        if not all(math.isfinite(value) for component in self.components for value in component):
            raise ValueError("every weight, mean and variance must be finite")
        return self

    @property
    def _normalised(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        w, m, v = (np.array(column, dtype=float) for column in zip(*self.components))
        return w / w.sum(), m, v

    @property
    def mean(self) -> float:
        w, m, _ = self._normalised
        return float(w @ m)

    @property
    def total_variance(self) -> float:
        w, m, v = self._normalised
        return float(w @ (v + m * m) - (w @ m) ** 2)

    def sample(self, rng: np.random.Generator, shape: Shape = ()) -> np.ndarray:
        shape = as_shape(shape)
        w, m, v = self._normalised
        # As the mixture (7): the components first, then the normals, whatever the components drawn.
        component = np.minimum(np.searchsorted(np.cumsum(w), rng.random(shape), side="right"), len(w) - 1)
        return m[component] + np.sqrt(v[component]) * rng.standard_normal(shape)

    def mixture(self) -> Components:
        return tuple((float(w), float(m), float(v)) for w, m, v in self.components)


class LogNormalNoise(StrictModel):
    """Range noise (8): ln(mu + r_s) ~ N(0, R), implemented as written (it has a non-zero mean)."""

    kind: Literal["lognormal"] = "lognormal"
    log_variance: PositiveFloat = Field(description="R, variance of ln(mu + r_s)")
    shift: NonNegativeFloat = Field(description="r_s (m): the noise is above -r_s")

    @property
    def mean(self) -> float:
        """E[mu] = exp(R / 2) - r_s: the bias this model puts on every range."""
        return math.exp(self.log_variance / 2) - self.shift

    @property
    def total_variance(self) -> float:
        """Var[mu] = (exp(R) - 1) exp(R), the variance of a log-normal with log-variance R."""
        return (math.exp(self.log_variance) - 1) * math.exp(self.log_variance)

    def sample(self, rng: np.random.Generator, shape: Shape = ()) -> np.ndarray:
        return np.exp(rng.normal(0.0, math.sqrt(self.log_variance), size=as_shape(shape))) - self.shift

    def mixture(self) -> Components:
        """A 6-component mixture fitted by EM to 50,000 samples (seed 0): the same fit every time."""
        return _fitted_mixture(self.log_variance, self.shift)


RangeNoise = Annotated[
    Union[GaussianNoise, GaussianMixtureNoise, MixtureNoise, LogNormalNoise], Field(discriminator="kind")
]


@lru_cache(maxsize=16)
def _fitted_mixture(log_variance: float, shift: float, components: int = 6, samples: int = 50_000,
                    iterations: int = 200) -> Components:
    noise = LogNormalNoise(log_variance=log_variance, shift=shift)
    x = np.sort(noise.sample(np.random.default_rng(0), samples))
    weight, mean, variance = em_mixture(
        x, np.full(len(x), 1.0 / len(x)), np.full(components, 1.0 / components),
        np.quantile(x, (np.arange(components) + 0.5) / components), np.full(components, x.var() / components),
        iterations, 1e-4)
    return tuple((float(w), float(m), float(v)) for w, m, v in zip(weight, mean, variance))
