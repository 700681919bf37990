"""lab/experiments/uwb_datasets.py: the converters on tiny hand-made checkouts, the noise fit, and the page."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from agent.config import ConfigError, load_yaml, read_yaml
from agent.core.params import AgentParams
from lab.cli import main as lab_main
from lab.experiments import uwb_datasets as uwb
from lab.experiments.replay import parse_csv

REPO = Path(__file__).resolve().parent.parent


# ----------------------------------------------------------------------------------------------- pieces
def test_planar_range_removes_the_height_difference():
    # 3-4-5 triangles: a 5 m range between antennas 3 m apart in height is 4 m across; below |dz| it is 0.
    np.testing.assert_allclose(uwb.planar_range([5.0, 5.0, 1.0], [3.0, -4.0, 2.0]), [4.0, 3.0, 0.0])


def test_thin_keeps_the_first_range_of_each_tick():
    t = np.array([10.0, 10.03, 10.1, 10.12, 10.25, 10.31, 10.399])
    # ticks from t0:  0      0      1     1      2      3      3
    assert uwb.thin(t, 0.1).tolist() == [0, 2, 4, 5]


def test_interpolate_refuses_outside_and_across_gaps():
    t = np.array([0.0, 1.0, 2.0, 4.0])
    values = np.column_stack([[0.0, 10.0, 20.0, 40.0], [1.0, 1.0, 1.0, 1.0]])
    out, usable = uwb.interpolate(np.array([-1.0, 0.5, 2.0, 3.0, 4.5]), t, values, max_gap=1.5)
    assert usable.tolist() == [False, True, True, False, False]   # 3.0 lies in a 2 s gap
    np.testing.assert_allclose(out[usable], [[5.0, 1.0], [20.0, 1.0]])


def test_yaw_from_quaternion():
    theta = math.radians(30.0)
    assert uwb.yaw_from_quaternion(math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2)) == pytest.approx(theta)
    # The CUHK-SZ motion capture's body frame is upside down: q = (0, cos f, sin f, 0), half a turn about a
    # horizontal axis at f. Its Z-Y-X yaw is 2 f.
    f = math.radians(20.0)
    assert uwb.yaw_from_quaternion(0.0, math.cos(f), math.sin(f), 0.0) == pytest.approx(2 * f)


# ----------------------------------------------------------------------------------------------- Hanyang
ORIGIN = 1_734_501_485_500_000_000   # ns, a multiple of 256 so that float64 holds it exactly


def _write(path: Path, header: str, rows: list[str]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join([header, *rows]) + "\n", encoding="utf-8")


def _hanyang_case(case: Path, ranges: list[tuple[float, str]]) -> None:
    """A case whose tag walks +x at 1 m/s along y = 0 at GNSS z = 0 (tag 1 m high) for 0.6 s, then a GNSS
    height fault at 0.8 s; every anchor 2 m high, A3 at (3, 4), the others elsewhere."""
    traj = [f"{float(ORIGIN + k * 200_000_000)!r},{0.2 * k},0.0,0.0,0.0" for k in range(4)]
    traj.append(f"{float(ORIGIN + 800_000_000)!r},0.8,0.0,0.9,0.0")
    _write(case / "trajectory.csv", "timestamp,x,y,z,heading_degrees", traj)
    header = ("%time,field.stamp,field.id,field.x,field.y,field.z,field.distanceFromTag,field.rssi,"
              "field.rssi_fp")
    for anchor, (x, y) in zip(uwb.HANYANG_ANCHORS, [(3.0, 4.0), (-3.0, 4.0), (3.0, -4.0), (-3.0, -4.0)]):
        rows = [f"{ORIGIN + round(s * 1e9)},{ORIGIN + round(s * 1e9)},3,{x},{y},2.0,{r},-80,-81" for s, r in ranges]
        _write(case / f"{anchor}.csv", header, rows)


def test_hanyang_runs_on_a_hand_made_case(tmp_path):
    # Ranges r with the anchor 1 m above the tag: planar sqrt(r^2 - 1). 0.15 s shares 0.1 s's tick; an empty
    # and a zero range are dropped; 0.7 s is past the last good truth (the 0.8 s height fault is dropped).
    ranges = [(0.10, repr(math.sqrt(26.0))), (0.15, "9.0"), (0.30, repr(math.sqrt(17.0))), (0.40, ""),
              (0.45, "0.0"), (0.50, "0.5"), (0.70, "7.0")]
    for condition in ("LOS", "NLOS"):
        for case in ("Case_1", "Case_2"):
            _hanyang_case(tmp_path / "Dynamic_measurements" / condition / "Trajectory_A" / case, ranges)
    runs = list(uwb.hanyang_runs(tmp_path))
    # Case 1 calibrates the sensor: never a scored run.
    assert [r.name for r in runs] == [f"{c}-case2-{a}" for c in ("los", "nlos") for a in uwb.HANYANG_ANCHORS]
    assert [r.name for r in uwb.calibration_runs("hanyang", tmp_path)] == [
        f"{c}-case1-{a}" for c in ("los", "nlos") for a in uwb.HANYANG_ANCHORS]
    first = runs[0]
    assert first.condition == "LOS" and first.kind == "tag-anchor"
    np.testing.assert_allclose(first.t, [0.1, 0.3, 0.5], atol=1e-9)
    np.testing.assert_allclose(first.range, [5.0, 4.0, 0.0], atol=1e-12)   # 0.5 m < 1 m height difference
    np.testing.assert_allclose(first.a, [[0.1, 0.0], [0.3, 0.0], [0.5, 0.0]], atol=1e-9)
    np.testing.assert_allclose(first.b, [[3.0, 4.0]] * 3)
    assert runs[4].condition == "NLOS"

    out = tmp_path / "out"
    written = uwb.convert("hanyang", tmp_path, out)
    assert len(written) == 8
    log = parse_csv(out / "los-case2-A3.csv")
    np.testing.assert_allclose(log.t, [0.0, 0.2, 0.4])
    np.testing.assert_allclose(log.range, [5.0, 4.0, 0.0])
    entries = uwb.read_manifest(out)
    assert [e.path.name for e in entries][:2] == ["los-case2-A3.csv", "los-case2-A5.csv"]
    assert entries[0].source == ("Dynamic_measurements/LOS/Trajectory_A/Case_2/A3.csv, "
                                 "Dynamic_measurements/LOS/Trajectory_A/Case_2/trajectory.csv")


def test_missing_source_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="Trajectory"):
        list(uwb.hanyang_runs(tmp_path))
    with pytest.raises(ConfigError, match="UWB_dynamic_exp"):
        list(uwb.cuhksz_runs(tmp_path))
    with pytest.raises(ConfigError, match="murp-datasets"):
        list(uwb.murp_runs(tmp_path, trials=(13,)))


# ----------------------------------------------------------------------------------------------- CUHK-SZ
def test_cuhksz_runs_on_a_hand_made_recording(tmp_path, capsys):
    base = tmp_path / "Planar_Dataset" / "Dynamic"
    # The trolley's centre moves +y at 1 m/s, 0.96 m high, with yaw -7 deg, which the authors' +7 deg
    # correction turns to 0: tag 0 sits at centre + (-0.0689, -0.1423), 0.9611 m high.
    half = math.radians(-7.0) / 2
    mocap = [f"2022-08-15 9:00:{s:06.3f},0.0,{s},0.96,{math.cos(half)!r},0,0,{math.sin(half)!r}"
             for s in (0.0, 0.1, 0.2, 0.3)]
    _write(base / "motion_capture_dynamic_exp_fast.csv", "time,x,y,z,rotation,,,", mocap)
    rows = []
    for s, r in ((0.0, 5.0), (0.05, 9.0), (0.1, 4.0), (0.2, 3.0)):
        values = ["1.0"] * 24
        values[0] = repr(r)   # a0-t0
        rows.append(f"2022-08-15 9:00:{s:06.3f}," + ",".join(values))
    base.joinpath("UWB_dynamic_exp_fast.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")

    runs = list(uwb.cuhksz_runs(tmp_path))
    assert "speed 'mid' skipped" in capsys.readouterr().err
    assert [r.name for r in runs] == [f"fast-tag0-anchor{k}" for k in range(8)]
    run = runs[0]
    np.testing.assert_allclose(run.t - run.t[0], [0.0, 0.1, 0.2], atol=1e-6)   # 0.05 s shares the first tick
    # dz = 0.96 + 0.0011 - 1.0442 = -0.0831 m: sqrt(25 - 0.00690561) = 4.999309, sqrt(16 - ...) = 3.999137,
    # sqrt(9 - ...) = 2.998849.
    np.testing.assert_allclose(run.range, [4.999309, 3.999137, 2.998849], atol=1e-6)
    np.testing.assert_allclose(run.a, [[-0.0689, -0.1423], [-0.0689, -0.0423], [-0.0689, 0.0577]], atol=1e-6)
    np.testing.assert_allclose(run.b[0], [-3.4203, 3.0053])


# ----------------------------------------------------------------------------------------------- MURP
def test_murp_runs_on_a_hand_made_trial(tmp_path):
    columns = "t,A_x,A_y,A_z,B_x,B_y,B_z,r"
    base = tmp_path / "datasets" / "parsed" / "13"
    # Robot 1 hovers 1.75 m high; robots 2 and 3 drive 0.5 m high, along x and along y.
    robots = {1: lambda k: (0.0, 0.0, 1.75), 2: lambda k: (1.0 + 0.6 * k, 0.0, 0.5),
              3: lambda k: (0.0, 2.0 + 0.6 * k, 0.5)}
    for first, second in ((1, 2), (1, 3), (2, 3)):
        # r = 3.25 with a 1.25 m height difference is 3 m across; 2.0 is sqrt(2.4375) = 1.561250 m across.
        ranges = (3.25, 2.0, 3.25) if first == 1 else (3.0, 3.0, 3.0)
        rows = [",".join(str(v) for v in (float(k), *robots[first](k), *robots[second](k), ranges[k]))
                for k in range(3)]
        _write(base / f"13_base-{first}_targ-{second}_win-1_step-1.csv", columns, rows)
    runs = list(uwb.murp_runs(tmp_path, trials=(13,)))
    assert [(r.name, r.kind) for r in runs] == [("trial13-robots12", "one end static"),
                                                ("trial13-robots13", "one end static"),
                                                ("trial13-robots23", "moving pair")]
    np.testing.assert_allclose(runs[0].range, [3.0, 1.561250, 3.0], atol=1e-6)
    np.testing.assert_allclose(runs[2].range, [3.0, 3.0, 3.0])            # same height: unchanged
    np.testing.assert_allclose(runs[0].a, [[0.0, 0.0]] * 3)
    np.testing.assert_allclose(runs[0].b, [[1.0, 0.0], [1.6, 0.0], [2.2, 0.0]])
    # Calibration reads the moving calibration trials 8-12, here absent: the error names the first.
    with pytest.raises(ConfigError, match="08_base-1_targ-2"):
        list(uwb.calibration_runs("murp", tmp_path))


# ----------------------------------------------------------------------------------------------- noise fit
def test_fit_mixture_weights_each_calibration_set_alike():
    rng = np.random.default_rng(11)
    small = rng.normal(1.0, 0.2, 500)
    large = rng.normal(0.0, 0.1, 5000)
    mixture = uwb.fit_mixture([large, small], components=2)
    # Ten times more samples in `large`, yet both sets carry half the weight.
    (w1, m1, v1), (w2, m2, v2) = sorted(mixture, key=lambda c: c[1])
    assert w1 == pytest.approx(0.5, abs=0.02) and w2 == pytest.approx(0.5, abs=0.02)
    assert m1 == pytest.approx(0.0, abs=0.01) and m2 == pytest.approx(1.0, abs=0.03)
    assert v1 == pytest.approx(0.01, rel=0.1) and v2 == pytest.approx(0.04, rel=0.2)


def test_mixture_variance_by_hand():
    # Means -1 and +1 with unit variances, equal weights: mean 0, variance 1 + 1.
    assert uwb.mixture_variance([(0.5, -1.0, 1.0), (0.5, 1.0, 1.0)]) == pytest.approx(2.0)
    assert uwb.mixture_variance([(2.0, 0.3, 0.25)]) == pytest.approx(0.25)


def _calibration_run(name: str, residuals: np.ndarray) -> uwb.Run:
    """A run whose ranges are its true distances (5 m, end b at the origin) plus `residuals`."""
    a = np.tile((3.0, 4.0), (len(residuals), 1))
    return uwb.Run(name, "LOS", "tag-anchor", "hand-made", np.arange(len(residuals)) * 0.1, 5.0 + residuals, a,
                   np.zeros_like(a))


def test_fit_sensor_noise_separates_the_pairs_biases_from_the_noise():
    rng = np.random.default_rng(8)
    biases = rng.normal(0.1, 0.05, 30)
    runs = [_calibration_run(f"r{j}", b + rng.normal(0.0, 0.02, 4000)) for j, b in enumerate(biases)]
    noise = uwb.fit_sensor_noise(runs, components=1)
    assert (noise.runs, noise.ranges) == (30, 120000)
    # The bias prior is the runs' means' spread: the drawn biases' sample variance, up to the noise's share in
    # each mean (0.02^2 / 4000, about 1e-7 against 2.5e-3).
    assert noise.bias_variance == pytest.approx(np.var(biases, ddof=1), rel=0.02)
    ((weight, mean, variance),) = noise.mixture
    # The density is the noise about each run's own mean, centred on the runs' common mean.
    assert weight == pytest.approx(1.0)
    assert mean == pytest.approx(biases.mean(), abs=1e-3)
    assert variance == pytest.approx(0.02 ** 2, rel=0.02)


def test_fit_noise_from_your_own_csvs(tmp_path, capsys):
    rng = np.random.default_rng(9)
    files = []
    for j, bias in enumerate((0.05, 0.15, 0.10)):
        run = _calibration_run(f"cal{j}", bias + rng.normal(0.0, 0.03, 600))
        files.append(str(uwb.write_run(run, tmp_path)))
    out = tmp_path / "mine.yaml"
    assert lab_main(["fit-noise", "csv", *files, "--components", "1", "--out", str(out)]) == 0
    # What was fitted, in one line: sd of the biases sqrt(0.0025) = 0.05 m, of the rest 0.03 m.
    printed = capsys.readouterr().out
    assert f"wrote {out}: 3 calibration runs, 1800 ranges; the runs' biases spread 0.05" in printed
    assert "the rest 0.03" in printed
    params = load_yaml(AgentParams, out)
    # The three runs' means (0.05, 0.15, 0.10 up to the noise's 0.03 / sqrt(600) and the CSV's millimetres):
    # sample variance 0.0025.
    assert params.relative.params_of("raw_range").bias_variance == pytest.approx(0.0025, rel=0.1)
    ((_, mean, variance),) = params.relative.params_of("raw_range").noise_components
    assert mean == pytest.approx(0.10, abs=0.005) and variance == pytest.approx(0.0009, rel=0.15)
    assert "the replay CSVs cal0.csv, cal1.csv, cal2.csv (3 runs, 1800 ranges)" in out.read_text(encoding="utf-8")
    # A data set takes one checkout; a bad CSV is a clear error.
    assert lab_main(["fit-noise", "murp", str(tmp_path), str(tmp_path)]) == 2
    assert "takes one checkout" in capsys.readouterr().err
    (tmp_path / "bad.csv").write_text("t,range\n0,1\n", encoding="utf-8")
    assert lab_main(["fit-noise", "csv", str(tmp_path / "bad.csv")]) == 2
    assert "bad.csv" in capsys.readouterr().err


@pytest.mark.slow   # runs usv-agent in a process of its own
def test_a_fit_noise_output_drops_into_the_agent_as_it_is(tmp_path):
    """What `fit-noise` writes is an AgentParams file: `usv-agent --params` runs with it, unedited, and so does
    a boat's settings naming it (`agent: my_uwb.yaml`); before, its `relative:` section had to be moved under
    the settings' `agent:` by hand."""
    import subprocess
    import sys

    import yaml

    rng = np.random.default_rng(4)
    files = [str(uwb.write_run(_calibration_run(f"cal{j}", bias + rng.normal(0.0, 0.03, 300)), tmp_path))
             for j, bias in enumerate((0.05, 0.15, 0.10))]
    out = tmp_path / "my_uwb.yaml"
    from lab import cli

    assert cli.main(["fit-noise", "csv", *files, "--components", "1", "--out", str(out)]) == 0
    fitted = load_yaml(AgentParams, out)
    assert fitted.relative.estimator != AgentParams().relative.estimator
    (tmp_path / "boat.yaml").write_text("clock: wall\nagent: my_uwb.yaml\n", encoding="utf-8")
    for arguments in (["--params", str(out)], ["--config", str(tmp_path / "boat.yaml")]):
        result = subprocess.run([sys.executable, "-m", "agent", "--vessel", "1", *arguments, "--print-config"],
                                capture_output=True, text=True, timeout=120)
        assert result.returncode == 0, result.stderr
        assert AgentParams.model_validate(yaml.safe_load(result.stdout)["agent"]) == fitted


