"""The fleet launcher: separate OS processes over Zenoh on loopback, a run folder, metrics from the logs."""

from __future__ import annotations

import json
import math
import re
import socket
import subprocess
import sys

import numpy as np
import pytest
import yaml
from conftest import bridge_counts

from agent.runtime.mcap_log import read_messages
from mission_log.reader import read_log
from mission_log.series import truth_of
from sim_bridge.fleet import PORT_TAKEN, Fleet
from sim_bridge.scenario import with_duration

pytestmark = pytest.mark.slow   # the fleet's processes over Zenoh


def test_fleet_run_leaves_a_run_folder_with_logs_plot_and_metrics(tmp_path, short_scenario):
    scenario = short_scenario
    result = subprocess.run([sys.executable, "-m", "sim_bridge.fleet_cli", "run", str(scenario),
                             "--out", str(tmp_path / "runs")], capture_output=True, text=True, check=False, timeout=240)
    assert result.returncode == 0, result.stderr
    (folder,) = list((tmp_path / "runs").iterdir())
    for name in ("sim.mcap", "agent-1.mcap", "agent-2.mcap", "agent-3.mcap", "metrics.json", "summary.md",
                 "trajectories.png"):
        assert (folder / name).exists(), name
    for figure in ("trajectories.png", "errors.png", "ranges.png"):
        assert (folder / figure).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["ticks"] == 121 and metrics["vessels"] == ["1", "2", "3"]
    # It ran to its end and says so; the summary has no word of a cut-short run.
    assert metrics["ticks_planned"] == 121 and metrics["complete"] is True and metrics["cut_short"] is None
    assert "cut short" not in (folder / "summary.md").read_text() and "121 ticks of 121 planned" in result.stdout
    # It says how fast it ran: the tick loop's real-time factor, and the whole launch's.
    said = re.search(r"12\.1 s of mission in ([0-9.]+) s of ticks: ([0-9.]+)x real time \(([0-9.]+)x with", result.stderr)
    assert said, result.stderr
    assert float(said[2]) == pytest.approx(12.1 / float(said[1]), rel=0.02) and float(said[3]) < float(said[2])
    # Every child's pid is on record (tests/test_launcher_faults.py checks that none outlives the launcher).
    assert set(json.loads((folder / "processes.json").read_text())) == {"launcher", "bridge", "agent-1", "agent-2",
                                                                          "agent-3"}
    assert all(math.isfinite(metrics[k]) for k in ("mean_e_ij", "mean_e_io", "mean_e_c"))
    assert metrics["settling_time"] is not None        # the fleet formed the circle over Zenoh
    assert metrics["mean_e_io"] < 1.0 and metrics["mean_e_ij"] < 1.0
    # In lockstep the bridge waits for every command: none missed, no vessel stopped, nothing refused.
    assert bridge_counts((folder / "bridge.log").read_text()) == {"ticks": 121, "missed": 0, "watchdog": 0,
                                                                   "refused": 0}
    # Each process ends its log with what the run cost it: every tick counted, CPU time measured.
    for name, topic in [("sim.mcap", "/bridge/summary"), *((f"agent-{i}.mcap", f"/{i}/summary") for i in "123")]:
        (summary,) = [m for t, _, m in read_messages(folder / name) if t == topic]
        assert summary["ticks"] == 121 and 0.0 < summary["cpu_seconds"] and 0.0 < summary["loop_seconds"]
        if name != "sim.mcap":   # and an agent, the part of it inside the core's step
            assert 0.0 < summary["core_cpu_seconds"] < summary["cpu_seconds"]
            # and its reaction times, clock to command, every tick: shorter than a lockstep tick, which waits
            # for every command
            reaction = summary["reaction_ms"]
            assert reaction["ticks"] == 121 and 0.0 < reaction["p50"] <= reaction["p99"] <= reaction["max"]
            assert reaction["p50"] < 1e3 * summary["loop_seconds"] / summary["ticks"]
            # the tick thread's CPU over part of each of those stretches: never more, tick by tick
            cpu = summary["reaction_cpu_ms"]
            assert cpu["ticks"] == 121 and 0.0 < cpu["p50"] <= reaction["p50"] and cpu["p99"] <= reaction["p99"]


