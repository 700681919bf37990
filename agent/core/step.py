"""One vessel's tick: `step(params, state, inputs) -> (state, output)`.

The whole per-vessel algorithm of one sampling period, as plain numpy with no clock, thread, file or
network: the pair filters advance over the new odometry and ranges (`neighbours.py`: (11), (12), (13),
(14), (15)), the neighbours' shared estimates are fused in (`cooperation.py`), the target filter runs
(`target.py`: (24), (25), (26)), the oscillator moves the phase (28), and the control law gives the command
(`command.py`: (30), (31), (32), (33), (34), (35)). The share carries the commanded velocity (2); the first
phase is the target's bearing, as (27) places the vessel. The outputs are a function of (params, state, inputs) alone, which is why the agent process,
the in-process runner and replay get the same numbers, and why replay can start from a saved state
(`snapshot.py`).

The state is updated in place and returned, not copied: a copy of every filter per tick would cost more
than the tick's arithmetic. A caller that wants to keep the state before a tick saves a snapshot first.
"""

from __future__ import annotations

import math
import statistics
from collections import Counter
from collections.abc import Callable

import numpy as np

from agent.core.antenna import ZERO, arm_vector
from agent.core.checks import finite_vector, obstacle_array, valid_range
from agent.core.command import control_command
from agent.core.control.leeway import leeway_sway, leeway_update, set_along, set_update
from agent.core.control.oscillator import oscillator_step
from agent.core.control.separation import coasting_distance, guarded_surge, range_allowance
from agent.core.cooperation import fuse_reciprocal, fuse_targets, swap_velocity
from agent.core.membership import forget_silent, receive_shares, start_track, store_ranges
from agent.core.neighbours import NeighbourTrack, stamp_key
from agent.core.params import AgentParams
from agent.core.records import (
    STOP,
    Command,
    NeighbourRecord,
    OdometryReading,
    PairShare,
    Share,
    TickInputs,
    TickOutput,
    TickRecord,
    neighbour_record,
)
from agent.core.state import VesselState
from agent.core.target import leeway_drift, leeway_estimate, own_motion, range_from_neighbours, track_target

SEPARATION_RANGES = 5   # the median of this many last ranges judges a localised neighbour, outliers aside
# |p^_ij| further than this from that median (m): the estimate is wrong, not localised. The median of five
# Table II ranges spreads about 0.4 m (the inliers' 0.63 m, outliers mostly voted out), and the ranges span
# half a second of relative motion (up to ~0.5 m in formation): 2 m is well beyond both.
RANGE_DISAGREEMENT = 2.0
# m/s: the set model learns only while the modelled surge is this close to the command. Starting from rest
# the hull lags the first-order model (acceleration and thrust limits) and taught it 0.4-0.6 m/s of false set.
SET_STEADY = 0.05
# The range guard (`_keep_apart`, docs/equations.md D18): a neighbour without a pair estimate is judged by the
# second smallest of its last five raw ranges (outliers are mostly long; a short one is rarely alone), no
# older than a second, and the surge is at most RANGE_GUARD_RATE per metre of it beyond the guard's distance.
RANGE_GUARD_COUNT = 5
RANGE_GUARD_RANK = 1
RANGE_GUARD_AGE = 1.0     # s
RANGE_GUARD_RATE = 0.4    # 1/s: 0.04 per tick, slow enough for the lag of the order statistic (D18)


def step(params: AgentParams, state: VesselState, inputs: TickInputs) -> tuple[VesselState, TickOutput]:
    """One tick of vessel `state.vessel` on `inputs`; returns the updated state and the tick's output."""
    state, _, report = decide(params, state, inputs)
    return state, report()


