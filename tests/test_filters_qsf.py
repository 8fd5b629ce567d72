"""AEKF / MAGYQ / Delay MAGYQ, the QSF detector and ``magenv/MagQSF-v0`` (issue 9)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from conftest import check_feature_table, kinematic_trial
from gymnasium.utils.env_checker import check_env

from magenv import metrics
from magenv import quaternion as quat
from magenv.baselines import qsf as bq
from magenv.baselines.qsf import DetectorPolicy
from magenv.envs.qsf import MagQSFEnv, MagQSFVectorEnv, decode_action
from magenv.filters import qsf
from magenv.filters.kalman_threshold import FilterError
from magenv.trial import Trial

FIELD = (46.0, 49.6)


def _static_trial(n=2000, rate=100.0, disturbance=(10.0, -5.0, 3.0), seed=0):
    rng = np.random.default_rng(seed)
    q = np.tile(quat.from_euler_zyx(0.7, 0.1, -0.2), (n, 1))
    field = quat.earth_field(*FIELD) + np.asarray(disturbance)
    gyr = rng.normal(0, np.deg2rad(0.3), (n, 3))
    acc = quat.rotate_inv(q, np.tile(quat.gravity_up(), (n, 1))) + rng.normal(0, 0.03, (n, 3))
    mag = quat.rotate_inv(q, np.tile(field, (n, 1))) + rng.normal(0, 0.3, (n, 3))
    return Trial("static", rate, gyr, acc, mag, q, *FIELD)


def _run(trial, mode, **kw):
    return qsf.run_trial(trial, mode=mode, sigma_gyr=np.deg2rad(0.5), **kw)


def _still_inputs(action: int) -> qsf.Inputs:
    """Two samples at rest, level and facing north (zero rate, gravity, the Earth field), trust 1."""
    return qsf.Inputs(
        np.zeros((2, 3)),
        np.tile(quat.gravity_up(), (2, 1)),
        np.tile(quat.earth_field(*FIELD), (2, 1)),
        np.full(2, action, np.int8),
        np.ones(2),
    )


# ------------------------------------------------------------ maths


def test_rotation_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    for _ in range(5):
        q, v = rng.normal(size=4), rng.normal(size=3)
        h = lambda qq: (qq[0] ** 2 - qq[1:] @ qq[1:]) * v + 2 * (qq[1:] @ v) * qq[1:] + 2 * qq[0] * np.cross(qq[1:], v)
        num = np.stack([(h(q + 1e-6 * e) - h(q - 1e-6 * e)) / 2e-6 for e in np.eye(4)], 1)
        np.testing.assert_allclose(qsf.rot_jacobian1(q, v), num, atol=1e-8)


# ------------------------------------------------------------ filters


@pytest.mark.parametrize("mode", ["aekf", "magyq", "delay_magyq"])
def test_filters_track_a_clean_kinematic_trial(mode):
    tr = kinematic_trial(seed=1, duration=30.0, rate=100.0)
    res = _run(tr, mode)
    s = metrics.score(res.q, tr.q_true)
    assert s.total < 2.0, s
    assert res.repairs < 0.01 * tr.n


@pytest.mark.parametrize("mode", ["aekf", "magyq", "delay_magyq"])
def test_tilt_converges_from_a_wrong_start(mode):
    tr = kinematic_trial(seed=2, duration=30.0, rate=100.0)
    q0 = quat.mul(quat.from_rotvec(np.deg2rad([8.0, -6.0, 0.0])), tr.q_true[0])
    res = _run(tr, mode, q0=q0, p0=dict(p0_angle=np.deg2rad(10.0)))
    incl = metrics.inclination_error(metrics.error_quaternion(res.q, tr.q_true))
    assert metrics.inclination_error(metrics.error_quaternion(q0, tr.q_true[0])) > 5.0
    assert np.mean(incl[-500:]) < 1.5


def test_aekf_corrects_heading_but_magyq_cannot():
    """The AEKF has an absolute heading reference (the Earth field); QSF filters only relative ones."""
    tr = kinematic_trial(seed=3, duration=30.0, rate=100.0)
    q0 = quat.mul(quat.from_rotvec(np.deg2rad([0.0, 0.0, 15.0])), tr.q_true[0])
    head = {
        m: metrics.heading_error(
            metrics.error_quaternion(_run(tr, m, q0=q0, p0=dict(p0_angle=np.deg2rad(20.0))).q, tr.q_true)
        )[-300:].mean()
        for m in ("aekf", "magyq")
    }
    assert head["aekf"] < 3.0 and head["magyq"] > 10.0


def test_steady_non_earth_field_magyq_keeps_heading_aekf_is_pulled():
    tr = kinematic_trial(seed=4, duration=40.0, rate=100.0, disturbance_ut=15.0, disturbance_window=(0.0, 1e9))
    err = {}
    for m in ("aekf", "magyq", "delay_magyq"):
        res = _run(tr, m, q0=tr.q_true[0])
        err[m] = metrics.score(res.q, tr.q_true).heading
    assert err["aekf"] > 10.0
    assert err["magyq"] < 2.0 and err["delay_magyq"] < 2.0


def test_innovation_property_of_section_5_5():
    """Static MIMU, one QSF period from the first sample, both filters started at truth: Delay MAGYQ's
    corrections K·δz are smaller than MAGYQ's (Fig. 10)."""
    tr = _static_trial()
    act = np.full(tr.n, qsf.MAG_KEEP, np.int8)
    act[0] = qsf.MAG_START
    corr = {}
    for m in ("magyq", "delay_magyq"):
        res = qsf.run_trial(tr, mode=m, q0=tr.q_true[0], actions=act, max_age_s=1e6)
        assert np.all(res.sig[:, 0] == 1.0)  # the period started on the first sample and never ended
        corr[m] = res.sig[1:, qsf.SIGNALS.index("corr_norm")].mean()
    assert corr["delay_magyq"] < 0.8 * corr["magyq"]


