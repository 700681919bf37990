"""`usv-lab bench`: per-update cost of every estimator, side by side with filterpy's KalmanFilter.

A benchmark, not a test: it prints a markdown table and writes `benchmark.md`; nothing here asserts a time.

Data (one seeded `numpy.random.Generator` tree, `--seed`): two vessels on the paper's Experiment 1 circles
(radius 5 m, yaw rate pi/30 rad/s, dt 0.1 s, half a turn apart; `comparison.relative_trajectory`), ranges
with the Table II mixture noise 0.8 N(0, 0.4) + 0.2 N(0, 10), odometry noise N(0, 1e-6 I) on each vessel.
Every input is computed before the clock starts:

More: docs/estimation.md §10, `lab/benchmarks/estimators.py`.
"""

from __future__ import annotations

import argparse
import gc
import math
import os
import platform
import statistics
import sys
import time
import tracemalloc
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agent.config import updated
from agent.core.estimators import estimator_names, make_relative_estimator
from agent.core.estimators.plkf import PLKF
from agent.core.estimators.pseudolinear import equivalent_noise_variance, pseudo_measurement
from agent.core.estimators.raw_range import NO_PRIOR_VARIANCE
from agent.core.params import AgentParams, RelativeEstimationParams
from agent.core.range_noise import GaussianMixtureNoise
from lab import arguments
from lab.experiments.comparison import ComparisonConfig, relative_trajectory
from lab.report.markdown import cpu_model, invocation, markdown_table
from sim_bridge.noise import IsotropicGaussianNoise

DT = 0.1
RADIUS = 5.0
FLEET_SIZE = 12
BANK_SIZE = FLEET_SIZE - 1
RANGE_NOISE = GaussianMixtureNoise(outlier_fraction=0.2, variance=0.4, outlier_variance=10.0)
DISPLACEMENT_VARIANCE = 1e-6
FILTERPY = "filterpy KF"
FILTERPY_IN_LOOP = "filterpy KF, z/R_z/H built in the loop"
PLKF_LABEL = "plkf (target tracker, 4 states)"
PAPER = "mckf"                 # the paper's filter (Sec. III-A)
DEFAULT = "raw_range"          # the agent's default estimator (params.py): the budget is for it
# The budget: at most 100 us per neighbour per tick, a bank of 11 at most 1 ms.
BUDGET_PER_NEIGHBOUR_US = 100.0
BUDGET_BANK_US = 1000.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=arguments.seed, default=7, help="seed of every random number")
    parser.add_argument("--updates", type=arguments.positive_int, default=3000, help="updates per repeat")
    parser.add_argument("--repeats", type=arguments.positive_int, default=5, help="repeats of every measurement")
    parser.add_argument("--out", type=arguments.folder, default=Path("docs/results"), help="where benchmark.md goes")


# ----------------------------------------------------------------------------------------------------------
# Data
# ----------------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PairData:
    """Everything one inter-vessel pair needs for `updates` predict+update steps, computed in advance."""

    truth: np.ndarray                              # (K+1, 2) true relative position at each epoch
    initial: np.ndarray                            # (2,) initial estimate
    displacements: list[np.ndarray]                # K measured relative displacements, (2,) each
    range_pairs: list[tuple[float, float]]         # K (r~_{k-1}, r~_k)
    # filterpy's inputs, filled by `prepare_filterpy`
    u: list[np.ndarray] = field(default_factory=list)   # (2, 1) displacement
    z: list[np.ndarray] = field(default_factory=list)   # (1, 1) pseudo-measurement (13)
    R: list[np.ndarray] = field(default_factory=list)   # (1, 1) R_z (14) at filterpy's prior
    H: list[np.ndarray] = field(default_factory=list)   # (1, 2) delta^T


@dataclass(frozen=True)
class TargetData:
    initial: np.ndarray                            # (4,) initial estimate of [p_io; v_io]
    bearings: list[np.ndarray]                     # K noisy bearings (target to vessel), (2,) each


def bench_params(params: AgentParams | None = None) -> RelativeEstimationParams:
    """The relative-estimation parameters of the benchmark: Table I with R = the mixture's variance."""
    relative = (params or AgentParams()).relative
    return updated(relative, range_variance=RANGE_NOISE.total_variance,
                   displacement_variance=DISPLACEMENT_VARIANCE)


def _pair_data(own: np.ndarray, other: np.ndarray, rng: np.random.Generator,
               params: RelativeEstimationParams) -> PairData:
    truth = own - other
    steps = len(truth) - 1
    # A range sensor reports no negative distance; the clip matters only for the bank's close neighbours
    # (2.6 m apart, outlier std 3.2 m), where our estimators would refuse a negative range and filterpy not.
    ranges = np.maximum(np.linalg.norm(truth, axis=1) + RANGE_NOISE.sample(rng, steps + 1), 0.0)
    odometry = IsotropicGaussianNoise(variance=DISPLACEMENT_VARIANCE)
    displacement = (np.diff(own, axis=0) + odometry.sample(rng, steps)) - (
        np.diff(other, axis=0) + odometry.sample(rng, steps))
    initial = truth[0] + rng.normal(0.0, math.sqrt(params.initial_covariance), size=2)
    r = ranges.tolist()
    return PairData(
        truth=truth, initial=initial,
        displacements=[np.ascontiguousarray(d) for d in displacement],
        range_pairs=list(zip(r[:-1], r[1:])),
    )


