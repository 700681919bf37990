"""How long the agent takes to answer a tick: from the tick's trigger (the sim clock's arrival, in real time its
own sensors' when they come after it, or the wall-clock timer's) to its command's put. Kept as a histogram, so
that a mission of any length costs the same memory; its quantiles are read to the bin's width. The agent logs
them in its summary (`AgentSummary.reaction_ms`).

It is wall time. On sim time in lockstep it includes the wait for the neighbours' shares of the tick before;
in real time and at sea it is the agent's work between its inputs and its command (decoding what came with the
trigger, the core's step, the command's encoding) and whatever waits for a core that work had: none to speak of
on a vessel's own computer, most of it in a fleet of processes sharing a laptop's cores. `usv-lab
runtime-bench` sets it beside the sensor-to-command latency the sim bridge measures, with the tick thread's CPU
time over the same stretch (`AgentSummary.reaction_cpu_ms`, the same histogram): the reaction without the
waits."""

from __future__ import annotations

import math

BIN_MS = 0.05     # width of a bin: the quantiles' resolution
BINS = 2000       # 0 to 100 ms; a longer time counts in the overflow, and `longest` keeps the longest


class ReactionTimes:
    """A histogram of reaction times, in milliseconds."""

    def __init__(self) -> None:
        self.counts = [0] * (BINS + 1)      # the last one: BINS * BIN_MS ms and over
        self.count = 0
        self.longest = 0.0

    def add(self, seconds: float) -> None:
        milliseconds = 1e3 * seconds
        if not math.isfinite(milliseconds) or milliseconds < 0.0:
            return    # a clock that went backwards between two readings: no time to count
        self.counts[min(int(milliseconds / BIN_MS), BINS)] += 1
        self.count += 1
        self.longest = max(self.longest, milliseconds)

    def quantile(self, q: float) -> float | None:
        """The upper edge of the bin holding the ceil(q * count)-th shortest time (ms), so never below the true
        quantile and at most BIN_MS above it; the longest time itself if that one is in the overflow. None
        before any time is counted."""
        if self.count == 0:
            return None
        rank = max(1, math.ceil(q * self.count))
        seen = 0
        for index, count in enumerate(self.counts):
            seen += count
            if seen >= rank:
                return self.longest if index == BINS else min((index + 1) * BIN_MS, self.longest)
        return self.longest   # pragma: no cover  (the counts sum to `count`)

    def summary(self) -> dict[str, float] | None:
        """{"p50", "p99", "max"} in milliseconds and "ticks" counted; None before any."""
        if self.count == 0:
            return None
        return {"p50": self.quantile(0.5), "p99": self.quantile(0.99), "max": self.longest, "ticks": self.count}