def test_no_magnetic_update_without_a_period():
    tr = _static_trial(n=300)
    res = qsf.run_trial(tr, mode="magyq", actions=np.zeros(tr.n, np.int8))
    assert not res.sig[:, qsf.SIGNALS.index("mag_updated")].any()
    keep_only = qsf.run_trial(tr, mode="magyq", actions=np.full(tr.n, qsf.MAG_KEEP, np.int8))
    np.testing.assert_array_equal(res.q, keep_only.q)  # keep without an active period = no update


def test_trust_zero_equals_no_update():
    tr = _static_trial(n=500)
    act = np.full(tr.n, qsf.MAG_KEEP, np.int8)
    act[0] = qsf.MAG_START
    a = qsf.run_trial(tr, mode="delay_magyq", actions=act, trust=0.0).q
    b = qsf.run_trial(tr, mode="delay_magyq", actions=np.zeros(tr.n, np.int8)).q
    np.testing.assert_allclose(a, b, atol=1e-12)


# ------------------------------------------------------------ covariance health and bad input


def test_period_that_never_ends_stays_healthy():
    tr = kinematic_trial(seed=5, duration=60.0, rate=100.0, disturbance_ut=10.0, disturbance_window=(0.0, 1e9))
    act = np.full(tr.n, qsf.MAG_KEEP, np.int8)
    act[0] = qsf.MAG_START
    params = qsf.make_params(*FIELD, mode="delay_magyq", sigma_gyr=np.deg2rad(0.5), max_age_s=1e6)
    state, out = qsf.initial_state(tr.q_true[0], tr.dt), qsf.Outputs.empty(tr.n)
    repairs = qsf.run(params, state, qsf.Inputs(tr.gyr, tr.acc, tr.mag, act, np.ones(tr.n)), tr.dt, 0, tr.n, out)
    q_out, sig, pa = out.q, out.sig, state.cov
    assert np.all(np.isfinite(q_out)) and np.all(sig[:, 0] == 1.0)
    assert sig[-1, qsf.SIGNALS.index("age")] == pytest.approx(tr.duration - tr.dt)
    np.testing.assert_array_equal(pa, pa.T)
    assert np.linalg.eigvalsh(pa).min() > 0.0
    assert repairs < 0.01 * tr.n
    assert metrics.score(q_out, tr.q_true).total < 3.0


