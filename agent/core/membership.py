"""Who the neighbours are: a neighbour joins with its first share, leaves when silent, and its pair filter
starts once there is a prior for it (a deployment estimate, both vessels' target estimates, or a range)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from agent.core.checks import valid_range, valid_share
from agent.core.neighbours import NeighbourPrior, NeighbourTrack, stamp_key
from agent.core.params import AgentParams
from agent.core.records import Share
from agent.core.state import VesselState


def receive_shares(params: AgentParams, state: VesselState, shares: Mapping[str, Share], now: float) -> None:
    """Keep each valid share in its neighbour's track; a share from a new id starts a track (a join)."""
    # In sender order, not arrival order: new tracks, and so every sum over neighbours, come out in the
    # same order whichever way the shares travelled.
    for sender, share in sorted(shares.items(), key=lambda item: str(item[0])):
        if sender == state.vessel or not valid_share(share, state.vessel):
            state.health.bad_shares += 1
            continue
        track = state.tracks.get(sender)
        if track is None:
            if now - share.odometry.stamp > params.fleet.neighbour_timeout:
                continue  # a stale share from a vessel we have already forgotten
            track = NeighbourTrack(sender, params.relative, params.dt, params.fleet.history_ticks)
            state.tracks[sender] = track
            state.health.neighbours_joined += 1
        track.receive(share, now)


def store_ranges(params: AgentParams, state: VesselState, ranges: Mapping[str, float], now: float) -> None:
    """Keep each valid range r~_ij of (6) at this tick's stamp, for the pair filter to pair with odometry (12)."""
    for neighbour, value in ranges.items():
        if not valid_range(value, params.relative.max_range):
            state.health.bad_ranges += 1
            continue
        track = state.tracks.get(neighbour)
        if track is not None:
            track.ranges.put(now, float(value))


def forget_silent(params: AgentParams, state: VesselState, now: float) -> None:
    """A neighbour not heard from for `neighbour_timeout` has left: drop its track (a leave)."""
    for neighbour in [j for j, t in state.tracks.items() if now - t.last_heard > params.fleet.neighbour_timeout]:
        del state.tracks[neighbour]
        state.priors.pop(neighbour, None)
        state.health.neighbours_dropped += 1


def start_track(params: AgentParams, state: VesselState, track: NeighbourTrack) -> None:
    """Start the pair filter of `track` from its deployment prior, else from the target estimates or a range."""
    if track.estimator is not None or track.share is None:
        return
    prior = state.priors.pop(track.neighbour, None)
    if prior is None:
        prior = prior_from_target(params, state, track)
    if prior is not None and not track.start(prior, state.own):
        state.priors[track.neighbour] = prior


def prior_from_target(params: AgentParams, state: VesselState, track: NeighbourTrack) -> NeighbourPrior | None:
    """The initial estimate of (10) for a newcomer with no prior: p_ij = p_io - p_jo from both vessels'
    target estimates at j's share stamp, with the sum of their covariances; without them, the range along x
    with a spread of max(r^2, P_ij,0).

    The target route waits until the trace of the two position covariances together is at most
    `fleet.target_route_factor` * P_io,0: a poor prior stays, because the range pairs barely observe some
    directions while the fleet holds formation (docs/fleet.md §7, the join). After `history_ticks` of
    waiting it takes the range instead."""
    share = track.share
    stamp = share.odometry.stamp
    if state.tracker is not None and share.target is not None:
        own_then, own_now = state.own.get(stamp_key(stamp)), state.own.get(stamp_key(state.motion.stamp))
        shift = own_now - own_then if own_then is not None and own_now is not None else np.zeros(2)
        mine = state.tracker.state[:2] - shift
        theirs = np.asarray(share.target, dtype=float)[:2]
        covariance = state.tracker.covariance[:2, :2] + np.asarray(share.target_covariance, dtype=float)[:2, :2]
        if np.trace(covariance) <= params.fleet.target_route_factor * params.target.initial_covariance:
            return NeighbourPrior(mine - theirs, covariance, stamp)
        if stamp - track.first_heard < params.fleet.history_ticks * params.dt:
            return None
    spread = params.relative.initial_covariance
    range_then = track.ranges.get(stamp_key(stamp))
    if range_then is None:
        return None
    return NeighbourPrior(np.array([range_then, 0.0]), np.eye(2) * max(range_then**2, spread), stamp)
