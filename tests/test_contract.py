"""The wire contract and the input gate: bad payloads of every kind are refused and counted, never fatal."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.contract import (
    MAX_PAYLOAD_BYTES,
    MAX_PEERS,
    TOPICS,
    VERDICTS,
    Bearing,
    Clock,
    Cmd,
    Odometry,
    Ranges,
    ReceivedShare,
    ShareMessage,
    covariance_problem,
    decode,
    encode,
    every,
    key,
    pair_covariance_problem,
    vessel_of,
)
from agent.core.build import InitialEstimates, initial_state
from agent.core.params import AgentParams
from agent.core.step import step
from agent.shell.gate import InputGate, SimClock
from agent.shell.translate import message_from_share, share_from_message

NOW = 100.0
NS = int(NOW * 1e9)


def gate(**kwargs) -> InputGate:
    return InputGate("1", known_peers=lambda: {"2", "3"}, **kwargs)


def odom(seq=0, stamp_ns=NS, sender="1", **extra) -> bytes:
    body = {"stamp_ns": stamp_ns, "seq": seq, "sender": sender, "position": [1.0, 2.0], "heading": 0.5} | extra
    return json.dumps(body).encode()


def test_keys():
    assert key("7", "sensor/odom") == "usv/7/sensor/odom"
    assert every("share") == "usv/*/share"
    assert vessel_of("usv/12/cmd") == "12" and vessel_of("sim/clock") is None
    with pytest.raises(ValueError):
        key("1", "sensor/lidar")


@pytest.mark.slow
def test_a_bridge_that_imports_the_contract_loads_no_part_of_the_core():
    """In a fresh interpreter, as a bridge starts: the contract alone brings in none of agent.core (the
    translation to the core's records is the shell's, agent/shell/translate.py)."""
    probe = ("import sys, agent.contract; "
             "print(sorted(m for m in sys.modules if m == 'agent.core' or m.startswith(('agent.core.', 'agent.shell'))))")
    loaded = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "[]", loaded
    # The probe can fail: the shell's translation does load the core's records.
    probe = probe.replace("agent.contract", "agent.shell.translate")
    loaded = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert "agent.core.records" in loaded


def test_the_verdicts_on_the_wire_are_the_cores():
    from agent.core.observability import VERDICTS as CORE_VERDICTS
    assert VERDICTS == CORE_VERDICTS


def test_round_trip_of_every_message_and_of_a_share():
    cmd = Cmd(stamp_ns=5, seq=1, sender="3", surge=1.5, yaw_rate=-0.2)
    assert decode(Cmd, encode(cmd)) == (cmd, "")
    params = AgentParams()
    state = initial_state("1", params, InitialEstimates(target=(5.0, 0.0, 0.1, 0.2)))
    g = gate()
    g.offer("usv/1/sensor/odom", odom(), NOW)
    share = step(params, state, g.snapshot(NOW))[1].share
    again = share_from_message(ShareMessage.model_validate_json(encode(message_from_share(share, 0))))
    np.testing.assert_allclose(again.target, share.target)
    np.testing.assert_allclose(again.target_covariance, share.target_covariance)
    assert again.odometry.stamp == pytest.approx(share.odometry.stamp)


@pytest.mark.parametrize("payload, reason", [
    (b"", "malformed"),
    (b"\xff\xfe not json", "malformed"),
    (b"[1, 2]", "malformed"),
    (odom(position=["a", 2.0]), "malformed"),                      # wrong type
    (odom(heading="NaN"), "malformed"),
    (b'{"stamp_ns": 1, "seq": 0, "sender": "1", "position": [NaN, 0], "heading": 0}', "malformed"),
    (b'{"stamp_ns": 1, "seq": 0, "sender": "1", "position": [Infinity, 0], "heading": 0}', "malformed"),
    (odom(covariance=[-1, 0, 0, 0, 1, 0, 0, 0, 1]), "malformed"),  # negative variance
    (odom(extra_field=3), "malformed"),                            # unknown key
    (odom(sender="2"), "sender_mismatch"),
    (odom(stamp_ns=NS - 10**10), "stale"),                        # 10 s in the past
    (odom(stamp_ns=NS + 10**10), "future"),                       # 10 s ahead
    (odom(stamp_ns=-5), "malformed"),
])
def test_bad_odometry_is_refused_with_its_reason(payload, reason):
    g = gate()
    assert not g.offer("usv/1/sensor/odom", payload, NOW)
    assert g.rejected[reason] == 1 and g.snapshot(NOW).odometry is None


def test_negative_ranges_unknown_peers_and_non_unit_bearings():
    g = gate()
    bad = {"stamp_ns": NS, "seq": 0, "sender": "1", "ranges": {"2": -1.0}}
    assert not g.offer("usv/1/sensor/uwb", json.dumps(bad).encode(), NOW)
    ok = {"stamp_ns": NS, "seq": 1, "sender": "1", "ranges": {"2": 4.0, "9": 3.0}}
    assert g.offer("usv/1/sensor/uwb", json.dumps(ok).encode(), NOW)
    # A range to a peer nobody has heard of is dropped when the tick reads it (the peer may yet show up).
    assert g.snapshot(NOW).ranges == {"2": 4.0} and g.rejected["unknown_peer"] == 1
    bearing = {"stamp_ns": NS, "seq": 0, "sender": "1", "bearing": [3.0, 4.0]}
    assert not g.offer("usv/1/sensor/bearing", json.dumps(bearing).encode(), NOW)


def test_duplicated_and_reordered_stamps_are_dropped_whatever_the_seq():
    g = gate()
    assert g.offer("usv/1/sensor/odom", odom(seq=5, stamp_ns=NS, position=[5.0, 5.0]), NOW)
    assert not g.offer("usv/1/sensor/odom", odom(seq=6, stamp_ns=NS), NOW)              # same stamp: a repeat
    assert not g.offer("usv/1/sensor/odom", odom(seq=7, stamp_ns=NS - 10**8), NOW)      # older: reordered
    assert g.offer("usv/1/sensor/odom", odom(seq=1, stamp_ns=NS + 10**8, position=[9.0, 9.0]), NOW)  # seq is no judge
    assert g.rejected["duplicate_or_reordered"] == 2
    np.testing.assert_array_equal(g.snapshot(NOW).odometry.position, [9.0, 9.0])


def test_a_poisoned_seq_does_not_lock_the_agent_out_of_its_odometry():
    """Regression: one message with seq 10^9 made the agent refuse its own odometry for the rest of the run
    (121/121 ticks STOP). Freshness is now judged by stamps; the seq is informative."""
    g = gate()
    assert g.offer("usv/1/sensor/odom", odom(seq=10**9, stamp_ns=NS), NOW)
    for k in range(1, 21):
        now = NOW + 0.1 * k
        assert g.offer("usv/1/sensor/odom", odom(seq=k, stamp_ns=NS + k * 10**8, position=[k, 0.0]), now)
        assert g.snapshot(now).odometry is not None
    assert g.rejected["duplicate_or_reordered"] == 0


def test_seq_zero_is_not_a_restart_that_replays_old_stamps():
    """A seq of 0 used to be accepted at any time as the sender's restart, so it let any replayed message in."""
    g = gate()
    assert g.offer("usv/1/sensor/odom", odom(seq=500, stamp_ns=NS), NOW)
    assert not g.offer("usv/1/sensor/odom", odom(seq=0, stamp_ns=NS - 10**8, position=[7.0, 7.0]), NOW)
    assert g.rejected["duplicate_or_reordered"] == 1
    np.testing.assert_array_equal(g.snapshot(NOW).odometry.position, [1.0, 2.0])


