"""Who the neighbours are: a neighbour joins with its first share, leaves when silent, and its pair filter
starts once there is a prior for it (a deployment estimate, both vessels' target estimates, or a range)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from agent.core.checks import checked_share, valid_range
from agent.core.median import median
from agent.core.neighbours import NeighbourPrior, NeighbourTrack, PairTiming, stamp_key
from agent.core.params import AgentParams
from agent.core.records import Share
from agent.core.state import VesselState

# Paired ranges a pair's target route needs before it is judged (`prior_from_target`): with ten, a route whose
# distance misses the ranges' median by more than 4 sqrt(range_variance / 10) (1.9 m with Table II's 2.32 m^2)
# is refused; one range alone lets 6 m through, and a restarted neighbour's target estimate is that far off.
ROUTE_RANGES = 10
# Ranges whose median may refuse a deployment prior (`_agrees_with_range`): three outvote one stray range.
PRIOR_RANGES = 3


def receive_shares(params: AgentParams, state: VesselState, shares: Mapping[str, Share], now: float) -> None:
    """Keep each valid share in its neighbour's track; a share from a new id starts a track (a join)."""
    # In sender order, not arrival order: new tracks, and so every sum over neighbours, come out in the
    # same order whichever way the shares travelled.
    for sender in sorted(shares, key=str):
        share = shares[sender]
        track = state.tracks.get(sender)
        if track is not None and track.share is share:
            # The share the track took last (the gate hands the latest one to every tick until the next comes,
            # the runner one that the next was lost): it was valid, and it is the newest the track holds, so
            # taking it again would write the same values back.
            continue
        checked = None if sender == state.vessel else checked_share(share, state.vessel)
        if checked is None:
            state.health.bad_shares += 1
            continue
        if track is None:
            if now - share.odometry.stamp > params.fleet.neighbour_timeout:
                continue  # a stale share from a vessel we have already forgotten
            track = NeighbourTrack(sender, params.relative, params.dt, params.fleet.history_ticks,
                                   PairTiming.of(params.fleet))
            state.tracks[sender] = track
            state.health.neighbours_joined += 1
        track.receive(share, now, checked)


def store_ranges(params: AgentParams, state: VesselState, ranges: Mapping[str, float], stamp: float) -> None:
    """Keep each valid range r~_ij of (6) at the time it was measured, for the pair filter to pair with both
    vessels' odometry of that time (12). A range older than its filter's epoch comes too late to be used."""
    key = stamp_key(stamp)
    for neighbour, value in ranges.items():
        if not valid_range(value, params.relative.max_range):
            state.health.bad_ranges += 1
            continue
        track = state.tracks.get(neighbour)
        if track is None:
            continue
        if track.epoch is not None and key <= track.epoch:
            state.health.ranges_late += 1
            continue
        track.ranges.put_key(key, float(value))


def forget_silent(params: AgentParams, state: VesselState, now: float) -> None:
    """A neighbour not heard from for `neighbour_timeout` has left: drop its track (a leave)."""
    for neighbour in [j for j, t in state.tracks.items() if now - t.last_heard > params.fleet.neighbour_timeout]:
        del state.tracks[neighbour]
        state.priors.pop(neighbour, None)
        state.health.neighbours_dropped += 1


def start_track(params: AgentParams, state: VesselState, track: NeighbourTrack, now: float) -> None:
    """Start the pair filter of `track` from its deployment prior, else from the target estimates or a range.

    A deployment prior must earn its place: one older than `fleet.prior_max_age`, or than the odometry
    kept, is stale (a restarted vessel's config describes the fleet as it was at launch); one that the
    measured range contradicts is refused. Either is counted and dropped, and the pair starts as a joiner's
    does."""
    if track.estimator is not None or track.share is None:
        return
    prior = state.priors.pop(track.neighbour, None)
    if prior is not None and prior.stamp is None:
        prior = NeighbourPrior(prior.position, prior.covariance, state.own.keys()[0] * 1e-6)
    if prior is not None and now - prior.stamp > params.fleet.prior_max_age:
        state.health.priors_stale += 1
        prior = None
    agrees = None if prior is None else _agrees_with_range(params, track, prior, now)
    if agrees is None and prior is not None:
        state.priors[track.neighbour] = prior     # too few ranges yet to refuse it by: judged next tick
        return
    if agrees is False:
        state.health.priors_refused += 1
        prior = None
    if prior is None:
        prior = prior_from_target(params, state, track)
    if prior is None:
        return
    try:
        started = track.start(prior, state.own, state.own_arms)
    except ValueError:      # a prior the filter cannot start from (not positive definite): earned nothing
        state.health.priors_refused += 1
        return
    if started == "wait":
        state.priors[track.neighbour] = prior
    elif started == "stale":
        state.health.priors_stale += 1


