"""In-process fleet runner: the world and one core (`step` and its state) per vessel in lockstep.

Each tick: the world senses, every live vessel ticks on its readings and on the shares its neighbours sent
at the previous tick (minus the ones `lost_shares` drops), the world applies the commands. Shares keep
their latest value per sender, as the agent process's input gate does. Everything random comes from one
seed, so a run is bit-for-bit repeatable; only the measured compute time differs. The sim bridge with one
agent process per vessel gives the same numbers in lockstep (tests/test_lockstep.py).
"""

from __future__ import annotations

import gc
import math
import time as clock
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agent.core.build import InitialEstimates, initial_state
from agent.core.params import AgentParams
from agent.core.records import Command, Share, TickInputs, TickRecord
from agent.core.state import VesselState
from agent.core.step import step
from mission_log.metrics import RunMetrics, summarise
from sim_bridge.scenario import Scenario, initial_estimates
from sim_bridge.world import Truth, World, WorldConfig, lost_shares, streams


@dataclass
class RunTrace:
    """What a run leaves for metrics and plots; arrays are (ticks, ...) and NaN where a vessel is absent."""

    scenario: str
    seed: int
    vessels: list[str]
    time: np.ndarray            # (K,)
    positions: np.ndarray       # (K, n, 2) true positions
    target: np.ndarray          # (K, 2) true target position
    occluded: np.ndarray        # (K, n) bool: no line of sight to the target
    e_ij: np.ndarray            # (K,)
    e_io: np.ndarray            # (K,)
    e_io_velocity: np.ndarray   # (K,)
    e_c: np.ndarray             # (K,)
    radii: np.ndarray           # (K, n)
    commands: np.ndarray        # (K, n, 2) surge, yaw rate
    estimates: np.ndarray       # (K, n, 4) each vessel's target estimate x^_io
    relative: np.ndarray        # (K, n, n, 2) vessel i's estimate p^_ij of each neighbour j
    tick_seconds: np.ndarray    # (K, n) compute time of each tick
    # (K, n) seconds each vessel's thrust demand has spent beyond its thrusters so far
    # (Truth.thrust_limit_time); NaN without hull dynamics
    thrust_limit: np.ndarray | None = None
    metrics: RunMetrics | None = None


# The collector's first threshold while a run goes on (CPython's default is 700). A large fleet's tick leaves
# thousands of short-lived container objects (its records and shares) alive until the next tick, so with the
# default the young generation was collected every tick or two, survivors promoted, and every few seconds the
# whole heap walked: 8.6 % of a 50-vessel run's CPU. Nothing of a run is cyclic garbage to wait for: the
# records die by reference counting. 10 000 leaves 5 young collections in 5 simulated seconds of 50 vessels.
GC_YOUNG_THRESHOLD = 10_000


# retune(vessel, time, vessels alive, its parameters) -> the parameters it ticks with (lab/harness/mission_plan.py)
Retune = Callable[[str, float, int, AgentParams], AgentParams]


# make_world(world config, the world's random stream) -> the world a run steps (lab/harness/plant_effects.py wraps one)
MakeWorld = Callable[[WorldConfig, np.random.Generator], World]


def run(scenario: Scenario, seed: np.random.SeedSequence | int | None = None,
        retune: Retune | None = None, make_world: MakeWorld = World) -> RunTrace:
    """One run of `scenario`; `seed` defaults to the scenario's own. A vessel that joins later, or one the
    scenario starts cold, starts with no estimates (its target from its first bearing, its neighbours from
    the ranges and shares), as its agent process would. `retune`, if given, gives each live vessel at each
    tick the parameters it ticks with, from those of its previous tick (the scenario's at first): an
    operator's mission commands (lab/harness/mission_plan.py). `make_world` builds the world (a plant with
    lags, a current, compass biases: lab/harness/plant_effects.py)."""
    thresholds = gc.get_threshold()
    gc.set_threshold(max(thresholds[0], GC_YOUNG_THRESHOLD), *thresholds[1:])
    try:
        return _run(scenario, seed, retune, make_world)
    finally:
        gc.set_threshold(*thresholds)


