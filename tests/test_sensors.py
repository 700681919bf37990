"""Sensor error models (sim_bridge/sensors.py) and their place in the world (WorldConfig.sensors).

Expected values are worked out here by hand or from closed forms, never read back from the code under test;
statistical checks compare against the closed form within the sampling error computed here (4 sigma).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from agent.config import ConfigError, parse_mapping
from agent.core.records import Command
from agent.runtime.mcap_log import read_messages
from lab.harness.runner import run as run_scenario
from sim_bridge.scenario import Scenario
from sim_bridge.sensors import (
    DvlGyro,
    Uwb,
    WaterLogCompass,
    advance_odometry,
    dead_reckon,
    gyro_heading_step,
    gyro_heading_variance,
    rotate,
    speed_log,
    start_odometry,
    tilt,
    tilted_azimuth,
    uwb_faults,
    white_displacement_variance,
)
from sim_bridge.world import World, WorldConfig

STILL_TARGET = {"kind": "constant_velocity", "position": (5.0, 0.0), "velocity": (0.0, 0.0)}
QUIET = {"range_noise": {"kind": "gaussian", "variance": 0.0}, "bearing_variance": 0.0,
         "displacement_variance": 0.0, "heading_variance": 0.0}
DEG = math.pi / 180


def world(vessels, sensors, seed=0, attitude=None, target=STILL_TARGET, **changes) -> World:
    data = {"vessels": vessels, "target": target, **QUIET, "sensors": sensors, **changes}
    return World(WorldConfig.model_validate(data), np.random.default_rng(seed), attitude=attitude)


def run(w: World, commands: dict, steps: int) -> None:
    for _ in range(steps):
        w.step({vessel: Command(*command) for vessel, command in commands.items()})


ONE = [{"id": "a", "position": (2.0, -1.0), "heading": 0.3}]


# --- speed log and compass ---------------------------------------------------------------------------------

def test_a_straight_run_with_a_compass_bias_is_dead_reckoned_rotated_by_the_bias():
    sensors = {"odometry": {"kind": "water_log_compass", "compass_biases_deg": {"a": 2.0}}}
    w = world(ONE, sensors)
    assert w.sense()["a"].odometry.heading == pytest.approx(0.3 + 2 * DEG, abs=1e-15)
    run(w, {"a": (1.5, 0.0)}, 40)
    # 1.5 m/s for 4 s along the compass heading 0.3 rad + 2 deg: 6 m at that angle, from the origin.
    reading = w.sense()["a"].odometry
    np.testing.assert_allclose(reading.position, 6.0 * np.array([math.cos(0.3 + 2 * DEG), math.sin(0.3 + 2 * DEG)]),
                               rtol=0, atol=1e-12)
    assert reading.heading == pytest.approx(0.3 + 2 * DEG, abs=1e-15)
    # The hull itself went along 0.3 rad: the odometry is the true displacement turned by the bias.
    true = w.truth().positions["a"] - np.array([2.0, -1.0])
    turned = np.array([[math.cos(2 * DEG), -math.sin(2 * DEG)], [math.sin(2 * DEG), math.cos(2 * DEG)]]) @ true
    np.testing.assert_allclose(reading.position, turned, rtol=0, atol=1e-12)


def test_the_dead_band_zeroes_slow_speeds_and_the_scale_error_scales_distance():
    model = {"kind": "water_log_compass", "dead_band": 0.25, "scale_errors": {"a": 0.05}}
    slow = world(ONE, {"odometry": model})
    run(slow, {"a": (0.2, 0.0)}, 30)
    assert slow.sense()["a"].odometry.position.tolist() == [0.0, 0.0]
    assert np.linalg.norm(slow.truth().positions["a"] - [2.0, -1.0]) == pytest.approx(0.6, abs=1e-12)
    fast = world(ONE, {"odometry": model})
    run(fast, {"a": (0.3, 0.0)}, 30)
    # 0.3 m/s for 3 s is 0.9 m; the log reads 5 % more: 0.945 m.
    assert np.linalg.norm(fast.sense()["a"].odometry.position) == pytest.approx(0.945, abs=1e-12)
    backwards = world(ONE, {"odometry": model})
    run(backwards, {"a": (-0.2, 0.0)}, 30)
    assert backwards.sense()["a"].odometry.position.tolist() == [0.0, 0.0]


def test_water_referenced_odometry_drifts_by_the_integral_of_the_current():
    # A hull that holds a turning course through the water, in a current c: over ground it moves at v_w + c.
    # The log and compass see only v_w, so the dead-reckoned track misses the current's integral c T.
    model = WaterLogCompass()
    c = np.array([0.3, -0.2])
    rng = np.random.default_rng(0)
    state = start_odometry(model, "a", 0.0, rng)
    heading, true, dt = 0.0, np.zeros(2), 0.1
    for _ in range(200):
        water = 1.2 * np.array([math.cos(heading), math.sin(heading)])
        ground = water + c
        state = advance_odometry(model, state, ground, water, heading, 0.02, dt, rng)
        true += ground * dt
        heading += 0.02
    np.testing.assert_allclose(np.array(state.position) - true, -c * 20.0, rtol=0, atol=1e-12)


def test_in_the_world_the_odometry_reads_the_vessels_water_velocity():
    # The kinematic world has no current: the motion that has one sets water_velocity. Here the hull heads
    # east at 1 m/s over ground in a 0.25 m/s current from astern: 0.75 m/s through the water.
    w = world([{"id": "a", "position": (0.0, 0.0)}], {"odometry": {"kind": "water_log_compass"}})
    for _ in range(50):
        w._vessels["a"].water_velocity = np.array([0.75, 0.0])
        run(w, {"a": (1.0, 0.0)}, 1)
    np.testing.assert_allclose(w.sense()["a"].odometry.position, [3.75, 0.0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(w.truth().positions["a"], [5.0, 0.0], rtol=0, atol=1e-12)   # drift -c T = -1.25


def test_a_bottom_tracking_dvl_ignores_the_current_and_its_scale_error_scales_distance():
    model = DvlGyro(scale_errors={"a": 0.004})
    rng = np.random.default_rng(0)
    state = start_odometry(model, "a", 0.7, rng)
    heading, true = 0.7, np.zeros(2)
    for _ in range(100):
        ground = np.array([math.cos(heading), math.sin(heading)]) * 2.0 + [0.3, 0.1]   # crabbing in a current
        state = advance_odometry(model, state, ground, ground - [0.3, 0.1], heading, -0.01, 0.1, rng)
        true += ground * 0.1
        heading -= 0.01
    # No gyro error: the heading reading is the true one, and the track is the true one scaled by 1.004.
    assert state.heading == pytest.approx(0.7 - 1.0, abs=1e-12)
    np.testing.assert_allclose(state.position, 1.004 * true, rtol=0, atol=1e-12)


def test_a_noise_free_dvl_gyro_world_reports_the_true_displacement_of_a_curved_run():
    w = world(ONE, {"odometry": {"kind": "dvl_gyro"}})
    run(w, {"a": (1.0, 0.4)}, 60)
    np.testing.assert_allclose(w.sense()["a"].odometry.position, w.truth().positions["a"] - [2.0, -1.0],
                               rtol=0, atol=1e-12)
    assert w.sense()["a"].odometry.heading == pytest.approx(w.truth().headings["a"], abs=1e-12)


def test_a_gyro_bias_makes_the_heading_drift_linearly():
    # b_0 = 0.05 deg/s, nothing else: after 30 s the heading reading is 1.5 deg off, and the track turned with it
    # step by step: each step's displacement turned by the error at its start, e_k = b_0 k dt.
    w = world(ONE, {"odometry": {"kind": "dvl_gyro", "gyro": {"turn_on_biases_deg_s": {"a": 0.05}}}})
    run(w, {"a": (1.0, 0.0)}, 300)
    reading = w.sense()["a"].odometry
    assert reading.heading == pytest.approx(0.3 + 1.5 * DEG, abs=1e-12)
    angles = 0.3 + 0.05 * DEG * 0.1 * np.arange(300)
    expected = 0.1 * np.array([np.cos(angles).sum(), np.sin(angles).sum()])
    np.testing.assert_allclose(reading.position, expected, rtol=0, atol=1e-11)


def test_the_gyro_heading_error_and_bias_variances_match_their_closed_forms():
    # M vessels, each its own gyro, through the model as the world runs it (units and all).
    s0, arw, rrw = 0.02, 3.0, 0.01      # deg/s, deg/sqrt(h), deg/s/sqrt(s)
    model = DvlGyro(gyro={"turn_on_bias_std_deg_s": s0, "angle_random_walk_deg_rt_h": arw,
                          "rate_random_walk_deg_s_rt_s": rrw})
    m, n, dt = 3000, 50, 0.1
    rng = np.random.default_rng(11)
    errors, biases = np.empty(m), np.empty(m)
    for i in range(m):
        state = start_odometry(model, "a", 0.0, rng)
        for _ in range(n):
            state = advance_odometry(model, state, (0.0, 0.0), (0.0, 0.0), 0.0, 0.0, dt, rng)
        errors[i], biases[i] = state.heading, state.bias
    s0, k, sigma_n = s0 * DEG, rrw * DEG, arw * DEG / 60.0          # rad/s, rad/s/sqrt(s), rad/sqrt(s)
    t = n * dt
    # Var(b_T) = s0^2 + K^2 T. The heading error dt sum_{k<N} (b_k + n_k): s0 counts N times, the walk's
    # increments K sqrt(dt) w_j count in every later step (N - 1 - j of them), the white noise once each.
    bias_variance = s0**2 + k**2 * t
    walk = sum((n - 1 - j) ** 2 for j in range(n)) * k**2 * dt * dt**2
    heading_variance = (n * dt * s0) ** 2 + walk + n * dt * sigma_n**2
    for sample, expected in ((biases, bias_variance), (errors, heading_variance)):
        tolerance = 4 * expected * math.sqrt(2 / (m - 1))       # std of a normal sample's variance
        assert abs(sample.var(ddof=1) - expected) < tolerance, (sample.var(ddof=1), expected)
    # And the walk part against its continuous limit K^2 T^3 / 3 (dt -> 0): 3 % apart at N = 50.
    assert walk == pytest.approx(k**2 * t**3 / 3, rel=0.04)
    assert gyro_heading_variance(s0, k, sigma_n, dt, n) == pytest.approx(heading_variance, rel=1e-12)


def same_angle(reading: float, angle: float) -> bool:
    """`reading` is wrapped into (-pi, pi] and is `angle` up to whole turns."""
    return -math.pi < reading <= math.pi and abs(math.remainder(reading - angle, 2 * math.pi)) < 1e-14


def test_one_odometry_step_is_the_kernels_applied_to_the_stated_draws():
    # The draws by hand, in the order the docstrings state, through the vectorised kernels.
    compass = WaterLogCompass(scale_error_std=0.03, dead_band=0.1, speed_noise_density=0.02,
                              compass_bias_std_deg=1.0, compass_noise_deg=0.5)
    dvl = DvlGyro(scale_error_std=0.01, velocity_noise_density=0.01,
                  gyro={"turn_on_bias_std_deg_s": 0.1, "angle_random_walk_deg_rt_h": 5.0,
                        "rate_random_walk_deg_s_rt_s": 0.01})
    # Near the seam: the headings after the turn wrap past pi.
    dt, heading, turn, ground, water = 0.1, 3.13, 0.03, np.array([-0.8, 0.6]), np.array([-0.7, 0.4])
    for seed in range(5):
        rng, hand = np.random.default_rng(seed), np.random.default_rng(seed)
        state = start_odometry(compass, "a", heading, rng)
        k, b = hand.normal(0, 0.03), hand.normal(0, 1.0) * DEG
        psi_c = heading + b + hand.normal(0, 0.5 * DEG)
        assert (state.scale, state.bias) == (k, b) and same_angle(state.heading, psi_c)
        after = advance_odometry(compass, state, ground, water, heading, turn, dt, rng)
        surge = water @ [math.cos(heading), math.sin(heading)]
        speed = speed_log(surge, k, 0.1, hand.normal(0, 0.02 / math.sqrt(dt)))
        np.testing.assert_allclose(after.position, dead_reckon((0.0, 0.0), speed, psi_c, dt), rtol=0, atol=1e-15)
        assert same_angle(after.heading, heading + turn + b + hand.normal(0, 0.5 * DEG))

        rng, hand = np.random.default_rng(seed), np.random.default_rng(seed)
        state = start_odometry(dvl, "a", heading, rng)
        k, b = hand.normal(0, 0.01), hand.normal(0, 0.1) * DEG
        assert (state.heading, state.scale, state.bias) == (heading, k, b)
        after = advance_odometry(dvl, state, ground, water, heading, turn, dt, rng)
        measured = (1 + k) * rotate(ground, -heading) + hand.normal(0, 0.01 / math.sqrt(dt), 2)
        np.testing.assert_allclose(after.position, rotate(measured, heading) * dt, rtol=0, atol=1e-15)
        rate_noise = hand.normal(0, 5.0 * DEG / 60 / math.sqrt(dt))
        psi, bias = gyro_heading_step(heading, b, turn, rate_noise, hand.normal(0, 0.01 * DEG * math.sqrt(dt)), dt)
        assert same_angle(after.heading, float(psi))
        assert after.bias == pytest.approx(float(bias), abs=1e-15)


def test_the_white_displacement_variance_is_what_one_step_of_the_model_spreads():
    model = WaterLogCompass(speed_noise_density=0.01, compass_noise_deg=5.0)
    along, across = white_displacement_variance(model, 2.0, 0.1)
    # By hand: (0.01 m/s/sqrt(Hz))^2 * 0.1 s = 1e-5 m^2; (2 m/s * 0.1 s * 5 deg)^2 = (0.2 * 0.0872665)^2.
    assert along == pytest.approx(1e-5, rel=1e-12)
    assert across == pytest.approx((0.2 * 5 * DEG) ** 2, rel=1e-12)
    assert white_displacement_variance(DvlGyro(velocity_noise_density=0.02), 1.0, 0.1) == pytest.approx(
        (4e-5, 4e-5), rel=1e-12)
    # Against the model: one step east at 2 m/s from a fresh compass reading, many times. Each noise alone,
    # so the other's second-order part (cos of a small angle) does not blur the comparison.
    rng, m = np.random.default_rng(8), 20000
    for noise, axis, expected in ((WaterLogCompass(speed_noise_density=0.01), 0, along),
                                  (WaterLogCompass(compass_noise_deg=5.0), 1, across)):
        steps = np.array([advance_odometry(noise, start_odometry(noise, "a", 0.0, rng), (2.0, 0.0), (2.0, 0.0),
                                           0.0, 0.0, 0.1, rng).position for _ in range(m)])
        # sin of a N(0, s^2) angle has variance (1 - exp(-2 s^2)) / 2, 0.8 % under s^2 at 5 deg: inside 4 sigma.
        assert abs(steps[:, axis].var(ddof=1) - expected) < 4 * expected * math.sqrt(2 / (m - 1))


# --- UWB -------------------------------------------------------------------------------------------------------

TWO = [{"id": "a", "position": (0.0, 0.0), "heading": 0.0},
       {"id": "b", "position": (10.0, 0.0), "heading": math.pi / 2}]


def test_the_range_is_between_antennas_that_turn_with_the_hull():
    uwb = {"antenna": (-0.5, 0.0, 0.0), "antennas": {"b": (0.5, 0.2, 0.0)}}
    w = world(TWO, {"uwb": uwb})
    # a's antenna at (-0.5, 0); b faces north, so its antenna 0.5 ahead and 0.2 left is at (10 - 0.2, 0.5).
    expected = math.hypot(9.8 + 0.5, 0.5)
    assert w.sense()["a"].ranges["b"] == pytest.approx(expected, abs=1e-12)
    assert w.sense()["b"].ranges["a"] == pytest.approx(expected, abs=1e-12)


def test_roll_and_pitch_move_a_raised_antenna():
    uwb = {"antenna": (0.0, 0.0, 1.0), "antennas": {"b": (0.0, 0.0, 0.0)}}
    north = [{"id": "a", "position": (0.0, 0.0), "heading": 0.0}, {"id": "b", "position": (0.0, 10.0)}]
    rolled = world(north, {"uwb": uwb}, attitude=lambda t, x, y, heading: (0.1, 0.0) if y < 5 else (0.0, 0.0))
    # a heads east and rolls 0.1 rad starboard down: its masthead swings to starboard (south), away from b.
    assert rolled.sense()["a"].ranges["b"] == pytest.approx(10.0 + math.sin(0.1), abs=1e-12)
    pitched = world(TWO, {"uwb": uwb}, attitude=lambda t, x, y, heading: (0.0, 0.2) if x < 5 else (0.0, 0.0))
    # Bow up 0.2 rad: the masthead goes aft (west), away from b in the east.
    assert pitched.sense()["a"].ranges["b"] == pytest.approx(10.0 + math.sin(0.2), abs=1e-12)
    assert world(TWO, {"uwb": uwb}).sense()["a"].ranges["b"] == pytest.approx(10.0, abs=1e-12)


def test_the_tilt_agrees_with_fossens_zyx_rotation_in_ned():
    # Independently: Fossen's R = Rz(psi) Ry(theta) Rx(phi) in NED (x forward, y starboard, z down), via scipy;
    # our frame is (forward, left, up), so y and z change sign on the way in and out.
    rng = np.random.default_rng(2)
    flip = np.array([1.0, -1.0, -1.0])
    for _ in range(20):
        roll, pitch = rng.uniform(-0.4, 0.4, 2)
        rotation = Rotation.from_euler("ZYX", [0.0, pitch, roll])
        arm = rng.uniform(-1, 1, 3)
        np.testing.assert_allclose(tilt(arm, roll, pitch), rotation.apply(arm * flip) * flip, rtol=0, atol=1e-14)
        azimuth, elevation = rng.uniform(-math.pi, math.pi), rng.uniform(-0.3, 0.3)
        sight = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                          math.sin(elevation)])
        body = rotation.inv().apply(sight * flip)                # the sight line in the tilted camera, NED
        measured = -math.atan2(body[1], body[0])                 # starboard-positive azimuth, turned to ours
        assert abs(math.remainder(float(tilted_azimuth(azimuth, elevation, roll, pitch)) - measured, 2 * math.pi)
                   ) < 1e-13


def test_dropout_and_outlier_rates_follow_the_logistic_law_within_binomial_error():
    law = {"floor": 0.02, "ceiling": 0.8, "midpoint": 30.0, "width": 8.0}
    model = Uwb(dropout=law, outlier={"floor": 0.05, "ceiling": 0.5, "midpoint": 20.0, "width": 5.0},
                outlier_mean=1.5)
    rng = np.random.default_rng(3)
    n = 20000
    for distance in (5.0, 20.0, 30.0, 45.0):
        true = np.full(n, distance)
        measured, kept = uwb_faults(model, true, true.copy(), rng)
        p_drop = 0.02 + 0.78 / (1 + math.exp(-(distance - 30.0) / 8.0))
        p_out = 0.05 + 0.45 / (1 + math.exp(-(distance - 20.0) / 5.0))
        for rate, p in ((1 - kept.mean(), p_drop), ((measured > true).mean(), p_out)):
            assert abs(rate - p) < 4 * math.sqrt(p * (1 - p) / n), (distance, rate, p)
        excess = (measured - true)[measured > true]
        # An exponential excess of mean 1.5 m: its sample mean within 4 standard errors (std = mean).
        assert abs(excess.mean() - 1.5) < 4 * 1.5 / math.sqrt(len(excess))


def test_a_dropped_range_is_not_reported_in_the_world():
    gone = world(TWO, {"uwb": {"dropout": {"floor": 1.0, "ceiling": 1.0, "midpoint": 0.0, "width": 1.0}}})
    assert gone.sense()["a"].ranges == {} and gone.sense()["b"].ranges == {}
    kept = world(TWO, {"uwb": {"dropout": {"floor": 0.0, "ceiling": 0.0, "midpoint": 0.0, "width": 1.0}}})
    assert kept.sense()["a"].ranges == {"b": 10.0}


# --- the camera ------------------------------------------------------------------------------------------------

def test_a_tilted_camera_measures_the_hand_computed_azimuth():
    # Pure pitch, level sight line: tan(alpha_m) = tan(alpha) / cos(theta).
    assert float(tilted_azimuth(math.pi / 4, 0.0, 0.0, 0.1)) == pytest.approx(math.atan(1 / math.cos(0.1)),
                                                                                abs=1e-15)
    # Pure roll, level sight line: tan(alpha_m) = tan(alpha) cos(phi).
    assert float(tilted_azimuth(math.pi / 4, 0.0, 0.2, 0.0)) == pytest.approx(math.atan(math.cos(0.2)), abs=1e-15)
    # Dead ahead, looking down at eps: a roll phi moves it sideways, tan(alpha_m) = sin(phi) tan(eps).
    eps = -math.atan(0.1)
    assert float(tilted_azimuth(0.0, eps, 0.1, 0.0)) == pytest.approx(math.atan(-0.1 * math.sin(0.1)), abs=1e-15)
    assert float(tilted_azimuth(1.0, -0.3, 0.0, 0.0)) == pytest.approx(1.0, abs=1e-15)


def test_in_the_world_roll_turns_the_bearing_and_the_heading_reference_adds_the_compass_error():
    vessel = [{"id": "a", "position": (0.0, 0.0), "heading": 0.0}]
    # Camera 0.5 m up, target 5 m dead ahead at the waterline: the sight line dips atan(0.1).
    tilted = world(vessel, {"camera": {"height": 0.5}}, attitude=lambda t, x, y, heading: (0.1, 0.0))
    alpha = math.atan(-0.1 * math.sin(0.1))
    np.testing.assert_allclose(tilted.sense()["a"].bearing, [-math.cos(alpha), -math.sin(alpha)], rtol=0,
                               atol=1e-15)
    level = world(vessel, {"camera": {"height": 0.5}})
    np.testing.assert_allclose(level.sense()["a"].bearing, [-1.0, 0.0], rtol=0, atol=1e-15)
    # A 3 deg compass bias, bearings referred to the compass: the bearing turns by 3 deg.
    biased = world(vessel, {"camera": {"heading_reference": "odometry"},
                            "odometry": {"kind": "water_log_compass", "compass_biases_deg": {"a": 3.0}}})
    np.testing.assert_allclose(biased.sense()["a"].bearing, [-math.cos(3 * DEG), -math.sin(3 * DEG)], rtol=0,
                               atol=1e-15)


# --- seeds, presets, the paper's world untouched ---------------------------------------------------------------

FLEET = [{"id": "1", "position": (-6.0, -7.0)}, {"id": "2", "position": (6.0, 6.0)},
         {"id": "3", "position": (-10.0, 3.0)}, {"id": "4", "position": (-5.0, 6.0), "join_time": 1.0}]
PAPER_NOISE = {"range_noise": {"kind": "gmm", "outlier_fraction": 0.2, "variance": 0.4, "outlier_variance": 10.0},
               "bearing_variance": 1e-4, "displacement_variance": 1e-6, "heading_variance": 1e-4}
WALK = {"kind": "random_walk", "position": (1.0, 1.0), "velocity": (0.5, 0.0), "process_noise": 0.01}


def trace(sensors, seed, steps=40, attitude=None):
    """Every reading and the truth over a run of the four-vessel fleet with the paper's noise."""
    data = {"vessels": FLEET, "target": WALK, **PAPER_NOISE}
    if sensors is not None:
        data["sensors"] = sensors
    w = World(WorldConfig.model_validate(data), np.random.default_rng(seed), attitude=attitude)
    rows = []
    for k in range(steps):
        for vessel, reading in sorted(w.sense().items()):
            rows.append((vessel, reading.odometry.position.tolist(), reading.odometry.heading,
                         sorted(reading.ranges.items()), None if reading.bearing is None else reading.bearing.tolist()))
        truth = w.truth()
        rows.append((truth.target_position.tolist(), sorted((v, p.tolist()) for v, p in truth.positions.items())))
        w.step({v: Command(1.0, 0.2 * math.sin(0.1 * k + int(v))) for v in w.live()})
    return rows, w._rng.bit_generator.state