def test_a_stamp_ahead_blocks_genuine_messages_only_until_the_clock_passes_it():
    g = gate()
    assert not g.offer("usv/1/sensor/odom", odom(stamp_ns=2**62), NOW)          # far ahead: refused, no mark
    assert g.rejected["future"] == 1
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=NS), NOW)                 # the genuine one still gets in
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=NS + 4 * 10**8), NOW)     # 0.4 s ahead: within the window
    assert not g.offer("usv/1/sensor/odom", odom(stamp_ns=NS + 10**8), NOW + 0.1)
    # Once the clock is past it, genuine stamps are newer again: at most max_future of lock-out.
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=NS + 5 * 10**8), NOW + 0.5)


def test_a_clock_stepped_back_is_not_locked_out_by_the_marks_of_before():
    g = gate()
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=NS), NOW)
    earlier = NOW - 5.0       # the system clock stepped back 5 s (chrony): the old mark is 5 s ahead of it
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=int(earlier * 1e9), position=[3.0, 3.0]), earlier)
    np.testing.assert_array_equal(g.snapshot(earlier).odometry.position, [3.0, 3.0])


def test_odometry_faster_than_a_kilometre_a_second_is_left_out_of_the_tick():
    """Found by the fuzz campaign: odometry stamped a nanosecond after the one the last tick used, a quarter of
    a metre away, gave the core an own velocity of 2.6e8 m/s and sent its target estimate to 1e7 m."""
    g = gate()
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=NS - 1, position=[0.0, 0.0]), NOW)
    assert g.snapshot(NOW).odometry is not None
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=NS, position=[0.26, 0.0]), NOW)
    assert g.snapshot(NOW).odometry is None and g.rejected["implausible_motion"] == 1
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=NS + 10**8, position=[5e4, 0.0]), NOW)   # 50 km in 0.1 s
    assert g.snapshot(NOW).odometry is None and g.rejected["implausible_motion"] == 2
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=NS + 2 * 10**8, position=[0.5, 0.0]), NOW)   # 2.5 m/s
    np.testing.assert_array_equal(g.snapshot(NOW).odometry.position, [0.5, 0.0])
    assert g.snapshot(NOW).odometry is not None          # the same odometry again: no motion, no refusal
    # Odometry older than the one used (accepted while there was no clock to judge it by) is left out too.
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=NS + 10**8, position=[0.4, 0.0]), None)
    assert g.snapshot(NOW).odometry is None and g.rejected["implausible_motion"] == 3
    # A clock stepped back 5 s: the odometry used before is then in the future, and no longer blocks.
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=NS - 5 * 10**9, position=[0.0, 0.0]), NOW - 5.0)
    assert g.snapshot(NOW - 5.0).odometry is not None


