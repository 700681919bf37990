"""The autopilot's state and the GNSS-denied path as processes: `usv-ardupilot-standin`, `usv-driver`, an agent
(a script, or `usv-agent` itself) and `usv-op status`, over real UDP and Zenoh."""

from __future__ import annotations

import math
import os
import pty
import signal
import subprocess
import sys
import time

import pytest
import yaml
import zenoh
from conftest import wait_until
from test_driver_mavlink_process import AGENT, kill_left, records, stop

from agent.contract import Status, VehicleState, decode
from agent.runtime.zenoh_session import ZenohSettings, zenoh_config
from sim_bridge.fleet import free_port

pytestmark = pytest.mark.slow   # three or four processes, UDP and Zenoh

TURN_RATE = 45.0   # deg/s: the stand-in's ACRO_TURN_RATE and the driver's acro_turn_rate


def standin(udp: int, record, *flags: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "sim_bridge.ardupilot_standin", "--listen", f"udpin:127.0.0.1:{udp}",
                             "--record", str(record), *flags], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def driver(config) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "driver_bridge", "--vessel", "1", "--config", str(config)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_without_a_position_acro_sticks_drive_the_boat_and_the_state_says_acro_armed(tmp_path):
    """GNSS-denied: the stand-in with --no-position refuses GUIDED and sends no position; the driver set to
    `control: acro` (odometry from a speed log's port, silent here) asks for ACRO, arms it and sends the
    agent's (u, r) as MANUAL_CONTROL; the hull moves at u and turns at r; the agent's death puts it in HOLD."""
    udp, zenoh_port = free_port(), free_port()
    record = tmp_path / "standin.jsonl"
    master, slave = pty.openpty()   # the speed log's port: the odometry of a boat without GNSS
    config = tmp_path / "driver.yaml"
    config.write_text(yaml.safe_dump({
        "zenoh": {"listen": [f"tcp/127.0.0.1:{zenoh_port}"]}, "odometry": {"device": os.ttyname(slave)},
        "mavlink": {"url": f"udpout:127.0.0.1:{udp}", "arm": True, "control": "acro", "own_system": 255,
                    "odometry": "none", "full_throttle_speed": 2.0, "acro_turn_rate": TURN_RATE}}))
    boat = standin(udp, record, "--no-position", "--acro-turn-rate", str(TURN_RATE), "--full-throttle-speed", "2")
    bridge = driver(config)
    agent = None
    states: list[VehicleState] = []

    def on_state(sample) -> None:
        message, reason = decode(VehicleState, sample.payload.to_bytes())
        assert message is not None, reason
        states.append(message)

    try:
        with zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{zenoh_port}"]))) as session:
            session.declare_subscriber("usv/1/sensor/vehicle", on_state)
            assert wait_until(lambda: any(s.linked for s in states), 30), states[-3:]
            agent = subprocess.Popen([sys.executable, "-c", AGENT, f"tcp/127.0.0.1:{zenoh_port}"],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, text=True)

            def taken() -> list[dict]:
                return [r for r in records(record) if r["kind"] == "sticks" and r["mode"] == "ACRO" and r["u"] > 0]

            assert wait_until(lambda: len(taken()) >= 40, 60), records(record)[-5:]
            assert wait_until(lambda: states[-1].mode == "ACRO" and states[-1].armed, 10), states[-3:]
            agent.send_signal(signal.SIGKILL)
            killed = time.monotonic()
            assert wait_until(lambda: any(r["kind"] == "mode" and r["mode"] == "HOLD" and r["t"] > killed
                                          for r in records(record)), 10), records(record)[-5:]
            assert wait_until(lambda: states[-1].mode == "HOLD", 5), states[-3:]
        driver_output, standin_output = stop(bridge, boat)
    finally:
        kill_left(agent, bridge, boat)
        os.close(master)
        os.close(slave)
    assert bridge.returncode == 0 and boat.returncode == 0, (driver_output, standin_output)
    assert "Traceback" not in driver_output and "refused mode" not in driver_output, driver_output
    log = records(record)
    hold = next(r["t"] for r in log if r["kind"] == "mode" and r["mode"] == "HOLD" and r["t"] > killed)
    assert hold - killed < 1.0
    assert [r["mode"] for r in log if r["kind"] == "mode"][:1] == ["ACRO"]
    assert not [r for r in log if r["kind"] == "mode_refused"]          # GUIDED never asked for
    # The stated mapping: u 1 m/s is half throttle (exactly 1 m/s back); r_k = 0.2 + 1e-4 (k mod 50) rad/s
    # within one step of the stick (1/1000 of ACRO_TURN_RATE).
    moving = [r for r in log if r["kind"] == "sticks" and r["mode"] == "ACRO" and r["u"] > 0]
    step = math.radians(TURN_RATE) / 1000
    assert all(r["u"] == 1.0 and 0.2 - step <= r["r"] <= 0.2049 + step for r in moving), moving[:3]
    # The hull moved as commanded: along its path at u, between the first and the last sticks taken.
    path = sum(math.dist((a["east"], a["north"]), (b["east"], b["north"])) for a, b in zip(moving, moving[1:]))
    span = moving[-1]["t"] - moving[0]["t"]
    assert path == pytest.approx(1.0 * span, rel=0.1), (path, span)
    print(f"ACRO: {len(moving)} sticks over {span:.1f} s, hull path {path:.2f} m at u = 1 m/s; HOLD "
          f"{hold - killed:.3f} s after SIGKILL")
    assert {s.control for s in states} == {"acro"} and max(s.refused for s in states) == 0


