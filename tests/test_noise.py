"""Noise models of Sec. II-B: moments against closed forms, and seeded determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import TypeAdapter, ValidationError

from sim_bridge.noise import (
    GaussianMixtureNoise,
    GaussianNoise,
    IsotropicGaussianNoise,
    LogNormalNoise,
    RangeNoise,
)

N = 400_000


def within(sample_value: float, expected: float, standard_error: float) -> bool:
    return abs(sample_value - expected) < 5 * standard_error


def test_gaussian_mixture_moments_and_outlier_share():
    model = GaussianMixtureNoise(outlier_fraction=0.2, variance=0.4, outlier_variance=10.0)
    x = model.sample(np.random.default_rng(1), N)
    assert model.total_variance == pytest.approx(0.8 * 0.4 + 0.2 * 10.0)
    # Var of the sample variance: (E x^4 - var^2) / N, E x^4 = 3 ((1-eps) R^2 + eps Ro^2) for a mixture.
    fourth = 3 * (0.8 * 0.16 + 0.2 * 100.0)
    assert within(x.var(), 2.32, math.sqrt((fourth - 2.32**2) / N))
    assert within(x.mean(), 0.0, math.sqrt(2.32 / N))
    beyond = np.mean(np.abs(x) > 4 * math.sqrt(0.4))  # nominal part almost never reaches 4 sigma
    p_outlier_beyond = 0.2 * math.erfc(4 * math.sqrt(0.4) / math.sqrt(2 * 10.0))
    assert within(beyond, p_outlier_beyond, math.sqrt(p_outlier_beyond / N))


def test_lognormal_as_written_has_the_predicted_bias():
    model = LogNormalNoise(log_variance=0.7, shift=0.75)
    assert model.mean == pytest.approx(math.exp(0.35) - 0.75)  # 0.669 m, the bias (8) puts on ranges
    assert model.mean == pytest.approx(0.669, abs=1e-3)
    x = model.sample(np.random.default_rng(2), N)
    assert within(x.mean(), model.mean, math.sqrt(model.total_variance / N))
    assert np.all(x > -0.75)  # mu + r_s = exp(.) > 0
    assert within(np.log(x + 0.75).var(), 0.7, 0.7 * math.sqrt(2 / N))


def test_isotropic_gaussian_shape_and_covariance():
    model = IsotropicGaussianNoise(variance=1e-4)
    x = model.sample(np.random.default_rng(3), (1000, 200))
    assert x.shape == (1000, 200, 2)
    cov = np.cov(x.reshape(-1, 2).T)
    np.testing.assert_allclose(cov, 1e-4 * np.eye(2), atol=5 * 1e-4 * math.sqrt(2 / 200_000))


@pytest.mark.parametrize("model", [
    GaussianNoise(variance=0.3),
    GaussianMixtureNoise(outlier_fraction=0.1, variance=0.2, outlier_variance=10),
    LogNormalNoise(log_variance=0.5, shift=0.5),
    IsotropicGaussianNoise(variance=1.0),
])
def test_same_seed_same_samples_other_seed_other_samples(model):
    a = model.sample(np.random.default_rng(42), 50)
    b = model.sample(np.random.default_rng(42), 50)
    c = model.sample(np.random.default_rng(43), 50)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_noise_specs_are_tagged_and_validated():
    adapter = TypeAdapter(RangeNoise)
    model = adapter.validate_python({"kind": "lognormal", "log_variance": 0.2, "shift": 0.2})
    assert isinstance(model, LogNormalNoise)
    with pytest.raises(ValidationError):
        adapter.validate_python({"kind": "gmm", "outlier_fraction": 1.5, "variance": 1, "outlier_variance": 1})
    with pytest.raises(ValidationError):
        adapter.validate_python({"kind": "gaussian", "variance": 1, "colour": "red"})
