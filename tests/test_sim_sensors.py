"""The MIMU sensor model: noise levels, bias, lag, sample-and-hold, saturation, seeding."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from magenv.sim.sensors import SensorConfig, SensorStream, apply_sensor_model

RATE = 256.0


def _ideal(n=20000):
    t = np.arange(n) / RATE
    gyr = np.zeros((n, 3))
    acc = np.tile([0.0, 0.0, 9.81], (n, 1))
    # A field that changes every sample (a ramp), so lag and repeats are visible.
    mag = np.stack([10.0 + t, 20.0 - 0.5 * t, -30.0 + 0.1 * t], axis=1)
    return gyr, acc, mag


def _run(cfg, seed=0, **kw):
    return apply_sensor_model(*_ideal(**kw), RATE, cfg, np.random.default_rng(seed))


@pytest.mark.parametrize("preset", [SensorConfig(), SensorConfig.papers()], ids=["broad_measured", "papers"])
def test_white_noise_levels_match_the_config(preset):
    cfg = dataclasses.replace(
        preset,
        gyr_bias_dps=0,
        gyr_drift_dps=0,
        acc_bias=0,
        mag_hard_iron_ut=0,
        mag_soft_iron=0,
        mag_lag_samples=0,
        mag_hold_fraction=0,
    )
    gyr, acc, mag = _run(cfg)
    g, a, m = _ideal()
    assert np.rad2deg(np.std(gyr - g)) == pytest.approx(cfg.gyr_noise_dps, rel=0.03)
    assert np.std(acc - a) == pytest.approx(cfg.acc_noise, rel=0.03)
    assert np.std(mag - m) == pytest.approx(cfg.mag_noise_ut, rel=0.03)


def test_papers_preset_quotes_the_papers():
    cfg = SensorConfig.papers()
    assert (cfg.gyr_noise_dps, cfg.acc_noise, cfg.mag_noise_ut) == (0.5, 0.02, 0.15)


def test_gyro_bias_is_constant_and_drift_grows_like_a_random_walk():
    cfg = SensorConfig(gyr_noise_dps=0.0, gyr_bias_dps=0.2, gyr_drift_dps=0.0)
    gyr, _, _ = _run(cfg)
    assert np.ptp(gyr, axis=0).max() == 0.0  # bias only: constant
    assert np.abs(gyr[0]).max() > 0.0
    # Random walk: variance after T seconds = drift²·T; check over many seeds.
    cfg = SensorConfig(gyr_noise_dps=0.0, gyr_bias_dps=0.0, gyr_drift_dps=0.01)
    ends = np.array([_run(cfg, seed=s, n=2560)[0][-1] for s in range(200)])  # T = 10 s
    assert np.rad2deg(ends.std()) == pytest.approx(0.01 * np.sqrt(10.0), rel=0.15)


def test_magnetometer_lags_by_the_configured_samples():
    cfg = SensorConfig(
        mag_noise_ut=0.0, mag_hard_iron_ut=0.0, mag_soft_iron=0.0, mag_hold_fraction=0.0, mag_lag_samples=4
    )
    _, _, mag = _run(dataclasses.replace(cfg, gyr_lag_samples=0))
    _, _, ideal = _ideal()
    np.testing.assert_array_equal(mag[4:], ideal[:-4])
    _, _, mag = _run(dataclasses.replace(cfg, gyr_lag_samples=2))  # 4 behind the gyro, which is 2 behind
    np.testing.assert_array_equal(mag[6:], ideal[:-6])


def test_gyro_lags_the_true_motion_by_the_configured_samples():
    cfg = SensorConfig(gyr_noise_dps=0.0, gyr_bias_dps=0.0, gyr_drift_dps=0.0, gyr_lag_samples=1)
    g, a, m = _ideal()
    g = np.stack([np.sin(np.arange(len(g)) / 50.0)] * 3, axis=1)
    gyr, acc, _ = apply_sensor_model(g, a, m, RATE, cfg, np.random.default_rng(0))
    np.testing.assert_array_equal(gyr[1:], g[:-1])
    assert np.array_equal(gyr[0], g[0])


def test_holds_come_in_runs_of_the_configured_length():
    for run in (1, 2, 3):
        _, _, mag = _run(SensorConfig(mag_hold_fraction=0.29, mag_hold_run=run))
        held = np.r_[False, np.all(mag[1:] == mag[:-1], axis=1)]
        edges = np.diff(np.r_[0, held.astype(int), 0])
        lengths = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
        assert set(lengths.tolist()) == {run}
        assert held.mean() == pytest.approx(0.29, abs=0.01)


def test_magnetometer_noise_is_low_pass_over_its_conversions():
    base = SensorConfig(mag_hard_iron_ut=0.0, mag_soft_iron=0.0, mag_lag_samples=0, gyr_lag_samples=0)
    g, a, ideal = _ideal(n=60000)
    for taps, rho1, rho2 in ((3, 4 / 6, 1 / 6), (1, 0.0, 0.0)):
        cfg = dataclasses.replace(base, mag_noise_taps=taps)
        _, _, mag = apply_sensor_model(g, a, ideal, RATE, cfg, np.random.default_rng(1))
        new = np.r_[True, np.any(mag[1:] != mag[:-1], axis=1)]
        e = (mag - ideal)[new]
        e = e - e.mean(0)
        ac = lambda k: np.mean([np.corrcoef(e[:-k, j], e[k:, j])[0, 1] for j in range(3)])
        assert ac(1) == pytest.approx(rho1, abs=0.03) and ac(2) == pytest.approx(rho2, abs=0.03)
        assert np.std(e) == pytest.approx(cfg.mag_noise_ut, rel=0.03)


def test_sample_and_hold_repeats_the_configured_fraction():
    cfg = SensorConfig(mag_hold_fraction=0.29)
    _, _, mag = _run(cfg)
    repeats = np.mean(np.all(mag[1:] == mag[:-1], axis=1))
    assert repeats == pytest.approx(0.29, abs=0.01)
    # Without hold, noise makes repeats impossible.
    _, _, mag = _run(dataclasses.replace(cfg, mag_hold_fraction=0.0))
    assert not np.any(np.all(mag[1:] == mag[:-1], axis=1))


def test_magnetometer_saturates():
    cfg = SensorConfig(mag_range_ut=25.0)
    _, _, mag = _run(cfg)
    assert np.abs(mag).max() == 25.0
    assert np.any(mag == -25.0) and np.any(mag == 25.0)


def test_residual_iron_distorts_the_field_slightly():
    cfg = SensorConfig(mag_noise_ut=0.0, mag_lag_samples=0, mag_hold_fraction=0.0)
    _, _, mag = _run(cfg)
    _, _, ideal = _ideal()
    err = np.linalg.norm(mag - ideal, axis=1)
    assert 0.0 < err.max() < 3.0  # ~0.3 µT offset + 0.5 % of a ~40 µT field


def test_same_seed_same_readings_other_seed_differs():
    a = _run(SensorConfig(), seed=7)
    b = _run(SensorConfig(), seed=7)
    c = _run(SensorConfig(), seed=8)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[0], c[0])


@pytest.mark.parametrize(
    "field, value",
    [
        ("gyr_noise_dps", -1.0),
        ("mag_hold_fraction", 1.0),
        ("mag_lag_samples", 2.5),
        ("gyr_lag_samples", 0.5),
        ("mag_hold_run", 0),
        ("mag_noise_taps", 1.5),
        ("acc_noise", float("nan")),
        ("mag_range_ut", 0.0),
    ],
)
def test_bad_sensor_parameters_are_named(field, value):
    with pytest.raises(ValueError, match=field):
        SensorConfig(**{field: value})


@pytest.mark.parametrize("block", [1, 5, 333])
def test_sensor_stream_in_blocks_equals_one_draw_bit_for_bit(block):
    """SensorStream fed block by block (noise streams split, the magnetometer lag and hold across block
    edges) gives apply_sensor_model's numbers, and leaves the generator where it leaves it."""
    cfg = SensorConfig(mag_lag_samples=4)
    gyr, acc, mag = _ideal()
    whole_rng, block_rng = np.random.default_rng(3), np.random.default_rng(3)
    whole = apply_sensor_model(gyr, acc, mag, RATE, cfg, whole_rng)
    stream = SensorStream(len(gyr), RATE, cfg, block_rng)
    parts = [
        stream.measure(gyr[a : a + block], acc[a : a + block], mag[a : a + block]) for a in range(0, len(gyr), block)
    ]
    for k in range(3):
        assert np.array_equal(np.concatenate([p[k] for p in parts]), whole[k])
    assert block_rng.integers(2**62) == whole_rng.integers(2**62)
