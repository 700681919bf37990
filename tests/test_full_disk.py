"""A full disk under the run folder never stops control: `usv-fleet run` of the short scenario with its run
folder on a real full filesystem (a 20 MB tmpfs, filled), over real processes. Commands flow for every tick
all run long, every agent's status says its log is suspended and counts what it drops, each process says so
once (on the launcher's stderr, off the full disk), and the launcher ends with exit 3 and one line naming
what it could not write, never a traceback. With room again mid-run, logging resumes: a new part whose first
message records the gap, read back by mission_log's reader, the consoles with a line saying what they lost,
and the summary written (sim_bridge/fleet.py, sim_bridge/console.py, agent/runtime/mcap_log.py)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from conftest import wait_until

from agent.config import read_yaml
from agent.contract import CLOCK_KEY
from agent.runtime.mcap_log import GAP_TOPIC, read_messages
from mission_log.reader import load_run
from sim_bridge.fleet import LOGS_LOST
from sim_bridge.scenario import with_duration

pytestmark = pytest.mark.slow   # the fleet's processes over Zenoh, and a tmpfs

SCENARIO = Path(__file__).parent / "data" / "short_scenario.yaml"
DT = 0.1
LEAVE = 48 * 1024     # bytes left free on the disk: the settings fit, the logs fill it within a second


@pytest.fixture
def full_disk(tmp_path):
    """A 20 MB tmpfs mounted in tmp_path, filled but for LEAVE bytes; unmounted afterwards."""
    mount = tmp_path / "disk"
    mount.mkdir()
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=20m", "tmpfs", str(mount)],
                          capture_output=True, text=True, check=False)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {made.stderr.strip()}")
    try:
        stat = os.statvfs(mount)
        (mount / "filler").write_bytes(b"\0" * (stat.f_bavail * stat.f_frsize - LEAVE))
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


class Watched:
    """`usv-fleet run` with its run folder on `disk`, and a Zenoh session on its bridge that counts every
    agent's commands and keeps its statuses."""

    def __init__(self, tmp_path: Path, disk: Path, duration: float) -> None:
        import zenoh

        (tmp_path / "scenario").mkdir()
        scenario = with_duration(SCENARIO, tmp_path / "scenario", duration)
        self.planned = round(duration / DT) + 1
        self.err_path = tmp_path / "launcher.err"
        self.out, self.err = (tmp_path / "launcher.out").open("w+"), self.err_path.open("w+")
        self.process = subprocess.Popen([sys.executable, "-m", "sim_bridge.fleet_cli", "run", str(scenario),
                                         "--out", str(disk / "runs")], stdout=self.out, stderr=self.err)
        self.commands: dict[str, set[int]] = {}     # vessel -> stamps of its commands
        self.moving: dict[str, int] = {}            # vessel -> commands that are not STOP
        self.statuses: dict[str, list[dict]] = {}
        self.first_tick: int | None = None          # the first sim tick this observer's session saw
        self.lock = threading.Lock()
        assert wait_until(lambda: list((disk / "runs").glob("*/bridge.yaml"))
                          or self.process.poll() is not None, timeout=60)
        (bridge,) = list((disk / "runs").glob("*/bridge.yaml"))
        self.folder = bridge.parent
        endpoint = read_yaml(bridge)["zenoh"]["listen"][0]
        config = zenoh.Config()
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("connect/endpoints", json.dumps([endpoint]))
        self.session = zenoh.open(config)
        self.session.declare_subscriber("usv/*/cmd", self._on_command)
        self.session.declare_subscriber("usv/*/status", self._on_status)
        self.session.declare_subscriber(CLOCK_KEY, self._on_clock)

    def _on_clock(self, sample) -> None:
        with self.lock:
            if self.first_tick is None:
                self.first_tick = json.loads(sample.payload.to_bytes())["seq"]

    def _on_command(self, sample) -> None:
        message = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.commands.setdefault(message["sender"], set()).add(message["stamp_ns"])
            if message["surge"] != 0.0 or message["yaw_rate"] != 0.0:
                self.moving[message["sender"]] = self.moving.get(message["sender"], 0) + 1

    def _on_status(self, sample) -> None:
        message = json.loads(sample.payload.to_bytes())
        if message.get("ticked", True):
            with self.lock:
                self.statuses.setdefault(message["sender"], []).append(message)

    def latest(self, vessel: str) -> dict:
        with self.lock:
            return (self.statuses.get(vessel) or [{"health": {}}])[-1]["health"]

    def finish(self, timeout: float = 240.0) -> tuple[int, str]:
        try:
            code = self.process.wait(timeout=timeout)
        finally:
            if self.process.poll() is None:
                self.process.kill()
                self.process.wait()
            self.session.close()
        return code, self.err_path.read_text()


