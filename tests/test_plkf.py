"""The target tracker (PLKF, Sec. III-B) against independent derivations and its expected behaviour."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.core.estimators.plkf import PLKF, plkf_predict, plkf_update
from agent.core.params import TargetEstimationParams

DT = 0.1


def transition(dt: float) -> np.ndarray:
    """A of (4) as a matrix, the reference the filter's written-out blocks are checked against."""
    a = np.eye(4)
    a[0, 2] = a[1, 3] = dt
    return a


def scalar_form_update(x, P, b, s, min_range):
    """The same update derived by hand in scalar form: with q the unit normal of b, G = q q^T, so (22)
    is the scalar equation q^T p = 0 with variance r^2 s (R_b = s I), and the optimal gain and the
    simple-form covariance follow (25) with an ordinary division in place of the pseudo-inverse."""
    q = np.array([-b[1], b[0]])
    h = np.concatenate([q, [0.0, 0.0]])
    r = max(np.linalg.norm(x[:2]), min_range)
    innovation_variance = h @ P @ h + r * r * s
    K = P @ h / innovation_variance
    return x - K * (h @ x), (np.eye(4) - np.outer(K, h)) @ P


def test_one_step_matches_the_scalar_derivation():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(4, 4))
    P = A @ A.T + 0.5 * np.eye(4)
    x = np.array([4.0, -2.0, 0.3, 0.1])
    b = np.array([0.8, -0.6])
    x_post, P_post, _, _ = plkf_update(x.tolist(), P.tolist(), *b, 1e-3, 0.1)
    x_ref, P_ref = scalar_form_update(x, P, b, 1e-3, 0.1)
    np.testing.assert_allclose(x_post, x_ref, atol=1e-10)
    np.testing.assert_allclose(P_post, P_ref, atol=1e-10)


def test_instrumental_variable_step_matches_the_scalar_derivation():
    """Gain at the predicted bearing b^ = p^/|p^|: with q^ its unit normal, the correction is
    P[:, :2] q^ (q^T G(b~) p^) / (q^T P_pp q^ + r^2 s)."""
    rng = np.random.default_rng(4)
    A = rng.normal(size=(4, 4))
    P = A @ A.T + 0.5 * np.eye(4)
    x = np.array([4.0, -2.0, 0.3, 0.1])
    b = np.array([0.8, -0.6])  # measured, 0.3 rad or so off the prediction
    x_post, P_post, _, _ = plkf_update(x.tolist(), P.tolist(), *b, 1e-3, 0.1, gain_bearing="predicted")
    r = np.linalg.norm(x[:2])
    q_hat = np.array([x[1], -x[0]]) / r
    h = np.concatenate([q_hat, [0.0, 0.0]])
    variance = h @ P @ h + r * r * 1e-3
    innovation = q_hat @ (np.eye(2) - np.outer(b, b)) @ x[:2]
    K = P @ h / variance
    np.testing.assert_allclose(x_post, x - K * innovation, atol=1e-10)
    np.testing.assert_allclose(P_post, (np.eye(4) - np.outer(K, h)) @ P, atol=1e-10)


def joseph_update(x, P, b, s, min_range, u):
    """(25) as matrices: H = [G(u) 0], R_z = r^2 s G G^T, K = P H^T pinv(H P H^T + R_z), the Joseph form."""
    n = len(x)
    G = np.eye(2) - np.outer(u, u)
    H = np.hstack([G, np.zeros((2, n - 2))])
    r = max(np.linalg.norm(x[:2]), min_range)
    Rz = r * r * s * G @ G.T
    K = P @ H.T @ np.linalg.pinv(H @ P @ H.T + Rz)
    I_KH = np.eye(n) - K @ H
    return x - K @ ((np.eye(2) - np.outer(b, b)) @ x[:2]), I_KH @ P @ I_KH.T + K @ Rz @ K.T


