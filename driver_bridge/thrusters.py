"""Thruster adapter, twin-thruster (differential) hull: Cmd (surge m/s, yaw rate rad/s) -> left/right thrust.

Model (steady state, linear drag; hull axes x forward, y to port, yaw counter-clockwise as in the contract):
the two thrusters sit at y = +b (left, port) and y = -b (right, starboard) and push along x. In a steady
run the thrust balances the drag:
    surge:  T_left + T_right = d_u * u                       (d_u: N per m/s)
    yaw:    b * (T_right - T_left) = d_r * r                 (d_r: N m per rad/s; a push at y=-b turns CCW)
so  T_right = (d_u u + d_r r / b) / 2  and  T_left = (d_u u - d_r r / b) / 2. Outputs are normalised by
max_thrust to [-1, 1] (thrust in N = value * max_thrust); forward and reverse are taken as symmetric.

Saturation keeps yaw authority first. Write the normalised pair as mean m and half-difference h
(left = m - h, right = m + h). h is clipped to [-1, 1] first; then m is clipped to [-(1 - |h|), 1 - |h|].
The difference, which turns the boat, is kept whole whenever it is feasible and speed gives way: on the
formation circle a lost turn drifts the vessel off the circle and towards its neighbours, a lost bit of
speed only delays it.

Watchdog (docs/contract.md, "Watchdog: your duty"): `output(now)` gives zero thrust when the last valid
command is older than `timeout` seconds, or when there has been none. A non-finite command is refused,
counted, and taken as a stop.

`command_line` writes the pair for a motor controller as `$THR,<left>,<right>*hh\r\n` (our format, NMEA
framing, see serial_port), each value signed with three decimals in [-1, 1].

More: docs/contract.md, "The driver bridge in detail", `driver_bridge/thrusters.py`.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

from pydantic import Field

from agent.config import PositiveFloat, StrictModel
from driver_bridge.serial_port import nmea_sentence


# Far beyond any vessel's, and small enough that the mix of any command the contract allows stays a number:
# with them a product can overflow to an infinity (which saturates, the right way) but never to NaN.
MAX_HULL_VALUE = 1e6


class ThrusterSettings(StrictModel):
    max_thrust: PositiveFloat = Field(le=MAX_HULL_VALUE, description="thrust of one thruster at full command "
                                      "(N)")
    half_beam: PositiveFloat = Field(le=MAX_HULL_VALUE, description="distance of each thruster from the "
                                     "centreline (m)")
    surge_drag: PositiveFloat = Field(le=MAX_HULL_VALUE, description="linear surge drag d_u (N per m/s)")
    yaw_drag: PositiveFloat = Field(le=MAX_HULL_VALUE, description="linear yaw drag d_r (N m per rad/s)")
    timeout: PositiveFloat = Field(0.5, description="stop when the last valid command is older (s)")


class CommandWindow(StrictModel):
    """How fresh a command must be, by the driver's wall clock (which the agent on the same boat shares)."""

    max_age: PositiveFloat = Field(0.5, description="refuse a command stamped longer ago than this (s): stale or "
                                   "replayed")
    # Also the longest a spoofed stamp can hold the real agent's commands off.
    max_ahead: PositiveFloat = Field(0.2, description="refuse a command stamped further ahead than this (s)")


class CommandGate:
    """`offer(stamp_ns, now_ns)` -> '' to take the command, else why not: `stale`, `future` or `out_of_order`
    (stamped at or before the command in force). `forget()` drops the command in force's stamp (its
    sender's session ended). Counts in `rejected`."""

    def __init__(self, window: CommandWindow) -> None:
        self.window = window
        self.rejected: Counter[str] = Counter()
        self.newest_ns: int | None = None

    def offer(self, stamp_ns: int, now_ns: int) -> str:
        age = (now_ns - stamp_ns) * 1e-9
        if age > self.window.max_age:
            reason = "stale"
        elif -age > self.window.max_ahead:
            reason = "future"
        elif self.newest_ns is not None and stamp_ns <= self.newest_ns:
            reason = "out_of_order"
        else:
            self.newest_ns = stamp_ns
            return ""
        self.rejected[reason] += 1
        return reason

    def forget(self) -> None:
        self.newest_ns = None