def _ticked_all_run_long(watched: Watched) -> None:
    """Every vessel commanded every tick (lockstep: one command per tick), and steered (not STOP) most.

    Counted from the first tick whose clock this observer received: the launcher's run starts before the
    observer can connect (it needs the run folder's bridge.yaml), and on a loaded machine its subscriptions
    can reach the router after the first commands went (CI once missed tick 0 of one vessel)."""
    assert watched.first_tick is not None and watched.first_tick < watched.planned // 10, watched.first_tick
    observed = set(range(watched.first_tick, watched.planned))
    for vessel in ("1", "2", "3"):
        stamps = sorted(watched.commands.get(vessel, ()))
        ticks = {round(stamp * 1e-9 / DT) for stamp in stamps}
        assert observed <= ticks <= set(range(watched.planned)), \
            f"vessel {vessel}: {len(ticks & observed)} of ticks {watched.first_tick}-{watched.planned - 1}"
        assert watched.moving.get(vessel, 0) > watched.planned // 2, (vessel, watched.moving)


def test_a_fleet_on_a_full_disk_commands_every_tick_and_the_launcher_ends_in_one_line(full_disk, tmp_path):
    watched = Watched(tmp_path, full_disk, duration=40.0)
    code, stderr = watched.finish()
    health = {v: [watched.latest(v).get(k) for k in ("log_suspended", "log_dropped")] for v in "123"}
    print(f"full disk all run long: exit {code}; commands per vessel "
          f"{ {v: len(s) for v, s in sorted(watched.commands.items())} } of {watched.planned} ticks; "
          f"last health (log_suspended, log_dropped) {health}")
    print(stderr)
    assert "Traceback" not in stderr
    assert code == LOGS_LOST, stderr
    _ticked_all_run_long(watched)
    for vessel in ("1", "2", "3"):
        health = watched.latest(vessel)
        assert health["log_suspended"] == 1 and health["log_dropped"] > 0, (vessel, health)
        # Said once, by the agent, repeated once on the launcher's stderr (the terminal, not the full disk).
        assert stderr.count(f"usv-agent {vessel}: logging suspended") == 1, stderr
    last = stderr.strip().splitlines()
    assert "the mission ran to its end but logs were lost (exit 3)" in last[-1]
    # One line of what was lost: the logs suspended, the consoles and summary files not written (or why the
    # logs could not be analysed at all).
    assert last[-2].startswith("usv-fleet: the logs of agent-1, agent-2, agent-3")
    assert "not written:" in last[-2]
    assert "summary.md (No space left on device)" in last[-2] or "the summary:" in last[-2]


