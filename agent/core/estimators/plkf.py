"""Pseudo-linear Kalman filter of the target, Sec. III-B (22), (23), (24), (25), (26).

State x_io = [p_io; v_io] (vessel relative to target), constant-velocity model (3), (4); the measured
bearing is the b~_io of (9).
"""

from __future__ import annotations

import math

import numpy as np

from agent.core.checks import cholesky_succeeds, finite_floats
from agent.core.params import TargetEstimationParams
from agent.core.records import BearingOutcome

# A measured bearing whose norm is this far from 1 is not a direction: a sensor fault, not noise.
BEARING_NORM_TOLERANCE = 0.5


def plkf_predict(x: np.ndarray, P: np.ndarray, dt: float, process_noise: float,
                 own_velocity_change: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(24): x^- = A x^+, P^- = A P^+ A^T + Q_o with A = [I dt I; 0 I] of (4) and Q_o = `process_noise` I, with the
    vessel's own manoeuvre as a known input.

    `own_velocity_change` is dv_i, the change of the vessel's own velocity at the start of this interval
    (known from its odometry): the relative velocity over the interval is v_io + dv_i, so
    x^- = A (x^+ + [0; dv_i]). The paper's (24) leaves it out and lets Q_o absorb the vessel's manoeuvres;
    with it the relative model is exact for a constant-velocity target. None or zero gives (24) as printed.

    In plain floats, A's blocks written out (A P adds dt times the velocity rows to the position rows, then
    (A P) A^T likewise the columns): the terms A's zeros and ones would add are exact, so the numbers are the
    matrix products' up to the rounding of their sums (numpy's small products cost more in calls than in
    arithmetic)."""
    x0, x1, x2, x3 = x.tolist()
    if own_velocity_change is not None:
        d0, d1 = own_velocity_change.tolist()
        x2, x3 = x2 + d0, x3 + d1
    (a, b, c, d), (e, f, g, h), (i, j, k, l), (m, n, o, p) = P.tolist()
    # A P: rows 0, 1 gain dt times rows 2, 3
    a, b, c, d = a + dt * i, b + dt * j, c + dt * k, d + dt * l
    e, f, g, h = e + dt * m, f + dt * n, g + dt * o, h + dt * p
    # (A P) A^T: columns 0, 1 gain dt times columns 2, 3; then Q_o on the diagonal
    a, e, i, m = a + dt * c, e + dt * g, i + dt * k, m + dt * o
    b, f, j, n = b + dt * d, f + dt * h, j + dt * l, n + dt * p
    a, f, k, p = a + process_noise, f + process_noise, k + process_noise, p + process_noise
    # symmetric to the last bit despite round-off: (P + P^T) / 2
    b = e = 0.5 * (b + e)
    c = i = 0.5 * (c + i)
    d = m = 0.5 * (d + m)
    g = j = 0.5 * (g + j)
    h = n = 0.5 * (h + n)
    l = o = 0.5 * (l + o)
    return (np.array([x0 + dt * x2, x1 + dt * x3, x2, x3]),
            np.array([[a, b, c, d], [e, f, g, h], [i, j, k, l], [m, n, o, p]]))


def plkf_update(x: list[float], P: list[list[float]], b0: float, b1: float, bearing_variance: float,
                min_range: float, gain_bearing: str = "measured"
                ) -> tuple[list[float], list[list[float]], float, float]:
    """(22), (23), (25) with a unit measured bearing b~ = (b0, b1) of (9), on the state x and the rows of P as
    floats: z = 0 (22), H = [G 0] (23), innovation -G(b~) p^-, R_z = r^2 G R_b G^T with r = |p^-| (floored at
    min_range), K = P H^T (H P H^T + R_z)^+ (pseudo-inverse), (25).

    G = I - u u^T = q q^T for the unit bearing u and its unit normal q (G q = q, as u . q = 0), so
    S = H P H^T + R_z = s q q^T with s = q^T (P_pp + r^2 R_b) q = s_0 + r^2 R_b: S is rank one and its
    pseudo-inverse is exactly q q^T / s. Hence K = k q^T / s and K H = k h^T / s with k = P h, h = [q; 0]:
    x^+ = x^- - k (q^T G(b~) p^-) / s. The covariance is the Joseph form (I - K H) P (I - K H)^T + K R_z K^T,
    equal to (25)'s (I - K H) P for this gain; with h^T P h = s_0 it is P - (2 / s - (s_0 + r^2 R_b g) / s^2)
    k k^T, g = q^T G G^T q (1 but for round-off), symmetric by construction. Plain floats: numpy's products of
    a 4x4 cost more in calls than in arithmetic, and the target filter runs every tick.

    `gain_bearing` picks the bearing G and H are built from for the gain and the covariance:
    - "measured": H = [G(b~) 0], (25) as printed. The noise of b~ then sits in both the gain and the
      innovation, and their product biases the range towards zero (the known pseudo-linear bias), strongly
      while the range is uncertain.
    - "predicted": H = [G(b^-) 0] with b^- = p^- / |p^-|, the instrumental-variable Kalman filter of
      N. H. Nguyen and K. Dogancay (IEEE Signal Processing Letters vol. 25 no. 9, 2018), which removes that
      correlation; the innovation still uses the measured bearing.

    Returns (x+, rows of P+, innovation, innovation variance s) with the innovation along q, the unit normal of
    the bearing the gain uses. x may hold more states after [p; v] (the leeway's, plkf_leeway.py): H is 0 there.
    """
    x0, x1 = x[0], x[1]
    distance = math.hypot(x0, x1)
    r = max(distance, min_range)
    u0, u1 = b0, b1                     # the gain's direction
    if gain_bearing == "predicted" and distance >= min_range:
        u0, u1 = x0 / r, x1 / r
    q0, q1 = -u1, u0
    noise = r * r * bearing_variance    # r^2 R_b
    # q^T G(b~) p^-: the innovation along q
    innovation = q0 * ((1.0 - b0 * b0) * x0 - b0 * b1 * x1) + q1 * ((1.0 - b1 * b1) * x1 - b1 * b0 * x0)
    k = [row[0] * q0 + row[1] * q1 for row in P]          # k = P h
    s0 = q0 * k[0] + q1 * k[1]
    s = s0 + noise
    # G q and so g = |G q|^2, with G of the gain's direction
    gq0 = (1.0 - u0 * u0) * q0 - u0 * u1 * q1
    gq1 = (1.0 - u1 * u1) * q1 - u1 * u0 * q0
    factor = (2.0 * s - (s0 + noise * (gq0 * gq0 + gq1 * gq1))) / (s * s)
    step = innovation / s
    x_post = [value - ka * step for value, ka in zip(x, k)]
    P_post = [[value - (factor * ka) * kb for value, kb in zip(row, k)] for row, ka in zip(P, k)]
    for a in range(len(x)):
        for b in range(a):
            P_post[a][b] = P_post[b][a] = 0.5 * (P_post[a][b] + P_post[b][a])
    return x_post, P_post, innovation, s


def valid_fused(state, covariance) -> tuple[np.ndarray, np.ndarray] | None:
    """A fused target estimate [p; v] (4) and its covariance, symmetrised, when both are finite and the
    covariance is positive-definite; None otherwise."""
    x = np.array(state, dtype=float).reshape(4)
    P = np.asarray(covariance, dtype=float).reshape(4, 4)
    P = 0.5 * (P + P.T)
    values = finite_floats(P, (4, 4))
    if finite_floats(x, (4,)) is None or values is None or not cholesky_succeeds(values, 4):
        return None
    return x, P


class PLKF:
    """Target tracker of one vessel: the relative state x_io to the target from bearings (9) alone;
    `predict` is (24), `update` is (25), or (26) without a bearing.

    `range_unobserved`: the filter starts from a bearing and a guessed range (no initial estimate: a vessel
    restarted or deployed without one). Its covariance P is then not to be believed along the line of sight:
    linearised at the guess, a tenth of a second of parallax moves the estimate metres along the bearing, and
    once it sits short of the target R_z = r^2 R_b (with the estimate's r) makes every later bearing look
    precise. Measured after a restart (Table II, seed 1): 3.5 m off with a position trace of 0.08 m^2 half a
    second after its first bearing, still 3 m off at 0.03 m^2 ten seconds later. Until the range is observed,
    the covariance it gives (`covariance`) keeps the variance along the estimate's line of sight at least
    `initial_range_guess`^2, what the start assumed: its neighbours do not start pairs from it, and their
    target estimates, fused in (`assimilate`), supply the range instead of being gated out as disagreeing
    with a confident wrong one. The filter's own gain still runs on P (the estimate's path is unchanged). The
    range counts as observed once an estimate fused with the neighbours', or a range fitted to the ranges to
    them (target.range_from_neighbours, D20), has been taken in, and not before: the bearings alone do not
    tell when (the same run's filter had swept a radian of arc while still 4.7 m off at 0.35 m^2), so a
    vessel alone keeps saying its range is unknown."""

    def __init__(self, params: TargetEstimationParams, state: np.ndarray, covariance: np.ndarray | None = None,
                 dt: float = 0.1, range_unobserved: bool = False) -> None:
        self.params = params
        self.dt = dt
        self.range_unobserved = range_unobserved
        self.predictions = 0
        self.updates = 0
        self.skipped = 0
        self.rejected = 0
        self.reset(state, covariance)

    @property
    def state(self) -> np.ndarray:
        return self._x.copy()

    @property
    def covariance(self) -> np.ndarray:
        """P, and while the range is unobserved, P with the variance along the estimate's line of sight raised
        to at least g^2 = `initial_range_guess`^2, what the start assumed, and across it to at least
        (g^2 + r^2) R_b, the spread of a bearing at a range that uncertain (R_z of (25) holds r^2 R_b for the
        estimate's r alone). Rank-one additions: still symmetric positive definite."""
        P = self._marginal_covariance()
        if not self.range_unobserved:
            return P
        distance = math.hypot(float(self._x[0]), float(self._x[1]))
        if distance > 0.0:
            u = self._x[:2] / distance
            q = np.array([-u[1], u[0]])
            guess = self.params.initial_range_guess**2
            for direction, least in ((u, guess), (q, (guess + distance**2) * self.params.bearing_variance)):
                deficit = least - float(direction @ P[:2, :2] @ direction)
                if deficit > 0.0:
                    P[:2, :2] += deficit * np.outer(direction, direction)
        return P

    def _marginal_covariance(self) -> np.ndarray:
        """The covariance of [p_io; v_io] (a copy): the filter's own P here."""
        return self._P.copy()

    def reset(self, state: np.ndarray, covariance: np.ndarray | None = None) -> None:
        x = np.asarray(state, dtype=float).reshape(4).copy()
        P = (self.params.initial_covariance * np.eye(4) if covariance is None
             else np.asarray(covariance, dtype=float).reshape(4, 4).copy())
        if not (np.isfinite(x).all() and np.isfinite(P).all()):
            raise ValueError("reset needs a finite state and covariance")
        self._x, self._P = x, 0.5 * (P + P.T)

    def export_state(self) -> dict:
        """Everything that changes between calls, as JSON-ready data (agent/core/snapshot.py)."""
        return {"state": self._x.tolist(), "covariance": self._P.ravel().tolist(), "predictions": self.predictions,
                "updates": self.updates, "skipped": self.skipped, "rejected": self.rejected,
                "range_unobserved": self.range_unobserved}

    def restore_state(self, data: dict) -> None:
        self._x = np.array(data["state"], dtype=float).reshape(4)
        self._P = np.array(data["covariance"], dtype=float).reshape(4, 4)
        self.predictions, self.updates = data["predictions"], data["updates"]
        self.skipped, self.rejected = data["skipped"], data["rejected"]
        self.range_unobserved = bool(data.get("range_unobserved", False))     # (snapshots from before it)

    def assimilate(self, state: np.ndarray, covariance: np.ndarray) -> bool:
        """Replace the estimate by a fused one (cooperative fusion with the neighbours' estimates).
        Refused (False, counted) unless finite and symmetric positive-definite."""
        fused = valid_fused(state, covariance)
        if fused is None:
            self.rejected += 1
            return False
        self._x, self._P = fused
        self.range_unobserved = False      # the range now comes from the neighbours' estimates too
        return True

    def _velocity_change(self, own_velocity_change) -> tuple[np.ndarray | None, bool]:
        """The own velocity change as a 2-vector, or None (refused and counted) when it is not finite."""
        if own_velocity_change is None:
            return None, True
        dv = np.asarray(own_velocity_change, dtype=float).reshape(2)
        if finite_floats(dv, (2,)) is None:
            self.rejected += 1
            return None, False
        return dv, True

    def predict(self, own_velocity_change: np.ndarray | None = None) -> bool:
        """Time update (24). A non-finite velocity change is refused (counted) and the step uses none."""
        own_velocity_change, accepted = self._velocity_change(own_velocity_change)
        self._x, self._P = plkf_predict(self._x, self._P, self.dt, self.params.process_noise,
                                       own_velocity_change)
        self.predictions += 1
        return accepted

    def update(self, bearing: np.ndarray | None) -> BearingOutcome:
        """Measurement update (25) with a measured bearing (target to vessel), or (26) when it is None.

        The measured bearing is normalised first: a bearing is a direction, and G is a projection only for
        a unit vector. A non-finite bearing, or one whose norm is far from 1, is refused and the step is
        prediction-only, exactly as for a missing one.
        """
        if bearing is None:
            self.skipped += 1
            return BearingOutcome(accepted=False, reason="no bearing (prediction only)")
        b = np.asarray(bearing, dtype=float).reshape(-1)
        b0, b1 = b.tolist() if b.shape == (2,) else (math.nan, math.nan)
        norm = math.hypot(b0, b1)
        if not (math.isfinite(norm) and abs(norm - 1.0) <= BEARING_NORM_TOLERANCE):
            self.rejected += 1
            return BearingOutcome(accepted=False, reason="bearing is not a finite unit vector")
        x, P, innovation, variance = plkf_update(
            self._x.tolist(), self._P.tolist(), b0 / norm, b1 / norm, self.params.bearing_variance,
            self.params.min_range, self.params.gain_bearing,
        )
        total = sum(x) + sum(map(sum, P))       # any inf or NaN makes the sum so; an overflow is looked into
        if total - total != 0.0 and not all(map(math.isfinite, x + [v for row in P for v in row])):
            self.rejected += 1
            return BearingOutcome(accepted=False, reason="update produced a non-finite state")
        x, P = np.array(x), np.array(P)
        self._x, self._P = x, P
        self.updates += 1
        return BearingOutcome(accepted=True, innovation=innovation, innovation_variance=variance)