@dataclass(frozen=True)
class Thrust:
    left: float     # normalised, -1..1 (x max_thrust = N)
    right: float


ZERO_THRUST = Thrust(0.0, 0.0)


def _clip(value: float, limit: float) -> float:
    return value if math.isnan(value) else max(-limit, min(limit, value))   # NaN stays NaN: command() stops


class ThrusterAdapter:
    """`command(surge, yaw_rate, now)` stores a command; `output(now)` gives the thrust to apply now.

    Counted in `rejected`: `non_finite` (command taken as a stop), `out_of_order` (a command stamped before
    the last one, ignored). Counted in `events`: `saturated` (a command the thrusters cannot follow
    exactly), `watchdog_stop` (each time the output goes to zero because commands went stale), and whatever
    `stop(reason)` is told.
    """

    def __init__(self, settings: ThrusterSettings):
        self.settings = settings
        self.rejected: Counter[str] = Counter()
        self.events: Counter[str] = Counter()
        self._thrust = ZERO_THRUST
        self._stamp: float | None = None
        self._stale = True

    def mix(self, surge: float, yaw_rate: float) -> Thrust:
        """The normalised thrust pair for a finite command, saturated with yaw first."""
        s = self.settings
        total = s.surge_drag * surge                          # T_left + T_right (N)
        difference = s.yaw_drag * yaw_rate / s.half_beam      # T_right - T_left (N)
        mean = total / (2 * s.max_thrust)
        half = difference / (2 * s.max_thrust)
        clipped_half = _clip(half, 1.0)
        clipped_mean = _clip(mean, 1.0 - abs(clipped_half))
        if (clipped_half, clipped_mean) != (half, mean):
            self.events["saturated"] += 1
        return Thrust(clipped_mean - clipped_half, clipped_mean + clipped_half)

    def command(self, surge: float, yaw_rate: float, now: float) -> Thrust:
        if not math.isfinite(now):
            self.rejected["non_finite"] += 1
            self._thrust = ZERO_THRUST  # a stop, and without a usable time it stays one until a good command
            return ZERO_THRUST
        if self._stamp is not None and now < self._stamp:
            self.rejected["out_of_order"] += 1
            return self._thrust
        self._stamp = now
        thrust = self.mix(surge, yaw_rate) if math.isfinite(surge) and math.isfinite(yaw_rate) else None
        if thrust is None or not (abs(thrust.left) <= 1.0 and abs(thrust.right) <= 1.0):
            # NaN, or a mix gone non-finite (a hull whose numbers overflow): a stop, never an unknown thrust.
            self.rejected["non_finite"] += 1
            thrust = ZERO_THRUST
        self._thrust = thrust
        return thrust

    def stop(self, reason: str) -> None:
        """Zero thrust now, until the next command (the agent is gone: no need to wait for the watchdog)."""
        self.events[reason] += 1
        self._thrust = ZERO_THRUST

    def output(self, now: float) -> Thrust:
        stale = self._stamp is None or not math.isfinite(now) or now - self._stamp > self.settings.timeout
        if stale and not self._stale:
            self.events["watchdog_stop"] += 1
        self._stale = stale
        return ZERO_THRUST if stale else self._thrust


def command_line(thrust: Thrust) -> bytes:
    """`$THR,+0.500,-0.250*hh\\r\\n` for a motor controller."""
    left, right = thrust.left + 0.0, thrust.right + 0.0  # + 0.0 turns -0.0 into 0.0
    return nmea_sentence(f"THR,{left:+.3f},{right:+.3f}")
