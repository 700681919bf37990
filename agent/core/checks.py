"""Checks of what reaches the core, before anything touches a filter.

The shell's input gate has already validated every payload against the contract; these checks hold for
any caller (the in-process runner, replay, a test), so the core itself never lets a non-finite number or a
malformed share into an estimate. Each returns a verdict only: counting what was refused is the step's job.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from agent.core.records import Share


def finite_vector(value, size: int) -> bool:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return False
    return array.shape == (size,) and bool(np.isfinite(array).all())


def finite_matrix(value) -> bool:
    """A finite 2x2 matrix."""
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return False
    return array.shape == (2, 2) and bool(np.isfinite(array).all())


def valid_range(value, max_range: float) -> bool:
    """A real number in [0, max_range] (a bool is not a range)."""
    return (not isinstance(value, bool) and isinstance(value, (int, float))
            and math.isfinite(value) and 0.0 <= value <= max_range)


def valid_share(share: object, receiver: str) -> bool:
    if not isinstance(share, Share):
        return False
    odometry = share.odometry
    return (finite_vector(odometry.position, 2) and isinstance(odometry.stamp, (int, float))
            and math.isfinite(odometry.stamp) and math.isfinite(share.phase)
            and finite_vector(share.velocity, 2)
            and (share.target is None or (finite_vector(share.target, 4)
                                          and share.target_covariance is not None
                                          and np.shape(share.target_covariance) == (4, 4)
                                          and np.isfinite(share.target_covariance).all()))
            and isinstance(share.neighbours, Mapping) and valid_pair_entry(share.neighbours.get(receiver)))


def valid_pair_entry(entry) -> bool:
    """The only entry of a share's `neighbours` a receiver uses is its own: check that one (O(1) per share,
    where checking them all would cost O(n^2) per tick in a large fleet)."""
    if entry is None:
        return True
    try:
        position, covariance, stamp = entry
    except (TypeError, ValueError):
        return False
    return finite_vector(position, 2) and finite_matrix(covariance) and isinstance(stamp, float) and math.isfinite(stamp)


def obstacle_array(points) -> tuple[np.ndarray | None, bool]:
    """(points as an (M, 2) array or None when there are none, whether they were malformed)."""
    if points is None:
        return None, False
    array = np.asarray(points, dtype=float) if not isinstance(points, np.ndarray) else points
    if array.size == 0:
        return None, False
    if array.ndim != 2 or array.shape[1] != 2 or not np.all(np.isfinite(array)):
        return None, True
    return array, False
