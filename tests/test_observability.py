"""Pair observability (agent/core/observability.py): the path spread against hand values, the verdicts of
parallel, straight and turning relative motion through the tick, the record, the status, the log, the snapshot
and `usv-log summary`'s table."""

from __future__ import annotations

import cmath
import json
import math

import numpy as np
import orjson
import pytest

from agent.contract import Status, decode
from agent.core.build import InitialEstimates, initial_state
from agent.core.observability import (
    MIRROR_AMBIGUOUS,
    OBSERVABLE,
    UNOBSERVABLE,
    PathSpread,
    eigenvalues,
    verdict,
)
from agent.core.params import AgentParams
from agent.core.records import OdometryReading, Share, TickInputs
from agent.core.snapshot import state_from_json, state_to_json
from agent.core.step import step
from agent.runtime.log_schema import Estimates
from agent.runtime.mcap_log import read_messages
from mission_log.summary import pair_observability, summary_markdown

DT = 0.1


def spread_of(points, tau=math.inf, dt=DT) -> PathSpread:
    """The spread of a path given by its points, one range epoch every `dt`."""
    spread = PathSpread()
    previous = points[0]
    spread.add(0.0, 0.0, 0.0, tau)
    for point in points[1:]:
        spread.add(point[0] - previous[0], point[1] - previous[1], dt, tau)
        previous = point
    return spread


# ----- the kernel, by hand -----
def test_no_relative_motion_has_no_spread():
    assert spread_of([(0.0, 0.0)] * 50).eigenvalues() == (0.0, 0.0)
    assert PathSpread().eigenvalues() == (0.0, 0.0)


def test_a_straight_path_has_a_zero_smallest_eigenvalue():
    # Ten points 1 m apart along (3, 4)/5, even weights: the variance along the line is (N^2 - 1)/12.
    points = [(0.6 * k, 0.8 * k) for k in range(10)]
    low, high = spread_of(points).eigenvalues()
    assert low == pytest.approx(0.0, abs=1e-12)
    assert high == pytest.approx((10**2 - 1) / 12, rel=1e-12)


def test_a_full_circle_has_equal_eigenvalues_of_half_the_radius_squared():
    rho, n = 2.0, 36
    points = [(rho * math.cos(2 * math.pi * k / n), rho * math.sin(2 * math.pi * k / n)) for k in range(n)]
    low, high = spread_of(points).eigenvalues()
    assert low == pytest.approx(rho**2 / 2, rel=1e-12) and high == pytest.approx(rho**2 / 2, rel=1e-12)


def test_a_pair_in_formation_gives_the_closed_form_of_the_docstring():
    """p_ij turning at omega* with |p_ij| = rho, forgotten with tau: the discrete sum exactly, and the
    continuous-time form of the module docstring to the sampling's 1e-5."""
    rho, omega, tau = 7.0, math.pi / 30, 10.0
    points = [(rho * math.cos(omega * k * DT), rho * math.sin(omega * k * DT)) for k in range(3001)]
    low, high = spread_of(points, tau).eigenvalues()
    # Discrete: weights lambda^k, lambda = exp(-dt / tau); E[z] and E[z^2] relative to the current point.
    lam, turn = math.exp(-DT / tau), cmath.exp(-1j * omega * DT)
    mean, square = (1 - lam) / (1 - lam * turn), (1 - lam) / (1 - lam * turn**2)
    total, circular = rho**2 * (1 - abs(mean) ** 2), abs(rho**2 * (square - mean**2))
    assert low == pytest.approx((total - circular) / 2, rel=1e-9)
    assert high == pytest.approx((total + circular) / 2, rel=1e-9)
    a = omega * tau
    base = rho**2 / 2 * a * a / (1 + a * a)
    assert low == pytest.approx(base * (1 - 1 / math.sqrt(1 + 4 * a * a)), rel=1e-4)
    assert high == pytest.approx(base * (1 + 1 / math.sqrt(1 + 4 * a * a)), rel=1e-4)


def test_the_forgotten_spread_is_the_weighted_covariance_wherever_the_path_is():
    rng = np.random.default_rng(3)
    steps = rng.normal(size=(200, 2))
    gaps = rng.uniform(0.05, 0.3, size=200)
    for offset in (0.0, 1e6):       # far from its origin the running form loses nothing
        spread = PathSpread()
        spread.add(offset, -offset, 0.0, 5.0)
        for (dx, dy), gap in zip(steps, gaps, strict=True):
            spread.add(dx, dy, gap, 5.0)
        path = np.cumsum(np.vstack([[0.0, 0.0], steps]), axis=0)
        age = np.concatenate([np.cumsum(gaps[::-1])[::-1], [0.0]])    # seconds before the last epoch
        weights = np.exp(-age / 5.0)
        centred = path - np.average(path, axis=0, weights=weights)
        expected = np.linalg.eigvalsh((weights[:, None] * centred).T @ centred / weights.sum())
        np.testing.assert_allclose(spread.eigenvalues(), expected, rtol=1e-9)


