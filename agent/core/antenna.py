"""UWB antennas off the hull's centre: where a range is really measured between.

A vessel's antenna sits at the lever arm a = (forward, left) from its hull's centre, so in the common frame
at p + R(psi) a. For the pair (i, j), p_ij = p_i - p_j (10), the UWB module measures

    r~_ij = |p_ij + delta_ij| + noise,    delta_ij = R(psi_i) a_i - R(psi_j) a_j

with both headings at the range's time; (6) is the case a_i = a_j = 0. The raw-range filter takes delta_ij
into its measurement model (raw_range.py); the paper's pseudo-linear filters ignore it. docs/sea.md "(i)
Antennas and heading" gives the reasons and the measurements. Plain floats; a vertical arm, which only roll
and pitch would swing sideways, is not the agent's to know.
"""

from __future__ import annotations

import math

ZERO = (0.0, 0.0)


def arm_vector(heading: float, arm: tuple[float, float]) -> tuple[float, float]:
    """R(psi) a: the antenna's offset from the hull's centre in the common frame (m)."""
    forward, left = arm
    c, s = math.cos(heading), math.sin(heading)
    return c * forward - s * left, s * forward + c * left


def antenna_offset(own: tuple[float, float], theirs: tuple[float, float]) -> tuple[float, float]:
    """delta_ij = R(psi_i) a_i - R(psi_j) a_j from the two arm vectors (`arm_vector`)."""
    return own[0] - theirs[0], own[1] - theirs[1]


def antenna_range(relative: tuple[float, float], offset: tuple[float, float]) -> float:
    """|p_ij + delta_ij|: the range between the antennas of hulls whose centres are p_ij apart."""
    return math.hypot(relative[0] + offset[0], relative[1] + offset[1])
