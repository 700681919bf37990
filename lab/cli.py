"""`usv-lab`: the offline experiments, one subcommand each.

    usv-lab compare   the paper's Figs. 4-5 estimator comparison (Monte Carlo)
    usv-lab replay    every estimator on a CSV of real ranges with ground truth (the analog of Fig. 6)
    usv-lab bench     per-update cost of each estimator against filterpy's KalmanFilter

Each subcommand module offers `add_arguments(parser)` and `run(args) -> exit code`.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from agent.config import ConfigError

SUBCOMMANDS = {
    "compare": ("lab.compare_cmd", "estimator comparison of the paper's Figs. 4 and 5"),
    "replay": ("lab.range_replay", "replay a CSV of real ranges with ground truth through every estimator"),
    "bench": ("lab.bench", "per-update cost of each estimator vs filterpy's KalmanFilter"),
    "scenario": ("lab.scenario_cmd", "scenario files' Monte Carlo vs the paper's Tables II-IV"),
    "fleet-bench": ("lab.fleet_bench", "Table II Monte Carlo wall time, tick cost by fleet size"),
    "runtime-bench": ("lab.runtime_bench",
                      "Zenoh runtime: sensor-to-command latency, lockstep real-time factor, memory"),
    "cluster-bench": ("lab.cluster_bench", "the same Monte Carlo campaign on the process pool and a local Dask cluster"),
    "runtime-ab": ("lab.runtime_ab", "what one change to the runtime bought: alternating runs before and after it"),
    "fuzz": ("lab.fuzz_bench", "fuzz campaign over Zenoh: bad payloads on every key one agent reads"),
    "sea-bench": ("lab.sea_bench", "the fleet in the sea mode against the ideal simulation, seed by seed"),
    "sea-agent-ab": ("lab.sea_agent_ab", "the agent's measures for lags, limits, compass bias and current, with and "
                                         "without"),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="usv-lab", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    modules = {}
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        module = importlib.import_module(module_name)
        module.add_arguments(commands.add_parser(name, help=help_text, description=help_text))
        modules[name] = module
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    args.argv = argv  # for report.invocation: the command that made each result
    try:
        return modules[args.command].run(args)
    except ConfigError as error:
        print(f"usv-lab {args.command}: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"usv-lab {args.command}: interrupted", file=sys.stderr)
        return 130
