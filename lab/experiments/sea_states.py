"""`usv-lab sea-states`: the sea states' page, docs/results/sea_states.md (issue 30, item 6).

    usv-lab sea-states [--variants a,b] [--runs N] [--seed S] [--duration S] [--no-cold] [--no-ab] [--out P]

Every variant of configs/scenarios/sea_states.yaml (the kinematic ideal first), run r of each on child r of
SeedSequence(seed); the cold start (cold_start.yaml's `initial` and duration) in the ideal and in `moderate`;
and the A/B of the agent's measures for the boat (AB_PLAN: with all of them, and without each one) on the
same seeds. One process pool runs it all. Per run figures: lab/experiments/sea_figures.py; the page gives
the tables, the verdict against the issue's acceptance, figures of run 0 and what it cost.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from agent.config import ConfigError, deep_merge, updated
from agent.core.params import AgentParams
from lab import arguments
from lab.experiments.sea_agent import COPING, ODOMETRY
from lab.experiments.sea_figures import (
    ACCEPTANCE,
    COLD_ACCEPTANCE,
    COLD_STATES,
    EVERY_STATE,
    StateSummary,
    command_limits,
    run_figures,
    spacing_errors,
    summarise,
    verdict,
)
from lab.harness.parallel import (
    add_engine_arguments,
    campaign_notes,
    engine_from,
    hand_off_lines,
    report_failures,
)
from lab.harness.run_cost import RunCost, costed_run
from lab.report.fleet_plots import radius_spacing_figure, trajectory_figure
from lab.report.markdown import cpu_model, invocation, markdown_table
from sim_bridge.environment import SEA_STATES
from sim_bridge.scenario import SCENARIOS_DIR, Scenario, load_scenarios, select_scenario

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_SCENARIO = SCENARIOS_DIR / "sea_states.yaml"
COLD_START = SCENARIOS_DIR / "cold_start.yaml"
DEFAULT_PAGE = ROOT / "docs" / "results" / "sea_states.md"
RUNS = 20                      # the seeds per state


def _control(*fields: str) -> dict:
    return {"control": {field: COPING["control"][field] for field in fields}}


# The agent's measures for the boat (docs/sea.md, What the agent does): name -> (what, the agent parameters
# that switch it on for a scenario). A measure the file already switches on keeps the file's values.
MEASURES = {
    "gain cut": ("formation gains cut (kappa_io, kappa_ij and their cap)",
                 lambda s: _control("gain_target", "gain_neighbour", "neighbour_gain_cap")),
    "heading loop": ("lag-compensated heading loop", lambda s: _control("yaw_lag", "heading_bandwidth")),
    "odometry noise": ("the pair filters' odometry noise from the sensors' specification",
                       lambda s: ODOMETRY),
    "limits": ("no command beyond the hull preset's turn rate and speeds ahead and astern",
               lambda s: {"control": {"boat_max_yaw_rate": command_limits(s).max_yaw_rate,
                                      "max_speed": command_limits(s).max_surge,
                                      "boat_max_astern": command_limits(s).max_reverse}}),
    "coasting": ("the separation guard keeps the coasting distance", lambda s: _control("surge_lag")),
}
# (state, measure) pairs of the A/B: calm has the hull's lags and limits alone; moderate has everything (the
# compass biases of the realistic sensors, the closest approaches the coasting distance is for).
AB_PLAN = [("calm", "gain cut"), ("calm", "heading loop"), ("calm", "limits"),
           ("moderate", "gain cut"), ("moderate", "heading loop"), ("moderate", "odometry noise"),
           ("moderate", "limits"), ("moderate", "coasting")]
ALL = "with all"
# Measures the file switches on per state, with their A/B as named variants (`<state>_no_<measure>`, or
# `wind_target_leeway`): named in the state's description only, never switched on by `with_all`.
FILE_MEASURES = {
    "leeway model": ("control", "leeway_time_constant"),
    "set model": ("control", "set_time_constant"),
    "leeway from the target": ("target", "leeway_variance"),
    "antenna offset": ("relative", "antenna"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", type=Path, default=DEFAULT_SCENARIO, help="the sea states' file")
    parser.add_argument("--variants", default=None, help="variants, comma-separated (default: all)")
    parser.add_argument("--runs", type=arguments.positive_int, default=RUNS, help="seeds per row")
    parser.add_argument("--seed", type=arguments.seed, default=None, help="root seed (default: the file's)")
    parser.add_argument("--duration", type=arguments.positive_float, default=None,
                        help="simulated seconds of every run (default: the files': sea states, cold start)")
    parser.add_argument("--no-cold", action="store_true", help="leave out the cold start")
    parser.add_argument("--no-ab", action="store_true", help="leave out the A/B of the agent's measures")
    add_engine_arguments(parser)
    parser.add_argument("--out", type=arguments.page, default=DEFAULT_PAGE, help="the page; figures go to its stem/")


# ----------------------------------------------------------------------------------------------------------
# What runs
# ----------------------------------------------------------------------------------------------------------

def states(path: Path, names: str | None, runs: int, seed: int | None, duration: float | None
           ) -> dict[str, Scenario]:
    """The file's variants (those named, if any), the kinematic ones first, with the command's overrides."""
    _, scenarios = load_scenarios(path)
    if names is not None:
        wanted = [n.strip() for n in names.split(",") if n.strip()]
        unknown = [n for n in wanted if n not in scenarios]
        if unknown or not wanted:
            raise ConfigError(f"--variants: {', '.join(unknown) or 'none given'}: {path} has "
                              f"{', '.join(scenarios)}")
        scenarios = {n: scenarios[n] for n in wanted}
    changes = {"runs": runs, **({"seed": seed} if seed is not None else {}),
               **({"duration": duration} if duration is not None else {})}
    ordered = sorted(scenarios, key=lambda n: scenarios[n].world.dynamics is not None)
    return {n: updated(scenarios[n], **changes) for n in ordered}


def cold(scenario: Scenario, duration: float | None) -> Scenario:
    """`scenario` started as cold_start.yaml starts its fleet (its `initial`: nothing known), for its
    duration."""
    _, start = select_scenario(COLD_START)
    return updated(scenario, initial=start.initial, duration=duration or start.duration)


def _fields(change: dict) -> list[tuple[str, str]]:
    return [(section, field) for section, values in change.items() for field in values]


def file_has(scenario: Scenario, measure: str) -> bool:
    """Whether the scenario's agent already has `measure` on: one of its parameters off its default."""
    default = AgentParams()
    return any(getattr(getattr(scenario.agent, s), f) != getattr(getattr(default, s), f)
               for s, f in _fields(MEASURES[measure][1](scenario)))


