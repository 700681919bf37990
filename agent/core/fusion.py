"""Covariance intersection of two estimates of the same quantity whose errors are correlated in an unknown way.

Not in the paper, whose vessels exchange only displacements and phases: it fuses estimates of the pair
position p_ij (10) and of the target state x_io of (24), (25) (agent/core/cooperation.py; docs/equations.md
lists it among the departures, with the measurement).

Two vessels estimate the same pair, p_ij and p_ji = -p_ij, from ranges they both measure and from priors
that may share history, so the correlation of their errors is unknown and a plain Kalman fusion would be
overconfident. Covariance intersection (Julier and Uhlmann, 1997; the fusion rule of the CKHCF reference
paper) is consistent for any correlation:

    P^-1 = w A^-1 + (1 - w) B^-1,   x = P (w A^-1 a + (1 - w) B^-1 b).

With w = 1/2 the rule is symmetric, so vessel i fusing (p^_ij, -p^_ji) and vessel j fusing (p^_ji, -p^_ij)
end with exactly opposite estimates: the formation terms of the pair then agree instead of pulling against
each other.
"""

from __future__ import annotations

import math

import numpy as np


def covariance_intersection(a: np.ndarray, A: np.ndarray, b: np.ndarray, B: np.ndarray, weight: float = 0.5
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Fuse (a, A) and (b, B) with weight w on the first; both covariances must be positive definite."""
    a, A, b, B = (np.asarray(v, dtype=float) for v in (a, A, b, B))
    if A.shape == B.shape == (2, 2):
        x, y, p11, p12, p22 = covariance_intersection_2d(*a.tolist(), *A.ravel().tolist(), *b.tolist(),
                                                         *B.ravel().tolist(), weight)
        return np.array([x, y]), np.array([[p11, p12], [p12, p22]])
    return covariance_intersection_weighted([(a, A), (b, B)], (weight, 1.0 - weight))


def covariance_intersection_2d(ax: float, ay: float, a11: float, a12: float, a21: float, a22: float,
                               bx: float, by: float, b11: float, b12: float, b21: float, b22: float,
                               weight: float = 0.5) -> tuple[float, float, float, float, float]:
    """`covariance_intersection` of two 2-D estimates in plain floats (at this size numpy's call overhead is
    most of the cost): a = (ax, ay), A = [[a11, a12], [a21, a22]], likewise b, B. Returns (x, y) and the
    symmetric part of P as (p11, p12, p22). Raises numpy.linalg.LinAlgError as `inverse` does."""
    w, v = weight, 1.0 - weight
    i11, i12, i21, i22 = _inverse_2d(a11, a12, a21, a22)
    j11, j12, j21, j22 = _inverse_2d(b11, b12, b21, b22)
    y11, y12, y21, y22 = w * i11, w * i12, w * i21, w * i22     # w A^-1
    z11, z12, z21, z22 = v * j11, v * j12, v * j21, v * j22     # (1 - w) B^-1
    q11, q12, q21, q22 = _inverse_2d(y11 + z11, y12 + z12, y21 + z21, y22 + z22)
    ux = (y11 * ax + y12 * ay) + (z11 * bx + z12 * by)
    uy = (y21 * ax + y22 * ay) + (z21 * bx + z22 * by)
    return q11 * ux + q12 * uy, q21 * ux + q22 * uy, 0.5 * (q11 + q11), 0.5 * (q12 + q21), 0.5 * (q22 + q22)


def covariance_intersection_many(estimates: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Covariance intersection of several estimates with equal weights 1/m: P^-1 = (1/m) sum P_k^-1.

    Equal weights make the result the same whichever vessel computes it from the same set, and the fused
    covariance is never smaller than the information average allows, whatever the correlations."""
    return covariance_intersection_weighted(estimates, [1.0 / len(estimates)] * len(estimates))


def covariance_intersection_weighted(estimates: list[tuple[np.ndarray, np.ndarray]], weights
                                     ) -> tuple[np.ndarray, np.ndarray]:
    """P^-1 = sum w_k P_k^-1, x = P sum w_k P_k^-1 x_k (weights summing to one); see
    `covariance_intersection_stacked`."""
    means = np.array([np.asarray(c, dtype=float) for c, _ in estimates])
    covariances = np.array([np.asarray(C, dtype=float) for _, C in estimates])
    return covariance_intersection_stacked(means, covariances, np.asarray(weights, dtype=float))


def covariance_intersection_stacked(means: np.ndarray, covariances: np.ndarray, weights: np.ndarray
                                    ) -> tuple[np.ndarray, np.ndarray]:
    """`covariance_intersection_weighted` of the estimates stacked as means (m, k), covariances (m, k, k)
    and weights (m,).

    All the inverses in one stacked call: numpy's per-call overhead, not the arithmetic, is the cost of a
    4x4 inverse, and a fleet of n fuses n target estimates per tick. The sums run over the stack in order,
    as a loop over the estimates would."""
    if covariances.shape[1:] == (2, 2):
        inverses = np.array([inverse(C) for C in covariances])
    else:
        inverses = np.linalg.inv(covariances)
    return covariance_intersection_information(means, weights[:, None, None] * inverses)


def covariance_intersection_information(means: np.ndarray, information: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`covariance_intersection_stacked` from the weighted information matrices w_k P_k^-1 (m, k, k), for a
    caller that has the inverses already: P = (sum w_k P_k^-1)^-1, x = P sum w_k P_k^-1 x_k, summed over the
    stack in order."""
    P = inverse(np.add.reduce(information, axis=0))
    x = P @ np.add.reduce(np.matmul(information, means[:, :, None])[:, :, 0], axis=0)
    return x, 0.5 * (P + P.T)


def inverse(matrix: np.ndarray) -> np.ndarray:
    """The inverse of a square matrix; 2x2 in closed form (at this size numpy's call overhead is most of
    the cost). Raises numpy.linalg.LinAlgError for a singular or non-finite matrix."""
    if matrix.shape != (2, 2):
        return np.linalg.inv(matrix)
    i11, i12, i21, i22 = _inverse_2d(*matrix.ravel().tolist())
    return np.array([[i11, i12], [i21, i22]])


def _inverse_2d(a: float, b: float, c: float, d: float) -> tuple[float, float, float, float]:
    """[[a, b], [c, d]]^-1 in row order; numpy.linalg.LinAlgError for a singular or non-finite matrix."""
    determinant = a * d - b * c
    if determinant == 0.0 or not math.isfinite(determinant):
        raise np.linalg.LinAlgError("singular or non-finite 2x2 matrix")
    return d / determinant, -b / determinant, -c / determinant, a / determinant
