"""`usv-lab fuzz`: a fuzz campaign against one real agent process over Zenoh. A test of robustness, not speed.

One `usv-agent` process runs on sim time and listens on loopback. A Zenoh session plays its world: a small
genuine mission (vessel 1, the agent's, and two neighbours 2 and 3 with live liveliness tokens, circling a
target at the origin), and between each tick's genuine messages a batch of bad payloads on every key the
agent subscribes to: its four sensor keys, every vessel's share (`usv/*/share/1`, `usv/*/share`), `sim/clock` and the
operator's mission keys (`mission/all`, `mission/1`; a genuine body is a harmless `set` of the radius and
direction the mission already has). The payloads
come from one seeded numpy Generator, in the classes listed in docs/reliability.md §4.

Every command the agent publishes is recorded and checked (finite, |surge| <= U_v, |yaw rate| <= U_omega_c +
omega*); the agent's peak resident memory is read from /proc (VmHWM) before and after; after the storm a
few genuine ticks must bring commands that move the vessel again. `tests/test_fuzz.py` runs a campaign of
5,000 payloads per key; `usv-lab fuzz` a larger one and writes docs/results/fuzz.md.

`usv-lab fuzz` then plays targeted attacks on the mission keys and on liveliness (`run_attacks`, ATTACKS):
a seq of 2^63 - 1, 300 new senders and a replayed hold, a flood from one sender while usv-op holds, 300
forged liveliness tokens and a vessel's restart, a dead vessel's id declared by another process; after
each, the operator's `usv-op hold` and `usv-op resume` must be applied. `tests/test_attacks.py` runs them.

More: docs/reliability.md §4, `lab/benchmarks/fuzz.py`.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
import zenoh

from agent.contract import share_key
from agent.core.params import AgentParams
from agent.runtime.zenoh_session import ZenohSettings, zenoh_config
from lab import arguments
from lab.benchmarks import mavlink_fuzz, serial_fuzz
from lab.report.markdown import invocation, machine, markdown_table

VESSEL = "1"
PEERS = ("2", "3")
KEYS = ("sensor/odom", "sensor/uwb", "sensor/bearing", "sensor/sonar", "share", "sim/clock", "mission/all",
        f"mission/{VESSEL}")
OPERATOR = "op"
CLASSES = ("random_bytes", "wrong_types", "extremes", "non_spd", "seq_poison", "stamp_poison", "phantom", "flood")
RADIUS = 5.0
OMEGA = math.pi / 30
DT = AgentParams().dt
SECOND = 10**9
ID_CHARS = np.array(list("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_-"))

# Numbers as JSON text: what a float cannot hold (1e400, 10^400) is written as the text itself.
EXTREME_NUMBERS = ("1e308", "-1e308", "1e-308", "5e-324", "-0.0", "1e400", "-1e400", "NaN", "Infinity",
                   "-Infinity", "100001.0", "1e6", "1e15", "9223372036854775808", "1" + "0" * 400, "-1",
                   "18446744073709551616", "0")
SEQS = ("1000000000", "9223372036854775807", "9223372036854775808", "1" + "0" * 400, "-1", "0", "1e9", "3.5")
WRONG_VALUES = ('"x"', "null", "true", "[]", "{}", '[1, "a"]', '{"a": 1}', '"NaN"', "[[[[[[[[1]]]]]]]]",
                '["' + "z" * 300 + '"]', "[" * 300 + "]" * 300)


@dataclass
class Results:
    payloads: dict[str, Counter] = field(default_factory=lambda: {k: Counter() for k in KEYS})
    genuine_ticks: int = 0
    commands: int = 0
    moving_commands: int = 0
    bad_commands: list = field(default_factory=list)   # non-finite or beyond the limits: must stay empty
    after_storm_commands: int = 0
    after_storm_moving: int = 0
    after_storm_ticked_statuses: int = 0
    health: dict[str, int] = field(default_factory=dict)
    alive_at_end: bool = False
    exit_code: int | None = None
    memory: list = field(default_factory=list)   # (fraction of the storm done, VmRSS MB)
    peak_mb: float = 0.0
    seconds: float = 0.0
    stderr_tail: str = ""
    error_kinds: list[str] = field(default_factory=list)

    def per_key(self) -> dict[str, int]:
        return {k: sum(c.values()) for k, c in self.payloads.items()}


def _memory_mb(pid: int, name: str) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(f"{name}:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


class World:
    """The genuine mission: three vessels evenly spaced on a circle of RADIUS around a target at the origin,
    moving at OMEGA; odometry in each vessel's own frame (zero at the start)."""

    ids = (VESSEL, *PEERS)

    def angle(self, vessel: str, t: float) -> float:
        return 2 * math.pi * self.ids.index(vessel) / len(self.ids) + OMEGA * t

    def position(self, vessel: str, t: float) -> np.ndarray:
        a = self.angle(vessel, t)
        return RADIUS * np.array([math.cos(a), math.sin(a)])

    def odometry(self, vessel: str, k: int) -> dict:
        t = k * DT
        return {"stamp_ns": round(t * SECOND), "seq": k, "sender": vessel,
                "position": (self.position(vessel, t) - self.position(vessel, 0.0)).tolist(),
                "heading": math.remainder(self.angle(vessel, t) + math.pi / 2, 2 * math.pi),
                "covariance": [1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-5]}

    def sensors(self, k: int) -> dict[str, dict]:
        t, stamp = k * DT, round(k * DT * SECOND)
        me = self.position(VESSEL, t)
        head = {"stamp_ns": stamp, "seq": k, "sender": VESSEL}
        return {
            "sensor/odom": self.odometry(VESSEL, k),
            "sensor/uwb": head | {"ranges": {j: float(np.linalg.norm(me - self.position(j, t))) for j in PEERS}},
            "sensor/bearing": head | {"bearing": (me / np.linalg.norm(me)).tolist()},
            "sensor/sonar": head | {"points": [[30.0, 1.0], [30.5, 1.2]]},
        }

    def share(self, vessel: str, k: int) -> dict:
        t = k * DT
        me = self.position(vessel, t)
        a = self.angle(vessel, t)
        odometry = {name: value for name, value in self.odometry(vessel, k).items() if name != "covariance"}
        return odometry | {
            "velocity": (OMEGA * RADIUS * np.array([-math.sin(a), math.cos(a)])).tolist(),
            "phase": math.remainder(a, 2 * math.pi),
            "target": [*me.tolist(), 0.0, 0.0], "target_covariance": (0.05 * np.eye(4)).ravel().tolist(),
            "neighbours": {VESSEL: {"position": (me - self.position(VESSEL, t)).tolist(),
                                    "covariance": [0.04, 0.0, 0.04]}}}

    def mission(self, k: int) -> dict:
        """An operator's `set` that changes nothing: the radius and direction the mission has."""
        return {"stamp_ns": round(k * DT * SECOND), "seq": k, "sender": OPERATOR, "command": "set",
                "radius": RADIUS, "direction": "ccw"}

    def clock(self, k: int) -> dict:
        return {"stamp_ns": round(k * DT * SECOND), "seq": k, "sender": "sim",
                "previous_ns": round((k - 1) * DT * SECOND) if k else None, "vessels": list(self.ids),
                "senders": None, "lost": [], "lockstep": False}

    def initial(self) -> dict:
        """The agent's deployment knowledge: x_io,0 and p_ij,0 (InitialEstimates)."""
        me = self.position(VESSEL, 0.0)
        velocity = OMEGA * RADIUS * np.array([-math.sin(self.angle(VESSEL, 0.0)), math.cos(self.angle(VESSEL, 0.0))])
        return {"target": [*me.tolist(), *velocity.tolist()], "target_variance": 0.5,
                "neighbours": {j: (me - self.position(j, 0.0)).tolist() for j in PEERS}}


