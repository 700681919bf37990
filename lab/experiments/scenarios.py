"""`usv-lab scenario`: Monte Carlo runs of the paper's scenario files (Sec. VI, Tables II-IV, Figs. 7-15).

Every run of every variant of every requested file goes through one process pool; run r of a variant gets
child r of `SeedSequence(scenario.seed)`, so the numbers do not depend on the number of workers (only the
measured tick times do). One markdown page per file puts our means beside the paper's (where it gives
any), then the whole-run means beside the means after settling, with two figures.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path

import numpy as np

from agent.config import ConfigError, updated
from lab import arguments
from lab.harness.errors import RunningMoments
from lab.harness.parallel import Engine, add_engine_arguments, campaign_notes, engine_from, report_failures
from lab.harness.runner import RunTrace
from lab.harness.runner import run as run_scenario
from lab.report.fleet_plots import error_figure, trajectory_figure
from lab.report.markdown import invocation, markdown_table
from mission_log.metrics import RunMetrics, nan_mean
from sim_bridge.scenario import (
    SCENARIOS_DIR,
    Scenario,
    ScenarioFile,
    load_scenarios,
    scenario_file,
    scenario_files,
)

DEFAULT_DIR = SCENARIOS_DIR
ERRORS = ("e_ij", "e_io", "e_c")            # the per-tick errors kept from every run, in this order
TIMING_KEYS = ("tick_ms", "p99_tick_ms")   # summary entries that depend on the machine, not the seed


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("names", nargs="+", metavar="NAME",
                        help="scenario file stem in --scenarios-dir (e.g. table2_estimators), a YAML path, "
                             "or 'all'")
    parser.add_argument("--runs", type=arguments.positive_int, default=None,
                        help="Monte Carlo runs of every variant (default: each file's own)")
    parser.add_argument("--seed", type=arguments.seed, default=None,
                        help="root seed of every variant (default: each file's own)")
    add_engine_arguments(parser)
    parser.add_argument("--out", type=arguments.folder, default=Path("docs/results/scenarios"),
                        help="where the pages and figures go")
    parser.add_argument("--scenarios-dir", type=Path, default=DEFAULT_DIR,
                        help="where NAME stems and 'all' are looked up")


# ----------------------------------------------------------------------------------------------------------
# Which files
# ----------------------------------------------------------------------------------------------------------

def resolve(names: Sequence[str], directory: Path) -> list[Path]:
    """The scenario files `names` stand for, in order, without repeats; ConfigError lists what exists."""
    paths: list[Path] = []
    for name in names:
        if name == "all":
            found = scenario_files(directory)
            if not found:
                raise ConfigError(f"no scenario files (*.yaml) in {directory}")
            paths += found
            continue
        try:
            paths.append(scenario_file(name, directory))
        except ConfigError as error:
            raise ConfigError(f"{error} (or 'all')") from None
    unique: dict[str, Path] = {}
    for path in paths:
        other = unique.setdefault(path.stem, path)
        if other.resolve() != path.resolve():
            raise ConfigError(f"two scenario files share the name {path.stem!r}: {other} and {path}")
    return list(unique.values())


def load(path: Path, runs: int | None = None, seed: int | None = None
         ) -> tuple[ScenarioFile, dict[str, Scenario]]:
    """A scenario file with the command line's overrides applied to every variant."""
    spec, scenarios = load_scenarios(path)
    overrides = {key: value for key, value in (("runs", runs), ("seed", seed)) if value is not None}
    if overrides:
        scenarios = {name: updated(scenario, **overrides) for name, scenario in scenarios.items()}
    return spec, scenarios


# ----------------------------------------------------------------------------------------------------------
# Monte Carlo
# ----------------------------------------------------------------------------------------------------------

def mean_after(time: np.ndarray, values: np.ndarray, start: float) -> float:
    """Time average of `values` from `start` (s) to the end of the run; NaN ticks (no estimate yet, a vessel
    absent) do not count."""
    return nan_mean(np.asarray(values)[np.asarray(time) >= start])


def closest_approach(positions: np.ndarray) -> float:
    """Smallest distance between any two vessels over the run; positions (K, n, 2), NaN when absent (a
    vessel that leaves before another joins is never compared with it)."""
    pairs = combinations(range(positions.shape[1]), 2)
    gaps = [np.hypot(*(positions[:, i] - positions[:, j]).T) for i, j in pairs]
    return float(np.nanmin(gaps))


