"""The vessel's own motion and its target filter (the PLKF of Sec. III-B) through one tick."""

from __future__ import annotations

import numpy as np

from agent.core.estimators.plkf import PLKF
from agent.core.params import AgentParams
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


def track_target(params: AgentParams, state: VesselState, bearing: np.ndarray | None,
                 velocity_change: np.ndarray | None
                 ) -> tuple[np.ndarray | None, np.ndarray | None, BearingOutcome | None]:
    """One PLKF cycle on the bearing of (9): predict (24) with the own velocity change, update (25) with
    the bearing or (26) without. Without a target estimate yet, the first bearing starts one at `initial_range_guess` along it.
    Returns (x^_io, P_io, the update's outcome), all None while there is no target estimate."""
    if state.tracker is None:
        if bearing is None or not np.linalg.norm(bearing) > 0:
            return None, None, None
        _start_tracker(params, state, bearing)
    tracker = state.tracker
    if velocity_change is not None:
        tracker.predict(velocity_change)
    outcome = tracker.update(bearing)
    if bearing is not None and not outcome.accepted:
        state.health.bad_bearing += 1
    elif bearing is not None and float(bearing @ tracker.state[:2]) < params.target.min_range:
        # The pseudo-linear measurement G(b) p = 0 holds for p and -p alike: an estimate pushed through the
        # vessel (a cold start's range guess far off while the target's velocity is unknown) would converge
        # on the point reflection of the target and never come back. The bearing says which side it is on.
        state.health.target_restarts += 1
        _start_tracker(params, state, bearing)
        tracker = state.tracker
    return tracker.state, tracker.covariance, outcome


def _start_tracker(params: AgentParams, state: VesselState, bearing: np.ndarray) -> None:
    """A target estimate from one bearing: `initial_range_guess` along it, the target taken as still."""
    p = params.target
    guess = bearing / np.linalg.norm(bearing) * p.initial_range_guess
    covariance = np.diag([p.initial_range_guess**2] * 2 + [p.initial_covariance] * 2)
    state.tracker = PLKF(p, np.concatenate([guess, -state.motion.velocity]), covariance, dt=params.dt,
                         range_unobserved=True)