@pytest.mark.parametrize("gain_bearing", ["measured", "predicted"])
@pytest.mark.parametrize("n", [4, 6])
def test_update_matches_the_joseph_form_with_a_pseudo_inverse(gain_bearing, n):
    """Random states of 4 and 6 elements (the leeway filter's): the rank-one closed form against the matrices
    of (25) with numpy's pseudo-inverse."""
    rng = np.random.default_rng(20 + n)
    for _ in range(20):
        L = rng.normal(size=(n, n))
        P = L @ L.T + 0.1 * np.eye(n)
        x = rng.normal(scale=5.0, size=n)
        angle = math.atan2(x[1], x[0]) + rng.normal(scale=0.2)
        b = np.array([math.cos(angle), math.sin(angle)])
        u = b if gain_bearing == "measured" else x[:2] / np.linalg.norm(x[:2])
        x_post, P_post, _, _ = plkf_update(x.tolist(), P.tolist(), *b, 1e-3, 0.1, gain_bearing)
        x_ref, P_ref = joseph_update(x, P, b, 1e-3, 0.1, u)
        np.testing.assert_allclose(x_post, x_ref, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(P_post, P_ref, rtol=1e-9, atol=1e-9)
        assert np.array_equal(P_post, np.transpose(P_post))


def range_after_circling(gain_bearing: str, seed: int, seconds: float = 60.0, radius: float = 5.0):
    """A vessel circling a 0.5 m/s target with Table I bearing noise; returns (estimated, true) range."""
    rng = np.random.default_rng(seed)
    relative, own_velocity = circling_scenario(seconds, radius=radius)
    relative = discretised(relative)
    params = TargetEstimationParams(gain_bearing=gain_bearing)
    tracker = PLKF(params, relative[0] + np.array([1.0, 0.5, 0.0, -0.3]), dt=DT)
    for k in range(1, len(relative)):
        tracker.predict(own_velocity[k] - own_velocity[k - 1])
        p = relative[k, :2]
        tracker.update(p / np.linalg.norm(p) + rng.normal(0.0, 0.01, 2))
    return np.linalg.norm(tracker.state[:2]), np.linalg.norm(relative[-1, :2]), tracker.state[:2] - relative[-1, :2]


def test_printed_gain_is_biased_towards_the_target_and_the_instrumental_variable_is_not():
    """Why `gain_bearing` defaults to "predicted": with Table I's bearing noise (R_b = 1e-4 I) the gain
    of (25) as printed drags the range estimate far towards zero, the instrumental-variable gain does not."""
    for seed in range(3):
        estimated, true, _ = range_after_circling("measured", seed)
        assert estimated < 0.5 * true
        _, _, error = range_after_circling("predicted", seed)
        assert np.linalg.norm(error) < 0.3


def test_prediction_step_hand_value():
    x = np.array([1.0, 2.0, 3.0, 4.0])
    x_prior, P_prior = plkf_predict(x, np.eye(4), 0.5, 0.01, np.array([1.0, -1.0]))
    # The velocity change acts over the whole interval: v = (4, 3), p = (1, 2) + 0.5 (4, 3).
    np.testing.assert_allclose(x_prior, [3.0, 3.5, 4.0, 3.0])
    # A I A^T: position variance 1 + dt^2 = 1.25, cross term dt = 0.5, plus Q.
    np.testing.assert_allclose(P_prior[0], [1.26, 0.0, 0.5, 0.0])
    np.testing.assert_allclose(P_prior[2], [0.5, 0.0, 1.01, 0.0])


def test_prediction_step_is_the_matrix_product_of_24():
    """The written-out blocks against A P A^T + Q_o with A of (4) as a matrix, for random covariances."""
    rng = np.random.default_rng(11)
    for _ in range(20):
        L = rng.normal(size=(4, 4))
        P = L @ L.T
        x, dv, dt = rng.normal(size=4), rng.normal(size=2), rng.uniform(0.01, 1.0)
        A = transition(dt)
        x_prior, P_prior = plkf_predict(x, P, dt, 0.02, dv)
        np.testing.assert_allclose(x_prior, A @ (x + np.concatenate([[0.0, 0.0], dv])), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(P_prior, A @ P @ A.T + 0.02 * np.eye(4), rtol=1e-12, atol=1e-12)
        assert np.array_equal(P_prior, P_prior.T)


def test_an_update_that_overflows_is_refused_and_leaves_the_estimate_alone():
    """A state so far out (1e200 m) that r^2 R_b overflows: the update's numbers are not finite, so the bearing
    is refused and counted, and the estimate stays as it was."""
    tracker = PLKF(TargetEstimationParams(), np.array([1e200, -1e200, 0.0, 0.0]), dt=DT)
    before = tracker.state, tracker.covariance
    outcome = tracker.update(np.array([0.6, 0.8]))
    assert not outcome.accepted and outcome.reason == "update produced a non-finite state"
    assert tracker.rejected == 1 and tracker.updates == 0
    assert np.array_equal(tracker.state, before[0]) and np.array_equal(tracker.covariance, before[1])


def circling_scenario(seconds: float, target_velocity=(0.5, 0.0), radius=8.0, omega=math.pi / 30):
    """A vessel circling a constant-velocity target: relative state over time and own velocity changes."""
    steps = int(round(seconds / DT))
    t = DT * np.arange(steps + 1)
    target = np.array([1.0, 1.0]) + np.outer(t, target_velocity)
    own_velocity = radius * omega * np.column_stack([-np.sin(omega * t), np.cos(omega * t)]) + target_velocity
    own = target + radius * np.column_stack([np.cos(omega * t), np.sin(omega * t)])
    relative = np.column_stack([own - target, own_velocity - np.asarray(target_velocity)])
    return relative, own_velocity


def run_tracker(relative, own_velocity, initial_error, bearing_of=None):
    """Feed a PLKF the exact relative motion; propagate with v_io (the vessel's velocity relative to target)."""
    tracker = PLKF(TargetEstimationParams(), relative[0] + initial_error, dt=DT)
    errors = []
    for k in range(1, len(relative)):
        # The vessel's velocity changes at the start of each interval, and it knows by how much.
        tracker.predict(own_velocity[k] - own_velocity[k - 1])
        p_true = relative[k, :2]
        bearing = p_true / np.linalg.norm(p_true) if bearing_of is None else bearing_of(k, p_true)
        tracker.update(bearing)
        errors.append(np.linalg.norm(tracker.state[:2] - p_true))
    return tracker, np.array(errors)


def discretised(relative):
    """Make the relative trajectory obey (4) exactly: v_k is the velocity over the interval that ends at
    step k, so p_k = p_{k-1} + dt v_k."""
    out = relative.copy()
    for k in range(1, len(out)):
        out[k, :2] = out[k - 1, :2] + DT * out[k, 2:]
    return out


def test_noise_free_bearings_with_persistent_excitation_converge_below_a_millimetre():
    relative, own_velocity = circling_scenario(300.0)
    relative = discretised(relative)
    _, errors = run_tracker(relative, own_velocity, np.array([1.5, -1.0, 0.4, -0.3]))
    assert errors[0] > 0.1  # it starts visibly wrong
    assert errors[-1] < 1e-3
    assert np.all(errors[-100:] < 1e-3)


def test_covariance_grows_during_prediction_only_steps():
    tracker = PLKF(TargetEstimationParams(), np.array([5.0, 0.0, 0.0, 0.5]))
    for _ in range(20):  # converge somewhat first
        tracker.predict()
        tracker.update(np.array([1.0, 0.0]))
    previous = np.trace(tracker.covariance)
    for _ in range(30):
        tracker.predict()
        assert not tracker.update(None).accepted
        now = np.trace(tracker.covariance)
        assert now > previous
        previous = now
    assert tracker.skipped == 30


@pytest.mark.parametrize("bad", [np.array([math.nan, 1.0]), np.array([math.inf, 0.0]), np.array([0.0, 0.0]),
                                 np.array([3.0, 4.0]), np.array([1.0, 0.0, 0.0]), "north"])
def test_invalid_bearings_give_a_prediction_only_step(bad):
    tracker = PLKF(TargetEstimationParams(), np.array([5.0, 0.0, 0.0, 0.5]))
    tracker.predict()
    before = tracker.state, tracker.covariance
    if isinstance(bad, str):
        with pytest.raises(ValueError):
            np.asarray(bad, dtype=float)
        bad = np.array([math.nan, math.nan])
    assert not tracker.update(bad).accepted
    np.testing.assert_array_equal(tracker.state, before[0])
    np.testing.assert_array_equal(tracker.covariance, before[1])
    assert tracker.rejected == 1


def test_non_finite_velocity_change_is_refused_and_counted():
    tracker = PLKF(TargetEstimationParams(), np.array([5.0, 0.0, 0.0, 0.5]))
    assert tracker.predict(np.array([math.nan, 0.0])) is False
    assert np.all(np.isfinite(tracker.state)) and tracker.rejected == 1
    np.testing.assert_allclose(tracker.state, [5.0, 0.05, 0.0, 0.5])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), occlusion=st.floats(0.0, 0.8))
