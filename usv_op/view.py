"""`usv-op view`: the live fleet in Foxglove, served over the Foxglove WebSocket protocol (foxglove-sdk).

What the fleet publishes on Zenoh becomes the topics, frames and schemas of the MCAP logs, so one Foxglove
layout (docs/foxglove_layout.json, `usv-op layout`) shows a live fleet and a recorded one alike:
- from each agent's share: `/<id>/tf` (foxglove.FrameTransforms), its hull and where it believes each
  neighbour and the target are (agent/runtime/foxglove.py `estimate_links`, as its log draws them);
- from each agent's status: `usv/<id>/status` as it went out (health figures to plot), and once a second
  `/<id>/scene` (foxglove.SceneUpdate), the circle it steers to around its target estimate;
- from the sim bridge in real time (`sim/truth`): `/tf`, the ground truth in `world`, and once a second
  `/scene`, the true target and the circle.
Payloads that do not decode are skipped and counted (`refused`), never shown half.
"""

from __future__ import annotations

import threading
import time

import orjson

from agent.contract import TRUTH_KEY, ShareMessage, Status, decode, every
from agent.runtime import foxglove as frames

SCENE_PERIOD = frames.SCENE_PERIOD_NS * 1e-9


def load_sdk():
    """foxglove-sdk, or an ImportError that says how to get it (it is the operator's extra, not the boats')."""
    try:
        import foxglove
    except ImportError:
        raise ImportError("usv-op view needs foxglove-sdk: pip install 'usv-circumnav[operator]'") from None
    return foxglove


class LiveView:
    """Zenoh samples in, Foxglove channels out. The callbacks run on Zenoh's threads."""

    def __init__(self, sdk) -> None:
        self.sdk = sdk
        self.refused = 0
        self.sent: dict[str, int] = {}
        self._channels: dict[str, object] = {}
        self._scenes: dict[str, tuple[float, frames.StaticScene]] = {}   # topic -> (radius, scene)
        self._next_scene: dict[str, float] = {}
        self._radius: float | None = None
        self._lock = threading.Lock()

    def subscribe(self, session) -> list:
        return [session.declare_subscriber(every("share"), self.on_share),
                session.declare_subscriber(every("status"), self.on_status),
                session.declare_subscriber(TRUTH_KEY, self.on_truth)]

    # ----- Zenoh callbacks -----
    def on_share(self, sample) -> None:
        share, _ = decode(ShareMessage, sample.payload.to_bytes())
        if share is None:
            self._refuse()
            return
        target = None if share.target is None else (share.target[0], share.target[1])
        links = frames.estimate_links(share.sender, share.heading,
                                      [(j, e.position[0], e.position[1]) for j, e in share.neighbours.items()], target)
        self._log(f"/{share.sender}/tf", frames.FrameTransforms, frames.transforms(share.stamp_ns, links))

    def on_status(self, sample) -> None:
        payload = sample.payload.to_bytes()
        status, _ = decode(Status, payload)
        if status is None:
            self._refuse()
            return
        self._log(f"usv/{status.sender}/status", Status, payload)
        if status.radius is not None and status.target is not None:
            self._radius = status.radius
            frame = frames.estimate_frame(status.sender, "target")
            self._scene(f"/{status.sender}/scene", frame, status.radius, f"target as {status.sender} sees it",
                        status.stamp_ns)

    def on_truth(self, sample) -> None:
        try:
            truth = orjson.loads(sample.payload.to_bytes())
            positions = {v: s["position"] for v, s in truth["vessels"].items()}
            headings = {v: float(s["heading"]) for v, s in truth["vessels"].items()}
            links = frames.world_links(positions, headings, truth["target"])
            stamp = int(truth["stamp_ns"])
        except (orjson.JSONDecodeError, KeyError, TypeError, ValueError, IndexError):
            self._refuse()
            return
        self._log("/tf", frames.FrameTransforms, frames.transforms(stamp, links))
        if self._radius is not None:
            self._scene("/scene", "target", self._radius, "target", stamp)

    # ----- out to Foxglove -----
    def _scene(self, topic: str, frame: str, radius: float, label: str, stamp_ns: int) -> None:
        now = time.monotonic()
        if now < self._next_scene.get(topic, 0.0):
            return
        self._next_scene[topic] = now + SCENE_PERIOD
        cached = self._scenes.get(topic)
        if cached is None or cached[0] != radius:
            cached = self._scenes[topic] = (radius, frames.StaticScene(frames.target_entities(0, frame, radius, label)))
        self._log(topic, frames.SceneUpdate, cached[1].at(stamp_ns))

    def _log(self, topic: str, model, message: dict | bytes) -> None:
        with self._lock:
            channel = self._channels.get(topic)
            if channel is None:
                # The schema's title names it, as in the MCAP logs (foxglove.FrameTransforms, Status, ...).
                channel = self._channels[topic] = self.sdk.Channel(topic, schema=model.model_json_schema())
            self.sent[topic] = self.sent.get(topic, 0) + 1
        channel.log(message if isinstance(message, bytes) else orjson.dumps(message))

    def _refuse(self) -> None:
        with self._lock:
            self.refused += 1


def serve(session, host: str, port: int, stop: threading.Event, out=print) -> int:
    """Serve the live view until `stop` is set; the exit code."""
    sdk = load_sdk()
    view = LiveView(sdk)
    server = sdk.start_server(name="usv-op view", host=host, port=port)
    subscribers = view.subscribe(session)
    out(f"usv-op view: Foxglove WebSocket on ws://{host}:{server.port}: in Foxglove, open a connection to it "
        f"and import docs/foxglove_layout.json; Ctrl-C to stop", flush=True)
    try:
        while not stop.wait(1.0):
            pass
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()
        server.stop()
    out(f"usv-op view: stopped; {sum(view.sent.values())} messages on {len(view.sent)} topics, "
        f"{view.refused} payloads skipped", flush=True)
    return 0

