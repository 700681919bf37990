"""The inner loop between a (u, r) command and the thrusters, after ArduPilot Rover's AR_AttitudeControl.

One step of period dt, for arrays of shape (n,) (one entry per boat):
    speed:  u_d moves towards the command by at most accel_max dt (the command clipped to the speed bounds);
            X = K_ff,u u_d + K_ff,uu |u_d| u_d + K_a,u du_d/dt + K_p,u (u_d - u) + I_u,  I_u += K_i,u (u_d - u) dt
    rate:   r_d moves towards the command by at most rate_accel_max dt (clipped to +-rate_max);
            N = K_ff,r r_d + K_ff,rr |r_d| r_d + K_a,r dr_d/dt + K_p,r e_r + I_r + K_d,r de_r/dt,  e_r = r_d - r
Each integrator is bounded by its imax and frozen while the output is beyond what the thrusters can give in
the error's direction (anti-windup); de_r/dt is low-passed at d_filter Hz. (X, N) are clipped to the pair's
range: X in [-2R, 2F], N in +-b (F + R). The arrays may be plain floats instead (one boat; the same numbers).

A command older than `timeout` (its age not <= timeout: a NaN age is stale too) gives X = N = 0 and resets
the loop: integrators to zero and the demands to the measured (u, r), so that a resumed command ramps from
the boat's motion. A non-finite command is taken as a stop (0, 0) (the caller counts it); a non-finite
measurement as zero. Every output is finite for any input. `step` is pure: it returns a new `LoopState`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from boat.elementwise import bound, clip, every, where
from boat.presets import InnerLoop, Thrusters

MEASURE_BOUND = 1e3   # m/s or rad/s: far beyond any hull's; keeps every product of the loop finite


class LoopState(NamedTuple):
    """The loop's memory between steps (a named tuple: one boat's in plain floats is cheap to make)."""

    speed_demand: np.ndarray    # u_d (m/s)
    rate_demand: np.ndarray     # r_d (rad/s)
    speed_integral: np.ndarray  # I_u (N)
    rate_integral: np.ndarray   # I_r (N m)
    rate_error: np.ndarray      # e_r of the step before (rad/s)
    rate_slope: np.ndarray      # low-passed de_r/dt (rad/s^2)

    @classmethod
    def zero(cls, n: int) -> LoopState:
        return cls(*(np.zeros(n) for _ in range(6)))


def _finite(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """values in [low, high], a non-finite one taken as 0 (np.clip's wrapper costs more than these calls)."""
    values = np.asarray(values, dtype=float)
    if not np.isfinite(values).all():
        values = np.where(np.isfinite(values), values, 0.0)
    return np.minimum(np.maximum(values, low), high)


def commands(loop: InnerLoop, speed_command: np.ndarray, rate_command: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """The command as the loop takes it: clipped to its bounds, a non-finite value taken as 0 (a stop)."""
    return (_finite(speed_command, -loop.max_reverse_speed, loop.max_speed),
            _finite(rate_command, -loop.rate_max, loop.rate_max))


def step(loop: InnerLoop, thrusters: Thrusters, state: LoopState, speed_command: np.ndarray,
         rate_command: np.ndarray, command_age: np.ndarray, u: np.ndarray, r: np.ndarray, dt: float,
         checked: bool = False) -> tuple[LoopState, np.ndarray, np.ndarray]:
    """(state, X, N) after one period dt: the surge force and yaw moment to allocate to the thrusters.
    `checked`: the caller vouches that the command came through `commands` and (u, r) are finite and
    within MEASURE_BOUND (a simulated hull's), so the checks are skipped: the same numbers, fewer calls."""
    if checked:
        target_u, target_r = speed_command, rate_command
    else:
        u, r = _finite(u, -MEASURE_BOUND, MEASURE_BOUND), _finite(r, -MEASURE_BOUND, MEASURE_BOUND)
        target_u, target_r = commands(loop, speed_command, rate_command)
    if type(u) is float and type(command_age) is float:   # one boat in plain floats
        fresh = command_age <= loop.timeout
    else:
        fresh = np.asarray(np.asarray(command_age, dtype=float) <= loop.timeout)

    step_u, step_r = loop.accel_max * dt, loop.rate_accel_max * dt
    u_d = state.speed_demand + clip(target_u - state.speed_demand, step_u)
    r_d = state.rate_demand + clip(target_r - state.rate_demand, step_r)

    x_max, x_min = 2 * thrusters.max_forward, -2 * thrusters.max_reverse
    n_max = thrusters.half_beam * (thrusters.max_forward + thrusters.max_reverse)

    e_u = u_d - u
    x = ((loop.speed_ff + loop.speed_ff_quadratic * abs(u_d)) * u_d + loop.speed_p * e_u + state.speed_integral
         + loop.speed_ff_accel / dt * (u_d - state.speed_demand))
    wind_u = ((x < x_max) | (e_u < 0)) & ((x > x_min) | (e_u > 0))
    i_u = where(wind_u, clip(state.speed_integral + loop.speed_i * e_u * dt, loop.speed_imax),
                state.speed_integral)

    e_r = r_d - r
    alpha = dt / (dt + 1.0 / (2 * math.pi * loop.d_filter))
    slope = state.rate_slope + alpha * ((e_r - state.rate_error) / dt - state.rate_slope)
    n = ((loop.rate_ff + loop.rate_ff_quadratic * abs(r_d)) * r_d + loop.rate_p * e_r + state.rate_integral
         + loop.rate_d * slope + loop.rate_ff_accel / dt * (r_d - state.rate_demand))
    wind_r = ((n < n_max) | (e_r < 0)) & ((n > -n_max) | (e_r > 0))
    i_r = where(wind_r, clip(state.rate_integral + loop.rate_i * e_r * dt, loop.rate_imax),
                state.rate_integral)

    force, moment = bound(x, x_min, x_max), clip(n, n_max)
    if every(fresh):
        return LoopState(u_d, r_d, i_u, i_r, e_r, slope), force, moment
    new = LoopState(where(fresh, u_d, u), where(fresh, r_d, r), where(fresh, i_u, 0.0),
                    where(fresh, i_r, 0.0), where(fresh, e_r, 0.0), where(fresh, slope, 0.0))
    return new, where(fresh, force, 0.0), where(fresh, moment, 0.0)
