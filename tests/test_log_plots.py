"""`usv-log plot`: the figures of a run, drawn from small hand-made logs (no MCAP files, no simulation)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from mission_log.plots import plot_run
from mission_log.reader import Log, RunLog, VesselLog, agent_radius

PNG = b"\x89PNG\r\n\x1a\n"
TICKS = 30
TICK_NS = 100_000_000
ABSENT = {"2": range(10, 25)}     # vessel 2 drops out for half the run
RADIUS = 4.0
FLEET = ("1", "2")                # the vessels the synthetic logs speak of


def _target(k: int) -> tuple[float, float]:
    return 0.05 * k, 0.0


def _position(vid: str, k: int) -> tuple[float, float]:
    """Vessels on the circle round the target, half a turn apart, 0.03 rad per tick."""
    angle = 0.03 * k + (0.0 if vid == "1" else math.pi)
    tx, ty = _target(k)
    return tx + RADIUS * math.cos(angle), ty + RADIUS * math.sin(angle)


def _present(vid: str, k: int) -> bool:
    return k not in ABSENT.get(vid, ())


def _minus(a, b) -> list[float]:
    return [a[0] - b[0], a[1] - b[1]]


def _outcomes(k: int, j: str) -> list[dict]:
    """One update per tick, with down-weighted outliers, rejections and a tick without any."""
    if k == 7:
        return []
    weight = 0.2 if k % 6 == 0 else 0.95
    outcome = {"stamp": 0.1 * k - 0.1, "range": 8.0, "accepted": True, "reason": "", "iterations": 2,
               "innovation": 0.3 * (-1) ** k, "innovation_variance": 0.09, "weight": weight}
    if k == 3:    # rejected before an innovation was computed
        outcome |= {"accepted": False, "reason": "stale", "innovation": None, "innovation_variance": None}
    if k == 26:   # rejected by the gate
        outcome |= {"accepted": False, "reason": "gated", "innovation": 5.0}
    return [outcome]


def _estimate(vid: str, k: int) -> dict:
    own, target = _position(vid, k), _target(k)
    neighbours = {
        j: {"position": [x + 0.1 for x in _minus(own, _position(j, k))], "covariance": [0.04, 0, 0, 0.04],
            "epoch": 0.1 * k, "iterations": 2, "updates": k, "rejected": 0, "outcomes": _outcomes(k, j)}
        for j in FLEET if j != vid and _present(j, k)
    }
    state = None if k == 5 else [*_minus(own, target), 0.5, 0.0]
    return {"time": 0.1 * k, "phase": 0.0, "neighbours": neighbours, "target_state": state,
            "target_covariance": None if state is None else [0.0] * 16, "bearing": None, "velocity": {},
            "saturated": {}, "health": {}}


def _inputs(vid: str, k: int) -> dict:
    own = _position(vid, k)
    ranges = {j: math.dist(own, _position(j, k)) for j in FLEET if j != vid and _present(j, k)}
    return {"time": 0.1 * k, "odometry": {"stamp": 0.1 * k, "position": list(own), "heading": 0.0},
            "ranges": ranges, "bearing": None, "obstacle_points": None, "shares": {}}


def _vessel(vid: str, settings: bool = True, estimates: bool = True) -> VesselLog:
    ticks = [k for k in range(TICKS) if _present(vid, k)]
    cmd = [(k * TICK_NS, {"stamp_ns": k * TICK_NS, "seq": k, "sender": vid, "surge": 1.0, "yaw_rate": 0.0})
           for k in ticks]
    topics = {f"/{vid}/inputs": [(k * TICK_NS, _inputs(vid, k)) for k in ticks], f"usv/{vid}/cmd": cmd}
    if estimates:
        topics[f"/{vid}/estimates"] = [(k * TICK_NS, _estimate(vid, k)) for k in ticks]
    metadata = {"vessel": vid}
    if settings:
        metadata["settings"] = json.dumps({"agent": {"control": {"radius": RADIUS}}})
    return VesselLog(Path(f"agent-{vid}.mcap"), metadata, topics, vessel=vid)


def _sim() -> Log:
    truth = [(k * TICK_NS, {"time": 0.1 * k, "target": list(_target(k)), "target_velocity": [0.5, 0.0],
                            "vessels": {vid: {"position": list(_position(vid, k)), "heading": 0.0}
                                        for vid in FLEET if _present(vid, k)}})
             for k in range(TICKS)]
    island = {"frame_id": "world", "id": "island/0",
              "lines": [{"points": [{"x": 8.0, "y": -1.0, "z": 0.0}, {"x": 10.0, "y": -1.0, "z": 0.0},
                                    {"x": 9.0, "y": 1.0, "z": 0.0}]}]}
    scene = [(0, {"deletions": [], "entities": [island]})]
    return Log(Path("sim.mcap"), {}, {"/truth": truth, "/scene": scene})


def _run(truth: bool = True) -> RunLog:
    vessels = {"1": _vessel("1"), "2": _vessel("2", settings=False)}
    return RunLog("synthetic", vessels, _sim() if truth else None)


def _written(paths: list[Path], out: Path) -> set[str]:
    for path in paths:
        assert path.parent == out
        assert path.read_bytes()[:8] == PNG
    return {path.name for path in paths}


@pytest.mark.slow
def test_with_truth_all_three_figures(tmp_path):
    out = tmp_path / "figures"     # not there yet: plot_run makes it
    assert _written(plot_run(_run(), out), out) == {"trajectories.png", "errors.png", "ranges.png"}


@pytest.mark.slow
@pytest.mark.parametrize("sim", ["none", "no truth topic"])
def test_without_truth_no_errors_figure(tmp_path, sim):
    run = _run(truth=False)
    if sim == "no truth topic":
        run.sim = Log(Path("sim.mcap"), {}, {"/scene": []})
    assert _written(plot_run(run, tmp_path), tmp_path) == {"trajectories.png", "ranges.png"}
    assert not (tmp_path / "errors.png").exists()


@pytest.mark.slow
def test_a_single_vessel_without_estimates(tmp_path):
    run = RunLog("synthetic", {"2": _vessel("2", settings=False, estimates=False)}, _sim())
    assert agent_radius(run) == 5.0
    assert _written(plot_run(run, tmp_path), tmp_path) == {"trajectories.png", "errors.png", "ranges.png"}


@pytest.mark.slow
def test_the_bridge_log_alone(tmp_path):
    run = RunLog("synthetic", {}, _sim())
    assert _written(plot_run(run, tmp_path, radius=3.0), tmp_path) == {"trajectories.png", "errors.png"}


def test_radius_from_any_vessel_with_settings():
    assert agent_radius(_run()) == RADIUS
    assert agent_radius(RunLog("synthetic", {"2": _vessel("2", settings=False)})) == 5.0


@pytest.mark.slow
def test_importing_the_module_does_not_load_matplotlib():
    """The module sits beside the reader the agent side uses; matplotlib must wait for a plot."""
    code = "import sys, mission_log.plots; sys.exit('matplotlib' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], cwd=Path(__file__).parents[1], check=False)
    assert done.returncode == 0


@pytest.mark.slow
def test_every_legend_lies_inside_its_figure(tmp_path, monkeypatch):
    """A legend wider than its figure is cut off at both sides in the PNG (ranges.png's legend below the
    panels did, with every neighbour in one row)."""
    from matplotlib.figure import Figure

    save = Figure.savefig
    outside = []

    def checked(fig, path, *args, **kwargs):
        fig.canvas.draw()
        box = fig.bbox
        for legend in [*fig.legends, *(ax.get_legend() for ax in fig.axes if ax.get_legend() is not None)]:
            extent = legend.get_window_extent()
            if extent.x0 < box.x0 - 1 or extent.x1 > box.x1 + 1 or extent.y0 < box.y0 - 1:
                outside.append((Path(path).name, extent.x0, extent.x1, box.x1))
        return save(fig, path, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", checked)
    monkeypatch.setattr(sys.modules[__name__], "FLEET", ("1", "2", "3", "4", "5"))   # four neighbours each
    run = _run()
    for vessel in "345":
        run.vessels[vessel] = _vessel(vessel, settings=False)
    plot_run(run, tmp_path)
    assert outside == []
