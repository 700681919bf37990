"""The sim bridge: how it judges commands (no Zenoh), and the bridge and agent shells over Zenoh on loopback (in
one test process, threads; slow)."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from agent.contract import Cmd, Status, encode, key, nanoseconds
from agent.core.records import STOP, Command
from agent.runtime.mcap_log import read_messages
from agent.runtime.zenoh_session import ZenohSettings
from agent.shell.node import AgentNode
from agent.shell.settings import NodeSettings
from sim_bridge.bridge import BridgeSettings, SimBridge
from sim_bridge.fleet import AGENT_LISTEN, free_port
from sim_bridge.scenario import Scenario, select_scenario

SEA_TRIAL = Path(__file__).resolve().parents[1] / "configs" / "scenarios" / "sea_trial.yaml"


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


def sample(vessel: str, topic: str, message) -> SimpleNamespace:
    """What a Zenoh subscriber hands the bridge's callbacks."""
    return SimpleNamespace(key_expr=key(vessel, topic), payload=SimpleNamespace(to_bytes=lambda: encode(message)))


def command(vessel: str, stamp_ns: int, seq: int = 0, surge: float = 1.0) -> SimpleNamespace:
    return sample(vessel, "cmd", Cmd(stamp_ns=stamp_ns, seq=seq, sender=vessel, surge=surge, yaw_rate=0.0))


def advance_to(bridge: SimBridge, seconds: float) -> None:
    while bridge.world.time < seconds - 1e-9:
        bridge.world.step({v: STOP for v in bridge.world.live()})


def test_a_command_is_fresh_by_when_it_arrived_not_by_the_stamp_its_agent_wrote():
    bridge = SimBridge(two_vessel_scenario(), BridgeSettings())    # watchdog 0.5 s of the bridge's sim time
    advance_to(bridge, 0.3)
    bridge._on_command(command("1", stamp_ns=0))                   # stamped 0 s, arrives at 0.3 s
    advance_to(bridge, 0.7)
    # 0.7 - 0.3 = 0.4 s since it arrived: applied (by its stamp it would be 0.7 s old, and stopped).
    assert bridge._commands_now(bridge.world.time) == {"1": Command(1.0, 0.0), "2": STOP}
    assert bridge.watchdog_stops == 1                               # vessel 2 has never had a command
    advance_to(bridge, 0.9)
    assert bridge._commands_now(bridge.world.time)["1"] == STOP    # 0.6 s since it arrived
    assert bridge.watchdog_stops == 3


def test_a_command_with_an_absurd_stamp_is_refused_and_counted():
    bridge = SimBridge(two_vessel_scenario(), BridgeSettings())    # max_command_skew 1 s
    advance_to(bridge, 2.0)
    bridge._on_command(command("1", stamp_ns=nanoseconds(2.0), seq=0))
    for seq, stamp in enumerate((2**62, nanoseconds(3.5), nanoseconds(0.5)), start=1):   # ahead, ahead, behind
        bridge._on_command(command("1", stamp_ns=stamp, seq=seq, surge=2.0))
    assert (bridge.refused_stamps, bridge.rejected) == (3, 3)
    assert bridge.commands["1"].stamp_ns == nanoseconds(2.0)        # the honest one is still the latest
    advance_to(bridge, 2.6)                                         # and it goes stale: the vessel stops
    assert bridge._commands_now(bridge.world.time)["1"] == STOP
    # A status may come from the past (a joiner's heartbeat is stamped 0 before its first clock), not ahead.
    bridge._on_status(sample("2", "status", Status(stamp_ns=0, seq=0, sender="2", phase=0.0, command=(0, 0))))
    bridge._on_status(sample("2", "status", Status(stamp_ns=2**62, seq=1, sender="2", phase=0.0, command=(0, 0))))
    assert bridge.statuses["2"].stamp_ns == 0 and bridge.refused_stamps == 4


def test_in_the_sea_mode_command_stamps_are_judged_by_the_wall_clock():
    _, scenario = select_scenario(SEA_TRIAL, "sea")
    bridge = SimBridge(scenario, BridgeSettings(mode="realtime"))
    bridge._on_command(command("1", stamp_ns=time.time_ns()))
    bridge._on_command(command("2", stamp_ns=nanoseconds(0.1)))    # a sim stamp is 56 years behind the wall
    assert "1" in bridge.commands and "2" not in bridge.commands and bridge.refused_stamps == 1
    assert bridge._commands_now(time.monotonic())["1"] == Command(1.0, 0.0)
    assert bridge._commands_now(time.monotonic() + 0.6)["1"] == STOP   # 0.6 s of wall time after it arrived