def test_a_clock_whose_previous_tick_is_not_before_it_is_refused():
    assert decode(Clock, json.dumps({"stamp_ns": 10, "seq": 1, "previous_ns": 9}).encode())[0] is not None
    for previous in (10, 11, 2**62):
        assert decode(Clock, json.dumps({"stamp_ns": 10, "seq": 1, "previous_ns": previous}).encode())[0] is None


def test_without_a_clock_stamps_are_not_judged_and_move_no_mark():
    g = gate()
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=2**62), None)     # sim time before the first clock
    assert g.snapshot(NOW).odometry is None                             # ... but never used: not fresh
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=NS, position=[4.0, 4.0]), NOW)
    np.testing.assert_array_equal(g.snapshot(NOW).odometry.position, [4.0, 4.0])


EXTREME_ODOMETRY = [
    {"position": [1e308, 1e308]},                     # regression: killed the agent in 0.19 s
    {"position": [1e5 + 1.0, 0.0]},                   # beyond the physical limit of 100 km
    {"heading": 1e300},
    {"heading": -1e7},
    {"covariance": [1, 2, 0, 0, 1, 0, 0, 0, 1]},      # not symmetric
    {"covariance": [1, 0, 0, 0, -1, 0, 0, 0, 1]},     # a negative variance
    {"covariance": [1, 2, 0, 2, 1, 0, 0, 0, 1]},      # symmetric, positive diagonal, but not semi-definite
    {"covariance": [1e11, 0, 0, 0, 1, 0, 0, 0, 1]},   # an entry beyond 1e10
    {"covariance": [1.0] * 8},                        # not 3x3
    {"covariance": [1.0] * 10000},
    {"stamp_ns": 10**400},
    {"stamp_ns": 2**63},
    {"seq": 10**400},
    {"seq": -1},
]


@pytest.mark.parametrize("change", EXTREME_ODOMETRY, ids=lambda c: json.dumps(c)[:40])
def test_extreme_odometry_is_refused_as_malformed(change):
    g = gate()
    body = {"stamp_ns": NS, "seq": 0, "sender": "1", "position": [1.0, 2.0], "heading": 0.5} | change
    assert not g.offer("usv/1/sensor/odom", json.dumps(body).encode(), NOW)
    assert g.rejected["malformed"] == 1 and g.snapshot(NOW).odometry is None


def test_tiny_and_zero_values_are_fine():
    g = gate()
    assert g.offer("usv/1/sensor/odom", odom(position=[1e-308, -5e-324], heading=-0.0, covariance=[0.0] * 9), NOW)
    assert g.snapshot(NOW).odometry is not None


@pytest.mark.parametrize("topic, body", [
    ("sensor/uwb", {"ranges": {"2": 1e6}}),
    ("sensor/uwb", {"ranges": {"2": 1e308}}),
    ("sensor/sonar", {"points": [[1e5 + 1.0, 0.0]]}),
    ("sensor/bearing", {"bearing": [1e308, 1e308]}),
])
def test_extreme_sensor_values_are_refused(topic, body):
    g = gate()
    assert not g.offer(f"usv/1/{topic}", json.dumps({"stamp_ns": NS, "seq": 0, "sender": "1"} | body).encode(), NOW)
    assert g.rejected["malformed"] == 1


def test_a_payload_over_the_size_limit_is_refused_before_parsing():
    g = gate()
    assert not g.offer("usv/1/sensor/odom", b" " * (MAX_PAYLOAD_BYTES + 1), NOW)
    assert g.rejected["malformed"] == 1 and "bytes" in g.recent_reasons[-1]


