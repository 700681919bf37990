"""Is a small covariance positive definite? A Cholesky factorisation in plain floats.

Shared by the wire contract (every odometry, share and target covariance that arrives is checked) and the
core (the target filter's covariance); it imports nothing of either, so a bridge that loads the contract
loads no part of the core.
"""

from __future__ import annotations

import math


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
