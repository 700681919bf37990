"""The MAVLink vehicle adapter (driver_bridge/mavlink_vehicle.py) and the ArduPilot stand-in
(sim_bridge/ardupilot_standin.py), in process: every message goes through real MAVLink 2 bytes (pymavlink's
encoder and parser), no socket. ArduPilot's documented values are written here by hand from its page
"Rover Commands in Guided Mode" (ardupilot.org/dev/docs/mavlink-rover-commands.html)."""

from __future__ import annotations

import math
import os
import pty
import select
import subprocess
import sys
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from agent.contract import Bearing, Odometry, decode, encode
from driver_bridge.mavlink_link import MissingExtra, open_link
from driver_bridge.mavlink_vehicle import MavlinkSettings, MavlinkVehicle
from driver_bridge.node import DriverBridge, DriverSettings
from sim_bridge.ardupilot_standin import Standin

# From ArduPilot's page, by hand: "Use Vel+Yaw Rate : 0b010111100111 / 0x05E7 / 1511 (decimal)"; the frame
# "MAV_FRAME_BODY_NED (8)": velocities relative to the vehicle's heading; the custom modes of Rover/mode.h.
DOC_VELOCITY_YAW_RATE = 1511
DOC_BODY_NED = 8
GUIDED, HOLD = 15, 4


def wire(messages, system: int = 1, component: int = 1) -> list:
    """`messages` packed by a sender with these ids and parsed back, as the other end receives them."""
    sender = mavlink2.MAVLink(None, srcSystem=system, srcComponent=component)
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    data = b"".join(message.pack(sender) for message in messages)
    return parser.parse_buffer(data) or []


def autopilot(system: int = 1) -> mavlink2.MAVLink:
    return mavlink2.MAVLink(None, srcSystem=system, srcComponent=1)


def vehicle(**settings) -> tuple[MavlinkVehicle, list[str]]:
    said: list[str] = []
    made = MavlinkVehicle(MavlinkSettings(url="udpout:127.0.0.1:1", **settings),
                          mavlink2.MAVLink(None, srcSystem=1, srcComponent=191), "1", said.append)
    return made, said


def heartbeat(mode: int, armed: bool, system: int = 1):
    return wire([autopilot(system).heartbeat_encode(11, 3, 1 | (128 if armed else 0), mode, 4)], system)[0]


def sent(messages, kind: str) -> list:
    return [m for m in wire(messages, 1, 191) if m.get_type() == kind]


def test_the_set_point_is_ardupilots_velocity_and_yaw_rate_in_the_body_frame():
    """(u, r) = (1.5 m/s, 0.2 rad/s counter-clockwise) becomes vx 1.5, vy 0 and a yaw rate of -0.2 (ArduPilot's
    example: yaw_rate +0.174 'rotates clock-wise'), with the documented type mask and frame."""
    adapter, _ = vehicle()
    adapter.receive(heartbeat(GUIDED, True), 0, 0.0)
    adapter.command(1.5, 0.2, 0.0)
    (setpoint,) = sent(adapter.tick(1, 0.0), "SET_POSITION_TARGET_LOCAL_NED")
    assert setpoint.type_mask == DOC_VELOCITY_YAW_RATE == 0x05E7 == 0b010111100111
    assert setpoint.coordinate_frame == DOC_BODY_NED
    assert (setpoint.target_system, setpoint.target_component) == (1, 1)
    assert (setpoint.vx, setpoint.vy, setpoint.vz) == (1.5, 0.0, 0.0)
    assert setpoint.yaw_rate == pytest.approx(-0.2)
    # The same bits by MAVLink's own names (pymavlink's enum): positions, vz, accelerations and yaw ignored.
    names = {entry.name for bit, entry in mavlink2.enums["POSITION_TARGET_TYPEMASK"].items()
             if not entry.name.endswith("ENUM_END") and setpoint.type_mask & bit}
    assert names == {f"POSITION_TARGET_TYPEMASK_{n}_IGNORE" for n in ("X", "Y", "Z", "VZ", "AX", "AY", "AZ", "YAW")}


