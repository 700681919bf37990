"""`usv-lab sea-agent-ab`: the agent's measures for the boat and the water as they are, with and without.

    usv-lab sea-agent-ab [--seeds S ...] [--conditions NAME ...] [--out PAGE]

The issue's figures of today's agent: `usv-lab sea-agent-ab --conditions yaw_lag surge_lag lags_0.3 bias_0.5
bias bias_2 current_0.3 limits --agents today --seeds 0 1 2 3 4 --out docs/results/sea_agent_issue.md`.

Each condition wraps today's kinematic world with plant effects (lab/harness/plant_effects.py); each agent is the
Table II raw_range agent with some of the measures of docs/sea.md (What the agent does) switched on. Every (condition, agent)
runs the same seeds in process; the page gives the runs settled, e_c and e_ij after settling (means over the
settled runs), the mean |r - r*| over the last 10 s, the closest approach over every run, and the largest
commands.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from lab import arguments
from lab.arguments import seed as seed_type
from lab.experiments.sea_agent import COPING, ODOMETRY, effect_scenario, measure, summary
from lab.harness.plant_effects import PlantEffects
from lab.report.markdown import invocation, markdown_table

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_PAGE = ROOT / "docs" / "results" / "sea_agent_ab.md"
OTTER_YAW_RATE = math.radians(10.0)  # the Otter's heading autopilot r_max (sea-physics.md, section 1)
OTTER_SPEED = 3.0  # m/s, under the Otter's 3.09 m/s
LAGS = {"surge_lag": 1.0, "yaw_lag": 1.0}
OTTER = {**LAGS, "max_yaw_rate": OTTER_YAW_RATE, "max_surge": OTTER_SPEED, "max_acceleration": 1.0}
BIAS = math.radians(1.0)

# name -> (what it holds, the effects, the target held still). A current holds it still anyway (ground-fixed).
CONDITIONS = {
    "calm": ("the kinematic world (the paper's)", PlantEffects(), False),
    "yaw_lag": ("yaw-rate lag 1 s", PlantEffects(yaw_lag=1.0), False),
    "lags": ("lags 1 s in surge and yaw", PlantEffects(**LAGS), False),
    "otter": (
        "lags 1 s, r <= 10 deg/s, u <= 3 m/s, abs(du/dt) <= 1 m/s^2; ground-fixed target",
        PlantEffects(**OTTER),
        True,
    ),
    "otter_moving": ("otter with Table II's target moving at 0.5 m/s", PlantEffects(**OTTER), False),
    "bias": ("compass bias N(0, 1 deg) per vessel", PlantEffects(compass_bias_std=BIAS), False),
    "current": (
        "current 0.5 m/s, water-referenced odometry, ground-fixed target",
        PlantEffects(current=(0.5, 0.0)),
        True,
    ),
    "moderate": (
        "otter + compass bias N(0, 1 deg) + current 0.5 m/s; ground-fixed target",
        PlantEffects(**OTTER, compass_bias_std=BIAS, current=(0.5, 0.0)),
        True,
    ),
    "moderate_0.15": (
        "moderate with a current of 0.15 m/s, which a 5 m circle at pi/30 rad/s allows with "
        "r <= 10 deg/s (docs/sea.md (What the agent does))",
        PlantEffects(**OTTER, compass_bias_std=BIAS, current=(0.15, 0.0)),
        True,
    ),
    # The issue's single effects (issue 30), for `--conditions ... --agents today --seeds 0 1 2 3 4`.
    "surge_lag": ("surge lag 1 s", PlantEffects(surge_lag=1.0), False),
    "lags_0.3": ("lags 0.3 s in surge and yaw", PlantEffects(surge_lag=0.3, yaw_lag=0.3), False),
    "bias_0.5": ("compass bias N(0, 0.5 deg) per vessel", PlantEffects(compass_bias_std=BIAS / 2), False),
    "bias_2": ("compass bias N(0, 2 deg) per vessel", PlantEffects(compass_bias_std=BIAS * 2), False),
    "current_0.3": (
        "current 0.3 m/s, water-referenced odometry, ground-fixed target",
        PlantEffects(current=(0.3, 0.0)),
        True,
    ),
    "limits": ("u <= 3 m/s, r <= 0.5 rad/s", PlantEffects(max_surge=3.0, max_yaw_rate=0.5), False),
}
HEADING = {"control": {"yaw_lag": 1.0, "heading_bandwidth": 2.0}}
GAINS = {"control": {"gain_target": 0.3, "gain_neighbour": 0.15, "neighbour_gain_cap": 0.45}}
LIMITS = {"control": {"boat_max_yaw_rate": OTTER_YAW_RATE, "max_speed": OTTER_SPEED}}
# name -> (what it switches on, agent parameters)
AGENTS = {
    "today": ("none", {}),
    "heading": ("(a) lag-compensated heading loop", HEADING),
    "gains": ("(a) formation gains cut (kappa_io 0.3, kappa_ij 0.15)", GAINS),
    "heading+gains": ("(a) both", {"control": {**HEADING["control"], **GAINS["control"]}}),
    "coping": (
        "(a) both + (d) guard's coasting distance + (e) odometry noise from the sensors' spec",
        COPING,
    ),
    "odometry": ("(e) odometry noise from the sensors' spec alone", ODOMETRY),
    "coping+limits": (
        "coping + the boat's r and u limits in the command",
        {**COPING, "control": {**COPING["control"], **LIMITS["control"]}},
    ),
    "gains+limits": (
        "formation gains cut + the boat's r and u limits in the command",
        {"control": {**GAINS["control"], **LIMITS["control"]}},
    ),
}
# The agents each condition is run with.
PLAN = {
    "calm": ["today", "gains", "coping"],
    "yaw_lag": ["today", "heading", "gains", "heading+gains"],
    "lags": ["today", "gains", "heading+gains", "coping"],
    "otter": ["today", "gains+limits", "coping", "coping+limits"],
    "otter_moving": ["today", "coping+limits"],
    "bias": ["today", "odometry", "coping"],
    "current": ["today", "coping"],
    "moderate": ["today", "gains+limits", "coping+limits"],
    "moderate_0.15": ["today", "coping+limits"],
    "surge_lag": ["today"],
    "lags_0.3": ["today"],
    "bias_0.5": ["today"],
    "bias_2": ["today"],
    "current_0.3": ["today"],
    "limits": ["today"],
}
ISSUE = ["yaw_lag", "surge_lag", "lags_0.3", "bias_0.5", "bias", "bias_2", "current_0.3", "limits"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=seed_type, nargs="+", default=list(range(20)))
    parser.add_argument(
        "--agents",
        nargs="+",
        choices=list(AGENTS),
        default=None,
        help="run only these of each condition's agents (default: the condition's plan)",
    )
    parser.add_argument(
        "--conditions",
        nargs="+",
        choices=list(CONDITIONS),
        default=[c for c in CONDITIONS if c not in ISSUE or c in ("yaw_lag", "bias")],
    )
    parser.add_argument("--out", type=arguments.page, default=DEFAULT_PAGE, help="the page to write")


def run(args: argparse.Namespace) -> int:
    rows = []
    started = time.monotonic()
    for condition in args.conditions:
        _, effects, still = CONDITIONS[condition]
        for agent in [a for a in PLAN[condition] if args.agents is None or a in args.agents]:
            scenario = effect_scenario(effects, AGENTS[agent][1], still_target=still)
            figures = [measure(scenario, effects, seed) for seed in args.seeds]
            s = summary(figures)
            rows.append(
                [
                    condition,
                    agent,
                    f"{s['settled']}/{s['runs']}",
                    _f(s["e_c"]),
                    _f(s["e_ij"]),
                    _f(s["radius_error"]),
                    _f(s["closest"], 2),
                    _f(s["max_surge"], 2),
                    f"{math.degrees(s['max_yaw_rate']):.1f}",
                ]
            )
            print(
                f"usv-lab sea-agent-ab: {condition} / {agent}: {rows[-1][2:]} "
                f"({time.monotonic() - started:.0f} s so far)",
                file=sys.stderr,
                flush=True,
            )
    page = render(args, rows)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(page)
    print(page)
    return 0


def _f(value: float, digits: int = 3) -> str:
    return "-" if math.isnan(value) else f"{value:.{digits}f}"


def render(args: argparse.Namespace, rows: list[list]) -> str:
    conditions = [[name, CONDITIONS[name][0]] for name in args.conditions]
    agents = [[name, words] for name, (words, _) in AGENTS.items()]
    return "\n".join(
        [
            "# The agent's measures for the boat and the water, with and without",
            "",
            f"Made by `{invocation(args)}` (seeds {', '.join(map(str, args.seeds))}; Table II fleet, "
            "raw_range, "
            "in process, today's kinematic world wrapped by lab/harness/plant_effects.py). What each measure does: "
            "docs/sea.md (What the agent does).",
            "",
            markdown_table(["condition", "effects"], conditions),
            "",
            markdown_table(["agent", "measures on"], agents),
            "",
            "e_c and e_ij are means from the settling time on, over the settled runs; abs(r - r*) is the "
            "mean over the last 10 s of every run; the closest approach is the least over every run; the "
            "commands are the largest over every run.",
            "",
            markdown_table(
                [
                    "condition",
                    "agent",
                    "settled",
                    "e_c after (m)",
                    "e_ij after (m)",
                    "mean abs(r - r*) last 10 s (m)",
                    "closest (m)",
                    "max abs(u) cmd (m/s)",
                    "max abs(r) cmd (deg/s)",
                ],
                rows,
            ),
            "",
        ]
    )
