"""The raw-range estimator's batch fix (raw_range.py): the negative log-likelihood of a window of ranges under
the assumed density (range_density.py) plus a Gaussian prior, its minimiser (EM steps far from the minimum,
Newton's near it, with step halving), the cold start points, the mirror across the anchors' line, the
covariance (P^-1 + I sum u u^T)^-1 and its widening where the cost is flatter than its Gaussian.
docs/estimation.md §8 gives the design and the measurements.
"""

from __future__ import annotations

import math

import numpy as np

from agent.core.estimators.range_density import RangeDensity

# Smallest distance from an anchor at which a range is used; closer, its direction is undefined.
MIN_DISTANCE = 1e-9
# Step halvings of one Gauss-Newton step before the solve stops where it is (a step of 2^-8).
MAX_HALVINGS = 8
# A batch solve switches from EM to Newton steps once a step is this short (m): near the minimum.
NEWTON_REACH = 0.05
# Before a fix, its covariance is checked against the window's cost this many standard deviations out along
# each principal axis, and widened where the cost rises less than a Gaussian's (at most MAX_WIDENING times).
LAPLACE_REACH = 4.0
MAX_WIDENING = 1e6


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