def test_each_command_goes_at_once_the_last_is_repeated_and_a_stale_one_becomes_a_stop():
    """Commands every 0.1 s for 0.5 s: one set point each, as they come; then none: the last repeated at
    min_rate_hz (2 Hz) until it is older than command_timeout (0.5 s), then zero."""
    adapter, _ = vehicle(min_rate_hz=2.0, command_timeout=0.5)
    adapter.receive(heartbeat(GUIDED, True), 0, 0.0)
    setpoints = []
    for t in np.round(np.arange(0.0, 2.0, 0.01), 2):
        if t <= 0.45 and round(t * 100) % 10 == 0:
            adapter.command(1.0 + t, 0.0, float(t))
        setpoints += [(t, m.vx) for m in sent(adapter.tick(0, float(t)), "SET_POSITION_TARGET_LOCAL_NED")]
    expected = [(t, pytest.approx(1.0 + t)) for t in (0.0, 0.1, 0.2, 0.3, 0.4)]
    expected += [(0.9, pytest.approx(1.4)), (1.4, 0.0), (1.9, 0.0)]    # 0.4 + 0.5 s: repeated; then stale
    assert setpoints == expected
    assert adapter.events["command_timeout"] == 1


def test_when_the_agent_leaves_the_vessel_gets_zero_velocity_then_hold():
    adapter, _ = vehicle()
    adapter.receive(heartbeat(GUIDED, True), 0, 0.0)
    adapter.command(2.0, 0.1, 0.0)
    adapter.tick(0, 0.0)
    adapter.agent_left(0.05)
    out = [m for t in np.arange(0.1, 0.5, 0.01) for m in wire(adapter.tick(0, float(t)), 1, 191)]
    kinds = [m.get_type() for m in out if m.get_type() != "HEARTBEAT" and m.get_type() != "TIMESYNC"]
    first_hold = next(k for k, m in enumerate(out) if m.get_type() == "COMMAND_LONG" and m.command == 176)
    setpoints = [m for m in out[:first_hold] if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
    assert setpoints and all(m.vx == 0.0 and m.yaw_rate == 0.0 for m in setpoints), kinds
    assert out[first_hold].param2 == HOLD and out[first_hold].param1 == 1   # custom mode HOLD
    # Once HOLD is seen, no more requests.
    adapter.receive(heartbeat(HOLD, True), 0, 0.6)
    later = [m for t in np.arange(0.6, 2.0, 0.05) for m in sent(adapter.tick(0, float(t)), "COMMAND_LONG")]
    assert later == []


def test_guided_and_arming_are_requested_while_commands_flow_and_a_refusal_is_one_line():
    adapter, said = vehicle(arm=True)
    adapter.receive(heartbeat(0, False), 0, 0.0)     # MANUAL, disarmed
    adapter.command(1.0, 0.0, 0.0)
    commands = sent(adapter.tick(0, 0.0), "COMMAND_LONG")
    assert {(m.command, m.param1, m.param2) for m in commands} >= {(176, 1.0, 15.0), (400, 1.0, 0.0)}
    for _ in range(3):
        ack = wire([autopilot().command_ack_encode(176, 4)])[0]   # MAV_RESULT_FAILED
        adapter.receive(ack, 0, 0.1)
    assert adapter.rejected["mode_refused"] == 3
    refusals = [line for line in said if "refused" in line]
    assert refusals == ["the autopilot refused mode (command 176): FAILED "
                        "(GUIDED needs a position estimate; without GNSS: mavlink.control acro, docs/boats.md)"]
    quiet, quiet_said = vehicle(arm=False)
    quiet.receive(heartbeat(GUIDED, False), 0, 0.0)
    quiet.command(1.0, 0.0, 0.0)
    quiet.tick(0, 0.0)
    quiet.tick(0, 0.5)
    assert sum("disarmed: the agent's commands move nothing" in line for line in quiet_said) == 1


def test_odometry_is_the_autopilots_state_on_the_vessels_clock():
    """TIMESYNC: our request stamped ts1 = 1000 s, the autopilot's boot clock 5 s, our clock 1000.002 s at the
    reply: offset = 1000.001 - 5 s. Then LOCAL_POSITION_NED at boot 6 s (3 m north, 4 m east) and 7 s (3 N,
    6 E) with the bow east (ATTITUDE yaw pi/2): 2 m east of the first, heading 0 (east), stamps mapped."""
    adapter, _ = vehicle(position_variance_per_m=0.01, heading_variance=0.002)
    adapter.receive(heartbeat(GUIDED, True), 0, 0.0)
    ap = autopilot()
    adapter.receive(wire([ap.timesync_encode(5_000_000_000, 1_000_000_000_000)])[0], 1_000_002_000_000, 0.0)
    assert adapter.offset_ns == 1_000_001_000_000 - 5_000_000_000
    adapter.receive(wire([ap.attitude_encode(5990, 0.0, 0.0, math.pi / 2, 0.0, 0.0, -0.1)])[0], 0, 0.1)
    arrival = 1_000_002_000_000 + 1_001_000_000   # each comes 1 ms after it was made
    first = adapter.receive(wire([ap.local_position_ned_encode(6000, 3.0, 4.0, 0.0, 0, 0, 0)])[0], arrival, 0.1)
    second = adapter.receive(wire([ap.local_position_ned_encode(7000, 3.0, 6.0, 0.0, 0, 0, 0)])[0],
                             arrival + 10**9, 0.2)
    assert first.position == (0.0, 0.0) and second.position == (pytest.approx(2.0), pytest.approx(0.0))
    assert first.stamp_ns == 6_000_000_000 + adapter.offset_ns
    assert second.stamp_ns - first.stamp_ns == 1_000_000_000
    assert second.heading == pytest.approx(0.0, abs=1e-6) and (first.seq, second.seq) == (0, 1)
    assert second.covariance == (pytest.approx(0.02), 0, 0, 0, pytest.approx(0.02), 0, 0, 0, 0.002)
    assert adapter.yaw_rate() == pytest.approx(0.1)   # ATTITUDE's yawspeed is clockwise


def test_a_lost_link_stops_odometry_and_is_said_once():
    adapter, said = vehicle(link_timeout=3.0)
    ap = autopilot()
    adapter.receive(heartbeat(GUIDED, True), 0, 0.0)
    adapter.receive(wire([ap.timesync_encode(1, 1)])[0], 2, 0.0)
    adapter.receive(wire([ap.attitude_encode(0, 0, 0, 0.0, 0, 0, 0)])[0], 0, 0.0)
    # The offset is 0: the autopilot's boot clock is ours; each message comes 1 ms after it was made.
    position = lambda ms, north: wire([ap.local_position_ned_encode(ms, north, 0, 0, 0, 0, 0)])[0]  # noqa: E731
    assert adapter.receive(position(10, 0), 11_000_000, 1.0) is not None
    for t in (3.5, 4.0, 5.0):
        adapter.tick(0, t)
    assert adapter.receive(position(4000, 1), 4_001_000_000, 5.0) is None
    assert sum("link lost" in line for line in said) == 1 and adapter.events["link_lost"] == 1
    adapter.receive(heartbeat(GUIDED, True), 0, 6.0)
    assert adapter.receive(position(6000, 1), 6_001_000_000, 6.0) is not None
    assert sum("link up" in line for line in said) == 2


def test_bad_mavlink_is_counted_and_refused_never_raised():
    """Garbage bytes, another system's heartbeats and a flood of the right one's, over seeded random runs:
    nothing raises, each is counted, and the real autopilot's state still gets through."""
    rng = np.random.default_rng(31)
    for _ in range(50):
        adapter, _ = vehicle()
        garbage = rng.integers(0, 256, size=int(rng.integers(1, 400)), dtype=np.uint8).tobytes()
        parser = mavlink2.MAVLink(None)
        parser.robust_parsing = True
        messages = parser.parse_buffer(garbage) or []
        for message in messages:
            adapter.receive(message, 0, 0.0)
        assert adapter.rejected["bad_data"] + adapter.rejected["wrong_system"] >= len(messages) > 0
        adapter.receive(heartbeat(GUIDED, True, system=7), 0, 1.0)   # not our autopilot
        assert adapter.mode is None and adapter.rejected["wrong_system"] >= 1
        for k in range(20):                                           # 20 in 0.1 s: 19 too many
            adapter.receive(heartbeat(GUIDED, True), 0, 2.0 + k * 0.005)
        assert adapter.rejected["heartbeat_flood"] == 19 and (adapter.mode, adapter.armed) == (GUIDED, True)


def test_the_driver_config_takes_mavlink_instead_of_the_thrusters_and_the_speed_log():
    settings = DriverSettings.model_validate({"mavlink": {"url": "udpin:0.0.0.0:14550"}})
    assert settings.mavlink.min_rate_hz == 2.0 and settings.mavlink.arm is False
    with pytest.raises(ValueError, match="mavlink drives the vessel: leave out thrusters"):
        DriverSettings.model_validate({"mavlink": {"url": "udpin:0.0.0.0:14550"},
                                       "thrusters": {"device": "/dev/null", "hull": {
                                           "max_thrust": 1, "half_beam": 1, "surge_drag": 1, "yaw_drag": 1}}})
    # The odometry is the autopilot's, or (GNSS-denied, mavlink.odometry none) the speed log's: exactly one.
    log = {"device": "/dev/null"}
    with pytest.raises(ValueError, match="give the odometry port exactly then"):
        DriverSettings.model_validate({"mavlink": {"url": "udpin:0.0.0.0:14550"}, "odometry": log})
    with pytest.raises(ValueError, match="give the odometry port exactly then"):
        DriverSettings.model_validate({"mavlink": {"url": "udpin:0.0.0.0:14550", "odometry": "none"}})
    denied = DriverSettings.model_validate({"mavlink": {"url": "udpin:0.0.0.0:14550", "odometry": "none",
                                                        "control": "acro"}, "odometry": log})
    assert denied.mavlink.control == "acro" and denied.odometry.device == "/dev/null"


def test_without_pymavlink_the_driver_says_so_in_one_line(tmp_path):
    """`usv-driver` with a mavlink vehicle where pymavlink is not installed (hidden from the child's imports)."""
    config = tmp_path / "driver.yaml"
    config.write_text("mavlink: {url: 'udpout:127.0.0.1:9'}\n")
    code = ("import sys; sys.modules['pymavlink'] = None\n"
            "from driver_bridge.node import main\n"
            f"sys.exit(main(['--vessel', '1', '--config', {str(config)!r}]))\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.strip() == ("usv-driver: the MAVLink vehicle needs pymavlink, in the optional extra "
                                     "'driver': pip install 'usv-circumnav[driver]'")


def test_a_serial_link_opens_through_pyserial_and_carries_mavlink_both_ways():
    """A serial autopilot (a pseudo-terminal here): pymavlink's mavutil opens it with the extra's pyserial."""
    master, slave = pty.openpty()
    link = open_link(os.ttyname(slave), 57_600, 255, 191)
    try:
        assert type(link.connection.port).__module__ == "serial.serialposix"
        os.write(master, autopilot().heartbeat_encode(11, 3, 1, GUIDED, 4).pack(autopilot()))
        got, deadline = [], time.monotonic() + 10.0
        while not got and time.monotonic() < deadline:
            if select.select([link.fd], [], [], 0.2)[0]:
                got = link.messages()
        assert [(m.get_type(), m.get_srcSystem(), m.custom_mode) for m in got] == [("HEARTBEAT", 1, GUIDED)]
        link.send(link.mav.heartbeat_encode(6, 8, 0, 0, 0))
        parser, seen, deadline = mavlink2.MAVLink(None), [], time.monotonic() + 10.0
        while not seen and time.monotonic() < deadline:
            if select.select([master], [], [], 0.2)[0]:
                seen = parser.parse_buffer(os.read(master, 4096)) or []
        assert [(m.get_type(), m.get_srcSystem(), m.get_srcComponent(), m.type) for m in seen] == [
            ("HEARTBEAT", 255, 191, 6)]
    finally:
        link.close()
        os.close(master)
        os.close(slave)


def test_a_serial_link_without_pyserial_is_one_line_naming_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "serial", None)   # mavutil imports pyserial only for a serial device
    master, slave = pty.openpty()
    try:
        with pytest.raises(MissingExtra, match=r"needs pyserial, in the optional extra 'driver': "
                                               r"pip install 'usv-circumnav\[driver\]'"):
            open_link(os.ttyname(slave), 57_600, 255, 191)
    finally:
        os.close(master)
        os.close(slave)