def test_max_age_restarts_a_period():
    tr = _static_trial(n=600)
    act = np.full(tr.n, qsf.MAG_KEEP, np.int8)
    act[0] = qsf.MAG_START
    res = qsf.run_trial(tr, mode="magyq", actions=act, max_age_s=1.0)
    age = res.sig[:, qsf.SIGNALS.index("age")]
    assert age.max() <= 1.0 + 1e-9 and np.sum(np.diff(age) < 0) >= 4


def test_broken_covariance_is_repaired_not_nan():
    params = qsf.make_params(*FIELD, mode="aekf")
    state = qsf.initial_state(np.array([1.0, 0, 0, 0]), 0.01)
    x, pa = state.x, state.cov
    pa[:11, :11] -= 1e-3 * np.eye(11)  # no longer positive definite
    pa[0, 1] += 1e-4  # nor symmetric
    sig = np.zeros(qsf.N_SIGNALS)
    st = qsf.step1(params, state, _still_inputs(action=0), 1, 0.01, sig)
    assert st == 1
    np.testing.assert_array_equal(pa, pa.T)
    assert np.linalg.eigvalsh(pa[:11, :11]).min() > 0.0 and np.all(np.isfinite(x))


def test_non_finite_input_fails_loudly():
    tr = _static_trial(n=100)
    tr.mag[50, 1] = np.nan  # bypass Trial's own check on purpose
    with pytest.raises(ValueError, match="finite"):  # the detector refuses it first
        qsf.run_trial(tr, mode="delay_magyq")
    params = qsf.make_params(*FIELD, mode="magyq")
    state = qsf.initial_state(tr.q_true[0], tr.dt)
    x, pa = state.x, state.cov
    with pytest.raises(FilterError, match="sample 50"):
        qsf.run(
            params,
            state,
            qsf.Inputs(tr.gyr, tr.acc, tr.mag, np.full(tr.n, 2, np.int8), np.ones(tr.n)),
            tr.dt,
            0,
            tr.n,
            qsf.Outputs.empty(tr.n),
        )
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(pa))  # state left at sample 49
    params = qsf.make_params(*FIELD)
    state = qsf.initial_state(np.array([1.0, 0, 0, 0]), 0.01)
    state.cov[0, 0] = np.inf
    sig = np.zeros(qsf.N_SIGNALS)
    assert qsf.step1(params, state, _still_inputs(action=2), 1, 0.01, sig) == -1


def test_bad_parameters_raise():
    with pytest.raises(ValueError):
        qsf.make_params(*FIELD, mode="ekf")
    with pytest.raises(ValueError):
        qsf.make_params(*FIELD, sigma_mag=-1.0)
    with pytest.raises(ValueError):
        qsf.QSFDetector(th_spread=0.0)
    with pytest.raises(ValueError):
        qsf.run_trial(_static_trial(n=50), actions=np.full(50, 3, np.int8))


# ------------------------------------------------------------ detector


def test_detector_flags_steady_field_and_not_a_varying_one():
    rng = np.random.default_rng(7)
    base = kinematic_trial(seed=7, duration=20.0, rate=100.0, noise=False)
    t = base.t
    field = np.tile(quat.earth_field(*FIELD) + np.array([8.0, 3.0, -4.0]), (base.n, 1))
    varying = t >= 10.0
    field[varying, 0] += 6.0 * np.sin(2 * np.pi * 0.7 * t[varying])  # time-varying field in the second half
    mag = quat.rotate_inv(base.q_true, field) + rng.normal(0, 0.15, (base.n, 3))
    gyr = base.gyr + rng.normal(0, np.deg2rad(0.3), base.gyr.shape)
    code, spread = qsf.QSFDetector().detect(gyr, mag, 100.0)
    steady_part = (t > 1.0) & (t < 10.0)
    assert np.mean(code[steady_part] > 0) > 0.9
    assert np.mean(code[t > 10.5] > 0) < 0.2
    assert np.all(code[:49] == 0) and np.all(np.isnan(spread[:49]))  # window not full yet
    assert code[49] == qsf.MAG_START  # the first full window starts a period, kept through the steady part
    assert np.all(code[50:1000] == qsf.MAG_KEEP)


