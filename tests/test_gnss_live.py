"""A live simulated field trial (issue 31's acceptance): `usv-fleet run sea_trial --gnss plain|rtk` has the sim
bridge write each vessel's and the target tag's GGA into a pty (sim_bridge/gnss_ptys.py), a real `usv-driver`
per id reads it as its GNSS serial device and logs the fixes (gnss.log), and `usv-log metrics RUN --truth gnss`
scores the run from them within the GNSS noise of the sim's own truth.

The bounds are tests/test_gnss_metrics.py's (the noise, derived there), plus what a live run adds: each fix
is stamped when its driver reads it, a lag l after the tick whose position it carries (its GGA's UTC time:
the tick's). Every position then moves by at most v l (v: the fastest vessel or target), so e_ij, e_io and
e_c of a tick by at most 2 v l_k (l_k the largest lag of the tick's fixes), and their means by 2 v mean_k l_k.
The GNSS time line starts at the first fix and keeps a tick only where every track has one (a lag can push
one end out), so the sim's truth is scored over the same span. The variant `wall_ideal` keeps every vessel on
the true clock: the drivers stamp on the host's clock, which the agents of the other variants read through
their vessel's simulated offset (docs/fleet.md).
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("pymap3d")
pytest.importorskip("pynmeagps")

from test_gnss_metrics import bounds

from agent.contract import gnss_truth_key
from mission_log import cli
from mission_log.gnss_truth import gnss_truth
from mission_log.metrics import truth_metrics
from mission_log.reader import load_run
from mission_log.series import TruthSeries, truth_of

pytestmark = pytest.mark.slow   # a real-time fleet of processes over Zenoh, ~35 s a run

DAY_NS = 86_400 * 10**9
SIGMA = {"plain": 1.5, "rtk": 0.02}


def lags(run) -> dict[str, np.ndarray]:
    """Each id's fixes: the driver's stamp minus the GGA's UTC time (the tick's), in s."""
    return {owner: np.array([(t % DAY_NS) * 1e-9 - fix["utc_time"]
                             for t, fix in log.messages(gnss_truth_key(owner))])
            for owner, log in run.gnss.items()}


def resample(sim: TruthSeries, track: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
    """A track of the sim's truth interpolated linearly at `t_ns` (NaN outside its span)."""
    x, at = (sim.t_ns - sim.t_ns[0]).astype(float), (t_ns - sim.t_ns[0]).astype(float)
    return np.stack([np.interp(at, x, track[:, i], left=np.nan, right=np.nan) for i in range(2)], axis=1)


def speeds(sim: TruthSeries, track: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
    """The speed (m/s) over the tick interval holding each of `t_ns` and the one before, the larger."""
    each = np.linalg.norm(np.diff(track, axis=0), axis=1) / (np.diff(sim.t_ns) * 1e-9)
    at = np.clip(np.searchsorted(sim.t_ns, t_ns) - 1, 0, len(each) - 1)
    return np.maximum(each[at], each[np.maximum(at - 1, 0)])


def moved_by_lag(run, sim: TruthSeries, t_ns: np.ndarray) -> np.ndarray:
    """At each of `t_ns`, the most any id's position moves during its fix's lag (interpolated between fixes)."""
    moved = []
    for owner, log in run.gnss.items():
        stamps = np.array([t for t, _ in log.messages(gnss_truth_key(owner))], dtype=np.int64)
        lag = np.interp((t_ns - stamps[0]).astype(float), (stamps - stamps[0]).astype(float), np.abs(lags(run)[owner]))
        track = sim.target if owner == "target" else sim.vessels[owner]
        moved.append(speeds(sim, track, t_ns) * lag)
    return np.max(moved, axis=0)


def bent(sim: TruthSeries, t_ns: np.ndarray) -> np.ndarray:
    """At each of `t_ns`, a bound on linear interpolation's error between the ticks around it, of the worst
    track: |p(k+1) - 2 p(k) + p(k-1)| / 8 (the larger at either end of its interval)."""
    worst = []
    for p in [sim.target, *sim.vessels.values()]:
        second = np.linalg.norm(np.diff(p, 2, axis=0), axis=1) / 8    # at ticks 1 .. K-2
        at = np.clip(np.searchsorted(sim.t_ns, t_ns) - 2, 0, len(second) - 1)
        worst.append(np.maximum(second[at], second[np.minimum(at + 1, len(second) - 1)]))
    return np.max(worst, axis=0)


@pytest.mark.parametrize("noise, seed", [("rtk", 3), ("plain", 4)])
def test_a_live_field_trial_scores_from_its_drivers_gnss_logs_within_the_gnss_noise(tmp_path, capsys, noise, seed):
    result = subprocess.run([sys.executable, "-m", "sim_bridge.fleet_cli", "run", "sea_trial", "--variant", "wall_ideal",
                             "--duration", "12", "--seed", str(seed), "--gnss", noise, "--out", str(tmp_path)],
                            capture_output=True, text=True, check=False, timeout=120)
    assert result.returncode == 0, result.stderr
    (folder,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    assert "GNSS sentences written {'1': 121, '2': 121, '3': 121, '4': 121, 'target': 121}, dropped {}" in \
        (folder / "bridge.log").read_text()
    run = load_run(folder)
    assert sorted(run.gnss) == ["1", "2", "3", "4", "target"]
    late = lags(run)
    # every tick's fix reached its driver (but the last, in flight as the bridge ended), after its tick
    assert all(len(v) >= 120 for v in late.values()), {k: len(v) for k, v in late.items()}
    # read after its tick, give or take the few ms between the bridge's monotonic ticks and its wall-clock epoch
    assert all(v.min() > -0.01 for v in late.values()), {k: v.min() for k, v in late.items()}

    sim, gnss = truth_of(run.sim), gnss_truth(run)
    on_line = TruthSeries(gnss.t_ns, resample(sim, sim.target, gnss.t_ns),
                          {v: resample(sim, p, gnss.t_ns) for v, p in sim.vessels.items()})
    from_sim, from_gnss = truth_metrics(run, truth=on_line), truth_metrics(run, truth=gnss)
    assert from_gnss["ticks"] == from_sim["ticks"] >= 119

    # per tick: any two positions apart by at most twice the most one moved in its fix's lag, and twice the
    # interpolation's error (the sim's ticks onto the line, the fixes between them)
    timing = 2 * float(np.nanmean(moved_by_lag(run, sim, gnss.t_ns)))
    curvature = 4 * float(np.nanmean(bent(sim, gnss.t_ns)))
    # each line point mixes two fixes, shared with its neighbours: a third as many independent ticks
    for name, bound in bounds(4, from_sim["ticks"] // 3, SIGMA[noise]).items():
        difference = abs(from_gnss[name] - from_sim[name])
        assert difference <= bound + timing + curvature, (name, from_gnss[name], from_sim[name], bound, timing,
                                                          curvature)

    # the command a trial's crew runs scores it the same way
    assert cli.main(["metrics", str(folder), "--truth", "gnss"]) == 0
    page = capsys.readouterr().out
    assert "Truth: the GNSS fixes (the target tagged (target)" in page
    assert f"| {from_gnss['mean_e_ij']:.3f} | {from_gnss['mean_e_io']:.3f} | {from_gnss['mean_e_c']:.3f} |" in page
