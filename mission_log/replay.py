"""`usv-log replay`: a vessel's recorded inputs through the agent core again, with the same or other settings.

The agent's log holds its node settings (metadata) and every tick's complete inputs, so the core can be
rebuilt as it started and fed the same ticks. With the settings unchanged the outputs are bit for bit the
recorded ones (the core has no clock, thread or randomness of its own). With changes (another estimator,
another kernel bandwidth, ...) the new MCAP shows what those settings would have done on the same data; it
has the same topics as an agent's log, so `usv-log summary|metrics|plot` read it too.

What cannot change on replay: the inputs themselves. A vessel's neighbours' shares are what they sent at the
time, computed with their settings, so a replay answers "what would this vessel have estimated and
commanded", not "what would the fleet have done".
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from agent.config import ConfigError, deep_merge, parse_mapping, parse_yaml
from agent.contract import Cmd
from agent.core.build import initial_state
from agent.core.records import inputs_from_json
from agent.core.snapshot import state_from_json
from agent.core.step import step
from agent.runtime.mcap_log import McapLog
from agent.shell.settings import NodeSettings
from agent.shell.tick_log import TickLogger, estimates_to_json
from mission_log.reader import LogError, VesselLog, read_log


@dataclass
class ReplayResult:
    vessel: str
    ticks: int
    changed: dict
    commands_compared: int
    commands_identical: int
    max_surge_difference: float
    max_yaw_rate_difference: float
    estimates_identical: int
    out: Path
    resumed_at: float | None = None   # s after the first tick: the saved state replay started from


def parse_assignments(assignments: list[str]) -> dict:
    """`relative.estimator=mckf` style settings of the agent's parameters as a nested mapping; values are
    read as YAML (so 0.8 is a number, [1, 2] a list)."""
    changes: dict = {}
    for item in assignments:
        path, sep, text = item.partition("=")
        if not sep or not path.strip():
            raise ConfigError(f"--set {item!r}: expected key.path=value, e.g. relative.estimator=mckf")
        node = changes
        keys = path.strip().split(".")
        for name in keys[:-1]:
            node = node.setdefault(name, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r}: {name} is set twice")
        node[keys[-1]] = parse_yaml(text, f"--set {item!r}")
    return changes


# The per-estimator blocks of `relative` in logs recorded before the estimator's own parameters moved under
# `relative.estimator` (a tagged union): every block was recorded, the named estimator used only its own.
OLD_ESTIMATOR_BLOCKS = ("mckf", "akf", "rls", "huber_rls", "raw_range")


def recorded_agent(agent: dict) -> dict:
    """A log's recorded agent settings in today's shape: an older log's `relative.estimator` name and its
    block become `relative.estimator: {name: ..., its block}` (Huber-RLS took RLS's forgetting factor)."""
    relative = agent.get("relative")
    if not isinstance(relative, dict) or not isinstance(relative.get("estimator"), str):
        return agent
    blocks = {key: relative[key] for key in OLD_ESTIMATOR_BLOCKS if isinstance(relative.get(key), dict)}
    if not blocks:
        return agent
    name = relative["estimator"]
    own = dict(blocks.get(name, {}))
    if name == "huber_rls" and "forgetting_factor" in blocks.get("rls", {}):
        own["forgetting_factor"] = blocks["rls"]["forgetting_factor"]
    rest = {key: value for key, value in relative.items() if key not in blocks}
    return {**agent, "relative": {**rest, "estimator": {"name": name, **own}}}


def replay(path: Path, out: Path, changes: dict | None = None, start: float | None = None) -> ReplayResult:
    """Replay the agent log at `path` into `out` with the agent parameters changed by `changes` (a nested
    mapping merged into the recorded `agent` settings). With `start` (seconds after the log's first tick),
    the core starts from the last state the agent saved before that time (`/<id>/state`, every
    `snapshot_every` ticks), or from the beginning if none was saved before it."""
    log = read_log(path)
    if not isinstance(log, VesselLog):
        raise LogError(f"{path}: not an agent's log (no vessel in its metadata)")
    if log.settings is None:
        raise LogError(f"{path}: the log has no settings recorded, so the core cannot be rebuilt")
    inputs = log.topic("inputs")
    if not inputs:
        raise LogError(f"{path}: no /{log.vessel}/inputs messages to replay")
    changes = changes or {}
    recorded = {**log.settings, "agent": recorded_agent(log.settings["agent"])}
    settings = parse_mapping(NodeSettings, {**recorded, "agent": deep_merge(recorded["agent"], changes)},
                             f"{path} settings with the changes")
    params = settings.agent
    state = initial_state(log.vessel, params, settings.initial)
    resumed_at = None
    if start is not None:
        target_ns = inputs[0][0] + round(start * 1e9)
        saved = [(stamp, data) for stamp, data in log.topic("state") if stamp < target_ns]
        if saved:
            resumed_at, data = saved[-1]
            try:
                state = state_from_json(data, params)
            except (KeyError, TypeError, ValueError) as error:
                raise LogError(f"{path}: the state saved at {resumed_at} ns cannot be read: {error}") from None
            inputs = [(stamp, tick) for stamp, tick in inputs if stamp > resumed_at]
    commands = dict(log.topic("cmd"))
    estimates = dict(log.topic("estimates"))
    result = ReplayResult(log.vessel, 0, changes, 0, 0, 0.0, 0.0, 0, Path(out),
                          None if resumed_at is None else (resumed_at - log.topic("inputs")[0][0]) * 1e-9)
    with McapLog(out, metadata={"vessel": log.vessel, "clock": recorded.get("clock", "sim"),
                                "settings": settings.model_dump_json(), "replay_of": str(path),
                                "changes": json.dumps(changes),
                                "resumed_at_ns": "" if resumed_at is None else str(resumed_at)}) as new_log:
        writer = TickLogger(new_log, log.vessel, params.control.radius)
        for seq, (stamp, data) in enumerate(inputs):
            tick_inputs = inputs_from_json(data)
            state, output = step(params, state, tick_inputs)
            command = Cmd(stamp_ns=stamp, seq=seq, sender=log.vessel, surge=output.command.surge,
                          yaw_rate=output.command.yaw_rate)
            writer.tick(stamp, tick_inputs, output, command)
            result.ticks += 1
            before = commands.get(stamp)
            if before is not None:
                result.commands_compared += 1
                surge, yaw_rate = abs(before["surge"] - command.surge), abs(before["yaw_rate"] - command.yaw_rate)
                result.commands_identical += surge == 0.0 and yaw_rate == 0.0
                result.max_surge_difference = max(result.max_surge_difference, surge)
                result.max_yaw_rate_difference = max(result.max_yaw_rate_difference, yaw_rate)
            if output.record is not None and stamp in estimates:
                # Compared through JSON, as logged: the recorded estimates went through the same encoding.
                again = json.loads(json.dumps(estimates_to_json(output.record)))
                result.estimates_identical += again == estimates[stamp]
    return result