def test_detector_window_of_one_sample_starts_on_the_first_sample():
    tr = _static_trial(n=100)
    code, _ = qsf.QSFDetector(window_s=0.01, th_spread=5.0).detect(tr.gyr, tr.mag, tr.rate)
    assert code[0] == qsf.MAG_START and np.all(code[1:] == qsf.MAG_KEEP)
    res = qsf.run_trial(tr, mode="delay_magyq", detector=qsf.QSFDetector(window_s=0.01, th_spread=5.0))
    assert res.sig[0, 0] == 1.0 and np.all(np.isfinite(res.q))


# ------------------------------------------------------------ estimators and env


def test_estimators_registered_and_deterministic():
    assert set(bq.methods()) >= {"aekf", "magyq", "delay_magyq"}
    tr = kinematic_trial(seed=8, duration=5.0, rate=100.0)
    a, b = bq.magyq().run(tr), bq.magyq().run(tr)
    np.testing.assert_array_equal(a.q, b.q)
    assert a.q.shape == (tr.n, 4) and a.trust.shape == (tr.n,)
    with pytest.raises(ValueError):
        bq.QSFEstimator(init="oracle")


def _env_trial():
    return kinematic_trial(seed=9, duration=6.0, rate=100.0, disturbance_ut=10.0, disturbance_window=(0.0, 1e9))


def test_env_passes_gymnasium_checker():
    env = MagQSFEnv(scenario=[_env_trial()], decision_every=5)
    check_env(env, skip_render_check=True)


def test_registered_env_id():
    if "magenv/MagQSF-v0" not in gym.registry:
        gym.register("magenv/MagQSF-v0", entry_point="magenv.envs.qsf:MagQSFEnv")
    env = gym.make("magenv/MagQSF-v0", scenario=[_env_trial()])
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert "qsf_detector" in bq.methods()  # the detector policy is offered once the env is registered


def test_env_draws_handheld_scenarios_by_name():
    env = MagQSFEnv(
        scenario="handheld_texting,handheld_swinging", episode_seconds=2.0, scenario_kwargs=dict(duration=3.0)
    )
    obs, info = env.reset(seed=3)
    assert info["trial"].startswith("handheld_") and info["n_samples"] == 200
    obs2, info2 = MagQSFEnv(
        scenario="handheld_texting,handheld_swinging", episode_seconds=2.0, scenario_kwargs=dict(duration=3.0)
    ).reset(seed=3)
    assert info2["trial"] == info["trial"] and np.array_equal(obs, obs2)


def test_detector_policy_reproduces_the_delay_magyq_estimator():
    tr = _env_trial()
    env = MagQSFEnv(scenario=[tr], decision_every=1)
    obs, _ = env.reset(seed=0)
    policy, done, rewards = DetectorPolicy(), False, []
    while not done:
        obs, r, _, done, info = env.step(policy(obs))
        rewards.append(r)
    np.testing.assert_array_equal(env.estimate, bq.delay_magyq().run(tr).q)
    assert np.all(np.asarray(rewards) <= 0.0)


def test_env_actions_decode_and_validate():
    assert decode_action([-1.0, 0.5])[:2] == (qsf.MAG_NONE, 0.5)
    assert decode_action([0.0, 1.0])[:2] == (qsf.MAG_KEEP, 1.0)
    assert decode_action([2.0, 1.5]) == (qsf.MAG_START, 1.0, True)
    with pytest.raises(ValueError):
        decode_action([np.nan, 1.0])
    with pytest.raises(ValueError):
        decode_action([0.0])
    env = MagQSFEnv(scenario=[_env_trial()], decision_every=10)
    with pytest.raises(RuntimeError):
        env.step([0.0, 1.0])
    env.reset(seed=1)
    _, _, _, _, info = env.step(np.array([1.0, 1.0], np.float32))
    assert info["decision"] == "start" and info["qsf_active"]
    _, _, _, _, info = env.step(np.array([-1.0, 1.0], np.float32))
    assert info["decision"] == "none" and not info["qsf_active"]


