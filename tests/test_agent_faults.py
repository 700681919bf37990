"""The agent survives what the issue found fatal, one case each: a regression test per single packet, over
real Zenoh with a real agent process where the issue saw it there, and the shell's own guards in process.

In process (fast): a tick that raises commands STOP and the run goes on; the same failure tick after tick
rebuilds the core; a command beyond the controller's limits never leaves; an error storm is told once; a sim
restart forgets the old timeline and starts a new log file.

Over Zenoh (slow): odometry at [1e308, 1e308], a share with a covariance of -I, a seq of 10^9, a phantom
id, 2,000 shares/s from new ids, clocks of 10^400 and 2^62 ns; the sim bridge killed and restarted; a
second agent with a vessel id already taken; start-up errors in one line; an id no bridge publishes for.
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from agent.contract import Clock, Status, decode, encode, key
from agent.core.build import InitialEstimates, initial_state
from agent.core.params import AgentParams
from agent.core.records import Command, OdometryReading, Share, TickInputs, TickOutput
from agent.runtime.mcap_log import read_messages
from agent.shell.failures import CommandOutOfLimits, check_command, error_kind
from agent.shell.node import AgentNode
from agent.shell.settings import NodeSettings

PARAMS = AgentParams()
DT = PARAMS.dt
MAX_SURGE = PARAMS.control.max_speed
MAX_YAW_RATE = PARAMS.control.max_correction_yaw_rate + PARAMS.control.yaw_rate
RADIUS = 5.0
OMEGA = math.pi / 30


# ----- in process: the shell's guards -----
class Sink:
    def __init__(self):
        self.payloads = []

    def put(self, payload):
        self.payloads.append(payload)


def publishers() -> dict[str, Sink]:
    return {"cmd": Sink(), "share": Sink(), "status": Sink()}


def commands(sinks) -> list[tuple[float, float]]:
    return [(m["surge"], m["yaw_rate"]) for m in map(json.loads, sinks["cmd"].payloads)]


def node(tmp_path=None, **settings) -> AgentNode:
    log = str(tmp_path / "agent-{vessel}.mcap") if tmp_path is not None else None
    agent = AgentNode("1", NodeSettings(clock="wall", id_check=0, log=log, **settings),
                      initial_state("1", PARAMS, InitialEstimates(target=(5.0, 0.0, 0.0, 0.0))))
    agent.recorder.open()
    return agent


def test_a_failing_tick_commands_stop_and_the_next_one_runs(monkeypatch, capsys):
    import agent.shell.node as node_module

    calls = []

    def decide(params, state, inputs):
        calls.append(1)
        if len(calls) == 2:
            raise ZeroDivisionError("boom")
        return state, Command(1.0, 0.1), lambda: TickOutput(Command(1.0, 0.1), None, None)

    monkeypatch.setattr(node_module, "decide", decide)
    agent, sinks = node(), publishers()
    for _ in range(4):
        agent._tick(sinks)
    assert commands(sinks) == [(1.0, 0.1), (0.0, 0.0), (1.0, 0.1), (1.0, 0.1)]
    assert agent.failures.total == 1 and agent.ticks == 4 and len(sinks["status"].payloads) == 4
    assert decode(Status, sinks["status"].payloads[1])[0].health["tick_errors"] == 1
    assert "ZeroDivisionError@" in capsys.readouterr().err


def test_the_same_failure_tick_after_tick_rebuilds_the_core(monkeypatch, capsys):
    import agent.shell.node as node_module

    def decide(params, state, inputs):
        raise ValueError("reset needs a symmetric positive-definite covariance")

    monkeypatch.setattr(node_module, "decide", decide)
    agent, sinks = node(rebuild_after=3), publishers()
    before = agent.state
    agent.state.phase = 1.0
    for _ in range(7):
        agent._tick(sinks)
    assert agent.failures.total == 7 and agent.failures.rebuilds == 2
    assert agent.state is not before and agent.state.phase is None and agent.state.tracker is None  # no initial estimates
    assert set(commands(sinks)) == {(0.0, 0.0)}
    err = capsys.readouterr().err
    assert err.count("tick at") == 1            # one kind of error: told once, not seven times
    assert err.count("core rebuilt") == 2


@pytest.mark.parametrize("command", [Command(MAX_SURGE * 1.5, 0.0), Command(0.0, -MAX_YAW_RATE * 1.01),
                                     Command(math.nan, 0.0), Command(0.0, math.inf)])
def test_a_command_beyond_the_limits_never_leaves(monkeypatch, command):
    import agent.shell.node as node_module

    monkeypatch.setattr(node_module, "decide",
                        lambda params, state, inputs: (state, command, lambda: TickOutput(command, None, None)))
    agent, sinks = node(), publishers()
    agent._tick(sinks)
    assert commands(sinks) == [(0.0, 0.0)] and agent.failures.total == 1
    assert "CommandOutOfLimits" in next(iter(agent.failures.kinds))


def test_a_command_at_the_limits_goes_out(monkeypatch):
    import agent.shell.node as node_module

    command = Command(-MAX_SURGE, MAX_YAW_RATE)
    monkeypatch.setattr(node_module, "decide",
                        lambda params, state, inputs: (state, command, lambda: TickOutput(command, None, None)))
    agent, sinks = node(), publishers()
    agent._tick(sinks)
    assert commands(sinks) == [(-MAX_SURGE, MAX_YAW_RATE)] and agent.failures.total == 0


def ticked_inputs(k: int) -> TickInputs:
    """Tick k's inputs past the gate: own odometry moving along x, a neighbour ranged and sharing from tick 1."""
    odometry = OdometryReading(k * DT, np.array([0.1 * k, 0.0]), 0.0)
    share = Share("9", OdometryReading(k * DT, np.array([4.0, 1.0]), 0.0), np.zeros(2), 0.0)
    return TickInputs(k * DT, odometry, ranges={"9": math.hypot(4.0 - 0.1 * k, 1.0)},
                      shares={"9": share} if k >= 1 else {}, bearing=np.array([-1.0, 0.0]))


