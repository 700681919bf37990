"""Cooperative fusion with the neighbours' shared estimates, by covariance intersection (`fusion.py`).

Two kinds: a neighbour's estimate of our pair, p^_ji, is fused into our p^_ij (reciprocal fusion); and
each neighbour's target estimate, moved to us through our estimate of where it is, is fused into ours,
after a chi-square gate that leaves out an estimate more likely a fault than noise.
"""

from __future__ import annotations

import math

import numpy as np

from agent.core.checks import share_floats
from agent.core.fusion import covariance_intersection_2d, covariance_intersection_information
from agent.core.neighbours import NeighbourTrack, stamp_key
from agent.core.params import AgentParams
from agent.core.records import Share
from agent.core.state import VesselState

# x = [p_io; v_io] <-> shared [p_io; v_o] with v_o = v_i - v_io: flips the velocity block's sign.
SWAP_VELOCITY = np.diag([1.0, 1.0, -1.0, -1.0])
# SWAP_VELOCITY P SWAP_VELOCITY element by element: the off-diagonal blocks change sign. One exact multiply
# instead of two matrix products (which give the same numbers: each element is one term times +-1).
SWAP_SIGNS = np.outer(np.diag(SWAP_VELOCITY), np.diag(SWAP_VELOCITY))


def swap_velocity(covariance: np.ndarray) -> np.ndarray:
    """SWAP_VELOCITY @ covariance @ SWAP_VELOCITY, for a 4x4 covariance of [p; v]."""
    return covariance * SWAP_SIGNS


def fuse_reciprocal(params: AgentParams, state: VesselState, track: NeighbourTrack) -> None:
    """This tick's p^_ij (`track.fused`): covariance intersection of our pair filter's estimate with j's own
    estimate of p_ji (as -p_ji), both at our filter's epoch. Not in the paper (docs/equations.md, D1).

    Each vessel shares its own filter's estimate, never a fused one, and neither filter takes the fusion in:
    the two vessels compute the same fused estimate (as p_ij and p_ji) from the same two independent ones,
    whoever ticks first. Fed back into the filters, as the paper-like design did, the result depended on the
    order of the ticks (the vessel whose tick came later kept most of its own prior), and at sea, where the
    vessels tick at their own times, pairs ended up with one vessel's prior instead of the mean of both.

    j's estimate refers to the time j gave with it (its filter's epoch, in j's clock). It is carried to our
    epoch by both vessels' measured odometry between the two times (j's from its shares), its covariance
    grown by the displacement noise of (15), if the two times are at most `fleet.max_odometry_gap` apart.
    Only measured motion enters: a commanded velocity the vessel did not follow (a boat held at the start, a
    thruster lagging) would otherwise be taken as truth."""
    # j's estimate as the floats checked where its share came in (membership.py receive_shares)
    if track.estimator is None or track.share is None or not track.reciprocal:
        return
    # In plain floats: a handful of 2-D operations per neighbour, where numpy's per-call overhead would be
    # most of the cost.
    px, py, b11, b12, b22, stamp = track.reciprocal
    bx, by = -px, -py
    key = stamp_key(stamp)
    if key != track.epoch:
        if abs(key - track.epoch) > track.gap_key:       # fleet.max_odometry_gap as a stamp key
            return
        mine_then, theirs_then, why = track.positions_at(state.own, key)
        if why:
            return
        (mx, my), (tx, ty) = mine_then, theirs_then
        (ox, oy), (ex, ey) = track.epoch_own, track.epoch_other
        bx, by = (bx + (ox - mx)) - (ex - tx), (by + (oy - my)) - (ey - ty)
        grown = 2.0 * params.relative.displacement_variance * (abs(key - track.epoch) * 1e-6 / params.dt)
        b11, b22 = b11 + grown, b22 + grown
    ax, ay, a11, a12, a22 = track.estimator.moments()
    try:
        x, y, p11, p12, p22 = covariance_intersection_2d(ax, ay, a11, a12, a12, a22, bx, by, b11, b12, b12, b22)
    except np.linalg.LinAlgError:
        state.health.bad_shares += 1
        return
    fused = (x, y, p11, p12, p22)
    if all(map(math.isfinite, fused)):
        track.fused = fused
    else:
        state.health.bad_shares += 1


