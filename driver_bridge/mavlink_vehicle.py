"""ArduPilot Rover / boat over MAVLink: the agent's (u, r) as GUIDED set points or ACRO sticks, its state as odometry.

`MavlinkVehicle` holds no socket: `receive(msg, now_ns, mono)` takes one parsed message, `tick(now_ns, mono)`
gives the messages to send now, built with the pymavlink encoder `mav` it is given (mavlink_link.py opens it).
- Out: HEARTBEAT at 1 Hz (an onboard controller); on each command (the agent's rate; the last repeated at
  `min_rate_hz` at least), by `control`: 'guided', SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_BODY_NED with
  VELOCITY_YAW_RATE: vx = u, vy = 0, yaw_rate = -r (NED yaw is clockwise); 'acro' (no position fix needed),
  MANUAL_CONTROL sticks (`sticks`). MAV_CMD_DO_SET_MODE to GUIDED or ACRO (and `arm`) while commands flow;
  MAV_CMD_SET_MESSAGE_INTERVAL for ATTITUDE and LOCAL_POSITION_NED, or ODOMETRY, at `stream_hz` (refused:
  REQUEST_DATA_STREAM); TIMESYNC.
- In: HEARTBEAT (mode, armed: `state()`, published for the agent's status), COMMAND_ACK (a refusal said in
  one line; a mode still not entered MODE_WAIT s after asking too), ATTITUDE, LOCAL_POSITION_NED or
  ODOMETRY (mavlink_odometry.py), TIMESYNC (the autopilot's boot clock against ours).
Odometry: x east, y north from the first position, heading = pi/2 - yaw (counter-clockwise from east),
stamped at the autopilot's boot time + the offset measured by TIMESYNC (the round trip's midpoint, the
shortest of the last OFFSET_SAMPLES); covariance diag(q d, q d, h): d the path length.
Stops: a command older than `command_timeout`: zero set points; the agent gone: zero set points, then HOLD.
Link: no heartbeat for `link_timeout`: no odometry, said once, and its return. Refused and counted in
`rejected`, never raised: bad_data, wrong_system, heartbeat_flood, non_finite, out_of_range, stamp_ahead,
mode_refused, mode_not_entered, commands_while_disarmed, ... A reboot (the clock going back) or an ODOMETRY
reset goes on from the last position. More: docs/boats.md, "ArduPilot over MAVLink".
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Callable
from typing import Literal

from pydantic import Field

from agent.angles import wrap_angle
from agent.config import NonNegativeFloat, PositiveFloat, StrictModel
from agent.contract import MAX_POSITION, MAX_SPEED, MAX_STAMP_NS, MAX_VARIANCE, Odometry, VehicleState
from driver_bridge.mavlink_odometry import odometry_pose

# MAVLink common (mavlink.io, common.xml). POSITION_TARGET_TYPEMASK: a set bit means "ignore this field".
X_IGNORE, Y_IGNORE, Z_IGNORE = 1, 2, 4
VZ_IGNORE = 32
AX_IGNORE, AY_IGNORE, AZ_IGNORE = 64, 128, 256
YAW_IGNORE = 1024
# Velocity and yaw rate used, everything else ignored (ArduPilot's "Use Vel+Yaw Rate").
VELOCITY_YAW_RATE = X_IGNORE | Y_IGNORE | Z_IGNORE | VZ_IGNORE | AX_IGNORE | AY_IGNORE | AZ_IGNORE | YAW_IGNORE
MAV_FRAME_BODY_NED = 8
MAV_CMD_DO_SET_MODE, MAV_CMD_COMPONENT_ARM_DISARM, MAV_CMD_SET_MESSAGE_INTERVAL = 176, 400, 511
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MAV_MODE_FLAG_SAFETY_ARMED = 1, 128
MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, MAV_STATE_ACTIVE = 18, 8, 4
MAV_RESULT = {0: "ACCEPTED", 1: "TEMPORARILY_REJECTED", 2: "DENIED", 3: "UNSUPPORTED", 4: "FAILED",
              5: "IN_PROGRESS", 6: "CANCELLED"}
ATTITUDE_ID, LOCAL_POSITION_NED_ID, ODOMETRY_ID = 30, 32, 331
STREAM_POSITION, STREAM_EXTRA1 = 6, 10   # MAV_DATA_STREAM groups: LOCAL_POSITION_NED, ATTITUDE
# ArduPilot Rover's custom modes (Rover/mode.h).
ROVER_MODES = {"MANUAL": 0, "ACRO": 1, "HOLD": 4, "LOITER": 5, "AUTO": 10, "RTL": 11, "GUIDED": 15}
MODE_NAMES = {number: name for name, number in ROVER_MODES.items()}

OFFSET_SAMPLES = 10          # TIMESYNC round trips kept; the shortest gives the offset
HEARTBEAT_MIN_GAP = 0.2      # s: ArduPilot beats at 1 Hz; heartbeats closer together are a flood
REQUEST_GAP = 1.0            # s: between two requests of a mode, arming or stream rates
REBOOT_MS = 1000             # time_boot_ms this far behind the last odometry's: the autopilot rebooted
AHEAD_NS, STALE_NS = 200_000_000, 2_000_000_000   # an odometry stamp further ahead of our clock, or behind
HOLD_AFTER = 0.2             # s of zero set points before HOLD, when the agent is gone
MODE_WAIT = 3.0              # s: a mode asked for and not in the heartbeats this long after: not entered
STATE_PERIOD = 1.0           # s: the vehicle's state is published on each change and at least this often
EPOCH_US = 10**15            # an ODOMETRY time_usec this large is Unix time, not time since boot (31 years)


class MavlinkSettings(StrictModel):
    url: str = Field(description="pymavlink connection: udpin:0.0.0.0:14550, udpout:HOST:PORT, tcp:HOST:PORT, "
                     "or a serial device")
    baud: int = Field(115_200, gt=0, description="serial baud rate (a serial device only)")
    system: int = Field(1, ge=1, le=255, description="the autopilot's MAVLink system id; others are refused")
    component: int = Field(1, ge=0, le=255, description="the autopilot's component id")
    own_system: int = Field(1, ge=1, le=255, description="our system id (a companion computer shares the "
                            "vehicle's)")
    own_component: int = Field(191, ge=1, le=255, description="our component id (191: onboard computer)")
    min_rate_hz: PositiveFloat = Field(
        2.0, le=50.0, description="set points per second at least: each command goes at once, the last repeated")
    stream_hz: PositiveFloat = Field(10.0, le=50.0, description="ATTITUDE and LOCAL_POSITION_NED per second")
    command_timeout: PositiveFloat = Field(0.5, description="zero set points when the agent's command is older (s)")
    link_timeout: PositiveFloat = Field(3.0, description="link lost after this long without a heartbeat (s)")
    arm: bool = Field(False, description="arm the vehicle when commands flow; false: a disarmed vehicle is said")
    position_variance_per_m: NonNegativeFloat = Field(
        1e-4, description="odometry error the agent assumes: per axis, m^2 per metre (GNSS EKF ~2e-3: docs/boats.md)")
    heading_variance: NonNegativeFloat = Field(1e-4, description="odometry error the agent assumes: yaw (rad^2)")
    control: Literal["guided", "acro"] = Field(
        "guided", description="'guided': GUIDED velocity set points (needs a position fix); 'acro': ACRO sticks")
    full_throttle_speed: PositiveFloat = Field(
        2.0, le=MAX_SPEED, description="acro: the surge at full throttle (m/s); throttle = u / this, open loop")
    acro_turn_rate: PositiveFloat = Field(
        180.0, le=3600.0, description="acro: the autopilot's ACRO_TURN_RATE (deg/s); steering = -r / this")
    odometry: Literal["local_position", "odometry", "none"] = Field(
        "local_position", description="ATTITUDE + LOCAL_POSITION_NED, ODOMETRY (#331), or none (a speed log's)")


class MavlinkVehicle:
    """See the module docstring. `report(line)` says what the operator must know, once per change."""

    def __init__(self, settings: MavlinkSettings, mav, sender: str,
                 report: Callable[[str], None] = lambda line: None) -> None:
        self.settings, self.mav, self.sender, self.report = settings, mav, sender, report
        self.rejected: Counter[str] = Counter()
        self.events: Counter[str] = Counter()
        self.sent: Counter[str] = Counter()
        self.mode: int | None = None
        self.armed = False
        self.heartbeat_at = -math.inf          # monotonic s of the last heartbeat taken
        self.linked = False
        self.offset_ns: int | None = None      # vessel clock - autopilot boot clock
        self._round_trips: deque[tuple[int, int]] = deque(maxlen=OFFSET_SAMPLES)   # (rtt, offset) ns
        self._attitude: tuple[float, float] | None = None   # yaw, yaw rate (NED, rad, rad/s)
        self._origin: tuple[float, float] | None = None
        self._last: tuple[float, float, int] | None = None   # east, north (m) and stamp (ns) of the last odometry
        self._distance = 0.0
        self._boot_ms: int | None = None       # time_boot_ms of the last odometry
        self.odometry_seq = 0
        self._command: tuple[float, float, float] | None = None   # u, r, monotonic s
        self._agent_gone_at: float | None = None
        self._next = {"heartbeat": -math.inf, "setpoint": -math.inf, "timesync": -math.inf, "mode": -math.inf,
                      "arm": -math.inf, "streams": -math.inf}
        self._said_disarmed = False
        self._fresh = False        # a command (or the agent's leaving) not yet sent
        self._timed_out = False
        self._legacy_streams = False   # SET_MESSAGE_INTERVAL refused: REQUEST_DATA_STREAM instead
        self._asked_mode: int | None = None
        self._replies: list = []   # answers owed to the autopilot (its TIMESYNC requests)
        self.wanted = ROVER_MODES["GUIDED" if settings.control == "guided" else "ACRO"]
        self._mode_wait: tuple[int, float] | None = None   # a mode asked for and not seen yet, since when
        self._said: set[str] = set()   # what was said of this episode (a refusal, the mode not entered)
        self._resets: int | None = None   # ODOMETRY's reset_counter last seen
        self.state_seq = 0
        self._state: tuple | None = None   # the state last published, and when next at the latest
        self._state_due = -math.inf
        if settings.control == "acro" and settings.own_system != 255:
            report(f"mavlink.control acro: ArduPilot takes MANUAL_CONTROL only from its GCS's system id "
                   f"(MAV_GCS_SYSID, 255 unless set): own_system is {settings.own_system}")

    # ----- the agent's side -----
    def command(self, surge: float, yaw_rate: float, mono: float) -> None:
        if not (abs(surge) <= MAX_SPEED and abs(yaw_rate) <= MAX_SPEED):   # NaN fails too
            self.rejected["command_out_of_range"] += 1
            surge = yaw_rate = 0.0   # taken as a stop (and a float32 on the wire never overflows)
        self._command = (surge, yaw_rate, mono)
        self._agent_gone_at = None
        self._fresh, self._timed_out = True, False

    def agent_left(self, mono: float) -> None:
        """The agent's session ended: zero set points now, HOLD after HOLD_AFTER."""
        self._command = None
        if self._agent_gone_at is None:
            self._agent_gone_at = mono
            self._fresh = True
            self.events["agent_left"] += 1

    # ----- what to send -----
    def tick(self, now_ns: int, mono: float) -> list:
        """The messages due now (call it often; each kind keeps its own rate)."""
        s, mav, out = self.settings, self.mav, self._replies[:8]
        self._replies.clear()
        if self._due("heartbeat", mono, 1.0):
            out.append(mav.heartbeat_encode(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0,
                                            MAV_STATE_ACTIVE))
        self._link(mono)
        if self._due("timesync", mono, 1.0):
            out.append(mav.timesync_encode(0, now_ns))
        if self.linked and self._due("streams", mono, 10.0):
            if self._legacy_streams:   # before ArduPilot 4.0: the stream groups holding the two messages
                rate = max(1, round(s.stream_hz))
                out += [mav.request_data_stream_encode(s.system, s.component, stream, rate, 1)
                        for stream in (STREAM_POSITION, STREAM_EXTRA1)]
            else:
                interval = 1e6 / s.stream_hz
                streams = (ODOMETRY_ID,) if s.odometry == "odometry" else (ATTITUDE_ID, LOCAL_POSITION_NED_ID)
                out += [self._long(MAV_CMD_SET_MESSAGE_INTERVAL, message, interval) for message in streams]
        gone = self._agent_gone_at
        if (gone is not None and mono - gone >= HOLD_AFTER and self.linked and self.mode != ROVER_MODES["HOLD"]
                and self._due("mode", mono, REQUEST_GAP)):
            out.append(self._long(MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, ROVER_MODES["HOLD"]))
        if self._fresh:   # a new command (or the agent gone) goes at once; the period restarts from it
            self._fresh = False
            self._next["setpoint"] = mono + 1.0 / s.min_rate_hz
        elif not self._due("setpoint", mono, 1.0 / s.min_rate_hz):
            return self._count(out)
        command = self._command
        if command is not None and mono - command[2] > s.command_timeout:
            command = None
            if not self._timed_out:
                self.events["command_timeout"] += 1
            self._timed_out = True
        if command is not None:
            u, r, _ = command
            if self.linked and self.mode != self.wanted and self._due("mode", mono, REQUEST_GAP):
                out.append(self._long(MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, self.wanted))
                if self._mode_wait is None or self._mode_wait[0] != self.wanted:
                    self._mode_wait = (self.wanted, mono)
            if self.linked and not self.armed:
                self.rejected["commands_while_disarmed"] += 1
                if s.arm and self._due("arm", mono, REQUEST_GAP):
                    out.append(self._long(MAV_CMD_COMPONENT_ARM_DISARM, 1))
                elif not s.arm and not self._said_disarmed:
                    self._said_disarmed = True
                    self.report("the vehicle is disarmed: the agent's commands move nothing until it is armed "
                                "(from the ground station, or mavlink.arm: true)")
        else:
            u = r = 0.0
        self._not_entered(mono)
        out.append(self.drive(u, r, mono))
        return self._count(out)

    def _not_entered(self, mono: float) -> None:
        """A mode asked for MODE_WAIT s ago and still not in the heartbeats (its ACK lost, or accepted and then
        left): one line, counted, unless its refusal was said."""
        wait = self._mode_wait
        if wait is None or not self.linked or mono - wait[1] < MODE_WAIT or self.mode == wait[0]:
            return
        self._mode_wait = (wait[0], mono)   # counted once per MODE_WAIT while it lasts
        self.rejected["mode_not_entered"] += 1
        if not self._said & {"mode", "mode_not_entered"}:
            self._said.add("mode_not_entered")
            now = MODE_NAMES.get(self.mode, f"mode {self.mode}") if self.mode is not None else "no mode"
            self.report(f"the autopilot did not enter {MODE_NAMES[wait[0]]} ({now} {MODE_WAIT:g} s after asking)")

    def drive(self, surge: float, yaw_rate: float, mono: float):
        """(u, r) as `control` sends it: a GUIDED set point, or ACRO sticks."""
        if self.settings.control == "acro":
            return self.sticks(surge, yaw_rate)
        return self.setpoint(surge, yaw_rate, mono)

    def sticks(self, surge: float, yaw_rate: float):
        """(u, r) as MANUAL_CONTROL for ACRO (Rover reads y: steering, z: throttle, each -1000..1000 to its RC
        range): throttle u / full_throttle_speed, steering -r / ACRO_TURN_RATE (positive turns clockwise),
        each clipped to full deflection."""
        s = self.settings
        throttle = max(-1.0, min(1.0, surge / s.full_throttle_speed))
        steering = max(-1.0, min(1.0, -yaw_rate / math.radians(s.acro_turn_rate)))
        return self.mav.manual_control_encode(s.system, 0, round(1000 * steering), round(1000 * throttle), 0, 0)

    def stop(self, mono: float) -> list:
        """What to send as the driver stops: a zero set point, then HOLD."""
        self.events["stopped"] += 1
        return self._count([self.drive(0.0, 0.0, mono), self._long(
            MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, ROVER_MODES["HOLD"])])

    def setpoint(self, surge: float, yaw_rate: float, mono: float):
        """(u, r) as ArduPilot's GUIDED velocity + yaw-rate set point, body frame; r counter-clockwise."""
        s = self.settings
        return self.mav.set_position_target_local_ned_encode(
            int(mono * 1000) & 0xFFFFFFFF, s.system, s.component, MAV_FRAME_BODY_NED, VELOCITY_YAW_RATE,
            0.0, 0.0, 0.0, surge, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -yaw_rate)

    def _long(self, command: int, *params: float):
        if command == MAV_CMD_DO_SET_MODE:
            self._asked_mode = int(params[1])
        p = (list(params) + [0.0] * 7)[:7]
        return self.mav.command_long_encode(self.settings.system, self.settings.component, command, 0, *p)

    def _due(self, what: str, mono: float, period: float) -> bool:
        if mono < self._next[what]:
            return False
        following = self._next[what] + period   # a steady rate; after a gap, from now
        self._next[what] = following if following > mono else mono + period
        return True

    def _count(self, out: list) -> list:
        for message in out:
            self.sent[message.get_type()] += 1
        return out

    def _link(self, mono: float) -> None:
        linked = mono - self.heartbeat_at <= self.settings.link_timeout
        if linked != self.linked:
            self.linked = linked
            if linked:
                self.report(f"autopilot link up (system {self.settings.system})")
                self._next["streams"] = -math.inf   # ask for the streams again: it may have rebooted
            else:
                self.events["link_lost"] += 1
                self.report(f"autopilot link lost: no heartbeat for {self.settings.link_timeout:g} s; "
                            "odometry stopped")

    # ----- what comes in -----
    def receive(self, msg, now_ns: int, mono: float) -> Odometry | None:
        """Take one parsed message; the odometry it completes, if any. Never raises on a message's content."""
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.rejected["bad_data"] += 1
            return None
        if msg.get_srcSystem() != self.settings.system:
            self.rejected["wrong_system"] += 1
            return None
        handler = getattr(self, f"_on_{kind.lower()}", None)
        if handler is None:
            return None
        if msg.get_srcComponent() != self.settings.component and kind != "TIMESYNC":
            self.rejected["wrong_component"] += 1
            return None
        return handler(msg, now_ns, mono)

    def _on_heartbeat(self, msg, now_ns: int, mono: float) -> None:
        if mono - self.heartbeat_at < HEARTBEAT_MIN_GAP:
            self.rejected["heartbeat_flood"] += 1
            return
        self.heartbeat_at = mono
        self._link(mono)
        armed = bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
        if msg.custom_mode != self.mode or armed != self.armed:
            name = MODE_NAMES.get(msg.custom_mode, f"mode {msg.custom_mode}")
            self.report(f"autopilot: {name}, {'armed' if armed else 'disarmed'}")
            if armed:
                self._said_disarmed = False
                self._said.discard("arm")
        self.mode, self.armed = msg.custom_mode, armed
        if self._mode_wait is not None and self._mode_wait[0] == self.mode:
            self._mode_wait = None   # entered: a refusal or a failure to enter is said again next time
            self._said -= {"mode", "mode_not_entered"}

    def _on_command_ack(self, msg, now_ns: int, mono: float) -> None:
        if msg.result == 0:
            return
        what = {MAV_CMD_DO_SET_MODE: "mode_refused", MAV_CMD_COMPONENT_ARM_DISARM: "arm_refused",
                MAV_CMD_SET_MESSAGE_INTERVAL: "stream_refused"}.get(msg.command)
        if what is None:
            return
        kind = what.split("_")[0]
        if kind not in self._said:
            self._said.add(kind)
            result = MAV_RESULT.get(msg.result, str(msg.result))
            guided = what == "mode_refused" and self._asked_mode == ROVER_MODES["GUIDED"]
            self.report(f"the autopilot refused {kind} (command {msg.command}): {result}"
                        + (" (GUIDED needs a position estimate; without GNSS: mavlink.control acro, docs/boats.md)"
                           if guided else "")
                        + ("; asking with REQUEST_DATA_STREAM" if what == "stream_refused" else ""))
        self.rejected[what] += 1
        if what == "stream_refused" and not self._legacy_streams:
            self._legacy_streams = True            # ask again at once, the old way
            self._next["streams"] = -math.inf

    def _on_timesync(self, msg, now_ns: int, mono: float) -> None:
        if msg.tc1 == 0:   # the autopilot asks: our time, its stamp echoed
            self._replies.append(self.mav.timesync_encode(now_ns, msg.ts1))
            return
        rtt = now_ns - msg.ts1
        if not 0 <= rtt <= 10**9 or msg.tc1 < 0:   # no reply to a request of the last second (or forged)
            self.rejected["timesync_unmatched"] += 1
            return
        self._round_trips.append((rtt, (msg.ts1 + now_ns) // 2 - msg.tc1))
        self.offset_ns = min(self._round_trips)[1]

    def _on_attitude(self, msg, now_ns: int, mono: float) -> None:
        if not (math.isfinite(msg.yaw) and math.isfinite(msg.yawspeed)) or abs(msg.yaw) > 2 * math.pi:
            self.rejected["attitude_out_of_range"] += 1
            return
        self._attitude = (msg.yaw, msg.yawspeed)

    def _on_local_position_ned(self, msg, now_ns: int, mono: float) -> Odometry | None:
        if self.settings.odometry != "local_position":
            return None
        yaw = None if self._attitude is None else self._attitude[0]
        return self._odometry(msg.time_boot_ms, None, msg.x, msg.y, yaw, now_ns)

    def _on_odometry(self, msg, now_ns: int, mono: float) -> Odometry | None:
        """ODOMETRY (#331), its frames as mavlink_odometry.py reads them; a new reset_counter (the estimate
        jumped) goes on from the last position, as a reboot does."""
        if self.settings.odometry != "odometry":
            return None
        pose = odometry_pose(msg.frame_id, msg.child_frame_id, msg.x, msg.y, list(msg.q), msg.yawspeed)
        if isinstance(pose, str):
            self.rejected[pose] += 1
            return None
        north, east, yaw, rate = pose
        if self._resets is not None and msg.reset_counter != self._resets:
            self.events["estimate_reset"] += 1
            self._origin = None
        self._resets = msg.reset_counter
        self._attitude = (yaw, -rate)
        if msg.time_usec >= EPOCH_US:   # Unix time: the vessel's clock already
            return self._odometry(None, msg.time_usec * 1000, north, east, yaw, now_ns)
        return self._odometry(msg.time_usec // 1000, None, north, east, yaw, now_ns)

    def _odometry(self, boot_ms: int | None, unix_ns: int | None, north: float, east: float, yaw: float | None,
                  now_ns: int) -> Odometry | None:
        """The agent's odometry from the autopilot's position (NED, m) and yaw (NED) at `boot_ms` of its boot
        clock (or `unix_ns`), or None and the reason counted."""
        s = self.settings
        if boot_ms is not None and self._boot_ms is not None and boot_ms < self._boot_ms - REBOOT_MS:
            self._rebooted()   # its clock went back: a new boot, a new offset and EKF origin
        if not self.linked:
            self.rejected["odometry_without_link"] += 1
            return None
        if (unix_ns is None and self.offset_ns is None) or yaw is None:
            self.rejected["odometry_without_attitude" if yaw is None else "odometry_without_clock"] += 1
            return None
        if not (math.isfinite(north) and math.isfinite(east)):
            self.rejected["non_finite"] += 1
            return None
        stamp = unix_ns if unix_ns is not None else boot_ms * 1_000_000 + self.offset_ns
        if not now_ns - STALE_NS <= stamp <= now_ns + AHEAD_NS:   # made after it came, or long before
            self.rejected["stamp_ahead" if stamp > now_ns else "stamp_stale"] += 1
            return None
        if self._origin is None:   # the first position, or the first since a reboot: the path goes on from there
            last_east, last_north = self._last[:2] if self._last is not None else (0.0, 0.0)
            self._origin = (east - last_east, north - last_north)
        east, north = east - self._origin[0], north - self._origin[1]
        if not (abs(east) <= MAX_POSITION and abs(north) <= MAX_POSITION and 0 <= stamp <= MAX_STAMP_NS):
            self.rejected["out_of_range"] += 1
            return None
        if self._last is not None:
            if stamp <= self._last[2]:
                self.rejected["out_of_order"] += 1
                return None
            self._distance += math.hypot(east - self._last[0], north - self._last[1])
        p = min(s.position_variance_per_m * self._distance, MAX_VARIANCE)
        heading = wrap_angle(math.pi / 2 - yaw)
        odometry = Odometry(stamp_ns=stamp, seq=self.odometry_seq, sender=self.sender, position=(east, north),
                            heading=heading, covariance=(p, 0.0, 0.0, 0.0, p, 0.0, 0.0, 0.0, s.heading_variance))
        self._last = (east, north, stamp)
        self._boot_ms = boot_ms
        self.odometry_seq += 1
        return odometry

    def _rebooted(self) -> None:
        self.events["autopilot_rebooted"] += 1
        self.report("the autopilot's clock went back (a reboot?): odometry waits for a new clock offset, "
                    "then goes on from its last position")
        self.offset_ns, self._origin, self._boot_ms = None, None, None
        self._round_trips.clear()
        self._next["streams"] = self._next["timesync"] = -math.inf

    def state(self, now_ns: int, mono: float) -> VehicleState | None:
        """The autopilot's state for the agent's status (`usv/<id>/sensor/vehicle`): on each change and every
        STATE_PERIOD s, else None. Mode '' until its first heartbeat."""
        refused = sum(self.rejected[k] for k in ("mode_refused", "arm_refused", "mode_not_entered"))
        mode = "" if self.mode is None else MODE_NAMES.get(self.mode, f"mode {self.mode}")
        state = (mode, self.armed, self.linked, refused)
        if state == self._state and mono < self._state_due:
            return None
        self._state, self._state_due = state, mono + STATE_PERIOD
        self.state_seq += 1
        return VehicleState(stamp_ns=now_ns, seq=self.state_seq - 1, sender=self.sender, mode=mode[:24],
                            armed=self.armed, linked=self.linked, control=self.settings.control, refused=refused)

    def yaw_rate(self) -> float | None:
        """The IMU's yaw rate, counter-clockwise (rad/s), from the last ATTITUDE."""
        return None if self._attitude is None else -self._attitude[1]
