"""How one agent process runs: its clock, Zenoh session, input ages, log file, initial estimates and parameters."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from agent.config import InlineOrFile, NonNegativeFloat, PositiveFloat, StrictModel
from agent.core.build import InitialEstimates
from agent.core.params import AgentParams
from agent.runtime.mcap_log import LogRotation
from agent.runtime.zenoh_session import ZenohSettings
from agent.shell.wall_clock import SimulatedVesselClock


class NodeSettings(StrictModel):
    """How one agent process runs; `agent` holds the algorithm's parameters (Table I by default), inline or as
    the name of an AgentParams file (relative to this file's folder), the shape of configs/agent.yaml."""

    clock: Literal["wall", "sim"] = Field("wall", description="monotonic 10 Hz timer, or sim/clock ticks")
    zenoh: ZenohSettings = ZenohSettings()
    max_input_age: PositiveFloat = Field(1.0, description="inputs older than this (s) are ignored")
    share_wait: PositiveFloat = Field(2.0, description="sim lockstep: wall seconds to wait for neighbours' shares")
    # 1 only while a fleet still has agents that predate format 2 (docs/contract.md, "Share format").
    share_format: Literal[1, 2] = Field(2, description="2: a share to each neighbour on usv/<id>/share/<j>; "
                                        "1: one to all on usv/<id>/share")
    # ----- robustness: what arrives is bounded, a failed tick is survived (agent/shell/gate.py, failures.py) -----
    max_input_future: PositiveFloat = Field(0.5, description="inputs stamped further ahead of the clock (s) are "
                                            "refused")
    # A token bucket per key; lockstep at 100x real time sends 1000/s.
    max_input_rate: PositiveFloat = Field(
        1000.0, description="messages per second on one key beyond which they are refused before decoding")
    # After it the agent sends heartbeat statuses, judges no stamps, and takes a clock that goes back as a
    # restart of the simulation.
    clock_timeout: PositiveFloat = Field(
        1.0, description="sim: wall seconds without a clock after which the agent takes the clock as silent")
    # Refused unless the clock was silent or `clock_confirm` such clocks in a row continue each other (then
    # the simulation restarted); the sim bridge's clock advances a tick at a time.
    max_clock_jump: PositiveFloat = Field(
        1.0, description="sim: a clock further than this from the last one, either way, is refused (sim s)")
    clock_confirm: int = Field(3, ge=1, description="sim: clocks beyond `max_clock_jump` that continue each "
                               "other and make a restart without a silence")
    rebuild_after: int = Field(
        5, ge=1, description="failed ticks in a row after which the core is rebuilt (with no initial estimates)")
    id_check: NonNegativeFloat = Field(
        1.0, description="seconds to look for another agent with this vessel id at start-up (0: do not look)")
    no_sensor_warning: PositiveFloat = Field(5.0, description="seconds without any own sensor message after "
                                             "which the agent says so on stderr")
    # '{start}' makes a restarted agent start a new file.
    log: str | None = Field(None, description="MCAP file to write; '{vessel}': the vessel id, '{start}': the "
                            "UTC start time")
    # The default keeps about 6 h of an agent's log (docs/reliability.md §3).
    log_rotation: LogRotation | None = Field(
        LogRotation(), description="start a new part of the log by size or time, keep a bounded total; null: "
                                   "one file")
    # So that `usv-log replay --start` can begin mid-mission; one costs about 8 kB compressed with 3
    # neighbours.
    snapshot_every: int = Field(
        50, ge=0, description="log the core's state every this many ticks (0: never)")
    # The sim bridge stamps this vessel's sensors with that clock; on a boat the agent and the driver share
    # the computer's clock.
    vessel_clock: SimulatedVesselClock | None = Field(
        None, description="sea mode only: read the system clock through this vessel's simulated clock; null: "
                          "the system clock")
    initial: InitialEstimates = InitialEstimates()
    agent: Annotated[AgentParams, InlineOrFile(AgentParams)] = Field(
        AgentParams(), description="the algorithm's parameters: an AgentParams file's content, or its name")
