"""The PLKF with the wind's leeway as two more states (agent/core/estimators/plkf_leeway.py): the transition
against hand-worked values, what a circle lets the bearings see of w, the fused marginal taken back, the
snapshot, bad input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import orjson
import pytest

import lab.harness.runner as runner
from agent.core.build import InitialEstimates, initial_state
from agent.core.estimators.plkf import PLKF
from agent.core.estimators.plkf_leeway import (
    LeewayPLKF,
    condition_on_marginal,
    leeway_predict,
    leeway_projection,
    leeway_transition,
    marginal_map,
)
from agent.core.params import AgentParams, TargetEstimationParams
from agent.core.records import OdometryReading, TickInputs
from agent.core.snapshot import state_from_json, state_to_json
from agent.core.step import step
from sim_bridge.scenario import select_scenario

SEA_STATES = Path(__file__).resolve().parents[1] / "configs" / "scenarios" / "sea_states.yaml"
OMEGA = math.pi / 30
DT = 0.1


def test_the_projection_is_the_port_side_twice():
    # n(0) = (0, 1): the sway of (0.3, 0.2) is 0.2 along y; n(pi/2) = (-1, 0): 0.3 along x.
    np.testing.assert_allclose(leeway_projection(0.0) @ [0.3, 0.2], [0.0, 0.2], atol=1e-15)
    np.testing.assert_allclose(leeway_projection(math.pi / 2) @ [0.3, 0.2], [0.3, 0.0], atol=1e-15)


def test_a_heading_change_moves_the_sway_from_one_axis_to_the_other():
    # From psi = 0 to pi/2: dN = N(pi/2) - N(0) = diag(1, -1). x = [p (1, 2); v (0.5, -0.5); w (0.3, 0.1)],
    # dv = (0.2, 0): v' = (0.5 + 0.2 + 0.3, -0.5 - 0.1) = (1.0, -0.6), p' = p + 0.1 v' = (1.1, 1.94), w' = w.
    F = leeway_transition(DT, 0.0, math.pi / 2)
    x = np.array([1.0, 2.0, 0.5, -0.5, 0.3, 0.1])
    x_next, P_next = leeway_predict(x, np.eye(6), F, DT, np.zeros((6, 6)), np.array([0.2, 0.0]))
    np.testing.assert_allclose(x_next, [1.1, 1.94, 1.0, -0.6, 0.3, 0.1], atol=1e-12)
    # P = I: row 0 of F is [1, 0, dt, 0, dt, 0], row 2 [0, 0, 1, 0, 1, 0].
    assert P_next[0, 0] == pytest.approx(1.0 + 2 * DT**2)
    assert P_next[2, 2] == pytest.approx(2.0)
    assert P_next[0, 2] == pytest.approx(2 * DT)
    assert P_next[4, 4] == pytest.approx(1.0)


def test_without_a_heading_change_the_position_and_velocity_are_the_plkf_s():
    """w is then a spectator: the [p; v] the filter shows are the PLKF's, through predictions and bearings."""
    params = TargetEstimationParams(leeway_variance=0.04)
    start, covariance = np.array([6.0, -2.0, 0.3, 0.1]), np.diag([4.0, 4.0, 1.0, 1.0])
    plain, leeway = PLKF(params, start, covariance), LeewayPLKF(params, start, covariance, heading=0.7)
    rng = np.random.default_rng(3)
    for _ in range(50):
        dv = rng.normal(0.0, 0.05, 2)
        plain.predict(dv)
        leeway.predict(dv, 0.7)
        angle = math.atan2(plain.state[1], plain.state[0]) + rng.normal(0.0, 0.01)
        bearing = np.array([math.cos(angle), math.sin(angle)])
        plain.update(bearing)
        leeway.update(bearing)
    np.testing.assert_allclose(leeway.state, plain.state, atol=1e-12)
    np.testing.assert_allclose(leeway._P[:4, :4], plain.covariance, atol=1e-12)
    np.testing.assert_allclose(leeway.leeway, [0.0, 0.0], atol=1e-15)
    # What it shows is v - N w, whose covariance adds N W N^T, W = 0.04 I plus 50 steps of Q = 1e-6 I.
    N = leeway_projection(0.7)
    shown = plain.covariance.copy()
    shown[2:, 2:] += N @ ((0.04 + 50 * 1e-6) * np.eye(2)) @ N.T
    np.testing.assert_allclose(leeway.covariance, shown, atol=1e-12)


