"""The extended observations of MagConstraint-v0 and MagQSF-v0 (``features="extended"``): causal, with memory,
the base features unchanged, documented, seeded, not batched."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest

import magenv  # noqa: F401  (registers the envs)
from magenv import scenarios
from magenv.envs import CONSTRAINT_ID, QSF_ID, constraint, constraint_memory, qsf, qsf_memory
from magenv.filters import qsf as fq

SPECS = {
    CONSTRAINT_ID: dict(
        module=constraint,
        memory=constraint_memory,
        env=constraint.MagConstraintEnv,
        trial=lambda: scenarios.make_trial("constraint_test2", 0, duration=6.0, disturbances=((2.0, 2.0),)),
        runner=lambda trial, ext: constraint.ConstraintRunner(trial, ext),
        actions=[(w, None) for w in (0.0, 0.4, 1.0, 0.7)],
        k=4,
    ),
    QSF_ID: dict(
        module=qsf,
        memory=qsf_memory,
        env=qsf.MagQSFEnv,
        trial=lambda: scenarios.make_trial("handheld_corridor", 0, duration=8.0),
        runner=lambda trial, ext: qsf.QSFRunner(trial, extended=ext),
        actions=[(fq.MAG_START, 1.0), (fq.MAG_KEEP, 0.5), (fq.MAG_KEEP, 1.0), (fq.MAG_NONE, 0.0)],
        k=10,
    ),
}
IDS = list(SPECS)


@pytest.fixture(scope="module")
def trials():
    return {env_id: spec["trial"]() for env_id, spec in SPECS.items()}


def _observations(spec, trial, steps=None):
    runner = spec["runner"](trial, True)
    obs, i = [runner.feat.copy()], 0
    while not runner.done and (steps is None or i < steps):
        runner.advance(spec["k"], spec["actions"][i % len(spec["actions"])])
        obs.append(runner.feat.copy())
        i += 1
    return np.array(obs)


@pytest.mark.parametrize("env_id", IDS)
def test_features_are_causal_and_truth_free(env_id, trials):
    """Changing the sensors from sample s on leaves every observation before sample s is read unchanged;
    changing the truth changes nothing."""
    spec, trial = SPECS[env_id], trials[env_id]
    s, k = 301, spec["k"]
    rng = np.random.default_rng(0)
    later = dataclasses.replace(
        trial, mag=np.concatenate([trial.mag[:s], trial.mag[s:] + rng.normal(0, 9.0, (trial.n - s, 3))])
    )
    a, b = _observations(spec, trial), _observations(spec, later)
    last_unchanged = (s - 1) // k  # its next sample j = k·d ≤ s − 1
    np.testing.assert_array_equal(a[: last_unchanged + 1], b[: last_unchanged + 1])
    assert not np.array_equal(a[last_unchanged + 1], b[last_unchanged + 1])
    q_true = trial.q_true[::-1].copy()
    other = dataclasses.replace(trial, truth={**trial.truth, "q_true": q_true})
    np.testing.assert_array_equal(_observations(spec, other, 60), a[:61])


@pytest.mark.parametrize("env_id", IDS)
def test_memory_holds_the_features_lags_decisions_earlier(env_id, trials):
    spec = SPECS[env_id]
    mod, mem = spec["module"], spec["memory"]
    n_current = len(mod.FEATURES) + len(mem.EXTRA)
    obs = _observations(spec, trials[env_id])
    assert obs.shape[1] == len(mod.EXTENDED) == n_current * (1 + len(mem.LAGS))
    current = obs[:, :n_current]
    for i, lag in enumerate(mem.LAGS):
        block = obs[:, n_current * (i + 1) : n_current * (i + 2)]
        np.testing.assert_array_equal(block[lag:], current[:-lag])
        np.testing.assert_array_equal(block[:lag], np.repeat(current[:1], lag, 0))  # before the start: the first
    assert np.all(np.any(current[1:, len(mod.FEATURES) :] != 0, axis=0))  # every extra feature moves


@pytest.mark.parametrize("env_id", IDS)
def test_base_features_and_estimate_are_unchanged_by_the_option(env_id, trials):
    spec, trial = SPECS[env_id], trials[env_id]
    plain, ext = spec["runner"](trial, False), spec["runner"](trial, True)
    n_base = len(spec["module"].FEATURES)
    for action in spec["actions"] * 10:
        plain.advance(spec["k"], action)
        ext.advance(spec["k"], action)
        np.testing.assert_array_equal(ext.feat[:n_base], plain.feat)
    np.testing.assert_array_equal(ext.est, plain.est)


@pytest.mark.parametrize("env_id", IDS)
def test_env_option_documented_default_kept_and_not_batched(env_id, trials):
    spec = SPECS[env_id]
    mod, mem = spec["module"], spec["memory"]
    env = gym.make(env_id, scenario=[trials[env_id]], features="extended").unwrapped
    assert env.observation_space.shape == (len(mod.EXTENDED),) and env.features == mod.EXTENDED.names
    assert gym.make(env_id, scenario=[trials[env_id]]).unwrapped.observation_space.shape == (len(mod.FEATURES),)
    picked = gym.make(env_id, scenario=[trials[env_id]], features=["gyro_norm", "d_anchor_lag" + str(mem.LAGS[0])])
    assert picked.unwrapped.observation_space.shape == (2,)
    for row in mem.EXTRA.markdown().splitlines():
        assert row in spec["env"].__doc__
    with pytest.raises(ValueError, match="extended"):
        gym.make(env_id, features="extnded")
    obs, _ = env.reset(seed=0)
    assert np.all(obs >= mod.EXTENDED.low) and np.all(obs <= mod.EXTENDED.high)
    with pytest.raises(ValueError, match="not batched"):
        gym.make_vec(env_id, 2, scenario=[trials[env_id]], features="extended")


@pytest.mark.parametrize(
    ("env_id", "scenario", "action"),
    [(CONSTRAINT_ID, "constraint_test2", [0.5]), (QSF_ID, "handheld_corridor", [0.0, 1.0])],
)
def test_extended_env_replays_its_seed(env_id, scenario, action):
    kwargs = {"scenario": scenario, "features": "extended", "scenario_kwargs": {"duration": 3.0}}

    def episode(seed):
        env = gym.make(env_id, **kwargs)
        obs = [env.reset(seed=seed)[0]]
        for _ in range(30):
            obs.append(env.step(np.array(action, np.float32))[0])
        return np.array(obs)

    a = episode(3)
    np.testing.assert_array_equal(a, episode(3))
    assert not np.array_equal(a, episode(4))


@pytest.mark.parametrize("control_gain", [False, True])
def test_bias_corrected_twin_follows_the_estimate_a_bias_free_gyro_would_give(control_gain):
    """The paper's gyro bias is learned from the 3 s at rest that start each two-link trial: `d_btwin` is the heading
    the same decisions (random w, and k by eq. 18 or random) would give on a gyro without the bias, `drift` the
    heading rate the bias causes."""
    from magenv.envs.blend_memory import _heading
    from magenv.quaternion import rotate1
    from magenv.scenarios.twolink import PAPER_GYRO_BIAS

    trial = scenarios.make_trial("constraint_test1", 0, duration=20.0)
    bias = np.array(PAPER_GYRO_BIAS)
    unbiased = dataclasses.replace(trial, gyr=trial.gyr - bias)
    ext, plain = constraint.ConstraintRunner(trial, True), constraint.ConstraintRunner(unbiased, False)
    rng = np.random.default_rng(0)
    while not ext.done:
        action = (float(rng.uniform()), float(rng.uniform(0.0, 0.4)) if control_gain else None)
        ext.advance(4, action)
        plain.advance(4, action)
    names = constraint.EXTENDED.names
    q = ext.est[-1]
    expected = _heading(*plain.est[-1], *q)  # degrees: the bias's share of the heading error, after 20 s
    assert abs(expected) > 0.3
    assert abs(ext.feat[names.index("d_btwin")] - expected) < 0.15 * abs(expected)
    drift = np.rad2deg(rotate1(q, bias)[2])
    assert abs(ext.feat[names.index("drift")] - drift) < 0.15 * abs(drift)


def test_constraint_error_estimate_tracks_the_tilt_error_and_steps_are_eq14s():
    """`cerr_*` estimate the earth-frame error of link i's estimate from the constraint alone: its east and north
    (tilt) components follow the true error along a roll-out of random w; `step*` are eq. 14's steps as
    earth-frame rotations (exp(ε·r) ⊗ q ≈ q + ε·Δq)."""
    from magenv import metrics
    from magenv import quaternion as quat
    from magenv.filters import constraint as cf

    trial = scenarios.make_trial("constraint_test1", 1, duration=20.0)
    ext = constraint.ConstraintRunner(trial, True)
    rng = np.random.default_rng(1)
    names = constraint.EXTENDED.names
    cols = [names.index(n) for n in ("cerr_e_05", "cerr_n_05", "cerr_e_2", "cerr_n_2")]
    est, at = [], []
    while not ext.done:
        ext.advance(4, (float(rng.uniform()), None))
        if not ext.done:
            est.append(ext.feat[cols].copy())
            at.append(ext.pos - 1)
            if len(at) == 300:  # the steps at one decision, from the env's own state
                q, (seen, ref, con) = ext.est[ext.pos - 1], cf.directions(ext.filter.params, ext.filter.inputs, ext.pos)
                for w, first in ((0.0, "step0_e"), (1.0, "step1_e")):
                    dq, jac = np.zeros(4), np.empty((9, 4))
                    cf.gn_step(q, seen, ref, w, con, jac, dq)
                    r = np.deg2rad(ext.feat[names.index(first) : names.index(first) + 3])
                    eps = 1e-4
                    moved = quat.mul(quat.from_rotvec(eps * r), q)
                    np.testing.assert_allclose(moved, (q + eps * dq) / np.linalg.norm(q + eps * dq), atol=1e-9)
    err = np.rad2deg(quat.to_rotvec(metrics.error_quaternion(ext.est, trial.q_true)))[at]
    assert len(at) > 300
    est, late = np.array(est), np.array(at) >= 300  # after the 3 s at rest
    for c, (k, axis) in enumerate(((0, 0), (1, 1), (2, 0), (3, 1))):
        truth, guess = err[late, axis], est[late, k]
        assert np.corrcoef(truth, guess)[0, 1] > 0.8, names[cols[c]]
        assert np.sqrt(np.mean((truth - guess) ** 2)) < 0.5 * truth.std(), names[cols[c]]
