"""`usv-lab sea-bench`: the fleet in the sim bridge's sea mode against the same fleet in the ideal lockstep
simulation, seed by seed, over real processes.

    usv-lab sea-bench [--scenario FILE] [--ideal NAME] [--sea NAME ...] [--seeds S ...] [--out PAGE]

For each seed the launcher runs the scenario's `ideal` variant (lockstep, one clock, no latency) and then each
sea variant (wall clock, clock offsets and drift, sensor latency and jitter, arrival stamps), and `usv-log`'s
metrics are read from each run's logs: e_ij and e_io compared with the truth at the true time each estimate
refers to (mission_log/series.py), the formation's e_c and the settling time. The page gives each run, and
per variant the ratio of its mean e_ij over the seeds to the ideal's: the sea mode is meant to cost at most
10 % (`LIMIT`). A sea run takes its duration in wall time plus about 13 s; the ideal runs take a few seconds.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from lab import arguments
from lab.arguments import seed as seed_type
from lab.report.markdown import invocation, markdown_table
from mission_log.metrics import truth_metrics
from mission_log.reader import load_run
from sim_bridge.fleet import launch
from sim_bridge.scenario import select_scenario

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_SCENARIO = ROOT / "configs" / "scenarios" / "sea_trial.yaml"
DEFAULT_PAGE = ROOT / "docs" / "results" / "sea_mode.md"
LIMIT = 1.10    # the sea mode's mean e_ij over the ideal's, at most


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", type=Path, default=DEFAULT_SCENARIO, help="scenario file with the variants")
    parser.add_argument("--ideal", default="ideal", help="the variant run in lockstep as the reference")
    parser.add_argument("--sea", nargs="+", default=["sea"], help="the sea-mode variants to compare")
    parser.add_argument("--seeds", type=seed_type, nargs="+", default=[2, 3, 4, 5, 6])
    parser.add_argument("--out", type=arguments.page, default=DEFAULT_PAGE, help="the page to write")
    parser.add_argument("--runs", type=Path, default=None, help="where the run folders go (default: a temporary "
                                                                 "folder, deleted afterwards)")


def run_once(scenario: Path, variant: str, seed: int, runs: Path) -> dict:
    """One launch; the metrics of its logs. The launcher's own output goes to the run folder's files."""
    _, spec = select_scenario(scenario, variant)
    folder = launch(scenario, variant, runs, seed, timeout=spec.duration * 3 + 120)
    radius = spec.agent_params().control.radius
    return truth_metrics(load_run(folder), radius) | {"folder": folder}


def run(args: argparse.Namespace) -> int:
    variants = [args.ideal, *args.sea]
    for variant in variants:
        select_scenario(args.scenario, variant)    # a typo fails now, not after minutes of runs
    with tempfile.TemporaryDirectory(prefix="usv-sea-bench-") as scratch:
        runs = args.runs or Path(scratch)
        results: dict[str, dict[int, dict]] = {v: {} for v in variants}
        total, done, started = len(variants) * len(args.seeds), 0, time.monotonic()
        for seed in args.seeds:
            for variant in variants:
                results[variant][seed] = run_once(args.scenario, variant, seed, runs)
                done += 1
                metrics = results[variant][seed]
                print(f"usv-lab sea-bench: [{done}/{total}] seed {seed} {variant}: e_ij {metrics['mean_e_ij']:.3f} m, "
                      f"settled {_settled(metrics)} ({time.monotonic() - started:.0f} s so far)", file=sys.stderr)
    page = render(args, results)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(page)
    print(page)
    return 0


def _settled(metrics: dict) -> str:
    return "never" if metrics["settling_time"] is None else f"{metrics['settling_time']:.1f} s"


def ratio_of_means(sea: list[float], ideal: list[float]) -> float:
    """Mean e_ij of the sea runs over that of the ideal runs (the same seeds)."""
    return float(np.mean(sea) / np.mean(ideal))


def render(args: argparse.Namespace, results: dict[str, dict[int, dict]]) -> str:
    ideal = results[args.ideal]
    rows = []
    for seed in args.seeds:
        for variant, by_seed in results.items():
            m = by_seed[seed]
            rows.append([seed, variant, f"{m['mean_e_ij']:.3f}", f"{m['mean_e_ij'] / ideal[seed]['mean_e_ij']:.2f}",
                         f"{m['mean_e_io']:.3f}", f"{m['mean_e_c']:.3f}", _settled(m)])
    summary = []
    for variant in args.sea:
        sea = [results[variant][s]["mean_e_ij"] for s in args.seeds]
        base = [ideal[s]["mean_e_ij"] for s in args.seeds]
        ratio = ratio_of_means(sea, base)
        settled = sum(results[variant][s]["settling_time"] is not None for s in args.seeds)
        summary.append([variant, f"{np.mean(base):.3f}", f"{np.mean(sea):.3f}", f"{ratio:.2f}",
                        "yes" if ratio <= LIMIT else "no", f"{settled}/{len(args.seeds)}"])
    return "\n".join([
        "# The sea mode against the ideal simulation",
        "",
        f"Made by `{invocation(args)}` (seeds {', '.join(map(str, args.seeds))}; scenario "
        f"`{args.scenario.relative_to(ROOT) if args.scenario.is_relative_to(ROOT) else args.scenario}`).",
        "",
        "Each seed runs the fleet over real processes twice or more: the ideal lockstep simulation, and the sea "
        "mode (vessel clocks with offsets and drift, sensor latency and jitter, stamps taken at arrival, ranges "
        "not on the ticks) on the wall clock. e_ij and e_io are compared with the truth at the true time each "
        "estimate refers to. The target is a mean e_ij within 10 % of the ideal's.",
        "",
        markdown_table(["sea variant", "ideal mean e_ij (m)", "sea mean e_ij (m)", "ratio", f"<= {LIMIT:.2f}",
                        "sea runs settled"], summary),
        "",
        "## Every run",
        "",
        markdown_table(["seed", "variant", "mean e_ij (m)", "e_ij / ideal", "mean e_io (m)", "mean e_c (m)",
                        "settled"], rows),
        "",
    ])
