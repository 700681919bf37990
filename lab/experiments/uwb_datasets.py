"""Public UWB range data sets with ground truth, turned into replay CSVs for `usv-lab replay`.

    usv-lab uwb-convert hanyang|cuhksz|murp SOURCE OUT
    usv-lab fit-noise hanyang|cuhksz|murp SOURCE [--out FILE]
    usv-lab fit-noise csv RUN.csv... [--out FILE]
    usv-lab uwb-page DIR... [--config FILE]... [--sensor-configs DIR] [--runs N] [--out FILE]

SOURCE is a checkout of the data set's repository (`SOURCES`). `uwb-convert` writes one CSV per run, header
`t,range,ax,ay,bx,by` (lab/experiments/replay.py), and `runs.csv`, the manifest: the run's file, condition (LOS or
NLOS), kind (tag-anchor, one end static, moving pair) and the source files it came from. Times start at 0 at
the run's first range; lengths are in metres, rounded to the millimetre.

From 3-D to the plane: each range r becomes the horizontal range sqrt(r^2 - dz^2) (0 when r < |dz|).

Tag-anchor runs put the moving tag at end a and the fixed anchor at end b, so the replay's relative position
is tag minus anchor and the synthetic odometry is the tag's own motion.

Calibration: `fit-noise` fits each sensor on its calibration runs only, which `uwb-convert` leaves out.

More: docs/real_data.md, "The modules in detail", `lab/experiments/uwb_datasets.py`.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np

from agent.config import ConfigError, load_yaml, yaml_scalar
from agent.core.estimators import estimator_names
from agent.core.mixture_fit import em_mixture
from agent.core.params import AgentParams
from lab import arguments
from lab.experiments.replay import RangeLog, parse_csv, range_residuals, replay
from lab.harness.parallel import Engine, add_engine_arguments, campaign_notes, engine_from, report_failures
from lab.report.estimator_plots import LABELS
from lab.report.markdown import markdown_table

DEFAULT_ESTIMATOR = AgentParams().relative.estimator.name
MANIFEST = "runs.csv"
MANIFEST_COLUMNS = ("file", "condition", "kind", "source")
# The agent takes at most one range per neighbour per tick: faster logs are thinned to one range per tick.
DEFAULT_INTERVAL = AgentParams().dt
# Truth samples further apart than this are not interpolated across (s).
MAX_TRUTH_GAP = 0.5
# A run whose ends both travel at least this far (m) is a moving pair.
MOVING_PATH = 1.0


@dataclass(frozen=True)
class Source:
    """Where a data set comes from and what may be done with it."""

    title: str
    url: str
    commit: str
    licence: str
    citation: str
    truth: str
    setting: str


SOURCES = {
    "hanyang": Source(
        title="Comprehensive outdoor UWB dataset: static and dynamic measurements in LOS/NLOS environments",
        url="https://github.com/cucudasluv/UWB-dataset",
        commit="c12599812e556324eadc763e409ea8f51098dda6",
        licence="Apache-2.0",
        citation="ADIP laboratory, Hanyang University; Zenodo doi:10.5281/zenodo.15226105",
        truth="RTK GNSS, 8 Hz",
        setting="outdoor, a moving tag (about 1 m/s, up to 50 m away) and 4 anchors of DWM1001 modules, "
                "LOS and NLOS (an obstacle between tag and anchors), 10 Hz per anchor",
    ),
    "cuhksz": Source(
        title="Efficient Planar Pose Estimation via UWB Measurements: planar dynamic data set",
        url="https://github.com/LIAS-CUHKSZ/Efficient-Pose-Estimation-via-UWB-measurements",
        commit="cabd39232cb855d3c1160ed16692034f4d41a092",
        licence="MIT",
        citation="H. Jiang, W. Wang, Y. Shen, X. Li, X. Ren, B. Mu, J. Wu, ICRA 2023, arXiv:2209.06779",
        truth="motion capture",
        setting="indoor LOS, a trolley with 3 tags (0.11-0.49 m/s) among 8 anchors 1 m high, "
                "100 Hz thinned to 10 Hz",
    ),
    "murp": Source(
        title="MURP: multi-agent UWB relative pose estimation, parsed data sets",
        url="https://github.com/mit-acl/murp-datasets",
        commit="9ac0c5f94a2e3c7e11170bbf104f92d241cac3ea",
        licence="none stated",
        citation="A. Fishberg, B. Quiter, J. P. How, IEEE RA-L 2024, arXiv:2312.17731",
        truth="motion capture",
        setting="indoor, three robots with 6 Nooploop LinkTrack antennas each, ranges between robots as the "
                "mean over the 36 antenna pairs, 1 s moving average at 1 Hz",
    ),
}


# ----------------------------------------------------------------------------------------------- runs
@dataclass(frozen=True)
class Run:
    """One range sequence between two ends, with the ground truth of both, ready for the replay CSV."""

    name: str
    condition: str       # "LOS" or "NLOS"
    kind: str            # "tag-anchor", "one end static" or "moving pair"
    source: str          # the source files, relative to the checkout
    t: np.ndarray        # (N,) s, strictly increasing
    range: np.ndarray    # (N,) planar range (m)
    a: np.ndarray        # (N, 2) end a (m)
    b: np.ndarray        # (N, 2) end b (m)


def planar_range(r: np.ndarray, dz: np.ndarray) -> np.ndarray:
    """The horizontal range sqrt(r^2 - dz^2) of 3-D ranges r between ends dz apart in height (0 if r < |dz|)."""
    r = np.asarray(r, dtype=float)
    return np.sqrt(np.maximum(r * r - np.asarray(dz, dtype=float) ** 2, 0.0))


def thin(t: np.ndarray, interval: float) -> np.ndarray:
    """Indices of the samples kept when at most one is taken per tick of `interval` s, counted from t[0]: the
    first of each tick, as the agent takes one range per neighbour per tick. A 10 Hz sensor with clock jitter
    keeps nearly all its samples; a 100 Hz one keeps one in ten."""
    ticks = np.floor((np.asarray(t) - t[0]) / interval + 1e-9).astype(np.int64)
    return np.flatnonzero(np.concatenate([[True], np.diff(ticks) > 0]))


def interpolate(t_query: np.ndarray, t: np.ndarray, values: np.ndarray,
                max_gap: float = MAX_TRUTH_GAP) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of `values` (N, k) sampled at increasing `t` to `t_query`: (values (M, k), usable),
    usable False outside [t0, tN] or where the two samples around the query are more than `max_gap` apart."""
    values = np.asarray(values, dtype=float).reshape(len(t), -1)
    after = np.searchsorted(t, t_query, side="left")
    inside = (t_query >= t[0]) & (t_query <= t[-1])
    lo = np.clip(after - 1, 0, len(t) - 1)
    hi = np.clip(after, 0, len(t) - 1)
    usable = inside & (t[hi] - t[lo] <= max_gap)
    out = np.column_stack([np.interp(t_query, t, values[:, c]) for c in range(values.shape[1])])
    return out, usable


