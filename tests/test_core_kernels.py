"""The closed-form and stacked kernels the core uses for speed give what the plain numpy algebra gives.

Each kernel is checked against the textbook form computed independently with numpy (inverse, solve, matrix
products, loops over the estimates), on random inputs, to floating-point rounding; and the checks keep the
verdicts of numpy's isfinite on every kind of input."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from agent.core.checks import finite_floats, finite_matrix, finite_vector, pair_entry_floats
from agent.core.control.formation import desired_offset, desired_offsets, formation_velocity
from agent.core.control.oscillator import coupling_gains, oscillator_step
from agent.core.control.separation import surge_interval, sweep_max_cos
from agent.core.cooperation import stacked_inverses
from agent.core.fusion import (
    covariance_intersection,
    covariance_intersection_2d,
    covariance_intersection_many,
    covariance_intersection_stacked,
    inverse,
)

RNG_SEEDS = range(20)


def _spd(rng: np.random.Generator, k: int) -> np.ndarray:
    M = rng.normal(size=(k, k))
    return M @ M.T + 0.1 * np.eye(k)


def _reference_intersection(estimates, weights):
    """P^-1 = sum w_k P_k^-1, x = P sum w_k P_k^-1 x_k with numpy.linalg.inv, one estimate at a time."""
    information = sum(w * np.linalg.inv(C) for w, (_, C) in zip(weights, estimates))
    P = np.linalg.inv(information)
    x = P @ sum(w * np.linalg.inv(C) @ c for w, (c, C) in zip(weights, estimates))
    return x, 0.5 * (P + P.T)


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_two_dimensional_intersection_in_floats_matches_numpy(seed):
    rng = np.random.default_rng(seed)
    a, A, b, B = rng.normal(size=2) * 10, _spd(rng, 2), rng.normal(size=2) * 10, _spd(rng, 2)
    weight = float(rng.uniform(0.1, 0.9))
    x_ref, P_ref = _reference_intersection([(a, A), (b, B)], (weight, 1.0 - weight))
    x, y, p11, p12, p22 = covariance_intersection_2d(*a, *A.ravel(), *b, *B.ravel(), weight)
    np.testing.assert_allclose([x, y], x_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose([[p11, p12], [p12, p22]], P_ref, rtol=1e-12, atol=1e-12)
    x_arr, P_arr = covariance_intersection(a, A, b, B, weight)
    np.testing.assert_array_equal(x_arr, [x, y])
    np.testing.assert_array_equal(P_arr, [[p11, p12], [p12, p22]])


@pytest.mark.parametrize("seed", RNG_SEEDS)
@pytest.mark.parametrize("k", [2, 4])
def test_stacked_intersection_matches_a_loop_over_the_estimates(seed, k):
    rng = np.random.default_rng(seed)
    m = int(rng.integers(1, 40))
    estimates = [(rng.normal(size=k) * 10, _spd(rng, k)) for _ in range(m)]
    x_ref, P_ref = _reference_intersection(estimates, [1.0 / m] * m)
    x, P = covariance_intersection_many(estimates)
    np.testing.assert_allclose(x, x_ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(P, P_ref, rtol=1e-9, atol=1e-12)
    x_s, P_s = covariance_intersection_stacked(np.array([c for c, _ in estimates]),
                                               np.array([C for _, C in estimates]), np.full(m, 1.0 / m))
    np.testing.assert_array_equal(x_s, x)
    np.testing.assert_array_equal(P_s, P)


def test_singular_covariances_raise_as_numpy_does():
    with pytest.raises(np.linalg.LinAlgError):
        covariance_intersection_2d(0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0)
    with pytest.raises(np.linalg.LinAlgError):
        inverse(np.array([[1.0, math.inf], [0.0, 1.0]]))
    with pytest.raises(np.linalg.LinAlgError):
        covariance_intersection_stacked(np.zeros((2, 4)), np.array([np.eye(4), np.zeros((4, 4))]), np.full(2, 0.5))


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_inverse_of_a_two_by_two_matches_numpy(seed):
    M = np.random.default_rng(seed).normal(size=(2, 2))
    np.testing.assert_allclose(inverse(M), np.linalg.inv(M), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_stacked_inverses_match_one_inverse_per_matrix_and_name_the_singular_ones(seed):
    rng = np.random.default_rng(seed)
    m = int(rng.integers(1, 30))
    matrices = np.array([_spd(rng, 4) for _ in range(m)])
    inverses, singular = stacked_inverses(matrices)
    assert singular == []
    for matrix, inverse_of in zip(matrices, inverses):
        np.testing.assert_allclose(inverse_of @ matrix, np.eye(4), atol=1e-9)
    matrices[0] = 0.0
    inverses_with, singular = stacked_inverses(matrices)
    assert singular == [0] and not inverses_with[0].any()
    np.testing.assert_array_equal(inverses_with[1:], inverses[1:])


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_formation_terms_match_the_loop_of_33(seed):
    rng = np.random.default_rng(seed)
    m = int(rng.integers(0, 50))
    phases = rng.uniform(-math.pi, math.pi, m)
    np.testing.assert_array_equal(desired_offsets(7.5, phases).reshape(m, 2),
                                  np.array([desired_offset(7.5, p) for p in phases]).reshape(m, 2))
    gains, errors = rng.uniform(0.0, 2.0, m), rng.normal(size=(m, 2)) * 5
    total = np.zeros(2)
    for gain, error in zip(gains, errors):
        total += gain * error
    np.testing.assert_array_equal(formation_velocity(zip(gains, errors[:, 0], errors[:, 1])), total)


def _oscillator_loop(phase, neighbour_phases, yaw_rate, dt, gain):
    """(28) as written: a loop over the harmonics and the neighbours."""
    n = len(neighbour_phases) + 1
    coupling = 0.0
    for m, k_m in enumerate(coupling_gains(n, gain), start=1):
        if k_m == 0.0:
            break
        coupling += k_m / (m * n) * sum(math.sin(m * (phase - other)) for other in neighbour_phases)
    return phase + yaw_rate * dt + dt * coupling


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_oscillator_matches_the_loop_of_28(seed):
    rng = np.random.default_rng(seed)
    neighbours = rng.uniform(-math.pi, math.pi, int(rng.integers(0, 60))).tolist()
    phase, gain = float(rng.uniform(-math.pi, math.pi)), float(rng.choice([0.0, 0.3, 1.0]))
    expected = math.remainder(_oscillator_loop(phase, neighbours, 0.1, 0.1, gain), 2 * math.pi)
    got = oscillator_step(phase, neighbours, 0.1, 0.1, gain)
    assert math.isclose(math.remainder(got - expected, 2 * math.pi), 0.0, abs_tol=1e-12)


@pytest.mark.parametrize("value, shape", [
    (np.array([1.0, 2.0]), (2,)), (np.array([1.0, np.nan]), (2,)), (np.array([np.inf, 0.0]), (2,)),
    (np.array([1.0, 2.0, 3.0]), (2,)), (np.eye(2), (2, 2)), (np.array([[1.0, -np.inf], [0.0, 1.0]]), (2, 2)),
    (np.eye(2), (2,)), ([1.0, 2.0], (2,)), ((1, 2), (2,)), ([1.0, float("nan")], (2,)), ("ab", (2,)),
    (None, (2,)), (np.array([1, 2]), (2,)), (np.array([1.0, 2.0], dtype=np.float32), (2,)),
    (np.array([1.0, 2.0]).astype(">f8"), (2,)), (np.array([1e308, 1e308]), (2,)), (np.eye(4), (4, 4)),
])
def test_finite_checks_keep_numpys_verdicts(value, shape):
    try:
        array = np.asarray(value, dtype=float)
        expected = array.shape == shape and bool(np.isfinite(array).all())
    except (TypeError, ValueError):
        expected = False
    values = finite_floats(value, shape)
    assert (values is not None) == expected
    if expected:
        assert values == np.asarray(value, dtype=float).ravel().tolist()
    if shape == (2,):
        assert finite_vector(value, 2) == expected
    if shape == (2, 2):
        assert finite_matrix(value) == expected


def test_pair_entry_check():
    # (a share without an entry for the receiver is valid: test_a_checked_share_gives_the_floats_the_track_keeps)
    entry = (0.0, 0.0, 1.0, 0.0, 1.0, 1.0)
    assert pair_entry_floats(entry) is entry                      # a tuple of floats is taken as it is
    assert pair_entry_floats((0.0, 0.0, 1.0, 0.0, 1.0, 1)) is None           # a stamp is a float
    assert pair_entry_floats((0.0, math.nan, 1.0, 0.0, 1.0, 1.0)) is None
    assert pair_entry_floats((0.0, 0.0, math.inf, 0.0, 1.0, 1.0)) is None
    assert pair_entry_floats((0.0, 0.0, 1.0, 0.0, 1.0, math.inf)) is None
    assert pair_entry_floats((0.0, 0.0, 1.0, 0.0, 1.0)) is None
    assert pair_entry_floats((np.zeros(2), np.eye(2), 1.0)) is None            # no arrays: six numbers
    assert pair_entry_floats((0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0)) is None
    assert pair_entry_floats((True, 0.0, 1.0, 0.0, 1.0, 1.0)) is None          # a bool is not a number
    assert pair_entry_floats(("0.5", 0.0, 1.0, 0.0, 1.0, 1.0)) is None
    assert pair_entry_floats((0.0, 0.0, 1.0, 0.0, None, 1.0)) is None
    assert pair_entry_floats(7) is None
    # finite numbers whose sum overflows are finite all the same
    assert pair_entry_floats((1e308, 1e308, 1e308, 0.0, 1.0, 2.0)) == (1e308, 1e308, 1e308, 0.0, 1.0, 2.0)
    # what the receiver fuses: position, covariance's three numbers, stamp, as a tuple of floats
    floats = pair_entry_floats([1, np.float64(2.0), 3, 4.0, 6.0, 7.0])
    assert floats == (1.0, 2.0, 3.0, 4.0, 6.0, 7.0) and type(floats) is tuple
    assert all(type(v) is float for v in floats)


def test_a_checked_share_gives_the_floats_the_track_keeps():
    """checked_share: the share's odometry position and velocity as float tuples and its entry for the receiver
    as pair_entry_floats gives it ((): none); None for a share the receiver refuses."""
    from agent.core.checks import checked_share
    from agent.core.records import OdometryReading, Share

    entry = (1.0, 2.0, 3.0, 4.0, 6.0, 7.0)
    share = Share("2", OdometryReading(0.5, np.array([8.0, 9.0]), 0.0), np.array([0.25, -0.5]), 0.0,
                  neighbours={"1": entry})
    checked = checked_share(share, "1")
    assert checked == ((8.0, 9.0), (0.25, -0.5), pair_entry_floats(entry))
    assert all(type(x) is float for x in (*checked[0], *checked[1]))
    assert checked_share(share, "3") == ((8.0, 9.0), (0.25, -0.5), ())
    bad = Share("2", share.odometry, share.velocity, 0.0, neighbours={"1": (0.0, 0.0, 1.0, 0.0, 1.0, 1)})
    assert checked_share(bad, "1") is None
    assert checked_share(Share("2", share.odometry, np.array([np.nan, 0.0]), 0.0), "1") is None


def _reference_checked_share(share, receiver):
    """checked_share written out independently, numpy's isfinite on every part, for one receiver: what each
    receiver checked for itself before the checks common to all receivers were kept on the share."""
    from agent.core.estimators.registry import MAX_LEVER_ARM
    from agent.core.records import Share

    def floats(value, shape):
        try:
            array = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            return None
        return array.ravel().tolist() if array.shape == shape and np.isfinite(array).all() else None

    def real(value):
        return isinstance(value, (int, float)) and math.isfinite(value)

    if not isinstance(share, Share):
        return None
    odometry = share.odometry
    position, velocity = floats(odometry.position, (2,)), floats(share.velocity, (2,))
    if position is None or velocity is None or not real(odometry.stamp) or not math.isfinite(share.phase):
        return None
    if share.target is not None and (floats(share.target, (4,)) is None or share.target_covariance is None
                                     or floats(share.target_covariance, (4, 4)) is None):
        return None
    if not isinstance(share.neighbours, dict):
        return None
    if share.antenna is not None:
        arm = floats(share.antenna, (2,))
        if arm is None or max(abs(v) for v in arm) > MAX_LEVER_ARM or not real(odometry.heading):
            return None
    entry = share.neighbours.get(receiver)
    if entry is None:
        return tuple(position), tuple(velocity), ()
    if not isinstance(entry, tuple) or len(entry) != 6:
        return None
    *numbers, stamp = entry
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in numbers):
        return None
    p, P = floats(numbers[:2], (2,)), floats(numbers[2:], (3,))
    if p is None or P is None or not (isinstance(stamp, float) and math.isfinite(stamp)):
        return None
    return tuple(position), tuple(velocity), (*p, *P, stamp)


def _hostile_shares(rng: np.random.Generator, receivers: list[str]) -> list:
    """Shares from "9" to `receivers`, valid and broken in each of the ways a share can be: a non-finite or
    misshapen part common to every receiver, or one receiver's own entry broken (the others' valid)."""
    from agent.core.records import OdometryReading, Share

    def entry():
        x, y = rng.normal(size=2).tolist()
        return x, y, float(rng.uniform(0.1, 2.0)), 0.0, float(rng.uniform(0.1, 2.0)), float(rng.uniform(0.0, 5.0))

    def share(**changes):
        parts = {"sender": "9", "odometry": OdometryReading(float(rng.uniform(0, 5)), rng.normal(size=2), 0.3),
                 "velocity": rng.normal(size=2), "phase": float(rng.uniform(-3, 3)), "target": rng.normal(size=4),
                 "target_covariance": np.eye(4), "neighbours": {r: entry() for r in receivers}, "antenna": None}
        return Share(**(parts | changes))

    nan, inf = math.nan, math.inf
    shares = [share(), share(target=None, target_covariance=None), share(neighbours={}),
              share(antenna=(0.2, -0.1)), share(velocity=[0.5, 1.0])]
    shares += [share(odometry=OdometryReading(0.1, np.array([nan, 0.0]), 0.0)),
               share(odometry=OdometryReading(inf, np.zeros(2), 0.0)),
               share(odometry=OdometryReading("0.1", np.zeros(2), 0.0)),
               share(odometry=OdometryReading(0.1, np.zeros(3), 0.0)),
               share(velocity=np.array([0.0, -inf])), share(velocity=np.zeros((2, 1))), share(velocity="ab"),
               share(phase=nan), share(target=np.array([0.0, 0.0, nan, 0.0])),
               share(target_covariance=None), share(target_covariance=np.full((4, 4), inf)),
               share(target_covariance=np.eye(3)), share(neighbours=[("1", entry())]),
               share(antenna=(nan, 0.0)), share(antenna=(30.0, 0.0)), share(antenna=(0.1,)),
               share(antenna=(0.1, 0.0), odometry=OdometryReading(0.1, np.zeros(2), nan)), "not a share", None]
    for broken in ((nan, 0.0, 1.0, 0.0, 1.0, 1.0), (0.0, 0.0, inf, 0.0, 1.0, 1.0), (0.0, 0.0, 1.0, 0.0, 1.0, 1),
                   (0.0, 0.0, 1.0, 0.0, 1.0, nan), (0.0, 0.0, 1.0, 0.0, 1.0), 7):
        victim = receivers[int(rng.integers(len(receivers)))]
        shares.append(share(neighbours={r: broken if r == victim else entry() for r in receivers}))
    return shares


@pytest.mark.parametrize("seed", range(5))
def test_a_share_checked_once_for_all_its_receivers_gives_each_the_verdict_of_its_own_check(seed):
    """checked_share keeps the checks common to every receiver on the share: each receiver, in any order and
    on a share others have checked already, gets what a check of its own (the reference, from scratch)
    gives, a refusal for a broken entry of its own included, and the other receivers are not affected."""
    from agent.core.checks import checked_share

    rng = np.random.default_rng(seed)
    receivers = ["1", "2", "3", "4"]
    for share in _hostile_shares(rng, receivers):
        expected = {r: _reference_checked_share(share, r) for r in receivers + ["5"]}
        for r in rng.permutation(receivers + ["5"]).tolist() * 2:     # twice: the kept verdict read again
            assert checked_share(share, r) == expected[r], (share, r)
    # what the shares above were built to hold: 5 valid, 19 refused by all, 6 by one receiver (its entry)
    verdicts = [[_reference_checked_share(s, r) is None for r in receivers] for s in _hostile_shares(rng, receivers)]
    assert [sum(not any(v) for v in verdicts), sum(all(v) for v in verdicts),
            sum(any(v) and not all(v) for v in verdicts)] == [5, 19, 6]


def _same(a, b) -> bool:
    """Equal value for value, arrays element by element. (A dataclass's == compares its fields one by one
    from Python 3.13 on, and an array field then has no truth value; before, tuples of the same array
    objects compared equal by identity.)"""
    if dataclasses.is_dataclass(a):
        return type(a) is type(b) and all(_same(getattr(a, f.name), getattr(b, f.name))
                                          for f in dataclasses.fields(a))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return bool(np.array_equal(a, b))
    if isinstance(a, (tuple, list)):
        return type(a) is type(b) and len(a) == len(b) and all(map(_same, a, b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return a == b


def test_the_fleet_counts_a_refused_share_at_each_receiver_as_a_check_per_receiver_did():
    """receive_shares: a share broken for every receiver is counted by each, at every delivery, the same
    object or not; one broken in one receiver's entry is refused (and counted) by that receiver alone; a valid
    share delivered again leaves the track as taking a fresh copy of it does."""
    from agent.core.build import InitialEstimates, initial_state
    from agent.core.membership import receive_shares
    from agent.core.params import AgentParams
    from agent.core.records import OdometryReading, Share

    params = AgentParams()
    states = {r: initial_state(r, params, InitialEstimates()) for r in ("1", "2", "3")}
    entry = (1.0, 2.0, 1.0, 0.0, 1.0, 0.1)
    good = Share("9", OdometryReading(0.1, np.array([4.0, 5.0]), 0.0), np.array([0.5, 0.0]), 0.2,
                 neighbours={r: entry for r in states})
    hostile = dataclasses.replace(good, velocity=np.array([math.nan, 0.0]))
    theirs = dataclasses.replace(good, neighbours={**good.neighbours, "2": (0.0, 0.0, 1.0, 0.0, 1.0, 1)})
    for tick in range(3):
        for r in ("3", "2", "1"):
            receive_shares(params, states[r], {"9": hostile}, 0.1 + tick)
    assert [states[r].health.bad_shares for r in ("1", "2", "3")] == [3, 3, 3]
    assert not any(state.tracks for state in states.values())
    for r in ("2", "1", "3"):
        receive_shares(params, states[r], {"9": theirs}, 0.1)
    assert [states[r].health.bad_shares for r in ("1", "2", "3")] == [3, 4, 3]
    assert "9" in states["1"].tracks and "9" not in states["2"].tracks and "9" in states["3"].tracks

    def kept(track):
        return (track.odometry.items(), track.arms.items(), track.share, track.reciprocal, track.velocity,
                track.last_heard, track.first_heard)

    again, fresh = (initial_state("1", params, InitialEstimates()) for _ in range(2))
    later = dataclasses.replace(good, odometry=OdometryReading(0.2, np.array([4.5, 5.0]), 0.0))
    for state, second in ((again, later), (fresh, dataclasses.replace(later))):
        receive_shares(params, state, {"9": good}, 0.1)
        receive_shares(params, state, {"9": later}, 0.2)
        receive_shares(params, state, {"9": second}, 0.3)      # the same object again, or an equal new one
    assert again.tracks["9"].share is later and fresh.tracks["9"].share is not later
    assert _same(kept(again.tracks["9"]), kept(fresh.tracks["9"]))
    assert again.health.as_dict() == fresh.health.as_dict()


def test_history_keeps_the_latest_stamps_in_order_without_a_resort():
    from agent.core.neighbours import History

    history = History(5)
    stamps = [0.1 * k for k in range(12)] + [0.35]     # the last one out of order
    for stamp in stamps:
        history.put(stamp, stamp)
    kept = sorted({round(s * 1e6) for s in stamps})[-5:]
    assert history.keys() == kept
    assert history.last_values(3) == [history.get(k) for k in kept[-3:]]
    assert history.last_values(10) == [history.get(k) for k in kept]


@pytest.mark.parametrize("seed", range(10))
def test_history_puts_keep_what_a_sorted_dict_trimmed_to_its_size_keeps(seed):
    """History against a plain dict trimmed to its `size` largest keys after each put: in-order puts (the
    fast path), repeated and out-of-order stamps, pops and restores, in random order."""
    from agent.core.neighbours import History

    rng = np.random.default_rng(seed)
    size = int(rng.integers(1, 8))
    history, reference = History(size), {}
    key = 0
    for _ in range(400):
        action = rng.choice(["next", "next", "next", "again", "earlier", "pop", "restore"], p=[.5, .1, .1, .1, .1, .05, .05])
        if action == "pop" and reference:
            old = int(rng.choice(sorted(reference)))
            history.pop(old)
            del reference[old]
        elif action == "restore":
            history.restore(history.items())
        else:
            key = {"next": key + int(rng.integers(1, 4)), "again": key,
                   "earlier": key - int(rng.integers(1, 10))}.get(str(action), key)
            value = (float(rng.normal()), float(rng.normal()))
            history.put_key(key, value)
            reference[key] = value
            while len(reference) > size:
                del reference[min(reference)]
        assert history.items() == sorted(reference.items())
        assert all(history.get(k) == reference.get(k) for k in range(key - 30, key + 5))   # dropped: gone
        assert history.latest() == (max(reference) if reference else None)
        assert history.last_values(3) == [reference[k] for k in sorted(reference)[-3:]]


def _share_with_target(stamp: float, target: np.ndarray, covariance: np.ndarray, velocity: np.ndarray):
    """A share from vessel "j" at `stamp` that carries a target estimate."""
    from agent.core.records import OdometryReading, Share

    return Share("j", OdometryReading(stamp, np.zeros(2), 0.0), velocity, 0.0, target=target,
                 target_covariance=covariance)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("far", [0, 2])
@pytest.mark.parametrize("count", [4, 12])      # moved in floats, and as numpy stacks (FLOAT_NEIGHBOURS = 8)
def test_target_fusion_matches_the_matrices_of_one_neighbour_at_a_time(seed, far, count):
    """fuse_targets, which gathers every neighbour's floats into stacks, against the transformations written
    as 4x4 matrices, one neighbour at a time: x_j carried by C = [I, -age I; 0, I] (and j's velocity), moved
    to us through p^_ij and v_i, covariance SWAP C P C^T SWAP + blkdiag(P_ij, 0), then the chi-square gate
    d^T (P_io + P_j)^-1 d <= 13.28 (4 degrees of freedom, 1 %) and equal-weight covariance intersection of
    ours with those kept. `far` of the `count` neighbours have target estimates 20 m off: gated out, counted."""
    from types import SimpleNamespace

    from agent.core.cooperation import SWAP_VELOCITY, fuse_targets

    rng = np.random.default_rng(seed)
    now, velocity = 12.3, rng.normal(size=2)
    own_state, own_cov = rng.normal(size=4), _spd(rng, 4) + 5.0 * np.eye(4)
    assimilated = []
    tracker = SimpleNamespace(state=own_state, covariance=own_cov,
                              assimilate=lambda x, P: assimilated.append((x, P)))
    neighbours, expected = [], [(own_state, own_cov)]
    gated = 0
    for k in range(count):
        pair_cov = _spd(rng, 2)
        moments = (*rng.normal(size=2), pair_cov[0, 0], 0.5 * (pair_cov[0, 1] + pair_cov[1, 0]), pair_cov[1, 1])
        offset = np.array([20.0, 0.0, 0.0, 0.0]) if k < far else 0.1 * rng.normal(size=4)
        share = _share_with_target(now - rng.uniform(0.0, 0.3), own_state + offset, _spd(rng, 4), rng.normal(size=2))
        track = SimpleNamespace(share=share, estimator=object(), moments=lambda m=moments: m)
        x, y = rng.normal(size=2)
        neighbours.append((share, x, y, track))
        age = now - share.odometry.stamp
        C = np.block([[np.eye(2), -age * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
        carried = C @ share.target + np.concatenate([age * share.velocity, np.zeros(2)])
        mean = np.concatenate([carried[:2] + [x, y], velocity - carried[2:]])
        _, _, p11, p12, p22 = moments
        cov = SWAP_VELOCITY @ C @ share.target_covariance @ C.T @ SWAP_VELOCITY
        cov[:2, :2] += [[p11, p12], [p12, p22]]
        difference = mean - own_state
        if difference @ np.linalg.solve(own_cov + cov, difference) > 13.28:
            gated += 1
        else:
            expected.append((mean, cov))
    assert gated == far     # (what the test means to set up)
    state = SimpleNamespace(tracker=tracker, motion=SimpleNamespace(velocity=velocity),
                            health=SimpleNamespace(target_estimates_gated=0))
    params = SimpleNamespace(fleet=SimpleNamespace(target_gate=13.28))
    fuse_targets(params, state, neighbours, now)
    assert state.health.target_estimates_gated == far
    (x_f, P_f), = assimilated
    x_r, P_r = _reference_intersection(expected, [1.0 / len(expected)] * len(expected))
    np.testing.assert_allclose(x_f, x_r, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(P_f, P_r, rtol=1e-9, atol=1e-12)


def test_track_estimate_in_floats_is_the_array_one():
    """estimate_floats_at and estimate_at give the same p^_ij; best() is the matrix form of moments()."""
    from agent.core.checks import checked_share
    from agent.core.neighbours import History, NeighbourPrior, NeighbourTrack, PairTiming, stamp_key
    from agent.core.params import AgentParams
    from agent.core.records import OdometryReading, Share

    params = AgentParams()
    track = NeighbourTrack("2", params.relative, params.dt, 50, PairTiming.of(params.fleet))
    own = History(50)
    for k in range(3):
        own.put(0.1 * k, (0.5 * k, 0.1))
        share = Share("2", OdometryReading(0.1 * k, np.array([0.0, 0.2 * k]), 0.0), np.array([0.0, 2.0]), 0.0)
        track.receive(share, 0.1 * k, checked_share(share, "1"))
    assert track.start(NeighbourPrior(np.array([3.0, -1.0]), np.eye(2), 0.1), own) == "started"
    floats = track.estimate_floats_at(own, stamp_key(0.2))
    assert floats == tuple(track.estimate_at(own, stamp_key(0.2)).tolist())
    # p_ij moves by i's motion minus j's: (3, -1) + (0.5, 0) - (0, 0.2)
    np.testing.assert_allclose(floats, (3.5, -1.2), rtol=0, atol=1e-12)
    px, py, p11, p12, p22 = track.moments()
    position, covariance = track.best()
    assert position.tolist() == [px, py] and covariance.tolist() == [[p11, p12], [p12, p22]]
    track.fused = (1.0, 2.0, 3.0, 0.5, 4.0)
    assert track.best_trace() == 7.0 and track.best()[1].tolist() == [[3.0, 0.5], [0.5, 4.0]]


# ----- issue 14, round 3: element-wise work in floats gives numpy's very numbers -----

def _shared_targets(rng: np.random.Generator, m: int, now: float):
    from types import SimpleNamespace

    shared = []
    for _ in range(m):
        pair_cov = _spd(rng, 2)
        moments = (*rng.normal(size=2), pair_cov[0, 0], 0.5 * (pair_cov[0, 1] + pair_cov[1, 0]), pair_cov[1, 1])
        share = _share_with_target(now - rng.uniform(0.0, 0.3), rng.normal(size=4) * 10, _spd(rng, 4),
                                   rng.normal(size=2))
        track = SimpleNamespace(moments=lambda m=moments: m)
        shared.append((share, *rng.normal(size=2).tolist(), track))
    return shared


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_target_estimates_moved_in_floats_are_the_stacks_bit_for_bit(seed):
    """moved_target_estimates for a few neighbours (floats) and for many (numpy stacks) are the same
    element-wise operations: the switch between them at FLOAT_NEIGHBOURS changes no bit."""
    from agent.core.cooperation import FLOAT_NEIGHBOURS, _moved_target_stacks, moved_target_estimates

    rng = np.random.default_rng(seed)
    now, velocity = 12.3, rng.normal(size=2)
    shared = _shared_targets(rng, int(rng.integers(1, FLOAT_NEIGHBOURS + 1)), now)
    x, P = moved_target_estimates(shared, now, velocity)
    x_s, P_s = _moved_target_stacks(shared, now, velocity)
    np.testing.assert_array_equal(x, x_s)
    np.testing.assert_array_equal(P, P_s)


def test_swapping_the_velocity_block_is_the_matrix_product():
    from agent.core.cooperation import SWAP_VELOCITY, swap_velocity

    rng = np.random.default_rng(3)
    for _ in range(50):
        P = _spd(rng, 4) * rng.uniform(0.01, 100.0)
        np.testing.assert_array_equal(swap_velocity(P), SWAP_VELOCITY @ P @ SWAP_VELOCITY)


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_the_cholesky_check_in_floats_keeps_numpys_verdict(seed):
    from agent.core.checks import cholesky_succeeds

    rng = np.random.default_rng(seed)
    for _ in range(20):
        k = int(rng.integers(1, 6))
        M = rng.normal(size=(k, k))
        S = 0.5 * (M + M.T) + rng.uniform(-2.0, 2.0) * np.eye(k)
        low = float(np.linalg.eigvalsh(S)[0])
        shift = float(rng.uniform(0.0, 0.5))
        for given, verdict in ((0.0, low > 0.0), (shift, low > -shift)):
            if abs(low + given) < 1e-9:
                continue    # at the boundary either verdict is round-off
            # the symmetric part is what is judged: an antisymmetric addition changes nothing
            A = M - M.T
            assert cholesky_succeeds((S + A).ravel().tolist(), k, given) == verdict


def test_world_ranges_are_the_per_vessel_norms():
    """The world's ranges of one tick (all pairs at once) are np.linalg.norm of each vessel's row, as they
    were computed one vessel at a time."""
    positions = np.random.default_rng(5).uniform(-30.0, 30.0, (12, 2))
    differences = positions[None, :, :] - positions[:, None, :]
    distances = np.sqrt(np.add.reduce(differences * differences, axis=2))
    rows = distances[~np.eye(12, dtype=bool)].reshape(12, 11)
    for i, here in enumerate(positions):
        others = np.delete(positions, i, axis=0)
        np.testing.assert_array_equal(rows[i], np.linalg.norm(others - here, axis=1))


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_oscillator_uses_the_harmonics_coupling_gains_leaves_non_zero(seed):
    """oscillator_step's count of harmonics (floor(n/2), none for a zero gain) is where coupling_gains puts its
    first zero, and the step is the one computed with that list of gains (to the last bits of the sines: the
    step sums few terms with the C library's sine, many with numpy's)."""
    rng = np.random.default_rng(seed)
    neighbours = rng.uniform(-math.pi, math.pi, int(rng.integers(0, 60))).tolist()
    phase, gain = float(rng.uniform(-math.pi, math.pi)), float(rng.choice([0.0, 0.3, 1.0]))
    n = len(neighbours) + 1
    gains = coupling_gains(n, gain)
    used = gains.index(0.0) if 0.0 in gains else len(gains)
    assert used == (0 if gain == 0.0 else n // 2)
    coupling = 0.0
    if used:
        harmonics = np.arange(1.0, used + 1.0)
        sines = np.sin(harmonics[:, None] * (phase - np.asarray(neighbours, dtype=float)))
        terms = np.array(gains[:used]) / (harmonics * n) * np.cumsum(sines, axis=1)[:, -1]
        coupling = 0.0 + float(np.cumsum(terms)[-1])
    from agent.angles import wrap_angle
    expected = wrap_angle(phase + 0.1 * 0.1 + 0.1 * coupling)
    got = oscillator_step(phase, neighbours, 0.1, 0.1, gain)
    assert math.isclose(math.remainder(got - expected, 2 * math.pi), 0.0, abs_tol=1e-13)


# ----- issue 32: per-neighbour work skipped or built directly gives the same numbers -----

def _interval_of_every_neighbour(heading, turn, neighbours, guard, rate):
    """surge_interval's bounds taken over every neighbour, none skipped: each one's allowance divided by the
    share of the surge that goes towards it, ahead and astern, the sweep's largest cosine found by sampling
    the sweep densely and at its ends, and where it crosses the direction itself."""
    low, high = -math.inf, math.inf
    for px, py in neighbours:
        d = math.hypot(px, py)
        if d == 0.0:
            return 0.0, 0.0
        allowed = rate * max(d - guard, 0.0)
        beta = math.atan2(-py, -px)
        for sign, start in ((1, heading - beta), (-1, heading - beta + math.pi)):
            share = sweep_max_cos(start, turn)
            # the closed form is itself checked against a sampled sweep: the largest cosine is at an end or 1
            sampled = max(math.cos(start + a) for a in np.linspace(0.0, turn, 2001))
            assert share >= sampled - 1e-12 and (share == 1.0 or share == max(math.cos(start),
                                                                             math.cos(start + turn)))
            if share > 0.0:
                if sign > 0:
                    high = min(high, allowed / share)
                else:
                    low = max(low, -allowed / share)
    return low, high


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_separation_interval_skipping_far_neighbours_is_the_full_one(seed):
    """surge_interval skips a neighbour whose allowance cannot tighten the interval kept: the interval is
    bit for bit the one taken over every neighbour (a fleet of 1-60 near and far neighbours)."""
    rng = np.random.default_rng(seed)
    count = int(rng.integers(1, 60))
    neighbours = [tuple((rng.normal(size=2) * rng.choice([1.0, 5.0, 30.0])).tolist()) for _ in range(count)]
    heading, turn = float(rng.uniform(-math.pi, math.pi)), float(rng.uniform(-0.3, 0.3))
    guard, rate = float(rng.uniform(1.0, 4.0)), 0.04
    assert surge_interval(heading, turn, neighbours, guard, rate) == _interval_of_every_neighbour(
        heading, turn, neighbours, guard, rate)


@pytest.mark.parametrize("values", [(1.0, 0.2, 2.0), (1e10, -1e10, 1e10), (1e10, 0.0, 1.0000001e10),
                                    (math.nan, 0.0, 1.0), (1.0, math.inf, 1.0), (-2e10, 0.0, 1.0)])
def test_a_shared_pair_estimate_is_bounded_as_numpy_bounds_it(values):
    """_shared_estimate leaves out a P_ij with an element beyond MAX_SHARED_VARIANCE, or NaN, as
    np.all(np.abs(P) <= bound) does, and otherwise carries p^_ij, P_ij and the epoch."""
    from types import SimpleNamespace

    from agent.core.step import MAX_SHARED_VARIANCE, _shared_estimate

    p11, p12, p22 = values
    track = SimpleNamespace(estimator=SimpleNamespace(moments=lambda: (1.5, -2.5, p11, p12, p22)), epoch=2_300_000)
    carried = _shared_estimate(track)
    matrix = np.array([[p11, p12], [p12, p22]])
    if not np.all(np.abs(matrix) <= MAX_SHARED_VARIANCE):
        assert carried is None
    else:
        assert carried == (1.5, -2.5, p11, p12, p22, 2.3)


def test_a_neighbour_record_built_directly_is_the_constructors():
    """neighbour_record takes every field of NeighbourRecord and gives the record its constructor gives:
    the same fields in the same order, the same objects, equal, and as frozen."""
    import dataclasses
    import inspect

    from agent.core.records import NeighbourRecord, neighbour_record

    names = [f.name for f in dataclasses.fields(NeighbourRecord)]
    assert list(inspect.signature(neighbour_record).parameters) == names
    values = dict(zip(names, (np.array([1.0, 2.0]), np.eye(2), 0.3, 4, 1, 2, ((0.3, 5.0, None),), True,
                              (0.1, 0.4), "mirror-ambiguous")))
    built, constructed = neighbour_record(**values), NeighbourRecord(**values)
    assert type(built) is NeighbourRecord
    assert list(vars(built)) == list(vars(constructed)) == names
    assert all(getattr(built, name) is value for name, value in values.items())
    assert repr(built) == repr(constructed)
    with pytest.raises(dataclasses.FrozenInstanceError):
        built.epoch = 1.0


def test_an_accepted_outcome_built_directly_is_the_constructors():
    """accepted_outcome sets every slot of UpdateOutcome: equal to the constructor's, field by field."""
    import dataclasses

    from agent.core.estimators.base import UpdateOutcome, accepted_outcome

    built = accepted_outcome(3, -0.25, 1.5, 0.75, "fix dropped")
    assert type(built) is UpdateOutcome
    assert built == UpdateOutcome(accepted=True, reason="fix dropped", iterations=3, innovation=-0.25,
                                  innovation_variance=1.5, weight=0.75, noise_scale=1.0)
    assert dataclasses.asdict(accepted_outcome(1, 0.0, 2.0, 1.0)) == {
        "accepted": True, "reason": "", "iterations": 1, "innovation": 0.0, "innovation_variance": 2.0,
        "weight": 1.0, "noise_scale": 1.0}
    with pytest.raises(dataclasses.FrozenInstanceError):
        built.weight = 0.0
