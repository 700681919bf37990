"""Raw-range relative position estimator: the ranges r_k = |p_k| + b + mu_k themselves, not the pseudo-linear
differences (12), (13). docs/estimation.md §8 gives the design, the reasons and the measurements.

Contract (`RawRange`; prediction (15) in the base class, `update` here):
- Fix: each range is kept with the relative displacement D summed to its epoch (at most `window`); every
  `solve_every` ranges (counted in ticks for a sensor slower than dt) `BatchWindow` minimises the window's
  negative log-likelihood under the assumed density (range_density.py) plus the prior carried by odometry.
  The position is fixed once the mirror solution is `ambiguity_threshold` nats worse, the batch covariance
  (P^-1 + I sum u u^T)^-1, widened where the cost is flatter than its Gaussian, is within `fix_max_variance`,
  and the best point fits the ranges (mean negative log-likelihood against the density's entropy). Until
  then `ambiguous` is True and `mirror` the other candidate; before the first solve a range moves the mean.
- Tracking: each range updates N(p^-, P) by moment matching on the range linearised at p^- (Masreliez 1975),
  p^+ = p^- + P H^T psi(e), P^+ = P - P H^T psi'(e) H P, psi the score of f_h = f * N(0, h); a monitor of the
  residuals' fit drops a fix the ranges no longer support (phase 1 again, from no prior).
- With `bias_variance` > 0 the range bias b is a state estimated with p (H = (u^T, 1)).
- `range_prev` of `update` is used once, for the first range of a sequence; `assimilate` while not fixed
  replaces the prior the window is solved with.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field

from agent.config import NonNegativeFloat, PositiveFloat, StrictModel
from agent.core.estimators.base import (
    REJECTED_RANGE,
    RelativePositionEstimator,
    UpdateOutcome,
    _as_range,
)
from agent.core.estimators.range_density import RangeDensity, lognormal_density, mixture_density
from agent.core.estimators.registry import EstimatorParams, register


class LogNormalNoiseParams(StrictModel):
    """A range noise known to be the paper's shifted log-normal (8): ln(mu + r_s) ~ N(0, R)."""

    log_variance: PositiveFloat = Field(description="R, variance of ln(mu + r_s)")
    shift: NonNegativeFloat = Field(description="r_s (m): the noise is above -r_s")


class RawRangeParams(EstimatorParams):
    """Batch fix over a window of ranges, then a moment-matching update on each range r = |p| + noise."""

    name: Literal["raw_range"] = "raw_range"
    noise_components: tuple[tuple[PositiveFloat, float, PositiveFloat], ...] = Field(
        ((0.8, 0.0, 0.4), (0.2, 0.0, 10.0)), min_length=1, max_length=8,
        description="assumed range-noise mixture, (weight, mean m, variance m^2) per component (Table II's)")
    gross_error_fraction: NonNegativeFloat = Field(
        1e-3, lt=1, description="weight of one more, very wide, zero-mean component for gross errors")
    gross_error_variance: PositiveFloat = Field(1e4, description="variance of that component (m^2)")
    tracking_lognormal: LogNormalNoiseParams | None = Field(
        None, description="a noise known to be the log-normal (8): tracking uses its exact density; None: "
                          "noise_components")
    window: int = Field(300, ge=5, le=100_000,
                        description="most ranges kept for the batch fix while the position is not yet fixed")
    min_ranges: int = Field(20, ge=3, le=100_000, description="ranges needed before the first batch solve")
    solve_every: int = Field(5, ge=1, le=10_000,
                             description="while not fixed, the batch is solved every this many ranges")
    ambiguity_threshold: PositiveFloat = Field(
        9.2, description="the fix is unique once the mirror's negative log-likelihood exceeds the best's by "
                         "this (nats)")
    fix_max_variance: PositiveFloat = Field(
        0.05, description="and once the batch covariance's largest eigenvalue is at most this (m^2)")
    batch_iterations: int = Field(20, ge=1, le=1000,
                                  description="Gauss-Newton/EM iterations of a batch solve")
    tolerance: PositiveFloat = Field(1e-6, description="stop iterating when the step is below this (m)")
    monitor_length: int = Field(100, ge=10, le=100_000,
                                description="ranges the tracking monitor averages the residuals' fit over")
    monitor_sigmas: PositiveFloat = Field(
        5.0, description="the fix is dropped once the monitor's mean NLL exceeds the entropy by this many "
                         "standard errors")
    bias_variance: NonNegativeFloat = Field(
        0.0, description="prior variance (m^2) of a constant range bias b, r = |p| + b + noise; 0: no bias "
                         "state")


