"""Twin-thruster allocation, saturation with asymmetric reverse thrust, and the first-order lag (boat/thrusters.py),
against hand values from the presets' published thrusts (Otter: 0.5 x 24.4 g N ahead, 0.5 x 13.6 g N astern
per propeller, at +-0.395 m)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from boat import thrusters
from boat.presets import PRESETS

OTTER = PRESETS["otter"].thrusters
G = 9.81
F, R, B = 0.5 * 24.4 * G, 0.5 * 13.6 * G, 0.395


def test_otter_limits_and_reverse_ratio_are_the_published_ones():
    assert (OTTER.max_forward, OTTER.max_reverse, OTTER.half_beam) == pytest.approx((F, R, B))
    assert 2 * OTTER.max_forward == pytest.approx(239.4, abs=0.1)     # bollard pull of the pair
    assert OTTER.max_reverse / OTTER.max_forward == pytest.approx(13.6 / 24.4)   # 0.557: "reverse ~ 55 %"


def test_allocation_inverts_the_force_map_inside_the_limits():
    rng = np.random.default_rng(7)
    port, starboard = rng.uniform(-R, F, 1000), rng.uniform(-R, F, 1000)
    x, n = thrusters.forces(OTTER, port, starboard)
    np.testing.assert_allclose(x, port + starboard)
    np.testing.assert_allclose(n, B * (starboard - port))
    p2, s2, saturated = thrusters.allocate(OTTER, x, n)
    np.testing.assert_allclose(p2, port, atol=1e-9)
    np.testing.assert_allclose(s2, starboard, atol=1e-9)
    assert not saturated.any()


def test_saturation_gives_full_ahead_full_astern_and_keeps_the_turn_first():
    big = np.array([1e4, -1e4, 0.0, 0.0, 200.0])
    turn = np.array([0.0, 0.0, 1e4, -1e4, 50.0])
    port, starboard, saturated = thrusters.allocate(OTTER, big, turn)
    assert saturated.all()
    np.testing.assert_allclose(port[:2], [F, -R])            # straight ahead / astern: both at their limits
    np.testing.assert_allclose(starboard[:2], [F, -R])
    np.testing.assert_allclose([port[2], starboard[2]], [-R, F])   # the largest moment: one ahead, one astern
    np.testing.assert_allclose([port[3], starboard[3]], [F, -R])
    # X = 200 N with N = 50 N m: the turn (h = 50 / 2b = 63.3 N) is kept, the mean gives way: m <= F - |h|.
    h = 50.0 / (2 * B)
    assert starboard[4] - port[4] == pytest.approx(2 * h)
    assert port[4] + starboard[4] == pytest.approx(2 * (F - h))


def test_allocation_stays_within_the_limits_for_any_demand_and_never_gives_a_non_finite_thrust():
    rng = np.random.default_rng(8)    # seed 8; also checked with 9
    x = rng.standard_cauchy(5000) * 300
    n = rng.standard_cauchy(5000) * 100
    x[:50], n[50:100] = np.nan, np.inf
    port, starboard, saturated = thrusters.allocate(OTTER, x, n)
    for t in (port, starboard):
        assert np.isfinite(t).all() and (t <= F + 1e-9).all() and (t >= -R - 1e-9).all()
    assert saturated[:100].all()
    np.testing.assert_array_equal(port[:100], 0.0)
    # Feasible demands are met exactly; infeasible ones keep N whenever |N| <= b (F + R).
    x_out, n_out = thrusters.forces(OTTER, port, starboard)
    ok = ~saturated
    np.testing.assert_allclose(x_out[ok], x[ok], rtol=1e-12, atol=1e-9)
    turnable = saturated & np.isfinite(n) & np.isfinite(x) & (np.abs(n) <= B * (F + R))
    np.testing.assert_allclose(n_out[turnable], n[turnable], rtol=1e-12, atol=1e-9)


def test_first_order_lag_reaches_63_percent_after_one_time_constant_and_its_mean_is_the_integral():
    tc = OTTER.time_constant
    thrust = np.zeros(1)
    for _ in range(10):                       # 10 steps of tc / 10
        thrust = thrusters.lag(OTTER, thrust, np.array([100.0]), tc / 10)
    assert thrust[0] == pytest.approx(100 * (1 - math.exp(-1)), rel=1e-12)
    mean = thrusters.mean_over(OTTER, np.array([20.0]), np.array([100.0]), 0.05)
    t = np.linspace(0.0, 0.05, 200001)
    exact = np.trapezoid(100 + (20 - 100) * np.exp(-t / tc), t) / 0.05
    assert mean[0] == pytest.approx(exact, rel=1e-9)
