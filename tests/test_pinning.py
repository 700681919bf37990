"""Pinning processes to CPUs (lab/benchmarks/pinning.py) and the runtime benchmark's pinned-agent plumbing:
the agent a PinnedFleet starts lands on its CPU, the option's sizes reach the run, the page's rows. No timings."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lab.benchmarks import pinning
from lab.benchmarks.pinned_agent import PinnedFleet, percentiles, row, section
from lab.benchmarks.pinning import AffinityUnsupported, affinities, pin, pinned, threads, usable_cpus
from lab.benchmarks.runtime import add_arguments, pinning_cpus

SCALE = Path(__file__).resolve().parents[1] / "configs" / "scenarios" / "table4_scale.yaml"
linux = pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="CPU affinity is Linux's")

# A child that starts three threads half a second after it starts, then lives on: pinned before its threads
# exist, they must take its CPUs.
LATE_THREADS = ("import threading, time; time.sleep(0.5); "
                "[threading.Thread(target=time.sleep, args=(30,), daemon=True).start() for _ in range(3)]; "
                "time.sleep(30)")


def _cpu_sets(pid: int) -> set[frozenset[int]]:
    """The distinct CPU sets of the threads of `pid`."""
    return {frozenset(cpus) for cpus in affinities(pid).values()}


def _wait_for_threads(pid: int, count: int) -> None:
    deadline = time.monotonic() + 10.0
    while len(threads(pid)) < count:
        assert time.monotonic() < deadline, f"process {pid} never had {count} threads"
        time.sleep(0.05)


@linux
def test_a_pinned_child_and_the_threads_it_starts_later_are_on_that_cpu_alone():
    cpu = usable_cpus()[-1]
    child = subprocess.Popen([sys.executable, "-c", LATE_THREADS])
    try:
        pin(child.pid, {cpu})
        _wait_for_threads(child.pid, 4)
        found = affinities(child.pid)
        assert len(found) == 4 and all(cpus == {cpu} for cpus in found.values())
    finally:
        child.kill()
        child.wait()


@linux
def test_pinned_moves_this_process_and_puts_it_back():
    before = os.sched_getaffinity(0)
    cpu = min(before)
    with pinned({cpu}):
        assert os.sched_getaffinity(0) == {cpu}
        child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
        try:
            assert _cpu_sets(child.pid) == {frozenset({cpu})}   # a child takes its parent's CPUs
        finally:
            child.kill()
            child.wait()
    assert os.sched_getaffinity(0) == before


def test_without_affinity_the_helper_says_why(monkeypatch):
    monkeypatch.delattr(os, "sched_setaffinity", raising=False)
    with pytest.raises(AffinityUnsupported, match="sched_setaffinity"):
        pin(os.getpid(), {0})
    cpus, why = pinning_cpus([4])
    assert cpus is None and why.startswith("skipped: pinning a process to a CPU needs")


def test_the_pinned_runs_need_two_cpus_and_a_size(monkeypatch):
    assert pinning_cpus([]) == (None, "not asked for (`--pinned-sizes` with no size)")
    monkeypatch.setattr("lab.benchmarks.runtime.usable_cpus", lambda: [3])
    cpus, why = pinning_cpus([4])
    assert cpus is None and "needs 2" in why
    monkeypatch.setattr("lab.benchmarks.runtime.usable_cpus", lambda: [1, 2, 5])
    assert pinning_cpus([4, 12]) == ((1, 2), "")
    lines = section([], [], None, why)
    assert lines[0].startswith("## One agent on a core of its own") and lines[2].startswith("Not measured: skipped")


def test_the_option_takes_sizes_or_none():
    import argparse

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert parser.parse_args([]).pinned_sizes == [4, 12]
    assert parser.parse_args(["--pinned-sizes", "4"]).pinned_sizes == [4]
    assert parser.parse_args(["--pinned-sizes"]).pinned_sizes == []
    with pytest.raises(SystemExit):
        parser.parse_args(["--pinned-sizes", "0"])
    # each pinned size once with the other agents as the launcher is, once at niceness 19
    assert parser.parse_args([]).others_nice == [0, 19]
    assert parser.parse_args(["--others-nice", "5"]).others_nice == [5]
    for wrong in ("20", "-1"):
        with pytest.raises(SystemExit):
            parser.parse_args(["--others-nice", wrong])


@linux
def test_a_pinned_fleet_pins_its_first_vessels_agent_as_it_starts_and_no_other(tmp_path, monkeypatch):
    """Fleet._start stands in for the agent with a process that starts threads late, as an agent does."""
    cpu = usable_cpus()[-1]
    started = []

    def start(self, name, command):
        started.append(subprocess.Popen([sys.executable, "-c", LATE_THREADS]))
        return started[-1]

    monkeypatch.setattr("sim_bridge.fleet.Fleet._start", start)
    fleet = PinnedFleet(SCALE, "n4_r5", tmp_path, mode="realtime", cpus={cpu}, others_nice=19)
    assert fleet.pinned_vessel == fleet.scenario.world.vessels[0].id
    try:
        for vessel in fleet.scenario.world.vessels[:2]:
            fleet.start_agent(vessel.id)
        first, second = started
        _wait_for_threads(first.pid, 4)
        _wait_for_threads(second.pid, 4)
        assert _cpu_sets(first.pid) == {frozenset({cpu})}
        assert _cpu_sets(second.pid) == {frozenset(os.sched_getaffinity(0))}
        # The other agent at niceness 19, every thread of it, the ones started later too; the pinned one as
        # this process is.
        mine = os.getpriority(os.PRIO_PROCESS, 0)
        assert {os.getpriority(os.PRIO_PROCESS, tid) for tid in threads(second.pid)} == {19}
        assert {os.getpriority(os.PRIO_PROCESS, tid) for tid in threads(first.pid)} == {mine}
    finally:
        for process in started:
            process.kill()
            process.wait()


def test_the_scheduler_figures_are_per_tick_between_the_two_reads(tmp_path):
    fleet = PinnedFleet(SCALE, "n4_r5", tmp_path, mode="realtime", cpus={0})
    assert fleet.waits() is None                      # the run ended before the second read
    cpu_before = {"busy": 100.0, "idle": 50.0, "steal": 1.0}
    cpu_after = {"busy": 115.0, "idle": 54.0, "steal": 2.0}   # 20 s of the CPU: 15 busy, 4 idle, 1 stolen
    fleet.snapshots = [(5.0, (1_000_000_000, 0), (0, 0), cpu_before),
                       (25.0, (1_400_000_000, 200_000_000), (600_000_000, 1_000_000_000), cpu_after)]
    # 20 s at dt 0.1 s: 200 ticks; the agent ran 0.4 s (2 ms a tick) and waited 0.2 s (1 ms); the bridge ran
    # 0.6 s (3 ms) and waited 1 s (5 ms); others had 15 - 0.4 of the CPU's 20 s, the hypervisor 1.
    assert fleet.scenario.world.dt == 0.1
    assert fleet.waits() == pytest.approx({"run_ms": 2.0, "wait_ms": 1.0, "bridge_run_ms": 3.0,
                                           "bridge_wait_ms": 5.0, "others": 14.6 / 20, "steal": 1 / 20})


def test_the_row_sets_the_pinned_agent_against_itself_unpinned_and_the_bare_round_trip():
    pinned_ms = [float(v) for v in range(1, 101)]          # p50 50.5, p99 99.01, max 100 (numpy's linear rule)
    unpinned_ms = [2.0 * v for v in pinned_ms]             # twice as long: ratios 0.50
    bare = {"round_trip_p50": 0.5, "round_trip_p99": 1.0}
    assert percentiles(pinned_ms) == pytest.approx((50.5, 99.01, 100.0))
    cells = row(4, "1", pinned_ms, unpinned_ms, bare, [3.0, 1.0, 2.0], 100, "agent 9/9", 19)
    assert cells == [4, 19, "1", "50.50", "99.01", "100.00", "no", "101.00 / 198.02", "0.50 / 0.50",
                     "0.500 / 1.000", "101.0x / 99.0x", "2.00", "100/100", "agent 9/9"]
    fast = row(4, "1", [1.0] * 99 + [4.0], None, bare, [], 100, "")
    assert fast[1] == 0 and fast[6] == "yes" and fast[7] == fast[8] == "-" and fast[11] == "-"


def test_the_helper_reads_cpus_from_this_kernel(monkeypatch):
    if not hasattr(os, "sched_getaffinity"):
        pytest.skip("CPU affinity is Linux's")
    assert usable_cpus() == sorted(os.sched_getaffinity(0))
    monkeypatch.setattr(pinning, "Path", lambda _: Path("/no/such/proc"))
    with pytest.raises(AffinityUnsupported):
        usable_cpus()
