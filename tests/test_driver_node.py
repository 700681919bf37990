"""The driver bridge process end to end: serial byte streams in over pseudo-terminals, the contract over Zenoh,
thrust lines out, and the watchdog stop."""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import re
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
import zenoh
from conftest import wait_until
from test_driver_odometry import xor_sentence
from test_driver_uwb import node_frame2

from agent.contract import Bearing, Cmd, Odometry, Ranges, decode, encode
from agent.runtime.zenoh_session import ZenohSettings, zenoh_config
from sim_bridge.fleet import free_port

pytestmark = pytest.mark.slow   # the driver bridge's process, over Zenoh

MODELS = {"sensor/odom": Odometry, "sensor/uwb": Ranges, "sensor/bearing": Bearing}
FULL_AHEAD = "$THR,+0.250,+0.250*"   # the thrust line of 1 m/s straight ahead (see below)
STOPPED = "$THR,+0.000,+0.000*"


def wait_for(condition, seconds: float = 10.0, what: str = "") -> None:
    assert wait_until(condition, seconds), f"timed out waiting for {what}"


class ThrustLines:
    """The $THR lines the driver writes to the thrusters' pseudo-terminal, read as they come."""

    def __init__(self, master: int) -> None:
        self.master, self.pending = master, b""

    def read(self, seconds: float) -> list[str]:
        """Every line that comes within `seconds`."""
        lines, deadline = [], time.monotonic() + seconds
        while time.monotonic() < deadline:
            lines += self._some(deadline - time.monotonic())
        return lines

    def read_until(self, predicate, seconds: float = 10.0, what: str = "") -> list[str]:
        """Lines up to and including the first for which `predicate` holds (which must come in `seconds`)."""
        lines, deadline = [], time.monotonic() + seconds
        while True:
            for line in self._some(0.05):
                lines.append(line)
                if predicate(line):
                    return lines
            assert time.monotonic() < deadline, f"timed out waiting for {what}; got {lines[-5:]}"

    def _some(self, seconds: float) -> list[str]:
        ready, _, _ = select.select([self.master], [], [], max(seconds, 0.0))
        if ready:
            self.pending += os.read(self.master, 4096)
        *complete, self.pending = self.pending.split(b"\r\n")
        return [line.decode() for line in complete if line.startswith(b"$THR")]


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
            write = {name: pair[0] for name, pair in ptys.items()}

            # Connected is not yet subscribed: until the driver has heard of our subscriber it sends to
            # nobody. So a UWB frame (node 3 only) goes in until its message comes out; then nothing is lost.
            def probe_heard() -> bool:
                os.write(write["uwb"], node_frame2(1, 500, [(3, 2000)]))
                return wait_until(lambda: received["sensor/uwb"], timeout=0.3)

            wait_for(probe_heard, what="the driver bridge to hear of the test's subscriber")

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

            def rounds() -> list:
                return [m for m in received["sensor/uwb"] if "3" not in m.ranges]   # the probes have node 3

            wait_for(rounds, what="a range message")
            (ranges,) = rounds()
            assert ranges.ranges == {"2": pytest.approx(7.5)}

            # Camera: a detection at the image centre with the bow east: the target is due east of the
            # vessel, so the unit vector from the target to the vessel points west. Then no detection.
            os.write(write["camera"], xor_sentence("DET,320,"))
            os.write(write["camera"], xor_sentence("DET,,"))
            wait_for(lambda: len(received["sensor/bearing"]) == 2, what="two bearing messages")
            first, second = received["sensor/bearing"]
            assert first.bearing == (pytest.approx(-1.0), pytest.approx(0.0, abs=1e-12))
            assert second.bearing is None

            # Commands: 1 m/s straight ahead is 50 N of drag, 25 N (0.25 of full) on each thruster. Before
            # the first command arrives the thrusters are stopped; from then on, commands every 0.05 s (well
            # within the 0.5 s timeout) hold them at 0.25.
            thrusters = ThrustLines(ptys["thrusters"][0])
            command = session.declare_publisher("usv/1/cmd")
            seqs = itertools.count()

            def ahead_for(seconds: float) -> list[str]:
                """Send a command of 1 m/s ahead, then read the thrust lines of the next `seconds`."""
                command.put(encode(Cmd(stamp_ns=time.time_ns(), seq=next(seqs), sender="1", surge=1.0,
                                       yaw_rate=0.0)))
                return thrusters.read(seconds)

            lines = ahead_for(0.05)
            deadline = time.monotonic() + 10
            while not any(line.startswith(FULL_AHEAD) for line in lines):
                assert time.monotonic() < deadline, f"the commands never moved the thrusters: {lines[-5:]}"
                lines += ahead_for(0.05)
            first = next(k for k, line in enumerate(lines) if line.startswith(FULL_AHEAD))
            assert all(line.startswith(STOPPED) for line in lines[:first]), lines
            assert all(line.startswith(FULL_AHEAD) for line in lines[first:]), lines
            held = [line for _ in range(10) for line in ahead_for(0.05)]
            assert held and all(line.startswith(FULL_AHEAD) for line in held), held
            # A command from another vessel is refused; then silence: the watchdog stops the thrusters.
            session.put("usv/1/cmd", encode(Cmd(stamp_ns=time.time_ns(), seq=99, sender="2", surge=3.0,
                                                yaw_rate=0.0)))
            fading = thrusters.read_until(lambda line: line.startswith(STOPPED), what="the watchdog's stop")
            # Full ahead until the 0.5 s timeout runs out, then stopped: never the refused 3 m/s.
            assert fading[-1].startswith(STOPPED) and all(line.startswith(FULL_AHEAD) for line in fading[:-1])
            lines = thrusters.read(0.3)
            assert lines and all(line.startswith(STOPPED) for line in lines), lines
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
    assert "'command_other_vessel': 1" in output, output
    assert "'odometry_lines_refused': {'bad_checksum': 3}" in output, output


