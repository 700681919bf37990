"""The vessel's own motion and its target filter (the PLKF of Sec. III-B) through one tick."""

from __future__ import annotations

import math

import numpy as np

from agent.core.estimators.plkf import PLKF
from agent.core.estimators.plkf_leeway import LeewayPLKF, leeway_projection
from agent.core.fusion import covariance_intersection_many
from agent.core.neighbours import stamp_key
from agent.core.params import AgentParams, TargetEstimationParams
from agent.core.records import BearingOutcome
from agent.core.state import VesselState
from agent.core.target_range import RangeWitness, range_along_bearing

# The least ranges, paired with both odometries, a neighbour's say on the target's range needs
# (`range_from_neighbours`), as a pair's target route asks (membership.ROUTE_RANGES).
WITNESS_RANGES = 10
# Neighbours asked at most, in the tracks' order: six pin s well (var(s) falls as 1/m), and each costs the fit
# its ranges and two more starts, which a 50-vessel joiner would pay every tick until the range is taken.
MAX_WITNESSES = 6
# How sure the ranges must make a range from the neighbours before it is taken (its variance from the ranges
# alone, the neighbours' target estimates taken as exact), as a fraction of the target routes' bound: the
# pairs started from the routes inherit its error, and the paper's MCKF never corrects it from the ranges.
FIX_VARIANCE = 0.05


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
    """A target estimate from one bearing: `initial_range_guess` along it, the target taken as still:
    v_io = v_i - v_o = v_i (x_io is the vessel relative to the target, as the bearing of (9) points)."""
    p = params.target
    guess = bearing / np.linalg.norm(bearing) * p.initial_range_guess
    covariance = np.diag([p.initial_range_guess**2] * 2 + [p.initial_covariance] * 2)
    state.tracker = target_filter(p, np.concatenate([guess, state.motion.velocity]), covariance, params.dt,
                                  range_unobserved=True, heading=heading)


def range_from_neighbours(params: AgentParams, state: VesselState, bearing: np.ndarray | None, now: float) -> bool:
    """A target filter whose range is unobserved (D19) takes it from its neighbours (target_range.py, D20):
    along this tick's bearing, the s that fits the ranges to every neighbour whose own target estimate is
    sure (position trace within `fleet.target_route_factor` * P_io,0), over every range kept to it.
    Taken in (`assimilate`: the range now counts as observed) when the ranges alone pin s within FIX_VARIANCE
    of that bound (the neighbours' own errors are in the routes' covariance either way), so that the pairs' target routes, which wait on it, can start. True when taken, counted in
    `target_ranges_fixed`.

    The velocity is taken from the same neighbours: v_io = v_i - v_o with v_o the covariance intersection
    (equal weights, as `fuse_targets`) of the witnesses' shared v^_o, and P_vv its covariance, uncorrelated
    with p. Why not the filter's own: while its range was unobserved, its bearings saw the relative motion
    only as the angular rate q^T v / r and the range rate u^T v / r, both at its own wrong r^ (D19), so
    its v is as unearned as its range, along u and across it, and P_vv as confident. Measured at the take
    (dropout_join, vessel 2 restarted at 30 s after 20 s down, seed 1): r^ 5.4 m for 26.1, v off by 2.6 m/s
    across u and 1.4 along it at P_vv 0.006 (m/s)^2 along u; kept, the range then drifted 5.5 m off in
    4 s. Widening P_vv along u by P_io,0's variance, or resetting u^T v to a still target's, made it worse
    (12 m): the bearings, with an uncertain u^T v, pulled the range as in D19 and the 2.6 m/s across
    went into u^T v as the line of sight turned.

    Why: a vessel restarted or joining without estimates cannot fuse its neighbours' target estimates before
    its pair filters are localised, and its pairs wait on target routes that wait on its target range: with
    the paper's MCKF, which does not localise from ranges, a joiner's pairs stayed 10-20 m wrong for the
    rest of the run (dropout_join, D19)."""
    tracker = state.tracker
    if tracker is None or not tracker.range_unobserved or bearing is None:
        return False
    norm = math.hypot(float(bearing[0]), float(bearing[1]))
    if not norm > 0.0:
        return False
    sure = params.fleet.target_route_factor * params.target.initial_covariance
    own_now = state.own.get(stamp_key(now))
    if own_now is None:
        return False
    witnesses, velocities = [], []
    for track in state.tracks.values():
        share = track.share
        if len(witnesses) == MAX_WITNESSES:
            break
        if share is None or share.target is None or share.target_covariance is None:
            continue
        shared_covariance = np.asarray(share.target_covariance, dtype=float)
        covariance = shared_covariance[:2, :2]
        if np.trace(covariance) > sure:
            continue
        carried = track.ranges_with_motion(state.own, stamp_key(share.odometry.stamp))
        if carried is None or len(carried[1]) < WITNESS_RANGES:
            continue
        mine_then, kept = carried
        distances = [measured for measured, _, _ in kept]
        moves = [(mx - tx, my - ty) for _, (mx, my), (tx, ty) in kept]
        # p_io at the share's time is p_io now less our motion since (the target taken as still over the
        # share's age, as a target route takes it, membership._route).
        shift = (own_now[0] - mine_then[0], own_now[1] - mine_then[1])
        shared_target = np.asarray(share.target, dtype=float)
        witnesses.append(RangeWitness(shared_target[:2] + shift, covariance, np.array(distances), np.array(moves),
                                      params.relative.range_variance))
        velocities.append((shared_target[2:], shared_covariance[2:, 2:]))
    direction = np.asarray(bearing, dtype=float) / norm
    fit = range_along_bearing(direction, witnesses, params.target.min_range)
    if fit is None or fit[2] > FIX_VARIANCE * sure:
        return False
    s, variance, _ = fit
    try:
        target_velocity, P_vv = covariance_intersection_many(velocities)
    except np.linalg.LinAlgError:
        return False
    across = np.array([-direction[1], direction[0]])
    P = np.zeros((4, 4))
    P[:2, :2] = (variance * np.outer(direction, direction)
                 + (s * s + variance) * params.target.bearing_variance * np.outer(across, across))
    P[2:, 2:] = P_vv
    x = np.concatenate([s * direction, state.motion.velocity - target_velocity])
    if not tracker.assimilate(x, P):
        return False
    state.health.target_ranges_fixed += 1
    return True
