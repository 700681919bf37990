"""`usv-lab replay`: every inter-vessel estimator on real ranges with ground truth (the paper's Fig. 6).

The file has the header `t,range,ax,ay,bx,by`: time (s), the measured range (m) and the ground-truth 2-D
positions (m) of the two ends of the range, a and b, either of which may be static. Time steps may be
irregular and have gaps. Vessel i is end a and vessel j is end b, so the estimated relative position is
p = a - b.

Odometry is synthesised from the ground truth: each end's true displacement plus N(0, R_delta h_k/dt I).

Each Monte Carlo run draws its own displacement noise and its own initial estimate
p0 ~ N(p(t0), P0) from one child of `SeedSequence(seed)`; every estimator of a run sees the same numbers.

The filters' range noise comes from the agent parameters (`--config`), as on a boat: the pseudo-linear filters'
variance `relative.range_variance` and raw_range's density, `noise_components` of its parameters.
`--range-variance` overrides the pseudo-linear variance only. `--truth-variance` instead gives every filter
the sample variance of this file's residuals against its ground truth, range - |a - b| (raw_range: one
zero-mean Gaussian of that variance, its gross-error component kept): that tunes the filters on the truth
they are scored against, so it is never the default and the output says so. The residuals' mean (the range
bias) is reported either way and never removed.

The pure parts (`parse_csv`, `range_residual_stats`, `synthesise_displacements`, `replay`) do no I/O beyond
reading the CSV; `run` adds the printing, the progress bar and the output files.

More: docs/real_data.md, "The modules in detail", `lab/experiments/replay.py`.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agent.config import ConfigError, load_yaml, updated
from agent.core.estimators import EstimatorParams, estimator_names, make_relative_estimator
from agent.core.params import AgentParams, RelativeEstimationParams
from lab import arguments
from lab.harness.errors import ErrorHistory, RunningMoments, moments_by_name
from lab.harness.parallel import Engine, add_engine_arguments, campaign_notes, engine_from, report_failures
from lab.report.estimator_plots import LABELS, rmse_figure
from lab.report.markdown import invocation, markdown_table
from sim_bridge.noise import IsotropicGaussianNoise

COLUMNS: tuple[str, ...] = ("t", "range", "ax", "ay", "bx", "by")
MIN_ROWS = 3
DEFAULT_RUNS = 20
DEFAULT_SEED = 1
DEFAULT_SETTLE = 10.0
DEFAULT_OUT = "docs/results"


# ----------------------------------------------------------------------------------------------- the data
@dataclass(frozen=True)
class RangeLog:
    """A parsed replay CSV: N range epochs with the ground truth of both ends."""

    source: str
    t: np.ndarray        # (N,) strictly increasing (s)
    range: np.ndarray    # (N,) measured ranges (m), >= 0
    a: np.ndarray        # (N, 2) true position of end a, vessel i (m)
    b: np.ndarray        # (N, 2) true position of end b, vessel j (m)

    @property
    def truth(self) -> np.ndarray:
        """The relative position p = a - b at every epoch, (N, 2)."""
        return self.a - self.b

    @property
    def elapsed(self) -> np.ndarray:
        """Time since the first epoch (s), (N,)."""
        return self.t - self.t[0]

    def __len__(self) -> int:
        return len(self.t)


def _problem(path: str | Path, line: int, column: str, text: str) -> ConfigError:
    return ConfigError(f"{path}: line {line}, column '{column}': {text}")


def _shown(value: str) -> str:
    """A field as it appears in a message: quoted, escaped onto one line, and not too long."""
    return repr(value if len(value) <= 40 else value[:37] + "...")


def parse_csv(path: str | Path) -> RangeLog:
    """Read and check a replay CSV; any problem raises ConfigError naming the file, line and column.

    Blank lines are skipped (they still count in line numbers); a UTF-8 byte-order mark is accepted.
    """
    try:
        with open(path, encoding="utf-8-sig", newline="") as handle:
            rows = [(line, row) for line, row in _numbered_rows(handle)]
    except OSError as error:
        raise ConfigError(f"{path}: cannot read: {error.strerror or error}") from None
    except (UnicodeDecodeError, csv.Error) as error:
        raise ConfigError(f"{path}: not a readable UTF-8 CSV file: {error}") from None

    expected = ",".join(COLUMNS)
    if not rows or rows[0][0] != 1:
        raise _problem(path, 1, COLUMNS[0], f"missing header; the first line must be exactly '{expected}'")
    header = [name.strip() for name in rows[0][1]]
    for position, name in enumerate(COLUMNS):
        if position >= len(header):
            raise _problem(path, 1, name, f"header lacks this column; it must be exactly '{expected}'")
        if header[position] != name:
            raise _problem(path, 1, name, f"header has {_shown(header[position])} where this column belongs; "
                                          f"it must be exactly '{expected}'")
    if len(header) > len(COLUMNS):
        raise _problem(path, 1, header[len(COLUMNS)],
                       f"unexpected extra header column; it must be exactly '{expected}'")

    values = np.empty((len(rows) - 1, len(COLUMNS)))
    previous_time, previous_line = -math.inf, 0
    for index, (line, row) in enumerate(rows[1:]):
        if len(row) < len(COLUMNS):
            raise _problem(path, line, COLUMNS[len(row)],
                           f"expected {len(COLUMNS)} fields ({expected}), found {len(row)}")
        if len(row) > len(COLUMNS):
            raise _problem(path, line, COLUMNS[-1],
                           f"expected {len(COLUMNS)} fields ({expected}), found {len(row)} "
                           f"(extra field after this column)")
        for position, (name, text) in enumerate(zip(COLUMNS, row)):
            try:
                value = float(text)
            except ValueError:
                raise _problem(path, line, name, f"not a number: {_shown(text)}") from None
            if not math.isfinite(value):
                raise _problem(path, line, name, f"not a finite number: {_shown(text)}")
            values[index, position] = value
        t, r = float(values[index, 0]), float(values[index, 1])
        if r < 0.0:
            raise _problem(path, line, "range", f"negative range {r:g}")
        if not t > previous_time:
            raise _problem(path, line, "t", f"time {t!r} is not after {previous_time!r} on line "
                                            f"{previous_line}; times must be strictly increasing")
        previous_time, previous_line = t, line

    count = len(values)
    if count < MIN_ROWS:
        last_line = rows[-1][0]
        raise _problem(path, last_line + 1, COLUMNS[0],
                       f"only {count} data row{'s' if count != 1 else ''}; at least {MIN_ROWS} are needed")
    return RangeLog(
        source=str(path),
        t=values[:, 0].copy(),
        range=values[:, 1].copy(),
        a=values[:, 2:4].copy(),
        b=values[:, 4:6].copy(),
    )


def _numbered_rows(handle) -> list[tuple[int, list[str]]]:
    """(1-based line number, fields) of every non-blank CSV record."""
    reader = csv.reader(handle)
    out = []
    for row in reader:
        if not row or all(not field.strip() for field in row) and len(row) == 1:
            continue
        out.append((reader.line_num, row))
    return out


def range_residuals(log) -> np.ndarray:
    """The range residuals range - |a - b| against the ground truth, of a RangeLog or anything with its `range`,
    `a` and `b` (a converted data set's run)."""
    return log.range - np.linalg.norm(log.a - log.b, axis=1)


def range_residual_stats(log: RangeLog) -> tuple[float, float]:
    """(mean, sample variance) of the range residuals range - |a - b| against the ground truth."""
    residual = range_residuals(log)
    return float(np.mean(residual)), float(np.var(residual, ddof=1))


# ----------------------------------------------------------------------------------------------- odometry
def synthesise_displacements(
    log: RangeLog, displacement_variance: float, dt: float, rng: np.random.Generator
) -> np.ndarray:
    """Measured relative displacements delta~_ij,k for k = 1..N-1, shape (N-1, 2).

    delta~_k = (a(t_k) - a(t_{k-1}) + n_a,k) - (b(t_k) - b(t_{k-1}) + n_b,k), with n_a,k and n_b,k independent
    N(0, displacement_variance * h_k / dt * I), h_k = t_k - t_{k-1}: the odometry noise per period dt summed
    over the h_k / dt periods of the interval. The variance-per-period model is drawn once for all
    intervals and each draw scaled by sqrt(h_k / dt), which is the same distribution as drawing from
    IsotropicGaussianNoise(variance=displacement_variance * h_k / dt) interval by interval.
    """
    intervals = np.diff(log.t) / dt
    per_period = IsotropicGaussianNoise(variance=displacement_variance)
    scale = np.sqrt(intervals)[:, None]
    noise_a = per_period.sample(rng, len(intervals)) * scale
    noise_b = per_period.sample(rng, len(intervals)) * scale
    return (np.diff(log.a, axis=0) + noise_a) - (np.diff(log.b, axis=0) + noise_b)


# ----------------------------------------------------------------------------------------------- replay
# Where the filters' range noise came from.
NOISE_CONFIG = "config"
NOISE_GIVEN = "given"
NOISE_TRUTH = "truth-derived"


@dataclass
class RangeReplayResult(ErrorHistory):
    """Every estimator over the runs added so far (per-epoch moments of its errors), and what the filters
    were given."""

    rejected: RunningMoments          # (estimators,) updates each estimator refused, over runs
    range_variance: float             # the pseudo-linear filters' range variance (m^2)
    noise_source: str                 # NOISE_CONFIG, NOISE_GIVEN or NOISE_TRUTH
    range_bias: float                 # mean range residual of the data (m)
    residual_variance: float          # sample variance of the range residuals (m^2)
    raw_range_components: tuple[tuple[float, float, float], ...] = ()   # raw_range's assumed density
    raw_range_gross: tuple[float, float] = (0.0, 1.0)   # its gross-error component (weight, variance m^2)
    raw_range_bias_variance: float = 0.0   # prior variance of its pair-bias state (m^2); 0: no bias state

    @property
    def tuned_on_truth(self) -> bool:
        return self.noise_source == NOISE_TRUTH

    def rejected_per_run(self, name: str) -> float:
        return float(self.rejected.mean[list(self.moments).index(name)])


def filter_params(params: AgentParams, range_variance: float) -> RelativeEstimationParams:
    """The relative-estimation parameters with `range_variance`, validated (model_copy would not check it)."""
    try:
        return updated(params.relative, range_variance=range_variance)
    except ValueError:
        raise ConfigError(
            f"range variance must be a positive finite number, got {range_variance!r}") from None


def truth_params(params: AgentParams, variance: float) -> tuple[RelativeEstimationParams, EstimatorParams]:
    """Every filter given `variance`: the pseudo-linear range variance, and raw_range's density as one
    zero-mean Gaussian of it (its gross-error component, a model of faults, kept from the config)."""
    relative = filter_params(params, variance)
    return relative, updated(relative.params_of("raw_range"), noise_components=((1.0, 0.0, variance),))


def noise_params(
    log: RangeLog, params: AgentParams, range_variance: float | None, truth_variance: bool
) -> tuple[RelativeEstimationParams, EstimatorParams, str]:
    """The relative-estimation parameters the filters run with, raw_range's own, and where their noise came
    from."""
    if truth_variance and range_variance is not None:
        raise ConfigError("give either a range variance or the truth-derived variance, not both")
    if truth_variance:
        _, residual_variance = range_residual_stats(log)
        if not residual_variance > 0.0:
            raise ConfigError(
                f"{log.source}: the ranges match the ground truth exactly (residual variance "
                f"{residual_variance:g} m^2), so no range variance can be derived from the truth")
        return (*truth_params(params, residual_variance), NOISE_TRUTH)
    if range_variance is not None:
        relative = filter_params(params, range_variance)
        return relative, relative.params_of("raw_range"), NOISE_GIVEN
    return params.relative, params.relative.params_of("raw_range"), NOISE_CONFIG


def run_estimators(
    log: RangeLog, relative: RelativeEstimationParams, dt: float, displacement: np.ndarray,
    initial: np.ndarray, names: Sequence[str], raw_range: EstimatorParams | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Every estimator of `names` through the log once: errors (estimators, N) and rejections (estimators,).

    One predict by the displacement of [t_{k-1}, t_k] and one update with the range pair per epoch. When an
    update is refused the last accepted range stays the earlier range of the next pair, and the estimator
    keeps accumulating displacement since that epoch, so the pair still covers exactly its interval. Should
    the first ranges themselves be unusable (beyond max_range), the first usable one opens the sequence.
    raw_range runs with `raw_range` as its parameters if given.
    """
    truth = log.truth
    intervals = np.diff(log.t) / dt
    ranges = log.range
    errors = np.empty((len(names), len(log)))
    rejected = np.zeros(len(names), dtype=np.int64)
    for e, name in enumerate(names):
        own = relative.selecting(raw_range) if name == "raw_range" and raw_range is not None else relative
        estimator = make_relative_estimator(own, initial, dt=dt, name=name)
        last_range: float | None = None
        for k in range(len(log)):
            if k > 0:
                estimator.predict(displacement[k - 1], intervals=float(intervals[k - 1]))
            r = float(ranges[k])
            if last_range is None:
                if 0.0 <= r <= relative.max_range:
                    estimator.mark_range_epoch()
                    last_range = r
                else:
                    rejected[e] += 1
            elif estimator.update(last_range, r).accepted:
                last_range = r
            else:
                rejected[e] += 1
            p = estimator.position
            errors[e, k] = math.hypot(p[0] - truth[k, 0], p[1] - truth[k, 1])
    return errors, rejected


@dataclass(frozen=True)
class ReplayJob:
    """What one Monte Carlo run of a replay needs; the run draws from its own child seed."""

    log: RangeLog
    relative: RelativeEstimationParams
    dt: float
    names: tuple[str, ...]
    seed: np.random.SeedSequence
    raw_range: EstimatorParams | None = None


def replay_run(job: ReplayJob) -> tuple[np.ndarray, np.ndarray]:
    """One run: its own odometry noise and initial estimate p0 ~ N(p(t0), P0), then every estimator."""
    rng = np.random.default_rng(job.seed)
    initial = job.log.truth[0] + rng.normal(0.0, math.sqrt(job.relative.initial_covariance), size=2)
    displacement = synthesise_displacements(job.log, job.relative.displacement_variance, job.dt, rng)
    return run_estimators(job.log, job.relative, job.dt, displacement, initial, job.names, job.raw_range)


def replay(
    log: RangeLog,
    params: AgentParams,
    runs: int = DEFAULT_RUNS,
    seed: int = DEFAULT_SEED,
    range_variance: float | None = None,
    names: Sequence[str] | None = None,
    progress: Callable[[int], None] | None = None,
    truth_variance: bool = False,
    engine: Engine | None = None,
) -> RangeReplayResult:
    """All Monte Carlo runs of every estimator on `log`, each folded into the result as it arrives, in run
    order; `progress(1)` is called after each run. The runs go to `engine` (this process if None).

    The range noise is the config's (`params`) unless `range_variance` (the pseudo-linear filters' only) or
    `truth_variance` (every filter, from the residuals against the truth) says otherwise; see the module.
    """
    if runs < 1:
        raise ConfigError(f"runs must be at least 1, got {runs}")
    if engine is None:
        with Engine() as here:
            result = replay(log, params, runs, seed, range_variance, names, progress, truth_variance, here)
        if here.failures:      # nobody to report them to: a library call fails as a whole
            raise RuntimeError(f"{here.failures[0].run} raised {here.failures[0].error}")
        return result
    bias, residual_variance = range_residual_stats(log)
    relative, raw, source = noise_params(log, params, range_variance, truth_variance)
    names = tuple(names or estimator_names())
    result = RangeReplayResult(
        time=log.elapsed, moments=moments_by_name(names, len(log)), rejected=RunningMoments(len(names)),
        range_variance=float(relative.range_variance), noise_source=source, range_bias=bias,
        residual_variance=residual_variance,
        raw_range_components=tuple(tuple(float(v) for v in c) for c in raw.noise_components),
        raw_range_gross=(float(raw.gross_error_fraction), float(raw.gross_error_variance)),
        raw_range_bias_variance=float(raw.bias_variance),
    )

    def consume(_: int, output) -> None:
        if output is not None:
            errors, rejected = output
            result.add_errors(errors)
            result.rejected.add(rejected)

    jobs = [ReplayJob(log, relative, params.dt, names, child, raw)
            for child in np.random.SeedSequence(seed).spawn(runs)]
    engine.map(replay_run, jobs, progress, lambda n: f"{log.source} run {n} (child {n} of seed {seed})",
               consume=consume)
    if engine.failures and result.runs == 0:
        raise ConfigError(f"every replay run of {log.source} raised: {engine.failures[0].error}")
    return result


# ----------------------------------------------------------------------------------------------- command
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("csv", type=Path,
                        help="ranges with ground truth; header exactly " + ",".join(COLUMNS))
    parser.add_argument("--config", "--params", dest="config", type=Path, default=None,
                        help="agent parameters (YAML, AgentParams), the filters' range noise included; "
                             "default: the paper's Table I")
    parser.add_argument("--seed", type=arguments.seed, default=DEFAULT_SEED,
                        help="root seed of the odometry noise and initial estimates "
                             f"(default {DEFAULT_SEED})")
    parser.add_argument("--runs", type=arguments.positive_int, default=DEFAULT_RUNS,
                        help=f"Monte Carlo runs (default {DEFAULT_RUNS})")
    parser.add_argument("--settle", type=arguments.non_negative_float, default=DEFAULT_SETTLE,
                        help="the 'after' column averages from this many seconds on "
                             f"(default {DEFAULT_SETTLE:g})")
    noise = parser.add_mutually_exclusive_group()
    noise.add_argument("--range-variance", type=arguments.positive_float, default=None,
                       help="range variance of the pseudo-linear filters (m^2), instead of the config's "
                            "relative.range_variance (raw_range keeps its noise_components)")
    noise.add_argument("--truth-variance", action="store_true",
                       help="TUNED ON THE TRUTH: give every filter the sample variance of the ranges' "
                            "residuals against this file's ground truth (raw_range: one Gaussian of it); "
                            "the output is labelled so")
    parser.add_argument("--out", type=arguments.folder, default=Path(DEFAULT_OUT),
                        help=f"directory of the table and figure (default {DEFAULT_OUT})")
    add_engine_arguments(parser)


def density_text(components: Sequence[Sequence[float]]) -> str:
    """A Gaussian mixture as text: 0.8 N(0, 0.4) + 0.2 N(0, 10), variances in m^2."""
    total = sum(c[0] for c in components)
    return " + ".join(f"{w / total:.3g} N({m:g}, {v:.3g})" for w, m, v in components)


def noise_lines(result: RangeReplayResult, config: Path | None) -> list[str]:
    """What range noise the filters ran with and where it came from, a line each."""
    where = f"the config {config}" if config is not None else "the default config (the paper's Table I)"
    if result.noise_source == NOISE_TRUTH:
        origin = ("TRUTH-DERIVED: the sample variance of this file's range residuals against its ground truth "
                  "(--truth-variance); the filters are tuned on the truth they are scored against")
    elif result.noise_source == NOISE_GIVEN:
        origin = f"given on the command line (--range-variance; raw_range's density from {where})"
    else:
        origin = f"from {where}, not from the ground truth"
    return [f"range noise: {origin}",
            f"pseudo-linear filters' range variance: {result.range_variance:.4g} m^2",
            (f"raw_range's noise density (m, m^2): {density_text(result.raw_range_components)}, with a gross-error "
             f"component of weight {result.raw_range_gross[0]:g} and variance {result.raw_range_gross[1]:g}"
             + (f"; a constant pair bias estimated as a state, prior variance {result.raw_range_bias_variance:g} m^2"
                if result.raw_range_bias_variance > 0.0 else ""))]


def run(args: argparse.Namespace) -> int:
    # tqdm (the optional 'lab' extra) is imported by the command that shows a bar, not by `usv-lab --help`.
    from tqdm import tqdm

    params = load_yaml(AgentParams, args.config) if args.config is not None else AgentParams()
    log = parse_csv(args.csv)
    duration = float(log.elapsed[-1])
    if args.settle > duration:
        raise ConfigError(
            f"--settle {args.settle:g} s is beyond the end of {args.csv} ({duration:g} s of data)")

    steps = np.diff(log.t)
    print(f"{args.csv}: {len(log)} ranges over {duration:.3f} s (interval median {np.median(steps):.3f} s, "
          f"max {np.max(steps):.3f} s)")
    with engine_from(args) as engine, tqdm(total=args.runs, desc="replay runs", unit="run", file=sys.stderr) as bar:
        result = replay(log, params, runs=args.runs, seed=args.seed, range_variance=args.range_variance,
                        truth_variance=args.truth_variance, progress=bar.update, engine=engine)
        where = engine.where()
    summary = [
        f"mean range bias (range - |a - b|): {result.range_bias:+.4f} m (not removed)",
        f"range residual sample variance: {result.residual_variance:.4g} m^2",
        *noise_lines(result, args.config),
        (f"displacement variance: {params.relative.displacement_variance:g} m^2 per dt = {params.dt:g} s, "
         f"per end; runs: {result.runs} of {args.runs}, seed: {args.seed}; ran on {where}"),
        *(note.removeprefix("- ") for note in campaign_notes(engine)),
    ]
    for line in summary:
        print(line)

    settle = args.settle
    header = ["estimator", "time-avg RMSE (m)", f"time-avg RMSE after {settle:g} s (m)", "final RMSE (m)",
              "rejected updates per run"]
    rows = [[LABELS.get(name, name), result.time_averaged_rmse(name), result.time_averaged_rmse(name, settle),
             result.final_rmse(name), result.rejected_per_run(name)] for name in result.moments]
    table = markdown_table(header, rows)
    print(table)

    out: Path = args.out
    stem = Path(args.csv).stem
    markdown_path, figure_path = out / f"replay_{stem}.md", out / f"replay_{stem}.png"
    out.mkdir(parents=True, exist_ok=True)
    title = f"# Replay of `{Path(args.csv).name}`"
    if result.tuned_on_truth:
        title += ": filters tuned on the ground truth"
    markdown = "\n".join([
        title,
        "",
        "```",
        invocation(args),
        "```",
        "",
        (f"- {len(log)} ranges over {duration:.3f} s; interval median {np.median(steps):.3f} s, "
         f"max {np.max(steps):.3f} s"),
        *(f"- {line}" for line in summary),
        "- RMSE over runs at each range epoch; time averages weight epochs by time (trapezoid rule)",
        "",
        table,
        "",
        f"![RMSE over time]({figure_path.name})",
        "",
    ])
    markdown_path.write_text(markdown, encoding="utf-8")
    rmse_figure(result.time, {name: (result.rmse(name), result.spread(name)) for name in result.moments},
                f"Replay of {Path(args.csv).name} ({args.runs} runs)", figure_path)
    print(f"wrote {markdown_path} and {figure_path}")
    return report_failures(engine)
