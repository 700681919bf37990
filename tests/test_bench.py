"""`usv-lab bench`: it runs and reports every row, and its filterpy comparison is like for like.

No timing is asserted here: the benchmark reports times; the tests check only that it measures the right
thing.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("filterpy")

from agent.core.estimators import estimator_names
from lab.benchmarks import estimators as bench
from lab.cli import main


def _table_rows(document: str) -> dict[str, list[str]]:
    """First cell -> other cells of every markdown table row (header and separator rows included)."""
    rows = {}
    for line in document.splitlines():
        if line.startswith("|") and not line.startswith("|---"):
            cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
            rows[cells[0]] = cells[1:]
    return rows


@pytest.mark.slow
def test_bench_writes_every_row_with_finite_positive_numbers(tmp_path, capsys):
    assert main(["bench", "--updates", "200", "--repeats", "1", "--out", str(tmp_path)]) == 0
    document = (tmp_path / "benchmark.md").read_text(encoding="utf-8")
    rows = _table_rows(document)
    cold = bench.Setup(bench.DEFAULT, cold=True).label
    phased = [bench.DEFAULT, cold, bench.bank_label(bench.DEFAULT), bench.bank_label(cold)]
    expected = [*estimator_names(), cold, bench.FILTERPY, bench.PLKF_LABEL,
                *(bench.bank_label(name) for name in (bench.PAPER, bench.DEFAULT, cold, bench.FILTERPY)),
                *(f"{label}: {phase}" for label in phased for phase in ("fix phase", "tracking")),
                f"one {bench.DEFAULT}", f"bank of {bench.BANK_SIZE} {bench.DEFAULT}"]
    for label in expected:
        assert label in rows, f"no row for {label!r} in benchmark.md"
        numbers = [float(cell) for cell in rows[label] if cell != "-"]
        assert len(numbers) >= 2, (label, rows[label])
        # A phase the data never reached has 0 steps and no figures ("-").
        assert all(math.isfinite(x) and x >= 0 for x in numbers), (label, rows[label])
        assert label.endswith(": tracking") or all(x > 0 for x in numbers), (label, rows[label])
    # MCKF iterates at least once per update and at most L_max times; raw_range reports no iterations.
    assert 1.0 <= float(rows["mckf"][-1]) <= 10.0
    assert 1.0 <= float(rows[bench.bank_label("mckf")][-1]) <= 10.0
    assert rows[bench.DEFAULT][-1] == "-"
    # raw_range starts in its fix phase, and the two phases split every step of a repeat between them.
    for label in phased:
        fix, tracking = (int(rows[f"{label}: {phase}"][0]) for phase in ("fix phase", "tracking"))
        assert fix > 0 and fix + tracking == 200, label
    # The summary states the verdict on the budget and the fix phase's cost.
    assert "Budget of the issue" in document and ("within" in document or "over" in document)
    assert "Fix phase of the bank" in document and "worst tick" in document
    assert f"usv-lab bench --updates 200 --repeats 1 --out {tmp_path}" in document
    assert "os.cpu_count()" in document and "numpy" in document
    assert "| mckf |" in capsys.readouterr().out


def test_filterpy_kf_and_our_kf_agree_on_the_bench_data():
    params = bench.bench_params()
    pair, bank, _ = bench.make_data(seed=7, updates=300, params=params)
    for data in (pair, *bank):
        ours = bench.run_ours(bench.Setup("kf"), data, params).positions
        theirs = bench.run_filterpy(data, params)
        assert np.all(np.isfinite(ours))
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9)
        # and the updates did something: the estimate is not the dead-reckoned initial guess
        dead_reckoned = data.initial + np.cumsum(data.displacements, axis=0)
        assert np.max(np.linalg.norm(ours - dead_reckoned, axis=1)) > 0.1


@pytest.mark.slow
@pytest.mark.parametrize("setup", bench.BANK_SETUPS, ids=lambda setup: setup.label)
def test_the_timed_bank_feeds_each_estimator_its_own_pair(setup):
    """The bank loop, its pairs interleaved tick by tick, ends where each pair run alone does: every
    estimator got its own data in order (and a cold start is a start from no prior)."""
    params = bench.bench_params()
    _, bank, _ = bench.make_data(seed=7, updates=300, params=params)
    estimators = [bench.new_ours(setup, data, params) for data in bank]
    assert len(bench._time_bank(estimators, bank, ours=True)) == 300
    for estimator, data in zip(estimators, bank):
        trace = bench.run_ours(setup, data, params)
        np.testing.assert_array_equal(estimator.position, trace.positions[-1])
        if setup.name == bench.DEFAULT:
            # the fix phase starts the data and ends within it
            assert trace.fixing[0] and not trace.fixing[-1]
        else:
            assert not any(trace.fixing)
    if setup.cold:
        assert bench.new_ours(setup, bank[0], params).covariance[0, 0] >= 1e12


@pytest.mark.slow
def test_phases_split_every_sample_and_a_tick_fixes_while_any_pair_does():
    params = bench.bench_params()
    _, bank, _ = bench.make_data(seed=7, updates=300, params=params)
    traces = [bench.run_ours(bench.Setup(bench.DEFAULT, cold=True), data, params) for data in bank]
    timing = bench.Timing()
    repeats = 2
    for repeat in range(repeats):
        timing.add((list(range(repeat, repeat + 300)), []))
    timing.set_phases(traces)
    assert timing.fixing == [any(trace.fixing[k] for trace in traces) for k in range(300)]
    assert timing.fix_updates == [sum(trace.fixing) for trace in traces]
    fix, tracking = timing.phase_ns(True), timing.phase_ns(False)
    assert len(fix) + len(tracking) == repeats * 300
    assert sorted(fix + tracking) == sorted(timing.full_ns)
    assert len(fix) == repeats * sum(timing.fixing)
    assert timing.worst_step == 299


def test_bench_data_is_reproducible_from_the_seed():
    params = bench.bench_params()
    first, _, target_a = bench.make_data(seed=3, updates=50, params=params)
    second, _, target_b = bench.make_data(seed=3, updates=50, params=params)
    assert first.range_pairs == second.range_pairs
    np.testing.assert_array_equal(first.initial, second.initial)
    np.testing.assert_array_equal(np.array(target_a.bearings), np.array(target_b.bearings))
    other, _, _ = bench.make_data(seed=4, updates=50, params=params)
    assert other.range_pairs != first.range_pairs
