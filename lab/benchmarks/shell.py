"""The shells in process: what the sim bridge and each agent cost per tick beyond the core, without Zenoh.

A lockstep fleet in one thread, built from the processes' own objects: the `SimBridge` and an `AgentNode` per
vessel, their MCAP logs included. Where Zenoh would carry a payload, the bytes are handed to the receiver's
subscriber callback directly (sensors and the clock from the bridge, the shares of the tick before between
agents, commands and statuses back to the bridge), in the order the lockstep protocol gives them. So every
step of a tick is timed except the transport: decoding and the gates, the core's `step`, building, checking
and encoding messages, the logs, and the bridge's world and sensors. CPU time of this one thread: unlike
the fleet over Zenoh (`runtime_bench.py`), six processes sharing two cores do not move these figures much,
so a change to the shells shows here first. The commands equal the in-process runner's (lab/harness/runner.py).
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import agent.shell.node as node_module
from agent.contract import CLOCK_KEY, SHARE_FORMAT, encode, share_receivers
from agent.shell.node import AgentNode
from agent.shell.publish import declare_publishers
from agent.shell.settings import NodeSettings
from sim_bridge.bridge import BridgeSettings, SimBridge
from sim_bridge.fleet import agent_configs
from sim_bridge.scenario import Scenario

AGENT_SECTIONS = ("inputs", "core", "logging", "publishing")
SECTION_TEXT = {
    "inputs": "decoding and the gate: what its Zenoh callbacks do",
    "core": "the core's `step` (`decide` and its `report`)",
    "logging": "its MCAP log",
    "publishing": "the rest of its tick: shares delivered, snapshot, messages built, checked and encoded",
    "bridge": "the sim bridge: world, sensors, messages, commands and statuses decoded, ground truth logged",
}


class _Wire:
    """Stands in for a Zenoh session and its publishers: every put lands in `sent` as (key, bytes)."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, bytes]] = []

    def declare_publisher(self, key_expr: str, **_options) -> _Publisher:
        return _Publisher(self, key_expr)

    def take(self) -> list[tuple[str, bytes]]:
        sent, self.sent = self.sent, []
        return sent


@dataclass
class _Publisher:
    wire: _Wire
    key_expr: str

    def put(self, payload: bytes) -> None:
        self.wire.sent.append((self.key_expr, bytes(payload)))

    def undeclare(self) -> None:
        pass


@dataclass
class _Sample:
    """What a Zenoh subscriber callback is given."""

    key_expr: str
    data: bytes

    @property
    def payload(self) -> _Sample:
        return self

    def to_bytes(self) -> bytes:
        return self.data


@dataclass
class ShellRun:
    ticks: int
    vessels: list[str]
    seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys((*AGENT_SECTIONS, "bridge"), 0.0))
    commands: np.ndarray | None = None     # (ticks, vessels, 2): surge and yaw rate as published
    share_bytes: int = 0          # share payloads delivered to agents, all ticks (Zenoh's framing not counted)
    share_messages: int = 0       # ... and how many
    share_seconds: float = 0.0    # of the inputs' CPU: the agents' callbacks on those shares

    def per_tick_ms(self, section: str) -> float:
        """Mean CPU milliseconds per tick: of one agent for an agent section, of the bridge for "bridge"."""
        agents = 1 if section == "bridge" else len(self.vessels)
        return 1e3 * self.seconds[section] / (self.ticks * agents)

    @property
    def agent_ms(self) -> float:
        return sum(self.per_tick_ms(s) for s in AGENT_SECTIONS)


class _Timed:
    """A callable that adds its thread CPU time to `run.seconds[section]`."""

    def __init__(self, function, run: ShellRun, section: str) -> None:
        self.function, self.run, self.section = function, run, section

    def __call__(self, *args, **kwargs):
        started = time.thread_time()
        try:
            return self.function(*args, **kwargs)
        finally:
            self.run.seconds[self.section] += time.thread_time() - started


class _TimedDecide(_Timed):
    """The core's `decide`, and the `report` it returns, both timed as the core."""

    def __call__(self, *args, **kwargs):
        state, command, report = super().__call__(*args, **kwargs)
        return state, command, _Timed(report, self.run, self.section)