def test_the_command_is_on_the_wire_before_the_core_builds_the_share_and_the_record(monkeypatch):
    """The thrusters' latency leaves out what only the neighbours and the log need: the real core's `report`
    runs after the command's put, and after the tick thread has let Zenoh's sending thread have the CPU; what
    goes out is what `step` gives on the same inputs."""
    import agent.shell.node as node_module
    from agent.core.step import step

    real_decide, on_the_wire = node_module.decide, []

    def decide(params, state, inputs):
        state, command, report = real_decide(params, state, inputs)

        def watched():
            on_the_wire.append(("report", len(sinks["cmd"].payloads)))
            return report()
        return state, command, watched

    monkeypatch.setattr(node_module, "decide", decide)
    monkeypatch.setattr(node_module, "yield_cpu", lambda: on_the_wire.append(("yield", len(sinks["cmd"].payloads))))
    agent, sinks = node(), publishers()
    alone = initial_state("1", PARAMS, InitialEstimates(target=(5.0, 0.0, 0.0, 0.0)))
    expected = []
    for k in range(6):
        agent.gate.snapshot = lambda now, k=k: ticked_inputs(k)
        agent._tick(sinks)
        alone, output = step(PARAMS, alone, ticked_inputs(k))
        expected.append((output.command.surge, output.command.yaw_rate))
    assert on_the_wire == [(event, k) for k in range(1, 7) for event in ("yield", "report")]
    assert commands(sinks) == expected and agent.failures.total == 0
    assert len(sinks["share"].payloads) == 6 and agent.state.phase == alone.phase


