"""`usv-log metrics` from GNSS (mission_log/gnss_truth.py): a field trial scored as a simulation is.

The acceptance test is a simulated field trial: an in-process run's ground truth becomes each vessel's and the
target tag's GGA sentences (sim_bridge/simulated_gnss.py, seeded noise, antennas off the reference point),
read and logged by the driver bridge (gnss.log), and the run is scored both ways. The bounds are derived,
with w_i ~ N(0, sigma^2 I) a fix's noise (independent between fixes), n vessels and K ticks:

- e_c: |e_c^G(k) - e_c^T(k)| <= |mean_i w_i - w_o| = |d_k| (triangle inequality), d_k ~ N(0, s^2 I) with
  s^2 = sigma^2 (1 + 1/n); |d_k| is Rayleigh: mean s sqrt(pi/2), standard deviation s sqrt(2 - pi/2);
- e_ij: |e_ij^G(k) - e_ij^T(k)| <= max_ij |w_i - w_j| <= 2 max_i |w_i|;
- e_io: |e_io^G(k) - e_io^T(k)| <= max_i |w_i - w_o| <= max_i |w_i| + |w_o|;
  E max_i |w_i| = sigma sqrt(pi/2) sum_k (-1)^(k+1) C(n, k) / sqrt(k) (the maximum of n Rayleighs, by
  inclusion-exclusion), its standard deviation at most sqrt(E max^2) <= sigma sqrt(2 n);
- so each mean over K ticks differs by at most the per-tick bound's mean plus 4 of its standard deviations
  over sqrt(K) (the ticks' noises are independent: by the central limit theorem, exceeded with probability
  about 3e-5), plus 1 mm for the format (7 decimals of a minute: <= 0.2 mm a coordinate) and the frames;
- settling: every radius moves by at most max |w_i - w_o|, under 6 sigma sqrt(2) at every tick (each
  exceeds it with probability exp(-18)), so the GNSS settling time lies between the truth's with the band
  widened and narrowed by that much.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("pymap3d")

from agent.runtime.mcap_log import McapLog
from driver_bridge.node import DriverBridge, DriverSettings, GnssPort
from lab.harness.runner import run as run_in_process
from mission_log import cli
from mission_log.gnss_truth import gnss_truth
from mission_log.metrics import SETTLING_BAND, run_metrics, settling_time
from mission_log.reader import LogError, load_run
from sim_bridge.scenario import select_scenario
from sim_bridge.simulated_gnss import SimulatedReceiver, plain, rtk, simulated_gga

ORIGIN = (59.9, 10.7)
TICK_NS = 100_000_000
RADIUS = 5.0
FORMAT_MARGIN = 1e-3     # m: the sentence's rounding (<= 0.2 mm a coordinate), the tangent planes (< 0.1 mm)
ANTENNAS = {"1": (0.6, -0.2), "2": (-0.4, 0.3), "3": (0.0, 0.5)}


class Discard:
    def put(self, payload: bytes) -> None:
        pass


def headings_of(positions: np.ndarray) -> np.ndarray:
    """(K, n) each vessel's heading along its track (the kinematic hull points where it goes)."""
    velocity = np.gradient(positions, axis=0)
    return np.arctan2(velocity[..., 1], velocity[..., 0])