@dataclass
class RunOutcome:
    """What one run sends back from a worker: metrics, error curves, the closest approach of any two
    vessels and, for run 0, the whole trace."""

    metrics: RunMetrics
    errors: np.ndarray                  # (3, K): ERRORS over time
    closest: float
    trace: RunTrace | None


@dataclass
class VariantResult:
    """A variant's runs, reduced as they arrived (in run order): what the pages need and no per-run curve, so
    a campaign of any size holds a few arrays per variant."""

    name: str
    scenario: Scenario
    time: np.ndarray                    # (K,)
    metrics: list[RunMetrics]           # one per run, in run order
    error_mean: np.ndarray              # (3, K): ERRORS over time, mean over the runs (NaN ticks left out)
    error_std: np.ndarray               # (3, K): their std
    settled: dict[str, np.ndarray]      # ERRORS -> each settled run's mean from its settling time on
    closest: np.ndarray                 # (runs,) closest approach of any two vessels
    first: RunTrace | None              # run 0, for the trajectory figure

    def mean_std(self, field: str) -> tuple[float, float]:
        values = np.array([getattr(m, field) for m in self.metrics], dtype=float)
        return _nan_mean_std(values)

    @property
    def settling_times(self) -> list[float]:
        return [m.settling_time for m in self.metrics if m.settling_time is not None]

    def after_settling(self, error: str) -> np.ndarray:
        """Each settled run's time average of `error` (one of ERRORS) from its own settling time to the
        end; the runs that never settle have none."""
        return self.settled[error]

    def summary(self) -> dict[str, float]:
        """The aggregated numbers of the variant; TIMING_KEYS are the only machine-dependent ones."""
        result = {"runs": float(len(self.metrics)), "settled": float(len(self.settling_times))}
        for key in ("e_ij", "e_io", "e_io_velocity", "e_c"):
            result[key], result[f"{key}_std"] = self.mean_std(f"mean_{key}")
        for key in ERRORS:
            result[f"{key}_settled"], result[f"{key}_settled_std"] = _nan_mean_std(self.after_settling(key))
        result["settling_time"], result["settling_time_std"] = _nan_mean_std(np.array(self.settling_times))
        result["closest"], result["closest_std"] = _nan_mean_std(self.closest)
        result["closest_min"] = float(np.min(self.closest))
        result["tick_ms"] = self.mean_std("mean_tick_ms")[0]
        result["p99_tick_ms"] = self.mean_std("p99_tick_ms")[0]
        return result


def _nan_mean_std(values: np.ndarray) -> tuple[float, float]:
    finite = values[np.isfinite(values)]
    if len(finite) == 0:
        return math.nan, math.nan
    return float(finite.mean()), float(finite.std())


class RunsGathered:
    """One variant's runs reduced as they come, in run order (so the sums are the same whoever ran them):
    the metrics and closest approaches kept, the error curves folded into a running mean and spread per tick
    (Welford's update; a NaN tick of a run is left out of that tick), each settled run's mean after settling."""

    def __init__(self, time: np.ndarray) -> None:
        self.time = time
        self.metrics: list[RunMetrics] = []
        self.closest: list[float] = []
        self.settled: dict[str, list[float]] = {error: [] for error in ERRORS}
        self.first: RunTrace | None = None
        self._errors = RunningMoments((len(ERRORS), len(time)))

    def add(self, metrics: RunMetrics, errors: np.ndarray, closest: float, trace: RunTrace | None = None) -> None:
        self.metrics.append(metrics)
        self.closest.append(closest)
        if trace is not None and self.first is None:
            self.first = trace
        if metrics.settling_time is not None:
            for panel, error in enumerate(ERRORS):
                self.settled[error].append(mean_after(self.time, errors[panel], metrics.settling_time))
        self._errors.add(errors)

    def result(self, name: str, scenario: Scenario) -> VariantResult:
        return VariantResult(name=name, scenario=scenario, time=self.time, metrics=list(self.metrics),
                             error_mean=self._errors.mean, error_std=self._errors.std,
                             settled={error: np.array(values) for error, values in self.settled.items()},
                             closest=np.array(self.closest), first=self.first)


