"""`usv-lab replay`: CSV checking, odometry synthesis, the replay itself and the command end to end."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from agent.config import ConfigError
from agent.core.estimators import estimator_names
from agent.core.params import AgentParams
from lab import cli
from lab.experiments.replay import (
    NOISE_CONFIG,
    NOISE_GIVEN,
    NOISE_TRUTH,
    RangeLog,
    RangeReplayResult,
    parse_csv,
    range_residual_stats,
    replay,
    synthesise_displacements,
)
from lab.harness.errors import RunningMoments, moments_by_name

HEADER = "t,range,ax,ay,bx,by"
GAP_START, GAP_LENGTH = 25.0, 3.0
YAW_RATE, RADIUS, CENTRE = math.pi / 30, 5.0, (3.0, 4.0)


def circle_scenario(seed: int, range_std: float, duration: float) -> tuple[np.ndarray, ...]:
    """End b static at the origin, end a on a circle of radius 5 m about (3, 4) at pi/30 rad/s (0.52 m/s).

    Sampling intervals are uniform in [0.05, 0.2] s (dt = 0.1 s on average) and no range comes for
    GAP_LENGTH seconds after GAP_START. Returns (t, range, a, b).
    """
    rng = np.random.default_rng(seed)
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.05, 0.2, size=int(duration / 0.1)))])
    t = t[t <= duration]
    t = np.where(t > GAP_START, t + GAP_LENGTH, t)
    phase = YAW_RATE * t
    a = np.column_stack([CENTRE[0] + RADIUS * np.cos(phase), CENTRE[1] + RADIUS * np.sin(phase)])
    b = np.zeros_like(a)
    ranges = np.abs(np.linalg.norm(a - b, axis=1) + rng.normal(0.0, range_std, size=len(t)))
    return t, ranges, a, b


def write_csv(path: Path, t, ranges, a, b) -> Path:
    # repr of a Python float round-trips exactly, so the parsed file equals the arrays bit for bit.
    lines = [HEADER] + [
        ",".join(repr(float(v)) for v in (t[k], ranges[k], a[k, 0], a[k, 1], b[k, 0], b[k, 1]))
        for k in range(len(t))
    ]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def with_relative(**relative) -> AgentParams:
    """Table I with the relative-estimation fields overridden (validated)."""
    data = AgentParams().model_dump()
    data["relative"].update(relative)
    return AgentParams.model_validate(data)


# ----------------------------------------------------------------------------------------------- parsing
def test_parse_round_trips_the_file(tmp_path):
    t, ranges, a, b = circle_scenario(seed=0, range_std=0.1, duration=10.0)
    log = parse_csv(write_csv(tmp_path / "ok.csv", t, ranges, a, b))
    assert len(log) == len(t)
    np.testing.assert_array_equal(log.t, t)
    np.testing.assert_array_equal(log.range, ranges)
    np.testing.assert_array_equal(log.truth, a - b)
    np.testing.assert_allclose(log.elapsed, t - t[0])


def test_blank_lines_and_byte_order_mark_are_accepted(tmp_path):
    path = tmp_path / "bom.csv"
    path.write_text("\ufeff" + HEADER + "\n0,1,1,0,0,0\n\n0.1,1,1,0,0,0\n0.2,1,1,0,0,0\n\n", encoding="utf-8")
    assert len(parse_csv(path)) == 3


GOOD = ["0,5,5,0,0,0", "0.1,5,5,0.1,0,0", "0.2,5,5,0.2,0,0"]


@pytest.mark.parametrize(
    ("lines", "line", "column"),
    [
        pytest.param(["t,range,ax,ay,bx,bz", *GOOD], 1, "by", id="wrong header name"),
        pytest.param(["t,range,ax,ay,bx", *GOOD], 1, "by", id="header lacks a column"),
        pytest.param([HEADER + ",cz", *GOOD], 1, "cz", id="header has an extra column"),
        pytest.param(GOOD, 1, "t", id="no header"),
        pytest.param([], 1, "t", id="empty file"),
        pytest.param([HEADER, GOOD[0], "0.1,5,5,0.1,0", GOOD[2]], 3, "by", id="too few fields"),
        pytest.param([HEADER, GOOD[0], GOOD[1], "0.2,5,5,0.2,0,0,9"], 4, "by", id="too many fields"),
        pytest.param([HEADER, GOOD[0], "0.1,5,5,abc,0,0", GOOD[2]], 3, "ay", id="not a number"),
        pytest.param([HEADER, GOOD[0], GOOD[1], "0.2,5,5,0.2,nan,0"], 4, "bx", id="nan"),
        pytest.param([HEADER, "0,5,inf,0,0,0", GOOD[1], GOOD[2]], 2, "ax", id="infinite"),
        pytest.param([HEADER, GOOD[0], "0.1,-0.5,5,0.1,0,0", GOOD[2]], 3, "range", id="negative range"),
        pytest.param([HEADER, GOOD[0], GOOD[1], "0.1,5,5,0.2,0,0"], 4, "t", id="repeated time"),
        pytest.param([HEADER, GOOD[0], GOOD[1], ",,,,,"], 4, "t", id="empty fields"),
        pytest.param([HEADER, GOOD[0], GOOD[1], "0.05,5,5,0.2,0,0"], 4, "t", id="time goes back"),
        pytest.param([HEADER, GOOD[0], GOOD[1]], 4, "t", id="only two rows"),
    ],
)
def test_malformed_file_names_file_line_and_column(tmp_path, lines, line, column):
    path = tmp_path / "bad.csv"
    path.write_text("".join(f"{text}\n" for text in lines), encoding="utf-8")
    with pytest.raises(ConfigError) as caught:
        parse_csv(path)
    message = str(caught.value)
    assert "\n" not in message
    assert str(path) in message
    assert f"line {line}," in message
    assert f"column '{column}'" in message


def test_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        parse_csv(tmp_path / "absent.csv")


# ----------------------------------------------------------------------------------------------- odometry
def test_displacement_covers_exactly_the_interval_between_range_epochs(tmp_path):
    t, ranges, a, b = circle_scenario(seed=1, range_std=0.0, duration=40.0)
    b = b + np.column_stack([0.2 * t, -0.1 * t])  # let end b move too, so both ends count
    log = parse_csv(write_csv(tmp_path / "gap.csv", t, ranges, a, b))
    steps = np.diff(log.t)
    gap = int(np.argmax(steps))
    assert steps[gap] > GAP_LENGTH  # the scenario really has a gap

    measured = synthesise_displacements(log, displacement_variance=1e-30, dt=0.1,
                                        rng=np.random.default_rng(0))
    true = np.diff(a, axis=0) - np.diff(b, axis=0)
    assert measured.shape == (len(t) - 1, 2)
    np.testing.assert_allclose(measured, true, rtol=0, atol=1e-9)
    assert np.linalg.norm(measured[gap]) > 1.0  # across the gap the vessels moved metres, and that is used


def test_displacement_noise_grows_linearly_with_the_interval():
    # Intervals alternate between dt and 10 dt; each end's noise variance per axis is R * h / dt.
    count = 4001
    t = np.cumsum(np.where(np.arange(count) % 2 == 0, 0.1, 1.0))
    zeros = np.zeros((count, 2))
    log = RangeLog("noise", t, np.ones(count), zeros, zeros)
    noise = synthesise_displacements(log, displacement_variance=0.5, dt=0.1, rng=np.random.default_rng(3))
    steps = np.diff(t)
    short = noise[np.isclose(steps, 0.1)]
    long = noise[np.isclose(steps, 1.0)]
    # The relative displacement carries both ends' noise: 2 R h / dt. 2000 samples per axis and group give a
    # sample variance within about 3 % (1 sigma), so a 15 % tolerance cannot fail by chance in practice.
    assert np.var(short, axis=0) == pytest.approx([1.0, 1.0], rel=0.15)
    assert np.var(long, axis=0) == pytest.approx([10.0, 10.0], rel=0.15)
    assert abs(np.mean(long)) < 0.3


# ----------------------------------------------------------------------------------------------- replay
def test_estimators_converge_on_a_noisy_irregular_log_with_a_gap():
    t, ranges, a, b = circle_scenario(seed=101, range_std=0.1, duration=120.0)
    log = RangeLog("circle", t, ranges, a, b)
    params = AgentParams()
    # The filters are tuned on the truth here (explicitly), so that the KF's consistency can be checked.
    result = replay(log, params, runs=5, seed=4, truth_variance=True)

    assert set(result.moments) == set(estimator_names()) and result.runs == 5
    for name in estimator_names():
        assert result.moments[name].count.tolist() == [5] * len(t), name
        assert np.isfinite(result.rmse(name)).all() and math.isfinite(result.largest_error(name)), name
        assert result.rejected.maximum[list(result.moments).index(name)] == 0, name
        assert math.isfinite(result.time_averaged_rmse(name, 10.0))

    # The range variance came from the data: range_std^2 = 0.01 m^2, estimated from ~1000 residuals, and
    # raw_range was given one Gaussian of it.
    assert result.noise_source == NOISE_TRUTH and result.tuned_on_truth
    assert result.range_variance == pytest.approx(0.01, rel=0.15)
    assert result.raw_range_components == ((1.0, 0.0, result.range_variance),)
    assert abs(result.range_bias) < 0.02

    # Every run starts from p0 ~ N(p, 25 I): an RMS error of sqrt(50) = 7.1 m.
    initial = result.rmse("kf")[0]
    assert 3.0 < initial < 12.0
    # The KF is consistent here (Gaussian ranges with the right variance). After two turns of 0.52 m/s
    # motion with 0.1 m range noise its final error is a few decimetres (median 0.16 m, worst 0.78 m over
    # 30 generated logs); 1 m is 7 times below the initial error, so a filter that did not converge fails.
    assert result.final_rmse("kf") < 1.0
    # The MCKF with Table I's bandwidth sigma3 = 0.8 down-weights ordinary Gaussian innovations and ends
    # up overconfident, so it converges more slowly than the KF (median 1.1 m, worst 3.4 m over the same
    # 30 logs). Here it must still at least halve the initial error, averaged after the first minute too.
    assert result.final_rmse("mckf") < 0.5 * initial
    assert result.time_averaged_rmse("mckf", 60.0) < 0.5 * initial
    # ... and given a bandwidth suited to Gaussian noise it does as well as the KF.
    wide = with_relative(estimator={"name": "mckf", "bandwidths": (1e4, 1e4, 5.0)})
    assert replay(log, wide, runs=5, seed=4, names=("mckf",), truth_variance=True).final_rmse("mckf") < 1.0


def test_exact_data_keeps_every_estimator_on_the_truth_across_the_gap():
    # Exact ranges and (almost) noiseless odometry, starting (almost) at the truth: by the cosine law every
    # pseudo-measurement is then exactly delta^T p, so any estimator stays on the truth, across the gap too,
    # unless a displacement or range pair covers the wrong interval.
    t, ranges, a, b = circle_scenario(seed=2, range_std=0.0, duration=40.0)
    log = RangeLog("exact", t, ranges, a, b)
    params = with_relative(displacement_variance=1e-24, initial_covariance=1e-14)
    result = replay(log, params, runs=2, seed=5, range_variance=1e-4)
    assert result.noise_source == NOISE_GIVEN and result.range_variance == 1e-4
    for name in estimator_names():
        assert result.largest_error(name) < 1e-5, name


def test_a_refused_range_keeps_the_last_accepted_one_for_the_next_pair():
    t, ranges, a, b = circle_scenario(seed=2, range_std=0.0, duration=40.0)
    ranges = ranges.copy()
    ranges[0] = 5000.0  # beyond max_range: the sequence opens at the next range
    ranges[len(t) // 2] = 5000.0  # refused mid-way: the pair after it must still use the range before it
    log = RangeLog("refused", t, ranges, a, b)
    params = with_relative(displacement_variance=1e-24, initial_covariance=1e-14)
    result = replay(log, params, runs=1, seed=5, range_variance=1e-4)
    for name in estimator_names():
        # Exactly the two bad ranges are refused; pairing the next range with a refused one would refuse more.
        assert result.rejected_per_run(name) == 2, name
        assert result.largest_error(name) < 1e-5, name


def test_estimators_are_driven_epoch_by_epoch_with_the_interval_lengths(monkeypatch):
    # Record the calls replay makes: one epoch mark, then per epoch one predict by that interval's
    # displacement with intervals = h / dt, and one update pairing the previous range with the current one.
    from lab.experiments import replay as module

    calls: list[tuple] = []
    real_make = module.make_relative_estimator

    class Spy:
        def __init__(self, estimator):
            self.estimator = estimator

        def mark_range_epoch(self):
            calls.append(("mark",))
            self.estimator.mark_range_epoch()

        def predict(self, displacement, intervals=1.0):
            calls.append(("predict", np.array(displacement, dtype=float), intervals))
            return self.estimator.predict(displacement, intervals)

        def update(self, range_prev, range_now):
            calls.append(("update", range_prev, range_now))
            return self.estimator.update(range_prev, range_now)

        @property
        def position(self):
            return self.estimator.position

    monkeypatch.setattr(module, "make_relative_estimator", lambda *a, **k: Spy(real_make(*a, **k)))
    t = np.array([0.0, 0.1, 0.35, 2.35])  # irregular, with a 2 s gap
    a = np.column_stack([t, 0.5 * t * t])
    b = np.column_stack([np.full(4, 3.0), -t])
    ranges = np.array([3.0, 2.9, 2.7, 2.0])
    log = RangeLog("spy", t, ranges, a, b)
    params = with_relative(displacement_variance=1e-24)
    replay(log, params, runs=1, seed=0, range_variance=0.1, names=("kf",))

    assert [c[0] for c in calls] == ["mark", "predict", "update", "predict", "update", "predict", "update"]
    predicts = [c for c in calls if c[0] == "predict"]
    np.testing.assert_allclose([c[2] for c in predicts], [1.0, 2.5, 20.0])
    np.testing.assert_allclose([c[1] for c in predicts], np.diff(a - b, axis=0), atol=1e-9)
    assert [c[1:] for c in calls if c[0] == "update"] == [(3.0, 2.9), (2.9, 2.7), (2.7, 2.0)]


def test_range_statistics_and_a_truth_variance_needs_residuals():
    t, ranges, a, b = circle_scenario(seed=2, range_std=0.0, duration=5.0)
    biased = RangeLog("biased", t, ranges + 0.25, a, b)
    bias, variance = range_residual_stats(biased)
    assert bias == pytest.approx(0.25) and variance == pytest.approx(0.0, abs=1e-20)
    # Exact ranges leave no variance to derive from the truth; the config's noise still works.
    with pytest.raises(ConfigError, match="from the truth"):
        replay(biased, AgentParams(), runs=1, truth_variance=True)
    assert replay(biased, AgentParams(), runs=1, names=("kf",)).noise_source == NOISE_CONFIG
    with pytest.raises(ConfigError, match="not both"):
        replay(biased, AgentParams(), runs=1, range_variance=1.0, truth_variance=True)


def test_noise_comes_from_the_config_by_default_not_from_the_truth():
    # Two logs on one path, range noise 0.05 m and 0.7 m: by default the filters get the config's noise for
    # both, whatever the residuals against the truth say.
    quiet = RangeLog("quiet", *circle_scenario(seed=5, range_std=0.05, duration=30.0))
    noisy = RangeLog("noisy", *circle_scenario(seed=5, range_std=0.7, duration=30.0))
    components = [(0.9, 0.05, 0.02), (0.1, 0.0, 1.0)]
    params = with_relative(range_variance=0.3, estimator={"name": "raw_range", "noise_components": components})
    for log in (quiet, noisy):
        result = replay(log, params, runs=1, seed=3)
        assert result.noise_source == NOISE_CONFIG and not result.tuned_on_truth
        assert result.range_variance == 0.3
        assert result.raw_range_components == ((0.9, 0.05, 0.02), (0.1, 0.0, 1.0))
        assert result.raw_range_gross == (0.001, 1e4)
    assert range_residual_stats(noisy)[1] > 100 * range_residual_stats(quiet)[1]


def test_a_config_sets_the_noise_raw_range_assumes():
    # raw_range ignores range_variance; its density is its noise_components, so a config for
    # real data must reach it: a different density gives different raw_range estimates from the same draws.
    log = RangeLog("circle", *circle_scenario(seed=8, range_std=0.1, duration=40.0))
    table_two = replay(log, AgentParams(), runs=2, seed=6, names=("raw_range", "kf"))
    narrow_density = {"name": "raw_range", "noise_components": [(1.0, 0.0, 0.01)]}
    narrow = replay(log, with_relative(estimator=narrow_density), runs=2, seed=6, names=("raw_range", "kf"))
    other_variance = replay(log, with_relative(range_variance=0.01), runs=2, seed=6, names=("raw_range", "kf"))
    assert not np.array_equal(table_two.rmse("raw_range"), narrow.rmse("raw_range"))
    np.testing.assert_array_equal(table_two.rmse("kf"), narrow.rmse("kf"))
    np.testing.assert_array_equal(table_two.rmse("raw_range"), other_variance.rmse("raw_range"))
    assert not np.array_equal(table_two.rmse("kf"), other_variance.rmse("kf"))


def test_rmse_summaries_weight_irregular_epochs_by_time():
    # Two runs with errors 3 and 4 at each epoch -> RMSE sqrt(12.5); then the last epoch has RMSE 10.
    result = RangeReplayResult(time=np.array([0.0, 1.0, 10.0]), moments=moments_by_name(["kf"], 3),
                               rejected=RunningMoments(1), range_variance=1.0, noise_source=NOISE_GIVEN,
                               range_bias=0.0, residual_variance=1.0)
    for run in ([3.0, 3.0, 10.0], [4.0, 4.0, 10.0]):
        result.add_errors(np.array([run]))
    rmse = math.sqrt(12.5)
    np.testing.assert_allclose(result.rmse("kf"), [rmse, rmse, 10.0])
    np.testing.assert_allclose(result.spread("kf"), [0.5, 0.5, 0.0])
    # Trapezoid over [0, 10]: the 9 s between t = 1 and t = 10 dominate, unlike a plain mean over epochs.
    assert result.time_averaged_rmse("kf") == pytest.approx((rmse * 1.0 + (rmse + 10.0) / 2 * 9.0) / 10.0)
    assert result.time_averaged_rmse("kf", start=1.0) == pytest.approx((rmse + 10.0) / 2)
    assert result.time_averaged_rmse("kf", start=10.0) == pytest.approx(10.0)
    assert result.final_rmse("kf") == pytest.approx(10.0)


def test_same_seed_same_errors_and_another_seed_differs():
    t, ranges, a, b = circle_scenario(seed=7, range_std=0.2, duration=15.0)
    log = RangeLog("seeded", t, ranges, a, b)
    first = replay(log, AgentParams(), runs=3, seed=11)
    again = replay(log, AgentParams(), runs=3, seed=11)
    other = replay(log, AgentParams(), runs=3, seed=12)
    for name in estimator_names():
        for summary in ("rmse", "spread"):
            np.testing.assert_array_equal(getattr(first, summary)(name), getattr(again, summary)(name))
            assert not np.array_equal(getattr(first, summary)(name), getattr(other, summary)(name))
    # Runs of one replay draw different initial estimates.
    assert first.spread("kf")[0] > 0.0


# ----------------------------------------------------------------------------------------------- command
@pytest.fixture
def replay_only(monkeypatch):
    """The CLI with only the replay subcommand, so this file does not depend on the other lab commands."""
    monkeypatch.setattr(cli, "SUBCOMMANDS", {"replay": cli.SUBCOMMANDS["replay"]})


@pytest.mark.slow
def test_cli_writes_table_and_figure(tmp_path, replay_only, capsys, monkeypatch):
    t, ranges, a, b = circle_scenario(seed=3, range_std=0.1, duration=20.0)
    csv_path = write_csv(tmp_path / "walk.csv", t, ranges, a, b)
    out = tmp_path / "results"
    argv = ["replay", str(csv_path), "--runs", "3", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", ["/venv/bin/usv-lab", *argv])  # what the installed script would see
    assert cli.main(argv) == 0

    printed = capsys.readouterr()
    assert "range noise: from the default config (the paper's Table I), not from the ground truth" in printed.out
    assert "pseudo-linear filters' range variance: 2.32 m^2" in printed.out
    assert "raw_range's noise density (m, m^2): 0.8 N(0, 0.4) + 0.2 N(0, 10)" in printed.out
    assert "TRUTH" not in printed.out and "mean range bias" in printed.out
    markdown = (out / "replay_walk.md").read_text(encoding="utf-8")
    assert "| estimator |" in markdown and "after 10 s" in markdown
    assert markdown.startswith("# Replay of `walk.csv`\n") and "not from the ground truth" in markdown
    for label in ("RLS", "Huber-RLS", "KF", "AKF", "MCKF", "raw_range"):
        assert f"| {label} |" in markdown
    assert markdown.split("```")[1].strip() == f"usv-lab replay {csv_path} --runs 3 --out {out}"
    assert (out / "replay_walk.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_cli_given_range_variance_and_config(tmp_path, replay_only, capsys):
    t, ranges, a, b = circle_scenario(seed=3, range_std=0.1, duration=12.0)
    csv_path = write_csv(tmp_path / "walk.csv", t, ranges, a, b)
    config = tmp_path / "agent.yaml"
    config.write_text("relative:\n  displacement_variance: 1.0e-5\n", encoding="utf-8")
    argv = ["replay", str(csv_path), "--runs", "2", "--out", str(tmp_path), "--range-variance", "0.5",
            "--config", str(config), "--settle", "5", "--seed", "9"]
    assert cli.main(argv) == 0
    printed = capsys.readouterr().out
    assert "range noise: given on the command line (--range-variance" in printed
    assert "pseudo-linear filters' range variance: 0.5 m^2" in printed and "1e-05 m^2 per dt" in printed


@pytest.mark.slow
def test_cli_config_sets_the_noise_and_the_truth_variance_is_labelled(tmp_path, replay_only, capsys):
    t, ranges, a, b = circle_scenario(seed=3, range_std=0.1, duration=12.0)
    csv_path = write_csv(tmp_path / "walk.csv", t, ranges, a, b)
    config = tmp_path / "real.yaml"
    config.write_text("relative:\n  range_variance: 0.04\n  estimator:\n    name: raw_range\n"
                      "    noise_components: [[1.0, 0.1, 0.02]]\n    bias_variance: 0.01\n", encoding="utf-8")
    assert cli.main(["replay", str(csv_path), "--runs", "1", "--out", str(tmp_path), "--params", str(config)]) == 0
    printed = capsys.readouterr().out
    assert f"range noise: from the config {config}, not from the ground truth" in printed
    assert "range variance: 0.04 m^2" in printed and "density (m, m^2): 1 N(0.1, 0.02)" in printed
    assert "a constant pair bias estimated as a state, prior variance 0.01 m^2" in printed

    assert cli.main(["replay", str(csv_path), "--runs", "1", "--out", str(tmp_path), "--truth-variance"]) == 0
    printed = capsys.readouterr().out
    assert "range noise: TRUTH-DERIVED" in printed and "tuned on the truth" in printed
    markdown = (tmp_path / "replay_walk.md").read_text(encoding="utf-8")
    assert markdown.startswith("# Replay of `walk.csv`: filters tuned on the ground truth\n")
    assert "TRUTH-DERIVED" in markdown

    with pytest.raises(SystemExit) as stopped:
        cli.main(["replay", str(csv_path), "--truth-variance", "--range-variance", "0.5"])
    assert stopped.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err


def test_cli_rejects_bad_input_with_exit_code_2(tmp_path, replay_only, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text(HEADER + "\n0,5,5,0,0,0\n0.1,5,x,0,0,0\n0.2,5,5,0,0,0\n", encoding="utf-8")
    assert cli.main(["replay", str(bad), "--out", str(tmp_path)]) == 2
    error = capsys.readouterr().err
    assert "line 3, column 'ax'" in error and str(bad) in error
    assert not list(tmp_path.glob("replay_*"))

    good = write_csv(tmp_path / "good.csv", *circle_scenario(seed=3, range_std=0.1, duration=5.0))
    config = tmp_path / "typo.yaml"
    config.write_text("relative:\n  rnage_variance: 1.0\n", encoding="utf-8")
    assert cli.main(["replay", str(good), "--config", str(config), "--out", str(tmp_path)]) == 2
    assert "rnage_variance" in capsys.readouterr().err
    assert cli.main(["replay", str(good), "--settle", "60", "--out", str(tmp_path)]) == 2
    assert "--settle" in capsys.readouterr().err