def share_body(sender="2", stamp_ns=NS, **change) -> dict:
    return {"stamp_ns": stamp_ns, "seq": 0, "sender": sender, "position": [1.0, 2.0], "heading": 0.1,
            "velocity": [0.5, 0.0], "phase": 0.3, "target": [4.0, 1.0, 0.0, 0.0],
            "target_covariance": np.eye(4).ravel().tolist(),
            "neighbours": {"1": {"position": [-3.0, 1.0], "covariance": [0.04, 0.0, 0.04]}}} | change


def share(**change) -> bytes:
    return json.dumps(share_body(**change)).encode()


@pytest.mark.parametrize("change", [
    {"target_covariance": (-np.eye(4)).ravel().tolist()},           # regression: killed all 4 agents in 0.4 s
    {"target_covariance": (np.eye(4) + np.diag([1.0] * 3, 1)).ravel().tolist()},   # not symmetric
    {"target_covariance": [1.0] * 15},
    {"target_covariance": None},                                      # a target without its covariance
    {"neighbours": {"1": {"position": [0.0, 0.0], "covariance": [1.0, 2.0, 1.0]}}},   # not semi-definite
    {"neighbours": {"1": {"position": [0.0, 0.0], "covariance": [-1.0, 0.0, 1.0]}}},
    {"position": [1e308, 0.0]},
    {"velocity": [1e4, 0.0]},
    {"target": [0.0, 0.0, 1e308, 0.0]},
    {"phase": 1e300},
])
def test_a_share_that_is_not_physical_is_refused(change):
    g = gate()
    assert not g.offer("usv/2/share", share(**change), NOW)
    assert g.rejected["malformed"] == 1 and not g.snapshot(NOW).shares


def test_a_share_needs_the_senders_liveliness_token():
    """Regression: a share alone created a neighbour, and a phantom id moved the whole fleet."""
    g = gate()
    assert not g.offer("usv/9/share", share(sender="9"), NOW)      # 9 has no token
    assert g.offer("usv/2/share", share(sender="2"), NOW)
    assert g.rejected["unknown_sender"] == 1 and set(g.snapshot(NOW).shares) == {"2"}


def test_a_new_liveliness_session_starts_the_senders_marks_again():
    g = gate()
    assert g.offer("usv/2/share", share(stamp_ns=NS), NOW)
    assert not g.offer("usv/2/share", share(stamp_ns=NS - 10**8), NOW)
    g.forget("2")                     # its token went away (or came back): its share and marks go
    assert not g.snapshot(NOW).shares
    assert g.offer("usv/2/share", share(stamp_ns=NS - 10**8), NOW)


def test_per_sender_state_is_bounded():
    g = InputGate("1", hold_shares=True)       # no liveliness to ask (a test harness): the bound still holds
    for n in range(MAX_PEERS + 50):
        g.offer(f"usv/p{n}/share", share(sender=f"p{n}"), NOW)
    assert g.rejected["too_many_peers"] == 50 and len(g._senders) == MAX_PEERS
    held = InputGate("1", known_peers=lambda: {"2"}, hold_shares=True, max_held=4)
    for k in range(10):
        held.offer("usv/2/share", share(stamp_ns=NS + k * 10**7), NOW)
    assert held.accepted["share"] == 4 and held.rejected["held_full"] == 6 and len(held._held) == 4


def test_a_share_keeps_only_the_senders_estimate_of_this_vessel():
    g = gate()
    many = {f"k{n}": {"position": [1.0, 1.0], "covariance": [0.04, 0.0, 0.04]} for n in range(MAX_PEERS - 1)}
    assert g.offer("usv/2/share", share(neighbours=many | {"1": {"position": [-3.0, 1.0],
                                                                  "covariance": [0.04, 0.01, 0.05]}}), NOW)
    (px, py, p11, p12, p22, stamp), = g.snapshot(NOW).shares["2"].neighbours.values()
    assert (px, py, p11, p12, p22) == (-3.0, 1.0, 0.04, 0.01, 0.05)
    assert stamp == NS * 1e-9           # no stamp of its own: the share's
    assert list(g.snapshot(NOW).shares["2"].neighbours) == ["1"]