def test_the_default_world_is_bit_for_bit_the_world_with_the_new_models_off():
    default = trace(None, 5)
    for off in ({}, "paper", {"preset": "paper"}, {"odometry": {"kind": "paper"}, "uwb": None, "camera": None}):
        assert trace(off, 5) == default
    # The paper's world takes nothing more from the generator (a wrong draw would show in every reading).
    assert trace(None, 6) != default


def test_the_new_models_draw_from_their_own_stream_and_leave_the_worlds_draws_as_they_were():
    paper_rows, paper_state = trace(None, 5)
    rows, state = trace("realistic", 5, attitude=lambda t, x, y, heading: (0.05 * math.sin(t), 0.03))
    assert state == paper_state        # the same number of world draws: the target's walk is the same too
    assert [r[0] for r in rows if len(r) == 2] == [r[0] for r in paper_rows if len(r) == 2]
    assert rows != paper_rows


def test_the_realistic_models_are_reproducible_from_the_seed():
    attitude = lambda t, x, y, heading: (0.05 * math.sin(t + x), 0.03 * math.cos(t))   # noqa: E731
    for preset in ("realistic", "realistic_dvl"):
        first = trace(preset, 9, attitude=attitude)
        assert trace(preset, 9, attitude=attitude) == first
        assert trace(preset, 10, attitude=attitude) != first


