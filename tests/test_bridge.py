"""The sim bridge and agent processes' shells over Zenoh on loopback (in one test process, threads)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from agent.runtime.mcap_log import read_messages
from agent.runtime.zenoh_session import ZenohSettings
from agent.shell.node import AgentNode
from agent.shell.settings import NodeSettings
from sim_bridge.bridge import BridgeSettings, SimBridge
from sim_bridge.fleet import AGENT_LISTEN, free_port
from sim_bridge.scenario import Scenario

pytestmark = pytest.mark.slow   # Zenoh sessions on loopback, in real time


def two_vessel_scenario(duration: float = 4.0) -> Scenario:
    return Scenario.model_validate({
        "name": "pair", "duration": duration, "seed": 3,
        "world": {"vessels": [{"id": "1", "position": [-6.0, -2.0]}, {"id": "2", "position": [5.0, 4.0]}],
                  "target": {"kind": "constant_velocity", "position": [0.0, 0.0], "velocity": [0.2, 0.0]}},
    })


def start_agent(vessel: str, bridge_port: int) -> tuple[AgentNode, threading.Thread]:
    # As the launcher does: the agent listens on port 0 (the OS picks as it binds), so it races nobody.
    settings = NodeSettings(clock="sim", zenoh=ZenohSettings(listen=[AGENT_LISTEN],
                                                             connect=[f"tcp/127.0.0.1:{bridge_port}"]))
    node = AgentNode(vessel, settings)
    thread = threading.Thread(target=node.run, daemon=True)
    thread.start()
    return node, thread


def test_lockstep_run_every_agent_answers_every_tick(tmp_path):
    port = free_port()
    scenario = two_vessel_scenario()
    bridge = SimBridge(scenario, BridgeSettings(zenoh=ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"]),
                                                log=str(tmp_path / "truth.mcap")))
    runner = threading.Thread(target=bridge.run, daemon=True)
    runner.start()
    agents = [start_agent(v, port) for v in ("1", "2")]
    runner.join(timeout=60)
    for node, thread in agents:
        node.stopping.set()
        thread.join(timeout=10)
    assert not runner.is_alive()
    assert bridge.ticks == 41 and bridge.missed_commands == 0 and bridge.watchdog_stops == 0
    assert all(node.ticks >= 40 for node, _ in agents)
    truth = [m for topic, _, m in read_messages(tmp_path / "truth.mcap") if topic == "/truth"]
    assert len(truth) == 41
    moved = np.linalg.norm(np.subtract(truth[-1]["vessels"]["1"]["position"], truth[0]["vessels"]["1"]["position"]))
    assert moved > 0.5  # the vessel followed its agent's commands
    # the two agents heard each other: each shared what it knew of the other
    assert all(node.gate.accepted["share"] > 30 for node, _ in agents)


def test_watchdog_stops_a_vessel_whose_agent_is_silent():
    port = free_port()
    settings = BridgeSettings(zenoh=ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"]), startup_timeout=1.0,
                              command_timeout=0.2)
    bridge = SimBridge(two_vessel_scenario(duration=1.0), settings)
    start = bridge.world.truth().positions["2"].copy()
    runner = threading.Thread(target=bridge.run, daemon=True)
    runner.start()
    node, thread = start_agent("1", port)       # nobody drives vessel 2
    runner.join(timeout=30)
    node.stopping.set()
    thread.join(timeout=10)
    assert bridge.ticks == 11
    assert bridge.watchdog_stops >= 11           # vessel 2 stopped at every tick
    assert bridge.startup_missing == {"2"}        # and the bridge says which agent never came
    np.testing.assert_array_equal(bridge.world.truth().positions["2"], start)
