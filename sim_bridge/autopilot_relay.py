"""The sim bridge's side of a fleet driven through MAVLink (`usv-fleet run --vehicle mavlink`): its keys and rule.

The sim bridge owns the world; each vessel's ArduPilot stand-in (`usv-ardupilot-standin --sim`) relays it:
- `sim/autopilot/<id>/pose`: the vessel's odometry reading of each tick (the Odometry the bridge would
  have given the agent), which the stand-in turns into ATTITUDE and LOCAL_POSITION_NED for the driver;
- `sim/autopilot/<id>/drive` (`Drive`): what the stand-in drives the hull at, (u, r), after its own rules
  (GUIDED, armed, GUID_TIMEOUT, HOLD), with the set point it last took; the bridge steps the world on it.
In lockstep a tick waits until the stand-in drives the agent's command of that tick (`drives_command`): the
set point on the wire is float32, so the command is compared as float32. Keys under `sim/`, which no agent
reads (an agent reads `sim/clock` only). More: docs/boats.md, "A fleet through MAVLink".
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import Field

from agent.config import StrictModel
from agent.contract import MAX_SPEED, Cmd

PREFIX = "sim/autopilot"
DRIVE_ALL = f"{PREFIX}/*/drive"

Speed = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_SPEED, le=MAX_SPEED)]


def pose_key(vessel: str) -> str:
    return f"{PREFIX}/{vessel}/pose"


def drive_key(vessel: str) -> str:
    return f"{PREFIX}/{vessel}/drive"


class Drive(StrictModel):
    stamp_ns: int = Field(ge=0, description="sim time of the last pose the stand-in had (ns)")
    sender: str = Field(min_length=1, max_length=64, description="the vessel")
    setpoint: tuple[Speed, Speed] | None = Field(description="the last set point taken: surge (m/s), yaw rate "
                                                 "(rad/s, counter-clockwise), as on the wire")
    drive: tuple[Speed, Speed] = Field(description="what the hull is driven at now: surge, yaw rate")
    mode: str = Field(max_length=16, description="the autopilot's mode: MANUAL, HOLD or GUIDED")
    armed: bool


def as_sent(command: Cmd) -> tuple[float, float]:
    """The agent's (u, r) as the stand-in reads it from the set point: float32 on the wire."""
    return float(np.float32(command.surge)), float(np.float32(command.yaw_rate))


def drives_command(drive: Drive | None, command: Cmd) -> bool:
    """The stand-in took `command` as its set point and drives the hull at it (GUIDED and armed)."""
    if drive is None or drive.setpoint is None:
        return False
    return tuple(drive.setpoint) == as_sent(command) and tuple(drive.drive) == tuple(drive.setpoint)
