"""agent/core/median.py: numpy.median's value without numpy.median (its first call imports numpy.ma, 38 ms)."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from agent.core.median import median


@pytest.mark.parametrize("seed", [0, 1])
def test_the_median_is_numpys_bit_for_bit_odd_or_even(seed):
    rng = np.random.default_rng(seed)
    for n in range(1, 41):
        values = rng.normal(0.0, rng.uniform(1e-3, 1e3), size=n)
        assert median(values) == float(np.median(values))
        assert median(values.tolist()) == float(np.median(values))
    assert median([3, 1, 2]) == 2.0 and median((4, 1, 2, 3)) == 2.5


def test_a_nan_or_nothing_gives_nan_as_numpy_does():
    with np.errstate(invalid="ignore"), pytest.warns(RuntimeWarning):
        assert math.isnan(np.median(np.array([])))
    assert math.isnan(median([])) and math.isnan(median(np.array([])))
    for values in ([1.0, math.nan, 2.0], [math.nan], np.array([0.5, 0.2, np.nan, 0.1])):
        assert math.isnan(np.median(values)) and math.isnan(median(values))


def test_vetting_a_returning_vessel_does_not_import_numpy_ma():
    """The medians of the vetting (a returning vessel's claims, a pair started from the ranges) and of the
    restarted target filter's range fit run at a tick: in a fresh process they leave numpy.ma unimported."""
    code = """
import sys
import numpy as np
from agent.core.vetting import range_misfit, residual_trend
from agent.core.target_range import RangeWitness
import agent.shell.node
rng = np.random.default_rng(0)
own, claimed = rng.normal(size=(12, 2)), rng.normal(size=(12, 2)) + 5.0
ranges = np.hypot(*(claimed - own).T)
assert range_misfit(own, claimed, ranges) < 1e-6
assert abs(residual_trend(rng.normal(size=12))) < 10.0
w = RangeWitness(target=np.array([5.0, 0.0]), target_covariance=np.eye(2), distances=np.full(5, 5.0),
            moves=np.zeros((5, 2)), range_variance=0.1)
w.miss(np.array([1.0, 0.0]), 10.0)
print('numpy.ma' in sys.modules)
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "False"
