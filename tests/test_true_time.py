"""The paper's estimate errors compare each estimate with the truth at the true time it refers to: a vessel's
stamp through its clock model (`/bridge/sea`), then the truth interpolated there (mission_log/series.py).

The logs here are built by hand (no MCAP files, no simulation). The motion is at constant velocity, so the
truth at any time is known in closed form, and an estimate that is exactly right at its true time must give
no error at all. Clock values are the sea trial's bounds: offset 50 ms, drift 20 ppm.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mission_log.metrics import truth_metrics
from mission_log.reader import Log, RunLog, VesselLog
from mission_log.series import (
    Beliefs,
    ClockModel,
    TruthSeries,
    beliefs_of,
    estimate_errors,
    take,
    true_time_ns,
    truth_of,
)
from sim_bridge.world import VesselClock

EPOCH_NS = 1_796_133_488_126_507_746        # a Unix time in ns, as the sea mode's epoch is
TICK_NS = 100_000_000                         # the bridge's truth: 10 Hz
TICKS = 51                                    # 0 to 5 s
OFFSET_S, DRIFT = 0.05, 20e-6                 # vessel 1's clock
PHASE_NS = 37_000_000                         # vessel 1's odometry is measured 37 ms after each truth tick

# Constant velocity (m, m/s): vessel 1 and 2 at 0.5 m/s, the target as in the paper.
START = {"1": np.array([-6.0, -7.0]), "2": np.array([6.0, 6.0]), "target": np.array([1.0, 1.0])}
VELOCITY = {"1": np.array([0.4, 0.3]), "2": np.array([-0.3, 0.4]), "target": np.array([0.5, 0.0])}


def position(body: str, t: float) -> np.ndarray:
    return START[body] + VELOCITY[body] * t


def truth_series(clocks: dict[str, ClockModel] | None = None, epoch_ns: int = EPOCH_NS) -> TruthSeries:
    """The truth as the sea mode logs it: at epoch + k tick."""
    times = np.arange(TICKS) * 0.1
    return TruthSeries(
        t_ns=epoch_ns + np.arange(TICKS, dtype=np.int64) * TICK_NS,
        target=np.array([position("target", t) for t in times]),
        vessels={v: np.array([position(v, t) for t in times]) for v in ("1", "2")},
        clocks=clocks or {},
    )


def vessel_1_stamp_ns(true_ns: int) -> int:
    """Vessel 1's stamp of true time t (ns since the epoch), by hand: c(t) = t + 0.05 s + 20e-6 t. The true
    times are whole multiples of 50 us, so 20e-6 t is a whole number of ns and the stamp is exact."""
    assert true_ns % 50_000 == 0
    return EPOCH_NS + true_ns + 50_000_000 + true_ns // 50_000


def measured_ns(k: int) -> int:
    return k * TICK_NS + PHASE_NS


# ----- the clock model -----------------------------------------------------------------------------------


@pytest.mark.parametrize("offset, drift", [(OFFSET_S, DRIFT), (-OFFSET_S, -DRIFT), (0.0123456789, 7.3e-6)])
def test_the_inverse_clock_undoes_the_sim_bridges_vessel_clock(offset, drift):
    clock = VesselClock(offset, drift)
    model = ClockModel(EPOCH_NS, offset, drift)
    times = [0.0, 0.1, 0.537, 12.345678901, 600.0, 3600.0 + 1e-9]
    stamps = np.array([clock.stamp_ns(t, EPOCH_NS) for t in times], dtype=np.int64)
    back = true_time_ns(stamps, model)
    expected = np.array([EPOCH_NS + round(t * 1e9) for t in times], dtype=np.int64)
    assert back.dtype == np.int64
    # The stamp is rounded to a ns, and so is its inverse: at most 1 ns off in all.
    assert np.max(np.abs(back - expected)) <= 1
    # One stamp at a time, as an array of one.
    assert abs(int(true_time_ns(stamps[3], model)) - int(expected[3])) <= 1


def test_the_inverse_clock_on_hand_worked_stamps():
    model = ClockModel(EPOCH_NS, OFFSET_S, DRIFT)
    true_ns = np.array([measured_ns(k) for k in range(TICKS)], dtype=np.int64)
    stamps = np.array([vessel_1_stamp_ns(int(t)) for t in true_ns], dtype=np.int64)
    np.testing.assert_array_equal(true_time_ns(stamps, model), EPOCH_NS + true_ns)
    # 50 ms of offset and 20 ppm: the stamp runs 50.1 ms ahead at 5.037 s.
    assert (stamps[-1] - EPOCH_NS - true_ns[-1]) == 50_000_000 + 100_740


def test_without_a_clock_model_the_stamps_are_the_true_times():
    stamps = np.array([0, 1, TICK_NS, EPOCH_NS, EPOCH_NS + 123_456_789], dtype=np.int64)
    found = true_time_ns(stamps, None)
    assert found.dtype == np.int64
    np.testing.assert_array_equal(found, stamps)
    found[0] = 99                                   # a copy: the caller's stamps stay as they were
    assert stamps[0] == 0


# ----- the truth between its ticks ----------------------------------------------------------------------


def test_the_truth_is_interpolated_linearly_and_nan_where_unknown():
    truth = TruthSeries(t_ns=np.array([0, 100, 200, 300], dtype=np.int64),
                        target=np.array([[0.0, 0.0], [1.0, 2.0], [3.0, 2.0], [3.0, 5.0]]),
                        vessels={"1": np.array([[0.3, 0.7], [np.nan, np.nan], [1.0, 1.0], [2.0, 1.0]])})
    at = truth.at(truth.target, [0, 25, 100, 150, 290, 300])
    np.testing.assert_allclose(at, [[0.0, 0.0], [0.25, 0.5], [1.0, 2.0], [2.0, 2.0], [3.0, 4.7], [3.0, 5.0]],
                               rtol=0, atol=1e-15)
    assert at[0].tolist() == [0.0, 0.0] and at[2].tolist() == [1.0, 2.0]     # a tick's sample as it is
    assert np.isnan(truth.at(truth.target, [-1, 301])).all()                  # outside the span
    vessel = truth.at(truth.vessels["1"], [0, 50, 100, 150, 200, 250])
    assert vessel[0].tolist() == [0.3, 0.7] and vessel[4].tolist() == [1.0, 1.0]
    assert np.isnan(vessel[1:4]).all()                    # absent at a sample on either side (or at it)
    np.testing.assert_allclose(vessel[5], [1.5, 1.0], rtol=0, atol=1e-15)
    assert truth.at(truth.target, np.array([], dtype=np.int64)).shape == (0, 2)


def test_unix_time_stamps_interpolate_without_losing_precision():
    truth = truth_series()
    middle = EPOCH_NS + 2 * TICK_NS + 1      # 1 ns after a tick: a float of the Unix time would not see it
    expected = position("1", 0.2 + 1e-9)
    np.testing.assert_allclose(truth.at(truth.vessels["1"], [middle])[0], expected, rtol=0, atol=1e-12)


# ----- the errors -----------------------------------------------------------------------------------------


def exact_beliefs(log_delay_ns: int = 3_000_000) -> Beliefs:
    """Vessel 1's estimates, exactly right at the true times they refer to: its odometry is measured 37 ms
    after each truth tick and stamped on its own clock; the agent logs the tick on the wall clock 3 ms later."""
    true_s = [measured_ns(k) * 1e-9 for k in range(TICKS - 1)]
    return Beliefs(
        t_ns=np.array([EPOCH_NS + measured_ns(k) + log_delay_ns for k in range(TICKS - 1)], dtype=np.int64),
        target=np.array([position("1", t) - position("target", t) for t in true_s]),
        neighbours={"2": np.array([position("1", t) - position("2", t) for t in true_s])},
        stamp_ns=np.array([vessel_1_stamp_ns(measured_ns(k)) for k in range(TICKS - 1)], dtype=np.int64),
    )


def nearest_tick_errors(beliefs: Beliefs, truth: TruthSeries) -> tuple[np.ndarray, np.ndarray]:
    """The method before: each estimate against the truth tick nearest its stamp, as it is."""
    index = truth.index(beliefs.stamps)
    p_i = take(truth.vessels["1"], index)
    e_ij = np.linalg.norm(beliefs.neighbours["2"] - (p_i - take(truth.vessels["2"], index)), axis=1)
    e_io = np.linalg.norm(beliefs.target - (p_i - take(truth.target, index)), axis=1)
    return e_ij, e_io


def test_an_estimate_right_at_its_true_time_has_no_error():
    truth = truth_series({"1": ClockModel(EPOCH_NS, OFFSET_S, DRIFT)})
    beliefs = exact_beliefs()
    e_ij, e_io = estimate_errors("1", beliefs, truth)
    # Each estimate (37 ms after tick k) counts at tick k; the last tick has none.
    np.testing.assert_array_equal(np.flatnonzero(np.isfinite(e_ij)), np.arange(TICKS - 1))
    np.testing.assert_array_equal(np.flatnonzero(np.isfinite(e_io)), np.arange(TICKS - 1))
    assert np.nanmax(e_ij) < 1e-9 and np.nanmax(e_io) < 1e-9

    # The nearest-tick method compares it with the truth 63 ms later: the stamp reads 87 ms after tick k
    # (37 ms + 50 ms offset, + 20 ppm), nearest to tick k + 1. At 0.5 m/s that is centimetres.
    old_ij, old_io = nearest_tick_errors(beliefs, truth)
    relative_ij = np.linalg.norm(VELOCITY["1"] - VELOCITY["2"])        # 0.707 m/s
    relative_io = np.linalg.norm(VELOCITY["1"] - VELOCITY["target"])   # 0.316 m/s
    np.testing.assert_allclose(old_ij, relative_ij * 0.063, rtol=1e-9)
    np.testing.assert_allclose(old_io, relative_io * 0.063, rtol=1e-9)
    assert old_ij.min() > 0.04


def test_a_vessel_without_a_clock_model_is_taken_at_its_stamp():
    # The same estimates with no clock model for vessel 1: its stamps are read as true times, 50 ms and
    # more late, so the estimates no longer match the truth there.
    e_ij, _ = estimate_errors("1", exact_beliefs(), truth_series({}))
    assert np.nanmin(e_ij) > 0.03


def test_lockstep_errors_are_unchanged_bit_for_bit():
    """In lockstep every estimate is stamped on a truth tick and there is no clock model: the errors are
    exactly the nearest-tick ones, with a vessel absent for a while and a target not yet seen."""
    rng = np.random.default_rng(7)
    n = 40
    t_ns = np.arange(n, dtype=np.int64) * TICK_NS
    vessels = {v: rng.normal(0.0, 5.0, (n, 2)) for v in ("1", "2", "3")}
    vessels["3"][10:20] = np.nan
    truth = TruthSeries(t_ns=t_ns, target=rng.normal(0.0, 5.0, (n, 2)), vessels=vessels)
    ticks = np.arange(2, n)
    target = rng.normal(0.0, 5.0, (len(ticks), 2))
    target[:5] = np.nan
    neighbours = {"2": rng.normal(0.0, 5.0, (len(ticks), 2)), "3": rng.normal(0.0, 5.0, (len(ticks), 2))}
    for stamps in (None, t_ns[ticks].copy()):
        beliefs = Beliefs(t_ns[ticks], target, neighbours, stamp_ns=stamps)
        e_ij, e_io = estimate_errors("1", beliefs, truth)
        index = truth.index(beliefs.t_ns)
        p_i = take(truth.vessels["1"], index)
        worst = np.full(len(ticks), np.nan)
        for j, estimate in neighbours.items():
            worst = np.fmax(worst, np.linalg.norm(estimate - (p_i - take(truth.vessels[j], index)), axis=1))
        old_io = np.linalg.norm(target - (p_i - take(truth.target, index)), axis=1)
        expected_ij, expected_io = np.full(n, np.nan), np.full(n, np.nan)
        expected_ij[ticks], expected_io[ticks] = worst, old_io
        assert np.array_equal(e_ij, expected_ij, equal_nan=True)
        assert np.array_equal(e_io, expected_io, equal_nan=True)


# ----- from the logs ---------------------------------------------------------------------------------------


CLOCKS = {"1": (OFFSET_S, DRIFT), "2": (-OFFSET_S, -DRIFT)}


def sea_run(with_clock_model: bool = True) -> RunLog:
    """A sea-mode run of two vessels, as the bridge and the agents log it: the truth at epoch + t, the clock
    model on `/bridge/sea`, and each vessel's exact estimates with their tick's time (its odometry stamp, in
    seconds on its own clock) logged on the wall clock a few ms after they were measured."""
    truth = []
    for k in range(TICKS):
        t = k * 0.1
        truth.append((EPOCH_NS + k * TICK_NS, {
            "time": t, "target": position("target", t).tolist(), "target_velocity": VELOCITY["target"].tolist(),
            "vessels": {v: {"position": position(v, t).tolist(), "heading": 0.0} for v in ("1", "2")}}))
    sea = {"epoch_ns": EPOCH_NS,
           "clocks": {v: {"offset_s": offset, "drift_ppm": drift * 1e6} for v, (offset, drift) in CLOCKS.items()}}
    topics = {"/truth": truth, **({"/bridge/sea": [(EPOCH_NS, sea)]} if with_clock_model else {})}
    sim = Log(Path("sim.mcap"), {}, topics)
    vessels = {}
    for vid, other, phase_ns in (("1", "2", 37_000_000), ("2", "1", 81_000_000)):
        clock = VesselClock(*CLOCKS[vid])
        estimates = []
        for k in range(TICKS - 1):
            t = (k * TICK_NS + phase_ns) * 1e-9
            stamp = clock.stamp_ns(t, EPOCH_NS)
            estimates.append((EPOCH_NS + round(t * 1e9) + 4_000_000, {
                "time": stamp * 1e-9,      # as the agent logs it: seconds(stamp_ns)
                "target_state": [*(position(vid, t) - position("target", t)), 0.0, 0.0],
                "neighbours": {other: {"position": (position(vid, t) - position(other, t)).tolist()}}}))
        vessels[vid] = VesselLog(Path(f"agent-{vid}.mcap"), {"vessel": vid}, {f"/{vid}/estimates": estimates},
                                 vessel=vid)
    return RunLog("synthetic sea run", vessels, sim)


def test_the_sea_runs_metrics_see_each_vessels_clock():
    run = sea_run()
    truth = truth_of(run.sim)
    assert truth.clocks == {"1": ClockModel(EPOCH_NS, OFFSET_S, pytest.approx(DRIFT, rel=1e-12)),
                            "2": ClockModel(EPOCH_NS, -OFFSET_S, pytest.approx(-DRIFT, rel=1e-12))}
    stamps = beliefs_of(run.vessels["1"]).stamps
    assert abs(int(stamps[0]) - VesselClock(*CLOCKS["1"]).stamp_ns(0.037, EPOCH_NS)) <= 256   # a float's seconds
    metrics = truth_metrics(run, radius=5.0)
    assert metrics["start_ns"] == EPOCH_NS
    # The logged time is a float of a Unix time in seconds (a quarter of a microsecond apart): at 0.7 m/s
    # that is well under a micrometre.
    assert metrics["mean_e_ij"] < 1e-6 and metrics["mean_e_io"] < 1e-6

    # Without the clock model the same estimates are compared 50 ms off: centimetres.
    assert truth_metrics(sea_run(with_clock_model=False), radius=5.0)["mean_e_ij"] > 0.02


def test_a_malformed_clock_model_leaves_the_stamps_as_they_are():
    run = sea_run()
    run.sim.topics["/bridge/sea"] = [(EPOCH_NS, {"epoch_ns": EPOCH_NS, "clocks": {
        "1": {"offset_s": "x", "drift_ppm": 20.0}, "2": {"offset_s": -OFFSET_S, "drift_ppm": -20.0}}})]
    assert list(truth_of(run.sim).clocks) == ["2"]
    metrics = truth_metrics(run, radius=5.0)
    assert math.isfinite(metrics["mean_e_ij"]) and metrics["mean_e_ij"] > 0.02   # vessel 1 taken at its stamps
    run.sim.topics["/bridge/sea"] = [(EPOCH_NS, {"clocks": {}})]                   # no epoch
    assert truth_of(run.sim).clocks == {}