def _agent(scenario: Scenario, change: dict) -> Scenario:
    agent = AgentParams.model_validate(deep_merge(scenario.agent.model_dump(), change))
    return updated(scenario, agent=agent)


def with_all(scenario: Scenario) -> Scenario:
    """The scenario with every measure on: the file's own values where it has them, MEASURES' otherwise."""
    for measure, (_, change) in MEASURES.items():
        if not file_has(scenario, measure):
            scenario = _agent(scenario, change(scenario))
    return scenario


def without(scenario: Scenario, measure: str) -> Scenario:
    """The scenario with `measure`'s parameters back at the agent's defaults (off)."""
    default = AgentParams()
    change: dict = {}
    for s, f in _fields(MEASURES[measure][1](scenario)):
        change.setdefault(s, {})[f] = getattr(getattr(default, s), f)
    return _agent(scenario, change)


def rows(args: argparse.Namespace) -> dict[tuple[str, str, str], Scenario]:
    """(table, state, agent) -> scenario: 'states' and 'cold' rows (agent ''), 'ab' rows (agent ALL or a
    measure). An A/B row 'with all' that is the state's own scenario is not run twice (see `_source`)."""
    found = states(args.scenario, args.variants, args.runs, args.seed, args.duration)
    table = {("states", name, ""): s for name, s in found.items()}
    if not args.no_cold:
        for name, s in found.items():
            if s.world.dynamics is None or name in COLD_STATES:
                table["cold", name, ""] = cold(s, args.duration)
    if not args.no_ab:
        for state, measure in AB_PLAN:
            if state in found:
                full = with_all(found[state])
                table.setdefault(("ab", state, ALL), full)
                table["ab", state, measure] = without(full, measure)
    return table


