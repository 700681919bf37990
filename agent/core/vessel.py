"""One vessel's tick: estimation, oscillator and formation control as one pure object.

`VesselAgent.tick(inputs) -> TickOutput` takes this tick's sensors and the neighbours' latest shares and
returns the command, what to share, and a record of everything it estimated and decided. No clock, thread
or I/O: the in-process fleet runner and the Zenoh agent process call exactly this, so for the same inputs
they get the same numbers.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from agent.core.control.avoidance import avoidance_velocity, safety_filter
from agent.core.control.formation import (
    desired_offset,
    desired_velocity,
    formation_velocity,
    neighbour_gain,
    saturate,
    surge_and_yaw_rate,
    tracking_velocity,
)
from agent.core.control.oscillator import oscillator_step
from agent.core.estimators import PLKF
from agent.core.estimators.plkf import BearingOutcome
from agent.core.fusion import covariance_intersection, covariance_intersection_many
from agent.core.neighbours import History, NeighbourPrior, NeighbourTrack, stamp_key
from agent.core.params import AgentParams
from agent.core.records import STOP, Command, Share, TickInputs


@dataclass(frozen=True)
class NeighbourRecord:
    position: np.ndarray          # p^_ij at the tick's time (m)
    covariance: np.ndarray        # of the filter state at its epoch
    epoch: float                  # time the filter state refers to (s)
    updates: int
    rejected: int
    iterations: int               # MCKF iterations of the last update
    outcomes: tuple = ()          # (stamp s, range m, UpdateOutcome) of each update this tick ran


@dataclass(frozen=True)
class TickRecord:
    """Everything one tick estimated and decided, for logs and metrics."""

    time: float
    phase: float
    neighbours: dict[str, NeighbourRecord]
    target_state: np.ndarray      # x^_io = [p_io; v_io]
    target_covariance: np.ndarray
    bearing_used: bool
    bearing_outcome: BearingOutcome | None   # the PLKF's update this tick (None before it has a target)
    formation_velocity: np.ndarray
    tracking_velocity: np.ndarray
    avoidance_velocity: np.ndarray
    safety_correction: np.ndarray  # what the safety filter added to (35)
    velocity_command: np.ndarray
    command: Command
    saturated: dict[str, bool]
    health: dict[str, int]


@dataclass(frozen=True)
class TickOutput:
    command: Command
    share: Share | None
    record: TickRecord | None


@dataclass
class Health:
    bad_odometry: int = 0
    bad_bearing: int = 0
    bad_ranges: int = 0
    bad_shares: int = 0
    bad_obstacles: int = 0
    stops: int = 0
    neighbours_dropped: int = 0
    neighbours_joined: int = 0
    non_finite_commands: int = 0
    target_estimates_gated: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class _Motion:
    """The vessel's own velocity over the last odometry interval, for (33) and the PLKF input."""

    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    stamp: float | None = None
    position: np.ndarray | None = None