def test_covariance_stays_symmetric_positive_definite(seed, occlusion):
    rng = np.random.default_rng(seed)
    tracker = PLKF(TargetEstimationParams(), rng.normal(0, 10, 4))
    for _ in range(300):
        tracker.predict(rng.normal(0, 0.1, 2))
        if rng.random() < occlusion:
            tracker.update(None)
        else:
            angle = rng.uniform(-math.pi, math.pi)
            tracker.update(np.array([math.cos(angle), math.sin(angle)]) + rng.normal(0, 0.01, 2))
        P = tracker.covariance
        assert np.allclose(P, P.T, atol=0, rtol=0)
        assert np.all(np.linalg.eigvalsh(P) > 0)
        assert np.all(np.isfinite(tracker.state))


def _tracked_state(position):
    """A vessel state whose target filter holds `position` (vessel relative to the target... as the PLKF
    stores it: along the bearing), still, with a modest covariance."""
    from agent.core.build import InitialEstimates, initial_state
    from agent.core.params import AgentParams

    params = AgentParams()
    state = initial_state("0", params, InitialEstimates())
    state.tracker = PLKF(params.target, np.array([*position, 0.0, 0.0]), np.eye(4) * 0.01, dt=params.dt)
    return params, state


def test_an_estimate_behind_the_bearing_starts_the_target_filter_again():
    # The pseudo-linear update cannot tell p from -p; an estimate on the wrong side of the vessel is restarted
    # at the range guess along the bearing and counted, not left to converge on the target's reflection.
    from agent.core.target import track_target

    params, state = _tracked_state([-4.0, -3.0])
    bearing = np.array([0.8, 0.6])
    x, _, _ = track_target(params, state, bearing, None)
    assert state.health.target_restarts == 1
    np.testing.assert_allclose(x[:2], bearing * params.target.initial_range_guess)


