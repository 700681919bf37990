"""The log format: each channel `usv-log` reads has a real JSON schema that the logged messages satisfy, and
every file records a format version that the reader checks."""

from __future__ import annotations

import json

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from agent.contract import Cmd
from agent.core.build import initial_state
from agent.core.records import TickInputs
from agent.core.step import step
from agent.runtime.log_schema import AgentSummary, Estimates
from agent.runtime.mcap_log import FORMAT_RECORD, FORMAT_VERSION, McapLog, read_metadata
from agent.shell.tick_log import TickLogger, log_topic
from mission_log import cli
from mission_log.reader import READS_FORMATS, LogError, load_run, read_log
from sim_bridge.bridge import BridgeSettings, SimBridge
from sim_bridge.scenario import initial_estimates, select_scenario
from sim_bridge.world import World, streams

jsonschema = pytest.importorskip("jsonschema")

TICKS = 40
REACTION = {"p50": 2.05, "p99": 3.1, "max": 3.1, "ticks": 3}   # a summary's reaction times, as ReactionTimes gives them
# Three vessels; an island between vessel 3 and the target hides the target from it and is in its sonar's range.
SCENARIO = """
name: format
base:
  duration: 4.0
  seed: 11
  world:
    vessels:
      - {id: "1", position: [-6.0, -7.0]}
      - {id: "2", position: [6.0, 6.0]}
      - {id: "3", position: [-10.0, 3.0]}
    target: {kind: constant_velocity, position: [1.0, 1.0], velocity: [0.5, 0.0]}
    islands: [[[-8.0, 1.5], [-6.0, 1.5], [-7.0, 3.5]]]
  agent: {control: {radius: 5.0}}
"""


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    """An in-process fleet's agent logs, written through TickLogger as the agent process writes them, and the
    sim bridge's log of the same world."""
    folder = tmp_path_factory.mktemp("format")
    (folder / "format.yaml").write_text(SCENARIO)
    _, scenario = select_scenario(folder / "format.yaml")
    random = streams(scenario.seed)
    world = World(scenario.world, random.world)
    params = scenario.agent_params()
    states = {i: initial_state(i, params, start)
              for i, start in initial_estimates(scenario, world.truth(), random.initial).items()}
    logs = {i: McapLog(folder / f"agent-{i}.mcap", metadata={"vessel": i}) for i in states}
    writers = {i: TickLogger(logs[i], i, params.control.radius) for i in states}
    sent = {}
    for k in range(TICKS):
        readings, stamp = world.sense(), world.time_ns
        commands, outgoing = {}, {}
        for i, state in states.items():
            reading = readings[i]
            inputs = TickInputs(time=world.time, odometry=None if (i, k) == ("2", 5) else reading.odometry,
                                ranges=reading.ranges, shares={j: s for j, s in sent.items() if j != i},
                                bearing=reading.bearing, obstacle_points=reading.obstacle_points)
            states[i], output = step(params, state, inputs)   # the same object, updated in place
            command = Cmd(stamp_ns=stamp, seq=k, sender=i, surge=output.command.surge,
                          yaw_rate=output.command.yaw_rate)
            writers[i].tick(stamp, inputs, output, command)
            commands[i] = output.command
            if output.share is not None:
                outgoing[i] = output.share
        sent = outgoing
        world.step(commands)
    for i, writer in writers.items():
        writer.summary(world.time_ns, ticks=TICKS, overruns=0, refused={"stale": 2}, loop_seconds=1.5,
                       cpu_seconds=0.25, reaction_ms=REACTION if i == "2" else None)
        logs[i].close()

    bridge = SimBridge(scenario, BridgeSettings(log=str(folder / "sim.mcap")))
    for _ in range(5):
        bridge._latency = {"1": 0.002}
        bridge._log_tick(bridge.world.time_ns)
        bridge.world.step({})
        bridge.ticks += 1
    bridge.startup_missing.add("3")
    bridge._log_summary(0.125)
    bridge.log.close()
    return folder


def channel_schemas(path) -> dict[str, tuple[str, dict]]:
    """topic -> (schema name, JSON schema) as written in the file."""
    with path.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    return {channel.topic: (summary.schemas[channel.schema_id].name,
                            json.loads(summary.schemas[channel.schema_id].data))
            for channel in summary.channels.values()}


CHECKED = {"inputs": "usv.Inputs", "estimates": "usv.Estimates", "summary": "usv.AgentSummary"}
BRIDGE = {"/truth": "usv.Truth", "/bridge/command_latency": "usv.CommandLatency",
          "/bridge/summary": "usv.BridgeSummary"}


