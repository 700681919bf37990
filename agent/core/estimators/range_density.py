"""The range-noise density f the raw-range estimator assumes (raw_range.py): a Gaussian mixture
sum_c w_c N(mu_c, sigma_c^2), the last component a wide zero-mean one for gross errors.

At a residual e each component has a log-density ln(w_c f_c(e)), a score s_c = -(ln f_c)'(e) =
(e - mu_c) / sigma_c^2 and the score's derivative s_c' = 1 / sigma_c^2. The mixture's score and its
derivative follow from the responsibilities gamma_c = w_c f_c / f:
    psi = sum gamma_c s_c,    psi' = sum gamma_c (s_c' - s_c^2) + psi^2.
The predictive density of a residual when the position has variance h along the range is f_h = f * N(0, h),
the same mixture with each variance sigma_c^2 + h.

A skewed noise such as the paper's log-normal (8) is given as a mixture fitted to it for the batch fix. Its
exact density was tried there (batch likelihood exact, predictive density by quadrature): the batch fix is then
decided by the few ranges at the density's steep left edge and is overconfident at small windows (mean NEES
4-6 at 5-10 s against 2), and the RMSE at 30 s was 1.4-1.6 times the bound against 1.2-1.3 with a 6-component
fit. Once fixed, though, the tracking's prior is narrow and the edge's information is what the fit misses (its
I_f 7.0 against the exact 9.85): `LogNormalDensity` gives tracking the exact predictive density, by
quadrature of the convolution (raw_range.py, `tracking_lognormal`).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

LOG_2PI = math.log(2.0 * math.pi)
_trapezoid = getattr(np, "trapezoid", None) or np.trapz
# ndarray.sum and .max without their Python wrappers (the same reductions): called some 40 times per solve
_sum, _max = np.add.reduce, np.maximum.reduce


class RangeDensity:
    """The assumed mixture: (weight, mean, variance) per component, weights summing to 1."""

    def __init__(self, components: tuple[tuple[float, float, float], ...]) -> None:
        self.components = components
        # (ln w_c, mu_c, sigma_c^2) for `predictive`, which runs once per range: the logarithms taken once
        self._tracking = tuple((math.log(w), mean, variance) for w, mean, variance in components)
        self.mean = np.array([c[1] for c in components])[:, None]
        self.var = np.array([c[2] for c in components])[:, None]
        self.precision = 1.0 / self.var
        self.log_norm = np.log(np.array([c[0] for c in components]))[:, None] - 0.5 * (LOG_2PI + np.log(self.var))
        self.fisher, self.entropy, self.spread = _statistics(components)

    def evaluate(self, e: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """At residuals e (N,): (-ln f summed over e, the responsibilities gamma_c (K, N), the scores s_c (K, N)).
        The solver asks `score`, `em_precision` and `curvature` of these only where it needs them: a line
        search's rejected trial needs the cost alone."""
        diff = e - self.mean                                               # (K, N)
        sc = diff * self.precision                                         # scores s_c
        logs = self.log_norm - 0.5 * diff * sc
        top = _max(logs, axis=0)
        g = np.exp(logs - top)
        total = _sum(g, axis=0)
        g /= total
        return float(_sum(-(top + np.log(total)))), g, sc

    def em_precision(self, g: np.ndarray) -> np.ndarray:
        """w = sum_c gamma_c / sigma_c^2 (N,): each residual's precision for an EM step."""
        return _sum(g * self.precision, axis=0)

    @staticmethod
    def score(g: np.ndarray, sc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(psi, gamma_c s_c): the mixture's score (N,) and the product `curvature` takes again."""
        weighted = g * sc
        return _sum(weighted, axis=0), weighted

    @staticmethod
    def curvature(weighted: np.ndarray, sc: np.ndarray, psi: np.ndarray, w: np.ndarray) -> np.ndarray:
        """psi' = w - sum_c gamma_c s_c^2 + psi^2 (N,), from `score`'s product and `em_precision`'s w."""
        return w - _sum(weighted * sc, axis=0) + psi * psi

    def predictive(self, e: float, h: float) -> tuple[float, float, float]:
        """The predictive density f_h = f * N(0, h) at one residual e: (-ln f_h(e), its score psi, psi').
        Plain floats: this runs once per range in tracking. Each component's widened variance and residual
        are kept from the first pass for the second (the same numbers, 1.8 -> 1.3 us a call)."""
        best = -math.inf
        terms = []
        log, exp = math.log, math.exp
        for log_weight, mean, variance in self._tracking:
            v = variance + h
            d = e - mean
            lp = log_weight - 0.5 * (log(v) + d * d / v)
            terms.append((lp, v, d))
            if lp > best:  # noqa: PLR1730 (max(best, lp) without its call, once per component and range)
                best = lp
        total = psi = curvature = 0.0
        for lp, v, d in terms:
            g = exp(lp - best)
            total += g
            sc = d / v
            psi += g * sc
            curvature += g * (1.0 / v - sc * sc)
        psi /= total
        return 0.5 * LOG_2PI - best - math.log(total), psi, curvature / total + psi * psi


# Gauss-Legendre points for the log-normal's predictive density, and how many standard deviations of ln y (the
# log-normal) and of the position along the range (the kernel N(0, h)) it spans.
_POINTS = 64
_REACH = 9.0
# Below this variance along the range (m^2) the kernel is a point: f_h is f itself, to about h f'' / f (2e-5 at
# the steep edge). The quadrature's psi' would lose its digits there, d^2 / h^2 - 1 / h cancelling.
_POINT_LIKE = 1e-8


class LogNormalDensity:
    """The shifted log-normal (8), ln(mu + r_s) ~ N(0, R), with the gross-error component of the mixture:
    f = (1 - eps) f_LN + eps N(0, V). Tracking's predictive density f_h = f * N(0, h) by quadrature."""

    def __init__(self, log_variance: float, shift: float, gross_fraction: float, gross_variance: float) -> None:
        self.log_variance, self.shift = log_variance, shift
        self.gross_fraction, self.gross_variance = gross_fraction, gross_variance
        self.fisher, self.entropy, self.spread = _lognormal_statistics(log_variance, shift, gross_fraction,
                                                                       gross_variance)
        # Nodes and weights on [-1, 1]; numpy.polynomial is imported here, not by every agent (0.7 MB).
        from numpy.polynomial.legendre import leggauss

        self._nodes, self._weights = leggauss(_POINTS)

    def predictive(self, e: float, h: float) -> tuple[float, float, float]:
        """(-ln f_h(e), its score psi, psi') at one residual e, as RangeDensity.predictive.

        With y = mu + r_s and u = ln y ~ N(0, R), f_LN * N(0, h) at e is the integral over u of
        N(u; 0, R) phi_h(c - e^u), c = e + r_s, and its derivatives in e put phi_h' and phi_h'' in place of
        phi_h. It is taken by Gauss-Legendre over the u where both factors are within _REACH standard
        deviations: both are smooth in u, also at the density's steep left edge, where a quadrature in the
        position along the range (Gauss-Hermite, tried first) lost up to half of psi' at h = 0.04 m^2."""
        eps, v = self.gross_fraction, self.gross_variance + h
        g = eps * math.exp(-0.5 * e * e / v) / math.sqrt(2.0 * math.pi * v)
        keep = 1.0 - eps
        if h < _POINT_LIKE:
            f, d1, d2 = (float(a[0]) for a in _shifted_lognormal(np.array([e]), self.log_variance, self.shift))
        else:
            f, d1, d2 = self._convolved(e, h)
        total = keep * f + g
        slope = keep * d1 - g * e / v
        bend = keep * d2 + g * (e * e / v - 1.0) / v
        if not total > 0.0:   # beyond every component's reach (|e| of kilometres): no information
            return math.inf, 0.0, 0.0
        psi = -slope / total
        return -math.log(total), psi, -bend / total + psi * psi

    def _convolved(self, e: float, h: float) -> tuple[float, float, float]:
        """f_LN * N(0, h) at e and its first two derivatives in e, by the quadrature `predictive` describes."""
        c = e + self.shift
        s = math.sqrt(h)
        reach = _REACH * math.sqrt(self.log_variance)
        high = min(reach, math.log(c + _REACH * s)) if c + _REACH * s > 0.0 else -math.inf
        low = max(-reach, math.log(c - _REACH * s)) if c - _REACH * s > 0.0 else -reach
        if not high > low:
            return 0.0, 0.0, 0.0
        half = 0.5 * (high - low)
        u = low + half * (self._nodes + 1.0)
        d = c - np.exp(u)                                   # the kernel's argument, c - y
        weights = half * self._weights * np.exp(-0.5 * (u * u / self.log_variance + d * d / h)) / (
            2.0 * math.pi * math.sqrt(self.log_variance * h))
        return float(weights.sum()), float(weights @ (-d / h)), float(weights @ (d * d / (h * h) - 1.0 / h))


def _shifted_lognormal(x: np.ndarray, log_variance: float, shift: float
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """f_LN and its first two derivatives at x (0 at and below -r_s). With y = x + r_s and
    g = -(1 + ln y / R) / y: f' = f g, f'' = f (g^2 + g'), g' = (1 + (ln y - 1) / R) / y^2."""
    y = x + shift
    inside = y > 0.0
    y = np.where(inside, y, 1.0)
    log_y = np.log(y)
    f = np.where(inside, np.exp(-0.5 * log_y * log_y / log_variance) / (y * math.sqrt(2.0 * math.pi * log_variance)),
                 0.0)
    g = -(1.0 + log_y / log_variance) / y
    return f, f * g, f * (g * g + (1.0 + (log_y - 1.0) / log_variance) / (y * y))


@lru_cache(maxsize=16)
def lognormal_density(log_variance: float, shift: float, fraction: float,
                      variance: float) -> LogNormalDensity:
    """The shifted log-normal (8) with a gross-error component of weight `fraction`, built once per model."""
    return LogNormalDensity(log_variance, shift, fraction, variance)


def _lognormal_statistics(log_variance: float, shift: float, fraction: float, variance: float
                          ) -> tuple[float, float, float]:
    """(I_f, H, S) of the log-normal with its gross-error component, as `_statistics` for a mixture: on a grid
    even in ln(x + r_s) for the log-normal (its tail reaches exp(12 sqrt(R)) - r_s) and even in x for the
    gross-error component."""
    spread_ln = 12.0 * math.sqrt(log_variance)
    x = np.unique(np.concatenate([np.exp(np.linspace(-spread_ln, spread_ln, 200_001)) - shift,
                                  math.sqrt(variance) * np.linspace(-12.0, 12.0, 40_001)]))
    f_ln, d_ln, _ = _shifted_lognormal(x, log_variance, shift)
    g = fraction * np.exp(-0.5 * x * x / variance) / math.sqrt(2.0 * math.pi * variance)
    f = (1.0 - fraction) * f_ln + g
    df = (1.0 - fraction) * d_ln - g * x / variance
    return _grid_statistics(x, f, df)


@lru_cache(maxsize=64)
def _cached(components: tuple[tuple[float, float, float], ...]) -> RangeDensity:
    return RangeDensity(components)


def mixture_density(noise_components: tuple[tuple[float, float, float], ...], gross_error_fraction: float,
                    gross_error_variance: float) -> RangeDensity:
    """The mixture of `noise_components` (weight, mean, variance), built once per noise model: they share
    what the gross-error component N(0, gross_error_variance), of weight gross_error_fraction and last,
    leaves."""
    total = sum(c[0] for c in noise_components)
    scale = (1.0 - gross_error_fraction) / total
    components = tuple((float(w) * scale, float(m), float(v)) for w, m, v in noise_components)
    if gross_error_fraction > 0.0:
        components += ((float(gross_error_fraction), 0.0, float(gross_error_variance)),)
    return _cached(components)


def _statistics(components: tuple[tuple[float, float, float], ...]) -> tuple[float, float, float]:
    """(I_f, H, S) of the mixture, integrated numerically once per noise model: the Fisher information as a
    location family I_f = ∫ f'^2 / f dx (m^-2), the entropy H = E[-ln f(mu)] and the standard deviation S of
    -ln f(mu), mu ~ f (nats; the goodness-of-fit tests)."""
    # One fine grid per component (+-12 of its standard deviations), merged: the components' widths may
    # differ by orders of magnitude.
    x = np.unique(np.concatenate([m + math.sqrt(v) * np.linspace(-12.0, 12.0, 40_001) for _, m, v in components]))
    f = np.zeros_like(x)
    df = np.zeros_like(x)
    for w, m, v in components:
        g = w * np.exp(-0.5 * (x - m) ** 2 / v) / math.sqrt(2 * math.pi * v)
        f += g
        df -= g * (x - m) / v
    return _grid_statistics(x, f, df)


def _grid_statistics(x: np.ndarray, f: np.ndarray, df: np.ndarray) -> tuple[float, float, float]:
    """(I_f, H, S) by the trapezoid rule from a density f and its derivative df on the grid x."""
    mask = f > 1e-300
    x, f, df = x[mask], f[mask], df[mask]
    nll = -np.log(f)
    entropy = float(_trapezoid(f * nll, x))
    spread = float(_trapezoid(f * (nll - entropy) ** 2, x))
    return float(_trapezoid(df ** 2 / f, x)), entropy, math.sqrt(max(spread, 0.0))
