"""How the agent and both bridges stop (`agent.runtime.process.stop_on_signals`), with real signals to real
processes: SIGTERM sets the stop flag and starts the deadline; a process still there at the deadline writes
every thread's stack to stderr and exits with code 1; SIGUSR1 writes the stacks and changes nothing else."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time

import pytest

pytestmark = pytest.mark.slow   # real processes, real time

# A process stopped the way the agent is: `teardown` is what it does once the stop flag is set.
PROGRAM = textwrap.dedent("""
    import sys, threading, time
    from agent.runtime.process import stop_on_signals

    def tick_loop(stopping):
        print("up", flush=True)
        while not stopping.is_set():
            time.sleep(0.01)

    def stuck_in_teardown():
        time.sleep(60)

    def quick_teardown():
        time.sleep(0.3)

    stopping = threading.Event()
    stop_on_signals(stopping, deadline=float(sys.argv[1]))
    tick_loop(stopping)
    {teardown}()
    print("stopped", flush=True)
""")


def start(teardown: str, deadline: float) -> subprocess.Popen:
    process = subprocess.Popen([sys.executable, "-c", PROGRAM.format(teardown=teardown), str(deadline)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert process.stdout.readline() == "up\n"
    return process


def test_a_process_stuck_after_sigterm_writes_its_stacks_and_exits_at_the_deadline():
    process = start("stuck_in_teardown", deadline=1.0)
    signalled = time.monotonic()
    process.send_signal(signal.SIGTERM)
    out, err = process.communicate(timeout=30)
    took = time.monotonic() - signalled
    assert process.returncode == 1, err
    assert took >= 1.0, took                     # not before the deadline
    assert "stopped" not in out
    assert "Timeout (0:00:01)!" in err, err
    assert "in stuck_in_teardown" in err, err    # the frame it was stuck in, named


def test_a_process_that_stops_within_the_deadline_exits_normally():
    process = start("quick_teardown", deadline=3.0)
    process.send_signal(signal.SIGTERM)
    out, err = process.communicate(timeout=30)
    assert process.returncode == 0, err
    assert out == "stopped\n"
    assert "Timeout" not in err, err


def test_sigint_stops_the_same_way():
    process = start("stuck_in_teardown", deadline=0.5)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=30)
    assert process.returncode == 1 and "Timeout (0:00:00.500000)!" in err, err


def test_sigusr1_writes_every_threads_stack_and_the_process_goes_on():
    process = start("quick_teardown", deadline=3.0)
    try:
        process.send_signal(signal.SIGUSR1)
        time.sleep(0.5)
        assert process.poll() is None                 # still running, not stopped by it
        process.send_signal(signal.SIGTERM)
        out, err = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0 and out == "stopped\n", err
    assert "Current thread" in err and "in tick_loop" in err, err
    assert "Timeout" not in err


def test_a_second_sigterm_does_not_restart_the_deadline():
    """The deadline counts from the first signal: a supervisor repeating SIGTERM cannot keep a stuck process."""
    process = start("stuck_in_teardown", deadline=2.0)
    signalled = time.monotonic()
    process.send_signal(signal.SIGTERM)
    time.sleep(1.5)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=30)
    took = time.monotonic() - signalled
    assert process.returncode == 1 and "Timeout (0:00:02)!" in err, err
    assert took < 1.5 + 2.0, took   # a restarted deadline would have ended it 3.5 s after the first signal