def _agrees_with_range(params: AgentParams, track: NeighbourTrack, prior: NeighbourPrior,
                       now: float) -> bool | None:
    """Whether |p^_ij,0| is within four standard deviations (and a metre) of the median of the ranges
    measured within `max_odometry_gap` of the prior's time (a median, so that one stray UWB range does not
    refuse a good estimate); True when there is no range to judge by. A refusal needs the median of
    `PRIOR_RANGES` ranges, or every range of that window: with fewer, while more can still come, None (wait).
    Before, the first range alone judged: one stray range (3.4 m against 10.8 m) refused a good prior."""
    key, window = stamp_key(prior.stamp), stamp_key(params.fleet.max_odometry_gap)
    near = [track.ranges.get(k) for k in track.ranges.keys() if abs(k - key) <= window]
    if not near:
        return True
    measured = float(median(near))
    position = np.asarray(prior.position, dtype=float)
    distance = float(np.hypot(*position))
    if distance == 0.0:
        return True
    direction = position / distance
    variance = float(direction @ np.asarray(prior.covariance, dtype=float) @ direction) + params.relative.range_variance
    miss = abs(measured - distance)
    if miss <= 1.0 or miss**2 <= 16.0 * variance:
        return True
    return False if len(near) >= PRIOR_RANGES or stamp_key(now) > key + window else None


def prior_from_target(params: AgentParams, state: VesselState, track: NeighbourTrack) -> NeighbourPrior | None:
    """The initial estimate of (10) for a newcomer with no prior: p_ij = p_io - p_jo from both vessels'
    target estimates at j's share stamp, with the sum of their covariances; without them, the range along x
    with a spread of max(r^2, P_ij,0).

    The target route waits until the trace of the two position covariances together is at most
    `fleet.target_route_factor` * P_io,0: a poor prior stays, because the range pairs barely observe some
    directions while the fleet holds formation (docs/fleet.md §7, the join). It also waits while our target
    estimate disagrees with the ranges (`_target_agrees_with_ranges`; counted in `priors_refused`), and until
    a range can judge it at all: a neighbour heard again after a restart shares at once a target estimate that
    its own new filter believes long before it is right, and a pair started from it before any range is kept
    (the track's histories begin with its first share) was localised at once, 7 m wrong on both sides of the
    pair, and never corrected (the ranges then look like outliers to it). After `history_ticks` of waiting it
    takes the range instead."""
    share = track.share
    stamp = share.odometry.stamp
    route = _route(state, track)
    if route is not None:
        if np.trace(route.covariance) <= params.fleet.target_route_factor * params.target.initial_covariance:
            agrees = _target_agrees_with_ranges(params, state, track, route)
            if agrees:
                return route
            if agrees is False:
                state.health.priors_refused += 1
        if stamp - track.first_heard < params.fleet.history_ticks * params.dt:
            return None
    spread = params.relative.initial_covariance
    # The range of the share's time; on a wall clock no range is measured at a neighbour's odometry stamp
    # (each vessel samples on its own phase), so the last range kept, at its own time: waiting for an exact
    # match kept a pair unstarted for good (a sea-mode fleet, 2026-12-04: two vessels frozen 3.5 m apart).
    key = stamp_key(stamp)
    range_then = track.ranges.get(key)
    if range_then is None and track.ranges.keys():
        key = track.ranges.keys()[-1]
        range_then = track.ranges.get(key)
    if range_then is None:
        return None
    return NeighbourPrior(np.array([range_then, 0.0]), np.eye(2) * max(range_then**2, spread), key * 1e-6)


