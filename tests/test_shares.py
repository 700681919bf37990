"""Share format 2 (docs/contract.md, "Share format"): a share to each receiver on `usv/<i>/share/<j>`, holding
its own pair estimate only; the gate takes both formats alike, and only the transport differs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agent.contract import (
    ShareMessage,
    decode,
    encode,
    encode_per_pair,
    share_key,
    share_receivers,
    shares_for,
)
from agent.shell.gate import InputGate
from agent.shell.publish import Outbox, PairPublishers
from lab.benchmarks.shell import run_shells
from sim_bridge.scenario import select_scenario, with_duration

SCENARIOS = Path(__file__).resolve().parents[1] / "configs" / "scenarios"
NOW_NS = 10 * 10**9


def random_share(rng: np.random.Generator, sender: str, others: list[str], stamp_ns: int = NOW_NS,
                 antenna: bool = False) -> ShareMessage:
    """A valid share of `sender` with an estimate of each of `others`, its numbers drawn from `rng`."""
    def spd2():
        a = rng.normal(size=(2, 2))
        m = a @ a.T + 0.01 * np.eye(2)
        return [float(m[0, 0]), float(m[0, 1]), float(m[1, 1])]

    a = rng.normal(size=(4, 4))
    target_covariance = (a @ a.T + 0.1 * np.eye(4)).ravel().tolist()
    return ShareMessage.model_validate({
        "stamp_ns": stamp_ns, "seq": int(rng.integers(0, 1000)), "sender": sender,
        "position": rng.uniform(-50, 50, 2).tolist(), "heading": float(rng.uniform(-4, 4)),
        "velocity": rng.uniform(-2, 2, 2).tolist(), "phase": float(rng.uniform(-4, 4)),
        "target": rng.uniform(-20, 20, 4).tolist(), "target_covariance": target_covariance,
        "neighbours": {j: {"position": rng.uniform(-30, 30, 2).tolist(), "covariance": spd2(),
                           "stamp_ns": stamp_ns - int(rng.integers(0, 10**8))} for j in others},
        **({"antenna": rng.uniform(-1, 1, 2).tolist()} if antenna else {})})


def test_keys_of_both_formats_and_who_receives_them():
    assert share_key("3") == "usv/3/share" and share_key("3", "7") == "usv/3/share/7"
    assert shares_for("7") == "usv/*/share/7"
    assert share_receivers("usv/3/share/7") == "7" and share_receivers("usv/3/share") == "*"
    assert [share_receivers(k) for k in ("usv/3/cmd", "usv/3/share/7/x", "sim/clock", "usv/3")] == [None] * 4


def test_each_receivers_payload_is_the_share_with_its_own_estimate_only_byte_for_byte():
    rng = np.random.default_rng(32)
    for trial in range(50):
        n = int(rng.integers(2, 40))
        ids = [f"v{k}" for k in range(n)]
        sender, others = ids[0], ids[1:]
        with_estimates = [j for j in others if rng.random() < 0.8]
        message = random_share(rng, sender, with_estimates, antenna=bool(trial % 2))
        payloads = encode_per_pair(message, [*others, 'bad"id', ""])
        assert sorted(payloads) == sorted(others)   # ids that are no vessel ids are never sent to
        for j, payload in payloads.items():
            alone = message.model_copy(update={"neighbours": {k: e for k, e in message.neighbours.items() if k == j}})
            assert payload == encode(alone)
            decoded, reason = decode(ShareMessage, payload)
            assert reason == "" and decoded == alone
            assert len(payload) < len(encode(message)) or len(with_estimates) <= 1


def gate(receiver: str = "1") -> InputGate:
    return InputGate(receiver, known_peers=lambda: {"2", "3"})


def test_the_gate_takes_a_share_to_itself_and_refuses_one_to_another_vessel():
    rng = np.random.default_rng(1)
    message = random_share(rng, "2", ["1", "3"])
    payloads = encode_per_pair(message, ["1", "3"])
    g = gate()
    assert g.offer("usv/2/share/1", payloads["1"], NOW_NS * 1e-9)
    share = g.snapshot(NOW_NS * 1e-9).shares["2"]
    assert set(share.neighbours) == {"1"}
    np.testing.assert_array_equal(share.neighbours["1"][:2], message.neighbours["1"].position)
    assert not g.offer("usv/2/share/3", payloads["3"], NOW_NS * 1e-9)
    assert not g.offer("usv/2/share/1/x", payloads["1"], NOW_NS * 1e-9)
    assert g.rejected["unexpected_key"] == 2


def test_a_share_to_one_receiver_with_other_vessels_estimates_is_malformed_the_broadcast_one_is_not():
    rng = np.random.default_rng(2)
    message = random_share(rng, "2", ["1", "3"])
    whole = encode(message)
    g = gate()
    assert not g.offer("usv/2/share/1", whole, NOW_NS * 1e-9)
    assert g.rejected["malformed"] == 1 and "other vessels' estimates" in g.recent_reasons[-1]
    assert g.offer("usv/2/share", whole, NOW_NS * 1e-9)          # format 1: every estimate, as before
    only_other = random_share(rng, "3", ["2"])
    assert not gate().offer("usv/3/share/1", encode(only_other), NOW_NS * 1e-9)
    assert gate().offer("usv/3/share/1", encode_per_pair(only_other, ["1"])["1"], NOW_NS * 1e-9)


def test_both_formats_share_one_freshness_mark_and_liveliness_rules_per_sender():
    rng = np.random.default_rng(3)
    g = gate()
    first = random_share(rng, "2", ["1"], stamp_ns=NOW_NS)
    assert g.offer("usv/2/share/1", encode_per_pair(first, ["1"])["1"], NOW_NS * 1e-9)
    # The same stamp again on the other format's key is a replay.
    assert not g.offer("usv/2/share", encode(first), NOW_NS * 1e-9)
    assert g.rejected["duplicate_or_reordered"] == 1
    later = random_share(rng, "2", ["1"], stamp_ns=NOW_NS + 10**8)
    assert g.offer("usv/2/share", encode(later), NOW_NS * 1e-9 + 0.1)
    # No liveliness token: refused before decoding, on either key; so is a stale stamp.
    stranger = random_share(rng, "9", ["1"])
    assert not g.offer("usv/9/share/1", encode_per_pair(stranger, ["1"])["1"], NOW_NS * 1e-9)
    assert g.rejected["unknown_sender"] == 1
    old = random_share(rng, "3", ["1"], stamp_ns=NOW_NS - 3 * 10**9)
    assert not g.offer("usv/3/share/1", encode_per_pair(old, ["1"])["1"], NOW_NS * 1e-9)
    assert g.rejected["stale"] == 1
    # A session that ends forgets the sender's marks and rate bucket of both keys.
    g.forget("2")
    assert g.offer("usv/2/share/1", encode_per_pair(first, ["1"])["1"], NOW_NS * 1e-9)


class FakePublisher:
    def __init__(self, key_expr: str, log: list) -> None:
        self.key_expr, self.log, self.undeclared = key_expr, log, False

    def put(self, payload: bytes) -> None:
        self.log.append((self.key_expr, payload))

    def undeclare(self) -> None:
        self.undeclared = True


class FakeSession:
    def __init__(self) -> None:
        self.sent: list[tuple[str, bytes]] = []
        self.declared: list[FakePublisher] = []

    def declare_publisher(self, key_expr: str, **_options) -> FakePublisher:
        self.declared.append(FakePublisher(key_expr, self.sent))
        return self.declared[-1]


def test_the_outbox_sends_one_share_to_each_live_peer_and_each_estimated_one_and_drops_those_gone():
    from agent.core.records import OdometryReading, Share
    session = FakeSession()
    publishers = {"share": PairPublishers(session, "1", {})}
    outbox = Outbox("1")
    estimate = (3.0, 4.0, 0.5, 0.0, 0.5, 0.9)
    share = Share(sender="1", odometry=OdometryReading(1.0, np.array([1.0, 2.0]), 0.3),
                  velocity=np.array([0.5, 0.0]), phase=0.1, neighbours={"2": estimate, "4": estimate})
    assert outbox.share(publishers, share, frozenset({"2", "3"}))
    assert sorted(k for k, _ in session.sent) == ["usv/1/share/2", "usv/1/share/3", "usv/1/share/4"]
    bodies = {k: json.loads(p) for k, p in session.sent}
    assert set(bodies["usv/1/share/2"]["neighbours"]) == {"2"} and bodies["usv/1/share/3"]["neighbours"] == {}
    assert {b["seq"] for b in bodies.values()} == {0}
    session.sent.clear()
    share = Share(sender="1", odometry=OdometryReading(1.1, np.array([1.0, 2.0]), 0.3),
                  velocity=np.array([0.5, 0.0]), phase=0.1, neighbours={"2": estimate})
    assert outbox.share(publishers, share, frozenset({"2"}))
    assert [k for k, _ in session.sent] == ["usv/1/share/2"]
    assert {p.key_expr for p in session.declared if p.undeclared} == {"usv/1/share/3", "usv/1/share/4"}
    assert {json.loads(p)["seq"] for _, p in session.sent} == {1}


@pytest.mark.slow
def test_per_pair_shares_command_bit_for_bit_what_broadcast_shares_command_and_carry_fewer_bytes(tmp_path):
    _, scenario = select_scenario(with_duration(SCENARIOS / "table4_scale.yaml", tmp_path, 3.0), "n8_r5")
    broadcast = run_shells(scenario, share_format=1)
    per_pair = run_shells(scenario, share_format=2)
    assert np.isfinite(per_pair.commands).all()
    np.testing.assert_array_equal(per_pair.commands, broadcast.commands)
    n, ticks = len(scenario.world.vessels), per_pair.ticks
    # Every agent gets every other's share of every tick but the last, in either format.
    assert per_pair.share_messages == broadcast.share_messages == n * (n - 1) * (ticks - 1)
    assert per_pair.share_bytes < 0.7 * broadcast.share_bytes


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:.*unfinished MCAP")
def test_a_fleet_over_zenoh_with_one_agent_on_format_1_equals_the_in_process_runner(tmp_path, monkeypatch):
    """The transition's first step (docs/contract.md, "Share format"): vessel 2 sends format 1 on usv/2/share,
    the others format 2, every agent hears both; in lockstep the fleet's processes still command what the
    in-process runner commands, to 1e-9, and every agent estimates its three neighbours."""
    from test_lockstep import logged

    import sim_bridge.fleet as fleet_module
    from lab.harness.runner import run
    from sim_bridge.fleet import launch

    configs = fleet_module.agent_configs

    def one_on_format_1(*args, **kwargs):
        made = configs(*args, **kwargs)
        made["2"]["share_format"] = 1
        return made

    monkeypatch.setattr(fleet_module, "agent_configs", one_on_format_1)
    path = with_duration(SCENARIOS / "table2_estimators.yaml", tmp_path, 10.0)
    _, scenario = select_scenario(path, "mckf")
    trace = run(scenario)
    folder = launch(path, "mckf", tmp_path / "runs", seed=None)
    assert "share_format: 1" in (next(folder.glob("agent-2.yaml"))).read_text()
    log = logged(folder, trace.vessels)
    stamps = sorted(log["truth"])
    assert len(stamps) == len(trace.time) == 101
    for k, stamp in enumerate(stamps):
        for n, i in enumerate(trace.vessels):
            np.testing.assert_allclose(log["cmd"][i][stamp], trace.commands[k, n], rtol=0, atol=1e-9)
            np.testing.assert_allclose(log["target"][i][stamp], trace.estimates[k, n], rtol=0, atol=1e-9)
    assert all(len(log["relative"][i][stamps[-1]]) == 3 for i in trace.vessels)


class StubChannel:
    def __init__(self, topic: str, schema=None) -> None:
        self.topic, self.logged = topic, []

    def log(self, payload: bytes) -> None:
        self.logged.append(json.loads(payload))


class StubSdk:
    Channel = StubChannel


class Sample:
    def __init__(self, key_expr: str, data: bytes) -> None:
        self.key_expr, self.payload = key_expr, self
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


def test_the_operators_view_draws_every_estimate_of_a_share_sent_per_pair():
    from usv_op.view import LiveView
    view = LiveView(StubSdk())
    rng = np.random.default_rng(4)

    def children() -> set[str]:
        return {t["child_frame_id"] for t in view._channels["/2/tf"].logged[-1]["transforms"]}

    for tick, others in enumerate((["1", "3", "4"], ["1", "3"])):
        message = random_share(rng, "2", others, stamp_ns=NOW_NS + tick * 10**8)
        for j, payload in encode_per_pair(message, others).items():
            view.on_share(Sample(share_key("2", j), payload))
    # Tick 1's estimates, and 4's of tick 0 (the share before): 4 dropped out after it.
    assert children() >= {"vessel/2/estimate/1", "vessel/2/estimate/3", "vessel/2/estimate/4"}
    message = random_share(rng, "2", ["1"], stamp_ns=NOW_NS + 2 * 10**8)
    view.on_share(Sample(share_key("2", "1"), encode_per_pair(message, ["1"])["1"]))
    assert "vessel/2/estimate/4" not in children() and "vessel/2/estimate/1" in children()
    view.on_share(Sample(share_key("2"), encode(random_share(rng, "2", ["1", "3"], stamp_ns=NOW_NS))))   # older
    assert view.refused == 0 and len(view._beliefs) == 1


@pytest.mark.slow
def test_share_bench_writes_its_page_with_identical_commands_in_both_formats(tmp_path, capsys):
    from lab import cli
    assert cli.main(["share-bench", "--sizes", "3", "--duration", "0.5", "--repeats", "1", "--zenoh-sizes",
                     "--out", str(tmp_path)]) == 0
    page = (tmp_path / "share_benchmark.md").read_text()
    assert "usv-lab share-bench --sizes 3" in page
    row = next(line for line in page.splitlines() if line.startswith("| 3 |")).split(" | ")
    assert row[-1].strip(" |") == "yes"
    assert int(row[4].replace(",", "")) < int(row[3].replace(",", ""))   # format 2 carries fewer bytes
