"""Thrusters under a boat preset's inner loop: Cmd (u*, r*) -> $THR, closed on the speed log and the yaw.

`LoopThrusters` has `ThrusterAdapter`'s interface (`command`, `stop`, `output`, `rejected`, `events`) and
runs, once per `output(now)` (the node's timer, at `loop_hz`), the very code the sim bridge runs:
`boat.inner_loop.step` with the command's age by the watchdog's clock, then `boat.thrusters.allocate`.
The measurements (`measure(now, speed, yaw)`, each speed-log sample): u = the speed through the water;
r = yaw_sign * the rate (a yaw-rate input), or the heading differenced between samples, wrap(yaw_sign
(psi_k - psi_k-1)) / dt (a yaw input; the first sample after a gap gives no rate), each then low-passed,
r_f += a (r - r_f), a = dt / (dt + rate_filter) (rate_filter 0: none). The speed is not filtered.

Zero thrust (and the loop reset, as a stale command resets it) when the command is older than the
preset's `timeout` or gone (`stop`), or when the last speed or rate sample is older than
`measurement_timeout`. Each start of a stop is counted in `events` (`watchdog_stop`, `measurement_stop`)
and said in one line through `report`; a stop lasts silently until it ends.

$THR value of each thruster (left = port, right = starboard): its demand T over its own limit in that
direction, T / F for T >= 0 and T / R for T < 0 (asymmetric reverse: -1 is full astern, R newtons), so a
motor controller maps +1 to F and -1 to R. Every value is finite and in [-1, 1] for any input.

More: docs/contract.md, "The driver bridge in detail", `driver_bridge/thrust_loop.py`; docs/sea.md.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable

import numpy as np
from pydantic import Field, model_validator

from agent.angles import wrap_angle
from agent.config import ConfigError, NonNegativeFloat, PositiveFloat, StrictModel
from boat import inner_loop, thrusters
from boat.presets import BoatPreset, preset
from driver_bridge.odometry import OdometrySettings
from driver_bridge.thrusters import Thrust


class LoopSettings(StrictModel):
    preset: str = Field(description="boat preset whose thrusters and inner loop run here: otter, heron, wamv")
    overrides: dict = Field(
        default_factory=dict,
        description="changes deep-merged onto the preset, e.g. {thrusters: {max_forward: 90}}")
    loop_hz: PositiveFloat = Field(
        50.0, le=1000.0, description="rate of the loop and its $THR lines (the sim's dynamics.inner_loop_hz)")
    measurement_timeout: PositiveFloat = Field(
        0.5, description="zero thrust when the last speed or yaw sample is older than this (s)")
    rate_filter: NonNegativeFloat = Field(
        0.05, le=10.0, description="time constant of the low-pass on the measured yaw rate (s); 0: none")

    @model_validator(mode="after")
    def _known(self) -> LoopSettings:
        try:
            self.boat()
        except ConfigError as error:   # a bad name or override, said with the driver's config
            raise ValueError(str(error)) from None
        return self

    def boat(self) -> BoatPreset:
        return preset(self.preset, self.overrides)


class Measurements:
    """The loop's (u, r) from speed-log samples; refusals counted in `rejected` (non_finite,
    speed_out_of_range, yaw_out_of_range, out_of_order), by the odometry's own bounds."""

    def __init__(self, odometry: OdometrySettings, settings: LoopSettings) -> None:
        self.odometry, self.settings = odometry, settings
        self.rejected: Counter[str] = Counter()
        self.u = self.r = 0.0
        self.speed_at = self.rate_at = -math.inf   # when the last speed and rate were taken (s)
        self._heading: float | None = None          # yaw input: the last heading, to difference
        self._filtered = False                      # r holds a value to filter from

    def update(self, now: float, speed: float, yaw: float) -> str:
        """Take a sample at `now` (the watchdog's clock); '' or why it was refused."""
        o = self.odometry
        reason = ""
        if not (math.isfinite(now) and math.isfinite(speed) and math.isfinite(yaw)):
            reason = "non_finite"
        elif abs(speed) > o.max_speed:
            reason = "speed_out_of_range"
        elif abs(yaw) > (o.max_yaw_rate if o.yaw_input == "yaw_rate" else 2 * math.pi):
            reason = "yaw_out_of_range"
        elif now <= self.speed_at:
            reason = "out_of_order"
        if reason:
            self.rejected[reason] += 1
            return reason
        gap = now - self.speed_at
        fresh = gap <= self.settings.measurement_timeout   # else a restart: nothing to difference or filter
        self.u, self.speed_at = speed, now
        if o.yaw_input == "yaw_rate":
            rate = o.yaw_sign * yaw
        else:
            previous, self._heading = self._heading, o.yaw_sign * yaw
            if previous is None or not fresh:
                self._filtered = False
                return ""
            rate = wrap_angle(self._heading - previous) / gap
        tau = self.settings.rate_filter
        if fresh and self._filtered and tau > 0:
            rate = self.r + gap / (gap + tau) * (rate - self.r)
        self.r, self.rate_at, self._filtered = rate, now, True
        return ""

    def fresh(self, now: float) -> bool:
        limit = self.settings.measurement_timeout
        return now - self.speed_at <= limit and now - self.rate_at <= limit


