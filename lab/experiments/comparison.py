"""Experiment 1, the paper's Figs. 4 and 5: five inter-vessel estimators on the same noisy data.

Two vessels move on the desired circles (radius r*, yaw rate omega*, half a turn apart, no target and no
controller: the trajectories are exact), so only the estimators differ. Each Monte Carlo run draws its own
range noise, displacement noise and initial estimate from a child of the experiment's seed; every estimator
of a run sees exactly the same numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import Field
from scipy.stats import chi2

from agent.config import PositiveFloat, StrictModel, updated
from agent.core.checks import valid_range
from agent.core.estimators import estimator_names, make_relative_estimator
from agent.core.params import AgentParams, RelativeEstimationParams
from agent.core.range_noise import GaussianMixtureNoise, LogNormalNoise, RangeNoise
from lab.experiments.bound import fisher_information, rms_bound
from lab.harness.errors import ErrorHistory, RunningMoments, moments_by_name
from lab.harness.parallel import Engine
from sim_bridge.noise import FILTER_NOISE_DESCRIPTION, FilterNoise, IsotropicGaussianNoise, assumed_relative


class ComparisonConfig(StrictModel):
    """One estimator comparison; YAML under configs/experiments/."""

    duration: PositiveFloat = Field(60.0, description="simulated seconds per run")
    radius: PositiveFloat = Field(5.0, description="r*, radius of both circles (m)")
    runs: int = Field(100, ge=1, le=100_000, description="Monte Carlo runs per noise model")
    seed: int = Field(2024, ge=0, description="root seed of every random number")
    settle_time: float = Field(10.0, ge=0, description="the 'after' column averages from this time on (s)")
    filter_noise: FilterNoise = Field("world", description=FILTER_NOISE_DESCRIPTION)
    noise_models: dict[str, RangeNoise] = Field(
        default_factory=lambda: {
            "gmm": GaussianMixtureNoise(outlier_fraction=0.2, variance=0.4, outlier_variance=10.0),
            "lognormal": LogNormalNoise(log_variance=0.7, shift=0.75),
        },
        description="range noise models, by name (Sec. VI-A: the paper's Fig. 4 and Fig. 5 settings)",
    )
    variance_scale: PositiveFloat = Field(
        1.0, description="multiplies the filters' range variance; 1 is the derivation, others diagnose"
    )
    estimators: tuple[str, ...] = Field(default_factory=estimator_names,
                                        description="the estimators compared (default: all)")
    agent: AgentParams = AgentParams()


# A run's RMSE is judged against the bound from here on (s): past the fix, where a run far above the bound is a
# fault of the estimator and not a slow start.
WORST_RUN_FROM = 30.0


@dataclass
class ComparisonResult(ErrorHistory):
    """Every estimator over the runs of one noise model, reduced as the runs arrive (`add_run`): per-epoch
    moments of the error norms and of the NEES, and per run only what the page needs of it."""

    noise_name: str
    range_bias: float                 # mean of the range noise model
    filter_range_variance: float
    fisher: float                     # Fisher information of the range noise as a location family (m^-2)
    bound: np.ndarray                 # (K+1,) posterior Cramér–Rao bound on the RMSE over runs (m)
    nees: dict[str, RunningMoments]   # estimator -> e^T P^-1 e with the estimator's own P, at each epoch
    least_squares: RunningMoments     # (len(LS_TIMES),) batch least-squares error at LS_TIMES
    worst_late: dict[str, float]      # estimator -> the largest over runs of a run's RMSE from WORST_RUN_FROM on
    iteration_sum: int = 0            # MCKF fixed-point iterations over every update that iterated
    iteration_count: int = 0
    iteration_max: int = 0

    def add_run(self, errors: np.ndarray, iterations: np.ndarray, least_squares: np.ndarray, nees: np.ndarray
                ) -> None:
        """One run as `run_once` returns it."""
        self.add_errors(errors)
        late = self.time >= WORST_RUN_FROM - 1e-9
        for e, name in enumerate(self.moments):
            self.nees[name].add(nees[e])
            if late.any():
                self.worst_late[name] = max(self.worst_late[name], float(np.sqrt(np.mean(errors[e, late] ** 2))))
        self.least_squares.add(least_squares)
        iterated = iterations[iterations > 0]
        self.iteration_sum += int(iterated.sum())
        self.iteration_count += len(iterated)
        self.iteration_max = max(self.iteration_max, int(iterated.max(initial=0)))

    def bound_at(self, t: float) -> float:
        """The bound at the epoch nearest to time t (s)."""
        return float(self.bound[int(np.argmin(np.abs(self.time - t)))])

    def rmse_at(self, name: str, t: float) -> float:
        """The RMSE over runs of one estimator at the epoch nearest to time t (s)."""
        return float(self.rmse(name)[int(np.argmin(np.abs(self.time - t)))])

    def mean_nees_at(self, name: str, t: float) -> float:
        """The mean over runs of one estimator's NEES at the epoch nearest to time t (s); 2 if consistent."""
        return float(self.nees[name].mean[int(np.argmin(np.abs(self.time - t)))])

    def worst_run_ratio(self, name: str) -> float:
        """The largest over runs of one run's RMSE over time from WORST_RUN_FROM on, divided by the bound's RMS
        over the same epochs: how far the worst run strays from the bound."""
        late = self.time >= WORST_RUN_FROM - 1e-9
        return self.worst_late[name] / math.sqrt(np.mean(self.bound[late] ** 2))

    @property
    def mean_iterations(self) -> float:
        return self.iteration_sum / self.iteration_count if self.iteration_count else math.nan


