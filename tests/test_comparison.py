"""Experiment 1's feeding of an estimator (lab/experiments/comparison.py `run_estimator`) against the agent's rules."""

from __future__ import annotations

import numpy as np
import pytest

from agent.core.estimators import make_relative_estimator
from agent.core.params import RelativeEstimationParams
from lab.experiments.comparison import run_estimator


def pair_data(steps: int = 60):
    """Exact ranges along a relative path that turns, and its displacements."""
    t = np.arange(steps + 1) * 0.1
    truth = np.stack([6.0 * np.cos(0.3 * t) + 0.5 * t, 6.0 * np.sin(0.3 * t)], axis=1)
    return np.diff(truth, axis=0), np.linalg.norm(truth, axis=1), truth


@pytest.mark.parametrize("name", ["kf", "mckf"])
def test_a_negative_range_is_dropped_and_the_next_pairs_with_the_last_accepted(name):
    """Regression (issue 13, item 7): the previous raw range was passed even when refused, so one negative
    draw cost two updates. Now the result equals that of the same data with the bad range left out and its
    displacement carried into the next step, which is what the agent does."""
    params = RelativeEstimationParams()
    displacement, ranges, truth = pair_data()
    bad = ranges.copy()
    bad[20] = -0.7
    start = truth[0] + [1.0, -0.5]
    fed = make_relative_estimator(params, start, name=name)
    outcomes = [outcome for _, outcome in run_estimator(fed, displacement, bad, params.max_range)]
    assert sum(o is not None and o.accepted for o in outcomes) == len(ranges) - 2   # all but step 20 (and step 0)
    assert outcomes[19] is None                                                     # step 20: no update
    # Independently: drop range 20 and merge displacements 19 and 20 into one step.
    merged = np.vstack([displacement[:19], displacement[19] + displacement[20], displacement[21:]])
    reference = make_relative_estimator(params, start, name=name)
    reference.mark_range_epoch()
    kept = np.delete(ranges, 20)
    for k in range(1, len(kept)):
        reference.predict(merged[k - 1], intervals=2.0 if k == 20 else 1.0)   # two periods' noise in the merged
        assert reference.update(kept[k - 1], kept[k]).accepted
    np.testing.assert_allclose(fed.position, reference.position, rtol=0, atol=1e-12)


def test_an_invalid_first_range_waits_for_the_first_valid_one():
    params = RelativeEstimationParams()
    displacement, ranges, truth = pair_data(10)
    bad = ranges.copy()
    bad[0] = float("nan")
    estimator = make_relative_estimator(params, truth[0], name="kf")
    outcomes = [outcome for _, outcome in run_estimator(estimator, displacement, bad, params.max_range)]
    assert outcomes[0] is None and all(o is not None and o.accepted for o in outcomes[1:])
