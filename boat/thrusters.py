"""Twin-thruster allocation, saturation with asymmetric reverse thrust, and first-order thruster lag.

Thrusters at y = +b (port) and y = -b (starboard) push along x, so
    X = T_p + T_s,    N = b (T_s - T_p)          (`forces`)
    T_p = X/2 - N/(2b),  T_s = X/2 + N/(2b)       (`allocate`, its inverse)
Each thrust lies in [-R, F] (R: the reverse limit, as a magnitude). Saturation keeps the turn first, as the
driver bridge's mixer does: with mean m = X/2 and half-difference h = N/(2b), h is clipped to +-(F + R)/2,
then m to [-R + |h|, F - |h|]. The thrust follows its demand with the first-order lag T dT/dt = T_d - T,
integrated exactly over a step dt: T += (T_d - T)(1 - exp(-dt/T)), whose mean over the step is
T_d + (T_0 - T_d)(T/dt)(1 - exp(-dt/T)) (`mean_over`). Arrays of shape (n,) throughout, or plain floats
(one boat; the same numbers).
"""

from __future__ import annotations

import math

import numpy as np

from boat.elementwise import bound, clip
from boat.presets import Thrusters


def allocate(thrusters: Thrusters, force: np.ndarray, moment: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T_p, T_s, saturated): the thrust pair for the demanded (X, N), saturated turn first; `saturated` is
    True where the pair could not give (X, N) exactly. Non-finite demands give zero thrust, saturated."""
    b, f, r = thrusters.half_beam, thrusters.max_forward, thrusters.max_reverse
    if type(force) is float and type(moment) is float:   # one boat in plain floats
        lost = not (math.isfinite(force) and math.isfinite(moment))
        if lost:
            force = moment = 0.0
    else:
        finite = np.isfinite(force) & np.isfinite(moment)
        lost = ~finite
        if not finite.all():
            force, moment = np.where(finite, force, 0.0), np.where(finite, moment, 0.0)
    mean, half = force * 0.5, moment * (0.5 / b)
    half_c = clip(half, 0.5 * (f + r))
    room = abs(half_c)
    mean_c = bound(mean, room - r, f - room)
    saturated = (half_c != half) | (mean_c != mean) | lost
    return mean_c - half_c, mean_c + half_c, saturated


def forces(thrusters: Thrusters, port: np.ndarray, starboard: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """tau = (X, N) of a thrust pair."""
    return port + starboard, thrusters.half_beam * (starboard - port)


def lag(thrusters: Thrusters, thrust: np.ndarray, demand: np.ndarray, dt: float) -> np.ndarray:
    """The thrust after dt of T dT/dt = T_d - T with the demand held: exact for a held demand."""
    return thrust + (demand - thrust) * (1.0 - math.exp(-dt / thrusters.time_constant))


def mean_over(thrusters: Thrusters, thrust: np.ndarray, demand: np.ndarray, dt: float) -> np.ndarray:
    """The mean thrust over dt of T dT/dt = T_d - T from `thrust`, the demand held."""
    tc = thrusters.time_constant
    return demand + (thrust - demand) * (tc / dt) * (1.0 - math.exp(-dt / tc))
