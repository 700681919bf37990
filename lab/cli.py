"""`usv-lab`: the lab's one front door (also `python -m lab`), one subcommand per experiment or benchmark.

Experiments (lab/experiments/):
    usv-lab compare         the paper's Figs. 4-5 estimator comparison (Monte Carlo)
    usv-lab scenario        scenario files' Monte Carlo against the paper's Tables II-IV
    usv-lab replay          every estimator on a CSV of real ranges with ground truth (the analog of Fig. 6)
    usv-lab uwb-convert     a public UWB data set's checkout to replay CSVs
    usv-lab fit-noise       a UWB sensor's noise config from its calibration runs
    usv-lab uwb-page        every converted run replayed; the real-data result page
    usv-lab cold-start      a fleet that starts knowing nothing, seed by seed
    usv-lab observability   which pairs are observable, and from when, seed by seed
    usv-lab hull            the hull presets' closed-form figures and inner-loop step responses
    usv-lab sea-agent-ab    the agent's measures for the boat's lags and limits, with and without
    usv-lab sea-states      the sea states' page: the fleet on the Otter's hull in each state, cold start, A/B
    usv-lab loop-margins    the heading loop's and the formation modes' margins under 1 s lags
    usv-lab sea-sway        the coping agent on the sea states, with and without the sideslip correction
    usv-lab sea-wind        the wind's leeway: odometry, radius and the leeway model, with and without
    usv-lab driver-loop     the driver bridge's inner loop on the Otter, the rate from a VHW compass
Benchmarks (lab/benchmarks/):
    usv-lab bench, fleet-bench, runtime-bench, runtime-ab, hull-ab, cluster-bench, share-bench, sea-bench, fuzz,
    serial-fuzz, mavlink-fuzz, mavlink-fleet

A subcommand is a module with `add_arguments(parser)` and `run(args) -> exit code`, or, for a module of
several, `add_<name>_arguments` and `run_<name>` (SUBCOMMANDS names them `module:name`).
"""

from __future__ import annotations

import argparse
import importlib
import sys

from agent.config import ConfigError

SUBCOMMANDS = {
    "compare": ("lab.experiments.compare", "estimator comparison of the paper's Figs. 4 and 5"),
    "scenario": ("lab.experiments.scenarios", "scenario files' Monte Carlo vs the paper's Tables II-IV"),
    "replay": ("lab.experiments.replay",
               "replay a CSV of real ranges with ground truth through every estimator"),
    "uwb-convert": ("lab.experiments.uwb_datasets:convert",
                    "a public UWB data set's checkout to replay CSVs and their manifest"),
    "fit-noise": ("lab.experiments.uwb_datasets:fit_noise",
                  "a UWB sensor's noise config from its calibration runs"),
    "uwb-page": ("lab.experiments.uwb_datasets:page",
                 "replay every converted run with config noise; write the real-data result page"),
    "cold-start": ("lab.experiments.cold_start",
                   "a fleet that starts with nothing: settling and closest approach"),
    "observability": ("lab.experiments.observability",
                      "which pairs of a fleet are observable, and from when"),
    "hull": ("lab.experiments.hull",
             "the hull presets: steady speeds, time constants, turning circles, inner-loop step responses"),
    "bench": ("lab.benchmarks.estimators", "per-update cost of each estimator vs filterpy's KalmanFilter"),
    "fleet-bench": ("lab.benchmarks.fleet", "Table II Monte Carlo wall time, tick cost by fleet size"),
    "runtime-bench": ("lab.benchmarks.runtime",
                      "Zenoh runtime: sensor-to-command latency, lockstep real-time factor, memory"),
    "share-bench": ("lab.benchmarks.shares",
                    "shares broadcast against per pair: bytes and decode CPU per agent per tick, by fleet size"),
    "cluster-bench": ("lab.benchmarks.cluster",
                      "the same Monte Carlo campaign on the process pool and a local Dask cluster"),
    "runtime-ab": ("lab.benchmarks.runtime_ab",
                   "what one change to the runtime bought: alternating runs before and after it"),
    "hull-ab": ("lab.benchmarks.hull_ab",
                "what one change to the hull world bought: Table II kinematic and on the Otter, before and after"),
    "fuzz": ("lab.benchmarks.fuzz", "fuzz campaign over Zenoh: bad payloads on every key one agent reads"),
    "serial-fuzz": ("lab.benchmarks.serial_fuzz",
                    "the serial side of the fuzz campaign alone: bad lines per parser"),
    "mavlink-fuzz": ("lab.benchmarks.mavlink_fuzz",
                     "the MAVLink side of the fuzz campaign: hostile datagrams at the driver's link"),
    "mavlink-fleet": ("lab.benchmarks.mavlink_fleet",
                      "the fleet through MAVLink stand-ins against the sim bridge: metrics, latency, HOLD"),
    "sea-bench": ("lab.benchmarks.sea",
                  "the fleet in the sea mode against the ideal simulation, seed by seed"),
    "sea-agent-ab": ("lab.experiments.sea_agent_ab",
                     "the agent's measures for lags, limits, compass bias and current, with and without"),
    "sea-states": ("lab.experiments.sea_states",
                   "the Table II fleet on the Otter's hull in each sea state vs the ideal; cold start; A/B"),
    "loop-margins": ("lab.experiments.loop_margins",
                     "phase and gain margins of the heading loop and the formation's modes under hull lags"),
    "sea-sway": ("lab.experiments.sea_sway:table",
                 "the coping agent on the sea states, with and without the speed log's sideslip correction"),
    "sea-wind": ("lab.experiments.sea_wind:table",
                 "the wind's leeway: the odometry, r* and the agent's leeway model, with and without"),
    "driver-loop": ("lab.experiments.driver_loop",
                    "the driver bridge's inner loop on a hull preset, the yaw rate from a VHW compass"),
}


def entry_points(target: str):
    """(add_arguments, run) of a SUBCOMMANDS target, `module` or `module:name`."""
    module_name, _, name = target.partition(":")
    module = importlib.import_module(module_name)
    if not name:
        return module.add_arguments, module.run
    return getattr(module, f"add_{name}_arguments"), getattr(module, f"run_{name}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="usv-lab", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    runs = {}
    for name, (target, help_text) in SUBCOMMANDS.items():
        add_arguments, runs[name] = entry_points(target)
        add_arguments(commands.add_parser(name, help=help_text, description=help_text))
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    args.argv = argv  # for report.invocation: the command that made each result
    try:
        return runs[args.command](args)
    except ConfigError as error:
        print(f"usv-lab {args.command}: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"usv-lab {args.command}: interrupted", file=sys.stderr)
        return 130