def test_a_receiver_judges_its_own_pair_estimate_and_leaves_the_others_to_their_vessels():
    """A share carries n - 1 pair estimates and each vessel uses only its own: a bad estimate of another pair
    does not make the share malformed for this vessel (checking them all would cost each vessel O(n^2) per
    tick); the vessel it concerns refuses the share, with the same reason as the whole message's check."""
    bad = {"position": [0.0, 0.0], "covariance": [1.0, 2.0, 1.0]}               # not semi-definite
    body = share_body(neighbours={"1": {"position": [-3.0, 1.0], "covariance": [0.04, 0.0, 0.04]}, "3": bad,
                                  "4": "not an estimate"})
    one = gate()
    assert one.offer("usv/2/share", json.dumps(body).encode(), NOW)
    assert list(one.snapshot(NOW).shares["2"].neighbours) == ["1"]
    three = InputGate("3", known_peers=lambda: {"1", "2"})
    assert not three.offer("usv/2/share", json.dumps(body).encode(), NOW)
    assert three.rejected["malformed"] == 1
    assert three.recent_reasons[-1].endswith("ShareMessage: neighbours.3.covariance: Value error, covariance is "
                                             "not positive semi-definite")
    whole, reason = decode(ShareMessage, json.dumps(body).encode())
    assert whole is None and reason.startswith("ShareMessage: neighbours.")


@pytest.mark.parametrize("entry", [
    {"position": [-3.0, 1.0], "covariance": [0.04, 0.01, 0.05]},
    {"position": [-3.0, 1.0], "covariance": [0.04, 0.01, 0.05], "stamp_ns": NS},
    {"position": [-3.0, 1.0], "covariance": [0.04, 0.01, 0.05], "stamp_ns": NS + 1},   # after the share
    {"position": [-3.0, 1.0], "covariance": [1.0, 2.0, 1.0]},
    {"position": [-3.0, 1e308], "covariance": [0.04, 0.0, 0.04]},
    {"position": [-3.0, 1.0], "covariance": [0.04, 0.0]},
    {"position": [-3.0, 1.0], "covariance": [0.04, 0.0, 0.04], "extra": 1},
    {"position": [-3.0, True], "covariance": [0.04, 0.0, 0.04]},
    {"position": ["-3.0", 1.0], "covariance": [0.04, 0.0, 0.04]},
    {"position": [-3.0, "NaN"], "covariance": [0.04, 0.0, 0.04]},
    {"position": [-3.0, 1.0], "covariance": [0.04, 0.0, 0.04], "stamp_ns": float(NS - 10**8)},
    {"position": [-3.0, 1.0], "covariance": [0.04, 0.0, 0.04], "stamp_ns": NS - 0.5},
    {"position": [-3.0, 1.0], "covariance": [0.04, 0.0, 0.04], "stamp_ns": -1},
    [1.0, 2.0],
    None,
])
def test_a_receivers_own_estimate_gets_the_whole_messages_verdict(entry):
    """Decoded as one receiver decodes it, a share with only that receiver's estimate is accepted exactly when
    ShareMessage accepts it, and yields the same estimate."""
    payload = json.dumps(share_body(neighbours={"1": entry})).encode()
    whole, _ = decode(ShareMessage, payload)
    received, reason = decode(ReceivedShare, payload)
    assert reason == ""
    mine, reason = received.estimate_for("1")
    assert (whole is not None) == (reason == "")
    if whole is not None:
        assert mine == whole.neighbours["1"]


def test_a_shared_estimate_keeps_its_own_stamp_which_may_not_be_after_the_shares():
    g = gate()
    entry = {"position": [-3.0, 1.0], "covariance": [0.04, 0.0, 0.04], "stamp_ns": NS - 70_000_000}
    assert g.offer("usv/2/share", share(neighbours={"1": entry}), NOW)
    assert g.snapshot(NOW).shares["2"].neighbours["1"][-1] == pytest.approx(NOW - 0.07, abs=1e-9)
    later = entry | {"stamp_ns": NS + 1}
    assert not g.offer("usv/3/share", share(sender="3", neighbours={"1": later}), NOW)
    assert g.rejected["malformed"] == 1 and "after the share's stamp" in g.recent_reasons[-1]


def test_input_rates_are_limited_per_key_before_decoding():
    clock = [0.0]
    g = InputGate("1", max_rate=10.0, burst=5.0, monotonic=lambda: clock[0])
    sent = [g.offer("usv/1/sensor/odom", odom(stamp_ns=NS + k), NOW) for k in range(20)]
    assert sum(sent) == 5 and g.rejected["rate_limited"] == 15
    assert g.offer("usv/1/sensor/uwb", json.dumps({"stamp_ns": NS, "seq": 0, "sender": "1",
                                                   "ranges": {}}).encode(), NOW)   # another key: its own bucket
    clock[0] = 0.5                                                                # 5 more tokens
    assert sum(g.offer("usv/1/sensor/odom", odom(stamp_ns=NS + 100 + k), NOW) for k in range(10)) == 5


