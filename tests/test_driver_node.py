"""The driver bridge process end to end: serial byte streams in over pseudo-terminals, the contract over Zenoh,
thrust lines out, and the watchdog stop."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time

import pytest
import yaml

zenoh = pytest.importorskip("zenoh")

from test_driver_odometry import xor_sentence  # noqa: E402
from test_driver_uwb import node_frame2  # noqa: E402

from agent.contract import Bearing, Cmd, Odometry, Ranges, decode, encode  # noqa: E402
from agent.runtime.zenoh_session import ZenohSettings, zenoh_config
from sim_bridge.fleet import free_port  # noqa: E402

MODELS = {"sensor/odom": Odometry, "sensor/uwb": Ranges, "sensor/bearing": Bearing}


def wait_for(condition, seconds: float = 10.0, what: str = "") -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def thrust_lines(master: int, seconds: float) -> list[str]:
    """The $THR lines the driver wrote within `seconds`."""
    data, deadline = b"", time.monotonic() + seconds
    while time.monotonic() < deadline:
        ready, _, _ = select.select([master], [], [], 0.05)
        if ready:
            data += os.read(master, 4096)
    return [line for line in data.decode().split("\r\n") if line.startswith("$THR")]


def test_driver_bridge_turns_serial_streams_into_the_contract_and_commands_into_thrust(tmp_path):
    ptys = {name: os.openpty() for name in ("uwb", "odometry", "camera", "thrusters")}
    port = free_port()
    config = tmp_path / "driver.yaml"
    config.write_text(yaml.safe_dump({
        "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]},
        "uwb": {"device": os.ttyname(ptys["uwb"][1]), "baud": 921600, "module": {"peers": {2: "2", 3: "3"}}},
        "odometry": {"device": os.ttyname(ptys["odometry"][1]), "baud": 4800},
        "camera": {"device": os.ttyname(ptys["camera"][1]), "camera": {"fx": 500.0, "cx": 320.0, "width": 640}},
        "thrusters": {"device": os.ttyname(ptys["thrusters"][1]), "rate_hz": 20.0,
                      "hull": {"max_thrust": 100.0, "half_beam": 0.5, "surge_drag": 50.0, "yaw_drag": 20.0,
                               "timeout": 0.5}},
    }))
    driver = subprocess.Popen([sys.executable, "-m", "driver_bridge", "--vessel", "1", "--config", str(config)],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    received: dict[str, list] = {topic: [] for topic in MODELS}

    def on_sensor(sample):
        topic = str(sample.key_expr).split("/", 2)[2]
        message, reason = decode(MODELS[topic], sample.payload.to_bytes())
        assert message is not None, reason
        received[topic].append(message)

    try:
        with zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"]))) as session:
            session.declare_subscriber("usv/1/sensor/*", on_sensor)
            wait_for(lambda: list(session.info.peers_zid()), what="the driver bridge's session")
            time.sleep(0.3)
            write = {name: pair[0] for name, pair in ptys.items()}

            # Speed log: 2 knots on a compass heading of 090 (east, +x); a bad checksum in between is refused.
            for _ in range(3):
                os.write(write["odometry"], xor_sentence("IIVHW,90.0,T,,M,2.0,N,,K"))
                os.write(write["odometry"], b"$IIVHW,90.0,T,,M,9.0,N,,K*00\r\n")
                time.sleep(0.2)
            wait_for(lambda: len(received["sensor/odom"]) == 3, what="three odometry messages")
            odometry = received["sensor/odom"]
            assert [m.seq for m in odometry] == [0, 1, 2] and all(m.sender == "1" for m in odometry)
            assert odometry[0].position == (0.0, 0.0) and odometry[0].heading == pytest.approx(0.0)
            assert odometry[2].position[0] > 0.2 and odometry[2].position[1] == pytest.approx(0.0, abs=1e-9)

            # UWB: one ranging round, node 2 at 7.5 m and node 9, which is no vessel of ours.
            os.write(write["uwb"], node_frame2(1, 1000, [(2, 7500), (9, 4000)]))
            wait_for(lambda: received["sensor/uwb"], what="a range message")
            assert received["sensor/uwb"][0].ranges == {"2": pytest.approx(7.5)}

            # Camera: a detection at the image centre with the bow east: the target is due east of the
            # vessel, so the unit vector from the target to the vessel points west. Then no detection.
            os.write(write["camera"], xor_sentence("DET,320,"))
            os.write(write["camera"], xor_sentence("DET,,"))
            wait_for(lambda: len(received["sensor/bearing"]) == 2, what="two bearing messages")
            first, second = received["sensor/bearing"]
            assert first.bearing == (pytest.approx(-1.0), pytest.approx(0.0, abs=1e-12))
            assert second.bearing is None

            # Commands: 1 m/s straight ahead is 50 N of drag, 25 N (0.25 of full) on each thruster.
            thrusters = ptys["thrusters"][0]
            thrust_lines(thrusters, 0.2)                                   # drain the stopped start
            command = session.declare_publisher("usv/1/cmd")
            for seq in range(10):
                command.put(encode(Cmd(stamp_ns=time.time_ns(), seq=seq, sender="1", surge=1.0, yaw_rate=0.0)))
                time.sleep(0.05)
            lines = thrust_lines(thrusters, 0.2)
            assert lines and all(line.startswith("$THR,+0.250,+0.250*") for line in lines), lines
            # A command from another vessel is refused; then silence: the watchdog stops the thrusters.
            session.put("usv/1/cmd", encode(Cmd(stamp_ns=time.time_ns(), seq=99, sender="2", surge=3.0,
                                                yaw_rate=0.0)))
            fading = thrust_lines(thrusters, 0.8)                          # the 0.5 s timeout runs out
            assert fading[0].startswith("$THR,+0.250") and fading[-1].startswith("$THR,+0.000"), fading
            lines = thrust_lines(thrusters, 0.3)
            assert lines and all(line.startswith("$THR,+0.000,+0.000*") for line in lines), lines
        driver.send_signal(signal.SIGTERM)
        output, _ = driver.communicate(timeout=15)
    finally:
        if driver.poll() is None:
            driver.kill()
        for master, slave in ptys.values():
            os.close(master)
            os.close(slave)
    assert driver.returncode == 0, output
    # What was refused is counted and reported: the other vessel's command, the three bad checksums.
    assert "'command': 1" in output and "'odometry_lines_refused': {'bad_checksum': 3}" in output, output


def test_a_bad_driver_config_is_a_clear_error(tmp_path):
    config = tmp_path / "driver.yaml"
    config.write_text(yaml.safe_dump({"thrusters": {"device": "/dev/null", "hull": {"max_thrust": -1}}}))
    result = subprocess.run([sys.executable, "-m", "driver_bridge", "--vessel", "1", "--config", str(config)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "thrusters.hull" in result.stderr and "Traceback" not in result.stderr
