"""Noise models of Sec. II-B: moments against closed forms, and seeded determinism."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pydantic import TypeAdapter, ValidationError

from agent.config import load_yaml, updated
from agent.core.params import AgentParams
from agent.core.range_noise import (
    GaussianMixtureNoise,
    GaussianNoise,
    LogNormalNoise,
    MixtureNoise,
    RangeNoise,
)
from agent.core.records import Command
from lab.experiments.comparison import ComparisonConfig, filter_relative
from sim_bridge.noise import IsotropicGaussianNoise, assumed_relative
from sim_bridge.scenario import select_scenario
from sim_bridge.world import World, WorldConfig

ROOT = Path(__file__).resolve().parents[1]

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


# ----- one RangeNoise family: a calibration's mixture, what the filters are told, each harness's one word
def test_a_calibrated_mixture_samples_its_closed_form_moments():
    # 0.5 N(-1, 0.04) + 1.5 N(2, 0.09) with weights given unnormalised: shares 1/4, 3/4.
    model = MixtureNoise(components=((0.5, -1.0, 0.04), (1.5, 2.0, 0.09)))
    mean = 0.25 * -1.0 + 0.75 * 2.0                                         # 1.25
    variance = 0.25 * (0.04 + 1.0) + 0.75 * (0.09 + 4.0) - mean ** 2        # 1.7125
    assert model.mean == pytest.approx(mean, abs=1e-15)
    assert model.total_variance == pytest.approx(variance, abs=1e-15)
    x = model.sample(np.random.default_rng(5), N)
    assert within(x.mean(), mean, math.sqrt(variance / N))
    assert within(np.mean(x < 0.5), 0.25, math.sqrt(0.25 * 0.75 / N))      # the components lie apart at 0.5
    assert model.sample(np.random.default_rng(5), (3, 4)).shape == (3, 4)
    with pytest.raises(ValidationError):
        MixtureNoise(components=((1.0, math.inf, 1.0),))
    with pytest.raises(ValidationError):
        MixtureNoise(components=())


def test_each_kind_gives_the_mixture_the_raw_range_estimator_assumes():
    assert GaussianNoise(variance=0.3).mixture() == ((1.0, 0.0, 0.3),)
    assert GaussianNoise(variance=0.0).mixture() == ((1.0, 0.0, 1e-8),)
    gmm = GaussianMixtureNoise(outlier_fraction=0.2, variance=0.4, outlier_variance=10.0)
    assert gmm.mixture() == ((0.8, 0.0, 0.4), (0.2, 0.0, 10.0))
    assert gmm.mixture() == AgentParams().relative.estimator.noise_components   # the default is Table II's
    calibration = load_yaml(AgentParams, ROOT / "configs" / "uwb" / "murp.yaml")
    calibrated = calibration.relative.estimator.noise_components
    assert MixtureNoise(components=calibrated).mixture() == calibrated
    lognormal = LogNormalNoise(log_variance=0.7, shift=0.75)
    fitted = lognormal.mixture()
    assert len(fitted) == 6 and fitted == LogNormalNoise(log_variance=0.7, shift=0.75).mixture()
    # EM keeps the mean of the samples it was fitted to: the fit's mean is the model's, to sampling error.
    fit = MixtureNoise(components=fitted)
    assert within(fit.mean, lognormal.mean, math.sqrt(lognormal.total_variance / 50_000))


def test_the_world_samples_a_calibrated_sensors_noise():
    config = WorldConfig.model_validate({
        "vessels": [{"id": "1", "position": [0.0, 0.0]}, {"id": "2", "position": [3.0, 4.0]}],
        "target": {"kind": "constant_velocity", "position": [20.0, 20.0], "velocity": [0.0, 0.0]},
        "range_noise": {"kind": "mixture", "components": [[1.0, 0.25, 0.0001]]}})
    world = World(config, np.random.default_rng(3))
    ranges = []
    for _ in range(100):
        ranges += [world.sense()[vessel].ranges[other] for vessel, other in (("1", "2"), ("2", "1"))]
        world.step({"1": Command(0.0, 0.0), "2": Command(0.0, 0.0)})
    # Two vessels 5 m apart that stay put: every range is 5 m + N(0.25, 0.01^2).
    assert np.mean(ranges) == pytest.approx(5.25, abs=5 * 0.01 / math.sqrt(200))
    assert np.std(ranges) == pytest.approx(0.01, rel=0.2)


@pytest.mark.parametrize("noise", [
    GaussianMixtureNoise(outlier_fraction=0.1, variance=0.2, outlier_variance=10.0),
    LogNormalNoise(log_variance=0.5, shift=0.5),
    MixtureNoise(components=((0.9, 0.1, 0.01), (0.1, -0.3, 1.0))),
])
def test_filters_that_assume_a_noise_are_told_its_variance_and_density(noise):
    relative = AgentParams().relative
    assumed = assumed_relative(relative, noise, variance_scale=2.0)
    assert assumed.range_variance == 2.0 * noise.total_variance
    assert assumed.estimator.name == "raw_range" and assumed.estimator.noise_components == noise.mixture()
    assert assumed.estimator.tracking_lognormal == (noise if isinstance(noise, LogNormalNoise) else None)
    assert assumed_relative(relative, noise, estimator="kf").estimator == relative.estimator
    # Another configured estimator keeps its own parameters; asked for raw_range, its density is raw_range's.
    mckf = updated(relative, estimator={"name": "mckf", "max_iterations": 3})
    assert assumed_relative(mckf, noise).estimator == mckf.estimator
    assert assumed_relative(mckf, noise, estimator="raw_range").estimator.noise_components == noise.mixture()


def test_each_harness_says_once_whether_its_filters_assume_the_worlds_noise():
    _, base = select_scenario(ROOT / "configs" / "scenarios" / "table3_noise.yaml", "lognormal_0.5")
    relative = updated(base.agent.relative, estimator="raw_range")
    raw = updated(base, agent=updated(base.agent, relative=relative))
    world = raw.world.range_noise
    told = raw.agent_params().relative
    assert told.range_variance == world.total_variance and told.estimator.tracking_lognormal == world
    configured = updated(raw, filter_noise="configured").agent_params()
    assert configured == raw.agent
    # A scenario running the MCKF is told the variance; its own parameters are left as they are.
    assert base.agent.relative.estimator.name == "mckf"
    assert base.agent_params().relative.estimator == base.agent.relative.estimator
    comparison = ComparisonConfig(estimators=("kf", "raw_range"), variance_scale=3.0)
    gmm = comparison.noise_models["gmm"]
    assert filter_relative(gmm, comparison).range_variance == 3.0 * gmm.total_variance
    assert filter_relative(gmm, comparison, "raw_range").estimator.noise_components == gmm.mixture()
    assert filter_relative(gmm, comparison, "kf").estimator == comparison.agent.relative.estimator
    mine = updated(comparison, filter_noise="configured")
    assert filter_relative(gmm, mine) == updated(AgentParams().relative, range_variance=3.0 * 2.32)
    with pytest.raises(ValidationError):
        ComparisonConfig(filter_range_variance="total")   # the old words are gone, not silently ignored