# ----- the stand-in -----
def standin(**options) -> Standin:
    clock = [0.0]
    made = Standin(mavlink2.MAVLink(None, srcSystem=1, srcComponent=1), clock=lambda: clock[0], **options)
    return made


def gcs() -> mavlink2.MAVLink:
    return mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)


def guided_and_armed(boat: Standin, now: float = 0.0) -> None:
    g = gcs()
    acks = [boat.receive(m, now) for m in wire([g.command_long_encode(1, 1, 176, 0, 1, GUIDED, 0, 0, 0, 0, 0),
                                                g.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)], 1, 191)]
    assert [m.result for ack in acks for m in ack] == [0, 0]


def setpoint(u: float, r: float, mask: int = DOC_VELOCITY_YAW_RATE, frame: int = DOC_BODY_NED, target: int = 1):
    return wire([gcs().set_position_target_local_ned_encode(0, target, 1, frame, mask, 0, 0, 0, u, 0, 0, 0, 0, 0,
                                                            0, -r)], 1, 191)[0]


def test_the_standin_turns_a_set_point_into_the_closed_form_arc():
    """u = 1 m/s, r = 0.2 rad/s counter-clockwise for 2 s from the origin, bow north: a circle of radius 5 about
    (-5, 0) east-north, 0.4 rad round it: east -5 + 5 cos 0.4, north 5 sin 0.4; NED yaw -0.4 (with r as the
    message's float32 carries it)."""
    boat = standin()
    guided_and_armed(boat)
    boat.receive(setpoint(1.0, 0.2), 0.0)
    for t in np.arange(0.0, 2.0 + 1e-9, 0.01):
        boat.step(float(t))
    r = float(np.float32(0.2))
    assert boat.east == pytest.approx(-1 / r + math.cos(2 * r) / r, abs=1e-9)
    assert boat.north == pytest.approx(math.sin(2 * r) / r, abs=1e-9)
    assert boat.yaw == pytest.approx(-2 * r, abs=1e-12)
    attitude = [m for m in wire(boat.step(2.25)) if m.get_type() == "ATTITUDE"]
    assert attitude and attitude[0].yawspeed == pytest.approx(-0.2)


