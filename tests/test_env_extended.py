"""The extended observations (``features="extended"``) of MagBlend-v0 and MagKalman-v0: causal, with memory, and
leaving the default features and the estimate unchanged."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
from conftest import kinematic_trial

import magenv  # noqa: F401  (registers the envs)
from magenv.envs import BLEND_ID, KALMAN_ID, blend, blend_memory, kalman, kalman_memory

ENVS = {
    "blend": (blend.BlendRunner, blend.FEATURES, blend_memory.EXTRA, blend.EXTENDED, blend.LAGS),
    "kalman": (kalman.KalmanRunner, kalman.FEATURES, kalman_memory.EXTRA, kalman.EXTENDED, kalman.LAGS),
}


@pytest.mark.parametrize(
    "env_id, name, lagged", [(BLEND_ID, "blend", "d_imu_lag8"), (KALMAN_ID, "kalman", "d_anchor_lag8")]
)
def test_env_option_documented_and_default_kept(env_id, name, lagged):
    _, features, extra, extended, _ = ENVS[name]
    env = gym.make(env_id, features="extended").unwrapped
    assert env.observation_space.shape == (len(extended),) and env.features == extended.names
    assert gym.make(env_id).unwrapped.observation_space.shape == (len(features),)
    assert gym.make(env_id, features=["norm_dev", lagged]).unwrapped.observation_space.shape == (2,)
    assert [row for row in extra.markdown().splitlines() if row not in type(env).__doc__] == []
    with pytest.raises(ValueError, match="extended"):
        gym.make(env_id, features="extnded")
    obs, _ = env.reset(seed=0)
    assert np.all(obs >= extended.low) and np.all(obs <= extended.high)


@pytest.fixture(scope="module")
def trial():
    return kinematic_trial(seed=4, duration=5.0, disturbance_ut=30.0, disturbance_window=(1.0, 3.0))


@pytest.fixture(params=sorted(ENVS))
def env(request):
    return ENVS[request.param]


def _observations(runner_class, trial, actions):
    runner = runner_class(trial, extended=True)
    obs = [runner.feat.copy()]
    for action in actions:
        if runner.done:
            break
        runner.advance(8, action)
        obs.append(runner.feat.copy())
    return np.array(obs)


def test_features_are_causal(trial, env):
    """Changing the sensors from sample s on leaves every observation before sample s is read unchanged."""
    runner_class = env[0]
    first = runner_class(trial).pos  # the first sample a step fuses
    actions = np.linspace(0.0, 1.0, trial.n // 8 + 1) % 0.7
    s = 400 + first  # the observation after decision d reads samples ≤ j = first + 8·d (the next sample)
    rng = np.random.default_rng(0)
    later = dataclasses.replace(
        trial,
        gyr=np.concatenate([trial.gyr[:s], trial.gyr[s:] + rng.normal(0, 0.3, trial.gyr[s:].shape)]),
        acc=np.concatenate([trial.acc[:s], trial.acc[s:] + rng.normal(0, 0.5, trial.acc[s:].shape)]),
        mag=np.concatenate([trial.mag[:s], trial.mag[s:] + rng.normal(0, 9.0, trial.mag[s:].shape)]),
    )
    a, b = _observations(runner_class, trial, actions), _observations(runner_class, later, actions)
    last_unchanged = (s - 1 - first) // 8  # its next sample j = first + 8·d ≤ s − 1
    np.testing.assert_array_equal(a[: last_unchanged + 1], b[: last_unchanged + 1])
    assert not np.array_equal(a[last_unchanged + 1], b[last_unchanged + 1])


def test_memory_holds_the_features_lags_decisions_earlier(trial, env):
    runner_class, features, extra, extended, lags = env
    n_current = len(features) + len(extra)
    obs = _observations(runner_class, trial, np.full(80, 0.3))
    assert obs.shape[1] == len(extended) == n_current * (1 + len(lags))
    current = obs[:, :n_current]
    for i, lag in enumerate(lags):
        block = obs[:, n_current * (i + 1) : n_current * (i + 2)]
        np.testing.assert_array_equal(block[lag:], current[:-lag])
        np.testing.assert_array_equal(block[:lag], np.repeat(current[:1], lag, 0))  # before the start: the first
    assert np.any(current[1:, len(features) :] != 0)  # the extra features move once samples are fused


def test_base_features_and_estimate_are_unchanged_by_the_option(trial, env):
    runner_class, features = env[0], env[1]
    plain, ext = runner_class(trial), runner_class(trial, extended=True)
    for action in (0.0, 0.4, 1.0, 0.2) * 10:
        plain.advance(8, action)
        ext.advance(8, action)
        np.testing.assert_array_equal(ext.feat[: len(features)], plain.feat)
    np.testing.assert_array_equal(ext.est, plain.est)