def make_data(seed: int, updates: int, params: RelativeEstimationParams
              ) -> tuple[PairData, list[PairData], TargetData]:
    """The Experiment 1 pair, the 11 pairs of vessel 0 in a ring of 12 on the same circle, and the target
    tracker's bearings; each from its own child of `seed`."""
    pair_seed, bank_seed, target_seed = np.random.SeedSequence(seed).spawn(3)
    config = ComparisonConfig(duration=updates * DT, radius=RADIUS, noise_models={"gmm": RANGE_NOISE})
    t, own, other = relative_trajectory(config)
    pair = _pair_data(own, other, np.random.default_rng(pair_seed), params)

    phase = AgentParams().control.yaw_rate * t
    bank = []
    for j, child in enumerate(bank_seed.spawn(BANK_SIZE), start=1):
        offset = 2.0 * math.pi * j / FLEET_SIZE
        other_j = RADIUS * np.column_stack([np.cos(phase + offset), np.sin(phase + offset)])
        bank.append(_pair_data(own, other_j, np.random.default_rng(child), params))

    # Target at the origin, vessel 0 circling it: x_io = [p_io; v_io]; bearing = unit(p_io) + N(0, R_b I).
    rng = np.random.default_rng(target_seed)
    target = AgentParams().target
    omega = AgentParams().control.yaw_rate
    velocity = RADIUS * omega * np.column_stack([-np.sin(phase), np.cos(phase)])
    unit = own / np.linalg.norm(own, axis=1, keepdims=True)
    noisy = unit[1:] + IsotropicGaussianNoise(variance=target.bearing_variance).sample(rng, len(t) - 1)
    state0 = np.concatenate([own[0], velocity[0]]) + rng.normal(0.0, math.sqrt(target.initial_covariance), 4)
    tracker = TargetData(initial=state0, bearings=[np.ascontiguousarray(b) for b in noisy])
    for data in (pair, *bank):
        prepare_filterpy(data, params)
    return pair, bank, tracker


# ----------------------------------------------------------------------------------------------------------
# Filters
# ----------------------------------------------------------------------------------------------------------

def new_filterpy(data: PairData, params: RelativeEstimationParams):
    """filterpy KalmanFilter set up as our KF: x0, P0 = initial_covariance I, F = I, B = I, Q = R_delta."""
    # filterpy is imported where it is used: it is no dependency of the lab (only of the tests), and `run`
    # says how to get it when it is missing.
    from filterpy.kalman import KalmanFilter

    kf = KalmanFilter(dim_x=2, dim_z=1, dim_u=2)
    kf.x = data.initial.reshape(2, 1).copy()
    kf.P = params.initial_covariance * np.eye(2)
    kf.F = np.eye(2)
    kf.B = np.eye(2)
    kf.Q = 2.0 * params.displacement_variance * np.eye(2)
    return kf


def prepare_filterpy(data: PairData, params: RelativeEstimationParams) -> np.ndarray:
    """Fill filterpy's inputs by one untimed pass, R_z being evaluated at the filter's own prior.

    Returns the posterior positions (K, 2) of that pass.
    """
    kf = new_filterpy(data, params)
    data.u.clear(), data.z.clear(), data.R.clear(), data.H.clear()
    positions = np.empty((len(data.range_pairs), 2))
    for k, (d, (r_prev, r_now)) in enumerate(zip(data.displacements, data.range_pairs)):
        dx, dy = float(d[0]), float(d[1])
        u = np.array([[dx], [dy]])
        kf.predict(u=u)
        px, py = float(kf.x[0, 0]), float(kf.x[1, 0])
        z = np.array([[pseudo_measurement(r_prev, r_now, dx, dy)]])
        R = np.array([[equivalent_noise_variance(px, py, dx, dy, params.range_variance,
                                                 2.0 * params.displacement_variance)]])
        H = np.array([[dx, dy]])
        kf.update(z, R=R, H=H)
        data.u.append(u), data.z.append(z), data.R.append(R), data.H.append(H)
        positions[k] = kf.x[:, 0]
    return positions


@dataclass(frozen=True)
class Setup:
    """One of our estimators as the bench starts it: from the bench's prior (`data.initial`,
    initial_covariance I) or cold (NO_PRIOR_VARIANCE I: no prior)."""

    name: str
    cold: bool = False

    @property
    def label(self) -> str:
        return f"{self.name}, cold start" if self.cold else self.name


SINGLE_SETUPS = (*(Setup(name) for name in estimator_names()), Setup(DEFAULT, cold=True))
BANK_SETUPS = (Setup(PAPER), Setup(DEFAULT), Setup(DEFAULT, cold=True))


def bank_label(label: str) -> str:
    return f"bank: {BANK_SIZE} x {label}"


def new_ours(setup: Setup, data: PairData, params: RelativeEstimationParams):
    covariance = NO_PRIOR_VARIANCE * np.eye(2) if setup.cold else None
    estimator = make_relative_estimator(params, data.initial, covariance, dt=DT, name=setup.name)
    estimator.mark_range_epoch()
    return estimator