def test_a_bad_driver_config_is_a_clear_error(tmp_path):
    config = tmp_path / "driver.yaml"
    config.write_text(yaml.safe_dump({"thrusters": {"device": "/dev/null", "hull": {"max_thrust": -1}}}))
    result = subprocess.run([sys.executable, "-m", "driver_bridge", "--vessel", "1", "--config", str(config)],
                            capture_output=True, text=True, check=False, timeout=60)
    assert result.returncode == 2 and "thrusters.hull" in result.stderr and "Traceback" not in result.stderr


def test_a_missing_serial_device_is_named_with_what_it_is(tmp_path):
    """A device that is not there: one line naming the device's role, its path and baud (the UWB module's
    default is LinkTrack's 921600), not a bare [Errno 2] with a path."""
    config = tmp_path / "driver.yaml"
    missing = tmp_path / "ttyUSB-not-there"
    config.write_text(yaml.safe_dump({"uwb": {"device": str(missing), "module": {"peers": {2: "2"}}}}))
    result = subprocess.run([sys.executable, "-m", "driver_bridge", "--vessel", "1", "--config", str(config)],
                            capture_output=True, text=True, check=False, timeout=60)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.strip() == (f"usv-driver: cannot open the UWB module (uwb.device {missing} at 921600 baud): "
                                     "No such file or directory")


REVERSE = "$THR,-0.250,-0.250*"      # -1 m/s: what the spoofer asks for, never the real agent


