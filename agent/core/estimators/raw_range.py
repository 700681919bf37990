"""Raw-range relative position estimator: the ranges r_k = |p_k| + b + mu_k themselves, not the pseudo-linear
differences (12), (13). docs/estimation.md §8 gives the design, the reasons and the measurements.

Pure functions over (p, P) as floats and a frozen `RawRangeState`, which snapshots store field by field; the
class `RawRange` (prediction (15) in the base) only holds them. Contract:
- Fix (`collected`, `batch_fixed`): each range is kept with the displacement D summed to its epoch (at most
  `window`); every `solve_every` ranges (counted in ticks for a sensor slower than dt) the window's negative
  log-likelihood under the assumed density plus the prior carried by odometry (`carried`) is minimised
  (raw_range_batch.py). The position is fixed once the mirror solution is `ambiguity_threshold` nats worse,
  the batch covariance (P^-1 + I sum u u^T)^-1, widened where the cost is flatter than its Gaussian, is
  within `fix_max_variance`, and the best point fits the ranges (mean NLL against the density's entropy).
  Until then `ambiguous` is True and `mirror` the other candidate; before the first solve a range moves
  the mean only.
- Tracking (`tracked`, `moment_matched`): each range updates N(p^-, P) by moment matching on the range
  linearised at p^- (Masreliez 1975), p^+ = p^- + P H^T psi(e), P^+ = P - P H^T psi'(e) H P, psi the score
  of f_h = f * N(0, h); a monitor of the residuals' fit (`fix_lost`) drops a fix (`refix`: phase 1 again).
- With `bias_variance` > 0 the range bias b is a state estimated with p (H = (u^T, 1)).
- Ranges between antennas off the hulls' centres (`update_between`): r = |p + delta| + b + noise with the
  known offset delta of each range (agent/core/antenna.py) in the window's anchors and the linearisation.
- `range_prev` of `update` is used once, for the first range of a sequence; `assimilate` while not fixed
  replaces the prior the window is solved with.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from pydantic import Field, TypeAdapter

from agent.config import NonNegativeFloat, PositiveFloat
from agent.core.estimators.base import (
    REJECTED_RANGE,
    RelativePositionEstimator,
    UpdateOutcome,
    _as_range,
    accepted_outcome,
)
from agent.core.estimators.range_density import (
    LogNormalDensity,
    RangeDensity,
    lognormal_density,
    mixture_density,
)
from agent.core.estimators.raw_range_batch import MIN_DISTANCE, BatchWindow, _largest_eigenvalue
from agent.core.estimators.registry import EstimatorParams, register
from agent.core.range_noise import LogNormalNoise


class RawRangeParams(EstimatorParams):
    """Batch fix over a window of ranges, then a moment-matching update on each range r = |p| + noise."""

    name: Literal["raw_range"] = "raw_range"
    noise_components: tuple[tuple[PositiveFloat, float, PositiveFloat], ...] = Field(
        ((0.8, 0.0, 0.4), (0.2, 0.0, 10.0)), min_length=1, max_length=8,
        description="assumed range-noise mixture, (weight, mean m, variance m^2) per component (Table II's)")
    gross_error_fraction: NonNegativeFloat = Field(
        1e-3, lt=1, description="weight of one more, very wide, zero-mean component for gross errors")
    gross_error_variance: PositiveFloat = Field(1e4, description="variance of that component (m^2)")
    tracking_lognormal: LogNormalNoise | None = Field(
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


REJECTED_OFFSET = "antenna offset is not finite"
# Sandwich covariance: pseudo-ranges at I_f a batch's score moments are shrunk towards, and the length of
# the tracking phase's running means (ranges).
SANDWICH_PRIOR = 20
SANDWICH_LENGTH = 200
# The covariance a dropped fix starts phase 1 again with: no prior.
NO_PRIOR_VARIANCE = 1e12
# Cold start points are scouted with this many iterations each, and the best SCOUTED_KEPT solved fully.
SCOUT_ITERATIONS = 3
SCOUTED_KEPT = 2



def _due(ranges: int, ticks: float, count: int, least: int = 1) -> bool:
    """A solve is due once `count` ranges have come, or, from a sensor slower than the tick, once the ranges
    span `count` ticks (and are at least `least`): the schedule is set in ranges at one range per tick, so
    that a 1 Hz sensor at dt = 0.1 s solves first after 2 s, as a 10 Hz one does, not after 20 s."""
    return ranges >= count or (ranges >= least and ticks >= count - 1e-6)


def _sandwich(psi2: float, dpsi: float, fisher: float) -> float:
    """Information per range for the covariance: the sandwich (mean psi')^2 / mean psi^2, which is I_f when the
    assumed density is the noise's and less when it is only an approximation (a fitted mixture, a bias), kept
    within [I_f / 20, I_f]."""
    if dpsi <= 0.0 or psi2 <= 0.0:
        return fisher / 20.0
    return min(max(dpsi * dpsi / psi2, fisher / 20.0), fisher)


Moments = tuple[float, float, float, float, float]     # (px, py, p11, p12, p22): p and P as plain floats


@dataclass(frozen=True, slots=True)
class NoiseModel:
    """What the parameters' noise density gives the filter, built once: the batch's mixture f with its
    Fisher information I_f, entropy H and spread S of -ln f, and tracking's exact density (None: f's)."""

    density: RangeDensity
    exact: LogNormalDensity | None
    fisher: float

    @classmethod
    def of(cls, p: RawRangeParams) -> NoiseModel:
        exact = p.tracking_lognormal
        gross = (p.gross_error_fraction, p.gross_error_variance)
        density = mixture_density(p.noise_components, *gross)
        known = None if exact is None else lognormal_density(exact.log_variance, exact.shift, *gross)
        return cls(density, known, density.fisher)

    def tracking_fit(self) -> tuple[float, float]:
        """(H, S) of the density tracking uses (the monitor's yardstick): the exact one's if any, else f's."""
        source = self.exact if self.exact is not None else self.density
        return source.entropy, source.spread


class RawRangeState(NamedTuple):
    """What a raw-range pair filter holds besides the base's p, P and pair displacement. Snapshots store its
    fields by name (`state_json`, `state_from_json`)."""

    fixed: bool                                         # phase 2 (tracking); False: phase 1 (fix)
    cumulative: tuple[float, float]                     # D, the relative displacement summed so far
    window: tuple[tuple[float, float, float], ...]      # (range, Dx, Dy) per range epoch while not fixed
    prior: Moments                                      # the batch's prior, carried to now by odometry
    mirror: tuple[float, float] | None                  # the other candidate while ambiguous
    unsolved: int                                       # ranges since the last batch solve
    unsolved_ticks: float                               # and the ticks (dt) they span
    solves: int
    evidence: float                                     # the other minimum's cost less the best's (nats)
    consistent: bool                                    # the last batch solution passed the goodness of fit
    monitor: float                                      # running mean of the tracking residuals' NLL (nats)
    tracked: int                                        # ranges since the fix
    refixes: int                                        # fixes dropped by the monitor
    sandwich: tuple[float, float, float]                # running means of psi^2 and psi', and I
    bias: tuple[float, float, float, float]             # b, cov(px, b), cov(py, b), var b


# Where tracking's per-range fields start: the state ends (monitor, tracked, refixes, sandwich, bias).
_MONITOR = RawRangeState._fields.index("monitor")
if RawRangeState._fields[_MONITOR:] != ("monitor", "tracked", "refixes", "sandwich", "bias"):
    raise ImportError("raw_range: RawRangeState's last fields moved; `tracked` builds them in this order")


def initial_state(m: Moments, p: RawRangeParams, model: NoiseModel) -> RawRangeState:
    """Phase 1 from the prior N(p, P) = `m`; b from its prior N(0, bias_variance) (all 0 without one)."""
    fisher = model.fisher
    return RawRangeState(fixed=False, cumulative=(0.0, 0.0), window=(), prior=m, mirror=None, unsolved=0,
                         unsolved_ticks=0.0, solves=0, evidence=0.0, consistent=False, monitor=0.0, tracked=0,
                         refixes=0, sandwich=(fisher, fisher, fisher), bias=(0.0, 0.0, 0.0, p.bias_variance))


def state_json(s: RawRangeState) -> dict:
    """The state's fields by name as JSON data (an infinite evidence as null)."""
    data = {name: _plain(getattr(s, name)) for name in RawRangeState._fields}
    data["evidence"] = None if math.isinf(s.evidence) else s.evidence
    return data


def state_from_json(data: dict, fresh: RawRangeState) -> RawRangeState:
    """`state_json`'s data back, through the fields' types; a field an older snapshot lacks is `fresh`'s
    (the ticks of `unsolved`: its count)."""
    values = {**{name: getattr(fresh, name) for name in RawRangeState._fields},
              "unsolved_ticks": data.get("unsolved", fresh.unsolved), **data}
    if values["evidence"] is None:
        values["evidence"] = math.inf
    return _STATE.validate_python(values)


def _plain(value: object) -> object:
    return [_plain(v) for v in value] if isinstance(value, tuple) else value


_STATE = TypeAdapter(RawRangeState)


def carried(s: RawRangeState, dx: float, dy: float, inflation: float) -> RawRangeState:
    """Phase 1's bookkeeping moved by a predicted displacement (15): D, the prior (its covariance grown by
    `inflation` per axis) and the mirror candidate. Phase 2 keeps nothing of it."""
    if s.fixed:
        return s
    qx, qy, q11, q12, q22 = s.prior
    cx, cy = s.cumulative
    return s._replace(cumulative=(cx + dx, cy + dy),
                   prior=(qx + dx, qy + dy, q11 + inflation, q12, q22 + inflation),
                   mirror=None if s.mirror is None else (s.mirror[0] + dx, s.mirror[1] + dy))


def moment_matched(m: Moments, s: RawRangeState, r: float, model: NoiseModel, shrink: bool = True,
                   offset: tuple[float, float] | None = None
                   ) -> tuple[Moments, tuple[float, float, float], tuple[float, float, float, float],
                              tuple[float, float, float, float]] | None:
    """The moment-matching update of N((p, b), P) by one range r = |p| + b + noise, linearised at p^-:
    H = (u^T, 1), k = P H^T, h = H k, e = r - |p^-| - b^-, psi and psi' the score at e of f_h widened by the
    range's curvature (v^T P v / |p|)^2 / 2 (docs/estimation.md §8):
        (p, b)^+ = (p, b)^- + k psi(e),    P^+ = P - k k^T psi'(e) I / I_f
    with I / I_f the sandwich share (while fixed on the mixture, its running means are updated first). Without
    b, H = u^T and the b terms are 0; without `shrink` only the mean moves. A range between antennas
    (`offset` delta, agent/core/antenna.py) is r = |p + delta| + b + noise: d and u are taken at p^- + delta,
    H is the same. Returns (m+, sandwich+, bias+, (-ln f_h(e), psi', e, h)), or None at the origin, where u
    is undefined."""
    px, py, p11, p12, p22 = m
    b, pxb, pyb, pbb = s.bias
    ax, ay = (px, py) if offset is None else (px + offset[0], py + offset[1])
    d = math.hypot(ax, ay)
    if d < MIN_DISTANCE:
        return None
    ux, uy = ax / d, ay / d
    hx = p11 * ux + p12 * uy + pxb               # P H^T
    hy = p12 * ux + p22 * uy + pyb
    hb = pxb * ux + pyb * uy + pbb
    h = ux * hx + uy * hy + hb                   # the prior's variance along the range
    across = uy * uy * p11 - 2.0 * ux * uy * p12 + ux * ux * p22
    innovation = r - d - b
    exact = model.exact if s.fixed else None
    nll, psi, dpsi = (exact or model.density).predictive(innovation, h + 0.5 * (across / d) ** 2)
    sandwich = s.sandwich
    if s.fixed and exact is None:
        psi2, mean_dpsi, _ = sandwich
        psi2 += (psi * psi - psi2) / SANDWICH_LENGTH
        mean_dpsi += (dpsi - mean_dpsi) / SANDWICH_LENGTH
        sandwich = (psi2, mean_dpsi, _sandwich(psi2, mean_dpsi, model.fisher))
    px, py = px + hx * psi, py + hy * psi
    if pbb > 0.0:
        b += hb * psi
    if shrink:
        # Where the assumed density only approximates the noise, the sandwich says how much of its
        # information a range really carries; the covariance shrinks by that share only.
        share = dpsi if exact is not None else dpsi * sandwich[2] / model.fisher
        p11, p12, p22 = p11 - hx * hx * share, p12 - hx * hy * share, p22 - hy * hy * share
        if pbb > 0.0:
            pxb, pyb, pbb = pxb - hx * hb * share, pyb - hy * hb * share, pbb - hb * hb * share
    return (px, py, p11, p12, p22), sandwich, (b, pxb, pyb, pbb), (nll, dpsi, innovation, h)


def tracked(m: Moments, s: RawRangeState, r: float, p: RawRangeParams, model: NoiseModel,
            offset: tuple[float, float] | None = None) -> tuple[Moments, RawRangeState, UpdateOutcome]:
    """Phase 2: the moment-matching update by one range (between antennas at `offset`, if given), then the
    monitor (`fix_lost`)."""
    step = moment_matched(m, s, r, model, offset=offset)
    if step is None:
        return m, s, UpdateOutcome(accepted=True, reason="at the origin: range direction undefined")
    m, sandwich, bias, (nll, dpsi, innovation, h) = step
    # s._replace(monitor=..., tracked=..., sandwich=..., bias=...), built directly: _replace (its keywords
    # mapped over every field) cost 2 us a range, as much as the moment matching.
    s = RawRangeState._make((*s[:_MONITOR], s.monitor + (nll - s.monitor) / p.monitor_length, s.tracked + 1,
                             s.refixes, sandwich, bias))
    reason = ""
    if fix_lost(s, p, model):
        m, s = refix(m, s, p)
        reason = "fix dropped: the ranges no longer fit"
    # weight: the share of the prior's variance along the range this range removed, h psi' (for a Gaussian
    # noise the Kalman gain's h / (sigma^2 + h); about 0 for a gross error).
    information = model.exact.fisher if model.exact is not None else s.sandwich[2]
    return m, s, accepted_outcome(1, innovation, h + 1.0 / information, dpsi * h if h > 0.0 else 1.0, reason)


def fix_lost(s: RawRangeState, p: RawRangeParams, model: NoiseModel) -> bool:
    """Tracking monitor: the exponential mean over about `monitor_length` ranges of the predicted residuals'
    negative log-likelihood exceeds the density's entropy by `monitor_sigmas` of its standard error
    S sqrt(1 / (2 L - 1)) (plus 0.2 nats for a density that is only approximate)."""
    length = p.monitor_length
    if s.tracked < length:
        return False
    entropy, spread = model.tracking_fit()
    return s.monitor > entropy + 0.2 + p.monitor_sigmas * spread / math.sqrt(2.0 * length - 1.0)


def refix(m: Moments, s: RawRangeState, p: RawRangeParams) -> tuple[Moments, RawRangeState]:
    """A dropped fix: phase 1 again at the current estimate, from no prior."""
    m = (m[0], m[1], NO_PRIOR_VARIANCE, 0.0, NO_PRIOR_VARIANCE)
    return m, s._replace(refixes=s.refixes + 1, fixed=False, window=(), mirror=None, solves=0, unsolved=0,
                      unsolved_ticks=0.0, consistent=False, prior=m, bias=(0.0, 0.0, 0.0, p.bias_variance))


def collected(m: Moments, s: RawRangeState, pair: tuple[float, float, float], range_prev: float, r: float,
              p: RawRangeParams, model: NoiseModel,
              offsets: tuple[tuple[float, float], tuple[float, float]] | None = None
              ) -> tuple[Moments, RawRangeState, UpdateOutcome]:
    """Phase 1: keep the range (first also `range_prev`, the range of the epoch `mark_range_epoch` declared,
    before the pair's displacement `pair` = (dx, dy, ticks)); solve the window when due (`batch_fixed`).
    Ranges between antennas (`offsets`: delta at range_prev's time and at r's) are kept with D + delta: the
    batch's p_m = p - (D_now - D_m) then becomes the antennas' p_m + delta_m, exactly."""
    cx, cy = s.cumulative
    window = s.window
    if offsets is None:
        (qx, qy), (ox, oy) = (cx, cy), (cx, cy)
    else:
        (before, now) = offsets
        (qx, qy), (ox, oy) = (cx + before[0], cy + before[1]), (cx + now[0], cy + now[1])
    if not window and s.solves == 0 and not math.isnan(range_prev) and pair[2] > 0:
        window = ((range_prev, qx - pair[0], qy - pair[1]),)
    window = (*window, (r, ox, oy))
    if len(window) > p.window:
        window = window[len(window) - p.window:]
    unsolved, unsolved_ticks = s.unsolved + 1, s.unsolved_ticks + pair[2]
    if s.solves == 0:
        # Pairs that start together would solve on the same ticks; the first solve waits up to
        # solve_every - 1 more ranges, by the millimetres of the pair's first range, which differ.
        stagger = int(window[0][0] * 1e3) % p.solve_every
        waiting = not _due(len(window), unsolved_ticks + 1, p.min_ranges + stagger, 3)
    else:
        waiting = not _due(unsolved, unsolved_ticks, p.solve_every)
    s = s._replace(window=window, unsolved=unsolved, unsolved_ticks=unsolved_ticks)
    if waiting:
        if s.solves == 0:
            # Before the first solve the range moves the estimate as in tracking, so that it does not stand
            # still for seconds at one range a second; the covariance stays the prior's (estimation.md §8).
            offset = None if offsets is None else offsets[1]
            step = moment_matched(m, s, r, model, shrink=False, offset=offset)
            if step is not None:
                m, sandwich, bias, _ = step
                s = s._replace(sandwich=sandwich, bias=bias)
        return m, s, UpdateOutcome(accepted=True, reason="collecting")
    return batch_fixed(m, s._replace(unsolved=0, unsolved_ticks=0.0), p, model)


def batch_fixed(m: Moments, s: RawRangeState, p: RawRangeParams,
                model: NoiseModel) -> tuple[Moments, RawRangeState, UpdateOutcome]:
    """Solve the window (raw_range_batch.BatchWindow) from the last solution or from cold points, decide the
    mirror ambiguity and the goodness of fit, and fix the position if the fix is unique, consistent and
    narrow (its covariance widened where the window's cost is flatter than its Gaussian)."""
    px, py = m[0], m[1]
    b = s.bias[0]
    data = np.array(s.window)
    cx, cy = s.cumulative
    anchors = np.column_stack([cx - data[:, 1], cy - data[:, 2]])
    batch = BatchWindow(data[:, 0], anchors, model.density, s.prior, p.bias_variance)
    starts = []
    if s.solves > 0:
        starts.append((px, py, b))
        if s.mirror is not None:
            starts.append((*s.mirror, b))
    if s.solves == 0 or not s.consistent:
        # Cold: both line candidates, the points straight across the anchors' centroid, the prior's mean.
        cold = (*batch.line_candidates(), *batch.centroid_candidates(), s.prior[:2])
        starts += [(x, y, 0.0) for x, y in cold]
    if len(starts) > SCOUTED_KEPT:
        # A few iterations from every cold start point, then only the most promising are solved fully.
        scouted = sorted((batch.solve(x, y, SCOUT_ITERATIONS, p.tolerance, b) for x, y, b in starts),
                         key=lambda solution: solution[3])
        starts = [solution[:3] for solution in scouted[:SCOUTED_KEPT]]
    # Warm (the last solve consistent): the starts are that solve's points, so Newton steps from the first.
    warm = s.solves > 0 and s.consistent
    solutions = [batch.solve(x, y, p.batch_iterations, p.tolerance, b, near=warm) for x, y, b in starts]
    bx, by, bb, best, at = min(solutions, key=lambda solution: solution[3])
    mx, my = batch.mirror(bx, by)
    mirror = batch.solve(mx, my, p.batch_iterations, p.tolerance, bb, near=warm)
    psi2, dpsi, n = batch.score_moments(at)     # at the best solution's last evaluated point
    fisher = model.fisher
    psi2 = (SANDWICH_PRIOR * fisher + psi2) / (SANDWICH_PRIOR + n)
    dpsi = (SANDWICH_PRIOR * fisher + dpsi) / (SANDWICH_PRIOR + n)
    info = _sandwich(psi2, dpsi, fisher)
    c11, c12, c22, *bias = batch.covariance(bx, by, info)
    pxb, pyb, pbb = bias or (0.0, 0.0, 0.0)
    largest = _largest_eigenvalue(c11, c12, c22)
    smallest = c11 + c22 - largest
    # Another local minimum, however near: one the solver from the mirror point did not leave. Only when it
    # converged back onto the best point is the minimum unique (the path has turned enough).
    same = max(1e-3, 0.25 * math.sqrt(max(smallest, 0.0)))
    separate = [solution for solution in (*solutions, mirror)
                if math.hypot(solution[0] - bx, solution[1] - by) > same]
    # Goodness of fit: the mean negative log-likelihood per range of the best point against the density's
    # entropy, with 4 standard errors and 0.2 nats of slack for a density that is only approximate. A point
    # that explains the ranges only as gross errors (a wrong basin) fails it.
    n = len(data)
    nll = (best - batch.prior_term(bx, by, bb)) / n
    density = model.density
    consistent = nll <= density.entropy + 0.2 + 4.0 * density.spread / math.sqrt(n)
    if separate:
        ax, ay, _, alt_cost, _ = min(separate, key=lambda solution: solution[3])
        evidence = alt_cost - best
    else:
        ax = ay = None
        evidence = math.inf
    s = s._replace(sandwich=(psi2, dpsi, info), bias=(bb, pxb, pyb, pbb), solves=s.solves + 1,
                consistent=consistent, evidence=evidence)
    ready = evidence >= p.ambiguity_threshold and consistent
    if ready and largest <= p.fix_max_variance:
        # About to fix: the Gaussian it hands to tracking must not claim more than the window's cost supports
        # out in its tails (a flat or bent likelihood along the path); widened, it may have to wait.
        c11, c12, c22 = batch.widened(bx, by, bb, c11, c12, c22)
        largest = _largest_eigenvalue(c11, c12, c22)
    if ready and largest <= p.fix_max_variance:
        s = s._replace(fixed=True, mirror=None, window=(), monitor=model.tracking_fit()[0], tracked=0)
        return (bx, by, c11, c12, c22), s, UpdateOutcome(accepted=True, reason="fixed", iterations=s.solves,
                                                         weight=1.0)
    if ax is None:
        s = s._replace(mirror=None)
    else:
        s = s._replace(mirror=(ax, ay))
        share = 1.0 / (1.0 + math.exp(min(evidence, 700.0)))
        vx, vy = ax - bx, ay - by
        c11, c12, c22 = c11 + share * vx * vx, c12 + share * vx * vy, c22 + share * vy * vy
    return (bx, by, c11, c12, c22), s, UpdateOutcome(
        accepted=True, reason="ambiguous", iterations=s.solves,
        weight=1.0 if ax is None else 1.0 / (1.0 + math.exp(-min(evidence, 700.0))))


@register
class RawRange(RelativePositionEstimator):
    """Batch fix over a window of raw ranges, mirror ambiguity explicit, then moment-matching updates on
    r = |p| + b (module docstring): the functions above over a `RawRangeState`."""

    name = "raw_range"
    Params = RawRangeParams
    table_order = 6

    # ----- reading -----
    @property
    def state(self) -> RawRangeState:
        return self._state

    @property
    def ambiguous(self) -> bool:
        """True until the position is fixed: before the first batch solve, and while p and its mirror
        across the line of the relative motion explain the ranges nearly equally well."""
        return not self._state.fixed

    @property
    def fixed(self) -> bool:
        return self._state.fixed

    @property
    def mirror(self) -> np.ndarray | None:
        """The other candidate while ambiguous (None before the first solve, when there is none, and once
        fixed)."""
        s = self._state
        return None if s.mirror is None or s.fixed else np.array(s.mirror)

    @property
    def bias(self) -> float:
        """The estimated range bias b (m): 0 unless `bias_variance` > 0."""
        return self._state.bias[0]

    @property
    def refixes(self) -> int:
        """How many times a fix was dropped by the tracking monitor."""
        return self._state.refixes

    # ----- life cycle -----
    def _reset_extra(self) -> None:
        self._model = NoiseModel.of(self.params)
        self._state = initial_state(self.moments(), self.params, self._model)

    def assimilate(self, position: np.ndarray, covariance: np.ndarray) -> bool:
        if not super().assimilate(position, covariance):
            return False
        # The fused position's correlation with b is unknown: dropped (the 3x3 stays positive definite).
        s = self._state
        b, _, _, pbb = s.bias
        s = s._replace(bias=(b, 0.0, 0.0, pbb))
        if not s.fixed:
            s = s._replace(prior=self.moments(), mirror=None)
        self._state = s
        return True

    # ----- prediction -----
    def predict(self, displacement, intervals: float = 1.0) -> bool:
        before_x, before_y, before_steps = self._pair_dx, self._pair_dy, self._pair_steps
        if not super().predict(displacement, intervals):
            return False
        if not self._state.fixed:
            inflation = 2.0 * self.relative.displacement_variance * (self._pair_steps - before_steps)
            self._state = carried(self._state, self._pair_dx - before_x, self._pair_dy - before_y, inflation)
        return True

    # ----- correction -----
    def update(self, range_prev: float, range_now: float) -> UpdateOutcome:
        return self._corrected(range_prev, range_now, None)

    def update_between(self, range_prev: float, range_now: float, offset_prev: tuple[float, float],
                       offset_now: tuple[float, float]) -> UpdateOutcome:
        """`update` on ranges between antennas, r = |p + delta| + b + noise: the offsets enter the window's
        anchors and the tracking linearisation exactly (`collected`, `moment_matched`)."""
        offsets = ((float(offset_prev[0]), float(offset_prev[1])),
                   (float(offset_now[0]), float(offset_now[1])))
        if not all(map(math.isfinite, (*offsets[0], *offsets[1]))):
            self._diag.rejected += 1
            return self._record(UpdateOutcome(accepted=False, reason=REJECTED_OFFSET))
        return self._corrected(range_prev, range_now, offsets)

    def _corrected(self, range_prev: float, range_now: float,
                   offsets: tuple[tuple[float, float], tuple[float, float]] | None) -> UpdateOutcome:
        # Both ranges are checked, as in every estimator, though only the first pair uses range_prev.
        r = _as_range(range_now, self.relative.max_range)
        first = _as_range(range_prev, self.relative.max_range)
        if math.isnan(r) or math.isnan(first):
            self._diag.rejected += 1
            return self._record(UpdateOutcome(accepted=False, reason=REJECTED_RANGE))
        saved = self.moments()
        if self._state.fixed:
            m, s, outcome = tracked(saved, self._state, r, self.params, self._model,
                                    None if offsets is None else offsets[1])
        else:
            pair = (self._pair_dx, self._pair_dy, self._pair_steps)
            m, s, outcome = collected(saved, self._state, pair, first, r, self.params, self._model, offsets)
        self._px, self._py, self._p11, self._p12, self._p22 = m
        self._state = s
        return self._settle(saved, outcome)

    # ----- saving and restoring -----
    def _export_extra(self) -> dict:
        return state_json(self._state)

    def _restore_extra(self, extra: dict) -> None:
        self._state = state_from_json(extra, self._state)