@dataclass(frozen=True)
class Trace:
    """What one of our estimators did at each update of one pair's data, from an untimed run."""

    positions: np.ndarray          # (K, 2) posterior
    iterations: list[int]          # UpdateOutcome.iterations
    fixing: list[bool]             # in the fix phase: raw_range not yet `fixed` (the others have none)


def run_ours(setup: Setup, data: PairData, params: RelativeEstimationParams) -> Trace:
    """Our estimator `setup` on `data`, untimed: for checking, and for what the timing loops do not keep."""
    estimator = new_ours(setup, data, params)
    n = len(data.range_pairs)
    positions, iterations, fixing = np.empty((n, 2)), [0] * n, [False] * n
    for k, (d, (r_prev, r_now)) in enumerate(zip(data.displacements, data.range_pairs)):
        fixing[k] = not getattr(estimator, "fixed", True)
        estimator.predict(d)
        iterations[k] = estimator.update(r_prev, r_now).iterations
        positions[k] = estimator.position
    return Trace(positions, iterations, fixing)


def run_filterpy(data: PairData, params: RelativeEstimationParams) -> np.ndarray:
    """Posterior positions (K, 2) of filterpy's KF fed the benchmark's pre-computed inputs (untimed)."""
    kf = new_filterpy(data, params)
    positions = np.empty((len(data.range_pairs), 2))
    for k in range(len(data.range_pairs)):
        kf.predict(u=data.u[k])
        kf.update(data.z[k], R=data.R[k], H=data.H[k])
        positions[k] = kf.x[:, 0]
    return positions


# ----------------------------------------------------------------------------------------------------------
# Timing loops: each returns per-step times in ns (and, for ours, the iterations of every update)
# ----------------------------------------------------------------------------------------------------------

def _time_ours(estimator, data: PairData, update_only: bool) -> tuple[list[int], list[int]]:
    predict, update, now = estimator.predict, estimator.update, time.perf_counter_ns
    n = len(data.range_pairs)
    times, iterations = [0] * n, [0] * n
    displacements, pairs = data.displacements, data.range_pairs
    if update_only:
        for k in range(n):
            d = displacements[k]
            a, b = pairs[k]
            predict(d)
            t0 = now()
            outcome = update(a, b)
            times[k] = now() - t0
            iterations[k] = outcome.iterations
    else:
        for k in range(n):
            d = displacements[k]
            a, b = pairs[k]
            t0 = now()
            predict(d)
            outcome = update(a, b)
            times[k] = now() - t0
            iterations[k] = outcome.iterations
    return times, iterations


def _time_filterpy(kf, data: PairData, update_only: bool) -> tuple[list[int], list[int]]:
    predict, update, now = kf.predict, kf.update, time.perf_counter_ns
    n = len(data.range_pairs)
    times = [0] * n
    us, zs, Rs, Hs = data.u, data.z, data.R, data.H
    if update_only:
        for k in range(n):
            u, z, R, H = us[k], zs[k], Rs[k], Hs[k]
            predict(u=u)
            t0 = now()
            update(z, R=R, H=H)
            times[k] = now() - t0
    else:
        for k in range(n):
            u, z, R, H = us[k], zs[k], Rs[k], Hs[k]
            t0 = now()
            predict(u=u)
            update(z, R=R, H=H)
            times[k] = now() - t0
    return times, []


def _time_filterpy_in_loop(kf, data: PairData, params: RelativeEstimationParams, update_only: bool
                           ) -> tuple[list[int], list[int]]:
    """filterpy as a caller would drive it from raw ranges and displacements: build u, z, R_z, H per step
    (R_z at the filter's prior, as our `update` does) inside the timed region."""
    predict, update, now = kf.predict, kf.update, time.perf_counter_ns
    n = len(data.range_pairs)
    times = [0] * n
    displacements, pairs = data.displacements, data.range_pairs
    rv, dv = params.range_variance, 2.0 * params.displacement_variance
    array = np.array
    for k in range(n):
        d = displacements[k]
        r_prev, r_now = pairs[k]
        if update_only:
            dx, dy = float(d[0]), float(d[1])
            predict(u=array([[dx], [dy]]))
            t0 = now()
        else:
            t0 = now()
            dx, dy = float(d[0]), float(d[1])
            predict(u=array([[dx], [dy]]))
        x = kf.x
        z = array([[pseudo_measurement(r_prev, r_now, dx, dy)]])
        R = array([[equivalent_noise_variance(float(x[0, 0]), float(x[1, 0]), dx, dy, rv, dv)]])
        update(z, R=R, H=array([[dx, dy]]))
        times[k] = now() - t0
    return times, []


def _time_bank(filters: Sequence, bank: Sequence[PairData], ours: bool) -> list[int]:
    """Per-tick time of predict+update of every filter of the bank, each on its own pair."""
    now = time.perf_counter_ns
    n = len(bank[0].range_pairs)
    times = [0] * n
    methods = [(f.predict, f.update) for f in filters]
    if ours:
        ticks = [[(data.displacements[k], *data.range_pairs[k]) for data in bank] for k in range(n)]
        for k in range(n):
            tick = ticks[k]
            t0 = now()
            for (predict, update), (d, a, b) in zip(methods, tick):
                predict(d)
                update(a, b)
            times[k] = now() - t0
    else:
        ticks = [[(data.u[k], data.z[k], data.R[k], data.H[k]) for data in bank] for k in range(n)]
        for k in range(n):
            tick = ticks[k]
            t0 = now()
            for (predict, update), (u, z, R, H) in zip(methods, tick):
                predict(u=u)
                update(z, R=R, H=H)
            times[k] = now() - t0
    return times