def _perturbation_on_circle(centre: tuple[float, float], dw: np.ndarray, du: np.ndarray, dp0: np.ndarray,
                            laps: float = 1.0) -> float:
    """max_k |G(b_k) dp_k|: the part of the position change the bearings see, for a change (dp0, du, dw) of
    the start carried by the kernel's transition along a circle of 10 m about `centre` (target at 0),
    heading tangent (counter-clockwise: the port side faces the centre)."""
    steps = int(round(laps * 2 * math.pi / OMEGA / DT))
    headings = [OMEGA * k * DT + math.pi / 2 for k in range(steps + 1)]
    dx = np.concatenate([dp0, leeway_projection(headings[0]) @ dw + du, dw])
    seen = 0.0
    for k in range(1, steps + 1):
        dx = leeway_transition(DT, headings[k - 1], headings[k]) @ dx
        theta = OMEGA * k * DT
        p = np.array(centre) + 10.0 * np.array([math.cos(theta), math.sin(theta)])
        b = p / np.linalg.norm(p)
        seen = max(seen, abs(b[0] * dx[1] - b[1] * dx[0]))
    return seen


def test_on_a_circle_about_the_target_the_bearings_cannot_see_the_leeway():
    """By hand, continuous time, theta = omega t, e(theta) the radial unit: N(psi) dw = (dw . e) e. For
    dw = (a, 0), du = -dw / 2 the position moves by int (a cos^2 theta, a sin theta cos theta) - (a/2, 0) dt
    = (a / (2 omega)) sin theta e(theta), radial; for dw = (0, a), du = (0, -a/2), dp0 = (-a / (2 omega), 0)
    by -(a / (2 omega)) cos theta e(theta). A radial change keeps every bearing: the kernel's discrete
    transition gives it to O(a dt), against O(a / omega) = 1.4 m off the centre."""
    a = 0.3
    for dw, du, dp0 in (((a, 0.0), (-a / 2, 0.0), (0.0, 0.0)),
                        ((0.0, a), (0.0, -a / 2), (-a / (2 * OMEGA), 0.0))):
        dw, du, dp0 = np.array(dw), np.array(du), np.array(dp0)
        assert _perturbation_on_circle((0.0, 0.0), dw, du, dp0) < 2 * a * DT
        assert _perturbation_on_circle((0.0, 6.0), dw, du, dp0) > 0.5


def _circle_filter(centre: tuple[float, float], w: np.ndarray, seconds: float = 120.0) -> LeewayPLKF:
    """The filter along a circle of 10 m about `centre` (target at 0, still, no current) with exact bearings;
    the odometry is the water-referenced velocity, the ground velocity less N(psi) w."""
    params = TargetEstimationParams(leeway_variance=0.04, bearing_variance=1e-6)

    def ground(k: int) -> np.ndarray:
        return np.array(centre) + 10.0 * np.array([math.cos(OMEGA * k * DT), math.sin(OMEGA * k * DT)])

    headings = [OMEGA * k * DT + math.pi / 2 for k in range(int(seconds / DT))]
    f = LeewayPLKF(params, np.concatenate([ground(0) + [1.0, -1.0], [0.0, 0.0]]),
                   np.diag([4.0, 4.0, 1.0, 1.0]), dt=DT, heading=headings[0])
    previous = np.zeros(2)
    for k in range(1, len(headings)):
        water = (ground(k) - ground(k - 1)) / DT - leeway_projection(headings[k]) @ w
        f.predict(water - previous, headings[k])
        previous = water
        f.update(ground(k) / np.linalg.norm(ground(k)))
    return f


def test_off_the_centre_the_circle_shows_the_leeway_and_about_it_not():
    w = np.array([0.34, 0.0])          # the Otter's leeway beam-on at 8 m/s (docs/sea.md, (f))
    off = _circle_filter((0.0, 6.0), w)
    assert np.max(np.linalg.eigvalsh(off.leeway_covariance)) < 0.1 * 0.04
    np.testing.assert_allclose(off.leeway, w, atol=0.05)
    about = _circle_filter((0.0, 0.0), w)
    # The unobservable combination keeps at least half its start's variance in some direction.
    assert np.max(np.linalg.eigvalsh(about.leeway_covariance)) > 0.5 * 0.04


def test_a_fused_marginal_reaches_w_through_the_cross_covariance():
    # Heading 0: N = diag(0, 1), so y's v_x is v_x itself. Cov(v_x, w_x) = 0.5, Var 1 each. The fused v_x is 1
    # higher with variance 0.5: w_x' = 0 + 0.5 / 1 * 1 = 0.5, Var(w_x') = 1 - 0.25 + 0.25 * 0.5 = 0.875.
    P = np.eye(6)
    P[2, 4] = P[4, 2] = 0.5
    x = np.zeros(6)
    T = marginal_map(0.0)
    S = T @ P @ T.T
    y = T @ x + np.array([0.0, 0.0, 1.0, 0.0])
    P_y = S.copy()
    P_y[2, 2] = 0.5
    x_post, P_post = condition_on_marginal(x, P, T, y, P_y)
    assert x_post[4] == pytest.approx(0.5)
    assert P_post[4, 4] == pytest.approx(0.875)
    np.testing.assert_allclose(T @ x_post, y, atol=1e-12)
    np.testing.assert_allclose(T @ P_post @ T.T, P_y, atol=1e-12)