def test_a_sim_restart_forgets_the_old_timeline_and_keeps_the_new():
    g = InputGate("1", known_peers=lambda: {"2"}, hold_shares=True)
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=NS), NOW)
    assert g.offer("usv/2/share", share(stamp_ns=NS), NOW)
    g.deliver_shares(NS, None)
    assert g.snapshot(NOW).shares
    # The new bridge's first sensors come before its first clock (no clock to judge them by) ...
    assert g.offer("usv/1/sensor/uwb", json.dumps({"stamp_ns": 0, "seq": 0, "sender": "1", "ranges": {}}).encode(),
                   None)
    g.reset(0)   # ... and its clock at 0 says the simulation restarted
    inputs = g.snapshot(0.0)
    assert not inputs.shares and inputs.odometry is None and g._latest.keys() == {"sensor/uwb"}
    assert g.offer("usv/1/sensor/odom", odom(stamp_ns=10**8), 0.0)     # no mark of the old timeline is left
    assert g.offer("usv/2/share", share(stamp_ns=0), 0.0)              # nor the delivered-through stamp


def test_a_new_timelines_share_that_comes_before_its_clock_is_kept():
    """Regression (a lockstep tick missed after a sim bridge restart): a neighbour that saw the new clock
    first shares for tick 0 before this agent's clock 0 arrives. Refused then as already delivered (the
    old timeline had delivered through NS), it left this agent waiting `share_wait` for it at tick 1."""
    g = InputGate("1", known_peers=lambda: {"2"}, hold_shares=True)
    assert g.offer("usv/2/share", share(stamp_ns=NS), NOW)
    g.deliver_shares(NS, None)
    assert g.offer("usv/2/share", share(stamp_ns=0), None)     # the clock is silent: nothing to judge by
    g.reset(0)
    assert g.deliver_shares(0, {"2"}) == set() and "2" in g.snapshot(0.0).shares
    # With a clock, the same share is late (the old timeline delivered through NS) and refused.
    late = InputGate("1", known_peers=lambda: {"2", "3"}, hold_shares=True)
    assert late.offer("usv/2/share", share(stamp_ns=NS), NOW)
    late.deliver_shares(NS, None)
    assert not late.offer("usv/3/share", share(sender="3", stamp_ns=NS - 10**8), NOW)
    assert late.rejected["late_share"] == 1


def test_the_sim_clock_is_bounded_and_follows_a_restart():
    wall = [0.0]
    clock = SimClock(dt=0.1, max_jump=1.0, confirm=3, silence=1.0, monotonic=lambda: wall[0])

    def offer(stamp_s: float, after: float = 0.01) -> str:
        wall[0] += after
        return clock.offer(Clock(stamp_ns=round(stamp_s * 1e9), seq=0))

    assert offer(30.0) == "first" and offer(30.1) == "tick"
    assert offer(30.1) == "clock_reordered" and offer(30.0) == "clock_reordered"
    # Regression: a clock of 2^62 ns froze every agent. Now it is refused, and the genuine clock goes on.
    assert clock.offer(Clock(stamp_ns=2**62, seq=0)) == "clock_jump"
    assert offer(30.2) == "tick"
    # One clock a little ahead (within max_jump) is taken; the genuine clock catches up with it, no restart.
    assert offer(30.8) == "tick"
    assert [offer(30.3), offer(30.4), offer(30.9)] == ["clock_reordered", "clock_reordered", "tick"]
    # One stray clock at 0 in the middle of a run is no restart ...
    assert offer(0.0) == "clock_jump" and offer(31.0) == "tick"
    # ... but a clock at 0 after a silence is (the sim bridge was restarted) ...
    assert offer(0.0, after=2.0) == "restart" and offer(0.1) == "tick"
    # ... and so is a new timeline that keeps going, without a silence, even with other clocks in between.
    assert [offer(50.0), offer(2.0**62 / 1e9), offer(50.1), offer(9.0), offer(50.2)] == ["clock_jump"] * 4 + ["restart"]
    assert clock.latest.stamp_ns == 50_200_000_000
    assert not clock.silent() and (offer(50.3, after=1.5) == "tick")
    # A clock far ahead after a silence is no restart on its own (a restarted simulation starts again from 0).
    assert offer(2.0**62 / 1e9, after=2.0) == "clock_jump" and offer(50.4) == "tick"


def _eigenvalue_verdict(values: list[float], size: int) -> str | None:
    """The rule covariance_problem states, by numpy's eigenvalues alone: the reference for its fast path."""
    matrix = np.array(values).reshape(size, size)
    tolerance = 1e-9 * np.abs(matrix).max()
    if np.abs(matrix - matrix.T).max() > tolerance:
        return "is not symmetric"
    if np.linalg.eigvalsh(0.5 * (matrix + matrix.T))[0] < -tolerance:
        return "is not positive semi-definite"
    return None