# Smallest distance from an anchor at which a range is used; closer, its direction is undefined.
MIN_DISTANCE = 1e-9
# Sandwich covariance: pseudo-ranges at I_f a batch's score moments are shrunk towards, and the length of
# the tracking phase's running means (ranges).
SANDWICH_PRIOR = 20
SANDWICH_LENGTH = 200
# Step halvings of one Gauss-Newton step before the solve stops where it is (a step of 2^-8).
MAX_HALVINGS = 8
# The covariance a dropped fix starts phase 1 again with: no prior.
NO_PRIOR_VARIANCE = 1e12
# A batch solve switches from EM to Newton steps once a step is this short (m): near the minimum.
NEWTON_REACH = 0.05
# Cold start points are scouted with this many iterations each, and the best SCOUTED_KEPT solved fully.
SCOUT_ITERATIONS = 3
SCOUTED_KEPT = 2
# Before a fix, its covariance is checked against the window's cost this many standard deviations out along
# each principal axis, and widened where the cost rises less than a Gaussian's (at most MAX_WIDENING times).
LAPLACE_REACH = 4.0
MAX_WIDENING = 1e6


def _due(ranges: int, ticks: float, count: int, least: int = 1) -> bool:
    """A solve is due once `count` ranges have come, or, from a sensor slower than the tick, once the ranges
    span `count` ticks (and are at least `least`): the schedule is set in ranges at one range per tick, so
    that a 1 Hz sensor at dt = 0.1 s solves first after 2 s, as a 10 Hz one does, not after 20 s."""
    return ranges >= count or (ranges >= least and ticks >= count - 1e-6)


def _inverse(a11: float, a12: float, a22: float) -> tuple[float, float, float]:
    det = a11 * a22 - a12 * a12
    return a22 / det, -a12 / det, a11 / det


def _inverse3(a11: float, a12: float, a22: float, c1: float, c2: float,
              c3: float) -> tuple[float, float, float, float, float, float]:
    """The inverse of the symmetric [[A, c], [c^T, c3]], A = [[a11, a12], [a12, a22]], by b's Schur complement
    s = c3 - c^T A^-1 c: (A^-1 + A^-1 c c^T A^-1 / s, -A^-1 c / s, 1 / s) as (x11, x12, x22, xb1, xb2, xbb)."""
    j11, j12, j22 = _inverse(a11, a12, a22)
    k1, k2 = j11 * c1 + j12 * c2, j12 * c1 + j22 * c2          # A^-1 c
    s = c3 - c1 * k1 - c2 * k2
    return j11 + k1 * k1 / s, j12 + k1 * k2 / s, j22 + k2 * k2 / s, -k1 / s, -k2 / s, 1.0 / s


def _step(a11: float, a12: float, a22: float, bias_row: tuple[float, float, float] | None, g1: float, g2: float,
          g3: float, damp: bool) -> tuple[float, float, float] | None:
    """The step s solving M s = g, M = [[A, c], [c^T, c3]] (A the 2x2 matrix of p, (c, c3) = bias_row; A alone
    without b). b is eliminated first: (A - c c^T / c3) s_p = g_p - c g3 / c3, s_b = (g3 - c^T s_p) / c3.
    None if M is not positive definite, unless `damp`, which then adds 1e-6 of its scale to the diagonal."""
    if bias_row is not None:
        c1, c2, c3 = bias_row
        if not c3 > 0.0:
            return None
        a11, a12, a22 = a11 - c1 * c1 / c3, a12 - c1 * c2 / c3, a22 - c2 * c2 / c3
        g1, g2 = g1 - c1 * g3 / c3, g2 - c2 * g3 / c3
    det = a11 * a22 - a12 * a12
    if not (a11 > 0.0 and det > 1e-12 * a11 * a22):
        if not damp:
            return None
        if not det > 1e-12 * max(a11 * a22, 1e-300):
            damping = 1e-6 * max(a11, a22, 1e-12)
            a11 += damping
            a22 += damping
            det = a11 * a22 - a12 * a12
    sx = (a22 * g1 - a12 * g2) / det
    sy = (a11 * g2 - a12 * g1) / det
    if bias_row is None:
        return sx, sy, 0.0
    return sx, sy, (g3 - c1 * sx - c2 * sy) / c3


def _sandwich(psi2: float, dpsi: float, fisher: float) -> float:
    """Information per range for the covariance: the sandwich (mean psi')^2 / mean psi^2, which is I_f when the
    assumed density is the noise's and less when it is only an approximation (a fitted mixture, a bias), kept
    within [I_f / 20, I_f]."""
    if dpsi <= 0.0 or psi2 <= 0.0:
        return fisher / 20.0
    return min(max(dpsi * dpsi / psi2, fisher / 20.0), fisher)


def _moments(c: np.ndarray, ux: np.ndarray, uy: np.ndarray) -> tuple[float, float, float]:
    """sum c u u^T over the window as (xx, xy, yy)."""
    cx = c * ux
    return float(cx @ ux), float(cx @ uy), float((c * uy) @ uy)


def _largest_eigenvalue(a11: float, a12: float, a22: float) -> float:
    half = 0.5 * (a11 + a22)
    return half + math.sqrt(max(0.25 * (a11 - a22) ** 2 + a12 * a12, 0.0))