def _route(state: VesselState, track: NeighbourTrack) -> NeighbourPrior | None:
    """p_ij = p_io - p_jo from both vessels' target estimates at j's share stamp, with the sum of their
    covariances; None without them."""
    share = track.share
    if state.tracker is None or share is None or share.target is None:
        return None
    stamp = share.odometry.stamp
    theirs = np.asarray(share.target, dtype=float)[:2]
    own_keys = state.own.keys()
    if own_keys and stamp_key(stamp) > own_keys[-1]:
        # j's share is newer than our last odometry (on wall clocks its period can run a few ms ahead of
        # ours, tick after tick): judged at its stamp the route could never be paired with our odometry.
        # Carry j's estimate back along j's odometry to our last odometry's time: p_j(t') - p_o =
        # (p_j(t) - p_o) - (p_j(t) - p_j(t')).
        then, _ = track.odometry.at(own_keys[-1], track.gap_key)
        if then is not None:
            theirs = theirs - np.subtract(share.odometry.position, then)
            stamp = own_keys[-1] * 1e-6
    own_then, own_now = state.own.get(stamp_key(stamp)), state.own.get(stamp_key(state.motion.stamp))
    shift = np.subtract(own_now, own_then) if own_then is not None and own_now is not None else np.zeros(2)
    mine = state.tracker.state[:2] - shift
    covariance = state.tracker.covariance[:2, :2] + np.asarray(share.target_covariance, dtype=float)[:2, :2]
    return NeighbourPrior(mine - theirs, covariance, stamp)


def _target_agrees_with_ranges(params: AgentParams, state: VesselState, track: NeighbourTrack,
                               route: NeighbourPrior) -> bool | None:
    """Whether the target route of `track` agrees with the ranges kept to its neighbour, and our target
    estimate, placed among the shared one of the neighbour whose line of sight lies closest to our bearing,
    with the ranges to that one (`_agrees_with_ranges_kept`).

    A vessel (re)started without initial estimates starts its target filter at a guessed range, and the
    filter can come to believe it long before it is right (a boat restarted 25 m from the target: a position
    trace of 0.4 m^2 with 20 m of error; under 1 m^2 with 6 m). A pair filter started from it is localised at
    once and wrong, on both sides of the pair, and so confident that the ranges barely move it: in the
    restart tests such pairs steered vessels to within 1.6 m of each other. That error lies along our
    bearing, and ranges see an error along their line of sight: the pair's own may not see it, the
    neighbour's closest to our bearing does. (One neighbour, not all: asking all of them for each pair
    waiting to start costs a 50-vessel joiner a third of a second a tick.) None while no range of the pair's
    own can judge the route yet."""
    own = _agrees_with_ranges_kept(params, state, track, route, least=ROUTE_RANGES)
    if not own:
        return own
    bearing = state.tracker.state[:2]
    across, alignment = None, -1.0
    for other in state.tracks.values():
        other_route = _route(state, other) if other is not track else None
        if other_route is not None:
            norm = float(np.hypot(*other_route.position) * np.hypot(*bearing))
            aligned = abs(float(other_route.position @ bearing)) / norm if norm > 0.0 else 0.0
            if aligned > alignment:
                across, alignment = (other, other_route), aligned
    return across is None or _agrees_with_ranges_kept(params, state, *across) is not False


def _agrees_with_ranges_kept(params: AgentParams, state: VesselState, track: NeighbourTrack,
                             prior: NeighbourPrior, least: int = 1) -> bool | None:
    """Whether `prior`, carried to the time of each range kept by both vessels' odometry, agrees with those
    ranges: the median of measured minus predicted |p_ij| within four standard deviations of a median of n
    ranges (range_variance / n; some 0.9 m with a full history). The prior's own covariance is left out: it
    is what is in doubt. None while fewer than `least` ranges can be paired with both odometries."""
    carried = track.ranges_with_motion(state.own, stamp_key(prior.stamp))
    if carried is None:
        return None
    position = np.asarray(prior.position, dtype=float)
    # (as arrays here, where these sums run once per prior tried)
    misses = [measured - float(np.hypot(*(position + mine - theirs))) for measured, mine, theirs in carried[1]]
    if len(misses) < least or not misses:
        return None
    return float(median(misses)) ** 2 <= 16.0 * params.relative.range_variance / len(misses)
