"""`usv-lab hull-ab`: what one change to the hull world bought, before against after, measured in one run.

As `usv-lab runtime-ab` does for the runtime: "before" is a git revision checked out in a temporary worktree,
"after" this checkout (or another revision); each side runs in its own interpreter with its own code first on
the path, in pairs taken alternately (before, after, after, before, ...), and the medians are compared. Each
measurement is one run of the Table II MCKF variant (60 s, Monte Carlo seed child r, r = pair mod 3) with
the paper's kinematic vessels and then with `world.dynamics: {preset: otter}` overlaid, in process: CPU
seconds (time.process_time) of the whole run and of World.step; then `World.step`'s CPU per vessel per tick
on the Otter for 4 and 50 vessels (lab/experiments/hull.py `world_step_cost`). Nothing is written but what
it prints; docs/sea.md ("What it costs") keeps the results.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from lab import arguments

FIGURES = {   # key: what it is
    "kinematic_s": "Table II run, kinematic: CPU (s)",
    "otter_s": "Table II run, Otter: CPU (s)",
    "ratio": "Otter / kinematic, the same seed",
    "kinematic_world_s": "World.step in the kinematic run (s)",
    "otter_world_s": "World.step in the Otter run (s)",
    "step_4_us": "Otter World.step per vessel per tick, 4 vessels (us)",
    "step_50_us": "Otter World.step per vessel per tick, 50 vessels (us)",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--before", required=True, help="git revision before the change (e.g. HEAD~1, a hash)")
    parser.add_argument("--after", default=None, help="git revision after it (default: this checkout as it is)")
    parser.add_argument("--pairs", type=arguments.positive_int, default=4, help="before/after pairs of runs")


def measure(run_index: int) -> dict[str, float]:
    """One measurement on the code first on sys.path (the interpreter's own side)."""
    import numpy as np

    from agent.config import updated
    from lab.experiments.hull import world_step_cost
    from lab.harness.runner import run
    from sim_bridge.scenario import select_scenario
    from sim_bridge.world import World

    class TimedWorld(World):    # lab/harness/run_cost.py's, here too: the revision measured may be older than it
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            self.seconds = 0.0

        def step(self, commands) -> None:
            started = time.process_time()
            super().step(commands)
            self.seconds += time.process_time() - started

    _, kinematic = select_scenario(Path("configs/scenarios/table2_estimators.yaml"), "mckf")
    otter = updated(kinematic, world=updated(kinematic.world, dynamics={"preset": "otter"}))
    seed = np.random.SeedSequence(kinematic.seed).spawn(run_index + 1)[run_index]
    figures: dict[str, float] = {}
    for label, scenario in (("kinematic", kinematic), ("otter", otter)):
        worlds: list[TimedWorld] = []
        started = time.process_time()
        run(scenario, seed, make_world=lambda config, rng: worlds.append(TimedWorld(config, rng)) or worlds[-1])
        figures[f"{label}_s"] = time.process_time() - started
        figures[f"{label}_world_s"] = worlds[0].seconds
    figures["ratio"] = figures["otter_s"] / figures["kinematic_s"]
    figures["step_4_us"] = world_step_cost("otter", 4) * 1e6
    figures["step_50_us"] = world_step_cost("otter", 50) * 1e6
    return figures


def _measure_at(root: Path, run_index: int) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(root)}
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--measure", str(root), str(run_index)],
                          cwd=root, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"measuring {root} failed: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def compare(before: str, after: str | None, pairs: int, progress=print) -> dict:
    """Medians of `pairs` alternating runs of each side (runtime_ab's checkouts), over three seeds in turn."""
    from lab.benchmarks.runtime_ab import alternate

    results = alternate(before, after, pairs, lambda root, pair: _measure_at(root, pair % 3), "hull-ab", progress)
    return {side: {name: statistics.median(run[name] for run in runs) for name in FIGURES}
            for side, runs in results.items()}


def run(args: argparse.Namespace) -> int:
    from lab.report.markdown import markdown_table

    medians = compare(args.before, args.after, args.pairs, progress=lambda text: print(text, file=sys.stderr))
    rows = [[text, f"{medians['before'][name]:.3g}", f"{medians['after'][name]:.3g}",
             f"{medians['after'][name] / medians['before'][name]:.2f}"] for name, text in FIGURES.items()]
    print(markdown_table(["figure (medians of {} pairs)".format(args.pairs), "before", "after", "after / before"],
                         rows))
    return 0


if __name__ == "__main__":   # the internal --measure run, in an interpreter with one side's code on the path
    root = Path(sys.argv[sys.argv.index("--measure") + 1]).resolve()
    sys.path.insert(0, str(root))
    print(json.dumps(measure(int(sys.argv[sys.argv.index("--measure") + 2]))))