def _time_plkf(data: TargetData, update_only: bool) -> tuple[list[int], list[int]]:
    tracker = PLKF(AgentParams().target, data.initial, dt=DT)
    predict, update, now = tracker.predict, tracker.update, time.perf_counter_ns
    n = len(data.bearings)
    times = [0] * n
    bearings = data.bearings
    if update_only:
        for k in range(n):
            b = bearings[k]
            predict()
            t0 = now()
            update(b)
            times[k] = now() - t0
    else:
        for k in range(n):
            b = bearings[k]
            t0 = now()
            predict()
            update(b)
            times[k] = now() - t0
    return times, []


def _quiet(measure: Callable[[], tuple[list[int], list[int]]]) -> tuple[list[int], list[int]]:
    """Run `measure` with the garbage collector off (as timeit does), restoring its previous state."""
    enabled = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        return measure()
    finally:
        if enabled:
            gc.enable()


def timer_overhead_ns(samples: int = 20_000) -> float:
    """Median of back-to-back perf_counter_ns readings: what every timed sample carries on top."""
    now = time.perf_counter_ns
    deltas = [0] * samples
    for k in range(samples):
        t0 = now()
        deltas[k] = now() - t0
    return float(statistics.median(deltas))


# ----------------------------------------------------------------------------------------------------------
# Results
# ----------------------------------------------------------------------------------------------------------

def figures_us(samples_ns: Sequence[int]) -> tuple[float, float, float, float]:
    """(median, mean, p99, max) of `samples_ns` in us; NaN each if there are none (a phase never reached)."""
    if not samples_ns:
        return (math.nan,) * 4
    us = np.asarray(samples_ns, dtype=float) / 1e3
    return float(np.median(us)), float(us.mean()), float(np.percentile(us, 99)), float(us.max())


@dataclass
class Timing:
    """The samples of one row, all repeats pooled: one per predict+update of one pair, or for a bank one per
    tick (predict+update of all its pairs)."""

    full_ns: list[int] = field(default_factory=list)       # predict + update (a bank: the whole tick)
    update_ns: list[int] = field(default_factory=list)     # update alone (single pair only)
    iterations: list[int] = field(default_factory=list)
    repeat_medians_ns: list[float] = field(default_factory=list)
    fixing: list[bool] = field(default_factory=list)       # per step of a repeat: in the fix phase?
    fix_updates: list[int] = field(default_factory=list)   # per pair: updates in its fix phase, in one repeat

    def add(self, full: tuple[list[int], list[int]],
            update: tuple[list[int], list[int]] | None = None) -> None:
        self.full_ns += full[0]
        self.iterations += full[1]
        if update is not None:
            self.update_ns += update[0]
        self.repeat_medians_ns.append(float(np.median(full[0])))

    def set_phases(self, traces: Sequence[Trace]) -> None:
        """Each step's phase, from untimed runs of the row's pairs: a tick is in the fix phase while any pair
        is."""
        self.fixing = [any(step) for step in zip(*(trace.fixing for trace in traces))]
        self.fix_updates = [sum(trace.fixing) for trace in traces]

    def phase_ns(self, fixing: bool) -> list[int]:
        """The samples of the fix phase (True) or of the tracking phase (False), all repeats."""
        steps = len(self.fixing)
        return [t for i, t in enumerate(self.full_ns) if self.fixing[i % steps] == fixing]

    @property
    def worst_step(self) -> int:
        """The step of a repeat with the slowest sample (after `set_phases`)."""
        return int(np.argmax(self.full_ns)) % len(self.fixing)

    @property
    def median_us(self) -> float:
        return float(np.median(self.full_ns)) / 1e3

    @property
    def mean_us(self) -> float:
        return float(np.mean(self.full_ns)) / 1e3

    @property
    def update_median_us(self) -> float:
        return float(np.median(self.update_ns)) / 1e3 if self.update_ns else math.nan

    @property
    def mean_iterations(self) -> float:
        return float(np.mean(self.iterations)) if self.iterations else math.nan


@dataclass
class Results:
    seed: int
    updates: int
    repeats: int
    single: dict[str, Timing]
    bank: dict[str, Timing]
    memory: dict[str, tuple[float, float]]
    kf_vs_filterpy: float          # max |our KF - filterpy KF| position difference, every pair and step (m)
    timer_overhead_ns: float


SINGLE_ROWS = (*(setup.label for setup in SINGLE_SETUPS), FILTERPY, FILTERPY_IN_LOOP, PLKF_LABEL)
BANK_ROWS = (*(bank_label(setup.label) for setup in BANK_SETUPS), bank_label(FILTERPY))