def decide(params: AgentParams, state: VesselState,
           inputs: TickInputs) -> tuple[VesselState, Command, Callable[[], TickOutput]]:
    """`step` in two parts: the tick's command, and `report()` for the rest of its output (the share and the
    record), which the command does not wait for. The agent puts the command on the wire between the two, so
    that the thrusters' latency leaves out what only the neighbours and the log need. `report` reads the state
    as this tick left it: call it before the next tick."""
    health = state.health
    now = inputs.time
    odometry = inputs.odometry
    if odometry is None or not finite_vector(odometry.position, 2) or not math.isfinite(odometry.heading):
        # Without own odometry nothing can be propagated: stop, as a driver's watchdog would.
        if odometry is not None:
            health.bad_odometry += 1
        health.stops += 1
        return state, STOP, _nothing_to_report
    position = np.asarray(odometry.position, dtype=float).reshape(2)
    elapsed = _elapsed(params, state.motion.stamp, now)
    leeway_model = params.target.leeway_variance > 0.0
    # With the target filter's leeway model (and leeway_odometry) the pair filters and the share take the
    # odometry with the leeway added; the target filter keeps the raw odometry (its own estimate must not
    # feed back into its input).
    drifting = leeway_model and params.target.leeway_odometry
    over_ground = leeway_drift(state, position, odometry.heading, elapsed) if drifting else position
    x, y = over_ground.tolist()
    state.own.put(now, (x, y))     # as (x, y) floats (History)
    antenna = params.relative.antenna
    if antenna != ZERO:
        state.own_arms.put(now, arm_vector(odometry.heading, antenna))
    velocity_change = own_motion(state, now, position)

    receive_shares(params, state, inputs.shares, now)
    for stamp, ranges in inputs.earlier_ranges:
        store_ranges(params, state, ranges, stamp)
    store_ranges(params, state, inputs.ranges, now if inputs.range_stamp is None else inputs.range_stamp)
    _remember_ranges(params, state, inputs.ranges, now)
    forget_silent(params, state, now)
    # One pass over the tracks: each pair filter advances over the new ranges and is fused with j's estimate,
    # then its estimate at now, whether it is localised, its record and what the share tells j of it. (Each
    # track's results depend on that track alone; one pass builds no per-neighbour dict but those kept.)
    unusable: Counter[str] = Counter()
    fuse_shared = params.fleet.fuse_shared_estimates
    localised: dict[str, tuple[float, float]] = {}     # p^_ij at now of the localised neighbours
    # The localised neighbours' shares that carry a target estimate, with p^_ij at now: for fuse_targets
    lent: list[tuple[Share, float, float, NeighbourTrack]] = []
    medians: dict[str, float | None] = {}
    distances: dict[str, float] = {}
    estimated: list[tuple[float, float]] = []     # the p^_ij at now the separation guard keeps apart from
    guard_trace = params.control.separation_margin ** 2
    reported: list[tuple[str, NeighbourTrack, tuple[float, float], bool]] = []   # what `report` builds the records of
    now_key = stamp_key(now)     # the tracks take the tick's time as a history key: converted once, not per track
    for j, track in state.tracks.items():
        if track.estimator is None:
            start_track(params, state, track, now)
        track.advance(state.own, now_key, unusable, state.own_arms)
        track.fused = None
        if fuse_shared:
            fuse_reciprocal(params, state, track)
        p_ij = track.estimate_floats_at(state.own, now_key)
        if p_ij is None:
            continue
        # Only a localised neighbour drives the formation and lends its target estimate: an unconverged pair
        # estimate would pull the vessel, and move the neighbour's target estimate, to the wrong place.
        medians[j] = median = _recent_range(track)
        distances[j] = distance = math.hypot(*p_ij)
        trace = track.best_trace()      # read once: the localisation and the guard take it
        is_localised = _localised(params, trace, distance, median)
        if is_localised:
            localised[j] = p_ij
            share = track.share
            if share is not None and share.target is not None:
                lent.append((share, *p_ij, track))
        if is_localised or trace <= guard_trace:
            estimated.append(p_ij)
        reported.append((j, track, p_ij, is_localised))
    health.ranges_unpaired += unusable["unpaired"]
    health.ranges_gap += unusable["gap"]

    bearing = _bearing(state, inputs.bearing)
    target_state, target_cov, bearing_outcome = track_target(params, state, bearing, velocity_change,
                                                             odometry.heading)
    if target_state is not None and bearing_outcome is not None and bearing_outcome.accepted \
            and range_from_neighbours(params, state, bearing, now):
        target_state, target_cov = state.tracker.state, state.tracker.covariance
    if target_state is not None and params.fleet.fuse_target_estimates:
        target_state, target_cov = fuse_targets(params, state, lent, now)
    if state.phase is None:
        state.phase = math.atan2(target_state[1], target_state[0]) if target_state is not None else 0.0

    control = params.control
    neighbour_phases = {j: _phase_of(params, t, now) for j, t in state.tracks.items() if t.share is not None}
    next_phase = oscillator_step(state.phase, list(neighbour_phases.values()), control.yaw_rate, elapsed,
                                 control.oscillator_gain)
    obstacles, malformed = obstacle_array(inputs.obstacle_points)
    if malformed:
        health.bad_obstacles += 1
    sway = 0.0
    if leeway_model:
        # The leeway the target filter sees in the bearings (a speed log cannot see it), steered against.
        w = leeway_estimate(state)
        sway = 0.0 if w is None else leeway_sway(w, odometry.heading)
    elif control.leeway_time_constant > 0.0:
        # The wind's leeway: the sway over ground the odometry showed over the last period, fitted by heading.
        if velocity_change is not None:
            state.motion.leeway = leeway_update(state.motion.leeway, state.motion.velocity, odometry.heading,
                                                1.0 - math.exp(-elapsed / control.leeway_time_constant))
        sway = leeway_sway(state.motion.leeway, odometry.heading)
    along = 0.0
    if control.set_time_constant > 0.0:
        # A current's set along the heading: the surge over ground the odometry showed less the modelled one.
        motion = state.motion
        if velocity_change is not None and motion.surge > 0.0 and abs(motion.surge_command - motion.surge) <= SET_STEADY:
            motion.set = set_update(motion.set, motion.velocity, odometry.heading, motion.surge,
                                    1.0 - math.exp(-elapsed / control.set_time_constant))
        along = set_along(state.motion.set, odometry.heading)
    command, terms, saturated = control_command(
        control, params.dt, state.phase, next_phase, odometry.heading, target_state, state.motion.velocity,
        localised, neighbour_phases, obstacles, state.motion.yaw_rate, sway, along)
    command = _keep_apart(params, state, inputs.ranges, localised, medians, distances, estimated,
                          odometry.heading, command, now)
    if not (math.isfinite(command.surge) and math.isfinite(command.yaw_rate)):
        # Never publish a non-finite command, whatever went wrong upstream.
        health.non_finite_commands += 1
        command = STOP
    if control.yaw_lag > 0.0:
        # The boat's rate over the coming period, as the first-order lag makes it of this command.
        rate = state.motion.yaw_rate
        state.motion.yaw_rate = rate + (1.0 - math.exp(-elapsed / control.yaw_lag)) * (command.yaw_rate - rate)
    if control.set_time_constant > 0.0:
        # The boat's surge through the water over the coming period: first-order lagged (surge_lag) or at once.
        model = state.motion.surge
        blend = 1.0 - math.exp(-elapsed / control.surge_lag) if control.surge_lag > 0.0 else 1.0
        state.motion.surge = model + blend * (command.surge - model)
        state.motion.surge_command = command.surge
    phase = state.phase
    state.phase = next_phase

    def report() -> TickOutput:
        records: dict[str, NeighbourRecord] = {}
        shared: dict[str, PairShare] = {}
        for j, track, estimate, is_localised in reported:
            records[j] = _neighbour_record(track, estimate, is_localised)
            carried = _shared_estimate(track)
            if carried is not None:
                shared[j] = carried
        surge, heading = command.surge, odometry.heading
        share = Share(
            sender=state.vessel, odometry=OdometryReading(odometry.stamp, over_ground, heading) if drifting
            else odometry,
            velocity=np.array([surge * math.cos(heading), surge * math.sin(heading)]),
            phase=phase,
            target=None if target_state is None else _to_shared(target_state, state.motion.velocity),
            target_covariance=None if target_cov is None else swap_velocity(target_cov),
            neighbours=shared,
            antenna=None if antenna == ZERO else (float(antenna[0]), float(antenna[1])),
        )
        record = TickRecord(
            time=now, phase=phase,
            neighbours=records,
            target_state=target_state, target_covariance=target_cov,
            bearing_used=bearing_outcome is not None and bearing_outcome.accepted, bearing_outcome=bearing_outcome,
            formation_velocity=terms.formation, tracking_velocity=terms.tracking, avoidance_velocity=terms.avoidance,
            safety_correction=terms.safety_correction, velocity_command=terms.command, command=command,
            saturated=saturated, health=health.as_dict(),
        )
        return TickOutput(command, share, record)

    return state, command, report