def test_drawn_biases_differ_between_vessels_and_a_given_one_leaves_the_others_alone():
    model = {"kind": "water_log_compass", "compass_bias_std_deg": 1.0, "scale_error_std": 0.02}
    drawn = world(TWO, {"odometry": model}, seed=4)
    states = {v: drawn._vessels[v].odometry_state for v in ("a", "b")}
    assert states["a"].bias != states["b"].bias and states["a"].scale != states["b"].scale
    named = world(TWO, {"odometry": {**model, "compass_biases_deg": {"a": 0.5}}}, seed=4)
    assert named._vessels["a"].odometry_state.bias == pytest.approx(0.5 * DEG, abs=1e-15)
    assert named._vessels["b"].odometry_state == states["b"]


def test_a_scenario_names_the_realistic_preset_and_may_change_one_field():
    base = {"vessels": FLEET, "target": WALK}
    named = Scenario.model_validate({"world": {**base, "sensors": "realistic"}})
    assert named.world.sensors.odometry.kind == "water_log_compass"
    assert named.world.sensors.odometry.compass_bias_std_deg == 1.0
    assert named.world.sensors.uwb.dropout is not None and named.world.sensors.camera.height == 0.5
    changed = Scenario.model_validate({"world": {**base, "sensors": {"preset": "realistic",
                                                                     "odometry": {"dead_band": 0.1}}}})
    assert changed.world.sensors.odometry.dead_band == 0.1
    assert changed.world.sensors.odometry.compass_bias_std_deg == 1.0
    assert Scenario.model_validate({"world": base}).world.sensors.is_paper


