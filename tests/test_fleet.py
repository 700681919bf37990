"""The fleet launcher: separate OS processes over Zenoh on loopback, a run folder, metrics from the logs."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

pytest.importorskip("zenoh")

def test_fleet_run_leaves_a_run_folder_with_logs_plot_and_metrics(tmp_path, short_scenario):
    scenario = short_scenario
    result = subprocess.run([sys.executable, "-m", "sim_bridge.fleet_cli", "run", str(scenario),
                             "--out", str(tmp_path / "runs")], capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stderr
    (folder,) = list((tmp_path / "runs").iterdir())
    for name in ("sim.mcap", "agent-1.mcap", "agent-2.mcap", "agent-3.mcap", "metrics.json", "summary.md",
                 "trajectories.png"):
        assert (folder / name).exists(), name
    for figure in ("trajectories.png", "errors.png", "ranges.png"):
        assert (folder / figure).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["ticks"] == 121 and metrics["vessels"] == ["1", "2", "3"]
    assert all(math.isfinite(metrics[k]) for k in ("mean_e_ij", "mean_e_io", "mean_e_c"))
    assert metrics["settling_time"] is not None        # the fleet formed the circle over Zenoh
    assert metrics["mean_e_io"] < 1.0 and metrics["mean_e_ij"] < 1.0
    assert "missed commands" in (folder / "bridge.log").read_text()
    # Each process ends its log with what the run cost it: every tick counted, CPU time measured.
    from agent.runtime.mcap_log import read_messages

    for name, topic in [("sim.mcap", "/bridge/summary"), *((f"agent-{i}.mcap", f"/{i}/summary") for i in "123")]:
        (summary,) = [m for t, _, m in read_messages(folder / name) if t == topic]
        assert summary["ticks"] == 121 and 0.0 < summary["cpu_seconds"] and 0.0 < summary["loop_seconds"]


def test_unknown_variant_is_a_clear_error(tmp_path, short_scenario):
    scenario = short_scenario
    result = subprocess.run([sys.executable, "-m", "sim_bridge.fleet_cli", "run", str(scenario), "--variant", "x",
                             "--out", str(tmp_path / "runs")], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "no variant 'x'" in result.stderr
