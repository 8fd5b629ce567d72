"""MagBlend-v0's extended observation (``features="extended"``): causal, with memory, documented, seeded."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
from conftest import check_seeded_replay, kinematic_trial

import magenv  # noqa: F401  (registers the envs)
from magenv.envs import BLEND_ID, blend_memory
from magenv.envs.blend import EXTENDED, FEATURES, LAGS, BlendRunner, MagBlendEnv

N_CURRENT = len(FEATURES) + len(blend_memory.EXTRA)


@pytest.fixture(scope="module")
def trial():
    return kinematic_trial(seed=4, duration=5.0, disturbance_ut=30.0, disturbance_window=(1.0, 3.0))


def _observations(trial, lams):
    runner = BlendRunner(trial, extended=True)
    obs = [runner.feat.copy()]
    for lam in lams:
        if runner.done:
            break
        runner.advance(8, lam)
        obs.append(runner.feat.copy())
    return np.array(obs)


def test_features_are_causal(trial):
    """Changing the sensors from sample s on leaves every observation before sample s is read unchanged."""
    lams = np.linspace(0.0, 1.0, trial.n // 8 + 1) % 0.7
    s = 400  # the observation after decision d reads samples < 8·d + 1
    rng = np.random.default_rng(0)
    later = dataclasses.replace(
        trial,
        gyr=np.concatenate([trial.gyr[:s], trial.gyr[s:] + rng.normal(0, 0.3, trial.gyr[s:].shape)]),
        acc=np.concatenate([trial.acc[:s], trial.acc[s:] + rng.normal(0, 0.5, trial.acc[s:].shape)]),
        mag=np.concatenate([trial.mag[:s], trial.mag[s:] + rng.normal(0, 9.0, trial.mag[s:].shape)]),
    )
    a, b = _observations(trial, lams), _observations(later, lams)
    last_unchanged = (s - 1) // 8  # its next sample j = 8·d ≤ s − 1
    np.testing.assert_array_equal(a[: last_unchanged + 1], b[: last_unchanged + 1])
    assert not np.array_equal(a[last_unchanged + 1], b[last_unchanged + 1])


def test_memory_holds_the_features_lags_decisions_earlier(trial):
    obs = _observations(trial, np.full(80, 0.3))
    assert obs.shape[1] == len(EXTENDED) == N_CURRENT * (1 + len(LAGS))
    current = obs[:, :N_CURRENT]
    for i, lag in enumerate(LAGS):
        block = obs[:, N_CURRENT * (i + 1) : N_CURRENT * (i + 2)]
        np.testing.assert_array_equal(block[lag:], current[:-lag])
        np.testing.assert_array_equal(block[:lag], np.repeat(current[:1], lag, 0))  # before the start: the first
    assert np.any(current[1:, len(FEATURES) :] != 0)  # the extra features move once samples are fused


def test_base_features_and_estimate_are_unchanged_by_the_option(trial):
    plain, ext = BlendRunner(trial), BlendRunner(trial, extended=True)
    for lam in (0.0, 0.4, 1.0, 0.2) * 10:
        plain.advance(8, lam)
        ext.advance(8, lam)
        np.testing.assert_array_equal(ext.feat[: len(FEATURES)], plain.feat)
    np.testing.assert_array_equal(ext.est, plain.est)


def test_env_option_documented_and_default_kept():
    env = gym.make(BLEND_ID, features="extended").unwrapped
    assert env.observation_space.shape == (len(EXTENDED),) and env.features == EXTENDED.names
    assert gym.make(BLEND_ID).unwrapped.observation_space.shape == (len(FEATURES),)
    picked = gym.make(BLEND_ID, features=["norm_dev", "d_imu_lag8"]).unwrapped
    assert picked.observation_space.shape == (2,)
    for row in blend_memory.EXTRA.markdown().splitlines():
        assert row in MagBlendEnv.__doc__
    with pytest.raises(ValueError, match="extended"):
        gym.make(BLEND_ID, features="extnded")
    obs, _ = env.reset(seed=0)
    assert np.all(obs >= EXTENDED.low) and np.all(obs <= EXTENDED.high)


def test_extended_env_replays_its_seed():
    check_seeded_replay(
        BLEND_ID, {"scenario": "dynamic_magnet", "features": "extended", "episode_seconds": 3.0}, 10, [0.5] * 96, 96
    )
