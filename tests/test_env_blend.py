"""The blend kernel and ``magenv/MagBlend-v0``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import magenv  # noqa: F401  (registers the env)
from magenv import metrics
from magenv import quaternion as quat
from magenv.envs import blend as blend_env
from magenv.envs.blend import FEATURES, BlendRunner, MagBlendEnv
from magenv.filters import madgwick as mg
from magenv.filters.blend import BlendEstimator
from tests.conftest import (
    check_feature_subset,
    check_feature_table,
    check_kernel_layout,
    check_scalar_action,
    check_seeded_replay,
    check_step_errors,
    check_step_order,
    check_with_checkers,
    kinematic_trial,
    run_episode,
)

ENV_ID = "magenv/MagBlend-v0"


@pytest.fixture(scope="module")
def disturbed():
    """12 s, a 30 µT eastward disturbance from 4 to 8 s."""
    return kinematic_trial(seed=5, duration=12.0, disturbance_ut=30.0, disturbance_window=(4.0, 8.0))


# ------------------------------------------------------------------ kernel


@pytest.mark.parametrize("lam,use_mag", [(0.0, True), (1.0, False)])
def test_blend_endpoints_are_the_plain_filters(disturbed, lam, use_mag):
    """λ = 0 is exactly the MIMU filter, λ = 1 exactly the IMU filter (hold off)."""
    runner = BlendRunner(disturbed, hold=False)
    est = runner.run_all(lam)
    plain = mg.run_madgwick(
        disturbed.gyr, disturbed.acc, disturbed.mag if use_mag else None, disturbed.rate, q0=runner.q0
    )
    np.testing.assert_allclose(est, plain, atol=1e-12)


def test_imu_ignores_disturbance_mimu_is_pulled_in_heading(disturbed):
    window = (disturbed.t > 5.0) & (disturbed.t < 8.0)
    before = disturbed.t < 4.0
    imu = BlendRunner(disturbed, hold=False).run_all(1.0)
    mimu = BlendRunner(disturbed, hold=False).run_all(0.0)
    s_imu = metrics.score(imu[window], disturbed.q_true[window])
    s_mimu = metrics.score(mimu[window], disturbed.q_true[window])
    assert metrics.score(mimu[before], disturbed.q_true[before]).total < 1.0  # fine before
    assert s_imu.total < 1.0
    assert s_mimu.heading > 10.0
    assert s_mimu.heading > s_mimu.inclination


def test_stationary_hold_keeps_the_estimate():
    still = kinematic_trial(
        seed=1, duration=6.0, max_rate_dps=0.0, noise=False, disturbance_ut=40.0, disturbance_window=(2.0, 6.0)
    )
    held = BlendRunner(still, hold=True)
    est = held.run_all(0.0)
    start = int(0.5 * still.rate)  # the detector needs t0 of history
    assert held.out.stationary[start:].all()  # every later sample is stationary
    np.testing.assert_array_equal(est[start:], np.broadcast_to(est[start], est[start:].shape))
    free = BlendRunner(still, hold=False).run_all(0.0)
    late = still.t > 4.0
    assert metrics.score(free[late], still.q_true[late]).heading > 5.0
    # held at its t0 value: within Madgwick's dither (~β·Δt = 0.02°) of the truth
    assert metrics.score(est[late], still.q_true[late]).total < 0.1


def test_env_steps_equal_one_whole_trial_run(disturbed):
    """The k-sample env path and the whole-trial runner are the same kernel: identical estimates."""
    env = MagBlendEnv(scenario=[disturbed], decision_every=7)
    env.reset(seed=0)
    truncated = False
    while not truncated:
        _, _, _, truncated, _ = env.step(np.array([0.3], np.float32))
    whole = BlendEstimator(float(np.float32(0.3))).run(disturbed).q
    np.testing.assert_array_equal(env.estimate, whole)
    assert np.all(env.lambdas == np.float32(0.3))


@pytest.mark.parametrize("extended", [False, True])
def test_runner_keeps_per_call_rows_of_one_call(disturbed, extended):
    """The dip and candidate angle are kept for one call's samples (not N rows) and widen for a longer call:
    calls of 1 … 300 samples and the rest in one give the estimates of calls of 7."""
    ref = BlendRunner(disturbed, extended=extended)
    while not ref.done:
        ref.advance(7, 0.4)
    runner = BlendRunner(disturbed, extended=extended)
    for k in (1, 6, 64, 65, 300):
        runner.advance(k, 0.4)
    assert len(runner.out.dip) == len(runner.out.cand_angle) == 300 < disturbed.n
    np.testing.assert_array_equal(runner.run_all(0.4), ref.est)
    np.testing.assert_array_equal(runner.lam, ref.lam)


def test_runners_of_same_typed_trials_share_one_compiled_kernel(disturbed, short_trials):
    """``TrialRunner.compiled``: one entry point per argument types, found again without numba's typeof."""
    a, b = BlendRunner(disturbed), BlendRunner(short_trials[0], hold=False)
    assert a._advance is b._advance
    c = BlendRunner(disturbed)
    c.run_all(0.3)
    np.testing.assert_array_equal(c.est, BlendEstimator(0.3).run(disturbed).q)


