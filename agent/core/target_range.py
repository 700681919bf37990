"""The target's range along our bearing, from the neighbours' target estimates and the ranges to them.

A target filter started without an estimate knows the target's direction from its bearing but not its
distance (docs/equations.md D19). If the target lies at s u (u our unit line of sight), a neighbour j whose
own target estimate is p_jo sits at p_ij = s u - p_jo, so the measured range to it says

    r_ij = | s u - p_jo |                                                      (R1)

one equation in the one unknown s. Each neighbour gives two roots (the line of sight cuts the circle of
radius r_ij about p_jo twice); two neighbours not in line with us pick one. Weighted least squares over all
of them (Gauss-Newton from every root) gives s and its variance

    var(s) = 1 / sum_j c_j^2 / sigma_j^2,  c_j = d|s u - p_jo|/ds = u . (s u - p_jo) / |s u - p_jo|     (R2)

with sigma_j^2 the variance of the range's median plus that of p_jo along the pair's line of sight. Each
range is carried to the share's time by both vessels' odometry, as a pair's target route is judged
(membership._agrees_with_ranges_kept), and a neighbour's misses enter as their median (Table II's ranges
have outliers). Not in the paper (D20)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agent.core.median import median

# A neighbour's range may miss the fit by at most this many of its standard deviations; another minimum
# must cost at least AMBIGUITY more (in squared standard deviations) than the best, else the fit waits.
RESIDUAL_GATE = 4.0
AMBIGUITY = 16.0
ITERATIONS = 20
# The variance of the median of n ranges is pi/2 times their mean's for Gaussian noise (exact as n grows); for
# Table II's mixture, whose median is surer than its variance says, it overstates.
MEDIAN_EFFICIENCY = math.pi / 2.0


@dataclass(frozen=True)
class RangeWitness:
    """One neighbour's say on the target's range, at a reference time t (its share's stamp): its target
    estimate p_jo(t) moved into our line of sight's time (`target`: p_jo(t) plus our own motion from t to
    now, m), that estimate's position covariance (2x2, m^2), the ranges kept to it (`distances`, m) and, for
    each, how the pair moved between t and that range's time by both odometries (`moves`, (n, 2), m:
    p_ij(t_k) = p_ij(t) + moves[k]). The misses' median has variance MEDIAN_EFFICIENCY * `range_variance` / n."""

    target: np.ndarray
    target_covariance: np.ndarray
    distances: np.ndarray
    moves: np.ndarray
    range_variance: float

    def miss(self, direction: np.ndarray, s: float) -> tuple[float, np.ndarray]:
        """The median over the ranges of r_k - |s u - p_jo + moves_k| (R1 carried to each range's time), and
        the unit vector of p_ij at the range that is that median (the slope's direction)."""
        offsets = (s * direction - self.target) + self.moves
        lengths = np.hypot(offsets[:, 0], offsets[:, 1])
        misses = self.distances - lengths
        middle = int(np.argsort(misses)[len(misses) // 2])
        length = float(lengths[middle])
        along = offsets[middle] / length if length > 0.0 else np.zeros(2)
        return median(misses), along

    def variance(self, along: np.ndarray) -> float:
        """sigma_j^2 of (R2): the median's variance plus p_jo's along the pair's line of sight."""
        return self.median_variance() + float(along @ self.target_covariance @ along)

    def median_variance(self) -> float:
        return MEDIAN_EFFICIENCY * self.range_variance / len(self.distances)


def _fit(direction: np.ndarray, witnesses: list[RangeWitness], s: float) -> tuple[float, float, float, float]:
    """Gauss-Newton on (R1) from s: (s, the weighted squared misses J, var(s) of (R2), and var(s) of (R2)
    with the ranges' variance alone, as if every p_jo were exact)."""
    variance = ranges_only = cost = math.inf
    for _ in range(ITERATIONS):
        numerator = information = from_ranges = cost = 0.0
        for w in witnesses:
            miss, along = w.miss(direction, s)
            sigma2 = w.variance(along)
            slope = float(direction @ along)                      # c_j of (R2)
            numerator += slope * miss / sigma2
            information += slope * slope / sigma2
            from_ranges += slope * slope / w.median_variance()
            cost += miss * miss / sigma2
        if not (information > 0.0 and from_ranges > 0.0):
            return s, cost, math.inf, math.inf
        variance, ranges_only = 1.0 / information, 1.0 / from_ranges
        change = numerator * variance
        s += change
        if abs(change) < 1e-6:
            break
    return s, cost, variance, ranges_only


def range_along_bearing(direction: np.ndarray, witnesses: list[RangeWitness],
                        least_range: float) -> tuple[float, float, float] | None:
    """(s, var(s), var(s) from the ranges alone): the target's range along the unit `direction` that fits (R1) for every witness, or None
    when fewer than two witnesses speak, no fit beyond `least_range` leaves every witness's median miss
    within RESIDUAL_GATE standard deviations, or a second fit is almost as good (the roots cannot be told
    apart). The fits start from both roots of (R1) for each witness's latest range."""
    if len(witnesses) < 2:
        return None
    u = np.asarray(direction, dtype=float)
    starts = []
    for w in witnesses:
        base = w.target - w.moves[-1]
        centre = float(u @ base)
        discriminant = centre * centre - float(base @ base) + float(w.distances[-1]) ** 2
        spread = math.sqrt(max(discriminant, 0.0))
        starts += [centre - spread, centre + spread]
    fits = []
    for start in starts:
        s, cost, variance, ranges_only = _fit(u, witnesses, start)
        if s > least_range and math.isfinite(cost) and math.isfinite(variance):
            fits.append((cost, s, variance, ranges_only))
    if not fits:
        return None
    fits.sort()
    cost, s, variance, ranges_only = fits[0]
    for w in witnesses:
        miss, along = w.miss(u, s)
        if miss * miss > RESIDUAL_GATE**2 * w.variance(along):
            return None
    for other_cost, other, _, _ in fits[1:]:
        if abs(other - s) > 0.5 * math.sqrt(variance) and other_cost < cost + AMBIGUITY:
            return None
    return s, variance, ranges_only