def test_fit_sensor_noise_needs_two_runs():
    with pytest.raises(ConfigError, match="at least two"):
        uwb.fit_sensor_noise([_calibration_run("one", np.zeros(10))])


def test_sensor_config_text_is_a_valid_agent_config(tmp_path):
    noise = uwb.SensorNoise(((0.75, 0.1, 0.01), (0.25, -0.05, 0.00002)), 0.004, 5, 800)
    text = uwb.sensor_config_text("the murp data set's UWB sensor", uwb.CALIBRATION["murp"], noise,
                                  ["fit-noise", "murp", "src"])
    path = tmp_path / "murp.yaml"
    path.write_text(text, encoding="utf-8")
    params = load_yaml(AgentParams, path)
    raw = params.relative.params_of("raw_range")
    assert raw.noise_components == ((0.75, 0.1, 0.01), (0.25, -0.05, 2e-05))   # 2e-05 read as a number
    assert raw.bias_variance == pytest.approx(0.004)
    # 0.75 (0.01 + 0.01) + 0.25 (0.00002 + 0.0025) - 0.0625^2, plus the biases' variance
    assert params.relative.range_variance == pytest.approx(0.015 + 0.000630 - 0.00390625 + 0.004, rel=1e-3)
    assert "# Regenerate with: usv-lab fit-noise murp src" in text
    assert uwb.CALIBRATION["murp"] in text and "(5 runs, 800 ranges)" in text


