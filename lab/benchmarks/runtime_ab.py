"""`usv-lab runtime-ab`: what one change to the runtime bought, before against after, measured in one run.

On this 2-core machine one lockstep fleet run moves by 15-30 % from the next (docs/results/runtime_profile.md),
more than most single changes are worth, so a change is judged by pairs of runs taken alternately
(before, after, after, before, ...) and their medians. Each pair runs, for each side:
- the shells in process (lab/benchmarks/shell.py, Table II with the MCKF): CPU per tick of an agent by section and
  of the sim bridge, on one thread, the steady figure;
- the same mission as a lockstep fleet over Zenoh (bridge and 4 agent processes): each process's CPU per tick
  from its log's summary, the tick loop's and the whole launch's real-time factors;
- a 4-vessel fleet in real time for REALTIME_SECONDS: the sensor-to-command latency's median and 99th
  percentile, as `usv-lab runtime-bench` measures it.

"Before" is a git revision, checked out in a temporary worktree; "after" is this checkout (or another
revision). Each side runs in its own interpreter with its own code on the path, the fleet's processes too.
A revision without lab/benchmarks/shell.py (older than the shell bench or than lab/'s rooms) gets this
checkout's (it drives the bridge and agent through the same methods they had then). The result is appended to a JSON record and the page
`runtime_changes.md` is written from the whole record.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

from lab import arguments

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = Path("configs/scenarios/table2_estimators.yaml")
VARIANT = "mckf"
REALTIME_SCENARIO, REALTIME_VARIANT = Path("configs/scenarios/table4_scale.yaml"), "n4_r5"
SHELL_BENCH = Path("lab/benchmarks/shell.py")
REALTIME_SECONDS = 20.0   # 200 ticks: 800 commands timed
FIGURES = {   # key: (what it is, unit, decimals)
    "shell_agent_ms": ("agent, in process", "ms", 3),
    "shell_core_ms": ("of which the core", "ms", 3),
    "shell_ratio": ("agent / core, in process", "", 2),
    "shell_bridge_ms": ("sim bridge, in process", "ms", 3),
    "fleet_agent_ms": ("agent, fleet over Zenoh", "ms", 2),
    "fleet_agent_per_core": ("fleet agent / in-process core", "", 2),
    "fleet_bridge_ms": ("sim bridge, fleet over Zenoh", "ms", 2),
    "fleet_factor": ("lockstep tick loop", "x", 1),
    "launch_factor": ("whole launch", "x", 1),
    "latency_p50_ms": ("sensor to command p50, 4 vessels in real time", "ms", 2),
    "latency_p99_ms": ("sensor to command p99", "ms", 2),
    "agent_mb": ("agent peak memory", "MB", 0),
    "bridge_mb": ("sim bridge peak memory", "MB", 0),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--before", required=True, help="git revision before the change (e.g. HEAD~1, a hash)")
    parser.add_argument("--after", default=None, help="git revision after it (default: this checkout as it is)")
    parser.add_argument("--label", required=True, help="what the change is, in a few words, for the page")
    parser.add_argument("--pairs", type=arguments.positive_int, default=4, help="before/after pairs of runs")
    parser.add_argument("--record", type=Path, default=Path("docs/results/runtime_changes.json"),
                        help="JSON record the result is appended to")
    parser.add_argument("--out", type=arguments.folder, default=Path("docs/results"), help="where runtime_changes.md goes")


# ----------------------------------------------------------------------------------------------- one side
def measure(root: Path) -> dict[str, float]:
    """One run of each measurement, on the code under `root` (which must be first on sys.path)."""
    import numpy as np

    from agent.runtime.mcap_log import read_messages
    from lab.benchmarks.shell import run_shells
    from sim_bridge.fleet import Fleet
    from sim_bridge.scenario import select_scenario, with_duration

    _, scenario = select_scenario(root / SCENARIO, VARIANT)
    shells = run_shells(scenario)
    figures = {"shell_agent_ms": shells.agent_ms, "shell_core_ms": shells.per_tick_ms("core"),
               "shell_bridge_ms": shells.per_tick_ms("bridge")}
    figures["shell_ratio"] = figures["shell_agent_ms"] / figures["shell_core_ms"]
    with tempfile.TemporaryDirectory() as scratch:
        started = time.monotonic()
        fleet = Fleet(root / SCENARIO, VARIANT, Path(scratch))
        folder = fleet.run()
        launch = time.monotonic() - started
        cpu, loop, ticks = {}, None, None
        for path in sorted(folder.glob("*.mcap")):
            for topic, _, message in read_messages(path):
                if topic.endswith("/summary") and message.get("ticks"):
                    cpu[topic] = 1e3 * message["cpu_seconds"] / message["ticks"]
                    if topic == "/bridge/summary":
                        loop, ticks = message["loop_seconds"], message["ticks"]
        memory = json.loads((folder / "memory.json").read_text())["peak_resident_mb"]
    simulated = ticks * scenario.world.dt
    figures.update(agent_mb=float(np.mean([v for k, v in memory.items() if k.startswith("agent-")])),
                   bridge_mb=memory["bridge"])
    figures.update(fleet_bridge_ms=cpu.pop("/bridge/summary"), fleet_agent_ms=float(np.mean(list(cpu.values()))),
                   fleet_factor=simulated / loop, launch_factor=simulated / launch)
    # The machine's speed drifts by tens of per cent over minutes: the core measured just before is the yardstick.
    figures["fleet_agent_per_core"] = figures["fleet_agent_ms"] / figures["shell_core_ms"]
    with tempfile.TemporaryDirectory() as scratch:
        path = with_duration(root / REALTIME_SCENARIO, Path(scratch), REALTIME_SECONDS)
        folder = Fleet(path, REALTIME_VARIANT, Path(scratch) / "runs", mode="realtime").run()
        latencies = [value for topic, _, message in read_messages(folder / "sim.mcap")
                     if topic == "/bridge/command_latency" for value in message["milliseconds"].values()]
    figures.update(latency_p50_ms=float(np.percentile(latencies, 50)),
                   latency_p99_ms=float(np.percentile(latencies, 99)))
    return figures


def _measure_at(root: Path) -> dict[str, float]:
    """`measure` in a new interpreter with `root`'s code first on the path (its child processes too)."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--measure", str(root)], cwd=root, env=env,
                          capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"measuring {root} failed: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------------------------- both sides
