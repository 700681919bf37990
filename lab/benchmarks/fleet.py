"""`usv-lab fleet-bench`: what the fleet simulation costs. A benchmark, not a test: it asserts no time.

(a) The CPU time of the whole Table II Monte Carlo, through the same engine as `usv-lab scenario`, with the
    paper's kinematic vessels and with a hull preset's dynamics overlaid on the same runs and seeds
    (`world.dynamics: {preset: otter}`, nothing else changed), the two side by side in one job list, and
    their ratio; then, in this process, a few of its runs alternately kinematic and on the hull, their CPU
    time split into World.step and the agents.
(b) The compute time of one vessel's tick (`RunTrace.tick_seconds`) for fleets of n vessels on each pair
    estimator asked for (the paper's MCKF and the agent's default by default), built from the
    Table IV base (constant-velocity target, U_v = 10, U_vf = 3) with r* = 20 m for every n, so that the rows
    differ in n only and 50 vessels fit on the circle. These runs are sequential, in this process, after the
    pool has shut down, so nothing else competes for the CPU while they are timed.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import time
from pathlib import Path

import numpy as np

from agent.config import ConfigError, deep_merge, parse_mapping, updated
from agent.core import neighbours
from agent.core.estimators import estimator_names
from boat.presets import PRESETS
from lab import arguments
from lab.experiments.scenarios import DEFAULT_DIR, load, resolve
from lab.harness.parallel import (
    add_engine_arguments,
    campaign_notes,
    engine_from,
    hand_off_lines,
    report_failures,
)
from lab.harness.run_cost import costed_run
from lab.harness.runner import run as run_scenario
from lab.report.markdown import invocation, machine, markdown_table
from sim_bridge.scenario import Scenario

RADIUS = 20.0          # r* (m) of every fleet-size run
HALF_WIDTH = 25.0      # drawn start positions lie in [-25, 25]^2 (m)
SPACING = 2.0          # drawn vessels start at least this far apart (m)
TARGET_CLEARANCE = 3.0  # and this far from the target, as the Table IV file's drawn positions (m)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--runs", type=arguments.positive_int, default=None,
                        help="Monte Carlo runs per estimator (default: the Table II file's own)")
    add_engine_arguments(parser)   # for the Monte Carlo part; the tick-time part runs here
    parser.add_argument("--preset", choices=sorted(PRESETS), default="otter",
                        help="hull preset overlaid on the Monte Carlo's runs (world.dynamics) for its second timing")
    parser.add_argument("--cpu-runs", type=arguments.positive_int, default=3,
                        help="runs of the Monte Carlo's --cpu-variant timed in process, each kinematic and on the hull")
    parser.add_argument("--cpu-variant", default="mckf", help="variant of the Monte Carlo file those runs come from")
    parser.add_argument("--out", type=arguments.folder, default=Path("docs/results"),
                        help="where fleet_benchmark.md goes")
    add_size_arguments(parser, 20.0, " of the tick-time part")
    parser.add_argument("--monte-carlo", default="table2_estimators", metavar="NAME",
                        help="scenario file of part (a), as for `usv-lab scenario`")
    parser.add_argument("--scale", default="table4_scale", metavar="NAME",
                        help="scenario file whose base and positions part (b) starts from")
    parser.add_argument("--scenarios-dir", type=Path, default=DEFAULT_DIR, help="where NAMEs are looked up")
    parser.add_argument("--estimators", nargs="+", choices=estimator_names(), default=["mckf", "raw_range"],
                        help="pair estimators of the tick-time part (default: the paper's and the agent's)")


def add_size_arguments(parser: argparse.ArgumentParser, duration: float, part: str = "") -> None:
    """--sizes, --duration and --seed of fleets built by `fleet_scenarios` (here and in `usv-lab share-bench`)."""
    parser.add_argument("--sizes", type=arguments.positive_int, nargs="+", default=[4, 12, 50],
                        help=f"fleet sizes n{part}")
    parser.add_argument("--duration", type=arguments.positive_float, default=duration,
                        help="simulated seconds of each fleet-size run")
    parser.add_argument("--seed", type=arguments.seed, default=50,
                        help="seed of the drawn start positions (fleet sizes the Table IV file lacks)")


def spread_positions(count: int, seed: int, avoid: tuple[float, float]) -> list[tuple[float, float]]:
    """`count` points uniform in [-HALF_WIDTH, HALF_WIDTH]^2, SPACING apart and TARGET_CLEARANCE from `avoid`,
    by rejection with `numpy.random.default_rng(seed)`."""
    rng = np.random.default_rng(seed)
    points: list[np.ndarray] = []
    for _ in range(1000 * count):
        if len(points) == count:
            break
        p = rng.uniform(-HALF_WIDTH, HALF_WIDTH, 2)
        if np.hypot(*(p - avoid)) >= TARGET_CLEARANCE and all(np.hypot(*(p - q)) >= SPACING for q in points):
            points.append(p)
    if len(points) < count:
        raise ConfigError(f"cannot place {count} vessels {SPACING} m apart "
                          f"in [-{HALF_WIDTH:g}, {HALF_WIDTH:g}]^2")
    return [(round(float(x), 2), round(float(y), 2)) for x, y in points]


def fleet_scenarios(base: dict, variants: dict[str, Scenario], sizes: list[int], duration: float, seed: int,
                    estimator: str | None = None) -> list[tuple[int, Scenario, str, float | None]]:
    """(n, scenario, where its start positions come from, the paper's run time for that n and r*); every
    vessel on `estimator` if given, else the file's own."""
    target = next(iter(variants.values())).world.target.position
    built = []
    for n in sizes:
        known = variants.get(f"n{n}_r{RADIUS:g}")
        if known is not None:
            vessels = [v.model_dump() for v in known.world.vessels]
            source, paper = f"Table IV file, variant {known.name}", known.paper.run_time_ms
        else:
            points = spread_positions(n, seed, target)
            vessels = [{"id": str(i + 1), "position": p} for i, p in enumerate(points)]
            source, paper = f"drawn (seed {seed})", None
        agent = {"control": {"radius": RADIUS}}
        if estimator is not None:
            agent["relative"] = {"estimator": estimator}
        merged = deep_merge(base, {"name": f"n{n}_r{RADIUS:g}", "duration": duration, "runs": 1,
                                   "world": {"vessels": vessels}, "agent": agent})
        built.append((n, parse_mapping(Scenario, merged, f"fleet-bench n = {n}"), source, paper))
    return built




def on_hull(scenario: Scenario, preset: str) -> Scenario:
    """`scenario` with every vessel on `preset`'s hull (world.dynamics) and nothing else changed: the same
    sensors, estimators and seeds, so that a difference in time is the hull's."""
    return updated(scenario, world=updated(scenario.world, dynamics={"preset": preset}))


def monte_carlo_pairs(variants: dict[str, Scenario], preset: str) -> list[tuple[str, Scenario, np.random.SeedSequence]]:
    """The Monte Carlo's runs (every variant, each run's own seed, as `usv-lab scenario` draws them), each
    kinematic and then on `preset`'s hull, side by side in one job list: a change of the machine's load in the
    middle of the campaign then falls on both alike."""
    jobs = []
    for scenario in variants.values():
        hull = on_hull(scenario, preset)
        for seed in np.random.SeedSequence(scenario.seed).spawn(scenario.runs):
            jobs += [("kinematic", scenario, seed), (preset, hull, seed)]
    return jobs


def timed_run(job: tuple[str, Scenario, np.random.SeedSequence]) -> tuple[str, float]:
    """(label, CPU seconds of the run in the worker that ran it: time.process_time, which the other processes
    on the machine do not inflate as they do the wall time)."""
    label, scenario, seed = job
    started = time.process_time()
    run_scenario(scenario, seed)
    return label, time.process_time() - started


def cpu_split(scenario: Scenario, seed: np.random.SeedSequence) -> tuple[float, float, float, float]:
    """CPU seconds of one run in this process: (whole run, World.step, the agents' ticks, the rest)."""
    _, cost = costed_run(scenario, seed)
    return cost.whole, cost.world, cost.agents, cost.rest


def cpu_comparison(kinematic: Scenario, hull: Scenario, runs: int) -> dict[str, list[float]]:
    """Medians over the scenario's first `runs` Monte Carlo seeds of `cpu_split`, kinematic and on the hull,
    taken alternately (kinematic first on even runs, the hull first on odd ones)."""
    seeds = np.random.SeedSequence(kinematic.seed).spawn(runs)   # run r of the Monte Carlo draws from child r
    figures: dict[str, list[tuple[float, ...]]] = {"kinematic": [], "hull": []}
    for r, seed in enumerate(seeds):
        order = [("kinematic", kinematic), ("hull", hull)]
        for label, scenario in order if r % 2 == 0 else order[::-1]:
            figures[label].append(cpu_split(scenario, seed))
    return {label: [statistics.median(column) for column in zip(*rows)] for label, rows in figures.items()}


# The pair filter's own work: what `NeighbourTrack.advance` asks of it per range (agent/core/neighbours.py).
FILTER_METHODS = ("predict", "update", "update_between")


class FilterClock:
    """Sums the CPU time (time.thread_time) of every pair filter's `FILTER_METHODS` calls while installed
    (`timing`): each estimator that `NeighbourTrack.start` makes gets its methods wrapped on the instance.
    `overhead` is what the wrapper itself adds to one bracketed call, measured on a method that does nothing;
    `seconds` has it taken off per call."""

    def __init__(self) -> None:
        self.raw = 0.0
        self.calls = 0
        self.overhead = 0.0

    @property
    def seconds(self) -> float:
        return self.raw - self.calls * self.overhead

    def wrap(self, method):
        clock, now = self, time.thread_time

        def timed(*args, **kwargs):
            started = now()
            try:
                return method(*args, **kwargs)
            finally:
                clock.raw += now() - started
                clock.calls += 1
        return timed

    def calibrate(self, calls: int = 200_000) -> None:
        """The wrapper's own time per call, the median of 5 batches of a method that does nothing."""
        probe = FilterClock()
        nothing = probe.wrap(lambda *args: None)
        per_call = []
        for _ in range(5):
            probe.raw, probe.calls = 0.0, 0
            for _ in range(calls):
                nothing(1.0, 2.0)
            per_call.append(probe.raw / probe.calls)
        self.overhead = statistics.median(per_call)

    @contextlib.contextmanager
    def timing(self):
        """A context in which every new track's filter is timed."""
        make = neighbours.make_relative_estimator

        def timed_filter(*args, **kwargs):
            estimator = make(*args, **kwargs)
            for name in FILTER_METHODS:
                setattr(estimator, name, self.wrap(getattr(estimator, name)))
            return estimator

        neighbours.make_relative_estimator = timed_filter
        try:
            yield self
        finally:
            neighbours.make_relative_estimator = make


def filter_ms_per_tick(scenario: Scenario) -> tuple[float, float]:
    """(the pair filters' own CPU time per vessel tick (ms), the wrapper's overhead per call (us)) over a run
    of `scenario` with every filter timed (`FilterClock`); a run of its own, apart from the tick-time run."""
    clock = FilterClock()
    clock.calibrate()
    with clock.timing():
        trace = run_scenario(scenario)
    ticks = int(np.isfinite(trace.tick_seconds).sum())
    return clock.seconds / ticks * 1e3, clock.overhead * 1e6


def run(args: argparse.Namespace) -> int:
    # tqdm (the optional 'lab' extra) is imported by the command that shows a bar, not by `usv-lab --help`.
    from tqdm import tqdm

    (mc_path,) = resolve([args.monte_carlo], args.scenarios_dir)
    (scale_path,) = resolve([args.scale], args.scenarios_dir)
    _, mc_variants = load(mc_path, args.runs)
    scale_spec, scale_variants = load(scale_path)
    fleets = [(name, *fleet) for name in args.estimators
              for fleet in fleet_scenarios(scale_spec.base, scale_variants, args.sizes, args.duration, args.seed,
                                           name)]

    jobs = monte_carlo_pairs(mc_variants, args.preset)
    cpu: dict[str, list[float]] = {"kinematic": [], args.preset: []}

    def keep(index: int, outcome: tuple[str, float] | None) -> None:
        if outcome is not None:
            cpu[outcome[0]].append(outcome[1])

    with engine_from(args) as engine, tqdm(total=len(jobs), unit="run", desc="Monte Carlo", dynamic_ncols=True) as bar:
        engine.prepare("lab.benchmarks.fleet")   # a cluster's workers import before the clock runs, as a fork has
        started = time.perf_counter()
        engine.map(timed_run, jobs, bar.update, lambda n: f"{jobs[n][0]} run {n // 2}", consume=keep)
        mc_seconds = time.perf_counter() - started
        where = engine.where()
    runs = sorted({s.runs for s in mc_variants.values()})
    kinematic, hull = (sum(cpu[label]) for label in ("kinematic", args.preset))
    mc_table = markdown_table(
        ["scenario file", "vessels", "variants", "runs per variant", "runs", "simulated s per run",
         "CPU of the runs (s)", "CPU per run (s)"],
        [[mc_path.name, label, len(mc_variants), "/".join(map(str, runs)), len(times),
          "/".join(f"{d:g}" for d in sorted({s.duration for s in mc_variants.values()})),
          f"{sum(times):.1f}", f"{sum(times) / max(len(times), 1):.2f}"] for label, times in cpu.items()])
    mc_table = "\n".join([mc_table, "", f"Ratio {args.preset} / kinematic: **{hull / kinematic:.2f}**. The "
                          f"campaign of both ({len(jobs)} runs) took {mc_seconds:.1f} s of wall time on {where}.",
                          *hand_off_lines(engine, mc_seconds, kinematic + hull, len(jobs)),
                          *campaign_notes(engine)])

    base = mc_variants.get(args.cpu_variant)
    if base is None:
        raise ConfigError(f"--cpu-variant: {mc_path.name} has no variant {args.cpu_variant!r}")
    print(f"in process: {args.cpu_runs} run(s) of {args.cpu_variant}, kinematic and {args.preset} ...", flush=True)
    split = cpu_comparison(base, on_hull(base, args.preset), args.cpu_runs)
    cpu_table = markdown_table(
        ["vessels", "whole run (s)", "World.step (s)", "agents' ticks (s)", "rest (s)", "whole run / kinematic"],
        [[label, *(f"{value:.2f}" for value in figures), f"{figures[0] / split['kinematic'][0]:.2f}"]
         for label, figures in (("kinematic", split["kinematic"]), (args.preset, split["hull"]))])

    rows = []
    per_size: dict[str, list[tuple[int, float, float]]] = {name: [] for name in args.estimators}
    overheads: list[float] = []
    for name, n, scenario, source, paper in fleets:
        print(f"fleet of {n}, {name}: {args.duration:g} s simulated ...", flush=True)
        started = time.perf_counter()
        trace = run_scenario(scenario)
        wall = time.perf_counter() - started
        ticks = trace.tick_seconds
        step_ms = np.nansum(ticks, axis=1) * 1e3   # all vessels of one sampling period, as one computer would
        print(f"fleet of {n}, {name}: again, its pair filters timed ...", flush=True)
        filter_ms, overhead_us = filter_ms_per_tick(scenario)
        mean_tick = float(np.nanmean(ticks)) * 1e3
        per_size[name].append((n, mean_tick, filter_ms))
        overheads.append(overhead_us)
        rows.append([name, n, f"{RADIUS:g}", source, int(np.isfinite(ticks).sum()),
                     f"{trace.metrics.mean_tick_ms:.3f}", f"{trace.metrics.p99_tick_ms:.3f}",
                     f"{step_ms.mean():.2f}", f"{filter_ms:.3f}", f"{mean_tick - filter_ms:.3f}",
                     "-" if paper is None else f"{paper:g}", f"{wall:.1f}"])
    tick_table = markdown_table(
        ["estimator", "n", "r* (m)", "start positions", "vessel ticks", "mean tick (ms)", "p99 tick (ms)",
         "mean fleet step (ms)", "of a tick, the pair filters' own (ms)", "of a tick, the rest (ms)",
         "paper Avg. Run Time (ms)", "run wall time (s)"], rows)
    tick_table = "\n".join([tick_table, "", *per_neighbour_lines(per_size, overheads)])

    document = render(invocation(args), mc_table, cpu_table, tick_table, args, scale_path, base)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "fleet_benchmark.md"
    path.write_text(document, encoding="utf-8")
    print(f"\n{mc_table}\n\n{cpu_table}\n\n{tick_table}\n\nwrote {path}")
    return report_failures(engine)


def per_neighbour_lines(per_size: dict[str, list[tuple[int, float, float]]], overheads: list[float]) -> list[str]:
    """Per estimator, what an extra neighbour adds to a vessel's tick between the smallest and the largest
    fleet: in all, and beyond its pair filter's own predict and update."""
    lines = []
    for name, sizes in per_size.items():
        if len(sizes) < 2:
            continue
        (n0, tick0, filter0), (n1, tick1, filter1) = min(sizes), max(sizes)
        extra = n1 - n0
        lines.append(f"- {name}: an extra neighbour adds {(tick1 - tick0) / extra * 1e3:.1f} us to a vessel's "
                     f"tick (n = {n0} to {n1}), of which its pair filter's own predict and update "
                     f"{(filter1 - filter0) / extra * 1e3:.1f} us and the rest "
                     f"{((tick1 - filter1) - (tick0 - filter0)) / extra * 1e3:.1f} us.")
    if overheads:
        lines.append(f"- The pair filters' own time comes from a second run of each fleet with every filter's "
                     f"{', '.join(FILTER_METHODS)} bracketed by time.thread_time; the bracket's own cost on a "
                     f"method that does nothing ({min(overheads):.2f}-{max(overheads):.2f} us a call, measured "
                     "before each run) is taken off every call. The rest is the tick's mean less that.")
    return lines


def render(command: str, mc_table: str, cpu_table: str, tick_table: str, args: argparse.Namespace,
           scale_path: Path, base: Scenario) -> str:
    return "\n".join([
        "# Fleet benchmark: Monte Carlo CPU time, kinematic and on a hull, and tick cost by fleet size",
        "",
        "Generated by the command below; do not edit by hand. Times depend on the machine and its load.",
        "",
        "```",
        command,
        "```",
        "",
        "## Machine",
        "",
        *(f"- {line}" for line in machine()),
        "",
        "## Table II Monte Carlo",
        "",
        "Every run of every estimator variant (the seeds of `usv-lab scenario`) through its engine (this "
        "machine's process pool unless --cluster), twice: with the paper's kinematic vessels (1), (2), and with "
        f"`world.dynamics: {{preset: {args.preset}}}` overlaid (docs/sea.md: Fossen's 3-DOF hull behind its "
        "thrusters and inner loop, in calm water), nothing else changed: the same estimators, sensors and "
        "seeds, so the ratio is what the hull costs. The two versions of each run are side by side in one job "
        "list, and each run's CPU time is taken in its worker (time.process_time): on a machine shared with "
        "other jobs the wall time of one campaign and then the other measured mostly the change of load.",
        "",
        mc_table,
        "",
        f"Where the time goes: {args.cpu_runs} run(s) of the variant `{base.name}` (its Monte Carlo seeds 0 to "
        f"{args.cpu_runs - 1}), each kinematic and on the hull, alternately, one after the other in the main "
        "process after the pool has shut down; CPU seconds (time.process_time) of the whole run, of "
        "World.step (the motion and the next tick's readings), of the agents' ticks (the runner's "
        "RunTrace.tick_seconds) and the rest (the runner's bookkeeping and metrics); medians over the runs.",
        "",
        cpu_table,
        "",
        "## Tick compute time by fleet size",
        "",
        f"One run per pair estimator and fleet size, {args.duration:g} s simulated, built from the base of "
        f"`{scale_path}` "
        f"(constant-velocity target, U_v = 10 m/s, U_vf = 3 m/s) with r* = {RADIUS:g} m for every n. Start "
        f"positions of the sizes the file has are its own; the others are drawn with "
        f"numpy.random.default_rng({args.seed}) uniformly in [-{HALF_WIDTH:g}, {HALF_WIDTH:g}]^2 m, at "
        f"least {SPACING:g} m apart and {TARGET_CLEARANCE:g} m from the target's start. The runs are "
        "sequential, in the main process, after the Monte Carlo pool has shut down.",
        "",
        "A vessel tick is one core `step` (its n - 1 inter-vessel estimators, the target tracker, "
        "the controller) timed by the runner as the CPU time of its thread (time.thread_time, so that other processes on the machine do not inflate it); mean and p99 are over all vessel ticks "
        "of the run. A fleet step is the sum over the vessels of one sampling period (what one computer "
        "simulating the whole fleet pays per 0.1 s). The paper's Avg. Run Time (Table IV, same n and r*) is "
        "per iteration on its own machine and language; compare how it grows with n, not its level.",
        "",
        tick_table,
        "",
    ])
