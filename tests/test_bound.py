"""lab/experiments/bound.py: Fisher information of the range-noise models and the posterior Cramér–Rao bound, each against
values worked out another way (closed forms, a direct grid integration, the joint information matrix)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.core.range_noise import GaussianMixtureNoise, GaussianNoise, LogNormalNoise, MixtureNoise
from lab.experiments.bound import fisher_information, pcrlb, rms_bound
from lab.experiments.comparison import ComparisonConfig, nees_band, relative_trajectory, run_comparison

TABLE_II_GMM = GaussianMixtureNoise(outlier_fraction=0.2, variance=0.4, outlier_variance=10.0)
TABLE_II_LOGNORMAL = LogNormalNoise(log_variance=0.7, shift=0.75)


def _grid_fisher(density, lower: float, upper: float, points: int = 2_000_001) -> float:
    """∫ f'^2 / f on a uniform grid, f' by central differences: no score, no quad, no change of variable."""
    x = np.linspace(lower, upper, points)
    f = density(x)
    slope = np.gradient(f, x)
    safe = f > 1e-280
    integrand = np.zeros_like(f)
    integrand[safe] = slope[safe] ** 2 / f[safe]
    return float(np.trapezoid(integrand, x))


def _normal_pdf(x, variance):
    return np.exp(-0.5 * x * x / variance) / math.sqrt(2 * math.pi * variance)


# ---- Fisher information --------------------------------------------------------------------------------

@pytest.mark.parametrize("variance", [1e-4, 0.4, 1.0, 2.32, 10.0, 1e3])
def test_gaussian_fisher_information_is_one_over_variance(variance):
    assert fisher_information(GaussianNoise(variance=variance)) == pytest.approx(1 / variance, rel=1e-6)


def test_noiseless_gaussian_has_infinite_information():
    assert fisher_information(GaussianNoise(variance=0.0)) == math.inf


@pytest.mark.parametrize("eps", [0.0, 0.3, 1.0])
def test_mixture_of_coinciding_components_is_the_gaussian(eps):
    noise = GaussianMixtureNoise(outlier_fraction=eps, variance=0.7, outlier_variance=0.7)
    assert fisher_information(noise) == pytest.approx(1 / 0.7, rel=1e-9)


def test_mixture_with_one_component_left_is_that_component():
    assert fisher_information(GaussianMixtureNoise(outlier_fraction=0.0, variance=0.4, outlier_variance=10.0)) \
        == pytest.approx(2.5, rel=1e-9)
    assert fisher_information(GaussianMixtureNoise(outlier_fraction=1.0, variance=0.4, outlier_variance=10.0)) \
        == pytest.approx(0.1, rel=1e-9)


def test_table_ii_mixture_against_a_direct_grid_integration():
    value = fisher_information(TABLE_II_GMM)

    def density(x):
        return 0.8 * _normal_pdf(x, 0.4) + 0.2 * _normal_pdf(x, 10.0)

    reference = _grid_fisher(density, -80.0, 80.0)
    assert value == pytest.approx(reference, rel=1e-5)
    assert value == pytest.approx(1.6253, abs=1e-4)          # the issue's ~1.63 m^-2
    # Between the Gaussian of the same variance (the least informative) and the convexity bound.
    assert 1 / TABLE_II_GMM.total_variance < value < 0.8 / 0.4 + 0.2 / 10.0


def test_a_calibrated_mixture_against_closed_forms_and_a_grid():
    # One shifted component: 1 / v, wherever it sits. Two far apart with one variance: each alone, 1 / v.
    assert fisher_information(MixtureNoise(components=((1.0, 3.0, 0.25),))) == pytest.approx(4.0, rel=1e-9)
    apart = MixtureNoise(components=((0.3, -5.0, 0.01), (0.7, 5.0, 0.01)))
    assert fisher_information(apart) == pytest.approx(100.0, rel=1e-9)
    # Zero means: the Table II mixture written as a calibration gives its value.
    assert fisher_information(MixtureNoise(components=TABLE_II_GMM.mixture())) == pytest.approx(
        fisher_information(TABLE_II_GMM), rel=1e-9)
    skewed = MixtureNoise(components=((0.9, 0.1, 0.02), (0.1, -0.4, 0.5)))

    def density(x):
        return 0.9 * _normal_pdf(x - 0.1, 0.02) + 0.1 * _normal_pdf(x + 0.4, 0.5)

    assert fisher_information(skewed) == pytest.approx(_grid_fisher(density, -30.0, 30.0), rel=1e-5)


@pytest.mark.parametrize(("log_variance", "shift"), [(0.7, 0.75), (0.2, 0.2), (0.05, 0.0), (1.5, 3.0)])
def test_log_normal_against_its_closed_form(log_variance, shift):
    # s(y) = -(1 + ln y / R) / y under y = mu + r_s; E[(1 + Z/R)^2 e^{-2Z}] with Z ~ N(0, R), from
    # E[e^{tZ}] = e^{t^2 R / 2}, E[Z e^{tZ}] = t R e^{t^2 R/2}, E[Z^2 e^{tZ}] = (R + t^2 R^2) e^{t^2 R/2}
    # at t = -2: e^{2R} (1 - 4 + 1/R + 4) = e^{2R} (1 + 1/R). The shift does not enter.
    closed_form = math.exp(2 * log_variance) * (1 + 1 / log_variance)
    value = fisher_information(LogNormalNoise(log_variance=log_variance, shift=shift))
    assert value == pytest.approx(closed_form, rel=1e-8)


def test_table_ii_log_normal_against_a_grid_over_the_noise_itself():
    """Density of mu as the simulator draws it, exp(N(0, R)) - r_s, on a grid over mu (not ln)."""
    r, shift = TABLE_II_LOGNORMAL.log_variance, TABLE_II_LOGNORMAL.shift

    def density(mu):
        y = mu + shift
        out = np.zeros_like(y)
        positive = y > 0
        out[positive] = np.exp(-0.5 * np.log(y[positive]) ** 2 / r) / (y[positive] * math.sqrt(2 * math.pi * r))
        return out

    # The density is flat to all orders at its lower end mu = -r_s; 60 m above covers the tail.
    reference = _grid_fisher(density, -shift, 60.0 - shift, points=4_000_001)
    assert fisher_information(TABLE_II_LOGNORMAL) == pytest.approx(reference, rel=1e-4)
    assert fisher_information(TABLE_II_LOGNORMAL) == pytest.approx(9.8483, abs=1e-4)


def test_log_normal_samples_match_the_density_used():
    """The simulator's draws have the mean and variance of the density integrated above."""
    samples = TABLE_II_LOGNORMAL.sample(np.random.default_rng(7), 400_000)
    assert samples.min() > -TABLE_II_LOGNORMAL.shift
    assert samples.mean() == pytest.approx(TABLE_II_LOGNORMAL.mean, abs=0.01)
    assert samples.var() == pytest.approx(TABLE_II_LOGNORMAL.total_variance, rel=0.03)