@pytest.mark.parametrize("size", [2, 3, 4])
def test_the_covariance_check_gives_the_eigenvalue_verdict(size):
    """The plain-float Cholesky path must not change a verdict: definite, singular, indefinite and just
    beyond the tolerance, at scales from 1e-8 to 1e8."""
    rng = np.random.default_rng(11)
    tolerance = 1e-9
    for _ in range(400):
        scale = 10 ** rng.uniform(-8, 8)
        q, _ = np.linalg.qr(rng.normal(size=(size, size)))
        eigenvalues = rng.uniform(0.0, 1.0, size) * scale
        kind = rng.integers(4)
        if kind == 1:
            eigenvalues[0] = 0.0                                   # singular: positive semi-definite
        elif kind == 2:
            eigenvalues[0] = -rng.uniform(0.01, 1.0) * scale        # clearly indefinite
        elif kind == 3:                                            # a hair either side of the tolerance
            eigenvalues[1:] = scale
            eigenvalues[0] = -tolerance * scale * rng.choice([0.5, 2.0])
        matrix = q @ np.diag(eigenvalues) @ q.T
        values = matrix.ravel().tolist()
        assert covariance_problem(values, size) == _eigenvalue_verdict(values, size)
    assert covariance_problem([1.0, 2.0, 2.0, 1.0], 2) == "is not positive semi-definite"   # eigenvalues 3, -1
    assert covariance_problem([0.0] * size * size, size) is None


def test_a_pair_estimate_is_judged_as_its_full_matrix():
    """A share's pair covariance, given by (p11, p12, p22), gets the verdict of the whole symmetric matrix."""
    rng = np.random.default_rng(12)
    for _ in range(2000):
        scale = 10 ** rng.uniform(-8, 8)
        p11, p22 = rng.uniform(-0.1, 1.0, 2) * scale
        # off-diagonals from well inside to a hair either side of the semi-definite limit sqrt(p11 p22)
        limit = math.sqrt(max(p11 * p22, 0.0))
        p12 = float(rng.choice([-1.0, 1.0]) * limit * rng.choice([0.3, 1.0 - 1e-12, 1.0 + 1e-12, 1.5]))
        values = [p11, p12, p12, p22]
        verdict = _eigenvalue_verdict(values, 2)
        assert pair_covariance_problem(p11, p12, p22) == covariance_problem(values, 2) == verdict
    assert pair_covariance_problem(0.0, 0.0, 0.0) is None
    assert pair_covariance_problem(1.0, 2.0, 1.0) == "is not positive semi-definite"


def test_the_contract_accepts_what_the_core_shares():
    """The bounds must never refuse a genuine share: a covariance of a filter passes, with rounding."""
    rng = np.random.default_rng(3)
    for _ in range(200):
        a = rng.normal(size=(4, 4)) * 10 ** rng.uniform(-6, 4)
        covariance = a @ a.T
        covariance[0, 1] += 1e-13 * abs(covariance).max()        # the asymmetry of a Kalman update's rounding
        assert covariance_problem(covariance.ravel().tolist(), 4) is None


def test_a_range_is_used_by_one_tick_only():
    g = gate()
    g.offer("usv/1/sensor/uwb", json.dumps({"stamp_ns": NS, "seq": 0, "sender": "1",
                                            "ranges": {"2": 4.0}}).encode(), NOW)
    assert g.snapshot(NOW).ranges == {"2": 4.0}
    assert g.snapshot(NOW + 0.1).ranges == {}


def test_every_range_set_since_the_last_tick_is_given_once_at_its_own_stamp():
    """A UWB module ranges at its own rate: at 8 Hz against 10 Hz ticks, some ticks see two sets. Keeping
    only the newest threw a quarter of the ranges away."""
    g = gate()

    def uwb(k: int, stamp_ns: int, ranges: dict) -> bytes:
        return json.dumps({"stamp_ns": stamp_ns, "seq": k, "sender": "1", "ranges": ranges}).encode()

    assert g.offer("usv/1/sensor/uwb", uwb(0, NS - 150_000_000, {"2": 4.0}), NOW)
    assert g.offer("usv/1/sensor/uwb", uwb(1, NS - 25_000_000, {"2": 4.1, "3": 6.0}), NOW)
    first = g.snapshot(NOW)
    assert first.ranges == {"2": 4.1, "3": 6.0} and first.range_stamp == pytest.approx(NOW - 0.025, abs=1e-9)
    assert first.earlier_ranges == ((pytest.approx(NOW - 0.15, abs=1e-9), {"2": 4.0}),)
    again = g.snapshot(NOW + 0.1)                            # nothing new: nothing given twice
    assert again.ranges == {} and again.range_stamp is None and again.earlier_ranges == ()
    # A set too old for the tick (max_age 1 s) is dropped, not carried to a later one.
    assert g.offer("usv/1/sensor/uwb", uwb(2, NS + 50_000_000, {"2": 4.2}), NOW + 0.1)
    assert g.snapshot(NOW + 1.2).ranges == {} and g.snapshot(NOW + 1.3).ranges == {}


