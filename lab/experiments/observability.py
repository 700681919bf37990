"""Which pairs of a fleet are observable, and from when: each pair filter's verdict (agent/core/observability.py)
over in-process runs, seed by seed.

    usv-lab observability [--scenario FILE] [--variant NAME] [--seeds FIRST LAST] [--duration S] [--cold]
                                [--abreast DISTANCE] [--weave AMPLITUDE] [--min-width W] [--window TAU]

Per seed, the settling time and the closest approach of two vessels; per pair i-j (vessel i's filter of
neighbour j): when the filter started and its error |p^_ij - p_ij| then, when the pair was first observable,
when a `raw_range` filter first fixed its position (the mirror resolved), when the pair was first localised
(steered the formation), the seconds it spent mirror-ambiguous or unobservable before it was first
observable and after, and the smallest eigenvalue of its path spread at the end. `--cold` starts every vessel
without initial estimates, as `usv-lab cold-start` does; `--abreast D` puts the vessels in a line abreast, 4 m apart, D metres west of the target and heading
east, so that they move in parallel towards it.

`--weave A` tries an excitation manoeuvre: during the first `WEAVE_UNTIL` seconds, while any of a vessel's
pairs is not observable and the vessel is moving, A sin(2 pi t / `WEAVE_PERIOD`) rad/s is added to its
commanded yaw rate (after the core, so it is an experiment here, not a behaviour of the agent). The last line
of each seed says when every pair was localised and the mean e_ij after 20 s, which the manoeuvre would have
to improve (docs/estimation.md, "Observability"). `--min-width` and `--window` judge the pairs with another
w_min and tau than the agent's defaults (`ObservabilityParams`).
"""

from __future__ import annotations

import argparse
import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from agent.config import updated
from agent.core.observability import OBSERVABLE, ObservabilityParams
from agent.core.records import Command, TickOutput
from agent.core.step import step
from lab.experiments.cold_start import LATE
from lab.experiments.scenarios import closest_approach, mean_after
from lab.harness import runner
from sim_bridge.scenario import select_scenario

DEFAULT = Path(__file__).resolve().parents[2] / "configs" / "scenarios" / "table2_estimators.yaml"
WEAVE_PERIOD = 6.0    # s
WEAVE_UNTIL = 30.0    # s


def pair_verdicts(scenario, seed: int, cold: bool, weave: float = 0.0) -> tuple[dict, runner.RunTrace]:
    """(i, j) -> [(time, lambda_min, lambda_max, verdict, localised, fixed)] of one run, and the run's trace;
    `fixed` is None for an estimator that is not raw_range."""
    seen: dict[tuple[str, str], list] = defaultdict(list)

    def observed_step(params, state, inputs):
        state, output = step(params, state, inputs)
        record = output.record
        if record is None:
            return state, output
        for j, n in record.neighbours.items():
            fixed = getattr(state.tracks[j].estimator, "fixed", None)
            seen[state.vessel, j].append((inputs.time, *n.excitation, n.observability, n.localised, fixed))
        short = not record.neighbours or any(n.observability != OBSERVABLE for n in record.neighbours.values())
        if weave and short and inputs.time < WEAVE_UNTIL and output.command.surge != 0.0:
            turn = weave * math.sin(2.0 * math.pi * inputs.time / WEAVE_PERIOD)
            command = Command(output.command.surge, output.command.yaw_rate + turn)
            output = TickOutput(command, output.share, record)
        return state, output

    if cold:
        scenario = updated(scenario, initial=updated(scenario.initial, cold="all"))
    saved = runner.step
    runner.step = observed_step
    try:
        trace = runner.run(scenario, seed)
    finally:
        runner.step = saved
    return dict(seen), trace


def pair_error(trace: runner.RunTrace, i: str, j: str) -> np.ndarray:
    """|p^_ij - p_ij| per tick (m), NaN where either is absent."""
    a, b = trace.vessels.index(i), trace.vessels.index(j)
    truth = trace.positions[:, a] - trace.positions[:, b]
    return np.hypot(*(trace.relative[:, a, b] - truth).T)