# ---- PCRLB -----------------------------------------------------------------------------------------------

def test_radial_motion_without_process_noise_accumulates_along_the_line_of_sight():
    """Q = 0 and a fixed direction u: J_k = J_0 + k I_f u u^T, so along u the bound is 1/sqrt(J0_uu + k I_f)
    and across u it stays at the prior."""
    u = np.array([0.6, 0.8])
    across = np.array([-0.8, 0.6])
    truth = np.outer(np.linspace(3.0, 20.0, 51), u)   # moving radially away
    p0, fisher = 4.0, 1.7
    bound = pcrlb(truth, 0.0, fisher, p0)
    k = np.arange(51)
    along = np.einsum("i,kij,j->k", u, bound.covariance, u)
    sideways = np.einsum("i,kij,j->k", across, bound.covariance, across)
    np.testing.assert_allclose(along, 1 / (1 / p0 + k * fisher), rtol=1e-12)
    np.testing.assert_allclose(sideways, p0, rtol=1e-12)
    np.testing.assert_allclose(bound.rmse, np.sqrt(1 / (1 / p0 + k * fisher) + p0), rtol=1e-12)
    np.testing.assert_allclose(bound.information, 1 / p0 * np.eye(2) + k[:, None, None] * fisher * np.outer(u, u),
                               rtol=1e-12)


def test_first_range_counts_one_more_measurement():
    u = np.array([1.0, 0.0])
    truth = np.outer(np.linspace(5.0, 6.0, 11), u)
    bound = pcrlb(truth, 0.0, 2.0, 1.0, first_range=True)
    np.testing.assert_allclose(bound.covariance[:, 0, 0], 1 / (1 + (np.arange(11) + 1) * 2.0), rtol=1e-12)


def test_alternating_orthogonal_directions_share_the_information():
    """Q = 0, line of sight alternating x, y, x, y, ...: after 2m steps each axis has m ranges."""
    truth = np.array([[7.0, 0.0] if k % 2 else [0.0, 7.0] for k in range(41)])
    p0, fisher = 9.0, 0.5
    bound = pcrlb(truth, 0.0, fisher, p0)
    k = np.arange(41)
    x_ranges = (k + 1) // 2    # steps 1, 3, 5, ... look along x
    y_ranges = k // 2          # steps 2, 4, ... along y
    np.testing.assert_allclose(bound.covariance[:, 0, 0], 1 / (1 / p0 + x_ranges * fisher), rtol=1e-12)
    np.testing.assert_allclose(bound.covariance[:, 1, 1], 1 / (1 / p0 + y_ranges * fisher), rtol=1e-12)
    np.testing.assert_allclose(bound.covariance[:, 0, 1], 0.0, atol=1e-15)
    even = k[k % 2 == 0]
    np.testing.assert_allclose(bound.rmse[even], np.sqrt(2 / (1 / p0 + even / 2 * fisher)), rtol=1e-12)