def write_run(folder, trace, receiver: SimulatedReceiver | None, seed: int, with_sim: bool = True) -> None:
    """The trace as the logs of a field trial: each agent's estimates and odometry heading, the sim bridge's
    truth (`with_sim`), and with `receiver` each vessel's and the target tag's GGA through the driver's
    GNSS log."""
    psi = headings_of(trace.positions)
    ticks = [k * TICK_NS for k in range(len(trace.time))]
    if with_sim:
        with McapLog(folder / "sim.mcap", metadata={"scenario": "gnss"}) as sim:
            for k, t in enumerate(ticks):
                sim.log("/truth", {"target": trace.target[k].tolist(),
                                   "vessels": {v: {"position": trace.positions[k, n].tolist()}
                                               for n, v in enumerate(trace.vessels)}}, t)
    for n, v in enumerate(trace.vessels):
        with McapLog(folder / f"agent-{v}.mcap", metadata={"vessel": v}) as agent:
            for k, t in enumerate(ticks):
                odometry = {"stamp": k * 0.1, "position": [0.0, 0.0], "heading": float(psi[k, n])}
                agent.log(f"/{v}/inputs", {"time": k * 0.1, "odometry": odometry}, t)
                # as an agent logs them: a neighbour it has no estimate of is left out, no target is null
                neighbours = {j: {"position": trace.relative[k, n, m].tolist()}
                              for m, j in enumerate(trace.vessels)
                              if m != n and np.isfinite(trace.relative[k, n, m]).all()}
                target = trace.estimates[k, n]
                known = target.tolist() if np.isfinite(target).all() else None
                estimates = {"time": k * 0.1, "neighbours": neighbours, "target_state": known}
                agent.log(f"/{v}/estimates", estimates, t)
    if receiver is None:
        return
    random = np.random.default_rng(seed)
    for n, v in [*enumerate(trace.vessels), (None, "target")]:
        antenna = (0.0, 0.0) if n is None else ANTENNAS[v]
        own = receiver.model_copy(update={"antenna": antenna})
        clock = iter(ticks)
        settings = DriverSettings(gnss=GnssPort(device="/dev/null", receiver={"antenna": antenna},
                                                log=str(folder / f"gnss-{v}.mcap")))
        bridge = DriverBridge(v, settings, clock_ns=lambda: next(clock))
        bridge.open_gnss_log()
        for k in range(len(ticks)):
            position, heading = (trace.target[k], 0.0) if n is None else (trace.positions[k, n], psi[k, n])
            sentence = simulated_gga(position, heading, 36000 + k * 0.1, own, random)
            bridge._on_gnss(sentence, {"truth/gnss": Discard()})
        bridge.gnss_log.close()
        assert bridge.published["truth/gnss"] == len(ticks) and not bridge.refusals()


def max_rayleigh_mean(n: int, sigma: float) -> float:
    return sigma * math.sqrt(math.pi / 2) * sum((-1) ** (k + 1) * math.comb(n, k) / math.sqrt(k)
                                                for k in range(1, n + 1))


def bounds(n: int, ticks: int, sigma: float) -> dict[str, float]:
    """The largest differences of the means the module's docstring derives."""
    spread = 4 / math.sqrt(ticks)
    s = sigma * math.sqrt(1 + 1 / n)
    rayleigh_sd = math.sqrt(2 - math.pi / 2)
    return {
        "mean_e_c": s * (math.sqrt(math.pi / 2) + spread * rayleigh_sd) + FORMAT_MARGIN,
        "mean_e_ij": 2 * (max_rayleigh_mean(n, sigma) + spread * sigma * math.sqrt(2 * n)) + FORMAT_MARGIN,
        "mean_e_io": (max_rayleigh_mean(n, sigma) + sigma * math.sqrt(math.pi / 2)
                      + spread * sigma * (math.sqrt(2 * n) + rayleigh_sd)) + FORMAT_MARGIN,
    }


def test_the_bound_of_the_maximum_of_rayleighs_against_a_closed_form_case():
    # n = 1: one Rayleigh, mean sigma sqrt(pi / 2); n = 2: sigma sqrt(pi / 2) (2 - 1 / sqrt 2).
    assert max_rayleigh_mean(1, 2.0) == pytest.approx(2.0 * 1.2533141373155001)
    assert max_rayleigh_mean(2, 1.0) == pytest.approx(1.2533141373155001 * (2 - 1 / math.sqrt(2)))
    draws = np.random.default_rng(0).normal(size=(200_000, 3, 2))
    largest = np.linalg.norm(draws, axis=2).max(axis=1)
    assert largest.mean() == pytest.approx(max_rayleigh_mean(3, 1.0), rel=0.01)


@pytest.fixture(scope="module", params=[5, 6])
def trace(request):
    _, scenario = select_scenario("tests/data/short_scenario.yaml")
    return run_in_process(scenario, request.param)


