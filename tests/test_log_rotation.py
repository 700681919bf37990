"""Log rotation and full disks: a log cut into complete parts by size or time, the set kept within its bound,
the parts read back as one log, and a full disk that neither stops the writer nor puts a traceback on
SIGTERM (an agent process on a tiny tmpfs)."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest
import yaml
from conftest import wait_until
from pydantic import ValidationError

from agent.runtime.mcap_log import (
    FORMAT_RECORD,
    FORMAT_VERSION,
    PART_RECORD,
    LogRotation,
    McapLog,
    read_metadata,
)
from mission_log import cli
from mission_log.reader import LogError, load_run, read_log, read_log_set

KB = 1000


def noise(k: int) -> dict:
    """A message of about 1 kB that zstd cannot shrink much."""
    generator = random.Random(k)
    return {"k": k, "noise": "".join(generator.choice("0123456789abcdef") for _ in range(1000))}


def write(log: McapLog, messages: range) -> None:
    for k in messages:
        log.log("/9/inputs", noise(k), log_time_ns=k * 100_000_000)


def ks(log) -> list[int]:
    return [m["k"] for _, m in log.messages("/9/inputs")]


def on_disk(folder: Path) -> int:
    return sum(path.stat().st_size for path in folder.glob("*.mcap"))


def test_a_log_rotates_by_size_into_complete_parts_that_sort_in_time_order(tmp_path):
    rotation = LogRotation(max_file_mb=0.02, max_total_mb=None)     # 20 kB parts, all kept
    with McapLog(tmp_path / "agent-9.mcap", flush_seconds=0.0, metadata={"vessel": "9"}, rotation=rotation) as log:
        write(log, range(100))
    names = [path.name for path in log.parts]
    assert len(names) >= 4 and names[:3] == ["agent-9.mcap", "agent-9.part0001.mcap", "agent-9.part0002.mcap"]
    assert sorted(tmp_path.glob("*.mcap")) == log.parts                  # ls order is time order
    sets = set()
    for number, path in enumerate(log.parts):
        with warnings.catch_warnings():
            warnings.simplefilter("error")                               # an unfinished part would warn
            part = read_log(path)
        metadata = read_metadata(path)
        assert metadata[FORMAT_RECORD] == {"version": FORMAT_VERSION} and metadata["run"] == {"vessel": "9"}
        assert metadata[PART_RECORD]["part"] == str(number) and metadata[PART_RECORD]["first"] == "agent-9.mcap"
        sets.add(metadata[PART_RECORD]["set"])
        assert part.vessel == "9" and ks(part), path
        if path != log.parts[-1]:
            # A part is cut at the first message past the limit, then gets its summary (its index, ~100 bytes
            # a chunk: here a chunk per message, in a real log one a second): a few kB over at most.
            assert 20 * KB <= path.stat().st_size <= 25 * KB, (path.name, path.stat().st_size)
    assert len(sets) == 1
    run = load_run(tmp_path)
    (vessel,) = run.vessels.values()
    assert ks(vessel) == list(range(100)) and vessel.parts == log.parts and vessel.missing_parts == []


def test_the_oldest_parts_are_deleted_to_keep_the_set_within_its_bound(tmp_path):
    rotation = LogRotation(max_file_mb=0.02, max_total_mb=0.07)
    largest = 0
    with McapLog(tmp_path / "agent-9.mcap", flush_seconds=0.0, metadata={"vessel": "9"}, rotation=rotation) as log:
        for k in range(300):
            write(log, range(k, k + 1))
            largest = max(largest, on_disk(tmp_path))
    # Within the bound at every moment, one message (~1 kB) over at most.
    assert largest <= 71 * KB, largest
    assert largest >= 55 * KB            # and the bound is used, not just respected
    kept = sorted(tmp_path.glob("*.mcap"))
    assert log.deleted == log.parts[:len(log.parts) - len(kept)] and len(log.deleted) >= 5
    assert kept == log.parts[len(log.deleted):]                          # the oldest went first
    run = load_run(tmp_path)
    (vessel,) = run.vessels.values()
    read = ks(vessel)
    assert read == list(range(read[0], 300)) and read[0] > 0            # the newest messages, none lost between
    assert vessel.missing_parts == list(range(len(log.deleted)))
    assert run.missing_parts == {kept[0]: vessel.missing_parts}


@pytest.mark.slow
def test_a_log_rotates_by_time(tmp_path):
    rotation = LogRotation(max_file_mb=None, max_file_seconds=0.3, max_total_mb=None)
    with McapLog(tmp_path / "sim.mcap", metadata={"scenario": "x"}, rotation=rotation) as log:
        started = time.monotonic()
        k = 0
        while time.monotonic() - started < 1.0:
            log.log("/truth", {"k": k}, log_time_ns=k)
            k += 1
            time.sleep(0.02)
    assert 3 <= len(log.parts) <= 5, log.parts
    counts = [len(read_log(path).messages("/truth")) for path in log.parts]
    assert sum(counts) == k and all(n > 0 for n in counts)
    # Each full part spans about 0.3 s of logging at ~45 messages a second.
    assert all(8 <= n <= 20 for n in counts[:-1]), counts


def test_without_rotation_the_log_is_one_file(tmp_path):
    with McapLog(tmp_path / "agent-9.mcap", flush_seconds=0.0, metadata={"vessel": "9"}) as log:
        write(log, range(100))
    assert [p.name for p in tmp_path.iterdir()] == ["agent-9.mcap"] and log.parts == [tmp_path / "agent-9.mcap"]
    assert (tmp_path / "agent-9.mcap").stat().st_size > 50 * KB


def test_a_rotation_that_cannot_work_is_refused():
    with pytest.raises(ValidationError, match="max_file_mb or max_file_seconds"):
        LogRotation(max_file_mb=None, max_file_seconds=None)
    with pytest.raises(ValidationError, match="less than one part"):
        LogRotation(max_file_mb=100, max_total_mb=50)
    assert LogRotation().max_total_mb == 512 and LogRotation().max_file_mb == 64    # ~6 h of an agent's log


def _rotated_set(folder: Path, vessel: str = "9", parts: int = 4) -> list[Path]:
    rotation = LogRotation(max_file_mb=0.02, max_total_mb=None)
    with McapLog(folder / f"agent-{vessel}.mcap", flush_seconds=0.0, metadata={"vessel": vessel},
                 rotation=rotation) as log:
        k = 0
        while len(log.parts) < parts:
            log.log(f"/{vessel}/inputs", noise(k), log_time_ns=k * 100_000_000)
            k += 1
    return log.parts


def test_parts_given_in_any_order_read_as_one_log_and_a_missing_one_is_noted(tmp_path, capsys):
    parts = _rotated_set(tmp_path)
    whole = ks(load_run(tmp_path).vessels["9"])
    in_part = {path: ks(read_log(path)) for path in parts}
    parts[1].unlink()
    shuffled = [str(p) for p in parts if p.exists()][::-1]
    run = load_run([Path(p) for p in shuffled])
    vessel = run.vessels["9"]
    assert ks(vessel) == [k for k in whole if k not in in_part[parts[1]]]
    assert vessel.missing_parts == [1] and vessel.path == parts[0]
    # Any part finds the others of its set in its folder.
    assert ks(read_log_set(parts[2])) == ks(vessel)
    # usv-log says which part is missing, and the summary says the log was rotated.
    assert cli.main(["summary", *shuffled]) == 0
    shown = capsys.readouterr()
    assert "part(s) 1 of this log are not among the files" in shown.err
    assert "The log was rotated: 3 part(s) read; part(s) 1 missing" in shown.out


def test_two_logs_of_one_vessel_are_still_refused(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    _rotated_set(tmp_path / "a", parts=2)
    _rotated_set(tmp_path / "b", parts=2)
    with pytest.raises(LogError, match="a second log of vessel 9"):
        load_run([tmp_path / "a", tmp_path / "b"])


# ----- a full disk: a real one, a tmpfs of a few hundred kB -----
@pytest.fixture
def tiny_disk(tmp_path):
    """A 512 kB tmpfs mounted in tmp_path (needs root: skipped otherwise), unmounted afterwards."""
    mount = tmp_path / "disk"
    mount.mkdir()
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=512k", "tmpfs", str(mount)], capture_output=True,
                          text=True, check=False)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {made.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def fill(disk: Path, leave: int) -> Path:
    """A file taking all but `leave` bytes of the disk."""
    stat = os.statvfs(disk)
    filler = disk / "filler"
    filler.write_bytes(b"\0" * max(0, stat.f_bavail * stat.f_frsize - leave))
    return filler


def test_on_a_full_disk_messages_are_counted_and_logging_resumes_in_a_new_part(tiny_disk, capsys):
    filler = fill(tiny_disk, leave=24 * KB)
    rotation = LogRotation(max_file_mb=1, max_total_mb=10)
    log = McapLog(tiny_disk / "agent-9.mcap", flush_seconds=0.0, metadata={"vessel": "9"}, rotation=rotation,
                  retry_seconds=0.2)
    raised = []
    for k in range(100):
        try:
            write(log, range(k, k + 1))
        except OSError as error:
            raised.append((k, error.errno))
    assert len(raised) == 1 and raised[0][1] == 28          # ENOSPC, raised once
    failed_at = raised[0][0]
    assert 5 < failed_at < 40 and log.dropped == 100 - failed_at
    # Retries while the disk is still full: nothing raised, no empty part left behind, no number skipped.
    for k in range(100, 110):
        time.sleep(0.05)
        write(log, range(k, k + 1))
    assert log.dropped == 110 - failed_at and log.errors >= 2
    assert sorted(p.name for p in tiny_disk.glob("*.mcap")) == ["agent-9.mcap"]
    filler.unlink()                                           # room again
    time.sleep(0.25)
    write(log, range(110, 130))                               # the retry opens part 1
    log.close()
    assert [p.name for p in log.parts] == ["agent-9.mcap", "agent-9.part0001.mcap"]
    said = capsys.readouterr().err
    assert said.count("\n") == 1 and f"{log.errors} write error(s)" in said
    assert f"{log.dropped} message(s) not logged" in said
    run = load_run(tiny_disk)
    vessel = run.vessels["9"]
    read = ks(vessel)
    # Everything before the failure is there, then nothing until the retry, then everything: the count of
    # dropped messages is exactly what is missing.
    assert read == list(range(failed_at)) + list(range(110, 130))
    assert len(read) + log.dropped == 130
    assert vessel.unfinished and read_log(log.parts[0]).unfinished and not read_log(log.parts[1]).unfinished


def test_without_rotation_a_full_disk_drops_and_counts_to_the_end(tiny_disk):
    fill(tiny_disk, leave=24 * KB)
    log = McapLog(tiny_disk / "sim.mcap", flush_seconds=0.0, retry_seconds=0.0)
    with pytest.raises(OSError):
        write(log, range(100))
    write(log, range(100, 110))
    log.close()
    assert log.parts == [tiny_disk / "sim.mcap"] and log.dropped >= 10
    # A retry on a still full disk leaves no empty part behind.
    assert sorted(p.name for p in tiny_disk.iterdir()) == ["filler", "sim.mcap"]


@pytest.mark.slow
def test_an_agent_on_a_full_disk_keeps_control_and_stops_on_sigterm_without_a_traceback(tiny_disk, tmp_path):
    """The agent's log fills the disk within a few seconds: its ticks go on (status every tick, log_errors
    counted), it says 'logging suspended' once, and SIGTERM ends it with code 0, one line from the log and no
    traceback. The test plays its bridge: odometry at 10 Hz."""
    zenoh = pytest.importorskip("zenoh")
    from agent.contract import Odometry, encode
    from sim_bridge.fleet import free_port

    fill(tiny_disk, leave=16 * KB)
    port = free_port()
    config = tmp_path / "node.yaml"
    config.write_text(yaml.safe_dump({"clock": "wall", "log": str(tiny_disk / "agent-7.mcap"),
                                      "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]}}))
    agent = subprocess.Popen([sys.executable, "-m", "agent", "--vessel", "7", "--config", str(config)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    statuses: list[dict] = []
    session_config = zenoh.Config()
    session_config.insert_json5("scouting/multicast/enabled", "false")
    session_config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    try:
        with zenoh.open(session_config) as session:
            session.declare_subscriber("usv/7/status", lambda s: statuses.append(json.loads(s.payload.to_bytes())))
            odometry = session.declare_publisher("usv/7/sensor/odom")
            sent = [0]

            def failing_for(ticks: int) -> bool:
                odometry.put(encode(Odometry(stamp_ns=time.time_ns(), seq=sent[0], sender="7", position=(0.0, 0.0),
                                             heading=0.0)))
                sent[0] += 1
                failed = [s for s in statuses if s["health"].get("log_errors", 0) > 0]
                return len(failed) >= ticks

            assert wait_until(lambda: failing_for(20) or agent.poll() is not None, timeout=90, interval=0.1), \
                f"the log never failed: {statuses[-1:] if statuses else 'no status'}"
            assert agent.poll() is None, agent.communicate()[1]
            stopping = time.monotonic()
            agent.send_signal(signal.SIGTERM)
            _, stderr = agent.communicate(timeout=20)
            stopped_in = time.monotonic() - stopping
    finally:
        if agent.poll() is None:
            agent.kill()
            agent.communicate()
    assert agent.returncode == 0, stderr
    assert "Traceback" not in stderr, stderr
    assert stderr.count("logging suspended") == 1 and stderr.count("mcap log ") == 1, stderr
    assert "No space left on device" in stderr
    # Control went on through the failure: a status every tick (10 Hz) after it, none skipped.
    seqs = [s["seq"] for s in statuses]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    assert stopped_in < 5.0
    print(f"full disk: {sum(s['health'].get('log_errors', 0) > 0 for s in statuses)} ticks with the log failed; "
          f"SIGTERM to exit {stopped_in:.2f} s")