def test_a_report_that_fails_leaves_the_command_that_went_out_and_is_counted(monkeypatch, capsys):
    """The command was sound and is on the wire: a failure building the share or the record after it costs
    that tick's share and record only, is counted as a failed tick, and the status still goes out."""
    import agent.shell.node as node_module

    real_decide = node_module.decide

    def decide(params, state, inputs):
        state, command, _ = real_decide(params, state, inputs)

        def failing():
            raise RuntimeError("the record failed")
        return state, command, failing

    monkeypatch.setattr(node_module, "decide", decide)
    agent, sinks = node(), publishers()
    for k in range(2):
        agent.gate.snapshot = lambda now, k=k: ticked_inputs(k)
        agent._tick(sinks)
    sent = commands(sinks)
    assert len(sent) == 2 and sent[-1] != (0.0, 0.0)
    assert sinks["share"].payloads == [] and len(sinks["status"].payloads) == 2
    assert agent.failures.total == 2 and "RuntimeError@" in capsys.readouterr().err


def test_the_real_core_failure_of_the_issue_is_survived(tmp_path):
    """The exact inputs that killed every agent (a new neighbour whose shared target covariance is not
    positive definite reaches the pair filter's `reset`) are fed to the tick past the gate: whatever the core
    does with them, a finite command within the limits goes out, and a failure is logged with its inputs."""
    agent, sinks = node(tmp_path), publishers()

    def inputs(k: int) -> TickInputs:
        odometry = OdometryReading(k * DT, np.array([0.1 * k, 0.0]), 0.0)
        share = Share("9", OdometryReading(k * DT, np.array([1.0, 1.0]), 0.0), np.zeros(2), 0.0,
                      np.array([3.0, 0.0, 0.0, 0.0]), -5.0 * np.eye(4))
        return TickInputs(k * DT, odometry, ranges={"9": 3.0}, shares={"9": share} if k >= 5 else {})

    for k in range(15):
        agent.gate.snapshot = lambda now, k=k: inputs(k)
        agent._tick(sinks)
    assert agent.ticks == 15
    for surge, yaw_rate in commands(sinks):
        assert math.isfinite(surge) and abs(surge) <= MAX_SURGE and abs(yaw_rate) <= MAX_YAW_RATE * (1 + 1e-9)
    agent.recorder.close()
    errors = [m for topic, _, m in read_messages(tmp_path / "agent-1.mcap") if topic == "/1/errors"]
    assert len(errors) == min(agent.failures.total, 1)
    if errors:
        assert errors[0]["inputs"]["shares"]["9"]["target_covariance"][0] == -5.0


def test_an_error_kind_names_the_place_in_our_code():
    try:
        check_command(Command(2.0, 0.0), SimpleNamespace(max_speed=1.0, max_correction_yaw_rate=0.5, yaw_rate=-0.5))
    except CommandOutOfLimits as error:
        kind = error_kind(error)
    assert kind.startswith("CommandOutOfLimits@agent/shell/failures.py:")


class FakeSample:
    def __init__(self, key_expr: str, payload: bytes):
        self.key_expr = key_expr
        self.payload = SimpleNamespace(to_bytes=lambda: payload)


def test_a_sim_restart_rebuilds_the_core_and_starts_a_new_log(tmp_path):
    settings = NodeSettings(clock="sim", id_check=0, log=str(tmp_path / "agent-{vessel}.mcap"),
                            initial=InitialEstimates(target=(5.0, 0.0, 0.0, 0.0)))
    agent = AgentNode("1", settings)
    agent.recorder.open()
    agent.ticker.clock.silence = 0.05
    agent._on_clock(FakeSample("sim/clock", encode(Clock(stamp_ns=30 * 10**9, seq=300))))
    agent.state.phase = 2.0
    agent.state.tracker = None
    time.sleep(0.1)                        # the sim bridge is gone ...
    assert agent.ticker.input_time() is None     # ... stamps are not judged meanwhile
    agent._on_clock(FakeSample("sim/clock", encode(Clock(stamp_ns=0, seq=0))))   # ... and back from 0
    assert agent.ticker.restart_pending and agent.gate._delivered_through is None
    assert agent.ticker.restarted() and not agent.ticker.restarted()   # once
    agent._restart()
    assert agent.ticker.restarts == 1 and agent.state.phase is None and agent.state.tracker is not None
    assert agent.recorder.log.path.name == "agent-1-mission2.mcap"
    agent.recorder.close()
    assert (tmp_path / "agent-1.mcap").exists()