@pytest.mark.parametrize("dataset", list(uwb.SOURCES))
def test_committed_sensor_configs_set_the_noise_and_nothing_else(dataset):
    path = REPO / "configs" / "uwb" / f"{dataset}.yaml"
    params = load_yaml(AgentParams, path)
    raw = params.relative.params_of("raw_range")
    assert raw.bias_variance > 0.0
    assert raw.noise_components != AgentParams().relative.params_of("raw_range").noise_components
    assert read_yaml(path) == {"relative": {"range_variance": params.relative.range_variance, "estimator": {
        "name": "raw_range", "noise_components": [list(c) for c in raw.noise_components],
        "bias_variance": raw.bias_variance}}}
    assert uwb.CALIBRATION[dataset] in path.read_text(encoding="utf-8")


# ----------------------------------------------------------------------------------------------- page
def test_page_scores_config_noise_and_counts_wins(tmp_path):
    rng = np.random.default_rng(4)
    rows = []
    for name in ("one", "two"):
        t = np.arange(0.0, 30.0, 0.1)
        a = np.column_stack([3.0 + 5.0 * np.cos(t * math.pi / 30), 4.0 + 5.0 * np.sin(t * math.pi / 30)])
        r = np.linalg.norm(a, axis=1) + rng.normal(0.0, 0.1, len(t))
        run = uwb.Run(name, "LOS", "tag-anchor", "hand-made", t, r, a, np.zeros_like(a))
        uwb.write_run(run, tmp_path)
        rows.append(("hanyang", f"{name}.csv", "LOS", "tag-anchor", "hand-made"))
    with open(tmp_path / uwb.MANIFEST, "w", encoding="utf-8", newline="") as handle:
        csv.writer(handle).writerows([("dataset", *uwb.MANIFEST_COLUMNS), *rows])
    out = tmp_path / "page.md"
    uwb.write_page([uwb.read_manifest(tmp_path)], [(None, AgentParams())], runs=1, seed=2, out=out,
                   argv=["uwb-page", str(tmp_path)])
    text = out.read_text(encoding="utf-8")
    assert text.startswith("# Real UWB ranges")
    assert f"usv-lab uwb-page {tmp_path}" in text
    assert "never from the runs' ground truth" in text and "TRUTH" not in text
    assert "| one |" in text and "| two |" in text
    assert "- Noise from the default config (configs/agent.yaml): **raw_range lowest on" in text
    assert "0.8 N(0, 0.4) + 0.2 N(0, 10)" in text and "Ran on this machine, 1 worker process(es)." in text