def test_vector_env_replays_single_envs():
    trials = [_env_trial(), kinematic_trial(seed=10, duration=4.0, rate=100.0)]
    venv = MagQSFVectorEnv(num_envs=2, scenario=trials, decision_every=20)
    obs, _ = venv.reset(seed=4)
    singles = [MagQSFEnv(scenario=trials, decision_every=20) for _ in range(2)]
    single_obs = [e.reset(seed=4 + i)[0] for i, e in enumerate(singles)]
    np.testing.assert_array_equal(obs, np.stack(single_obs))
    act = np.array([[1.0, 1.0], [-1.0, 0.5]], np.float32)
    obs, rew, _, _, info = venv.step(act)
    for i, e in enumerate(singles):
        o, r, _, _, _ = e.step(act[i])
        np.testing.assert_array_equal(obs[i], o)
        assert rew[i] == r
    with pytest.raises(ValueError):
        venv.step(np.zeros((2, 1), np.float32))


def test_start_follows_the_trial_protocol():
    """init="auto": hand-held trials (walk starts in a disturbed field) start from truth, others from TRIAD."""
    from magenv import scenarios as hs

    hand = hs.make_trial("handheld_texting", 0, duration=2.0)
    other = _env_trial()
    params = qsf.make_params(hand.field_norm, hand.field_dip)
    np.testing.assert_array_equal(qsf.initial_orientation(hand, "auto", params), hand.q_true[0])
    np.testing.assert_array_equal(
        qsf.initial_orientation(other, "auto", params), qsf.initial_orientation(other, "triad", params)
    )
    assert not np.allclose(qsf.initial_orientation(hand, "triad", params), hand.q_true[0], atol=1e-3)
    est = bq.delay_magyq().run(hand)  # the estimator and the env start alike
    env = MagQSFEnv(scenario=[hand], decision_every=1)
    obs, _ = env.reset(seed=0)
    policy, done = DetectorPolicy(), False
    while not done:
        obs, _, _, done, _ = env.step(policy(obs))
    np.testing.assert_array_equal(env.estimate, est.q)
    with pytest.raises(ValueError, match="init must be one of"):
        qsf.initial_orientation(hand, "oracle", params)
    nan_start = Trial("nan", 100.0, other.gyr, other.acc, other.mag, np.full_like(other.q_true, np.nan), *FIELD)
    with pytest.raises(ValueError, match="finite q_true"):
        qsf.initial_orientation(nan_start, "truth", params)


def test_features_are_scaled_and_report_the_period():
    tr = _static_trial(n=600)
    env = MagQSFEnv(scenario=[tr], decision_every=10)
    obs, _ = env.reset(seed=0)
    f = dict(zip(env.features, obs))
    assert f["active"] == 0 and f["age"] == 0 and f["ref_mismatch"] == 0 and f["trust_prev"] == 0
    for _ in range(30):  # start, then keep for 3 s
        obs, *_ = env.step(np.array([1.0 if _ == 0 else 0.0, 1.0], np.float32))
    f = dict(zip(env.features, obs))
    assert f["active"] == 1 and f["age"] == pytest.approx(0.299, abs=0.011)  # units of 10 s
    assert f["trust_prev"] == 1.0
    assert 0 < f["ref_mismatch"] < 1.0  # static: well within σ_m of the reference
    assert f["spread"] < 1.0 and f["det_keep"] == 1  # steady field: below the detector threshold
    assert abs(f["dip_dev"]) < 0.1 and abs(f["acc_dev"]) < 0.05
    assert env.observation_space.contains(obs)


