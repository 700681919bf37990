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

FLOAT64 = np.dtype(np.float64)


def finite_vector(value, size: int) -> bool:
    return finite_floats(value, (size,)) is not None


def finite_matrix(value) -> bool:
    """A finite 2x2 matrix."""
    return finite_floats(value, (2, 2)) is not None


def finite_array(value, shape: tuple[int, ...]) -> bool:
    """`value`, as a float array, has `shape` and only finite elements."""
    return finite_floats(value, shape) is not None


def finite_floats(value, shape: tuple[int, ...]) -> list[float] | None:
    """The elements of `value` as a flat list of floats if it passes `finite_array`, else None: the check and
    the conversion a caller doing its algebra in floats needs, in one pass."""
    if type(value) is np.ndarray and (value.dtype is FLOAT64 or value.dtype == FLOAT64):
        # The common case, without a conversion: math.isfinite over a few elements costs less than numpy's
        # isfinite-and-reduce, and these checks run several times per share and neighbour each tick.
        if value.shape != shape:
            return None
        # A vector is flat already: ravel's view would only add a call (a share brings three vectors a tick)
        values = value.tolist() if len(shape) == 1 else value.ravel().tolist()
        # Any inf or NaN makes the sum non-finite, so a finite sum settles it in one call; only a sum that
        # overflowed (or a non-finite element) needs the element-wise look.
        total = sum(values)
        if total - total == 0.0:
            return values
    else:
        try:
            array = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            return None
        if array.shape != shape:
            return None
        values = array.ravel().tolist()
    return values if all(map(math.isfinite, values)) else None


def cholesky_succeeds(values: list[float], size: int, shift: float = 0.0) -> bool:
    """True if the symmetric part of the size x size matrix of `values` (row-major, finite) plus `shift` I is
    positive definite: every pivot of its Cholesky factorisation positive, in plain floats (cheaper than numpy's
    eigenvalues on a 4x4). It proves the smallest eigenvalue is above -shift; at the boundary the verdict is
    round-off. Sizes 3 and 4 (an odometry's and a target's covariance, checked per message) are written out:
    the same operations in the same order as the loops, at a third of their cost."""
    if size == 4:
        return _cholesky_4(values, shift)
    if size == 3:
        return _cholesky_3(values, shift)
    lower: list[list[float]] = []
    for i in range(size):
        row: list[float] = []
        for j in range(i + 1):
            entry = 0.5 * (values[i * size + j] + values[j * size + i]) + (shift if i == j else 0.0)
            other = lower[j] if j < i else row
            for k in range(j):
                entry -= row[k] * other[k]
            if i == j:
                if not entry > 0.0:
                    return False
                row.append(math.sqrt(entry))
            else:
                row.append(entry / lower[j][j])
        lower.append(row)
    return True


def _cholesky_4(v, shift: float) -> bool:
    """`cholesky_succeeds` of a 4x4: pivots d_i and factors l_ij of the symmetric part (a_ij + a_ji) / 2."""
    d0 = v[0] + shift
    if not d0 > 0.0:
        return False
    r0 = math.sqrt(d0)
    l10, l20, l30 = 0.5 * (v[4] + v[1]) / r0, 0.5 * (v[8] + v[2]) / r0, 0.5 * (v[12] + v[3]) / r0
    d1 = v[5] + shift - l10 * l10
    if not d1 > 0.0:
        return False
    r1 = math.sqrt(d1)
    l21, l31 = (0.5 * (v[9] + v[6]) - l20 * l10) / r1, (0.5 * (v[13] + v[7]) - l30 * l10) / r1
    d2 = v[10] + shift - l20 * l20 - l21 * l21
    if not d2 > 0.0:
        return False
    l32 = (0.5 * (v[14] + v[11]) - l30 * l20 - l31 * l21) / math.sqrt(d2)
    return v[15] + shift - l30 * l30 - l31 * l31 - l32 * l32 > 0.0


def _cholesky_3(v, shift: float) -> bool:
    """`cholesky_succeeds` of a 3x3, as `_cholesky_4`."""
    d0 = v[0] + shift
    if not d0 > 0.0:
        return False
    r0 = math.sqrt(d0)
    l10, l20 = 0.5 * (v[3] + v[1]) / r0, 0.5 * (v[6] + v[2]) / r0
    d1 = v[4] + shift - l10 * l10
    if not d1 > 0.0:
        return False
    l21 = (0.5 * (v[7] + v[5]) - l20 * l10) / math.sqrt(d1)
    return v[8] + shift - l20 * l20 - l21 * l21 > 0.0


def valid_range(value, max_range: float) -> bool:
    """A real number in [0, max_range] (a bool is not a range)."""
    return (not isinstance(value, bool) and isinstance(value, (int, float))
            and math.isfinite(value) and 0.0 <= value <= max_range)


# What a receiver takes from a valid share beside the share itself, as the floats its check gave: (the
# sender's odometry position, its commanded velocity (2), its estimate of the receiver's pair as
# `pair_entry_floats` gives it or () if none). A plain tuple: a NamedTuple's constructor, per share and tick,
# would cost about as much as the conversions it saves.
CheckedShare = tuple[tuple[float, float], tuple[float, float], tuple[float, ...]]


def checked_share(share: object, receiver: str) -> CheckedShare | None:
    """What a receiver takes from a share (`CheckedShare`), or None if the share is not valid. Of the share's
    `neighbours` only the receiver's own entry is checked (O(1) per share, where checking them all would cost
    O(n^2) per tick in a large fleet). The track reads these floats every tick: they are checked and converted
    once, where the share comes in."""
    if not isinstance(share, Share):
        return None
    odometry = share.odometry
    # One chain that keeps the floats it checks: a check after a failed one is still not evaluated.
    if not ((position := finite_floats(odometry.position, (2,))) is not None
            and isinstance(odometry.stamp, (int, float))
            and math.isfinite(odometry.stamp) and math.isfinite(share.phase)
            and (velocity := finite_floats(share.velocity, (2,))) is not None
            and (share.target is None or (finite_floats(share.target, (4,)) is not None
                                          and share.target_covariance is not None
                                          and _finite_4x4(share.target_covariance)))
            and (type(share.neighbours) is dict or isinstance(share.neighbours, Mapping))):
        return None
    entry = share.neighbours.get(receiver)
    reciprocal = () if entry is None else pair_entry_floats(entry)
    if reciprocal is None:
        return None
    (px, py), (vx, vy) = position, velocity
    return (px, py), (vx, vy), reciprocal


def _finite_4x4(value) -> bool:
    """Shape (4, 4) and every element finite."""
    if type(value) is np.ndarray and value.dtype == FLOAT64:
        return finite_floats(value, (4, 4)) is not None
    return np.shape(value) == (4, 4) and bool(np.isfinite(value).all())


def pair_entry_floats(entry) -> tuple[float, ...] | None:
    """A share's (position, covariance, stamp) of one pair as the floats (px, py, c11, c12, c21, c22, stamp),
    the covariance row by row; None unless the position and covariance are finite and the stamp is a finite
    float."""
    try:
        position, covariance, stamp = entry
    except (TypeError, ValueError):
        return None
    position = finite_floats(position, (2,))
    if position is None:
        return None
    covariance = finite_floats(covariance, (2, 2))
    if covariance is None or not (isinstance(stamp, float) and math.isfinite(stamp)):
        return None
    return (*position, *covariance, stamp)


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
