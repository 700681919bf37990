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
    return covariance_intersection_weighted([(a, A), (b, B)], (weight, 1.0 - weight))


def covariance_intersection_many(estimates: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Covariance intersection of several estimates with equal weights 1/m: P^-1 = (1/m) sum P_k^-1.

    Equal weights make the result the same whichever vessel computes it from the same set, and the fused
    covariance is never smaller than the information average allows, whatever the correlations."""
    return covariance_intersection_weighted(estimates, [1.0 / len(estimates)] * len(estimates))


def covariance_intersection_weighted(estimates: list[tuple[np.ndarray, np.ndarray]], weights
                                     ) -> tuple[np.ndarray, np.ndarray]:
    """P^-1 = sum w_k P_k^-1, x = P sum w_k P_k^-1 x_k (weights summing to one)."""
    information = [w * inverse(np.asarray(C, dtype=float)) for w, (_, C) in zip(weights, estimates)]
    P = inverse(sum(information))
    x = P @ sum(Y @ np.asarray(c, dtype=float) for Y, (c, _) in zip(information, estimates))
    return x, 0.5 * (P + P.T)


def inverse(matrix: np.ndarray) -> np.ndarray:
    """The inverse of a square matrix; 2x2 in closed form (at this size numpy's call overhead is most of
    the cost). Raises numpy.linalg.LinAlgError for a singular or non-finite matrix."""
    if matrix.shape != (2, 2):
        return np.linalg.inv(matrix)
    (a, b), (c, d) = matrix.tolist()
    determinant = a * d - b * c
    if determinant == 0.0 or not math.isfinite(determinant):
        raise np.linalg.LinAlgError("singular or non-finite 2x2 matrix")
    return np.array([[d, -b], [-c, a]]) / determinant
