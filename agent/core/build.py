"""A vessel's core as a mission starts it: its parameters and what it knows at deployment."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from agent.config import PositiveFloat, StrictModel
from agent.core.neighbours import NeighbourPrior
from agent.core.params import AgentParams
from agent.core.vessel import VesselAgent


class InitialEstimates(StrictModel):
    """Where the agent starts (a mission's deployment knowledge; the paper's p^_ij,0 and x^_io,0)."""

    target: tuple[float, float, float, float] | None = Field(None, description="x^_io,0 = [p_io; v_io]")
    target_variance: PositiveFloat = Field(1.0, description="P_io,0 = value * I")
    neighbours: dict[str, tuple[float, float]] = Field(default_factory=dict, description="p^_ij,0 by id")
    neighbour_variance: PositiveFloat = Field(0.04, description="P_ij,0 = value * I")
    stamp: float = Field(0.0, description="time (s) the estimates refer to")


def build_core(vessel_id: str, params: AgentParams, initial: InitialEstimates) -> VesselAgent:
    """The vessel's core as a mission starts it; the one place a core is built (agent process, in-process
    runner, replay)."""
    priors = {j: NeighbourPrior(np.array(p), initial.neighbour_variance * np.eye(2), initial.stamp)
              for j, p in initial.neighbours.items()}
    target = None if initial.target is None else np.array(initial.target)
    return VesselAgent(vessel_id, params, target, initial.target_variance * np.eye(4), priors=priors)
