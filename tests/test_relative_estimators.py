"""The inter-vessel estimators checked against values worked out independently of their code."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.core.estimators import estimator_names, make_relative_estimator
from agent.core.estimators.akf import sage_husa_scale
from agent.core.estimators.huber_rls import huber_weight
from agent.core.estimators.kf import kf_correct
from agent.core.estimators.mckf import mckf_correct
from agent.core.estimators.pseudolinear import equivalent_noise_variance, pseudo_measurement
from agent.core.estimators.rls import rls_correct
from agent.core.params import RelativeEstimationParams

ALL = sorted(estimator_names())


def circling_pair(steps: int, dt: float = 0.1, radius: float = 5.0, omega: float = math.pi / 30):
    """True relative positions and displacements of two vessels half a turn apart on one circle."""
    phase = omega * dt * np.arange(steps + 1)
    relative = 2 * radius * np.column_stack([np.cos(phase), np.sin(phase)])
    return relative, np.diff(relative, axis=0)


# ---------- the pseudo-linear measurement and R_z ----------

def test_pseudo_measurement_is_the_cosine_law():
    # p_k = (3, 4), delta = (3, 0) so p_{k-1} = (0, 4): r_k = 5, r_{k-1} = 4; delta^T p_k = 9.
    assert pseudo_measurement(4.0, 5.0, 3.0, 0.0) == pytest.approx(9.0, abs=1e-12)


def test_equivalent_noise_variance_hand_value():
    # r_k^2 = 25, r_{k-1}^2 = 16, s2 = 0.5: 0.5 * 41 + 0.25 = 20.75, plus 0.1 * 16 from the displacement.
    assert equivalent_noise_variance(3.0, 4.0, 3.0, 0.0, 0.5, 0.1) == pytest.approx(22.35, abs=1e-12)


def test_equivalent_noise_variance_matches_monte_carlo_of_14():
    """R_z from (14) against the empirical variance of the exact equivalent noise for Gaussian ranges."""
    rng = np.random.default_rng(11)
    p_now, delta, s2 = np.array([6.0, 8.0]), np.array([0.3, -0.2]), 0.04
    p_prev = p_now - delta
    mu = rng.normal(0.0, math.sqrt(s2), size=(2, 400_000))
    r_now, r_prev = np.linalg.norm(p_now) + mu[0], np.linalg.norm(p_prev) + mu[1]
    noise = 0.5 * (r_now**2 - r_prev**2 + delta @ delta) - delta @ p_now
    predicted = equivalent_noise_variance(*p_now, *delta, s2, 0.0)
    standard_error = predicted * math.sqrt(2 / noise.size)
    assert abs(noise.var() - predicted) < 5 * standard_error


# ---------- KF: a hand-worked step ----------

def test_kf_step_hand_value():
    # P = diag(4, 1), delta = (1, 0), R = 4: K = (0.5, 0); innovation 5 - 3 = 2 -> p = (4, 1);
    # Joseph: diag(0.5, 1) diag(4, 1) diag(0.5, 1) + K 4 K^T = diag(1, 1) + diag(1, 0) = diag(2, 1).
    px, py, p11, p12, p22, innovation, s = kf_correct(3.0, 1.0, 4.0, 0.0, 1.0, 1.0, 0.0, 5.0, 4.0)
    assert (px, py) == pytest.approx((4.0, 1.0), abs=1e-12)
    assert (p11, p12, p22) == pytest.approx((2.0, 0.0, 1.0), abs=1e-12)
    assert (innovation, s) == pytest.approx((2.0, 8.0), abs=1e-12)


def test_kf_estimator_step_through_the_interface():
    """One predict + update through the public API against the textbook matrix form."""
    params = RelativeEstimationParams(range_variance=0.3, displacement_variance=1e-4)
    est = make_relative_estimator(params, (6.0, 7.0), np.array([[3.0, 0.5], [0.5, 2.0]]), name="kf")
    est.mark_range_epoch()
    delta = np.array([0.2, -0.1])
    est.predict(delta)
    est.update(9.0, 9.3)
    # Independent matrix-form computation.
    p = np.array([6.0, 7.0]) + delta
    P = np.array([[3.0, 0.5], [0.5, 2.0]]) + 2e-4 * np.eye(2)
    z = 0.5 * (9.3**2 - 9.0**2 + delta @ delta)
    r_now, r_prev = np.linalg.norm(p), np.linalg.norm(p - delta)
    R = 0.3 * (r_now**2 + r_prev**2) + 0.09 + 2e-4 * r_prev**2
    H = delta.reshape(1, 2)
    K = P @ H.T / (H @ P @ H.T + R)
    expected_p = p + (K * (z - H @ p)).ravel()
    expected_P = (np.eye(2) - K @ H) @ P
    np.testing.assert_allclose(est.position, expected_p, atol=1e-12)
    np.testing.assert_allclose(est.covariance, expected_P, atol=1e-12)


# ---------- MCKF ----------

def mckf_matrix_form(p_prior, P_prior, delta, z, R, sigma, tol, lmax):
    """Sec. III-A steps 3-6 written literally with matrices, as an independent reference."""
    Bp = np.linalg.cholesky(P_prior)
    Bz = np.sqrt(R)
    B = np.zeros((3, 3))
    B[:2, :2], B[2, 2] = Bp, Bz
    Binv = np.linalg.inv(B)
    D = Binv @ np.append(p_prior, z)
    W = Binv @ np.vstack([np.eye(2), delta])
    p_prev, iterations = p_prior.copy(), 0
    for s in range(1, lmax + 1):
        iterations = s
        w = D - W @ p_prev
        C = np.exp(-w**2 / (2 * np.asarray(sigma) ** 2))
        P_bar = Bp @ np.diag(1 / C[:2]) @ Bp.T
        R_bar = Bz * (1 / C[2]) * Bz
        K = P_bar @ delta / (delta @ P_bar @ delta + R_bar)
        p_new = p_prior + K * (z - delta @ p_prior)
        done = np.linalg.norm(p_new - p_prev) / np.linalg.norm(p_prev) <= tol
        p_prev = p_new
        if done:
            break
    A = np.eye(2) - np.outer(K, delta)
    return p_prev, A @ P_prior @ A.T + R * np.outer(K, K), iterations


def test_mckf_step_matches_literal_matrix_form():
    p, P = np.array([7.0, -3.0]), np.array([[2.5, 0.7], [0.7, 1.2]])
    delta, z, R = np.array([0.4, 0.3]), 6.5, 3.0
    sigma, tol, lmax = (2.0, 1.5, 0.8), 1e-10, 50
    expected_p, expected_P, expected_iterations = mckf_matrix_form(p, P, delta, z, R, sigma, tol, lmax)
    px, py, p11, p12, p22, iterations, _ = mckf_correct(*p, P[0, 0], P[0, 1], P[1, 1], *delta, z, R,
                                                       *sigma, tol, lmax)
    np.testing.assert_allclose([px, py], expected_p, atol=1e-12)
    np.testing.assert_allclose([[p11, p12], [p12, p22]], expected_P, atol=1e-12)
    assert iterations == expected_iterations > 1


def test_mckf_step_hand_fixed_point():
    """p- = (3, 1), P- = diag(4, 1), delta = (1, 0), z = 5, R = 4, sigma3 = 2, sigma1,2 huge.

    Only x moves: with u = x - 3, the fixed point solves u = 2 c / (c + 1), c = exp(-((2 - u) / 2)^2 / 8),
    since K = 4c / (4c + 4). Solved here by bisection on g(u) = u - 2c/(c+1), which is increasing.
    """
    def g(u):
        c = math.exp(-((2 - u) / 2) ** 2 / 8)
        return u - 2 * c / (c + 1)

    lo, hi = 0.0, 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if g(mid) < 0 else (lo, mid)
    px, py, *_ = mckf_correct(3.0, 1.0, 4.0, 0.0, 1.0, 1.0, 0.0, 5.0, 4.0, 1e8, 1e8, 2.0, 1e-14, 200)
    assert px == pytest.approx(3.0 + lo, abs=1e-9)
    assert py == pytest.approx(1.0, abs=1e-12)
    # The first iterate alone (L_max = 1): c = exp(-1/8), K = c / (c + 1), x = 3 + 2K.
    c = math.exp(-1 / 8)
    px1, *_ , iterations, _ = mckf_correct(3.0, 1.0, 4.0, 0.0, 1.0, 1.0, 0.0, 5.0, 4.0, 1e8, 1e8, 2.0, 1e-14, 1)
    assert px1 == pytest.approx(3.0 + 2 * c / (c + 1), abs=1e-12) and iterations == 1


def test_mckf_ignores_a_gross_outlier():
    # A residual of 1e4 whitened standard deviations: the kernel weight underflows to 0, so the gain is 0.
    px, py, p11, p12, p22, _, weight = mckf_correct(3.0, 1.0, 4.0, 0.0, 1.0, 1.0, 0.0, 2e4, 4.0,
                                                    9999.0, 9999.0, 0.8, 1e-6, 10)
    assert weight == 0.0
    assert (px, py, p11, p12, p22) == (3.0, 1.0, 4.0, 0.0, 1.0)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_mckf_with_huge_bandwidths_equals_kf(seed):
    rng = np.random.default_rng(seed)
    huge = RelativeEstimationParams(estimator={"name": "mckf", "bandwidths": (1e12, 1e12, 1e12)})
    start = rng.normal(0, 10, 2)
    mckf = make_relative_estimator(huge, start, name="mckf")
    kf = make_relative_estimator(huge, start, name="kf")
    truth, displacement = circling_pair(300)
    ranges = np.linalg.norm(truth, axis=1) + rng.normal(0, 0.6, len(truth)) * (rng.random(len(truth)) < 0.9)
    for est in (mckf, kf):
        est.mark_range_epoch()
    for k in range(1, len(truth)):
        for est in (mckf, kf):
            est.predict(displacement[k - 1])
            est.update(abs(ranges[k - 1]), abs(ranges[k]))
        np.testing.assert_allclose(mckf.position, kf.position, rtol=0, atol=1e-9)
        np.testing.assert_allclose(mckf.covariance, kf.covariance, rtol=0, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(
    prior=st.tuples(*[st.floats(-50, 50)] * 2),
    spread=st.floats(1e-3, 100), corr=st.floats(-0.95, 0.95), delta=st.tuples(*[st.floats(-2, 2)] * 2),
    z=st.floats(-1e4, 1e4), r=st.floats(1e-3, 1e3), sigma3=st.floats(0.05, 50),
    lmax=st.integers(1, 12), tol=st.sampled_from([0.0, 1e-300, 1e-12, 1e-6, 1e-2]),
)
def test_mckf_never_exceeds_lmax(prior, spread, corr, delta, z, r, sigma3, lmax, tol):
    p12 = corr * spread
    *_, iterations, weight = mckf_correct(*prior, spread, p12, spread, *delta, z, r, 9999.0, 9999.0,
                                          sigma3, tol, lmax)
    assert 1 <= iterations <= lmax
    assert 0.0 <= weight <= 1.0


# ---------- RLS, Huber-RLS, AKF pieces ----------

def test_rls_step_hand_value():
    # P = 2 I, phi = (1, 1), lambda = 0.5: phi^T P phi = 4, K = (2, 2) / 4.5; innovation 3 - 0 = 3.
    px, py, p11, p12, p22, innovation, _ = rls_correct(0.0, 0.0, 2.0, 0.0, 2.0, 1.0, 1.0, 3.0, 0.5)
    assert (px, py) == pytest.approx((4 / 3, 4 / 3), abs=1e-12)
    # P+ = (P - K phi^T P) / lambda = (2I - (4/4.5) [[1,1],[1,1]]) / 0.5
    assert (p11, p12, p22) == pytest.approx(((2 - 4 / 4.5) * 2, -(4 / 4.5) * 2, (2 - 4 / 4.5) * 2), abs=1e-12)
    assert innovation == 3.0


def test_rls_without_forgetting_on_exact_data_leaves_only_the_prior_error():
    """lambda = 1 and exact ranges: RLS is least squares with a prior, so the final error is exactly
    (P0^-1 + sum delta delta^T)^-1 P0^-1 e0."""
    truth, displacement = circling_pair(200)
    params = RelativeEstimationParams(estimator={"name": "rls", "forgetting_factor": 1.0})
    initial_error = np.array([4.0, -3.0])
    est = make_relative_estimator(params, truth[0] + initial_error, name="rls")
    est.mark_range_epoch()
    ranges = np.linalg.norm(truth, axis=1)
    for k in range(1, len(truth)):
        est.predict(displacement[k - 1])
        est.update(ranges[k - 1], ranges[k])
    prior_information = np.eye(2) / 25.0
    expected = np.linalg.solve(prior_information + displacement.T @ displacement, prior_information @ initial_error)
    np.testing.assert_allclose(est.position - truth[-1], expected, atol=1e-9)


def test_huber_weight_hand_values():
    assert huber_weight(1.0, 1.0, 1.345) == 1.0
    assert huber_weight(-2.69, 1.0, 1.345) == pytest.approx(0.5)
    assert huber_weight(10.0, 2.0, 1.5) == pytest.approx(0.3)


def test_sage_husa_scale_learns_the_true_noise_level():
    """Innovations drawn with variance h + 4 R: the estimated scale on R must approach 4."""
    rng = np.random.default_rng(5)
    h, rz, scale = 2.0, 3.0, 1.0
    for count in range(20_000):
        innovation = rng.normal(0.0, math.sqrt(h + 4.0 * rz))
        scale = sage_husa_scale(scale, count, 0.999, innovation, h, rz, 0.01, 100.0)
    assert scale == pytest.approx(4.0, rel=0.15)
    # First step: d_0 = 1, so the estimate is exactly the raw one (clamped).
    assert sage_husa_scale(1.0, 0, 0.98, 3.0, 1.0, 2.0, 0.01, 100.0) == pytest.approx((9 - 1) / 2)


# ---------- every estimator: the same expectations ----------

@pytest.mark.parametrize("name", ALL)
def test_converges_on_noise_free_ranges(name):
    truth, displacement = circling_pair(600)
    params = RelativeEstimationParams(range_variance=1e-4)
    est = make_relative_estimator(params, truth[0] + np.array([3.0, 2.0]), name=name)
    est.mark_range_epoch()
    ranges = np.linalg.norm(truth, axis=1)
    for k in range(1, len(truth)):
        est.predict(displacement[k - 1])
        assert est.update(ranges[k - 1], ranges[k]).accepted
    assert np.linalg.norm(est.position - truth[-1]) < 0.05


@pytest.mark.parametrize("name", ALL)
@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), outlier=st.floats(0.0, 0.5), scale=st.floats(0.01, 5.0))
def test_covariance_stays_symmetric_positive_definite(name, seed, outlier, scale):
    rng = np.random.default_rng(seed)
    params = RelativeEstimationParams(range_variance=scale)
    est = make_relative_estimator(params, rng.normal(0, 20, 2), name=name)
    est.mark_range_epoch()
    previous = abs(rng.normal(10, 3))
    for _ in range(400):
        est.predict(rng.normal(0, 0.3, 2) * (rng.random() < 0.95))
        now = abs(rng.normal(10, 3) + (rng.normal(0, 30) if rng.random() < outlier else 0.0))
        if est.update(previous, now).accepted:
            previous = now
        P = est.covariance
        assert np.array_equal(P, P.T)
        assert np.all(np.linalg.eigvalsh(P) > 0)
        assert np.all(np.isfinite(est.position))


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, -1.0, 1e9, "5", None, True])
def test_bad_ranges_are_rejected_and_change_nothing(name, bad):
    est = make_relative_estimator(RelativeEstimationParams(), (4.0, 3.0), name=name)
    est.mark_range_epoch()
    est.predict((0.1, 0.0))
    before = (est.position, est.covariance)
    for pair in ((bad, 5.0), (5.0, bad)):
        outcome = est.update(*pair)
        assert not outcome.accepted
        np.testing.assert_array_equal(est.position, before[0])
        np.testing.assert_array_equal(est.covariance, before[1])
    assert est.diagnostics.rejected == 2 and est.diagnostics.updates == 0


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("bad", [(math.nan, 0.0), (0.0, math.inf), (1.0,), "xy", None])
def test_bad_displacements_are_rejected(name, bad):
    est = make_relative_estimator(RelativeEstimationParams(), (4.0, 3.0), name=name)
    assert est.predict(bad) is False
    np.testing.assert_array_equal(est.position, [4.0, 3.0])
    assert est.diagnostics.rejected == 1 and est.diagnostics.predictions == 0


@pytest.mark.parametrize("intervals", [math.nan, -1.0, None, "2"])
def test_bad_interval_lengths_are_rejected(intervals):
    est = make_relative_estimator(RelativeEstimationParams(), (4.0, 3.0), name="mckf")
    assert est.predict((0.1, 0.0), intervals=intervals) is False
    np.testing.assert_array_equal(est.position, [4.0, 3.0])
    assert est.diagnostics.rejected == 1


def test_missed_range_epoch_keeps_the_displacement_of_the_whole_interval():
    """Two predicts between range epochs: the pair uses their sum, so exact data still fits exactly."""
    truth, displacement = circling_pair(3)
    params = RelativeEstimationParams(range_variance=1e-6)
    est = make_relative_estimator(params, truth[0], np.eye(2) * 1e-8, name="kf")
    est.mark_range_epoch()
    est.predict(displacement[0])
    est.predict(displacement[1])  # no range at epoch 1
    outcome = est.update(np.linalg.norm(truth[0]), np.linalg.norm(truth[2]))
    assert outcome.innovation == pytest.approx(0.0, abs=1e-9)


def test_reset_rejects_a_bad_covariance():
    est = make_relative_estimator(RelativeEstimationParams(), (0.0, 0.0), name="mckf")
    with pytest.raises(ValueError):
        est.reset((1.0, 2.0), np.array([[1.0, 2.0], [2.0, 1.0]]))
    est.reset((1.0, 2.0))
    np.testing.assert_array_equal(est.covariance, 25.0 * np.eye(2))


# ---------- consistency: the fact behind docs/estimation.md's analysis of Experiment 1 ----------

def average_nees(noise_kind: str, runs: int = 200, steps: int = 300) -> float:
    """Mean NEES at the last step of a KF on z_k = delta_k^T p_k + n_k with R = 2 r^2 s2 (the white-noise
    R_z of (14) at constant range r), when n_k is white with that variance, or the MA(1) noise
    n_k = a_k - a_{k-1}, a_k = r mu_k, that consecutive range pairs really produce."""
    truth, displacement = circling_pair(steps)
    r, s2 = 10.0, 1e-4
    total = 0.0
    for run in range(runs):
        rng = np.random.default_rng(run)
        a = r * rng.normal(0.0, math.sqrt(s2), steps + 1)
        px, py = truth[0] + rng.normal(0.0, 5.0, 2)
        p11, p12, p22 = 25.0, 0.0, 25.0
        for k in range(1, steps + 1):
            dx, dy = displacement[k - 1]
            px, py = px + dx, py + dy
            n = rng.normal(0.0, math.sqrt(2 * r * r * s2)) if noise_kind == "white" else a[k] - a[k - 1]
            z = dx * truth[k, 0] + dy * truth[k, 1] + n
            px, py, p11, p12, p22, _, _ = kf_correct(px, py, p11, p12, p22, dx, dy, z, 2 * r * r * s2)
        e = np.array([px, py]) - truth[-1]
        total += e @ np.linalg.solve(np.array([[p11, p12], [p12, p22]]), e)
    return total / runs


def test_kf_is_consistent_on_white_noise():
    # NEES ~ chi^2 with 2 dof: mean 2, sd 2; the mean of 200 has sd 0.14, so 4 sd is 0.57.
    assert average_nees("white") == pytest.approx(2.0, abs=0.57)


def test_kf_is_far_too_cautious_on_the_correlated_noise_of_consecutive_range_pairs():
    # The shared range telescopes: the true error is a small fraction of what P claims.
    assert average_nees("ma1") < 0.1
