"""Real recordings (BROAD): loader, bad input, and the authors' VQF figures."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from magenv import metrics
from magenv.papers import README_VQF
from magenv.recordings import (
    BERLIN_FIELD_DIP,
    BERLIN_FIELD_NORM,
    REQUIRED,
    estimate_field,
    find_recording,
    list_recordings,
    load_recording,
)
from magenv.trial import Trial, TrialError

TOL = 0.05  # degrees; the README's figures are rounded to 0.01


@pytest.fixture(scope="module")
def trial02(broad_dir) -> Trial:
    return load_recording(find_recording("02", broad_dir))


# ------------------------------------------------------------------ loader


def test_all_nine_recordings_listed(broad_dir):
    names = [p.stem[:2] for p in list_recordings(broad_dir)]
    assert names == sorted(README_VQF)


def test_loader_matches_file(broad_dir, trial02):
    path = find_recording("02", broad_dir)
    with h5py.File(path, "r") as f:
        gyr, quat_true, movement, pos = f["imu_gyr"][()], f["opt_quat"][()], f["movement"][()], f["opt_pos"][()]
        rate = float(f.attrs["sampling_rate"])
    t = trial02
    assert t.name == path.stem
    assert t.rate == pytest.approx(285.714, abs=1e-3) and t.rate == rate
    assert t.gyr.shape == t.acc.shape == t.mag.shape == (53240, 3)
    assert t.q_true.shape == (53240, 4)
    np.testing.assert_array_equal(t.gyr, gyr)
    np.testing.assert_array_equal(t.score_mask, movement)
    assert t.score_mask.dtype == bool and 0 < t.score_mask.sum() < t.n
    np.testing.assert_array_equal(t.truth["opt_pos"], pos)
    # NaN truth rows are kept as NaN, exactly where the file has them
    nan_rows = np.isnan(quat_true).any(1)
    assert nan_rows.sum() > 1000
    np.testing.assert_array_equal(np.isnan(t.q_true).any(1), nan_rows)
    assert "BROAD" in t.meta["info"] and t.meta["source"] == "BROAD"
    json.dumps(t.meta)  # serialisable


def test_earth_field_estimated_from_rest(broad_dir):
    for path in list_recordings(broad_dir):
        t = load_recording(path)
        assert t.meta["field_source"] == "initial_rest", path.name
        assert 40.0 < t.field_norm < 46.0 and 66.0 < t.field_dip < 73.0, (path.name, t.field_norm, t.field_dip)
        assert t.meta["initial_rest_s"] > 5.0


def test_earth_field_falls_back_without_rest():
    rng = np.random.default_rng(0)
    n, rate = 2000, 200.0
    gyr = np.tile([0.0, 0.0, 1.0], (n, 1))  # always turning: no initial rest
    acc = np.tile([0.0, 0.0, 9.81], (n, 1))
    mag = rng.normal(0, 1, (n, 3)) + [0, 20, -40]
    assert estimate_field(gyr, acc, mag, rate) == (BERLIN_FIELD_NORM, BERLIN_FIELD_DIP, "documented")
    # at rest but a field nowhere near Berlin's: also the documented constants
    gyr[:] = 0.0
    assert estimate_field(gyr, acc, mag * 3, rate)[2] == "documented"
    # at rest in a Berlin-like field: estimated
    norm, dip, src = estimate_field(gyr, acc, np.tile([0.0, 16.0, -41.7], (n, 1)), rate)
    assert src == "initial_rest" and norm == pytest.approx(44.66, abs=0.01) and dip == pytest.approx(69.0, abs=0.1)


# --------------------------------------------------------------- bad input


def write_recording(path, n=100, drop=(), rate=100.0, **override):
    """A small BROAD-layout file at ``path``: ``n`` rows at rest, every dataset but ``drop``, ``override``s."""
    data = {
        "imu_gyr": np.zeros((n, 3)),
        "imu_acc": np.tile([0, 0, 9.81], (n, 1)),
        "imu_mag": np.tile([0, 16.0, -41.7], (n, 1)),
        "opt_quat": np.tile([1.0, 0, 0, 0], (n, 1)),
        "opt_pos": np.zeros((n, 3)),
        "movement": np.ones(n, bool),
    }
    data.update(override)
    with h5py.File(path, "w") as f:
        for k, v in data.items():
            if k not in drop:
                f.create_dataset(k, data=v)
        if rate is not None:
            f.attrs["sampling_rate"] = rate
    return path


def test_good_synthetic_file_loads(tmp_path):
    q = np.tile([1.0, 0, 0, 0], (100, 1))
    q[10:20] = np.nan
    t = load_recording(write_recording(tmp_path / "ok.hdf5", opt_quat=q))
    assert t.n == 100 and t.rate == 100.0 and np.isnan(t.q_true[10:20]).all()


def test_missing_file(tmp_path):
    with pytest.raises(TrialError, match="nope.hdf5: no such file"):
        load_recording(tmp_path / "nope.hdf5")


def test_not_hdf5(tmp_path):
    p = tmp_path / "text.hdf5"
    p.write_text("not hdf5 at all")
    with pytest.raises(TrialError, match="text.hdf5: not an HDF5 file"):
        load_recording(p)


@pytest.mark.parametrize("field", REQUIRED)
def test_missing_dataset(tmp_path, field):
    p = write_recording(tmp_path / "lacks.hdf5", drop=(field,))
    with pytest.raises(TrialError, match=rf"lacks.hdf5: missing dataset\(s\) {field}"):
        load_recording(p)


def test_missing_rate(tmp_path):
    with pytest.raises(TrialError, match="norate.hdf5: missing attribute sampling_rate"):
        load_recording(write_recording(tmp_path / "norate.hdf5", rate=None))


def test_bad_rate(tmp_path):
    with pytest.raises(
        TrialError, match="zerorate.hdf5: attribute sampling_rate must be a sampling rate from 1 to 100000 Hz"
    ):
        load_recording(write_recording(tmp_path / "zerorate.hdf5", rate=0.0))


@pytest.mark.parametrize(
    "field,shape", [("imu_acc", (99, 3)), ("opt_quat", (100, 3)), ("movement", (101,)), ("opt_pos", (100, 2))]
)
def test_mismatched_lengths(tmp_path, field, shape):
    p = write_recording(tmp_path / "short.hdf5", **{field: np.zeros(shape, bool if field == "movement" else float)})
    with pytest.raises(TrialError, match=rf"short.hdf5: mismatched shapes or lengths: {field}"):
        load_recording(p)


@pytest.mark.parametrize("field", ["imu_gyr", "imu_acc", "imu_mag"])
def test_nan_in_sensor(tmp_path, field):
    x = np.ones((100, 3))
    x[42, 1] = np.nan
    p = write_recording(tmp_path / "nan.hdf5", **{field: x})
    with pytest.raises(
        TrialError, match=rf"nan.hdf5: sensor channel {field} has NaN/inf in 1 row\(s\), first at row 42"
    ):
        load_recording(p)


# ----------------------------------------------- the authors' VQF figures


def _vqf_scores(trial, **params):
    from vqf import VQF

    f = VQF(trial.dt, trial.dt, trial.dt, **params)
    q = f.updateBatch(trial.gyr, trial.acc, trial.mag)["quat9D"]
    return metrics.score(q, trial.q_true, trial.score_mask)


def _check(trial, key):
    for params, expected in zip(({}, {"magDistRejectionEnabled": False}), README_VQF[key]):
        s = _vqf_scores(trial, **params)
        for got, want, what in zip((s.total, s.heading, s.inclination), expected, ("total", "heading", "inclination")):
            if want is not None:
                assert got == pytest.approx(want, abs=TOL), (
                    f"{trial.name} {params or 'default'} {what}: {got:.3f} vs README {want}"
                )


def test_vqf_reproduces_readme_all_nine(broad_dir):
    # VQF runs in C++ (~0.1 s a trial), so all nine trials fit the default suite.
    for path in list_recordings(broad_dir):
        _check(load_recording(path), path.stem[:2])


def test_vqf_scoring_can_fail(trial02):
    """The check is sharp: shifting the estimate by 2 samples, or scoring every
    sample instead of the movement mask, moves the figure beyond the tolerance."""
    from vqf import VQF

    q = VQF(trial02.dt, trial02.dt, trial02.dt).updateBatch(trial02.gyr, trial02.acc, trial02.mag)["quat9D"]
    exact = metrics.score(q, trial02.q_true, trial02.score_mask).total
    assert exact == pytest.approx(1.38, abs=TOL)
    assert abs(metrics.score(q, trial02.q_true, None).total - 1.38) > TOL
    assert abs(metrics.score(np.roll(q, 30, 0), trial02.q_true, trial02.score_mask).total - 1.38) > TOL


# ------------------------------------------------------ sensor statistics


def _delayed(trial, lag, hold_every=None):
    """``trial`` with its magnetometer ``lag`` samples late, optionally holding
    two samples in every ``hold_every`` (BROAD's pattern)."""
    import dataclasses

    mag = np.roll(trial.mag, lag, axis=0)
    if hold_every:
        for i in range(hold_every, trial.n, hold_every):
            mag[i - 1] = mag[i - 2] = mag[i - 3]
    return dataclasses.replace(trial, mag=mag)


@pytest.mark.parametrize("lag", [0, 3, 5])
def test_mag_lag_recovers_known_delay(make_kinematic_trial, lag):
    from magenv.sensor_stats import hold_fraction, mag_lag, truth_lag

    trial = _delayed(make_kinematic_trial(seed=2, duration=30.0, rate=200.0), lag)
    assert mag_lag(trial) == pytest.approx(lag, abs=0.2)
    assert truth_lag(trial, "mag") == pytest.approx(lag, abs=0.1)
    assert truth_lag(trial, "gyr") == pytest.approx(0.0, abs=0.1)
    assert hold_fraction(trial.mag) == 0.0


def test_hold_adds_its_mean_age_to_the_lag(make_kinematic_trial):
    """Two held samples in every 7 (≈ 28.6 %) age the data by 3/7 sample on average."""
    from magenv.sensor_stats import hold_fraction, truth_lag

    trial = _delayed(make_kinematic_trial(seed=2, duration=30.0, rate=200.0), 3, hold_every=7)
    assert hold_fraction(trial.mag) == pytest.approx(2 / 7, abs=0.01)
    assert truth_lag(trial, "mag") == pytest.approx(3 + 3 / 7, abs=0.1)


def test_rest_noise_on_synthetic_rest():
    from magenv.sensor_stats import rest_autocorr, rest_noise

    rng = np.random.default_rng(0)
    n, rate = 4000, 200.0
    gyr = rng.normal(0, np.deg2rad(0.1), (n, 3))
    gyr[3000:] += 1.0  # motion starts at 15 s: rest = first 10 s (the cap)
    trial = Trial(
        name="rest",
        rate=rate,
        gyr=gyr,
        acc=rng.normal(0, 0.05, (n, 3)) + [0, 0, 9.81],
        mag=rng.normal(0, 0.7, (n, 3)) + [0, 16, -41.7],
        q_true=np.full((n, 4), np.nan),
        field_norm=44.7,
        field_dip=69.0,
    )
    noise = rest_noise(trial)
    assert noise["rest_s"] == pytest.approx(10.0, abs=0.1)
    np.testing.assert_allclose(noise["gyr"], 0.1, rtol=0.1)
    np.testing.assert_allclose(noise["acc"], 0.05, rtol=0.1)
    np.testing.assert_allclose(noise["mag"], 0.7, rtol=0.1)
    assert abs(rest_autocorr(trial, "mag")) < 0.05


def test_sensor_stats_of_a_recording(trial02):
    """Regression on measured facts of trial 02 (see studies/realism.py)."""
    from magenv.sensor_stats import sensor_stats

    s = sensor_stats(trial02)
    assert 0.07 < s.gyr_noise_dps < 0.13 and 0.04 < s.acc_noise_ms2 < 0.07 and 0.6 < s.mag_noise_ut < 0.8
    assert s.mag_hold_fraction == pytest.approx(0.29, abs=0.01)
    assert 2.8 < s.mag_lag_samples < 3.6  # behind the gyro
    assert 4.0 < s.mag_truth_lag_samples < 4.8 and 0.9 < s.gyr_truth_lag_samples < 1.5
    assert s.gyr_quantum_dps == pytest.approx(0.061, abs=0.001)  # ±2000 °/s over 16 bit
    assert s.mag_hold_run2_share > 0.99 and 1.99 < s.mag_hold_run_mean < 2.01  # holds come in pairs
    assert 0.55 < s.mag_autocorr1_distinct < 0.75 and 0.08 < s.mag_autocorr2_distinct < 0.25  # low-pass noise


def test_hold_runs_counts_runs_of_repeats():
    from magenv.sensor_stats import hold_runs

    x = np.arange(20.0)[:, None].repeat(3, 1)
    x[3] = x[4] = x[2]  # a run of 2 repeats
    x[10] = x[9]  # a run of 1
    assert hold_runs(x) == (1.5, 0.5)
    assert np.isnan(hold_runs(np.arange(5.0)[:, None])[0])


def test_realism_benchmark_runs(broad_dir, tmp_path, capsys):
    """studies/realism.py on the recordings alone: table, recommendations, figure."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "studies" / "realism.py"
    spec = importlib.util.spec_from_file_location("realism", path)
    realism = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(realism)
    out = tmp_path / "realism.png"
    assert realism.main(["--no-sim", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "magnetometer noise σ, µT per axis" in text and "32_disturbed_attached_ma" in text
    assert out.stat().st_size > 10_000


# ------------------------------------------------------------------ physical sense (check_physical)


def test_the_nine_recordings_make_physical_sense(broad_dir):
    import warnings

    from magenv.recordings import check_physical, gyro_turn_ratio

    for path in list_recordings(broad_dir):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # not even a warning
            trial = load_recording(path)
        assert check_physical(trial) == []
        ratio, windows = gyro_turn_ratio(trial)
        assert 0.99 < ratio < 1.01 and windows > 100, (path.name, ratio, windows)


@pytest.mark.parametrize("scenario", ["dynamic_magnet", "stationary_magnet", "handheld_texting", "constraint_test1"])
def test_simulated_trials_make_physical_sense(scenario):
    from magenv.recordings import check_physical
    from magenv.scenarios import make_trial

    assert check_physical(make_trial(scenario, 0)) == []


@pytest.fixture(scope="module")
def moving(broad_dir) -> Trial:
    return load_recording(find_recording("02", broad_dir))


def _changed(trial: Trial, **change) -> Trial:
    import dataclasses

    return dataclasses.replace(trial, **change)


NO_TRUTH = "no truth"


@pytest.mark.parametrize(
    "change, message",
    [
        ({"mag": 1e3}, r"magnetometer norm 4.4e\+04 looks like nT, expected µT \(20–70 µT\)"),
        ({"mag": 10.0}, "magnetometer norm 4.4e.02 looks like mG, expected µT"),
        ({"mag": 1e-2}, "magnetometer norm 0.44 looks like G, expected µT"),
        ({"mag": 1e-6}, "magnetometer norm 4.4e-05 looks like T, expected µT"),
        ({"mag": 1e6}, "magnetometer norm 4.38e.07 µT is implausible in any unit"),
        ({"mag": 0.0}, "magnetometer norm is all zero"),
        ({"acc": 1 / 9.81}, "accelerometer norm at rest 1 looks like g, expected m/s²"),
        ({"acc": 1e3 / 9.81}, "accelerometer norm 1e.03 looks like mg, expected m/s²"),
        ({"acc": 0.0}, "accelerometer norm at rest is all zero"),
        ({"gyr": 180 / np.pi}, "gyro rates look like °/s, expected rad/s"),
        ({"gyr": 0.0}, "the gyroscope is all zero: the gyro turns 0× as far as the truth"),
        ({"rate": 10.0}, "sampling rate 2857.14 Hz looks 10× too high: the gyro turns 0.0998× as far as the truth"),
        ({"rate": 0.1}, "sampling rate 28.5714 Hz looks 10× too low: the gyro turns 10× as far as the truth"),
        ({"rate": 10.0, NO_TRUTH: True}, "sampling rate 2857.14 Hz looks 10× too high: .* the accelerometer tilts"),
        ({"gyr": 180 / np.pi, NO_TRUTH: True}, "gyro rates look like °/s"),
    ],
)
def test_magnitudes_that_another_unit_explains_are_refused(moving, change, message):
    """Recording 02 with one channel (or the rate) scaled, as if written in another unit: refused, naming it."""
    from magenv.recordings import check_physical

    change = dict(change)
    fields = {}
    if change.pop(NO_TRUTH, False):
        fields["q_true"] = np.full_like(moving.q_true, np.nan)
    for key, factor in change.items():
        fields[key] = getattr(moving, key) * factor
    with pytest.raises(TrialError, match=f"^02_x: {message}"):
        check_physical(_changed(moving, **fields), "02_x")


def test_slightly_off_magnitudes_are_warnings(moving):
    from magenv.recordings import check_physical

    assert check_physical(_changed(moving, rate=moving.rate * 1.3)) == [
        "the gyro turns 0.766× as far as the truth (681 windows): a gyro scale or sampling-rate error?"
    ]
    weak = check_physical(_changed(moving, mag=moving.mag * 0.4))
    assert weak == ["magnetometer norm 17.5 µT is outside the expected 20–70 µT"]
    assert check_physical(_changed(moving, acc=moving.acc * 1.15)) == [
        "accelerometer norm at rest 11.3 m/s² is outside the expected 8.83–10.8 m/s²"
    ]


def test_a_corrupt_gyro_sample_is_refused(moving):
    from magenv.recordings import check_physical

    gyr = moving.gyr.copy()
    gyr[1000] = [0.0, 1e300, 0.0]
    with pytest.raises(TrialError, match=r"gyro rate 1e\+300 rad/s at row 1000 is beyond any gyroscope's range"):
        check_physical(_changed(moving, gyr=gyr))
    gyr[1000] = [0.0, 80.0, 0.0]  # 4600 °/s
    with pytest.raises(TrialError, match="gyro rate 80 rad/s at row 1000"):
        check_physical(_changed(moving, gyr=gyr))
