"""Twin scenarios (``twin:PATH``): the fit, its cache, the sensor model pieces, determinism, the scenario API."""

from __future__ import annotations

import numpy as np
import pytest

from magenv import scenarios
from magenv.envs.common import TrialSource
from magenv.recordings import find_recording
from magenv.scenarios import twin, twin_fit
from magenv.sensor_stats import hold_fraction, rest_noise
from magenv.sim import truth_motion as tm
from magenv.sim.sensors import hold_pattern, hold_samples, noise_121


@pytest.fixture(scope="module")
def name07(broad_dir) -> str:
    return f"twin:{find_recording('07', broad_dir)}"


@pytest.fixture(scope="module")
def fitted07(name07):
    return twin.fitted(name07)


def test_noise_121_has_unit_std_and_the_colour():
    v = noise_121(np.random.default_rng(0).standard_normal((100_000, 3)))
    assert np.allclose(v.std(0), 1.0, atol=0.02)
    rho1 = np.corrcoef(v[1:, 0], v[:-1, 0])[0, 1]
    rho2 = np.corrcoef(v[2:, 0], v[:-2, 0])[0, 1]
    assert rho1 == pytest.approx(4 / 6, abs=0.02) and rho2 == pytest.approx(1 / 6, abs=0.02)


def test_hold_samples_repeat_the_last_new_row():
    x = np.arange(6.0)[:, None]
    held = np.array([True, True, False, True, False, False])
    assert hold_samples(x, held).ravel().tolist() == [0, 0, 2, 2, 4, 5]
    assert hold_pattern(10_000, 0.29, 0.4).mean() == pytest.approx(0.29, abs=0.001)


def test_delay_is_fractional_and_bridge_meets_both_ends():
    x = np.arange(10.0)[:, None]
    assert tm.delay(x, 1.5).ravel()[5] == pytest.approx(3.5)
    # a rotation about z at 1 rad/s, with a gap bridged from an exact gyro
    rate, n = 100.0, 200
    ang = np.arange(n) / rate
    q = np.c_[np.cos(ang / 2), np.zeros((n, 2)), np.sin(ang / 2)]
    gap = q.copy()
    gap[80:120] = np.nan
    gyr = np.tile([0.0, 0.0, 1.0], (n, 1))
    bridged, bad = tm.bridge_gaps(gap, gyr, rate, np.zeros(3), 0.0)
    assert bad.sum() == 40
    assert np.max(np.abs(np.abs(np.sum(bridged * q, 1)) - 1.0)) < 1e-6


def test_fit_of_a_real_recording(fitted07):
    rec, mo, fit = fitted07
    assert fit.disturbance == "none"  # 07 is an undisturbed recording
    assert 0.9 < fit.gyr_lag < 1.5  # BROAD: the gyro ~1.2 samples behind the optical truth
    assert 3.5 < fit.mag_lag < 5.0  # the magnetometer ~4.2 behind
    assert 0.55 < fit.mag_rho1 < 0.8  # the low-pass noise colour of the unit
    assert abs(np.linalg.norm(fit.mag_h_E) - rec.field_norm) < 1.5


def test_fit_recovers_the_lags_it_is_given(fitted07):
    """Refitting a twin made with known lags gives those lags back."""
    rec, mo, fit = fitted07
    tw = twin.make_twin(rec, mo, fit, twin.TwinConfig(gyr_lag=0.5, mag_lag=3.0), 1, "twin:x")
    mag_lag, *_ = twin_fit.fit_mag(tw, mo)
    gyr_lag, *_ = twin_fit.fit_gyro(tw, mo)
    assert mag_lag == pytest.approx(3.0, abs=0.3)
    assert gyr_lag == pytest.approx(0.5, abs=0.3)


