"""A `--cluster` address that accepts the connection and never answers (not a Dask scheduler, or one stuck):
the command says so in one line within its deadline instead of hanging without a word (lab/harness/parallel.py)."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import pytest

pytest.importorskip("distributed", reason="the lab-cluster extra (Dask) is not installed")

from lab.harness.parallel import FIRST_ANSWER_SECONDS  # noqa: E402


@pytest.fixture
def silent_server() -> Iterator[str]:
    """A loopback TCP server that accepts every connection and never sends a byte."""
    server = socket.create_server(("127.0.0.1", 0))
    accepted: list[socket.socket] = []
    stop = threading.Event()

    def serve() -> None:
        server.settimeout(0.1)
        while not stop.is_set():
            try:
                accepted.append(server.accept()[0])
            except OSError:
                continue

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield f"tcp://127.0.0.1:{server.getsockname()[1]}"
    finally:
        stop.set()
        thread.join()
        for connection in accepted:
            connection.close()
        server.close()
        assert accepted, "the command never connected"


def _compare(address: str, *options: str) -> tuple[subprocess.CompletedProcess, float]:
    started = time.monotonic()
    command = [sys.executable, "-m", "lab", "compare", "--runs", "2", "--no-diagnosis", "--cluster", address]
    done = subprocess.run([*command, *options], capture_output=True, text=True, timeout=180)
    return done, time.monotonic() - started


@pytest.mark.slow
def test_compare_gives_up_on_a_silent_scheduler_by_the_default_deadline(silent_server, tmp_path):
    done, seconds = _compare(silent_server, "--out", str(tmp_path))
    lines = done.stderr.strip().splitlines()
    print(f"usv-lab compare --cluster (silent): exit {done.returncode} after {seconds:.1f} s: "
          f"{done.stderr.strip()}")
    assert done.returncode == 2, done.stderr[-2000:]
    assert lines and silent_server in lines[-1]
    assert f"did not answer within {FIRST_ANSWER_SECONDS:g} s" in lines[-1]
    assert "Traceback" not in done.stderr
    assert not list(tmp_path.iterdir()), "no page for a campaign that never ran"


@pytest.mark.slow
def test_the_deadline_is_an_option(silent_server, tmp_path):
    done, seconds = _compare(silent_server, "--out", str(tmp_path), "--cluster-timeout", "2")
    print(f"usv-lab compare --cluster (silent) --cluster-timeout 2: exit {done.returncode} after "
          f"{seconds:.1f} s")
    assert done.returncode == 2, done.stderr[-2000:]
    assert "did not answer within 2 s" in done.stderr.strip().splitlines()[-1]
