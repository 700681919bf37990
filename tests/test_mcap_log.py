"""MCAP logs: readable back with schemas, an unfinished file (hard kill) read up to its last chunk, and a log
finished or at least closed however its writer ends."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import pytest
from mcap.reader import make_reader

from agent.contract import Cmd
from agent.runtime.mcap_log import McapLog, read_messages


def test_messages_and_schemas_round_trip(tmp_path):
    path = tmp_path / "run.mcap"
    with McapLog(path, metadata={"vessel": "1"}) as log:
        for k in range(50):
            log.log("usv/1/cmd", Cmd(stamp_ns=k, seq=k, sender="1", surge=0.1 * k, yaw_rate=0.0), log_time_ns=k)
        log.log("usv/1/note", {"text": "hello"}, log_time_ns=99)
    messages = list(read_messages(path))
    assert len(messages) == 51
    assert messages[10] == ("usv/1/cmd", 10, json.loads(Cmd(stamp_ns=10, seq=10, sender="1", surge=1.0,
                                                                 yaw_rate=0.0).model_dump_json()))
    with path.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    schemas = {s.name: json.loads(s.data) for s in summary.schemas.values()}
    assert schemas["Cmd"]["properties"]["surge"]["type"] == "number"
    assert summary.statistics.message_count == 51


def test_a_process_killed_hard_loses_at_most_the_last_second(tmp_path):
    """A child logs 20 messages a second and flushes every second; SIGKILL after ~2.5 s of logging."""
    path = tmp_path / "killed.mcap"
    child = textwrap.dedent(f"""
        import time, sys
        from agent.runtime.mcap_log import McapLog
        log = McapLog({str(path)!r}, flush_seconds=1.0)
        k = 0
        while True:
            log.log("tick", {{"k": k}}, log_time_ns=k)
            print(k, flush=True)
            k += 1
            time.sleep(0.05)
    """)
    process = subprocess.Popen([sys.executable, "-c", child], stdout=subprocess.PIPE, text=True)
    written = 0
    started = time.monotonic()
    while time.monotonic() - started < 2.5:
        line = process.stdout.readline()
        if line:
            written = int(line) + 1
    os.kill(process.pid, signal.SIGKILL)
    process.wait(timeout=5)
    with pytest.warns(UserWarning, match="unfinished MCAP"):
        messages = list(read_messages(path))
    ks = [m[2]["k"] for m in messages]
    assert ks == list(range(len(ks)))          # in order, nothing corrupt
    assert written - len(ks) <= 25             # at most about one second (20 per second) lost
    assert len(ks) >= 20                       # and at least the first flushed second is there


def test_a_block_that_raises_still_leaves_a_finished_log(tmp_path):
    path = tmp_path / "crashed.mcap"
    with pytest.raises(RuntimeError, match="the core failed"), McapLog(path) as log:
        log.log("tick", {"k": 1}, log_time_ns=1)
        raise RuntimeError("the core failed")
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # an unfinished file would warn
        assert list(read_messages(path)) == [("tick", 1, {"k": 1})]
    with path.open("rb") as handle:
        assert make_reader(handle).get_summary().statistics.message_count == 1   # the footer is there
    log.close()                                 # closing again does nothing
    log.log("tick", {"k": 2}, log_time_ns=2)    # nor does logging to a closed log
    assert len(list(read_messages(path))) == 1


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full to fail writes")
def test_a_write_error_is_raised_once_then_messages_are_counted_and_close_says_one_line(capsys):
    """/dev/full fails every write that reaches it, as a full disk does. The failing call raises (its caller
    counts it); later messages are dropped and counted, not raised again; close() never raises, closes the
    file once, and says in one line what the log lost."""
    log = McapLog("/dev/full", flush_seconds=0.0)
    with pytest.raises(OSError, match="No space left"):
        log.log("tick", {"k": 1}, log_time_ns=1)
    for k in (2, 3):
        log.log("tick", {"k": k}, log_time_ns=k)   # no exception: counted
    assert log.errors == 1 and log.dropped == 3
    log.close()
    assert log._file.closed
    said = capsys.readouterr().err
    assert said.count("\n") == 1 and "/dev/full: 1 write error(s)" in said and "3 message(s) not logged" in said
    assert "unfinished" in said
    log.close()                                 # a second close neither raises nor writes nor says more
    log.log("tick", {"k": 4}, log_time_ns=4)
    assert capsys.readouterr().err == "" and log.dropped == 3


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full to fail writes")
def test_a_log_whose_close_fails_does_not_raise(capsys):
    """Nothing reached the disk before close (it was all buffered): the footer's write fails, and close
    returns all the same, with the error kept and one line said (what SIGTERM on a full disk meets)."""
    log = McapLog("/dev/full")
    log.log("tick", {"k": 1}, log_time_ns=1)
    log.close()
    assert isinstance(log.close_error, OSError) and log._file.closed and log.errors >= 1
    assert capsys.readouterr().err.count("\n") == 1


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full to fail writes")
def test_a_log_that_cannot_be_finished_does_not_hide_the_error_that_ended_the_block(capsys):
    with pytest.raises(RuntimeError, match="the core failed") as raised, McapLog("/dev/full") as log:
        log.log("tick", {"k": 1}, log_time_ns=1)
        raise RuntimeError("the core failed")
    # The log's failure goes with the error: as its note, or on stderr where exceptions have none (3.10).
    said = getattr(raised.value, "__notes__", None) or capsys.readouterr().err.splitlines()
    assert any("closing the log /dev/full failed: OSError" in note for note in said)
    assert log._file.closed


def test_a_log_cut_at_any_byte_reads_up_to_its_cut_without_raising(tmp_path):
    """A part cut by a full disk may end inside a record's header: read with a warning, never struct.error
    (the launcher's analysis died on one)."""
    import warnings

    path = tmp_path / "a.mcap"
    with McapLog(path) as log:
        for k in range(200):
            log.log("t", {"k": k}, log_time_ns=k)
    data = path.read_bytes()
    for cut in range(9, len(data), 7):
        path.write_bytes(data[:cut])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            list(read_messages(path))