def _one_repeat(pair: PairData, bank: list[PairData], target: TargetData, params: RelativeEstimationParams,
                single: dict[str, Timing], banked: dict[str, Timing]) -> None:
    """Every timing once, fresh filters each, appended to `single` and `banked`."""
    for setup in SINGLE_SETUPS:
        single[setup.label].add(_quiet(lambda: _time_ours(new_ours(setup, pair, params), pair, False)),
                                _quiet(lambda: _time_ours(new_ours(setup, pair, params), pair, True)))
    single[FILTERPY].add(_quiet(lambda: _time_filterpy(new_filterpy(pair, params), pair, False)),
                         _quiet(lambda: _time_filterpy(new_filterpy(pair, params), pair, True)))
    single[FILTERPY_IN_LOOP].add(
        _quiet(lambda: _time_filterpy_in_loop(new_filterpy(pair, params), pair, params, False)),
        _quiet(lambda: _time_filterpy_in_loop(new_filterpy(pair, params), pair, params, True)))
    single[PLKF_LABEL].add(_quiet(lambda: _time_plkf(target, False)),
                           _quiet(lambda: _time_plkf(target, True)))
    for setup in BANK_SETUPS:
        estimators = [new_ours(setup, data, params) for data in bank]
        banked[bank_label(setup.label)].add(_quiet(lambda: (_time_bank(estimators, bank, ours=True), [])))
    kfs = [new_filterpy(data, params) for data in bank]
    banked[bank_label(FILTERPY)].add(_quiet(lambda: (_time_bank(kfs, bank, ours=False), [])))


def measure(seed: int, updates: int, repeats: int, progress: Callable[[str], None] = lambda _: None
            ) -> Results:
    """Every measurement of the benchmark."""
    params = bench_params()
    progress("generating data")
    pair, bank, target = make_data(seed, updates, params)
    difference = max(float(np.max(np.abs(run_ours(Setup("kf"), data, params).positions
                                          - run_filterpy(data, params))))
                     for data in (pair, *bank))

    # A warm-up repeat whose numbers are discarded: the first pass of each code path pays for cold caches.
    progress("warm-up")
    _one_repeat(pair, bank, target, params, {name: Timing() for name in SINGLE_ROWS},
                {name: Timing() for name in BANK_ROWS})
    single = {name: Timing() for name in SINGLE_ROWS}
    banked = {name: Timing() for name in BANK_ROWS}
    for repeat in range(repeats):
        progress(f"repeat {repeat + 1}/{repeats}")
        _one_repeat(pair, bank, target, params, single, banked)

    # Phases, and the banks' iterations (the timed bank loop keeps no outcomes), from untimed runs.
    progress("tracing phases")
    for setup in SINGLE_SETUPS:
        single[setup.label].set_phases([run_ours(setup, pair, params)])
    for setup in BANK_SETUPS:
        traces = [run_ours(setup, data, params) for data in bank]
        banked[bank_label(setup.label)].set_phases(traces)
        banked[bank_label(setup.label)].iterations = [i for trace in traces for i in trace.iterations]

    progress("measuring memory")
    memory = {}
    for setup in (Setup(PAPER), Setup(DEFAULT)):
        memory[f"one {setup.label}"] = _peak_memory(
            lambda: [new_ours(setup, pair, params)], [pair], ours=True)
        memory[f"bank of {BANK_SIZE} {setup.label}"] = _peak_memory(
            lambda: [new_ours(setup, data, params) for data in bank], bank, ours=True)
    memory["one filterpy KF"] = _peak_memory(lambda: [new_filterpy(pair, params)], [pair], ours=False)
    memory[f"{BANK_SIZE} filterpy KFs"] = _peak_memory(
        lambda: [new_filterpy(data, params) for data in bank], bank, ours=False)
    return Results(seed=seed, updates=updates, repeats=repeats, single=single, bank=banked, memory=memory,
                   kf_vs_filterpy=difference, timer_overhead_ns=timer_overhead_ns())


def _peak_memory(build: Callable[[], list], pairs: Sequence[PairData], ours: bool) -> tuple[float, float]:
    """(peak, retained) KiB traced while building the filters and running them over all of `pairs`' data:
    the peak covers every temporary of an update, the retained size is what the live filters hold."""
    gc.collect()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        filters = build()
        for k in range(len(pairs[0].range_pairs)):
            for f, data in zip(filters, pairs):
                if ours:
                    f.predict(data.displacements[k])
                    f.update(*data.range_pairs[k])
                else:
                    f.predict(u=data.u[k])
                    f.update(data.z[k], R=data.R[k], H=data.H[k])
        current, peak = tracemalloc.get_traced_memory()
        del filters
    finally:
        tracemalloc.stop()
    return (peak - base) / 1024.0, (current - base) / 1024.0


def machine_info() -> list[tuple[str, str]]:
    import filterpy  # optional, as in new_filterpy

    cpu = cpu_model()
    return [
        ("Python", f"{platform.python_implementation()} {platform.python_version()}"),
        ("numpy", np.__version__),
        ("filterpy", filterpy.__version__),
        ("platform", platform.platform()),
        ("CPU", f"{cpu}, os.cpu_count() = {os.cpu_count()}"),
    ]


