"""The runtime benchmark's tools: the transport floor over real processes, and the before/after page."""

from __future__ import annotations

import pytest

from lab.benchmarks.runtime_ab import FIGURES, page
from lab.benchmarks.transport_floor import transport_floor


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


def test_the_share_decoding_rows_time_what_the_gate_keeps():
    """The benchmark's share decodes both ways to the same estimate of the receiver's pair, and its rows say
    how many vessels, bytes and microseconds, with the ratio and a tick's n - 1 shares worked out from them."""
    from agent.contract import ShareMessage, decode
    from lab.benchmarks.runtime import receive_share, share_decode_rows, share_payload

    payload = share_payload(5)
    whole, _ = decode(ShareMessage, payload)
    assert sorted(whole.neighbours) == ["2", "3", "4", "5"]
    assert receive_share(payload, "3") == whole.neighbours["3"]
    (n, size, mine, every, ratio, per_tick), = share_decode_rows(sizes=(5,), repeats=20)
    assert (n, size) == (5, len(payload))
    assert float(ratio) == pytest.approx(float(mine) / float(every), abs=0.01)
    assert float(per_tick) == pytest.approx(4 * float(mine) / 1e3, abs=1e-3)
