"""How one agent process runs: its clock, Zenoh session, input ages, log file, initial estimates and parameters."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from agent.config import PositiveFloat, StrictModel
from agent.core.build import InitialEstimates
from agent.core.params import AgentParams
from agent.runtime.zenoh_session import ZenohSettings


class NodeSettings(StrictModel):
    """How one agent process runs; `agent` holds the algorithm's parameters (Table I by default)."""

    clock: Literal["wall", "sim"] = Field("wall", description="monotonic 10 Hz timer, or sim/clock ticks")
    zenoh: ZenohSettings = ZenohSettings()
    max_input_age: PositiveFloat = Field(1.0, description="inputs older than this (s) are ignored")
    share_wait: PositiveFloat = Field(2.0, description="sim lockstep: wall seconds to wait for neighbours' shares")
    log: str | None = Field(None, description="MCAP file to write; '{vessel}' is replaced by the vessel id and "
                            "'{start}' by the UTC start time (so a restarted agent starts a new file)")
    snapshot_every: int = Field(
        50, ge=0, description="log the core's state every this many ticks (0: never), so that `usv-log replay "
                              "--start` can begin mid-mission; one costs about 8 kB compressed with 3 neighbours")
    initial: InitialEstimates = InitialEstimates()
    agent: AgentParams = AgentParams()
