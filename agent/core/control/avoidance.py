"""Vector-field obstacle avoidance (34), and a safety filter applied after (35) (not in the paper)."""

from __future__ import annotations

import numpy as np


def avoidance_velocity(points: np.ndarray | None, safety_distance: float, gain: float, spread: float
                       ) -> np.ndarray:
    """(34): v^s = sum_m k1 exp(-|p_im|^2 / (2 k2 d_s^2)) p_im / |p_im| over the obstacle points closer than
    d_s. `points` are obstacle points relative to the vessel (point - p_i), so p_im = -point: the field
    pushes away from the obstacle."""
    if points is None or len(points) == 0:
        return np.zeros(2)
    away = -np.asarray(points, dtype=float).reshape(-1, 2)
    distance = np.hypot(away[:, 0], away[:, 1])
    near = (distance < safety_distance) & (distance > 0.0)
    if not np.any(near):
        return np.zeros(2)
    away, distance = away[near], distance[near]
    unit = away / distance[:, None]  # before weighting: dividing the weight by a tiny distance overflows
    weight = gain * np.exp(-distance**2 / (2.0 * spread * safety_distance**2))
    return (weight[:, None] * unit).sum(axis=0)


def safety_filter(velocity: np.ndarray, points: np.ndarray | None, min_clearance: float, rate: float
                  ) -> tuple[np.ndarray, bool]:
    """Keep clear of land whatever the formation asks: a control-barrier-style limit on (35)'s command, not
    in the paper ((35) bounds the push of (34) by U_vs, which the other terms of (35) can outweigh).

    With d the distance to the nearest obstacle point and n the unit vector from it to the vessel, the
    command may close on the point no faster than rate * (d - d_min): n^T v >= -rate (d - d_min). Inside
    d_min that asks for an opening speed. A command that breaks the limit loses just enough of its
    component along -n; one that keeps it is returned unchanged. Returns (velocity, whether it acted).
    """
    if points is None or len(points) == 0:
        return velocity, False
    away = -np.asarray(points, dtype=float).reshape(-1, 2)
    distance = np.hypot(away[:, 0], away[:, 1])
    nearest = int(np.argmin(distance))
    d = float(distance[nearest])
    if d <= 0.0:
        return velocity, False  # on the point itself no direction is known; (34) has already pushed
    n = away[nearest] / d
    floor = -rate * (d - min_clearance)
    closing = float(n @ velocity)
    if closing >= floor:
        return velocity, False
    return velocity + (floor - closing) * n, True
