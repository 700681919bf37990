"""The driver bridge process: a vessel's hardware behind the agents' Zenoh contract (`usv-driver`).

It does on a boat what the sim bridge does in simulation, for one vessel: it reads the serial devices,
publishes the contract's sensor messages under `usv/<id>/sensor/...`, and turns the agent's commands into
thrust. Each device (an autopilot too) is one adapter; this file only wires them to the ports and to Zenoh.

    UWB module  --NLink frames-->  NLinkParser     -> usv/<id>/sensor/uwb      (Ranges)
    speed log   --$..VHW------->   DeadReckoning   -> usv/<id>/sensor/odom     (Odometry)
    detector    --$DET--------->   BearingAdapter  -> usv/<id>/sensor/bearing  (Bearing, with the odometry's heading)
    GNSS        --$..GGA------->   GnssAdapter     -> usv/<id>/truth/gnss      (GnssFix: truth, no agent reads it)
    usv/<id>/cmd (Cmd)  -------->  ThrusterAdapter -> $THR lines to the motor controller, `rate_hz` times a second
                                   or LoopThrusters (thrusters.control: inner_loop, closed on the
                                   speed log and yaw) -> $THR lines at the loop's `loop_hz`
    usv/<id>/cmd, autopilot <-> MavlinkVehicle (`mavlink`): set points; its state -> sensor/odom, sensor/vehicle

The watchdog is the adapter's: with no fresh command the thrusters get zero. Stamps are wall time (at sea),
or `clock: sim` the sim bridge's sim/clock (MAVLink stand-ins). One thread reads the ports (select); the
Zenoh callback only stores the latest command (and wakes the loop for an autopilot). SIGINT and SIGTERM stop it, with a last zero-thrust
line (an autopilot: a zero set point and HOLD).

No line or frame ends the process: that would take the watchdog's stop with it. Each adapter bounds what
it produces to the contract (odometry.py, uwb.py, bearing.py) and counts what it refuses by reason; each
sentence, frame and command is handled under a last-resort guard that counts an unexpected error as
`<port>_failed` and goes on. What was refused is said on stderr at most every REPORT_SECONDS, and in full
at the end. More: docs/contract.md, "The driver bridge in detail"; docs/boats.md.
"""

from __future__ import annotations

import math
import os
import select
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from typing import Literal

import zenoh
from pydantic import Field, model_validator

from agent.config import PositiveFloat, StrictModel
from agent.contract import (
    CLOCK_KEY,
    LIVELINESS,
    VEHICLE_TOPIC,
    Bearing,
    Clock,
    Cmd,
    Odometry,
    Ranges,
    VehicleState,
    decode,
    encode,
    gnss_truth_key,
    key,
)
from agent.runtime.mcap_log import McapLog
from agent.runtime.process import stop_on_signals, vessel_process
from agent.runtime.zenoh_session import ZenohSettings, zenoh_config
from driver_bridge.bearing import BearingAdapter, CameraSettings, read_detection
from driver_bridge.gnss import GnssAdapter, ReceiverSettings
from driver_bridge.mavlink_link import MissingExtra, open_link
from driver_bridge.mavlink_vehicle import MavlinkSettings, MavlinkVehicle
from driver_bridge.odometry import DeadReckoning, OdometrySettings, read_vhw
from driver_bridge.serial_port import LineReader, libraries, open_serial
from driver_bridge.thrust_loop import LoopSettings, LoopThrusters
from driver_bridge.thrusters import (
    ZERO_THRUST,
    CommandGate,
    CommandWindow,
    ThrusterAdapter,
    ThrusterSettings,
    command_line,
)
from driver_bridge.uwb import NLinkParser, UwbSettings

REPORT_SECONDS = 10.0   # the most often the refusals are said on stderr
VEHICLE_PERIOD = 0.01   # s: how often the autopilot's link is served (each message keeps its own rate)


class Port(StrictModel):
    device: str = Field(description="serial device, e.g. /dev/ttyUSB0 or /dev/serial/by-id/...")
    baud: int = Field(115_200, gt=0)


# What each device is, for a line that says which one could not be opened.
DEVICES = {"uwb": "the UWB module", "odometry": "the speed log and compass", "camera": "the camera",
           "thrusters": "the thrusters' controller", "gnss": "the GNSS receiver"}


class UwbPort(Port):
    # LinkTrack's own UART rate: Nooploop's driver (nlink_parser) opens the module at 921600.
    baud: int = Field(921_600, gt=0)
    module: UwbSettings


