"""The VQF trust env ``magenv/MagVQF-v0`` (``magenv.envs.vqf``), its policies (``magenv.baselines.vqf_rules``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import vqf

import magenv  # noqa: F401  (registers the env)
from magenv import evaluation, metrics, registry
from magenv.baselines.reference import VQFEstimator
from magenv.baselines.rules import FanLambda
from magenv.envs import vqf as vqf_env
from magenv.envs.vqf import FEATURES, MagVQFEnv, tau_of_trust
from magenv.recordings import find_recording, load_recording
from tests.conftest import (
    check_feature_table,
    check_kernel_layout,
    check_scalar_action,
    check_seeded_replay,
    check_with_checkers,
    kinematic_trial,
)
from tests.test_env_kalman import _run  # one episode, the last action repeated: (obs, rewards, infos)

ENV_ID = "magenv/MagVQF-v0"


@pytest.fixture(scope="module")
def disturbed():
    """10 s, a 30 µT eastward disturbance from 4 to 7 s."""
    return kinematic_trial(seed=5, duration=10.0, disturbance_ut=30.0, disturbance_window=(4.0, 7.0))


@pytest.fixture(scope="module")
def recording(broad_dir):
    """BROAD trial 29 (a magnet near the resting and moving sensor), first 60 s."""
    return load_recording(find_recording("29", broad_dir)).slice(0, 17143)


# ------------------------------------------------------------------ the filter is VQF as shipped


def test_vqf_rejection_policy_reproduces_the_vqf_estimator_on_a_recording(recording):
    """u = 1 with VQF's rejection on is the reference ``vqf`` estimator (agreement to 1e-9, in fact exact)."""
    ref = evaluation.run_method("vqf", registry.make("vqf"), recording)
    run = evaluation.run_method("vqf_rejection", registry.make("vqf_rejection"), recording)
    assert np.abs(run.q - ref.q).max() <= 1e-9
    assert run.scored.total == pytest.approx(ref.scored.total, abs=1e-9)
    # its trust history: 0 where VQF's rejection zeroed the gain, as the estimator's
    env = MagVQFEnv(scenario=[recording], rejection="on")
    _run(env, [1.0])
    np.testing.assert_array_equal(env.vqf_gain, ref.trust)
    assert 0.0 < env.vqf_gain.mean() < 1.0  # the magnet is detected part of the time


def test_rejection_off_is_vqf_without_rejection_bit_for_bit(recording):
    off = VQFEstimator(magDistRejectionEnabled=False).run(recording).q
    env = MagVQFEnv(scenario=[recording], rejection="off")
    _, _, infos = _run(env, [1.0])
    np.testing.assert_array_equal(env.estimate, off)
    assert any(i["mag_dist"] for i in infos)  # VQF's detector still runs and is observed
    assert env.mag_dist_detected.any()


def test_trust_maps_to_vqf_gain():
    ts = 1 / 286.0
    k1 = vqf.VQF.gainFromTau(9.0, ts)
    assert tau_of_trust(1.0, 9.0, ts) == 9.0
    assert vqf.VQF.gainFromTau(tau_of_trust(0.0, 9.0, ts), ts) == 0.0
    for u in (1e-6, 0.1, 0.5, 0.9, 0.999):
        assert vqf.VQF.gainFromTau(tau_of_trust(u, 9.0, ts), ts) == pytest.approx(u * k1, rel=1e-12)
    assert vqf.VQF.gainFromTau(tau_of_trust(0.5, 0.0, ts), ts) == pytest.approx(0.5, rel=1e-12)  # τ = 0: k₁ = 1


def test_zero_trust_ignores_the_disturbance(disturbed):
    """u = 0 (after the first window, whose first sample aligns the heading): the estimate on the disturbed trial
    is bit for bit the one on its clean twin; u = 1 is pulled off."""
    clean = dataclasses.replace(disturbed, mag=disturbed.mag - disturbed.truth["mag_disturbance"], name="clean")
    ests = {}
    for trial in (disturbed, clean):
        for u in (0.0, 1.0):
            env = MagVQFEnv(scenario=[trial])
            _run(env, [u])
            ests[trial.name, u] = env.estimate.copy()
    np.testing.assert_array_equal(ests[disturbed.name, 0.0], ests["clean", 0.0])
    err = {
        u: metrics.total_error(metrics.error_quaternion(ests[disturbed.name, u], disturbed.q_true)).max()
        for u in (0.0, 1.0)
    }
    assert err[1.0] > err[0.0] + 1.0


def test_observation_reads_vqf_and_the_next_sample(disturbed):
    env = MagVQFEnv(scenario=[disturbed], decision_every=10, backend="cpp")
    obs, _ = env.reset(seed=0)
    assert obs[FEATURES.index("trust_prev")] == 1.0 and obs[FEATURES.index("ref_known")] == 0.0
    for _ in range(60):
        obs, *_ = env.step(np.array([0.7], np.float32))
    runner = env._runner
    j, f = runner.pos, runner.filter
    _, sigma = f.getBiasEstimate()
    assert obs[FEATURES.index("delta")] == pytest.approx(f.getDelta() / np.pi, abs=1e-6)
    assert obs[FEATURES.index("bias_sigma")] == pytest.approx(np.rad2deg(sigma), rel=1e-5)
    assert obs[FEATURES.index("rest")] == float(f.getRestDetected())
    assert obs[FEATURES.index("trust_prev")] == pytest.approx(0.7)
    m = disturbed.mag[j]
    assert obs[FEATURES.index("norm_dev")] == pytest.approx((np.linalg.norm(m) - 46.0) / 46.0, abs=1e-6)
    if f.getMagRefNorm() > 0:
        assert obs[FEATURES.index("ref_known")] == 1.0