# ----- over Zenoh: a real agent process -----
def session_to(port: int):
    import zenoh

    from agent.runtime.zenoh_session import ZenohSettings, zenoh_config
    return zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"])))


def peak_memory_mb(pid: int, field: str = "VmHWM") -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) / 1024.0
    raise AssertionError(f"no {field} for {pid}")


STARTED: list[AgentProcess] = []


@pytest.fixture(autouse=True)
def _close_agents():
    yield
    while STARTED:
        STARTED.pop().close()


class AgentProcess:
    """One `usv-agent` process listening on a free port, a session connected to it, and what it publishes."""

    def __init__(self, tmp_path: Path, vessel: str = "1", clock: str = "sim", connect: list[str] = (), **settings):
        from sim_bridge.fleet import free_port

        self.vessel, self.port = vessel, free_port()
        config = {"clock": clock, "zenoh": {"listen": [f"tcp/127.0.0.1:{self.port}"], "connect": list(connect)},
                  "id_check": 0.2, "initial": {"target": [RADIUS, 0.0, 0.0, 0.0]}} | settings
        path = tmp_path / f"agent-{vessel}-{self.port}.yaml"
        path.write_text(yaml.safe_dump(config))
        self.stderr_path = tmp_path / f"agent-{vessel}-{self.port}.err"
        self.process = subprocess.Popen([sys.executable, "-m", "agent", "--vessel", vessel, "--config", str(path)],
                                        stderr=self.stderr_path.open("w"))
        self.commands: list[dict] = []
        self.statuses: list[Status] = []
        self.session = session_to(self.port)
        STARTED.append(self)
        self.session.declare_subscriber(key(vessel, "cmd"),
                                        lambda s: self.commands.append(json.loads(s.payload.to_bytes())))
        self.session.declare_subscriber(key(vessel, "status"),
                                        lambda s: self.statuses.append(decode(Status, s.payload.to_bytes())[0]))
        from conftest import wait_until
        assert wait_until(lambda: self.statuses or self.process.poll() is not None, timeout=30), self.stderr()
        assert self.process.poll() is None, self.stderr()

    def stderr(self) -> str:
        return self.stderr_path.read_text(errors="replace")

    def put(self, topic_key: str, payload: bytes | dict) -> None:
        self.session.put(topic_key, payload if isinstance(payload, bytes) else json.dumps(payload).encode())

    def sensors(self, k: int, **change) -> None:
        """Valid sensors of tick k of a vessel circling the target at the origin, `change` replacing fields."""
        stamp, angle = round(k * DT * 1e9), OMEGA * k * DT
        position = RADIUS * np.array([math.cos(angle), math.sin(angle)])
        odometry = {"stamp_ns": stamp, "seq": k, "sender": self.vessel,
                    "position": (position - [RADIUS, 0.0]).tolist(), "heading": angle + math.pi / 2}
        self.put(key(self.vessel, "sensor/odom"), odometry | change.get("odom", {}))
        self.put(key(self.vessel, "sensor/uwb"), {"stamp_ns": stamp, "seq": k, "sender": self.vessel,
                                                  "ranges": change.get("ranges", {})})
        self.put(key(self.vessel, "sensor/bearing"), {"stamp_ns": stamp, "seq": k, "sender": self.vessel,
                                                      "bearing": (position / RADIUS).tolist()})
        self.put(key(self.vessel, "sensor/sonar"), {"stamp_ns": stamp, "seq": k, "sender": self.vessel,
                                                    "points": []})

    def clock(self, k: int, **change) -> None:
        body = {"stamp_ns": round(k * DT * 1e9), "seq": k, "vessels": [self.vessel],
                "previous_ns": round((k - 1) * DT * 1e9) if k else None} | change
        self.put("sim/clock", body)

    def tick(self, k: int, wait: bool = True, **change) -> dict | None:
        """Publish tick k's sensors and clock; with `wait`, its command (stamped k dt)."""
        from conftest import wait_until
        self.sensors(k, **change)
        self.clock(k)
        if not wait:
            return None
        stamp = round(k * DT * 1e9)
        # The status follows the command: wait for both, so that `health` is this tick's.
        assert wait_until(lambda: any(c["stamp_ns"] == stamp for c in self.commands)
                          and any(s.stamp_ns == stamp for s in self.statuses), timeout=10), (
            f"no command and status for tick {k}: {self.stderr()[-2000:]}")
        return next(c for c in self.commands if c["stamp_ns"] == stamp)

    def health(self) -> Counter[str]:
        """The counters of the latest status (0 for one not there)."""
        return Counter(self.statuses[-1].health)

    def close(self) -> None:
        """Whatever a test left running: a failed test must not leave a process or a session (whose
        threads would keep pytest from exiting)."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10)
        self.session.close()

    def stop(self) -> str:
        """SIGTERM, then the agent's stderr; the agent must have been alive and must exit cleanly."""
        assert self.process.poll() is None, f"the agent died: {self.stderr()[-3000:]}"
        self.session.close()
        self.process.send_signal(signal.SIGTERM)
        assert self.process.wait(timeout=20) == 0, self.stderr()[-3000:]
        return self.stderr()


