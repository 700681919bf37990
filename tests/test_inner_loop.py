"""The inner loop (boat/inner_loop.py): its step responses on each preset's hull (sim_bridge/hull.py), its limits,
the stale-command stop, and finite output for any input.

Bounds of the step responses (docs/sea.md, "Inner loop"): speed 0 -> 1 m/s from rest: 10-90 % rise <= 1.0 s
(the demand's own ramp at accel_max = 1 m/s^2 takes 0.8 s), overshoot <= 15 %; turn rate 0 -> 0.2 rad/s:
rise <= 0.4 s, overshoot <= 25 % at rest and <= 35 % at 1 m/s (the Munk moment couples the turn to the sway);
every response within 2 % of the command after 10 s.
"""

from __future__ import annotations

import numpy as np
import pytest

from boat import inner_loop
from boat.inner_loop import LoopState
from boat.presets import PRESETS
from lab.experiments.hull import rise_overshoot, step_response


@pytest.mark.parametrize("name", ["otter", "heron", "wamv"])
def test_speed_step_response(name):
    t, u = step_response(name, "speed", 1.0, 0.0)
    assert u.max() >= 0.9, "never reached 90 %"
    rise, overshoot = rise_overshoot(t, u, 1.0)
    assert rise <= 1.0 and overshoot <= 0.15
    assert u[-1] == pytest.approx(1.0, rel=0.02)


@pytest.mark.parametrize("cruise, bound", [(0.0, 0.25), (1.0, 0.35)])
@pytest.mark.parametrize("name", ["otter", "heron", "wamv"])
def test_turn_rate_step_response(name, cruise, bound):
    t, r = step_response(name, "rate", 0.2, cruise)
    assert r.max() >= 0.9 * 0.2, "never reached 90 %"
    rise, overshoot = rise_overshoot(t, r, 0.2)
    assert rise <= 0.4 and overshoot <= bound
    assert r[-1] == pytest.approx(0.2, rel=0.02)


def _loop_step(state, speed, rate, age, u=0.0, r=0.0, name="otter", dt=0.02):
    boat = PRESETS[name]
    n = np.size(speed)
    return inner_loop.step(boat.inner_loop, boat.thrusters, state, np.full(n, speed, dtype=float),
                           np.full(n, rate, dtype=float), age, np.full(n, u), np.full(n, r), dt)


def test_the_demand_ramps_at_the_acceleration_limits_and_is_clipped_to_the_rate_bounds():
    loop = PRESETS["otter"].inner_loop
    state = LoopState.zero(1)
    for k in range(1, 11):
        state, _, _ = _loop_step(state, 2.0, 5.0, 0.0)
        assert state.speed_demand[0] == pytest.approx(k * loop.accel_max * 0.02)
        assert state.rate_demand[0] == pytest.approx(min(k * loop.rate_accel_max * 0.02, loop.rate_max))
    assert state.rate_demand[0] == loop.rate_max     # 0.3 rad/s: the Otter's bound, reached after 8 steps


def test_a_stale_command_gives_zero_thrust_and_resets_the_loop():
    loop = PRESETS["otter"].inner_loop
    state = LoopState.zero(2)
    for _ in range(20):
        state, x, n = _loop_step(state, 1.0, 0.2, 0.0, u=0.3, r=0.05)
    assert (x > 0).all() and (n > 0).all() and (state.speed_integral != 0).all()
    age = np.array([loop.timeout, loop.timeout + 1e-6])      # at the timeout still fresh; beyond it stale
    state, x, n = _loop_step(state, 1.0, 0.2, age, u=0.3, r=0.05)
    assert x[0] > 0 and n[0] > 0
    assert x[1] == 0.0 and n[1] == 0.0
    assert state.speed_integral[1] == 0.0 and state.rate_integral[1] == 0.0
    assert state.speed_demand[1] == 0.3 and state.rate_demand[1] == 0.05   # resumes from the boat's motion
    state, x, n = _loop_step(LoopState.zero(1), 1.0, 0.2, np.nan)   # an unknown age is stale too
    assert x[0] == 0.0 and n[0] == 0.0


def test_any_input_gives_a_finite_output_within_the_thrusters_range():
    rng = np.random.default_rng(11)      # seed 11; also checked with 12
    boat = PRESETS["otter"]
    tr = boat.thrusters
    state = LoopState.zero(400)
    specials = np.array([np.nan, np.inf, -np.inf, 1e308, -1e308, 0.0])
    for _ in range(50):
        pick = lambda: np.where(rng.random(400) < 0.2, rng.choice(specials, 400), rng.standard_cauchy(400) * 10)
        state, x, n = inner_loop.step(boat.inner_loop, tr, state, pick(), pick(), rng.uniform(0, 1, 400),
                                      pick(), pick(), 0.02)
        assert np.isfinite(x).all() and np.isfinite(n).all()
        assert (x <= 2 * tr.max_forward).all() and (x >= -2 * tr.max_reverse).all()
        assert (np.abs(n) <= tr.half_beam * (tr.max_forward + tr.max_reverse) + 1e-9).all()
        for field in (state.speed_integral, state.rate_integral, state.speed_demand, state.rate_demand):
            assert np.isfinite(field).all()
        assert (np.abs(state.speed_integral) <= boat.inner_loop.speed_imax).all()


def test_a_non_finite_command_is_a_stop():
    state, x, n = _loop_step(LoopState.zero(1), np.nan, np.inf, 0.0, u=0.0, r=0.0)
    assert state.speed_demand[0] == 0.0 and state.rate_demand[0] == 0.0 and x[0] == 0.0 and n[0] == 0.0