def test_reward_and_info_match_the_metrics_module(disturbed):
    env = MagVQFEnv(scenario=[disturbed], decision_every=16)
    env.reset(seed=0)
    for step in range(40):
        _, reward, _, _, info = env.step(np.array([0.5], np.float32))
        sl = slice(16 * step, 16 * (step + 1))
        q_err = metrics.error_quaternion(env.estimate[sl], disturbed.q_true[sl])
        assert reward == pytest.approx(-np.mean(metrics.total_error(q_err)), abs=1e-9)
        assert info["error_heading"] == pytest.approx(np.mean(metrics.heading_error(q_err)), abs=1e-9)
        dist = np.linalg.norm(disturbed.truth["mag_disturbance"][sl], axis=1).mean()
        assert info["disturbance_norm"] == pytest.approx(dist)
        np.testing.assert_array_equal(info["q_est"], env.estimate[sl.stop - 1])
        assert info["trust"] == 0.5 and info["sample"] == sl.stop


# ------------------------------------------------------------------ env API


def test_gymnasium_and_sb3_checkers(short_trials):
    check_with_checkers(ENV_ID, MagVQFEnv, scenario=short_trials)


def test_same_seed_same_episode_on_a_simulated_scenario():
    kw = dict(scenario="dynamic_magnet", episode_seconds=1.0)
    check_seeded_replay(ENV_ID, kw, 7, np.linspace(0, 1, 40), 32)  # 1 s at 256 Hz, 8 samples per step


def test_bad_actions_and_arguments(short_trials):
    env = MagVQFEnv(scenario=short_trials)
    env.reset(seed=0)
    check_scalar_action(env, "trust")
    np.testing.assert_array_equal(env.trust[:24], np.r_[[1.0] * 8, [0.0] * 8, [0.25] * 8])
    with pytest.raises(ValueError, match="rejection"):
        MagVQFEnv(scenario=short_trials, rejection="maybe")
    with pytest.raises(TypeError, match="rejection"):
        MagVQFEnv(scenario=short_trials, rejection=True)
    with pytest.raises(ValueError, match="tau_mag"):
        MagVQFEnv(scenario=short_trials, tau_mag=-1.0)
    with pytest.raises(ValueError, match="decision_every"):
        MagVQFEnv(scenario=short_trials, decision_every=0)


def test_feature_table_is_the_space_the_docstring_and_the_kernel_layout(short_trials):
    env = MagVQFEnv(scenario=short_trials)
    check_feature_table(env, FEATURES)
    check_kernel_layout(env, FEATURES, vqf_env.F)


def test_sb3_vec_env_adapter_runs(short_trials):
    from stable_baselines3.common.env_util import make_vec_env

    venv = make_vec_env(ENV_ID, n_envs=2, seed=0, env_kwargs={"scenario": short_trials})
    obs = venv.reset()
    assert obs.shape == (2, len(FEATURES))
    _, rewards, _, _ = venv.step(np.full((2, 1), 0.5, np.float32))
    assert rewards.shape == (2,) and np.all(rewards <= 0)


# ------------------------------------------------------------------ recordings as a scenario


def test_a_recording_glob_is_one_family_of_a_mixture(broad_dir):
    env = MagVQFEnv(scenario="dynamic_magnet,recording:3*", episode_seconds=0.5)
    names = {env.reset(seed=s)[1]["trial"] for s in range(12)}
    recs = {n for n in names if not n.startswith("dynamic_magnet")}
    assert recs and recs <= {p.stem for p in broad_dir.glob("3*.hdf5")}
    assert len(recs) < len(names)  # simulated trials drawn too
    again = MagVQFEnv(scenario="dynamic_magnet,recording:3*", episode_seconds=0.5)
    assert [again.reset(seed=s)[1]["trial"] for s in range(4)] == [env.reset(seed=s)[1]["trial"] for s in range(4)]
    with pytest.raises(ValueError, match="matches no file"):
        MagVQFEnv(scenario="dynamic_magnet,recording:zz*")


# ------------------------------------------------------------------ policies


def test_vqf_rules_are_the_blend_rules_as_trust(short_trials):
    env = MagVQFEnv(scenario=short_trials)
    obs, _ = env.reset(seed=0)
    for _ in range(20):
        obs, *_ = env.step(np.array([1.0], np.float32))
    rule = registry.make("vqf_fan_lambda")
    blend_rule = FanLambda()
    ix = [FEATURES.index("norm_dev"), FEATURES.index("dip_dev")]
    blend_obs = np.zeros(13, np.float32)
    blend_obs[[0, 1]] = obs[ix]
    assert rule(obs)[0] == pytest.approx(1.0 - blend_rule(blend_obs)[0])
    assert rule.env_kwargs == {"rejection": "off"} and rule.env_id == ENV_ID
    assert registry.rule_class("vqf_threshold").from_params({"norm_th": 1e9, "dip_th_deg": 1e9})(obs)[0] == 1.0
