"""Whether a neighbour's claimed motion agrees with the ranges measured to it: the check a vessel id must pass
before its shares steer anyone when it comes back (agent/shell/peers.py).

With both odometries in the common heading reference, the true offset between the vessels is constant in
their frames: |c + a_k - b_k| = r_k for our odometry a_k, the neighbour's claimed odometry b_k and the range
r_k at the same time t_k, for one unknown c (the two frames' origins, p_ij at the odometries' zero). With the
anchors q_k = b_k - a_k that is trilateration, |c - q_k| = r_k: a vessel whose claims are true leaves
residuals of the size of the range noise at the best c; one that claims a motion it does not make leaves the
difference between the motion claimed and the motion ranged, whatever c absorbs of it.
"""

from __future__ import annotations

import numpy as np

from agent.core.median import median


def best_offset(anchors: np.ndarray, ranges: np.ndarray, iterations: int = 8) -> np.ndarray:
    """c minimising sum_k (|c - q_k| - r_k)^2 for anchors q_k (K, 2) and ranges r_k (K,): the linear solution
    of |c|^2 - 2 c.q_k + |q_k|^2 = r_k^2 (in c and |c|^2; the minimum-norm one when the anchors are collinear
    or one point), then Gauss-Newton."""
    anchors, ranges = np.asarray(anchors, dtype=float), np.asarray(ranges, dtype=float)
    rows = np.column_stack([-2.0 * anchors, np.ones(len(anchors))])
    solution, *_ = np.linalg.lstsq(rows, ranges**2 - np.sum(anchors**2, axis=1), rcond=None)
    offset = solution[:2]
    if not np.all(np.isfinite(offset)) or np.allclose(offset, anchors.mean(axis=0)):
        # No direction to start from (anchors that do not move): any point at the mean range will do.
        offset = anchors.mean(axis=0) + np.array([float(np.mean(ranges)), 0.0])
    for _ in range(iterations):
        towards = offset - anchors
        distances = np.hypot(towards[:, 0], towards[:, 1])
        if np.any(distances < 1e-9):
            break
        jacobian = towards / distances[:, None]
        step, *_ = np.linalg.lstsq(jacobian, ranges - distances, rcond=None)
        offset = offset + step
        if np.hypot(*step) < 1e-6:
            break
    return offset


def range_residuals(own: np.ndarray, claimed: np.ndarray, ranges: np.ndarray,
                    offset: np.ndarray | None = None) -> np.ndarray:
    """r_k - |c - q_k| for our odometry `own` (K, 2), the claimed odometry `claimed` (K, 2), both at the times
    of the ranges `ranges` (K,), at the offset c given (None: the best one, `best_offset`)."""
    anchors = np.asarray(claimed, dtype=float) - np.asarray(own, dtype=float)
    ranges = np.asarray(ranges, dtype=float)
    offset = best_offset(anchors, ranges) if offset is None else np.asarray(offset, dtype=float)
    return ranges - np.hypot(*(offset - anchors).T)


def range_misfit(own: np.ndarray, claimed: np.ndarray, ranges: np.ndarray) -> float:
    """The median |r_k - |c - q_k|| at the best offset c: how far (m) the claims are from the ranges (a
    median, so that a few stray UWB ranges do not refuse a genuine vessel)."""
    return median(np.abs(range_residuals(own, claimed, ranges)))


def residual_trend(residuals: np.ndarray) -> float:
    """How far (m) the residuals moved over their window: the median of the last third less that of the first.
    A claim whose motion differs from the ranged one leaves a trend (a range rate the claims do not have)
    before it leaves a large residual; a median of each third, so that stray ranges do not make one."""
    third = max(1, len(residuals) // 3)
    return median(residuals[-third:]) - median(residuals[:third])
