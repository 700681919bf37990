"""Formation controller (27), (29), (31), (33) and the command of (31), with the paper's saturations.

The pieces of one vessel's command: desired offset (27), desired velocity (29), formation and tracking
velocities (33), saturation sat(U, u) and the (surge, yaw rate) command of (31). The per-vessel sums, the
desired pair offset (30) and the commanded velocity (32), or (35) with avoidance, are assembled from them in
agent/core/command.py (`control_command`).

Vectors are 2-D numpy arrays in the common heading reference; p_ij = p_i - p_j and p_io = p_i - p_o as in
the paper, so p*_io is where vessel i should sit relative to the target.
"""

from __future__ import annotations

import math

import numpy as np

from agent.angles import wrap_angle


def saturate(bound: float, vector: np.ndarray) -> np.ndarray:
    """sat(U, u) = min(U, |u|) / |u| u of (31), and 0 for u = 0; it bounds the terms of (32), (33), (35)."""
    norm = math.hypot(vector[0], vector[1])
    if norm <= bound:
        return vector
    return vector * (bound / norm)


def saturate_floats(bound: float, x: float, y: float) -> tuple[float, float]:
    """`saturate` of the vector (x, y) in plain floats: the same operations, the same numbers."""
    norm = math.hypot(x, y)
    if norm <= bound:
        return x, y
    scale = bound / norm
    return x * scale, y * scale


def desired_offset(radius: float, phase: float) -> tuple[float, float]:
    """(27): p*_io = r* [cos phi_i, sin phi_i]. The desired pair offset (30) is the difference of two of
    these, p*_ij = p*_io - p*_jo."""
    return radius * math.cos(phase), radius * math.sin(phase)


def desired_offsets(radius: float, phases: np.ndarray) -> np.ndarray:
    """(27) for several phases at once: the rows r* [cos phi_j, sin phi_j], (m, 2)."""
    return np.stack([radius * np.cos(phases), radius * np.sin(phases)], axis=1)


def desired_velocity(radius: float, phase: float, next_phase: float, dt: float) -> tuple[float, float]:
    """(29): v*_io = (p*_io,k+1 - p*_io,k) / dt."""
    (ox, oy), (nx, ny) = desired_offset(radius, phase), desired_offset(radius, next_phase)
    return (nx - ox) / dt, (ny - oy) / dt


def neighbour_gain(count: int, gain: float, total_cap: float | None) -> float:
    """kappa_ij of (33) for each of `count` neighbours, scaled down so that their sum stays within
    `total_cap`.

    Summed over a complete graph, (33) moves vessel i with gain (n - 1) kappa_ij + kappa_io per metre of
    error, and the sampled loop is only well damped while dt times that stays well below 1; with Table I's
    gains (kappa_ij = 1.5, dt = 0.1) that holds for n = 4 (0.54) but not for n = 12 (1.74, on the edge of
    oscillation, which the U_vf saturation turns into a limit cycle). Capping the sum at the n = 4 value
    (4.5) leaves (33) unchanged up to four vessels. None gives (33) as written.
    """
    if total_cap is None or count * gain <= total_cap:
        return gain
    return total_cap / count


def formation_velocity(terms) -> tuple[float, float]:
    """(33) first line: v^f = sum_j kappa_ij (p*_ij - p^_ij), given (kappa, x error, y error) per neighbour and
    for the target, summed in their order (plain floats: numpy's per-call cost was most of the tick's)."""
    fx = fy = 0.0
    for gain, ex, ey in terms:
        fx, fy = fx + gain * ex, fy + gain * ey
    return fx, fy


def tracking_velocity(target_velocity_estimate: tuple[float, float], desired_relative_velocity: tuple[float, float],
                      max_target_speed: float) -> tuple[float, float]:
    """(33) second line: v^t = sat(U_vo, v^_o) + v*_io."""
    sx, sy = saturate_floats(max_target_speed, *target_velocity_estimate)
    return sx + desired_relative_velocity[0], sy + desired_relative_velocity[1]


def surge_and_yaw_rate(velocity_command: np.ndarray, heading: float, yaw_rate: float, dt: float,
                       max_correction: float, max_speed: float, heading_gain: float | None = None
                       ) -> tuple[float, float, bool]:
    """(31): v = [cos theta, sin theta] v^c (bounded by U_v), omega = sat(U_omega_c, omega^c) + omega*.

    The correction omega^c = (atan2(v^c) - theta) / dt, with the heading error wrapped to (-pi, pi]: the
    paper's arccos of the x-component loses the sign of the heading. A zero v^c asks for no turn.
    `heading_gain` K: omega^c = K (atan2(v^c) - theta) instead (None: K = 1/dt, (31) as written).
    Returns (surge, yaw rate, whether the correction saturated).
    """
    vx, vy = np.asarray(velocity_command, dtype=float).tolist()      # floats: numpy's scalars cost more
    speed = math.hypot(vx, vy)
    surge = math.cos(heading) * vx + math.sin(heading) * vy
    surge = min(max(surge, -max_speed), max_speed)
    if speed == 0.0:
        correction = 0.0
    else:
        error = wrap_angle(math.atan2(vy, vx) - heading)
        correction = error / dt if heading_gain is None else heading_gain * error
    saturated = abs(correction) > max_correction
    correction = min(max(correction, -max_correction), max_correction)
    return surge, correction + yaw_rate, saturated


def lag_compensated_rate(error: float, rate: float, reference_rate: float, lag: float, bandwidth: float,
                         damping: float) -> float:
    """The yaw-rate command u for a boat whose rate r follows it with a first-order lag, tau r' = u - r:
    u = r + tau (w_n^2 e + 2 zeta w_n (omega_d - r)), which makes the heading error e = theta_d - theta obey
    e'' + 2 zeta w_n e' + w_n^2 e = 0 while theta_d turns at omega_d (state feedback on theta and r)."""
    return rate + lag * (bandwidth * bandwidth * error + 2.0 * damping * bandwidth * (reference_rate - rate))
