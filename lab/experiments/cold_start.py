"""A fleet that starts with nothing: the closest approach between vessels and the settling, seed by seed.

    usv-lab cold-start [--scenario FILE] [--variant NAME] [--seeds FIRST LAST] [--duration S] [--cold all|ID]

Every vessel (or the one named) starts without initial estimates (the scenario's `initial.cold`), as a fleet
deployed without an `initial:` section or a vessel restarted mid-mission does, and the in-process runner
runs the scenario. The table shows per seed the settling time, the closest approach of any two vessels, and
e_ij and e_io after 20 s (time averages from 20 s to the end); the last lines sum them up against issue 13's
acceptance (at least 19 of 20 runs settle, e_ij after 20 s at most 0.2 m). configs/scenarios/cold_start.yaml
is the same fleet as a scenario page (`usv-lab scenario cold_start`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from agent.config import updated
from lab.experiments.scenarios import closest_approach, mean_after
from lab.harness import runner
from sim_bridge.scenario import select_scenario

DEFAULT = Path(__file__).resolve().parents[2] / "configs" / "scenarios" / "table2_estimators.yaml"
LATE = 20.0     # s: the errors are averaged from here to the end


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", type=Path, default=DEFAULT)
    parser.add_argument("--variant", default="mckf")
    parser.add_argument("--seeds", type=int, nargs=2, default=(0, 10), metavar=("FIRST", "LAST"))
    parser.add_argument("--duration", type=float, default=90.0)
    parser.add_argument("--cold", default="all", help="'all', or the id of the one vessel that starts cold")


def run(args: argparse.Namespace) -> int:
    _, scenario = select_scenario(args.scenario, args.variant)
    cold = "all" if args.cold == "all" else [args.cold]
    scenario = updated(scenario, duration=args.duration, initial=updated(scenario.initial, cold=cold))

    print(f"| seed | settled (s) | closest approach (m) | e_ij after {LATE:.0f} s (m) | "
          f"e_io after {LATE:.0f} s (m) |")
    print("|---|---|---|---|---|")
    settled, late_ij = 0, []
    for seed in range(*args.seeds):
        trace = runner.run(scenario, seed)
        settling = trace.metrics.settling_time
        e_ij, e_io = mean_after(trace.time, trace.e_ij, LATE), mean_after(trace.time, trace.e_io, LATE)
        settled += settling is not None
        late_ij.append(e_ij)
        print(f"| {seed} | {'never' if settling is None else f'{settling:.1f}'} | "
              f"{closest_approach(trace.positions):.2f} | {e_ij:.2f} | {e_io:.2f} |")
    print(f"\nsettled {settled}/{len(late_ij)}; e_ij after {LATE:.0f} s: mean {np.mean(late_ij):.3f} m, "
          f"worst run {np.max(late_ij):.3f} m")
    return 0