def _source(key: tuple[str, str, str], table: dict) -> tuple[str, str, str]:
    """The row whose runs `key` takes: an A/B 'with all' equal to its state's scenario takes the state's."""
    if key[0] == "ab" and key[2] == ALL and table[key] == table.get(("states", key[1], "")):
        return ("states", key[1], "")
    return key


def _job(job: tuple[Scenario, np.random.SeedSequence, bool]):
    """One run in a worker: its figures, its trace if kept, and what it cost (the run by part, then the
    figures' CPU seconds)."""
    scenario, seed, keep = job
    trace, cost = costed_run(scenario, seed)
    started = time.process_time()
    figures = run_figures(trace)
    return figures, (trace if keep else None), cost, time.process_time() - started


def run_all(table: dict, engine) -> tuple[dict, dict, dict, float]:
    """Every row's runs ({key: [SeaRun] in run order}, a run that raised left out), run 0's traces of the
    'states' and 'cold' rows ({key: trace}), what each row's runs cost ({key: [(RunCost, the figures' CPU
    seconds)]}, rows that take another's runs left out) and the campaign's wall time (s)."""
    keys, jobs = [], []
    for key, scenario in table.items():
        if _source(key, table) != key:
            continue
        for index, seed in enumerate(np.random.SeedSequence(scenario.seed).spawn(scenario.runs)):
            keys.append((key, index))
            jobs.append((scenario, seed, index == 0 and key[0] != "ab"))
    started, done = time.monotonic(), [0]

    def progress(count: int) -> None:
        done[0] += count
        print(f"usv-lab sea-states: {done[0]}/{len(jobs)} runs, {time.monotonic() - started:.0f} s",
              file=sys.stderr, flush=True)

    def describe(n: int) -> str:
        (table_name, state, agent), index = keys[n]
        return f"{table_name} {state} {agent} run {index}".replace("  ", " ")

    results: dict = {key: [] for key in table}
    traces: dict = {}
    costs: dict = {}

    def consume(n: int, outcome) -> None:
        key, _ = keys[n]
        if outcome is not None:
            results[key].append(outcome[0])
            if outcome[1] is not None:
                traces[key] = outcome[1]
            costs.setdefault(key, []).append((outcome[2], outcome[3]))

    engine.map(_job, jobs, progress, describe, consume=consume)
    wall = time.monotonic() - started
    for key in table:
        results[key] = results[_source(key, table)]
    return results, traces, costs, wall


def cost_lines(table: dict, costs: dict[tuple, list[tuple[RunCost, float]]], engine, wall: float) -> list[str]:
    """What the runs cost, per state and for the A/B together: CPU seconds per run (time.process_time in the
    worker) of the world, the agents' ticks, the runner's own work and the figures; then the workers' time
    beyond the runs (the process hand-off)."""
    if not costs:
        return []
    groups: dict[str, list[tuple[RunCost, float]]] = {}
    simulated: dict[str, float] = {}
    for key, spent in costs.items():
        label = "A/B, every state and measure" if key[0] == "ab" else f"{key[0]}: {key[1]}"
        groups.setdefault(label, []).extend(spent)
        simulated[label] = table[key].duration
    rows = []
    for label, spent in groups.items():
        runs = len(spent)
        whole = sum(c.whole for c, _ in spent) / runs
        metrics = sum(m for _, m in spent) / runs
        rows.append([label, runs, f"{simulated[label]:g}", f"{whole + metrics:.2f}",
                     f"{sum(c.world for c, _ in spent) / runs:.2f}", f"{sum(c.agents for c, _ in spent) / runs:.2f}",
                     f"{sum(c.rest for c, _ in spent) / runs:.2f}", f"{metrics:.2f}"])
    everything = [pair for spent in groups.values() for pair in spent]
    cpu = sum(c.whole + m for c, m in everything)
    return ["CPU seconds per run (time.process_time, in the worker that ran it; a mean over the row's runs): "
            "the world (World.step: the hull, the sea and the next tick's readings), the agents' ticks (the "
            "core `step` of every vessel), the runner's own work (shares handed round, the trace's records) "
            "and the figures of the run (lab/experiments/sea_figures.py).", "",
            markdown_table(["row", "runs", "simulated s per run", "CPU per run (s)", "world (s)",
                            "agents' ticks (s)", "runner (s)", "figures (s)"], rows), "",
            f"- In all, {len(everything)} runs took {cpu:.1f} s of CPU ({cpu / len(everything):.2f} s a run).",
            *hand_off_lines(engine, wall, cpu, len(everything))]