def test_a_shipped_scenario_runs_by_name_from_anywhere_with_the_default_estimator_and_says_how_to_watch(tmp_path):
    """`usv-fleet run table2_estimators --duration 2` from another directory: the file found by its name, the
    variant that runs the product's default estimator (raw_range, not the file's first, rls), 2 s simulated,
    and a line that says how to reach the running fleet with usv-op."""
    result = subprocess.run([sys.executable, "-m", "sim_bridge.fleet_cli", "run", "table2_estimators", "--duration", "2",
                             "--out", str(tmp_path / "runs")], capture_output=True, text=True, check=False, timeout=240,
                            cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    (folder,) = list((tmp_path / "runs").iterdir())
    assert folder.name.startswith("table2_estimators-raw_range-")
    assert json.loads((folder / "metrics.json").read_text())["ticks"] == 21
    port = yaml.safe_load((folder / "bridge.yaml").read_text())["zenoh"]["listen"][0].rsplit(":", 1)[1]
    assert f"usv-op --connect tcp/127.0.0.1:{port} status" in result.stderr
    wrong = subprocess.run([sys.executable, "-m", "sim_bridge.fleet_cli", "run", "no_such_scenario"],
                           capture_output=True, text=True, check=False, timeout=60, cwd=tmp_path)
    assert wrong.returncode == 2 and "known in" in wrong.stderr and "table2_estimators" in wrong.stderr
    short = subprocess.run([sys.executable, "-m", "sim_bridge.fleet_cli", "run", "cold_start", "--duration", "-1"],
                           capture_output=True, text=True, check=False, timeout=60, cwd=tmp_path)
    assert short.returncode == 2 and "--duration -1" in short.stderr


def test_unknown_variant_is_a_clear_error(tmp_path, short_scenario):
    scenario = short_scenario
    result = subprocess.run([sys.executable, "-m", "sim_bridge.fleet_cli", "run", str(scenario), "--variant", "x",
                             "--out", str(tmp_path / "runs")], capture_output=True, text=True, check=False, timeout=60)
    assert result.returncode == 2 and "no variant 'x'" in result.stderr


def test_a_taken_bridge_port_is_given_up_for_a_fresh_one(tmp_path, short_scenario):
    """Another process binds the sim bridge's port between the launcher drawing it and the bridge binding
    it: the bridge exits at start-up, and the launcher starts it again on another port."""
    (tmp_path / "short").mkdir()
    fleet = Fleet(with_duration(short_scenario, tmp_path / "short", 2.0), None, tmp_path / "runs")
    taken = fleet.bridge_port
    with socket.socket() as thief:
        thief.bind(("127.0.0.1", taken))
        thief.listen()
        folder = fleet.run(timeout=120)
    assert fleet.bridge_port != taken
    assert PORT_TAKEN in (folder / "bridge-attempt1.log").read_text()
    assert bridge_counts((folder / "bridge.log").read_text())["missed"] == 0
    for vessel in ("1", "2", "3"):   # every agent was told the new port
        settings = yaml.safe_load((folder / f"agent-{vessel}.yaml").read_text())
        assert settings["zenoh"]["connect"] == [f"tcp/127.0.0.1:{fleet.bridge_port}"]


def test_an_agent_that_exits_on_its_own_fails_the_launch_and_is_named(tmp_path, short_scenario):
    """The mission must not run on without a vessel's agent (the bridge would stop that vessel at every
    tick, and the launch would end with exit code 0): the launcher fails it, naming the agent."""
    fleet = Fleet(short_scenario, None, tmp_path / "runs")
    (fleet.folder / "agent-2.yaml").write_text("clock: sundial\n")   # agent 2 refuses it and exits with 2
    with pytest.raises(RuntimeError, match=r"agent of vessel 2 exited with code 2 during the mission.*clock"):
        fleet.run(timeout=120)
    assert fleet.bridge.poll() is not None and all(p.poll() is not None for p in fleet.agents.values())


def test_the_moderate_sea_runs_as_a_real_time_fleet_of_processes_within_the_otters_limits(tmp_path):
    """Issue 30, item 6: `usv-fleet run sea_states --variant moderate --mode realtime`: the Otter's hulls, the
    water and the realistic sensors behind the sim bridge at the wall clock's pace, an agent process per vessel.
    Every command stays within the preset's limits; the hulls move as hulls (from rest, no faster than the
    Otter can go plus the water); the logs score the run."""
    result = subprocess.run([sys.executable, "-m", "sim_bridge.fleet_cli", "run", "sea_states", "--variant", "moderate",
                             "--mode", "realtime", "--duration", "12", "--out", str(tmp_path / "runs")],
                            capture_output=True, text=True, check=False, timeout=240, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    (folder,) = list((tmp_path / "runs").iterdir())
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["complete"] is True and metrics["vessels"] == ["1", "2", "3", "4"]
    assert all(math.isfinite(metrics[k]) for k in ("mean_e_ij", "mean_e_io", "mean_e_c"))
    for vessel in "1234":
        commands = [m for _, m in read_log(folder / f"agent-{vessel}.mcap").topic("cmd")]
        assert len(commands) >= 100                                  # 10 Hz over 12 s, less the start
        surge = np.array([c["surge"] for c in commands])
        yaw_rate = np.array([c["yaw_rate"] for c in commands])
        assert np.all(surge <= 3.0) and np.all(surge >= -1.0) and np.all(np.abs(yaw_rate) <= 0.3)
    truth = truth_of(read_log(folder / "sim.mcap"))
    dt = np.diff(truth.t_ns) * 1e-9
    for vessel, path in truth.vessels.items():
        speed = np.linalg.norm(np.diff(path, axis=0), axis=1) / dt
        # from rest: no kinematic jump to the commanded speed on the first tick; never beyond the Otter's
        # 3.09 m/s through the water plus the moderate sea's current (0.3 m/s and 0.01/s shear over ~20 m)
        assert speed[0] < 0.5 and np.nanmax(speed) < 3.09 + 0.6, (vessel, speed[:3], np.nanmax(speed))
