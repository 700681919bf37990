"""The median of a few floats, as numpy.median gives it, at a fraction of its cost.

numpy.median imports numpy.ma on its first call (about 38 ms and 10 MB in an agent that has not needed it:
a latency spike at the tick a returning vessel is first vetted) and costs about 100 us a call on a handful of
floats, where sorting them costs a few."""

from __future__ import annotations

import math
import statistics


def median(values) -> float:
    """numpy.median's value of `values` (any iterable of numbers, a numpy array included): the middle one, or
    the mean of the two middle ones; NaN if there is none or any is NaN, as numpy's (without its warning)."""
    floats = [float(v) for v in values]
    if not floats or any(math.isnan(v) for v in floats):
        return math.nan
    return float(statistics.median(floats))
