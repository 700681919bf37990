"""The hull and inner-loop figures of docs/sea.md: `usv-lab hull [--out docs/results]`.

Writes inner_loop_steps.png (each preset's speed and turn-rate step responses through its inner loop) and
prints the figures the page quotes: steady speeds, time constants, turning diameters, step-response rise
times and overshoots, and the world step's CPU cost per vessel per tick, kinematic against each preset.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from agent.core.records import Command
from boat.presets import PRESETS, steady_speed
from lab import arguments
from sim_bridge.hull import HullFleet, Model, rk4
from sim_bridge.world import World, WorldConfig

SPEED_STEP, RATE_STEP, CRUISE = 1.0, 0.2, 1.0


def step_response(name: str, kind: str, size: float, cruise: float, h: float = 0.02, seconds: float = 10.0):
    """(t, y): u_r (kind 'speed') or r ('rate') of one hull after a step command at t = 0 (20 s of cruise
    first when cruise > 0)."""
    fleet = HullFleet(PRESETS[name], 1, h, 1)
    t = 0.0
    for _ in range(200 if cruise else 0):
        fleet.advance(t, 0.1, np.array([cruise]), np.zeros(1), t)
        t += 0.1
    out = []
    for _ in range(round(seconds / h)):
        speed, rate = (size, 0.0) if kind == "speed" else (cruise, size)
        fleet.advance(t, h, np.array([speed]), np.array([rate]), t)
        t += h
        out.append(fleet.state[3 if kind == "speed" else 5, 0])
    return h * np.arange(1, len(out) + 1), np.array(out)


def rise_overshoot(t: np.ndarray, y: np.ndarray, size: float) -> tuple[float, float]:
    """10-90 % rise time (s) and overshoot (a fraction of `size`) of the step response y(t)."""
    first90 = int(np.argmax(y >= 0.9 * size))
    if y[first90] < 0.9 * size:
        raise ValueError("the response never reached 90 % of the step")
    t10 = np.interp(0.1 * size, y[:first90 + 1], t[:first90 + 1])
    return float(t[first90] - t10), float((y.max() - size) / size)


def turning_diameter(name: str, h: float = 0.02) -> float:
    """Diameter of the steady circle at full differential thrust (port astern, starboard ahead)."""
    boat = PRESETS[name]
    tr = boat.thrusters
    tau = np.array([[tr.max_forward - tr.max_reverse], [0.0], [tr.half_beam * (tr.max_forward + tr.max_reverse)]])
    model, state = Model.of(boat.hull), np.zeros((6, 1))
    for _ in range(round(60 / h)):
        state = rk4(model, state, tau, np.zeros((2, 1)), h)
    return 2 * math.hypot(state[3, 0], state[4, 0]) / abs(state[5, 0])


def world_step_cost(preset: str | None, vessels: int, ticks: int = 300) -> float:
    """CPU seconds of one World.step per vessel, vessels on a 20 m circle, each commanded 1 m/s and 0.1 rad/s."""
    angles = np.linspace(0, 2 * math.pi, vessels, endpoint=False)
    config = WorldConfig(
        vessels=[{"id": str(i), "position": (20 * math.cos(a), 20 * math.sin(a)), "heading": a + math.pi / 2}
                 for i, a in enumerate(angles)],
        target={"kind": "constant_velocity", "position": (0.0, 0.0), "velocity": (0.0, 0.0)},
        dynamics=None if preset is None else {"preset": preset})
    world = World(config, np.random.default_rng(0))
    commands = {str(i): Command(surge=1.0, yaw_rate=0.1) for i in range(vessels)}
    started = time.process_time()
    for _ in range(ticks):
        world.step(commands)
    return (time.process_time() - started) / ticks / vessels


def plot(out: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 3, figsize=(14, 4), constrained_layout=True)
    cases = [("speed", SPEED_STEP, 0.0, "speed step 0 -> 1 m/s from rest", "u_r (m/s)"),
             ("rate", RATE_STEP, 0.0, "turn-rate step 0 -> 0.2 rad/s at rest", "r (rad/s)"),
             ("rate", RATE_STEP, CRUISE, "turn-rate step 0 -> 0.2 rad/s at 1 m/s", "r (rad/s)")]
    for axis, (kind, size, cruise, title, label) in zip(axes, cases):
        for name in PRESETS:
            t, y = step_response(name, kind, size, cruise)
            rise, over = rise_overshoot(t, y, size)
            axis.plot(t, y, label=f"{name}: rise {rise:.2f} s, overshoot {100 * over:.0f} %")
        axis.axhline(size, color="k", lw=0.6, ls="--")
        axis.set(title=title, xlabel="time after the step (s)", ylabel=label, xlim=(0, 10))
        axis.legend(fontsize=8)
    figure.suptitle("Inner loop step responses per hull preset (sim_bridge/hull.py, 20 ms RK4, loop at 50 Hz)")
    out.mkdir(parents=True, exist_ok=True)
    figure.savefig(out / "inner_loop_steps.png", dpi=110)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=arguments.folder, default=Path("docs/results"), help="folder for inner_loop_steps.png")


def run(args: argparse.Namespace) -> int:
    for name, boat in PRESETS.items():
        model = Model.of(boat.hull)
        tr = boat.thrusters
        print(f"{name}: steady speed at full thrust {steady_speed(boat.hull, 2 * tr.max_forward):.4f} m/s; "
              f"surge T (linear) {model.m11 / model.linear[0, 0]:.3f} s; yaw T (linear) "
              f"{(model.m33 - model.m23 ** 2 / model.m22) / model.linear[2, 0]:.3f} s; "
              f"turning diameter at full differential thrust {turning_diameter(name):.2f} m")
        for kind, size, cruise in (("speed", SPEED_STEP, 0.0), ("rate", RATE_STEP, 0.0), ("rate", RATE_STEP, CRUISE)):
            rise, over = rise_overshoot(*step_response(name, kind, size, cruise), size)
            print(f"  {kind} step {size:g} at {cruise:g} m/s: rise {rise:.3f} s, overshoot {100 * over:.1f} %")
    for vessels in (4, 50):
        kinematic = world_step_cost(None, vessels)
        line = f"world step, {vessels} vessels, CPU per vessel per tick: kinematic {kinematic * 1e6:.1f} us"
        for name in PRESETS:
            line += f", {name} {world_step_cost(name, vessels) * 1e6:.1f} us"
        print(line)
    plot(args.out)
    print(f"wrote {args.out / 'inner_loop_steps.png'}")
    return 0