def test_eigenvalues_and_verdicts():
    assert eigenvalues(2.0, 0.0, 1.0) == (1.0, 2.0)
    assert eigenvalues(1.0, 1.0, 1.0) == pytest.approx((0.0, 2.0))
    assert eigenvalues(1.0, 1.0 + 1e-12, 1.0)[0] == 0.0          # round-off never gives a negative spread
    assert verdict(0.0, 0.0, 0.25) == UNOBSERVABLE
    assert verdict(0.0, 0.0625, 0.25) == MIRROR_AMBIGUOUS         # w_min^2 = 0.0625 m^2
    assert verdict(0.0624, 1.0, 0.25) == MIRROR_AMBIGUOUS
    assert verdict(0.0625, 1.0, 0.25) == OBSERVABLE


def test_a_snapshot_keeps_the_spread():
    spread = spread_of([(math.cos(0.1 * k), math.sin(0.2 * k)) for k in range(40)], tau=3.0)
    again = PathSpread()
    again.restore_state(json.loads(json.dumps(spread.export_state())))
    assert again.export_state() == spread.export_state()


# ----- through the tick: parallel, straight and turning relative motion -----
def world_paths(motion: str, ticks: int) -> tuple[np.ndarray, np.ndarray]:
    """True positions of vessel 1 and of its neighbour 2 (10 m to the north at the start)."""
    t = np.arange(ticks)[:, None] * DT
    if motion == "parallel":
        one, two = t * [1.0, 0.0], [0.0, 10.0] + t * [1.0, 0.0]
    elif motion == "straight":
        one, two = t * [1.0, 0.0], np.tile([0.0, 10.0], (ticks, 1))
    else:  # turning: vessel 1 on a circle of 5 m at 0.3 rad/s
        one = 5.0 * np.column_stack([np.sin(0.3 * t[:, 0]), 1.0 - np.cos(0.3 * t[:, 0])])
        two = np.tile([0.0, 10.0], (ticks, 1))
    return one, two


def inputs_of(motion: str, ticks: int):
    """The tick inputs of vessel 1: its odometry, the range to 2, and 2's share of the tick before."""
    one, two = world_paths(motion, ticks)
    for k in range(ticks):
        t = k * DT
        share = None if k == 0 else Share("2", OdometryReading(t - DT, two[k - 1] - two[0], 0.0),
                                          (two[k] - two[k - 1]) / DT, 0.0)
        yield TickInputs(time=t, odometry=OdometryReading(t, one[k] - one[0], 0.0),
                         ranges={"2": float(np.hypot(*(one[k] - two[k])))},
                         shares={} if share is None else {"2": share}, bearing=np.array([1.0, 0.0]))


def start(params: AgentParams):
    return initial_state("1", params, InitialEstimates(target=(5.0, 0.0, 0.0, 0.0), neighbours={"2": (0.0, -10.0)},
                                                       neighbour_variance=0.04))


@pytest.mark.parametrize("motion, expected", [("parallel", UNOBSERVABLE), ("straight", MIRROR_AMBIGUOUS),
                                              ("turning", OBSERVABLE)])
def test_the_record_says_what_the_relative_motion_lets_the_ranges_tell(motion, expected):
    params = AgentParams()
    state = start(params)
    record = None
    for inputs in inputs_of(motion, 150):
        state, output = step(params, state, inputs)
        record = output.record.neighbours.get("2", record)   # from the first share on
    low, high = record.excitation
    assert record.observability == expected
    if motion == "parallel":
        assert (low, high) == (0.0, 0.0)             # the relative displacement is exactly zero
    elif motion == "straight":
        assert low == 0.0 and high > 1.0             # every displacement along x: a line
    else:
        assert low > 0.25**2


def test_a_state_saved_mid_run_continues_the_spread_bit_for_bit():
    params = AgentParams()
    ticks = list(inputs_of("turning", 120))
    state = start(params)
    original = []
    for inputs in ticks:
        state, output = step(params, state, inputs)
        original.append(output.record.neighbours.get("2"))
    state = start(params)
    again = []
    for k, inputs in enumerate(ticks):
        if k == 60:
            state = state_from_json(orjson.loads(orjson.dumps(state_to_json(state),
                                                               option=orjson.OPT_SERIALIZE_NUMPY)), params)
        state, output = step(params, state, inputs)
        again.append(output.record.neighbours.get("2"))
    assert [n and n.excitation for n in again] == [n and n.excitation for n in original]
    assert original[-1].observability == OBSERVABLE