def _circle(steps: int, radius: float = 10.0, turn: float = 2 * math.pi) -> np.ndarray:
    phase = np.linspace(0.0, turn, steps + 1)
    return radius * np.column_stack([np.cos(phase), np.sin(phase)])


def test_bound_never_rises_without_process_noise():
    bound = pcrlb(_circle(600), 0.0, 1.6, 25.0)
    assert np.all(np.diff(bound.rmse) <= 1e-12)
    assert bound.rmse[0] == pytest.approx(math.sqrt(50.0))


def test_a_full_circle_without_process_noise_gives_each_axis_half():
    """600 ranges at evenly spaced angles 2 pi m / 600 (sum of cos^2 = sum of sin^2 = 300, sum of cos sin
    = 0): the range information is I_f * 300 per axis, isotropic."""
    phase = 2 * math.pi * np.arange(600) / 600
    evenly = 10.0 * np.column_stack([np.cos(phase), np.sin(phase)])
    truth = np.vstack([[3.0, 4.0], evenly])   # step 0 carries no range; steps 1..600 are the evenly spaced ones
    bound = pcrlb(truth, 0.0, 1.6, 25.0)
    np.testing.assert_allclose(bound.information[-1], (1 / 25.0 + 1.6 * 300) * np.eye(2), rtol=1e-10, atol=1e-9)


def test_recursion_matches_the_joint_information_matrix():
    """Build the Fisher information of the whole path x_0..x_K at once (prior on x_0, a Gaussian
    displacement between each pair of steps, a range at each step 1..K), invert it, and read the last
    block: the recursion must give the same J_K^{-1}, for every K."""
    rng = np.random.default_rng(3)
    steps = 12
    truth = rng.normal(0.0, 4.0, size=(steps + 1, 2)) + np.array([6.0, 0.0])
    r_delta, fisher, p0 = 0.05, 1.3, np.array([[3.0, 0.4], [0.4, 2.0]])
    q_inv = np.eye(2) / (2 * r_delta)
    bound = pcrlb(truth, r_delta, fisher, p0)
    for last in range(steps + 1):
        n = last + 1
        joint = np.zeros((2 * n, 2 * n))
        joint[:2, :2] += np.linalg.inv(p0)
        for k in range(1, n):
            a, b = slice(2 * (k - 1), 2 * k), slice(2 * k, 2 * k + 2)
            joint[a, a] += q_inv
            joint[b, b] += q_inv
            joint[a, b] -= q_inv
            joint[b, a] -= q_inv
            u = truth[k] / np.linalg.norm(truth[k])
            joint[b, b] += fisher * np.outer(u, u)
        tail = np.linalg.inv(joint)[-2:, -2:]
        np.testing.assert_allclose(bound.covariance[last], tail, rtol=1e-9, atol=1e-12)


def test_process_noise_raises_the_bound():
    truth = _circle(300)
    still = pcrlb(truth, 0.0, 1.6, 25.0).rmse
    moving = pcrlb(truth, 1e-3, 1.6, 25.0).rmse
    assert np.all(moving[1:] > still[1:])
    assert moving[0] == still[0]


def test_rms_bound_of_identical_paths_is_the_path_bound_and_averages_squares():
    a, b = _circle(100), _circle(100, radius=3.0, turn=0.2)
    single = pcrlb(a, 1e-6, 1.6, 25.0).rmse
    np.testing.assert_allclose(rms_bound([a, a, a], 1e-6, 1.6, 25.0), single, rtol=1e-14)
    other = pcrlb(b, 1e-6, 1.6, 25.0).rmse
    np.testing.assert_allclose(rms_bound([a, b], 1e-6, 1.6, 25.0), np.sqrt((single ** 2 + other ** 2) / 2))


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError):
        pcrlb(np.array([[1.0, 0.0], [0.0, 0.0]]), 0.0, 1.0, 1.0)
    with pytest.raises(ValueError):
        pcrlb(np.zeros((3, 3)), 0.0, 1.0, 1.0)
    with pytest.raises(ValueError):
        pcrlb(_circle(3), 0.0, math.inf, 1.0)
    with pytest.raises(ValueError):
        pcrlb(_circle(3), 0.0, 1.0, np.eye(3))


