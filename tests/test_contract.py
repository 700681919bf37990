"""The wire contract and the input gate: bad payloads of every kind are refused and counted, never fatal."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.contract import (
    TOPICS,
    Bearing,
    Cmd,
    Odometry,
    Ranges,
    ShareMessage,
    decode,
    encode,
    every,
    key,
    message_from_share,
    share_from_message,
    vessel_of,
)
from agent.core.build import InitialEstimates, initial_state
from agent.core.params import AgentParams
from agent.core.step import step
from agent.shell.gate import InputGate

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


def test_duplicated_and_reordered_seq_are_dropped():
    g = gate()
    assert g.offer("usv/1/sensor/odom", odom(seq=5, position=[5.0, 5.0]), NOW)
    assert not g.offer("usv/1/sensor/odom", odom(seq=5), NOW)          # duplicate
    assert not g.offer("usv/1/sensor/odom", odom(seq=3), NOW)          # reordered, older
    assert g.offer("usv/1/sensor/odom", odom(seq=9, position=[9.0, 9.0]), NOW)   # a gap is fine
    assert g.rejected["duplicate_or_reordered"] == 2
    np.testing.assert_array_equal(g.snapshot(NOW).odometry.position, [9.0, 9.0])


def test_a_sender_that_restarts_at_seq_zero_is_accepted_again():
    g = gate()
    assert g.offer("usv/1/sensor/odom", odom(seq=500), NOW)
    assert g.offer("usv/1/sensor/odom", odom(seq=0, position=[7.0, 7.0]), NOW)
    assert g.accepted["sender_restarted"] == 1
    assert not g.offer("usv/1/sensor/odom", odom(seq=0), NOW)   # a second 0 is a duplicate
    np.testing.assert_array_equal(g.snapshot(NOW).odometry.position, [7.0, 7.0])


def test_a_range_is_used_by_one_tick_only():
    g = gate()
    g.offer("usv/1/sensor/uwb", json.dumps({"stamp_ns": NS, "seq": 0, "sender": "1",
                                            "ranges": {"2": 4.0}}).encode(), NOW)
    assert g.snapshot(NOW).ranges == {"2": 4.0}
    assert g.snapshot(NOW + 0.1).ranges == {}


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
