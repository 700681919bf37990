"""`usv-log export --ros2`: a run's logs as a rosbag2 (written with rosbags), decoded message by message with the
other library, mcap-ros2-support, and compared with the logs as `load_run` reads them.

No ROS 2 is installed here, so `ros2 bag play` is not run: the bag's rosbag2 MCAP profile (the `ros2` profile,
`ros2msg` schemas, `cdr` messages, the `rosbag2` metadata record) and its metadata.yaml are checked instead.
"""

from __future__ import annotations

import contextlib
import io
import math
import re
import shutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from agent.contract import Cmd
from agent.core.build import initial_state
from agent.core.records import TickInputs
from agent.core.step import step
from agent.runtime.mcap_log import LogRotation, McapLog
from agent.shell.tick_log import TickLogger
from mission_log import cli
from mission_log.reader import LogError, load_run
from mission_log.ros2_export import namespace
from sim_bridge.bridge import BridgeSettings, SimBridge
from sim_bridge.scenario import initial_estimates, select_scenario
from sim_bridge.world import streams

TICKS = 30
SCENARIO = """
name: ros2
base:
  duration: 3.0
  seed: 5
  world:
    vessels:
      - {id: "1", position: [-6.0, -7.0]}
      - {id: "2", position: [6.0, 6.0]}
      - {id: "3", position: [-10.0, 3.0]}
    target: {kind: constant_velocity, position: [1.0, 1.0], velocity: [0.5, 0.0]}
  agent: {control: {radius: 5.0}}
"""
# ROS 2's rules for a topic name: absolute, tokens of letters, digits and '_' that do not start with a digit.
ROS_TOPIC = re.compile(r"(/[A-Za-z_][A-Za-z0-9_]*)+")


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory) -> Path:
    """Three agents' logs, written by TickLogger as the agent process writes them, stepping the sim bridge's
    world, whose `/truth` the bridge logs each tick. Vessel 2 has no odometry at tick 5 and vessel 1 gets the
    same odometry sample at ticks 7 and 8 (a sensor slower than the ticks); vessel 3's log rotates into parts."""
    folder = tmp_path_factory.mktemp("ros2")
    (folder / "ros2.yaml").write_text(SCENARIO)
    _, scenario = select_scenario(folder / "ros2.yaml")
    bridge = SimBridge(scenario, BridgeSettings(log=str(folder / "sim.mcap")))
    world = bridge.world
    params = scenario.agent_params()
    states = {i: initial_state(i, params, start)
              for i, start in initial_estimates(scenario, world.truth(), streams(scenario.seed).initial).items()}
    rotation = {"3": LogRotation(max_file_mb=0.03, max_total_mb=None)}
    logs = {i: McapLog(folder / f"agent-{i}.mcap", flush_seconds=0.0, metadata={"vessel": i},
                       rotation=rotation.get(i)) for i in states}
    writers = {i: TickLogger(logs[i], i, params.control.radius) for i in states}
    sent, held = {}, None
    for k in range(TICKS):
        readings, stamp = world.sense(), world.time_ns
        bridge._log_tick(stamp)
        commands, outgoing = {}, {}
        for i, state in states.items():
            reading = readings[i]
            odometry, time = reading.odometry, world.time
            if (i, k) == ("2", 5):
                odometry = None
            if (i, k) == ("1", 7):
                held = odometry
            if (i, k) == ("1", 8):
                odometry, time = held, held.stamp
            inputs = TickInputs(time=time, odometry=odometry, ranges=reading.ranges,
                                shares={j: s for j, s in sent.items() if j != i}, bearing=reading.bearing,
                                obstacle_points=reading.obstacle_points)
            states[i], output = step(params, state, inputs)
            command = Cmd(stamp_ns=stamp, seq=k, sender=i, surge=output.command.surge,
                          yaw_rate=output.command.yaw_rate)
            writers[i].tick(stamp, inputs, output, command)
            commands[i] = output.command
            if output.share is not None:
                outgoing[i] = output.share
        sent = outgoing
        world.step(commands)
    for log in logs.values():
        log.close()
    bridge.log.close()
    assert len(logs["3"].parts) >= 3     # the rotated log's parts are there to be joined (and one lost below)
    return folder


@pytest.fixture(scope="module")
def exported(run_folder, tmp_path_factory) -> tuple[Path, str]:
    """(the bag's folder, what the command printed) of `usv-log export --ros2 RUN`, in process."""
    out = tmp_path_factory.mktemp("bag") / "bag"
    code, printed, errors = run_cli("export", "--ros2", str(run_folder), "--out", str(out))
    assert code == 0 and errors == "", errors
    return out, printed


