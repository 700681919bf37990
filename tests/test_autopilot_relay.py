"""The pieces of `usv-fleet run --vehicle mavlink` in process: the lockstep rule (a stand-in drives the agent's
command, compared as the float32 the wire carries), the sim bridge's refusals of bad Drive messages, and a
relayed stand-in's pose through real MAVLink bytes into the driver's MavlinkVehicle, stamped on sim time."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from agent.contract import Cmd, encode
from driver_bridge.mavlink_vehicle import MavlinkSettings, MavlinkVehicle
from sim_bridge.ardupilot_standin import GUIDED, RELAY_BOOT_NS, Standin
from sim_bridge.autopilot_relay import Drive, as_sent, drives_command
from sim_bridge.bridge import BridgeSettings, SimBridge
from sim_bridge.scenario import select_scenario


def command(rng, surge=None) -> Cmd:
    return Cmd(stamp_ns=int(rng.integers(0, 10**12)), seq=0, sender="1",
               surge=float(rng.uniform(-5, 5)) if surge is None else surge, yaw_rate=float(rng.uniform(-1, 1)))


def test_a_tick_waits_until_the_standin_drives_that_command_as_the_wire_carries_it():
    rng = np.random.default_rng(31)
    for _ in range(500):
        cmd = command(rng)
        sent = as_sent(cmd)
        taken = Drive(stamp_ns=0, sender="1", setpoint=sent, drive=sent, mode="GUIDED", armed=True)
        assert drives_command(taken, cmd)
        # not GUIDED or not armed: the set point taken, the hull stopped
        stopped = taken.model_copy(update={"drive": (0.0, 0.0), "mode": "HOLD"})
        assert drives_command(stopped, cmd) == (sent == (0.0, 0.0))
        other = command(rng)
        assert drives_command(taken, other) == (as_sent(other) == sent)
        assert not drives_command(None, cmd)
        assert not drives_command(taken.model_copy(update={"setpoint": None}), cmd)
        # the float64 value itself is not what the wire carries (unless it is a float32 already)
        exact = Drive(stamp_ns=0, sender="1", setpoint=(cmd.surge, cmd.yaw_rate), drive=(cmd.surge, cmd.yaw_rate),
                      mode="GUIDED", armed=True)
        assert drives_command(exact, cmd) == ((cmd.surge, cmd.yaw_rate) == sent)


class Sample:
    def __init__(self, key: str, payload: bytes) -> None:
        self.key_expr, self._payload = key, payload

    @property
    def payload(self):
        return self

    def to_bytes(self) -> bytes:
        return self._payload


def test_the_bridge_refuses_and_counts_bad_drives_and_never_steps_on_a_non_finite_command(short_scenario):
    _, scenario = select_scenario(short_scenario, None)
    bridge = SimBridge(scenario, BridgeSettings(autopilots=["1", "2"]))
    rng = np.random.default_rng(7)
    good = Drive(stamp_ns=0, sender="1", setpoint=(1.0, 0.1), drive=(1.0, 0.1), mode="GUIDED", armed=True)
    bad = [b"", b"{}", b"\xff" * 40, b'{"stamp_ns": 0}', rng.integers(0, 256, 300, dtype=np.uint8).tobytes(),
           encode(good).replace(b"1.0,", b"NaN,"), encode(good).replace(b"1.0,", b"1e309,"),
           encode(good).replace(b"1.0,", b"1e4,")]
    bridge._on_drive(Sample("sim/autopilot/1/drive", encode(good)))
    for payload in bad:
        bridge._on_drive(Sample("sim/autopilot/1/drive", payload))
    bridge._on_drive(Sample("sim/autopilot/2/drive", encode(good)))   # vessel 1's Drive on vessel 2's key
    bridge._on_drive(Sample("sim/autopilot/3/drive", encode(good.model_copy(update={"sender": "3"}))))   # no stand-in
    assert bridge.rejected == len(bad) + 2
    assert set(bridge.drives) == {"1"} and bridge.drives["1"] == good
    commands = bridge._commands_now(0.0)
    assert (commands["1"].surge, commands["1"].yaw_rate) == (1.0, 0.1)
    assert (commands["2"].surge, commands["2"].yaw_rate) == (0.0, 0.0)   # no Drive yet: stopped
    assert all(math.isfinite(c.surge) and math.isfinite(c.yaw_rate) for c in commands.values())
    # A Drive older than the watchdog stops the vessel, as a command would.
    late = bridge._commands_now(bridge.settings.watchdog + 0.01)
    assert (late["1"].surge, late["1"].yaw_rate) == (0.0, 0.0)


def wire(messages, sender, receiver) -> list:
    """Messages encoded by `sender` as bytes, parsed back by `receiver` (pymavlink's own framing)."""
    out = []
    for message in messages:
        out += receiver.parse_buffer(message.pack(sender)) or []
    return out


def test_a_relayed_standin_gives_the_driver_the_sims_pose_stamped_on_sim_time():
    boat, computer = (mavlink2.MAVLink(None, srcSystem=1, srcComponent=1),
                      mavlink2.MAVLink(None, srcSystem=1, srcComponent=191))
    mono = 100.0
    standin = Standin(boat, relayed=True, clock=lambda: mono)
    standin.mode, standin.armed = GUIDED, True
    vehicle = MavlinkVehicle(MavlinkSettings(url="udpin:127.0.0.1:0"), computer, "1")
    # The driver's clock is the sim clock: 0 before the first tick. TIMESYNC: the stand-in's boot clock is it.
    requests = [m for m in vehicle.tick(0, mono) if m.get_type() == "TIMESYNC"]
    replies = standin.receive(wire(requests, computer, boat)[0], mono)
    for msg in wire(replies + standin.step(mono), boat, computer):
        vehicle.receive(msg, 0, mono)
    assert vehicle.offset_ns == -RELAY_BOOT_NS and vehicle.linked   # its heartbeat came with the reply
    rng = np.random.default_rng(3)
    east, north, heading = 3.0, -4.0, 0.3
    for k in range(50):
        stamp = k * 100_000_000
        east, north = east + rng.normal(0, 0.2), north + rng.normal(0, 0.2)
        heading = heading + rng.normal(0, 0.1)
        yaw = math.remainder(math.pi / 2 - heading, math.tau)
        (odometry,) = [o for o in (vehicle.receive(m, stamp, mono + k * 0.1)
                                   for m in wire(standin.pose(north, east, yaw, 0.0, stamp), boat, computer))
                       if o is not None]
        assert odometry.stamp_ns == stamp   # the tick's own stamp, sim time 0 included
        if k == 0:
            origin = (east, north)
        assert odometry.position == pytest.approx((east - origin[0], north - origin[1]), abs=1e-5)
        assert math.remainder(odometry.heading - heading, math.tau) == pytest.approx(0.0, abs=1e-6)
