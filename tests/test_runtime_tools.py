"""The runtime benchmark's tools: the transport floor over real processes, and the before/after page."""

from __future__ import annotations

import pytest

from lab.runtime_ab import FIGURES, page
from lab.transport_floor import transport_floor


@pytest.mark.slow   # five processes over Zenoh
def test_the_transport_floor_carries_the_lockstep_pattern_and_measures_every_process():
    ticks = 100
    floor = transport_floor(vessels=3, ticks=ticks)
    assert floor["missed"] == 0
    assert floor["shares_per_tick"] == 2.0   # each agent hears the other two on every measured tick
    assert 0.0 < floor["agent_cpu_ms"] < 100.0 and 0.0 < floor["bridge_cpu_ms"] < 100.0 and floor["loop_ms"] > 0.0


def test_the_changes_page_gives_each_figure_before_after_and_their_ratio():
    before = {name: 2.0 for name in FIGURES}
    after = {name: 1.5 for name in FIGURES}
    entry = {"label": "a change", "before": "abc1234", "after": "def5678", "pairs": 3,
             "medians": {"before": before, "after": after},
             "spread": {"before": {n: [1.9, 2.2] for n in FIGURES}, "after": {n: [1.4, 1.6] for n in FIGURES}}}
    old = {"label": "recorded before the spread", "before": "1", "after": "2", "pairs": 4,
           "medians": {"before": {"shell_ratio": 2.12}, "after": {"shell_ratio": 1.85}}}
    text = page([entry, old])
    row = next(line for line in text.splitlines() if line.startswith("| a change"))
    assert row.count("(0.75)") == len(FIGURES) and "[1.90-2.20] [1.40-1.60]" in row
    assert "`abc1234` → `def5678`" in row
    older = next(line for line in text.splitlines() if line.startswith("| recorded before"))
    assert "2.12 → 1.85 (0.87)" in older and older.count("| - ") == len(FIGURES) - 1
