"""Element-wise bounds and choice for the boat's kernels, on numpy arrays of shape (n,) (a fleet) or on plain
Python floats (one boat): the same numbers either way, since IEEE min, max and comparisons are exact. On a few
boats plain floats cost a tenth of numpy's per-call overhead (docs/sea.md, "What it costs")."""

from __future__ import annotations

import numpy as np


def bound(values, low, high):
    """values in [low, high] (no NaN handling: the callers pass finite numbers)."""
    if type(values) is float:
        return min(max(values, low), high)
    return np.minimum(np.maximum(values, low), high)


def clip(values, limit: float):
    """values in [-limit, limit]."""
    if type(values) is float:
        return min(max(values, -limit), limit)
    return np.minimum(np.maximum(values, -limit), limit)


def where(condition, yes, no):
    """`yes` where `condition` holds, else `no` (a plain bool picks one whole)."""
    if type(condition) is bool:
        return yes if condition else no
    return np.where(condition, yes, no)


def every(condition) -> bool:
    """Whether `condition` holds everywhere."""
    return condition if type(condition) is bool else bool(np.all(condition))
