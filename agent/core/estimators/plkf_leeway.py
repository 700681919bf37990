"""The PLKF of the target with the wind's leeway as two more states, for water-referenced odometry.

A steady wind makes a hull drift sideways at (w . n(psi)) n(psi), n = (-sin psi, cos psi) its port side and
w = kappa W one vector (agent/core/control/leeway.py). A speed log and a compass do not see that drift; the
target is ground-fixed, so the relative velocity over ground is v_io = v_water + N(psi) w + u, N = n n^T,
u = c - v_o constant. The state is x = [p_io; v_io; w]; the own velocity change dv_i of the odometry (raw,
water-referenced) and the heading psi_k of the compass are known inputs:

    p_{k+1} = p_k + dt v_{k+1},  v_{k+1} = v_k + dv_i + (N(psi_{k+1}) - N(psi_k)) w_k,  w_{k+1} = w_k,

(24) with B = [I 0 0; 0 I dN; 0 0 I] before A; the bearing update is (25) on p (H = [G 0 0]). What the rest of
the agent sees is the leeway-free marginal y = T x = [p_io; v_io - N(psi) w] (T = [I 0 0; 0 I -N]): the
4-state estimate a filter would hold without the wind, which is shared and fused as before; a fused y is
taken back by Gaussian conditioning (`condition_on_marginal`), the change reaching w through P's cross terms.

Observability: on a circle centred on the target with the heading tangent (the port side towards the
target), N(psi) dw moves p radially by (|dw| / (2 omega)) sin(theta - phi) once u takes -dw / 2: the bearings
cannot see w. Off that circle (an approach, a circle not centred on the target, a crabbing hull) they do,
and the neighbours' estimates fused in fix the range (docs/sea.md, "(h) The leeway seen from the target").
"""

from __future__ import annotations

import math

import numpy as np

from agent.core.checks import finite_floats
from agent.core.estimators.plkf import PLKF, valid_fused
from agent.core.params import TargetEstimationParams


def leeway_projection(heading: float) -> np.ndarray:
    """N(psi) = n n^T, n = (-sin psi, cos psi): the sway of a velocity w is N w."""
    nx, ny = -math.sin(heading), math.cos(heading)
    return np.array([[nx * nx, nx * ny], [ny * nx, ny * ny]])


def leeway_transition(dt: float, before: float, after: float) -> np.ndarray:
    """F = A B (6 x 6): B adds (N(after) - N(before)) w to v, A of (4) moves p by dt v, w is kept."""
    dN = leeway_projection(after) - leeway_projection(before)
    F = np.eye(6)
    F[0, 2] = F[1, 3] = dt
    F[0:2, 4:6] = dt * dN
    F[2:4, 4:6] = dN
    return F


