"""A fleet that starts with nothing: the closest approach between vessels and the settling, seed by seed.

    python -m lab.cold_start [--scenario FILE] [--variant NAME] [--seeds FIRST LAST] [--duration S] [--cold all|ID]

Every vessel (or the one named) starts without initial estimates, as a fleet deployed without an
`initial:` section or a vessel restarted mid-mission does, and the in-process runner runs the scenario. The
table shows per seed the settling time, the closest approach of any two vessels, and e_ij and e_io after
20 s.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from agent.core.build import InitialEstimates
from lab import runner
from sim_bridge.scenario import initial_estimates, select_scenario

DEFAULT = Path(__file__).resolve().parents[1] / "configs" / "scenarios" / "table2_estimators.yaml"


def closest_approach(positions: np.ndarray) -> float:
    """Smallest distance between any two vessels over the run; positions (K, n, 2), NaN when absent."""
    n = positions.shape[1]
    return min(float(np.nanmin(np.hypot(*(positions[:, i] - positions[:, j]).T)))
               for i in range(n) for j in range(i + 1, n))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lab.cold_start", description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", type=Path, default=DEFAULT)
    parser.add_argument("--variant", default="mckf")
    parser.add_argument("--seeds", type=int, nargs=2, default=(0, 10), metavar=("FIRST", "LAST"))
    parser.add_argument("--duration", type=float, default=90.0)
    parser.add_argument("--cold", default="all", help="'all', or the id of the one vessel that starts cold")
    args = parser.parse_args(argv)
    _, scenario = select_scenario(args.scenario, args.variant)
    scenario = scenario.model_copy(update={"duration": args.duration})

    def cold_starts(scenario, truth, rng):
        drawn = initial_estimates(scenario, truth, rng)    # drawn anyway: the random streams stay the same
        return {v: InitialEstimates() if args.cold in ("all", v) else start for v, start in drawn.items()}

    runner.initial_estimates = cold_starts
    print("| seed | settled (s) | closest approach (m) | e_ij after 20 s (m) | e_io after 20 s (m) |")
    print("|---|---|---|---|---|")
    for seed in range(*args.seeds):
        trace = runner.run(scenario, seed)
        late = trace.time >= 20.0
        settled = trace.metrics.settling_time
        print(f"| {seed} | {'never' if settled is None else f'{settled:.1f}'} | "
              f"{closest_approach(trace.positions):.2f} | {np.nanmean(trace.e_ij[late]):.2f} | "
              f"{np.nanmean(trace.e_io[late]):.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
