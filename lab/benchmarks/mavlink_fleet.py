"""`usv-lab mavlink-fleet`: the fleet through MAVLink (`usv-fleet run --vehicle mavlink`) against the same fleet
through the sim bridge directly, seed by seed and in both modes, over real processes.

    usv-lab mavlink-fleet [--scenario NAME] [--seeds S ...] [--duration S] [--out PAGE]

For each seed and mode (lockstep, realtime) the launcher runs the scenario's default variant twice: the sim
bridge moving the vessels, then each vessel through an ArduPilot stand-in and a usv-driver over real MAVLink
on UDP (sim_bridge/fleet_mavlink.py). The page gives the paper's metrics of both and their differences (the
target: within 10 %, `LIMIT`), the set points that carried a fresh command a second (the agent's rate is
1/dt) and their added latency (target: p99 <= 20 ms in real time), and a last real-time run in which one
agent is killed (SIGKILL) mid-mission: how long until its stand-in is in HOLD (target: within 1 s).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from lab import arguments
from lab.arguments import seed as seed_type
from lab.report.markdown import invocation, markdown_table
from mission_log.metrics import truth_metrics
from mission_log.reader import load_run
from sim_bridge.fleet import launch
from sim_bridge.scenario import default_variant, scenario_file, select_scenario, with_duration

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_PAGE = ROOT / "docs" / "results" / "mavlink_fleet.md"
LIMIT = 0.10            # |MAVLink - direct| / direct of each metric, at most
LATENCY_MS = 20.0       # p99 added latency in real time, at most
HOLD_S = 1.0            # from an agent's SIGKILL to its vessel in HOLD, at most
MODES = ("lockstep", "realtime")
METRICS = ("mean_e_ij", "mean_e_io", "mean_e_c", "settling_time")
KILLED, KILL_AT = "1", 0.5   # the vessel whose agent the last run kills, at this share of its duration


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", default="table2_estimators", help="a scenario file or name")
    parser.add_argument("--seeds", type=seed_type, nargs="+", default=[2, 3])
    parser.add_argument("--duration", type=float, default=None, help="simulated seconds (default: the scenario's)")
    parser.add_argument("--out", type=arguments.page, default=DEFAULT_PAGE, help="the page to write")
    parser.add_argument("--runs", type=arguments.folder, default=None, help="where the run folders go (default: a temporary "
                                                                 "folder, deleted afterwards)")


def run_once(path: Path, seed: int, mode: str, vehicle: str, runs: Path, on_time=None) -> dict:
    """One launch: the metrics of its logs, and with MAVLink the path's figures (fleet_mavlink.figures)."""
    variant = default_variant(path)
    _, spec = select_scenario(path, variant)
    folder = launch(path, variant, runs, seed, timeout=spec.duration * 4 + 180, mode=mode, vehicle=vehicle,
                    on_time=on_time)
    metrics = truth_metrics(load_run(folder), spec.agent_params().control.radius)
    if vehicle == "mavlink":   # written by the launch (fleet_mavlink.figures)
        metrics["mavlink"] = json.loads((folder / "mavlink.json").read_text())
    return metrics


def kill_halfway(duration: float):
    def on_time(fleet, sim_seconds: float) -> None:
        if sim_seconds >= KILL_AT * duration and KILLED not in fleet.killed:
            fleet.kill(KILLED)
    return on_time


def run(args: argparse.Namespace) -> int:
    path = scenario_file(args.scenario)
    with tempfile.TemporaryDirectory(prefix="usv-mavlink-fleet-") as scratch:
        if args.duration is not None:
            path = with_duration(path, scratch, args.duration)
        _, spec = select_scenario(path, default_variant(path))
        runs = args.runs or Path(scratch)
        results: dict[tuple[int, str, str], dict] = {}
        total, started = len(args.seeds) * len(MODES) * 2 + 1, time.monotonic()
        for seed in args.seeds:
            for mode in MODES:
                for vehicle in ("sim", "mavlink"):
                    results[seed, mode, vehicle] = metrics = run_once(path, seed, mode, vehicle, runs)
                    print(f"usv-lab mavlink-fleet: [{len(results)}/{total}] seed {seed} {mode} {vehicle}: e_ij "
                          f"{metrics['mean_e_ij']:.3f} m, e_c {metrics['mean_e_c']:.3f} m "
                          f"({time.monotonic() - started:.0f} s so far)", file=sys.stderr)
        killed = run_once(path, args.seeds[0], "realtime", "mavlink", runs, kill_halfway(spec.duration))
    page = render(args, path, spec, results, killed)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(page)
    print(page)
    return 0