# ------------------------------------------------------------------ env API


def test_gymnasium_and_sb3_checkers(short_trials):
    check_with_checkers(ENV_ID, MagBlendEnv, scenario=short_trials)


def test_same_seed_same_episode(short_trials):
    acts = np.random.default_rng(0).uniform(0, 1, 40)
    a = run_episode(MagBlendEnv(scenario=short_trials), 123, acts)
    b = run_episode(MagBlendEnv(scenario=short_trials), 123, acts)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    names = set()
    env = MagBlendEnv(scenario=short_trials)
    for seed in range(8):
        names.add(env.reset(seed=seed)[1]["trial"])
    assert len(names) == 2  # seeds do choose between trials


def test_same_seed_same_episode_on_a_simulated_scenario():
    pytest.importorskip("magenv.scenarios")
    kw = dict(scenario="random", episode_seconds=2.0)
    acts = np.linspace(0, 1, 70)
    check_seeded_replay(ENV_ID, kw, 7, acts, 64)  # 2 s at 256 Hz, 8 samples per step


def test_step_before_reset_and_after_end(short_trials):
    check_step_order(MagBlendEnv(scenario=short_trials))


def test_bad_actions(short_trials):
    env = MagBlendEnv(scenario=short_trials)
    env.reset(seed=0)
    check_scalar_action(env, "lambda")
    assert np.all(env.lambdas[:8] == 1.0) and np.all(env.lambdas[8:16] == 0.0)


def test_reward_and_info_match_the_metrics_module(disturbed):
    check_step_errors(MagBlendEnv(scenario=[disturbed], decision_every=16), disturbed, 0.0, first=0, every=16)


def test_observation_features_are_physical(disturbed):
    env = MagBlendEnv(scenario=[disturbed], decision_every=8)
    obs, _ = env.reset(seed=0)
    ix = {f: i for i, f in enumerate(FEATURES.names)}
    for step in range(200):
        assert env.observation_space.contains(obs)
        j = 8 * step  # the next sample to fuse
        m = np.linalg.norm(disturbed.mag[j])
        assert obs[ix["norm_dev"]] == pytest.approx((m - 46.0) / 46.0, abs=1e-6)
        assert obs[ix["gyro_norm"]] == pytest.approx(np.linalg.norm(disturbed.gyr[j]) / (2 * np.pi), abs=1e-6)
        # dip by eq. 18 with the current estimate
        q = env.estimate[j - 1] if j > 0 else mg.ecompass1(disturbed.acc[0], disturbed.mag[0])
        h = quat.rotate(q, disturbed.mag[j])
        dip = np.rad2deg(np.arcsin(-h[2] / np.linalg.norm(h)))
        assert 90.0 * obs[ix["dip_dev"]] == pytest.approx(dip - 49.6, abs=1e-3)
        obs, *_ = env.step(np.array([1.0], np.float32))
    # undisturbed and converged: small deviations; inside the disturbance: large
    assert abs(90.0 * obs[ix["dip_dev"]]) > 5.0 or obs[ix["norm_dev_max"]] > 0.1  # sample 1600 = 6.25 s, disturbed