def _git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, check=True).stdout.strip()


def _checkout(revision: str, folder: Path) -> Path:
    """A worktree of `revision` in `folder`; this checkout's shell bench if the revision has none at its path."""
    _git("worktree", "add", "--detach", str(folder), revision)
    bench = folder / SHELL_BENCH
    if not bench.exists():   # a revision from before lab/ had rooms, or before the shell bench
        bench.parent.mkdir(exist_ok=True)
        (bench.parent / "__init__.py").touch()
        shutil.copy(ROOT / SHELL_BENCH, bench)
    return folder


def alternate(before: str, after: str | None, pairs: int, measure, label: str, progress=print
              ) -> dict[str, list[dict[str, float]]]:
    """`measure(root, pair)` on checkouts of `before` and `after` (None: this checkout), `pairs` times each,
    alternating which side goes first; every result of each side, in order."""
    results: dict[str, list[dict[str, float]]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as scratch:
        roots = {"before": Path(scratch) / "before", "after": ROOT if after is None else Path(scratch) / "after"}
        try:
            _checkout(before, roots["before"])
            if after is not None:
                _checkout(after, roots["after"])
            for pair in range(pairs):
                for side in ("before", "after") if pair % 2 == 0 else ("after", "before"):
                    results[side].append(measure(roots[side], pair))
                    progress(f"{label}: pair {pair + 1}/{pairs}, {side}: " + ", ".join(
                        f"{name} {value:.3g}" for name, value in results[side][-1].items()))
        finally:
            for root in roots.values():
                if root != ROOT and root.exists():
                    _git("worktree", "remove", "--force", str(root))
    return results


def compare(before: str, after: str | None, pairs: int, progress=print) -> dict:
    """Medians of `pairs` alternating runs of each side, and what they were run on."""
    results = alternate(before, after, pairs, lambda root, _: _measure_at(root), "runtime-ab", progress)
    medians = {side: {name: statistics.median(run[name] for run in runs) for name in FIGURES}
               for side, runs in results.items()}
    spread = {side: {name: [min(run[name] for run in runs), max(run[name] for run in runs)] for name in FIGURES}
              for side, runs in results.items()}
    dirty = after is None and bool(_git("status", "--porcelain", "--untracked-files=no"))
    return {"before": _git("rev-parse", "--short", before),
            "after": (_git("rev-parse", "--short", after) if after is not None
                      else _git("rev-parse", "--short", "HEAD") + ("+changes" if dirty else "")),
            "pairs": pairs, "medians": medians, "spread": spread, "runs": results, "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
            "cores": os.cpu_count()}


# ----------------------------------------------------------------------------------------------- page
def page(record: list[dict]) -> str:
    from lab.report.markdown import markdown_table

    header = ["change", "before → after", "pairs"] + [f"{text} ({unit})" if unit else text
                                                      for text, unit, _ in FIGURES.values()]
    rows = []
    for entry in record:
        cells = []
        for name, (_, _, decimals) in FIGURES.items():
            if name not in entry["medians"]["before"]:
                cells.append("-")
                continue
            was, now = entry["medians"]["before"][name], entry["medians"]["after"][name]
            cell = f"{was:.{decimals}f} → {now:.{decimals}f} ({now / was:.2f})"
            if "spread" in entry:
                low, high = (entry["spread"][side][name] for side in ("before", "after"))
                cell += f"<br>[{low[0]:.{decimals}f}-{low[1]:.{decimals}f}] [{high[0]:.{decimals}f}-{high[1]:.{decimals}f}]"
            cells.append(cell)
        rows.append([entry["label"], f"`{entry['before']}` → `{entry['after']}`", entry["pairs"], *cells])
    return "\n".join([
        "# What each change to the runtime bought", "",
        "Each row is one run of `usv-lab runtime-ab --before REV --label TEXT` (lab/benchmarks/runtime_ab.py): the medians "
        "of alternating pairs of runs before and after the change, on this machine (2 cores), with the "
        "after/before ratio in brackets and, below, the range of each side's runs. CPU figures are milliseconds per tick; \"in process\" is the shells "
        "in one thread without Zenoh (lab/benchmarks/shell.py), \"fleet over Zenoh\" the lockstep Table II fleet, "
        "bridge and 4 agent processes sharing the 2 cores. The targets of issue #14 are in "
        "runtime_benchmark.md.", "",
        markdown_table(header, rows), "",
        *[f"- {entry['label']}: {entry['note']}" for entry in record if entry.get("note")], ""])


def run(args: argparse.Namespace) -> int:
    result = compare(args.before, args.after, args.pairs, progress=lambda text: print(text, file=sys.stderr))
    record = json.loads(args.record.read_text()) if args.record.exists() else []
    record.append({"label": args.label, **result})
    args.record.parent.mkdir(parents=True, exist_ok=True)
    args.record.write_text(json.dumps(record, indent=1) + "\n")
    args.out.mkdir(parents=True, exist_ok=True)
    text = page(record)
    (args.out / "runtime_changes.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":   # the internal --measure run, in an interpreter with one side's code on the path
    root = Path(sys.argv[sys.argv.index("--measure") + 1]).resolve()
    sys.path.insert(0, str(root))
    print(json.dumps(measure(root)))