# ----------------------------------------------------------------------------------------------------------
# The command
# ----------------------------------------------------------------------------------------------------------

def run(args: argparse.Namespace) -> int:
    table = rows(args)
    started = time.monotonic()
    with engine_from(args) as engine:
        results, traces, costs, wall = run_all(table, engine)
        where = engine.where()
        spent = cost_lines(table, costs, engine, wall)
    elapsed = time.monotonic() - started
    summaries = {key: summarise(runs, command_limits(table[key])) for key, runs in results.items() if runs}
    figures_dir = args.out.parent / args.out.stem
    figures = _figures(table, traces, figures_dir)
    runs = sum(len(results[key]) for key in table if key == _source(key, table))
    page = render(args, table, summaries, figures, elapsed, runs, where, spent + campaign_notes(engine))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(page, encoding="utf-8")
    print(page)
    print(f"usv-lab sea-states: wrote {args.out} ({runs} runs, {elapsed:.0f} s)", file=sys.stderr)
    return report_failures(engine)


def _figures(table: dict, traces: dict, folder: Path) -> list[tuple[str, str]]:
    """(caption, file relative to the page) of the figures of run 0."""
    made = []
    for name, what in (("states", "each state"), ("cold", "the cold start")):
        panels = {key[1]: (traces[key], table[key]) for key in table if key[0] == name and key in traces}
        if not panels:
            continue
        paths = trajectory_figure(panels, f"{what}: paths over ground of run 0", folder / f"{name}_paths.png")
        curves = {}
        for state, (trace, scenario) in panels.items():
            radii = np.hypot(*(trace.positions - trace.target[:, None, :]).transpose(2, 0, 1))
            curves[state] = (trace.time, radii, spacing_errors(trace.positions, trace.target),
                             scenario.agent.control.radius)
        spacing = radius_spacing_figure(curves, f"{what}: run 0", folder / f"{name}_distance_spacing.png")
        made += [(f"Paths over ground, run 0 of {what} (start ○, end △; the target's path dashed; the "
                  "circle r* around its final position)", f"{folder.name}/{paths.name}"),
                 (f"Distance of each vessel to the target (the band is r* ± 10 %) and the spacing error, "
                  f"run 0 of {what}", f"{folder.name}/{spacing.name}")]
    return made


# ----------------------------------------------------------------------------------------------------------
# The page
# ----------------------------------------------------------------------------------------------------------

def _f(value: float, digits: int = 3) -> str:
    return "-" if math.isnan(value) else f"{value:.{digits}f}"


def _state_row(label: str, s: StateSummary) -> list[str]:
    return [label, f"{s.settled}/{s.runs}", _f(s.settling_median, 1),
            f"{_f(s.e_ij)} / {_f(s.e_ij_after)}", f"{_f(s.e_io)} / {_f(s.e_io_after)}",
            f"{_f(s.e_c)} / {_f(s.e_c_after)}", _f(math.degrees(s.spacing_after), 1), _f(s.closest, 2),
            f"{_f(s.thrust_limit_mean, 2)} / {_f(s.thrust_limit_max, 2)}",
            f"{_f(s.max_surge, 2)}, {_f(s.min_surge, 2)} ({_f(s.limits.max_surge, 1)}, "
            f"{_f(-s.limits.max_reverse, 1)})",
            f"{_f(math.degrees(s.max_yaw_rate), 1)} ({_f(math.degrees(s.limits.max_yaw_rate), 1)})",
            "yes" if s.within_limits else "**no**"]


