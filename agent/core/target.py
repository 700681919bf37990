"""The vessel's own motion and its target filter (the PLKF of Sec. III-B) through one tick."""

from __future__ import annotations

import numpy as np

from agent.core.estimators.plkf import PLKF
from agent.core.estimators.plkf_leeway import LeewayPLKF, leeway_projection
from agent.core.params import AgentParams, TargetEstimationParams
from agent.core.records import BearingOutcome
from agent.core.state import VesselState


def own_motion(state: VesselState, now: float, position: np.ndarray) -> np.ndarray | None:
    """The change of own velocity (2), from odometry differences (5), at the start of the interval just
    ended (the input u of (24)); None on
    the first tick, when there is no interval yet and the initial target estimate already refers to now."""
    motion = state.motion
    change = None
    # Odometry samples closer than a millisecond would turn their noise into any velocity at all.
    if motion.stamp is not None and now - motion.stamp >= 1e-3:
        velocity = (position - motion.position) / (now - motion.stamp)
        change = velocity - motion.velocity
        motion.velocity = velocity
    motion.stamp, motion.position = now, position
    return change


def target_filter(params: TargetEstimationParams, state: np.ndarray, covariance: np.ndarray, dt: float,
                  range_unobserved: bool = False, heading: float | None = None) -> PLKF:
    """The target filter the parameters ask for: the PLKF, or with `leeway_variance` > 0 the PLKF with the
    wind's leeway (plkf_leeway.py), both from a 4-state estimate [p_io; v_io]."""
    if params.leeway_variance > 0.0:
        return LeewayPLKF(params, state, covariance, dt=dt, range_unobserved=range_unobserved,
                          heading=heading)
    return PLKF(params, state, covariance, dt=dt, range_unobserved=range_unobserved)


def leeway_estimate(state: VesselState) -> np.ndarray | None:
    """w of the target filter's leeway model; None without one (or before there is a target estimate)."""
    tracker = state.tracker
    return tracker.leeway if isinstance(tracker, LeewayPLKF) else None


def leeway_drift(state: VesselState, position: np.ndarray, heading: float, elapsed: float) -> np.ndarray:
    """The own odometry with the leeway the target filter estimates added: the raw position plus the sum of
    N(psi) w over the odometry's intervals, which the pair filters and the share take (what the neighbours
    and this vessel's pair filters need is motion over ground; a uniform current is common to the fleet).
    The raw position where there is no leeway model; the target filter itself keeps the raw odometry."""
    w = leeway_estimate(state)
    if w is not None and state.motion.stamp is not None:
        step = elapsed * (leeway_projection(heading) @ w)
        if np.all(np.isfinite(step)):
            state.motion.drift = state.motion.drift + step
    return position + state.motion.drift


def track_target(params: AgentParams, state: VesselState, bearing: np.ndarray | None,
                 velocity_change: np.ndarray | None, heading: float = 0.0
                 ) -> tuple[np.ndarray | None, np.ndarray | None, BearingOutcome | None]:
    """One PLKF cycle on the bearing of (9): predict (24) with the own velocity change, update (25) with
    the bearing or (26) without. Without a target estimate yet, the first bearing starts one at `initial_range_guess` along it.
    `heading` (the compass) is the leeway model's input (plkf_leeway.py); the PLKF does not use it.
    Returns (x^_io, P_io, the update's outcome), all None while there is no target estimate."""
    if state.tracker is None:
        if bearing is None or not np.linalg.norm(bearing) > 0:
            return None, None, None
        _start_tracker(params, state, bearing, heading)
    tracker = state.tracker
    if isinstance(tracker, LeewayPLKF):
        tracker.face(heading)
    if velocity_change is not None:
        if isinstance(tracker, LeewayPLKF):
            tracker.predict(velocity_change, heading)
        else:
            tracker.predict(velocity_change)
    outcome = tracker.update(bearing)
    if bearing is not None and not outcome.accepted:
        state.health.bad_bearing += 1
    elif bearing is not None and float(bearing @ tracker.state[:2]) < params.target.min_range:
        # The pseudo-linear measurement G(b) p = 0 holds for p and -p alike: an estimate pushed through the
        # vessel (a cold start's range guess far off while the target's velocity is unknown) would converge
        # on the point reflection of the target and never come back. The bearing says which side it is on.
        state.health.target_restarts += 1
        _start_tracker(params, state, bearing, heading)
        tracker = state.tracker
    return tracker.state, tracker.covariance, outcome


def _start_tracker(params: AgentParams, state: VesselState, bearing: np.ndarray, heading: float) -> None:
    """A target estimate from one bearing: `initial_range_guess` along it, the target taken as still."""
    p = params.target
    guess = bearing / np.linalg.norm(bearing) * p.initial_range_guess
    covariance = np.diag([p.initial_range_guess**2] * 2 + [p.initial_covariance] * 2)
    state.tracker = target_filter(p, np.concatenate([guess, -state.motion.velocity]), covariance, params.dt,
                                  range_unobserved=True, heading=heading)
