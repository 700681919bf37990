"""The coping agent on the sea states with and without the speed log's sideslip correction (boat/sway.py).

    .venv/bin/python -m lab.experiments.sea_sway [--seeds S ...] [--variants NAME ...] [--radii R ...]
    .venv/bin/python -m lab.experiments.sea_sway --as-written [--seeds S ...] [--variants NAME ...]

Each run is a variant of configs/scenarios/sea_states.yaml in process (lab/harness/runner.py), its agent the
coping one (lab/experiments/sea_agent.py COPING, with the Otter's turn-rate limit) and its odometry a speed
log with `sway` none or hull, against Table II's moving target and a ground-fixed one; r* Table II's 5 m (and a
larger one for the variants with a current). `--as-written`: the variants as the file holds them. Prints one
markdown table: the figures of sea_agent.summary.
"""

from __future__ import annotations

import argparse

from agent.config import deep_merge
from lab.experiments.sea_agent import COPING, ROOT, figures, summary
from lab.harness.runner import run
from sim_bridge.scenario import Scenario, select_scenario

SEA_STATES = ROOT / "configs" / "scenarios" / "sea_states.yaml"
OTTER_RATE = 0.3   # rad/s: the Otter preset's inner-loop rate_max (boat/presets.py)
AGENT = deep_merge(COPING, {"control": {"boat_max_yaw_rate": OTTER_RATE}})
CURRENTS = ("current", "gradient", "moderate")   # the variants with a current, where r* is varied
TARGETS = {"moving": [0.5, 0.0], "fixed": [0.0, 0.0]}   # Table II's velocity, or still over ground
RADIUS = 5.0       # m: Table II's r*


def scenario(variant: str, sway: str, target: str, radius: float | None, max_speed: float | None = None
             ) -> Scenario:
    """`variant` of sea_states.yaml with the coping agent (its surge bounded by `max_speed` if given), the
    log's `sway`, the `target` and r*."""
    _, base = select_scenario(SEA_STATES, variant)
    data = base.model_dump()
    data["agent"] = deep_merge(data["agent"], AGENT)
    data["agent"] = deep_merge(data["agent"], {"control": {"radius": RADIUS if radius is None else radius}})
    if max_speed is not None:
        data["agent"] = deep_merge(data["agent"], {"control": {"max_speed": max_speed}})
    if data["world"]["sensors"]["odometry"]["kind"] == "water_log_compass":
        data["world"]["sensors"]["odometry"]["sway"] = sway
    position = data["world"]["target"]["position"]
    data["world"]["target"] = {"kind": "constant_velocity", "position": position, "velocity": TARGETS[target]}
    return Scenario.model_validate(data)


def add_table_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--variants", nargs="+", default=["calm", "current", "gradient", "wind", "waves",
                                                          "moderate"])
    parser.add_argument("--targets", nargs="+", default=list(TARGETS), choices=list(TARGETS))
    parser.add_argument("--sways", nargs="+", default=["none", "hull"], choices=["none", "hull"])
    parser.add_argument("--radii", type=float, nargs="+", default=[10.0],
                        help="r* (m) tried besides Table II's on the variants with a current")
    parser.add_argument("--radius-everywhere", action="store_true", help="try --radii on every variant")
    parser.add_argument("--max-speed", type=float,
                        help="the agent's control.max_speed (m/s); default the variant's")
    parser.add_argument("--as-written", action="store_true", help="run the variants as the file holds them")


def run_table(args: argparse.Namespace) -> int:
    limit = "the variant's" if args.max_speed is None else f"{args.max_speed:g} m/s"
    print(f"seeds {' '.join(map(str, args.seeds))}, control.max_speed {limit}")
    if args.as_written:
        print("| variant | settled | e_c after (m) | e_ij after (m) | closest (m) | max abs(u) cmd (m/s) "
              "| max abs(r) cmd (rad/s) |")
        print("|---|---|---|---|---|---|---|")
        for variant in args.variants:
            _, s = select_scenario(SEA_STATES, variant)
            f = summary([figures(s, run(s, seed), seed) for seed in args.seeds])
            print(f"| {variant} | {f['settled']}/{f['runs']} | {f['e_c']:.3f} | {f['e_ij']:.3f} | "
                  f"{f['closest']:.2f} | {f['max_surge']:.2f} | {f['max_yaw_rate']:.3f} |", flush=True)
        return 0
    print("| variant | target | r* (m) | sway | settled | e_c after (m) | e_ij after (m) | closest (m) "
          "| max abs(u) cmd (m/s) | max abs(r) cmd (rad/s) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for variant in args.variants:
        radii = [None] + (args.radii if variant in CURRENTS or args.radius_everywhere else [])
        for target in args.targets:
            for radius in radii:
                for sway in args.sways:
                    s = scenario(variant, sway, target, radius, args.max_speed)
                    runs = [figures(s, run(s, seed), seed) for seed in args.seeds]
                    f = summary(runs)
                    print(f"| {variant} | {target} | {s.agent.control.radius:g} | {sway} | {f['settled']}/"
                          f"{f['runs']} | {f['e_c']:.3f} | {f['e_ij']:.3f} | {f['closest']:.2f} | "
                          f"{f['max_surge']:.2f} | {f['max_yaw_rate']:.3f} |", flush=True)
    return 0
