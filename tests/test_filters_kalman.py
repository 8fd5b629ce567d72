"""The Kalman filter family: survey A.1/A.2 estimators, the trust KF core, covariance health."""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest
from conftest import kinematic_trial

from magenv import metrics
from magenv import quaternion as quat
from magenv.baselines import kalman as bk
from magenv.filters import kalman_trust as kt
from magenv.filters.kalman_model import ModelKF
from magenv.filters.kalman_threshold import FilterError, ThresholdKF, repair_cov1
from magenv.filters.sensors import Sensors
from magenv.protocols import Estimate, Estimator

STRONG = dict(duration=20.0, disturbance_ut=30.0, disturbance_window=(8.0, 12.0))  # short, strong
WEAK = dict(duration=25.0, disturbance_ut=5.0, disturbance_window=(5.0, 20.0))  # long, weak (passes Table A1)


@cache
def trial(seed=0, kind="clean"):
    kw = {"clean": dict(duration=20.0), "strong": STRONG, "weak": WEAK}[kind]
    return kinematic_trial(seed=seed, **kw)


@cache
def oscillating_trial(seed=0, amp=5.0, freq=0.25):
    """Clean kinematic trial plus an east-pointing earth-frame disturbance amp·sin(2πft), µT."""
    tr = kinematic_trial(seed=seed, duration=20.0)
    d_e = np.zeros((tr.n, 3))
    d_e[:, 0] = amp * np.sin(2 * np.pi * freq * tr.t)
    d_s = quat.rotate_inv(tr.q_true, d_e)
    return dataclasses.replace(tr, mag=tr.mag + d_s, truth={**tr.truth, "mag_disturbance": d_s})


def score(est, tr, after=2.0):
    return metrics.score(est.q, tr.q_true, tr.t >= after)


def in_window(tr, window):
    return (tr.t >= window[0]) & (tr.t < window[1])


# ------------------------------------------------------------- estimators


def test_methods_registry_and_protocol():
    assert set(bk.methods()) == {"th_triad", "th_quest", "mod_triad", "mod_quest"}
    tr = trial()
    for name, factory in bk.methods().items():
        est = factory()
        assert isinstance(est, Estimator), name
        out = est.run(tr)
        assert isinstance(out, Estimate)
        assert out.q.shape == (tr.n, 4) and out.trust.shape == (tr.n,)
        assert np.all(np.isfinite(out.q)) and np.all((out.trust >= 0) & (out.trust <= 1)), name
        np.testing.assert_allclose(np.linalg.norm(out.q, axis=1), 1.0, atol=1e-9)


@pytest.mark.parametrize("name", ["th_triad", "th_quest", "mod_triad", "mod_quest"])
def test_converges_on_clean_trial(name):
    tr = trial(seed=1)
    s = score(bk.methods()[name]().run(tr), tr)
    assert s.total < 0.5, s  # degrees; sensor noise alone


def test_threshold_rejects_short_strong_disturbance():
    tr = trial(seed=2, kind="strong")
    win = in_window(tr, STRONG["disturbance_window"])
    for name in ("th_triad", "th_quest"):
        out = bk.methods()[name]().run(tr)
        assert out.trust[win].mean() < 0.01, name  # replaced (A8)
        assert out.trust[~win].mean() > 0.99, name  # accepted outside
        assert score(out, tr).heading < 0.5, name
    for name in ("mod_triad", "mod_quest"):  # a first-order GM model cannot reject 30 µT for 4 s (survey §5)
        assert score(bk.methods()[name]().run(tr), tr).heading > 5.0, name


def test_triad_keeps_inclination_under_magnetic_disturbance():
    tr = trial(seed=2, kind="strong")
    incl = {name: score(f().run(tr), tr).inclination for name, f in bk.methods().items()}
    assert incl["mod_triad"] < 0.2, incl  # disturbance absorbed into ĥ, yet no tilt
    assert incl["mod_quest"] > 3 * incl["mod_triad"], incl  # QUEST lets the disturbance tilt the estimate