@pytest.mark.parametrize("sensors, words", [
    ("stormy", "unknown sensors preset 'stormy'"),
    ({"odometry": {"kind": "sextant"}}, "odometry"),
    ({"odometry": {"kind": "water_log_compass", "dead_band": -0.1}}, "dead_band"),
    ({"odometry": {"kind": "water_log_compass", "compass_biases_deg": {"z": 1.0}}}, "unknown vessels ['z']"),
    ({"odometry": {"kind": "paper", "dead_band": 0.1}}, "unknown key"),
    ({"uwb": {"dropout": {"floor": 0.5, "ceiling": 0.1, "midpoint": 10.0, "width": 1.0}}}, "grows with range"),
    ({"uwb": {"outlier": {"floor": 0.0, "ceiling": 1.5, "midpoint": 10.0, "width": 1.0}}}, "ceiling"),
    ({"uwb": {"antenna": (0.0, float("nan"), 0.0)}}, "antenna"),
    ({"camera": {"heading_reference": "gps"}}, "heading_reference"),
    ({"odometry": {"kind": "dvl_gyro", "gyro": {"angle_random_walk_deg_rt_h": -1.0}}}, "angle_random_walk"),
])
def test_bad_sensor_configs_are_refused_in_one_line(sensors, words):
    data = {"vessels": TWO, "target": STILL_TARGET, "sensors": sensors}
    with pytest.raises(ConfigError) as error:
        parse_mapping(WorldConfig, data, "scenario.yaml")
    assert words in str(error.value) and "\n" not in str(error.value)


