"""`usv-fleet run --vehicle mavlink`: each vessel driven through MAVLink, and the figures of that path.

Per vessel, beside its agent: `usv-ardupilot-standin --sim` (real MAVLink on a UDP port of the loopback; its
hull is the sim bridge's vessel, sim_bridge/standin_relay.py) and `usv-driver` in MAVLink mode on the sim
clock. The agent is the same program with the same settings: its odometry comes from the driver instead of
the sim bridge, which still gives the UWB ranges, the bearing, the sonar and the truth, and steps its world
on what each stand-in drives (sim_bridge/autopilot_relay.py).

`figures(folder, kills)` reads the stand-ins' records (`standin-<id>.jsonl`): the set points taken that carried
a fresh command of the agent, a second, and their added latency (from the command reaching the stand-in's
process over Zenoh, as it reaches the sim bridge without MAVLink, to the set point taken; < 0 when the set
point came first), the new set points matched to no command (`new_unmatched`), and for
each vessel whose agent was killed (`kills`: vessel -> monotonic s) how long until the stand-in was in HOLD.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

LINK_UP = "autopilot link up"   # the driver's line once the stand-in's heartbeat came (mavlink_vehicle.py)


def driver_settings(bridge_port: int, udp_port: int, listen: str) -> dict:
    """A vessel's usv-driver settings: the sim clock, loopback Zenoh, the stand-in's UDP port, arming."""
    return {"clock": "sim", "zenoh": {"listen": [listen], "connect": [f"tcp/127.0.0.1:{bridge_port}"]},
            "mavlink": {"url": f"udpout:127.0.0.1:{udp_port}", "arm": True}}


def standin_command(bridge_port: int, udp_port: int, vessel: str, record: Path) -> list[str]:
    return [sys.executable, "-m", "sim_bridge.ardupilot_standin", "--listen", f"udpin:127.0.0.1:{udp_port}",
            "--sim", f"tcp/127.0.0.1:{bridge_port}", "--vessel", vessel, "--record", str(record)]


def driver_command(vessel: str, config: Path) -> list[str]:
    return [sys.executable, "-m", "driver_bridge", "--vessel", vessel, "--config", str(config)]


def records(path: Path) -> list[dict]:
    """A stand-in's JSON lines (a last line cut by a kill left out)."""
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        return []
    out = []
    for line in lines:
        try:
            out.append(json.loads(line))
        except ValueError:
            continue
    return out


def figures(folder: Path, kills: dict[str, float] | None = None) -> dict:
    """The MAVLink path's figures of a run folder (module docstring); also written to `mavlink.json`."""
    kills = kills or {}
    vessels, added = {}, []
    for path in sorted(folder.glob("standin-*.jsonl")):
        vessel = path.stem.removeprefix("standin-")
        log = records(path)
        taken = [r for r in log if r["kind"] == "setpoint"]
        fresh = [r for r in log if "added_ms" in r]   # a set point's, or one's that came before its command
        new = sum(i == 0 or (a["u"], a["r"]) != (b["u"], b["r"]) for i, (b, a) in enumerate(zip([{}] + taken, taken)))
        span = taken[-1]["t"] - taken[0]["t"] if len(taken) > 1 else 0.0
        row = {"setpoints": len(taken), "fresh": len(fresh), "new_unmatched": new - len(fresh),
               "fresh_per_s": (len(fresh) - 1) / span if span > 0 else None,
               "modes": [r["mode"] for r in log if r["kind"] == "mode"]}
        added += [r["added_ms"] for r in fresh]
        if vessel in kills:
            holds = [r["t"] for r in log if r["kind"] == "mode" and r["mode"] == "HOLD" and r["t"] > kills[vessel]]
            row["hold_after_kill_s"] = holds[0] - kills[vessel] if holds else None
        vessels[vessel] = row
    result = {"vessels": vessels, "fresh_setpoints": len(added),
              "new_unmatched": sum(row["new_unmatched"] for row in vessels.values())}
    if added:
        p50, p99, top = np.percentile(added, [50, 99, 100])
        result.update(added_ms_p50=float(p50), added_ms_p99=float(p99), added_ms_max=float(top))
    (folder / "mavlink.json").write_text(json.dumps(result, indent=2))
    return result


def say(result: dict) -> str:
    """One line of `figures`."""
    rates = [row["fresh_per_s"] for row in result["vessels"].values() if row["fresh_per_s"] is not None]
    holds = {v: row["hold_after_kill_s"] for v, row in result["vessels"].items() if "hold_after_kill_s" in row}
    line = (f"{result['fresh_setpoints']} fresh set points ({result['new_unmatched']} new ones not matched to an "
            "agent command)")
    if rates:
        line += f", {min(rates):.2f} to {max(rates):.2f} a second per vessel"
    if "added_ms_p99" in result:
        line += f"; added latency p50 {result['added_ms_p50']:.2f} ms, p99 {result['added_ms_p99']:.2f} ms"
    for vessel, hold in holds.items():
        line += f"; vessel {vessel} in HOLD {'never' if hold is None else f'{hold:.3f} s'} after its agent was killed"
    return line