class OdometryPort(Port):
    # NMEA VHW gives a compass heading (clockwise from north): with x east and y north that is yaw_sign -1
    # and yaw_offset pi/2 in the common counter-clockwise reference.
    dead_reckoning: OdometrySettings = OdometrySettings(yaw_sign=-1, yaw_offset=math.pi / 2)


class CameraPort(Port):
    camera: CameraSettings


class GnssPort(Port):
    # 9600: the NMEA output rate u-blox receivers start at (NMEA 0183's own 4800 is too slow for 5 Hz GGA).
    baud: int = Field(9_600, gt=0)
    receiver: ReceiverSettings = ReceiverSettings()
    log: str | None = Field(None, description="an MCAP file the fixes also go to: usv-log metrics scores a "
                                              "field trial from it (docs/logs.md)")


THR_LINE_BITS = 10 * len(b"$THR,+0.000,+0.000*00\r\n")   # one thrust line at 8N1


class ThrusterPort(Port):
    control: Literal["mix", "inner_loop"] = Field(
        "mix", description="'mix': open-loop steady-state mix of the command; 'inner_loop': a preset's loop")
    hull: ThrusterSettings | None = Field(None, description="the mix's hull (control: mix)")
    inner_loop: LoopSettings | None = Field(None, description="the preset and its loop (control: inner_loop)")
    rate_hz: PositiveFloat = Field(10.0, description="thrust lines per second with the mix (loop: loop_hz)")

    @model_validator(mode="after")
    def _control(self) -> ThrusterPort:
        if self.control == "mix" and self.hull is None:
            raise ValueError("control 'mix' needs hull (its drag, beam and thrust)")
        if self.control == "inner_loop" and self.inner_loop is None:
            raise ValueError("control 'inner_loop' needs inner_loop (at least its preset)")
        if self.baud < self.lines_per_second() * THR_LINE_BITS:
            lines = self.lines_per_second()
            raise ValueError(f"{self.baud} baud cannot carry {lines:g} thrust lines a second "
                             f"(needs {lines * THR_LINE_BITS:g})")
        return self

    def lines_per_second(self) -> float:
        return self.inner_loop.loop_hz if self.control == "inner_loop" else self.rate_hz


class DriverSettings(StrictModel):
    zenoh: ZenohSettings = ZenohSettings()
    uwb: UwbPort | None = None
    odometry: OdometryPort | None = None
    camera: CameraPort | None = None
    thrusters: ThrusterPort | None = None
    gnss: GnssPort | None = Field(None, description="a GNSS receiver's GGA, published as truth for scoring only")
    mavlink: MavlinkSettings | None = Field(None, description="an ArduPilot autopilot: it drives the vessel and "
                                            "gives its odometry (docs/boats.md)")
    commands: CommandWindow = CommandWindow()
    clock: Literal["wall", "sim"] = Field("wall", description="wall: a boat's; sim: the sim bridge's sim/clock "
                                          "(usv-fleet run --vehicle mavlink)")

    @model_validator(mode="after")
    def _measured(self) -> DriverSettings:
        if self.mavlink is not None and self.thrusters is not None:
            raise ValueError("mavlink drives the vessel: leave out thrusters")
        if self.mavlink is not None and (self.mavlink.odometry == "none") != (self.odometry is not None):
            raise ValueError("with mavlink the odometry comes from the autopilot, or (mavlink.odometry: none) from "
                             "the speed log's port: give the odometry port exactly then")
        if self.thrusters is not None and self.thrusters.control == "inner_loop" and self.odometry is None:
            raise ValueError("thrusters.control 'inner_loop' closes its loop on the speed log and yaw: "
                             "it needs the odometry port")
        return self


