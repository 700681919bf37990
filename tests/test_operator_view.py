"""`usv-op view` and `usv-op layout`: the live fleet in Foxglove, over the Foxglove WebSocket protocol."""

from __future__ import annotations

import contextlib
import json
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from test_foxglove import assert_same_fields, published

from agent.runtime import foxglove as frames
from usv_op.layout import fleet_layout

ROOT = Path(__file__).resolve().parents[1]
websockets = pytest.importorskip("websockets.sync.client")
websockets_exceptions = pytest.importorskip("websockets.exceptions")
jsonschema = pytest.importorskip("jsonschema")


def test_the_committed_layout_is_the_one_usv_op_makes():
    committed = json.loads((ROOT / "docs" / "foxglove_layout.json").read_text())
    assert committed == json.loads(fleet_layout(["1", "2", "3", "4"]))
    text = json.dumps(committed)
    assert '"followTf": "world"' in text and '\\"usv/3/status\\".health.rejected_stale' in text


def plot_paths(node: dict) -> list[str]:
    """Every message path the layout's Plot panels read, walking its split tree as the app does."""
    content = node.get("content", node)
    if content.get("type") == "split":
        return [path for item in content["items"] for path in plot_paths(item)]
    assert content.get("type") == "panel" and content["panelType"] in ("ThreeDee", "Plot", "Map"), content
    return [series["value"] for series in content["config"].get("paths", [])]


def resolve(message: dict, path: str):
    """A Foxglove message path's value in `message` (the part after the quoted topic: `.a.b[0]`)."""
    value = message
    for name, index in re.findall(r"\.(\w+)|\[(\d+)\]", path):
        value = value[name] if name else value[int(index)]
    return value


@pytest.mark.slow   # a fleet of processes and the view over Zenoh, in real time
def test_a_foxglove_client_gets_every_live_vessels_frames_from_the_live_view(tmp_path):
    from sim_bridge.fleet import Fleet, Interrupted
    from sim_bridge.scenario import with_duration

    fleet = Fleet(with_duration(ROOT / "configs" / "scenarios" / "table2_estimators.yaml", tmp_path, 25.0), "mckf",
                  tmp_path / "runs", mode="realtime")
    def run_until_stopped() -> None:
        with contextlib.suppress(Interrupted):   # the test stops it once it has seen what it needs
            fleet.run(timeout=120)

    runner = threading.Thread(target=run_until_stopped, daemon=True)
    runner.start()
    view = subprocess.Popen([sys.executable, "-m", "usv_op", "--connect", f"tcp/127.0.0.1:{fleet.bridge_port}",
                             "view", "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = view.stdout.readline()
        url = re.search(r"ws://[0-9.]+:\d+", line)
        assert url, line + view.stderr.read()
        channels, schemas, received, subscriptions = {}, {}, {}, {}
        # The SDK's server speaks only its own subprotocol: an older client's offer is refused (docs/operator.md).
        with pytest.raises(websockets_exceptions.InvalidStatus, match="400"):
            websockets.connect(url[0], subprotocols=["foxglove.websocket.v1"], open_timeout=10)
        with websockets.connect(url[0], subprotocols=["foxglove.sdk.v1"], open_timeout=10) as client:
            def subscribe(channel: int) -> None:
                client.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": subscriptions[channel], "channelId": channel}]}))

            deadline = time.monotonic() + 30
            # The committed layout's plots, read as the app reads them: the quoted topic, then the field.
            paths = plot_paths(json.loads((ROOT / "docs" / "foxglove_layout.json").read_text()))
            plotted = [re.fullmatch(r'"([^"]+)"(.+)', path).groups() for path in paths]
            wanted = {f"/{v}/tf" for v in "1234"} | {"/tf"} | {topic for topic, _ in plotted}
            while not wanted <= set(received) and time.monotonic() < deadline:
                try:
                    frame = client.recv(timeout=1.0)
                except TimeoutError:
                    continue
                if isinstance(frame, str):
                    message = json.loads(frame)
                    if message["op"] == "advertise":
                        for c in message["channels"]:
                            if c["topic"] in wanted and c["topic"] not in schemas:
                                channels[len(channels) + 1] = c["topic"]
                                schemas[c["topic"]] = c
                                subscriptions[c["id"]] = len(channels)
                                subscribe(c["id"])
                    elif message["op"] == "status" and "Unknown channel ID" in message.get("message", ""):
                        # The server can advertise a channel a moment before it takes subscriptions to it.
                        time.sleep(0.2)
                        subscribe(int(message["message"].rsplit(" ", 1)[-1]))
                elif frame[0] == 1:   # message data: opcode, subscription id, log time, payload
                    subscription, _ = struct.unpack_from("<IQ", frame, 1)
                    received.setdefault(channels[subscription], []).append(json.loads(frame[13:]))
        assert wanted <= set(received), f"frames from {sorted(received)}"
    finally:
        view.send_signal(signal.SIGTERM)
        out, err = view.communicate(timeout=20)
        fleet.interrupt(signal.SIGINT)
        runner.join(timeout=60)
    assert view.returncode == 0, err
    assert re.search(r"stopped; \d+ messages on \d+ topics, 0 payloads skipped", out), out
    # Every plotted field is in the live messages, a number the plot can draw.
    assert len(plotted) == 4 + 4 * 5
    for topic, fields in plotted:
        value = resolve(received[topic][-1], fields)
        assert isinstance(value, (int, float)) and not isinstance(value, bool), (topic, fields, value)
    # The same schemas and the same checks as the logs' Foxglove messages.
    schema = published("FrameTransforms")
    validator = jsonschema.Draft7Validator(schema)
    for topic, messages in received.items():
        if not topic.endswith("tf"):
            continue
        advertised = schemas[topic]
        assert advertised["schemaName"] == "foxglove.FrameTransforms" and advertised["encoding"] == "json"
        assert json.loads(advertised["schema"]) == frames.FrameTransforms.model_json_schema()
        for message in messages:
            assert not list(validator.iter_errors(message))
            assert_same_fields(message, schema)
    # Each vessel's frames are its beliefs: its hull and the estimate of each neighbour hang off vessel/<id>.
    children = {t["child_frame_id"] for t in received["/2/tf"][-1]["transforms"]}
    assert {"vessel/2/hull", "vessel/2/estimate/1", "vessel/2/estimate/3", "vessel/2/estimate/4"} <= children
    truth = {t["child_frame_id"] for t in received["/tf"][-1]["transforms"]}
    assert {"target", "vessel/1", "vessel/4/hull"} <= truth
