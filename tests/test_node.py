"""The agent process over Zenoh on loopback: it ticks on sim time, answers, refuses bad input, stops cleanly."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import warnings

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from conftest import wait_until  # noqa: E402

from agent.contract import Bearing, Clock, Cmd, Odometry, Ranges, Status, decode, encode, key  # noqa: E402
from agent.core.build import InitialEstimates, initial_state
from agent.runtime.mcap_log import read_messages
from agent.runtime.zenoh_session import ZenohSettings
from agent.shell.node import AgentNode
from agent.shell.settings import NodeSettings
from sim_bridge.fleet import free_port  # noqa: E402


def test_node_ticks_on_sim_time_and_answers_each_tick(tmp_path):
    port = free_port()
    settings = NodeSettings(clock="sim", zenoh=ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"]),
                            log=str(tmp_path / "agent-{vessel}.mcap"))
    node = AgentNode("1", settings, initial_state("1", settings.agent, InitialEstimates(target=(5.0, 0.0, 0.0, 0.0))))
    thread = threading.Thread(target=node.run, kwargs={"max_ticks": 20}, daemon=True)
    thread.start()

    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    commands, statuses = [], []
    with zenoh.open(config) as session:
        session.declare_subscriber(key("1", "cmd"), lambda s: commands.append(decode(Cmd, s.payload.to_bytes())[0]))
        session.declare_subscriber(key("1", "status"),
                                   lambda s: statuses.append(decode(Status, s.payload.to_bytes())[0]))
        # The agent's heartbeat status before its first tick says the link is up both ways.
        assert wait_until(lambda: statuses, timeout=20)
        session.put(key("1", "sensor/odom"), b"this is not json")
        for k in range(20):
            stamp = int(k * 0.1 * 1e9)
            session.put(key("1", "sensor/odom"), encode(Odometry(
                stamp_ns=stamp, seq=k, sender="1", position=(0.05 * k, 0.0), heading=0.0)))
            session.put(key("1", "sensor/uwb"), encode(Ranges(stamp_ns=stamp, seq=k, sender="1", ranges={})))
            session.put(key("1", "sensor/bearing"), encode(Bearing(stamp_ns=stamp, seq=k, sender="1",
                                                                   bearing=(1.0, 0.0))))
            # The tick's sensors are in before its clock, and each tick is answered before the next.
            assert wait_until(lambda: node.gate.accepted["sensor/bearing"] == k + 1)
            session.put("sim/clock", encode(Clock(stamp_ns=stamp, seq=k)))
            assert wait_until(lambda: len(commands) == k + 1)
        thread.join(timeout=10)
    assert not thread.is_alive()
    assert node.ticks == 20
    assert len(commands) == 20 and all(c is not None for c in commands)
    assert all(np.isfinite(c.surge) and np.isfinite(c.yaw_rate) for c in commands)
    assert [c.seq for c in commands] == sorted(c.seq for c in commands)
    assert statuses[-1].health.get("rejected_malformed") == 1
    assert node.gate.accepted["sensor/odom"] == 20
    logged = list(read_messages(tmp_path / "agent-1.mcap"))   # finished cleanly: no warning
    topics = [topic for topic, _, _ in logged]
    assert topics.count("usv/1/cmd") == 20 and topics.count("/1/estimates") == 20
    assert [t for topic, t, _ in logged if topic == "usv/1/cmd"] == [int(k * 0.1 * 1e9) for k in range(20)]


def test_agent_process_stops_cleanly_on_sigterm(tmp_path):
    config = tmp_path / "node.yaml"
    port = free_port()
    config.write_text(f"clock: wall\nzenoh:\n  listen: [tcp/127.0.0.1:{port}]\n")
    process = subprocess.Popen([sys.executable, "-m", "agent", "--vessel", "7", "--config", str(config)],
                               stderr=subprocess.PIPE, text=True)
    statuses = []
    session_config = zenoh.Config()
    session_config.insert_json5("scouting/multicast/enabled", "false")
    session_config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    with zenoh.open(session_config) as session:
        session.declare_subscriber(key("7", "status"), lambda s: statuses.append(s))
        # Ticking on its wall timer: without sensors it commands STOP, and says so every tick.
        assert wait_until(lambda: len(statuses) >= 5 or process.poll() is not None, timeout=30)
    assert process.poll() is None and len(statuses) >= 5
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=10)
    assert process.returncode == 0, err
    assert "usv-agent 7: stopped after" in err


def test_a_bad_vessel_id_or_config_is_a_clear_error(tmp_path):
    bad = subprocess.run([sys.executable, "-m", "agent", "--vessel", "no spaces"], capture_output=True, text=True)
    assert bad.returncode == 2 and "invalid --vessel" in bad.stderr
    config = tmp_path / "node.yaml"
    config.write_text("clock: sundial\n")
    bad = subprocess.run([sys.executable, "-m", "agent", "--vessel", "1", "--config", str(config)],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "field 'clock'" in bad.stderr and "node.yaml" in bad.stderr


def test_a_failing_log_does_not_stop_the_ticks(tmp_path):
    settings = NodeSettings(clock="sim", log=str(tmp_path / "x.mcap"))
    node = AgentNode("1", settings, initial_state("1", settings.agent, InitialEstimates(target=(5.0, 0.0, 0.0, 0.0))))
    node.recorder.open()

    class Sink:
        def __init__(self):
            self.payloads = []

        def put(self, payload):
            self.payloads.append(payload)

    def broken(*args, **kwargs):
        raise OSError("disk full")

    node.recorder.log.log = broken
    publishers = {"cmd": Sink(), "share": Sink(), "status": Sink()}
    for _ in range(3):
        node._tick(publishers)
    assert node.ticks == 3 and node.recorder.errors == 3 and len(publishers["cmd"].payloads) == 3
    status = decode(Status, publishers["status"].payloads[-1])[0]
    assert status.health["log_errors"] == 2  # counted before this tick's own attempt


def test_an_exception_in_the_core_is_survived_and_logged_with_its_inputs(tmp_path, monkeypatch, capsys):
    """The core raising on its third tick costs that tick only: it commands STOP, is counted and told once,
    its inputs go to the log's `errors` topic, and the run goes on to its end with a finished file."""
    import agent.shell.node as node_module

    real_decide = node_module.decide
    calls = []

    def failing_decide(params, state, inputs):
        calls.append(inputs.time)
        if len(calls) == 3:
            raise RuntimeError("the core failed")
        return real_decide(params, state, inputs)

    monkeypatch.setattr(node_module, "decide", failing_decide)
    node = AgentNode("1", NodeSettings(clock="wall", id_check=0, log=str(tmp_path / "agent-{vessel}.mcap")))
    node.run(max_ticks=10)
    assert len(calls) == 10 and node.ticks == 10 and node.failures.total == 1 and node.failures.rebuilds == 0
    err = capsys.readouterr().err
    assert err.count("failed (RuntimeError@") == 1 and "commanding STOP" in err
    with warnings.catch_warnings():
        warnings.simplefilter("error")           # an unfinished file would warn
        logged = list(read_messages(tmp_path / "agent-1.mcap"))
    assert [topic for topic, _, _ in logged].count("usv/1/cmd") == 10
    errors = [message for topic, _, message in logged if topic == "/1/errors"]
    assert len(errors) == 1 and errors[0]["message"] == "RuntimeError: the core failed"
    assert errors[0]["inputs"]["time"] == pytest.approx(calls[2]) and errors[0]["count"] == 1
    statuses = [message for topic, _, message in logged if topic == "usv/1/status"]
    assert statuses[-1]["health"]["tick_errors"] == 1
