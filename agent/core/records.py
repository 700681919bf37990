"""What one vessel's tick takes in and gives out: plain immutable records, no I/O.

Frames. Every vessel keeps its own odometry frame: its origin is wherever the vessel started, and its axes
are the common heading reference every vessel's IMU/compass gives (as in the paper, displacements of
different vessels can be subtracted). Positions in `Odometry` are cumulative dead-reckoned positions in that
frame, so the displacement over any interval is a difference of two of them and a lost message loses
nothing (../shared/DESIGN.md, principle 5). Relative vectors (ranges' geometry, bearings, sonar points,
estimates) are in the common orientation and need no origin.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Odometry:
    """Cumulative dead-reckoned position (m) and heading (rad) of a vessel at `stamp` (s)."""

    stamp: float
    position: np.ndarray      # (2,) in the vessel's own odometry frame
    heading: float            # yaw, common reference, rad


@dataclass(frozen=True)
class Share:
    """What a vessel tells its neighbours each tick (usv/<id>/share).

    `odometry` is its own cumulative odometry at `odometry.stamp`; `velocity` is the velocity it commanded
    for the interval that starts there (lets a receiver carry the neighbour forward to its own time);
    `phase` is its oscillator phase at that stamp; `target` its estimate [p_jo; v_o] of its own position
    relative to the target and of the target's velocity (None before it has one), with `target_covariance`
    (4x4), used to initialise a newcomer and for cooperative target estimation; `neighbours` its estimates
    of p_jk for each neighbour k, at that stamp, with their covariances.
    """

    sender: str
    odometry: Odometry
    velocity: np.ndarray       # (2,)
    phase: float
    target: np.ndarray | None = None                 # (4,) [p_jo; v_o]
    target_covariance: np.ndarray | None = None      # (4, 4)
    neighbours: Mapping[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)


@dataclass(frozen=True)
class TickInputs:
    """Everything one tick of vessel i sees. Missing sensors are None or empty, never NaN."""

    time: float                                   # this tick's time (s), the clock the agent runs on
    odometry: Odometry | None                     # own odometry at `time` (None: no fresh odometry)
    ranges: Mapping[str, float] = field(default_factory=dict)   # neighbour id -> range (m) measured at `time`
    shares: Mapping[str, Share] = field(default_factory=dict)   # neighbour id -> latest share received
    bearing: np.ndarray | None = None             # (2,) measured unit vector from the target to the vessel
    obstacle_points: np.ndarray | None = None     # (M, 2) obstacle points relative to the vessel (m)


@dataclass(frozen=True)
class Command:
    """Surge speed (m/s) and yaw rate (rad/s), always finite."""

    surge: float
    yaw_rate: float


STOP = Command(0.0, 0.0)
