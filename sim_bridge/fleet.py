"""`usv-fleet run SCENARIO`: the sim bridge and one agent per vessel as separate OS processes on loopback.

It writes each process's settings into a run folder, starts the bridge (lockstep) and the agents, waits
for the mission to end, stops the agents with SIGTERM (they finish their logs), and then computes the
paper's metrics from the logs alone: the bridge's ground truth against what each agent logged it believed.
The folder ends up with every MCAP log, `metrics.json`, `summary.md` and `trajectories.png`.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import socket
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import yaml

from agent.mcap_log import read_messages
from agent.params import ConfigError
from sim_bridge.metrics import summarise
from sim_bridge.scenario import select_scenario


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def launch(scenario_path: Path, variant: str | None, out: Path, seed: int | None,
           timeout: float = 600.0) -> Path:
    """Run the fleet; returns the run folder."""
    name, scenario = select_scenario(scenario_path, variant)
    folder = out / f"{scenario_path.stem}-{name}-{datetime.now(timezone.utc):%Y%m%dT%H%M%S}"
    folder.mkdir(parents=True, exist_ok=False)
    bridge_port = free_port()
    bridge_config = folder / "bridge.yaml"
    bridge_config.write_text(yaml.safe_dump({
        "mode": "lockstep", "zenoh": {"listen": [f"tcp/127.0.0.1:{bridge_port}"]},
        "log": str(folder / "sim.mcap")}))
    agent_params = scenario.agent_params().model_dump(mode="json")
    starts = _initial_estimates(scenario, seed)
    processes: dict[str, subprocess.Popen] = {}
    logs = {}
    bridge_cmd = [sys.executable, "-m", "sim_bridge", "--scenario", str(scenario_path), "--variant", name,
                  "--config", str(bridge_config)] + (["--seed", str(seed)] if seed is not None else [])
    logs["bridge"] = (folder / "bridge.log").open("w")
    bridge = subprocess.Popen(bridge_cmd, stdout=logs["bridge"], stderr=subprocess.STDOUT)
    for vessel in scenario.world.vessels:
        config = folder / f"agent-{vessel.id}.yaml"
        config.write_text(yaml.safe_dump({
            "clock": "sim",
            "zenoh": {"listen": [f"tcp/127.0.0.1:{free_port()}"], "connect": [f"tcp/127.0.0.1:{bridge_port}"]},
            "log": str(folder / f"agent-{vessel.id}.mcap"),
            "agent": agent_params,
            "initial": starts.get(vessel.id, {}),
        }))
        logs[vessel.id] = (folder / f"agent-{vessel.id}.log").open("w")
        processes[vessel.id] = subprocess.Popen(
            [sys.executable, "-m", "agent", "--vessel", vessel.id, "--config", str(config)],
            stdout=logs[vessel.id], stderr=subprocess.STDOUT)
    print(f"usv-fleet: {len(processes)} agents and the sim bridge started; run folder {folder}", file=sys.stderr)
    try:
        bridge.wait(timeout=timeout)
    finally:
        for process in [*processes.values(), bridge]:
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        for process in [*processes.values(), bridge]:
            try:
                process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                process.kill()
        for handle in logs.values():
            handle.close()
    analyse(folder, scenario.agent_params().control.radius)
    return folder


def _initial_estimates(scenario, seed: int | None) -> dict[str, dict]:
    """Each agent's starting estimates, drawn as the in-process runner draws them (for the vessels there
    at the start; a later joiner starts from its first bearing and its neighbours' estimates)."""
    from sim_bridge.runner import initial_estimates
    from sim_bridge.world import World

    sequence = np.random.SeedSequence(scenario.seed if seed is None else seed)
    world_seed, init_seed = sequence.spawn(2)
    world = World(scenario.world, np.random.default_rng(world_seed))
    present = world.live()
    drawn = initial_estimates(scenario, world.truth(), present, np.random.default_rng(init_seed), present)
    return {v: {"target": [float(x) for x in target],
                "target_variance": scenario.initial.target_covariance,
                "neighbours": {j: [float(x) for x in prior.position] for j, prior in priors.items()},
                "neighbour_variance": scenario.initial.neighbour_covariance}
            for v, (target, priors) in drawn.items()}