def sound(command: dict) -> bool:
    return (math.isfinite(command["surge"]) and math.isfinite(command["yaw_rate"])
            and abs(command["surge"]) <= MAX_SURGE and abs(command["yaw_rate"]) <= MAX_YAW_RATE * (1 + 1e-9))


def moving(command: dict) -> bool:
    return command["surge"] != 0.0 or command["yaw_rate"] != 0.0


@pytest.mark.slow
def test_odometry_at_1e308_is_refused_and_the_agent_goes_on(tmp_path):
    """Regression: odometry at [1e308, 1e308] killed the agent in 0.19 s."""
    agent = AgentProcess(tmp_path)
    before = [agent.tick(k) for k in range(5)]
    agent.tick(5, odom={"position": [1e308, 1e308]})
    agent.tick(6, odom={"position": [1e308, -1e308], "heading": 1e300})
    after = [agent.tick(k) for k in range(7, 15)]
    assert all(map(sound, agent.commands)) and all(map(moving, before[1:] + after[2:]))
    assert agent.health()["rejected_malformed"] == 2 and agent.health()["tick_errors"] == 0
    agent.stop()


@pytest.mark.slow
def test_a_share_with_a_covariance_of_minus_identity_is_refused(tmp_path):
    """Regression: a share from a new id with a covariance of -I killed all 4 agents within 0.4 s. It is
    refused whether or not the id has a liveliness token; a sound share from the same id is taken."""
    agent = AgentProcess(tmp_path)
    token = agent.session.liveliness().declare_token(key("9", "alive"))
    from conftest import wait_until
    assert wait_until(lambda: agent.statuses and "9" in agent.statuses[-1].peers, timeout=10)

    def share(k: int, sender: str, covariance) -> dict:
        return {"stamp_ns": round(k * DT * 1e9), "seq": k, "sender": sender, "position": [0.0, 0.0],
                "heading": 0.0, "velocity": [0.0, 0.0], "phase": 1.0, "target": [-RADIUS, 0.0, 0.0, 0.0],
                "target_covariance": np.asarray(covariance, dtype=float).ravel().tolist(), "neighbours": {}}

    for k in range(12):
        bad = -np.eye(4)
        agent.put(key("9", "share"), share(k, "9", bad if k < 6 else 0.1 * np.eye(4)))
        agent.put(key("8", "share"), share(k, "8", bad))          # no token at all
        agent.tick(k, ranges={"9": 7.0})
    # One more tick: the shares travel on their own subscriber's thread, so the last ones can be counted after
    # the status of the tick they were sent before (seen under load: 11 of 12).
    agent.tick(12, ranges={"9": 7.0})
    health = agent.health()
    assert health["rejected_malformed"] == 6 and health["rejected_unknown_sender"] == 12
    assert health["neighbours_joined"] == 1 and health["tick_errors"] == 0
    assert all(map(sound, agent.commands))
    token.undeclare()
    agent.stop()