def fuse_targets(params: AgentParams, state: VesselState, shared: list[tuple[Share, float, float, NeighbourTrack]],
                 now: float) -> tuple[np.ndarray, np.ndarray]:
    """Covariance intersection of our target estimate with each neighbour's, moved to us:
    p_io = p^_ij + p^_jo (carried to now with j's commanded velocity), v_io = v_i - v^_o as in (33), with
    p^_ij of (10). `shared` gives, for each neighbour whose share carries a target estimate, that share, p^_ij
    at now (x, y) and its track. Not in the paper (docs/equations.md, D2).
    A neighbour whose estimate disagrees with ours beyond `fleet.target_gate` (chi-square, 4 degrees of
    freedom) is left out and counted. Returns the fused state and covariance (ours alone if none fits)."""
    tracker = state.tracker
    own_x, own_P = tracker.state, tracker.covariance
    if not shared:
        return own_x, own_P
    x, P = moved_target_estimates(shared, now, state.motion.velocity)
    m = len(x)
    # One stacked inverse serves the gate, (P_io + P_k)^-1, and the intersection, P_io^-1 and each P_k^-1:
    # numpy's per-call overhead, not the arithmetic, is the cost of a 4x4 inverse.
    inverses, singular = stacked_inverses(np.concatenate([own_P + P, own_P[None], P]))
    differences = x - own_x
    distances = np.add.reduce(differences * np.matmul(inverses[:m], differences[:, :, None])[:, :, 0], axis=1)
    gate = params.fleet.target_gate
    # NaN fails the gate test `distance > gate` and so is kept; a singular P_io + P_k is infinitely far.
    keep = [k for k, distance in enumerate(distances.tolist()) if not distance > gate]
    if singular:
        keep = [k for k in keep if k not in singular]
    state.health.target_estimates_gated += m - len(keep)
    if not keep or singular and (m in singular or any(m + 1 + k in singular for k in keep)):
        return own_x, own_P
    if len(keep) < m:
        x, rows = x[keep], [m] + [m + 1 + k for k in keep]
        information = inverses[rows]
    else:
        information = inverses[m:]
    try:
        fused, fused_covariance = covariance_intersection_information(
            np.concatenate([own_x[None], x]), information * (1.0 / len(information)))
    except np.linalg.LinAlgError:
        return own_x, own_P
    tracker.assimilate(fused, fused_covariance)
    return tracker.state, tracker.covariance


def stacked_inverses(matrices: np.ndarray) -> tuple[np.ndarray, list[int]]:
    """The inverse of each matrix of the stack (m, k, k) and the indices of those that are singular (their
    inverse left as zeros): one numpy call unless one is singular, then one per matrix."""
    try:
        return np.linalg.inv(matrices), []
    except np.linalg.LinAlgError:
        inverses, singular = np.zeros_like(matrices), []
        for k, matrix in enumerate(matrices):
            try:
                inverses[k] = np.linalg.inv(matrix)
            except np.linalg.LinAlgError:
                singular.append(k)
        return inverses, singular


# Up to this many neighbours their target estimates are moved in plain floats, above it as numpy stacks: both
# give the same numbers (element-wise operations, rounded alike); per-call overhead decides which costs less.
FLOAT_NEIGHBOURS = 8


