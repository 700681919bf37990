"""What one in-process run costs, by part: the CPU time of the world (`World.step`: the motion and the next
tick's readings), of the agents' ticks (the core `step`, as the runner times each one in its thread) and of
the runner's own bookkeeping around them. A campaign adds what its workers spent beyond the runs (the
process hand-off, `hand_off_lines` in lab/harness/parallel.py)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from lab.harness.runner import RunTrace
from lab.harness.runner import run as run_scenario
from sim_bridge.scenario import Scenario
from sim_bridge.world import World


class TimedWorld(World):
    """A World that adds the CPU time of each `step` (the motion and the next tick's readings) to `seconds`."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.seconds = 0.0

    def step(self, commands) -> None:
        started = time.process_time()
        super().step(commands)
        self.seconds += time.process_time() - started


@dataclass(frozen=True)
class RunCost:
    """CPU seconds (time.process_time) of one run in the process that ran it, by part."""

    whole: float
    world: float
    agents: float

    @property
    def rest(self) -> float:
        """The runner's own work: handing shares round, lost packets, the trace's records."""
        return self.whole - self.world - self.agents


def costed_run(scenario: Scenario, seed: np.random.SeedSequence) -> tuple[RunTrace, RunCost]:
    """One run of `scenario` in this process (lab/harness/runner.py), and what it cost by part."""
    worlds: list[TimedWorld] = []

    def make_world(config, rng) -> TimedWorld:
        worlds.append(TimedWorld(config, rng))
        return worlds[-1]

    started = time.process_time()
    trace = run_scenario(scenario, seed, make_world=make_world)
    whole = time.process_time() - started
    return trace, RunCost(whole, worlds[0].seconds, float(np.nansum(trace.tick_seconds)))