Job = tuple[Scenario, np.random.SeedSequence, bool]


def _run_job(job: Job) -> RunOutcome:
    scenario, seed, keep_trace = job
    trace = run_scenario(scenario, seed)
    errors = np.stack([getattr(trace, name) for name in ERRORS])
    return RunOutcome(trace.metrics, errors, closest_approach(trace.positions), trace if keep_trace else None)


def run_monte_carlo(files: dict[str, dict[str, Scenario]], engine: Engine | int,
                    progress: Callable[[int], None] | None = None) -> dict[str, dict[str, VariantResult]]:
    """Every run of every variant of `files` ({stem: {variant: scenario}}), results in the same shape. A run
    that raised is left out (`engine.failures` names it); so is a variant whose run 0 (the figures') did. Each
    run is reduced as it comes (`RunsGathered`), in run order, so the client holds no per-run curve. An int
    `engine` is a process pool of that many workers."""
    keys: list[tuple[str, str, int]] = []
    jobs: list[Job] = []
    for stem, scenarios in files.items():
        for variant, scenario in scenarios.items():
            for index, seed in enumerate(np.random.SeedSequence(scenario.seed).spawn(scenario.runs)):
                keys.append((stem, variant, index))
                jobs.append((scenario, seed, index == 0))
    if isinstance(engine, int):
        with Engine(engine) as pool:
            return run_monte_carlo(files, pool, progress)

    def describe(n: int) -> str:
        stem, variant, index = keys[n]
        return f"{stem} variant {variant} run {index} (child {index} of seed {files[stem][variant].seed})"

    gathered: dict[tuple[str, str], RunsGathered] = {}
    dropped: set[tuple[str, str]] = set()

    def consume(n: int, outcome: RunOutcome | None) -> None:
        stem, variant, index = keys[n]
        if outcome is None:
            if index == 0:   # run 0 keeps its trace for the figures; it failed, and so the variant is left out
                dropped.add((stem, variant))
            return
        runs = gathered.get((stem, variant))
        if runs is None:
            time = np.arange(outcome.errors.shape[1]) * files[stem][variant].world.dt   # the runner's time base
            runs = gathered[stem, variant] = RunsGathered(time)
        runs.add(outcome.metrics, outcome.errors, outcome.closest, outcome.trace)

    engine.map(_run_job, jobs, progress, describe, consume=consume)
    results: dict[str, dict[str, VariantResult]] = {}
    for (stem, variant), runs in gathered.items():
        if (stem, variant) not in dropped:
            results.setdefault(stem, {})[variant] = runs.result(variant, files[stem][variant])
    return results


# ----------------------------------------------------------------------------------------------------------
# The command
# ----------------------------------------------------------------------------------------------------------

def run(args: argparse.Namespace) -> int:
    # tqdm (the optional 'lab' extra) is imported by the command that shows a bar, not by `usv-lab --help`.
    from tqdm import tqdm

    paths = resolve(args.names, args.scenarios_dir)
    loaded = {path.stem: (path, *load(path, args.runs, args.seed)) for path in paths}
    files = {stem: scenarios for stem, (_, _, scenarios) in loaded.items()}
    total = sum(s.runs for scenarios in files.values() for s in scenarios.values())
    started = time.perf_counter()
    with engine_from(args) as engine, tqdm(total=total, unit="run", desc="scenarios", dynamic_ncols=True) as bar:
        results = run_monte_carlo(files, engine, bar.update)
        where = engine.where()
    elapsed = time.perf_counter() - started

    args.out.mkdir(parents=True, exist_ok=True)
    command = invocation(args)
    index = []
    for stem, (path, spec, _) in loaded.items():
        variants = results.get(stem)
        if not variants:
            print(f"\n{stem}: no variant finished its run 0; no page", file=sys.stderr)
            continue
        trajectories = trajectory_figure(
            {name: (v.first, v.scenario) for name, v in variants.items()},
            f"{spec.name}: trajectories of run 0", args.out / f"{stem}_trajectories.png")
        errors = error_figure(
            {name: (v.time, v.error_mean, v.error_std) for name, v in variants.items()}, join_leave_events(variants),
            f"{spec.name}: errors, mean over runs +-1 std", args.out / f"{stem}_errors.png")
        tables = (comparison_table(variants), settling_table(variants))
        page = render_page(path, spec, variants, tables, command, elapsed, where,
                           (trajectories.name, errors.name), campaign_notes(engine))
        (args.out / f"{stem}.md").write_text(page, encoding="utf-8")
        print(f"\n{stem}:\n{tables[0]}\n\n{tables[1]}")
        index.append((stem, spec, variants))
    if "all" in args.names:
        (args.out / "README.md").write_text(render_index(index, command), encoding="utf-8")
    print(f"\nwrote {len(index)} page(s) to {args.out} in {elapsed:.1f} s")
    return report_failures(engine)