def _axes(a11: float, a12: float, a22: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """The principal axes of the symmetric [[a11, a12], [a12, a22]]: (eigenvalue, unit vector x, y), the
    largest first."""
    largest = _largest_eigenvalue(a11, a12, a22)
    # Of the two forms of the eigenvector, the longer one (the other can vanish to rounding).
    vx, vy = max(((largest - a22, a12), (a12, largest - a11)), key=lambda v: abs(v[0]) + abs(v[1]))
    norm = math.hypot(vx, vy)
    vx, vy = (vx / norm, vy / norm) if norm > 0.0 else (1.0, 0.0)
    return (largest, vx, vy), (a11 + a22 - largest, -vy, vx)


class BatchWindow:
    """Negative log-likelihood of the window's ranges plus a Gaussian prior, and its minimiser (numpy).

    With a range bias (`bias_variance` > 0) the unknowns are x = (p, b), the ranges r_m = |p - a_m| + b + noise
    and b has the prior N(0, bias_variance); without one b = 0 and the arithmetic is that of p alone."""

    def __init__(self, ranges: np.ndarray, anchors: np.ndarray, density: RangeDensity,
                 prior: tuple[float, ...], bias_variance: float = 0.0) -> None:
        self.r = ranges                       # (N,)
        self.a = anchors                      # (N, 2): p_m = p - a_m
        self.ax, self.ay = anchors[:, 0].copy(), anchors[:, 1].copy()    # contiguous: every evaluation reads them
        self.density = density
        qx, qy, q11, q12, q22 = prior
        self.q = (qx, qy)
        self.i11, self.i12, self.i22 = _inverse(q11, q12, q22)
        self.ib = 1.0 / bias_variance if bias_variance > 0.0 else 0.0   # prior information of b; 0: no b

    def prior_term(self, px: float, py: float, b: float = 0.0) -> float:
        ex, ey = px - self.q[0], py - self.q[1]
        return 0.5 * (self.i11 * ex * ex + 2 * self.i12 * ex * ey + self.i22 * ey * ey + self.ib * b * b)

    def evaluate(self, px: float, py: float, b: float = 0.0) -> tuple[float, tuple]:
        """The cost at (p, b), and what `derivatives` needs to go on from there (a line search's rejected trial
        needs the cost alone)."""
        dx = px - self.ax
        dy = py - self.ay
        d = np.maximum(np.hypot(dx, dy), MIN_DISTANCE)
        nll, g, sc = self.density.evaluate(self.r - d - b if self.ib else self.r - d)
        return nll + self.prior_term(px, py, b), (dx, dy, d, g, sc)

    def derivatives(self, at: tuple) -> tuple[np.ndarray, ...]:
        """From `evaluate`'s state: the unit vectors ux, uy of p - a_m, the distances d, the residuals' score
        psi = -(ln f)'(e), e = r - d - b, and the density's (g, sc, gamma_c s_c) for `em_precision` and
        `curvature` (range_density.py), arrays of N (K by N)."""
        dx, dy, d, g, sc = at
        psi, weighted = self.density.score(g, sc)
        return dx / d, dy / d, d, psi, g, sc, weighted

    def solve(self, px: float, py: float, iterations: int, tolerance: float,
              b: float = 0.0, near: bool = False) -> tuple[float, float, float, float, tuple]:
        """EM steps from (p, b), then Newton's method once a step is shorter than NEWTON_REACH, with step
        halving; (px, py, b, cost, state) at the end, state `evaluate`'s at the last point evaluated (within one
        converged step of the end). Both use the exact gradient sum psi u - P^-1 (p - p_0) (and
        sum psi - b / bias_variance for b). EM's matrix sum w u u^T + P^-1 (w = sum_c gamma_c / sigma_c^2) is
        positive definite everywhere and its steps are safe far from a minimum, but converge only linearly;
        the Hessian sum psi' u u^T - sum (psi / d) (I - u u^T) + P^-1 converges quadratically near one (it
        halves the cost of a solve) and is used there while positive definite. With b, each matrix gains the
        row (sum c u^T, sum c + 1 / bias_variance), c = psi' or w, and b is eliminated first (_step)."""
        density = self.density
        cost, at = self.evaluate(px, py, b)
        ux, uy, d, psi, g, sc, weighted = self.derivatives(at)
        newton = near
        full_newton, last = False, math.inf     # the last step a whole Newton step, and its length
        for _ in range(iterations):
            g1 = float(psi @ ux) + self.i11 * (self.q[0] - px) + self.i12 * (self.q[1] - py)
            g2 = float(psi @ uy) + self.i12 * (self.q[0] - px) + self.i22 * (self.q[1] - py)
            g3 = float(psi.sum()) - self.ib * b if self.ib else 0.0
            step_p = newton_step = None
            w = density.em_precision(g)
            if newton:
                dpsi = density.curvature(weighted, sc, psi, w)
                # sum psi' u u^T - sum (psi / d)(I - u u^T) = sum (psi' + psi / d) u u^T - (sum psi / d) I
                bend = psi / d
                c11, c12, c22 = _moments(dpsi + bend, ux, uy)
                turn = float(bend.sum())
                bias_row = self._bias_row(dpsi, ux, uy)
                step_p = newton_step = _step(c11 - turn + self.i11, c12 + self.i12, c22 - turn + self.i22,
                                             bias_row, g1, g2, g3, damp=False)
            if step_p is None:
                a11, a12, a22 = _moments(w, ux, uy)
                step_p = _step(a11 + self.i11, a12 + self.i12, a22 + self.i22, self._bias_row(w, ux, uy),
                               g1, g2, g3, damp=True)
                if step_p is None:
                    break
            sx, sy, sb = step_p
            length = math.hypot(sx, sy, sb)
            if length <= tolerance or (full_newton and length < last and length ** 3 <= tolerance * last * last):
                # Converged: the step is below the tolerance, or Newton's quadratic convergence, its rate
                # measured on the last two full steps (next ~ length^3 / last^2), puts the next one below it.
                # The step is taken without evaluating the cost there: for a Newton step (s = H^-1 g) the
                # quadratic model gives it, the cost less g^T s / 2, to the third order in the step; for an EM
                # step (below the tolerance) the cost before it is as near.
                px, py, b = px + sx, py + sy, b + sb
                if step_p is newton_step:
                    cost -= 0.5 * (g1 * sx + g2 * sy + g3 * sb)
                break
            step = 1.0
            for _ in range(MAX_HALVINGS):
                trial, trial_at = self.evaluate(px + step * sx, py + step * sy, b + step * sb)
                if trial <= cost + 1e-12 * abs(cost):
                    break
                step *= 0.5
            else:
                break
            px, py, b = px + step * sx, py + step * sy, b + step * sb
            cost, at = trial, trial_at
            ux, uy, d, psi, g, sc, weighted = self.derivatives(at)
            full_newton, last = newton and step == 1.0 and step_p is newton_step, step * length
            if last <= tolerance:
                break
            newton = newton or last <= NEWTON_REACH
        return px, py, b, cost, at

    def _bias_row(self, c: np.ndarray, ux: np.ndarray, uy: np.ndarray) -> tuple[float, float, float] | None:
        """(sum c ux, sum c uy, sum c + 1 / bias_variance): b's row of the matrix; None without b."""
        if not self.ib:
            return None
        return float(c @ ux), float(c @ uy), float(c.sum()) + self.ib

    def score_moments(self, at: tuple) -> tuple[float, float, int]:
        """(sum of psi^2, sum of psi', N) of the ranges' residuals at a point `evaluate` gave `at` for, under the
        assumed density: the two estimates of the Fisher information the sandwich compares (module docstring)."""
        _, _, _, psi, g, sc, weighted = self.derivatives(at)
        dpsi = self.density.curvature(weighted, sc, psi, self.density.em_precision(g))
        return float((psi * psi).sum()), float(dpsi.sum()), len(psi)

    def covariance(self, px: float, py: float, fisher: float) -> tuple[float, ...]:
        """The inverse of P^-1 + I_f sum u u^T at p: (c11, c12, c22); with b, of the information of (p, b),
        I_f sum (u, 1)(u, 1)^T + diag(P^-1, 1 / bias_variance): (c11, c12, c22, cxb, cyb, cbb)."""
        dx = px - self.a[:, 0]
        dy = py - self.a[:, 1]
        d = np.maximum(np.hypot(dx, dy), MIN_DISTANCE)
        ux, uy = dx / d, dy / d
        s11, s12, s22 = float(ux @ ux), float(ux @ uy), float(uy @ uy)
        a11, a12, a22 = fisher * s11 + self.i11, fisher * s12 + self.i12, fisher * s22 + self.i22
        if not self.ib:
            return _inverse(a11, a12, a22)
        f1, f2, f3 = fisher * float(ux.sum()), fisher * float(uy.sum()), fisher * len(ux) + self.ib
        return _inverse3(a11, a12, a22, f1, f2, f3)

    def widened(self, px: float, py: float, b: float, c11: float, c12: float,
                c22: float) -> tuple[float, float, float]:
        """The covariance (c11, c12, c22) of p at the minimum (p, b), each principal axis's variance lam
        widened where the cost rises less than a Gaussian's, k^2 / 2 at k = LAPLACE_REACH standard deviations
        out on the flatter side: lam k^2 / (2 rise), never narrowed. b stays where it is."""
        base = self.evaluate(px, py, b)[0]
        least = 0.5 * LAPLACE_REACH ** 2 / MAX_WIDENING
        out11 = out12 = out22 = 0.0
        for lam, vx, vy in _axes(c11, c12, c22):
            reach = LAPLACE_REACH * math.sqrt(max(lam, 0.0))
            rise = min(self.evaluate(px + sign * reach * vx, py + sign * reach * vy, b)[0]
                       for sign in (1.0, -1.0)) - base
            lam *= max(1.0, 0.5 * LAPLACE_REACH ** 2 / max(rise, least))
            out11, out12, out22 = out11 + lam * vx * vx, out12 + lam * vx * vy, out22 + lam * vy * vy
        return out11, out12, out22

    def line(self) -> tuple[float, float, float, float]:
        """Centroid (cx, cy) and unit direction (tx, ty) of the anchors' principal line."""
        cx, cy = (float(v) for v in self.a.mean(axis=0))
        x = self.a[:, 0] - cx
        y = self.a[:, 1] - cy
        sxx, sxy, syy = float((x * x).sum()), float((x * y).sum()), float((y * y).sum())
        angle = 0.5 * math.atan2(2 * sxy, sxx - syy)
        return cx, cy, math.cos(angle), math.sin(angle)

    def line_candidates(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """The two points at +-beta from the anchors' line: r_m^2 - s_m^2 = -2 alpha s_m + (alpha^2 + beta^2),
        s_m the anchors' coordinate along the line, fitted by least squares (beta = 0 if the fit says less)."""
        cx, cy, tx, ty = self.line()
        s = (self.a[:, 0] - cx) * tx + (self.a[:, 1] - cy) * ty
        y = self.r * self.r - s * s
        s_mean, y_mean = float(s.mean()), float(y.mean())
        spread = float(((s - s_mean) ** 2).sum())
        alpha = -0.5 * float(((s - s_mean) * (y - y_mean)).sum()) / spread if spread > 1e-12 else 0.0
        c = y_mean + 2 * alpha * s_mean
        beta = math.sqrt(max(c - alpha * alpha, 0.0))
        bx, by = cx + alpha * tx, cy + alpha * ty
        return (bx - beta * ty, by + beta * tx), (bx + beta * ty, by - beta * tx)

    def centroid_candidates(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """The two points at the mean range straight across the anchors' line from their centroid."""
        cx, cy, tx, ty = self.line()
        reach = math.sqrt(float((self.r * self.r).mean()))
        return (cx - reach * ty, cy + reach * tx), (cx + reach * ty, cy - reach * tx)

    def mirror(self, px: float, py: float) -> tuple[float, float]:
        """The reflection of p across the anchors' line."""
        cx, cy, tx, ty = self.line()
        vx, vy = px - cx, py - cy
        along = vx * tx + vy * ty
        return cx + 2 * along * tx - vx, cy + 2 * along * ty - vy


@register
class RawRange(RelativePositionEstimator):
    """Batch fix over a window of raw ranges, mirror ambiguity explicit, then moment-matching updates on
    r = |p| (module docstring)."""

    name = "raw_range"
    Params = RawRangeParams
    table_order = 6

    # ----- reading -----
    @property
    def ambiguous(self) -> bool:
        """True until the position is fixed: before the first batch solve, and while p and its mirror
        across the line of the relative motion explain the ranges nearly equally well."""
        return not self._fixed

    @property
    def fixed(self) -> bool:
        return self._fixed

    @property
    def mirror(self) -> np.ndarray | None:
        """The other candidate while ambiguous (None before the first solve, when there is none, and once
        fixed)."""
        return None if self._alt is None or self._fixed else np.array(self._alt)

    @property
    def bias(self) -> float:
        """The estimated range bias b (m): 0 unless `bias_variance` > 0."""
        return self._b

    @property
    def refixes(self) -> int:
        """How many times a fix was dropped by the tracking monitor."""
        return self._refixes

    # ----- life cycle -----
    def _reset_extra(self) -> None:
        p = self.params
        self._density = density = mixture_density(p.noise_components, p.gross_error_fraction,
                                                  p.gross_error_variance)
        self._fisher, self._entropy, self._nll_spread = density.fisher, density.entropy, density.spread
        # Tracking's exact density of a known log-normal noise (None: the mixture's): the noise's own, so no
        # sandwich share is needed once it takes over.
        exact = p.tracking_lognormal
        self._exact = None if exact is None else lognormal_density(
            exact.log_variance, exact.shift, p.gross_error_fraction, p.gross_error_variance)
        # Sandwich: running means of psi^2 and psi' of the residuals (both I_f when the density is right), and
        # the information per range the covariance uses, (mean psi')^2 / mean psi^2 within [I_f / 20, I_f].
        self._psi2 = self._dpsi = self._info = self._fisher
        self._fixed = False
        self._cx = self._cy = 0.0                      # cumulative relative displacement D
        self._window: list[tuple[float, float, float]] = []   # (range, Dx, Dy) per range epoch
        self._prior = (self._px, self._py, self._p11, self._p12, self._p22)   # carried to now by odometry
        self._alt: tuple[float, float] | None = None
        self._unsolved = 0                             # ranges since the last batch solve
        self._unsolved_ticks = 0.0                     # and ticks (dt) they span
        self._solves = 0
        self._evidence = 0.0                           # other minimum's cost minus the best's (nats)
        self._consistent = False                       # the last batch solution passed the goodness-of-fit test
        self._monitor = 0.0                            # running mean of the tracking residuals' NLL (nats)
        self._tracked = 0                              # ranges since the fix
        self._refixes = 0
        self._reset_bias()

    def _reset_bias(self) -> None:
        """The range bias b and its covariance with p (pxb, pyb) and its own (pbb): b's prior N(0, bias_variance);
        all 0, and b out of every equation, without one."""
        self._b = self._pxb = self._pyb = 0.0
        self._pbb = self.params.bias_variance

    def assimilate(self, position: np.ndarray, covariance: np.ndarray) -> bool:
        if not super().assimilate(position, covariance):
            return False
        # The fused position's correlation with b is unknown: dropped (the 3x3 stays positive definite).
        self._pxb = self._pyb = 0.0
        if not self._fixed:
            self._prior = (self._px, self._py, self._p11, self._p12, self._p22)
            self._alt = None
        return True

    # ----- prediction -----
    def predict(self, displacement, intervals: float = 1.0) -> bool:
        before_x, before_y, before_steps = self._pair_dx, self._pair_dy, self._pair_steps
        if not super().predict(displacement, intervals):
            return False
        dx, dy = self._pair_dx - before_x, self._pair_dy - before_y
        if not self._fixed:
            self._cx += dx
            self._cy += dy
            qx, qy, q11, q12, q22 = self._prior
            inflation = 2.0 * self.relative.displacement_variance * (self._pair_steps - before_steps)
            self._prior = (qx + dx, qy + dy, q11 + inflation, q12, q22 + inflation)
            if self._alt is not None:
                self._alt = (self._alt[0] + dx, self._alt[1] + dy)
        return True

    # ----- correction -----
    def update(self, range_prev: float, range_now: float) -> UpdateOutcome:
        # Both ranges are checked, as in every estimator, though only the first pair uses range_prev.
        r = _as_range(range_now, self.relative.max_range)
        if math.isnan(r) or math.isnan(_as_range(range_prev, self.relative.max_range)):
            self._diag.rejected += 1
            return self._record(UpdateOutcome(accepted=False, reason=REJECTED_RANGE))
        saved = (self._px, self._py, self._p11, self._p12, self._p22)
        if self._fixed:
            outcome = self._track(r)
        else:
            outcome = self._collect(range_prev, r)
        return self._settle(saved, outcome)

    def _collect(self, range_prev: float, r: float) -> UpdateOutcome:
        """Phase 1: keep the range, and solve the window every `solve_every` ranges."""
        p = self.params
        if not self._window and self._solves == 0:
            first = _as_range(range_prev, self.relative.max_range)
            if not math.isnan(first) and self._pair_steps > 0:
                # The range of the epoch `mark_range_epoch` declared, before this pair's displacement.
                self._window.append((first, self._cx - self._pair_dx, self._cy - self._pair_dy))
        self._window.append((r, self._cx, self._cy))
        if len(self._window) > p.window:
            del self._window[: len(self._window) - p.window]
        self._unsolved += 1
        self._unsolved_ticks += self._pair_steps
        if self._solves == 0:
            # Pairs that start together would solve on the same ticks; the first solve waits up to
            # solve_every - 1 more ranges, by the millimetres of the pair's first range, which differ.
            stagger = int(self._window[0][0] * 1e3) % p.solve_every
            waiting = not _due(len(self._window), self._unsolved_ticks + 1, p.min_ranges + stagger, 3)
        else:
            waiting = not _due(self._unsolved, self._unsolved_ticks, p.solve_every)
        if waiting:
            if self._solves == 0:
                # Before the first solve the range moves the estimate as in tracking, so that it does not stand
                # still for seconds at one range a second; the covariance stays the prior's (module docstring).
                self._moment_match(r, shrink=False)
            return UpdateOutcome(accepted=True, reason="collecting")
        self._unsolved = 0
        self._unsolved_ticks = 0.0
        return self._solve()

    def _solve(self) -> UpdateOutcome:
        p = self.params
        data = np.array(self._window)
        anchors = np.column_stack([self._cx - data[:, 1], self._cy - data[:, 2]])
        batch = BatchWindow(data[:, 0], anchors, self._density, self._prior, p.bias_variance)
        starts = []
        if self._solves > 0:
            starts.append((self._px, self._py, self._b))
            if self._alt is not None:
                starts.append((*self._alt, self._b))
        if self._solves == 0 or not self._consistent:
            # Cold: both line candidates, the points straight across the anchors' centroid, the prior's mean.
            starts += [(x, y, 0.0) for x, y in (*batch.line_candidates(), *batch.centroid_candidates(),
                                                self._prior[:2])]
        if len(starts) > SCOUTED_KEPT:
            # A few iterations from every cold start point, then only the most promising are solved fully.
            scouted = sorted((batch.solve(x, y, SCOUT_ITERATIONS, p.tolerance, b) for x, y, b in starts),
                             key=lambda s: s[3])
            starts = [s[:3] for s in scouted[:SCOUTED_KEPT]]
        # Warm (the last solve consistent): the starts are that solve's points, so Newton steps from the first.
        warm = self._solves > 0 and self._consistent
        solutions = [batch.solve(x, y, p.batch_iterations, p.tolerance, b, near=warm) for x, y, b in starts]
        bx, by, bb, best, at = min(solutions, key=lambda s: s[3])
        mx, my = batch.mirror(bx, by)
        mirror = batch.solve(mx, my, p.batch_iterations, p.tolerance, bb, near=warm)
        psi2, dpsi, n = batch.score_moments(at)     # at the best solution's last evaluated point
        self._psi2 = (SANDWICH_PRIOR * self._fisher + psi2) / (SANDWICH_PRIOR + n)
        self._dpsi = (SANDWICH_PRIOR * self._fisher + dpsi) / (SANDWICH_PRIOR + n)
        self._info = self._sandwich()
        c11, c12, c22, *bias = batch.covariance(bx, by, self._info)
        self._b = bb
        self._pxb, self._pyb, self._pbb = bias or (0.0, 0.0, 0.0)
        largest = _largest_eigenvalue(c11, c12, c22)
        smallest = c11 + c22 - largest
        # Another local minimum, however near: one the solver from the mirror point did not leave. Only when
        # it converged back onto the best point is the minimum unique (the path has turned enough).
        same = max(1e-3, 0.25 * math.sqrt(max(smallest, 0.0)))
        separate = [s for s in (*solutions, mirror) if math.hypot(s[0] - bx, s[1] - by) > same]
        self._solves += 1
        # Goodness of fit: the mean negative log-likelihood per range of the best point against the density's
        # entropy, with 4 standard errors and 0.2 nats of slack for a density that is only approximate. A
        # point that explains the ranges only as gross errors (a wrong basin) fails it.
        n = len(data)
        nll = (best - batch.prior_term(bx, by, bb)) / n
        self._consistent = nll <= self._entropy + 0.2 + 4.0 * self._nll_spread / math.sqrt(n)
        if separate:
            ax, ay, _, alt_cost, _ = min(separate, key=lambda s: s[3])
            evidence = alt_cost - best
        else:
            ax = ay = None
            evidence = math.inf
        self._evidence = evidence
        self._px, self._py = bx, by
        ready = evidence >= p.ambiguity_threshold and self._consistent
        if ready and largest <= p.fix_max_variance:
            # About to fix: the Gaussian it hands to tracking must not claim more than the window's cost
            # supports out in its tails (a flat or bent likelihood along the path); widened, it may have to wait.
            c11, c12, c22 = batch.widened(bx, by, bb, c11, c12, c22)
            largest = _largest_eigenvalue(c11, c12, c22)
        if ready and largest <= p.fix_max_variance:
            self._fixed = True
            self._alt = None
            self._window = []
            self._monitor = self._tracking_fit()[0]
            self._tracked = 0
            self._p11, self._p12, self._p22 = c11, c12, c22
            return UpdateOutcome(accepted=True, reason="fixed", iterations=self._solves, weight=1.0)
        if ax is None:
            self._alt = None
            self._p11, self._p12, self._p22 = c11, c12, c22
        else:
            self._alt = (ax, ay)
            share = 1.0 / (1.0 + math.exp(min(evidence, 700.0)))
            vx, vy = ax - bx, ay - by
            self._p11, self._p12, self._p22 = c11 + share * vx * vx, c12 + share * vx * vy, c22 + share * vy * vy
        return UpdateOutcome(accepted=True, reason="ambiguous", iterations=self._solves,
                             weight=1.0 if ax is None else 1.0 / (1.0 + math.exp(-min(evidence, 700.0))))

    def _track(self, r: float) -> UpdateOutcome:
        """Phase 2: the moment-matching update of a Gaussian prior N(p^-, P) by one range (module docstring)."""
        step = self._moment_match(r)
        if step is None:
            return UpdateOutcome(accepted=True, reason="at the origin: range direction undefined")
        nll, dpsi, innovation, h = step
        self._tracked += 1
        reason = "fix dropped: the ranges no longer fit" if self._watch(nll) else ""
        # weight: the share of the prior's variance along the range this range removed, h psi' (for a Gaussian
        # noise the Kalman gain's h / (sigma^2 + h); about 0 for a gross error).
        information = self._exact.fisher if self._exact is not None else self._info
        return UpdateOutcome(accepted=True, reason=reason, iterations=1, innovation=innovation,
                             innovation_variance=h + 1.0 / information, weight=dpsi * h if h > 0.0 else 1.0)

    def _moment_match(self, r: float, shrink: bool = True) -> tuple[float, float, float, float] | None:
        """The moment-matching update of N((p, b), P) by one range r = |p| + b + noise, linearised at p^-:
        H = (u^T, 1), k = P H^T, h = H k, e = r - |p^-| - b^-, psi and psi' the score at e of f_h widened by
        the range's curvature (v^T P v / |p|)^2 / 2 (module docstring):
            (p, b)^+ = (p, b)^- + k psi(e),    P^+ = P - k k^T psi'(e) I / I_f
        with I / I_f the sandwich share (tracking updates the sandwich's running means first). Without b,
        H = u^T and the b terms are 0. Without `shrink` only the mean moves. Plain floats. Returns
        (-ln f_h(e), psi', e, h), or None at the origin, where u is undefined."""
        px, py, p11, p12, p22 = self._px, self._py, self._p11, self._p12, self._p22
        pxb, pyb, pbb = self._pxb, self._pyb, self._pbb
        d = math.hypot(px, py)
        if d < MIN_DISTANCE:
            return None
        ux, uy = px / d, py / d
        hx = p11 * ux + p12 * uy + pxb               # P H^T
        hy = p12 * ux + p22 * uy + pyb
        hb = pxb * ux + pyb * uy + pbb
        h = ux * hx + uy * hy + hb                   # the prior's variance along the range
        across = uy * uy * p11 - 2.0 * ux * uy * p12 + ux * ux * p22
        innovation = r - d - self._b
        exact = self._exact if self._fixed else None
        nll, psi, dpsi = (exact or self._density).predictive(innovation, h + 0.5 * (across / d) ** 2)
        if self._fixed and exact is None:
            self._psi2 += (psi * psi - self._psi2) / SANDWICH_LENGTH
            self._dpsi += (dpsi - self._dpsi) / SANDWICH_LENGTH
            self._info = self._sandwich()
        self._px, self._py = px + hx * psi, py + hy * psi
        if pbb > 0.0:
            self._b += hb * psi
        if not shrink:
            return nll, dpsi, innovation, h
        # Where the assumed density only approximates the noise, the sandwich says how much of its
        # information a range really carries; the covariance shrinks by that share only.
        share = dpsi if exact is not None else dpsi * self._info / self._fisher
        self._p11, self._p12, self._p22 = p11 - hx * hx * share, p12 - hx * hy * share, p22 - hy * hy * share
        if pbb > 0.0:
            self._pxb, self._pyb, self._pbb = pxb - hx * hb * share, pyb - hy * hb * share, pbb - hb * hb * share
        return nll, dpsi, innovation, h

    def _sandwich(self) -> float:
        return _sandwich(self._psi2, self._dpsi, self._fisher)

    def _tracking_fit(self) -> tuple[float, float]:
        """(H, S), the entropy and the spread of -ln f of the density tracking uses (the monitor's yardstick):
        the exact one's when there is one, else the mixture's."""
        if self._exact is not None:
            return self._exact.entropy, self._exact.spread
        return self._entropy, self._nll_spread

    def _watch(self, nll: float) -> bool:
        """Tracking monitor: an exponential mean over about `monitor_length` ranges of the predicted residuals'
        negative log-likelihood; once it exceeds the density's entropy by `monitor_sigmas` of its standard
        error (plus 0.2 nats for a density that is only approximate), drop the fix and start phase 1 again
        from no prior at the current estimate. True if it did."""
        p = self.params
        length = p.monitor_length
        self._monitor += (nll - self._monitor) / length
        if self._tracked < length:
            return False
        # The exponential mean's standard error: S sqrt(1 / (2 L - 1)).
        entropy, spread = self._tracking_fit()
        limit = entropy + 0.2 + p.monitor_sigmas * spread / math.sqrt(2.0 * length - 1.0)
        if self._monitor <= limit:
            return False
        self._refixes += 1
        self._fixed = False
        self._window = []
        self._alt = None
        self._solves = 0
        self._unsolved = 0
        self._unsolved_ticks = 0.0
        self._consistent = False
        self._p11 = self._p22 = NO_PRIOR_VARIANCE
        self._p12 = 0.0
        self._prior = (self._px, self._py, self._p11, self._p12, self._p22)
        self._reset_bias()
        return True

    # ----- saving and restoring -----
    def _export_extra(self) -> dict:
        return {
            "fixed": self._fixed, "cumulative": [self._cx, self._cy],
            "window": [list(entry) for entry in self._window], "prior": list(self._prior),
            "mirror": None if self._alt is None else list(self._alt), "unsolved": self._unsolved,
            "unsolved_ticks": self._unsolved_ticks,
            "solves": self._solves, "evidence": None if math.isinf(self._evidence) else self._evidence,
            "consistent": self._consistent, "monitor": self._monitor, "tracked": self._tracked,
            "refixes": self._refixes, "sandwich": [self._psi2, self._dpsi, self._info],
            "bias": [self._b, self._pxb, self._pyb, self._pbb],
        }

    def _restore_extra(self, extra: dict) -> None:
        self._fixed = bool(extra["fixed"])
        self._cx, self._cy = (float(v) for v in extra["cumulative"])
        self._window = [(float(r), float(x), float(y)) for r, x, y in extra["window"]]
        self._prior = tuple(float(v) for v in extra["prior"])
        self._alt = None if extra["mirror"] is None else (float(extra["mirror"][0]), float(extra["mirror"][1]))
        self._unsolved = int(extra["unsolved"])
        self._unsolved_ticks = float(extra.get("unsolved_ticks", self._unsolved))
        self._solves = int(extra["solves"])
        self._evidence = math.inf if extra["evidence"] is None else float(extra["evidence"])
        self._consistent = bool(extra["consistent"])
        self._monitor = float(extra["monitor"])
        self._tracked = int(extra["tracked"])
        self._refixes = int(extra["refixes"])
        self._psi2, self._dpsi, self._info = (float(v) for v in extra["sandwich"])
        if "bias" in extra:
            self._b, self._pxb, self._pyb, self._pbb = (float(v) for v in extra["bias"])
