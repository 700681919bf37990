"""The figures of one run in a sea state, a state's summary over its runs, and the verdict against issue 30.

`run_figures(trace)` reduces a run (lab/harness/runner.py's trace) to `SeaRun`: settling, e_ij, e_io, e_c over
the whole run and from the settling time on, the spacing error after settling, the closest approach of any
pair, the time at the thrust limit and the largest commands. `summarise(runs, limits)` gives a state's
`StateSummary`; `verdict(summary, checks)` each acceptance check's words and whether it holds. Pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lab.experiments.scenarios import closest_approach, mean_after
from lab.harness.runner import RunTrace
from mission_log.metrics import gap_departures, nan_mean
from sim_bridge.scenario import Scenario

# Issue 30's acceptance per state: (figure, "<=" or ">=", bound); "settled": the fraction of runs that settle.
EVERY_STATE = [("closest", ">=", 3.0), ("within_limits", ">=", 1.0)]
ACCEPTANCE = {
    **{state: [("settled", ">=", 1.0), ("e_c_after", "<=", 0.3), *EVERY_STATE]
       for state in ("calm", "current", "gradient", "wind", "waves")},
    "moderate": [("settled", ">=", 0.95), ("e_c_after", "<=", 0.5), ("e_ij_after", "<=", 0.3), *EVERY_STATE],
}
COLD_ACCEPTANCE = {"moderate": [("settled", ">=", 0.95)]}
# The states whose cold start the page runs: the acceptance's, with each odometry the page judges it with.
COLD_STATES = ("moderate", "moderate_dvl")
WORDS = {"settled": "settled", "e_c_after": "e_c after settling", "e_ij_after": "e_ij after settling",
         "closest": "closest approach", "within_limits": "commands within the limits"}
UNITS = {"e_c_after": " m", "e_ij_after": " m", "closest": " m"}


@dataclass(frozen=True)
class SeaRun:
    settling_time: float | None   # s; None: never settled
    e_ij: float                   # whole-run means (m)
    e_io: float
    e_c: float
    e_ij_after: float             # means from the settling time on (m); NaN when it never settled
    e_io_after: float
    e_c_after: float
    spacing_after: float          # mean over the ticks after settling of the mean |gap - 2 pi / n| (rad)
    closest: float                # closest approach of any two vessels (m)
    thrust_limit: float           # s the worst vessel's thrust demand spent beyond its thrusters; NaN: none
    max_surge: float              # largest commanded surge (m/s)
    min_surge: float              # smallest (most astern) commanded surge (m/s)
    max_yaw_rate: float           # largest |commanded yaw rate| (rad/s)


@dataclass(frozen=True)
class Limits:
    """The command bounds a run is judged against: the hull preset's inner-loop bounds, or the kinematic
    world's."""

    max_surge: float
    max_reverse: float
    max_yaw_rate: float
    source: str

    def holds(self, run: SeaRun) -> bool:
        return (run.max_surge <= self.max_surge and run.min_surge >= -self.max_reverse
                and run.max_yaw_rate <= self.max_yaw_rate)


def command_limits(scenario: Scenario) -> Limits:
    world = scenario.world
    if world.dynamics is None:
        return Limits(world.max_speed, world.max_speed, world.max_yaw_rate, "the kinematic world's bounds")
    loop = world.dynamics.boat().inner_loop
    preset = world.dynamics.preset
    return Limits(loop.max_speed, loop.max_reverse_speed, loop.rate_max, f"the {preset} preset's")


