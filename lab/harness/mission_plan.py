"""The operator's mission commands in an in-process run: `usv-op set` at given times, judged and applied by
each vessel as its agent does (agent/shell/mission.py's MissionOrders), for lab/harness/runner.py's `retune`.

Each command is sent on `mission/all` at its time; a vessel takes it at its first tick at or after that
time, with the number of vessels alive at that tick as the fleet it knows. Only `set` is simulated (a hold
is the agent process's STOP, outside the core)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence

from agent.core.params import AgentParams
from agent.shell.mission import MissionOrders

OPERATOR = "operator"


class MissionPlan:
    """`set` commands as (time (s), fields of the set: radius, yaw_rate, direction), in time order. Called as
    the runner's `retune`; `refusals` collects what each vessel refused: (time, vessel, reason)."""

    def __init__(self, sets: Sequence[tuple[float, dict]]) -> None:
        self._orders = [(time, json.dumps({"stamp_ns": round(time * 1e9), "seq": seq, "sender": OPERATOR,
                                           "command": "set", **fields}).encode())
                        for seq, (time, fields) in enumerate(sorted(sets, key=lambda s: s[0]), start=1)]
        self._missions: dict[str, MissionOrders] = {}
        self._next: dict[str, int] = {}
        self.refusals: list[tuple[float, str, str]] = []

    def __call__(self, vessel: str, now: float, alive: int, params: AgentParams) -> AgentParams:
        mission = self._missions.get(vessel)
        if mission is None:
            mission = MissionOrders(vessel, math.inf, math.inf, lambda kind, why: None)
            self._missions[vessel] = mission
            self._next[vessel] = 0
        k = self._next[vessel]
        while k < len(self._orders) and self._orders[k][0] <= now + 1e-9:
            mission.offer("mission/all", self._orders[k][1], None, round(now * 1e9), frozenset)
            k += 1
        self._next[vessel] = k
        params = mission.apply(params, round(now * 1e9), vessels=alive)
        for _, ack, _ in mission.judged():
            if not ack.applied:
                self.refusals.append((now, vessel, ack.reason))
        return params
