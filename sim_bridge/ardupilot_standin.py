"""`usv-ardupilot-standin`: one simulated boat that speaks MAVLink as ArduPilot Rover documents it, for tests.

It serves one MAVLink link (pymavlink URL, e.g. udpin:127.0.0.1:14550: it answers whoever spoke last) and
moves a kinematic hull: heading and position follow the commanded (u, r) exactly (boat.sway.arc_step), or
with --preset a boat preset's hull, thrusters and inner loop (sim_bridge/hull.py) take (u, r) as commands.
- HEARTBEAT at 1 Hz: MAV_TYPE_SURFACE_BOAT, ARDUPILOTMEGA, the Rover mode in custom_mode, the armed flag;
  it boots in MANUAL, disarmed. Arming by MAV_CMD_COMPONENT_ARM_DISARM; every command gets a COMMAND_ACK.
- Modes MANUAL, ACRO, HOLD, GUIDED (MAV_CMD_DO_SET_MODE or SET_MODE; others: UNSUPPORTED). --no-position:
  GUIDED refused (FAILED) as ArduPilot refuses a mode that needs a position, and no LOCAL_POSITION_NED or
  ODOMETRY; ACRO (a skid-steered boat needs no velocity estimate either) and MANUAL still work.
- GUIDED: SET_POSITION_TARGET_LOCAL_NED, velocity and yaw rate used (yaw ignored): body frames (8, 9): u =
  vx; local (1, 7): u = the velocity along the heading; r = -yaw_rate. Other masks: `setpoint_unsupported`.
  No set point for --guid-timeout s (GUID_TIMEOUT): stop. HOLD and disarmed: stopped.
- ACRO and MANUAL: MANUAL_CONTROL from --gcs-system (MAV_GCS_SYSID) aimed at it, y steering and z throttle
  (-1000..1000): r = -steering x --acro-turn-rate, u = throttle x --full-throttle-speed (MANUAL's open-loop
  steering taken as ACRO's rate); the sticks centre after RC_OVERRIDE_TIME (3 s) without one.
- Streams: ATTITUDE and LOCAL_POSITION_NED at 4 Hz, ODOMETRY (LOCAL_NED, BODY_FRD) off, until
  MAV_CMD_SET_MESSAGE_INTERVAL or REQUEST_DATA_STREAM sets them; TIMESYNC answered with its boot time.
- Counted, never raised: bad_data, wrong_target, every refusal. --record FILE: a JSON line per set point or
  sticks taken (with the wall clock's ns) and per mode change, refusal or arming, at its monotonic time.
Not modelled: ArduPilot's own speed and turn-rate controllers (the preset's loop stands in), the EKF and
its errors, RC, failsafes, missions, parameters. docs/boats.md, "ArduPilot over MAVLink".
"""

from __future__ import annotations

import argparse
import json
import math
import os
import select
import signal
import sys
import threading
import time
from collections import Counter

import numpy as np

from agent.angles import wrap_angle
from boat.presets import preset as boat_preset
from boat.sway import arc_step
from sim_bridge.hull import HullFleet

MANUAL, ACRO, HOLD, GUIDED = 0, 1, 4, 15
MODES = {MANUAL: "MANUAL", ACRO: "ACRO", HOLD: "HOLD", GUIDED: "GUIDED"}
STICK_MODES = (MANUAL, ACRO)   # the modes the pilot's sticks (RC, or MANUAL_CONTROL's overrides) drive
ACCEPTED, UNSUPPORTED, FAILED = 0, 3, 4
BODY_FRAMES, LOCAL_FRAMES = (8, 9), (1, 7)
POSITION_BITS, VELOCITY_XY_BITS, YAW_BIT, YAW_RATE_BIT = 1 | 2 | 4, 8 | 16, 1024, 2048
ATTITUDE_ID, LOCAL_POSITION_NED_ID, ODOMETRY_ID = 30, 32, 331
POSITION_STREAMS = (LOCAL_POSITION_NED_ID, ODOMETRY_ID)   # sent only with a position estimate
STREAM_OF = {6: (LOCAL_POSITION_NED_ID,), 10: (ATTITUDE_ID,), 0: (ATTITUDE_ID, LOCAL_POSITION_NED_ID)}
DEFAULT_INTERVAL = 0.25   # s: 4 Hz until asked otherwise (our choice; ArduPilot's SRx_ parameters set it)
STEP = 0.005              # s: the loop's period
HULL_STEP = 0.02          # s: the hull's substep with --preset (the sim's default dynamics step)
# Relayed: boot time = sim time + this (no time_boot_ms of 0), and TIMESYNC answers so: the driver stamps the
# pose of sim time t at t exactly (an agent's share carries its odometry's stamp, which must be the tick's).
RELAY_BOOT_NS = 1_000_000_000


