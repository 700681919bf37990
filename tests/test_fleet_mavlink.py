"""`usv-fleet run --vehicle mavlink`: the fleet with each vessel behind an ArduPilot stand-in and a usv-driver,
real MAVLink on UDP and real Zenoh, in lockstep (against the same seed through the sim bridge directly) and
in real time with an agent killed mid-mission."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from conftest import bridge_counts

from agent.runtime.mcap_log import read_messages
from sim_bridge.fleet import launch
from sim_bridge.scenario import with_duration

pytestmark = pytest.mark.slow   # ten processes, UDP and Zenoh

DURATION = 6.0
TICKS = 61


def fleet(tmp_path, scenario, *extra: str) -> tuple[subprocess.CompletedProcess, dict, object]:
    out = tmp_path / ("runs-" + "-".join(extra).replace("--", ""))
    result = subprocess.run([sys.executable, "-m", "sim_bridge.fleet_cli", "run", str(scenario), "--duration",
                             str(DURATION), "--out", str(out), *extra], capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stderr[-3000:]
    (folder,) = list(out.iterdir())
    return result, json.loads((folder / "metrics.json").read_text()), folder


def commands(folder, vessel: str) -> int:
    return sum(topic == f"usv/{vessel}/cmd" for topic, _, _ in read_messages(folder / f"agent-{vessel}.mcap"))


def test_a_lockstep_fleet_through_mavlink_matches_the_sim_bridge_and_every_command_reaches_its_standin(
        tmp_path, short_scenario):
    _, direct, _ = fleet(tmp_path, short_scenario)
    result, through, folder = fleet(tmp_path, short_scenario, "--vehicle", "mavlink")
    assert through["ticks"] == TICKS and through["complete"]
    # The same world on the same commands: the metrics as the sim bridge's alone (the issue asks within 10 %;
    # lockstep gives the same to 1e-3, the wire's float32 aside), and it settles when that does.
    for name in ("mean_e_ij", "mean_e_io", "mean_e_c"):
        assert through[name] == pytest.approx(direct[name], rel=1e-3), (name, through, direct)
    assert (through["settling_time"] is None) == (direct["settling_time"] is None)
    assert set(json.loads((folder / "processes.json").read_text())) == {
        "launcher", "bridge", *(f"{kind}-{v}" for kind in ("agent", "standin", "driver") for v in "123")}
    # Each tick waited until the stand-ins drove its commands: none missed, nothing stopped, nothing refused.
    assert bridge_counts((folder / "bridge.log").read_text()) == {"ticks": TICKS, "missed": 0, "watchdog": 0,
                                                                   "refused": 0}
    figures = json.loads((folder / "mavlink.json").read_text())
    for vessel, row in figures["vessels"].items():
        assert row["modes"][:1] == ["GUIDED"], row   # GUIDED for the mission (HOLD as the driver stops, if in time)
        assert row["fresh"] == commands(folder, vessel) == TICKS, row   # every command, as a set point
        driver = (folder / f"driver-{vessel}.log").read_text()
        assert f"'sensor/odom': {TICKS}" in driver, driver[-500:]   # the agent's odometry: the driver's
    assert "MAVLink:" in result.stderr and "added latency p50" in result.stderr


def test_a_real_time_fleet_through_mavlink_puts_a_killed_agents_vessel_in_hold(tmp_path, short_scenario):
    path = with_duration(short_scenario, tmp_path, DURATION)

    def kill(fleet, sim_seconds: float) -> None:
        if sim_seconds >= 3.0 and "1" not in fleet.killed:
            fleet.kill("1")

    folder = launch(path, None, tmp_path / "runs", None, mode="realtime", vehicle="mavlink", on_time=kill)
    figures = json.loads((folder / "mavlink.json").read_text())
    killed = figures["vessels"]["1"]
    assert killed["modes"][:2] == ["GUIDED", "HOLD"] and killed["hold_after_kill_s"] is not None, killed
    assert 0.0 < killed["hold_after_kill_s"]
    for vessel in "23":   # the others: every command reached the stand-in as a set point, at the agent's rate
        assert figures["vessels"][vessel]["fresh"] == commands(folder, vessel), figures["vessels"][vessel]
    print(f"HOLD {killed['hold_after_kill_s']:.3f} s after SIGKILL; added latency p50 "
          f"{figures['added_ms_p50']:.2f} ms, p99 {figures['added_ms_p99']:.2f} ms "
          f"({figures['fresh_setpoints']} set points)")
