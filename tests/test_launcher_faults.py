"""`usv-fleet run` when things go wrong, with real processes: the launcher stopped by SIGTERM or SIGINT, or
killed outright; the sim bridge or an agent ending mid-run. Every time: no process of the run survives, the
exit code is not 0 and a line says why, and the summary says the run was cut short (ticks done of planned).

Which processes belong to a run is read two ways, so that neither can hide a survivor: the run folder's
`processes.json`, and /proc (every child of the launcher seen while the mission ran)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest
from conftest import wait_until

from agent.runtime.mcap_log import read_messages
from mission_log.reader import load_run
from sim_bridge import fleet as fleet_module
from sim_bridge.fleet import Fleet
from sim_bridge.scenario import with_duration

pytestmark = pytest.mark.slow   # the fleet's processes over Zenoh

LONG = 600.0                    # s of sim time: far more than any test lets run (lockstep: about a minute)
PLANNED = 6001


class Launch:
    """`usv-fleet run` of the short scenario lengthened to LONG, as a child of the test."""

    def __init__(self, tmp_path: Path, scenario: Path, duration: float = LONG) -> None:
        (tmp_path / "scenario").mkdir()
        path = with_duration(scenario, tmp_path / "scenario", duration)
        self.out = tmp_path / "runs"
        self.stdout, self.stderr = (tmp_path / "launcher.out").open("w+"), (tmp_path / "launcher.err").open("w+")
        self.process = subprocess.Popen([sys.executable, "-m", "sim_bridge.fleet_cli", "run", str(path), "--out",
                                         str(self.out)], stdout=self.stdout, stderr=self.stderr)
        self.children: dict[int, str] = {}    # pid -> command line, of every child seen

    @property
    def folder(self) -> Path:
        (folder,) = list(self.out.iterdir())
        return folder

    def note_children(self) -> None:
        launcher = Path(f"/proc/{self.process.pid}/cmdline")
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                fields = stat.read_text().rsplit(")", 1)[1].split()
                if int(fields[1]) == self.process.pid:
                    pid = int(stat.parent.name)
                    command = (stat.parent / "cmdline").read_bytes()
                    # A child caught between fork and exec still shows the launcher's command line: noted as
                    # that, it would later count as a reused pid, and so as gone while it still runs.
                    if command != launcher.read_bytes():
                        self.children.setdefault(pid, command.decode(errors="replace"))
            except (OSError, IndexError, ValueError):
                continue    # a process that ended while we looked

    def ticks(self) -> int:
        """/truth messages the sim bridge has logged so far (its file is unfinished while it runs)."""
        path = self.folder / "sim.mcap" if self.out.exists() and any(self.out.iterdir()) else None
        if path is None or not path.exists():
            return 0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return sum(topic == "/truth" for topic, _, _ in read_messages(path))

    def wait_for_ticks(self, ticks: int) -> None:
        def running() -> bool:
            self.note_children()
            return self.process.poll() is not None or self.ticks() >= ticks
        assert wait_until(running, timeout=180, interval=0.2), "the mission never got going"
        assert self.process.poll() is None, self.output()
        self.note_children()
        recorded = json.loads((self.folder / "processes.json").read_text())
        assert set(recorded) == {"launcher", "bridge", "agent-1", "agent-2", "agent-3"}
        assert recorded["launcher"] == self.process.pid
        # /proc and processes.json agree on who the children are.
        assert {pid for name, pid in recorded.items() if name != "launcher"} <= set(self.children)

    def wait(self, seconds: float = 60) -> float:
        started = time.monotonic()
        self.process.wait(timeout=seconds)
        return time.monotonic() - started

    def output(self) -> str:
        self.stderr.seek(0)
        return self.stderr.read()

    def survivors(self) -> list[str]:
        """Children of the run still alive (a zombie is dead; a reused pid runs another command)."""
        alive = []
        for pid, command in self.children.items():
            try:
                stat = Path(f"/proc/{pid}/stat").read_text()
                now = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
            except OSError:
                continue
            if stat.rsplit(")", 1)[1].split()[0] != "Z" and now == command:
                alive.append(f"{pid}: {command}")
        return alive

    def stacks_of_survivors(self) -> str:
        """The survivors, and what each was doing: SIGUSR1 makes a process of the run write every thread's
        stack to its log (stop_on_signals), even while it is stuck in native code."""
        alive = self.survivors()
        for line in alive:
            subprocess.run(["kill", "-USR1", line.split(":")[0]], check=False, capture_output=True)
        time.sleep(1.0)
        logs = [f"--- {log.name}\n{log.read_text()[-6000:]}" for log in sorted(self.folder.glob("*.log"))]
        return "\n".join(alive + logs)

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        for pid in self.children:   # whatever a failed test left behind
            try:
                Path(f"/proc/{pid}").stat()
                subprocess.run(["kill", "-9", str(pid)], check=False, capture_output=True)
            except OSError:
                pass
        self.stdout.close()
        self.stderr.close()


@pytest.fixture
def launch(tmp_path, short_scenario):
    made: list[Launch] = []

    def start(duration: float = LONG) -> Launch:
        made.append(Launch(tmp_path, short_scenario, duration))
        return made[-1]

    yield start
    for one in made:
        one.close()


def cut_short(folder: Path) -> tuple[dict, str]:
    return json.loads((folder / "metrics.json").read_text()), (folder / "summary.md").read_text()


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_stops_every_process_and_says_the_run_was_cut_short(launch, signum):
    run = launch()
    run.wait_for_ticks(30)
    signalled = time.monotonic()
    run.process.send_signal(signum)
    assert wait_until(lambda: run.survivors() == [], timeout=30, interval=0.01), run.survivors()
    children_gone = time.monotonic() - signalled
    took = run.wait() + children_gone
    said = run.output()
    name = signal.Signals(signum).name
    assert run.process.returncode == 128 + signum, said
    assert f"interrupted by {name}" in said and "stopped the sim bridge and 3 agent(s)" in said, said
    assert "Traceback" not in said, said
    assert run.survivors() == []
    metrics, summary = cut_short(run.folder)
    done = metrics["ticks"]
    assert 30 <= done < PLANNED and metrics["ticks_planned"] == PLANNED and metrics["complete"] is False
    assert f"**This run was cut short: {done} of {PLANNED} ticks" in summary and f"interrupted by {name}" in summary
    assert f"cut short after {done} of {PLANNED} ticks" in said
    # The agents were stopped, not killed: each finished its log, and so did the bridge.
    logs = load_run(run.folder)
    assert sorted(logs.vessels) == ["1", "2", "3"] and logs.unfinished == []
    assert logs.sim.last("/bridge/summary")["ticks"] == done
    # Stopping takes the agents' and the bridge's clean shutdown, not the 10 s SIGKILL deadline; the rest is
    # the analysis of the logs there are (the plots).
    assert took < 30
    assert children_gone < 10     # well within STOP_SECONDS: nobody needed SIGKILL
    print(f"{name}: {done} of {PLANNED} ticks; every child gone {children_gone:.2f} s after the signal, the "
          f"launcher {took:.2f} s after it")


def test_a_launcher_killed_outright_leaves_no_process_behind(launch):
    """SIGKILL cannot be handled: the children's parent-death signal (SIGTERM from the kernel) stops them."""
    run = launch()
    run.wait_for_ticks(30)
    killed = time.monotonic()
    run.process.kill()
    run.wait()
    assert wait_until(lambda: run.survivors() == [], timeout=20, interval=0.01), run.stacks_of_survivors()
    print(f"launcher SIGKILL: every child gone {time.monotonic() - killed:.2f} s later")
    # Gone, but perhaps only at their stop deadline (agent.runtime.process.STOP_DEADLINE): then their logs hold
    # every thread's stack at that moment, which is what a hang there needs to be understood.
    for log in sorted(run.folder.glob("*.log")):
        if "Timeout (" in log.read_text():
            warnings.warn(f"{log.name} stopped only at its deadline:\n{log.read_text()[-6000:]}", stacklevel=1)
    # They were stopped with SIGTERM, so the agents still finished their logs. (Waited for: on a loaded machine
    # /proc has, rarely, shown no child left while an agent was still closing its log; a killed agent would
    # never finish it.)
    assert wait_until(lambda: load_run(run.folder).unfinished == [], timeout=10, interval=0.1), \
        load_run(run.folder).unfinished