def run_cli(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(list(args))
    return code, out.getvalue(), err.getvalue()


def decoded(bag: Path) -> dict[str, list[tuple[int, str, object]]]:
    """topic -> [(log time ns, schema name, message)] of the bag's MCAP file, decoded by mcap-ros2-support."""
    (path,) = bag.glob("*.mcap")
    found = defaultdict(list)
    with path.open("rb") as handle:
        for schema, channel, message, ros in make_reader(handle, decoder_factories=[DecoderFactory()]) \
                .iter_decoded_messages():
            found[channel.topic].append((message.log_time, schema.name, ros))
    return dict(found)


def seconds(stamp) -> float:
    assert 0 <= stamp.nanosec < 1_000_000_000
    return stamp.sec + stamp.nanosec * 1e-9


def yaw_of(q) -> float:
    """The rotation about z of a quaternion that turns about z only."""
    assert q.x == 0.0 and q.y == 0.0 and q.z ** 2 + q.w ** 2 == pytest.approx(1.0, abs=1e-15)
    return 2.0 * math.atan2(q.z, q.w)


def same_angle(a: float, b: float) -> bool:
    return abs(math.remainder(a - b, 2.0 * math.pi)) < 1e-12


def covariance_block(covariance) -> np.ndarray:
    """The (x, y) block of a 6x6 row-major covariance, after checking that everything else is zero."""
    full = np.asarray(covariance, dtype=float).reshape(6, 6)
    rest = full.copy()
    rest[:2, :2] = 0.0
    assert not rest.any()
    return full[:2, :2]


def test_the_bag_holds_each_vessels_odometry_commands_estimates_and_the_truth(exported, run_folder):
    bag, printed = exported
    messages = decoded(bag)
    run = load_run(run_folder)
    expected = {"/tf": "tf2_msgs/msg/TFMessage", "/truth/target": "nav_msgs/msg/Odometry"}
    for i in ("1", "2", "3"):
        expected |= {f"/usv_{i}/odom": "nav_msgs/msg/Odometry", f"/usv_{i}/cmd_vel": "geometry_msgs/msg/Twist",
                     f"/usv_{i}/estimate/target": "geometry_msgs/msg/PoseWithCovarianceStamped",
                     f"/truth/usv_{i}": "nav_msgs/msg/Odometry"}
        expected |= {f"/usv_{i}/estimate/usv_{j}": "geometry_msgs/msg/PoseWithCovarianceStamped"
                     for j in ("1", "2", "3") if j != i}
    assert {topic: {name for _, name, _ in found} for topic, found in messages.items()} == \
           {topic: {name} for topic, name in expected.items()}
    assert all(ROS_TOPIC.fullmatch(topic) for topic in messages)
    for topic, found in messages.items():
        assert f"  {topic}  {expected[topic]}  {len(found)}\n" in printed
        times = [t for t, _, _ in found]
        assert times == sorted(times)
    assert len(run.vessels["3"].parts) >= 3 and len(messages["/usv_3/cmd_vel"]) == TICKS   # the parts joined


def test_odometry_is_each_fresh_sample_once_in_the_vessels_odom_frame(exported, run_folder):
    messages = decoded(exported[0])
    run = load_run(run_folder)
    for i, log in run.vessels.items():
        samples = [(t, m["odometry"]) for t, m in log.topic("inputs") if m["odometry"] is not None]
        fresh = [(t, o) for n, (t, o) in enumerate(samples) if n == 0 or o["stamp"] != samples[n - 1][1]["stamp"]]
        assert len(fresh) == {"1": TICKS - 1, "2": TICKS - 1, "3": TICKS}[i]   # 1: a sample twice; 2: one missed
        odometry = messages[f"/usv_{i}/odom"]
        assert len(odometry) == len(fresh)
        for (t, o), (log_time, _, message) in zip(fresh, odometry, strict=True):
            assert log_time == t
            assert seconds(message.header.stamp) == pytest.approx(o["stamp"], abs=1e-9)
            assert message.header.frame_id == f"usv_{i}/odom" and message.child_frame_id == f"usv_{i}/base_link"
            p = message.pose.pose.position
            assert (p.x, p.y, p.z) == (o["position"][0], o["position"][1], 0.0)
            assert same_angle(yaw_of(message.pose.pose.orientation), o["heading"])
            assert not np.any(message.pose.covariance) and not np.any(message.twist.covariance)
            twist = message.twist.twist
            assert (twist.linear.x, twist.linear.y, twist.linear.z, twist.angular.z) == (0.0, 0.0, 0.0, 0.0)


def test_commands_are_twists_of_surge_and_yaw_rate(exported, run_folder):
    messages = decoded(exported[0])
    for i, log in load_run(run_folder).vessels.items():
        commands = log.topic("cmd")
        assert len(commands) == TICKS
        for (t, command), (log_time, _, twist) in zip(commands, messages[f"/usv_{i}/cmd_vel"], strict=True):
            assert log_time == t
            assert (twist.linear.x, twist.angular.z) == (command["surge"], command["yaw_rate"])
            assert (twist.linear.y, twist.linear.z, twist.angular.x, twist.angular.y) == (0.0, 0.0, 0.0, 0.0)
        assert any(command["surge"] != 0.0 for _, command in commands)   # the values compared are not all zero


def test_estimates_are_poses_with_their_covariance_at_minus_p_hat(exported, run_folder):
    messages = decoded(exported[0])
    for i, log in load_run(run_folder).vessels.items():
        records = log.topic("estimates")
        assert len(records) >= TICKS - 1
        for j in {"1", "2", "3"} - {i}:
            poses = messages[f"/usv_{i}/estimate/usv_{j}"]
            wanted = [(t, r) for t, r in records if j in r["neighbours"]]
            assert len(poses) == len(wanted) > 0
            for (t, record), (log_time, _, pose) in zip(wanted, poses, strict=True):
                p_ij, covariance = record["neighbours"][j]["position"], record["neighbours"][j]["covariance"]
                assert log_time == t and pose.header.frame_id == f"usv_{i}/odom_aligned"
                assert seconds(pose.header.stamp) == pytest.approx(record["time"], abs=1e-9)
                position = pose.pose.pose.position
                assert (position.x, position.y, position.z) == (-p_ij[0], -p_ij[1], 0.0)
                assert yaw_of(pose.pose.pose.orientation) == 0.0
                assert covariance_block(pose.pose.covariance).tolist() == [covariance[:2], covariance[2:]]
        targets = messages[f"/usv_{i}/estimate/target"]
        wanted = [(t, r) for t, r in records if r["target_state"] is not None]
        assert len(targets) == len(wanted) > 0
        for (t, record), (log_time, _, pose) in zip(wanted, targets, strict=True):
            x_io, full = record["target_state"], record["target_covariance"]
            position = pose.pose.pose.position
            assert log_time == t and (position.x, position.y) == (-x_io[0], -x_io[1])
            # P_io is 4x4 over [p_x, p_y, v_x, v_y], row by row: its position block is entries 0, 1, 4, 5.
            assert covariance_block(pose.pose.covariance).tolist() == [[full[0], full[1]], [full[4], full[5]]]


def test_the_truth_is_in_world_stamped_at_its_tick(exported, run_folder):
    messages = decoded(exported[0])
    truth = load_run(run_folder).sim.messages("/truth")
    assert len(truth) == TICKS
    for i in ("1", "2", "3"):
        for (t, record), (log_time, _, odometry) in zip(truth, messages[f"/truth/usv_{i}"], strict=True):
            assert log_time == t and seconds(odometry.header.stamp) == pytest.approx(t * 1e-9, abs=1e-12)
            assert odometry.header.frame_id == "world" and odometry.child_frame_id == f"truth/usv_{i}"
            p = odometry.pose.pose.position
            assert [p.x, p.y] == record["vessels"][i]["position"]
            assert same_angle(yaw_of(odometry.pose.pose.orientation), record["vessels"][i]["heading"])
    for (t, record), (log_time, _, odometry) in zip(truth, messages["/truth/target"], strict=True):
        p, v = odometry.pose.pose.position, odometry.twist.twist.linear
        assert log_time == t and [p.x, p.y] == record["target"] and [v.x, v.y] == record["target_velocity"]
        assert record["target_velocity"] == [0.5, 0.0]


def test_the_frames_on_tf_are_the_odometry_the_estimates_and_the_truth(exported, run_folder):
    messages = decoded(exported[0])
    run = load_run(run_folder)
    seen = {}
    for _, _, tf in messages["/tf"]:
        for transform in tf.transforms:
            key = (round(seconds(transform.header.stamp), 6), transform.header.frame_id, transform.child_frame_id)
            move = transform.transform
            assert move.translation.z == 0.0 and key not in seen
            seen[key] = (move.translation.x, move.translation.y, yaw_of(move.rotation))
    wanted = {}
    for i, log in run.vessels.items():
        ns = f"usv_{i}"
        for _, inputs in log.topic("inputs"):
            o = inputs["odometry"]
            if o is not None:
                stamp = round(o["stamp"], 6)
                wanted[(stamp, f"{ns}/odom", f"{ns}/odom_aligned")] = (*o["position"], 0.0)
                wanted[(stamp, f"{ns}/odom_aligned", f"{ns}/base_link")] = (0.0, 0.0, o["heading"])
        for _, record in log.topic("estimates"):
            # A tick at the time of the last (vessel 1's tick 8) adds none: tf2 keeps one per frame and stamp.
            stamp = round(record["time"], 6)
            for j, n in record["neighbours"].items():
                wanted.setdefault((stamp, f"{ns}/odom_aligned", f"{ns}/estimate/usv_{j}"),
                                  (-n["position"][0], -n["position"][1], 0.0))
            if record["target_state"] is not None:
                x_io = record["target_state"]
                wanted.setdefault((stamp, f"{ns}/odom_aligned", f"{ns}/estimate/target"),
                                  (-x_io[0], -x_io[1], 0.0))
    for t, truth in run.sim.messages("/truth"):
        stamp = round(t * 1e-9, 6)
        wanted[(stamp, "world", "truth/target")] = (*truth["target"], 0.0)
        for i, state in truth["vessels"].items():
            wanted[(stamp, "world", f"truth/usv_{i}")] = (*state["position"], state["heading"])
    assert seen.keys() == wanted.keys()
    for key, (x, y, yaw) in wanted.items():
        assert seen[key][:2] == (x, y) and same_angle(seen[key][2], yaw), key


def test_the_bag_is_in_rosbag2s_mcap_profile_with_its_metadata(exported):
    bag, _ = exported
    (path,) = bag.glob("*.mcap")
    with path.open("rb") as handle:
        reader = make_reader(handle)
        header, summary = reader.get_header(), reader.get_summary()
        metadata = {record.name: record.metadata for record in reader.iter_metadata()}
    assert header.profile == "ros2"
    assert {schema.encoding for schema in summary.schemas.values()} == {"ros2msg"}
    assert {channel.message_encoding for channel in summary.channels.values()} == {"cdr"}
    assert {index.compression for index in summary.chunk_indexes} == {"zstd"}     # rosbag2's MCAP reads zstd
    info = yaml.safe_load(metadata["rosbag2"]["serialized_metadata"])
    on_disk = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert on_disk["version"] == info["version"] == 8 and on_disk["storage_identifier"] == "mcap"
    assert on_disk["relative_file_paths"] == [path.name]
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in on_disk["topics_with_message_count"]}
    assert counts == {channel.topic: summary.statistics.channel_message_counts[channel.id]
                      for channel in summary.channels.values()}
    assert on_disk["message_count"] == summary.statistics.message_count == sum(counts.values())
    for topic in on_disk["topics_with_message_count"]:
        (channel,) = [c for c in summary.channels.values() if c.topic == topic["topic_metadata"]["name"]]
        assert summary.schemas[channel.schema_id].name == topic["topic_metadata"]["type"]
        assert topic["topic_metadata"]["serialization_format"] == "cdr"
        assert topic["topic_metadata"]["type_description_hash"].startswith("RIHS01_")
    assert "usv_partial" not in on_disk["custom_data"] and on_disk["custom_data"]["usv_source"]