# ---- Experiment 1 (`usv-lab compare`) carries the bound -------------------------------------------------

def test_comparison_result_carries_the_bound_of_its_true_path():


    config = ComparisonConfig(runs=2, duration=6.0, estimators=("kf", "mckf"))
    result = run_comparison(config, "gmm")
    _, own, other = relative_trajectory(config)
    relative = config.agent.relative
    expected = pcrlb(own - other, relative.displacement_variance, fisher_information(TABLE_II_GMM),
                     relative.initial_covariance, first_range=True).rmse
    assert result.fisher == pytest.approx(1.6253, abs=1e-4)
    np.testing.assert_allclose(result.bound, expected, rtol=1e-12)
    assert result.bound.shape == result.time.shape
    assert result.bound_at(5.0) == pytest.approx(expected[50])


@pytest.mark.slow
def test_compare_page_has_the_bound_and_the_ratios_and_is_reproducible(tmp_path):
    pytest.importorskip("tqdm")
    pytest.importorskip("matplotlib")
    from lab.cli import main

    pages = []
    for name in ("first", "second"):
        out = tmp_path / name
        assert main(["compare", "--runs", "2", "--seed", "5", "--no-diagnosis", "--workers", "1",
                     "--out", str(out)]) == 0
        assert (out / "comparison_gmm.png").stat().st_size > 0
        assert (out / "comparison_lognormal.png").stat().st_size > 0
        pages.append((out / "estimator_comparison.md").read_text(encoding="utf-8"))
    # Identical from the seed, but for the wall time and the output directory in the command line.
    strip = [[line for line in page.replace("first", "X").replace("second", "X").splitlines()
              if "Wall time" not in line] for page in pages]
    assert strip[0] == strip[1]
    page = pages[0]
    assert "I_f = 1.6253 m^-2" in page and "I_f = 9.8483 m^-2" in page
    for section in page.split("\n## ")[1:]:
        section, consistency = section.split("\nConsistency, over the 2 runs")
        rows = {}
        for line in section.splitlines():
            if line.startswith("| ") and "/ bound at" not in line:
                cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
                rows[cells[0]] = cells[1:]
        bound = rows["Cramér–Rao bound"]
        assert bound[1::2] == ["1.0", "1.0", "1.0"]
        for label in ("RLS", "Huber-RLS", "KF", "AKF", "MCKF", "batch least squares (offline)"):
            cells = rows[label]
            for t in range(3):
                rmse, ratio = float(cells[2 * t]), float(cells[2 * t + 1])
                assert ratio == pytest.approx(rmse / float(bound[2 * t]), rel=0.01, abs=0.06)
                assert ratio > 1.0
        # Every estimator has its worst-run ratio and mean NEES at the three horizons; the two-run band.
        low, high = nees_band(2)
        assert f"inside [{low:.2f}, {high:.2f}]" in consistency
        table = [line for line in consistency.splitlines() if line.startswith("| ")][1:]
        assert sorted(line.split("|")[1].strip() for line in table) == sorted(
            ("RLS", "Huber-RLS", "KF", "AKF", "MCKF", "raw_range"))
        for line in table:
            cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
            assert float(cells[1]) > 0 and len(cells) == 5


def test_nees_band_is_the_chi_square_quantiles_of_the_mean():
    # chi^2 with 200 degrees of freedom: 2.5 % and 97.5 % quantiles 162.728 and 241.058 (tables).
    low, high = nees_band(100)
    assert low == pytest.approx(1.62728, abs=1e-4) and high == pytest.approx(2.41058, abs=1e-4)
    # One run: chi^2(2) is exponential with mean 2, quantiles -2 ln(1 - q).
    low, high = nees_band(1)
    assert low == pytest.approx(-2 * math.log(0.975)) and high == pytest.approx(-2 * math.log(0.025))


def test_nees_of_each_run_uses_the_estimators_own_covariance():
    config = ComparisonConfig(runs=3, duration=3.0, estimators=("kf", "raw_range"))
    result = run_comparison(config, "gmm")
    assert set(result.nees) == {"kf", "raw_range"}
    for name in ("kf", "raw_range"):
        assert result.nees[name].count.tolist() == [3] * len(result.time)
        assert np.all(result.nees[name].mean >= 0)
    # At the start every estimator holds the initial estimate with P_0 = initial_covariance * I: the mean
    # NEES is the mean squared error over P_0.
    p0 = config.agent.relative.initial_covariance
    assert result.mean_nees_at("kf", 0.0) == pytest.approx(result.rmse("kf")[0] ** 2 / p0, rel=1e-12)