def test_detector_thresholds_are_tunable():
    from magenv.registry import rule_class

    cls = rule_class("delay_magyq")
    assert cls().params == {"window_s": 0.5, "th_spread": 1.0, "th_drift": 2.0, "max_period_s": 10.0}
    tuned = cls.from_params({"th_spread": 3.0, "window_s": 0.2})
    assert tuned.detector.th_spread == 3.0 and tuned.detector.window_s == 0.2 and tuned.mode == "delay_magyq"
    with pytest.raises(ValueError, match="no parameter"):
        cls.from_params({"gain": 1.0})


def test_detector_option_takes_a_mapping():
    env = MagQSFEnv(scenario=[_env_trial()], detector={"th_spread": 3.0, "window_s": 0.2})
    assert env.detector == qsf.QSFDetector(th_spread=3.0, window_s=0.2)
    with pytest.raises(TypeError, match="detector must be"):
        MagQSFEnv(scenario=[_env_trial()], detector=3.0)
    with pytest.raises(ValueError, match="th_drift must be a finite number > 0"):
        MagQSFEnv(scenario=[_env_trial()], detector={"th_drift": -1.0})


def _detector_episode(trial, thresholds, decision_every):
    """The env after a whole episode of the detector policy with ``thresholds`` on ``trial``."""
    policy = DetectorPolicy(detector=thresholds)
    env = MagQSFEnv(scenario=[trial], decision_every=decision_every, **policy.env_kwargs)
    obs, _ = env.reset(seed=0)
    done = False
    while not done:
        obs, _, _, done, _ = env.step(policy(obs))
    return env


def test_detector_policy_with_thresholds_matches_the_tuned_estimator():
    thresholds = {"window_s": 0.3, "th_spread": 4.0, "th_drift": 12.0, "max_period_s": 20.0}
    tr = _env_trial()
    env = _detector_episode(tr, thresholds, decision_every=1)
    from magenv.registry import rule_class

    np.testing.assert_array_equal(env.estimate, rule_class("delay_magyq").from_params(thresholds).run(tr).q)
    with pytest.raises(ValueError, match="window_s must be a finite number > 0"):
        DetectorPolicy(detector={"window_s": 0.0})


def test_detector_policy_restarts_a_period_at_the_detectors_max_period():
    # A still trial: the detector keeps one period and restarts it every max_period_s at one sample, which a
    # decision every 10 samples mostly misses; the policy restarts on the period's age instead.
    tr = _static_trial(n=3000, disturbance=(0.0, 0.0, 0.0))
    thresholds = {"window_s": 0.3, "th_spread": 4.0, "th_drift": 12.0, "max_period_s": 5.0}
    env = _detector_episode(tr, thresholds, decision_every=10)
    starts = np.flatnonzero(env._runner.inputs.action == qsf.MAG_START)
    assert len(starts) >= 5 and np.all(np.diff(starts) <= 5.0 * tr.rate + 10)  # 30 s: a period per ≤ 5.1 s


def test_last_observation_reports_the_last_step():
    tr = _static_trial(n=95)
    env = MagQSFEnv(scenario=[tr], decision_every=10)
    env.reset(seed=0)
    done, trust = False, 0.0
    while not done:
        trust = 0.9 if trust != 0.9 else 0.3
        obs, _, _, done, _ = env.step(np.array([0.0, trust], np.float32))
    assert dict(zip(env.features, obs))["trust_prev"] == pytest.approx(trust)


# ------------------------------------------------------------ structure


def test_feature_table_is_the_observation_and_the_docs():
    from magenv.envs import qsf as eq

    check_feature_table(MagQSFEnv(scenario=[_env_trial()]), eq.FEATURES)
    policy = DetectorPolicy()  # reads the layout from the env module
    assert policy._i == {f: eq.FEATURES.index(f) for f in ("det_start", "det_keep", "active", "age")}


def test_filters_hold_estimators_only():
    import importlib

    with pytest.raises(ImportError):
        importlib.import_module("magenv.filters.qsf_env")
    for name in ("FEATURES", "QSFRunner", "NX", "NA", "NREF", "NPARAM", "P_SG"):
        assert not hasattr(qsf, name)


