"""Odometry adapter: dead reckoning from speed (m/s) and IMU yaw samples to the contract's odometry.

Frames and units (docs/contract.md, "Odometry"):
- heading (rad): yaw in the fleet's common heading reference, counter-clockwise from the x axis, wrapped to
  (-pi, pi]. A sensor yaw is mapped as heading = yaw_sign * yaw + yaw_offset; a compass heading (clockwise
  from north, with x east and y north) needs yaw_sign = -1 and yaw_offset = pi/2.
- position (m): cumulative, in the vessel's own odometry frame, whose axes are those of the common heading
  reference and whose origin is where the first sample was taken. It never jumps.
- covariance: 3x3 of (x, y, heading), row-major: each position axis grows by `position_variance_per_m` per
  metre travelled; the heading has `heading_variance` (absolute yaw) plus, when the yaw is integrated from
  a rate, `yaw_rate_variance_per_s` per second elapsed.

Between two samples the vessel is taken to move along a circular arc: constant turn rate from the first
heading to the second (or, with a yaw rate input, a turn of the trapezoid of the two rates times dt), and
distance = trapezoid of the two speeds times dt. The arc's chord has length
ds * sin(dpsi/2) / (dpsi/2) along psi0 + dpsi/2, which is exact for a steady turn at steady speed.

`parse_vhw` reads NMEA 0183 VHW, "water speed and heading"
(https://gpsd.gitlab.io/gpsd/NMEA.html#_vhw_water_speed_and_heading):
`$--VHW,<heading true, deg>,T,<heading magnetic, deg>,M,<speed, knots>,N,<speed, km/h>,K*hh`.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Literal

from pydantic import Field

from agent.angles import wrap_angle
from agent.config import NonNegativeFloat, StrictModel
from agent.contract import Odometry, nanoseconds

KNOT = 1852.0 / 3600.0  # m/s


class OdometrySettings(StrictModel):
    yaw_input: Literal["yaw", "yaw_rate"] = Field(
        "yaw", description="the IMU gives yaw (rad) or yaw rate (rad/s)")
    yaw_sign: Literal[1, -1] = Field(1, description="+1: sensor yaw counter-clockwise; -1: clockwise")
    yaw_offset: float = Field(0.0, allow_inf_nan=False, description="added after the sign (rad)")
    initial_heading: float = Field(0.0, allow_inf_nan=False,
                                   description="heading at the first sample, with a yaw rate input (rad)")
    position_variance_per_m: NonNegativeFloat = Field(1e-4, description="per axis, m^2 per metre travelled")
    heading_variance: NonNegativeFloat = Field(1e-4, description="of one yaw reading, or of initial_heading")
    yaw_rate_variance_per_s: NonNegativeFloat = Field(1e-6, description="rad^2/s, only with yaw_rate input")


@dataclass(frozen=True)
class OdometryState:
    stamp: float                                # s
    x: float                                    # m, own odometry frame
    y: float                                    # m
    heading: float                              # rad, common reference, CCW from x
    distance: float                             # m travelled (path length) since the first sample
    covariance: tuple[float, ...]               # 3x3 row-major (x, y, heading)

    def message(self, seq: int, sender: str) -> Odometry:
        """This state as the contract's Odometry payload."""
        return Odometry(stamp_ns=nanoseconds(self.stamp), seq=seq, sender=sender,
                        position=(self.x, self.y), heading=self.heading, covariance=self.covariance)


class DeadReckoning:
    """`update(stamp_s, speed, yaw)` -> the new OdometryState, or the unchanged one if the sample is refused.

    Refused samples are counted in `rejected`: `non_finite` (NaN or infinity anywhere), `out_of_order` (a
    stamp not after the last accepted one). Before the first accepted sample `update` returns None.
    """

    def __init__(self, settings: OdometrySettings | None = None):
        self.settings = settings or OdometrySettings()
        self.rejected: Counter[str] = Counter()
        self.state: OdometryState | None = None
        self._speed = self._rate = self._start = 0.0  # previous speed and yaw rate; first stamp

    def update(self, stamp_s: float, speed: float, yaw: float) -> OdometryState | None:
        if not all(math.isfinite(v) for v in (stamp_s, speed, yaw)):
            self.rejected["non_finite"] += 1
            return self.state
        s = self.settings
        last = self.state
        if last is None:
            heading = s.initial_heading if s.yaw_input == "yaw_rate" else s.yaw_sign * yaw + s.yaw_offset
            self._start, self._speed, self._rate = stamp_s, speed, yaw
            self.state = self._state(stamp_s, 0.0, 0.0, heading, 0.0)
            return self.state
        dt = stamp_s - last.stamp
        if dt <= 0:
            self.rejected["out_of_order"] += 1
            return last
        if s.yaw_input == "yaw_rate":
            turn = s.yaw_sign * 0.5 * (self._rate + yaw) * dt  # trapezoid, like the speed
        else:
            turn = wrap_angle(s.yaw_sign * yaw + s.yaw_offset - last.heading)  # shortest way round
        ds = 0.5 * (self._speed + speed) * dt
        half = 0.5 * turn
        chord = ds * (math.sin(half) / half if abs(half) > 1e-9 else 1.0 - half * half / 6.0)
        direction = last.heading + half
        self._speed, self._rate = speed, yaw
        self.state = self._state(stamp_s, last.x + chord * math.cos(direction),
                                 last.y + chord * math.sin(direction), last.heading + turn,
                                 last.distance + abs(ds))
        return self.state

    def _state(self, stamp: float, x: float, y: float, heading: float, distance: float) -> OdometryState:
        s = self.settings
        p = s.position_variance_per_m * distance
        h = s.heading_variance
        if s.yaw_input == "yaw_rate":
            h += s.yaw_rate_variance_per_s * (stamp - self._start)
        covariance = (p, 0.0, 0.0, 0.0, p, 0.0, 0.0, 0.0, h)
        return OdometryState(stamp, x, y, wrap_angle(heading), distance, covariance)


def parse_vhw(body: bytes) -> tuple[float, float] | None:
    """(speed through water in m/s, true heading in rad clockwise from north) from a VHW body, or None.

    `body` is what serial_port.LineReader returns (no `$`, no `*hh`). Knots are preferred; km/h is used
    when the knots field is empty.
    """
    fields = body.decode("ascii", "replace").split(",")
    if len(fields) != 9 or not fields[0].endswith("VHW") or fields[2] != "T":
        return None
    try:
        heading = math.radians(float(fields[1]))
        if fields[5] and fields[6] == "N":
            speed = float(fields[5]) * KNOT
        elif fields[7] and fields[8] == "K":
            speed = float(fields[7]) / 3.6
        else:
            return None
    except ValueError:
        return None
    return speed, heading