def test_the_standin_stops_after_guid_timeout_and_refuses_what_ardupilot_would():
    boat = standin(guid_timeout=3.0)
    boat.receive(setpoint(1.0, 0.0), 0.0)                     # not GUIDED yet: ignored
    assert boat.counts["setpoint_not_guided"] == 1
    guided_and_armed(boat)
    boat.receive(setpoint(1.0, 0.0), 0.0)
    boat.step(2.9)
    assert boat.u == 1.0
    boat.step(3.1)
    assert boat.u == 0.0 and boat.counts["guided_timeout"] == 1
    boat.receive(setpoint(1.0, 0.0, mask=3580), 3.2)           # "Use Position": not modelled, counted
    boat.receive(setpoint(1.0, 0.0, target=9), 3.2)            # another vehicle's
    assert boat.counts["setpoint_unsupported"] == 1 and boat.counts["wrong_target"] == 1
    blind = standin(position=False)
    (ack,) = blind.receive(wire([gcs().command_long_encode(1, 1, 176, 0, 1, GUIDED, 0, 0, 0, 0, 0)], 1, 191)[0], 0)
    assert ack.result == 4 and blind.mode != GUIDED            # MAV_RESULT_FAILED


def random_float(rng: np.random.Generator) -> float:
    special = (math.nan, math.inf, -math.inf, 1e38, -1e38, 3.4e38, 0.0, -0.0, 1e-45)
    return float(rng.choice(special)) if rng.random() < 0.3 else float(rng.normal(0.0, 10.0 ** rng.integers(0, 6)))