def nees_band(runs: int, dof: int = 2, level: float = 0.95) -> tuple[float, float]:
    """The two-sided band of the mean NEES over `runs` independent runs of a consistent estimator:
    runs * mean ~ chi^2(runs * dof)."""
    low, high = chi2.ppf([(1 - level) / 2, (1 + level) / 2], runs * dof)
    return float(low / runs), float(high / runs)


def relative_trajectory(config: ComparisonConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Time, and the true positions of vessel i and j, each (K+1, 2)."""
    dt = config.agent.dt
    steps = int(round(config.duration / dt))
    t = np.arange(steps + 1) * dt
    phase = config.agent.control.yaw_rate * t
    own = config.radius * np.column_stack([np.cos(phase), np.sin(phase)])
    other = config.radius * np.column_stack([np.cos(phase + math.pi), np.sin(phase + math.pi)])
    return t, own, other


def position_bound(config: ComparisonConfig, noise: RangeNoise, paths: list[np.ndarray]) -> tuple[float, np.ndarray]:
    """The noise model's Fisher information, and the posterior Cramér–Rao bound (lab/experiments/bound.py) on the RMSE
    over runs along the runs' true paths p_ij = p_i - p_j: sqrt(mean over runs of trace(J_k^{-1})), the floor
    of the mean squared error the RMSE curves square-average. Process noise Q = 2 R_delta I (both vessels'
    odometry, (15)); J_0 = P_0^{-1} (the initial estimate); one range per epoch, counting the one at epoch 0,
    which the pair filters use in their first update."""
    relative = config.agent.relative
    fisher = fisher_information(noise)
    bound = rms_bound(paths, relative.displacement_variance, fisher, relative.initial_covariance,
                      first_range=True)
    return fisher, bound


def filter_range_variance(noise: RangeNoise, config: ComparisonConfig) -> float:
    """The range variance the filters are given to build R_z, as `config.filter_noise` says, x variance_scale."""
    base = noise.total_variance if config.filter_noise == "world" else config.agent.relative.range_variance
    return base * config.variance_scale


def filter_relative(noise: RangeNoise, config: ComparisonConfig, name: str | None = None
                    ) -> RelativeEstimationParams:
    """The relative-estimation parameters estimator `name` (default: the configured one) is given in a run, as
    `config.filter_noise` says: assuming the run's noise model, or as configured with R_z's range variance
    x variance_scale."""
    relative = config.agent.relative
    if config.filter_noise == "configured":
        return updated(relative, range_variance=filter_range_variance(noise, config))
    return assumed_relative(relative, noise, config.variance_scale, estimator=name)


def run_once(config: ComparisonConfig, noise: RangeNoise, seed_sequence: np.random.SeedSequence
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One Monte Carlo run: errors (estimators, K+1), MCKF iterations (K,), batch LS errors at LS_TIMES, NEES
    (estimators, K+1)."""
    rng = np.random.default_rng(seed_sequence)
    t, own, other = relative_trajectory(config)
    truth = own - other
    steps = len(t) - 1
    relative = config.agent.relative
    ranges = np.linalg.norm(truth, axis=1) + noise.sample(rng, steps + 1)
    odometry_noise = IsotropicGaussianNoise(variance=relative.displacement_variance)
    measured_own = np.diff(own, axis=0) + odometry_noise.sample(rng, steps)
    measured_other = np.diff(other, axis=0) + odometry_noise.sample(rng, steps)
    displacement = measured_own - measured_other
    initial = truth[0] + rng.normal(0.0, math.sqrt(relative.initial_covariance), size=2)

    errors = np.empty((len(config.estimators), steps + 1))
    nees = np.empty((len(config.estimators), steps + 1))
    iterations = np.zeros(steps, dtype=np.int16)
    for e, name in enumerate(config.estimators):
        params = filter_relative(noise, config, name)
        estimator = make_relative_estimator(params, initial, dt=config.agent.dt, name=name)
        errors[e, 0] = math.hypot(*(initial - truth[0]))
        nees[e, 0] = _nees(initial - truth[0], estimator.covariance)
        for k, outcome in run_estimator(estimator, displacement, ranges, params.max_range):
            if name == "mckf" and outcome is not None:
                iterations[k - 1] = outcome.iterations
            p = estimator.position
            errors[e, k] = math.hypot(p[0] - truth[k, 0], p[1] - truth[k, 1])
            nees[e, k] = _nees(p - truth[k], estimator.covariance)
    least_squares = np.array([
        np.linalg.norm(batch_least_squares(displacement[:k], ranges[: k + 1]) - truth[k]) if k <= steps
        else math.nan
        for k in (int(round(t_ls / config.agent.dt)) for t_ls in LS_TIMES)
    ])
    return errors, iterations, least_squares, nees


def _nees(error: np.ndarray, covariance: np.ndarray) -> float:
    """e^T P^-1 e for a 2x2 P, closed form."""
    (a, b), (_, d) = covariance
    x, y = error
    return float((d * x * x - 2 * b * x * y + a * y * y) / (a * d - b * b))


def run_estimator(estimator, displacement: np.ndarray, ranges: np.ndarray, max_range: float):
    """Feed one pair's displacements and ranges to `estimator` as the agent does (membership.store_ranges,
    NeighbourTrack.advance): an invalid range (a negative draw) is dropped and the displacement carries on to
    the next one, and each range pairs with the last one accepted. Yields (k, the update's outcome or None)
    after step k = 1..K, the estimator then holding its estimate of step k."""
    previous = None
    if valid_range(ranges[0], max_range):
        estimator.mark_range_epoch()
        previous = ranges[0]
    for k in range(1, len(ranges)):
        estimator.predict(displacement[k - 1])
        outcome = None
        if not valid_range(ranges[k], max_range):
            pass
        elif previous is None:
            estimator.mark_range_epoch()
            previous = ranges[k]
        else:
            outcome = estimator.update(previous, ranges[k])
            if outcome.accepted:
                previous = ranges[k]
        yield k, outcome


# Times (s) at which the offline batch least-squares reference is evaluated.
LS_TIMES = (10.0, 30.0, 60.0)


def batch_least_squares(displacement: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """Offline reference: unweighted least squares of every pseudo-linear equation (12) up to epoch K,
    solved for p_K. Not an estimator we ship; it shows what the equations contain when nothing is
    down-weighted, so the consecutive-pair noise telescopes (see docs/estimation.md).

    With p_k = p_K - sum_{m>k} delta_m, equation k reads z_k + delta_k^T sum_{m>k} delta_m = delta_k^T p_K.
    """
    d = displacement
    z = 0.5 * (ranges[1:] ** 2 - ranges[:-1] ** 2 + np.sum(d * d, axis=1))
    later = np.cumsum(d[::-1], axis=0)[::-1] - d  # sum over m > k
    solution, *_ = np.linalg.lstsq(d, z + np.sum(d * later, axis=1), rcond=None)
    return solution


def _run_job(job: tuple[ComparisonConfig, RangeNoise, np.random.SeedSequence]
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return run_once(*job)


def run_comparison(config: ComparisonConfig, noise_name: str, engine: Engine | int = 1, progress=None
                   ) -> ComparisonResult:
    """All Monte Carlo runs for one noise model, each folded into the result as it arrives, in run order;
    `progress(n)` is called as runs finish. A run that raised is left out (`engine.failures` names it). An
    int `engine` is a process pool of that many workers."""
    if isinstance(engine, int):
        with Engine(engine) as pool:
            return run_comparison(config, noise_name, pool, progress)
    noise = config.noise_models[noise_name]
    # One child seed per (noise model, run): adding runs or models never changes an existing run.
    root = np.random.SeedSequence([config.seed, _stable_id(noise_name)])
    jobs = [(config, noise, child) for child in root.spawn(config.runs)]
    t, own, other = relative_trajectory(config)
    # Every run follows the same true path (the seed draws only the noise and the initial estimate), so the
    # RMS over runs of the per-run bound is the bound of that one path: computed once.
    fisher, bound = position_bound(config, noise, [own - other])
    result = ComparisonResult(
        time=t, moments=moments_by_name(config.estimators, len(t)), noise_name=noise_name,
        range_bias=noise.mean, filter_range_variance=filter_range_variance(noise, config), fisher=fisher,
        bound=bound,
        nees=moments_by_name(config.estimators, len(t)), least_squares=RunningMoments(len(LS_TIMES)),
        worst_late=dict.fromkeys(config.estimators, 0.0))

    def consume(_: int, output) -> None:
        if output is not None:
            result.add_run(*output)

    engine.map(_run_job, jobs, progress,
               lambda n: f"{noise_name} run {n} (child {n} of seed [{config.seed}, {_stable_id(noise_name)}])",
               consume=consume)
    return result


def _stable_id(text: str) -> int:
    """A seed word from a name that is the same in every process (unlike hash())."""
    return int.from_bytes(text.encode("utf-8")[:8].ljust(8, b"\0"), "little")