class VesselAgent:
    """The per-vessel core: call `tick` once per sampling period."""

    def __init__(
        self,
        vessel_id: str,
        params: AgentParams,
        initial_target: np.ndarray | None = None,
        target_covariance: np.ndarray | None = None,
        initial_phase: float | None = None,
        priors: dict[str, NeighbourPrior] | None = None,
    ) -> None:
        self.id = vessel_id
        self.params = params
        self.dt = params.dt
        self.history = params.fleet.history_ticks
        self.own = History(self.history)
        self.tracks: dict[str, NeighbourTrack] = {}
        self.priors = dict(priors or {})
        self.tracker: PLKF | None = None
        if initial_target is not None:
            self.tracker = PLKF(params.target, initial_target, target_covariance, dt=self.dt)
        self.phase = initial_phase
        self.motion = _Motion()
        self.health = Health()

    # ----- the tick -----
    def tick(self, inputs: TickInputs) -> TickOutput:
        now = inputs.time
        odometry = inputs.odometry
        if odometry is None or not _finite_vector(odometry.position, 2) or not math.isfinite(odometry.heading):
            # Without own odometry nothing can be propagated: stop, as a driver's watchdog would.
            if odometry is not None:
                self.health.bad_odometry += 1
            self.health.stops += 1
            return TickOutput(STOP, None, None)
        position = np.asarray(odometry.position, dtype=float).reshape(2)
        self.own.put(now, position)
        velocity_change = self._own_motion(now, position)

        self._receive_shares(inputs, now)
        self._store_ranges(inputs, now)
        self._forget_silent(now)
        for track in self.tracks.values():
            self._start_if_needed(track)
            track.advance(self.own)
            if self.params.fleet.fuse_shared_estimates:
                self._fuse_reciprocal(track)

        estimates = {j: t.estimate_at(self.own, now) for j, t in self.tracks.items()}
        bearing = self._valid_bearing(inputs.bearing)
        target_state, target_cov, bearing_outcome = self._track_target(bearing, velocity_change)
        if target_state is not None and self.params.fleet.fuse_target_estimates:
            target_state, target_cov = self._fuse_targets(estimates, now)
        if self.phase is None:
            self.phase = math.atan2(target_state[1], target_state[0]) if target_state is not None else 0.0

        neighbour_phases = {j: self._phase_of(t, now) for j, t in self.tracks.items() if t.share is not None}
        next_phase = oscillator_step(self.phase, list(neighbour_phases.values()), self.params.control.yaw_rate,
                                     self.dt, self.params.control.oscillator_gain)
        command, parts, saturated = self._control(odometry.heading, target_state, estimates, neighbour_phases,
                                                  next_phase, inputs.obstacle_points)
        if not (math.isfinite(command.surge) and math.isfinite(command.yaw_rate)):
            # Never publish a non-finite command, whatever went wrong upstream.
            self.health.non_finite_commands += 1
            command = STOP
        heading_vector = np.array([math.cos(odometry.heading), math.sin(odometry.heading)])
        share = Share(
            sender=self.id, odometry=odometry, velocity=command.surge * heading_vector, phase=self.phase,
            target=None if target_state is None else _to_shared(target_state, self.motion.velocity),
            target_covariance=None if target_cov is None else _SWAP_VELOCITY @ target_cov @ _SWAP_VELOCITY,
            neighbours={j: (estimate, _symmetric(self.tracks[j].estimator.covariance))
                        for j, estimate in estimates.items() if estimate is not None},
        )
        record = TickRecord(
            time=now, phase=self.phase,
            neighbours={j: self._neighbour_record(t, estimates[j]) for j, t in self.tracks.items()
                        if estimates[j] is not None},
            target_state=target_state, target_covariance=target_cov,
            bearing_used=bearing_outcome is not None and bearing_outcome.accepted, bearing_outcome=bearing_outcome,
            formation_velocity=parts[0], tracking_velocity=parts[1], avoidance_velocity=parts[2],
            safety_correction=parts[3], velocity_command=parts[4], command=command, saturated=saturated,
            health=self.health.as_dict(),
        )
        self.phase = next_phase
        return TickOutput(command, share, record)

    # ----- inputs -----
    def _own_motion(self, now: float, position: np.ndarray) -> np.ndarray | None:
        """The change of own velocity at the start of the interval just ended (the PLKF input); None on the
        first tick, when there is no interval yet and the initial target estimate already refers to now."""
        change = None
        if self.motion.stamp is not None and now > self.motion.stamp:
            velocity = (position - self.motion.position) / (now - self.motion.stamp)
            change = velocity - self.motion.velocity
            self.motion.velocity = velocity
        self.motion.stamp, self.motion.position = now, position
        return change

    def _receive_shares(self, inputs: TickInputs, now: float) -> None:
        # In sender order, not arrival order: new tracks, and so every sum over neighbours, come out in the
        # same order whichever way the shares travelled.
        for sender, share in sorted(inputs.shares.items(), key=lambda item: str(item[0])):
            if sender == self.id or not _valid_share(share, self.id):
                self.health.bad_shares += 1
                continue
            track = self.tracks.get(sender)
            if track is None:
                if now - share.odometry.stamp > self.params.fleet.neighbour_timeout:
                    continue  # a stale share from a vessel we have already forgotten
                track = NeighbourTrack(sender, self.params.relative, self.dt, self.history)
                self.tracks[sender] = track
                self.health.neighbours_joined += 1
            track.receive(share, now)

    def _store_ranges(self, inputs: TickInputs, now: float) -> None:
        for neighbour, value in inputs.ranges.items():
            track = self.tracks.get(neighbour)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                    math.isfinite(value) and 0.0 <= value <= self.params.relative.max_range):
                self.health.bad_ranges += 1
                continue
            if track is not None:
                track.ranges.put(now, float(value))

    def _forget_silent(self, now: float) -> None:
        for neighbour in [j for j, t in self.tracks.items()
                          if now - t.last_heard > self.params.fleet.neighbour_timeout]:
            del self.tracks[neighbour]
            self.priors.pop(neighbour, None)
            self.health.neighbours_dropped += 1

    def _start_if_needed(self, track: NeighbourTrack) -> None:
        if track.estimator is not None or track.share is None:
            return
        prior = self.priors.pop(track.neighbour, None)
        if prior is None:
            prior = self._prior_from_target(track)
        if prior is not None and not track.start(prior, self.own):
            self.priors[track.neighbour] = prior

    def _fuse_reciprocal(self, track: NeighbourTrack) -> None:
        """Fuse j's shared estimate of p_ji (as -p_ji) into ours when both refer to the same stamp."""
        share = track.share
        if track.estimator is None or share is None or track.epoch != stamp_key(share.odometry.stamp):
            return
        theirs = share.neighbours.get(self.id)
        if theirs is None:
            return
        position, covariance = theirs
        if not (_finite_vector(position, 2) and _finite_matrix(covariance)):
            self.health.bad_shares += 1
            return
        try:
            fused, fused_covariance = covariance_intersection(
                track.estimator.position, track.estimator.covariance, -np.asarray(position, dtype=float),
                np.asarray(covariance, dtype=float))
        except np.linalg.LinAlgError:
            self.health.bad_shares += 1
            return
        if not track.estimator.assimilate(fused, fused_covariance):
            self.health.bad_shares += 1

    def _fuse_targets(self, estimates: dict[str, np.ndarray | None], now: float):
        """Covariance intersection of our target estimate with each neighbour's, moved to us:
        p_io = p^_ij + p^_jo (carried to now with j's commanded velocity), v_io = v_i - v^_o.
        A neighbour whose estimate disagrees with ours beyond the chi-square gate is left out (counted)."""
        own = (self.tracker.state, self.tracker.covariance)
        candidates = [own]
        for j, track in self.tracks.items():
            share, relative = track.share, estimates.get(j)
            if share is None or share.target is None or relative is None or track.estimator is None:
                continue
            age = now - share.odometry.stamp
            carry = np.eye(4)
            carry[0:2, 2:4] = -age * np.eye(2)           # p_jo moves with v_j - v_o over the share's age
            x_shared = carry @ np.asarray(share.target, dtype=float)
            x_shared[:2] += age * np.asarray(share.velocity, dtype=float)
            P_shared = carry @ np.asarray(share.target_covariance, dtype=float) @ carry.T
            x = np.concatenate([relative + x_shared[:2], self.motion.velocity - x_shared[2:]])
            P = _SWAP_VELOCITY @ P_shared @ _SWAP_VELOCITY
            P[:2, :2] += track.estimator.covariance
            difference = x - own[0]
            try:
                distance = float(difference @ np.linalg.solve(own[1] + P, difference))
            except np.linalg.LinAlgError:
                distance = math.inf
            if distance > TARGET_GATE:
                self.health.target_estimates_gated += 1
                continue
            candidates.append((x, P))
        if len(candidates) > 1:
            try:
                fused, fused_covariance = covariance_intersection_many(candidates)
            except np.linalg.LinAlgError:
                return own
            self.tracker.assimilate(fused, fused_covariance)
        return self.tracker.state, self.tracker.covariance

    def _prior_from_target(self, track: NeighbourTrack) -> NeighbourPrior | None:
        """A newcomer with no prior: p_ij = p_io - p_jo from both vessels' target estimates at j's share
        stamp, with the sum of their covariances; without them, the range along x with an r^2 spread.

        The target route waits until the trace of the two position covariances together is at most
        TARGET_ROUTE_FACTOR * P_io,0: a poor prior stays, because the range pairs barely observe some
        directions while the fleet holds formation (docs/fleet.md §7, the join). After `history_ticks` of
        waiting it takes the range instead."""
        share = track.share
        stamp = share.odometry.stamp
        if self.tracker is not None and share.target is not None:
            own_then, own_now = self.own.get(stamp_key(stamp)), self.own.get(stamp_key(self.motion.stamp))
            shift = own_now - own_then if own_then is not None and own_now is not None else np.zeros(2)
            mine = self.tracker.state[:2] - shift
            theirs = np.asarray(share.target, dtype=float)[:2]
            covariance = self.tracker.covariance[:2, :2] + np.asarray(share.target_covariance, dtype=float)[:2, :2]
            if np.trace(covariance) <= TARGET_ROUTE_FACTOR * self.params.target.initial_covariance:
                return NeighbourPrior(mine - theirs, covariance, stamp)
            if stamp - track.first_heard < self.history * self.dt:
                return None
        spread = self.params.relative.initial_covariance
        range_then = track.ranges.get(stamp_key(stamp))
        if range_then is None:
            return None
        return NeighbourPrior(np.array([range_then, 0.0]), np.eye(2) * max(range_then**2, spread), stamp)

    def _valid_bearing(self, bearing) -> np.ndarray | None:
        if bearing is None:
            return None
        if not _finite_vector(bearing, 2):
            self.health.bad_bearing += 1
            return None
        return np.asarray(bearing, dtype=float).reshape(2)

    def _track_target(self, bearing: np.ndarray | None, velocity_change: np.ndarray):
        if self.tracker is None:
            if bearing is None or not np.linalg.norm(bearing) > 0:
                return None, None, None
            p = self.params.target
            guess = bearing / np.linalg.norm(bearing) * p.initial_range_guess
            covariance = np.diag([p.initial_range_guess**2] * 2 + [p.initial_covariance] * 2)
            self.tracker = PLKF(p, np.concatenate([guess, -self.motion.velocity]), covariance, dt=self.dt)
        if velocity_change is not None:
            self.tracker.predict(velocity_change)
        outcome = self.tracker.update(bearing)
        if bearing is not None and not outcome.accepted:
            self.health.bad_bearing += 1
        return self.tracker.state, self.tracker.covariance, outcome

    def _phase_of(self, track: NeighbourTrack, now: float) -> float:
        """j's phase carried from its share's stamp to now at the nominal rate omega*."""
        share = track.share
        return share.phase + self.params.control.yaw_rate * (now - share.odometry.stamp)

    # ----- control -----
    def _control(self, heading, target_state, estimates, neighbour_phases, next_phase, obstacles):
        c = self.params.control
        offset = desired_offset(c.radius, self.phase)
        usable = [j for j, estimate in estimates.items() if estimate is not None and j in neighbour_phases]
        gain = neighbour_gain(len(usable), c.gain_neighbour, c.neighbour_gain_cap)
        errors = [(gain, offset - desired_offset(c.radius, neighbour_phases[j]) - estimates[j])   # (30), (33)
                  for j in usable]
        tracking = np.zeros(2)
        if target_state is not None:
            errors.append((c.gain_target, offset - target_state[:2]))
            target_velocity = self.motion.velocity - target_state[2:]               # v^_o = v_i - v^_io
            tracking = tracking_velocity(target_velocity, desired_velocity(c.radius, self.phase, next_phase,
                                                                           self.dt), c.max_target_speed)
        formation = formation_velocity(errors)
        points = self._valid_obstacles(obstacles)
        avoidance = avoidance_velocity(points, c.safety_distance, c.avoidance_gain, c.avoidance_spread)
        formation_bounded = saturate(c.max_formation_speed, formation)
        avoidance_bounded = saturate(c.max_avoidance_speed, avoidance)
        command_velocity = formation_bounded + tracking + avoidance_bounded        # (35)
        filtered, unfiltered = False, command_velocity
        if c.safety_filter:
            command_velocity, filtered = safety_filter(command_velocity, points, c.min_clearance,
                                                       c.clearance_rate)
        surge, yaw_rate, yaw_saturated = surge_and_yaw_rate(
            command_velocity, heading, c.yaw_rate, self.dt, c.max_correction_yaw_rate, c.max_speed)
        saturated = {
            "formation": formation_bounded is not formation,
            "avoidance": avoidance_bounded is not avoidance,
            "yaw_rate": yaw_saturated,
            "speed": abs(surge) >= c.max_speed,
            "safety_filter": filtered,
        }
        parts = (formation, tracking, avoidance, command_velocity - unfiltered, command_velocity)
        return Command(surge, yaw_rate), parts, saturated

    def _valid_obstacles(self, points) -> np.ndarray | None:
        if points is None:
            return None
        array = np.asarray(points, dtype=float) if not isinstance(points, np.ndarray) else points
        if array.size == 0:
            return None
        if array.ndim != 2 or array.shape[1] != 2 or not np.all(np.isfinite(array)):
            self.health.bad_obstacles += 1
            return None
        return array

    @staticmethod
    def _neighbour_record(track: NeighbourTrack, estimate: np.ndarray) -> NeighbourRecord:
        return NeighbourRecord(
            position=estimate, covariance=track.estimator.covariance, epoch=track.epoch * 1e-6,
            updates=track.updates, rejected=track.rejected, iterations=track.last_iterations,
            outcomes=tuple(track.outcomes),
        )


