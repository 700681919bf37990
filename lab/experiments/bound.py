"""The Cramér–Rao bound of inter-vessel relative localisation from ranges and odometry (paper Sec. III-A).

What the data of Experiment 1 contain, whatever the estimator: a floor under the RMSE of the relative
position p_ij = p_i - p_j.

Two pieces, both pure numpy/scipy:

- `fisher_information(noise)`: how much one range tells about the range, I_f = ∫ f'(x)^2 / f(x) dx, where f
  is the density of the range noise mu of (6) taken as a location family (the range r = |p| + mu shifts f).
  For a Gaussian I_f = 1 / variance; any other density of the same variance has a larger I_f, which is what
  an estimator that knows the density (not only its variance) can exploit.
- `pcrlb(truth, displacement_variance, fisher, initial_covariance)`: the posterior Cramér–Rao bound along a
  true path p_0 .. p_K, from the information recursion of Tichavský, Muravchik and Nehorai (1998):

      J_0     = P_0^{-1}                                   (the initial estimate, N(p_0, P_0))
      J_{k+1} = (Q + J_k^{-1})^{-1} + I_f H_{k+1}^T H_{k+1}

  with Q = 2 R_delta I the noise of the relative displacement delta_ij = delta_i - delta_j of (5) and (15)
  (both vessels' odometry, each N(0, R_delta I) per step) and H_k = p_k^T / |p_k| the gradient of the range
  |p_k| at the truth. The state moves by the measured displacement, p_{k+1} = p_k + delta_ij,k, so the known
  part of the motion drops out and only its noise Q enters. The bound on the RMSE of any unbiased estimate of
  p_k from the data up to step k is sqrt(trace(J_k^{-1})).

More: docs/estimation.md §10, `lab/experiments/bound.py`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from agent.core.range_noise import GaussianMixtureNoise, GaussianNoise, LogNormalNoise, MixtureNoise

# --------------------------------------------------------------------------------------------------------
# Fisher information of a range-noise density
# --------------------------------------------------------------------------------------------------------

def fisher_information(noise) -> float:
    """Fisher information I_f (m^-2) of the range-noise density f as a location family.

    I_f = ∫ f'(x)^2 / f(x) dx = ∫ f(x) s(x)^2 dx, with s = (ln f)' the score. Integrated numerically
    (scipy.integrate.quad); the score is written so that it stays finite far in the tails, where f itself
    underflows.

    - `GaussianNoise` N(0, R): I_f = 1 / R (inf for R = 0: a noiseless range).
    - `GaussianMixtureNoise` (7), (1 - eps) N(0, R) + eps N(0, R_out): no closed form; it lies between
      1 / Var (the Gaussian of the same variance, the least informative) and (1 - eps) / R + eps / R_out
      (I_f is convex in f). For Table II (eps 0.2, R 0.4, R_out 10): 1.625 m^-2, against 1 / 2.32 = 0.431.
    - `MixtureNoise` sum_k w_k N(m_k, v_k) (a calibration's): as the mixture (7), over the whole line.
    - `LogNormalNoise` (8), mu = exp(Z) - r_s with Z ~ N(0, R): the shift r_s moves f without changing I_f;
      integrated over z = ln(mu + r_s). The closed form is exp(2 R) (1 + 1 / R) (9.848 m^-2 for R = 0.7,
      against 1 / Var = 0.490): the density rises steeply from its lower end at mu = -r_s, and that edge is
      very informative.
    """
    if isinstance(noise, GaussianNoise):
        return _gaussian_mixture_information((1.0,), (noise.variance,))
    if isinstance(noise, GaussianMixtureNoise):
        eps = noise.outlier_fraction
        return _gaussian_mixture_information((1.0 - eps, eps), (noise.variance, noise.outlier_variance))
    if isinstance(noise, LogNormalNoise):
        return _log_normal_information(noise.log_variance)
    if isinstance(noise, MixtureNoise):
        return _shifted_mixture_information(*zip(*noise.mixture()))
    raise TypeError(f"no Fisher information for range noise {type(noise).__name__}")


def _gaussian_mixture_information(weights: tuple[float, ...], variances: tuple[float, ...]) -> float:
    """I_f of sum_i w_i N(0, v_i). The score is s(x) = -x sum_i g_i(x) / v_i, with g_i(x) the posterior
    weight of component i at x (computed from log-densities, so it is exact where the densities underflow)."""
    from scipy import integrate  # here, not at the top: importing lab.experiments.comparison stays light

    parts = [(w, v) for w, v in zip(weights, variances) if w > 0]
    if any(v == 0 for _, v in parts):
        return math.inf
    w = np.array([p[0] for p in parts], dtype=float)
    v = np.array([p[1] for p in parts], dtype=float)
    w = w / w.sum()
    log_norm = np.log(w) - 0.5 * np.log(2 * math.pi * v)

    def integrand(x: float) -> float:
        log_terms = log_norm - 0.5 * x * x / v
        top = log_terms.max()
        terms = np.exp(log_terms - top)
        g = terms / terms.sum()
        score = -x * float(np.sum(g / v))
        density = math.exp(top) * float(terms.sum())
        return density * score * score

    # The mixture is symmetric: twice the half line. Split at multiples of each component's standard
    # deviation so quad sees every scale; beyond 40 of the widest standard deviations nothing is left
    # (the integrand is below exp(-800)).
    widest = math.sqrt(v.max())
    cuts = sorted({0.0, *(c * math.sqrt(s) for s in v for c in (1.0, 3.0, 8.0)), 40.0 * widest})
    total = 0.0
    for a, b in pairwise(cuts):
        value, _ = integrate.quad(integrand, a, b, epsabs=0.0, epsrel=1e-12, limit=200)
        total += value
    return 2.0 * total


def _shifted_mixture_information(weights: tuple[float, ...], means: tuple[float, ...],
                                 variances: tuple[float, ...]) -> float:
    """I_f of sum_i w_i N(m_i, v_i): the score is s(x) = -sum_i g_i(x) (x - m_i) / v_i, integrated over the line
    split at each mean and at 1, 3, 8 and 40 standard deviations either side of it."""
    from scipy import integrate

    w = np.array(weights, dtype=float) / sum(weights)
    m = np.array(means, dtype=float)
    v = np.array(variances, dtype=float)
    log_norm = np.log(w) - 0.5 * np.log(2 * math.pi * v)

    def integrand(x: float) -> float:
        log_terms = log_norm - 0.5 * (x - m) ** 2 / v
        top = log_terms.max()
        terms = np.exp(log_terms - top)
        g = terms / terms.sum()
        score = -float(np.sum(g * (x - m) / v))
        return math.exp(top) * float(terms.sum()) * score * score

    widest = math.sqrt(v.max())
    cuts = sorted({*(float(c) for c in m), *(float(mi + c * math.sqrt(vi)) for mi, vi in zip(m, v)
                                            for c in (-8.0, -3.0, -1.0, 1.0, 3.0, 8.0)),
                   float(m.min() - 40.0 * widest), float(m.max() + 40.0 * widest)})
    total = 0.0
    for a, b in pairwise(cuts):
        value, _ = integrate.quad(integrand, a, b, epsabs=0.0, epsrel=1e-12, limit=200)
        total += value
    return total


def _log_normal_information(log_variance: float) -> float:
    """I_f of mu = exp(Z) - r_s, Z ~ N(0, R). With y = mu + r_s > 0, f(y) = phi(ln y) / y and the score is
    s = -(1 + ln(y) / R) / y; over z = ln y the integral is ∫ phi(z) (1 + z / R)^2 exp(-2 z) dz."""
    from scipy import integrate

    r = log_variance
    sd = math.sqrt(r)

    def integrand(z: float) -> float:
        # phi(z) exp(-2 z) in one exponent, so it neither overflows nor underflows early.
        return math.exp(-0.5 * z * z / r - 2.0 * z) / math.sqrt(2 * math.pi * r) * (1.0 + z / r) ** 2

    # The weight phi(z) exp(-2z) is a Gaussian centred at -2R with standard deviation sqrt(R).
    centre = -2.0 * r
    cuts = [centre + c * sd for c in (-40.0, -8.0, -3.0, -1.0, 0.0, 1.0, 3.0, 8.0, 40.0)]
    total = 0.0
    for a, b in pairwise(cuts):
        value, _ = integrate.quad(integrand, a, b, epsabs=0.0, epsrel=1e-12, limit=200)
        total += value
    return total


# --------------------------------------------------------------------------------------------------------
# Posterior Cramér–Rao bound along a path
# --------------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PositionBound:
    """The bound at each step k = 0 .. K of a path.

    rmse:        (K+1,) sqrt(trace(J_k^{-1})), the floor on the relative position RMSE (m)
    covariance:  (K+1, 2, 2) J_k^{-1}, the floor on the error covariance (m^2)
    information: (K+1, 2, 2) J_k, the Fisher information of the data up to step k (m^-2)
    """

    rmse: np.ndarray
    covariance: np.ndarray
    information: np.ndarray


def _as_matrix(value, name: str) -> np.ndarray:
    matrix = np.asarray(value, dtype=float)
    if matrix.ndim == 0:
        return float(matrix) * np.eye(2)
    if matrix.shape != (2, 2):
        raise ValueError(f"{name} must be a scalar (times I) or a 2x2 matrix, not shape {matrix.shape}")
    return matrix


def pcrlb(truth: np.ndarray, displacement_variance: float, fisher: float, initial_covariance,
          *, first_range: bool = False) -> PositionBound:
    """Posterior Cramér–Rao bound of the relative position p_k = p_ij,k along a true path.

    truth:                 (K+1, 2) true p_ij,0 .. p_ij,K (m)
    displacement_variance: R_delta, the odometry noise of ONE vessel per axis per step (m^2); the relative
                           displacement carries both vessels', so Q = 2 R_delta I
    fisher:                I_f of the range noise (m^-2), from `fisher_information`
    initial_covariance:    P_0, scalar (times I) or 2x2 (m^2); J_0 = P_0^{-1}
    first_range:           also count a range at step 0 (J_0 = P_0^{-1} + I_f H_0^T H_0). False (the recursion
                           as usually written): ranges at steps 1 .. K. The pair filters of this repository
                           use the range of step 0 too (their first update takes ranges 0 and 1), so a bound
                           on them must count it.

    One range per step, r_k = |p_k| + mu_k, each with Fisher information I_f about |p_k|; its information
    about p_k is I_f H_k^T H_k with H_k = p_k^T / |p_k| (rank one: a range says nothing across the line of
    sight). Between steps J_{k+1} = (Q + J_k^{-1})^{-1} + I_f H_{k+1}^T H_{k+1}.
    """
    truth = np.asarray(truth, dtype=float)
    if truth.ndim != 2 or truth.shape[1] != 2 or len(truth) == 0:
        raise ValueError(f"truth must be shaped (K+1, 2), not {truth.shape}")
    if fisher < 0 or not math.isfinite(fisher):
        raise ValueError(f"Fisher information must be finite and >= 0, not {fisher}")
    if displacement_variance < 0:
        raise ValueError("displacement_variance must be >= 0")
    distance = np.linalg.norm(truth, axis=1)
    if np.any(distance == 0):
        raise ValueError("the true path passes through p_ij = 0, where the range has no gradient")
    u = truth / distance[:, None]                       # H_k^T, unit line of sight
    range_information = fisher * u[:, :, None] * u[:, None, :]   # I_f H_k^T H_k, (K+1, 2, 2)

    q = 2.0 * displacement_variance * np.eye(2)
    prior = _as_matrix(initial_covariance, "initial_covariance")
    steps = len(truth)
    information = np.empty((steps, 2, 2))
    covariance = np.empty((steps, 2, 2))
    j = np.linalg.inv(prior)
    if first_range:
        j = j + range_information[0]
    for k in range(steps):
        if k > 0:
            j = np.linalg.inv(q + covariance[k - 1]) + range_information[k]
        j = 0.5 * (j + j.T)
        information[k] = j
        p = np.linalg.inv(j)
        covariance[k] = 0.5 * (p + p.T)
    rmse = np.sqrt(np.trace(covariance, axis1=1, axis2=2))
    return PositionBound(rmse=rmse, covariance=covariance, information=information)


def rms_bound(paths, displacement_variance: float, fisher: float, initial_covariance,
              *, first_range: bool = False) -> np.ndarray:
    """The bound on an RMSE over Monte Carlo runs, each with its own true path: (K+1,)
    sqrt(mean over runs of trace(J_run,k^{-1})).

    Why this and not the bound of the mean information: the RMSE over runs is sqrt(mean of squared errors),
    and each run's expected squared error is at least its own trace(J^{-1}), so the mean of those traces is
    the floor of the mean squared error. Inverting the mean information instead gives a smaller number
    (trace of the inverse is convex), a looser floor.
    """
    traces = [pcrlb(path, displacement_variance, fisher, initial_covariance, first_range=first_range).rmse ** 2
              for path in paths]
    return np.sqrt(np.mean(traces, axis=0))