def test_logging_resumes_when_there_is_room_again(full_disk, tmp_path):
    watched = Watched(tmp_path, full_disk, duration=80.0)
    try:
        assert wait_until(lambda: all(watched.latest(v).get("log_suspended") == 1 for v in "123")
                          or watched.process.poll() is not None, timeout=120), "no agent's log was suspended"
        assert watched.process.poll() is None
        suspended_at = {v: watched.latest(v)["log_dropped"] for v in "123"}
        (full_disk / "filler").unlink()                        # room again
        freed = time.monotonic()
        assert wait_until(lambda: all(watched.latest(v).get("log_suspended") == 0 for v in "123")
                          or watched.process.poll() is not None, timeout=60), "logging did not resume"
        resumed_in = time.monotonic() - freed
    finally:
        code, stderr = watched.finish()
    print(f"room again: every agent's log resumed {resumed_in:.1f} s after the filler went; exit {code}")
    print(stderr)
    assert "Traceback" not in stderr
    assert code == LOGS_LOST, stderr
    _ticked_all_run_long(watched)
    for vessel in ("1", "2", "3"):
        assert stderr.count(f"usv-agent {vessel}: logging suspended") == 1, stderr
        dropped = watched.latest(vessel)["log_dropped"]
        assert watched.latest(vessel)["log_suspended"] == 0 and dropped >= suspended_at[vessel] > 0
        # The part that resumed the log starts with the record of the gap: what and how much was lost.
        part = watched.folder / f"agent-{vessel}.part0001.mcap"
        topic, _, gap = next(iter(read_messages(part)))
        assert topic == GAP_TOPIC and gap["dropped"] == dropped and gap["topics"]
        assert gap["first_lost_ns"] <= gap["last_lost_ns"] and gap["suspended_at"] < gap["resumed_at"]
        assert "No space left on device" in gap["error"]
        # Its console: the lines of the full disk's time kept and written, after a line saying what was lost.
        console = (watched.folder / f"agent-{vessel}.log").read_text()
        assert "[usv-fleet: this console could not be written from" in console
        assert "logging suspended" in console and "logging resumed" in console
    # mission_log's reader joins the parts: every vessel's log reads, and the summary was written from them.
    run = load_run(watched.folder)
    assert sorted(run.vessels) == ["1", "2", "3"] and run.has_truth
    # Where the bridge's own log was suspended, the ticks of the gap are missing from the ground truth's log
    # (whether its writes met the full disk depends on when its chunks were flushed); either way the run is
    # complete, and the summary says how many of the ticks simulated the logs hold (not "cut short").
    metrics = json.loads((watched.folder / "metrics.json").read_text())
    assert {"agent-1", "agent-2", "agent-3"} <= set(metrics["logs_lost"])
    if "bridge" in metrics["logs_lost"]:
        assert metrics["complete"] and 0 < metrics["ticks"] < watched.planned
    else:
        assert metrics["complete"] and metrics["ticks"] == watched.planned
    summary = (watched.folder / "summary.md").read_text()
    assert f"{metrics['ticks']} of the {watched.planned} ticks simulated" in summary
    assert "cut short" not in summary
    assert stderr.strip().splitlines()[-1].endswith("logs were lost (exit 3)")


def test_an_agent_whose_stderr_is_on_the_full_disk_keeps_steering(full_disk, tmp_path):
    """Outside the launcher (a boat's agent with its stderr sent to a file on the log disk): the lines it
    cannot write are lost, the agent is not. Its log and its stderr both on the full disk; the test plays its
    bridge (odometry at 10 Hz) and watches its status for 30 ticks after the log was suspended; SIGTERM ends
    it with code 0."""
    import zenoh

    from agent.contract import Odometry, encode
    from sim_bridge.fleet import free_port

    port = free_port()
    config = tmp_path / "node.yaml"
    config.write_text(json.dumps({"clock": "wall", "log": str(full_disk / "agent-7.mcap"),
                                  "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]}}))
    (full_disk / "filler").unlink()          # this agent alone: a smaller filler, leaving a few pages
    stat = os.statvfs(full_disk)
    (full_disk / "filler").write_bytes(b"\0" * (stat.f_bavail * stat.f_frsize - 16 * 1024))
    with (full_disk / "agent-7.err").open("w") as console:
        agent = subprocess.Popen([sys.executable, "-m", "agent", "--vessel", "7", "--config", str(config)],
                                 stdout=console, stderr=console)
    statuses: list[dict] = []
    session_config = zenoh.Config()
    session_config.insert_json5("scouting/multicast/enabled", "false")
    session_config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    try:
        with zenoh.open(session_config) as session:
            session.declare_subscriber("usv/7/status",
                                       lambda s: statuses.append(json.loads(s.payload.to_bytes())))
            odometry = session.declare_publisher("usv/7/sensor/odom")
            sent = [0]

            def suspended_for(ticks: int) -> bool:
                odometry.put(encode(Odometry(stamp_ns=time.time_ns(), seq=sent[0], sender="7",
                                             position=(0.0, 0.0), heading=0.0)))
                sent[0] += 1
                return sum(s["health"].get("log_suspended", 0) == 1 for s in statuses) >= ticks

            assert wait_until(lambda: suspended_for(30) or agent.poll() is not None, timeout=90,
                              interval=0.1), f"the log was never suspended: {statuses[-1:] or 'no status'}"
            assert agent.poll() is None, f"the agent exited with code {agent.returncode}"
            agent.send_signal(signal.SIGTERM)
            code = agent.wait(timeout=20)
    finally:
        if agent.poll() is None:
            agent.kill()
            agent.wait()
    suspended = sum(s["health"].get("log_suspended", 0) for s in statuses)
    print(f"agent with stderr on the full disk: {suspended} statuses with its log suspended, last "
          f"log_dropped {statuses[-1]['health']['log_dropped']}; exit {code}")
    assert code == 0
    seqs = [s["seq"] for s in statuses]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))     # a status every tick, none skipped
    assert statuses[-1]["health"]["log_dropped"] > 0