def _nothing_to_report() -> TickOutput:
    return TickOutput(STOP, None, None)


def _elapsed(params: AgentParams, previous: float | None, now: float) -> float:
    """The time the phase of (28) advances by this tick: the sampling period dt in the lockstep simulation
    (and whenever the ticks are a period apart, to a microsecond), else the time since the last tick, kept
    within [0, 3 dt]. On a wall clock the tick's time is its odometry's stamp, which can repeat or skip a
    period; advancing by dt regardless would move the phase away from the neighbours' phases, which are
    carried by time."""
    if previous is None:
        return params.dt
    elapsed = now - previous
    if abs(elapsed - params.dt) <= 1e-6:
        return params.dt
    return min(max(elapsed, 0.0), 3.0 * params.dt)


def _localised(params: AgentParams, trace: float, distance: float, median: float | None) -> bool:
    """The pair filter has converged enough to steer by: trace(P_ij) (`trace`, `NeighbourTrack.best_trace`) at
    most `fleet.localised_trace`, and its estimate agrees with the ranges: |p^_ij| within `RANGE_DISAGREEMENT`
    of `median`, that of the last `SEPARATION_RANGES` ranges (`_recent_range`). A filter that cannot learn from the ranges (the paper's
    pseudo-linear ones) keeps a wrong start for good while its covariance says it is sure: in a restart test
    two vessels that both believed 5.3 m crept to 0.19 m, the guard stopping them only on the ticks the
    ranges' median happened to exceed the limit. Unlocalised, the neighbour is judged by its raw ranges
    (`_keep_apart`). `distance` is |p^_ij|."""
    if trace > params.fleet.localised_trace:
        return False
    return median is None or abs(median - distance) <= RANGE_DISAGREEMENT


