"""Covariance intersection of two estimates of the same quantity whose errors are correlated in an unknown way.

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

import numpy as np


def covariance_intersection(a: np.ndarray, A: np.ndarray, b: np.ndarray, B: np.ndarray, weight: float = 0.5
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Fuse (a, A) and (b, B) with weight w on the first; both covariances must be positive definite."""
    A_inv, B_inv = np.linalg.inv(A), np.linalg.inv(B)
    information = weight * A_inv + (1.0 - weight) * B_inv
    P = np.linalg.inv(information)
    x = P @ (weight * A_inv @ a + (1.0 - weight) * B_inv @ b)
    return x, 0.5 * (P + P.T)


def covariance_intersection_many(estimates: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Covariance intersection of several estimates with equal weights 1/m: P^-1 = (1/m) sum P_k^-1.

    Equal weights make the result the same whichever vessel computes it from the same set, and the fused
    covariance is never smaller than the information average allows, whatever the correlations."""
    weight = 1.0 / len(estimates)
    information = sum(weight * np.linalg.inv(P) for _, P in estimates)
    P = np.linalg.inv(information)
    x = P @ sum(weight * np.linalg.inv(C) @ c for c, C in estimates)
    return x, 0.5 * (P + P.T)