def random_message(rng: np.random.Generator, ap: mavlink2.MAVLink, boot_ms: int):
    """One message of a kind the adapter reads, with fields anywhere their wire types allow."""
    kind = rng.integers(0, 6)
    f = lambda: random_float(rng)   # noqa: E731
    if kind == 0:
        return ap.heartbeat_encode(11, 3, int(rng.integers(0, 256)), int(rng.integers(0, 2**32)), 4)
    if kind == 1:
        return ap.attitude_encode(int(rng.integers(0, 2**32)), f(), f(), f(), f(), f(), f())
    if kind == 2:
        return ap.local_position_ned_encode(int(rng.integers(0, 2**32)), f(), f(), f(), f(), f(), f())
    if kind == 3:
        return ap.timesync_encode(int(rng.integers(-2**63, 2**63, dtype=np.int64)),
                                  int(rng.integers(-2**63, 2**63, dtype=np.int64)))
    if kind == 4:
        return ap.command_ack_encode(int(rng.choice([176, 400, 511, 0, 65535])), int(rng.integers(0, 256)))
    return ap.local_position_ned_encode(boot_ms, float(rng.normal(0, 50)),
                                        float(rng.normal(0, 50)), 0.0, 0.0, 0.0, 0.0)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_any_autopilot_input_gives_odometry_within_the_contract_and_finite_set_points(seed):
    """A seeded storm of garbage and of well-formed messages with any field values (NaN, infinities, 3.4e38,
    int64 extremes in TIMESYNC), good ones in between, and agent commands, some non-finite: nothing raises,
    every odometry message the adapter gives passes the contract's own checks once encoded and decoded, and
    every set point it sends is finite."""
    rng = np.random.default_rng(seed)
    adapter, _ = vehicle()
    ap = autopilot()
    published = setpoints = 0
    clock_ns = 1_700_000_000 * 10**9
    for step in range(3000):
        mono = step * 0.01
        now_ns = clock_ns + step * 10_000_000
        if step % 500 == 0:   # a good round trip now and then, so that odometry can flow
            adapter.receive(heartbeat(GUIDED, True), now_ns, mono)
            adapter.receive(wire([ap.timesync_encode(10**9 + step * 10**7, now_ns - 10**6)])[0], now_ns, mono)
        if rng.random() < 0.1:
            garbage = rng.integers(0, 256, size=int(rng.integers(1, 100)), dtype=np.uint8).tobytes()
            parser = mavlink2.MAVLink(None)
            parser.robust_parsing = True
            messages = parser.parse_buffer(garbage) or []
        else:
            messages = wire([random_message(rng, ap, 1000 + step * 10)])
        for message in messages:
            odometry = adapter.receive(message, now_ns, mono)
            if odometry is not None:
                decoded, reason = decode(Odometry, encode(odometry))
                assert decoded is not None, reason
                published += 1
        if rng.random() < 0.1:
            value = lambda: 1e300 if rng.random() < 0.05 else random_float(rng)   # noqa: E731
            adapter.command(value(), value(), mono)
        for message in sent(adapter.tick(now_ns, mono), "SET_POSITION_TARGET_LOCAL_NED"):
            assert math.isfinite(message.vx) and math.isfinite(message.yaw_rate)
            setpoints += 1
    assert published > 10 and setpoints > 10


