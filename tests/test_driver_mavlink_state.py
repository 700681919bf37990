"""The autopilot's state for the agent's status, ACRO sticks for a boat without GNSS, and ODOMETRY (#331):
driver_bridge/mavlink_vehicle.py, mavlink_odometry.py and the stand-in, in process over real MAVLink 2 bytes.
Hand-worked values: ArduPilot Rover's MANUAL_CONTROL (y steering, z throttle, -1000..1000 over the RC range,
GCS_MAVLink_Rover.cpp) and ACRO (steering x ACRO_TURN_RATE, positive clockwise, mode_acro.cpp)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from test_driver_mavlink import autopilot, heartbeat, sent, vehicle, wire

from agent.contract import Status, VehicleState, decode, encode
from agent.shell.gate import InputGate
from driver_bridge.mavlink_odometry import odometry_pose, quaternion_yaw
from sim_bridge.ardupilot_standin import Standin

MANUAL, ACRO, HOLD, GUIDED = 0, 1, 4, 15
NOW_NS = 1_700_000_000 * 10**9


def to_standin(messages, system: int = 255) -> list:
    """What the driver sends, as the stand-in receives it from a sender with system id `system`."""
    return wire(messages, system, 191)


# ----- the state the agent's status carries -----
def test_the_state_is_published_on_each_change_and_once_a_second_and_says_the_link_lost():
    adapter, _ = vehicle()
    first = adapter.state(NOW_NS, 0.0)
    assert (first.mode, first.armed, first.linked, first.control, first.refused) == ("", False, False, "guided", 0)
    assert adapter.state(NOW_NS, 0.5) is None                      # nothing changed, within a second
    adapter.receive(heartbeat(MANUAL, False), NOW_NS, 0.6)
    changed = adapter.state(NOW_NS + 1, 0.6)                       # the heartbeat: at once
    assert (changed.mode, changed.armed, changed.linked, changed.seq) == ("MANUAL", False, True, 1)
    assert adapter.state(NOW_NS, 1.0) is None and adapter.state(NOW_NS, 1.6).mode == "MANUAL"   # a second on
    adapter.receive(heartbeat(GUIDED, True), NOW_NS, 1.7)
    assert (adapter.state(NOW_NS, 1.7).mode, adapter.state(NOW_NS, 2.8).armed) == ("GUIDED", True)
    adapter.tick(NOW_NS, 1.7 + 3.1)                                # no heartbeat for link_timeout (3 s)
    lost = adapter.state(NOW_NS, 4.8)
    assert (lost.mode, lost.linked) == ("GUIDED", False)
    # It is a contract message: it round-trips, and a status carries it only when there is one.
    assert decode(VehicleState, encode(lost))[0] == lost
    bare = Status(stamp_ns=5, seq=0, sender="1", phase=0.0, command=(0.0, 0.0))
    assert "vehicle" not in json.loads(encode(bare))
    carried = bare.model_copy(update={"vehicle": lost})
    assert decode(Status, encode(carried))[0].vehicle == lost


def test_the_agent_gate_keeps_its_own_vehicle_state_and_refuses_anothers():
    gate = InputGate("1", known_peers=lambda: {"2"})
    state = VehicleState(stamp_ns=NOW_NS, seq=0, sender="1", mode="ACRO", armed=True, linked=True, control="acro")
    assert gate.offer("usv/1/sensor/vehicle", encode(state), NOW_NS * 1e-9)
    assert gate.vehicle() == state
    other = state.model_copy(update={"sender": "2"})
    assert not gate.offer("usv/2/sensor/vehicle", encode(other), NOW_NS * 1e-9)
    assert not gate.offer("usv/1/sensor/vehicle", b'{"mode": "GUIDED"}', NOW_NS * 1e-9)
    assert gate.rejected["unexpected_key"] == 1 and gate.rejected["malformed"] == 1 and gate.vehicle() == state
    assert gate.snapshot(NOW_NS * 1e-9).odometry is None          # a tick reads nothing of it


def test_usv_op_shows_the_autopilot_column():
    from usv_op.cli import autopilot as column
    from usv_op.cli import status_lines
    state = VehicleState(stamp_ns=10**9, seq=0, sender="1", mode="GUIDED", armed=True, linked=True, control="guided")
    status = Status(stamp_ns=10**9, seq=0, sender="1", phase=0.0, command=(0.0, 0.0), vehicle=state)
    assert column(status) == "GUIDED armed"
    assert column(status.model_copy(update={"stamp_ns": 6 * 10**9})) == "GUIDED armed (5 s)"
    assert column(status.model_copy(update={"vehicle": state.model_copy(update={"linked": False})})) == "link lost"
    assert column(status.model_copy(update={"vehicle": None})) == "-"
    assert status_lines({"1": (9.9, status)}, {"1"}, now=10.0)[1].split()[7:9] == ["GUIDED", "armed"]


def standin(**settings) -> Standin:
    return Standin(mavlink2.MAVLink(None, srcSystem=1, srcComponent=1), clock=lambda: 0.0, **settings)


def commands(adapter, start: float, seconds: float, mode: int, ack: int | None = None) -> None:
    """The agent's commands at 10 Hz from `start`, the autopilot's heartbeat saying `mode` (armed) each
    second, and (`ack`) a COMMAND_ACK of the mode with that result each second."""
    for k in range(round(seconds * 10)):
        t = start + 0.1 * k
        adapter.command(1.0, 0.0, t)
        adapter.tick(0, t)
        if k % 10 == 5:
            adapter.receive(heartbeat(mode, True), 0, t)
        if ack is not None and k % 10 == 1:
            adapter.receive(wire([autopilot().command_ack_encode(176, ack)])[0], 0, t)


# ----- refusals: one line each, counted -----
def test_a_mode_not_entered_is_one_line_counted_and_said_again_after_it_was_entered_once():
    adapter, said = vehicle()
    adapter.receive(heartbeat(MANUAL, True), 0, 0.0)
    commands(adapter, 0.0, 8.0, MANUAL, ack=0)           # accepted, and yet the heartbeats say MANUAL
    lines = [line for line in said if "did not enter" in line]
    assert lines == ["the autopilot did not enter GUIDED (MANUAL 3 s after asking)"]
    assert adapter.rejected["mode_not_entered"] == 2     # at 3 s and 6 s
    adapter.receive(heartbeat(GUIDED, True), 0, 8.1)     # entered; then pushed out (a pilot's switch)
    adapter.receive(heartbeat(HOLD, True), 0, 9.2)
    commands(adapter, 9.3, 4.0, HOLD)
    assert [line for line in said if "did not enter" in line][1:] == [
        "the autopilot did not enter GUIDED (HOLD 3 s after asking)"]
    assert adapter.state(0, 13.5).refused == 3


def test_a_refused_mode_is_said_once_and_not_again_as_not_entered():
    adapter, said = vehicle()
    adapter.receive(heartbeat(MANUAL, True), 0, 0.0)
    commands(adapter, 0.0, 5.0, MANUAL, ack=4)           # MAV_RESULT_FAILED each second
    assert len([line for line in said if "refused mode" in line or "did not enter" in line]) == 1
    assert adapter.rejected["mode_refused"] == 5 and adapter.rejected["mode_not_entered"] == 1


def test_a_disarmed_vehicle_is_one_line_and_each_command_it_ignores_is_counted():
    adapter, said = vehicle()
    adapter.receive(heartbeat(GUIDED, False), 0, 0.0)
    for k in range(5):
        adapter.command(1.0, 0.0, 0.1 * k)
        adapter.tick(0, 0.1 * k)
    assert [line for line in said if "disarmed:" in line] == [
        "the vehicle is disarmed: the agent's commands move nothing until it is armed (from the ground station, "
        "or mavlink.arm: true)"]
    assert adapter.rejected["commands_while_disarmed"] == 5


# ----- ACRO: the GNSS-denied path -----
def test_acro_sends_manual_control_sticks_by_the_stated_mapping():
    """full_throttle_speed 2 m/s, ACRO_TURN_RATE 90 deg/s: u 1 m/s is half throttle, z 500; r 0.5 rad/s
    counter-clockwise is steering -0.5 / (pi/2) = -0.3183 (left), y -318; beyond them, full deflection."""
    adapter, _ = vehicle(control="acro", own_system=255, full_throttle_speed=2.0, acro_turn_rate=90.0)
    adapter.receive(heartbeat(MANUAL, True), 0, 0.0)
    adapter.command(1.0, 0.5, 0.0)
    out = adapter.tick(0, 0.0)
    (mode,) = [m for m in sent(out, "COMMAND_LONG") if m.command == 176]
    assert mode.param2 == ACRO and not sent(out, "SET_POSITION_TARGET_LOCAL_NED")
    (sticks,) = sent(out, "MANUAL_CONTROL")
    assert (sticks.target, sticks.x, sticks.y, sticks.z, sticks.r) == (1, 0, -318, 500, 0)
    for (u, r), (y, z) in {(5.0, -10.0): (1000, 1000), (-1.0, 0.0): (0, -500), (0.0, 0.0): (0, 0)}.items():
        adapter.command(u, r, 0.1)
        (sticks,) = sent(adapter.tick(0, 0.1), "MANUAL_CONTROL")
        assert (sticks.y, sticks.z) == (y, z)
    stop = sent(adapter.stop(0.2), "MANUAL_CONTROL") + sent(adapter.stop(0.2), "COMMAND_LONG")
    assert (stop[0].y, stop[0].z, stop[1].command, stop[1].param2) == (0, 0, 176, HOLD)


def test_a_boat_without_a_position_refuses_guided_takes_acro_and_its_sticks_move_it():
    boat = standin(position=False, acro_turn_rate=90.0, full_throttle_speed=2.0)
    driver, _ = vehicle(control="acro", own_system=255, full_throttle_speed=2.0, acro_turn_rate=90.0)
    ask = lambda mode: to_standin([driver._long(176, 1, mode)])[0]   # noqa: E731
    assert boat.receive(ask(GUIDED), 0.0)[0].result == 4 and boat.receive(ask(ACRO), 0.0)[0].result == 0
    boat.receive(to_standin([driver._long(400, 1)])[0], 0.0)
    boat.receive(to_standin([driver.drive(1.0, 0.5, 0.0)])[0], 0.0)
    boat.step(0.0)
    assert boat.u == 1.0 and boat.r == pytest.approx(0.318 * math.pi / 2)   # -(-0.318) x 90 deg/s
    for t in np.arange(0.01, 2.0 + 1e-9, 0.01):
        boat.step(float(t))
    assert math.hypot(boat.east, boat.north) == pytest.approx(2 / boat.r * math.sin(boat.r), rel=1e-6)  # the chord
    # The sticks centre after RC_OVERRIDE_TIME (3 s) without a new one; another system's are refused.
    boat.step(3.5)
    assert (boat.u, boat.r) == (0.0, 0.0) and boat.counts["override_timeout"] == 1
    boat.receive(wire([driver.drive(1.0, 0.0, 0.0)], 1, 191)[0], 3.6)
    assert boat.counts["manual_control_refused"] == 1
    # Without a position estimate it sends no position (LOCAL_POSITION_NED, ODOMETRY), its attitude still.
    kinds = {m.get_type() for m in wire(boat.step(5.0) + boat.step(5.3))}
    assert "ATTITUDE" in kinds and not kinds & {"LOCAL_POSITION_NED", "ODOMETRY"}


# ----- ODOMETRY (#331) -----
def yaw_quaternion(yaw: float, roll: float = 0.0) -> list[float]:
    """(w, x, y, z) of a yaw about the frame's third axis after a roll about the body's first."""
    cy, sy, cr, sr = math.cos(yaw / 2), math.sin(yaw / 2), math.cos(roll / 2), math.sin(roll / 2)
    return [cy * cr, cy * sr, sy * sr, sy * cr]


def test_odometry_frames_by_hand():
    """A boat 3 m north and 4 m east, heading 30 deg clockwise from north (60 deg counter-clockwise from
    east), turning clockwise at 0.1 rad/s: said in LOCAL_NED with a FRD body, and in LOCAL_ENU with FLU."""
    d30 = math.radians(30)
    ned = odometry_pose(1, 12, 3.0, 4.0, yaw_quaternion(d30), 0.1)
    enu = odometry_pose(4, 21, 4.0, 3.0, yaw_quaternion(math.radians(60)), -0.1)
    for pose in (ned, enu):
        north, east, yaw, rate = pose
        assert (north, east) == (3.0, 4.0)
        assert yaw == pytest.approx(d30, abs=1e-12) and rate == pytest.approx(-0.1)
    assert quaternion_yaw(*yaw_quaternion(d30, roll=math.radians(10))) == pytest.approx(d30, abs=1e-12)
    assert odometry_pose(1, 8, 0, 0, yaw_quaternion(-3.0), 0.2)[2:] == pytest.approx((-3.0, -0.2))
    assert odometry_pose(20, 12, 0, 0, [1, 0, 0, 0], 0) == "odometry_frame"     # LOCAL_FRD: no common heading
    assert odometry_pose(1, 30, 0, 0, [1, 0, 0, 0], 0) == "odometry_frame"
    assert odometry_pose(1, 12, 0, 0, [2, 0, 0, 0], 0) == "odometry_quaternion"
    assert odometry_pose(1, 12, math.nan, 0, [1, 0, 0, 0], 0) == "non_finite"


def test_the_standins_odometry_through_the_adapter_gives_the_agents_odometry():
    """The stand-in asked for ODOMETRY (and nothing else) by SET_MESSAGE_INTERVAL; the adapter set to read it
    gives heading pi/2 - yaw and the path from the first position, stamped through TIMESYNC; a reset of the
    estimate (reset_counter) goes on from the last position."""
    t0 = 100.0
    boat = Standin(mavlink2.MAVLink(None, srcSystem=1, srcComponent=1), clock=lambda: t0, guid_timeout=100.0)
    adapter, _ = vehicle(odometry="odometry")

    def vessel_ns(t: float) -> int:   # the vessel's clock: NOW_NS at the stand-in's boot
        return NOW_NS + round((t - t0) * 1e9)

    adapter.receive(wire(boat.step(t0 + 0.01))[0], vessel_ns(t0 + 0.01), t0 + 0.01)   # its heartbeat: linked
    asks = [m for m in sent(adapter.tick(vessel_ns(t0 + 0.01), t0 + 0.01), "COMMAND_LONG") if m.command == 511]
    assert [m.param1 for m in asks] == [331]
    for ask in asks:
        assert boat.receive(to_standin([ask], 1)[0], t0 + 0.01)[0].result == 0
    adapter.offset_ns = NOW_NS                          # what a TIMESYNC of no delay measures
    boat.mode, boat.armed, boat.setpoint = GUIDED, True, (1.0, -0.2, t0)
    odometry, kinds = [], set()
    for t in np.arange(t0 + 0.02, t0 + 3.0, 0.01):
        for msg in wire(boat.step(float(t))):
            got = adapter.receive(msg, vessel_ns(float(t)) + 1, float(t))
            if got is not None:
                kinds.add(msg.get_type())
                odometry.append((got, boat.east, boat.north, boat.yaw))
    assert len(odometry) >= 25 and kinds == {"ODOMETRY"}   # LOCAL_POSITION_NED still comes, and is not used
    first = odometry[0]
    for got, east, north, yaw in odometry:
        assert got.heading == pytest.approx(math.remainder(math.pi / 2 - yaw, 2 * math.pi), abs=1e-6)
        assert got.position[0] == pytest.approx(east - first[1], abs=1e-5)
        assert got.position[1] == pytest.approx(north - first[2], abs=1e-5)
    assert odometry[-1][0].heading - odometry[0][0].heading == pytest.approx(-0.2 * 2.9, abs=0.03)
    # A reset of the estimate: 50 m away on the wire, the path goes on from the last position.
    last = odometry[-1][0]
    unknown = [math.nan] + [0.0] * 20
    msg = autopilot().odometry_encode(3_100_000, 1, 12, 50.0, 50.0, 0.0, yaw_quaternion(0.3), 0, 0, 0, 0, 0, 0,
                                      unknown, unknown, 1)
    got = adapter.receive(wire([msg])[0], vessel_ns(t0 + 3.1) + 1, t0 + 3.1)
    assert got.position == pytest.approx(last.position) and adapter.events["estimate_reset"] == 1


def test_any_odometry_message_is_taken_within_the_contract_or_refused_and_counted():
    """ODOMETRY with fields anywhere their wire types allow (NaN, infinities, 3.4e38, any frame, any
    quaternion, any time): never an exception, and whatever is taken is valid odometry (the contract's model
    checks it as it is made)."""
    rng = np.random.default_rng(331)
    adapter, _ = vehicle(odometry="odometry")
    adapter.receive(heartbeat(GUIDED, True), NOW_NS, 0.0)
    adapter.offset_ns = NOW_NS
    ap = autopilot()
    special = (math.nan, math.inf, -math.inf, 3.4e38, -3.4e38, 0.0, 1.0)

    def f() -> float:
        return float(rng.choice(special)) if rng.random() < 0.2 else float(rng.normal(0.0, 10.0 ** rng.integers(0, 5)))

    taken = 0
    for k in range(3000):
        q = [f() for _ in range(4)] if rng.random() < 0.5 else yaw_quaternion(float(rng.uniform(-10, 10)))
        frame = int(rng.choice([1, 4] if rng.random() < 0.8 else [20, 0, 8, 12, 21, 255]))
        child = int(rng.choice([1, 4, 8, 12, 20, 21] if rng.random() < 0.8 else [0, 2, 255]))
        time_usec = int(rng.choice([k * 10_000] * 4 + [int(rng.integers(0, 2**63)), 10**15 + k]))
        nan21 = [f() for _ in range(21)]
        msg = wire([ap.odometry_encode(time_usec, frame, child, f(), f(), f(), q, f(), f(), f(), f(), f(), f(),
                                       nan21, nan21, int(rng.integers(0, 256)))])[0]
        got = adapter.receive(msg, NOW_NS + k * 10_000_000, 0.01 * k)
        if got is not None:
            taken += 1
            assert all(math.isfinite(v) for v in (*got.position, got.heading))
        yaw_rate = adapter.yaw_rate()
        assert yaw_rate is None or math.isfinite(yaw_rate)
    refused = {k: v for k, v in adapter.rejected.items() if v}
    print(f"ODOMETRY fuzz: {taken} taken, refused {refused}")
    assert taken > 0 and {"odometry_frame", "non_finite", "odometry_quaternion"} <= set(refused), refused
