"""In-process fleet runner: the world and one `VesselAgent` per vessel in lockstep.

Each tick: the world senses, every live vessel ticks on its readings and on the shares its neighbours sent
at the previous tick (minus the ones the packet-loss rule drops), the world applies the commands. Shares
keep their latest value per sender, as a Zenoh subscriber with a one-slot ring would. Everything random
comes from one seed, so a run is bit-for-bit repeatable; only the measured compute time differs.
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
from sim_bridge.world import Truth, World, message_lost


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
    tick_seconds: np.ndarray    # (K, n) compute time of each tick
    metrics: RunMetrics | None = None


def initial_estimates(scenario: Scenario, truth: Truth, present: list[str], rng: np.random.Generator,
                      vessels: list[str]) -> dict[str, tuple[np.ndarray, dict[str, NeighbourPrior]]]:
    """First estimates drawn around the truth as in Sec. VI: x^_io,0 ~ N(x_io,0, P_io,0) for each of
    `vessels`, and p^_ij,0 ~ N(p_ij,0, P_ij,0) for the vessels there from the start."""
    p_ij, p_io = scenario.initial.neighbour_covariance, scenario.initial.target_covariance
    estimates = {}
    for i in vessels:
        x_io = np.concatenate([truth.positions[i] - truth.target_position,
                               truth.velocities[i] - truth.target_velocity])
        target = x_io + rng.normal(0.0, math.sqrt(p_io), 4)
        priors = {}
        if truth.time == 0.0:  # the paper's initial estimates exist for the vessels there from the start
            for j in present:
                if j != i:
                    true = truth.positions[i] - truth.positions[j]
                    priors[j] = NeighbourPrior(true + rng.normal(0.0, math.sqrt(p_ij), 2), p_ij * np.eye(2),
                                               truth.time)
        estimates[i] = (target, priors)
    return estimates


def initial_agents(scenario: Scenario, world: World, rng: np.random.Generator, params, vessels) -> dict:
    """Agents for `vessels`, started from `initial_estimates`."""
    estimates = initial_estimates(scenario, world.truth(), world.live(), rng, vessels)
    p_io = scenario.initial.target_covariance
    return {i: VesselAgent(i, params, target, p_io * np.eye(4), priors=priors)
            for i, (target, priors) in estimates.items()}


def run(scenario: Scenario, seed: np.random.SeedSequence | int | None = None) -> RunTrace:
    """One run of `scenario`; `seed` defaults to the scenario's own."""
    sequence = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(
        scenario.seed if seed is None else seed)
    world_rng, init_rng = (np.random.default_rng(s) for s in sequence.spawn(2))
    loss_seed = int(sequence.generate_state(1)[0])
    world = World(scenario.world, world_rng)
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
        new = [v for v in live if v not in agents]
        if new:
            agents.update(initial_agents(scenario, world, init_rng, params, new))
        for gone in [v for v in agents if v not in live]:
            del agents[gone]
            inbox.pop(gone, None)
        truth = world.truth()
        commands: dict[str, Command] = {}
        records: dict[str, TickRecord] = {}
        outgoing: dict[str, Share] = {}
        for i in live:
            box = inbox.setdefault(i, {})
            for j, share in sent.items():
                if j != i and j in agents and not message_lost(loss_seed, j, i, k, scenario.world.packet_loss):
                    box[j] = share
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
        estimates=nan((steps, n, 4), np.nan), tick_seconds=nan((steps, n), np.nan),
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