def test_long_weak_disturbance_passes_thresholds_and_model_based_does_better():
    tr = trial(seed=3, kind="weak")
    win = in_window(tr, WEAK["disturbance_window"])
    th = bk.th_triad().run(tr)
    assert th.trust[win].mean() > 0.95  # 5 µT east: |Δm| ≈ 0.3 µT, Δdip ≈ 0.4° — under Table A1
    s_th = score(th, tr).heading
    s_mod = score(bk.mod_triad().run(tr), tr).heading
    assert s_th > 5.0  # fully biased (≈ atan(5 / 29.8) inside the window)
    assert s_mod < s_th - 0.3, (s_mod, s_th)


def test_model_based_disturbance_estimate_tracks_onset():
    tr = trial(seed=3, kind="weak")
    res = ModelKF().run(tr)
    err = np.linalg.norm(res.disturbance - tr.truth["mag_disturbance"], axis=1)
    before = in_window(tr, (1.0, 5.0))
    onset = in_window(tr, (5.0, 5.5))
    assert err[before].mean() < 0.5  # µT
    assert err[onset].mean() < 1.0  # the first half second of a 5 µT step is attributed to d̂
    assert np.linalg.norm(res.disturbance[onset], axis=1).mean() > 4.0


def test_model_based_beats_threshold_on_weak_varying_disturbance():
    tr = oscillating_trial(seed=4)
    s_th = min(score(bk.th_triad().run(tr), tr).heading, score(bk.th_quest().run(tr), tr).heading)
    s_mod = max(score(bk.mod_triad().run(tr), tr).heading, score(bk.mod_quest().run(tr), tr).heading)
    assert s_mod < 0.7 * s_th, (s_mod, s_th)


# -------------------------------------------------------------- trust KF


def gyro_only(tr, q0):
    q = np.empty((tr.n, 4))
    q[0] = q0
    for i in range(1, tr.n):
        q[i] = quat.integrate_gyro1(q[i - 1], 0.5 * (tr.gyr[i - 1] + tr.gyr[i]), tr.dt)
    return q


def test_trust_zero_ignores_magnetometer_entirely():
    tr = trial(seed=5, kind="strong")
    q, sig = kt.run_trial(tr, 0.0)
    ref = gyro_only(tr, q[0])
    # heading moves with the gyro alone (the accelerometer only corrects tilt)
    assert metrics.heading_error(metrics.error_quaternion(q, ref)).max() < 0.01
    # bit-for-bit independent of the magnetometer after sample 0 (which only initialises)
    bogus_mag = tr.mag[::-1] * 3.0 + 7.0
    bogus_mag[0] = tr.mag[0]
    q2, _ = kt.run_trial(dataclasses.replace(tr, mag=bogus_mag), 0.0)
    np.testing.assert_array_equal(q2, q)
    assert np.all(sig[1:, 12] == 0.0)


def test_trust_one_nominal_and_consistent():
    tr = trial(seed=6)
    q, sig = kt.run_trial(tr, 1.0)
    s = metrics.score(q, tr.q_true, tr.t >= 2.0)
    assert s.total < 0.2, s
    nis = sig[tr.t >= 2.0, 4]
    assert 2.6 < nis.mean() < 3.4  # χ²₃ mean: the filter's S matches its innovations
    assert np.all(np.isfinite(sig[1:]))


def test_trust_kf_converges_from_wrong_heading():
    tr = trial(seed=7)
    params = kt.make_params(tr.field_norm, tr.field_dip, tr.dt, p0=np.deg2rad(30.0) ** 2)
    state = kt.init(params, tr.acc[0], tr.mag[0])
    q, p = state
    q[:] = quat.mul1(quat.from_rotvec1(np.array([0.0, 0.0, np.deg2rad(30.0)])), q)
    q_out = np.empty((tr.n, 4))
    sig = np.empty((tr.n, kt.NSIG))
    kt.run_k(params, state, Sensors.of(tr), 1, tr.n, 1.0, q_out, sig)
    late = tr.t >= 3.0
    assert metrics.score(q_out[1:], tr.q_true[1:], late[1:]).total < 0.5
    # a +30° heading error turns north toward west: east innovation ≈ −sin 30°·|h_horizontal|
    h_n = tr.field_norm * np.cos(np.deg2rad(tr.field_dip))
    assert sig[1, 0] == pytest.approx(-np.sin(np.deg2rad(30.0)) * h_n, rel=0.1)


