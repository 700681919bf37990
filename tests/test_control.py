"""Control, Sec. IV: oscillator (28), formation controller (27)-(33), avoidance (34), command (31)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.angles import wrap_angle
from agent.core.build import InitialEstimates, initial_state
from agent.core.control.avoidance import avoidance_velocity, safety_filter
from agent.core.control.formation import desired_offset, desired_velocity, saturate, surge_and_yaw_rate
from agent.core.control.oscillator import coupling_gains, oscillator_step
from agent.core.params import AgentParams
from agent.core.records import OdometryReading, Share, TickInputs
from agent.core.step import step

DT, OMEGA = 0.1, math.pi / 30


def spacing_error(phases) -> float:
    """Largest deviation of the gaps between sorted phases from 2 pi / n."""
    a = np.sort(np.mod(np.asarray(phases), 2 * math.pi))
    gaps = np.diff(np.append(a, a[0] + 2 * math.pi))
    return float(np.max(np.abs(gaps - 2 * math.pi / len(a))))


def run_oscillators(phases, seconds, gain=1.0):
    phases = list(phases)
    for _ in range(int(round(seconds / DT))):
        phases = [oscillator_step(p, phases[:i] + phases[i + 1:], OMEGA, DT, gain) for i, p in enumerate(phases)]
    return phases


def test_coupling_gains_cover_harmonics_up_to_half_the_fleet():
    assert coupling_gains(2, 1.5) == [1.5, 0.0]
    assert coupling_gains(5, 1.0) == [1.0, 1.0, 0.0, 0.0, 0.0]
    assert coupling_gains(12, 2.0) == [2.0] * 6 + [0.0] * 6


@pytest.mark.parametrize("n", range(2, 13))
def test_oscillator_reaches_uniform_spacing_from_random_phases(n):
    rng = np.random.default_rng(n)
    for _ in range(3):
        phases = run_oscillators(rng.uniform(-math.pi, math.pi, n), 60.0)
        assert spacing_error(phases) < 1e-3


def test_oscillator_respaces_after_a_leave_and_a_join():
    rng = np.random.default_rng(0)
    phases = run_oscillators(rng.uniform(-math.pi, math.pi, 5), 60.0)
    assert spacing_error(phases) < 1e-3
    phases = run_oscillators(phases[:3] + phases[4:], 60.0)          # vessel 4 leaves
    assert len(phases) == 4 and spacing_error(phases) < 1e-3
    phases = run_oscillators(phases + [phases[0] + 0.05], 60.0)       # a newcomer right next to vessel 1
    assert len(phases) == 5 and spacing_error(phases) < 1e-3


def test_oscillator_without_neighbours_turns_at_the_desired_rate():
    assert oscillator_step(0.3, [], OMEGA, DT, 1.0) == pytest.approx(0.3 + OMEGA * DT)


def test_desired_offset_and_velocity_hand_values():
    np.testing.assert_allclose(desired_offset(5.0, math.pi / 2), [0.0, 5.0], atol=1e-12)
    # (29): chord between two points of the circle over dt.
    v = desired_velocity(5.0, 0.0, 0.1, 0.1)
    np.testing.assert_allclose(v, [(5 * math.cos(0.1) - 5) / 0.1, 5 * math.sin(0.1) / 0.1], atol=1e-12)


@given(x=st.floats(-1e6, 1e6), y=st.floats(-1e6, 1e6), bound=st.floats(1e-6, 1e3))
def test_saturation_bounds_the_norm_and_keeps_the_direction(x, y, bound):
    u = np.array([x, y])
    s = saturate(bound, u)
    assert np.hypot(*s) <= bound * (1 + 1e-12) or np.allclose(s, u)
    if np.hypot(x, y) > 0:
        assert u[0] * s[1] - u[1] * s[0] == pytest.approx(0.0, abs=1e-9 * max(1.0, np.hypot(x, y)))
        assert np.dot(u, s) >= 0


@pytest.mark.parametrize("heading, desired, expected_error", [
    (0.0, math.radians(30), math.radians(30)),          # quadrant I
    (0.0, math.radians(150), math.radians(150)),        # quadrant II
    (0.0, math.radians(-150), math.radians(-150)),      # quadrant III (arccos would say +150)
    (0.0, math.radians(-30), math.radians(-30)),        # quadrant IV (arccos would say +30)
    (math.radians(179), math.radians(-179), math.radians(2)),    # across the +-pi seam: turn left 2 deg
    (math.radians(-179), math.radians(179), math.radians(-2)),   # and back: turn right 2 deg
])
def test_heading_correction_keeps_the_sign_in_all_quadrants_and_across_the_seam(heading, desired, expected_error):
    command = np.array([math.cos(desired), math.sin(desired)])
    surge, yaw_rate, _ = surge_and_yaw_rate(command, heading, 0.0, DT, max_correction=100.0, max_speed=5.0)
    assert yaw_rate == pytest.approx(expected_error / DT, abs=1e-9)
    assert surge == pytest.approx(math.cos(desired - heading), abs=1e-12)


def test_correction_saturates_and_adds_the_desired_yaw_rate():
    _, yaw_rate, saturated = surge_and_yaw_rate(np.array([0.0, 1.0]), 0.0, OMEGA, DT, math.pi / 3, 5.0)
    assert saturated and yaw_rate == pytest.approx(math.pi / 3 + OMEGA)


def test_wrap_angle_seam():
    assert wrap_angle(math.pi) == pytest.approx(math.pi)
    assert wrap_angle(-math.pi) == pytest.approx(math.pi)
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    np.testing.assert_allclose(wrap_angle(np.array([-math.pi, 7.0])), [math.pi, 7.0 - 2 * math.pi])


def test_avoidance_hand_value_and_range():
    # One point 1 m east of the vessel, d_s = 3, k1 = 1.7, k2 = 0.5: push west with 1.7 exp(-1 / 9).
    v = avoidance_velocity(np.array([[1.0, 0.0]]), 3.0, 1.7, 0.5)
    np.testing.assert_allclose(v, [-1.7 * math.exp(-1.0 / 9.0), 0.0], atol=1e-12)
    assert np.all(avoidance_velocity(np.array([[3.5, 0.0], [0.0, -4.0]]), 3.0, 1.7, 0.5) == 0.0)
    assert np.all(avoidance_velocity(np.zeros((0, 2)), 3.0, 1.7, 0.5) == 0.0)
    # A point almost on top of the vessel (a denormal distance) still gives a finite push.
    np.testing.assert_allclose(avoidance_velocity(np.array([[0.0, 5e-324]]), 3.0, 1.7, 0.5), [0.0, -1.7])


def test_safety_filter_limits_the_closing_speed_and_leaves_safe_commands_alone():
    point = np.array([[2.0, 0.0]])  # 2 m east: n = (-1, 0), allowed closing speed 1 * (2 - 1) = 1 m/s
    v, acted = safety_filter(np.array([3.0, 0.5]), point, 1.0, 1.0)
    assert acted and v == pytest.approx([1.0, 0.5])        # only the component towards the point is cut
    v, acted = safety_filter(np.array([0.5, 2.0]), point, 1.0, 1.0)
    assert not acted and v == pytest.approx([0.5, 2.0])
    v, acted = safety_filter(np.array([0.0, 0.0]), np.array([[0.5, 0.0]]), 1.0, 1.0)
    assert acted and v == pytest.approx([-0.5, 0.0])        # inside the clearance: back away


# ----- the whole tick: bounds hold whatever it is fed -----

finite = st.floats(-50, 50)


@settings(max_examples=60, deadline=None)
@given(
    heading=st.floats(-math.pi, math.pi), bearing_angle=st.floats(-math.pi, math.pi),
    target=st.tuples(finite, finite, st.floats(-3, 3), st.floats(-3, 3)),
    neighbours=st.lists(st.tuples(finite, finite, st.floats(-math.pi, math.pi), st.floats(-3, 3)),
                        max_size=5),
    obstacles=st.lists(st.tuples(st.floats(-4, 4), st.floats(-4, 4)), max_size=6),
    seconds=st.integers(1, 4),
)
def test_no_saturation_bound_is_ever_exceeded(heading, bearing_angle, target, neighbours, obstacles, seconds):
    params = AgentParams()
    c = params.control
    state = initial_state("1", params, InitialEstimates(target=tuple(target)))
    for k in range(seconds * 10):
        t = k * DT
        shares = {
            f"n{j}": Share(f"n{j}", OdometryReading(t - DT, np.array([x, y]) + 0.1 * k, 0.0),
                           np.array([v, -v]), phase)
            for j, (x, y, phase, v) in enumerate(neighbours)
        } if k > 0 else {}
        ranges = {f"n{j}": float(np.hypot(x, y)) + 1.0 for j, (x, y, _, _) in enumerate(neighbours)}
        state, out = step(params, state, TickInputs(
            time=t, odometry=OdometryReading(t, np.array([0.05 * k, 0.0]), heading), ranges=ranges, shares=shares,
            bearing=np.array([math.cos(bearing_angle), math.sin(bearing_angle)]),
            obstacle_points=np.array(obstacles, dtype=float).reshape(-1, 2),
        ))
        command, record = out.command, out.record
        assert math.isfinite(command.surge) and math.isfinite(command.yaw_rate)
        assert record.health["non_finite_commands"] == 0  # finite because it is right, not because of the guard
        assert abs(command.surge) <= c.max_speed + 1e-12
        assert abs(command.yaw_rate - c.yaw_rate) <= c.max_correction_yaw_rate + 1e-12
        bounded_formation = (record.velocity_command - record.safety_correction - record.tracking_velocity
                             - saturate(c.max_avoidance_speed, record.avoidance_velocity))
        assert np.hypot(*bounded_formation) <= c.max_formation_speed + 1e-9
        assert np.hypot(*saturate(c.max_avoidance_speed, record.avoidance_velocity)) <= c.max_avoidance_speed + 1e-12
        # the target-velocity feedforward is bounded by U_vo inside the tracking term
        assert np.all(np.isfinite(record.tracking_velocity))