def test_a_version_2_snapshot_reads_with_a_fresh_spread():
    params = AgentParams()
    state = start(params)
    for inputs in inputs_of("turning", 40):
        state, _ = step(params, state, inputs)
    data = orjson.loads(orjson.dumps(state_to_json(state), option=orjson.OPT_SERIALIZE_NUMPY))
    data["version"] = 2
    for track in data["tracks"].values():
        del track["spread"]
    restored = state_from_json(data, params)
    assert restored.tracks["2"].spread.eigenvalues() == (0.0, 0.0)
    np.testing.assert_array_equal(restored.tracks["2"].estimator.position, state.tracks["2"].estimator.position)


# ----- the agent process: status and log -----
def test_the_status_and_the_log_carry_each_pairs_observability(tmp_path):
    from agent.shell.node import AgentNode
    from agent.shell.settings import NodeSettings

    class Sink(list):
        def put(self, payload):
            self.append(payload)

    params = AgentParams()
    agent = AgentNode("1", NodeSettings(clock="wall", id_check=0, log=str(tmp_path / "agent-{vessel}.mcap")),
                      start(params))
    agent.recorder.open()
    sinks = {"cmd": Sink(), "share": Sink(), "status": Sink()}
    for inputs in inputs_of("straight", 60):
        agent.gate.snapshot = lambda now, inputs=inputs: inputs
        agent._tick(sinks)
    agent.recorder.close()
    status = decode(Status, sinks["status"][-1])[0]
    assert status.health["pairs_mirror_ambiguous"] == 1 and status.health["pairs_unobservable"] == 0
    assert status.weakest_pair.neighbour == "2" and status.weakest_pair.observability == MIRROR_AMBIGUOUS
    assert status.weakest_pair.excitation == 0.0
    estimates = [m for topic, _, m in read_messages(tmp_path / "agent-1.mcap") if topic == "/1/estimates"]
    assert len(estimates) == 60
    for message in estimates:
        Estimates.model_validate(message)
    last = estimates[-1]["neighbours"]["2"]
    assert last["observability"] == MIRROR_AMBIGUOUS and last["excitation"][0] == 0.0
    assert last["excitation"][1] == pytest.approx(agent.state.tracks["2"].spread.eigenvalues()[1])


# ----- usv-log summary -----
def logged(time: float, verdicts: dict[str, str]) -> tuple[int, dict]:
    return round(time * 1e9), {"neighbours": {j: {"observability": v, "excitation": [0.1, 2.0]}
                                              for j, v in verdicts.items()}}


def test_the_summary_gives_the_share_observable_and_the_spans_not():
    verdicts = ([UNOBSERVABLE] * 2 + [MIRROR_AMBIGUOUS] * 3 + [OBSERVABLE] * 4 + [MIRROR_AMBIGUOUS] * 1
                + [OBSERVABLE] * 2)
    estimates = [logged(0.1 * k, {"2": v}) for k, v in enumerate(verdicts)]
    estimates.append((round(1.2e9), {"neighbours": {"3": {"position": [1.0, 0.0]}}}))   # format 4: not recorded
    pairs = pair_observability(estimates)
    assert list(pairs) == ["2"]
    pair = pairs["2"]
    assert pair["ticks"] == 12 and pair["observable_fraction"] == pytest.approx(6 / 12)
    assert pair["first_observable_s"] == pytest.approx(0.5)
    spans = [(pytest.approx(a), pytest.approx(b), v) for a, b, v in pair["not_observable"]]
    assert spans == [(0.0, 0.2, UNOBSERVABLE), (0.2, 0.5, MIRROR_AMBIGUOUS), (0.9, 1.0, MIRROR_AMBIGUOUS)]
    assert pair["final"] == OBSERVABLE and pair["final_excitation"] == [0.1, 2.0]
    table = summary_markdown({"source": "x", "vessels": {"1": {
        "file": "x", "unfinished": False, "from_s": 0.0, "to_s": 1.1, "ticks": 12, "ticks_with_estimates": 12,
        "refused": {}, "overruns": 0, "cpu_ms_per_tick": None, "topics": {}, "saturation_s": {}, "core_health": {},
        "health_over_time": [], "observability": pairs}}, "sim": None})
    assert ("| 2 | 50 | 0.5 | observable | 0.10, 2.00 | 0.0–0.2 unobservable, 0.2–0.5 mirror-ambiguous, "
            "0.9–1.0 mirror-ambiguous |") in table
