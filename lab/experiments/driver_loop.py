"""The driver bridge's inner loop (driver_bridge/thrust_loop.py) on a preset's hull, its yaw rate measured as
a real speed log gives it: the compass heading of VHW, rounded to its 0.1 degree, differenced at the
sentence rate and low-passed (rate_filter), the speed rounded to 0.1 kn (docs/sea.md, "Inner loop").

`turn(...)` steps the hull here (sim_bridge/hull.py's Model and rk4, boat.thrusters' lag, calm water: the
substep of HullFleet.advance) under the driver's thrust demand, since HullFleet runs the sim's own loop.
A turn-rate step 0 -> 0.2 rad/s at 1 m/s after 20 s of cruise: rise (10-90 %), overshoot, and the mean
change of a $THR value from one line to the next over the last 5 s (the thrusters' jitter).
`python -m lab.experiments.driver_loop` prints the table of docs/sea.md.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from boat import thrusters
from boat.presets import PRESETS
from driver_bridge.odometry import KNOT, OdometrySettings
from driver_bridge.thrust_loop import LoopSettings, LoopThrusters
from lab.experiments.hull import rise_overshoot
from sim_bridge.hull import Model, rk4

H = 0.02   # the loop's period at its default 50 Hz, and the hull's step


def turn(name: str, sentence_hz: float | None, rate_filter: float, cruise: float = 1.0, size: float = 0.2
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, r, thr) from the step at t = 0: the hull's turn rate and the $THR pairs. `sentence_hz` None: the
    loop is fed the hull's exact (u_r, r) every period, as a yaw-rate input (no rounding, no filter)."""
    boat = PRESETS[name]
    exact = sentence_hz is None
    odometry = OdometrySettings(yaw_input="yaw_rate" if exact else "yaw", yaw_sign=-1, yaw_offset=math.pi / 2)
    driver = LoopThrusters(LoopSettings(preset=name, rate_filter=0.0 if exact else rate_filter), odometry)
    model, state, thrust = Model.of(boat.hull), np.zeros((6, 1)), np.zeros((2, 1))
    every = 1 if exact else round(1 / (sentence_hz * H))
    tau, calm = np.zeros((3, 1)), np.zeros((2, 1))
    r, thr = [], []
    for k in range(round(30.0 / H)):
        t = k * H
        if k % every == 0:
            if exact:
                driver.measure(t, state[3, 0], -state[5, 0])
            else:
                compass = round(math.degrees(math.pi / 2 - state[2, 0]) % 360.0, 1)
                driver.measure(t, round(state[3, 0] / KNOT, 1) * KNOT, math.radians(compass))
        driver.command(cruise, size if k * H >= 20.0 else 0.0, t)
        out = driver.output(t)
        demand = np.array(driver.demand).reshape(2, 1)
        mean = thrusters.mean_over(boat.thrusters, thrust, demand, H)
        thrust = thrusters.lag(boat.thrusters, thrust, demand, H)
        tau[0], tau[2] = thrusters.forces(boat.thrusters, mean[0], mean[1])
        state = rk4(model, state, tau, calm, H)
        r.append(state[5, 0])
        thr.append((out.left, out.right))
    start = round(20.0 / H)
    return H * np.arange(1, len(r) - start + 1), np.array(r[start:]), np.array(thr[start:])


def figures(name: str, sentence_hz: float | None, rate_filter: float) -> tuple[float, float, float]:
    """(rise s, overshoot fraction, mean |change| of a $THR value per line over the last 5 s)."""
    t, r, thr = turn(name, sentence_hz, rate_filter)
    rise, overshoot = rise_overshoot(t, r, 0.2)
    return rise, overshoot, float(np.abs(np.diff(thr[t > 5.0], axis=0)).mean())


def table(name: str = "otter") -> str:
    rows = ["| VHW rate | rate_filter | rise | overshoot | $THR change per line |", "|---|---|---|---|---|"]
    for hz, tau in [(None, 0.0), (2, 0.0), (5, 0.0), (10, 0.0), (10, 0.05), (10, 0.1), (25, 0.0), (25, 0.05),
                    (50, 0.0), (50, 0.05), (50, 0.1)]:
        rise, overshoot, jitter = figures(name, hz, tau)
        rows.append(f"| {'exact r' if hz is None else f'{hz} Hz'} | {tau:g} s | {rise:.2f} s | "
                    f"{100 * overshoot:.1f} % | {jitter:.4f} |")
    return "\n".join(rows)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", default="otter", help="the boat preset (boat/presets.py)")


def run(args: argparse.Namespace) -> int:
    print(table(args.preset))
    return 0