@contextlib.contextmanager
def thruster_driver(tmp_path: Path, extra: dict | None = None, watchdog: float = 5.0,
                    control: dict | None = None):
    """`usv-driver` for vessel 1 with a hull on a pseudo-terminal (a `watchdog` s timeout, or the thrusters'
    `control` settings instead of the mix's): yields the process (stdout and stderr in one text pipe), its
    thrust lines and its Zenoh port; killed if still running at the end."""
    master, slave = os.openpty()
    port = free_port()
    config = tmp_path / "driver.yaml"
    config.write_text(yaml.safe_dump({
        "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]},
        "thrusters": {"device": os.ttyname(slave), **(control or {
            "rate_hz": 20.0, "hull": {"max_thrust": 100.0, "half_beam": 0.5, "surge_drag": 50.0, "yaw_drag": 20.0,
                                      "timeout": watchdog}})},
        **(extra or {}),
    }))
    driver = subprocess.Popen([sys.executable, "-m", "driver_bridge", "--vessel", "1", "--config", str(config)],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        yield driver, ThrustLines(master), port
    finally:
        if driver.poll() is None:
            driver.kill()
        os.close(master)
        os.close(slave)


class RealAgent:
    """The vessel's agent as the driver sees it: a liveliness token and a command of 1 m/s ahead every 50 ms,
    stamped by the wall clock, seq counting from 0, on its own Zenoh session."""

    def __init__(self, port: int) -> None:
        import threading

        self.session = zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"])))
        self.token = self.session.liveliness().declare_token("usv/1/alive")
        self.publisher = self.session.declare_publisher("usv/1/cmd")
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        for seq in itertools.count():
            if self.stopping.wait(0.05):
                return
            self.publisher.put(encode(Cmd(stamp_ns=time.time_ns(), seq=seq, sender="1", surge=1.0, yaw_rate=0.0)))

    def leave(self) -> None:
        """Stop commanding and close the session: its liveliness token goes with it."""
        self.stopping.set()
        self.thread.join(5)
        self.session.close()


def test_commands_are_judged_by_stamp_and_session_so_a_spoofed_seq_or_stamp_cannot_take_the_thrusters(tmp_path):
    """A spoofer on the network (sender "1", as anyone can write without TLS) tries what a seq high-water
    mark let through: an absurd seq (which locked the real agent out), a seq of 0 stamped far ahead (taken
    as a restart at any time), a replay of an old command. None takes the thrusters from the real agent;
    a stamp just inside the window holds it off for at most `max_ahead`. When the agent's session ends the
    thrusters stop at once, long before the (here 5 s) watchdog."""
    agent = None
    with thruster_driver(tmp_path, {"commands": {"max_age": 0.5, "max_ahead": 0.2}}) as (driver, thrusters, port):
        try:
            with zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"]))) as spoofer:
                wait_for(lambda: list(spoofer.info.peers_zid()), what="the driver bridge's session")
                agent = RealAgent(port)
                thrusters.read_until(lambda line: line.startswith(FULL_AHEAD), seconds=15, what="the agent's thrust")

                def spoof(stamp_ns: int, seq: int) -> None:
                    spoofer.put("usv/1/cmd", encode(Cmd(stamp_ns=stamp_ns, seq=seq, sender="1", surge=-1.0,
                                                        yaw_rate=0.0)))

                # 1. An absurd seq, freshly stamped: taken (nothing tells it from the agent's), but only until the
                # agent's next command 50 ms later; the agent is not locked out.
                spoof(time.time_ns(), 2**62)
                lines = thrusters.read(1.0)
                assert sum(line.startswith(REVERSE) for line in lines) <= 2, lines
                assert all(line.startswith(FULL_AHEAD) for line in lines[-15:]), lines
                # 2. A "restart" (seq 0) stamped 1000 s ahead, and 3. a replay of a command 10 s old: refused.
                spoof(time.time_ns() + 1000 * 10**9, 0)
                spoof(time.time_ns() - 10 * 10**9, 0)
                lines = thrusters.read(0.6)
                assert lines and all(line.startswith(FULL_AHEAD) for line in lines), lines
                # 4. A stamp just inside the window (0.18 s ahead): it holds the agent's commands off until the
                # agent's clock passes it, at most max_ahead (0.2 s) and a drive period.
                spoof(time.time_ns() + 180_000_000, 7)
                lines = thrusters.read(1.0)
                held = sum(line.startswith(REVERSE) for line in lines)
                assert 1 <= held <= 6, lines                              # 6 lines at 20 Hz: 0.3 s
                assert all(line.startswith(FULL_AHEAD) for line in lines[-10:]), lines
                # 5. The agent's session ends: its token goes, and the thrusters stop within a few lines.
                left = time.monotonic()
                agent.leave()
                thrusters.read_until(lambda line: line.startswith(STOPPED), seconds=4.0, what="the stop on leaving")
                stopped_in = time.monotonic() - left
                assert stopped_in < 1.0
            driver.send_signal(signal.SIGTERM)
            output, _ = driver.communicate(timeout=15)
        finally:
            if agent is not None and not agent.stopping.is_set():
                agent.leave()
    assert driver.returncode == 0, output
    assert "'command_future': 1" in output and "'command_stale': 1" in output, output
    assert "'command_out_of_order':" in output and "'agent_left': 1" in output, output
    print(f"spoofed stamp 0.18 s ahead held the agent off for {held} thrust lines ({held * 0.05:.2f} s); "
          f"stop {stopped_in:.2f} s after the agent's session ended")


def test_a_driver_stopped_under_way_leaves_the_thrusters_stopped(tmp_path):
    """SIGTERM while the agent commands full ahead: the last thrust line is a stop, written as the loop ends
    (before Zenoh's teardown, which the stop deadline might have to cut short), and the driver exits 0."""
    with thruster_driver(tmp_path) as (driver, thrusters, port):
        agent = RealAgent(port)
        try:
            thrusters.read_until(lambda line: line.startswith(FULL_AHEAD), seconds=15, what="the agent's thrust")
            driver.send_signal(signal.SIGTERM)   # the agent still commands full ahead: only the stop can stop it
            output, _ = driver.communicate(timeout=15)
            lines = thrusters.read(0.3)
        finally:
            agent.leave()
    assert driver.returncode == 0, output
    assert lines and lines[-1].startswith(STOPPED), lines
    assert "Timeout (" not in output, output


def test_a_serial_device_that_vanishes_under_way_ends_the_driver_with_one_line_and_the_thrusters_stopped(
        tmp_path):
    """The speed log unplugged while the agent commands full ahead (its pseudo-terminal's other end closed:
    the port reports itself ready and has nothing, as a USB adapter pulled out does). Before pyserial the
    driver read nothing forever, at full CPU, never saying so; now it stops with one line naming the device
    (systemd's Restart=always opens it again), and the last thrust line is a stop."""
    log_master, log_slave = os.openpty()
    device = os.ttyname(log_slave)
    extra = {"odometry": {"device": device, "baud": 4800}}
    try:
        with thruster_driver(tmp_path, extra) as (driver, thrusters, port):
            agent = RealAgent(port)
            try:
                thrusters.read_until(lambda line: line.startswith(FULL_AHEAD), seconds=15,
                                     what="the agent's thrust")
                os.close(log_master)
                log_master = None
                output, _ = driver.communicate(timeout=20)
                lines = thrusters.read(0.3)
            finally:
                agent.leave()
    finally:
        for fd in (log_master, log_slave):
            if fd is not None:
                os.close(fd)
    assert driver.returncode == 1 and "Traceback" not in output, output
    assert output.splitlines()[-1].startswith(
        f"usv-driver: lost the speed log and compass (odometry.device {device}): "), output
    assert lines and lines[-1].startswith(STOPPED), lines


def test_without_the_driver_extra_the_driver_says_what_to_install_in_one_line(tmp_path):
    config = tmp_path / "driver.yaml"
    config.write_text(yaml.safe_dump({"thrusters": {"device": "/dev/null", "hull": {
        "max_thrust": 100.0, "half_beam": 0.5, "surge_drag": 50.0, "yaw_drag": 20.0}}}))
    for library in ("serial", "pynmeagps"):
        hide = (f"import sys; sys.modules[{library!r}] = None; from driver_bridge.node import main; "
                f"sys.exit(main(['--vessel', '1', '--config', {str(config)!r}]))")
        result = subprocess.run([sys.executable, "-c", hide], capture_output=True, text=True, check=False,
                                timeout=60)
        assert result.returncode == 1 and result.stderr == (
            f"usv-driver: the driver bridge needs pyserial and pynmeagps ({library} is missing): "
            "pip install 'usv-circumnav[driver]'\n"), result.stderr


def test_a_storm_of_bad_serial_lines_leaves_the_driver_alive_its_watchdog_working_and_its_odometry_flowing(
        tmp_path):
    """A few hundred bad sentences on the speed log's port (lab/benchmarks/serial_fuzz.py's classes, seed 5, and bursts),
    with VHW lines of +-1e30 and +-1e308 knots and km/h under valid checksums among them: before, the first
    1e30 line ended usv-driver and its watchdog with it. Now the driver stays up, the thrusters follow the
    agent through the storm, good sentences after it are published as odometry within the contract, and the
    watchdog stops the thrusters once the agent's commands cease (its session still up)."""
    import numpy as np

    from driver_bridge.serial_port import write_all
    from lab.benchmarks.serial_fuzz import SerialLines, classes_for, sentence

    log_master, log_slave = os.openpty()
    os.set_blocking(log_master, False)
    odometry: list = []
    extra = {"odometry": {"device": os.ttyname(log_slave), "baud": 4800}}
    agent = None
    try:
        with thruster_driver(tmp_path, extra, watchdog=0.5) as (driver, thrusters, port), \
                zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"]))) as session:
            def on_odometry(sample) -> None:
                message, reason = decode(Odometry, sample.payload.to_bytes())
                odometry.append(message if message is not None else reason)

            session.declare_subscriber("usv/1/sensor/odom", on_odometry)
            wait_for(lambda: list(session.info.peers_zid()), what="the driver bridge's session")

            def good() -> bool:
                write_all(log_master, xor_sentence("IIVHW,90.0,T,,M,2.0,N,,K"), timeout_s=5.0)
                return wait_until(lambda: odometry, timeout=0.3)

            wait_for(good, what="the driver's first odometry")
            agent = RealAgent(port)
            thrusters.read_until(lambda line: line.startswith(FULL_AHEAD), seconds=15, what="the agent's thrust")
            bad = SerialLines("vhw", np.random.default_rng(5))
            kinds = [c for c in classes_for("vhw") if c not in ("burst", "walk")]   # walk: minutes apart
            huge = [xor_sentence(f"IIVHW,90.0,T,,M,{v},N,,K") for v in ("1e30", "-1e30", "1e308", "-1e308")]
            huge += [xor_sentence(f"IIVHW,90.0,T,,M,,N,{v},K") for v in ("1e30", "-1e308")]
            bursts = [b"".join(bad.bad(kinds[k % len(kinds)]) for k in range(50)) for _ in range(3)]
            storm = [*huge, *(bad.bad(kinds[k % len(kinds)]) for k in range(300)), *bursts, *huge]

            def alive(after: int) -> None:
                assert driver.poll() is None, (f"usv-driver exited with {driver.returncode} after {after} "
                                               f"lines: {driver.communicate(timeout=5)[0][-3000:]}")

            for k, line in enumerate(storm):
                if k % 25 == 0:
                    time.sleep(0.02)
                    alive(k)
                try:
                    write_all(log_master, line, timeout_s=5.0)
                except TimeoutError:      # nobody reads the port any more
                    alive(k)
                    raise
            time.sleep(0.5)
            alive(len(storm))
            lines = thrusters.read(0.5)       # the loop goes on: the agent's commands drive the thrusters
            assert lines and all(line.startswith(FULL_AHEAD) for line in lines), lines

            before = len(odometry)
            write_all(log_master, b"\r\n" + sentence("IIVHW,90.0,T,,M,2.0,N,,K"), timeout_s=5.0)
            for _ in range(5):
                time.sleep(0.1)
                write_all(log_master, xor_sentence("IIVHW,90.0,T,,M,2.0,N,,K"), timeout_s=5.0)
            wait_for(lambda: len(odometry) >= before + 5, what="odometry from good sentences after the storm")

            agent.stopping.set()              # the agent stops commanding; its session (and token) stay
            agent.thread.join(5)
            fading = thrusters.read_until(lambda line: line.startswith(STOPPED), seconds=10,
                                          what="the watchdog")
            assert all(line.startswith(FULL_AHEAD) for line in fading[:-1]), fading
            agent.leave()
            driver.send_signal(signal.SIGTERM)
            output, _ = driver.communicate(timeout=15)
    finally:
        if agent is not None and not agent.stopping.is_set():
            agent.leave()
        os.close(log_master)
        os.close(log_slave)
    assert driver.returncode == 0, output
    closing = output.splitlines()[-1]
    refused = re.search(r"'speed_out_of_range': (\d+)", closing)
    assert refused and int(refused.group(1)) >= 12, output     # the twelve huge ones, and the campaign's
    assert "refused so far (dropped, going on)" in output and "Traceback" not in output, output
    assert all(isinstance(message, Odometry) for message in odometry), odometry   # each within the contract


def _thrust_pair(line: str) -> tuple[float, float]:
    left, right = line.split("*")[0].split(",")[1:]
    return float(left), float(right)


class Repeating:
    """Calls `act(value)` every 50 ms with the value last set (None: nothing), on its own thread."""

    def __init__(self, act) -> None:
        import threading

        self.act, self.value, self.stopping = act, None, threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stopping.wait(0.05):
            if self.value is not None:
                self.act(self.value)

    def close(self) -> None:
        self.stopping.set()
        self.thread.join(5)


def test_the_driver_bridges_inner_loop_answers_commands_with_thrust_of_the_right_sign_and_ratio(tmp_path):
    """thrusters.control inner_loop with the Otter preset, closed on a speed log (VHW, 20 Hz) whose compass
    heading turns as commanded. A turn in place (0 m/s, 0.2 rad/s counter-clockwise): port astern, starboard
    ahead, and while the port one is not at full astern the pair's thrust cancels in surge, T_p = -T_s, so
    left / right = -F / R (each value is over its own limit). Commands stop: zero within the 0.5 s timeout.
    Straight ahead with the boat still: both ahead, equal. The speed log falls silent: zero. Each stop said once."""
    from boat.presets import PRESETS
    from driver_bridge.serial_port import write_all

    tr = PRESETS["otter"].thrusters
    log_master, log_slave = os.openpty()
    os.set_blocking(log_master, False)
    heading = [90.0]

    def vhw(turn_deg_s: float) -> None:   # the compass heading (clockwise) falls when turning counter-clockwise
        heading[0] = (heading[0] - turn_deg_s * 0.05) % 360.0
        write_all(log_master, xor_sentence(f"IIVHW,{heading[0]:.3f},T,,M,0.0,N,,K"), timeout_s=5.0)

    extra = {"odometry": {"device": os.ttyname(log_slave), "baud": 4800}}
    control = {"control": "inner_loop", "inner_loop": {"preset": "otter"}}
    speed_log = commands = None
    with thruster_driver(tmp_path, extra, control=control) as (driver, thrusters, port):
        try:
            with zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"]))) as session:
                wait_for(lambda: list(session.info.peers_zid()), what="the driver bridge's session")
                publisher = session.declare_publisher("usv/1/cmd")
                seqs = itertools.count()
                speed_log = Repeating(vhw)
                commands = Repeating(lambda c: publisher.put(encode(Cmd(
                    stamp_ns=time.time_ns(), seq=next(seqs), sender="1", surge=c[0], yaw_rate=c[1]))))
                speed_log.value = math.degrees(0.2)
                time.sleep(0.5)
                commands.value = (0.0, 0.2)
                thrusters.read_until(lambda line: not line.startswith(STOPPED), seconds=15, what="the turn")
                turn = [_thrust_pair(line) for line in thrusters.read(2.0)]
                assert all(left < 0 < right for left, right in turn), turn
                unsaturated = [(left, right) for left, right in turn if left > -0.9995]
                assert len(unsaturated) >= 40, turn             # 2 s at 50 Hz, the first 0.1 s saturated
                for left, right in unsaturated:                 # T_p = -T_s, within the lines' 3 decimals
                    assert abs(left * tr.max_reverse + right * tr.max_forward) <= 5e-4 * (tr.max_forward
                                                                                        + tr.max_reverse)

                commands.value = None
                thrusters.read_until(lambda line: line.startswith(STOPPED), seconds=10, what="the watchdog's stop")
                speed_log.value = 0.0                           # still water, heading held: r decays to 0
                lines = thrusters.read(1.5)
                assert lines and all(line.startswith(STOPPED) for line in lines), lines

                commands.value = (1.0, 0.0)
                thrusters.read_until(lambda line: not line.startswith(STOPPED), seconds=10, what="ahead")
                ahead = [_thrust_pair(line) for line in thrusters.read(1.0)]
                assert ahead and all(0 < left == right for left, right in ahead), ahead

                speed_log.value = None                          # the speed log falls silent; commands go on
                thrusters.read_until(lambda line: line.startswith(STOPPED), seconds=10,
                                     what="the stop without measurements")
                lines = thrusters.read(0.5)
                assert lines and all(line.startswith(STOPPED) for line in lines), lines
                commands.close()                                # then the commands stop too: said once more
                thrusters.read(1.5)
            driver.send_signal(signal.SIGTERM)
            output, _ = driver.communicate(timeout=15)
        finally:
            for repeating in (speed_log, commands):
                if repeating is not None:
                    repeating.close()
            os.close(log_master)
            os.close(log_slave)
    assert driver.returncode == 0, output
    assert output.count("thrusters stopped: no fresh command (timeout 0.5 s)") == 2, output
    assert output.count("thrusters stopped: no speed-log or yaw sample for ") == 1, output
    assert "'thruster_events': {'watchdog_stop': 2, 'measurement_stop': 1}" in output, output
