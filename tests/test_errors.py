"""Monte Carlo results reduced as the runs arrive (lab/harness/errors.py): the same figures as numpy over every run's
curve held at once, in state whose size does not grow with the number of runs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_range_replay import circle_scenario

from agent.core.params import AgentParams
from lab.experiments.comparison import (
    LS_TIMES,
    WORST_RUN_FROM,
    ComparisonConfig,
    _stable_id,
    run_comparison,
    run_once,
)
from lab.experiments.replay import RangeLog, ReplayJob, noise_params, replay, replay_run
from lab.harness.errors import RunningMoments


def test_running_moments_equal_numpy_over_the_stacked_runs_leaving_nans_out():
    rng = np.random.default_rng(11)
    runs = rng.gamma(2.0, 0.5, size=(9, 3, 25))
    runs[rng.random(runs.shape) < 0.15] = np.nan
    runs[:, 1, :2] = np.nan                                  # elements no run has
    moments = RunningMoments((3, 25))
    for run in runs:
        moments.add(run)
    with np.errstate(invalid="ignore"), pytest.warns(RuntimeWarning):
        mean, std = np.nanmean(runs, axis=0), np.nanstd(runs, axis=0)
        rms, largest = np.sqrt(np.nanmean(runs ** 2, axis=0)), np.nanmax(runs, axis=0)
    np.testing.assert_array_equal(moments.count, np.sum(~np.isnan(runs), axis=0))
    np.testing.assert_allclose(moments.mean, mean, rtol=1e-12)
    np.testing.assert_allclose(moments.std, std, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(moments.rms, rms, rtol=1e-12)
    np.testing.assert_array_equal(moments.maximum, largest)
    assert np.isnan(moments.mean[1, :2]).all() and np.isnan(moments.rms[1, :2]).all()


def test_a_comparison_reduced_run_by_run_equals_its_runs_stacked():
    """The page's figures from the running reduction against the same runs' curves computed directly with
    `run_once` on the same child seeds, stacked and summarised with numpy."""
    config = ComparisonConfig(runs=4, duration=35.0, estimators=("kf", "mckf", "raw_range"))
    result = run_comparison(config, "gmm")
    root = np.random.SeedSequence([config.seed, _stable_id("gmm")])
    outputs = [run_once(config, config.noise_models["gmm"], child) for child in root.spawn(config.runs)]
    errors = np.stack([o[0] for o in outputs])                       # (runs, estimators, K+1)
    iterations = np.stack([o[1] for o in outputs])
    least_squares = np.stack([o[2] for o in outputs])
    nees = np.stack([o[3] for o in outputs])
    late = result.time >= WORST_RUN_FROM - 1e-9
    assert result.runs == 4 and late.sum() == 51
    for e, name in enumerate(config.estimators):
        np.testing.assert_allclose(result.rmse(name), np.sqrt(np.mean(errors[:, e] ** 2, axis=0)), rtol=1e-12)
        np.testing.assert_allclose(result.spread(name), np.std(errors[:, e], axis=0), rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(result.nees[name].mean, np.mean(nees[:, e], axis=0), rtol=1e-12)
        worst = np.sqrt(np.mean(errors[:, e][:, late] ** 2, axis=1)).max()
        assert result.worst_run_ratio(name) == pytest.approx(
            worst / math.sqrt(np.mean(result.bound[late] ** 2)), rel=1e-12)
    # 10 s and 30 s are inside the 35 s run, 60 s is not.
    np.testing.assert_allclose(result.least_squares.rms[:2], np.sqrt(np.mean(least_squares[:, :2] ** 2, axis=0)),
                               rtol=1e-12)
    assert LS_TIMES[2] > config.duration and math.isnan(result.least_squares.rms[2])
    iterated = iterations[iterations > 0]
    assert result.mean_iterations == pytest.approx(iterated.mean(), rel=1e-12)
    assert result.iteration_max == iterated.max()


def _state_bytes(result) -> int:
    groups = [result.moments, getattr(result, "nees", {})]
    return sum(m.nbytes for group in groups for m in group.values())


def test_what_a_campaign_holds_does_not_grow_with_its_runs():
    small = run_comparison(ComparisonConfig(runs=2, duration=3.0, estimators=("kf", "rls")), "lognormal")
    large = run_comparison(ComparisonConfig(runs=12, duration=3.0, estimators=("kf", "rls")), "lognormal")
    assert (small.runs, large.runs) == (2, 12)
    assert _state_bytes(small) == _state_bytes(large) > 0
    log = RangeLog("walk", *circle_scenario(seed=5, range_std=0.1, duration=6.0))
    assert _state_bytes(replay(log, AgentParams(), runs=1, names=("kf",))) == \
        _state_bytes(replay(log, AgentParams(), runs=7, names=("kf",)))


def test_a_replay_reduced_run_by_run_equals_its_runs_stacked():
    log = RangeLog("walk", *circle_scenario(seed=5, range_std=0.1, duration=15.0))
    params = AgentParams()
    result = replay(log, params, runs=4, seed=8)
    relative, raw_range, _ = noise_params(log, params, None, False)
    names = tuple(result.moments)
    runs = [replay_run(ReplayJob(log, relative, params.dt, names, child, raw_range))
            for child in np.random.SeedSequence(8).spawn(4)]
    errors = np.stack([r[0] for r in runs])
    rejected = np.stack([r[1] for r in runs])
    for e, name in enumerate(names):
        np.testing.assert_allclose(result.rmse(name), np.sqrt(np.mean(errors[:, e] ** 2, axis=0)), rtol=1e-12)
        np.testing.assert_allclose(result.spread(name), np.std(errors[:, e], axis=0), rtol=1e-9, atol=1e-15)
        assert result.largest_error(name) == errors[:, e].max()
        assert result.rejected_per_run(name) == pytest.approx(rejected[:, e].mean())