def test_an_autopilot_reboot_pauses_odometry_until_a_new_offset_then_it_goes_on_from_where_it_was():
    """Offset 0; positions at boot 10 s (0 m north) and 11 s (1 m). The autopilot reboots: its next position
    is stamped 0.5 s since boot, 50 m north of a new EKF origin: refused, said, the offset dropped. A new
    TIMESYNC round trip (boot 0.6 s at our 12.099 s) gives offset 11.499 s; then 50 m and 52 m north of the
    new origin are 1 m and 3 m north on the same path, stamped after the last."""
    adapter, said = vehicle()
    ap = autopilot()
    position = lambda ms, north: wire([ap.local_position_ned_encode(ms, north, 0, 0, 0, 0, 0)])[0]  # noqa: E731
    adapter.receive(heartbeat(GUIDED, True), 0, 0.0)
    adapter.receive(wire([ap.timesync_encode(1, 1)])[0], 2, 0.0)
    adapter.receive(wire([ap.attitude_encode(0, 0, 0, 0.0, 0, 0, 0)])[0], 0, 0.0)
    before = [adapter.receive(position(ms, north), ms * 10**6 + 10**6, 0.5) for ms, north in ((10_000, 0),
                                                                                             (11_000, 1))]
    assert [o.position for o in before] == [(0.0, 0.0), (0.0, 1.0)]
    assert adapter.receive(position(500, 50), 12_001_000_000, 1.0) is None
    assert adapter.events["autopilot_rebooted"] == 1 and adapter.offset_ns is None
    assert sum("clock went back" in line for line in said) == 1
    adapter.receive(wire([ap.timesync_encode(600_000_000, 12_098_000_000)])[0], 12_100_000_000, 1.1)
    assert adapter.offset_ns == 11_499_000_000
    after = [adapter.receive(position(ms, north), ms * 10**6 + 11_500_000_000, 1.2) for ms, north in ((700, 50),
                                                                                                      (800, 52))]
    assert [o.position for o in after] == [(0.0, 1.0), (0.0, 3.0)]
    assert [o.stamp_ns for o in after] == [12_199_000_000, 12_299_000_000]
    assert after[0].stamp_ns > before[-1].stamp_ns and [o.seq for o in after] == [2, 3]