def test_a_sim_bridge_that_ends_early_fails_the_run(launch):
    """The bridge stopped from outside with SIGTERM exits 0 after the tick it was on: once a normal-looking
    run from part of the ticks, now a failure that says how many ran."""
    run = launch()
    run.wait_for_ticks(30)
    bridge = json.loads((run.folder / "processes.json").read_text())["bridge"]
    subprocess.run(["kill", "-TERM", str(bridge)], check=True)
    run.wait()
    said = run.output()
    metrics, summary = cut_short(run.folder)
    done = metrics["ticks"]
    assert run.process.returncode == 1, said
    assert f"the sim bridge exited with code 0 after {done} of {PLANNED} ticks" in said, said
    assert 30 <= done < PLANNED and not metrics["complete"] and "This run was cut short" in summary
    assert run.survivors() == []


def test_an_agent_killed_mid_run_fails_the_run_and_is_named(launch):
    run = launch()
    run.wait_for_ticks(30)
    agent = json.loads((run.folder / "processes.json").read_text())["agent-2"]
    subprocess.run(["kill", "-KILL", str(agent)], check=True)
    run.wait()
    said = run.output()
    assert run.process.returncode == 1, said
    assert "the agent of vessel 2 exited with code -9 during the mission" in said, said
    metrics, summary = cut_short(run.folder)
    assert not metrics["complete"] and metrics["ticks"] < PLANNED
    assert "the agent of vessel 2 exited with code -9" in summary
    assert run.survivors() == []