def test_the_agents_status_carries_the_autopilots_state_and_usv_op_shows_it(tmp_path):
    """A real `usv-agent` (wall clock) beside the driver and the stand-in: its status repeats the vehicle's
    state, and `usv-op status --once` prints it in the autopilot column."""
    udp, zenoh_port = free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{zenoh_port}"
    agent_config = tmp_path / "agent.yaml"
    agent_config.write_text(f"clock: wall\nzenoh:\n  listen: [{endpoint}]\n")
    config = tmp_path / "driver.yaml"
    config.write_text(yaml.safe_dump({"zenoh": {"connect": [endpoint]},
                                      "mavlink": {"url": f"udpout:127.0.0.1:{udp}", "arm": True}}))
    agent = subprocess.Popen([sys.executable, "-m", "agent", "--vessel", "1", "--config", str(agent_config)],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    boat = standin(udp, tmp_path / "standin.jsonl")
    bridge = driver(config)
    statuses: list[Status] = []
    try:
        with zenoh.open(zenoh_config(ZenohSettings(connect=[endpoint]))) as session:
            session.declare_subscriber("usv/1/status", lambda s: statuses.append(decode(Status, s.payload.to_bytes())[0]))
            assert wait_until(lambda: any(s.vehicle is not None and s.vehicle.mode == "GUIDED" and s.vehicle.armed
                                          for s in statuses if s is not None), 60), statuses[-1:]
        console = subprocess.run([sys.executable, "-m", "usv_op", "--connect", endpoint, "status", "--once"],
                                 capture_output=True, text=True, timeout=60, check=False)
        agent.send_signal(signal.SIGTERM)
        agent_output = agent.communicate(timeout=20)[0]
        driver_output, _ = stop(bridge, boat)
    finally:
        kill_left(agent, bridge, boat)
    assert console.returncode == 0, console.stderr
    header, line = console.stdout.splitlines()[:2]
    assert "autopilot" in header and line.startswith("1 ") and " GUIDED armed " in line, console.stdout
    assert agent.returncode == 0 and "Traceback" not in agent_output + driver_output, agent_output
    # The agent took the driver's state as its own input: nothing of it refused.
    vehicle = [s.vehicle for s in statuses if s is not None and s.vehicle is not None]
    assert {v.sender for v in vehicle} == {"1"} and vehicle[-1].control == "guided"
