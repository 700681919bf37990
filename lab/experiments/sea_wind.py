"""The coping agent in the `wind` sea state with and without the leeway model (agent/core/control/leeway.py).

    .venv/bin/python -m lab.experiments.sea_wind [--seeds S ...] [--odometry KIND ...] [--radii R ...]
        [--leeway T ...] [--wind-speed U] [--gust-gain K]

Each run is configs/scenarios/sea_states.yaml's `wind` variant in process (lab/harness/runner.py), its
odometry replaced by `--odometry` (`as-written`: the file's speed log; `paper`: ground truth; a sensors
preset such as `realistic_dvl`), r* and the agent's control.leeway_time_constant (0: no model) varied, the
wind's mean and gust gain optionally changed. Prints one markdown table of sea_agent.summary's figures
and the mean once-an-orbit amplitude of r - r* over the last 30 s (the leeway's signature: a fit of
a + b cos(theta - phi), theta the bearing of the vessel from the target).
"""

from __future__ import annotations

import argparse

import numpy as np

from agent.config import deep_merge
from lab.experiments.sea_agent import ROOT, figures, summary
from lab.harness.runner import run
from sim_bridge.scenario import Scenario, select_scenario

SEA_STATES = ROOT / "configs" / "scenarios" / "sea_states.yaml"
FIT = 30.0   # s: the once-an-orbit fit's window, at the run's end


def scenario(odometry: str, radius: float, leeway: float, wind_speed: float | None = None,
             gust_gain: float | None = None) -> Scenario:
    _, base = select_scenario(SEA_STATES, "wind")
    data = base.model_dump()
    if odometry == "paper":
        data["world"]["sensors"]["odometry"] = {"kind": "paper"}
    elif odometry != "as-written":
        data["world"]["sensors"] = odometry
    data["agent"] = deep_merge(data["agent"], {"control": {"radius": radius, "leeway_time_constant": leeway}})
    if wind_speed is not None or gust_gain is not None:
        wind = data["world"]["environment"]["wind"]
        wind["speed"] = wind["speed"] if wind_speed is None else wind_speed
        wind["gain"] = wind["gain"] if gust_gain is None else gust_gain
    return Scenario.model_validate(data)


def orbit_amplitude(trace, radius: float) -> float:
    """Mean over the vessels of b in r - r* = a + b cos(theta - phi) + rest, fitted over the last FIT s."""
    late = trace.time >= trace.time[-1] - FIT
    offsets = trace.positions[late] - trace.target[late, None, :]
    theta = np.arctan2(offsets[..., 1], offsets[..., 0])
    amplitudes = []
    for i in range(theta.shape[1]):
        basis = np.c_[np.ones(late.sum()), np.cos(theta[:, i]), np.sin(theta[:, i])]
        coefficients, *_ = np.linalg.lstsq(basis, trace.radii[late, i] - radius, rcond=None)
        amplitudes.append(np.hypot(coefficients[1], coefficients[2]))
    return float(np.mean(amplitudes))


def add_table_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--odometry", nargs="+", default=["as-written", "paper"],
                        help="as-written, paper, or a sensors preset (realistic_dvl)")
    parser.add_argument("--radii", type=float, nargs="+", default=[5.0, 10.0])
    parser.add_argument("--leeway", type=float, nargs="+", default=[0.0, 10.0],
                        help="control.leeway_time_constant (s); 0: no leeway model")
    parser.add_argument("--wind-speed", type=float, help="the wind's mean (m/s); default the state's 8")
    parser.add_argument("--gust-gain", type=float, help="the gust's gain (m/s); default the state's 2")


def run_table(args: argparse.Namespace) -> int:
    print(f"seeds {' '.join(map(str, args.seeds))}, wind {args.wind_speed or 'as written'}, "
          f"gust gain {'as written' if args.gust_gain is None else args.gust_gain}")
    print("| odometry | r* (m) | leeway T (s) | settled | e_c after (m) | mean abs(r - r*) last 10 s (m) "
          "| once-an-orbit amplitude (m) | closest (m) |")
    print("|---|---|---|---|---|---|---|---|")
    for odometry in args.odometry:
        for radius in args.radii:
            for leeway in args.leeway:
                s = scenario(odometry, radius, leeway, args.wind_speed, args.gust_gain)
                traces = [run(s, seed) for seed in args.seeds]
                f = summary([figures(s, trace, seed) for trace, seed in zip(traces, args.seeds)])
                b = np.mean([orbit_amplitude(trace, radius) for trace in traces])
                print(f"| {odometry} | {radius:g} | {leeway:g} | {f['settled']}/{f['runs']} | "
                      f"{f['e_c']:.3f} | {f['radius_error']:.3f} | {b:.2f} | {f['closest']:.2f} |",
                      flush=True)
    return 0