@pytest.mark.slow
def test_a_seq_of_a_billion_does_not_lock_the_agent_out(tmp_path):
    """Regression: one odometry message with seq 10^9 made the agent refuse its own odometry for the rest of
    the run (121/121 ticks STOP)."""
    agent = AgentProcess(tmp_path)
    agent.tick(0)
    agent.tick(1, odom={"seq": 10**9})
    after = [agent.tick(k) for k in range(2, 15)]
    assert all(map(moving, after)) and agent.health()["rejected_duplicate_or_reordered"] == 0
    assert agent.health()["stops"] <= 1           # only a first tick may lack odometry
    agent.stop()


@pytest.mark.slow
def test_a_phantom_id_is_no_neighbour(tmp_path):
    """Regression: a share alone created a neighbour, and a phantom id moved the whole fleet."""
    agent = AgentProcess(tmp_path)
    for k in range(10):
        agent.put(key("ghost", "share"), {
            "stamp_ns": round(k * DT * 1e9), "seq": k, "sender": "ghost", "position": [0.0, 0.0], "heading": 0.0,
            "velocity": [0.0, 0.0], "phase": 2.0, "target": [-3.0, 0.0, 0.0, 0.0],
            "target_covariance": np.eye(4).ravel().tolist(), "neighbours": {}})
        agent.tick(k, ranges={"ghost": 2.0})
    health = agent.health()
    assert health["neighbours_joined"] == 0 and health["rejected_unknown_sender"] == 10
    assert health["rejected_unknown_peer"] >= 9 and "ghost" not in agent.statuses[-1].peers
    agent.stop()


@pytest.mark.slow
def test_a_flood_of_shares_from_new_ids_costs_neither_memory_nor_the_command_rate(tmp_path):
    """Regression: 2,000 shares/s from new ids took an agent from 74 to 335 MB and its command rate to 0.5 Hz.
    On the wall clock (10 Hz), five seconds of that flood leave the command rate and the memory as they were."""
    agent = AgentProcess(tmp_path, clock="wall")
    time.sleep(2.0)
    resident = peak_memory_mb(agent.process.pid, "VmRSS")
    counted, started, n = len(agent.commands), time.monotonic(), 0
    while (elapsed := time.monotonic() - started) < 5.0:
        stamp = time.time_ns()
        for _ in range(20):
            sender = f"x{n}"
            agent.put(key(sender, "share"), {"stamp_ns": stamp, "seq": 0, "sender": sender, "position": [0.0, 0.0],
                                             "heading": 0.0, "velocity": [0.0, 0.0], "phase": 0.0})
            n += 1
        time.sleep(max(0.0, n / 2000.0 - (time.monotonic() - started)))
    rate = (len(agent.commands) - counted) / elapsed
    assert n >= 9000 and rate >= 8.0, (n, rate)
    assert agent.health()["rejected_unknown_sender"] >= 0.9 * n
    assert peak_memory_mb(agent.process.pid) - resident < 25.0
    agent.stop()


@pytest.mark.slow
def test_clocks_of_10_to_the_400_and_2_to_the_62_neither_crash_nor_freeze(tmp_path):
    """Regression: a sim/clock stamp of 10^400 crashed every agent; 2^62 froze them."""
    agent = AgentProcess(tmp_path)
    for k in range(5):
        agent.tick(k)
    agent.put("sim/clock", b'{"stamp_ns": 1' + b"0" * 400 + b', "seq": 5}')
    agent.put("sim/clock", {"stamp_ns": 2**62, "seq": 5})
    agent.put("sim/clock", {"stamp_ns": 2**63, "seq": 5})
    after = [agent.tick(k) for k in range(5, 15)]
    assert all(map(moving, after))
    health = agent.health()
    assert health["rejected_malformed_clock"] == 2 and health["rejected_clock_jump"] == 1
    assert health["sim_restarts"] == 0
    agent.stop()