@pytest.mark.parametrize("make, seed", [(plain, 101), (rtk, 102)])
def test_a_simulated_field_trial_scores_from_gnss_as_from_the_truth_within_the_gnss_noise(
        trace, tmp_path, make, seed):
    receiver = make(ORIGIN)
    write_run(tmp_path, trace, receiver, seed)
    run = load_run(tmp_path)
    from_sim = run_metrics(run, truth="sim")["truth"]
    # the logs are the trace's: scored from the sim's truth they give the in-process runner's own figures
    for name in ("mean_e_ij", "mean_e_io", "mean_e_c"):
        assert from_sim[name] == pytest.approx(getattr(trace.metrics, name), abs=1e-12), name
    assert from_sim["settling_time"] == pytest.approx(trace.metrics.settling_time)
    from_gnss = run_metrics(run, truth="gnss")["truth"]
    assert from_gnss["source"] == "gnss" and from_gnss["target"] == "tagged (target)"
    assert from_gnss["ticks"] == from_sim["ticks"] == len(trace.time)
    assert from_gnss["vessels"] == trace.vessels
    limit = bounds(len(trace.vessels), len(trace.time), receiver.sigma)
    for name, bound in limit.items():
        assert abs(from_gnss[name] - from_sim[name]) <= bound, (name, from_gnss[name], from_sim[name], bound)
    # settling: between the truth's with the band widened and narrowed by the largest radius error
    worst = 6 * receiver.sigma * math.sqrt(2) + FORMAT_MARGIN
    early = settling_time(trace.time, trace.radii, RADIUS, SETTLING_BAND + worst / RADIUS)
    late = settling_time(trace.time, trace.radii, RADIUS, SETTLING_BAND - worst / RADIUS)
    measured = from_gnss["settling_time"]
    assert early is not None and (measured is None) <= (late is None)
    if measured is not None:
        assert early - 1e-9 <= measured <= (math.inf if late is None else late + 1e-9)
    if make is rtk:   # 2 cm: the band moves by 17 cm, and settling is found, near the truth's
        assert measured is not None and late is not None


def test_usv_log_metrics_scores_a_run_with_gnss_and_no_sim_from_the_gnss(trace, tmp_path, capsys):
    write_run(tmp_path, trace, rtk(ORIGIN), 9, with_sim=False)
    assert cli.main(["metrics", str(tmp_path), "--json", str(tmp_path / "m.json")]) == 0
    page = capsys.readouterr().out
    assert "Truth: the GNSS fixes (the target tagged (target)" in page and "3 vessels, 121 ticks" in page
    assert cli.main(["metrics", str(tmp_path), "--truth", "sim"]) == 2
    assert "--truth sim, but no sim bridge log" in capsys.readouterr().err


def fix_log(folder, owner: str, fixes: list[tuple[int, float, float]], antenna=(0.0, 0.0)) -> None:
    with McapLog(folder / f"gnss-{owner}.mcap", metadata={"gnss_of": owner}) as log:
        for t, lat, lon in fixes:
            log.log(f"usv/{owner}/truth/gnss", {"stamp_ns": t, "seq": 0, "sender": owner, "latitude": lat,
                                                "longitude": lon, "quality": 4, "antenna": list(antenna)}, t)


def test_gnss_positions_worked_by_hand(tmp_path):
    """At the equator 0.001 deg of latitude is 110.574 m north (the meridian's radius a (1 - e^2), see
    test_simulated_gnss). Vessel 1's antenna 1 m ahead and 0.5 m left, heading north (pi / 2, from its
    agent's odometry), is 1 m north and 0.5 m west of its reference point."""
    fix_log(tmp_path, "target", [(0, 0.0, 0.0), (TICK_NS, 0.0, 0.0)])
    fix_log(tmp_path, "1", [(0, 0.001, 0.0), (TICK_NS, 0.001, 0.0)], antenna=(1.0, 0.5))
    fix_log(tmp_path, "2", [(0, -0.001, 0.0), (TICK_NS, -0.001, 0.0)])
    with McapLog(tmp_path / "agent-1.mcap", metadata={"vessel": "1"}) as agent:
        odometry = {"stamp": 0.0, "position": [0, 0], "heading": math.pi / 2}
        agent.log("/1/inputs", {"time": 0.0, "odometry": odometry}, 0)
    truth = gnss_truth(load_run(tmp_path))
    assert truth.t_ns.tolist() == [0, TICK_NS]
    assert truth.vessels["1"] == pytest.approx(np.array([[0.5, 110.574276 - 1.0]] * 2), abs=1e-6)
    assert truth.vessels["2"] == pytest.approx(np.array([[0.0, -110.574276]] * 2), abs=1e-6)
    assert truth.target == pytest.approx(np.zeros((2, 2)))
    # surveyed instead: the target where surveyed, 0.001 deg east (111.319 m at the equator: a pi / 180e3)
    surveyed = gnss_truth(load_run(tmp_path), target_id="none", surveyed=(0.0, -0.001))
    assert sorted(surveyed.vessels) == ["1", "2", "target"]
    assert surveyed.vessels["2"][0] == pytest.approx([6378137.0 * math.radians(0.001), -110.574276], abs=1e-4)