def test_the_sea_mode_refuses_the_uwb_and_camera_models_it_does_not_apply():
    data = {"vessels": TWO, "target": STILL_TARGET, "sea": {}, "sensors": "realistic"}
    with pytest.raises(ConfigError, match="sea mode's measurements lack the uwb and camera models"):
        parse_mapping(WorldConfig, data, "scenario.yaml")
    data["sensors"] = {"odometry": {"kind": "water_log_compass", "compass_bias_std_deg": 1.0}}
    assert parse_mapping(WorldConfig, data, "scenario.yaml").sensors.odometry.kind == "water_log_compass"


# --- over Zenoh ------------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_the_realistic_sensors_over_zenoh_in_lockstep_equal_the_in_process_runner(tmp_path):
    """The sim bridge publishes what the world reads (biased odometry, ranges between antennas with some
    dropped, turned bearings), and the agents' commands match the runner's tick for tick."""
    from test_lockstep import assert_same_motion, logged

    from sim_bridge.fleet import launch
    from sim_bridge.scenario import select_scenario, with_duration

    path = with_duration(Path(__file__).resolve().parents[1] / "configs" / "scenarios" / "table2_estimators.yaml",
                         tmp_path, 10.0)
    data = yaml.safe_load(path.read_text())
    # Dropouts often enough to be seen in 10 s (about one range in six at these 5-15 m).
    data["base"]["world"]["sensors"] = {"preset": "realistic", "uwb": {"dropout": {"floor": 0.15}}}
    path.write_text(yaml.safe_dump(data))
    _, scenario = select_scenario(path, "raw_range")
    trace = run_scenario(scenario)
    folder = launch(path, "raw_range", tmp_path / "runs", seed=None)
    log = logged(folder, trace.vessels)
    stamps = sorted(log["truth"])
    assert len(stamps) == len(trace.time) == 101
    assert_same_motion(log, trace, stamps)
    # And the agent's tick inputs held fewer ranges than peers at times: the dropouts went over the wire.
    received = [len(message["ranges"]) for topic, _, message in read_messages(folder / "agent-1.mcap")
                if topic == "/1/inputs"]
    assert len(received) == 101 and min(received) < 3 and max(received) == 3
    assert (folder / "metrics.json").exists() and (folder / "ranges.png").exists()   # the analysis took them