def _recent_range(track: NeighbourTrack) -> float | None:
    """The median of the last `SEPARATION_RANGES` ranges kept to the neighbour (a stray range voted out);
    None while fewer are kept."""
    recent = track.ranges.last_values(SEPARATION_RANGES)
    if len(recent) < SEPARATION_RANGES:
        return None
    # The standard library's median is numpy's value on these checked floats; agent/core/median.py's NaN scan
    # and copy would cost as much again, per neighbour and tick.
    return float(statistics.median(recent))


def _keep_apart(params: AgentParams, state: VesselState, ranges, localised: dict[str, tuple[float, float]],
                medians: dict[str, float | None], distances: dict[str, float],
                estimated: list[tuple[float, float]], heading: float, command: Command, now: float) -> Command:
    """The last guard, after (31): no command moves the vessel into a neighbour.

    Every neighbour in `estimated` bounds the surge by its estimate p^_ij: the motion over the period,
    along the heading as it turns, closes on it no faster than the separation guard allows
    (agent/core/control/separation.py), which keeps its estimated distance at least `control.min_separation`
    + `control.separation_margin` whatever the formation asks. `estimated` holds the localised neighbours and
    those whose covariance puts their estimate within the margin (trace P_ij <= margin^2): a converged
    estimate that a burst of outlying ranges made disagree with their median for a few ticks was the only
    sign of a neighbour 3.5 m away while the median said 6 m (12 vessels on a 5 m circle). Not every
    estimate: a wrong one (the RLS's, metres off) would stop vessels for phantoms, and vessels that stop
    give their pair filters no motion to learn from (its closest approaches fell from 2.55 m to 1.45 m over
    Table II's seeds 0-9 when every estimate counted).
    And the ranges stop the vessel (forward or astern) where the estimates cannot be trusted: an
    unlocalised neighbour closer than `min_separation` by its raw range, or a localised one whose last
    `SEPARATION_RANGES` ranges' median is under `min_separation` while its estimate is not (a stray UWB
    range must not stop the formation, but an estimate that has gone wrong must not hide a neighbour that
    is really close).
    A neighbour without a pair estimate (its track waits on a target route, or it is not tracked: silent,
    or not yet heard) bounds the surge, either way, by its last raw ranges alone (`_range_allowances`): both
    vessels of such a pair close at most 2 x 0.04 (q - D)^+ a tick. Counted in `separation_stops`, whether
    the surge was stopped or only cut."""
    control = params.control
    limit = control.min_separation
    too_close = False
    for j, value in ranges.items():
        if j not in localised and valid_range(value, params.relative.max_range) and value < limit:
            too_close = True
    for j in localised:
        if medians[j] is not None and medians[j] < limit and distances[j] >= limit:
            too_close = True    # short ranges the estimate does not explain: its direction is not to be trusted
    if command.surge == 0.0:
        return command
    guard = limit + control.separation_margin
    if control.surge_lag > 0.0:
        # A boat whose surge lags the command by tau_u coasts |u| tau_u after a stop: keep that much further.
        guard += coasting_distance(math.hypot(*state.motion.velocity.tolist()), control.surge_lag)
    surge = 0.0 if too_close else guarded_surge(command.surge, heading, command.yaw_rate, params.dt,
                                                estimated, guard, control.separation_rate)
    if surge != 0.0:
        allowed = min(_range_allowances(state, distances, limit + control.separation_margin, now), default=math.inf)
        surge = min(max(surge, -allowed), allowed)
    if surge == command.surge:
        return command
    state.health.separation_stops += 1
    return Command(surge, command.yaw_rate)