def test_trust_reduces_disturbance_error_and_run_k_chunks_match():
    tr = trial(seed=8, kind="strong")
    params = kt.make_params(tr.field_norm, tr.field_dip, tr.dt)
    q_full, sig_full = kt.run_trial(tr, 1.0, params)
    # chunked calls as the env will make them, 16 samples per decision
    state = kt.init(params, tr.acc[0], tr.mag[0])
    q, p = state
    q_out = np.empty((tr.n, 4))
    q_out[0] = q
    sig = np.full((tr.n, kt.NSIG), np.nan)
    for i0 in range(1, tr.n, 16):
        kt.run_k(params, state, Sensors.of(tr), i0, min(i0 + 16, tr.n), 1.0, q_out, sig)
    np.testing.assert_array_equal(q_out, q_full)
    np.testing.assert_array_equal(sig[1:], sig_full[1:])
    # gating the magnetometer inside the disturbance window beats trusting it
    win = in_window(tr, STRONG["disturbance_window"])
    q_gate, sig_gate = kt.run_trial(tr, np.where(win, 0.0, 1.0))
    assert metrics.score(q_gate, tr.q_true).heading < 0.5 < metrics.score(q_full, tr.q_true).heading
    assert sig_full[win, 4].mean() > 100 * sig_full[in_window(tr, (2.0, 8.0)), 4].mean()  # NIS flags it


def test_trust_kf_rejects_bad_arguments():
    tr = trial()
    params = kt.make_params(tr.field_norm, tr.field_dip, tr.dt)
    state = kt.init(params, tr.acc[0], tr.mag[0])
    q, p = state
    q_out, sig = np.empty((tr.n, 4)), np.empty((tr.n, kt.NSIG))
    with pytest.raises(ValueError, match="trust"):
        kt.run_k(params, state, Sensors.of(tr), 1, 10, 1.5, q_out, sig)
    with pytest.raises(ValueError, match="i0"):
        kt.run_k(params, state, Sensors.of(tr), 0, 10, 1.0, q_out, sig)
    with pytest.raises(FilterError, match="initialise"):
        kt.init(params, np.zeros(3), tr.mag[0])


# ------------------------------------------------------- covariance health


def test_repair_cov_symmetrises_and_floors():
    p = np.array([[1.0, 0.3, 0.0], [0.1, -2.0, 0.0], [0.0, 0.0, 1e-3]])
    assert repair_cov1(p, 1e-9) == 1
    np.testing.assert_array_equal(p, p.T)
    assert np.linalg.eigvalsh(p).min() >= 1e-9 * (1 - 1e-6)
    good = np.diag([1.0, 2.0, 3.0])
    assert repair_cov1(good, 1e-9) == 0
    np.testing.assert_array_equal(good, np.diag([1.0, 2.0, 3.0]))
    bad = np.eye(3)
    bad[1, 2] = np.nan
    assert repair_cov1(bad, 1e-9) == -1


def _poisoned(tr, k, value):
    tr = dataclasses.replace(tr, acc=tr.acc.copy())  # Trial refuses NaN; poison after construction
    tr.acc[k] = value
    return tr


@pytest.mark.parametrize(
    "kf",
    [ThresholdKF("triad"), ThresholdKF("quest"), ModelKF("triad"), ModelKF("quest")],
    ids=["th_triad", "th_quest", "mod_triad", "mod_quest"],
)
def test_nan_sample_fails_loudly(kf):
    tr = _poisoned(trial(), 100, np.nan)
    with pytest.raises(FilterError, match="sample 100"):
        kf.run(tr)


def test_trust_kf_nan_sample_fails_loudly_and_keeps_state():
    tr = _poisoned(trial(), 50, np.inf)
    params = kt.make_params(tr.field_norm, tr.field_dip, tr.dt)
    state = kt.init(params, tr.acc[0], tr.mag[0])
    q, p = state
    q_out, sig = np.empty((tr.n, 4)), np.empty((tr.n, kt.NSIG))
    kt.run_k(params, state, Sensors.of(tr), 1, 50, 1.0, q_out, sig)
    q_before, p_before = q.copy(), p.copy()
    with pytest.raises(FilterError, match="sample 50"):
        kt.run_k(params, state, Sensors.of(tr), 50, 60, 1.0, q_out, sig)
    np.testing.assert_array_equal(q, q_before)
    np.testing.assert_array_equal(p, p_before)


