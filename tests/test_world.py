"""The world model: kinematics (1), sensors (5)-(9), targets (3)-(4), islands, fleet changes, determinism.

Every expected value is worked out here from the definitions (hand values, closed forms, or an independent
computation from the true state), never read back from the code under test.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.integrate import quad

from agent.angles import wrap_angle
from agent.core.records import Command
from sim_bridge.geometry import (
    is_simple_polygon,
    point_in_polygon,
    sample_boundary,
    segment_intersects_polygon,
    segments_intersect,
)
from sim_bridge.targets import RandomWalkSpec, SinusoidSpec, make_target
from sim_bridge.world import World, WorldConfig, message_lost

REPO = Path(__file__).resolve().parents[1]

STILL_TARGET = {"kind": "constant_velocity", "position": (0.0, 0.0), "velocity": (0.0, 0.0)}
QUIET = {  # every sensor exact
    "range_noise": {"kind": "gaussian", "variance": 0.0},
    "bearing_variance": 0.0,
    "displacement_variance": 0.0,
    "heading_variance": 0.0,
}
SQUARE = [(-2.0, -2.0), (2.0, -2.0), (2.0, 2.0), (-2.0, 2.0)]


def make_config(vessels, target=STILL_TARGET, **changes) -> WorldConfig:
    data = {"vessels": vessels, "target": target, **QUIET}
    data.update(changes)
    return WorldConfig.model_validate(data)


def make_world(vessels, target=STILL_TARGET, seed=0, **changes) -> World:
    return World(make_config(vessels, target, **changes), np.random.default_rng(seed))


# --- kinematics (1) and command handling ---------------------------------------------------------------

def test_kinematics_one_step_against_hand_values():
    world = make_world([{"id": "a", "position": (1.0, 2.0), "heading": math.pi / 6}])
    world.step({"a": Command(surge=2.0, yaw_rate=0.5)})
    truth = world.truth()
    # p += [cos 30deg, sin 30deg] * 2 m/s * 0.1 s = (0.2 * sqrt(3)/2, 0.1); theta += 0.5 * 0.1.
    np.testing.assert_allclose(truth.positions["a"], [1.0 + 0.1 * math.sqrt(3), 2.1], rtol=0, atol=1e-15)
    assert truth.headings["a"] == pytest.approx(math.pi / 6 + 0.05, abs=1e-15)
    np.testing.assert_allclose(truth.velocities["a"], [math.sqrt(3), 1.0], rtol=0, atol=1e-15)
    assert (world.time, world.tick) == (pytest.approx(0.1), 1)
    # The second step moves along the heading reached after the first, then the heading crosses nothing.
    world.step({"a": Command(surge=-1.0, yaw_rate=0.0)})
    theta = math.pi / 6 + 0.05
    expected = [1.0 + 0.1 * math.sqrt(3) - 0.1 * math.cos(theta), 2.1 - 0.1 * math.sin(theta)]
    np.testing.assert_allclose(world.truth().positions["a"], expected, rtol=0, atol=1e-15)


def test_heading_wraps_across_the_seam():
    world = make_world([{"id": "a", "position": (0.0, 0.0), "heading": 3.1}])
    world.step({"a": Command(0.0, 1.0)})   # 3.1 + 0.1 = 3.2 > pi
    assert world.truth().headings["a"] == pytest.approx(3.2 - 2 * math.pi, abs=1e-12)


def test_commands_are_clipped_to_the_physical_bounds():
    vessels = [{"id": "fast", "position": (0.0, 0.0)}, {"id": "back", "position": (0.0, 10.0)}]
    world = make_world(vessels, max_speed=2.0, max_yaw_rate=0.5)
    world.step({"fast": Command(100.0, 10.0), "back": Command(-100.0, -10.0)})
    truth = world.truth()
    np.testing.assert_allclose(truth.positions["fast"], [0.2, 0.0], atol=1e-15)      # 2 m/s * 0.1 s
    np.testing.assert_allclose(truth.positions["back"], [-0.2, 10.0], atol=1e-15)
    assert truth.headings["fast"] == pytest.approx(0.05) and truth.headings["back"] == pytest.approx(-0.05)
    assert world.bad_commands == 0


def test_missing_or_non_finite_command_stops_the_vessel_and_is_counted():
    ids = ["missing", "nan", "inf", "good"]
    world = make_world([{"id": i, "position": (10.0 * k, 0.0)} for k, i in enumerate(ids)])
    commands = {"nan": Command(math.nan, 0.1), "inf": Command(1.0, math.inf), "good": Command(1.0, 0.0)}
    for _ in range(2):
        world.step(commands)
    truth = world.truth()
    for k, i in enumerate(ids[:3]):
        np.testing.assert_array_equal(truth.positions[i], [10.0 * k, 0.0])
        assert truth.headings[i] == 0.0
        np.testing.assert_array_equal(truth.velocities[i], [0.0, 0.0])
    np.testing.assert_allclose(truth.positions["good"], [30.2, 0.0], atol=1e-12)
    assert world.bad_commands == 6   # three bad vessels, two steps


# --- sensors (5), (6), (9) -------------------------------------------------------------------------------

def test_noise_free_world_reports_the_true_geometry():
    vessels = [
        {"id": "a", "position": (-6.0, -7.0), "heading": 0.3},
        {"id": "b", "position": (6.0, 6.0), "heading": -2.0},
        {"id": "c", "position": (-10.0, 3.0), "heading": 2.5},
    ]
    target = {"kind": "constant_velocity", "position": (1.0, 1.0), "velocity": (0.5, 0.0)}
    world = make_world(vessels, target)
    start = {i: np.array(p["position"]) for i, p in zip("abc", vessels)}
    command_rng = np.random.default_rng(3)
    for _ in range(60):
        world.step({i: Command(*command_rng.uniform([0, -0.5], [2, 0.5])) for i in "abc"})
        truth = world.truth()
        readings = world.sense()
        for i in "abc":
            reading = readings[i]
            for j in "abc":
                if j != i:
                    distance = math.dist(truth.positions[i], truth.positions[j])
                    assert reading.ranges[j] == pytest.approx(distance, abs=1e-12)
            offset = truth.positions[i] - truth.target_position
            np.testing.assert_allclose(reading.bearing, offset / np.hypot(*offset), atol=1e-15)
            assert not reading.occluded
            # Odometry: the sum of the true displacements is the displacement from the start.
            np.testing.assert_allclose(reading.odometry.position, truth.positions[i] - start[i], atol=1e-12)
            assert reading.odometry.heading == truth.headings[i]
            assert reading.odometry.stamp == world.time
    assert world.time == pytest.approx(6.0)


def test_odometry_error_grows_like_a_random_walk():
    # After N steps the error of each axis is a sum of N draws of N(0, q): mean 0, variance N q.
    q, steps, fleet, worlds = 0.01, 25, 50, 18
    errors = []
    for seed in range(worlds):
        vessels = [{"id": f"v{k}", "position": (k, 0.0), "heading": 0.1 * k} for k in range(fleet)]
        world = make_world(vessels, seed=seed, displacement_variance=q)
        start = world.truth().positions
        for _ in range(steps):
            world.step({f"v{k}": Command(1.0, 0.2) for k in range(fleet)})
        truth, readings = world.truth(), world.sense()
        for i in truth.positions:
            errors.append(readings[i].odometry.position - (truth.positions[i] - start[i]))
    errors = np.concatenate(errors)        # one sample per axis per vessel: 1800 in all
    n, variance = len(errors), steps * q
    # 5 standard errors: sd of the mean sqrt(var / n); sd of the sample variance var sqrt(2 / n) (normal).
    assert abs(errors.mean()) < 5 * math.sqrt(variance / n)
    assert abs(errors.var() - variance) < 5 * variance * math.sqrt(2 / n)


def test_heading_noise_is_fresh_each_reading_and_sense_does_not_redraw():
    world = make_world([{"id": "a", "position": (0.0, 0.0)}], heading_variance=0.01, seed=5)
    errors = []
    for _ in range(2000):
        first = world.sense()["a"]
        assert world.sense()["a"] is first     # a second call in the same tick draws nothing new
        errors.append(wrap_angle(first.odometry.heading - world.truth().headings["a"]))
        world.step({"a": Command(0.0, 0.3)})
    errors = np.array(errors)
    assert abs(errors.var() - 0.01) < 5 * 0.01 * math.sqrt(2 / len(errors))


def test_negative_ranges_are_clipped_and_a_vessel_on_the_target_has_no_bearing():
    vessels = [{"id": "a", "position": (0.0, 0.0)}, {"id": "b", "position": (0.01, 0.0)}]
    world = make_world(vessels, range_noise={"kind": "gaussian", "variance": 1.0})
    ranges = []
    for _ in range(300):
        readings = world.sense()
        ranges += [readings["a"].ranges["b"], readings["b"].ranges["a"]]
        assert readings["a"].bearing is None and not readings["a"].occluded    # a sits on the target
        assert readings["b"].bearing is not None
        world.step({})
    ranges = np.array(ranges)
    assert ranges.min() == 0.0 and 0.4 < np.mean(ranges == 0.0) < 0.6    # about half the draws are < 0
    # The two directions of a pair are independent draws.
    assert not np.array_equal(ranges[0::2], ranges[1::2])


def test_bearing_is_a_unit_vector_whose_angle_noise_has_the_configured_variance():
    vessels = [{"id": "a", "position": (3.0, 4.0)}]
    world = make_world(vessels, bearing_variance=1e-4, seed=9)
    samples = []
    for _ in range(2000):
        samples.append(world.sense()["a"].bearing)
        world.step({})
    samples = np.array(samples)
    np.testing.assert_allclose(np.hypot(*samples.T), 1.0, rtol=0, atol=1e-12)   # a direction, as the camera says
    # (9) adds N(0, s2 I) to the true unit vector; after normalising, the angle error is the tangential part,
    # atan2(n_t, 1 + n_r) ~ n_t: zero mean and variance s2 (to a relative O(s2) = 1e-4).
    errors = np.arctan2(samples[:, 1], samples[:, 0]) - math.atan2(0.8, 0.6)
    assert abs(errors.mean()) < 5 * math.sqrt(1e-4 / errors.size)
    assert abs(errors.var() / 1e-4 - 1.0) < 5 * math.sqrt(2 / errors.size)


# --- islands: line of sight and sonar ----------------------------------------------------------------------

def test_an_island_between_vessel_and_target_blocks_the_bearing_until_the_vessel_moves_aside():
    # Target at (10, 0), vessel at (-10, y) going north at 4 m/s. The line to the target clears the square's
    # corner (2, 2) when 0.4 y > 2, i.e. y > 5: blocked at y = 4.8 (tick 12), visible at y = 5.2 (tick 13).
    target = {"kind": "constant_velocity", "position": (10.0, 0.0), "velocity": (0.0, 0.0)}
    world = make_world([{"id": "a", "position": (-10.0, 0.0), "heading": math.pi / 2}], target, islands=[SQUARE])
    seen = []
    for _ in range(16):
        reading = world.sense()["a"]
        assert reading.occluded == (reading.bearing is None)
        seen.append(reading.occluded)
        world.step({"a": Command(4.0, 0.0)})
    assert seen == [True] * 13 + [False] * 3


def test_sight_is_blocked_from_inside_an_island_and_clear_beside_it():
    assert segment_intersects_polygon((0.5, 0.5), (0.6, 0.6), SQUARE)        # wholly inside
    assert segment_intersects_polygon((0.0, 0.0), (5.0, 0.0), SQUARE)        # leaves through an edge
    assert segment_intersects_polygon((-3.0, 2.0), (3.0, 2.0), SQUARE)       # runs along an edge
    assert not segment_intersects_polygon((-3.0, 2.5), (3.0, 2.5), SQUARE)
    assert segment_intersects_polygon((2.0, 0.0), (5.0, 0.0), SQUARE)        # starts on an edge
    assert segment_intersects_polygon((5.0, 0.0), (2.0, 0.0), SQUARE)        # ends on an edge
    assert segment_intersects_polygon((0.0, 4.0), (4.0, 0.0), SQUARE)        # grazes the corner (2, 2)
    assert not segment_intersects_polygon((0.0, 4.1), (4.1, 0.0), SQUARE)
    # A concave island (a U): a segment through the notch misses it, one across the arms does not.
    u_shape = [(0, 0), (3, 0), (3, 3), (2, 3), (2, 1), (1, 1), (1, 3), (0, 3)]
    assert not segment_intersects_polygon((1.5, 4.0), (1.5, 1.5), u_shape)
    assert segment_intersects_polygon((-1.0, 2.0), (4.0, 2.0), u_shape)
    assert point_in_polygon((0.5, 2.0), u_shape) and not point_in_polygon((1.5, 2.0), u_shape)
    assert not point_in_polygon((0.0, 1.0), u_shape)                          # on the boundary
    # Rays through vertices: the diamond's corners (1, 0) and (-1, 0) lie on the ray y = 0.
    diamond = [(0, -1), (1, 0), (0, 1), (-1, 0)]
    assert point_in_polygon((-0.5, 0.0), diamond) and point_in_polygon((0.9, 0.0), diamond)
    assert not point_in_polygon((-1.5, 0.0), diamond) and not point_in_polygon((1.5, 0.0), diamond)
    # A T junction: one segment ends on the other, in either order of the ends.
    for stem in [((2.0, 0.0), (2.0, 3.0)), ((2.0, 3.0), (2.0, 0.0))]:
        assert segments_intersect((0.0, 0.0), (4.0, 0.0), *stem)
        assert segments_intersect(*stem, (0.0, 0.0), (4.0, 0.0))
    assert not segments_intersect((0.0, 0.0), (4.0, 0.0), (2.0, 0.1), (2.0, 3.0))


def test_sonar_reports_nearby_island_points_relative_to_the_vessel():
    island = [(10.0, 0.0), (14.0, 0.0), (14.0, 4.0), (10.0, 4.0)]
    world = make_world([{"id": "a", "position": (8.0, 2.0)}, {"id": "far", "position": (-50.0, 0.0)}],
                       islands=[island], sonar_range=3.0, sonar_spacing=0.25)
    readings = world.sense()
    assert readings["far"].obstacle_points.shape == (0, 2)
    # Every boundary point of the 4 m square, 0.25 m apart, written out edge by edge.
    steps = np.arange(16) * 0.25
    boundary = np.concatenate([
        np.column_stack([10 + steps, np.zeros(16)]), np.column_stack([np.full(16, 14.0), steps]),
        np.column_stack([14 - steps, np.full(16, 4.0)]), np.column_stack([np.full(16, 10.0), 4 - steps]),
    ])
    relative = boundary - [8.0, 2.0]
    expected = {tuple(np.round(p, 9)) for p in relative if np.hypot(*p) <= 3.0}
    got = {tuple(np.round(p, 9)) for p in readings["a"].obstacle_points}
    assert got == expected and len(expected) == 17     # the near edge x = 10, y = 0 .. 4
    assert np.all(np.hypot(*readings["a"].obstacle_points.T) <= 3.0)


def test_boundary_sampling_spacing():
    points = sample_boundary([(0, 0), (4, 0), (4, 4), (0, 4)], 0.25)
    assert len(points) == 64
    gaps = np.hypot(*np.diff(np.vstack([points, points[:1]]), axis=0).T)
    np.testing.assert_allclose(gaps, 0.25, atol=1e-12)
    # An edge that is not a whole number of spacings: points every 0.25 m, then a shorter last gap.
    edge = sample_boundary([(0, 0), (1.1, 0), (0, 1.1)], 0.25)[:5]
    np.testing.assert_allclose(edge[:, 0], [0, 0.25, 0.5, 0.75, 1.0], atol=1e-12)
    # A repeated vertex (a zero-length edge) adds nothing and no NaN.
    assert np.array_equal(sample_boundary([(0, 0), (4, 0), (4, 0), (4, 4), (0, 4)], 0.25), points)


# --- targets --------------------------------------------------------------------------------------------

def test_constant_velocity_target_is_exact():
    target = {"kind": "constant_velocity", "position": (1.0, 1.0), "velocity": (0.5, -0.25)}
    world = make_world([{"id": "a", "position": (5.0, 5.0)}], target)
    for _ in range(100):
        world.step({})
    truth = world.truth()
    np.testing.assert_allclose(truth.target_position, [1.0 + 0.5 * 10, 1.0 - 0.25 * 10], atol=1e-12)
    np.testing.assert_array_equal(truth.target_velocity, [0.5, -0.25])


def test_sinusoid_target_keeps_its_speed_and_its_path():
    amplitude, wavelength, direction, speed, dt = 3.0, 20.0, 0.7, 0.5, 0.1
    spec = SinusoidSpec(position=(1.0, -2.0), speed=speed, amplitude=amplitude, wavelength=wavelength,
                        direction=direction)
    target = make_target(spec)
    c, s = math.cos(direction), math.sin(direction)
    points = [target.position.copy()]
    for _ in range(2000):   # 100 m of path, about four wavelengths
        np.testing.assert_allclose(np.hypot(*target.velocity), speed, rtol=1e-12)
        target.step(dt, np.random.default_rng(0))
        points.append(target.position.copy())
    points = np.array(points)
    steps = np.hypot(*np.diff(points, axis=0).T)
    np.testing.assert_allclose(steps, speed * dt, rtol=0, atol=1e-9)
    # Back into the path's frame: x' along `direction`, y' to its left.
    local = points - [1.0, -2.0]
    along, lateral = local @ [c, s], local @ [-s, c]
    # Each point is put on the curve exactly; only rounding of ~100 m coordinates (~1e-14 m) is left.
    np.testing.assert_allclose(lateral, amplitude * np.sin(2 * math.pi * along / wavelength), atol=1e-9)
    assert np.all(np.diff(along) > 0) and along[-1] > 3 * wavelength
    # The path length (quadrature of sqrt(1 + y'^2)) matches the distance travelled: the chords fall short
    # of the arc by kappa^2 h^3 / 24 per step, under 1e-7 m here, so 2000 steps lose well under 1e-3 m.
    slope = lambda x: amplitude * 2 * math.pi / wavelength * math.cos(2 * math.pi * x / wavelength)
    arc, _ = quad(lambda x: math.hypot(1.0, slope(x)), 0.0, along[-1], limit=200)
    assert arc == pytest.approx(2000 * speed * dt, abs=1e-3)


def test_random_walk_target_follows_the_double_integrator_and_respects_its_speed_bound():
    # Without noise (3)-(4) reduce to constant velocity.
    quiet = make_target(RandomWalkSpec(position=(0.0, 0.0), velocity=(0.3, 0.4), process_noise=0.0))
    for _ in range(50):
        quiet.step(0.1, np.random.default_rng(1))
    np.testing.assert_allclose(quiet.position, [1.5, 2.0], atol=1e-12)
    # (3)-(4) with noise: the position moves by dt times the previous velocity plus its own noise, which
    # is independent of the velocity noise (a scheme using the new velocity would correlate them by dt).
    q = 0.01
    free = make_target(RandomWalkSpec(position=(0.0, 0.0), process_noise=q, max_speed=1e6))
    rng = np.random.default_rng(4)
    position_noise, velocity_noise = [], []
    for _ in range(4000):
        before_p, before_v = free.position, free.velocity
        free.step(0.1, rng)
        position_noise.append(free.position - before_p - 0.1 * before_v)
        velocity_noise.append(free.velocity - before_v)
    position_noise, velocity_noise = np.ravel(position_noise), np.ravel(velocity_noise)
    n = position_noise.size
    for noise in (position_noise, velocity_noise):
        assert abs(noise.var() - q) < 5 * q * math.sqrt(2 / n)
    # The sample correlation of independent normals has sd 1 / sqrt(n) (0.011 here; dt would give 0.1).
    assert abs(np.corrcoef(position_noise, velocity_noise)[0, 1]) < 5 / math.sqrt(n)
    # With strong noise the bound must act: the speed reaches it and never passes it.
    noisy = make_target(RandomWalkSpec(position=(0.0, 0.0), process_noise=0.01, max_speed=0.5))
    rng = np.random.default_rng(2)
    speeds = []
    for _ in range(3000):
        noisy.step(0.1, rng)
        speeds.append(np.hypot(*noisy.velocity))
    speeds = np.array(speeds)
    assert speeds.max() <= 0.5 + 1e-12
    assert np.mean(np.isclose(speeds, 0.5, rtol=0, atol=1e-12)) > 0.1


# --- joining and leaving ----------------------------------------------------------------------------------

def test_vessels_join_and_leave_at_the_right_tick():
    vessels = [
        {"id": "a", "position": (0.0, 0.0)},
        {"id": "new", "position": (5.0, 5.0), "heading": 1.0, "join_time": 0.35},
        {"id": "gone", "position": (-5.0, 0.0), "leave_time": 0.5},
    ]
    world = make_world(vessels)
    live = [world.live()]
    for _ in range(7):
        readings = world.sense()
        assert sorted(readings) == sorted(world.live())
        assert sorted(readings["a"].ranges) == sorted(set(world.live()) - {"a"})
        world.step({i: Command(1.0, 0.1) for i in world.live()})
        live.append(world.live())
    # dt = 0.1: "new" appears at the first tick at or after 0.35 s (tick 4), "gone" leaves at tick 5.
    assert live == [["a", "gone"]] * 4 + [["a", "new", "gone"]] + [["a", "new"]] * 3


def test_a_joiner_starts_with_zero_odometry_at_its_spawn_point():
    vessels = [{"id": "a", "position": (0.0, 0.0)},
               {"id": "new", "position": (5.0, 5.0), "heading": 1.0, "join_time": 0.9}]
    # dt = 0.3: 3 * 0.3 = 0.8999999999999999 < 0.9, so only the tolerance lets it join at tick 3.
    world = make_world(vessels, dt=0.3)
    for _ in range(3):
        world.step({"a": Command(1.0, 0.0), "new": Command(1.0, 0.0)})
    assert world.live() == ["a", "new"] and world.tick == 3
    reading = world.sense()["new"]
    np.testing.assert_array_equal(reading.odometry.position, [0.0, 0.0])
    assert reading.odometry.stamp == world.time and reading.odometry.heading == 1.0
    np.testing.assert_array_equal(world.truth().positions["new"], [5.0, 5.0])
    np.testing.assert_array_equal(world.truth().velocities["new"], [0.0, 0.0])
    world.step({"a": Command(1.0, 0.0), "new": Command(2.0, 0.0)})
    np.testing.assert_allclose(world.sense()["new"].odometry.position,
                               [0.6 * math.cos(1.0), 0.6 * math.sin(1.0)], atol=1e-15)


# --- determinism ---------------------------------------------------------------------------------------------

def _busy_config() -> WorldConfig:
    return WorldConfig.model_validate({
        "vessels": [
            {"id": "a", "position": (-6.0, -7.0)}, {"id": "b", "position": (6.0, 6.0)},
            {"id": "c", "position": (-10.0, 3.0), "leave_time": 12.0},
            {"id": "d", "position": (-5.0, 6.0), "join_time": 5.0},
        ],
        "target": {"kind": "random_walk", "position": (1.0, 1.0), "velocity": (0.3, 0.0)},
        "islands": [SQUARE],
        "heading_variance": 1e-3,
    })


def _run(seed: int, steps: int = 200, look: bool = True) -> list:
    world = World(_busy_config(), np.random.default_rng(seed))
    commands = np.random.default_rng(99)
    history = []
    for _ in range(steps):
        if look:
            history.append((world.sense(), world.truth()))
        world.step({i: Command(*commands.uniform([-1, -1], [3, 1])) for i in "abcd"})
    history.append((world.sense(), world.truth()))
    return history


def _flatten(history: list) -> list[float]:
    numbers = []
    for readings, truth in history:
        for i, r in readings.items():
            numbers += [*r.odometry.position, r.odometry.heading, r.odometry.stamp, *r.ranges.values(),
                        *(r.bearing if r.bearing is not None else [math.inf]), *r.obstacle_points.ravel(),
                        float(r.occluded)]
        numbers += [truth.time, *truth.target_position, *truth.target_velocity]
        for i in truth.positions:
            numbers += [*truth.positions[i], truth.headings[i], *truth.velocities[i]]
    return numbers


def test_same_seed_gives_the_same_run_and_another_seed_does_not():
    first, second = _flatten(_run(7)), _flatten(_run(7))
    assert first == second                                    # bit for bit, not approximately
    assert len(first) > 5000
    assert _flatten(_run(8)) != first
    # Looking at the world (or not) draws nothing: the last tick is the same either way.
    assert _flatten(_run(7, look=False)) == _flatten(_run(7)[-1:])


# --- message loss ----------------------------------------------------------------------------------------

def test_message_loss_is_deterministic_and_has_the_right_rate():
    draws = 20_000
    p = 0.05
    lost = [message_lost(42, "a", "b", tick, p) for tick in range(draws)]
    assert lost == [message_lost(42, "a", "b", tick, p) for tick in range(draws)]
    # Binomial: mean n p, sd sqrt(n p (1 - p)); 5 sd.
    assert abs(sum(lost) - draws * p) < 5 * math.sqrt(draws * p * (1 - p))
    reverse = [message_lost(42, "b", "a", tick, p) for tick in range(draws)]
    assert abs(sum(a and b for a, b in zip(lost, reverse)) - draws * p * p) < 5 * math.sqrt(draws * p * p)
    assert not any(message_lost(seed, "a", "b", tick, 0.0) for seed in range(20) for tick in range(1000))
    assert all(message_lost(3, "a", "b", tick, 1.0) for tick in range(1000))
    with pytest.raises(ValueError):
        message_lost(1, "a", "b", 0, 1.5)


@pytest.mark.slow
def test_message_loss_is_the_same_in_another_process():
    code = ("from sim_bridge.world import message_lost; "
            "print(''.join('1' if message_lost(5, 'usv1', 'usv2', t, 0.3) else '0' for t in range(300)))")
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    other = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                           check=True).stdout.strip()
    here = "".join("1" if message_lost(5, "usv1", "usv2", t, 0.3) else "0" for t in range(300))
    assert other == here and "1" in here and "0" in here


# --- angles ------------------------------------------------------------------------------------------------

def test_wrap_angle_on_the_seam():
    assert wrap_angle(math.pi) == math.pi
    assert wrap_angle(-math.pi) == math.pi
    assert wrap_angle(3 * math.pi) == pytest.approx(math.pi) and wrap_angle(3 * math.pi) > 0
    just_past = wrap_angle(np.nextafter(math.pi, 4.0))
    assert -math.pi < just_past < -math.pi + 1e-15
    assert wrap_angle(np.nextafter(-math.pi, 0.0)) == np.nextafter(-math.pi, 0.0)
    assert wrap_angle(0.01) == 0.01 and isinstance(wrap_angle(0.01), float)   # in range: untouched
    assert wrap_angle(7.0) == pytest.approx(7.0 - 2 * math.pi)
    assert wrap_angle(-7.0) == pytest.approx(-7.0 + 2 * math.pi)
    angles = np.array([math.pi, -math.pi, 4.0, -4.0, 0.0, 100.0])
    wrapped = wrap_angle(angles)
    assert isinstance(wrapped, np.ndarray) and wrapped.shape == angles.shape
    assert np.all((wrapped > -math.pi) & (wrapped <= math.pi))
    np.testing.assert_allclose(np.cos(wrapped), np.cos(angles), atol=1e-12)
    np.testing.assert_allclose(np.sin(wrapped), np.sin(angles), atol=1e-12)
    # Far from zero, subtracting whole turns rounds; angles a few ulps either side of every seam out to
    # 1e6 rad must still land in (-pi, pi] (many land just outside before the final correction).
    seams = (2 * np.arange(-160_000, 160_000) + 1) * math.pi
    near = np.concatenate([seams, np.nextafter(seams, np.inf), np.nextafter(seams, -np.inf)])
    wrapped = wrap_angle(near)
    assert np.all((wrapped > -math.pi) & (wrapped <= math.pi))
    assert np.all(np.abs(np.abs(wrapped) - math.pi) < 1e-9)
    # Around 1e12 rad the rounding can fall on the other side too (just below -pi before the correction).
    seams = (2 * (np.arange(-100_000, 100_000) * 10_000_000 + 3) + 1) * math.pi
    wrapped = wrap_angle(np.concatenate([seams, np.nextafter(seams, np.inf), np.nextafter(seams, -np.inf)]))
    assert np.all((wrapped > -math.pi) & (wrapped <= math.pi))


# --- configuration -----------------------------------------------------------------------------------------

ONE_VESSEL = [{"id": "a", "position": (0.0, 0.0)}]


@pytest.mark.parametrize("changes, words", [
    ({"islands": [[(0, 0), (1, 0)]]}, "islands.0"),
    ({"islands": [[(0, 0), (1, 1), (1, 0), (0, 1)]]}, "simple polygon"),          # a bow tie
    ({"islands": [[(0, 0), (2, 2), (2, 0), (0, 1)]]}, "simple polygon"),          # lopsided: non-zero area
    ({"islands": [[(0, 0), (0, 1), (2, 0), (2, 2)]]}, "simple polygon"),          # edges 1 and 3 cross
    ({"islands": [[(0, 0), (3, 0), (1, 0), (2, 2)]]}, "simple polygon"),          # an edge folds back
    ({"islands": [SQUARE, [(0, 0), (1, 0), (1, 0), (0, 1)]]}, "island 1"),      # repeated vertex
    ({"packet_loss": 1.0}, "packet_loss"),
    ({"vessels": [{"id": "a", "position": (0, 0)}, {"id": "a", "position": (1, 1)}]}, "unique"),
    ({"vessels": [{"id": "a", "position": (0, 0), "join_time": 5.0, "leave_time": 2.0}]}, "leave_time"),
    ({"vessels": []}, "vessels"),
    ({"vessels": [{"id": "", "position": (0, 0)}]}, "id"),
    ({"dt": 0.0}, "dt"),
    ({"bearing_variance": -1.0}, "bearing_variance"),
    ({"target": {"kind": "sinusoid", "position": (0, 0), "speed": 0.5, "amplitude": 1.0,
                 "wavelength": 0.0}}, "wavelength"),
    ({"target": {"kind": "teleport", "position": (0, 0)}}, "kind"),
    ({"sonar_rnage": 5.0}, "sonar_rnage"),
])
def test_bad_configuration_is_refused(changes, words):
    data = {"vessels": ONE_VESSEL, "target": STILL_TARGET, **changes}
    with pytest.raises(ValidationError) as caught:
        WorldConfig.model_validate(data)
    assert words in str(caught.value)


def test_defaults_are_the_papers():
    config = WorldConfig(vessels=ONE_VESSEL, target=STILL_TARGET)
    assert config.range_noise.kind == "gmm" and config.range_noise.total_variance == pytest.approx(2.32)
    assert (config.dt, config.bearing_variance, config.displacement_variance) == (0.1, 1e-4, 1e-6)
    assert config.max_yaw_rate == pytest.approx(math.pi / 3 + math.pi / 30)
    assert is_simple_polygon(SQUARE) and not is_simple_polygon([(0, 0), (1, 0), (2, 0)])
    assert is_simple_polygon([(0, 0), (3, 0), (3, 3), (2, 3), (2, 1), (1, 1), (1, 3), (0, 3)])   # concave
    assert is_simple_polygon([(0, 0), (1, 0), (2, 0), (2, 2)])                  # straight through a vertex