def test_named_parameters_state_and_signals():
    p = qsf.make_params(*FIELD, mode="magyq", sigma_mag=2.0, update_reference=False)
    assert isinstance(p, qsf.Params) and p.mode == qsf.MODE_MAGYQ and p.sigma_mag == 2.0
    assert not p.update_reference and p.sigma_acc == pytest.approx(0.1 * quat.GRAVITY)
    np.testing.assert_array_equal(p.earth_field, quat.earth_field(*FIELD))
    state = qsf.initial_state(quat.from_euler_zyx(0.3, 0.0, 0.0), 0.01)
    assert state.x.shape == (qsf.N_AUGMENTED,) and state.cov.shape == (qsf.N_AUGMENTED, qsf.N_AUGMENTED)
    np.testing.assert_allclose(state.x[qsf.ORIENTATION], quat.from_euler_zyx(0.3, 0.0, 0.0), atol=1e-15)
    assert not state.x[qsf.N_STATE :].any() and not state.cov[qsf.CLONE].any()
    assert not state.period_active[0] and state.period_age[0] == 0.0
    assert [getattr(qsf.SIGNAL, s) for s in qsf.SIGNALS] == list(range(qsf.N_SIGNALS))
    tr = _static_trial(n=300)
    act = np.full(tr.n, qsf.MAG_KEEP, np.int8)
    act[0] = qsf.MAG_START
    res = qsf.run_trial(tr, mode="delay_magyq", actions=act)
    p = qsf.make_params(*FIELD)
    state = qsf.initial_state(qsf.initial_orientation(tr, "auto", p), tr.dt)
    inputs, out = qsf.Inputs(tr.gyr, tr.acc, tr.mag, act, np.ones(tr.n)), qsf.Outputs.empty(tr.n)
    qsf.run(p, state, inputs, tr.dt, 0, 120, out)  # in two parts, as the env steps …
    qsf.run(p, state, inputs, tr.dt, 120, tr.n, out)
    np.testing.assert_array_equal(out.q, res.q)  # … equals the whole trial
    np.testing.assert_array_equal(out.sig, res.sig)
    assert state.period_active[0] and state.period_age[0] == pytest.approx((tr.n - 1) * tr.dt)
    np.testing.assert_array_equal(state.mag_t0, tr.mag[0])
    assert state.cov[qsf.CLONE, qsf.CLONE].any()  # Delay MAGYQ: the clone block is live during a period


@pytest.mark.parametrize(
    "spoil", ["none", "inf_diagonal", "nan_diagonal", "inf_off_diagonal", "nan_off_diagonal", "not_pd", "last_row"]
)
def test_health_check_decides_as_repair_sym(spoil):
    """The commit's Cholesky-first health check gives repair_sym's status and matrix, healthy or not."""
    from magenv.filters.kalman_threshold import COV_FLOOR, repair_sym

    rng = np.random.default_rng(3)
    a = rng.normal(size=(15, 30))
    p = a @ a.T * 1e-4
    i, j = 9, 4
    if spoil == "inf_diagonal":
        p[i, i] = np.inf
    elif spoil == "nan_diagonal":
        p[i, i] = np.nan
    elif spoil in ("inf_off_diagonal", "nan_off_diagonal"):
        p[i, j] = p[j, i] = np.inf if spoil.startswith("inf") else np.nan
    elif spoil == "not_pd":
        p[i, j] = p[j, i] = 2.0 * np.sqrt(p[i, i] * p[j, j])
    elif spoil == "last_row":
        p[14, 0] = p[0, 14] = np.inf
    state = qsf.initial_state((1.0, 0.0, 0.0, 0.0), 0.01)
    w = qsf.work()
    w.x[:] = state.x
    w.p[:, :] = p
    want = p.copy()
    status = qsf._commit_healthy(state, w, 15, COV_FLOOR)
    want_status = repair_sym(want, 15, COV_FLOOR, np.empty((15, 15)))
    assert status == want_status
    if status >= 0:
        np.testing.assert_array_equal(state.cov, want)