def test_extreme_finite_samples_give_no_nan():
    tr = trial(seed=9)
    acc, mag, gyr = tr.acc.copy(), tr.mag.copy(), tr.gyr.copy()
    acc[200], mag[300], gyr[400] = 1e6, -1e6, 50.0  # saturating spikes
    acc[500] = 0.0  # free fall
    tr = dataclasses.replace(tr, acc=acc, mag=mag, gyr=gyr)
    for name, f in bk.methods().items():
        out = f().run(tr)
        assert np.all(np.isfinite(out.q)), name
    q, sig = kt.run_trial(tr, 1.0)
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(sig[1:]))


def test_long_run_keeps_covariances_healthy():
    tr = kinematic_trial(seed=10, duration=120.0)
    for kf in (ThresholdKF("quest"), ThresholdKF("triad"), ModelKF("triad")):
        assert kf.run(tr).repairs == 0, kf
    params = kt.make_params(tr.field_norm, tr.field_dip, tr.dt)
    state = kt.init(params, tr.acc[0], tr.mag[0])
    q, p = state
    q_out, sig = np.empty((tr.n, 4)), np.empty((tr.n, kt.NSIG))
    for trust in (1.0, 0.3, 0.0):  # a third of the trial each
        i0 = {1.0: 1, 0.3: tr.n // 3, 0.0: 2 * tr.n // 3}[trust]
        i1 = {1.0: tr.n // 3, 0.3: 2 * tr.n // 3, 0.0: tr.n}[trust]
        assert kt.run_k(params, state, Sensors.of(tr), i0, i1, trust, q_out, sig) == 0
    np.testing.assert_array_equal(p, p.T)
    assert np.linalg.eigvalsh(p).min() > 0
    assert metrics.score(q_out[1:], tr.q_true[1:]).inclination < 0.2


# ------------------------------------------------------------ unit checks


def test_vector_selector_a7_a8():
    from magenv.filters.kalman_threshold import select1

    m0 = 46.0
    g_ref, h_ref = quat.gravity_up(), quat.earth_field(46.0, 49.6)
    q = quat.from_euler_zyx(0.7, 0.2, -0.4)
    g_b, h_b = quat.rotate_inv1(q, g_ref), quat.rotate_inv1(q, h_ref)
    prm = ThresholdKF(th_acc=0.08, th_mag=1.2, th_dip=5.0).params(m0, 49.6, 0.01)
    q_pred = quat.mul1(quat.from_rotvec1(np.array([0.0, 0.0, 0.1])), q)  # prior off by 0.1 rad heading
    s_g, s_h, a_ok, m_ok = select1(prm, q_pred, g_b, h_b)
    assert a_ok and m_ok
    np.testing.assert_allclose(s_h, h_b / m0, atol=1e-12)
    # body acceleration of 0.5 m/s² along gravity → replaced by the prediction (A7)
    s_g, s_h, a_ok, m_ok = select1(prm, q_pred, g_b * (1 + 0.5 / 9.81), h_b)
    assert not a_ok
    np.testing.assert_allclose(s_g, quat.rotate_inv1(q_pred, g_ref) / 9.81, atol=1e-12)
    # same norm, dip 10° steeper → rejected by the dip test (A8)
    h_steep = quat.rotate_inv1(q, quat.earth_field(46.0, 59.6))
    s_g, s_h, a_ok, m_ok = select1(prm, q_pred, g_b, h_steep)
    assert a_ok and not m_ok
    np.testing.assert_allclose(s_h, quat.rotate_inv1(q_pred, h_ref) / m0, atol=1e-12)
    # dip 3° steeper, norm +1 µT → accepted; norm +1.5 µT → rejected by the norm test
    h_ok = quat.rotate_inv1(q, quat.earth_field(47.0, 52.6))
    assert select1(prm, q_pred, g_b, h_ok)[3]
    h_big = quat.rotate_inv1(q, quat.earth_field(47.5, 49.6))
    assert not select1(prm, q_pred, g_b, h_big)[3]


def test_quaternion_kf_prediction_a1_a6():
    from magenv.filters.kalman_threshold import predict1, xi1

    q = quat.from_euler_zyx(0.3, -0.2, 0.5)
    w = np.array([0.4, -1.0, 2.0])
    qp, pp = predict1(q, np.zeros((4, 4)), w, 0.01, 0.02)
    np.testing.assert_allclose(qp, quat.integrate_gyro1(q, w, 0.01), atol=1e-15)
    xi = xi1(q)
    np.testing.assert_allclose(xi @ w, quat.mul1(q, np.r_[0.0, w]), atol=1e-15)  # Ξ n = q ⊗ [0, n]
    np.testing.assert_allclose(pp, (0.005 * 0.02) ** 2 * xi @ xi.T, atol=1e-20)  # A4
    assert abs(q @ pp @ q) < 1e-20  # process noise is tangent to the unit sphere


def test_gauss_markov_split_a9_a10():
    from magenv.filters.kalman_model import VecParams, vec_step1

    r, d = np.array([10.0, -20.0, 30.0]), np.array([1.0, 2.0, -3.0])
    omega, dt, c_a = np.array([0.5, -0.2, 1.0]), 0.01, 0.1
    r_pred = quat.rotate_inv1(quat.from_rotvec1(omega * dt), r)  # ṙ = −ω × r
    np.testing.assert_allclose(r_pred, r - np.cross(omega, r) * dt, atol=1e-3)
    y = r_pred + c_a * d  # a measurement equal to the prediction (A10) leaves the state at F x (A9)
    vp = VecParams(dt=dt, sigma_gyr=0.01, sigma_y=0.15, c_a=c_a, c_b=1.0, p0_ref=1.0, cov_floor=1e-14)
    x, p = np.r_[r, d], np.eye(6)
    gain, status = vec_step1(vp, x, p, omega, y, np.empty((6, 6)))
    np.testing.assert_allclose(x, np.r_[r_pred, c_a * d], atol=1e-12)
    assert status == 0 and 0 < gain < 1
    np.testing.assert_array_equal(p, p.T)


def test_trust_scales_the_magnetometer_influence():
    tr = trial(seed=8, kind="strong")
    head = [metrics.score(kt.run_trial(tr, t)[0], tr.q_true).heading for t in (0.0, 0.02, 0.2, 1.0)]
    assert head[0] < head[1] < head[2] < head[3], head  # a 30 µT disturbance: the more trust, the more error


def test_trust_kf_heading_only_keeps_magnetometer_out_of_tilt():
    tr = trial(seed=8, kind="strong")
    incl = {}
    for heading_only in (True, False):
        params = kt.make_params(tr.field_norm, tr.field_dip, tr.dt, kt.Options(heading_only=heading_only))
        incl[heading_only] = metrics.score(kt.run_trial(tr, 1.0, params)[0], tr.q_true).inclination
    assert incl[True] < 0.1 < 0.5 < incl[False], incl


@pytest.mark.slow
def test_survey_findings_over_seeds():
    """RMSE table of the four combinations (print with ``-s``) and the survey's qualitative findings.

    ``.venv/bin/python -m pytest tests/test_filters_kalman.py -m slow -s``
    """
    cases = {
        "clean": lambda s: trial(s, "clean"),
        "short_strong": lambda s: trial(s, "strong"),
        "long_weak": lambda s: trial(s, "weak"),
        "weak_varying": lambda s: oscillating_trial(s),
    }
    table = {}
    for case, make in cases.items():
        for name, factory in bk.methods().items():
            rows = [metrics.score(factory().run(make(s)).q, make(s).q_true) for s in range(5)]
            table[case, name] = np.mean([[r.total, r.heading, r.inclination] for r in rows], axis=0)
    print("\ncase          method      total  heading  inclination  (deg RMSE, mean of 5 seeds)")
    for (case, name), v in table.items():
        print(f"{case:13s} {name:10s} {v[0]:6.2f}  {v[1]:6.2f}   {v[2]:6.3f}")
    for th in ("th_triad", "th_quest"):
        for mod in ("mod_triad", "mod_quest"):
            assert table["short_strong", th][0] < table["short_strong", mod][0]  # thresholds win short-strong
            assert table["long_weak", mod][0] < table["long_weak", th][0]  # model-based win long-weak
            assert table["weak_varying", mod][0] < table["weak_varying", th][0]
    assert table["short_strong", "mod_triad"][2] < table["short_strong", "mod_quest"][2]  # TRIAD keeps tilt
