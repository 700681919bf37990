"""Phase and gain margins of the agent's loops on a boat with first-order lags, sampled at dt
(docs/sea.md (What the agent does)).

The boat as lab/harness/plant_effects.py makes it: a command u_k held over the period moves the rate to
x_{k+1} = a x_k + (1 - a) u_k, a = e^{-dt/tau}, and the heading (or the position along a line) by dt x_{k+1}:
P(z) = dt (1 - a) z / ((z - 1)(z - a)). The loops:
- the heading loop of (31), omega^c = K e: L = K P;
- the lag-compensated heading loop (control.yaw_lag), u = r + tau (w_n^2 e + 2 zeta w_n (omega_d - r)) with
  the rate r known: L = tau w_n^2 (1 - a) / (z - a - (1 - a)(1 - 2 zeta w_n tau)) dt z / (z - 1);
- a formation mode of gain lambda (1/s) through a closed heading loop T = L / (1 + L) (across the track,
  y' = u (theta - theta_ff)): lambda T dt z / (z - 1); along the track through the surge lag: lambda P.
`usv-lab loop-margins` prints the table of docs/sea.md (What the agent does).
"""

from __future__ import annotations

import math

import numpy as np


def _frequencies(dt: float) -> tuple[np.ndarray, np.ndarray]:
    w = np.logspace(-3, math.log10(math.pi / dt) - 1e-9, 100_000)
    return w, np.exp(1j * w * dt)


def plant(z: np.ndarray, tau: float, dt: float) -> np.ndarray:
    a = math.exp(-dt / tau) if tau > 0 else 0.0
    return dt * (1 - a) * z / ((z - 1) * (z - a))


def compensated(z: np.ndarray, tau: float, dt: float, bandwidth: float, damping: float) -> np.ndarray:
    a = math.exp(-dt / tau)
    inner = tau * bandwidth**2 * (1 - a) / (z - a - (1 - a) * (1 - 2 * damping * bandwidth * tau))
    return inner * dt * z / (z - 1)


def margins(loop: np.ndarray, w: np.ndarray) -> tuple[float, float, float]:
    """(crossover rad/s, phase margin deg, gain margin dB) of the open loop sampled at `w`; NaN where
    absent."""
    magnitude, phase = np.abs(loop), np.unwrap(np.angle(loop))
    cross = np.flatnonzero(np.diff(np.sign(magnitude - 1.0)))
    flip = np.flatnonzero(np.diff(np.sign(np.degrees(phase) + 180.0)))
    crossover = w[cross[0]] if len(cross) else math.nan
    margin = 180.0 + math.degrees(phase[cross[0]]) if len(cross) else math.nan
    gain = -20.0 * math.log10(magnitude[flip[0]]) if len(flip) else math.nan
    return float(crossover), float(margin), float(gain)


def table(dt: float = 0.1, tau: float = 1.0) -> list[list[str]]:
    """The rows of docs/sea.md (What the agent does)'s margins: each loop and gain with tau_u = tau_r = tau."""
    w, z = _frequencies(dt)
    rows = []

    def row(name: str, loop: np.ndarray) -> None:
        crossover, pm, gm = margins(loop, w)
        rows.append([name, f"{crossover:.2f}", f"{pm:.1f}", "-" if math.isnan(gm) else f"{gm:.1f}"])

    for k in (1.0 / dt, 2.0, 1.0):
        row(f"heading (31), K = {k:g}/s, no lag", k * plant(z, 0.0, dt))
        row(f"heading (31), K = {k:g}/s, tau_r = {tau:g} s", k * plant(z, tau, dt))
    for bandwidth in (1.0, 2.0):
        row(
            f"heading, lag-compensated, w_n = {bandwidth:g}, zeta = 0.8",
            compensated(z, tau, dt, bandwidth, 0.8),
        )
    paper = 1.0 / dt * plant(z, tau, dt)
    for name, heading in (
        ("(31) K = 1/dt", paper / (1 + paper)),
        (
            "lag-compensated w_n = 2",
            compensated(z, tau, dt, 2.0, 0.8) / (1 + compensated(z, tau, dt, 2.0, 0.8)),
        ),
    ):
        for gain in (6.9, 2.3, 0.9):
            row(
                f"across the track, mode {gain:g}/s, through heading {name}",
                gain * heading * dt * z / (z - 1),
            )
    for gain in (6.9, 2.3, 0.9):
        row(f"along the track, mode {gain:g}/s, tau_u = {tau:g} s", gain * plant(z, tau, dt))
    return rows


def add_arguments(parser) -> None:
    """No options: the table is of the fixed 1 s lags and dt = 0.1 s."""


def run(args) -> int:
    from lab.report.markdown import markdown_table

    print(markdown_table(
        ["loop (1 s lags, dt = 0.1 s)", "crossover (rad/s)", "phase margin (deg)", "gain margin (dB)"], table()))
    return 0
