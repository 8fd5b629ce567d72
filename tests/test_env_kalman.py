"""The Kalman-gain env ``magenv/MagKalman-v0``, its kernel and features (``magenv.envs.kalman``)."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest

import magenv  # noqa: F401  (registers the env)
from magenv import metrics
from magenv.envs import kalman as kalman_env
from magenv.envs.kalman import FEATURES, MagKalmanEnv
from magenv.filters import kalman_trust as kt
from magenv.filters.kalman_model import ModelKF
from tests.conftest import (
    check_feature_subset,
    check_feature_table,
    check_kernel_layout,
    check_scalar_action,
    check_step_errors,
    check_step_order,
    check_with_checkers,
    kinematic_trial,
)

ENV_ID = "magenv/MagKalman-v0"
IX = {f: i for i, f in enumerate(FEATURES.names)}


@pytest.fixture(scope="module")
def disturbed():
    """10 s, a 30 µT eastward disturbance from 4 to 7 s."""
    return kinematic_trial(seed=5, duration=10.0, disturbance_ut=30.0, disturbance_window=(4.0, 7.0))


def _run(env, actions, seed=0, options=None):
    """Episode with actions[i] at step i (the last one repeated); returns obs, rewards, infos."""
    obs, _ = env.reset(seed=seed, options=options)
    out_obs, rewards, infos = [obs], [], []
    i, trunc = 0, False
    while not trunc:
        obs, r, term, trunc, info = env.step(np.array([actions[min(i, len(actions) - 1)]], np.float32))
        assert not term
        out_obs.append(obs)
        rewards.append(r)
        infos.append(info)
        i += 1
    return np.array(out_obs), np.array(rewards), infos


# ------------------------------------------------------------------ filter equivalence


def test_env_steps_equal_a_whole_trial_run_with_the_same_trust(disturbed):
    """k-sample steps with a varying γ are the trust KF run over the whole trial with that γ series."""
    env = MagKalmanEnv(scenario=[disturbed], decision_every=7)
    acts = np.random.default_rng(3).uniform(0, 1, 400)
    _run(env, acts)
    n_steps = -(-(disturbed.n - 1) // 7)
    expected = np.concatenate([[1.0], np.repeat(acts[:n_steps].astype(np.float32).astype(float), 7)])[: disturbed.n]
    np.testing.assert_array_equal(env.trust, expected)
    np.testing.assert_array_equal(env.lambdas, 1.0 - expected)
    q, sig = kt.run_trial(disturbed, env.trust)
    np.testing.assert_array_equal(env.estimate, q)
    np.testing.assert_array_equal(env.signals[1:], sig[1:])
    assert not np.isnan(env.estimate).any()


def test_zero_trust_ignores_the_disturbance(disturbed):
    """γ = 0: the estimate on the disturbed trial is bit for bit the one on the clean twin; γ = 1 is pulled off."""
    clean = dataclasses.replace(disturbed, mag=disturbed.mag - disturbed.truth["mag_disturbance"], name="clean")
    runs = {}
    for name, trial in (("dist", disturbed), ("clean", clean)):
        for g in (0.0, 1.0):
            env = MagKalmanEnv(scenario=[trial], decision_every=8)
            _run(env, [g])
            runs[name, g] = env.estimate.copy()
    np.testing.assert_array_equal(runs["dist", 0.0], runs["clean", 0.0])
    inside = (disturbed.t > 5.0) & (disturbed.t < 7.0)
    s1 = metrics.score(runs["dist", 1.0][inside], disturbed.q_true[inside])
    s0 = metrics.score(runs["dist", 0.0][inside], disturbed.q_true[inside])
    assert s1.heading > 10.0 and s0.total < 1.0
    assert not np.array_equal(runs["dist", 1.0], runs["clean", 1.0])


# ------------------------------------------------------------------ observation


def test_observation_is_the_a_priori_view_of_the_next_sample(disturbed):
    """Features of sample j equal the trust-independent signals the filter computes when it fuses j."""
    k = 8
    env = MagKalmanEnv(scenario=[disturbed], decision_every=k)
    obs, _ = env.reset(seed=0)
    m0, dip0 = disturbed.field_norm, disturbed.field_dip
    model = np.linalg.norm(ModelKF().run(disturbed).disturbance, axis=1)
    seen_disturbed = False
    for step in range(160):
        assert env.observation_space.contains(obs)
        j = 1 + k * step
        g = 0.0 if step % 2 else 1.0
        prev_obs = obs
        obs, *_ = env.step(np.array([g], np.float32))
        s = env.signals[j]  # written now that j is fused
        assert prev_obs[IX["field_ref"]] == pytest.approx(m0 / 50.0)
        assert prev_obs[IX["norm_dev"]] == pytest.approx((np.linalg.norm(disturbed.mag[j]) - m0) / m0, abs=1e-6)
        assert prev_obs[IX["norm_dev"]] == pytest.approx(s[8] / m0, abs=1e-6)
        assert 90.0 * prev_obs[IX["dip_dev"]] == pytest.approx(s[9], abs=1e-4)
        assert prev_obs[IX["innov_norm"]] == pytest.approx(s[3] / m0, abs=1e-6)
        assert prev_obs[IX["innov_east"]] == pytest.approx(s[0] / (m0 * np.cos(np.deg2rad(dip0))), abs=1e-5)
        assert prev_obs[IX["log_nis"]] == pytest.approx(np.log10(1.0 + s[4]), abs=1e-5)
        assert prev_obs[IX["acc_dev"]] == pytest.approx(s[10] / 9.81, rel=1e-3, abs=1e-6)
        assert prev_obs[IX["gyro_norm"]] == pytest.approx(np.linalg.norm(disturbed.gyr[j]) / (2 * np.pi), abs=1e-6)
        assert prev_obs[IX["model_dist"]] == pytest.approx(model[j] / m0, abs=1e-6)
        if g == 0.0:  # with γ = 0 the a-posteriori heading std is the a-priori one
            assert prev_obs[IX["heading_std"]] == pytest.approx(np.log10(np.rad2deg(s[7])), abs=1e-5)
        assert obs[IX["trust_prev"]] == g
        win = slice(j, j + k + 1)  # fused samples j … j+k−1 plus the next one
        assert obs[IX["norm_dev_max"]] == pytest.approx(
            np.abs(np.linalg.norm(disturbed.mag[win], axis=1) - m0).max() / m0, abs=1e-6
        )
        seen_disturbed |= bool(prev_obs[IX["norm_dev"]] > 0.1 and prev_obs[IX["model_dist"]] > 0.1)
    assert seen_disturbed  # 160 steps of 8 reach past the onset at 4 s (sample 1024)


def test_feature_subset_and_order(short_trials):
    check_feature_subset(MagKalmanEnv, short_trials, FEATURES, ["log_nis", "norm_dev"], seed=4)


# ------------------------------------------------------------------ reward and info


def test_reward_and_info_match_the_metrics_module(disturbed):
    env = MagKalmanEnv(scenario=[disturbed], decision_every=16)
    steps = check_step_errors(env, disturbed, 0.5, first=1, every=16)  # sample 0 initialises the filter
    assert all(info["trust"] == 0.5 and info["sample"] == sl.stop for sl, info in steps)


# ------------------------------------------------------------------ env API


def test_gymnasium_and_sb3_checkers(short_trials):
    check_with_checkers(ENV_ID, MagKalmanEnv, scenario=short_trials)


def test_same_seed_same_episode(short_trials):
    acts = np.random.default_rng(0).uniform(0, 1, 40)
    a = _run(MagKalmanEnv(scenario=short_trials), acts, seed=123)
    b = _run(MagKalmanEnv(scenario=short_trials), acts, seed=123)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    env = MagKalmanEnv(scenario=short_trials)
    assert len({env.reset(seed=s)[1]["trial"] for s in range(8)}) == 2  # seeds do choose between trials


def test_same_seed_same_episode_on_a_simulated_scenario():
    pytest.importorskip("magenv.scenarios")
    kw = dict(scenario="dynamic_magnet", episode_seconds=1.0)
    acts = np.linspace(0, 1, 40)
    a = _run(gym.make(ENV_ID, **kw), acts, seed=7)
    b = _run(gym.make(ENV_ID, **kw), acts, seed=7)
    c = _run(gym.make(ENV_ID, **kw), acts, seed=8)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])


def test_episode_length_and_decision_every(short_trials):
    env = MagKalmanEnv(scenario=short_trials, decision_every=1)
    _, rewards, infos = _run(env, [1.0])
    assert len(rewards) == short_trials[0].n - 1 and infos[-1]["sample"] == short_trials[0].n
    env = MagKalmanEnv(scenario=short_trials, decision_every=10, episode_seconds=1.0)
    _, rewards, _ = _run(env, [1.0])
    assert env.trial.n == 256 and len(rewards) == 26  # ⌈255 / 10⌉


def test_step_before_reset_and_after_end(short_trials):
    env = MagKalmanEnv(scenario=short_trials)
    with pytest.raises(RuntimeError, match="reset"):
        env.estimate
    check_step_order(env)


def test_bad_actions_and_arguments(short_trials):
    env = MagKalmanEnv(scenario=short_trials)
    env.reset(seed=0)
    check_scalar_action(env, "trust")
    np.testing.assert_array_equal(env.trust[:25], np.r_[1.0, [1.0] * 8, [0.0] * 8, [0.25] * 8])
    with pytest.raises(ValueError, match="render_mode"):
        MagKalmanEnv(scenario=short_trials, render_mode="rgb")
    with pytest.raises(ValueError, match="decision_every"):
        MagKalmanEnv(scenario=short_trials, decision_every=0)
    with pytest.raises(ValueError, match="sigma_mag"):
        MagKalmanEnv(scenario=short_trials, sigma_mag=0.0)
    with pytest.raises(ValueError, match="unknown scenario"):
        MagKalmanEnv(scenario="no_such_scenario")
    with pytest.raises(TypeError, match="Trial"):
        env.reset(options={"trial": "not a trial"})


def test_reset_with_a_given_trial(short_trials, disturbed):
    env = MagKalmanEnv(scenario=short_trials)
    _, info = env.reset(seed=0, options={"trial": disturbed})
    assert info["trial"] == disturbed.name and env.trust.shape == (disturbed.n,)


def test_vector_env_replays_the_single_envs(short_trials):
    vec = gym.make_vec(ENV_ID, num_envs=2, vectorization_mode="vector_entry_point", scenario=short_trials)
    obs, _ = vec.reset(seed=10)
    singles = [MagKalmanEnv(scenario=short_trials) for _ in range(2)]
    np.testing.assert_array_equal(obs, np.stack([e.reset(seed=10 + i)[0] for i, e in enumerate(singles)]))
    for _ in range(5):
        obs, rew, *_ = vec.step(np.full((2, 1), 0.3, np.float32))
        expect = [e.step(np.array([0.3], np.float32)) for e in singles]
        np.testing.assert_array_equal(obs, np.stack([x[0] for x in expect]))
        np.testing.assert_array_equal(rew, [x[1] for x in expect])


def test_sb3_make_vec_env_falls_back_from_render_mode(short_trials):
    from stable_baselines3.common.env_util import make_vec_env

    venv = make_vec_env(ENV_ID, n_envs=2, seed=0, env_kwargs={"scenario": short_trials})
    obs = venv.reset()
    assert obs.shape == (2, len(FEATURES.names))
    obs, rewards, dones, infos = venv.step(np.full((2, 1), 0.5, np.float32))
    assert rewards.shape == (2,) and np.all(rewards <= 0)


def test_feature_table_is_the_space_the_docstring_and_the_kernel_layout(short_trials):
    env = MagKalmanEnv(scenario=short_trials)
    check_feature_table(env, FEATURES)
    check_kernel_layout(env, FEATURES, kalman_env.F)
    assert kt.SIG._fields == kt.SIGNALS and len(kt.SIGNALS) == kt.NSIG