def test_every_message_the_readers_use_satisfies_its_channel_schema(run_folder):
    run = load_run(run_folder)
    assert sorted(run.vessels) == ["1", "2", "3"] and run.sim is not None
    files = [(log, {log_topic(v, name): title for name, title in CHECKED.items()}) for v, log in run.vessels.items()]
    for log, expected in [*files, (run.sim, BRIDGE)]:
        schemas = channel_schemas(log.path)
        for topic, title in expected.items():
            name, schema = schemas[topic]
            assert name == title and schema["title"] == title
            assert schema["type"] == "object" and schema["properties"] and schema["additionalProperties"] is False
            validator = jsonschema.Draft202012Validator(schema)
            validator.check_schema(schema)
            messages = log.messages(topic)
            assert messages, f"{log.path.name}: nothing on {topic}"
            for _, message in messages:
                errors = list(validator.iter_errors(message))
                assert not errors, f"{log.path.name} {topic}: {errors[0].json_path}: {errors[0].message}"


def test_the_logs_of_a_real_fleet_satisfy_the_schemas(fleet_run):
    # Separate processes over Zenoh: the agents' inputs come through the input gate from the wire.
    folder, _ = fleet_run
    run = load_run(folder)
    files = [(log, {log_topic(v, name): title for name, title in CHECKED.items() if name != "summary"})
             for v, log in run.vessels.items()]
    for log, expected in [*files, (run.sim, BRIDGE)]:
        schemas = channel_schemas(log.path)
        for topic, title in expected.items():
            name, schema = schemas[topic]
            assert name == title
            validator = jsonschema.Draft202012Validator(schema)
            for _, message in log.messages(topic):
                errors = list(validator.iter_errors(message))
                assert not errors, f"{log.path.name} {topic}: {errors[0].json_path}: {errors[0].message}"
    summary = jsonschema.Draft202012Validator(AgentSummary.model_json_schema())
    for vessel, log in run.vessels.items():
        assert summary.is_valid(log.last(log_topic(vessel, "summary")))


def test_the_run_covers_the_optional_parts_of_the_schemas(run_folder):
    # The optional and nested parts were validated above only if the run wrote them.
    run = load_run(run_folder)
    inputs = [m for log in run.vessels.values() for _, m in log.topic("inputs")]
    estimates = [m for log in run.vessels.values() for _, m in log.topic("estimates")]
    assert any(m["odometry"] is None for m in inputs) and any(m["odometry"] for m in inputs)
    assert any(m["bearing"] is None for m in inputs) and any(m["bearing"] for m in inputs)
    assert any(m["obstacle_points"] for m in inputs)
    assert any(s["target"] is not None and s["neighbours"] for m in inputs for s in m["shares"].values())
    assert any(n["outcomes"] for m in estimates for n in m["neighbours"].values())
    assert any(m["bearing"] is not None for m in estimates) and any(m["target_state"] for m in estimates)
    assert len(estimates) == 3 * TICKS - 1          # vessel 2's tick without odometry has no estimates
    assert run.vessels["2"].last("/2/summary") == {"ticks": TICKS, "overruns": 0, "refused": {"stale": 2},
                                                   "loop_seconds": 1.5, "cpu_seconds": 0.25, "core_cpu_seconds": None,
                                                   "reaction_ms": REACTION, "reaction_cpu_ms": None}
    assert run.vessels["1"].last("/1/summary")["reaction_ms"] is None
    assert run.sim.last("/bridge/summary")["startup_missing"] == ["3"]


def test_a_message_that_drifts_from_its_schema_fails(run_folder):
    _, schema = channel_schemas(run_folder / "agent-1.mcap")["/1/estimates"]
    validator = jsonschema.Draft202012Validator(schema)
    message = read_log(run_folder / "agent-1.mcap").last("/1/estimates")
    assert validator.is_valid(message)
    extra = {**message, "new_field": 1.0}
    missing = {k: v for k, v in message.items() if k != "saturated"}
    not_finite = {**message, "velocity": {**message["velocity"], "command": [None, 0.0]}}   # NaN as orjson writes it
    wrong_shape = {**message, "target_covariance": message["target_covariance"][:4]}
    for drifted in (extra, missing, not_finite, wrong_shape):
        assert not validator.is_valid(drifted)


def test_the_schema_in_the_file_is_the_models(run_folder):
    _, schema = channel_schemas(run_folder / "agent-1.mcap")["/1/estimates"]
    assert schema == Estimates.model_json_schema()