def test_the_standin_with_a_preset_drives_that_hull_through_its_inner_loop():
    """--preset otter: 1 m/s ahead (set points every second) from rest, bow north: after 30 s the Otter runs
    north at the commanded speed on a straight line; then 0.2 rad/s: it turns counter-clockwise (NED yaw
    falls, ATTITUDE's yawspeed negative); then no set point: GUID_TIMEOUT's stop brakes it."""
    boat = standin(preset="otter")
    guided_and_armed(boat)
    for second in range(30):
        boat.receive(setpoint(1.0, 0.0), float(second))
        for t in np.arange(second, second + 1, 0.02):
            boat.step(float(t))
    north, east, rate = boat.motion()
    assert north == pytest.approx(1.0, abs=0.03) and abs(east) < 1e-9 and abs(boat.east) < 1e-9
    assert boat.north > 20 and abs(boat.yaw) < 1e-9
    yaw = boat.yaw
    for second in range(30, 45):
        boat.receive(setpoint(1.0, 0.2), float(second))
        for t in np.arange(second, second + 1, 0.02):
            boat.step(float(t))
    assert boat.motion()[2] == pytest.approx(0.2, abs=0.02) and boat.yaw < yaw
    attitude = [m for m in wire(boat.step(45.3)) if m.get_type() == "ATTITUDE"]
    assert attitude and attitude[0].yawspeed < -0.15
    for t in np.arange(45.3, 70.0, 0.02):
        boat.step(float(t))
    assert boat.counts["guided_timeout"] == 1 and math.hypot(*boat.motion()[:2]) < 0.1