def test_a_missing_part_and_a_cut_log_are_exported_as_far_as_they_go_and_say_so(run_folder, tmp_path):
    damaged = tmp_path / "run"
    shutil.copytree(run_folder, damaged)
    (damaged / "agent-3.part0001.mcap").unlink()
    whole = (damaged / "agent-2.mcap").read_bytes()
    (damaged / "agent-2.mcap").write_bytes(whole[:len(whole) * 2 // 3])
    code, printed, errors = run_cli("export", "--ros2", str(damaged))
    assert code == 0, errors
    assert "agent-2.mcap is unfinished" in errors and "part(s) 1 of this log are not among the files" in errors
    assert "usv-log export: partial: agent-2.mcap cut short; agent-3.mcap: part(s) 1 missing" in errors
    bag = damaged / "ros2"
    assert f"-> {bag}" in printed
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["custom_data"]["usv_partial"] == "agent-2.mcap cut short; agent-3.mcap: part(s) 1 missing"
    messages = decoded(bag)
    run = load_run(damaged)
    for i in ("2", "3"):
        commands = run.vessels[i].topic("cmd")
        assert 0 < len(commands) < TICKS
        assert [(t, m["surge"]) for t, m in commands] == \
               [(t, twist.linear.x) for t, _, twist in messages[f"/usv_{i}/cmd_vel"]]
    assert len(messages["/usv_1/cmd_vel"]) == TICKS
    # A second export beside the first is numbered, not written over it.
    assert run_cli("export", "--ros2", str(damaged))[0] == 0 and (damaged / "ros2-2" / "metadata.yaml").is_file()


def test_bad_paths_get_one_line_and_leave_nothing(run_folder, tmp_path):
    for args, says in [
        ((str(tmp_path / "nowhere"),), "nowhere: no such file"),
        ((str(tmp_path),), "no .mcap files in this folder"),
        ((str(run_folder), "--out", str(run_folder)), "already exists; not overwriting"),
    ]:
        code, printed, errors = run_cli("export", "--ros2", *args)
        assert code == 2 and printed == "" and errors.count("\n") == 1 and says in errors, errors
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(SystemExit) as exited:   # the format must be said
        run_cli("export", str(run_folder))
    assert exited.value.code == 2


def test_a_message_the_export_cannot_read_is_one_line_naming_its_file_and_topic(tmp_path):
    for name, topic, message, says in [
        ("bad", "usv/9/cmd", {"yaw_rate": 0.1},
         "usv/9/cmd: a message of a shape the export cannot read (KeyError"),
        ("early", "/9/inputs", {"odometry": {"stamp": -0.5, "position": [0.0, 0.0], "heading": 0.0}},
         "/9/inputs: time -0.5 s cannot be a ROS 2 stamp"),
        ("empty", "/9/summary", {"ticks": 0}, "no odometry, command, estimate or truth to export"),
    ]:
        folder = tmp_path / name
        folder.mkdir()
        with McapLog(folder / "agent-9.mcap", metadata={"vessel": "9"}) as log:
            log.log(topic, message, log_time_ns=1_000)
        code, printed, errors = run_cli("export", "--ros2", str(folder))
        assert code == 2 and printed == "" and errors.count("\n") == 1 and says in errors, errors
        assert [path.name for path in folder.iterdir()] == ["agent-9.mcap"]     # no half-written bag left


def test_without_the_ros2_extra_the_export_says_how_to_install_it(run_folder, tmp_path, monkeypatch):
    for name in [name for name in sys.modules if name.split(".")[0] == "rosbags"] + ["rosbags"]:
        monkeypatch.setitem(sys.modules, name, None)      # importing it now raises ImportError
    code, _, errors = run_cli("export", "--ros2", str(run_folder), "--out", str(tmp_path / "bag"))
    assert code == 2
    assert errors == "usv-log: usv-log export --ros2 needs rosbags: pip install 'usv-circumnav[ros2]'\n"
    assert not (tmp_path / "bag").exists()


def test_vessel_ids_become_ros_names(tmp_path):
    assert [namespace(v) for v in ("1", "boat-7", "A_2")] == ["usv_1", "usv_boat_7", "usv_A_2"]
    for bad in ("a--b", "_x"):   # usv_a__b, usv__x: a ROS 2 name has no '__'
        with pytest.raises(LogError, match="no ROS 2 name"):
            namespace(bad)
    for vessel in ("a-b", "a_b"):
        with McapLog(tmp_path / f"agent-{vessel}.mcap", metadata={"vessel": vessel}) as log:
            log.log(f"usv/{vessel}/cmd", {"surge": 1.0, "yaw_rate": 0.0}, log_time_ns=1_000)
    code, _, errors = run_cli("export", "--ros2", str(tmp_path))
    assert code == 2 and "vessels a-b and a_b make the same ROS 2 name usv_a_b\n" in errors, errors
    assert not (tmp_path / "ros2").exists()


@pytest.mark.slow   # a process: the command as a user types it
def test_the_command_line_exports_a_run(run_folder, tmp_path):
    out = tmp_path / "bag"
    result = subprocess.run([sys.executable, "-m", "mission_log", "export", "--ros2", str(run_folder), "--out",
                             str(out)], capture_output=True, text=True, check=False, timeout=240)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("usv-log export: ") and f"-> {out}" in result.stdout
    assert sum(len(found) for found in decoded(out).values()) == \
           yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["message_count"]