def spacing_errors(positions: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(K,): at each tick the mean over the gaps of |angle between neighbours around the target - 2 pi / n|
    (rad), over the vessels present; NaN with fewer than two."""
    result = np.full(len(positions), np.nan)
    for k, (where, centre) in enumerate(zip(positions, target)):
        present = where[np.all(np.isfinite(where), axis=1)]
        if len(present) >= 2:
            result[k] = float(np.mean(np.abs(gap_departures(present, centre))))
    return result


def run_figures(trace: RunTrace) -> SeaRun:
    metrics = trace.metrics
    settling = metrics.settling_time
    start = math.inf if settling is None else settling

    def after(values: np.ndarray) -> float:
        return math.nan if settling is None else mean_after(trace.time, values, start)

    limit = trace.thrust_limit[-1]
    commands = trace.commands
    return SeaRun(
        settling_time=settling, e_ij=metrics.mean_e_ij, e_io=metrics.mean_e_io, e_c=metrics.mean_e_c,
        e_ij_after=after(trace.e_ij), e_io_after=after(trace.e_io), e_c_after=after(trace.e_c),
        spacing_after=math.nan if settling is None else after(spacing_errors(trace.positions, trace.target)),
        closest=closest_approach(trace.positions),
        thrust_limit=float(np.nanmax(limit)) if np.isfinite(limit).any() else math.nan,
        max_surge=float(np.nanmax(commands[..., 0])), min_surge=float(np.nanmin(commands[..., 0])),
        max_yaw_rate=float(np.nanmax(np.abs(commands[..., 1]))),
    )


@dataclass(frozen=True)
class StateSummary:
    runs: int
    settled: int
    settling_median: float        # s, over the settled runs; NaN if none
    e_ij: float                   # means over the runs of the whole-run means
    e_io: float
    e_c: float
    e_ij_after: float             # means over the settled runs
    e_io_after: float
    e_c_after: float
    spacing_after: float          # rad
    closest: float                # the least over every run
    thrust_limit_mean: float      # s, mean over the runs of the worst vessel's; NaN for a kinematic world
    thrust_limit_max: float
    max_surge: float              # over every run
    min_surge: float
    max_yaw_rate: float
    limits: Limits

    @property
    def within_limits(self) -> float:
        """1.0 if no command of any run went beyond the limits, else 0.0 (a figure, for `verdict`)."""
        return float(self.max_surge <= self.limits.max_surge and self.min_surge >= -self.limits.max_reverse
                     and self.max_yaw_rate <= self.limits.max_yaw_rate)


def summarise(runs: list[SeaRun], limits: Limits) -> StateSummary:
    settled = [r for r in runs if r.settling_time is not None]

    def mean(field: str, of: list[SeaRun]) -> float:
        return nan_mean(np.array([getattr(r, field) for r in of], dtype=float))

    limit = np.array([r.thrust_limit for r in runs])
    return StateSummary(
        runs=len(runs), settled=len(settled),
        settling_median=float(np.median([r.settling_time for r in settled])) if settled else math.nan,
        e_ij=mean("e_ij", runs), e_io=mean("e_io", runs), e_c=mean("e_c", runs),
        e_ij_after=mean("e_ij_after", settled), e_io_after=mean("e_io_after", settled),
        e_c_after=mean("e_c_after", settled), spacing_after=mean("spacing_after", settled),
        closest=min(r.closest for r in runs),
        thrust_limit_mean=nan_mean(limit),
        thrust_limit_max=float(np.nanmax(limit)) if np.isfinite(limit).any() else math.nan,
        max_surge=max(r.max_surge for r in runs), min_surge=min(r.min_surge for r in runs),
        max_yaw_rate=max(r.max_yaw_rate for r in runs), limits=limits)


def verdict(summary: StateSummary, checks: list[tuple[str, str, float]]) -> list[tuple[str, bool]]:
    """Each check's words ("settled 19/20 >= 19/20") and whether the summary meets it; a NaN figure (no run
    settled) fails. The settled fraction f needs at least ceil(f runs) settled runs."""
    results = []
    for figure, sign, bound in checks:
        if figure == "settled":
            needed = math.ceil(bound * summary.runs - 1e-9)
            results.append((f"settled {summary.settled}/{summary.runs} >= {needed}/{summary.runs}",
                            summary.settled >= needed))
            continue
        if figure == "within_limits":
            ok = summary.within_limits >= bound
            results.append((f"{WORDS[figure]} ({summary.limits.source}): {'yes' if ok else 'no'}", ok))
            continue
        value = getattr(summary, figure)
        ok = value <= bound if sign == "<=" else value >= bound
        shown = "none (no run settled)" if math.isnan(value) else f"{value:.3f}{UNITS.get(figure, '')}"
        results.append((f"{WORDS[figure]} {shown} {sign} {bound:g}", bool(ok)))
    return results
