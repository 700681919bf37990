"""`usv-log` on the logs of a short real fleet run (separate processes over Zenoh, made once per module)."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("zenoh")

from conftest import wait_until

from mission_log.metrics import agreement, innovation_statistics, run_metrics
from mission_log.reader import LogError, RunLog, VesselLog, load_run, read_log
from mission_log.replay import replay
from mission_log.summary import run_summary, topic_statistics
from sim_bridge.fleet import free_port

TICKS = 121   # the short run of conftest.fleet_run: 12 s at 10 Hz


def usv_log(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mission_log", *args], capture_output=True, text=True, check=False,
                          timeout=240)


def test_summary_counts_every_message_of_every_process(fleet_run):
    folder, _ = fleet_run
    summary = run_summary(load_run(folder))
    assert sorted(summary["vessels"]) == ["1", "2", "3"]
    for vessel, s in summary["vessels"].items():
        assert s["ticks"] == TICKS and not s["unfinished"] and not any(s["refused"].values()) and s["overruns"] == 0
        assert s["duration_s"] == pytest.approx(12.0)
        for topic in (f"usv/{vessel}/cmd", f"usv/{vessel}/status", f"/{vessel}/inputs", f"/{vessel}/tf"):
            stats = s["topics"][topic]
            assert stats["messages"] == TICKS and stats["gaps"] == 0
            assert stats["rate_hz"] == pytest.approx(10.0)        # sim time: exactly one per 0.1 s
        assert s["topics"][f"/{vessel}/scene"]["messages"] == 13   # once a second, 0 to 12 s
        assert sum(row["ticks"] for row in s["health_over_time"]) == TICKS
        assert s["cpu_ms_per_tick"] > 0
        assert s["reaction_ms"]["ticks"] == TICKS and 0 < s["reaction_ms"]["p50"] <= s["reaction_ms"]["p99"]
    assert summary["sim"]["ticks"] == TICKS and summary["sim"]["missed_commands"] == 0
    shown = usv_log("summary", str(folder))
    assert shown.returncode == 0, shown.stderr
    assert "| 1 | 0.0 | 12.0 | 121 |" in shown.stdout and "## Sim bridge" in shown.stdout
    reaction = summary["vessels"]["1"]["reaction_ms"]
    assert f"| {reaction['p50']:.2f} / {reaction['p99']:.2f} | complete |" in shown.stdout, shown.stdout


def test_summary_shows_each_pairs_observability(fleet_run):
    """Each vessel's two pairs: the share of ticks observable, when first, the spans not, the last spread; the
    status says how many pairs fall short and which is the weakest, the same as the estimates."""
    folder, _ = fleet_run
    run = load_run(folder)
    summary = run_summary(run)
    for vessel, s in summary["vessels"].items():
        pairs = s["observability"]
        assert sorted(pairs) == sorted({"1", "2", "3"} - {vessel})
        for pair in pairs.values():
            assert 0 < pair["ticks"] <= TICKS and 0.0 <= pair["observable_fraction"] <= 1.0
            low, high = pair["final_excitation"]
            assert 0.0 <= low <= high
            assert pair["final"] in ("observable", "mirror-ambiguous", "unobservable")
            observable = pair["observable_fraction"] * pair["ticks"]
            not_observable = sum(round((end - start) / 0.1) for start, end, _ in pair["not_observable"])
            # Each span runs to the next verdict's tick (or to the last tick, which then is not counted).
            assert not_observable in (pair["ticks"] - round(observable), pair["ticks"] - round(observable) - 1)
        log = run.vessels[vessel]
        last_status, last_estimates = log.last(f"usv/{vessel}/status"), log.last(f"/{vessel}/estimates")
        verdicts = [n["observability"] for n in last_estimates["neighbours"].values()]
        assert last_status["health"]["pairs_mirror_ambiguous"] == verdicts.count("mirror-ambiguous")
        assert last_status["health"]["pairs_unobservable"] == verdicts.count("unobservable")
        weakest = last_status["weakest_pair"]
        assert weakest["excitation"] == min(n["excitation"][0] for n in last_estimates["neighbours"].values())
    shown = usv_log("summary", str(folder))
    assert shown.returncode == 0, shown.stderr
    assert shown.stdout.count("Pair observability") == 3 and "| last verdict |" in shown.stdout


def test_a_gap_in_a_topic_is_found():
    stamps = [k * 100_000_000 for k in range(100) if not 30 <= k < 40]    # 10 Hz with 1 s missing
    stats = topic_statistics([(t, {}) for t in stamps])
    assert stats["messages"] == 90 and stats["gaps"] == 1
    assert stats["largest_gap_s"] == pytest.approx(1.1)


def test_metrics_from_the_logs_equal_the_in_process_runner(fleet_run):
    # The fleet over Zenoh in lockstep computes what the in-process runner computes, so the paper's metrics
    # worked out from the logs must equal the runner's, which come from its own arrays by another route.
    folder, scenario_path = fleet_run
    from lab.harness.runner import run
    from sim_bridge.scenario import select_scenario

    _, scenario = select_scenario(scenario_path)
    expected = run(scenario).metrics
    measured = run_metrics(load_run(folder))["truth"]
    for name in ("mean_e_ij", "mean_e_io", "mean_e_c"):
        assert measured[name] == pytest.approx(getattr(expected, name), abs=1e-9), name
    assert measured["settling_time"] == pytest.approx(expected.settling_time)


def test_metrics_without_truth_say_so_and_check_the_vessels_against_each_other(fleet_run, tmp_path):
    folder, _ = fleet_run
    for path in folder.glob("agent-*.mcap"):
        shutil.copy(path, tmp_path / path.name)
    run = load_run(tmp_path)
    assert not run.has_truth
    result = run_metrics(run)
    assert result["truth"] is None
    # Pair agreement straight from the raw estimates of vessels 1 and 2.
    one, two = dict(run.vessels["1"].topic("estimates")), dict(run.vessels["2"].topic("estimates"))
    gaps = [math.hypot(*(np.array(one[t]["neighbours"]["2"]["position"]) + two[t]["neighbours"]["1"]["position"]))
            for t in sorted(one.keys() & two.keys())
            if "2" in one[t]["neighbours"] and "1" in two[t]["neighbours"]]
    pair = result["agreement"]["pairs"]["1-2"]
    assert pair["ticks"] == len(gaps) and pair["mean_m"] == pytest.approx(np.mean(gaps))
    # The vessels fuse their pair estimates symmetrically, so each is nearly the other's opposite.
    assert pair["mean_m"] < 0.05
    shown = usv_log("metrics", str(tmp_path))
    assert shown.returncode == 0 and "No ground truth" in shown.stdout and "| 1-2 |" in shown.stdout


def _estimates(*outcomes: tuple[float, float, bool], bearing=None) -> dict:
    return {"neighbours": {"2": {"position": [1.0, 0.0], "outcomes": [
        {"stamp": 0.0, "range": 1.0, "accepted": a, "reason": "", "iterations": 1, "innovation": i,
         "innovation_variance": v, "weight": 1.0} for i, v, a in outcomes]}},
        "target_state": None, "bearing": bearing}


def test_innovation_statistics_of_known_innovations(tmp_path):
    # NIS 1 and 4 (innovations 1 and 2 over unit variance); the refused update does not count. Bearing NIS 9.
    log = VesselLog(tmp_path / "x.mcap", {}, {"/1/estimates": [
        (0, _estimates((1.0, 1.0, True), (5.0, 1.0, False))),
        (1, _estimates((2.0, 1.0, True), bearing={"accepted": True, "innovation": 3.0, "innovation_variance": 1.0,
                                                  "reason": ""}))]}, vessel="1")
    stats = innovation_statistics(RunLog("x", {"1": log}))["1"]
    assert stats["relative"]["2"]["updates"] == 2
    assert stats["relative"]["2"]["mean_nis"] == pytest.approx(2.5)
    assert stats["relative"]["2"]["within_95"] == pytest.approx(0.5)      # 4 > 3.84
    assert stats["target"] == {"updates": 1, "mean_nis": pytest.approx(9.0), "within_95": 0.0}
    assert agreement(RunLog("x", {"1": log}))["pairs"] == {}


def test_plot_writes_the_figures_with_and_without_truth(fleet_run, tmp_path):
    folder, _ = fleet_run
    made = usv_log("plot", str(folder), "--out", str(tmp_path / "all"))
    assert made.returncode == 0, made.stderr
    for name in ("trajectories.png", "errors.png", "ranges.png"):
        assert (tmp_path / "all" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    agents = [str(p) for p in sorted(folder.glob("agent-*.mcap"))]
    made = usv_log("plot", *agents, "--out", str(tmp_path / "boats"))
    assert made.returncode == 0, made.stderr
    assert (tmp_path / "boats" / "ranges.png").exists() and not (tmp_path / "boats" / "errors.png").exists()


def test_replay_with_the_same_settings_reproduces_the_recording_exactly(fleet_run, tmp_path):
    folder, _ = fleet_run
    result = replay(folder / "agent-2.mcap", tmp_path / "again.mcap")
    assert result.ticks == TICKS
    assert result.commands_identical == result.commands_compared == TICKS
    assert result.estimates_identical == TICKS
    recorded, again = read_log(folder / "agent-2.mcap"), read_log(tmp_path / "again.mcap")
    for topic in ("usv/2/cmd", "/2/estimates", "/2/tf", "/2/inputs"):
        before, after = recorded.messages(topic), again.messages(topic)
        assert len(before) == len(after) == TICKS
        if topic == "usv/2/cmd":
            assert [(t, m["surge"], m["yaw_rate"]) for t, m in before] == [(t, m["surge"], m["yaw_rate"]) for t, m in after]
        else:
            assert before == after, topic


def test_a_replay_started_mid_mission_gives_the_recorded_outputs_from_there(fleet_run, tmp_path):
    """The agent saves its core's state every 50 ticks (after ticks 0, 50, 100); --start 7.3 resumes after
    tick 50, 5.0 s after the first tick, and every tick from 51 on is the recorded one, bit for bit."""
    folder, _ = fleet_run
    recorded = read_log(folder / "agent-3.mcap")
    saved = recorded.topic("state")
    first = recorded.topic("inputs")[0][0]
    assert [round((stamp - first) * 1e-9, 6) for stamp, _ in saved] == [0.0, 5.0, 10.0]
    shown = usv_log("replay", str(folder / "agent-3.mcap"), "--out", str(tmp_path / "mid.mcap"), "--start", "7.3")
    assert shown.returncode == 0, shown.stderr
    assert f"{TICKS - 51} ticks from the state saved at 5.0 s" in shown.stdout
    again = read_log(tmp_path / "mid.mcap")
    for topic in ("/3/estimates", "/3/tf"):
        assert again.messages(topic) == recorded.messages(topic)[51:], topic
    after = [(t, m["surge"], m["yaw_rate"]) for t, m in again.messages("usv/3/cmd")]
    assert after == [(t, m["surge"], m["yaw_rate"]) for t, m in recorded.messages("usv/3/cmd")[51:]]
    result = replay(folder / "agent-3.mcap", tmp_path / "mid2.mcap", start=7.3)
    assert result.ticks == result.commands_identical == result.estimates_identical == TICKS - 51
    # Before the first saved state there is nothing to resume from but the beginning.
    from_start = replay(folder / "agent-3.mcap", tmp_path / "start.mcap", start=0.0)
    assert from_start.resumed_at is None and from_start.ticks == TICKS
    wrong = usv_log("replay", str(folder / "agent-3.mcap"), "--out", str(tmp_path / "x.mcap"), "--start", "-1")
    assert wrong.returncode == 2 and "--start" in wrong.stderr


def test_replay_with_other_settings_changes_the_outputs(fleet_run, tmp_path):
    folder, _ = fleet_run
    shown = usv_log("replay", str(folder / "agent-1.mcap"), "--out", str(tmp_path / "kf.mcap"),
                    "--set", "relative.estimator=kf")
    assert shown.returncode == 0, shown.stderr
    assert '"estimator": "kf"' in shown.stdout
    result = run_summary(load_run(tmp_path / "kf.mcap"))["vessels"]["1"]
    assert result["ticks"] == TICKS
    log = read_log(tmp_path / "kf.mcap")
    assert json.loads(log.metadata["settings"])["agent"]["relative"]["estimator"] == {"name": "kf"}
    changed = replay(folder / "agent-1.mcap", tmp_path / "kf2.mcap", {"relative": {"estimator": "kf"}})
    assert changed.estimates_identical < TICKS


def test_bad_input_gets_a_clear_error(fleet_run, tmp_path):
    folder, _ = fleet_run
    wrong = usv_log("replay", str(folder / "agent-1.mcap"), "--out", str(tmp_path / "x.mcap"),
                    "--set", "relative.estimator=nonsense")
    assert wrong.returncode == 2 and "relative.estimator" in wrong.stderr and "Traceback" not in wrong.stderr
    wrong = usv_log("replay", str(folder / "agent-1.mcap"), "--out", str(tmp_path / "x.mcap"), "--set", "novalue")
    assert wrong.returncode == 2 and "key.path=value" in wrong.stderr
    (tmp_path / "bad.yaml").write_text("relative: {estimatr: kf}\n", encoding="utf-8")   # an AgentParams file
    wrong = usv_log("replay", str(folder / "agent-1.mcap"), "--out", str(tmp_path / "x.mcap"), "--params",
                    str(tmp_path / "bad.yaml"))
    assert wrong.returncode == 2 and f"{tmp_path / 'bad.yaml'}: field 'relative.estimatr': unknown key" in wrong.stderr
    with pytest.raises(LogError, match="not an agent's log"):
        replay(folder / "sim.mcap", tmp_path / "y.mcap")
    (tmp_path / "junk.mcap").write_bytes(b"not a log at all")
    wrong = usv_log("summary", str(tmp_path / "junk.mcap"))
    assert wrong.returncode == 2 and "not an MCAP file" in wrong.stderr
    wrong = usv_log("metrics", str(tmp_path / "nothing-here"))
    assert wrong.returncode == 2 and "no such file" in wrong.stderr


def test_the_log_of_an_agent_killed_with_sigkill_is_read_up_to_its_last_chunk(tmp_path):
    """A wall-clock agent is killed after about 3 s of ticks. Its file is read up to its last chunk, and
    that chunk is at most about a second older than the agent's last published tick (the writer flushes
    at least once a second): judged against the agent's own stamps, not the test's clock."""
    import signal

    import yaml

    zenoh = pytest.importorskip("zenoh")
    log_path = tmp_path / "agent-7.mcap"
    config = tmp_path / "node.yaml"
    port = free_port()
    config.write_text(yaml.safe_dump({"clock": "wall", "log": str(log_path),
                                      "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]}}))
    agent = subprocess.Popen([sys.executable, "-m", "agent", "--vessel", "7", "--config", str(config)],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    stamps = []
    session_config = zenoh.Config()
    session_config.insert_json5("scouting/multicast/enabled", "false")
    session_config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    try:
        with zenoh.open(session_config) as session:
            session.declare_subscriber("usv/7/status",
                                       lambda s: stamps.append(json.loads(s.payload.to_bytes())["stamp_ns"]))
            assert wait_until(lambda: len(stamps) >= 30 or agent.poll() is not None, timeout=60)
            agent.send_signal(signal.SIGKILL)
            agent.wait()
    finally:
        if agent.poll() is None:
            agent.kill()
            agent.wait()
    log = read_log(log_path)
    assert log.unfinished and log.vessel == "7"
    ticks = log.messages("/7/inputs")
    assert len(ticks) >= 10
    assert (stamps[-1] - ticks[-1][0]) * 1e-9 < 1.5
    shown = usv_log("summary", str(log_path))
    assert shown.returncode == 0 and "unfinished" in shown.stderr and "**unfinished**" in shown.stdout


WALL_START_NS = 1_700_000_000_123_456_789   # a wall-clock run: log times are Unix times in ns


def _wall_clock_run(folder):
    """A sim bridge's and one agent's logs stamped on the wall clock: vessel 1 is 8 m from the target for
    3 s, then on the 5 m circle; its estimates are exact."""
    from agent.runtime.mcap_log import McapLog

    with McapLog(folder / "sim.mcap", metadata={"scenario": "wall"}) as sim, \
            McapLog(folder / "agent-1.mcap", metadata={"vessel": "1"}) as agent:
        for k in range(100):
            t = WALL_START_NS + k * 100_000_000
            radius = 8.0 if k < 30 else 5.0
            sim.log("/truth", {"target": [0.0, 0.0], "vessels": {"1": {"position": [radius, 0.0]}}}, t)
            agent.log("/1/inputs", {"time": k * 0.1}, t)
            agent.log("/1/estimates", {"neighbours": {}, "target_state": [radius, 0.0, 0.0, 0.0]}, t)
    return load_run(folder)


def test_times_of_a_wall_clock_run_are_seconds_from_the_mission_start(tmp_path, capsys):
    """On the wall clock log times are Unix times: the settling time, the spans and the health windows are
    still seconds from the start (3.0 s here, not 1.7e9), and the start is given once as a UTC time."""
    from mission_log import cli
    from mission_log.summary import summary_markdown

    run = _wall_clock_run(tmp_path)
    truth = run_metrics(run, radius=5.0)["truth"]
    assert truth["settling_time"] == pytest.approx(3.0) and truth["start_ns"] == WALL_START_NS
    assert truth["mean_e_io"] == pytest.approx(0.0)
    summary = run_summary(run)
    vessel = summary["vessels"]["1"]
    assert summary["clock"] == "wall"
    assert vessel["from_s"] == pytest.approx(0.0) and vessel["to_s"] == pytest.approx(9.9)
    assert [row["from_s"] for row in vessel["health_over_time"]] == pytest.approx([0.0])
    assert "2023-11-14 22:13:20 UTC (wall clock)" in summary_markdown(summary)
    assert cli.main(["metrics", str(tmp_path), "--radius", "5"]) == 0
    assert "| 3.0 s after the start |" in capsys.readouterr().out


def test_the_logs_of_a_restarted_agent_are_read_as_one_vessel_in_time_order(tmp_path):
    """A restarted agent writes a second log (systemd, or the launcher's restart): usv-log joins the runs of
    one vessel in time order, and refuses two logs of one vessel that overlap in time."""
    from agent.runtime.mcap_log import McapLog

    def agent_log(name: str, ticks: range) -> None:
        with McapLog(tmp_path / name, metadata={"vessel": "1"}) as agent:
            for k in ticks:
                agent.log("/1/estimates", {"neighbours": {}, "target_state": [5.0, 0.0, 0.0, 0.0], "k": k},
                          WALL_START_NS + k * 100_000_000)

    agent_log("agent-1-restart1.mcap", range(50, 80))       # named to sort first: time decides, not names
    agent_log("agent-1.mcap", range(0, 30))
    run = load_run(tmp_path)
    vessel = run.vessels["1"]
    assert [m["k"] for _, m in vessel.topic("estimates")] == [*range(30), *range(50, 80)]
    assert [p.name for p in vessel.sessions] == ["agent-1.mcap", "agent-1-restart1.mcap"]
    from mission_log.summary import run_summary, summary_markdown
    page = summary_markdown(run_summary(run))
    assert "The agent ran 2 times (restarted), one log each, read in time order: `agent-1.mcap`, " \
           "`agent-1-restart1.mcap`." in page and "rotated" not in page
    agent_log("agent-1-again.mcap", range(70, 90))         # a second agent with id 1, at the same time
    with pytest.raises(LogError, match="a second log of vessel 1 that overlaps in time"):
        load_run(tmp_path)


def _set_radius_run(folder):
    """Two vessels on a 5 m circle for 2 s; then an operator's `set` takes r* to 8 m, which each agent moves
    to at 1 m per tick (vessel 2 a tick later), and both sail out to it, arriving 4 s after the set."""
    from agent.runtime.mcap_log import McapLog
    from agent.shell.tick_log import log_topic

    with McapLog(folder / "sim.mcap", metadata={"scenario": "set"}) as sim, \
            McapLog(folder / "agent-1.mcap", metadata={"vessel": "1"}) as one, \
            McapLog(folder / "agent-2.mcap", metadata={"vessel": "2"}) as two:
        for k in range(100):
            t = k * 100_000_000
            true_radius = 5.0 if k < 20 else min(8.0, 5.0 + 3.0 * (k - 20) / 40)
            sim.log("/truth", {"target": [0.0, 0.0], "vessels": {"1": {"position": [true_radius, 0.0]},
                                                                 "2": {"position": [-true_radius, 0.0]}}}, t)
            for vessel, log, delay in (("1", one, 0), ("2", two, 1)):
                wanted = 5.0 if k < 20 + delay else min(8.0, 5.0 + (k - 19 - delay))
                log.log(f"/{vessel}/inputs", {"time": k * 0.1}, t)
                log.log(log_topic(vessel, "status"), {"radius": wanted}, t)
    return load_run(folder)


def test_the_metrics_judge_settling_against_the_circle_in_force(tmp_path, capsys):
    """After `set radius=8` the fleet settles on 8 m: settling is judged against each vessel's r* at each
    moment (from its statuses), not against the configured 5 m, which would say it never settled."""
    from mission_log import cli
    from mission_log.metrics import circle_words, truth_metrics
    from mission_log.reader import radius_schedule

    run = _set_radius_run(tmp_path)
    schedule = radius_schedule(run)
    # r* of vessel 2 at 2.0 s (still 5 m), at 2.15 s (its first step, 6 m) and at the end (8 m).
    np.testing.assert_array_equal(schedule.at("2", np.array([20, 21, 22, 99]) * 100_000_000), [5.0, 6.0, 7.0, 8.0])
    assert schedule.changes() == [(pytest.approx(2.2), "1", 8.0), (pytest.approx(2.3), "2", 8.0)]
    truth = truth_metrics(run)
    # The true radius reaches 7.2 m (8 m less 10 %) at tick 20 + 40 * 2.2 / 3 = 49.33, so tick 50: 5.0 s.
    assert truth["settling_time"] == pytest.approx(5.0)
    assert truth["radius"] == 5.0 and circle_words(truth) == "r* = 5 m, 8 m from 2.2 s (vessel 1), 8 m from 2.3 s (vessel 2)"
    # A fixed r* for the whole run, as --radius asks: 5 m, never settled.
    assert truth_metrics(run, radius=5.0)["settling_time"] is None
    assert cli.main(["metrics", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| 5.0 s after the start |" in out and "8 m from 2.2 s (vessel 1)" in out