def line_abreast(scenario, distance: float):
    """The scenario with its vessels 4 m apart on a north-south line `distance` metres west of the target,
    heading east."""
    world = scenario.world
    x, y = world.target.position
    n = len(world.vessels)
    vessels = [v.model_copy(update={"position": (x - distance, y + 4.0 * (k - (n - 1) / 2)), "heading": 0.0})
               for k, v in enumerate(world.vessels)]
    return scenario.model_copy(update={"world": world.model_copy(update={"vessels": vessels})})


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", type=Path, default=DEFAULT)
    parser.add_argument("--variant", default="raw_range")
    parser.add_argument("--seeds", type=int, nargs=2, default=(0, 3), metavar=("FIRST", "LAST"))
    parser.add_argument("--duration", type=float, default=None, help="s (default: the scenario's)")
    parser.add_argument("--cold", action="store_true", help="every vessel starts without initial estimates")
    parser.add_argument("--abreast", type=float, default=None, metavar="DISTANCE",
                        help="start in a line abreast this far (m) west of the target, heading east")
    parser.add_argument("--weave", type=float, default=0.0, metavar="AMPLITUDE",
                        help="yaw-rate amplitude (rad/s) of the trial excitation manoeuvre (default: none)")
    parser.add_argument("--min-width", type=float, default=None, metavar="W", help="w_min (m) to judge with")
    parser.add_argument("--window", type=float, default=None, metavar="TAU", help="tau (s) to judge with")


def run(args: argparse.Namespace) -> int:
    _, scenario = select_scenario(args.scenario, args.variant)
    if args.duration is not None:
        scenario = scenario.model_copy(update={"duration": args.duration})
    if args.abreast is not None:
        scenario = line_abreast(scenario, args.abreast)
    dt = scenario.world.dt
    if args.min_width is not None or args.window is not None:
        relative = scenario.agent.relative
        judged = ObservabilityParams(min_width=args.min_width or relative.observability.min_width,
                                     window=args.window or relative.observability.window)
        scenario = updated(scenario, agent=updated(scenario.agent, relative=updated(relative, observability=judged)))
    for seed in range(*args.seeds):
        seen, trace = pair_verdicts(scenario, seed, args.cold, args.weave)
        settled = trace.metrics.settling_time
        print(f"seed {seed}: settled {'never' if settled is None else f'{settled:.1f} s'}, closest approach "
              f"{closest_approach(trace.positions):.2f} m\n")
        print("| pair | started (s) | e_ij then (m) | first observable (s) | fixed (s) | first localised (s) | "
              "not observable before, after (s) | lambda_min at the end (m^2) |")
        print("|---|---|---|---|---|---|---|---|")
        for (i, j), rows in sorted(seen.items()):
            started = rows[0][0]
            first = next((row[0] for row in rows if row[3] == OBSERVABLE), None)
            fixed = next((row[0] for row in rows if row[5]), None)
            localised = next((row[0] for row in rows if row[4]), None)
            before = dt * sum(row[3] != OBSERVABLE for row in rows if first is None or row[0] < first)
            after = dt * sum(row[3] != OBSERVABLE for row in rows if first is not None and row[0] >= first)
            error = float(pair_error(trace, i, j)[round(started / dt)])
            print(f"| {i}-{j} | {started:.1f} | {error:.2f} | {_time(first)} | {_time(fixed)} | {_time(localised)} | "
                  f"{before:.1f}, {after:.1f} | {rows[-1][1]:.2f} |")
        localised = [next((row[0] for row in rows if row[4]), None) for rows in seen.values()]
        everyone = None if None in localised or not localised else max(localised)
        print(f"\nevery pair localised by {_time(everyone)} s; mean e_ij after {LATE:.0f} s "
              f"{mean_after(trace.time, trace.e_ij, LATE):.3f} m\n")
    return 0


def _time(value: float | None) -> str:
    return "never" if value is None else f"{value:.1f}"