def test_a_child_that_ignores_sigterm_is_killed_after_the_deadline(tmp_path, short_scenario, monkeypatch):
    """The launcher waits STOP_SECONDS for its children after SIGTERM, then SIGKILLs the rest, and says so."""
    monkeypatch.setattr(fleet_module, "STOP_SECONDS", 1.0)
    fleet = Fleet(short_scenario, None, tmp_path / "runs")
    stubborn = "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print('up', flush=True); time.sleep(60)"
    polite = "import time; print('up', flush=True); time.sleep(60)"
    fleet.agents = {"1": fleet._start("agent-1", [sys.executable, "-c", stubborn]),
                    "2": fleet._start("agent-2", [sys.executable, "-c", polite])}
    assert wait_until(lambda: all("up" in (fleet.folder / f"agent-{v}.log").read_text() for v in "12"), 20)
    started = time.monotonic()
    fleet._stop()
    took = time.monotonic() - started
    assert fleet.hard_killed == ["agent-1"]
    assert fleet.agents["1"].returncode == -signal.SIGKILL and fleet.agents["2"].returncode == -signal.SIGTERM
    assert 1.0 <= took < 3.0


def test_an_agent_asked_for_its_stacks_writes_them_and_goes_on(launch):
    """`kill -USR1` on a running agent: every thread's Python stack in its log (here agent-2.log, its stderr),
    and the mission goes on; it stops cleanly afterwards."""
    run = launch()
    run.wait_for_ticks(30)
    agent = json.loads((run.folder / "processes.json").read_text())["agent-2"]
    log = run.folder / "agent-2.log"
    subprocess.run(["kill", "-USR1", str(agent)], check=True)
    # The dump is written thread by thread: read it once the tick loop's thread is in it, not at its first
    # line (a CI run read it half written, 2026-12-03).
    def dumped() -> bool:
        stacks = log.read_text()
        return "Current thread" in stacks and "agent/shell/node.py" in stacks and "in _run" in stacks

    assert wait_until(dumped, timeout=10), log.read_text()     # the tick loop's thread, named
    done = run.ticks()
    run.wait_for_ticks(done + 20)              # still ticking: the launcher and every process still run
    run.process.send_signal(signal.SIGTERM)
    run.wait()
    assert run.process.returncode == 128 + signal.SIGTERM and "exited with code" not in run.output(), run.output()
    assert load_run(run.folder).unfinished == []
    assert "Timeout (" not in log.read_text()