def test_tracks_are_put_on_one_time_line_and_not_bridged_across_a_lost_fix(tmp_path):
    # vessel 1 at 5 Hz, moving 1 m north a fix, lost for 3 s in the middle; the target at 5 Hz throughout
    step = 2 * TICK_NS
    times = [k * step for k in range(5)] + [k * step for k in range(20, 25)]
    fix_log(tmp_path, "1", [(t, t / step * 1e-5 * 0.9043, 0.0) for t in times])
    fix_log(tmp_path, "target", [(k * step, 0.0, 0.0) for k in range(25)])
    truth = gnss_truth(load_run(tmp_path))
    assert truth.t_ns.tolist() == [k * step for k in range(25)]
    north = truth.vessels["1"][:, 1]
    assert np.isfinite(north[:5]).all() and np.isfinite(north[20:]).all() and np.isnan(north[5:20]).all()
    # 0.9043e-5 deg of latitude at the equator: 110574.276 m/deg * 0.9043e-5 = 0.99992 m a fix
    assert np.diff(north[:5]) == pytest.approx([0.99992] * 4, abs=1e-5)


def test_bad_gnss_runs_get_one_clear_error(tmp_path, capsys):
    fix_log(tmp_path, "1", [(0, 0.001, 0.0)], antenna=(1.0, 0.0))
    with pytest.raises(LogError, match=r"no target position: give its surveyed latitude and longitude"):
        gnss_truth(load_run(tmp_path))
    with pytest.raises(LogError, match=r"vessel 1's antenna is off its reference point .* no heading"):
        gnss_truth(load_run(tmp_path), surveyed=(0.0, 0.0))
    tagged = tmp_path / "tagged"
    tagged.mkdir()
    fix_log(tagged, "1", [(0, 0.001, 0.0)])
    fix_log(tagged, "target", [(0, 0.0, 0.0)], antenna=(0.2, 0.0))
    with pytest.raises(LogError, match=r"the target's tag is off its reference point"):
        gnss_truth(load_run(tagged))
    assert cli.main(["metrics", str(tagged)]) == 2
    assert "usv-log: the target's tag is off" in capsys.readouterr().err
    # malformed fixes (a hand-edited or damaged log) are left out; a log of nothing else is one clear error
    broken = tmp_path / "broken"
    broken.mkdir()
    fix_log(broken, "1", [(0, 0.001, 0.0), (TICK_NS, math.nan, 0.0)])
    fix_log(broken, "target", [(k * TICK_NS, 0.0, 0.0) for k in range(3)])
    with McapLog(broken / "gnss-1b.mcap", metadata={"gnss_of": "1"}) as log:
        log.log("usv/1/truth/gnss", {"latitude": "north", "longitude": 0.0, "antenna": "x"}, 2 * TICK_NS)
    assert np.isfinite(gnss_truth(load_run(broken)).vessels["1"]).all(axis=1).tolist() == [True, False, False]
    (broken / "gnss-1.mcap").unlink()
    with pytest.raises(LogError, match=r"no readable GNSS fix of 1"):
        gnss_truth(load_run(broken))
    for bad in ("91,0", "north"):
        with pytest.raises(SystemExit):
            cli.main(["metrics", str(tagged), "--target-at", bad])
        assert "--target-at: " in capsys.readouterr().err
