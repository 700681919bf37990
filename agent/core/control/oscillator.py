"""Coupled phase oscillator (28) that spreads the vessels evenly around the target.

The paper leaves the gains K_m of (28) open. We take K_m = K > 0 for m = 1..floor(n/2) and K_m = 0 above.
With the sign of (28) (+ sin(m (phi_i - phi_j))) each harmonic m <= n/2 pushes the m-th phase order
parameter |(1/n) sum_j exp(i m phi_j)| to zero, and the only arrangement that zeroes all of them is the
splay state, phases 2 pi / n apart: it is the minimum of the potential sum_m K_m / m |p_m|^2, the all-to-all
splay stabilisation of Sepulchre, Paley and Leonard (IEEE TAC vol. 52 no. 5, 2007). Harmonics above n/2 are
left out because for them the splay state is not a minimum (n = 2, m = 2 would pull the pair together).
Because n is the current fleet size, a join or a leave changes the gains and the fleet re-spaces by itself.
`tests/test_control.py` checks convergence for n = 2..12 from random phases and after joins and leaves.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from agent.angles import wrap_angle

# Up to this many terms sin(m (phi_i - phi_j)) the coupling is summed in plain floats, above it in numpy:
# per-call overhead decides which costs less (a 4-vessel fleet has 2 x 3 of them, a 50-vessel one 25 x 49).
FLOAT_TERMS = 64


def coupled_harmonics(n: int, gain: float) -> int:
    """How many of the first harmonics m = 1, 2, ... have K_m != 0: floor(n / 2), none when the gain is 0."""
    return 0 if gain == 0.0 else n // 2


def coupling_gains(n: int, gain: float) -> list[float]:
    """K_1..K_n of (28): `gain` for m <= floor(n / 2), 0 above."""
    return [gain if m <= n // 2 else 0.0 for m in range(1, n + 1)]


def oscillator_step(phase: float, neighbour_phases: Sequence[float], yaw_rate: float, dt: float,
                    gain: float) -> float:
    """(28): phi_{i,k+1} = phi_{i,k} + omega* dt + dt sum_j sum_m K_m / (m n) sin(m (phi_i - phi_j)),
    with n the fleet size including vessel i; the result is wrapped to (-pi, pi]."""
    n = len(neighbour_phases) + 1
    used = coupled_harmonics(n, gain)
    coupling = 0.0
    if used * (n - 1) <= FLOAT_TERMS:
        # Each harmonic's sines summed in order over the neighbours, then the harmonics in order: the sums of
        # the numpy branch below, in its order (numpy's sine and the C library's may differ in the last bit).
        for m in range(1, used + 1):
            sines = 0.0
            for other in neighbour_phases:
                sines += math.sin(m * (phase - other))
            coupling += gain / (m * n) * sines
    else:
        # All sin(m (phi_i - phi_j)) in one numpy call: a 50-vessel fleet has 25 x 49 of them per tick.
        # cumsum adds in order, left to right, as the loop above does.
        harmonics = np.arange(1.0, used + 1.0)
        sines = np.sin(harmonics[:, None] * (phase - np.asarray(neighbour_phases, dtype=float)))
        terms = gain / (harmonics * n) * np.cumsum(sines, axis=1)[:, -1]
        coupling = 0.0 + float(np.cumsum(terms)[-1])
    return wrap_angle(phase + yaw_rate * dt + dt * coupling)
