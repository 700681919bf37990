"""The Zenoh session settings every process of the fleet shares (agents, bridges, launcher, operator tools)."""

from __future__ import annotations

import json
import os
from typing import Literal

import zenoh
from pydantic import Field

from agent.config import PositiveFloat, StrictModel


class ZenohSettings(StrictModel):
    mode: Literal["peer", "client"] = "peer"
    connect: list[str] = Field(default_factory=list, description="endpoints to connect to, e.g. tcp/10.0.0.2:7447")
    listen: list[str] = Field(default_factory=list, description="endpoints to listen on, e.g. tcp/0.0.0.0:7447")
    multicast_scouting: bool = Field(False, description="off by default: explicit endpoints only")
    connect_timeout: PositiveFloat = Field(
        30.0, description="client: seconds to keep trying to reach the router at start-up (a boat's agent may "
                          "boot before the shore router is up); then it exits and its service restarts it")


def zenoh_config(settings: ZenohSettings):
    """A zenoh.Config from our settings; ZENOH_CONFIG (a json5 file) takes precedence when set."""

    path = os.environ.get("ZENOH_CONFIG")
    if path:
        return zenoh.Config.from_file(path)
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(settings.mode))
    config.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    if settings.connect:
        config.insert_json5("connect/endpoints", json.dumps(settings.connect))
    if settings.listen:
        config.insert_json5("listen/endpoints", json.dumps(settings.listen))
    if settings.mode == "client":
        config.insert_json5("connect/timeout_ms", json.dumps(int(settings.connect_timeout * 1000)))
    return config