def _clean(t: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Indices of the usable ranges in time order: finite and positive, the first of any repeated time."""
    order = np.argsort(t, kind="stable")
    good = [k for k in order if math.isfinite(r[k]) and r[k] > 0.0]
    kept, last = [], -math.inf
    for k in good:
        if t[k] > last:
            kept.append(k)
            last = t[k]
    return np.array(kept, dtype=int)


def _kind(a: np.ndarray, b: np.ndarray) -> str:
    travelled = [float(np.sum(np.linalg.norm(np.diff(end, axis=0), axis=1))) for end in (a, b)]
    return "moving pair" if min(travelled) >= MOVING_PATH else "one end static"


def _table(path: Path, header: bool = True) -> tuple[list[str], list[list[str]]]:
    """(column names, rows of fields) of a CSV file; blank rows skipped."""
    with open(path, encoding="utf-8-sig", newline="") as handle:
        rows = [row for row in csv.reader(handle) if row and any(field.strip() for field in row)]
    if not rows:
        raise ConfigError(f"{path}: empty file")
    return ([name.strip() for name in rows[0]], rows[1:]) if header else ([], rows)


def _column(path: Path, names: list[str], rows: list[list[str]], name: str) -> np.ndarray:
    if name not in names:
        raise ConfigError(f"{path}: no column '{name}'")
    index = names.index(name)
    return np.array([float(row[index]) if index < len(row) and row[index].strip() else math.nan
                     for row in rows])


# ----------------------------------------------------------------------------------------------- Hanyang
HANYANG_ANCHORS = ("A3", "A5", "A9", "A12")
# The tag rode 1 m above the GNSS antenna's trajectory z: the height the data set's own evaluation uses
# (Technical_validation/localization_error_analysis.py) and the static measurements' tag height.
HANYANG_TAG_HEIGHT = 1.0
# GNSS heights beyond +-0.5 m of the start are height faults; the data set's evaluation drops them too.
HANYANG_MAX_Z = 0.5


# Case 1 (LOS and NLOS) calibrates the sensor and is never scored; cases 2-4 are the scored runs.
HANYANG_CALIBRATION = ("Case_1",)


def hanyang_runs(root: Path, interval: float = DEFAULT_INTERVAL, calibration: bool = False) -> Iterator[Run]:
    """The moving runs, 2 conditions x 4 anchors per case: the scored cases 2-4, or with `calibration` the
    calibration case 1. End a is the tag, end b the anchor."""
    base = Path(root) / "Dynamic_measurements"
    for condition in ("LOS", "NLOS"):
        cases = sorted((base / condition).glob("Trajectory_*/Case_*"), key=lambda p: p.name)
        if not cases:
            raise ConfigError(f"{base / condition}: no Trajectory_*/Case_* folders; is {root} the data set?")
        for case in cases:
            if (case.name in HANYANG_CALIBRATION) == calibration:
                yield from _hanyang_case(root, case, condition, interval)


def _hanyang_case(root: Path, case: Path, condition: str, interval: float) -> Iterator[Run]:
    path = case / "trajectory.csv"
    names, rows = _table(path)
    stamp = _column(path, names, rows, "timestamp")   # ns
    origin = stamp[0]
    truth_t = (stamp - origin) * 1e-9
    x, y, z = (_column(path, names, rows, c) for c in ("x", "y", "z"))
    good = np.abs(z) < HANYANG_MAX_Z
    truth_t, truth = truth_t[good], np.column_stack([x, y, z + HANYANG_TAG_HEIGHT])[good]
    for anchor in HANYANG_ANCHORS:
        apath = case / f"{anchor}.csv"
        anames, arows = _table(apath)
        # The message's own stamp (ns), on the same clock as the GNSS header stamps of the trajectory.
        t = np.array([(int(row[anames.index("field.stamp")]) - int(origin)) * 1e-9 for row in arows])
        r = _column(apath, anames, arows, "field.distanceFromTag")
        where = np.column_stack([_column(apath, anames, arows, f"field.{c}") for c in "xyz"])
        if not np.allclose(where, where[0]):
            raise ConfigError(f"{apath}: the anchor moves; a tag-anchor run needs it fixed")
        keep = _clean(t, r)
        t, r = t[keep], r[keep]
        tag, usable = interpolate(t, truth_t, truth)
        t, r, tag = t[usable], r[usable], tag[usable]
        keep = thin(t, interval)
        t, r, tag = t[keep], r[keep], tag[keep]
        planar = planar_range(r, tag[:, 2] - where[0, 2])
        relative = case.relative_to(root).as_posix()
        yield Run(
            name=f"{condition.lower()}-{case.name.lower().replace('_', '')}-{anchor}",
            condition=condition, kind="tag-anchor",
            source=f"{relative}/{anchor}.csv, {relative}/trajectory.csv",
            t=t, range=planar, a=tag[:, :2], b=np.tile(where[0, :2], (len(t), 1)),
        )


# ----------------------------------------------------------------------------------------------- CUHK-SZ
CUHKSZ_ANCHORS = (
    (-3.4203, 3.0053, 1.0442), (0.0016, 3.0110, 1.0446), (3.6056, 2.9795, 1.0463), (3.6011, -0.0008, 1.0422),
    (3.5674, -3.0087, 1.0443), (-0.0072, -2.9652, 1.0444), (-3.4673, -2.9587, 1.0445), (-3.4858, -0.0098, 1.0457),
)
# The tags in the trolley's frame (m), about its motion-capture centre.
CUHKSZ_TAGS = ((-0.0689, -0.1423, 0.0011), (-0.0750, 0.1402, 0.0016), (0.2034, 0.1451, -0.0008))
# The authors' correction of the motion-capture yaw (Dynamic_pose_estimation.mlx, `degree`), in degrees.
CUHKSZ_YAW_CORRECTION = 7.0
CUHKSZ_SPEEDS = ("fast", "mid", "slow")
# Tag 0 is scored; tags 1 and 2, on the same trolley, calibrate the sensor.
CUHKSZ_CALIBRATION_TAGS = (1, 2)


def _clock(text: str) -> float:
    """Seconds since midnight of a 'YYYY-MM-DD H:MM:SS.fff' local time stamp (no time zone is needed)."""
    stamp = datetime.strptime(text.strip(), "%Y-%m-%d %H:%M:%S.%f")
    return stamp.hour * 3600.0 + stamp.minute * 60.0 + stamp.second + stamp.microsecond * 1e-6


def yaw_from_quaternion(w: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Yaw (rad) of the Z-Y-X Euler angles of scalar-first quaternions, as MATLAB's quat2angle(q, 'ZYX')."""
    return np.arctan2(2.0 * (x * y + w * z), w * w + x * x - y * y - z * z)


def cuhksz_runs(root: Path, tags: Sequence[int] = (0,), interval: float = DEFAULT_INTERVAL) -> Iterator[Run]:
    """Every (speed, tag, anchor) run of Planar_Dataset/Dynamic whose two files are in the checkout. The three
    tags ride one trolley, so their runs are nearly copies: one tag by default. End a is the tag."""
    base = Path(root) / "Planar_Dataset" / "Dynamic"
    found = False
    for speed in CUHKSZ_SPEEDS:
        ranges, mocap = base / f"UWB_dynamic_exp_{speed}.csv", base / f"motion_capture_dynamic_exp_{speed}.csv"
        if not (ranges.exists() and mocap.exists()):
            print(f"cuhksz: no {ranges.name} and {mocap.name} in {base}; speed '{speed}' skipped",
                  file=sys.stderr)
            continue
        found = True
        yield from _cuhksz_speed(root, speed, ranges, mocap, tags, interval)
    if not found:
        raise ConfigError(f"{base}: no UWB_dynamic_exp_*.csv with its motion_capture_dynamic_exp_*.csv")


def _cuhksz_speed(root: Path, speed: str, ranges: Path, mocap: Path, tags: Sequence[int],
                  interval: float) -> Iterator[Run]:
    _, rows = _table(mocap)   # header: time,x,y,z,rotation (w, x, y, z)
    truth_t = np.array([_clock(row[0]) for row in rows])
    m = np.array([[float(v) for v in row[1:8]] for row in rows])
    yaw = np.unwrap(yaw_from_quaternion(m[:, 3], m[:, 4], m[:, 5], m[:, 6])) + math.radians(CUHKSZ_YAW_CORRECTION)
    truth = np.column_stack([m[:, 0], m[:, 1], m[:, 2], yaw])
    _, urows = _table(ranges, header=False)
    t_all = np.array([_clock(row[0]) for row in urows])
    sources = f"{ranges.relative_to(root).as_posix()}, {mocap.relative_to(root).as_posix()}"
    for tag in tags:
        sx, sy, sz = CUHKSZ_TAGS[tag]
        for index, (ax, ay, az) in enumerate(CUHKSZ_ANCHORS):
            column = 1 + 3 * index + tag   # the columns run a0-t0, a0-t1, a0-t2, a1-t0, ...
            r = np.array([float(row[column]) if column < len(row) and row[column].strip() else math.nan
                          for row in urows])
            keep = _clean(t_all, r)
            t, r = t_all[keep], r[keep]
            pose, usable = interpolate(t, truth_t, truth)
            t, r, pose = t[usable], r[usable], pose[usable]
            keep = thin(t, interval)
            t, r, pose = t[keep], r[keep], pose[keep]
            cos, sin = np.cos(pose[:, 3]), np.sin(pose[:, 3])
            tag_xy = np.column_stack([pose[:, 0] + cos * sx - sin * sy, pose[:, 1] + sin * sx + cos * sy])
            planar = planar_range(r, pose[:, 2] + sz - az)
            yield Run(name=f"{speed}-tag{tag}-anchor{index}", condition="LOS", kind="tag-anchor",
                      source=sources, t=t, range=planar, a=tag_xy, b=np.tile((ax, ay), (len(t), 1)))


# ----------------------------------------------------------------------------------------------- MURP
MURP_TRIALS = tuple(range(13, 23))        # 13-15: robot 1 still, 2 and 3 moving; 16-22: all three moving
# The calibration trials in which the robots move (0.4-0.9 m/s apart); in trials 1-7 they stand or creep
# (under 0.03 m/s), unlike any scored run.
MURP_CALIBRATION = tuple(range(8, 13))


def _murp_files(root: Path, trials: Sequence[int]) -> Iterator[tuple[int, int, int, Path]]:
    """(trial, base, target, file) of every unordered robot pair: base < target, as the reverse direction
    holds nearly the same ranges."""
    base = Path(root) / "datasets" / "parsed"
    for trial in trials:
        for first in (1, 2, 3):
            for second in range(first + 1, 4):
                path = base / f"{trial:02d}" / f"{trial:02d}_base-{first}_targ-{second}_win-1_step-1.csv"
                if not path.exists():
                    raise ConfigError(f"{path}: not found; is {root} the murp-datasets repository?")
                yield trial, first, second, path


def _murp_read(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t, mean measured range, base position (N, 3), target position (N, 3))."""
    names, rows = _table(path)
    t, r, ax, ay, az, bx, by, bz = (_column(path, names, rows, name)
                                    for name in ("t", "r", "A_x", "A_y", "A_z", "B_x", "B_y", "B_z"))
    return t, r, np.column_stack([ax, ay, az]), np.column_stack([bx, by, bz])


def murp_runs(root: Path, trials: Sequence[int] = MURP_TRIALS) -> Iterator[Run]:
    """Every robot pair of `trials`; end a is the base robot, end b the target, both from motion capture.
    The range is the mean over the 36 antenna pairs (the data set's `r`), taken between the robots' centres:
    the antennas' offsets from the centre make 0.01-0.10 m of the error, as they would on a boat."""
    for trial, first, second, path in _murp_files(root, trials):
        t, r, a, b = _murp_read(path)
        keep = _clean(t, r)
        t, r, a, b = t[keep], r[keep], a[keep], b[keep]
        yield Run(name=f"trial{trial:02d}-robots{first}{second}", condition="LOS", kind=_kind(a[:, :2], b[:, :2]),
                  source=path.relative_to(root).as_posix(), t=t, range=planar_range(r, a[:, 2] - b[:, 2]),
                  a=a[:, :2], b=b[:, :2])


READERS = {"hanyang": hanyang_runs, "cuhksz": cuhksz_runs, "murp": murp_runs}
# Each data set's calibration runs, in words (`calibration_runs` reads them).
CALIBRATION = {
    "hanyang": "case 1 of the moving runs, LOS and NLOS, every anchor",
    "cuhksz": "tags 1 and 2 of the moving runs, every anchor (tag 0 is scored)",
    "murp": "calibration trials 8-12, every robot pair, the robots moving",
}


def calibration_runs(dataset: str, root: Path, interval: float = DEFAULT_INTERVAL) -> Iterator[Run]:
    """The runs that calibrate `dataset`'s sensor (`CALIBRATION`), read as the scored ones are."""
    if dataset == "hanyang":
        return hanyang_runs(root, interval, calibration=True)
    if dataset == "cuhksz":
        return cuhksz_runs(root, tags=CUHKSZ_CALIBRATION_TAGS, interval=interval)
    if dataset == "murp":
        return murp_runs(root, trials=MURP_CALIBRATION)
    raise ConfigError(f"unknown data set '{dataset}'; known: {', '.join(READERS)}")


# ----------------------------------------------------------------------------------------------- writing
def write_run(run: Run, directory: Path) -> Path:
    """The replay CSV of `run` in `directory`: time from the run's first range, millimetres."""
    path = Path(directory) / f"{run.name}.csv"
    t = run.t - run.t[0]
    lines = ["t,range,ax,ay,bx,by"]
    lines += [f"{t[k]:.3f},{run.range[k]:.3f},{run.a[k, 0]:.3f},{run.a[k, 1]:.3f},{run.b[k, 0]:.3f},"
              f"{run.b[k, 1]:.3f}" for k in range(len(t))]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def convert(dataset: str, source: Path, out: Path, interval: float = DEFAULT_INTERVAL) -> list[Path]:
    """Write every run of `dataset` read from the checkout `source` into `out`, with its manifest."""
    if dataset not in READERS:
        raise ConfigError(f"unknown data set '{dataset}'; known: {', '.join(READERS)}")
    out.mkdir(parents=True, exist_ok=True)
    runs = READERS[dataset](source) if dataset == "murp" else READERS[dataset](source, interval=interval)
    written, manifest = [], []
    for run in runs:
        if len(run.t) < 3:
            print(f"{dataset}: run {run.name} has {len(run.t)} usable ranges; left out", file=sys.stderr)
            continue
        written.append(write_run(run, out))
        manifest.append((written[-1].name, run.condition, run.kind, run.source))
    with open(out / MANIFEST, "w", encoding="utf-8", newline="") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(("dataset", *MANIFEST_COLUMNS))
        writer.writerows((dataset, *row) for row in manifest)
    return written


@dataclass(frozen=True)
class Entry:
    """One line of a manifest: a replay CSV and what it is."""

    dataset: str
    path: Path
    condition: str
    kind: str
    source: str


def read_manifest(directory: Path) -> list[Entry]:
    path = Path(directory) / MANIFEST
    names, rows = _table(path)
    expected = ["dataset", *MANIFEST_COLUMNS]
    if names != expected:
        raise ConfigError(f"{path}: header must be {','.join(expected)}")
    entries = [Entry(row[0], Path(directory) / row[1], row[2], row[3], row[4]) for row in rows]
    for entry in entries:
        if entry.dataset not in SOURCES:
            raise ConfigError(f"{path}: unknown data set '{entry.dataset}'")
    return entries


# ----------------------------------------------------------------------------------------------- noise fit
def fit_mixture(samples: Sequence[np.ndarray], components: int = 3, iterations: int = 500,
                min_variance: float = 1e-4) -> tuple[tuple[float, float, float], ...]:
    """A Gaussian mixture (weight, mean, variance) fitted by EM to the pooled `samples`, each array carrying the
    same total weight so that a large calibration set does not drown a small one. Started from the pooled
    weighted quantiles; variances floored at `min_variance` (ranges come in millimetres)."""
    x = np.concatenate([np.asarray(s, dtype=float) for s in samples])
    weight = np.concatenate([np.full(len(s), 1.0 / len(s)) for s in samples])
    weight /= weight.sum()
    order = np.argsort(x)
    cumulative = np.cumsum(weight[order])
    means = x[order][np.searchsorted(cumulative, (np.arange(components) + 0.5) / components)]
    variances = np.full(components, max(float(np.var(x)) / components, min_variance))
    shares, means, variances = em_mixture(x, weight, np.full(components, 1.0 / components), means, variances,
                                          iterations, min_variance)
    order = np.argsort(-shares)
    return tuple((float(shares[k]), float(means[k]), float(variances[k])) for k in order)


def mixture_variance(mixture: Sequence[tuple[float, float, float]]) -> float:
    """Variance of a Gaussian mixture about its mean (m^2)."""
    w = np.array([c[0] for c in mixture])
    m = np.array([c[1] for c in mixture])
    v = np.array([c[2] for c in mixture])
    w = w / w.sum()
    mean = float(w @ m)
    return float(w @ (v + m * m) - mean * mean)


@dataclass(frozen=True)
class SensorNoise:
    """A sensor's range noise, fitted to its calibration runs."""

    mixture: tuple[tuple[float, float, float], ...]   # (weight, mean, variance) of the residuals about each
                                                      # run's own mean, the runs' common mean kept
    bias_variance: float                              # variance of the runs' mean residuals (m^2)
    runs: int
    ranges: int


def fit_sensor_noise(runs: Sequence[Run | RangeLog], components: int = 3) -> SensorNoise:
    """The noise model r = |p| + b + e of raw_range from calibration runs with ground truth: each run (one
    pair of antennas, one session) has its own constant bias b, whose spread over the runs is b's prior
    variance (the sample variance of the runs' mean residuals), and e is the Gaussian mixture fitted to the
    residuals less their run's mean, plus the runs' common mean, each run weighted alike."""
    residuals = [range_residuals(run) for run in runs]
    residuals = [r for r in residuals if len(r)]
    if len(residuals) < 2:
        raise ConfigError(f"{len(residuals)} calibration run(s) with ranges: a sensor's calibration needs at least "
                          "two, the spread of their biases being the bias state's prior")
    means = np.array([float(r.mean()) for r in residuals])
    common = float(means.mean())
    mixture = fit_mixture([r - m + common for r, m in zip(residuals, means)], components)
    return SensorNoise(mixture, float(np.var(means, ddof=1)), len(residuals), sum(len(r) for r in residuals))


def sensor_config_text(sensor: str, calibration: str, noise: SensorNoise, argv: Sequence[str]) -> str:
    """configs/uwb/<dataset>.yaml: raw_range's density and bias prior, and the pseudo-linear filters' range
    variance (the residuals' whole variance, the biases' spread included). `sensor` names the sensor
    ("the murp data set's UWB sensor"), `calibration` says which runs it was fitted to."""
    rounded = [(float(f"{w:.3g}"), round(m, 3), float(f"{v:.3g}")) for w, m, v in noise.mixture]
    components = ", ".join(yaml_scalar(c) for c in rounded)
    bias_variance = float(f"{noise.bias_variance:.3g}")
    range_variance = float(f"{mixture_variance(rounded) + bias_variance:.4g}")
    return "\n".join([
        f"# Range noise of {sensor}: every key not named is the default (configs/agent.yaml).",
        (f"# Fitted to calibration runs, which no score uses: {calibration} ({noise.runs} runs, {noise.ranges} "
         "ranges)."),
        "# Regenerate with: usv-lab " + " ".join(argv),
        "relative:",
        (f"  range_variance: {yaml_scalar(range_variance)}  # the residuals' variance, the runs' biases included "
         "(pseudo-linear filters)"),
        "  estimator:",
        "    name: raw_range",
        (f"    noise_components: [{components}]  # (weight, mean m, variance m^2): EM fit to the residuals about "
         "each run's mean, each run weighted alike"),
        (f"    bias_variance: {yaml_scalar(bias_variance)}  # variance of the runs' mean residuals: a pair's "
         "constant bias, estimated as a state"),
        "",
    ])


# ----------------------------------------------------------------------------------------------- page
# The diagnostics' late window: RMSE averaged from this many seconds on, once every estimator has had time.
LATE = 30.0


@dataclass(frozen=True)
class Outcome:
    """One run replayed with one config: every estimator's time-averaged RMSE and what explains a loss."""

    entry: Entry
    ranges: int
    duration: float                 # s
    interval: float                 # median time between ranges (s)
    bias: float                     # mean range residual against the truth (m): a diagnostic, never fed back
    spread: float                   # 1.4826 x median absolute deviation of those residuals (m): likewise
    rmse: dict[str, float]          # time-averaged RMSE over the whole run (m)
    late: dict[str, float]          # time-averaged RMSE from LATE s on (m)
    debiased: float | None          # DEFAULT_ESTIMATOR on ranges less the truth-derived bias, if it lost: a
                                    # diagnostic only

    @property
    def winner(self) -> str:
        return min(self.rmse, key=self.rmse.get)


def score(entry: Entry, params: AgentParams, runs: int, seed: int) -> Outcome:
    """Replay `entry` with the config's noise (never the truth's) and summarise it (one process: the page's
    engine spreads the entries)."""
    log = parse_csv(entry.path)
    result = replay(log, params, runs=runs, seed=seed)
    rmse = {name: result.time_averaged_rmse(name) for name in estimator_names()}
    late = {name: result.time_averaged_rmse(name, LATE) for name in estimator_names()}
    interval = float(np.median(np.diff(log.t)))
    residual = range_residuals(log)
    spread = 1.4826 * float(np.median(np.abs(residual - np.median(residual))))
    debiased = None
    if min(rmse, key=rmse.get) != DEFAULT_ESTIMATOR:
        # What a known bias would be worth: the truth's mean residual taken off the ranges. Diagnostic only.
        unbiased = RangeLog(log.source, log.t, np.maximum(log.range - result.range_bias, 0.0), log.a, log.b)
        debiased = replay(unbiased, params, runs=runs, seed=seed, names=(DEFAULT_ESTIMATOR,)).time_averaged_rmse(
            DEFAULT_ESTIMATOR)
    return Outcome(entry, len(log), float(log.elapsed[-1]), interval, result.range_bias, spread, rmse, late,
                   debiased)


def _score_job(job: tuple[Entry, AgentParams, int, int]) -> Outcome:
    return score(*job)


def _label(name: str) -> str:
    return LABELS.get(name, name)


def _wins(outcomes: Sequence[Outcome]) -> dict[str, int]:
    counts = dict.fromkeys(estimator_names(), 0)
    for outcome in outcomes:
        counts[outcome.winner] += 1
    return counts


def _share(part: int, whole: int) -> str:
    return f"{part} of {whole} ({100.0 * part / whole:.0f} %)" if whole else "0 of 0"


def _residuals(group: Sequence[Outcome]) -> list[str]:
    """The group's median range bias and spread against the truth, as table cells."""
    return [f"{np.median([o.bias for o in group]):+.3f}", f"{np.median([o.spread for o in group]):.3f}"]


def _summary(outcomes: Sequence[Outcome]) -> list[str]:
    datasets = sorted({o.entry.dataset for o in outcomes}, key=list(SOURCES).index)
    kinds = sorted({o.entry.kind for o in outcomes})
    rows = []
    for dataset in datasets:
        for condition in ("LOS", "NLOS"):
            for kind in kinds:
                group = [o for o in outcomes
                         if (o.entry.dataset, o.entry.condition, o.entry.kind) == (dataset, condition, kind)]
                if group:
                    wins = _wins(group)
                    rows.append([dataset, condition, kind, len(group), *_residuals(group),
                                 *(wins[n] for n in estimator_names())])
    wins = _wins(outcomes)
    rows.append(["all", "", "", len(outcomes), *_residuals(outcomes), *(wins[n] for n in estimator_names())])
    header = ["data set", "condition", "kind", "runs", "median bias (m)*", "median spread (m)*",
              *(f"{_label(n)} lowest" for n in estimator_names())]
    return [markdown_table(header, rows)]


def _per_run(outcomes: Sequence[Outcome]) -> str:
    header = ["data set", "run", "cond.", "kind", "s", "ranges", "bias (m)*", "spread (m)*",
              *(_label(n) for n in estimator_names()), "lowest"]
    rows = [[o.entry.dataset, o.entry.path.stem, o.entry.condition, o.entry.kind, f"{o.duration:.0f}", o.ranges,
             f"{o.bias:+.3f}", f"{o.spread:.3f}", *(o.rmse[n] for n in estimator_names()), _label(o.winner)]
            for o in outcomes]
    return markdown_table(header, rows)


def _losses(outcomes: Sequence[Outcome], params: AgentParams) -> list[str]:
    lost = [o for o in outcomes if o.winner != DEFAULT_ESTIMATOR]
    if not lost:
        return [f"{DEFAULT_ESTIMATOR} has the lowest time-averaged RMSE on every run."]
    header = ["run", "interval (s)", "bias (m)*", f"{DEFAULT_ESTIMATOR}", "lowest",
              f"{DEFAULT_ESTIMATOR} from {LATE:g} s", f"lowest from {LATE:g} s", f"{DEFAULT_ESTIMATOR}, bias removed*"]
    rows = [[f"{o.entry.dataset}/{o.entry.path.stem}", f"{o.interval:.2f}",
             f"{o.bias:+.3f}", o.rmse[DEFAULT_ESTIMATOR], f"{_label(o.winner)} {o.rmse[o.winner]:.3f}",
             o.late[DEFAULT_ESTIMATOR], o.late[o.winner], o.debiased] for o in lost]
    slow = [o for o in lost if o.interval > 1.5 * params.dt]
    late = [o for o in lost if o.late[DEFAULT_ESTIMATOR] <= o.late[o.winner]]
    both = [o for o in lost if o.debiased is not None and o.debiased < o.rmse[o.winner]]
    won = [o for o in outcomes if o.winner == DEFAULT_ESTIMATOR]

    def bias(group: Sequence[Outcome]) -> float:
        return float(np.median([abs(o.bias) for o in group])) if group else math.nan

    return [
        (f"{DEFAULT_ESTIMATOR} is not lowest on {len(lost)} run{'s' if len(lost) != 1 else ''}. What the numbers "
         "below say about why:"),
        "",
        (f"- Time base: {len(slow)} of them have ranges further apart than the agent's tick (median interval above "
         f"{1.5 * params.dt:g} s)."),
        (f"- After the start: from {LATE:g} s on, {DEFAULT_ESTIMATOR} is at or below the run's lowest estimator "
         f"on {len(late)} of the {len(lost)}."),
        (f"- Range bias: the median |mean residual| is {bias(lost):.3f} m on these runs and {bias(won):.3f} m on "
         f"the runs {DEFAULT_ESTIMATOR} wins. With each run's truth-derived mean residual taken off its ranges (last "
         f"column, a diagnostic that uses the truth, never a setting) {DEFAULT_ESTIMATOR} would be lowest on "
         f"{len(both)} of the {len(lost)}."),
        "",
        markdown_table(header, rows),
    ]


def _datasets(outcomes: Sequence[Outcome]) -> str:
    rows = []
    for name, source in SOURCES.items():
        group = [o for o in outcomes if o.entry.dataset == name]
        if not group:
            continue
        conditions = ", ".join(sorted({o.entry.condition for o in group}))
        rows.append([name, f"[{source.title}]({source.url}) at `{source.commit[:7]}`", source.licence,
                     source.truth, source.setting, f"{len(group)} ({conditions})"])
    return markdown_table(["name", "source", "licence", "truth", "setting", "runs"], rows)


def _config_comment(path: Path | None) -> list[str]:
    """The leading comment of a config file as a quote (where its noise came from), or nothing."""
    if path is None:
        return []
    lines = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.startswith("#"):
            break
        lines.append("> " + line.lstrip("#").strip())
    return [*lines, ""] if lines else []


def _noise_words(params: AgentParams) -> str:
    """What a config tells the filters about the range noise, in one sentence."""
    raw = params.relative.params_of("raw_range")
    noise = " + ".join(f"{w:g} N({m:g}, {v:g})" for w, m, v in raw.noise_components)
    bias = (f", and a constant pair bias of prior variance {raw.bias_variance:g} m^2 estimated with the position"
            if raw.bias_variance > 0.0 else "")
    return (f"raw_range assumes {noise} (m, m^2) with a gross-error weight of {raw.gross_error_fraction:g}{bias}; "
            f"the pseudo-linear filters a range variance of {params.relative.range_variance:g} m^2.")


Config = tuple[Path | None, AgentParams]


def _section(label: str, chosen: dict[str | None, Config], entries: Sequence[Entry], runs: int, seed: int,
             engine: Engine) -> tuple[str, list[str], list[Outcome]]:
    """Replay `entries`, each with its data set's config in `chosen` (the None key: every data set's), and
    write the page's section: (its summary line, its lines, its outcomes)."""
    done = []

    def progress(_: int) -> None:
        done.append(1)
        print(f"[{len(done)}/{len(entries)}] replayed ({label})", file=sys.stderr)

    def config(entry: Entry) -> Config:
        return chosen[entry.dataset] if entry.dataset in chosen else chosen[None]

    outcomes = [o for o in engine.map(_score_job, [(e, config(e)[1], runs, seed) for e in entries], progress,
                                      lambda n: f"{entries[n].dataset}/{entries[n].path.name} ({label})")
                if o is not None]
    if not outcomes:
        raise ConfigError(f"every run raised with {label}: {engine.failures[0].error}")
    wins = _wins(outcomes)[DEFAULT_ESTIMATOR]
    total = f"- Noise from {label}: **{DEFAULT_ESTIMATOR} lowest on {_share(wins, len(outcomes))} runs**."
    described = []
    for dataset, (path, params) in chosen.items():
        if dataset is not None and not any(e.dataset == dataset for e in entries):
            continue
        prefix = f"**{dataset}** (`{path}`): " if dataset is not None else ""
        described += [*_config_comment(path), prefix + _noise_words(params), ""]
    params = next(iter(chosen.values()))[1]
    lines = [
        f"## Noise from {label}",
        "",
        *described,
        *_summary(outcomes),
        "",
        *_losses(outcomes, params),
        "",
        "<details><summary>Every run: time-averaged RMSE (m) of each estimator</summary>",
        "",
        _per_run(outcomes),
        "",
        "</details>",
        "",
    ]
    return total, lines, outcomes


def write_page(manifests: Sequence[Sequence[Entry]], configs: Sequence[Config], runs: int, seed: int, out: Path,
               argv: Sequence[str], engine: Engine | None = None,
               sensor_configs: dict[str, Config] | None = None) -> Path:
    """Replay every run of `manifests` with each config, and, given `sensor_configs` (data set -> config),
    with each data set's own, the runs spread over `engine` (this process if None); write the page to `out`."""
    if engine is None:
        with Engine() as here:
            return write_page(manifests, configs, runs, seed, out, argv, here, sensor_configs)
    entries = [entry for manifest in manifests for entry in manifest]
    if not entries:
        raise ConfigError("no runs: the manifests are empty")
    if not configs and sensor_configs is None:
        raise ConfigError("no config to replay with: give a config or the sensor configs")
    missing = sorted({e.dataset for e in entries} - set(sensor_configs or {})) if sensor_configs is not None else []
    if missing:
        raise ConfigError(f"no sensor config for {', '.join(missing)}: each data set replayed needs its own "
                          "(usv-lab fit-noise DATASET SOURCE)")
    chosen: list[tuple[str, dict[str | None, Config]]] = [
        (f"`{path}`" if path is not None else "the default config (configs/agent.yaml)", {None: (path, params)})
        for path, params in configs]
    if sensor_configs is not None:
        chosen.append(("each data set's calibrated sensor config", dict(sensor_configs)))
    sections: list[str] = []
    totals: list[str] = []
    outcomes_first: list[Outcome] = []
    for label, by_dataset in chosen:
        total, lines, outcomes = _section(label, by_dataset, entries, runs, seed, engine)
        totals.append(total)
        sections += lines
        outcomes_first = outcomes_first or outcomes
    command = "usv-lab " + " ".join(argv)
    text = "\n".join([
        "# Real UWB ranges: every estimator on public data sets, noise from the config",
        "",
        "```",
        command,
        "```",
        "",
        (f"Each run is replayed by `usv-lab replay` (lab/experiments/replay.py): {runs} Monte Carlo runs, seed {seed}, "
         "each drawing its own synthetic odometry noise and initial estimate p0 ~ N(p, P0). The filters' range "
         "noise comes from the config named, never from the runs' ground truth. The score is the RMSE over the "
         "Monte Carlo runs at each range epoch, averaged over the whole run by time (the start included). "
         f"The default estimator is `{DEFAULT_ESTIMATOR}`. Ran on {engine.where()}."),
        "",
        *totals,
        *campaign_notes(engine),
        "",
        "## Data sets",
        "",
        _datasets(outcomes_first),
        "",
        ("Ranges are 3-D; each is mapped to the horizontal range sqrt(r^2 - dz^2) with the two antennas' heights "
         "from the ground truth (lab/experiments/uwb_datasets.py says why). Tag-anchor runs have the moving tag as end a and "
         "the fixed anchor as end b. docs/real_data.md gives each data set's source and the commands that convert it "
         "(none of the data is kept in this repository)."),
        "",
        ("A sensor config (configs/uwb/<data set>.yaml, `usv-lab fit-noise`) is fitted to its "
         "data set's calibration runs, which are never scored: "
         + "; ".join(f"{name}: {words}" for name, words in CALIBRATION.items()) + "."),
        "",
        ("\\* bias and spread: the mean and the robust spread (1.4826 x median absolute deviation) of the run's "
         "range residuals against its ground truth, reported to explain results; neither is given to any filter."),
        "",
        *sections,
    ])
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    return out


# ----------------------------------------------------------------------------------------------- commands
def add_convert_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", choices=sorted(READERS))
    parser.add_argument("source", type=Path, help="checkout of the data set's repository")
    parser.add_argument("out", type=arguments.folder, help="directory of the CSVs and runs.csv")
    parser.add_argument("--interval", type=arguments.positive_float, default=DEFAULT_INTERVAL,
                        help=f"keep at most one range per this many seconds (default {DEFAULT_INTERVAL:g}, "
                             "the agent's tick); MURP's 1 Hz windows are kept as they are")


def run_convert(args: argparse.Namespace) -> int:
    written = convert(args.dataset, args.source, args.out, args.interval)
    print(f"wrote {len(written)} runs and {MANIFEST} to {args.out}")
    return 0


def add_fit_noise_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", choices=[*sorted(READERS), "csv"],
                        help="a data set (its calibration runs), or csv: your own runs as replay CSV files")
    parser.add_argument("source", type=Path, nargs="+",
                        help="checkout of the data set's repository; with csv, the replay CSV files")
    parser.add_argument("--components", type=arguments.positive_int, default=3,
                        help="Gaussian components of the fitted density (default 3)")
    parser.add_argument("--out", type=arguments.page, default=None,
                        help="write the config here, e.g. configs/uwb/DATASET.yaml (default: print it)")


def run_fit_noise(args: argparse.Namespace) -> int:
    if args.dataset == "csv":
        noise = fit_sensor_noise([parse_csv(path) for path in args.source], args.components)
        sensor, words = "a UWB sensor", "the replay CSVs " + ", ".join(p.name for p in args.source)
    else:
        if len(args.source) != 1:
            raise ConfigError(f"fit-noise {args.dataset} takes one checkout, got {len(args.source)} paths")
        noise = fit_sensor_noise(list(calibration_runs(args.dataset, args.source[0])), args.components)
        sensor = f"the {args.dataset} data set's UWB sensor (docs/results/real_uwb.md)"
        words = CALIBRATION[args.dataset]
    text = sensor_config_text(sensor, words, noise, args.argv)
    if args.out is None:
        print(text, end="")
    else:
        args.out.write_text(text, encoding="utf-8")
        spread = math.sqrt(mixture_variance(noise.mixture))
        print(f"wrote {args.out}: {noise.runs} calibration runs, {noise.ranges} ranges; the runs' biases "
              f"spread {math.sqrt(noise.bias_variance):.3f} m (sd), the rest {spread:.3f} m (sd)")
    return 0


def add_page_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dirs", type=Path, nargs="+", help="directories written by `uwb-convert`")
    parser.add_argument("--config", type=Path, action="append", default=None,
                        help="agent parameters for every run, repeatable (one section each); default: the "
                             "built-in defaults (configs/agent.yaml), unless --sensor-configs is given alone")
    parser.add_argument("--sensor-configs", type=Path, default=None, metavar="DIR",
                        help="one more section: each data set replayed with DIR/<data set>.yaml (fit-noise)")
    parser.add_argument("--runs", type=arguments.positive_int, default=10,
                        help="Monte Carlo runs per replay (default 10)")
    parser.add_argument("--seed", type=arguments.seed, default=1)
    parser.add_argument("--out", type=arguments.page, default=Path("docs/results/real_uwb.md"))
    add_engine_arguments(parser)


def run_page(args: argparse.Namespace) -> int:
    params = [(path, load_yaml(AgentParams, path)) for path in args.config] if args.config else (
        [] if args.sensor_configs is not None else [(None, AgentParams())])
    manifests = [read_manifest(d) for d in args.dirs]
    sensors = None
    if args.sensor_configs is not None:
        replayed = {e.dataset for m in manifests for e in m}
        paths = [args.sensor_configs / f"{name}.yaml" for name in SOURCES if name in replayed]
        sensors = {path.stem: (path, load_yaml(AgentParams, path)) for path in paths}
    with engine_from(args) as engine:
        write_page(manifests, params, args.runs, args.seed, args.out, args.argv, engine, sensors)
    print(f"wrote {args.out}")
    return report_failures(engine)