class Fuzzer:
    """Bad payloads of each class for each key, from one seeded Generator."""

    def __init__(self, rng: np.random.Generator, world: World) -> None:
        self.rng = rng
        self.world = world
        self._phantoms = 0
        self._share_keys = 0

    # ----- helpers -----
    def _pick(self, values):
        return values[int(self.rng.integers(len(values)))]

    def _id(self) -> str:
        self._phantoms += 1
        n = int(self.rng.integers(1, 12))
        return "".join(self.rng.choice(ID_CHARS, n)) + f"-{self._phantoms}"

    def genuine(self, topic: str, k: int) -> dict:
        if topic == "share":
            return self.world.share(self._pick(PEERS), k)
        if topic == "sim/clock":
            return self.world.clock(k)
        if topic.startswith("mission/"):
            return self.world.mission(k)
        return self.world.sensors(k)[topic]

    def _share_key(self, sender: str) -> str:
        """The agent hears shares in both formats: bad ones go to its per-pair key and to the broadcast key in
        turn (a counter, not the Generator, so the campaign's draws are those of one key)."""
        self._share_keys += 1
        return share_key(sender, VESSEL if self._share_keys % 2 else None)

    def key_of(self, topic: str, body: dict | None = None) -> str:
        if topic == "sim/clock" or topic.startswith("mission/"):
            return topic
        if topic == "share":
            sender = body.get("sender") if isinstance(body, dict) else None
            return self._share_key(sender if isinstance(sender, str) and sender in PEERS else self._pick(PEERS))
        return f"usv/{VESSEL}/{topic}"

    @staticmethod
    def _dump(body: dict, raw: dict[str, str]) -> bytes:
        """JSON of `body`, with the values of `raw` (field -> JSON text) written as they are."""
        marked = {name: f"\x00{name}\x00" if name in raw else value for name, value in body.items()}
        text = json.dumps(marked)
        for name, value in raw.items():
            text = text.replace(json.dumps(f"\x00{name}\x00"), value)
        return text.encode()

    def _numeric_fields(self, body: dict) -> list[str]:
        return [name for name, value in body.items()
                if name not in ("sender", "lockstep") and value is not None and not isinstance(value, str)]

    def _replace_number(self, value, text: str) -> str:
        """JSON text of `value` with one of its numbers replaced by `text`."""
        if isinstance(value, bool) or value is None:
            return text
        if isinstance(value, (int, float)):
            return text
        if isinstance(value, list) and value:
            i = int(self.rng.integers(len(value)))
            parts = [json.dumps(v) for v in value]
            parts[i] = self._replace_number(value[i], text)
            return "[" + ", ".join(parts) + "]"
        if isinstance(value, dict) and value:
            keys = list(value)
            name = keys[int(self.rng.integers(len(keys)))]
            return "{" + ", ".join(f"{json.dumps(n)}: " + (self._replace_number(v, text) if n == name else json.dumps(v))
                                   for n, v in value.items()) + "}"
        return text

    # ----- the classes -----
    def payload(self, topic: str, cls: str, k: int) -> tuple[str, bytes]:
        body = self.genuine(topic, k)
        key = self.key_of(topic, body)
        rng = self.rng
        if cls == "random_bytes":
            data = rng.bytes(int(rng.integers(0, 600)))
            if rng.random() < 0.3:
                data = b'{"stamp_ns": ' + data
            return key, data
        if cls == "wrong_types":
            choice = rng.random()
            if choice < 0.15:
                return key, self._pick(WRONG_VALUES).encode()
            body = dict(body)
            if choice < 0.3 and body:
                del body[self._pick(list(body))]
                return key, json.dumps(body).encode()
            if choice < 0.4:
                body["extra_field"] = 1
                return key, json.dumps(body).encode()
            names = list(body)
            raw = {name: self._pick(WRONG_VALUES) for name in rng.choice(names, min(len(names), int(rng.integers(1, 4))),
                                                                          replace=False)}
            return key, self._dump(body, raw)
        if cls == "extremes":
            names = self._numeric_fields(body)
            raw = {name: self._replace_number(body[name], self._pick(EXTREME_NUMBERS))
                   for name in rng.choice(names, min(len(names), int(rng.integers(1, 3))), replace=False)}
            return key, self._dump(body, raw)
        if cls == "non_spd":
            matrix = self._bad_covariance()
            if topic == "sensor/odom":
                return key, self._dump(body, {"covariance": json.dumps(self._sized(matrix, 3))})
            if topic == "share":
                if rng.random() < 0.5:
                    return key, self._dump(body, {"target_covariance": json.dumps(self._sized(matrix, 4))})
                m = self._sized(matrix, 2)
                pair = {"position": [1.0, 1.0], "covariance": [m[0], m[1], m[3]] if len(m) == 4 else m[:3]}
                return key, json.dumps(body | {"neighbours": {VESSEL: pair}}).encode()
            raise ValueError(f"no covariance on {topic}")
        if cls == "seq_poison":
            return key, self._dump(body, {"seq": self._pick(SEQS)})
        if cls == "stamp_poison":
            now = body["stamp_ns"]
            stamp = self._pick((
                "0", str(2**62), str(2**63 - 1), str(2**63), "1" + "0" * 400, "-1", "1e18", "4.5",
                str(now + 10 * SECOND), str(max(0, now - 10 * SECOND)), str(now + SECOND // 3),
                str(now + SECOND // 2 - 1), str(max(0, now - 9 * SECOND // 10)), str(now + SECOND // 20)))
            if topic == "sim/clock" and rng.random() < 0.5:
                return key, self._dump(body, {"previous_ns": stamp})
            return key, self._dump(body, {"stamp_ns": stamp})
        if cls == "phantom":
            return self._phantom(topic, body, key)
        raise ValueError(f"unknown class {cls}")

    def _bad_covariance(self) -> np.ndarray:
        rng = self.rng
        n = 4
        kind = int(rng.integers(6))
        if kind == 0:
            return -np.eye(n) * 10 ** rng.uniform(-3, 3)
        if kind == 1:
            a = np.eye(n)
            a[0, 1] = 1.0 + rng.random()                       # asymmetric
            return a
        if kind == 2:
            v = rng.normal(size=n)
            return np.eye(n) - 2.5 * np.outer(v, v) / (v @ v)  # symmetric, one eigenvalue -1.5
        if kind == 3:
            return np.eye(n) * 1e11                            # beyond MAX_VARIANCE
        if kind == 4:
            a = rng.normal(size=(n, n))
            return a + a.T                                     # symmetric, indefinite (almost surely)
        return np.full((n, n), np.nan)

    @staticmethod
    def _sized(matrix: np.ndarray, n: int) -> list:
        values = matrix[:n, :n].ravel().tolist()
        return [v if math.isfinite(v) else "NaN" for v in values]

    def _phantom(self, topic: str, body: dict, key: str) -> tuple[str, bytes]:
        rng = self.rng
        if topic == "share":
            if rng.random() < 0.6:
                sender = self._id()
                return self._share_key(sender), json.dumps(body | {"sender": sender}).encode()
            if rng.random() < 0.5:
                return key, json.dumps(body | {"sender": self._pick([p for p in PEERS if f"/{p}/" not in key])}).encode()
            many = {self._id(): {"position": [1.0, 1.0], "covariance": [0.04, 0.0, 0.04]} for _ in range(256)}
            return key, json.dumps(body | {"neighbours": many}).encode()
        if topic == "sim/clock":
            if rng.random() < 0.5:
                return key, json.dumps(body | {"vessels": [VESSEL, *[self._id() for _ in range(255)]],
                                               "senders": [self._id() for _ in range(200)]}).encode()
            return key, json.dumps(body | {"lost": [[self._id(), VESSEL] for _ in range(2000)]}).encode()
        if topic.startswith("mission/"):
            if rng.random() < 0.6:
                return f"mission/{self._id()}", json.dumps(body).encode()
            return key, json.dumps(body | {"sender": self._id() * 20}).encode()
        if topic == "sensor/uwb" and rng.random() < 0.7:
            return key, json.dumps(body | {"ranges": {self._id(): float(rng.uniform(0, 50)) for _ in range(256)}}).encode()
        return key, json.dumps(body | {"sender": self._pick(PEERS)}).encode()

    def classes_for(self, topic: str) -> tuple[str, ...]:
        return tuple(c for c in CLASSES if c != "flood" and (c != "non_spd" or topic in ("sensor/odom", "share")))

    def flood(self, topic: str, k: int, n: int) -> list[tuple[str, bytes]]:
        """`n` messages on one key at once: genuine-looking ones (a share from a new id each time)."""
        out = []
        for i in range(n):
            body = self.genuine(topic, k)
            if topic == "share":
                sender = self._id()
                out.append((self._share_key(sender), json.dumps(body | {"sender": sender}).encode()))
            else:
                out.append((self.key_of(topic, body), json.dumps(body | {"seq": body["seq"] + i}).encode()))
        return out


def _agent_config(folder: Path, port: int, world: World) -> Path:
    config = {"clock": "sim", "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]}, "id_check": 0.2,
              "log": str(folder / "agent-{vessel}.mcap"), "initial": world.initial()}
    path = folder / "agent.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def run_campaign(per_key: int = 5000, seed: int = 1, folder: Path | None = None, after_storm: int = 30,
                 flood_size: int = 1200, progress=None) -> Results:
    """Run one campaign: at least `per_key` bad payloads on each subscribed key (floods of `flood_size`
    included), between genuine ticks; then `after_storm` genuine ticks alone. Returns what was seen."""
    from sim_bridge.fleet import free_port

    results = Results()
    temporary = tempfile.TemporaryDirectory(prefix="usv-fuzz-") if folder is None else None
    folder = Path(temporary.name) if temporary is not None else folder
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    world, params = World(), AgentParams()
    fuzzer = Fuzzer(rng, world)
    limits = (params.control.max_speed, params.control.max_correction_yaw_rate + params.control.yaw_rate)
    port = free_port()
    stderr_path = folder / "agent.err"
    started = time.monotonic()
    process = subprocess.Popen([sys.executable, "-m", "agent", "--vessel", VESSEL, "--config",
                                str(_agent_config(folder, port, world))], stderr=stderr_path.open("w"))
    lock = threading.Lock()
    stamps: set[int] = set()
    statuses: list[dict] = []
    phase = {"storm": True}

    def on_command(sample) -> None:
        try:
            command = json.loads(sample.payload.to_bytes())
            surge, yaw_rate = float(command["surge"]), float(command["yaw_rate"])
            sound = (math.isfinite(surge) and math.isfinite(yaw_rate) and abs(surge) <= limits[0]
                     and abs(yaw_rate) <= limits[1] * (1 + 1e-9))
        except (ValueError, KeyError, TypeError) as error:
            command, surge, yaw_rate, sound = {"error": str(error)}, math.nan, math.nan, False
        with lock:
            results.commands += 1
            moving = sound and (surge != 0.0 or yaw_rate != 0.0)
            results.moving_commands += moving
            if not sound:
                results.bad_commands.append(command)
            if not phase["storm"]:
                results.after_storm_commands += 1
                results.after_storm_moving += moving
            stamps.add(command.get("stamp_ns"))

    def on_status(sample) -> None:
        with lock:
            status = json.loads(sample.payload.to_bytes())
            statuses.append(status)
            if len(statuses) > 100:
                del statuses[:50]
            if not phase["storm"] and status.get("ticked"):
                results.after_storm_ticked_statuses += 1

    session = zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"])))
    publishers: dict[str, object] = {}

    def put(key: str, payload: bytes) -> None:
        """Publish without dropping anything: a declared publisher for the genuine keys, a put for the rest."""
        publisher = publishers.get(key)
        if publisher is None and (key == "sim/clock" or key.split("/")[1] in (*world.ids, "all")):
            publisher = publishers[key] = session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK)
        if publisher is not None:
            publisher.put(payload)
        else:
            session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    try:
        session.declare_subscriber(f"usv/{VESSEL}/cmd", on_command)
        session.declare_subscriber(f"usv/{VESSEL}/status", on_status)
        tokens = [session.liveliness().declare_token(f"usv/{j}/alive") for j in PEERS]
        deadline = time.monotonic() + 60
        while not (statuses and set(PEERS) <= set(statuses[-1].get("peers", []))):
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the agent did not come up: {stderr_path.read_text()[-2000:]}")
            time.sleep(0.02)
        plan = []   # (topic, class) of every bad payload, shuffled, floods as one entry each
        for topic in KEYS:
            classes = fuzzer.classes_for(topic)
            floods = max(1, per_key // (5 * flood_size))         # about a fifth of the payloads come in floods
            singles = per_key - floods * flood_size
            plan += [(topic, classes[i % len(classes)]) for i in range(singles)]
            plan += [(topic, "flood")] * floods
        order = rng.permutation(len(plan))
        ticks = max(50, len(plan) // 60)
        batches = np.array_split(order, ticks)
        k = 0
        for k in range(ticks):
            for topic, body in world.sensors(k).items():
                put(f"usv/{VESSEL}/{topic}", json.dumps(body).encode())
            for j in PEERS:
                put(share_key(j, VESSEL), json.dumps(world.share(j, k)).encode())
            for index in batches[k]:
                topic, cls = plan[index]
                if cls == "flood":
                    for key, payload in fuzzer.flood(topic, k, flood_size):
                        put(key, payload)
                    results.payloads[topic]["flood"] += flood_size
                    continue
                if topic == "sim/clock" and cls == "stamp_poison" and rng.random() < 0.02:
                    # A forged timeline: three clocks that continue each other, far from the genuine one.
                    base = int(rng.integers(20, 10_000)) * SECOND
                    for i in range(3):
                        put("sim/clock", json.dumps(world.clock(k) | {"stamp_ns": base + i * SECOND // 10}).encode())
                    results.payloads[topic]["stamp_poison"] += 3
                    continue
                key, payload = fuzzer.payload(topic, cls, k)
                put(key, payload)
                results.payloads[topic][cls] += 1
            stamp = round(k * DT * SECOND)
            put("sim/clock", json.dumps(world.clock(k)).encode())
            results.genuine_ticks += 1
            _wait(lambda stamp=stamp: stamp in stamps or process.poll() is not None, 0.2)
            if process.poll() is not None:
                break
            if (k + 1) % max(1, ticks // 8) == 0 or k + 1 == ticks:
                results.memory.append(((k + 1) / ticks, _memory_mb(process.pid, "VmRSS")))
            if progress is not None:
                progress(k + 1, ticks)
        phase["storm"] = False
        for tick in range(k + 1, k + 1 + after_storm):
            for topic, body in world.sensors(tick).items():
                put(f"usv/{VESSEL}/{topic}", json.dumps(body).encode())
            for j in PEERS:
                put(share_key(j, VESSEL), json.dumps(world.share(j, tick)).encode())
            stamp = round(tick * DT * SECOND)
            put("sim/clock", json.dumps(world.clock(tick)).encode())
            _wait(lambda stamp=stamp: stamp in stamps or process.poll() is not None, 1.0)
        time.sleep(0.3)
        results.peak_mb = _memory_mb(process.pid, "VmHWM")
        results.alive_at_end = process.poll() is None
        with lock:
            results.health = dict(statuses[-1].get("health", {})) if statuses else {}
        for token in tokens:
            token.undeclare()
    finally:
        session.close()
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        results.exit_code = process.returncode
        results.seconds = time.monotonic() - started
        err = stderr_path.read_text(errors="replace")
        results.stderr_tail = err[-3000:]
        results.error_kinds = sorted({line.split("failed (", 1)[1].split(",", 1)[0]
                                      for line in err.splitlines() if "failed (" in line and "usv-agent" in line})
        if temporary is not None:
            temporary.cleanup()
    return results


def _wait(predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.001)
    return bool(predicate())


# ----- usv-lab fuzz -----
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--per-key", type=arguments.positive_int, default=20000,
                        help="bad payloads per subscribed key (floods included)")
    parser.add_argument("--seed", type=arguments.seed, default=1, help="seed of the payloads' Generator")
    parser.add_argument("--out", type=arguments.folder, default=Path("docs/results"), help="where fuzz.md goes")
    parser.add_argument("--serial-lines", type=arguments.positive_int, default=20000,
                        help="bad lines or frames per parser of the driver bridge (lab/benchmarks/serial_fuzz.py), "
                             "a section of the page")
    parser.add_argument("--mavlink-datagrams", type=arguments.positive_int, default=20000,
                        help="hostile datagrams at the driver's autopilot link (lab/benchmarks/mavlink_fuzz.py), "
                             "a section of the page")


def run(args: argparse.Namespace) -> int:
    print("baseline: the genuine mission alone ...", flush=True)
    baseline = run_campaign(per_key=0, seed=args.seed, after_storm=200)
    print(f"campaign: {args.per_key} payloads per key, seed {args.seed} ...", flush=True)
    last = [0.0]

    def progress(done: int, total: int) -> None:
        if time.monotonic() - last[0] > 10:
            last[0] = time.monotonic()
            print(f"  tick {done}/{total}", flush=True)

    results = run_campaign(per_key=args.per_key, seed=args.seed, progress=progress)
    serial_section, serial_sound = serial_fuzz.page_section(args.serial_lines, args.seed, invocation(args))
    mavlink_section, mavlink_sound = mavlink_fuzz.page_section(args.mavlink_datagrams, args.seed,
                                                               invocation(args))
    print("attacks on the mission keys and liveliness ...", flush=True)
    attacks = run_attacks(progress=lambda name: print(f"  {name}", flush=True))
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "fuzz.md"
    path.write_text(render(invocation(args), results, baseline) + "\n".join(render_attacks(attacks)) + "\n"
                    + serial_section + "\n" + mavlink_section)
    print(f"wrote {path}")
    sound = (results.alive_at_end and results.exit_code == 0 and not results.bad_commands
             and results.after_storm_moving > 0 and serial_sound and mavlink_sound)
    guarded = (attacks.alive_at_end and attacks.exit_code == 0 and not attacks.bad_commands
               and all(a.verdict and a.operator_applied for a in attacks.attacks))
    return 0 if sound and guarded else 1


def render(command: str, results: Results, baseline: Results) -> str:
    per_key = results.per_key()
    rows = [[key if key == "sim/clock" or key.startswith("mission/") else f"usv/{'*' if key == 'share' else VESSEL}/{key}",
             *[results.payloads[key][c] for c in CLASSES], per_key[key]] for key in KEYS]
    payload_table = markdown_table(["key", *CLASSES, "total"], rows)
    refused = sorted(((k[len("rejected_"):], v) for k, v in results.health.items() if k.startswith("rejected_")),
                     key=lambda item: -item[1])
    refusal_table = markdown_table(["reason", "refused"], refused)
    core = {k: v for k, v in results.health.items() if not k.startswith("rejected_")}
    grown = results.peak_mb - baseline.peak_mb
    lines = [
        "# Fuzz campaign: one agent over Zenoh against bad payloads on every key it reads",
        "",
        "Generated by the command below; do not edit by hand. `lab/benchmarks/fuzz.py` describes the campaign and",
        "the payload classes; `tests/test_fuzz.py` runs a smaller one (5,000 payloads per key) in CI.",
        "",
        "```",
        command,
        "```",
        "",
        "## Machine",
        "",
        *(f"- {line}" for line in machine()),
        "",
        "## Verdict",
        "",
        f"- agent alive at the end: **{results.alive_at_end}**; exit code on SIGTERM: {results.exit_code}",
        (f"- commands: {results.commands}, of which {results.moving_commands} not STOP; "
         f"non-finite or beyond the limits: **{len(results.bad_commands)}**"),
        (f"- after the storm, {results.after_storm_commands} commands for the genuine ticks alone, "
         f"{results.after_storm_moving} of them not STOP; {results.after_storm_ticked_statuses} ticked statuses"),
        (f"- failed ticks (caught, STOP that tick): {results.health.get('tick_errors', 0)}"
         + (f", kinds: {', '.join(f'`{k}`' for k in results.error_kinds)}" if results.error_kinds else "")
         + f"; core rebuilt: {results.health.get('core_rebuilds', 0)}; sim restarts followed: "
           f"{results.health.get('sim_restarts', 0)}; shares not sent: {results.health.get('shares_unsent', 0)}"),
        (f"- peak resident memory (VmHWM): {results.peak_mb:.1f} MB, against {baseline.peak_mb:.1f} MB for "
         f"the genuine mission alone ({grown:+.1f} MB)"),
        "- resident memory (VmRSS) through the storm: "
        + ", ".join(f"{mb:.1f} MB at {fraction:.0%}" for fraction, mb in results.memory),
        f"- genuine ticks during the storm: {results.genuine_ticks}; wall time: {results.seconds:.1f} s",
        "",
        "## What the figures mean",
        "",
        "- No payload crashed the agent or failed a tick, and nothing it commanded was non-finite or beyond",
        "  U_v and U_omega_c + omega*. Ranges, positions, angles, covariances and stamps beyond the contract's",
        "  limits are refused at the gate (`malformed`), before the core.",
        "- Memory: what the agent keeps per sender is bounded (MAX_PEERS live senders, 16 held shares each,",
        "  a share cut to its entry for this vessel); the rest of the rise over the genuine mission is the",
        "  allocator's high-water mark after decoding large payloads and Zenoh's buffers after floods, and it",
        "  levels off (the VmRSS line above).",
        "- `sim restarts followed`: sim/clock is trusted as the simulation's time. Three clocks that continue",
        "  each other far from the agent's clock (the campaign forges a few such timelines), or any clock that",
        "  goes back after a second of silence, are a restarted simulation: the agent starts the mission again",
        "  (the core rebuilt from its initial estimates, a new log file up to 20). It then follows the genuine",
        "  clock back the same way. A process that can publish on sim/clock drives the agents' time; on a boat",
        "  there is no sim/clock.",
        "- `implausible_motion`: odometry with valid values but a forged stamp (a nanosecond after the one",
        "  the last tick used, a position a quarter of a metre away) would give the core an own velocity of",
        "  1e8 m/s and send its target estimate to 1e7 m; a tick leaves out odometry older than the last used",
        "  or faster than 1 km/s from it. `shares not sent` counts shares the agent's own contract refused (an",
        "  estimate beyond the physical limits); the command stays within its limits regardless.",
        "",
        "## Payloads per key and class",
        "",
        payload_table,
        "",
        "## Refusals by reason (the agent's last status)",
        "",
        refusal_table,
        "",
        "A payload is counted under the first check that refuses it, not under its class: a flood of sensor",
        "messages is mostly `duplicate_or_reordered` (they share a stamp) and `rate_limited`, a share from a",
        "phantom id `unknown_sender` before anything is decoded.",
        "",
        "## Health counters (the agent's last status: the core's and the shell's)",
        "",
        ", ".join(f"{k} {v}" for k, v in sorted(core.items())) or "none",
        "",
    ]
    return "\n".join(lines)


# ----- attacks on the mission keys and on liveliness -----
# Each case is played against one agent process on sim time, ticked at the pace of real time (usv-op stamps
# with the sim clock and waits for the answers in the statuses); after each, the operator's genuine commands
# (`usv-op hold` and `usv-op resume`, to vessel 1) must be applied.
ATTACKS = ("seq_lockout", "junk_senders_replay", "flood", "spoofed_alive_restart", "takeover_after_kill")
MISSION_ATTACKS, LIVELINESS_ATTACKS = ATTACKS[:3], ATTACKS[3:]
FORGED_TOKENS = 300
JUNK_SENDERS = 300
FLOOD_RATE = 10000       # commands per second from one sender (at most: what one Python session puts)
PROOF_WAIT = 16.0        # s of sim time a returning vessel is given to prove itself (and an impostor watched)
OP_TIMEOUT = 30.0        # s a usv-op command may take (it waits 3 s for its answers)
STATUS_LAG = 2.0         # s the harness's own statuses may trail usv-op's under a flood (20 ticks)


@dataclass
class Attack:
    name: str
    verdict: bool = False      # what the case guards against did not happen
    operator: list = field(default_factory=list)   # (usv-op command, exit code, its output), after the case
    figures: dict = field(default_factory=dict)
    detail: str = ""

    @property
    def operator_applied(self) -> bool:
        return bool(self.operator) and all(code == 0 for _, code, _ in self.operator)


@dataclass
class AttackResults:
    attacks: list[Attack] = field(default_factory=list)
    commands: int = 0
    bad_commands: list = field(default_factory=list)
    alive_at_end: bool = False
    exit_code: int | None = None
    seconds: float = 0.0
    health: dict[str, int] = field(default_factory=dict)
    stderr_tail: str = ""
    op_retries: int = 0

    def by_name(self) -> dict[str, Attack]:
        return {a.name: a for a in self.attacks}


class AttackHarness:
    """One agent process (vessel 1) and the world around it, ticked by a thread at real time: its sensors
    (ranges to 2 and 3 from where their hulls are), the shares of 2 and 3 (or of whoever speaks for them),
    their liveliness tokens and the sim clock."""

    def __init__(self, folder: Path) -> None:
        from sim_bridge.fleet import free_port

        self.world = World()
        self.folder = folder
        self.port = free_port()
        self.stderr_path = folder / "agent.err"
        params = AgentParams()
        control = params.control
        self.limits = (control.max_speed, control.max_correction_yaw_rate + control.yaw_rate)
        self.process = subprocess.Popen([sys.executable, "-m", "agent", "--vessel", VESSEL, "--config",
                                         str(_agent_config(folder, port=self.port, world=self.world))],
                                        stderr=self.stderr_path.open("w"))
        self.lock = threading.Lock()
        self.k = 0
        self.frozen: dict[str, float] = {}            # vessel -> time its hull stopped
        self.speakers: dict[str, Callable | None] = {j: self.world.share for j in PEERS}   # j -> share(j, k)
        self.status: dict = {}
        self.commands = 0
        self.bad_commands: list = []
        self.op_retries = 0
        self.stop = threading.Event()
        self.session = zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{self.port}"])))
        self.session.declare_subscriber(f"usv/{VESSEL}/cmd", self._on_command)
        self.session.declare_subscriber(f"usv/{VESSEL}/status", self._on_status)
        self.tokens = {j: self.session.liveliness().declare_token(f"usv/{j}/alive") for j in PEERS}
        self.publishers: dict[str, object] = {}
        self.others: list = []   # the forger's and the impostor's sessions
        self.held_tokens: list = []   # theirs (a token dropped is undeclared)
        self.ticker = threading.Thread(target=self._tick_on, daemon=True)

    # ----- the world -----
    def now_ns(self) -> int:
        return round(self.k * DT * SECOND)

    def position(self, vessel: str, t: float) -> np.ndarray:
        return self.world.position(vessel, min(t, self.frozen.get(vessel, t)))

    def put(self, key: str, payload: bytes) -> None:
        publisher = self.publishers.get(key)
        if publisher is None:
            publisher = self.publishers[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK)
        publisher.put(payload)

    def _tick_on(self) -> None:
        next_at = time.monotonic()
        while not self.stop.is_set() and self.process.poll() is None:
            with self.lock:
                k = self.k
                t = k * DT
                sensors = self.world.sensors(k)
                me = self.world.position(VESSEL, t)
                sensors["sensor/uwb"]["ranges"] = {j: float(np.linalg.norm(me - self.position(j, t)))
                                                   for j in PEERS}
                speakers = dict(self.speakers)
            for topic, body in sensors.items():
                self.put(f"usv/{VESSEL}/{topic}", json.dumps(body).encode())
            for j, speaker in speakers.items():
                if speaker is not None:
                    self.put(share_key(j, VESSEL), json.dumps(speaker(j, k)).encode())
            self.put("sim/clock", json.dumps(self.world.clock(k)).encode())
            with self.lock:
                self.k += 1
            next_at += DT
            self.stop.wait(max(0.0, next_at - time.monotonic()))

    def _on_command(self, sample) -> None:
        try:
            command = json.loads(sample.payload.to_bytes())
            surge, yaw_rate = float(command["surge"]), float(command["yaw_rate"])
            sound = (math.isfinite(surge) and math.isfinite(yaw_rate) and abs(surge) <= self.limits[0]
                     and abs(yaw_rate) <= self.limits[1] * (1 + 1e-9))
        except (ValueError, KeyError, TypeError) as error:
            command, sound = {"error": str(error)}, False
        with self.lock:
            self.commands += 1
            if not sound:
                self.bad_commands.append(command)

    def _on_status(self, sample) -> None:
        try:
            status = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        if status.get("ticked"):
            with self.lock:
                self.status = status

    def latest(self) -> dict:
        with self.lock:
            return dict(self.status)

    def wait_ticks(self, n: int) -> None:
        target = self.k + n
        _wait(lambda: self.k >= target or self.process.poll() is not None, n * DT * 10 + 5)

    def start(self) -> None:
        self.ticker.start()
        deadline = time.monotonic() + 60
        while not set(PEERS) <= set(self.latest().get("peers", [])):
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the agent did not come up: {self.stderr_path.read_text()[-2000:]}")
            time.sleep(0.05)
        self.wait_ticks(30)   # the pairs localise

    def op(self, *args: str) -> tuple[str, int, str]:
        """The operator's command line, as an operator runs it, to vessel 1. Run again once if it heard no sim
        clock in its half second of listening (a loaded machine) and so stamped with the wall clock: that is
        usv-op's start-up, not the attack (counted in `op_retries`)."""
        for _ in range(2):
            try:
                result = subprocess.run([sys.executable, "-m", "usv_op", "--connect",
                                         f"tcp/127.0.0.1:{self.port}", *args, "--vessel", VESSEL],
                                        capture_output=True, text=True,
                                        timeout=OP_TIMEOUT, check=False)
            except subprocess.TimeoutExpired:
                return " ".join(args), -1, f"usv-op did not finish in {OP_TIMEOUT:g} s"
            said = (result.stdout + result.stderr).strip()[-500:]
            if not re.search(r"refused: future: stamped \d{6,}", said):
                break
            self.op_retries += 1
        return " ".join(args), result.returncode, said

    def mission(self, sender: str, seq: int, command: str, stamp_ns: int | None = None, **values) -> bytes:
        return json.dumps({"stamp_ns": self.now_ns() if stamp_ns is None else stamp_ns, "seq": seq,
                           "sender": sender, "command": command, **values}).encode()

    def close(self) -> AttackResults:
        results = AttackResults()
        self.stop.set()
        self.ticker.join(timeout=10)
        results.alive_at_end = self.process.poll() is None
        results.health = dict(self.latest().get("health", {}))
        for token in self.tokens.values():
            if token is not None:
                token.undeclare()
        for token in self.held_tokens:
            token.undeclare()
        for session in self.others:
            session.close()
        self.session.close()
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        results.exit_code = self.process.returncode
        results.commands, results.bad_commands = self.commands, list(self.bad_commands)
        results.op_retries = self.op_retries
        results.stderr_tail = self.stderr_path.read_text(errors="replace")[-3000:]
        return results

    # ----- the cases -----
    def seq_lockout(self, attack: Attack) -> None:
        """One `resume` from "operator" with seq 2^63 - 1 must not lock the operator out."""
        self.put("mission/all", self.mission("operator", 2**63 - 1, "resume"))
        self.wait_ticks(3)
        attack.verdict = True   # the operator's commands that follow are the verdict

    def junk_senders_replay(self, attack: Attack) -> None:
        """The operator holds and resumes within half a second; JUNK_SENDERS new senders speak; the hold,
        captured, is replayed within the window: it must not be applied again."""
        seq = time.time_ns()
        hold = self.mission("console", seq, "hold")   # an operator's console of its own
        self.put("mission/all", hold)
        self.wait_ticks(2)
        self.put("mission/all", self.mission("console", seq + 1, "resume"))
        self.wait_ticks(2)
        for n in range(JUNK_SENDERS):
            self.put("mission/all", self.mission(f"junk{n}", 1, "set", radius=RADIUS, direction="ccw"))
        self.wait_ticks(1)
        self.put("mission/all", hold)   # stamped 0.5 s ago: within the window
        self.wait_ticks(5)
        status = self.latest()
        attack.figures = {"held_after_replay": bool(status.get("held")),
                          "refused_replayed": status.get("health", {}).get("rejected_mission_replayed", 0)}
        attack.verdict = not status.get("held")

    def flood(self, attack: Attack) -> None:
        """One sender floods FLOOD_RATE commands a second while the operator's `hold` goes out."""
        done = threading.Event()
        sent = [0]

        def flood() -> None:
            started, n = time.monotonic(), 0
            while not done.is_set():
                self.put("mission/all", self.mission("flood", n + 1, "set", radius=RADIUS, direction="ccw"))
                n += 1
                ahead = n / FLOOD_RATE - (time.monotonic() - started)
                if ahead > 0:
                    time.sleep(ahead)
            sent[0] = n

        thread = threading.Thread(target=flood, daemon=True)
        began = time.monotonic()
        thread.start()
        time.sleep(0.5)
        attack.operator.append(self.op("hold"))
        # usv-op's 'applied' is a status it saw; this session's copy of the statuses can trail it under the
        # flood (CI saw the one before the hold): the agent must show itself held, the flood still on.
        held = _wait(lambda: bool(self.latest().get("held")), STATUS_LAG)
        done.set()
        thread.join(timeout=10)
        rate = round(sent[0] / max(1e-9, time.monotonic() - began))
        attack.figures = {"flood_commands": sent[0], "flood_per_s": rate, "held": held,
                          "refused_flood": self.latest().get("health", {}).get("rejected_mission_flood", 0)}
        attack.verdict = attack.operator[-1][1] == 0 and held

    def spoofed_alive_restart(self, attack: Attack) -> None:
        """FORGED_TOKENS forged tokens fill the table; then vessel 2 restarts (its token and shares go away
        for 1.5 s and come back) while 20 more are declared: it must be a neighbour again."""
        forger = zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{self.port}"])))
        self.others.append(forger)
        self.held_tokens += [forger.liveliness().declare_token(f"usv/forged{n}/alive")
                             for n in range(FORGED_TOKENS)]
        self.wait_ticks(10)
        before = self.latest().get("health", {})
        with self.lock:
            self.speakers["2"] = None
        self.tokens["2"].undeclare()
        self.wait_ticks(5)
        # The forger goes on declaring new ids: the place vessel 2 left is taken before it comes back.
        self.held_tokens += [forger.liveliness().declare_token(f"usv/forged{n}/alive")
                             for n in range(FORGED_TOKENS, FORGED_TOKENS + 20)]
        self.wait_ticks(10)
        self.tokens["2"] = self.session.liveliness().declare_token("usv/2/alive")
        with self.lock:
            self.speakers["2"] = self.world.share
        back = self.k
        deadline = back + round(PROOF_WAIT / DT)
        _wait(lambda: self.latest().get("health", {}).get("peers_proven", 0) > before.get("peers_proven", 0)
              or self.k >= deadline or self.process.poll() is not None, PROOF_WAIT * 3)
        status = self.latest()
        health = status.get("health", {})
        attack.figures = {
            "forged_tokens": FORGED_TOKENS, "peers_in_status": len(status.get("peers", [])),
            "vessel_2_live": "2" in status.get("peers", []),
            "proven_after_s": round((self.k - back) * DT, 1) if health.get("peers_proven", 0) else None,
            "shares_refused_unknown_sender": health.get("rejected_unknown_sender", 0)
            - before.get("rejected_unknown_sender", 0),
            "evicted": health.get("peers_evicted", 0)}
        attack.verdict = "2" in status.get("peers", []) and bool(attack.figures["proven_after_s"])

    def takeover_after_kill(self, attack: Attack) -> None:
        """Vessel 3 is killed (its token and shares go; its hull stops where it is); a process declares its
        token and shares odometry that goes on circling: it must not become vessel 3."""
        with self.lock:
            self.speakers["3"] = None
            self.frozen["3"] = self.k * DT
        self.tokens["3"].undeclare()
        self.tokens["3"] = None
        self.wait_ticks(15)
        impostor = zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{self.port}"])))
        self.others.append(impostor)
        self.held_tokens.append(impostor.liveliness().declare_token("usv/3/alive"))
        with self.lock:
            self.speakers["3"] = self.world.share     # the circle it would be on, not where its hull is
        came = self.k
        estimates: list[bool] = []

        def on_share(sample) -> None:
            try:
                estimates.append("3" in json.loads(sample.payload.to_bytes()).get("neighbours", {}))
            except ValueError:
                pass

        watcher = self.session.declare_subscriber(f"{share_key(VESSEL)}/**", on_share)   # either format
        self.wait_ticks(round(PROOF_WAIT / DT))
        watcher.undeclare()
        health = self.latest().get("health", {})
        steered = sum(estimates[-round(PROOF_WAIT / DT / 2):])   # shares of the last half estimating 3
        attack.figures = {"seconds_watched": round((self.k - came) * DT, 1),
                          "shares_with_3_in_last_half": steered, "refuted": health.get("peers_refuted", 0),
                          "withheld": health.get("peers_withheld", 0)}
        attack.verdict = steered == 0


def run_attacks(cases: tuple[str, ...] = ATTACKS, folder: Path | None = None, progress=None) -> AttackResults:
    """Play `cases` (names from ATTACKS, in that order) against one agent process; after each, the operator's
    `hold` and `resume` to vessel 1 through usv-op. The cases draw no random numbers: what varies from run to
    run is the timing of the processes."""
    temporary = tempfile.TemporaryDirectory(prefix="usv-attacks-") if folder is None else None
    folder = Path(temporary.name) if temporary is not None else folder
    folder.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    harness = AttackHarness(folder)
    attacks = []
    try:
        harness.start()
        for name in cases:
            if progress is not None:
                progress(name)
            attack = Attack(name)
            try:
                getattr(harness, name)(attack)
            except Exception as error:  # noqa: BLE001  (a broken case is a failed one, said so)
                attack.detail = f"{type(error).__name__}: {error}"
            attack.operator += [harness.op("hold"), harness.op("resume")]
            attacks.append(attack)
    finally:
        results = harness.close()
        results.attacks = attacks
        results.seconds = time.monotonic() - started
        if temporary is not None:
            temporary.cleanup()
    return results


def render_attacks(results: AttackResults) -> list[str]:
    """The attacks' section of the fuzz page."""
    rows = [[a.name, "yes" if a.verdict else "**no**", "yes" if a.operator_applied else "**no**",
             ", ".join(f"{k} {v}" for k, v in a.figures.items()) + (f" ({a.detail})" if a.detail else "")]
            for a in results.attacks]
    return [
        "## Attacks on the mission keys and on liveliness",
        "",
        "One agent process on sim time at the pace of real time, its world played by a Zenoh session",
        "(vessels 2 and 3 share and are ranged); each case in turn, then `usv-op hold` and `usv-op resume`",
        "to vessel 1 as an operator runs them (`lab/benchmarks/fuzz.py` AttackHarness):",
        "- seq_lockout: one `resume` with seq 2^63 - 1 as \"operator\";",
        f"- junk_senders_replay: a console holds and resumes within 0.2 s, {JUNK_SENDERS} new senders",
        "  speak, and the captured hold is replayed 0.5 s after it was stamped;",
        f"- flood: up to {FLOOD_RATE} commands/s from one sender while usv-op holds;",
        f"- spoofed_alive_restart: {FORGED_TOKENS} forged tokens, then vessel 2 restarts (1.5 s away) while",
        "  20 more are declared;",
        "- takeover_after_kill: vessel 3 is killed (its hull stops where it is) and a process declares its",
        "  token and shares the slot on the circle it would be on.",
        "",
        markdown_table(["case", "guarded", "operator's hold and resume applied", "figures"], rows),
        "",
        (f"Commands: {results.commands}, non-finite or beyond the limits: **{len(results.bad_commands)}**; "
         f"agent alive at the end: **{results.alive_at_end}**, exit code {results.exit_code}; "
         f"{results.seconds:.0f} s; usv-op run again for want of a sim clock heard: {results.op_retries}."),
        "",
    ]