def leeway_predict(x: np.ndarray, P: np.ndarray, F: np.ndarray, dt: float, Q: np.ndarray,
                   own_velocity_change: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """x^- = F x + [dt dv_i; dv_i; 0], P^- = F P F^T + Q (the known input enters as in `plkf_predict`)."""
    prior = F @ x
    if own_velocity_change is not None:
        prior[0:2] += dt * own_velocity_change
        prior[2:4] += own_velocity_change
    P_prior = F @ P @ F.T + Q
    return prior, 0.5 * (P_prior + P_prior.T)


def marginal_map(heading: float) -> np.ndarray:
    """T (4 x 6) with y = T x = [p; v - N(psi) w]."""
    T = np.zeros((4, 6))
    T[0, 0] = T[1, 1] = T[2, 2] = T[3, 3] = 1.0
    T[2:4, 4:6] = -leeway_projection(heading)
    return T


def condition_on_marginal(x: np.ndarray, P: np.ndarray, T: np.ndarray, y: np.ndarray, P_y: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """x, P given that T x is now distributed N(y, P_y), the rest of x kept as conditioned on T x:
    L = P T^T (T P T^T)^-1, x' = x + L (y - T x), P' = (P - L T P) + L P_y L^T, so that T P' T^T = P_y.
    Raises numpy.linalg.LinAlgError when T P T^T is singular."""
    C = P @ T.T
    L = np.linalg.solve(T @ C, C.T).T
    x_post = x + L @ (y - T @ x)
    P_post = (P - L @ C.T) + L @ P_y @ L.T
    return x_post, 0.5 * (P_post + P_post.T)


class LeewayPLKF(PLKF):
    """`PLKF` with the leeway w as two more states (this module's docstring). `state` and `covariance` are the
    leeway-free marginal at the last heading, what the agent shares and fuses; `leeway` is w."""

    def __init__(self, params: TargetEstimationParams, state: np.ndarray,
                 covariance: np.ndarray | None = None, dt: float = 0.1, range_unobserved: bool = False,
                 heading: float | None = None) -> None:
        self.heading = heading     # psi at the last step; None until the first heading is known
        super().__init__(params, state, covariance, dt, range_unobserved)
        self._Q = np.diag([params.process_noise] * 4 + [params.leeway_process_noise] * 2)

    @property
    def state(self) -> np.ndarray:
        return marginal_map(self._heading()) @ self._x

    def _marginal_covariance(self) -> np.ndarray:
        T = marginal_map(self._heading())
        P = T @ self._P @ T.T
        return 0.5 * (P + P.T)

    def _heading(self) -> float:
        return 0.0 if self.heading is None else self.heading

    def face(self, heading: float) -> None:
        """Take the heading at the filter's time if it has none yet (a filter started without one)."""
        if self.heading is None and math.isfinite(heading):
            self.heading = float(heading)

    @property
    def leeway(self) -> np.ndarray:
        """w (m/s): the sway at heading psi is w . n(psi)."""
        return self._x[4:6].copy()

    @property
    def leeway_covariance(self) -> np.ndarray:
        return self._P[4:6, 4:6].copy()

    def reset(self, state: np.ndarray, covariance: np.ndarray | None = None) -> None:
        """From a 4-state [p; v] (w = 0 with `leeway_variance`) or the full 6-state."""
        x = np.asarray(state, dtype=float).reshape(-1)
        if x.shape == (4,):
            P4 = (self.params.initial_covariance * np.eye(4) if covariance is None
                  else np.asarray(covariance, dtype=float).reshape(4, 4))
            x = np.concatenate([x, np.zeros(2)])
            P = np.zeros((6, 6))
            P[:4, :4] = P4
            P[4, 4] = P[5, 5] = self.params.leeway_variance
        else:
            x = x.reshape(6)
            P = np.asarray(covariance, dtype=float).reshape(6, 6)
        if not (np.isfinite(x).all() and np.isfinite(P).all()):
            raise ValueError("reset needs a finite state and covariance")
        self._x, self._P = x.copy(), 0.5 * (P + P.T)

    def export_state(self) -> dict:
        return {**super().export_state(), "heading": self.heading}

    def restore_state(self, data: dict) -> None:
        self._x = np.array(data["state"], dtype=float).reshape(6)
        self._P = np.array(data["covariance"], dtype=float).reshape(6, 6)
        self.predictions, self.updates = data["predictions"], data["updates"]
        self.skipped, self.rejected = data["skipped"], data["rejected"]
        self.range_unobserved = bool(data.get("range_unobserved", False))
        self.heading = None if data["heading"] is None else float(data["heading"])

    def assimilate(self, state: np.ndarray, covariance: np.ndarray) -> bool:
        """Take a fused leeway-free marginal [p; v - N w] back (`condition_on_marginal`). Refused (False,
        counted) unless finite and symmetric positive-definite, or when the conditioning fails."""
        fused = valid_fused(state, covariance)
        if fused is None:
            self.rejected += 1
            return False
        y, P_y = fused
        try:
            x, P = condition_on_marginal(self._x, self._P, marginal_map(self._heading()), y, P_y)
        except np.linalg.LinAlgError:
            self.rejected += 1
            return False
        if finite_floats(x, (6,)) is None or finite_floats(P, (6, 6)) is None:
            self.rejected += 1
            return False
        self._x, self._P = x, P
        self.range_unobserved = False
        return True

    def predict(self, own_velocity_change: np.ndarray | None = None, heading: float | None = None) -> bool:
        """Time update with the own velocity change and the compass heading at the end of the interval; a
        non-finite one of either is refused (counted): the step then uses no velocity change, or keeps the
        last heading."""
        own_velocity_change, accepted = self._velocity_change(own_velocity_change)
        after = self.heading
        if heading is not None:
            if math.isfinite(heading):
                after = float(heading)
            else:
                self.rejected += 1
                accepted = False
        if after is None:
            after = 0.0
        F = leeway_transition(self.dt, after if self.heading is None else self.heading, after)
        self._x, self._P = leeway_predict(self._x, self._P, F, self.dt, self._Q, own_velocity_change)
        self.heading = after
        self.predictions += 1
        return accepted