HEADER = ["state", "settled", "settling, median (s)", "e_ij whole / after (m)", "e_io whole / after (m)",
          "e_c whole / after (m)", "spacing after (deg)", "closest (m)", "thrust limit mean / max (s)",
          "u cmd max, min (limits) (m/s)", "abs(r) cmd max (limit) (deg/s)", "within limits"]


def _target(s: Scenario) -> str:
    spec = s.world.target
    velocity = getattr(spec, "velocity", None)
    if spec.kind != "constant_velocity" or velocity is None:
        return f"target {spec.kind}"
    speed = math.hypot(*velocity)
    return "target still over ground" if speed == 0.0 else f"target at {speed:g} m/s over ground"


def _describe(s: Scenario) -> str:
    world = s.world
    circle = f"r* {s.agent.control.radius:g} m, {_target(s)}"
    if world.dynamics is None:
        return f"the paper's kinematics (1)-(2) and odometry (5); {circle}"
    env = world.environment
    sea = "calm water" if env is None else next((n for n, c in SEA_STATES.items() if c == env), "own water")
    sensors = world.sensors
    words = "the paper's sensors" if sensors.is_paper else f"odometry {sensors.odometry.kind}" + (
        ", UWB antennas and faults" if sensors.uwb is not None else "") + (
        ", camera" if sensors.camera is not None else "")
    default = AgentParams()
    measures = [m for m in MEASURES if file_has(s, m)] + [
        m for m, (section, field) in FILE_MEASURES.items()
        if getattr(getattr(s.agent, section), field) != getattr(getattr(default, section), field)] or ["none"]
    return (f"{world.dynamics.preset} hull, {sea}, {words}; {circle}; estimator "
            f"{s.agent.relative.estimator.name}; the agent's measures on: {', '.join(measures)}")


def _acceptance(summaries: dict, table: dict, table_name: str, checks_of: dict) -> list[str]:
    """A line per row of `table_name`: each check of the issue's acceptance, computed; whether all hold."""
    lines = []
    for key, s in summaries.items():
        if key[0] != table_name:
            continue
        if table[key].world.dynamics is None:
            lines.append(f"- {key[1]}: the ideal, no target")
            continue
        # A variant of an issue's state (`wind_dvl`, `calm_moving_target`) is judged as that state.
        state = key[1] if key[1] in checks_of else key[1].split("_")[0]
        checks = checks_of.get(state, EVERY_STATE if table_name == "states" else [])
        if not checks:
            continue
        results = verdict(s, checks)
        met = all(ok for _, ok in results)
        judged = f" (judged as {state})" if state != key[1] and state in checks_of else ""
        lines.append(f"- {key[1]}{judged}: **{'met' if met else 'not met'}**: "
                     + "; ".join(f"{text} {'✓' if ok else '✗'}" for text, ok in results))
    return lines


