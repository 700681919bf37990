"""The lab's plant effects (lab/harness/plant_effects.py) against hand-worked values, and the agent's measures for the
boat as it is (docs/sea.md (What the agent does)): the lag-compensated heading loop against its closed form, the separation
guard's coasting distance, and the coping agent settling with 1 s lags over seeds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.config import updated
from agent.core.control.formation import lag_compensated_rate
from agent.core.command import control_command
from agent.core.control.separation import coasting_distance
from agent.core.odometry_noise import displacement_variance
from agent.core.params import ControlParams
from agent.core.records import Command
from lab.experiments.loop_margins import _frequencies, margins, plant
from lab.experiments.sea_agent import COPING, effect_scenario, measure
from lab.harness import runner
from lab.harness.plant_effects import PlantEffects, lag_step, with_effects, world_factory
from sim_bridge.world import World


def _world(**effects):
    scenario = effect_scenario(PlantEffects())
    world = World(scenario.world, np.random.default_rng(5))
    return with_effects(world, PlantEffects(**effects), np.random.default_rng(6))


def test_a_lag_step_response_is_one_minus_exp():
    # A unit step through tau = 1 s sampled at 0.1 s: x_k = 1 - exp(-k dt / tau), exactly.
    x = 0.0
    for k in range(1, 31):
        x = lag_step(x, 1.0, 0.1, 1.0, None, None)
        assert x == pytest.approx(1.0 - math.exp(-0.1 * k), abs=1e-12)


def test_rate_and_acceleration_limits_clip_the_response():
    assert lag_step(0.0, 5.0, 0.1, 0.0, 0.2, None) == 0.2  # the command clipped to the rate limit
    assert lag_step(0.0, 5.0, 0.1, 0.0, None, 1.0) == pytest.approx(0.1)  # 1 m/s^2 over 0.1 s
    assert lag_step(0.3, -5.0, 0.1, 0.0, 0.2, 1.0) == pytest.approx(0.2)  # down by at most 0.1


def test_the_world_moves_with_the_lagged_yaw_rate():
    world = _world(yaw_lag=1.0)
    start = world.truth().headings["1"]
    for _ in range(10):
        world.step({v: Command(0.0, 0.5) for v in world.live()})
    # The heading turns by dt sum_k r_k with r_k = 0.5 (1 - e^{-0.1 k}), k = 1..10.
    turned = 0.1 * sum(0.5 * (1.0 - math.exp(-0.1 * k)) for k in range(1, 11))
    assert world.truth().headings["1"] - start == pytest.approx(turned, abs=1e-12)


def test_a_compass_bias_rotates_the_odometry_and_the_bearing():
    bias = math.radians(2.0)
    plain = World(effect_scenario(PlantEffects()).world, np.random.default_rng(5))
    biased = _world(compass_biases=(bias, 0.0, 0.0, 0.0))
    for _ in range(20):
        commands = {v: Command(1.0, 0.1) for v in plain.live()}
        plain.step(commands)
        biased.step(commands)
    a, b = plain.sense()["1"], biased.sense()["1"]
    x, y = a.odometry.position
    # R(b) p: worked by hand from the unbiased reading.
    assert b.odometry.position[0] == pytest.approx(math.cos(bias) * x - math.sin(bias) * y, abs=1e-12)
    assert b.odometry.position[1] == pytest.approx(math.sin(bias) * x + math.cos(bias) * y, abs=1e-12)
    assert b.odometry.heading == pytest.approx(a.odometry.heading + bias, abs=1e-12)
    assert math.atan2(b.bearing[1], b.bearing[0]) - math.atan2(a.bearing[1], a.bearing[0]) == pytest.approx(
        bias, abs=1e-12
    )
    np.testing.assert_array_equal(plain.sense()["2"].odometry.position, biased.sense()["2"].odometry.position)


def test_a_current_carries_the_vessel_over_ground_and_not_its_odometry():
    plain = World(effect_scenario(PlantEffects()).world, np.random.default_rng(5))
    drifted = _world(current=(0.3, -0.2))
    start = drifted.truth().positions["1"]
    for _ in range(50):
        commands = {v: Command(1.0, 0.0) for v in plain.live()}
        plain.step(commands)
        drifted.step(commands)
    moved = drifted.truth().positions["1"] - start
    own = plain.truth().positions["1"] - start
    np.testing.assert_allclose(moved - own, [0.3 * 5.0, -0.2 * 5.0], atol=1e-9)  # c t, t = 50 dt
    np.testing.assert_array_equal(
        plain.sense()["1"].odometry.position, drifted.sense()["1"].odometry.position
    )


def test_no_effect_is_the_kinematic_world_bit_for_bit():
    scenario = updated(effect_scenario(PlantEffects()), duration=5.0)
    plain = runner.run(scenario, 3)
    wrapped = runner.run(scenario, 3, make_world=world_factory(PlantEffects(), 3))
    np.testing.assert_array_equal(plain.positions, wrapped.positions)
    np.testing.assert_array_equal(plain.commands, wrapped.commands)


def test_the_lag_compensated_heading_loop_has_its_designed_error_dynamics():
    # Plant tau r' = u - r, theta' = r with u from the loop; the heading error obeys
    # e'' + 2 zeta w e' + w^2 e = 0: with zeta = 1, e(t) = e0 (1 + w t) exp(-w t) for e'(0) = 0.
    tau, w, zeta, e0, dt = 1.0, 1.0, 1.0, 0.2, 1e-4
    theta, r = 0.0, 0.0
    for k in range(1, 30001):
        u = lag_compensated_rate(e0 - theta, r, 0.0, tau, w, zeta)
        r += dt * (u - r) / tau
        theta += dt * r
        if k % 10000 == 0:
            t = k * dt
            assert e0 - theta == pytest.approx(e0 * (1 + w * t) * math.exp(-w * t), abs=2e-4)


def test_the_coasting_distance_is_what_a_lagged_boat_runs_after_a_stop():
    # A boat at 1.5 m/s commanded to stop through tau_u = 1 s runs int u0 e^{-t/tau} dt = u0 tau; summed
    # here step by step through the plant's own lag (the boat moves with each step's response).
    dt, u, run = 1e-3, 1.5, 0.0
    for _ in range(40000):
        u = lag_step(u, 0.0, dt, 1.0, None, None)
        run += u * dt
    assert run == pytest.approx(coasting_distance(1.5, 1.0), rel=1e-3)
    assert coasting_distance(1.5, 0.0) == 0.0


@pytest.mark.slow   # an in-process fleet run of seconds: the full suite's, not test-fast's
@pytest.mark.parametrize("seed", [11, 12, 13])
def test_the_coping_agent_settles_and_keeps_apart_under_one_second_lags(seed):
    effects = PlantEffects(surge_lag=1.0, yaw_lag=1.0)
    figures = measure(effect_scenario(effects, COPING), effects, seed)
    assert figures.settled
    assert figures.closest >= 3.0


@pytest.mark.slow   # an in-process fleet run of seconds: the full suite's, not test-fast's
@pytest.mark.parametrize("seed", [21, 22])
def test_the_coping_agent_with_the_otters_limits_settles_and_commands_within_them(seed):
    limits = {"control": {"boat_max_yaw_rate": math.radians(10.0), "max_speed": 3.0}}
    effects = PlantEffects(
        surge_lag=1.0, yaw_lag=1.0, max_yaw_rate=math.radians(10.0), max_surge=3.0, max_acceleration=1.0
    )
    agent = {**COPING, "control": {**COPING["control"], **limits["control"]}}
    figures = measure(effect_scenario(effects, agent, still_target=True), effects, seed)
    assert figures.settled
    assert figures.closest >= 3.0
    assert figures.max_yaw_rate <= math.radians(10.0) and figures.max_surge <= 3.0


def test_the_odometry_variance_from_the_spec_covers_the_displacement_error():
    # Monte Carlo of one period's dead-reckoned displacement with a speed log of 0.1 m/s and a compass of
    # 3 deg at 2 m/s: its error covariance's largest eigenvalue is the variance the filters get per axis.
    rng = np.random.default_rng(7)
    speed, dt, sigma_s, sigma_psi, heading = 2.0, 0.1, 0.1, math.radians(3.0), 0.7
    for s_std, psi_std in ((sigma_s, sigma_psi), (0.01, sigma_psi)):  # along the track, then across it
        ds = rng.normal(0.0, s_std, 200_000)
        dpsi = rng.normal(0.0, psi_std, 200_000)
        measured = (
            (speed + ds)[:, None] * dt * np.stack([np.cos(heading + dpsi), np.sin(heading + dpsi)], axis=1)
        )
        error = measured - speed * dt * np.array([math.cos(heading), math.sin(heading)])
        largest = np.linalg.eigvalsh(np.cov(error.T))[-1]
        assert displacement_variance(s_std, psi_std, speed, dt) == pytest.approx(largest, rel=0.05)


def test_the_margins_of_a_sampled_integrator_are_the_closed_form():
    # L(z) = K dt / (z - 1): |L| = 1 where 2 sin(w dt / 2) = K dt, and there the phase is
    # -(90 + w dt / 2) deg.
    w, z = _frequencies(0.1)
    for gain in (10.0, 2.0):
        crossover, margin, _ = margins(gain * plant(z, 0.0, 0.1), w)
        expected = 2.0 / 0.1 * math.asin(gain * 0.1 / 2.0)
        assert crossover == pytest.approx(expected, rel=1e-3)
        assert margin == pytest.approx(90.0 - math.degrees(expected * 0.1 / 2.0), abs=0.05)


@pytest.mark.parametrize("seed", [41, 42])
def test_no_command_goes_beyond_the_boats_turn_rate_or_astern_limit(seed):
    """Over random situations (estimates, target, obstacles, heading, the lag-compensated loop on and off) the
    command stays within boat_max_yaw_rate and boat_max_astern, and they bite: without them some commands go
    beyond."""
    rng = np.random.default_rng(seed)
    bounded = ControlParams(boat_max_yaw_rate=0.3, boat_max_astern=1.0, max_speed=3.0)
    beyond = {"rate": 0, "astern": 0}
    for k in range(400):
        lag = {"yaw_lag": 1.0} if k % 2 else {}
        phase = rng.uniform(-math.pi, math.pi)
        args = (0.1, phase, phase + math.pi / 300, rng.uniform(-math.pi, math.pi),
                np.append(rng.normal(0, 8, 2), rng.normal(0, 0.5, 2)), rng.normal(0, 1, 2),
                {j: rng.normal(0, 8, 2) for j in "234"}, {j: rng.uniform(0, 2 * math.pi) for j in "234"},
                rng.normal(0, 4, (3, 2)) if k % 3 == 0 else None)
        free, _, _ = control_command(updated(ControlParams(max_speed=3.0), **lag), *args, yaw_rate_estimate=0.1)
        command, _, saturated = control_command(updated(bounded, **lag), *args, yaw_rate_estimate=0.1)
        assert abs(command.yaw_rate) <= 0.3 and -1.0 <= command.surge <= 3.0
        assert math.isfinite(command.surge) and math.isfinite(command.yaw_rate)
        if free.surge < -1.0:
            beyond["astern"] += 1
            assert command.surge == -1.0 and saturated["speed"]
        if abs(free.yaw_rate) > 0.3:
            beyond["rate"] += 1
        else:
            assert command.yaw_rate == free.yaw_rate
    assert beyond["astern"] >= 20 and beyond["rate"] >= 20, beyond