@pytest.mark.slow
def test_an_id_no_bridge_publishes_for_is_told(tmp_path):
    """A valid but unknown vessel id: after `no_sensor_warning` seconds the agent says it has no sensors, and
    which vessels the sim clock lists, rather than silently commanding STOP."""
    agent = AgentProcess(tmp_path, vessel="9", no_sensor_warning=1.0)
    from conftest import wait_until
    for k in range(40):
        agent.put("sim/clock", {"stamp_ns": round(k * DT * 1e9), "seq": k, "vessels": ["1", "2"]})
        time.sleep(0.05)
        if "no sensor data" in agent.stderr():
            break
    assert wait_until(lambda: "no sensor data" in agent.stderr(), timeout=5)
    line = next(line for line in agent.stderr().splitlines() if "no sensor data" in line)
    assert "usv/9/sensor/*" in line and "lists vessels 1, 2, not 9" in line
    agent.stop()


@pytest.mark.slow
def test_a_second_agent_with_a_taken_vessel_id_refuses_to_start(tmp_path):
    """Regression: two agents with the same vessel id alternated on usv/2/cmd and nothing warned."""
    log = tmp_path / "agent-2.mcap"
    first = AgentProcess(tmp_path, vessel="2", clock="wall", log=str(log))
    config = tmp_path / "second.yaml"
    config.write_text(yaml.safe_dump({"clock": "wall", "zenoh": {"connect": [f"tcp/127.0.0.1:{first.port}"]},
                                      "log": str(log)}))
    second = subprocess.run([sys.executable, "-m", "agent", "--vessel", "2", "--config", str(config)],
                            capture_output=True, text=True, timeout=60, check=False)
    assert second.returncode == 2, second.stderr
    lines = second.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("usv-agent 2: vessel id 2 is taken"), second.stderr
    # Another id on the same link starts.
    third = AgentProcess(tmp_path, vessel="3", clock="wall", connect=[f"tcp/127.0.0.1:{first.port}"])
    third.stop()
    first.stop()
    # The refused agent never opened the log of the one it would have doubled.
    ticks = [t for topic, t, _ in read_messages(log) if topic == "usv/2/cmd"]
    assert len(ticks) >= 20 and ticks == sorted(ticks)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["log", "endpoint", "listen", "router"])
def test_start_up_errors_are_one_line_and_exit_2(tmp_path, case):
    from sim_bridge.fleet import free_port
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    settings = {
        "log": {"log": str(blocker / "agent.mcap")},                                   # its directory is a file
        "endpoint": {"zenoh": {"connect": ["nonsense"]}},
        "listen": {"zenoh": {"listen": ["tcp/192.0.2.1:7447"]}},                       # not this machine's
        "router": {"zenoh": {"mode": "client", "connect": [f"tcp/127.0.0.1:{free_port()}"], "connect_timeout": 0.5}},
    }[case]
    config = tmp_path / "node.yaml"
    config.write_text(yaml.safe_dump(settings))
    result = subprocess.run([sys.executable, "-m", "agent", "--vessel", "1", "--config", str(config)],
                            capture_output=True, text=True, timeout=60, check=False)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert lines[0].startswith("usv-agent") and "Traceback" not in result.stderr and ".rs:" not in lines[0]
    expected = {"log": "cannot write its log", "endpoint": "zenoh.connect: Endpoints must be of the form",
                "listen": "cannot open the Zenoh session", "router": "Unable to connect"}[case]
    assert expected in lines[0], lines[0]