def test_range_sets_beyond_the_bound_drop_the_oldest_and_are_counted():
    from agent.shell.gate import MAX_RANGE_SETS

    g = gate()
    for k in range(MAX_RANGE_SETS + 3):
        stamp = NS - 500_000_000 + k * 10_000_000
        assert g.offer("usv/1/sensor/uwb", json.dumps({"stamp_ns": stamp, "seq": k, "sender": "1",
                                                       "ranges": {"2": 4.0 + k}}).encode(), NOW)
    inputs = g.snapshot(NOW)
    assert g.rejected["range_sets_dropped"] == 3 and len(inputs.earlier_ranges) == MAX_RANGE_SETS - 1
    assert inputs.earlier_ranges[0][1] == {"2": 7.0} and inputs.ranges == {"2": 4.0 + MAX_RANGE_SETS + 2}


def test_keys_the_agent_does_not_own_are_refused():
    g = gate()
    assert not g.offer("usv/2/sensor/odom", odom(sender="2"), NOW)     # another vessel's sensor
    assert not g.offer("elsewhere/x", b"{}", NOW)
    assert g.rejected["unexpected_key"] == 2
    # Its own share echoed back by the subscription to every vessel's is ignored, not counted as bad input.
    assert not g.offer("usv/1/share", odom(), NOW)
    assert sum(g.rejected.values()) == 2 and not g.snapshot(NOW).shares


@settings(max_examples=300, deadline=None)
@given(topic=st.sampled_from(sorted(TOPICS)), sender=st.sampled_from(["1", "2", "3", "x"]),
       payload=st.binary(max_size=300))
def test_random_bytes_on_any_key_never_raise(topic, sender, payload):
    g = gate()
    g.offer(f"usv/{sender}/{topic}", payload, NOW)
    inputs = g.snapshot(NOW)
    assert inputs.odometry is None or np.all(np.isfinite(inputs.odometry.position))


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10**20, 10**20) | st.text(max_size=5)
    | st.floats(allow_nan=True, allow_infinity=True),
    lambda children: st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=5), children, max_size=5),
    max_leaves=20,
)


@settings(max_examples=300, deadline=None)
@given(topic=st.sampled_from(sorted(TOPICS)), body=st.dictionaries(
    st.sampled_from(["stamp_ns", "seq", "sender", "position", "heading", "ranges", "bearing", "points",
                     "velocity", "phase", "target", "target_covariance", "neighbours", "covariance",
                     "surge", "yaw_rate"]), json_values, max_size=10))
def test_valid_json_with_wrong_contents_never_reaches_the_tick_as_garbage(topic, body):
    """Whatever is accepted must drive the tick to a finite command."""
    g = gate()
    sender = "2" if topic == "share" else "1"
    try:
        payload = json.dumps(body | {"sender": sender}).encode()
    except (TypeError, ValueError):
        return
    g.offer(f"usv/{sender}/{topic}", payload, NOW)
    g.offer("usv/1/sensor/odom", odom(seq=10**9), NOW)
    params = AgentParams()
    state = initial_state("1", params, InitialEstimates(target=(5.0, 0.0, 0.0, 0.0)))
    command = step(params, state, g.snapshot(NOW))[1].command
    assert math.isfinite(command.surge) and math.isfinite(command.yaw_rate)


def test_an_accepted_bearing_and_sonar_reach_the_tick():
    g = gate()
    g.offer("usv/1/sensor/odom", odom(), NOW)
    g.offer("usv/1/sensor/bearing", Bearing(stamp_ns=NS, seq=0, sender="1", bearing=(0.6, 0.8)).model_dump_json()
            .encode(), NOW)
    g.offer("usv/1/sensor/sonar", json.dumps({"stamp_ns": NS, "seq": 0, "sender": "1",
                                              "points": [[1.0, 2.0]]}).encode(), NOW)
    inputs = g.snapshot(NOW)
    np.testing.assert_allclose(inputs.bearing, [0.6, 0.8])
    np.testing.assert_allclose(inputs.obstacle_points, [[1.0, 2.0]])
    assert inputs.time == pytest.approx(NOW)
    assert isinstance(Odometry.model_json_schema(), dict) and isinstance(Ranges.model_json_schema(), dict)
