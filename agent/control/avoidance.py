"""Vector-field obstacle avoidance (34)."""

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