def test_page_with_each_data_sets_sensor_config(tmp_path, capsys):
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 20.0, 0.1)
    a = np.column_stack([3.0 + 5.0 * np.cos(t * math.pi / 20), 4.0 + 5.0 * np.sin(t * math.pi / 20)])
    uwb.write_run(uwb.Run("one", "LOS", "tag-anchor", "hand-made", t,
                          np.linalg.norm(a, axis=1) + 0.1 + rng.normal(0.0, 0.05, len(t)), a, np.zeros_like(a)),
                  tmp_path)
    with open(tmp_path / uwb.MANIFEST, "w", encoding="utf-8", newline="") as handle:
        csv.writer(handle).writerows([("dataset", *uwb.MANIFEST_COLUMNS),
                                      ("cuhksz", "one.csv", "LOS", "tag-anchor", "hand-made")])
    configs = tmp_path / "sensors"
    configs.mkdir()
    noise = uwb.SensorNoise(((1.0, 0.1, 0.0025),), 0.01, 2, 400)
    (configs / "cuhksz.yaml").write_text(uwb.sensor_config_text("a sensor", "hand-made", noise, ["fit-noise"]),
                                         encoding="utf-8")
    out = tmp_path / "page.md"
    assert lab_main(["uwb-page", str(tmp_path), "--sensor-configs", str(configs), "--runs", "1", "--out",
                     str(out)]) == 0
    text = out.read_text(encoding="utf-8")
    # Only the sensor section: no --config given.
    assert "Noise from the default config" not in text
    assert "- Noise from each data set's calibrated sensor config: **raw_range lowest on" in text
    assert f"**cuhksz** (`{configs / 'cuhksz.yaml'}`): raw_range assumes 1 N(0.1, 0.0025)" in text
    assert "a constant pair bias of prior variance 0.01 m^2" in text
    # A data set without its config: a clear error, nothing written.
    (configs / "cuhksz.yaml").rename(configs / "hanyang.yaml")
    out.unlink()
    assert lab_main(["uwb-page", str(tmp_path), "--sensor-configs", str(configs), "--out", str(out)]) == 2
    assert "cuhksz.yaml" in capsys.readouterr().err and not out.exists()
    with pytest.raises(ConfigError, match="no sensor config for cuhksz"):
        uwb.write_page([uwb.read_manifest(tmp_path)], [], runs=1, seed=1, out=out, argv=["uwb-page"],
                       sensor_configs={"hanyang": (None, AgentParams())})
    with pytest.raises(ConfigError, match="no config to replay with"):
        uwb.write_page([uwb.read_manifest(tmp_path)], [], runs=1, seed=1, out=out, argv=["uwb-page"])


def test_the_data_sets_are_described_where_users_look_for_them():
    # No data is kept in the repository; docs/real_data.md says where each set comes from and under what licence.
    text = (REPO / "docs" / "real_data.md").read_text(encoding="utf-8")
    for name, source in uwb.SOURCES.items():
        assert source.url in text and source.commit in text and source.licence in text, name
    assert not (REPO / "data" / "uwb").exists()
