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
distance = trapezoid of the two speeds times dt, on the arc's chord (boat.sway.arc_step, exact for a steady
turn). With `sway_preset` the hull's sideslip (boat/sway.py) joins the log's surge on the same arc.

`parse_vhw` reads NMEA 0183 VHW, "water speed and heading", through pynmeagps
(https://gpsd.gitlab.io/gpsd/NMEA.html#_vhw_water_speed_and_heading):
`$--VHW,<heading true, deg>,T,<heading magnetic, deg>,M,<speed, knots>,N,<speed, km/h>,K*hh`.

Bounds: a step that would break the contract (position or variance beyond its limits) is refused whole.

More: docs/contract.md, "The driver bridge in detail", `driver_bridge/odometry.py`.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, replace
from typing import Literal

from pydantic import Field

from agent.angles import wrap_angle
from agent.config import NonNegativeFloat, PositiveFloat, StrictModel
from agent.contract import (MAX_ANGLE, MAX_POSITION, MAX_SPEED, MAX_STAMP_NS, MAX_VARIANCE, Odometry,
                            nanoseconds)
from boat import sway
from boat.presets import PRESETS
from driver_bridge.serial_port import read_sentence

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
    max_speed: PositiveFloat = Field(50.0, le=MAX_SPEED, description="fastest believable speed either way "
                                     "(m/s); a sample beyond it is refused")
    max_yaw_rate: PositiveFloat = Field(10.0, le=MAX_ANGLE, description="fastest believable yaw rate "
                                        "(rad/s), with a yaw_rate input; a sample beyond it is refused")
    sway_preset: Literal[tuple(PRESETS)] | None = Field(  # type: ignore[valid-type]
        None, description="boat preset whose sway model adds the hull's sideslip to the log; None: none")


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

    Refused samples are counted in `rejected`: `non_finite` (NaN or infinity anywhere), `stamp_out_of_range`
    (before 0 or beyond an int64 of ns), `speed_out_of_range` (beyond max_speed), `yaw_out_of_range` (beyond
    the contract's MAX_ANGLE, or max_yaw_rate for a rate), `out_of_order` (a stamp not after the last
    accepted one), `position_out_of_bounds` (the step would leave the contract's +-MAX_POSITION),
    `covariance_out_of_bounds` (a variance would pass MAX_VARIANCE). Before the first accepted sample
    `update` returns None.
    """

    def __init__(self, settings: OdometrySettings | None = None):
        self.settings = settings or OdometrySettings()
        self.rejected: Counter[str] = Counter()
        self.state: OdometryState | None = None
        self._from: OdometryState | None = None       # where the next step starts (see the position bound)
        self._speed = self._rate = self._start = 0.0  # previous speed and yaw rate; first stamp
        self._sway_model = None if self.settings.sway_preset is None else sway.SwayModel.of(
            PRESETS[self.settings.sway_preset].hull)
        self._sway = self._turn_rate = 0.0            # the last step's sway estimate (m/s) and turn rate (rad/s)

    def update(self, stamp_s: float, speed: float, yaw: float) -> OdometryState | None:
        s = self.settings
        problem = self._problem(stamp_s, speed, yaw)
        if problem:
            self.rejected[problem] += 1
            return self.state
        last = self._from
        if last is None:
            heading = s.initial_heading if s.yaw_input == "yaw_rate" else s.yaw_sign * yaw + s.yaw_offset
            self._start = stamp_s
            state = self._state(stamp_s, 0.0, 0.0, heading, 0.0)
        else:
            dt = stamp_s - last.stamp
            if dt <= 0:
                self.rejected["out_of_order"] += 1
                return self.state
            if s.yaw_input == "yaw_rate":
                turn = s.yaw_sign * 0.5 * (self._rate + yaw) * dt  # trapezoid, like the speed
            else:
                turn = wrap_angle(s.yaw_sign * yaw + s.yaw_offset - last.heading)  # shortest way round
            ds = 0.5 * (self._speed + speed) * dt
            across = 0.0
            if self._sway_model is not None:
                rate = turn / dt
                v = float(sway.step(self._sway_model, self._sway, ds / dt, rate, rate - self._turn_rate, dt))
                across = 0.5 * (self._sway + v) * dt
                self._sway, self._turn_rate = v, rate
            x, y = sway.arc_step(last.x, last.y, last.heading, turn, ds, across)
            state = self._state(stamp_s, x, y, last.heading + turn, last.distance + math.hypot(ds, across))
        # A step beyond the contract is refused whole (every agent would refuse the state). The next one
        # starts at this sample's time and heading but the last position: otherwise the interval to integrate,
        # and with it the step, would only grow, and the odometry would stay stuck once the vessel heads back.
        problem = ""
        if not (abs(state.x) <= MAX_POSITION and abs(state.y) <= MAX_POSITION):
            problem = "position_out_of_bounds"
        elif not max(state.covariance) <= MAX_VARIANCE:
            problem = "covariance_out_of_bounds"
        self._speed, self._rate = speed, yaw
        if problem:
            self.rejected[problem] += 1
            if last is not None:
                self._from = replace(last, stamp=stamp_s, heading=state.heading)
            return self.state
        self.state = self._from = state
        return state

    def _problem(self, stamp_s: float, speed: float, yaw: float) -> str:
        """Why a sample is refused before it is integrated, or ""."""
        s = self.settings
        if not all(math.isfinite(v) for v in (stamp_s, speed, yaw)):
            return "non_finite"
        if not 0 <= nanoseconds(stamp_s) <= MAX_STAMP_NS:
            return "stamp_out_of_range"
        if abs(speed) > s.max_speed:
            return "speed_out_of_range"
        if abs(yaw) > (s.max_yaw_rate if s.yaw_input == "yaw_rate" else MAX_ANGLE):
            return "yaw_out_of_range"
        return ""

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
    when the knots field is empty. `read_vhw` also says why a body is refused.
    """
    return read_vhw(body)[0]


def read_vhw(body: bytes) -> tuple[tuple[float, float] | None, str]:
    """(sample, "") or (None, why): `not_vhw` (another sentence, or the wrong fields), `bad_number` (a number
    field, used or not, that is no finite decimal), `no_speed` (neither knots nor km/h given),
    `heading_out_of_range` (a true heading outside [0, 360] degrees). The fields are pynmeagps's (VHW's
    table: hdgT, hdgM, spdN, spdK and their units). The speed's size is judged by DeadReckoning."""
    message, why = read_sentence(body, "VHW", 8)
    if message is None:
        return None, why
    if message.hgdTu != "T":   # sic: pynmeagps's name for the true heading's unit
        return None, "not_vhw"
    if message.spdN != "" and message.spdNu == "N":
        speed = message.spdN * KNOT
    elif message.spdK != "" and message.spdKu == "K":
        speed = message.spdK / 3.6
    else:
        return None, "no_speed"
    if message.hdgT == "":
        return None, "bad_number"
    heading = message.hdgT
    if not 0.0 <= heading <= 360.0:
        return None, "heading_out_of_range"
    return (speed, math.radians(heading)), ""