def test_cache_is_plain_npz_and_round_trips(fitted07, name07, tmp_path):
    _, _, fit = fitted07
    file = twin.cache_file(twin.recording_path(name07))
    assert file.is_file() and file.suffix == ".npz" and str(file).startswith(str(twin.cache_dir()))
    with np.load(file, allow_pickle=False) as data:
        assert all(data[k].dtype != object for k in data.files)
    back = twin.load_fit(twin.save_fit(fit, tmp_path / "f.npz"))
    for k, v in fit.to_arrays().items():
        got = np.asarray(getattr(back, k))
        assert np.array_equal(got, v, equal_nan=v.dtype.kind == "f"), k


def test_twin_keeps_the_truth_and_is_deterministic(name07, fitted07):
    rec = fitted07[0]
    a, b, c = (scenarios.make_trial(name07, s) for s in (3, 3, 4))
    for key in ("gyr", "acc", "mag"):
        assert np.array_equal(getattr(a, key), getattr(b, key))
        assert not np.array_equal(getattr(a, key), getattr(c, key))
    assert np.array_equal(a.q_true, rec.q_true, equal_nan=True)
    assert np.array_equal(a.score_mask, rec.score_mask)
    assert a.meta["scenario"] == f"twin:{rec.name}" and a.meta["seed"] == 3
    assert scenarios.world_of(name07) == "twin"


def test_twin_sensors_look_like_the_recording(name07, fitted07):
    rec = fitted07[0]
    tw = scenarios.make_trial(name07, 0)
    real, sim = rest_noise(rec), rest_noise(tw)
    for key in ("gyr", "mag"):
        assert np.allclose(sim[key], real[key], rtol=0.25), key
    assert hold_fraction(tw.mag) == pytest.approx(hold_fraction(rec.mag), abs=0.002)
    assert hold_fraction(scenarios.make_trial(name07, 0, hold="none").mag) < 0.01
    err = np.linalg.norm(tw.mag - rec.mag, axis=1)[rec.score_mask]
    assert np.median(err) < 2.5  # µT: the same field along the same motion, apart from the noise


def test_bad_twin_arguments(name07, tmp_path):
    with pytest.raises(ValueError, match="no recording file"):
        scenarios.make_trial(f"twin:{tmp_path / 'missing.hdf5'}", 0)
    with pytest.raises(ValueError, match="'mag_noise_ut'"):
        scenarios.make_trial(name07, 0, mag_noise_ut=0.3)
    with pytest.raises(ValueError, match="hold"):
        scenarios.configure(name07, hold="sometimes")
    with pytest.raises(ValueError, match="seed"):
        scenarios.make_trial(name07, -1)


def test_trial_source_takes_twin_scenarios(name07):
    src = TrialSource(f"dynamic_clean,{name07}", {})
    assert src.kind == "scenario" and src.source[1] == name07
    with pytest.raises(ValueError, match="unknown"):
        TrialSource(name07, {}, world="twolink")


def test_twins_entry_of_a_mixture_is_every_recording_of_the_folder(broad_dir, tmp_path):
    files = sorted(broad_dir.glob("*.hdf5"))
    names = scenarios.expand_mixture(f"dynamic_clean, twins:{broad_dir}")
    assert names == ["dynamic_clean"] + [f"twin:{p.resolve()}" for p in files]
    src = TrialSource(f"dynamic_clean,twins:{broad_dir}", {})
    assert src.kind == "scenario" and list(src.source) == names
    with pytest.raises(ValueError, match="no \\*.hdf5 recording"):
        scenarios.expand_mixture([f"twins:{tmp_path}"])
    with pytest.raises(ValueError, match="twins:"):
        scenarios.expand_mixture(f"twins:{tmp_path / 'missing'}")


def test_dagger_config_takes_a_twins_entry(broad_dir):
    from magenv.agents import dagger

    cfg = dagger.check_config({"scenarios": ["dynamic_magnet", f"twins:{broad_dir}"]})
    assert cfg["scenarios"][0] == "dynamic_magnet" and len(cfg["scenarios"]) == 1 + len(list(broad_dir.glob("*.hdf5")))
    assert all(s.startswith("twin:") for s in cfg["scenarios"][1:])