def test_feature_subset_and_errors(short_trials):
    check_feature_subset(MagBlendEnv, short_trials, FEATURES, ["dip_dev", "norm_dev"], seed=3)
    with pytest.raises(ValueError, match="decision_every"):
        MagBlendEnv(scenario=short_trials, decision_every=0)
    with pytest.raises(ValueError, match="known scenarios"):
        MagBlendEnv(scenario="no_such_scenario")


def test_episode_seconds_and_trial_option(short_trials, disturbed):
    env = MagBlendEnv(scenario=short_trials, episode_seconds=1.0, decision_every=10)
    env.reset(seed=0)
    steps, trunc = 0, False
    while not trunc:
        _, _, _, trunc, _ = env.step(np.array([0.5], np.float32))
        steps += 1
    assert steps == 26 and env.trial.n == 256  # 256 samples: 25 steps of 10 + one of 6
    _, info = env.reset(options={"trial": disturbed})
    assert info["trial"] == disturbed.name and env.trial.n == 256  # episode_seconds still applies


def test_stationary_hold_option_reaches_the_filter():
    still = kinematic_trial(
        seed=1, duration=3.0, max_rate_dps=0.0, noise=False, disturbance_ut=40.0, disturbance_window=(1.0, 3.0)
    )
    held, free = (MagBlendEnv(scenario=[still], stationary_hold=h) for h in (True, False))
    for env in (held, free):
        env.reset(seed=0)
        trunc = False
        while not trunc:
            *_, trunc, _ = env.step(np.array([0.0], np.float32))
    assert held.stationary[200:].all()
    err = lambda e: metrics.score(e.estimate[-100:], still.q_true[-100:]).heading
    assert err(held) < 0.1 < 1.0 < err(free)


def test_recording_source(broad_dir):
    path = broad_dir / "29_disturbed_stationary_magnet_B.hdf5"
    env = gym.make(ENV_ID, scenario=f"recording:{path}", episode_seconds=2.0)
    obs, info = env.reset(seed=0)
    assert info["trial"].startswith("29_") and env.observation_space.contains(obs)
    _, reward, _, _, _ = env.step(np.array([0.5], np.float32))
    assert np.isfinite(reward)


def test_vector_env_replays_single_envs(short_trials):
    vec = gym.make_vec(
        ENV_ID,
        num_envs=3,
        vectorization_mode="vector_entry_point",
        scenario=short_trials,
        episode_seconds=0.5,
        decision_every=16,
    )
    assert vec.observation_space.shape == (3, len(FEATURES.names))
    acts = np.random.default_rng(1).uniform(0, 1, (12, 3, 1)).astype(np.float32)
    obs, _ = vec.reset(seed=10)
    vobs, vrew, vtrunc = [obs], [], []
    for a in acts:
        obs, r, _, trunc, _ = vec.step(a)
        vobs.append(obs)
        vrew.append(r)
        vtrunc.append(trunc)
    vobs, vrew, vtrunc = np.array(vobs), np.array(vrew), np.array(vtrunc)
    assert vtrunc[7].all()  # 128 samples = 8 steps of 16; step 9 is the autoreset
    for i in range(3):
        single = MagBlendEnv(scenario=short_trials, episode_seconds=0.5, decision_every=16)
        o, _ = single.reset(seed=10 + i)
        np.testing.assert_array_equal(vobs[0, i], o)
        for t in range(8):
            o, r, _, _, _ = single.step(acts[t, i])
            np.testing.assert_array_equal(vobs[t + 1, i], o)
            assert vrew[t, i] == r
        o, _ = single.reset()  # the autoreset draws the next trial from the same generator
        np.testing.assert_array_equal(vobs[9, i], o)
        assert vrew[8, i] == 0.0