def analyse(folder: Path, radius: float) -> dict:
    """The paper's metrics from the run folder's logs; writes metrics.json, summary.md, trajectories.png."""
    truth = {t: m for topic, t, m in read_messages(folder / "sim.mcap") if topic == "/truth"}
    stamps = sorted(truth)
    vessels = sorted({v for m in truth.values() for v in m["vessels"]})
    index = {t: k for k, t in enumerate(stamps)}
    n = len(stamps)
    e_ij, e_io, e_v = (np.full(n, np.nan) for _ in range(3))
    for vessel in vessels:
        path = folder / f"agent-{vessel}.mcap"
        if not path.exists():
            continue
        for topic, t, m in read_messages(path):
            if topic != f"/{vessel}/estimates" or t not in index:
                continue
            k, world = index[t], truth[t]
            own = np.array(world["vessels"].get(vessel, {}).get("position", [math.nan] * 2))
            for j, estimate in m["neighbours"].items():
                if j in world["vessels"]:
                    error = np.hypot(*(np.array(estimate["position"]) - (own - world["vessels"][j]["position"])))
                    e_ij[k] = np.nanmax([e_ij[k], error])
            if m["target_state"] is not None:
                error = np.hypot(*(np.array(m["target_state"][:2]) - (own - np.array(world["target"]))))
                e_io[k] = np.nanmax([e_io[k], error])
    positions = np.full((n, len(vessels), 2), np.nan)
    target = np.array([truth[t]["target"] for t in stamps])
    for k, t in enumerate(stamps):
        for v, state in truth[t]["vessels"].items():
            positions[k, vessels.index(v)] = state["position"]
    radii = np.linalg.norm(positions - target[:, None, :], axis=-1)
    e_c = np.linalg.norm(np.nanmean(positions, axis=1) - target, axis=-1)
    time_s = np.array(stamps) * 1e-9
    metrics = summarise(time_s, e_ij, e_io, e_v, e_c, radii, radius, [])
    result = {
        "vessels": vessels, "ticks": n, "radius": radius,
        "mean_e_ij": metrics.mean_e_ij, "mean_e_io": metrics.mean_e_io, "mean_e_c": metrics.mean_e_c,
        "settling_time": metrics.settling_time,
    }
    (folder / "metrics.json").write_text(json.dumps(result, indent=2))
    lines = [f"# Fleet run {folder.name}", "", f"{len(vessels)} vessels, {n} ticks, r* = {radius} m", "",
             "| mean e_ij (m) | mean e_io (m) | mean e_c (m) | settling time (s) |", "|---|---|---|---|",
             f"| {metrics.mean_e_ij:.3f} | {metrics.mean_e_io:.3f} | {metrics.mean_e_c:.3f} | "
             f"{'never' if metrics.settling_time is None else f'{metrics.settling_time:.1f}'} |", "",
             "Computed from the logs alone: `sim.mcap` (ground truth) and `agent-<id>.mcap` (what each believed).",
             "", "![trajectories](trajectories.png)"]
    (folder / "summary.md").write_text("\n".join(lines) + "\n")
    _plot(folder / "trajectories.png", positions, target, vessels, radius)
    return result


def _plot(path: Path, positions: np.ndarray, target: np.ndarray, vessels: list[str], radius: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4.5), dpi=120)
    for n, vessel in enumerate(vessels):
        line, = ax.plot(positions[:, n, 0], positions[:, n, 1], lw=1.2, label=f"USV {vessel}")
        present = np.isfinite(positions[:, n, 0])
        if present.any():
            ax.plot(*positions[present, n][-1], "^", color=line.get_color())
    ax.plot(target[:, 0], target[:, 1], "k--", lw=1, label="target")
    circle = plt.Circle(target[-1], radius, fill=False, ls=":", color="grey")
    ax.add_patch(circle)
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("fleet run over Zenoh (truth from the sim bridge's log)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="usv-fleet", description="Run a simulated fleet as separate processes.")
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="the sim bridge and one agent process per vessel")
    run.add_argument("scenario", type=Path, help="scenario YAML, e.g. configs/scenarios/table2_estimators.yaml")
    run.add_argument("--variant", default=None, help="variant of the file (default: the first)")
    run.add_argument("--out", type=Path, default=Path("runs"), help="parent of the run folder")
    run.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    args = parser.parse_args(argv)
    started = time.monotonic()
    try:
        folder = launch(args.scenario, args.variant, args.out, args.seed)
    except ConfigError as error:
        print(f"usv-fleet: {error}", file=sys.stderr)
        return 2
    print((folder / "summary.md").read_text())
    print(f"usv-fleet: run folder {folder} ({time.monotonic() - started:.1f} s)", file=sys.stderr)
    return 0