def test_stream_rates_are_asked_by_message_and_by_the_old_stream_groups_when_that_is_refused():
    """SET_MESSAGE_INTERVAL for ATTITUDE (30) and LOCAL_POSITION_NED (32) at 1e6 / stream_hz us; an
    autopilot older than ArduPilot 4.0 answers UNSUPPORTED: then REQUEST_DATA_STREAM for the POSITION (6)
    and EXTRA1 (10) groups at once, and said once."""
    adapter, said = vehicle(stream_hz=5.0)
    adapter.receive(heartbeat(0, False), 0, 0.0)
    asked = sent(adapter.tick(0, 0.0), "COMMAND_LONG")
    assert {(m.command, m.param1, m.param2) for m in asked} == {(511, 30.0, 200_000.0), (511, 32.0, 200_000.0)}
    adapter.receive(wire([autopilot().command_ack_encode(511, 3)])[0], 0, 0.1)
    groups = sent(adapter.tick(0, 0.1), "REQUEST_DATA_STREAM")
    assert {(m.req_stream_id, m.req_message_rate, m.start_stop) for m in groups} == {(6, 5, 1), (10, 5, 1)}
    assert [line for line in said if "refused" in line] == [
        "the autopilot refused stream (command 511): UNSUPPORTED; asking with REQUEST_DATA_STREAM"]


class FakeLink:
    """What the driver's loop reads from the autopilot's link: messages already parsed."""

    def __init__(self, messages: list) -> None:
        self.pending = messages

    def messages(self) -> list:
        out, self.pending = self.pending, []
        return out


class Sink:
    def __init__(self, topic: str, into: list) -> None:
        self.topic, self.into = topic, into

    def put(self, payload: bytes) -> None:
        self.into.append((self.topic, payload))


def test_the_driver_publishes_the_autopilots_odometry_and_bearings_take_its_heading():
    """DriverBridge with `mavlink` and a camera: the autopilot's state (bow east: ATTITUDE yaw pi/2) becomes
    usv/1/sensor/odom through the bridge's own handler, and a detection at the image centre then gives the
    bearing of a target due east: the unit vector from the target to the vessel points west."""
    settings = DriverSettings.model_validate({"mavlink": {"url": "udpout:127.0.0.1:9"}, "camera": {
        "device": "/dev/null", "camera": {"fx": 500.0, "cx": 320.0, "width": 640}}})
    now_ns = 1_700_000_000 * 10**9
    bridge = DriverBridge("1", settings, clock_ns=lambda: now_ns, report=lambda line: None)
    bridge.vehicle = MavlinkVehicle(settings.mavlink, mavlink2.MAVLink(None, 1, 191), "1")
    published: list = []
    publishers = {topic: Sink(topic, published) for topic in ("sensor/odom", "sensor/bearing", "sensor/uwb")}
    ap = autopilot()
    bridge._detection(b"DET,320,", publishers)
    assert published == [] and bridge.refused["bearing_without_heading"] == 1
    bridge._on_mavlink(FakeLink([heartbeat(GUIDED, True), wire([ap.timesync_encode(10**9, now_ns - 10**6)])[0],
                                 wire([ap.attitude_encode(1000, 0, 0, math.pi / 2, 0, 0, 0)])[0],
                                 wire([ap.local_position_ned_encode(1000, 0, 0, 0, 0, 0, 0)])[0]]), publishers)
    bridge._detection(b"DET,320,", publishers)
    (odom_topic, odom), (bearing_topic, bearing) = published
    assert odom_topic == "sensor/odom" and decode(Odometry, odom)[0].heading == pytest.approx(0.0, abs=1e-7)
    assert bearing_topic == "sensor/bearing"
    assert decode(Bearing, bearing)[0].bearing == (pytest.approx(-1.0), pytest.approx(0.0, abs=1e-7))
