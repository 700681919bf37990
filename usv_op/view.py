"""`usv-op view`: the live fleet in Foxglove, served over the Foxglove WebSocket protocol (foxglove-sdk).

What the fleet publishes on Zenoh becomes the topics, frames and schemas of the MCAP logs, so one Foxglove
layout (docs/foxglove_layout.json, `usv-op layout`) shows a live fleet and a recorded one alike:
- from each agent's share: `/<id>/tf` (foxglove.FrameTransforms), its hull and where it believes each
  neighbour and the target are (agent/runtime/foxglove.py `estimate_links`, as its log draws them);
- from each agent's status: `usv/<id>/status` as it went out (health figures to plot), and once a second
  `/<id>/scene` (foxglove.SceneUpdate), the circle it steers to around its target estimate;
- from the sim bridge in real time (`sim/truth`): `/tf`, the ground truth in `world`, and once a second
  `/scene`, the true target and the circle;
- from each driver's GNSS receiver (`usv/<id>/truth/gnss`, a field trial's truth; the target's tag too):
  `/<id>/gnss` (foxglove.LocationFix) for Foxglove's Map panel, its covariance HDOP x the fix quality's
  nominal accuracy (`location_fix`).
Payloads that do not decode, or whose sender is not the vessel of their key, are skipped and counted
(`refused`), never shown half. Channels are bounded: at most `max_vessels` vessels get channels of each kind
(tf, status, scene: a vessel's three), the first come first served; a message that would open one more is
dropped and counted (`channels_refused`), and the first of each kind is told on stderr. Without TLS anyone
on the network can publish as any vessel id, and each forged id would otherwise cost a Foxglove channel (5,000
forged senders made 15,000 channels, 339 MB, and 50 s for a new client to connect).
"""

from __future__ import annotations

import sys
import threading
import time

import orjson

from agent.contract import TRUTH_KEY, GnssFix, ShareMessage, Status, decode, every, gnss_truth_key, vessel_of
from agent.runtime import foxglove as frames

SCENE_PERIOD = frames.SCENE_PERIOD_NS * 1e-9
# Per-axis horizontal 1-sigma (m) at HDOP 1 by GGA fix quality, for the Map panel's ellipse (our choice, as the
# sim's receivers: 1 GNSS 1.5 m, 4 RTK fixed 2 cm; DGNSS and RTK float between). Vertical: twice it.
NOMINAL_SIGMA = {1: 1.5, 2: 0.5, 4: 0.02, 5: 0.3}
MAX_VESSELS = 64   # vessels with channels of each kind (a fleet is a handful; `usv-op view --max-vessels`)


def load_sdk():
    """foxglove-sdk, or an ImportError that says how to get it (it is the operator's extra, not the boats')."""
    try:
        import foxglove
    except ImportError:
        raise ImportError("usv-op view needs foxglove-sdk: pip install 'usv-circumnav[operator]'") from None
    return foxglove