def test_the_filter_takes_a_fused_marginal_back_exactly_and_stays_positive_definite():
    rng = np.random.default_rng(11)
    params = TargetEstimationParams(leeway_variance=0.04)
    for _ in range(50):
        root = rng.normal(size=(6, 6))
        heading = float(rng.uniform(-3, 3))
        f = LeewayPLKF(params, np.zeros(6), root @ root.T + 0.1 * np.eye(6), heading=heading)
        root4 = rng.normal(size=(4, 4))
        fused, fused_covariance = rng.normal(size=4), root4 @ root4.T + 0.01 * np.eye(4)
        assert f.assimilate(fused, fused_covariance)
        np.testing.assert_allclose(f.state, fused, atol=1e-9)
        np.testing.assert_allclose(f.covariance, fused_covariance, atol=1e-9)
        assert np.min(np.linalg.eigvalsh(f._P)) > -1e-9


def test_bad_input_is_refused_and_counted():
    f = LeewayPLKF(TargetEstimationParams(leeway_variance=0.04), np.array([5.0, 0.0, 0.0, 0.0]), heading=0.0)
    assert not f.assimilate(np.array([np.nan, 0, 0, 0]), np.eye(4))
    assert not f.assimilate(np.zeros(4), -np.eye(4))
    assert not f.predict(np.array([np.inf, 0.0]), 0.1)
    assert not f.predict(np.zeros(2), math.nan)
    assert f.heading == pytest.approx(0.1) and f.rejected == 4
    assert np.isfinite(f.state).all() and np.isfinite(f.covariance).all()


def test_two_leeway_models_at_once_are_refused():
    with pytest.raises(ValueError, match="choose one"):
        AgentParams.model_validate({"target": {"leeway_variance": 0.04},
                                    "control": {"leeway_time_constant": 10.0}})


@pytest.mark.slow
def test_a_wind_fleet_with_the_leeway_model_round_trips_through_a_snapshot_bit_for_bit(monkeypatch):
    _, scenario = select_scenario(SEA_STATES, "wind")
    agent = scenario.agent.model_copy(update={"target": scenario.agent.target.model_copy(
        update={"leeway_variance": 0.04, "leeway_odometry": True})})
    scenario = scenario.model_copy(update={"duration": 8.0, "agent": agent})
    original = runner.run(scenario, 1)
    trips = []

    def step_with_a_round_trip(params, state, inputs):
        if abs(inputs.time - 4.0) < 1e-9:
            assert isinstance(state.tracker, LeewayPLKF) and np.any(state.motion.drift != 0.0)
            trips.append(state.vessel)
            state = state_from_json(orjson.loads(orjson.dumps(state_to_json(state),
                                                              option=orjson.OPT_SERIALIZE_NUMPY)), params)
        return step(params, state, inputs)

    monkeypatch.setattr(runner, "step", step_with_a_round_trip)
    again = runner.run(scenario, 1)
    for name in ("commands", "estimates", "relative", "positions"):
        np.testing.assert_array_equal(getattr(again, name), getattr(original, name), err_msg=name)
    assert sorted(trips) == ["1", "2", "3", "4"]


def test_a_tick_steers_against_the_leeway_and_shares_the_odometry_with_it():
    params = AgentParams.model_validate({"target": {"leeway_variance": 0.04, "leeway_odometry": True}})
    state = initial_state("1", params, InitialEstimates(target=(5.0, 0.0, 0.0, 0.0)))
    east = np.array([1.0, 0.0])
    state, _ = step(params, state, TickInputs(time=0.0, odometry=OdometryReading(0.0, np.zeros(2), 0.0),
                                              bearing=east))
    assert isinstance(state.tracker, LeewayPLKF)
    state.tracker._x[4:6] = (0.3, 0.2)
    state, output = step(params, state, TickInputs(time=0.1, odometry=OdometryReading(0.1, 0.1 * east, 0.0),
                                                   bearing=east))
    # The interval's leeway at psi = 0 is N(0) w = (0, 0.2): 0.02 m over the 0.1 s, added to the shared
    # odometry and the pair filters' history; the target filter's own odometry stays raw.
    np.testing.assert_allclose(output.share.odometry.position, [0.1, 0.02], atol=1e-15)
    assert state.own.get(state.own.latest()) == pytest.approx((0.1, 0.02))
    np.testing.assert_array_equal(state.motion.position, [0.1, 0.0])
    # The command asks for the velocity less the sway w . n(psi) n(psi) of the w after this tick's update.
    record = output.record
    assert not record.saturated["formation"]
    w = state.tracker.leeway
    n = np.array([0.0, 1.0])
    wanted = record.formation_velocity + record.tracking_velocity + record.avoidance_velocity
    np.testing.assert_allclose(record.velocity_command, wanted - (w @ n) * n, atol=1e-12)
    assert abs(w @ n) > 0.1