class DriverBridge:
    """`clock_ns` gives the wall clock the messages are stamped with and commands judged by (ns); a test or a
    fuzz campaign passes its own."""

    def __init__(self, vessel: str, settings: DriverSettings, clock_ns: Callable[[], int] = time.time_ns,
                 report: Callable[[str], None] | None = None) -> None:
        self.id = vessel
        self.settings = settings
        self.clock_ns = clock_ns if settings.clock == "wall" else self._sim_ns
        self._sim_stamp = 0   # clock: sim: the stamp of the latest sim/clock (ns)
        self._report = report or (lambda line: print(line, file=sys.stderr, flush=True))
        self._reported: tuple[float, dict] = (-math.inf, {})
        self.stopping = threading.Event()
        self.uwb = NLinkParser(settings.uwb.module) if settings.uwb else None
        self.dead_reckoning = DeadReckoning(settings.odometry.dead_reckoning) if settings.odometry else None
        self.camera = BearingAdapter(settings.camera.camera) if settings.camera else None
        self.gnss = GnssAdapter(settings.gnss.receiver) if settings.gnss else None
        self.gnss_log: McapLog | None = None   # opened by open_gnss_log (run), when gnss.log is set
        self.thrusters = self._thrusters(settings)
        self.vehicle: MavlinkVehicle | None = None   # made when its link opens (it needs the link's encoder)
        self._autopilot_heading: float | None = None
        self._wake: tuple[int, int] | None = None    # a pipe that wakes the loop for a command (autopilot only)
        self.published: Counter[str] = Counter()
        self.refused: Counter[str] = Counter()
        self.lines = {"odometry": LineReader(), "camera": LineReader(), "gnss": LineReader()}
        self._seq: Counter[str] = Counter()
        self._command_lock = threading.Lock()
        self.command_gate = CommandGate(settings.commands)
        self._command: Cmd | None = None
        self._applied: Cmd | None = None
        self._agent_left = False

    def _thrusters(self, settings: DriverSettings) -> ThrusterAdapter | LoopThrusters | None:
        port = settings.thrusters
        if port is None:
            return None
        if port.control == "mix":
            return ThrusterAdapter(port.hull)
        return LoopThrusters(port.inner_loop, settings.odometry.dead_reckoning,
                             lambda line: self._report(f"usv-driver {self.id}: {line}"))

    # ----- refusals and the last-resort guard -----
    def refusals(self) -> dict[str, dict[str, int]]:
        """Everything refused so far, by where and why (what the closing line and the reports say)."""
        counts = {"refused": dict(self.refused)}
        for name in ("uwb", "dead_reckoning", "camera", "thrusters", "gnss", "vehicle"):
            adapter = getattr(self, name)
            if adapter is not None and adapter.rejected:
                counts[f"{name}_refused"] = dict(adapter.rejected)
        for name, lines in self.lines.items():
            if lines.rejected:
                counts[f"{name}_lines_refused"] = dict(lines.rejected)
        return {name: values for name, values in counts.items() if values}

    def report_refusals(self, now: float) -> None:
        """One stderr line with the refusals so far, if they changed, at most every REPORT_SECONDS (`now`:
        monotonic)."""
        last, said = self._reported
        if now - last < REPORT_SECONDS:
            return
        counts = self.refusals()
        if counts != said:
            self._report(f"usv-driver {self.id}: refused so far (dropped, going on): {counts}")
            self._reported = (now, counts)

    def _guarded(self, port: str, handle: Callable, *args) -> list:
        """`handle(*args)`, or [] if it raised: counted as `<port>_failed`, the first said at once."""
        try:
            return handle(*args)
        except Exception as error:   # one line must never end the process, and the watchdog's stop with it
            kind = f"{port}_failed"
            if not self.refused[kind]:
                self._report(f"usv-driver {self.id}: {port}: dropped an input that raised "
                             f"{type(error).__name__}: {str(error)[:300]} (counted as {kind}; going on)")
            self.refused[kind] += 1
            return []

    def _each(self, port: str, items: Iterable, handle: Callable, publishers) -> None:
        for item in items:
            self._guarded(port, handle, item, publishers)

    # ----- Zenoh side -----
    def _on_command(self, sample) -> None:
        self._guarded("command", self._command_payload, sample)

    def _command_payload(self, sample) -> None:
        message, _ = decode(Cmd, sample.payload.to_bytes())
        if message is None or message.sender != self.id:
            self.refused["command_malformed" if message is None else "command_other_vessel"] += 1
            return
        with self._command_lock:
            reason = self.command_gate.offer(message.stamp_ns, self.clock_ns())
            if reason:
                self.refused[f"command_{reason}"] += 1
            else:
                self._command = message
        self._wake_loop()

    def _wake_loop(self) -> None:
        """With an autopilot, a command goes out as it comes: the loop's select is woken for it."""
        if self._wake is not None:
            try:
                os.write(self._wake[1], b"!")
            except OSError:   # the pipe is full: the loop is awake already (or closed: it is stopping)
                pass

    def _on_agent_liveliness(self, sample) -> None:
        """The agent's session ended (its token went away): the command in force goes with it."""
        if sample.kind == zenoh.SampleKind.DELETE:
            with self._command_lock:
                self._command = None
                self.command_gate.forget()
                self._agent_left = True
            self._wake_loop()

    def _sim_ns(self) -> int:
        return self._sim_stamp

    def _on_sim_clock(self, sample) -> None:
        message, _ = decode(Clock, sample.payload.to_bytes())
        if message is None:
            self.refused["clock_malformed"] += 1
        else:
            self._sim_stamp = message.stamp_ns

    def _publish(self, publishers, topic: str, message) -> None:
        publishers[topic].put(encode(message))
        self.published[topic] += 1

    def _next(self, topic: str) -> int:
        value = self._seq[topic]
        self._seq[topic] += 1
        return value

    # ----- device side: each chunk split under the guard, then each frame or sentence handled under it -----
    def _on_uwb(self, data: bytes, publishers) -> None:
        self._each("uwb", self._guarded("uwb", self.uwb.feed, data), self._uwb_frame, publishers)

    def _uwb_frame(self, frame, publishers) -> None:
        self._publish(publishers, "sensor/uwb", Ranges(
            stamp_ns=self.clock_ns(), seq=self._next("uwb"), sender=self.id, ranges=frame.ranges))

    def _on_odometry(self, data: bytes, publishers) -> None:
        bodies = self._guarded("odometry", self.lines["odometry"].feed, data)
        self._each("odometry", bodies, self._vhw, publishers)

    def _vhw(self, body: bytes, publishers) -> None:
        sample, reason = read_vhw(body)
        if sample is None:
            self.refused[f"odometry_{reason}"] += 1
            return
        speed, heading = sample
        if isinstance(self.thrusters, LoopThrusters):
            self.thrusters.measure(time.monotonic(), speed, heading)   # the watchdog's clock
        before = self.dead_reckoning.state
        state = self.dead_reckoning.update(self.clock_ns() * 1e-9, speed, heading)   # refusals counted there
        if state is not None and state is not before:
            self._publish(publishers, "sensor/odom", state.message(self._next("odom"), self.id))

    def _on_camera(self, data: bytes, publishers) -> None:
        bodies = self._guarded("camera", self.lines["camera"].feed, data)
        self._each("camera", bodies, self._detection, publishers)

    def _detection(self, body: bytes, publishers) -> None:
        detection, reason = read_detection(body)
        if detection is None:
            self.refused[f"camera_{reason}"] += 1
            return
        heading = self._heading
        if heading is None:
            self.refused["bearing_without_heading"] += 1   # a bearing needs the common heading
            return
        column, row = detection
        vector = self.camera.bearing(column, row, heading)
        if vector is None and column is not None:
            return   # refused by the adapter (counted there)
        self._publish(publishers, "sensor/bearing", Bearing(
            stamp_ns=self.clock_ns(), seq=self._next("bearing"), sender=self.id, bearing=vector))

    def _on_gnss(self, data: bytes, publishers) -> None:
        bodies = self._guarded("gnss", self.lines["gnss"].feed, data)
        self._each("gnss", bodies, self._gga, publishers)

    def _gga(self, body: bytes, publishers) -> None:
        fix = self.gnss.fix(body, self.clock_ns(), self._seq["gnss"], self.id)   # refusals counted there
        if fix is not None:
            self._next("gnss")
            self._publish(publishers, "truth/gnss", fix)
            if self.gnss_log is not None:   # a write's OSError is said once by the log and counted there
                self.gnss_log.log(gnss_truth_key(self.id), fix, fix.stamp_ns)

    def open_gnss_log(self) -> None:
        """The GNSS log of `gnss.log`, beside the agent's on the boat's computer (docs/logs.md), or an OSError
        that names it."""
        path = self.settings.gnss.log if self.settings.gnss is not None else None
        if path is None or self.gnss_log is not None:
            return
        try:
            self.gnss_log = McapLog(path, metadata={"gnss_of": self.id}, announce=lambda line: self._report(
                f"usv-driver {self.id}: GNSS log: {line}"))
        except OSError as error:
            raise OSError(f"cannot write the GNSS log (gnss.log {path}): {error.strerror or error}") from None

    @property
    def _heading(self) -> float | None:
        """The vessel's heading in the common reference, from the speed log's compass or the autopilot."""
        if self.dead_reckoning is not None and self.dead_reckoning.state is not None:
            return self.dead_reckoning.state.heading
        return self._autopilot_heading

    def _on_mavlink(self, link, publishers, mono: float | None = None) -> None:
        """What the link has, through the vehicle; `mono`: the monotonic clock (a fuzz campaign's own)."""
        for msg in self._guarded("mavlink", link.messages):
            now = time.monotonic() if mono is None else mono
            odometry = self._guarded("mavlink", self.vehicle.receive, msg, self.clock_ns(), now)
            if isinstance(odometry, Odometry):
                self._autopilot_heading = odometry.heading
                self._publish(publishers, "sensor/odom", odometry)

    def _drive_vehicle(self, link, mono: float, publishers=None) -> None:
        """The agent's command (or its leaving) to the autopilot, then whatever is due on the link; the
        autopilot's state to `publishers` when it is due."""
        with self._command_lock:
            command, left, self._agent_left = self._command, self._agent_left, False
        if left:
            self.vehicle.agent_left(mono)
        if command is not None and command is not self._applied:
            self._applied = command
            self.vehicle.command(command.surge, command.yaw_rate, mono)
        for msg in self._guarded("mavlink", self.vehicle.tick, self.clock_ns(), mono):
            self._guarded("mavlink", link.send, msg)
        if publishers is not None and VEHICLE_TOPIC in publishers:
            state = self._guarded("mavlink", self.vehicle.state, self.clock_ns(), mono)
            if isinstance(state, VehicleState):
                self._publish(publishers, VEHICLE_TOPIC, state)

    def _drive(self, port, now: float) -> None:
        """One thrust line to `port` (pyserial's write gives up after 1 s); `now`: the monotonic clock."""
        port.write(self.thrust_line(now))

    def thrust_line(self, now: float) -> bytes:
        """The thrust line to write now: the command in force's, or a stop. `now`: the monotonic clock."""
        with self._command_lock:
            command, left, self._agent_left = self._command, self._agent_left, False
        if left:
            self.thrusters.stop("agent_left")
        if command is not None and command is not self._applied:
            self._applied = command
            # Its stamp was judged on arrival (CommandGate); the watchdog counts from its application.
            self.thrusters.command(command.surge, command.yaw_rate, now)
        return command_line(self.thrusters.output(now))

    # ----- the loop -----
    def run(self, max_seconds: float | None = None) -> None:
        ports = {}
        for name in ("uwb", "odometry", "camera", "thrusters", "gnss"):
            port = getattr(self.settings, name)
            if port is not None:
                try:
                    ports[name] = open_serial(port.device, port.baud)
                except (OSError, ValueError) as error:   # pyserial: SerialException (an OSError), a bad baud
                    for opened in ports.values():
                        opened.close()
                    why = os.strerror(error.errno) if getattr(error, "errno", None) else str(error)
                    raise OSError(f"cannot open {DEVICES[name]} ({name}.device {port.device} at {port.baud} "
                                  f"baud): {why}") from None
        handlers = {"uwb": self._on_uwb, "odometry": self._on_odometry, "camera": self._on_camera,
                    "gnss": self._on_gnss}
        readers = {port: name for name, port in ports.items() if name in handlers}
        link = self._open_vehicle(ports)
        started = time.monotonic()
        try:
            self.open_gnss_log()
            with zenoh.open(zenoh_config(self.settings.zenoh)) as session:
                publishers = {t: session.declare_publisher(key(self.id, t))
                              for t in ("sensor/uwb", "sensor/odom", "sensor/bearing")}
                if link is not None:
                    publishers[VEHICLE_TOPIC] = session.declare_publisher(key(self.id, VEHICLE_TOPIC))
                if self.gnss is not None:   # truth: a key outside every agent's subscriptions
                    publishers["truth/gnss"] = session.declare_publisher(gnss_truth_key(self.id))
                # the agent's commands only where something drives: a GNSS tag (or a GNSS-only driver beside an
                # autopilot's) would count commands it has no use for as refused
                listening = [] if self.thrusters is None and link is None else [
                    session.declare_subscriber(key(self.id, "cmd"), self._on_command),
                    session.liveliness().declare_subscriber(key(self.id, LIVELINESS), self._on_agent_liveliness,
                                                            history=True)]
                if self.settings.clock == "sim":
                    listening.append(session.declare_subscriber(CLOCK_KEY, self._on_sim_clock))
                period = (1.0 / self.settings.thrusters.lines_per_second() if self.thrusters
                          else VEHICLE_PERIOD if link else 0.1)
                waits = list(readers) + ([link.fd, self._wake[0]] if link else [])
                next_drive = time.monotonic()
                while not self.stopping.is_set():
                    if max_seconds is not None and time.monotonic() - started > max_seconds:
                        break
                    ready, _, _ = select.select(waits, [], [], max(0.0, next_drive - time.monotonic()))
                    for port in ready:   # a serial port, or the autopilot's link or wake-up pipe (descriptors)
                        if link is not None and port == link.fd:
                            self._on_mavlink(link, publishers)
                            continue
                        if self._wake is not None and port == self._wake[0]:
                            os.read(port, 4096)
                            self._drive_vehicle(link, time.monotonic(), publishers)
                            continue
                        data = self._read(port, readers[port])
                        if data:
                            handlers[readers[port]](data, publishers)
                    self.report_refusals(time.monotonic())
                    if time.monotonic() >= next_drive:
                        next_drive += period
                        if self.thrusters:
                            self._drive(ports["thrusters"], time.monotonic())
                        elif link is not None:
                            self._drive_vehicle(link, time.monotonic(), publishers)
                if link is not None:   # leave the boat stopped and holding, as the thrusters' last line does
                    for msg in self.vehicle.stop(time.monotonic()):
                        self._guarded("mavlink", link.send, msg)
                if "thrusters" in ports:   # stopped before Zenoh's teardown, which might not end by the deadline
                    ports["thrusters"].write(command_line(ZERO_THRUST))
                for entity in listening:
                    entity.undeclare()
        finally:
            try:
                if "thrusters" in ports:
                    ports["thrusters"].write(command_line(ZERO_THRUST))   # leave the boat stopped
            finally:
                for port in ports.values():
                    port.close()
                if link is not None:
                    link.close()
                if self.gnss_log is not None:
                    self.gnss_log.close()
                if self._wake is not None:
                    for fd in self._wake:
                        os.close(fd)
                    self._wake = None

    def _read(self, port, name: str) -> bytes:
        """What `port` has, or an OSError that names the device: one that vanished (unplugged) reports
        itself ready and then has nothing, or fails the read (pyserial raises either way)."""
        try:
            return port.read(4096)
        except OSError as error:
            device = getattr(self.settings, name).device
            raise OSError(f"lost {DEVICES[name]} ({name}.device {device}): {error}") from None

    def _open_vehicle(self, ports: dict):
        """The autopilot's link and its MavlinkVehicle, or None without `mavlink`; OSError naming it if not."""
        s = self.settings.mavlink
        if s is None:
            return None
        try:
            link = open_link(s.url, s.baud, s.own_system, s.own_component)
        except (MissingExtra, OSError, ValueError) as error:
            for port in ports.values():
                port.close()
            text = str(error) if isinstance(error, MissingExtra) else (
                f"cannot open the autopilot's link (mavlink.url {s.url}): {getattr(error, 'strerror', None) or error}")
            raise OSError(text) from None
        self._wake = os.pipe()
        for fd in self._wake:
            os.set_blocking(fd, False)
        self.vehicle = MavlinkVehicle(s, link.mav, self.id, lambda line: self._report(f"usv-driver {self.id}: {line}"))
        return link