@pytest.mark.slow
def test_the_sim_bridge_killed_and_restarted_is_followed(tmp_path, short_scenario):
    """Regression: with the sim bridge gone, agents published nothing, then refused its new clock as stale
    for ever. Now they send heartbeats while it is gone, see the new clock start from 0 as a restart, and
    run the new mission to its end: the second bridge misses no command."""
    from conftest import bridge_counts, wait_until

    from sim_bridge.fleet import agent_configs, free_port
    from sim_bridge.scenario import select_scenario

    _, scenario = select_scenario(short_scenario, None)
    port = free_port()
    bridge_config = tmp_path / "bridge.yaml"
    bridge_config.write_text(yaml.safe_dump({"mode": "lockstep", "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]}}))
    bridge_cmd = [sys.executable, "-m", "sim_bridge", "--scenario", str(short_scenario), "--config", str(bridge_config)]
    # The first mission is long, so that it is still running when the test's session has connected and it
    # is killed: a lockstep fleet can run the short one to its end before that.
    long_scenario = tmp_path / "long.yaml"
    long = yaml.safe_load(short_scenario.read_text())
    long["base"]["duration"] = 600.0
    long_scenario.write_text(yaml.safe_dump(long))
    agents = {}
    for vessel, settings in agent_configs(scenario, None, tmp_path, lambda v: {
            "listen": ["tcp/127.0.0.1:0"], "connect": [f"tcp/127.0.0.1:{port}"]}).items():
        path = tmp_path / f"agent-{vessel}.yaml"
        path.write_text(yaml.safe_dump(settings | {"id_check": 0.2}))
        agents[vessel] = subprocess.Popen([sys.executable, "-m", "agent", "--vessel", vessel, "--config", str(path)],
                                          stderr=(tmp_path / f"agent-{vessel}.err").open("w"))
    statuses: list[Status] = []
    first = subprocess.Popen([*bridge_cmd[:4], str(long_scenario), *bridge_cmd[5:]], stderr=subprocess.PIPE, text=True)
    try:
        with session_to(port) as session:
            session.declare_subscriber("usv/*/status",
                                       lambda s: statuses.append(decode(Status, s.payload.to_bytes())[0]))
            # Kill the first bridge a few seconds of sim time in.
            assert wait_until(lambda: any(s.ticked and s.stamp_ns >= 3 * 10**9 for s in statuses), timeout=60)
            first.kill()
            first.wait()
            gone = len(statuses)
            newest = max(s.stamp_ns for s in statuses[:gone] if s.ticked)
            time.sleep(2.0)
            heartbeats = statuses[gone:]
            assert {s.sender for s in heartbeats if not s.ticked and s.stamp_ns == 0} == set(agents)
            # No tick without a bridge: the only ticked statuses after the kill answer clocks it had sent, in
            # lockstep a tick or two beyond the newest status seen before it (a loaded machine delivers them late).
            tick_ns = round(scenario.world.dt * 1e9)
            assert all(s.stamp_ns <= newest + 2 * tick_ns for s in heartbeats if s.ticked)
        second = subprocess.run(bridge_cmd, capture_output=True, text=True, timeout=120, check=False)
        assert second.returncode == 0, second.stderr
        counts = bridge_counts(second.stderr)
        assert counts["ticks"] == round(scenario.duration / scenario.world.dt) + 1
        assert counts["missed"] == 0 and counts["watchdog"] == 0, second.stderr
        for vessel, process in agents.items():
            assert process.poll() is None, (tmp_path / f"agent-{vessel}.err").read_text()
            process.send_signal(signal.SIGTERM)
            assert process.wait(timeout=20) == 0
            err = (tmp_path / f"agent-{vessel}.err").read_text()
            assert err.count("the simulation restarted") == 1, err
            second_log = tmp_path / f"agent-{vessel}-mission2.mcap"
            ticks = [t for topic, t, _ in read_messages(second_log) if topic == f"usv/{vessel}/cmd"]
            assert ticks[0] == 0 and len(ticks) == counts["ticks"]
    finally:
        for process in [first, *agents.values()]:
            if process.poll() is None:
                process.kill()
                process.wait()



@pytest.mark.slow
def test_an_agent_on_sim_time_without_a_simulation_says_so_and_one_without_a_log_too(tmp_path):
    """No sim/clock at all: the agent says that no simulation runs (it ticks on sim time), not that no
    bridge publishes its sensors; and with no `log:` in its settings it says it records nothing."""
    agent = AgentProcess(tmp_path, vessel="4", no_sensor_warning=1.0)
    from conftest import wait_until
    assert wait_until(lambda: "no sim/clock" in agent.stderr(), timeout=15)
    said = agent.stderr()
    assert "no simulation is running" in said and "no sensor data" not in said
    assert "usv-agent 4: no MCAP log: the settings name none" in said
    agent.stop()