def test_sb3_make_vec_env_builds_rgb_array_envs():
    from stable_baselines3.common.env_util import make_vec_env

    venv = make_vec_env(ENV_ID, n_envs=2, seed=0, env_kwargs={"episode_seconds": 2.0})
    obs = venv.reset()
    assert obs.shape == (2, venv.observation_space.shape[0])
    assert venv.get_attr("render_mode") == ["rgb_array"] * 2  # make_vec_env's default; nothing drawn unless asked
    venv.close()


def test_scenario_mixture_draws_only_training_seeds():
    from magenv.seeding import HELD_OUT_BELOW

    env = gym.make(ENV_ID, scenario="dynamic_clean, dynamic_magnet", episode_seconds=0.5).unwrapped
    seen = set()
    for s in range(12):
        env.reset(seed=s)
        assert env.trial.meta["seed"] >= HELD_OUT_BELOW
        seen.add(env.trial.meta["scenario"])
    assert seen == {"dynamic_clean", "dynamic_magnet"}
    with pytest.raises(ValueError, match="unknown scenario.*'nope'.*known scenarios"):
        gym.make(ENV_ID, scenario="dynamic_clean,nope")


def test_prefetch_gives_the_same_episodes_bit_for_bit():
    a = np.array([0.3], np.float32)

    def episodes(env, seeds):
        out = []
        for s in seeds:  # None: the next trial of the sequence; an int: reseed (the prefetch guess misses)
            obs, _ = env.reset(seed=s)
            total = 0.0
            for _ in range(20):
                obs, r, *_ = env.step(a)
                total += r
            out.append((env.unwrapped.trial.name, obs.tobytes(), total))
        return out

    seeds = [3, None, None, 7, None]
    plain = gym.make(ENV_ID, scenario="dynamic_clean,dynamic_magnet")
    ahead = gym.make(ENV_ID, scenario="dynamic_clean,dynamic_magnet", prefetch=True)
    try:
        assert episodes(ahead, seeds) == episodes(plain, seeds)
        assert ahead.unwrapped.trials._pending  # the next trial is being made
    finally:
        ahead.close()
    assert ahead.unwrapped.trials._pool is None


# ------------------------------------------------------------------ one feature table


def test_feature_table_is_the_space_the_docstring_and_the_kernel_layout(short_trials):
    env = MagBlendEnv(scenario=short_trials)
    check_feature_table(env, FEATURES)
    check_kernel_layout(env, FEATURES, blend_env.F)


@pytest.mark.slow
def test_env_kernels_load_from_the_numba_cache(tmp_path):
    """``cache=True`` works with the named-tuple signatures: a second process compiles nothing."""
    code = (
        "from tests.conftest import kinematic_trial\n"
        "from magenv.envs import blend, kalman\n"
        "tr = kinematic_trial(seed=1, duration=1.0)\n"
        "blend.BlendRunner(tr).run_all(0.3)\n"
        "kalman.KalmanRunner(tr).advance(10, 0.5)\n"
        "print(sum(sum(k.stats.cache_misses.values()) for k in (blend.advance, kalman.advance,"
        " kalman.model_disturbance)))\n"
    )
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "PYTHONPATH": str(root)}
    runs = [
        subprocess.run(
            [sys.executable, "-W", "error", "-c", code],
            cwd=root,
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
            check=False,
        )
        for _ in range(2)
    ]
    assert all(r.returncode == 0 for r in runs), runs[-1].stderr[-2000:]
    assert [r.stdout.split()[-1] for r in runs] == ["3", "0"]
