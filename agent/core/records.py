"""What one vessel's tick takes in and gives out: plain immutable records, no I/O, and their JSON forms.

Frames. Every vessel keeps its own odometry frame: its origin is wherever the vessel started, and its axes
are the common heading reference every vessel's IMU/compass gives (as in the paper, displacements of
different vessels can be subtracted). Positions in `OdometryReading` are cumulative dead-reckoned positions in
that frame, so the displacement over any interval is a difference of two of them and a lost message loses
nothing (../shared/DESIGN.md, principle 5). Relative vectors (ranges' geometry, bearings, sonar points,
estimates) are in the common orientation and need no origin.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class OdometryReading:
    """Cumulative dead-reckoned position (m) and heading (rad) of a vessel at `stamp` (s)."""

    stamp: float
    position: np.ndarray      # (2,) in the vessel's own odometry frame
    heading: float            # yaw, common reference, rad


# A share's estimate of one pair: p^_jk (px, py), P_jk as the three numbers of its symmetric part (p11, p12,
# p22) as the wire carries them (agent/contract.py PairEstimate), and the time (s) it refers to. One flat tuple
# of floats: a vessel builds one per neighbour and tick, each receiver checks its own as it is, and a fleet in
# one process holds n (n - 1) of them at once (nested tuples or arrays were more objects to allocate, and for
# the collector to count).
PairShare = tuple[float, float, float, float, float, float]


@dataclass(frozen=True)
class Share:
    """What a vessel tells its neighbours each tick (usv/<id>/share).

    `odometry` is its own cumulative odometry at `odometry.stamp`; `velocity` is the velocity it commanded
    for the interval that starts there (lets a receiver carry the neighbour forward to its own time);
    `phase` is its oscillator phase at that stamp; `target` its estimate [p_jo; v_o] of its own position
    relative to the target and of the target's velocity (None before it has one), with `target_covariance`
    (4x4), used to initialise a newcomer and for cooperative target estimation; `neighbours` its estimates
    of p_jk for each neighbour k with their covariances and the time (s, the sender's clock) each refers to:
    its pair filter's epoch, the last range it used, where both vessels' odometry was measured. An estimate
    carried on to the share's stamp would carry k with k's commanded velocity, and a receiver that fuses it
    would take that guess into its filter, tick after tick. `antenna` is its UWB antenna's lever arm, which
    with `odometry.heading` places the antenna its ranges are measured from (agent/core/antenna.py).
    """

    sender: str
    odometry: OdometryReading
    velocity: np.ndarray       # (2,)
    phase: float
    target: np.ndarray | None = None                 # (4,) [p_jo; v_o]
    target_covariance: np.ndarray | None = None      # (4, 4)
    neighbours: Mapping[str, PairShare] = field(default_factory=dict)
    antenna: tuple[float, float] | None = None       # its UWB antenna (forward, left) (m); None: centre


@dataclass(frozen=True)
class TickInputs:
    """Everything one tick of vessel i sees. Missing sensors are None or empty, never NaN."""

    time: float                                   # this tick's time (s), the clock the agent runs on
    odometry: OdometryReading | None              # own odometry at `time` (None: no fresh odometry)
    ranges: Mapping[str, float] = field(default_factory=dict)   # neighbour id -> range (m) at `range_stamp`
    shares: Mapping[str, Share] = field(default_factory=dict)   # neighbour id -> latest share received
    bearing: np.ndarray | None = None             # (2,) measured unit vector from the target to the vessel
    obstacle_points: np.ndarray | None = None     # (M, 2) obstacle points relative to the vessel (m)
    range_stamp: float | None = None              # when the ranges were measured (s); None: at `time`
    # Range sets measured before `range_stamp` and not yet used, oldest first: (stamp s, neighbour id -> m).
    # A UWB module ranges at its own rate, not the tick's, so one tick may bring more than one set.
    earlier_ranges: tuple[tuple[float, Mapping[str, float]], ...] = ()


@dataclass(frozen=True)
class Command:
    """Surge speed (m/s) and yaw rate (rad/s), always finite."""

    surge: float
    yaw_rate: float


STOP = Command(0.0, 0.0)


@dataclass(frozen=True)
class NeighbourRecord:
    position: np.ndarray          # p^_ij at the tick's time (m)
    covariance: np.ndarray        # of the filter state at its epoch
    epoch: float                  # time the filter state refers to (s)
    updates: int
    rejected: int
    iterations: int               # MCKF iterations of the last update
    outcomes: tuple = ()          # (stamp s, range m, UpdateOutcome) of each update this tick ran
    localised: bool = False       # steered the formation this tick (step.py `_localised`)
    # The relative path's spread over the window (observability.py): its eigenvalues (m^2), smallest first,
    # and what they make of the pair: observable, mirror-ambiguous or unobservable.
    excitation: tuple[float, float] = (0.0, 0.0)
    observability: str = "unobservable"


def neighbour_record(position: np.ndarray, covariance: np.ndarray, epoch: float, updates: int, rejected: int,
                     iterations: int, outcomes: tuple, localised: bool, excitation: tuple[float, float],
                     observability: str) -> NeighbourRecord:
    """`NeighbourRecord` with every field given, the same record: its frozen __init__ sets the ten fields
    through object.__setattr__ one by one (about 3 us, per neighbour and tick), here its __dict__ is filled at
    once, in the fields' order."""
    record = object.__new__(NeighbourRecord)
    record.__dict__.update(position=position, covariance=covariance, epoch=epoch, updates=updates,
                           rejected=rejected, iterations=iterations, outcomes=outcomes, localised=localised,
                           excitation=excitation, observability=observability)
    return record


@dataclass(frozen=True, slots=True)
class BearingOutcome:
    """What one bearing update did; `innovation` is the cross-bearing component q^T p^- (metres) and
    `innovation_variance` its predicted variance q^T (P^-_pp + R_z) q."""

    accepted: bool
    reason: str = ""
    innovation: float = 0.0
    innovation_variance: float = 0.0


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


# ----- JSON forms (plain dicts). JSON writes a float as the shortest text that reads back to the same float,
# so a record read back from a log or a snapshot is bit for bit the one written. -----
def floats(values) -> list[float]:
    return np.asarray(values, dtype=float).ravel().tolist()


def _pair_share(entry: dict, share_stamp: float) -> PairShare:
    """A logged estimate of a pair (its covariance a 2x2 row by row) as a `PairShare`."""
    px, py = floats(entry["position"])
    p11, p12, _, p22 = floats(entry["covariance"])
    # Before log format 4 an estimate referred to the share's own stamp.
    return px, py, p11, p12, p22, float(entry.get("stamp", share_stamp))


def odometry_to_json(odometry: OdometryReading) -> dict:
    return {"stamp": float(odometry.stamp), "position": floats(odometry.position),
            "heading": float(odometry.heading)}


def odometry_from_json(data: dict) -> OdometryReading:
    return OdometryReading(data["stamp"], np.array(data["position"], dtype=float), data["heading"])


def share_to_json(share: Share) -> dict:
    return {
        "sender": share.sender, "odometry": odometry_to_json(share.odometry), "velocity": floats(share.velocity),
        "phase": float(share.phase),
        "target": None if share.target is None else floats(share.target),
        "target_covariance": None if share.target_covariance is None else floats(share.target_covariance),
        # The covariance as its 2x2 row by row, as logs have always held it.
        "neighbours": {j: {"position": [px, py], "covariance": [p11, p12, p12, p22], "stamp": stamp}
                       for j, (px, py, p11, p12, p22, stamp) in share.neighbours.items()},
        # Only when there is one: a share with its antenna at the centre is written as before.
        **({} if share.antenna is None else {"antenna": floats(share.antenna)}),
    }


def share_from_json(data: dict) -> Share:
    return Share(
        sender=data["sender"], odometry=odometry_from_json(data["odometry"]),
        velocity=np.array(data["velocity"], dtype=float), phase=data["phase"],
        target=None if data["target"] is None else np.array(data["target"], dtype=float),
        target_covariance=None if data["target_covariance"] is None
        else np.array(data["target_covariance"], dtype=float).reshape(4, 4),
        # Before log format 4 an estimate referred to the share's own stamp.
        neighbours={j: _pair_share(e, data["odometry"]["stamp"]) for j, e in data["neighbours"].items()},
        antenna=None if data.get("antenna") is None else tuple(float(v) for v in data["antenna"]),
    )


def inputs_to_json(inputs: TickInputs) -> dict:
    return {
        "time": float(inputs.time),
        "odometry": None if inputs.odometry is None else odometry_to_json(inputs.odometry),
        "ranges": {j: float(r) for j, r in inputs.ranges.items()},
        "bearing": None if inputs.bearing is None else floats(inputs.bearing),
        "obstacle_points": None if inputs.obstacle_points is None
        else np.asarray(inputs.obstacle_points, dtype=float).reshape(-1, 2).tolist(),
        "shares": {j: share_to_json(share) for j, share in inputs.shares.items()},
        "range_stamp": inputs.range_stamp,
        "earlier_ranges": [[float(stamp), {j: float(r) for j, r in ranges.items()}]
                           for stamp, ranges in inputs.earlier_ranges],
    }


def inputs_from_json(data: dict) -> TickInputs:
    points = data["obstacle_points"]
    return TickInputs(
        time=data["time"],
        odometry=None if data["odometry"] is None else odometry_from_json(data["odometry"]),
        ranges=dict(data["ranges"]),
        shares={j: share_from_json(s) for j, s in data["shares"].items()},
        bearing=None if data["bearing"] is None else np.array(data["bearing"], dtype=float),
        obstacle_points=None if points is None else np.array(points, dtype=float).reshape(-1, 2),
        range_stamp=data.get("range_stamp"),   # absent in format 1: the ranges were measured at `time`
        earlier_ranges=tuple((float(stamp), dict(ranges)) for stamp, ranges in data.get("earlier_ranges", ())),
    )