def _remember_ranges(params: AgentParams, state: VesselState, ranges, now: float) -> None:
    """Keep the last `RANGE_GUARD_COUNT` valid raw ranges to each id ranged, tracked or not; forget an id
    not ranged for `RANGE_GUARD_AGE`."""
    kept, max_range = state.recent_ranges, params.relative.max_range
    for j, value in ranges.items():
        if valid_range(value, max_range):
            pairs = kept.get(j)
            if pairs is None:
                kept[j] = [(now, float(value))]
            else:
                # In place, per neighbour and tick: a new list each time was two more objects to collect.
                pairs.append((now, float(value)))
                if len(pairs) > RANGE_GUARD_COUNT:
                    del pairs[:-RANGE_GUARD_COUNT]
    oldest = now - RANGE_GUARD_AGE
    for j in [j for j, pairs in kept.items() if pairs[-1][0] < oldest]:
        del kept[j]


def _range_allowances(state: VesselState, distances: dict[str, float], guard_distance: float, now: float):
    """The surge each neighbour without a pair estimate allows (`range_allowance`). A neighbour with an
    estimate (in `distances`) is left to the estimate's guard, one whose initial estimate waits in
    `state.priors` too (its filter starts with its first share, the next tick)."""
    for j, pairs in state.recent_ranges.items():
        if j in distances or j in state.priors:
            continue
        recent = [r for t, r in pairs if t >= now - RANGE_GUARD_AGE]
        if recent:
            yield range_allowance(recent, RANGE_GUARD_RANK, guard_distance, RANGE_GUARD_RATE)


def _bearing(state: VesselState, bearing) -> np.ndarray | None:
    if bearing is None:
        return None
    if not finite_vector(bearing, 2):
        state.health.bad_bearing += 1
        return None
    return np.asarray(bearing, dtype=float).reshape(2)


def _phase_of(params: AgentParams, track: NeighbourTrack, now: float) -> float:
    """j's phase carried from its share's stamp to now at the nominal rate omega* of (28)."""
    share = track.share
    return share.phase + params.control.yaw_rate * (now - share.odometry.stamp)


# A pair estimate wider than this says nothing (a fix dropped starts again from 1e12 m^2, raw_range.py); the
# share leaves it out, as the wire contract cannot carry it (agent/contract.py MAX_VARIANCE, the same bound).
MAX_SHARED_VARIANCE = 1e10


def _to_shared(state: np.ndarray, own_velocity: np.ndarray) -> np.ndarray:
    return np.concatenate([state[:2], own_velocity - state[2:]])


def _shared_estimate(track: NeighbourTrack) -> PairShare | None:
    """What a share carries of the pair filter (`PairShare`): p^_ij, P_ij and the epoch (s); None when an
    element of P_ij exceeds `MAX_SHARED_VARIANCE` (or is NaN). P_ij as the three numbers of its symmetric part
    (what the wire carries), so a share means the same in process and on the wire."""
    px, py, p11, p12, p22 = track.estimator.moments()
    # The bound on the floats, before any array: numpy's all-abs-compare on a 2x2 cost 2.4 us per neighbour.
    if not (abs(p11) <= MAX_SHARED_VARIANCE and abs(p12) <= MAX_SHARED_VARIANCE
            and abs(p22) <= MAX_SHARED_VARIANCE):
        return None
    return px, py, p11, p12, p22, track.epoch * 1e-6


def _neighbour_record(track: NeighbourTrack, estimate: tuple[float, float], localised: bool) -> NeighbourRecord:
    low, high, observability = track.excitation()
    _, _, p11, p12, p22 = track.moments()
    return neighbour_record(
        position=np.array(estimate), covariance=np.array([[p11, p12], [p12, p22]]), epoch=track.epoch * 1e-6,
        updates=track.updates, rejected=track.rejected, iterations=track.last_iterations,
        outcomes=track.outcomes, localised=localised, excitation=(low, high), observability=observability,
    )