class Standin:
    def __init__(self, mav, system: int = 1, component: int = 1, guid_timeout: float = 3.0,
                 position: bool = True, record=None, clock=time.monotonic, preset: str | None = None,
                 gcs_system: int = 255, full_throttle_speed: float = 2.0, acro_turn_rate: float = 180.0,
                 override_timeout: float = 3.0, relayed: bool = False) -> None:
        self.mav, self.system, self.component = mav, system, component
        self.relayed = relayed   # the hull is the sim bridge's (standin_relay.py): no motion, no streams of its own
        self.arrival = None      # relayed: (u, r) -> wall ns the agent's command reached the relay, for latency
        self.guid_timeout, self.position, self.record, self.clock = guid_timeout, position, record, clock
        self.boot = clock()
        self.counts: Counter[str] = Counter()
        self.mode, self.armed = MANUAL, False
        self.north = self.east = 0.0
        self.yaw = 0.0                        # NED: clockwise from north (rad)
        self.u = self.r = 0.0                 # what the hull does now (r counter-clockwise)
        self.setpoint: tuple[float, float, float] | None = None   # u, r, when (monotonic s)
        # The sticks: MANUAL_CONTROL from the GCS's system id (MAV_GCS_SYSID), overriding RC for
        # RC_OVERRIDE_TIME (`override_timeout`); ACRO turns at steering x ACRO_TURN_RATE (deg/s), and with no
        # speed estimate (no GNSS) sets throttle, which this hull turns into full_throttle_speed x throttle.
        self.gcs_system, self.full_throttle_speed = gcs_system, full_throttle_speed
        self.acro_turn_rate, self.override_timeout = math.radians(acro_turn_rate), override_timeout
        self.sticks: tuple[float, float, float] | None = None   # steering, throttle (-1..1), when (monotonic s)
        self.intervals = {ATTITUDE_ID: DEFAULT_INTERVAL, LOCAL_POSITION_NED_ID: DEFAULT_INTERVAL, ODOMETRY_ID: None}
        self.due = {ATTITUDE_ID: self.boot, LOCAL_POSITION_NED_ID: self.boot, ODOMETRY_ID: self.boot,
                    "heartbeat": self.boot}
        self.stepped = self.boot
        self.posed: int | None = None         # relayed: sim time (ns) of the last pose
        self.hulls = None
        if preset is not None:   # x east, y north, psi counter-clockwise from east: bow north at the origin
            self.hulls = HullFleet(boat_preset(preset), 1, HULL_STEP, 1)
            self.hulls.place(0, 0.0, 0.0, math.pi / 2)

    def boot_ms(self, now: float) -> int:
        return int((now - self.boot) * 1000) & 0xFFFFFFFF

    def _note(self, kind: str, now: float, **fields) -> None:
        if self.record is not None:
            self.record.write(json.dumps({"t": now, "kind": kind, **fields}) + "\n")
            self.record.flush()

    def _set_mode(self, mode: int, now: float, why: str) -> int:
        if mode not in MODES:
            self.counts["mode_unsupported"] += 1
            return UNSUPPORTED
        if mode == GUIDED and not self.position:
            self.counts["mode_refused_no_position"] += 1
            self._note("mode_refused", now, mode=MODES[mode], why="no position estimate")
            return FAILED
        if mode != self.mode:
            self.mode = mode
            self._note("mode", now, mode=MODES[mode], why=why)
        return ACCEPTED

    # ----- what comes in -----
    def receive(self, msg, now: float) -> list:
        """One parsed message in; the replies out."""
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.counts["bad_data"] += 1
            return []
        target = getattr(msg, "target_system", None)
        if target is not None and target not in (0, self.system):
            self.counts["wrong_target"] += 1
            return []
        handler = getattr(self, f"_on_{kind.lower()}", None)
        return handler(msg, now) if handler else []

    def _ack(self, command: int, result: int) -> list:
        return [self.mav.command_ack_encode(command, result)]

    def _on_command_long(self, msg, now: float) -> list:
        command = msg.command
        if command == 176:        # MAV_CMD_DO_SET_MODE: param2 the custom mode
            return self._ack(command, self._set_mode(int(msg.param2), now, "command"))
        if command == 400:        # MAV_CMD_COMPONENT_ARM_DISARM
            armed = msg.param1 == 1
            if armed != self.armed:
                self.armed = armed
                self._note("armed", now, armed=armed)
            return self._ack(command, ACCEPTED)
        if command == 511:        # MAV_CMD_SET_MESSAGE_INTERVAL: param1 message id, param2 interval (us)
            message, interval = int(msg.param1), msg.param2
            if message not in self.intervals or not math.isfinite(interval):
                return self._ack(command, FAILED)
            self.intervals[message] = (None if interval < 0 else DEFAULT_INTERVAL if interval == 0
                                       else max(interval * 1e-6, 0.01))
            return self._ack(command, ACCEPTED)
        self.counts["command_unsupported"] += 1
        return self._ack(command, UNSUPPORTED)

    def _on_set_mode(self, msg, now: float) -> list:
        return self._ack(11, self._set_mode(int(msg.custom_mode), now, "set_mode"))

    def _on_request_data_stream(self, msg, now: float) -> list:
        for message in STREAM_OF.get(msg.req_stream_id, ()):
            rate = msg.req_message_rate
            self.intervals[message] = 1.0 / rate if msg.start_stop and rate > 0 else None
        return []

    def _on_timesync(self, msg, now: float) -> list:
        if msg.tc1 != 0:
            return []
        if self.relayed:   # its boot clock: the sim clock (the asker's own) + RELAY_BOOT_NS
            return [self.mav.timesync_encode(msg.ts1 + RELAY_BOOT_NS, msg.ts1)]
        return [self.mav.timesync_encode(int((now - self.boot) * 1e9), msg.ts1)]

    def _on_manual_control(self, msg, now: float) -> list:
        """Rover's MANUAL_CONTROL: y the steering, z the throttle, each -1000..1000 over the RC range (x, r
        unused); taken only from the GCS's system id and aimed at this vehicle, as ArduPilot does."""
        if msg.get_srcSystem() != self.gcs_system or msg.target != self.system:
            self.counts["manual_control_refused"] += 1
            return []
        steering, throttle = (max(-1.0, min(1.0, value / 1000.0)) for value in (msg.y, msg.z))
        self.sticks = (steering, throttle, now)
        self.counts["manual_control"] += 1
        self._note("sticks", now, u=throttle * self.full_throttle_speed, r=-steering * self.acro_turn_rate,
                   east=self.east, north=self.north, mode=MODES[self.mode], wall_ns=time.time_ns())
        return []

    def _on_set_position_target_local_ned(self, msg, now: float) -> list:
        mask, frame = msg.type_mask, msg.coordinate_frame
        if self.mode != GUIDED:
            self.counts["setpoint_not_guided"] += 1
            return []
        velocity_and_rate = (mask & POSITION_BITS == POSITION_BITS and not mask & VELOCITY_XY_BITS
                             and mask & YAW_BIT and not mask & YAW_RATE_BIT)
        if not velocity_and_rate or frame not in BODY_FRAMES + LOCAL_FRAMES:
            self.counts["setpoint_unsupported"] += 1
            return []
        if not all(math.isfinite(v) for v in (msg.vx, msg.vy, msg.yaw_rate)):
            self.counts["setpoint_non_finite"] += 1
            return []
        u = msg.vx if frame in BODY_FRAMES else msg.vx * math.cos(self.yaw) + msg.vy * math.sin(self.yaw)
        self.setpoint = (u, -msg.yaw_rate, now)
        self.counts["setpoints"] += 1
        wall_ns = time.time_ns()
        arrived = self.arrival(u, -msg.yaw_rate) if self.arrival is not None else None
        added = {} if arrived is None else {"added_ms": (wall_ns - arrived) * 1e-6}
        self._note("setpoint", now, u=u, r=-msg.yaw_rate, wall_ns=wall_ns, **added)
        return []

    # ----- the hull and what goes out -----
    def step(self, now: float) -> list:
        """Move the hull to `now` under what it does, decide what it does next; the messages due."""
        dt = now - self.stepped
        if self.relayed:
            pass
        elif self.hulls is not None:
            while self.stepped + HULL_STEP <= now:   # the preset's hull under its inner loop, (u, r) held
                self.hulls.advance(self.stepped, HULL_STEP, np.array([self.u]), np.array([self.r]), self.stepped)
                self.stepped += HULL_STEP
            east, north, psi = self.hulls.state[:3, 0]
            self.east, self.north, self.yaw = float(east), float(north), wrap_angle(math.pi / 2 - float(psi))
        elif dt > 0:
            heading = math.pi / 2 - self.yaw          # counter-clockwise from east
            turn = self.r * dt
            east, north = arc_step(self.east, self.north, heading, turn, self.u * dt, 0.0)
            self.east, self.north = east, north
            self.yaw = wrap_angle(self.yaw - turn)
            self.stepped = now
        self.u = self.r = 0.0
        if self.mode == GUIDED and self.setpoint is not None:
            if now - self.setpoint[2] > self.guid_timeout:
                self.setpoint = None
                self.counts["guided_timeout"] += 1
                self._note("guided_timeout", now)
            elif self.armed:
                self.u, self.r = self.setpoint[0], self.setpoint[1]
        if self.mode in STICK_MODES and self.sticks is not None:
            if now - self.sticks[2] > self.override_timeout:
                self.sticks = None   # the override lapses: the sticks (no RC here) are centred
                self.counts["override_timeout"] += 1
                self._note("override_timeout", now)
            elif self.armed:
                self.u = self.sticks[1] * self.full_throttle_speed
                self.r = -self.sticks[0] * self.acro_turn_rate
        out = []
        if now >= self.due["heartbeat"]:
            self.due["heartbeat"] += 1.0
            base = 1 | (128 if self.armed else 0)   # CUSTOM_MODE_ENABLED, SAFETY_ARMED
            out.append(self.mav.heartbeat_encode(11, 3, base, self.mode, 4 if self.armed else 3))
        for message, interval in self.intervals.items():
            if (interval is None or now < self.due[message] or message in POSITION_STREAMS and not self.position
                    or self.relayed):
                continue
            self.due[message] = max(self.due[message] + interval, now)
            ms = self.boot_ms(now)
            north_speed, east_speed, rate = self.motion()
            if message == ATTITUDE_ID:
                out.append(self.mav.attitude_encode(ms, 0.0, 0.0, self.yaw, 0.0, 0.0, -rate))
            elif message == ODOMETRY_ID:   # LOCAL_NED pose, BODY_FRD velocity and rates, covariances unknown
                unknown = [math.nan] + [0.0] * 20
                forward = north_speed * math.cos(self.yaw) + east_speed * math.sin(self.yaw)
                out.append(self.mav.odometry_encode(
                    int((now - self.boot) * 1e6), 1, 12, self.north, self.east, 0.0,
                    [math.cos(self.yaw / 2), 0.0, 0.0, math.sin(self.yaw / 2)], forward, 0.0, 0.0, 0.0, 0.0, -rate,
                    unknown, unknown, 0, 0, 0))
            else:
                out.append(self.mav.local_position_ned_encode(ms, self.north, self.east, 0.0, north_speed,
                                                              east_speed, 0.0))
        return out

    def pose(self, north: float, east: float, yaw: float, rate: float, stamp_ns: int) -> list:
        """Relayed: the sim's pose of sim time `stamp_ns` (yaw NED, `rate` its rate counter-clockwise) as
        ATTITUDE and LOCAL_POSITION_NED, stamped on the sim clock (+ RELAY_BOOT_NS: no boot time is 0)."""
        speed_north, speed_east = (north - self.north, east - self.east) if self.posed is not None else (0.0, 0.0)
        dt = (stamp_ns - self.posed) * 1e-9 if self.posed is not None else 0.0
        self.north, self.east, self.yaw = north, east, yaw
        self.posed = stamp_ns
        ms = ((stamp_ns + RELAY_BOOT_NS) // 1_000_000) & 0xFFFFFFFF
        north_speed, east_speed = (speed_north / dt, speed_east / dt) if dt > 0 else (0.0, 0.0)
        return [self.mav.attitude_encode(ms, 0.0, 0.0, yaw, 0.0, 0.0, -rate),
                self.mav.local_position_ned_encode(ms, north, east, 0.0, north_speed, east_speed, 0.0)]

    def motion(self) -> tuple[float, float, float]:
        """Velocity north and east (m/s) and yaw rate (rad/s, counter-clockwise) over ground now."""
        if self.hulls is None:
            return self.u * math.cos(self.yaw), self.u * math.sin(self.yaw), self.r
        vx, vy = self.hulls.ground_velocity()
        return float(vy[0]), float(vx[0]), float(self.hulls.state[5, 0])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="usv-ardupilot-standin", description=__doc__.split("\n")[0])
    parser.add_argument("--listen", required=True, help="pymavlink URL to serve, e.g. udpin:127.0.0.1:14550")
    parser.add_argument("--system", type=int, default=1, help="its MAVLink system id")
    parser.add_argument("--guid-timeout", type=float, default=3.0, help="GUID_TIMEOUT (s)")
    parser.add_argument("--no-position", action="store_true", help="no position estimate: GUIDED refused, "
                        "no LOCAL_POSITION_NED or ODOMETRY (ACRO and MANUAL work)")
    parser.add_argument("--gcs-system", type=int, default=255, help="MAV_GCS_SYSID: MANUAL_CONTROL's sender")
    parser.add_argument("--full-throttle-speed", type=float, default=2.0, help="the hull's speed at full "
                        "throttle in ACRO/MANUAL (m/s)")
    parser.add_argument("--acro-turn-rate", type=float, default=180.0, help="ACRO_TURN_RATE (deg/s)")
    parser.add_argument("--preset", default=None, help="a boat preset's hull and inner loop (otter, heron, "
                        "wamv) instead of the kinematic hull")
    parser.add_argument("--record", default=None, help="JSON lines of set points and mode changes")
    parser.add_argument("--seconds", type=float, default=None, help="stop after this long")
    parser.add_argument("--sim", default=None, help="a sim bridge's Zenoh endpoint: the hull is its vessel "
                        "--vessel (usv-fleet run --vehicle mavlink; sim_bridge/standin_relay.py)")
    parser.add_argument("--vessel", default=None, help="with --sim: the vessel's id")
    args = parser.parse_args(argv)
    if (args.sim is None) != (args.vessel is None) or (args.sim is not None and args.preset is not None):
        parser.error("--sim and --vessel go together, and without --preset (the sim's world moves the hull)")
    os.environ.setdefault("MAVLINK20", "1")   # mavutil picks the wire version from the environment
    try:
        from pymavlink import mavutil
    except ImportError:
        print("usv-ardupilot-standin: needs pymavlink, in the optional extra 'driver': "
              "pip install 'usv-circumnav[driver]'", file=sys.stderr)
        return 2
    connection = mavutil.mavlink_connection(args.listen, source_system=args.system, source_component=1)
    stopping = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stopping.set())
    record = open(args.record, "a", encoding="utf-8") if args.record else None
    standin = Standin(connection.mav, args.system, 1, args.guid_timeout, not args.no_position, record,
                      preset=args.preset, gcs_system=args.gcs_system, full_throttle_speed=args.full_throttle_speed,
                      acro_turn_rate=args.acro_turn_rate, relayed=args.sim is not None)
    relay = None
    if args.sim is not None:
        from sim_bridge.standin_relay import SimRelay
        relay = SimRelay(args.sim, args.vessel, standin, MODES)
        standin.arrival = relay.arrival
    spoken = False   # an udpin link has nobody to send to until someone speaks
    try:
        while not stopping.is_set() and (args.seconds is None or time.monotonic() - standin.boot < args.seconds):
            ready, _, _ = select.select([connection.fd] + ([relay.wake_fd] if relay else []), [], [], STEP)
            replies, taken = [], standin.counts["setpoints"]
            posed = relay is not None and relay.wake_fd in ready
            if posed:
                replies += relay.poses()
            if connection.fd in ready:
                for _ in range(256):
                    try:
                        msg = connection.recv_msg()
                    except Exception as error:   # noqa: BLE001 - a link's bytes never end the boat
                        standin.counts[f"link_{type(error).__name__}"] += 1
                        break
                    if msg is None:
                        break
                    spoken = True
                    replies += standin.receive(msg, time.monotonic())
            out = replies + standin.step(time.monotonic())
            if spoken:
                for message in out:
                    connection.mav.send(message)
            if relay is not None:
                relay.publish(posed or standin.counts["setpoints"] > taken)
                for added in relay.late_matches():
                    standin._note("setpoint_ahead", time.monotonic(), added_ms=added)
    finally:
        if record is not None:
            record.close()
        if relay is not None:
            relay.close()
    print(f"usv-ardupilot-standin: stopped; {dict(standin.counts)}", file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