class LiveView:
    """Zenoh samples in, Foxglove channels out. The callbacks run on Zenoh's threads."""

    def __init__(self, sdk, max_vessels: int = MAX_VESSELS, warn=None) -> None:
        self.sdk = sdk
        self.max_vessels = max_vessels
        self.refused = 0
        self.channels_refused = 0
        self.sent: dict[str, int] = {}
        self._channels: dict[str, object] = {}
        self._vessels: dict[str, set[str]] = {}   # kind (tf, status, scene) -> vessels with a channel of it
        self._told: set[str] = set()              # kinds whose cap was told on stderr
        self._warn = warn if warn is not None else (lambda text: print(text, file=sys.stderr, flush=True))
        self._scenes: dict[str, tuple[float, frames.StaticScene]] = {}   # topic -> (radius, scene)
        self._next_scene: dict[str, float] = {}
        self._radius: float | None = None
        self._lock = threading.Lock()

    def subscribe(self, session) -> list:
        return [session.declare_subscriber(every("share"), self.on_share),
                session.declare_subscriber(every("status"), self.on_status),
                session.declare_subscriber(TRUTH_KEY, self.on_truth),
                session.declare_subscriber(gnss_truth_key("*"), self.on_gnss)]

    # ----- Zenoh callbacks -----
    def on_share(self, sample) -> None:
        share, _ = decode(ShareMessage, sample.payload.to_bytes())
        if share is None or share.sender != vessel_of(str(sample.key_expr)):
            self._refuse()
            return
        target = None if share.target is None else (share.target[0], share.target[1])
        links = frames.estimate_links(share.sender, share.heading,
                                      [(j, e.position[0], e.position[1]) for j, e in share.neighbours.items()], target)
        self._log(f"/{share.sender}/tf", frames.FrameTransforms, frames.transforms(share.stamp_ns, links),
                  ("tf", share.sender))

    def on_status(self, sample) -> None:
        payload = sample.payload.to_bytes()
        status, _ = decode(Status, payload)
        if status is None or status.sender != vessel_of(str(sample.key_expr)):
            self._refuse()
            return
        self._log(f"usv/{status.sender}/status", Status, payload, ("status", status.sender))
        if status.radius is not None and status.target is not None:
            self._radius = status.radius
            frame = frames.estimate_frame(status.sender, "target")
            self._scene(f"/{status.sender}/scene", frame, status.radius, f"target as {status.sender} sees it",
                        status.stamp_ns, ("scene", status.sender))

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

    def on_gnss(self, sample) -> None:
        fix, _ = decode(GnssFix, sample.payload.to_bytes())
        if fix is None or fix.sender != vessel_of(str(sample.key_expr)):
            self._refuse()
            return
        self._log(f"/{fix.sender}/gnss", frames.LocationFix, location_fix(fix), ("gnss", fix.sender))

    # ----- out to Foxglove -----
    def _scene(self, topic: str, frame: str, radius: float, label: str, stamp_ns: int,
               owner: tuple[str, str] | None = None) -> None:
        now = time.monotonic()
        if now < self._next_scene.get(topic, 0.0) or (topic not in self._channels and not self._room(owner)):
            return
        self._next_scene[topic] = now + SCENE_PERIOD
        cached = self._scenes.get(topic)
        if cached is None or cached[0] != radius:
            cached = self._scenes[topic] = (radius, frames.StaticScene(frames.target_entities(0, frame, radius, label)))
        self._log(topic, frames.SceneUpdate, cached[1].at(stamp_ns), owner)

    def _room(self, owner: tuple[str, str] | None) -> bool:
        """Whether `owner` (kind, vessel) has or may open a channel; counted and told (the first of each kind)
        when not."""
        if owner is None:
            return True
        kind, vessel = owner
        with self._lock:
            vessels = self._vessels.setdefault(kind, set())
            if vessel in vessels or len(vessels) < self.max_vessels:
                vessels.add(vessel)
                return True
            self.channels_refused += 1
            first = kind not in self._told
            self._told.add(kind)
        if first:
            self._warn(f"usv-op view: {self.max_vessels} vessels have {kind} channels already; messages of "
                       f"more (here from {vessel!r}) are dropped and counted (--max-vessels to see more)")
        return False

    def _log(self, topic: str, model, message: dict | bytes, owner: tuple[str, str] | None = None) -> None:
        if topic not in self._channels and not self._room(owner):
            return
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


def location_fix(fix: GnssFix) -> dict:
    """A GnssFix as foxglove.LocationFix: the antenna's position; an approximated diagonal covariance, (HDOP x
    NOMINAL_SIGMA of its quality)^2 east and north and four times that up, when both are known, else type 0."""
    sigma = NOMINAL_SIGMA.get(fix.quality)
    known = sigma is not None and fix.hdop is not None
    h = (fix.hdop * sigma) ** 2 if known else 0.0
    frame = "target" if fix.sender == "target" else frames.vessel_frame(fix.sender)
    return {"timestamp": frames.time_of(fix.stamp_ns).model_dump(), "frame_id": frame,
            "latitude": fix.latitude, "longitude": fix.longitude,
            "altitude": 0.0 if fix.altitude is None else fix.altitude,
            "position_covariance": [h, 0.0, 0.0, 0.0, h, 0.0, 0.0, 0.0, 4 * h], "position_covariance_type": int(known)}


def serve(session, host: str, port: int, stop: threading.Event, out=print,
          max_vessels: int = MAX_VESSELS) -> int:
    """Serve the live view until `stop` is set; the exit code."""
    sdk = load_sdk()
    view = LiveView(sdk, max_vessels)
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
        f"{view.refused} payloads skipped, {view.channels_refused} messages of vessels beyond {max_vessels} "
        "dropped", flush=True)
    return 0

