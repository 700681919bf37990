"""`usv-op view` shows a field trial's GNSS fixes on Foxglove's map: each driver's `usv/<id>/truth/gnss`
(the target tag's too) becomes `/<id>/gnss`, a foxglove.LocationFix, checked against Foxglove's published
schema (tests/data/foxglove/LocationFix.json) with the fix's own values."""

from __future__ import annotations

import json
import re
import signal
import struct
import subprocess
import sys
import time

import pytest
import zenoh
from test_foxglove import assert_same_fields, published

from agent.contract import GnssFix, encode, gnss_truth_key
from agent.runtime import foxglove as frames
from usv_op.view import NOMINAL_SIGMA, LiveView, location_fix

jsonschema = pytest.importorskip("jsonschema")
ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]

RTK = GnssFix(stamp_ns=1_764_000_000_123_456_789, seq=3, sender="1", latitude=59.9000123, longitude=10.7000456,
              altitude=12.5, quality=4, satellites=14, hdop=0.8, utc_time=36000.1, antenna=(0.6, -0.2))
TAG = GnssFix(stamp_ns=1_764_000_000_200_000_000, seq=0, sender="target", latitude=-33.5, longitude=-70.25,
              quality=1, hdop=None)


def test_a_fix_becomes_a_location_fix_with_its_values_and_an_approximated_covariance():
    message = location_fix(RTK)
    schema = published("LocationFix")
    assert not list(jsonschema.Draft7Validator(schema).iter_errors(message))
    assert_same_fields(message, schema)
    assert frames.LocationFix.model_validate(message).model_dump() == message
    assert message["timestamp"] == {"sec": 1_764_000_000, "nsec": 123_456_789}
    assert (message["latitude"], message["longitude"], message["altitude"]) == (59.9000123, 10.7000456, 12.5)
    assert message["frame_id"] == "vessel/1"
    h = (0.8 * 0.02) ** 2    # HDOP x RTK fixed's 2 cm, squared: east, north; four times that up
    assert message["position_covariance"] == pytest.approx([h, 0, 0, 0, h, 0, 0, 0, 4 * h], abs=0, rel=1e-12)
    assert message["position_covariance_type"] == 1
    # no HDOP (or a quality without a nominal accuracy): no covariance, type UNKNOWN, altitude 0 when not given
    tag = location_fix(TAG)
    assert tag["frame_id"] == "target" and tag["altitude"] == 0.0 and (tag["latitude"], tag["longitude"]) == (-33.5, -70.25)
    assert tag["position_covariance"] == [0.0] * 9 and tag["position_covariance_type"] == 0
    assert 3 not in NOMINAL_SIGMA and location_fix(RTK.model_copy(update={"quality": 3}))["position_covariance_type"] == 0


def test_the_committed_layout_has_a_map_that_follows_the_target_tags_fixes():
    layout = json.loads((ROOT / "docs" / "foxglove_layout.json").read_text())
    maps = []

    def walk(node: dict) -> None:
        content = node.get("content", node)
        if content.get("type") == "split":
            for item in content["items"]:
                walk(item)
        elif content.get("panelType") == "Map":
            maps.append(content)

    walk(layout)
    assert len(maps) == 1 and maps[0]["config"] == {"followTopic": "/target/gnss"}


class Recorder:
    """The part of foxglove-sdk LiveView uses: channels that keep what is logged on them."""

    def __init__(self) -> None:
        self.channels: dict[str, tuple[dict, list]] = {}

    def Channel(self, topic: str, schema: dict):
        logged: list = []
        self.channels[topic] = (schema, logged)
        return type("Channel", (), {"log": lambda _, payload: logged.append(json.loads(payload))})()


class Sample:
    def __init__(self, key_expr: str, payload: bytes) -> None:
        self.key_expr = key_expr
        self.payload = type("Payload", (), {"to_bytes": lambda _: payload})()


