"""Checks of what reaches the core, before anything touches a filter.

The shell's input gate has already validated every payload against the contract; these checks hold for
any caller (the in-process runner, replay, a test), so the core itself never lets a non-finite number or a
malformed share into an estimate. Each returns a verdict only: counting what was refused is the step's job.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from agent.cholesky import cholesky_succeeds  # noqa: F401  (the core's name for it: plkf.py)
from agent.core.estimators.registry import MAX_LEVER_ARM
from agent.core.records import PairShare, Share

FLOAT64 = np.dtype(np.float64)


def finite_vector(value, size: int) -> bool:
    return finite_floats(value, (size,)) is not None


def finite_matrix(value) -> bool:
    """A finite 2x2 matrix."""
    return finite_floats(value, (2, 2)) is not None


def finite_array(value, shape: tuple[int, ...]) -> bool:
    """`value`, as a float array, has `shape` and only finite elements."""
    return finite_floats(value, shape) is not None


def finite_floats(value, shape: tuple[int, ...]) -> list[float] | None:
    """The elements of `value` as a flat list of floats if it passes `finite_array`, else None: the check and
    the conversion a caller doing its algebra in floats needs, in one pass."""
    if type(value) is np.ndarray and (value.dtype is FLOAT64 or value.dtype == FLOAT64):
        # The common case, without a conversion: math.isfinite over a few elements costs less than numpy's
        # isfinite-and-reduce, and these checks run several times per share and neighbour each tick.
        if value.shape != shape:
            return None
        # A vector is flat already: ravel's view would only add a call (a share brings three vectors a tick)
        values = value.tolist() if len(shape) == 1 else value.ravel().tolist()
        # Any inf or NaN makes the sum non-finite, so a finite sum settles it in one call; only a sum that
        # overflowed (or a non-finite element) needs the element-wise look.
        total = sum(values)
        if total - total == 0.0:
            return values
    else:
        try:
            array = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            return None
        if array.shape != shape:
            return None
        values = array.ravel().tolist()
    return values if all(map(math.isfinite, values)) else None


def valid_range(value, max_range: float) -> bool:
    """A real number in [0, max_range] (a bool is not a range)."""
    return (not isinstance(value, bool) and isinstance(value, (int, float))
            and math.isfinite(value) and 0.0 <= value <= max_range)


# What a receiver takes from a valid share beside the share itself, as the floats its check gave: (the
# sender's odometry position, its commanded velocity (2), its estimate of the receiver's pair as
# `pair_entry_floats` gives it or () if none). A plain tuple: a NamedTuple's constructor, per share and tick,
# would cost about as much as the conversions it saves.
CheckedShare = tuple[tuple[float, float], tuple[float, float], tuple[float, ...]]


def checked_share(share: object, receiver: str) -> CheckedShare | None:
    """What a receiver takes from a share (`CheckedShare`), or None if the share is not valid. Of the share's
    `neighbours` only the receiver's own entry is checked (O(1) per share, where checking them all would cost
    O(n^2) per tick in a large fleet). The track reads these floats every tick: they are checked and converted
    once, where the share comes in; what every receiver finds alike, once per share (`share_floats`)."""
    if not isinstance(share, Share):
        return None
    common = share_floats(share)
    if common is None:
        return None
    entry = share.neighbours.get(receiver)
    reciprocal = () if entry is None else pair_entry_floats(entry)
    if reciprocal is None:
        return None
    position, velocity, _ = common
    return position, velocity, reciprocal


# Where `share_floats` keeps its verdict: in the share's own __dict__ (a frozen dataclass's fields are its
# constructor's; this is not one of them, so equality, repr and the codecs ignore it). In process every
# receiver gets the same Share object, and an agent's tick is handed the same object until the sender's next
# share replaces it: the checks run once per share, not once per receiver and tick (with 50 vessels they were
# a tenth of the fleet's tick). Nothing writes to a share's arrays once it is built: the core's step builds
# them fresh, the gate decodes them fresh.
_VERDICT = "_checked_floats"
_UNSEEN = object()


# What `share_floats` keeps of a valid share: (the odometry position, the commanded velocity, the target
# estimate as (x (4 floats), P row by row (16)) or None when it shares none).
SharedFloats = tuple[tuple[float, float], tuple[float, float], tuple[list[float], list[float]] | None]


def share_floats(share: Share) -> SharedFloats | None:
    """The checks of `checked_share` that do not depend on the receiver, once per share: `SharedFloats`, or
    None if the share is not valid."""
    kept = share.__dict__
    verdict = kept.get(_VERDICT, _UNSEEN)
    if verdict is _UNSEEN:
        verdict = kept[_VERDICT] = _share_floats(share)
    return verdict


def _share_floats(share: Share) -> SharedFloats | None:
    odometry = share.odometry
    target = None
    # One chain that keeps the floats it checks: a check after a failed one is still not evaluated.
    if not ((position := finite_floats(odometry.position, (2,))) is not None
            and isinstance(odometry.stamp, (int, float))
            and math.isfinite(odometry.stamp) and math.isfinite(share.phase)
            and (velocity := finite_floats(share.velocity, (2,))) is not None
            and (share.target is None or (target := _target_floats(share)) is not None)
            and (type(share.neighbours) is dict or isinstance(share.neighbours, Mapping))
            and (share.antenna is None or _valid_antenna(share.antenna, odometry.heading))):
        return None
    (px, py), (vx, vy) = position, velocity
    return (px, py), (vx, vy), target


def _target_floats(share: Share) -> tuple[list[float], list[float]] | None:
    """The share's target estimate (4) and its covariance (4x4, row by row) as floats; None unless both are
    there and finite."""
    x = finite_floats(share.target, (4,))
    if x is None or share.target_covariance is None:
        return None
    P = finite_floats(share.target_covariance, (4, 4))
    return None if P is None else (x, P)


def _valid_antenna(antenna, heading) -> bool:
    """A lever arm (forward, left), finite and within MAX_LEVER_ARM (m), and a finite heading to turn it."""
    arm = finite_floats(antenna, (2,))
    return (arm is not None and all(abs(v) <= MAX_LEVER_ARM for v in arm)
            and isinstance(heading, (int, float)) and math.isfinite(heading))


def pair_entry_floats(entry) -> PairShare | None:
    """A share's estimate of one pair (`records.PairShare`: px, py, p11, p12, p22, stamp) as six floats: the
    entry itself when it is a tuple of floats; None unless it has six elements, the first five real (not
    bool) and finite, and the stamp a finite float."""
    try:
        px, py, p11, p12, p22, stamp = entry
    except (TypeError, ValueError):
        return None
    # Per neighbour and tick: one chained type test for the floats the core and the gate build.
    if not type(px) is type(py) is type(p11) is type(p12) is type(p22) is float or type(entry) is not tuple:
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (px, py, p11, p12, p22)):
            return None
        px, py, p11, p12, p22 = float(px), float(py), float(p11), float(p12), float(p22)
        entry = (px, py, p11, p12, p22, stamp)
    total = px + py + p11 + p12 + p22
    # A finite sum settles it; only an overflowed one (or a non-finite number) needs the look at each.
    if total - total != 0.0 and not all(map(math.isfinite, (px, py, p11, p12, p22))):
        return None
    if not (isinstance(stamp, float) and math.isfinite(stamp)):
        return None
    return entry


def obstacle_array(points) -> tuple[np.ndarray | None, bool]:
    """(points as an (M, 2) array or None when there are none, whether they were malformed)."""
    if points is None:
        return None, False
    array = np.asarray(points, dtype=float) if not isinstance(points, np.ndarray) else points
    if array.size == 0:
        return None, False
    if array.ndim != 2 or array.shape[1] != 2 or not np.all(np.isfinite(array)):
        return None, True
    return array, False