def main(argv: list[str] | None = None) -> int:
    started = vessel_process("usv-driver", "The driver bridge of one vessel.", DriverSettings, argv, lambda parser:
                             parser.add_argument("--seconds", type=float, default=None,
                                                 help="stop after this long (tests)"), config_required=True)
    if isinstance(started, int):
        return started
    args, settings = started
    try:
        libraries()
    except ImportError as error:   # the `driver` extra: one line, not a traceback
        print(f"usv-driver: {error}", file=sys.stderr)
        return 1
    bridge = DriverBridge(args.vessel, settings)
    # Within systemd's TimeoutStopSec (5 s, deploy/systemd/usv-driver@.service), so that a hang is seen in stacks.
    stop_on_signals(bridge.stopping, deadline=4.0)
    try:
        bridge.run(args.seconds)
    except OSError as error:
        print(f"usv-driver: {error}", file=sys.stderr)
        return 1
    counts = {"published": dict(bridge.published), "refused": dict(bridge.refused)} | bridge.refusals()
    if bridge.gnss is not None and bridge.gnss.passed_over:
        counts["gnss_other_sentences"] = bridge.gnss.passed_over
    if bridge.thrusters is not None and bridge.thrusters.events:
        counts["thruster_events"] = dict(bridge.thrusters.events)
    if bridge.vehicle is not None:
        counts["mavlink_sent"] = dict(bridge.vehicle.sent)
        counts["mavlink_events"] = dict(bridge.vehicle.events)
    print(f"usv-driver {args.vessel}: stopped; {counts}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