def run_shells(scenario: Scenario, folder: Path | None = None, between_ticks=None,
               share_format: int = SHARE_FORMAT) -> ShellRun:
    """One lockstep run of `scenario` (every vessel there from start to end) through the sim bridge's and the
    agents' shells, timed by section; the logs go to `folder` (a temporary folder if None).
    `between_ticks(k, nodes)`, if given, is called once every agent has ticked k (and before the world moves
    on): what arrives then is the next tick's. The agents send shares in `share_format` (docs/contract.md),
    each delivered as Zenoh would route it."""
    with tempfile.TemporaryDirectory() as scratch:
        return _run(scenario, Path(folder or scratch), between_ticks, share_format)


def _run(scenario: Scenario, folder: Path, between_ticks, share_format: int) -> ShellRun:
    folder.mkdir(parents=True, exist_ok=True)
    ids = [v.id for v in scenario.world.vessels]
    if any(v.join_time > 0 or v.leave_time is not None for v in scenario.world.vessels):
        raise ValueError(f"{scenario.name}: the shell bench needs every vessel there for the whole run")
    steps = round(scenario.duration / scenario.world.dt) + 1
    run = ShellRun(ticks=steps, vessels=ids, commands=np.full((steps, len(ids), 2), np.nan))
    bridge = SimBridge(scenario, BridgeSettings(log=str(folder / "sim.mcap")))
    configs = agent_configs(scenario, None, folder, lambda vessel: {})
    nodes = {v: AgentNode(v, NodeSettings.model_validate(configs[v])) for v in ids}
    wire = {v: _Wire() for v in ["bridge", *ids]}
    publishers = {v: declare_publishers(wire[v], v, True, share_format) for v in ids}
    core_decide = node_module.decide
    node_module.decide = _TimedDecide(core_decide, run, "core")
    try:
        for vessel, node in nodes.items():
            node.recorder.open()
            node.recorder.tick_log.tick = _Timed(node.recorder.tick_log.tick, run, "logging")
            node.live_peers = set(ids) - {vessel}
            node._live_view = frozenset(node.live_peers)
        bridge.alive = set(ids)
        previous: int | None = None
        shares: list[tuple[str, bytes]] = []
        for k in range(steps):
            started = time.thread_time()
            now, stamp, live = bridge.world.time, bridge.world.time_ns, bridge.world.live()
            bridge._publish_sensors(wire["bridge"], stamp)
            clock = bridge._clock(k, stamp, previous, live, set(live) if k == 0 else set())
            bridge._publisher(wire["bridge"], CLOCK_KEY).put(encode(clock))
            run.seconds["bridge"] += time.thread_time() - started
            published = wire["bridge"].take()
            answers = []
            for vessel in ids:
                node = nodes[vessel]
                started = time.thread_time()
                for key_expr, payload in published:
                    if key_expr.startswith(f"usv/{vessel}/"):
                        node._on_input(_Sample(key_expr, payload))
                sharing = time.thread_time()
                for key_expr, payload in shares:
                    if share_receivers(key_expr) in (vessel, "*") and not key_expr.startswith(f"usv/{vessel}/"):
                        node._on_input(_Sample(key_expr, payload))
                        run.share_bytes += len(payload)
                        run.share_messages += 1
                run.share_seconds += time.thread_time() - sharing
                node._on_clock(_Sample(CLOCK_KEY, published[-1][1]))
                node.ticker.clocked.clear()
                ticking = time.thread_time()
                run.seconds["inputs"] += ticking - started
                inner = run.seconds["core"] + run.seconds["logging"]
                node._tick(publishers[vessel], node.ticker.clock.latest)
                inner = run.seconds["core"] + run.seconds["logging"] - inner
                run.seconds["publishing"] += time.thread_time() - ticking - inner
                answers += wire[vessel].take()
            if between_ticks is not None:
                between_ticks(k, nodes)
            started = time.thread_time()
            shares = []
            for key_expr, payload in answers:
                if key_expr.endswith("/cmd"):
                    bridge._on_command(_Sample(key_expr, payload))
                elif key_expr.endswith("/status"):
                    bridge._on_status(_Sample(key_expr, payload))
                else:
                    shares.append((key_expr, payload))
            bridge._log_tick(stamp)
            bridge.world.step(bridge._commands_now(now))
            bridge.ticks += 1
            run.seconds["bridge"] += time.thread_time() - started
            for n, vessel in enumerate(ids):
                command = bridge.commands[vessel]
                run.commands[k, n] = command.surge, command.yaw_rate
            previous = stamp
    finally:
        node_module.decide = core_decide
        for node in nodes.values():
            node.recorder.close()
        if bridge.log is not None:
            bridge.log.close()
    return run
