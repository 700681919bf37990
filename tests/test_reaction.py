"""The agent's reaction-time histogram (agent/shell/reaction.py) against exact quantiles of the same times."""

from __future__ import annotations

import numpy as np
import pytest

from agent.shell.reaction import BIN_MS, BINS, ReactionTimes


def filled(seconds) -> ReactionTimes:
    times = ReactionTimes()
    for value in seconds:
        times.add(float(value))
    return times


@pytest.mark.parametrize("seed", [0, 1])
def test_quantiles_are_the_exact_ones_read_to_a_bins_width(seed):
    rng = np.random.default_rng(seed)
    seconds = rng.lognormal(np.log(2e-3), 0.6, size=5000)     # about 2 ms, a long right tail
    times = filled(seconds)
    for q in (0.01, 0.5, 0.9, 0.99):
        # The ceil(q n)-th shortest time: numpy's inverted-CDF quantile.
        exact = 1e3 * np.quantile(seconds, q, method="inverted_cdf")
        read = times.quantile(q)
        assert exact <= read <= exact + BIN_MS + 1e-12, (q, exact, read)
    summary = times.summary()
    assert summary["ticks"] == 5000
    assert summary["max"] == pytest.approx(1e3 * seconds.max(), rel=1e-12)


def test_times_beyond_the_last_bin_are_read_as_the_longest():
    limit = BINS * BIN_MS / 1e3          # seconds
    times = filled([1e-3] * 97 + [2 * limit, 3 * limit, 5 * limit])
    assert times.quantile(0.5) == pytest.approx(1.05)
    assert times.quantile(0.99) == pytest.approx(5e3 * limit)   # in the overflow: the longest itself
    assert times.summary()["p99"] == times.summary()["max"]


def test_a_quantile_is_never_above_the_longest_time():
    times = filled([1.0e-3, 1.01e-3])
    assert times.quantile(0.99) == pytest.approx(1.01)   # not the bin's upper edge, 1.05


def test_nothing_counted_reads_none_and_a_negative_or_non_finite_time_is_not_counted():
    times = filled([-1e-3, float("nan"), float("inf")])
    assert times.count == 0 and times.quantile(0.5) is None and times.summary() is None
