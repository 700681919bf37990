"""boat/sway.py: the sway observer against closed forms and against the hull simulation's own sway."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.config import ConfigError, parse_mapping
from agent.core.records import Command
from boat.presets import PRESETS, preset
from boat.sway import SwayModel, arc_step, steady, step
from sim_bridge.hull import HullFleet
from sim_bridge.world import World, WorldConfig


def test_the_otter_circling_at_the_coping_agents_speed_skids_outward_at_0_152_m_s():
    # By hand: m11 = 80 + 0.1 * 55 = 85.5 kg; -Y_|v|v = rho T C_D L = 1026 * (80 / 1025 / 0.4) * 1.004 * 2.0
    # / 2 = 200.996 N s^2/m^2 and no linear term, so 200.996 v |v| = -85.5 * 0.52 * 0.105 = -4.6683 N:
    # v = -sqrt(4.6683 / 200.996) = -0.15240 m/s, to starboard (outward) in a turn to port.
    otter = SwayModel.of(PRESETS["otter"].hull)
    assert otter.m11 == pytest.approx(85.5) and otter.linear == 0.0
    assert otter.quadratic == pytest.approx(200.996, rel=1e-5)
    assert steady(otter, 0.52, 0.105) == pytest.approx(-0.15240, abs=5e-5)
    assert math.degrees(math.atan2(0.15240, 0.52)) == pytest.approx(16.3, abs=0.05)   # the sideslip angle
    # The observer held at that (u, r) settles on that value, for any step (linearly implicit).
    for dt in (0.1, 1.0, 10.0):
        v = np.zeros(3)
        for _ in range(round(200 / dt)):
            v = step(otter, v, np.full(3, 0.52), np.full(3, 0.105), 0.0, dt)
        np.testing.assert_allclose(v, -0.15240, atol=5e-5)
    assert steady(otter, -0.52, 0.105) == pytest.approx(0.15240, abs=5e-5)   # astern: the other way


def test_linear_sway_damping_decays_with_the_time_constant_m22_over_d22():
    # Heron: m22 = 28 + 1.5 * 28 = 70 kg, -Y_v = 2.5 * 28 = 70 N s/m: T = 1 s. With u r = 0 the scheme gives
    # v_n = (1 + h/T)^-n exactly, and e^-t/T <= v_n <= e^-t/T e^(t h / 2 T^2) (ln(1 + x) in [x - x^2/2, x]).
    heron = SwayModel.of(PRESETS["heron"].hull)
    assert heron.m22 / heron.linear == pytest.approx(1.0)
    assert steady(heron, 1.0, 0.2) == pytest.approx(-30.8 * 0.2 / 70.0)   # m11 = 28 + 2.8
    for h in (0.1, 0.01, 0.001):
        v, t = np.array([1.0, -2.0]), 0.0
        for _ in range(round(3.0 / h)):
            v, t = step(heron, v, np.zeros(2), np.zeros(2), 0.0, h), t + h
            exact = math.exp(-t)
            assert exact <= v[0] <= exact * math.exp(t * h / 2) + 1e-15
        np.testing.assert_allclose(v[1], -2 * v[0], rtol=1e-12)                # linear: scales
    # The time constant read off the decay: ln(v(1) / v(2)) at h = 1 ms.
    v = np.array([1.0])
    samples = []
    for n in range(1, 2001):
        v = step(heron, v, np.zeros(1), np.zeros(1), 0.0, 1e-3)
        if n in (1000, 2000):
            samples.append(v[0])
    assert 1.0 / math.log(samples[0] / samples[1]) == pytest.approx(1.0, rel=1e-3)


@pytest.mark.parametrize("name", ["otter", "heron"])
def test_the_observer_follows_the_hull_simulations_sway_in_calm_water(name):
    """Fed the hull's (u_r, r) every 0.1 s under a varying command, it stays within the implicit Euler bound
    h (max |v''| + max |f'|) / (2 lambda_min): local error h^2/2 (|v''| + |f'|), with f = m11 u r / m22 taken
    at the step's mean, spent at the contraction rate lambda = (d22 + 2 d22q |v|) / m22 of the sway row."""
    boat = PRESETS[name]
    model = SwayModel.of(boat.hull)
    hulls = HullFleet(boat, 1, 0.02, 1)
    h, t = 0.1, 0.0
    estimate = np.zeros(1)
    u0, r0 = hulls.state[3].copy(), hulls.state[5].copy()
    rows = []
    for _ in range(600):
        speed = 0.6 + 0.3 * math.sin(2 * math.pi * t / 20)
        rate = 0.12 + 0.08 * math.sin(2 * math.pi * t / 13)       # turning one way: |v| stays away from 0
        hulls.advance(t, h, np.array([speed]), np.array([rate]), t)
        t += h
        u1, r1 = hulls.state[3].copy(), hulls.state[5].copy()
        estimate = step(model, estimate, 0.5 * (u0 + u1), 0.5 * (r0 + r1), r1 - r0, h)
        rows.append((u1[0], hulls.state[4][0], r1[0], estimate[0]))
        u0, r0 = u1, r1
    u, v, r, v_hat = np.array(rows).T
    after = slice(100, None)                                     # the start from rest: 10 s
    v_dd = np.abs(np.diff(v, 2) / h**2)[100:].max()
    f_d = np.abs(np.diff(model.m11 * u * r / model.m22) / h)[100:].max()
    rate = ((model.linear + 2 * model.quadratic * np.abs(v)) / model.m22)[after].min()
    bound = h * (v_dd + f_d) / (2 * rate)
    assert bound < 0.1 * np.abs(v[after]).max()                  # a bound that says something
    assert np.abs(v_hat - v)[after].max() <= bound


