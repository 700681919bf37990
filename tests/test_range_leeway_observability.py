"""Can the fleet's ranges see the wind's leeway w (docs/sea.md, "(j) The leeway seen from the ranges")?

Four vessels on the ideal counter-clockwise circle about the target (radius R, rate omega, a quarter turn
apart), the heading along the circle, so each one's leeway N(psi) w = (w . e) e is radial. A speed log does not
see it: the pair i-j's relative position is p_ij(t) = p_ij(0) + (odometry's part) + S_ij(t) w with
S_ij(t) = integral of N(psi_j) - N(psi_i). By hand (e e^T = I/2 + A(2 theta)/2 with A(phi) the reflection
[[cos, sin], [sin, -cos]]), S_ij(t) = (B(2 theta_j) - B(2 theta_i))(t) - (...)(0) over 4 omega, where
B(phi) = [[sin phi, -cos phi], [-cos phi, -sin phi]]: opposite vessels (2 theta apart by 2 pi) see nothing,
adjacent ones (by pi) up to |w| / omega of relative motion, 3.2 m at 0.34 m/s on pi/30 rad/s. But the
formation turns rigidly: the range change u_ij(t) . S_ij(t) w is exactly u_ij(t) . c_ij of a constant c_ij
linear in w, so to first order a leeway looks like an error of the pairs' initial positions and the ranges
tell w only as well as those are known: the information of vessel 1's three ranges (variance sigma^2) with
the unknowns p_1j(0) (prior variance s^2) and w gives var(w) ~ omega^2 s^2 however long it listens.
"""

import math

import numpy as np

from agent.core.estimators.plkf_leeway import leeway_projection

R, OMEGA, N_VESSELS = 10.0, math.pi / 30, 4
RATE, SIGMA2 = 10.0, 0.4           # ranges a second per pair, Table II's inlier variance (m^2)


def phases(t: float) -> np.ndarray:
    return 2 * math.pi * np.arange(N_VESSELS) / N_VESSELS + OMEGA * t


def sensitivity_by_hand(i: int, j: int, t: float) -> np.ndarray:
    def b(phi):
        return np.array([[math.sin(phi), -math.cos(phi)], [-math.cos(phi), -math.sin(phi)]])
    now, then = 2 * phases(t), 2 * phases(0.0)
    return (b(now[j]) - b(now[i]) - b(then[j]) + b(then[i])) / (4 * OMEGA)


def sensitivity_integrated(i: int, j: int, t: float, dt: float = 1e-3) -> np.ndarray:
    total = np.zeros((2, 2))
    for k in range(int(round(t / dt))):
        theta = phases((k + 0.5) * dt)
        heading = theta + math.pi / 2
        total += dt * (leeway_projection(heading[j]) - leeway_projection(heading[i]))
    return total


def line_of_sight(j: int, t: float) -> np.ndarray:
    where = R * np.stack([np.cos(phases(t)), np.sin(phases(t))], axis=1)
    p = where[j] - where[0]
    return p / np.linalg.norm(p)


def leeway_variance(duration: float, position_prior: float = 0.04, w_prior: float = 1.0) -> np.ndarray:
    """w's covariance from vessel 1's ranges to the other three over `duration` s, exact geometry."""
    unknowns = 2 * (N_VESSELS - 1) + 2
    information = np.diag([1 / position_prior] * (unknowns - 2) + [1 / w_prior] * 2)
    for k in range(1, int(duration * RATE) + 1):
        t = k / RATE
        for n, j in enumerate(range(1, N_VESSELS)):
            u = line_of_sight(j, t)
            row = np.zeros(unknowns)
            row[2 * n:2 * n + 2] = u
            row[-2:] = u @ sensitivity_by_hand(0, j, t)
            information += np.outer(row, row) / SIGMA2
    return np.linalg.inv(information)[-2:, -2:]


def test_the_sensitivity_by_hand_is_the_integral_of_the_projections():
    for t in (3.0, 17.5, 40.0):
        for j in (1, 2, 3):
            np.testing.assert_allclose(sensitivity_by_hand(0, j, t), sensitivity_integrated(0, j, t), atol=1e-5)


def test_opposite_vessels_see_no_leeway_and_adjacent_ones_up_to_w_over_omega():
    times = np.linspace(0, 60, 241)
    opposite = max(np.linalg.norm(sensitivity_by_hand(0, 2, t), 2) for t in times)
    adjacent = max(np.linalg.norm(sensitivity_by_hand(0, 1, t), 2) for t in times)
    assert opposite < 1e-12
    # B is a reflection (norm 1): adjacent, S = (B(2 theta_0(0)) - B(2 theta_0(t))) / (2 omega), at most 1/omega.
    assert math.isclose(adjacent, 1 / OMEGA, rel_tol=1e-3)
    assert math.isclose(0.336 * adjacent, 3.21, abs_tol=0.01)


def test_to_first_order_a_leeway_is_an_error_of_the_initial_relative_position():
    # For each adjacent pair there is one constant c with u(t) . S(t) w = u(t) . c at every t: the least
    # squares fit of c over an orbit leaves nothing; c is linear in w (twice w, twice c).
    w = np.random.default_rng(30).normal(size=2) * 0.3
    times = np.linspace(0.0, 60.0, 25)
    for j in (1, 3):
        sights = np.array([line_of_sight(j, t) for t in times])
        changes = np.array([line_of_sight(j, t) @ sensitivity_by_hand(0, j, t) @ w for t in times])
        c, *_ = np.linalg.lstsq(sights, changes, rcond=None)
        np.testing.assert_allclose(sights @ c, changes, atol=1e-12)
        assert np.linalg.norm(c) > 0.3 * np.linalg.norm(w) / OMEGA    # metres of it: not a small effect
        doubled, *_ = np.linalg.lstsq(sights, 2 * changes, rcond=None)
        np.testing.assert_allclose(doubled, 2 * c, atol=1e-9)


def test_the_ranges_tell_w_only_as_well_as_the_initial_positions_are_known():
    # var(w) ~ omega^2 s^2 (with w's own prior 1 (m/s)^2 beside it): within 5 % of 1 / (1 / (omega^2 s^2) + 1)
    # for s^2 from Table II's 0.04 m^2 to 100 m^2, and a second minute of ranges changes it by under 2 %.
    for prior in (0.04, 1.0, 100.0):
        minute = float(np.linalg.eigvalsh(leeway_variance(60.0, prior))[-1])
        expected = 1.0 / (1.0 / (OMEGA**2 * prior) + 1.0)
        assert math.isclose(minute, expected, rel_tol=0.05)
        assert math.isclose(float(np.linalg.eigvalsh(leeway_variance(120.0, prior))[-1]), minute, rel_tol=0.02)
    # What the ranges add quickly is only the initial positions: from 10 s on w's variance stays within a factor
    # two of its limit (Table II's prior: 4.6e-4 (m/s)^2, 0.021 m/s, against w's 0.34 m/s).
    ten, minute = (float(np.linalg.eigvalsh(leeway_variance(d))[-1]) for d in (10.0, 60.0))
    assert minute < ten < 2 * minute and minute < 5e-4
