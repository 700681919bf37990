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


_I4 = np.eye(4)
_I4.setflags(write=False)


def transition(dt: float) -> np.ndarray:
    """A of (4)."""
    a = np.eye(4)
    a[0, 2] = a[1, 3] = dt
    return a


def plkf_predict(x: np.ndarray, P: np.ndarray, A: np.ndarray, Q: np.ndarray,
                 own_velocity_change: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(24): x^- = A x^+, P^- = A P^+ A^T + Q_o (A of (4)), with the vessel's own manoeuvre as a known input.

    `own_velocity_change` is dv_i, the change of the vessel's own velocity at the start of this interval
    (known from its odometry): the relative velocity over the interval is v_io + dv_i, so
    x^- = A (x^+ + [0; dv_i]). The paper's (24) leaves it out and lets Q_o absorb the vessel's manoeuvres;
    with it the relative model is exact for a constant-velocity target. None or zero gives (24) as printed.
    """
    if own_velocity_change is not None:
        x = x.copy()
        x[2:] += own_velocity_change
    P_prior = A @ P @ A.T + Q
    return A @ x, 0.5 * (P_prior + P_prior.T)  # keep it exactly symmetric despite round-off


def plkf_update(x: np.ndarray, P: np.ndarray, bearing: np.ndarray, bearing_variance: float,
                min_range: float, gain_bearing: str = "measured") -> tuple[np.ndarray, np.ndarray, float, float]:
    """(22), (23), (25) with a unit measured bearing b~ of (9): z = 0 (22), H = [G 0] (23), innovation
    -G(b~) p^-, R_z = r^2 G R_b G^T with r = |p^-| (floored at min_range), K = P H^T (H P H^T + R_z)^+
    (pseudo-inverse), (25).
    G = I - u u^T = q q^T for the unit bearing u and its unit normal q, so S = H P H^T + R_z = s q q^T with
    s = q^T (P_pp + r^2 R_b) q: S is rank one, and its pseudo-inverse is exactly q q^T / s.
    x^+ = x^- - K G(b~) p^-. The covariance uses the Joseph form (I - K H) P (I - K H)^T + K R_z K^T, equal to
    (25)'s (I - K H) P for this gain and symmetric positive semi-definite by construction.

    `gain_bearing` picks the bearing G and H are built from for the gain and the covariance:
    - "measured": H = [G(b~) 0], (25) as printed. The noise of b~ then sits in both the gain and the
      innovation, and their product biases the range towards zero (the known pseudo-linear bias), strongly
      while the range is uncertain.
    - "predicted": H = [G(b^-) 0] with b^- = p^- / |p^-|, the instrumental-variable Kalman filter of
      N. H. Nguyen and K. Dogancay (IEEE Signal Processing Letters vol. 25 no. 9, 2018), which removes that
      correlation; the innovation still uses the measured bearing.

    Returns (x+, P+, innovation, innovation variance) with the innovation along q, the unit normal of the
    bearing the gain uses. x may hold more states after [p; v] (the leeway's, plkf_leeway.py): H is 0 there.
    """
    # The element-wise pieces (G = I - u u^T, H, q q^T) are built from floats, the same numbers numpy's eye and
    # outer give; the matrix products stay numpy's.
    x0, x1 = float(x[0]), float(x[1])
    distance = math.hypot(x0, x1)
    r = max(distance, min_range)
    b0, b1 = float(bearing[0]), float(bearing[1])
    u0, u1 = b0, b1                     # the gain's direction
    if gain_bearing == "predicted" and distance >= min_range:
        u0, u1 = x0 / r, x1 / r
    G_measured = np.array([[1.0 - b0 * b0, 0.0 - b0 * b1], [0.0 - b1 * b0, 1.0 - b1 * b1]])
    g00, g01, g10, g11 = 1.0 - u0 * u0, 0.0 - u0 * u1, 0.0 - u1 * u0, 1.0 - u1 * u1
    G = np.array([[g00, g01], [g10, g11]])
    n = len(x)
    H = (np.array([[g00, g01, 0.0, 0.0], [g10, g11, 0.0, 0.0]]) if n == 4
         else np.array([[g00, g01] + [0.0] * (n - 2), [g10, g11] + [0.0] * (n - 2)]))
    Rz = (r * r * bearing_variance) * (G @ G.T)
    q0, q1 = -u1, u0
    q = np.array([q0, q1])
    s = float(q @ P[:2, :2] @ q) + r * r * bearing_variance
    K = P @ H.T @ np.array([[q0 * q0, q0 * q1], [q1 * q0, q1 * q1]]) / s
    I_KH = (_I4 if n == 4 else np.eye(n)) - K @ H
    x_post = x - K @ (G_measured @ x[:2])
    P_post = I_KH @ P @ I_KH.T + K @ Rz @ K.T
    return x_post, 0.5 * (P_post + P_post.T), float(q @ G_measured @ x[:2]), s


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
        self._A = transition(dt)
        self._Q = params.process_noise * np.eye(4)
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
        self._x, self._P = plkf_predict(self._x, self._P, self._A, self._Q, own_velocity_change)
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
        norm = float(np.hypot(b[0], b[1])) if b.shape == (2,) else math.nan
        if not (math.isfinite(norm) and abs(norm - 1.0) <= BEARING_NORM_TOLERANCE):
            self.rejected += 1
            return BearingOutcome(accepted=False, reason="bearing is not a finite unit vector")
        x, P, innovation, variance = plkf_update(
            self._x, self._P, b / norm, self.params.bearing_variance, self.params.min_range,
            self.params.gain_bearing,
        )
        if finite_floats(x, self._x.shape) is None or finite_floats(P, self._P.shape) is None:
            self.rejected += 1
            return BearingOutcome(accepted=False, reason="update produced a non-finite state")
        self._x, self._P = x, P
        self.updates += 1
        return BearingOutcome(accepted=True, innovation=innovation, innovation_variance=variance)
