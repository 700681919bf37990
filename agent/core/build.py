"""A vessel's core as a mission starts it: the one place its starting state is built (agent process,
in-process runner, replay), from its parameters and what it knows at deployment."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from agent.config import PositiveFloat, StrictModel
from agent.core.neighbours import History, NeighbourPrior
from agent.core.params import AgentParams
from agent.core.state import Health, OwnMotion, VesselState
from agent.core.target import target_filter


class InitialEstimates(StrictModel):
    """Where the agent starts (a mission's deployment knowledge; the paper's p^_ij,0 and x^_io,0)."""

    target: tuple[float, float, float, float] | None = Field(None, description="x^_io,0 = [p_io; v_io]")
    target_variance: PositiveFloat = Field(1.0, description="P_io,0 = value * I")
    neighbours: dict[str, tuple[float, float]] = Field(default_factory=dict, description="p^_ij,0 by id")
    neighbour_variance: PositiveFloat = Field(0.04, description="P_ij,0 = value * I")
    # null: the estimates are what the agent is told at launch, taken at its first tick.
    stamp: float | None = Field(0.0, description="time the estimates refer to, in the fleet's clock (s); "
                                                   "null: the first tick")


def initial_state(vessel_id: str, params: AgentParams, initial: InitialEstimates) -> VesselState:
    """The state a vessel's core starts from: what it knows at deployment (`initial`, which may be empty:
    then the target filter starts from the first bearing and the pair filters from the shares)."""
    priors = {j: NeighbourPrior(np.array(p), initial.neighbour_variance * np.eye(2), initial.stamp)
              for j, p in initial.neighbours.items()}
    tracker = None
    if initial.target is not None:
        tracker = target_filter(params.target, np.array(initial.target), initial.target_variance * np.eye(4),
                                params.dt)
    return VesselState(vessel=vessel_id, own=History(params.fleet.history_ticks), motion=OwnMotion(), tracks={},
                       priors=priors, tracker=tracker, phase=None, health=Health())