def test_every_file_records_the_format_version(run_folder):
    for path in run_folder.glob("*.mcap"):
        assert read_metadata(path)[FORMAT_RECORD] == {"version": FORMAT_VERSION}
        assert read_log(path).format_version == FORMAT_VERSION
    assert FORMAT_VERSION in READS_FORMATS


def write_raw(path, format_version: str | None) -> None:
    """An MCAP file as McapLog writes one, with any format record (None: none, as before it was recorded)."""
    with path.open("wb") as handle:
        writer = Writer(handle)
        writer.start(profile="", library="test")
        if format_version is not None:
            writer.add_metadata(FORMAT_RECORD, {"version": format_version})
        writer.add_metadata("run", {"vessel": "1"})
        schema = writer.register_schema(name="x", encoding="jsonschema", data=b'{"type": "object"}')
        channel = writer.register_channel(topic="/1/summary", message_encoding="json", schema_id=schema)
        writer.add_message(channel_id=channel, log_time=1, publish_time=1, data=b'{"ticks": 3}')
        writer.finish()


def test_a_file_of_an_unknown_version_is_refused_in_one_line(tmp_path):
    path = tmp_path / "agent-1.mcap"
    write_raw(path, "99")
    with pytest.raises(LogError) as raised:
        read_log(path)
    message = str(raised.value)
    assert "\n" not in message
    assert str(path) in message and "version 99" in message and f"reads version {', '.join(READS_FORMATS)}" in message


def test_the_command_line_says_why_it_refuses_a_file(tmp_path, capsys):
    write_raw(tmp_path / "agent-1.mcap", "7")
    assert cli.main(["summary", str(tmp_path)]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "log format version 7" in error


def test_a_file_from_before_the_version_was_recorded_reads_as_version_1(tmp_path):
    path = tmp_path / "agent-1.mcap"
    write_raw(path, None)
    log = read_log(path)
    assert log.format_version == "1" and log.last("/1/summary") == {"ticks": 3}


def test_inputs_of_format_1_read_as_ranges_measured_at_the_tick():
    """Format 1 had no range_stamp: its ranges were measured at the tick's time, which None says."""
    from agent.core.records import inputs_from_json

    old = {"time": 1.5, "odometry": None, "ranges": {"2": 3.0}, "bearing": None, "obstacle_points": None,
           "shares": {}}
    assert inputs_from_json(old).range_stamp is None
    assert inputs_from_json({**old, "range_stamp": 1.47}).range_stamp == 1.47
    assert inputs_from_json(old).earlier_ranges == ()       # formats 1 and 2: one range set per tick


def test_earlier_range_sets_go_through_the_log_codec():
    from agent.core.records import TickInputs, inputs_from_json, inputs_to_json

    inputs = TickInputs(time=2.0, odometry=None, ranges={"2": 4.0}, range_stamp=1.98,
                        earlier_ranges=((1.855, {"2": 3.9, "3": 7.25}), (1.93, {"3": 7.5})))
    back = inputs_from_json(json.loads(json.dumps(inputs_to_json(inputs))))
    assert back.earlier_ranges == ((1.855, {"2": 3.9, "3": 7.25}), (1.93, {"3": 7.5}))
    assert back.ranges == {"2": 4.0} and back.range_stamp == 1.98


def test_a_tick_loggers_topics_have_their_schemas_before_the_first_tick(tmp_path, monkeypatch):
    """TickLogger prepares its per-tick topics when it is made (the agent makes it before it tells the fleet
    it is up), so that its first tick generates no JSON schema: the log's channels are in the file before any
    message, with the schemas a first message would have made."""
    from pydantic import BaseModel

    expected = {"cmd": Cmd.model_json_schema().get("title", "Cmd"), "estimates": Estimates.model_json_schema()["title"]}
    log = McapLog(tmp_path / "agent-1.mcap", metadata={"vessel": "1"})
    TickLogger(log, "1", 5.0)
    made = []
    monkeypatch.setattr(BaseModel, "model_json_schema", classmethod(lambda cls, *a, **k: made.append(cls) or {}))
    log.log(log_topic("1", "cmd"), Cmd(stamp_ns=1, seq=0, sender="1", surge=0.5, yaw_rate=0.1), 1)
    log.close()
    assert made == []
    with open(tmp_path / "agent-1.mcap", "rb") as handle:
        summary = make_reader(handle).get_summary()
    topics = {channel.topic: summary.schemas[channel.schema_id].name for channel in summary.channels.values()}
    assert topics[log_topic("1", "cmd")] == expected["cmd"]
    assert topics[log_topic("1", "estimates")] == expected["estimates"]
    assert {log_topic("1", name) for name in ("inputs", "cmd", "status", "estimates", "tf", "scene")} <= set(topics)