def join_leave_events(variants: dict[str, VariantResult]) -> list[tuple[float, str]]:
    """(time, 'vessel 5 joins (join)') for every vessel that joins late or leaves, over all variants."""
    events = []
    for name, result in variants.items():
        for vessel in result.scenario.world.vessels:
            if vessel.join_time > 0:
                events.append((vessel.join_time, f"{vessel.id} joins ({name})"))
            if vessel.leave_time is not None:
                events.append((vessel.leave_time, f"{vessel.id} leaves ({name})"))
    return sorted(events)


# ----------------------------------------------------------------------------------------------------------
# Pages
# ----------------------------------------------------------------------------------------------------------

def _ours(mean: float, std: float, digits: int = 3) -> str:
    return "-" if math.isnan(mean) else f"{mean:.{digits}f} ± {std:.{digits}f}"


def _paper(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _paper_tables(variants: dict[str, VariantResult]) -> list[str]:
    """The paper's tables the variants are compared with; none when the paper gives no numbers."""
    return sorted({r.scenario.paper.table for r in variants.values() if r.scenario.paper.table})


def comparison_table(variants: dict[str, VariantResult]) -> str:
    """The whole-run means, each beside the paper's figure when the paper gives any for the file."""
    with_paper = bool(_paper_tables(variants))

    def pair(ours: str, paper: str) -> list[str]:
        return [ours, paper] if with_paper else [ours]

    header = ["variant", *pair("e_ij ours (m)", "e_ij paper"), *pair("e_io ours (m)", "e_io paper"),
              *pair("e_c ours (m)", "e_c paper"), *pair("settling ours (s)", "settling paper"),
              *pair("tick ours (ms)", "run time paper (ms)"), "settled runs"]
    rows = []
    for name, result in variants.items():
        s, paper = result.summary(), result.scenario.paper
        rows.append([
            name,
            *pair(_ours(s["e_ij"], s["e_ij_std"]), _paper(paper.mean_e_ij)),
            *pair(_ours(s["e_io"], s["e_io_std"]), _paper(paper.mean_e_io)),
            *pair(_ours(s["e_c"], s["e_c_std"]), _paper(paper.mean_e_c)),
            *pair(_ours(s["settling_time"], s["settling_time_std"], 2) if s["settled"] else "never",
                  _paper(paper.settling_time, 2)),
            *pair(f"{s['tick_ms']:.3f}", _paper(paper.run_time_ms, 2)),
            f"{int(s['settled'])}/{int(s['runs'])}",
        ])
    return markdown_table(header, rows)


def settling_table(variants: dict[str, VariantResult]) -> str:
    """e_c over the whole run beside the means after settling, and how close any two vessels came."""
    header = ["variant", "e_c whole run (m)", "e_c after settling (m)", "e_ij after settling (m)",
              "e_io after settling (m)", "closest approach (m)", "closest, worst run (m)", "settled runs"]
    rows = []
    for name, result in variants.items():
        s = result.summary()
        rows.append([
            name, _ours(s["e_c"], s["e_c_std"]),
            *(_ours(s[f"{key}_settled"], s[f"{key}_settled_std"]) for key in ("e_c", "e_ij", "e_io")),
            _ours(s["closest"], s["closest_std"], 2), f"{s['closest_min']:.2f}",
            f"{int(s['settled'])}/{int(s['runs'])}",
        ])
    return markdown_table(header, rows)


def _setting(variants: dict[str, VariantResult], value: Callable[[Scenario], object]) -> str:
    """One value if every variant agrees, else each variant's."""
    values = {name: value(result.scenario) for name, result in variants.items()}
    if len(set(values.values())) == 1:
        return str(next(iter(values.values())))
    return "; ".join(f"{name}: {v}" for name, v in values.items())


def _start(scenario: Scenario) -> str:
    """What the vessels know at the start, for the settings list."""
    cold = scenario.initial.cold
    if cold == "all":
        return "none, every vessel starts cold"
    drawn = (f"drawn around the truth, P_ij,0 = {scenario.initial.neighbour_variance} I, "
             f"P_io,0 = {scenario.initial.target_variance} I")
    return drawn + (f"; none for {', '.join(cold)} (cold)" if cold else "")


def render_page(path: Path, spec: ScenarioFile, variants: dict[str, VariantResult], tables: tuple[str, str],
                command: str, elapsed: float, where: str, figures: tuple[str, str], notes: list[str] = ()) -> str:
    paper = _paper_tables(variants)
    heading = (f"Ours vs the paper's Table {', '.join(paper)}" if paper
               else "Ours (the paper gives no numbers)")
    paper_time = (" The paper's Avg. Run Time is per iteration on its own machine, and it shows a single "
                  "run, so its numbers have no spread." if paper else "")
    runs = _setting(variants, lambda s: s.runs)
    return "\n".join([
        f"# Scenario {spec.name}" + (f": {spec.description}" if spec.description else ""),
        "",
        f"Generated from `{path}` by the command below; do not edit by hand.",
        "",
        "```",
        command,
        "```",
        "",
        "## Settings",
        "",
        f"- duration (s): {_setting(variants, lambda s: s.duration)}",
        f"- Monte Carlo runs per variant: {runs}",
        f"- root seed: {_setting(variants, lambda s: s.seed)} "
        "(run r uses child r of numpy's SeedSequence(seed))",
        f"- vessels: {_setting(variants, lambda s: len(s.world.vessels))}; "
        f"r* (m): {_setting(variants, lambda s: s.agent.control.radius)}; "
        f"dt (s): {_setting(variants, lambda s: s.world.dt)}",
        f"- initial estimates: {_setting(variants, _start)}",
        f"- wall time {elapsed:.1f} s for all the files of the command; ran on {where}; "
        f"os.cpu_count() = {os.cpu_count()}",
        *notes,
        "",
        f"## {heading}",
        "",
        "Ours: mean ± std over the runs of each run's time average of the error over the whole run (the "
        "paper's \"Mean\", Sec. VI: e_ij, e_io the worst over the vessels at each tick, e_c the formation "
        "centre's distance to the target; a tick at which no vessel has an estimate yet does not count). "
        "Settling: first time from which every radius stays within ±10 % of r* to the end; mean ± std over "
        "the settled runs only, whose count is the last column. Tick: mean compute time of one vessel's tick "
        "(all its estimators and its controller), the CPU time of the worker's thread on this machine."
        f"{paper_time}",
        "",
        tables[0],
        "",
        "## Whole run and after settling",
        "",
        "The whole-run mean includes the start-up transient. After settling: each settled run's time "
        "average from its own settling time to the end of the run, then mean ± std over the settled runs "
        "(a run that never settles has no such average; the last column counts the settled runs). Closest "
        "approach: the smallest distance between any two vessels in a run, mean ± std over all runs, and "
        "the smallest of any run.",
        "",
        tables[1],
        "",
        "## Figures",
        "",
        "Trajectories of run 0 of each variant (start ○, end △; red dotted: line of sight to the target "
        "blocked by an island, every 10th blocked tick):",
        "",
        f"![trajectories]({figures[0]})",
        "",
        "Errors over time, mean over the runs with a ±1 std band (dashed vertical lines: a vessel joins or "
        "leaves):",
        "",
        f"![errors]({figures[1]})",
        "",
    ])


def render_index(pages: list[tuple[str, ScenarioFile, dict[str, VariantResult]]], command: str) -> str:
    lines = ["# Scenario results", "", "Generated by the command below; do not edit by hand.", "", "```",
             command, "```", ""]
    for stem, spec, variants in pages:
        runs = sum(len(v.metrics) for v in variants.values())
        settled = sum(len(v.settling_times) for v in variants.values())
        lines.append(f"- [{stem}]({stem}.md): {spec.description} {len(variants)} variant(s), {runs} runs, "
                     f"{settled}/{runs} settled.")
    return "\n".join(lines) + "\n"