def test_a_target_filter_started_while_the_vessel_moves_takes_the_target_as_still():
    # x_io is the vessel relative to the target, so a still target gives v_io = v_i - 0 = v_i: the sign the
    # simulation's initial estimates use (sim_bridge/scenario.py). The update cannot move v here: P's
    # position-velocity blocks start at zero, so the gain's velocity rows are zero.
    from agent.core.build import InitialEstimates, initial_state
    from agent.core.params import AgentParams
    from agent.core.target import track_target

    params = AgentParams()
    state = initial_state("0", params, InitialEstimates())
    state.motion.velocity = np.array([1.2, -0.4])
    bearing = np.array([0.6, -0.8])
    x, _, _ = track_target(params, state, bearing, None)
    np.testing.assert_array_equal(x[2:], [1.2, -0.4])
    # and restarted behind the bearing while moving, likewise
    params, state = _tracked_state([-4.0, -3.0])
    state.motion.velocity = np.array([-0.5, 2.0])
    x, _, _ = track_target(params, state, np.array([0.8, 0.6]), None)
    assert state.health.target_restarts == 1
    np.testing.assert_array_equal(x[2:], [-0.5, 2.0])


def test_an_estimate_along_the_bearing_is_not_restarted():
    from agent.core.target import track_target

    params, state = _tracked_state([4.0, 3.0])
    x, _, _ = track_target(params, state, np.array([0.8, 0.6]), None)
    assert state.health.target_restarts == 0
    np.testing.assert_allclose(x[:2], [4.0, 3.0], atol=1e-9)
