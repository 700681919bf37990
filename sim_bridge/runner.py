"""In-process fleet runner: the world and one `VesselAgent` per vessel in lockstep.

Each tick: the world senses, every live vessel ticks on its readings and on the shares its neighbours sent
at the previous tick (minus the ones `lost_shares` drops), the world applies the commands. Shares keep
their latest value per sender, as the agent process's input gate does. Everything random comes from one
seed, so a run is bit-for-bit repeatable; only the measured compute time differs. The sim bridge with one
agent process per vessel gives the same numbers in lockstep (tests/test_lockstep.py).
"""

from __future__ import annotations

import math
import time as clock
from dataclasses import dataclass

import numpy as np

from agent.neighbours import NeighbourPrior
from agent.tick_io import Command, Share, TickInputs
from agent.vessel import TickRecord, VesselAgent
from sim_bridge.metrics import RunMetrics, summarise
from sim_bridge.scenario import Scenario
from sim_bridge.world import Truth, World, lost_shares


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
    metrics: RunMetrics | None = None


def initial_estimates(scenario: Scenario, truth: Truth, rng: np.random.Generator
                      ) -> dict[str, tuple[np.ndarray, dict[str, NeighbourPrior]]]:
    """The deployment knowledge of the vessels there at the start (`truth` at time 0), drawn around the
    truth as in Sec. VI: x^_io,0 ~ N(x_io,0, P_io,0) for each, and p^_ij,0 ~ N(p_ij,0, P_ij,0) for each pair."""
    p_ij, p_io = scenario.initial.neighbour_covariance, scenario.initial.target_covariance
    estimates = {}
    for i in truth.positions:
        x_io = np.concatenate([truth.positions[i] - truth.target_position,
                               truth.velocities[i] - truth.target_velocity])
        target = x_io + rng.normal(0.0, math.sqrt(p_io), 4)
        priors = {}
        for j in truth.positions:
            if j != i:
                true = truth.positions[i] - truth.positions[j]
                priors[j] = NeighbourPrior(true + rng.normal(0.0, math.sqrt(p_ij), 2), p_ij * np.eye(2),
                                           truth.time)
        estimates[i] = (target, priors)
    return estimates


def initial_agents(scenario: Scenario, world: World, rng: np.random.Generator, params) -> dict:
    """Agents for the vessels there at the start, started from `initial_estimates`."""
    p_io = scenario.initial.target_covariance
    return {i: VesselAgent(i, params, target, p_io * np.eye(4), priors=priors)
            for i, (target, priors) in initial_estimates(scenario, world.truth(), rng).items()}


@dataclass(frozen=True)
class Streams:
    """The random streams of one run, all from its seed: the world's, the initial estimates', and the key
    of the packet-loss hash. The sim bridge and the fleet launcher derive them the same way."""

    world: np.random.Generator
    initial: np.random.Generator
    loss_seed: int


def streams(seed: np.random.SeedSequence | int) -> Streams:
    sequence = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    world_seed, initial_seed = sequence.spawn(2)
    return Streams(np.random.default_rng(world_seed), np.random.default_rng(initial_seed),
                   int(sequence.generate_state(1)[0]))


def run(scenario: Scenario, seed: np.random.SeedSequence | int | None = None) -> RunTrace:
    """One run of `scenario`; `seed` defaults to the scenario's own. A vessel that joins later starts with
    no estimates (its target from its first bearing, its neighbours from the shares), as its agent process
    would."""
    sequence = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(
        scenario.seed if seed is None else seed)
    random = streams(sequence)
    world = World(scenario.world, random.world)
    params = scenario.agent_params()
    ids = [v.id for v in scenario.world.vessels]
    index = {v: n for n, v in enumerate(ids)}
    steps = int(round(scenario.duration / scenario.world.dt)) + 1
    trace = _empty_trace(scenario, int(sequence.entropy) if isinstance(sequence.entropy, int) else 0, ids, steps)

    agents: dict[str, VesselAgent] = {}
    inbox: dict[str, dict[str, Share]] = {}
    sent: dict[str, Share] = {}
    for k in range(steps):
        readings = world.sense()
        live = world.live()
        joined = {v for v in live if v not in agents}
        if k == 0:
            agents.update(initial_agents(scenario, world, random.initial, params))
        else:
            agents.update({i: VesselAgent(i, params) for i in joined})
        for gone in [v for v in agents if v not in live]:
            del agents[gone]
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
                if j != i and (j, i) not in lost:
                    box[j] = sent[j]
            reading = readings[i]
            inputs = TickInputs(time=truth.time, odometry=reading.odometry, ranges=reading.ranges,
                                shares=dict(box), bearing=reading.bearing,
                                obstacle_points=reading.obstacle_points)
            started = clock.perf_counter()
            output = agents[i].tick(inputs)
            trace.tick_seconds[k, index[i]] = clock.perf_counter() - started
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
        tick_seconds=nan((steps, n), np.nan),
    )


def _record(trace: RunTrace, k: int, truth: Truth, records: dict[str, TickRecord],
            commands: dict[str, Command], index: dict[str, int], scenario: Scenario) -> None:
    trace.target[k] = truth.target_position
    worst_ij = worst_io = worst_v = -math.inf
    for i, position in truth.positions.items():
        n = index[i]
        trace.positions[k, n] = position
        trace.radii[k, n] = float(np.hypot(*(position - truth.target_position)))
        if i in commands:
            trace.commands[k, n] = (commands[i].surge, commands[i].yaw_rate)
        record = records.get(i)
        if record is None:
            continue
        for j, neighbour in record.neighbours.items():
            trace.relative[k, n, index[j]] = neighbour.position
            if j in truth.positions:
                error = neighbour.position - (position - truth.positions[j])
                worst_ij = max(worst_ij, float(np.hypot(*error)))
        if record.target_state is not None:
            trace.estimates[k, n] = record.target_state
            worst_io = max(worst_io, float(np.hypot(*(record.target_state[:2] - (position - truth.target_position)))))
            relative_velocity = truth.velocities[i] - truth.target_velocity
            worst_v = max(worst_v, float(np.hypot(*(record.target_state[2:] - relative_velocity))))
    for array, value in ((trace.e_ij, worst_ij), (trace.e_io, worst_io), (trace.e_io_velocity, worst_v)):
        array[k] = value if value > -math.inf else np.nan
    centre = np.mean(list(truth.positions.values()), axis=0)
    trace.e_c[k] = float(np.hypot(*(centre - truth.target_position)))