def test_a_hull_without_sway_damping_is_refused():
    with pytest.raises(ConfigError, match="no sway damping"):
        SwayModel.of(preset("otter", {"hull": {"sway_damping_quadratic": 0.0}}).hull)


def test_non_finite_inputs_give_a_non_finite_sway_for_the_caller_to_refuse():
    otter = SwayModel.of(PRESETS["otter"].hull)
    out = step(otter, np.zeros(3), np.array([math.nan, 0.5, 0.5]), np.array([0.1, math.inf, 0.1]), 0.0, 0.1)
    assert not np.isfinite(out[:2]).any() and np.isfinite(out[2])


def test_the_arc_step_is_exact_for_a_steady_turn_with_sideslip():
    # A hull at (u, v) through a turn at r: the centre is at R(psi) (-v, u) / r from it, the radius
    # sqrt(u^2 + v^2) / r; after dt it is on that circle, turned by r dt.
    u, v, r, dt, psi = 0.52, -0.1524, 0.105, 2.0, 0.3
    x, y = arc_step(1.0, 2.0, psi, r * dt, u * dt, v * dt)
    cx = 1.0 + (math.cos(psi) * -v - math.sin(psi) * u) / r
    cy = 2.0 + (math.sin(psi) * -v + math.cos(psi) * u) / r
    angle = math.atan2(2.0 - cy, 1.0 - cx) + r * dt
    radius = math.hypot(u, v) / r
    assert (x, y) == pytest.approx((cx + radius * math.cos(angle), cy + radius * math.sin(angle)), abs=1e-12)
    assert arc_step(0.0, 0.0, 0.5, 0.0, 2.0, 0.0) == pytest.approx((2 * math.cos(0.5), 2 * math.sin(0.5)))


# --- the sim's speed log and compass with `sway: hull` ------------------------------------------------------

def otter_world(sway: str, seed: int = 0, **odometry) -> World:
    data = {"vessels": [{"id": "a", "position": (0.0, 0.0), "heading": 0.0}],
            "target": {"kind": "constant_velocity", "position": (5.0, 0.0), "velocity": (0.0, 0.0)},
            "range_noise": {"kind": "gaussian", "variance": 0.0}, "bearing_variance": 0.0,
            "displacement_variance": 0.0, "dynamics": {"preset": "otter"},
            "sensors": {"odometry": {"kind": "water_log_compass", "sway": sway, **odometry}}}
    return World(WorldConfig.model_validate(data), np.random.default_rng(seed))


def dead_reckoning_errors(w: World, steps: int, keep_from: int) -> np.ndarray:
    errors = []
    for k in range(steps):
        w.step({"a": Command(0.52, 0.105)})
        if k >= keep_from:   # the odometry frame is the world's here: start at the origin, heading 0
            errors.append(np.linalg.norm(w.sense()["a"].odometry.position - w.truth().positions["a"]))
    return np.array(errors)


def test_the_sway_correction_cuts_the_dead_reckoning_error_of_a_circle_by_two_orders():
    # The Otter circling at (0.52 m/s, 0.105 rad/s) skids at v = -0.1524 m/s: the log's track is the true one
    # turned by the sideslip b = atan2(0.1524, 0.52) and shrunk by cos b, so it misses by sin b |p - p0|,
    # at most sin b 2 rho = 0.2812 * 2 * 5.161 = 2.90 m across the circle (rho = sqrt(u^2 + v^2) / r).
    # Measured on the second circle (60-120 s, seed 0): 2.78 m without the correction, 0.0154 m with it.
    plain = dead_reckoning_errors(otter_world("none"), 1200, 600)
    corrected = dead_reckoning_errors(otter_world("hull"), 1200, 600)
    assert 0.9 * 2.90 <= plain.max() <= 2.90 * 1.01
    assert corrected.max() <= 0.02                  # the observer's O(dt) lag in the start from rest
    assert plain.max() / corrected.max() >= 100


def test_the_correction_draws_nothing_more_and_the_compass_reads_the_same():
    noisy = {"speed_noise_density": 0.01, "compass_noise_deg": 0.2, "compass_bias_std_deg": 1.0,
             "scale_error_std": 0.02}
    a, b = otter_world("none", 3, **noisy), otter_world("hull", 3, **noisy)
    for _ in range(100):
        a.step({"a": Command(0.52, 0.105)})
        b.step({"a": Command(0.52, 0.105)})
        assert a.sense()["a"].odometry.heading == b.sense()["a"].odometry.heading
    assert np.array_equal(a.truth().positions["a"], b.truth().positions["a"])
    assert not np.array_equal(a.sense()["a"].odometry.position, b.sense()["a"].odometry.position)


@pytest.mark.parametrize("changes, words", [
    ({}, "takes the hull model of world.dynamics"),
    ({"dynamics": {"preset": "otter", "overrides": {"hull": {"sway_damping_quadratic": 0.0}}}},
     "no sway damping"),
])
def test_a_sway_correction_without_a_hull_model_is_refused_in_one_line(changes, words):
    data = {"vessels": [{"id": "a", "position": (0.0, 0.0)}],
            "target": {"kind": "constant_velocity", "position": (5.0, 0.0), "velocity": (0.0, 0.0)},
            "sensors": {"odometry": {"kind": "water_log_compass", "sway": "hull"}}, **changes}
    with pytest.raises(ConfigError) as error:
        parse_mapping(WorldConfig, data, "scenario.yaml")
    assert words in str(error.value) and "\n" not in str(error.value)