def moved_target_estimates(shared: list, now: float, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each neighbour's shared target estimate moved to us, as `fuse_targets` fuses them: the means (m, 4) and
    covariances (m, 4, 4). `shared` holds (share, x, y, track) with p^_ij = (x, y) at now; `velocity` is v_i.
    p_jo moves with v_j - v_o over the share's age: x <- C x, P <- C P C^T with C = [I, -age I; 0, I]; then to
    our frame, p_io = p^_ij + p_jo and v_io = v_i - v^_o, SWAP_VELOCITY's sign flip of P's off-diagonal blocks
    and p^_ij's covariance added to the position block."""
    if len(shared) > FLOAT_NEIGHBOURS:
        return _moved_target_stacks(shared, now, velocity)
    vx, vy = np.asarray(velocity, dtype=float).tolist()
    means, covariances = [], []
    for share, px, py, track in shared:
        # The floats the share's check kept (checks.py share_floats): every share a track holds passed it.
        _, (ux, uy), ((t0, t1, t2, t3), P) = share_floats(share)
        age = now - share.odometry.stamp
        _, _, p11, p12, p22 = track.moments()
        means.append((((t0 - age * t2) + age * ux) + px, ((t1 - age * t3) + age * uy) + py, vx - t2, vy - t3))
        covariances.append(carried_target_covariance(P, age, p11, p12, p22))
    return np.array(means), np.array(covariances).reshape(-1, 4, 4)


def _moved_target_stacks(shared: list, now: float, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`moved_target_estimates` for every neighbour at once, as stacks: per neighbour, numpy's call overhead
    would be most of the cost. Two arrays, one row per neighbour: what this tick gives (the share's age, p^_ij
    and the symmetric P_ij) and what the share alone gives (j's velocity, its target estimate and covariance,
    `_shared_target_row`); x and P are views of the second."""
    ours: list[float] = []
    theirs = []
    for share, x, y, track in shared:
        _, _, p11, p12, p22 = track.moments()
        ours += (now - share.odometry.stamp, x, y, p11, p12, p22)
        theirs.append(_shared_target_row(share))
    tick = np.array(ours).reshape(-1, 6)
    floats = np.array(theirs)
    age = tick[:, :1]
    x, P = floats[:, 2:6], floats[:, 6:22].reshape(-1, 4, 4)
    # C's zeros and ones add nothing but rounding-free terms: written out by blocks.
    x[:, :2] -= age * x[:, 2:]
    x[:, :2] += age * floats[:, :2]
    P[:, :2, :] -= age[:, :, None] * P[:, 2:, :]
    P[:, :, :2] -= age[:, :, None] * P[:, :, 2:]
    x[:, :2] += tick[:, 1:3]
    x[:, 2:] = velocity - x[:, 2:]
    P[:, :2, 2:] *= -1.0
    P[:, 2:, :2] *= -1.0
    p11, p12, p22 = tick[:, 3], tick[:, 4], tick[:, 5]
    P[:, 0, 0] += p11
    P[:, 0, 1] += p12
    P[:, 1, 0] += p12
    P[:, 1, 1] += p22
    return x, P


# Where `_shared_target_row` keeps a share's row, in the share's own __dict__ as `checks.share_floats` keeps
# its verdict (equality, repr and the codecs ignore it): in process every receiver gets the same Share.
_TARGET_ROW = "_target_row"


def _shared_target_row(share) -> np.ndarray:
    """j's velocity (2), target estimate (4) and its covariance row by row (16) as one float array, the floats
    the share's check kept; built once per share and read only (the stacks copy it)."""
    row = share.__dict__.get(_TARGET_ROW)
    if row is None:
        _, velocity_j, (target, covariance) = share_floats(share)
        row = share.__dict__[_TARGET_ROW] = np.array((*velocity_j, *target, *covariance))
    return row


def carried_target_covariance(P: list[float], age: float, p11: float, p12: float, p22: float) -> list[float]:
    """A neighbour's shared target covariance (4x4, row-major floats, of [p_jo; v_o]) carried over the share's
    age and moved to our frame, as `fuse_targets` does: C P C^T with C = [I, -age I; 0, I] (rows 0, 1 less age
    times rows 2, 3, then likewise the columns), SWAP_VELOCITY's sign flip of the off-diagonal blocks, and
    P_ij = [[p11, p12], [p12, p22]] added to the position block. Element-wise, in numpy's order of operations
    (`_moved_target_stacks`), written out: a loop over the indices cost three times as much."""
    a, b, c, d, e, f, g, h, i, j, k, l, m, n, o, p = P
    # rows 0, 1 less age times rows 2, 3
    a, b, c, d = a - age * i, b - age * j, c - age * k, d - age * l
    e, f, g, h = e - age * m, f - age * n, g - age * o, h - age * p
    # columns 0, 1 less age times columns 2, 3; the off-diagonal blocks change sign; P_ij joins the position block
    a, b, e, f = a - age * c, b - age * d, e - age * g, f - age * h
    i, j, m, n = i - age * k, j - age * l, m - age * o, n - age * p
    return [a + p11, b + p12, -c, -d, e + p12, f + p22, -g, -h, -i, -j, k, l, -m, -n, o, p]