# x = [p_io; v_io] <-> shared [p_io; v_o] with v_o = v_i - v_io: flips the velocity block's sign.
# A joiner's pair filters start from the target estimates once trace(P_io,pp + P_jo,pp) <= this * P_io,0.
# Measured on the join scenario (10 runs): 4 (each estimate as good as a deployment one) left 2 runs with
# pair errors of 3 m; 1 settles all 10 with half the error; 0.25 waits too long and falls back to the
# range prior, which is far worse (docs/fleet.md §7).
TARGET_ROUTE_FACTOR = 1.0
_SWAP_VELOCITY = np.diag([1.0, 1.0, -1.0, -1.0])
# Chi-square 99.9 % point for 4 degrees of freedom: a neighbour's target estimate further than this from
# ours is more likely a fault than noise.
TARGET_GATE = 18.47


def _to_shared(state: np.ndarray, own_velocity: np.ndarray) -> np.ndarray:
    return np.concatenate([state[:2], own_velocity - state[2:]])


def _symmetric(matrix: np.ndarray) -> np.ndarray:
    """The symmetric part: what a share can carry (three numbers), so a share means the same in process
    and on the wire."""
    return 0.5 * (matrix + matrix.T)


def _finite_vector(value, size: int) -> bool:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return False
    return array.shape == (size,) and bool(np.isfinite(array).all())


def _finite_matrix(value) -> bool:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return False
    return array.shape == (2, 2) and bool(np.isfinite(array).all())


def _valid_share(share: object, receiver: str) -> bool:
    if not isinstance(share, Share):
        return False
    odometry = share.odometry
    return (_finite_vector(odometry.position, 2) and isinstance(odometry.stamp, (int, float))
            and math.isfinite(odometry.stamp) and math.isfinite(share.phase)
            and _finite_vector(share.velocity, 2)
            and (share.target is None or (_finite_vector(share.target, 4)
                                          and share.target_covariance is not None
                                          and np.shape(share.target_covariance) == (4, 4)
                                          and np.isfinite(share.target_covariance).all()))
            and isinstance(share.neighbours, Mapping) and _valid_pair_entry(share.neighbours.get(receiver)))


def _valid_pair_entry(entry) -> bool:
    """The only entry of a share's `neighbours` a receiver uses is its own: check that one (O(1) per share,
    where checking them all would cost O(n^2) per tick in a large fleet)."""
    if entry is None:
        return True
    try:
        position, covariance = entry
    except (TypeError, ValueError):
        return False
    return _finite_vector(position, 2) and _finite_matrix(covariance)