class LoopThrusters:
    """`command(surge, yaw_rate, now)` stores a command, `measure(now, speed, yaw)` a speed-log sample, and
    `output(now)` runs one loop step of 1 / loop_hz and gives the normalised thrust pair. `now`: the
    watchdog's clock (s). Counted in `rejected`: `non_finite` and `out_of_order` commands (as the mix's),
    `measurement_<why>` (Measurements). `demand`: the last (T_port, T_starboard) in newtons."""

    def __init__(self, settings: LoopSettings, odometry: OdometrySettings,
                 report: Callable[[str], None] = lambda line: None) -> None:
        self.settings = settings
        self.boat = settings.boat()
        self.measurements = Measurements(odometry, settings)
        self.report = report
        self.rejected: Counter[str] = Counter()
        self.events: Counter[str] = Counter()
        self.state = inner_loop.LoopState.zero(1)
        self.demand = (0.0, 0.0)
        self._command: tuple[float, float] | None = None
        self._stamp: float | None = None
        self._stopped = "command"   # why the thrust is zero ("": it is not): no command yet

    def command(self, surge: float, yaw_rate: float, now: float) -> None:
        if not math.isfinite(now):
            self.rejected["non_finite"] += 1
            self._command = None    # a stop, as the mix: without a usable time it stays one
            return
        if self._stamp is not None and now < self._stamp:
            self.rejected["out_of_order"] += 1
            return
        if not (math.isfinite(surge) and math.isfinite(yaw_rate)):
            self.rejected["non_finite"] += 1
            surge = yaw_rate = 0.0  # taken as a stop: the loop brakes the boat
        self._command, self._stamp = (surge, yaw_rate), now

    def measure(self, now: float, speed: float, yaw: float) -> None:
        reason = self.measurements.update(now, speed, yaw)
        if reason:
            self.rejected[f"measurement_{reason}"] += 1

    def stop(self, reason: str) -> None:
        """Zero thrust from now until the next command (said once; the watchdog then says nothing more)."""
        self.events[reason] += 1
        self._command = None
        if self._stopped != "command":
            self.report(f"thrusters stopped: {reason}")
        self._stopped = "command"

    def output(self, now: float) -> Thrust:
        boat, m = self.boat, self.measurements
        age = now - self._stamp if self._command is not None and math.isfinite(now) else math.inf
        stopped = ("command" if not age <= boat.inner_loop.timeout
                   else "" if m.fresh(now) else "measurements")
        self._said(stopped, now)
        surge, rate = self._command or (0.0, 0.0)
        self.state, force, moment = inner_loop.step(
            boat.inner_loop, boat.thrusters, self.state, np.array([surge]), np.array([rate]),
            np.array([age if not stopped else math.inf]), np.array([m.u]), np.array([m.r]),
            1.0 / self.settings.loop_hz)
        port, starboard, _ = thrusters.allocate(boat.thrusters, force, moment)
        self.demand = (float(port[0]), float(starboard[0]))
        return Thrust(*(self._normalised(t) for t in self.demand))

    def _normalised(self, thrust: float) -> float:
        t = self.boat.thrusters
        value = thrust / t.max_forward if thrust >= 0 else thrust / t.max_reverse
        return min(max(value, -1.0), 1.0) if math.isfinite(value) else 0.0   # allocate's range; kept whatever

    def _said(self, stopped: str, now: float) -> None:
        """Count and say the start of a stop, once."""
        if stopped and stopped != self._stopped:
            m = self.measurements
            if stopped == "command":
                self.events["watchdog_stop"] += 1
                timeout = self.boat.inner_loop.timeout
                self.report(f"thrusters stopped: no fresh command (timeout {timeout:g} s); "
                            "counted as watchdog_stop")
            else:
                self.events["measurement_stop"] += 1
                since = now - min(m.speed_at, m.rate_at)
                self.report(f"thrusters stopped: no speed-log or yaw sample "
                            f"{'yet' if since == math.inf else f'for {since:.2f} s'} (measurement_timeout "
                            f"{self.settings.measurement_timeout:g} s); counted as measurement_stop")
        self._stopped = stopped
