"""`usv-lab bench`: it runs and reports every row, and its filterpy comparison is like for like.

No timing is asserted here: the benchmark reports times; the tests check only that it measures the right
thing.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("filterpy")

from agent.core.params import ESTIMATOR_NAMES
from lab import bench
from lab.cli import main


def _table_rows(document: str) -> dict[str, list[str]]:
    """First cell -> other cells of every markdown table row (header and separator rows included)."""
    rows = {}
    for line in document.splitlines():
        if line.startswith("|") and not line.startswith("|---"):
            cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
            rows[cells[0]] = cells[1:]
    return rows


def test_bench_writes_every_row_with_finite_positive_numbers(tmp_path, capsys):
    assert main(["bench", "--updates", "200", "--repeats", "1", "--out", str(tmp_path)]) == 0
    document = (tmp_path / "benchmark.md").read_text(encoding="utf-8")
    rows = _table_rows(document)
    expected = [*ESTIMATOR_NAMES, bench.FILTERPY, bench.PLKF_LABEL,
                f"bank: {bench.BANK_SIZE} x mckf", f"bank: {bench.BANK_SIZE} x {bench.FILTERPY}"]
    for label in expected:
        assert label in rows, f"no row for {label!r} in benchmark.md"
        numbers = [float(cell) for cell in rows[label] if cell != "-"]
        assert len(numbers) >= 3, (label, rows[label])
        assert all(math.isfinite(x) and x > 0 for x in numbers), (label, rows[label])
    # MCKF iterates at least once per update and at most L_max times.
    assert 1.0 <= float(rows["mckf"][-1]) <= 10.0
    assert f"usv-lab bench --updates 200 --repeats 1 --out {tmp_path}" in document
    assert "os.cpu_count()" in document and "numpy" in document
    assert "| mckf |" in capsys.readouterr().out


def test_filterpy_kf_and_our_kf_agree_on_the_bench_data():
    params = bench.bench_params()
    pair, bank, _ = bench.make_data(seed=7, updates=300, params=params)
    for data in (pair, *bank):
        ours = bench.run_ours("kf", data, params)
        theirs = bench.run_filterpy(data, params)
        assert np.all(np.isfinite(ours))
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9)
        # and the updates did something: the estimate is not the dead-reckoned initial guess
        dead_reckoned = data.initial + np.cumsum(data.displacements, axis=0)
        assert np.max(np.linalg.norm(ours - dead_reckoned, axis=1)) > 0.1


def test_bench_data_is_reproducible_from_the_seed():
    params = bench.bench_params()
    first, _, target_a = bench.make_data(seed=3, updates=50, params=params)
    second, _, target_b = bench.make_data(seed=3, updates=50, params=params)
    assert first.range_pairs == second.range_pairs
    np.testing.assert_array_equal(first.initial, second.initial)
    np.testing.assert_array_equal(np.array(target_a.bearings), np.array(target_b.bearings))
    other, _, _ = bench.make_data(seed=4, updates=50, params=params)
    assert other.range_pairs != first.range_pairs
