"""The pseudo-linear range-displacement measurement, Sec. III-A (11), (12), (13), (14), and 2-D Kalman
algebra.

Everything here works on plain floats: a relative position (px, py), a symmetric 2x2 covariance stored as
(p11, p12, p22) and a relative displacement (dx, dy). Written out in closed form because a 2-D filter spends
most of its time in call overhead, not arithmetic; these functions are the kernels every inter-vessel
estimator shares.
"""

from __future__ import annotations

import math


def pseudo_measurement(range_prev: float, range_now: float, dx: float, dy: float) -> float:
    """Equivalent measurement z_ij,k of (13): 0.5 (r~_k^2 - r~_{k-1}^2 + |delta~_ij,k|^2).

    By the cosine law (11), z = delta^T p_ij,k, where delta is the relative displacement over exactly the
    interval between the two range epochs and p_ij,k the relative position at the later epoch: the
    measurement model (12).
    """
    return 0.5 * (range_now * range_now - range_prev * range_prev + dx * dx + dy * dy)


def equivalent_noise_variance(
    px: float, py: float, dx: float, dy: float, range_variance: float, displacement_variance: float
) -> float:
    """R_z of (12) from (14) at the predicted ranges r_k = |p^-_k| and r_{k-1} = |p^-_k - delta~|, the
    choice the paper makes for the PLKF and the default here. See `range_pair_noise_variance`."""
    return range_pair_noise_variance(
        math.hypot(px, py), math.hypot(px - dx, py - dy), range_variance, displacement_variance
    )


def range_pair_noise_variance(
    range_now: float, range_prev: float, range_variance: float, displacement_variance: float
) -> float:
    """Variance of the equivalent noise mu_z in (12), derived from (14).

    (14) gives mu_z ~= r_k mu_k - r_{k-1} mu_{k-1} + (mu_k^2 - mu_{k-1}^2) / 2. With independent zero-mean
    range errors of variance s2 and a Gaussian fourth moment (E mu^4 = 3 s2^2, so Var mu^2 = 2 s2^2) the
    odd cross moments vanish and

        Var mu_z = s2 (r_k^2 + r_{k-1}^2) + s2^2.

    The paper neglects the displacement noise; it is kept here because it costs nothing: with
    delta~ = delta + n, the error it adds to z - delta~^T p is n^T (delta - p) = -n^T p_{k-1}, of variance
    r_{k-1}^2 * displacement_variance for isotropic n.
    """
    r_now_sq = range_now * range_now
    r_prev_sq = range_prev * range_prev
    return range_variance * (r_now_sq + r_prev_sq) + range_variance * range_variance + (
        displacement_variance * r_prev_sq
    )


def gain(p11: float, p12: float, p22: float, dx: float, dy: float, r: float) -> tuple[float, float, float]:
    """Kalman gain K = P delta / (delta^T P delta + r) for the scalar measurement z = delta^T p of (12).

    This is K-bar of (19) with every kernel weight equal to 1, the limit sigma -> infinity in which the
    paper notes the MCKF becomes the Kalman filter.

    Returns (kx, ky, s) with s = delta^T P delta + r, the innovation variance.
    """
    hx = p11 * dx + p12 * dy
    hy = p12 * dx + p22 * dy
    s = dx * hx + dy * hy + r
    return hx / s, hy / s, s


def joseph(
    p11: float, p12: float, p22: float, kx: float, ky: float, dx: float, dy: float, r: float
) -> tuple[float, float, float]:
    """Joseph-form covariance update (21): (I - K delta^T) P (I - K delta^T)^T + K r K^T.

    Valid for any gain K, which the MCKF needs since its gain is not the optimal one for r.
    """
    a11, a12 = 1.0 - kx * dx, -kx * dy
    a21, a22 = -ky * dx, 1.0 - ky * dy
    m11 = a11 * p11 + a12 * p12
    m12 = a11 * p12 + a12 * p22
    m21 = a21 * p11 + a22 * p12
    m22 = a21 * p12 + a22 * p22
    return (
        m11 * a11 + m12 * a12 + kx * kx * r,
        m11 * a21 + m12 * a22 + kx * ky * r,
        m21 * a21 + m22 * a22 + ky * ky * r,
    )


def is_positive_definite(p11: float, p12: float, p22: float) -> bool:
    """Sylvester's criterion for a symmetric 2x2 matrix (False for NaN)."""
    return p11 > 0.0 and p11 * p22 - p12 * p12 > 0.0 and math.isfinite(p22)