def _iterations(timing: Timing) -> str:
    # raw_range's outcomes count its batch solves in `iterations`, not iterations of one update.
    return f"{timing.mean_iterations:.3f}" if timing.iterations and not any(timing.fixing) else "-"


def _cells(values: Sequence[float]) -> list[object]:
    """'-' for a figure of a phase the data never reached (NaN)."""
    return ["-" if math.isnan(value) else value for value in values]


def _lasted(steps: int, total: int, unit: str) -> str:
    """How long a fix phase lasted, in steps and in seconds of data."""
    end = "" if steps < total else ", all of the data: it did not end"
    return f"{steps} {unit} ({steps * DT:.1f} s{end})"


def _verdict(bank_mean_us: float) -> str:
    return ("within" if bank_mean_us <= BUDGET_BANK_US and bank_mean_us / BANK_SIZE <= BUDGET_PER_NEIGHBOUR_US
            else "over")


def _phase_rows(results: Results) -> list[list[object]]:
    """The default estimator's rows, single pair and bank, from the bench's prior and cold, split by phase."""
    phased = [(setup.label, results.single[setup.label], 1)
              for setup in SINGLE_SETUPS if setup.name == DEFAULT]
    phased += [(bank_label(setup.label), results.bank[bank_label(setup.label)], BANK_SIZE)
               for setup in BANK_SETUPS if setup.name == DEFAULT]
    rows = []
    for label, timing, pairs in phased:
        for fixing, phase in ((True, "fix phase"), (False, "tracking")):
            steps = sum(1 for f in timing.fixing if f == fixing)
            median, mean, p99, worst = figures_us(timing.phase_ns(fixing))
            rows.append([f"{label}: {phase}", steps, f"{steps * DT:.1f}",
                         *_cells([median, mean, p99, worst, mean / pairs])])
    return rows


def _summary(results: Results) -> str:
    single, banks = results.single, results.bank
    cold = Setup(DEFAULT, cold=True).label
    reference, fp_bank = single[FILTERPY], banks[bank_label(FILTERPY)]
    ref_full, ref_update = reference.median_us, reference.update_median_us
    steps = results.updates
    budget = (f"mean <= {BUDGET_PER_NEIGHBOUR_US:g} us per neighbour per tick, bank of {BANK_SIZE} <= "
              f"{BUDGET_BANK_US / 1e3:g} ms")
    verdicts = []
    for start, label in (("from the bench's prior", DEFAULT), ("from a cold start", cold)):
        mean = banks[bank_label(label)].mean_us
        verdicts.append(f"{start}: {mean:.1f} us per tick mean ({mean / BANK_SIZE:.1f} us per neighbour, "
                        f"{mean / fp_bank.mean_us:.2f} x {BANK_SIZE} filterpy KFs): {_verdict(mean)}")
    lines = [
        f"Budget of the issue ({budget}), default estimator {DEFAULT}, bank of {BANK_SIZE} (one vessel of a "
        f"{FLEET_SIZE}-vessel fleet), over the {steps} ticks ({steps * DT:g} s) of a run, fix phase "
        f"included: {'; '.join(verdicts)}."
    ]
    fix_texts = []
    for start, label in (("From a cold start", cold), ("From the bench's prior", DEFAULT)):
        timing = banks[bank_label(label)]
        samples = timing.phase_ns(True)
        _, mean, p99, worst = figures_us(samples)
        over = sum(1 for t in samples if t > BUDGET_BANK_US * 1e3) / results.repeats
        fix_texts.append(
            f"{start} it lasted {_lasted(sum(timing.fixing), steps, 'ticks')}, its pairs' own fix phases "
            f"{min(timing.fix_updates)}-{max(timing.fix_updates)} updates: {mean:.0f} us per tick mean "
            f"({mean / BUDGET_BANK_US:.2f} x the budget, {mean / BANK_SIZE:.1f} us per neighbour), "
            f"{over:.0f} of its ticks over {BUDGET_BANK_US / 1e3:g} ms, p99 {p99:.0f} us "
            f"({p99 / BUDGET_BANK_US:.1f} x), worst tick {worst:.0f} us ({worst / BUDGET_BANK_US:.1f} x, "
            f"step {timing.worst_step})")
    tracking = figures_us(banks[bank_label(cold)].phase_ns(False))[1]
    lines.append(
        "Fix phase of the bank (its ticks until the last pair reported `fixed`), which the mean hides: its "
        "pairs, started together, solve their windows every few ticks, each pair's first solve put off by "
        f"up to `solve_every` - 1 ranges so that they spread over the ticks. {'. '.join(fix_texts)}."
        + ("" if math.isnan(tracking) else f" Tracking afterwards: {tracking:.1f} us per tick mean "
           f"({tracking / BANK_SIZE:.1f} us per neighbour)."))
    raw = single[DEFAULT]
    median, mean, p99, worst = figures_us(raw.full_ns)
    fix = "; ".join(f"{start}, {_lasted(sum(single[label].fixing), steps, 'updates')} at "
                    f"{figures_us(single[label].phase_ns(True))[1]:.0f} us mean"
                    for start, label in (("from the bench's prior", DEFAULT), ("cold", cold)))
    tracking = figures_us(raw.phase_ns(False))[0]
    lines.append(
        f"One {DEFAULT} pair predict+update: {median:.2f} us median, {mean:.2f} us mean, p99 {p99:.1f} us, "
        f"max {worst:.0f} us, vs filterpy KF {ref_full:.2f} us median: ratio {median / ref_full:.2f}. "
        f"Its fix phase lasted, {fix}"
        + ("." if math.isnan(tracking) else f"; tracking: {tracking:.2f} us median."))
    mckf, bank_mckf = single[PAPER], banks[bank_label(PAPER)]
    lines.append(
        f"One MCKF pair predict+update: {mckf.median_us:.2f} us median vs filterpy KF {ref_full:.2f} us: "
        f"ratio {mckf.median_us / ref_full:.2f} (update alone: {mckf.update_median_us:.2f} vs "
        f"{ref_update:.2f} us, ratio {mckf.update_median_us / ref_update:.2f}); "
        f"{mckf.mean_iterations:.2f} MCKF iterations per update on average.")
    lines.append(
        f"Bank of {BANK_SIZE} MCKF pairs: {bank_mckf.median_us:.1f} us per tick median "
        f"({bank_mckf.mean_us:.1f} mean) vs {fp_bank.median_us:.1f} us ({fp_bank.mean_us:.1f}) for "
        f"{BANK_SIZE} filterpy KFs: ratio {bank_mckf.median_us / fp_bank.median_us:.2f} "
        f"({bank_mckf.mean_us / fp_bank.mean_us:.2f}); "
        f"{100 * bank_mckf.mean_us * 1e-6 / DT:.2f} % of the {DT:g} s sampling period.")
    return "\n".join(lines)