@pytest.mark.slow   # Zenoh sessions on loopback, in real time
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


@pytest.mark.slow   # Zenoh sessions on loopback, in real time
def test_watchdog_stops_a_vessel_whose_agent_is_silent():
    port = free_port()
    # 5 s for the agent of vessel 1 to come up (it first looks for another agent with its id, `id_check`).
    settings = BridgeSettings(zenoh=ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"]), startup_timeout=5.0,
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


class TimedSession:
    """A stand-in Zenoh session whose publishers note (key, monotonic time) of each put."""

    def __init__(self) -> None:
        self.puts: list[tuple[str, float]] = []

    def declare_publisher(self, key_expr: str, **_):
        return SimpleNamespace(put=lambda payload: self.puts.append((key_expr, time.monotonic())))


def four_vessel_scenario(duration: float) -> Scenario:
    return Scenario.model_validate({
        "name": "four", "duration": duration, "seed": 3,
        "world": {"vessels": [{"id": str(v), "position": [3.0 * v, 1.0]} for v in range(1, 5)],
                  "target": {"kind": "constant_velocity", "position": [0.0, 0.0], "velocity": [0.0, 0.0]}},
    })


def timed_ticks(stagger: float, ticks: int = 3) -> tuple[SimBridge, list[tuple[str, float]], float]:
    """The real-time bridge's first `ticks` ticks on a TimedSession (no agents: their readiness is not waited
    for); (bridge, the puts, the monotonic time of tick 0)."""
    bridge = SimBridge(four_vessel_scenario(duration=ticks * 0.1), BridgeSettings(mode="realtime",
                                                                                      stagger=stagger))
    bridge._wait_for_agents = lambda vessels: None
    session = TimedSession()
    start, _ = bridge._run_ticks(session, ticks)
    return bridge, session.puts, start


def test_in_real_time_each_vessels_sensors_come_in_its_own_slot_after_the_clock():
    """12 agents woken by one clock queued for 2 cores (sensor-to-command p99 42 ms): the bridge spreads the
    vessels' sensors over `stagger` of dt, the clock first, and times each vessel's latency from its own."""
    bridge, puts, start = timed_ticks(stagger=0.5)
    dt, vessels = 0.1, ["1", "2", "3", "4"]
    ticks = [[]]
    for put in puts:
        if put[0] == "sim/truth":
            ticks.append([])
        else:
            ticks[-1].append(put)
    assert bridge.ticks == 3 and len(ticks) == 4 and ticks[-1] == []
    for k, tick in enumerate(ticks[:3]):
        assert tick[0][0] == "sim/clock"
        sensors = tick[1:]
        assert [name for name, _ in sensors] == [f"usv/{v}/sensor/{topic}" for v in vessels
                                                 for topic in ("odom", "uwb", "bearing", "sonar")]
        for m, vessel in enumerate(vessels):
            first = sensors[4 * m][1]
            # not before its slot, (m + 1/2) x 0.5 dt / 4 into the tick, nor (on a machine not stalled) after
            # half of dt
            assert start + k * dt + (m + 0.5) * dt * 0.5 / 4 <= first < start + k * dt + 0.5 * dt
    # The latency runs from the vessel's own sensors: the last slot's command 1 ms after them takes 1 ms.
    last = bridge._sent["4"]
    bridge._sent["4"] = time.monotonic() - 0.001
    bridge._on_command(command("4", stamp_ns=bridge._tick_stamp))
    assert 0.001 <= bridge._latency["4"] < 0.001 + (time.monotonic() - last)


def test_with_no_stagger_every_vessels_sensors_go_at_once_before_the_clock():
    _, puts, _ = timed_ticks(stagger=0.0, ticks=1)
    names = [name for name, _ in puts]
    assert names.index("sim/clock") == 16 and all(name.startswith("usv/") for name in names[:16])
    assert puts[15][1] - puts[0][1] < 0.02


def test_a_stagger_beyond_half_of_dt_is_refused():
    with pytest.raises(ValueError, match="stagger"):
        BridgeSettings(stagger=0.6)