def _run(scenario: Scenario, seed: np.random.SeedSequence | int | None, retune: Retune | None,
         make_world: MakeWorld) -> RunTrace:
    sequence = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(
        scenario.seed if seed is None else seed)
    random = streams(sequence)
    world = make_world(scenario.world, random.world)
    params = scenario.agent_params()
    ids = [v.id for v in scenario.world.vessels]
    index = {v: n for n, v in enumerate(ids)}
    steps = int(round(scenario.duration / scenario.world.dt)) + 1
    trace = _empty_trace(scenario, int(sequence.entropy) if isinstance(sequence.entropy, int) else 0, ids, steps)

    agents: dict[str, VesselState] = {}
    tuned: dict[str, AgentParams] = {}    # each vessel's parameters, when retuned
    inbox: dict[str, dict[str, Share]] = {}
    sent: dict[str, Share] = {}
    for k in range(steps):
        readings = world.sense()
        live = world.live()
        joined = {v for v in live if v not in agents}
        starts = initial_estimates(scenario, world.truth(), random.initial) if k == 0 else {}
        agents.update({i: initial_state(i, params, starts.get(i, InitialEstimates()))
                       for i in live if i not in agents})
        present = set(live)
        for gone in [v for v in agents if v not in present]:
            del agents[gone]
            tuned.pop(gone, None)
            inbox.pop(gone, None)
            for box in inbox.values():
                box.pop(gone, None)
        senders = [j for j in sent if j in agents]
        lost = set(lost_shares(random.loss_seed, senders, live, joined, k, scenario.world.packet_loss))
        truth = world.truth()
        commands: dict[str, Command] = {}
        records: dict[str, TickRecord] = {}
        outgoing: dict[str, Share] = {}
        for i in live:
            box = inbox.setdefault(i, {})
            for j in senders:
                if j != i and (not lost or (j, i) not in lost):
                    box[j] = sent[j]
            reading = readings[i]
            inputs = TickInputs(time=truth.time, odometry=reading.odometry, ranges=reading.ranges,
                                shares=dict(box), bearing=reading.bearing,
                                obstacle_points=reading.obstacle_points)
            # CPU time of this thread: what the tick costs, not what a loaded machine adds while it waits for a core
            if retune is not None:
                tuned[i] = retune(i, truth.time, len(live), tuned.get(i, params))
            started = clock.thread_time()
            agents[i], output = step(params if retune is None else tuned[i], agents[i], inputs)
            trace.tick_seconds[k, index[i]] = clock.thread_time() - started
            commands[i] = output.command
            if output.share is not None:
                outgoing[i] = output.share
            if output.record is not None:
                records[i] = output.record
            trace.occluded[k, index[i]] = reading.occluded
        _record(trace, k, truth, records, commands, index, scenario)
        sent = outgoing
        world.step(commands)
    trace.metrics = summarise(trace.time, trace.e_ij, trace.e_io, trace.e_io_velocity, trace.e_c, trace.radii,
                              params.control.radius, trace.tick_seconds)
    return trace


def _empty_trace(scenario: Scenario, seed: int, ids: list[str], steps: int) -> RunTrace:
    n = len(ids)
    nan = np.full
    return RunTrace(
        scenario=scenario.name, seed=seed, vessels=ids,
        time=np.arange(steps) * scenario.world.dt,
        positions=nan((steps, n, 2), np.nan), target=nan((steps, 2), np.nan),
        occluded=np.zeros((steps, n), dtype=bool),
        e_ij=nan(steps, np.nan), e_io=nan(steps, np.nan), e_io_velocity=nan(steps, np.nan),
        e_c=nan(steps, np.nan), radii=nan((steps, n), np.nan), commands=nan((steps, n, 2), np.nan),
        estimates=nan((steps, n, 4), np.nan), relative=nan((steps, n, n, 2), np.nan),
        tick_seconds=nan((steps, n), np.nan), thrust_limit=nan((steps, n), np.nan),
    )


def _record(trace: RunTrace, k: int, truth: Truth, records: dict[str, TickRecord],
            commands: dict[str, Command], index: dict[str, int], scenario: Scenario) -> None:
    """Tick k's row of the trace. The differences are taken in plain floats (the element-wise operations numpy
    would do) and every length of the tick goes through one np.hypot call: numpy's per-call overhead on
    2-vectors, not the arithmetic, was the cost (n (n - 1) + 3 n calls per tick)."""
    trace.target[k] = truth.target_position
    for i, seconds in truth.thrust_limit_time.items():
        trace.thrust_limit[k, index[i]] = seconds
    tx, ty = truth.target_position.tolist()
    tvx, tvy = truth.target_velocity.tolist()
    where = {i: position.tolist() for i, position in truth.positions.items()}
    xs, ys = [], []                     # p_i - p_o of each vessel, for its radius
    for i, (x, y) in where.items():
        n = index[i]
        trace.positions[k, n] = (x, y)
        xs.append(x - tx)
        ys.append(y - ty)
        if i in commands:
            trace.commands[k, n] = (commands[i].surge, commands[i].yaw_rate)
    pair_x, pair_y, target_x, target_y = [], [], [], []     # e_ij candidates; e_io and e_io_velocity ones
    for i, (x, y) in where.items():
        record = records.get(i)
        if record is None:
            continue
        n = index[i]
        for j, neighbour in record.neighbours.items():
            trace.relative[k, n, index[j]] = neighbour.position
            there = where.get(j)
            if there is not None:
                ex, ey = neighbour.position.tolist()
                pair_x.append(ex - (x - there[0]))
                pair_y.append(ey - (y - there[1]))
        if record.target_state is not None:
            trace.estimates[k, n] = record.target_state
            s0, s1, s2, s3 = record.target_state.tolist()
            vx, vy = truth.velocities[i].tolist()
            target_x += [s0 - (x - tx), s2 - (vx - tvx)]
            target_y += [s1 - (y - ty), s3 - (vy - tvy)]
    lengths = np.hypot(np.array(xs + pair_x + target_x), np.array(ys + pair_y + target_y)).tolist()
    count, pairs = len(xs), len(pair_x)
    trace.radii[k, [index[i] for i in where]] = lengths[:count]
    targets = lengths[count + pairs:]
    worst_ij, worst_io, worst_v = _worst(lengths[count:count + pairs]), _worst(targets[::2]), _worst(targets[1::2])
    for array, value in ((trace.e_ij, worst_ij), (trace.e_io, worst_io), (trace.e_io_velocity, worst_v)):
        array[k] = value if value > -math.inf else np.nan
    centre = np.mean(list(truth.positions.values()), axis=0)
    trace.e_c[k] = float(np.hypot(*(centre - truth.target_position)))


def _worst(values: list[float]) -> float:
    """max(-inf, v, ...) over `values` as Python's max takes them one by one: a NaN never wins."""
    worst = -math.inf
    for value in values:
        worst = max(worst, value)
    return worst
