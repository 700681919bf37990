"""Cooperative fusion with the neighbours' shared estimates, by covariance intersection (`fusion.py`).

Two kinds: a neighbour's estimate of our pair, p^_ji, is fused into our p^_ij (reciprocal fusion); and
each neighbour's target estimate, moved to us through our estimate of where it is, is fused into ours,
after a chi-square gate that leaves out an estimate more likely a fault than noise.
"""

from __future__ import annotations

import math

import numpy as np

from agent.core.checks import finite_matrix, finite_vector
from agent.core.fusion import covariance_intersection, covariance_intersection_many
from agent.core.neighbours import NeighbourTrack, stamp_key
from agent.core.params import AgentParams
from agent.core.state import VesselState

# x = [p_io; v_io] <-> shared [p_io; v_o] with v_o = v_i - v_io: flips the velocity block's sign.
SWAP_VELOCITY = np.diag([1.0, 1.0, -1.0, -1.0])


def fuse_reciprocal(params: AgentParams, state: VesselState, track: NeighbourTrack) -> None:
    """This tick's p^_ij (`track.fused`): covariance intersection of our pair filter's estimate with j's own
    estimate of p_ji (as -p_ji), both at our filter's epoch. Not in the paper (docs/equations.md, D1).

    Each vessel shares its own filter's estimate, never a fused one, and neither filter takes the fusion in:
    the two vessels compute the same fused estimate (as p_ij and p_ji) from the same two independent ones,
    whoever ticks first. Fed back into the filters, as the paper-like design did, the result depended on the
    order of the ticks (the vessel whose tick came later kept most of its own prior), and at sea, where the
    vessels tick at their own times, pairs ended up with one vessel's prior instead of the mean of both.

    j's estimate refers to the time j gave with it (its filter's epoch, in j's clock). It is carried to our
    epoch by both vessels' measured odometry between the two times (j's from its shares), its covariance
    grown by the displacement noise of (15), if the two times are at most `fleet.max_odometry_gap` apart.
    Only measured motion enters: a commanded velocity the vessel did not follow (a boat held at the start, a
    thruster lagging) would otherwise be taken as truth."""
    share = track.share
    if track.estimator is None or share is None:
        return
    theirs = share.neighbours.get(state.vessel)
    if theirs is None:
        return
    position, covariance, stamp = theirs
    if not (finite_vector(position, 2) and finite_matrix(covariance) and math.isfinite(stamp)):
        state.health.bad_shares += 1
        return
    their_position, their_covariance = -np.asarray(position, dtype=float), np.asarray(covariance, dtype=float)
    key = stamp_key(stamp)
    if key != track.epoch:
        gap = stamp_key(params.fleet.max_odometry_gap)
        if abs(key - track.epoch) > gap:
            return
        mine_then, theirs_then, why = track.positions_at(state.own, key)
        if why:
            return
        their_position = their_position + (track.epoch_own - mine_then) - (track.epoch_other - theirs_then)
        intervals = abs(key - track.epoch) * 1e-6 / params.dt
        their_covariance = their_covariance + 2.0 * params.relative.displacement_variance * intervals * np.eye(2)
    try:
        fused, fused_covariance = covariance_intersection(
            track.estimator.position, track.estimator.covariance, their_position, their_covariance)
    except np.linalg.LinAlgError:
        state.health.bad_shares += 1
        return
    if finite_vector(fused, 2) and finite_matrix(fused_covariance):
        track.fused = (fused, fused_covariance)
    else:
        state.health.bad_shares += 1


def fuse_targets(params: AgentParams, state: VesselState, estimates: dict[str, np.ndarray | None], now: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Covariance intersection of our target estimate with each neighbour's, moved to us:
    p_io = p^_ij + p^_jo (carried to now with j's commanded velocity), v_io = v_i - v^_o as in (33), with
    p^_ij of (10). Not in the paper (docs/equations.md, D2).
    A neighbour whose estimate disagrees with ours beyond `fleet.target_gate` (chi-square, 4 degrees of
    freedom) is left out and counted. Returns the fused state and covariance (ours alone if none fits)."""
    tracker = state.tracker
    own = (tracker.state, tracker.covariance)
    candidates = [own]
    for j, track in state.tracks.items():
        share, relative = track.share, estimates.get(j)
        if share is None or share.target is None or relative is None or track.estimator is None:
            continue
        age = now - share.odometry.stamp
        carry = np.eye(4)
        carry[0:2, 2:4] = -age * np.eye(2)           # p_jo moves with v_j - v_o over the share's age
        x_shared = carry @ np.asarray(share.target, dtype=float)
        x_shared[:2] += age * np.asarray(share.velocity, dtype=float)
        P_shared = carry @ np.asarray(share.target_covariance, dtype=float) @ carry.T
        x = np.concatenate([relative + x_shared[:2], state.motion.velocity - x_shared[2:]])
        P = SWAP_VELOCITY @ P_shared @ SWAP_VELOCITY
        P[:2, :2] += track.best()[1]
        difference = x - own[0]
        try:
            distance = float(difference @ np.linalg.solve(own[1] + P, difference))
        except np.linalg.LinAlgError:
            distance = math.inf
        if distance > params.fleet.target_gate:
            state.health.target_estimates_gated += 1
            continue
        candidates.append((x, P))
    if len(candidates) > 1:
        try:
            fused, fused_covariance = covariance_intersection_many(candidates)
        except np.linalg.LinAlgError:
            return own
        tracker.assimilate(fused, fused_covariance)
    return tracker.state, tracker.covariance