def test_the_view_publishes_each_senders_fixes_and_skips_a_forged_or_broken_one():
    sdk = Recorder()
    view = LiveView(sdk)
    view.on_gnss(Sample(gnss_truth_key("1"), encode(RTK)))
    view.on_gnss(Sample(gnss_truth_key("target"), encode(TAG)))
    view.on_gnss(Sample(gnss_truth_key("2"), encode(RTK)))         # vessel 1's fix on vessel 2's key
    view.on_gnss(Sample(gnss_truth_key("1"), b'{"latitude": 91}'))  # not a GnssFix
    assert sorted(sdk.channels) == ["/1/gnss", "/target/gnss"] and view.refused == 2
    schema, logged = sdk.channels["/1/gnss"]
    assert schema["title"] == "foxglove.LocationFix" and logged == [location_fix(RTK)]


def subscribe(client, subscription: int, channel: int) -> None:
    client.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": subscription, "channelId": channel}]}))


@pytest.mark.slow   # usv-op view and a Zenoh session over loopback, about 10 s
def test_a_foxglove_client_gets_the_fixes_from_the_live_view():
    from agent.runtime.zenoh_session import ZenohSettings, zenoh_config
    from sim_bridge.fleet import free_port

    websockets = pytest.importorskip("websockets.sync.client")
    pytest.importorskip("foxglove", reason="usv-op view needs foxglove-sdk")
    port = free_port()
    session = zenoh.open(zenoh_config(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"])))
    view = subprocess.Popen([sys.executable, "-m", "usv_op", "--connect", f"tcp/127.0.0.1:{port}", "view",
                             "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    received: dict[str, list] = {}
    advertised: dict[str, dict] = {}
    try:
        url = re.search(r"ws://[0-9.]+:\d+", line := view.stdout.readline())
        assert url, line + view.stderr.read()
        with websockets.connect(url[0], subprotocols=["foxglove.sdk.v1"], open_timeout=10) as client:
            ids: dict[int, str] = {}
            deadline = time.monotonic() + 20
            while not {"/1/gnss", "/target/gnss"} <= set(received) and time.monotonic() < deadline:
                session.put(gnss_truth_key("1"), encode(RTK))
                session.put(gnss_truth_key("target"), encode(TAG))
                try:
                    frame = client.recv(timeout=0.3)
                except TimeoutError:
                    continue
                if isinstance(frame, str):
                    message = json.loads(frame)
                    for channel in message.get("channels", []) if message["op"] == "advertise" else []:
                        if channel["topic"].endswith("/gnss") and channel["topic"] not in advertised:
                            advertised[channel["topic"]] = channel
                            ids[len(ids) + 1] = channel["topic"]
                            subscribe(client, len(ids), channel["id"])
                    if message["op"] == "status" and "Unknown channel ID" in message.get("message", ""):
                        # the server can advertise a channel a moment before it takes subscriptions to it
                        time.sleep(0.2)
                        channel_id = int(message["message"].rsplit(" ", 1)[-1])
                        topic = next(t for t, c in advertised.items() if c["id"] == channel_id)
                        subscribe(client, next(n for n, t in ids.items() if t == topic), channel_id)
                elif frame[0] == 1:   # message data: opcode, subscription id, log time, payload
                    subscription, _ = struct.unpack_from("<IQ", frame, 1)
                    received.setdefault(ids[subscription], []).append(json.loads(frame[13:]))
    finally:
        view.send_signal(signal.SIGTERM)
        out, err = view.communicate(timeout=20)
        session.close()
    assert view.returncode == 0, err
    assert {"/1/gnss", "/target/gnss"} <= set(received), (sorted(advertised), out, err)
    for topic, fix in (("/1/gnss", RTK), ("/target/gnss", TAG)):
        assert advertised[topic]["schemaName"] == "foxglove.LocationFix" and advertised[topic]["encoding"] == "json"
        assert received[topic][-1] == location_fix(fix)