def _value(metrics: dict, name: str) -> str:
    value = metrics[name]
    return "never" if value is None else f"{value:.3f}" if name != "settling_time" else f"{value:.1f}"


def difference(mavlink: dict, direct: dict, name: str) -> float | None:
    """|MAVLink - direct| / direct; None when either never settled (or the direct figure is 0)."""
    a, b = mavlink[name], direct[name]
    return None if a is None or b is None or b == 0 else abs(a - b) / abs(b)


def render(args, path: Path, spec, results: dict, killed: dict) -> str:
    rows, paths, worst = [], [], 0.0
    for (seed, mode, vehicle), metrics in results.items():
        if vehicle == "sim":
            continue
        direct = results[seed, mode, "sim"]
        diffs = [difference(metrics, direct, name) for name in METRICS]
        worst = max([worst, *(d if d is not None else float("inf") for d in diffs)])
        for label, m in (("sim bridge", direct), ("MAVLink", metrics)):
            rows.append([seed, mode, label, *(_value(m, name) for name in METRICS)])
        rows.append([seed, mode, "difference", *("–" if d is None else f"{100 * d:.1f} %" for d in diffs)])
        figure = metrics["mavlink"]
        rates = [v["fresh_per_s"] for v in figure["vessels"].values() if v["fresh_per_s"] is not None]
        paths.append([seed, mode, figure["fresh_setpoints"], figure["new_unmatched"],
                      f"{min(rates):.2f} to {max(rates):.2f}", f"{figure['added_ms_p50']:.2f}",
                      f"{figure['added_ms_p99']:.2f}", f"{figure['added_ms_max']:.2f}"])
    realtime_p99 = max(results[seed, "realtime", "mavlink"]["mavlink"]["added_ms_p99"] for seed in args.seeds)
    hold = killed["mavlink"]["vessels"][KILLED].get("hold_after_kill_s")
    verdicts = [
        ["metrics within 10 % of the sim bridge's (each seed, mode, metric)", f"worst {100 * worst:.1f} %",
         "yes" if worst <= LIMIT else "no"],
        ["p99 added latency in real time <= 20 ms", f"{realtime_p99:.2f} ms (worst seed)",
         "yes" if realtime_p99 <= LATENCY_MS else "no"],
        [f"a killed agent's vessel in HOLD within {HOLD_S:g} s", "never" if hold is None else f"{hold:.3f} s",
         "yes" if hold is not None and hold <= HOLD_S else "no"],
    ]
    name = path.stem
    return "\n".join([
        "# The fleet through MAVLink against the sim bridge",
        "",
        f"Made by `{invocation(args)}` (scenario {name}, variant {spec.name}, {spec.duration:g} s, seeds "
        f"{', '.join(map(str, args.seeds))}; run on a shared 2-core machine).",
        "",
        "Each seed and mode runs the fleet over real processes twice: the sim bridge moving the vessels, and "
        "`usv-fleet run --vehicle mavlink`, where each vessel is an ArduPilot stand-in relaying the sim's vessel "
        "over real MAVLink on UDP, driven by a usv-driver on the sim clock (docs/boats.md, \"A fleet through "
        "MAVLink\"). The agents are the same programs with the same settings.",
        "",
        markdown_table(["acceptance", "measured", "met"], verdicts),
        "",
        "## Metrics",
        "",
        markdown_table(["seed", "mode", "vehicle", "mean e_ij (m)", "mean e_io (m)", "mean e_c (m)",
                        "settling (s)"], rows),
        "",
        "## The MAVLink path",
        "",
        "A fresh set point is one the stand-in took that carried a new command of the agent (the driver repeats "
        "the last at 2 Hz too); its added latency runs from the command reaching the stand-in's process over "
        "Zenoh (as it reaches the sim bridge without MAVLink) to the stand-in taking the set point from the "
        "driver (negative when the set point came first). The agent commands once a tick: 10 a second in real "
        "time, faster in lockstep. A new set point not matched is one that differs from the last and matched no "
        "command of the agent within 1 s (the driver's zero set points before the agent's first command).",
        "",
        markdown_table(["seed", "mode", "fresh set points", "new, not matched", "fresh a second per vessel",
                        "added p50 (ms)", "added p99 (ms)", "added max (ms)"], paths),
        "",
        f"Killing vessel {KILLED}'s agent (SIGKILL) at {KILL_AT * spec.duration:g} s of a real-time run "
        f"(seed {args.seeds[0]}): its stand-in was in HOLD {'never' if hold is None else f'{hold:.3f} s'} later.",
        "",
    ])