def render(results: Results, command: str, info: Sequence[tuple[str, str]]) -> tuple[str, str]:
    """(document, tables and summary) in markdown."""
    single = results.single
    reference = single[FILTERPY]
    ref_full, ref_update = reference.median_us, reference.update_median_us
    rows = []
    for name, timing in single.items():
        median, mean, p99, worst = figures_us(timing.full_ns)
        rows.append([name, median, mean, p99, worst, f"{median / ref_full:.2f}", timing.update_median_us,
                     f"{timing.update_median_us / ref_update:.2f}", _iterations(timing)])
    header = ["estimator", "median us, predict+update", "mean us", "p99 us", "max us", "ratio to filterpy KF",
              "median us, update only", "update ratio to filterpy KF", "mean iterations"]
    fp_bank = results.bank[bank_label(FILTERPY)]
    bank_rows = []
    for name, timing in results.bank.items():
        median, mean, p99, worst = figures_us(timing.full_ns)
        bank_rows.append([name, median, mean, p99, worst, f"{median / fp_bank.median_us:.2f}",
                          f"{mean / fp_bank.mean_us:.2f}", mean / BANK_SIZE, _iterations(timing)])
    bank_header = ["bank (one tick)", "median us per tick", "mean us per tick", "p99 us", "max us",
                   "median ratio to filterpy bank", "mean ratio to filterpy bank", "mean us per neighbour",
                   "mean iterations"]
    phase_header = [f"{DEFAULT}: phase", "steps per repeat", "s of data", "median us", "mean us", "p99 us",
                    "max us", "mean us per neighbour"]
    table = markdown_table(header, rows)
    bank_table = markdown_table(bank_header, bank_rows)
    phase_table = markdown_table(phase_header, _phase_rows(results))
    summary = _summary(results)
    memory_rows = [[name, peak, retained] for name, (peak, retained) in results.memory.items()]
    spread = ", ".join(f"{name} {min(t.repeat_medians_ns) / 1e3:.2f}-{max(t.repeat_medians_ns) / 1e3:.2f}"
                       for name, t in single.items() if name in (PAPER, DEFAULT, FILTERPY))
    updates, repeats = results.updates, results.repeats
    spread0 = bench_params().initial_covariance
    document = "\n".join([
        "# Benchmark: per-update cost of the estimators vs filterpy's KalmanFilter",
        "",
        "Generated by the command below; do not edit by hand. Timings depend on the machine and its load;",
        "the ratios, measured in the same run, are what carries over.",
        "",
        "```",
        command,
        "```",
        "",
        "## Summary",
        "",
        summary.replace("\n", "\n\n"),
        "",
        "## Machine",
        "",
        *[f"- {key}: {value}" for key, value in info],
        f"- timer: time.perf_counter_ns, {results.timer_overhead_ns:.0f} ns per back-to-back reading "
        "(included in every sample below, not subtracted)",
        "",
        "## What was measured",
        "",
        f"- Data (seed {results.seed}): the paper's Experiment 1, two vessels on circles of radius "
        f"{RADIUS:g} m at pi/30 rad/s, dt {DT:g} s, half a turn apart; range noise "
        "0.8 N(0, 0.4) + 0.2 N(0, 10), "
        f"displacement noise N(0, {DISPLACEMENT_VARIANCE:g} I) per vessel; filters with R = 2.32 (the "
        "mixture's variance) and Table I otherwise. Measured ranges are clipped at 0 (a range sensor "
        "reports no negative distance). All inputs are computed before timing.",
        f"- {updates} predict+update steps per repeat, {repeats} repeats (after one discarded warm-up "
        "repeat); every repeat starts fresh filters on the same data, the repeats visit the estimators in "
        "turn, the garbage collector is off while timing.",
        "- Each sample is one `predict` + one `update` call bracketed by `perf_counter_ns` (the update-only "
        "columns bracket the `update` call alone). Median, mean, p99 and max are over the individual samples "
        f"of all repeats pooled ({updates * repeats} per row). Repeat medians ranged {spread} us.",
        "- Ours: `predict(delta)` with delta a numpy (2,) float64 row, `update(r_prev, r_now)` with two "
        "Python floats; `update` computes its measurement itself (the pseudo-linear ones: z (13) and "
        "R_z (14)), checks its inputs and returns an `UpdateOutcome`.",
        f"- Start: our estimators start from the true relative position plus N(0, {spread0:g} I), with "
        f"covariance {spread0:g} I (Table I). `{Setup(DEFAULT, cold=True).label}`: {DEFAULT}, the agent's "
        f"default, started with covariance {NO_PRIOR_VARIANCE:g} I, no prior at all (as it restarts a "
        "dropped fix; a joiner with no estimate starts from the range along x with a spread of the range "
        "itself, nearly as uninformative).",
        f"- Phases of {DEFAULT}: a batch fix (a non-linear least squares over a window of ranges every "
        "`solve_every` ranges) until it reports `fixed`, then one cheap tracking update per range. An "
        "update is in the fix phase if the estimator had not reported `fixed` before it; a bank's tick, if "
        "any of its pairs' updates is. Which updates these are comes from an untimed run over the same data "
        "(the estimators are deterministic). The mean of a whole run depends on its length: the fix phase "
        "is a fixed stretch at the start.",
        "- filterpy 2.0.0 `KalmanFilter(dim_x=2, dim_z=1)` with F = I, B = I, Q = R_delta = 2e-6 I: "
        "`predict(u=delta)` (delta a (2, 1) array) and `update(z, R=R_z, H=delta^T)` with z, R_z, H "
        "pre-computed (1, 1), (1, 1), (1, 2) arrays, R_z evaluated at filterpy's own prior estimate. "
        "Predict is the same work on both sides (x += delta, P += R_delta); the update is the same "
        f"Joseph-form correction. Ratios are to this row. Check: our KF and this filterpy KF agree to "
        f"{results.kf_vs_filterpy:.1e} m at every step of every pair (single and bank).",
        f"- `{FILTERPY_IN_LOOP}`: filterpy as a caller would drive it from raw ranges, building u, z, R_z, H "
        "inside the timed region, i.e. the same inputs our `update` takes.",
        f"- `{PLKF_LABEL}`: PLKF `predict()` + `update(bearing)` with a noisy unit bearing (R_b = 1e-4 I), "
        "vessel 0 circling a target at the origin. Its ratio is to the 2-state filterpy KF above and only "
        "sizes it: it is a 4-state filter with a 2-D measurement.",
        f"- Bank: vessel 0 of a ring of {FLEET_SIZE} vessels on the same circle estimates its {BANK_SIZE} "
        f"neighbours with independent estimators ({PAPER}, the paper's filter; {DEFAULT}, the default, also "
        "cold), each fed its own pair (own noise draws), all started at the same tick (the worst case for "
        f"{DEFAULT}: its pairs' batch solves come close together); one sample is one "
        f"tick, i.e. predict+update of all {BANK_SIZE}. Compared with {BANK_SIZE} filterpy KFs on the same "
        "data.",
        "- Mean iterations: MCKF iterations per update (L_max = 10, tolerance 1e-6); 1 for the other "
        f"pseudo-linear estimators; '-' for {DEFAULT}, whose outcomes count batch solves.",
        "",
        "## Single pair",
        "",
        table,
        "",
        "## Bank of one vessel",
        "",
        bank_table,
        "",
        f"## Fix and tracking phases of {DEFAULT}",
        "",
        "Steps per repeat: updates (single pair) or ticks (bank) in that phase, in one repeat; s of data: "
        f"those steps times dt. Mean us per neighbour: a bank's mean per tick over its {BANK_SIZE} pairs.",
        "",
        phase_table,
        "",
        "## Memory (tracemalloc)",
        "",
        "Peak: the most memory traced at once while building the filters and running all the updates "
        "(the data itself is allocated before tracing starts). Retained: what the live filters hold at the "
        "end.",
        "",
        markdown_table(["filters", "peak KiB", "retained KiB"], memory_rows),
        "",
    ])
    printed = "\n\n".join([table, bank_table, phase_table, summary])
    return document, printed


def run(args: argparse.Namespace) -> int:
    try:
        import filterpy  # noqa: F401  (optional, as in new_filterpy: checked here, before any work)
    except ImportError:
        print("usv-lab bench: needs filterpy (pip install -e '.[test]')", file=sys.stderr)
        return 2
    started = time.perf_counter()
    results = measure(args.seed, args.updates, args.repeats,
                      progress=lambda text: print(f"bench: {text}", file=sys.stderr, flush=True))
    document, printed = render(results, invocation(args), machine_info())
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "benchmark.md"
    path.write_text(document, encoding="utf-8")
    print(printed)
    print(f"\nwrote {path} in {time.perf_counter() - started:.1f} s")
    return 0