def render(args: argparse.Namespace, table: dict, summaries: dict, figures: list, elapsed: float, runs: int,
           where: str, notes: list[str]) -> str:
    states_ = [(k, s) for k, s in summaries.items() if k[0] == "states"]
    first = table[next(iter(table))]
    lines = [
        "# Sea states: the Table II fleet on the Otter's hull, against the kinematic ideal",
        "",
        f"Generated from `{args.scenario}` by the command below (issue 30, item 6); do not edit by hand.",
        "",
        "```", invocation(args), "```", "",
        "## Settings", "",
        f"- seeds: {args.runs} per row, run r on child r of numpy's SeedSequence({first.seed}); every row "
        "(states, cold start, A/B) meets the same seeds",
        f"- duration {first.duration:g} s (cold start {_cold_duration(table)}), dt {first.world.dt:g} s, "
        f"{len(first.world.vessels)} vessels",
        "",
        markdown_table(["state", "what it holds"], [[k[1], _describe(table[k])] for k, _ in states_]),
        "",
        "## The states", "",
        "Settled: runs in which every vessel's distance to the target stays within r* ± 10 % from some time "
        "to the end (mission_log/metrics.py); the settling time is the median over the settled runs. e_ij, "
        "e_io, e_c (Sec. VI: worst inter-vessel estimate, worst target estimate, the formation centre's "
        "distance to the target over ground): the mean over the runs of each run's time average over the "
        "whole run / the mean over the settled runs of each one's average from its settling time on. "
        "Spacing: at each tick the mean over neighbouring pairs of |angle between them around the target − "
        "2π/n|, averaged after settling. Closest: the least distance between any two vessels over every run."
        " Thrust limit: seconds the worst vessel's thrust demand spent beyond its thrusters in a run, mean /"
        " max over the runs. Commands: the largest and smallest commanded surge and the largest |yaw rate| "
        "over every run, against the hull preset's inner-loop bounds (the kinematic world's for the ideal).",
        "",
        markdown_table(HEADER, [_state_row(k[1], s) for k, s in states_]),
        "",
        "### Against the acceptance", "",
        "Issue 30: in calm, current, gradient, wind and waves every run settles and e_c after settling ≤ 0.3"
        " m; in moderate ≥ 19/20 settle, e_c after settling ≤ 0.5 m, e_ij after settling ≤ 0.3 m; in every "
        "state the closest approach of every run ≥ 3 m and no command beyond the preset's limits (e_c and "
        "e_ij: the means over the settled runs; the settled fraction scaled to the runs made).",
        "",
        *_acceptance(summaries, table, "states", ACCEPTANCE),
        "",
    ]
    colds = [(k, s) for k, s in summaries.items() if k[0] == "cold"]
    if colds:
        lines += ["## The cold start", "",
                  "Each state's scenario with cold_start.yaml's start: no vessel knows anything (no p^_ij,0,"
                  " no "
                  "x^_io,0); its duration. Same columns as above.", "",
                  markdown_table(HEADER, [_state_row(k[1], s) for k, s in colds]), "",
                  "Against the acceptance (the cold start in moderate: ≥ 19/20 settle):", "",
                  *_acceptance(summaries, table, "cold", COLD_ACCEPTANCE), ""]
    abs_ = [(k, s) for k, s in summaries.items() if k[0] == "ab"]
    if abs_:
        lines += ["## The agent's measures, with all and without each one", "",
                  "Each state's scenario with every measure on (the file's values where it has the measure "
                  "on, else the ones below), and without one (its parameters at the agent's defaults), on "
                  "the same "
                  "seeds. A 'with all' equal to the state's scenario is its row above.", "",
                  markdown_table(["measure", "what it is", "parameters when the file has it off"],
                                 [[m, words, _params(change(table[abs_[0][0]]))]
                                  for m, (words, change) in MEASURES.items()]),
                  "",
                  markdown_table(["state", "agent", "settled", "e_c after (m)", "e_ij after (m)",
                                  "spacing after (deg)", "closest (m)", "u cmd max, min (m/s)",
                                  "abs(r) cmd max (deg/s)", "within limits"],
                                 [[k[1], k[2] if k[2] == ALL else f"without {k[2]}", f"{s.settled}/{s.runs}",
                                   _f(s.e_c_after), _f(s.e_ij_after), _f(math.degrees(s.spacing_after), 1),
                                   _f(s.closest, 2), f"{_f(s.max_surge, 2)}, {_f(s.min_surge, 2)}",
                                   _f(math.degrees(s.max_yaw_rate), 1),
                                   "yes" if s.within_limits else "**no**"] for k, s in abs_]),
                  ""]
    lines += ["## Figures", ""]
    for caption, path in figures:
        lines += [f"{caption}:", "", f"![{Path(path).stem}]({path})", ""]
    lines += ["## What it cost", "",
              f"{runs} runs in {elapsed:.0f} s of wall time on {where} (os.cpu_count() = {os.cpu_count()}; "
              f"CPU: {cpu_model()}), in process (lab/harness/runner.py).", "", *notes, ""]
    return "\n".join(lines)


def _cold_duration(table: dict) -> str:
    durations = sorted({f"{s.duration:g} s" for k, s in table.items() if k[0] == "cold"})
    return ", ".join(durations) or "not run"


def _params(change: dict) -> str:
    return ", ".join(f"{s}.{f} = {v:.3g}" if isinstance(v, float) else f"{s}.{f} = {v}"
                     for s, values in change.items() for f, v in values.items())
