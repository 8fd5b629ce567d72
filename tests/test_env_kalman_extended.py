"""MagKalman-v0's extended observation (``features="extended"``): documented, the default kept (causality and
memory: ``test_env_extended.py``)."""

from __future__ import annotations

import gymnasium as gym
import pytest

import magenv  # noqa: F401  (registers the envs)
from magenv.envs import KALMAN_ID, kalman_memory
from magenv.envs.kalman import EXTENDED, FEATURES, MagKalmanEnv


def test_env_option_documented_and_default_kept():
    env = gym.make(KALMAN_ID, features="extended").unwrapped
    assert env.observation_space.shape == (len(EXTENDED),) and env.features == EXTENDED.names
    assert gym.make(KALMAN_ID).unwrapped.observation_space.shape == (len(FEATURES),)
    picked = gym.make(KALMAN_ID, features=["norm_dev", "d_anchor_lag8"]).unwrapped
    assert picked.observation_space.shape == (2,)
    for row in kalman_memory.EXTRA.markdown().splitlines():
        assert row in MagKalmanEnv.__doc__
    with pytest.raises(ValueError, match="not batched"):
        gym.make_vec(KALMAN_ID, num_envs=2, vectorization_mode="vector_entry_point", features="extended")


def test_the_still_anchor_holds_the_last_clean_orientation_of_a_still_mimu():
    """On the still gimbal of ``stationary_magnet`` with the magnetometer refused (γ = 0, so the estimate drifts
    with the gyro bias), ``d_still`` is the heading the estimate has left the last clean sample's orientation
    by, which tracks the true signed heading error; ``pull_still`` is a full update's heading correction toward
    the anchor."""
    import numpy as np

    from magenv.envs.blend_memory import _heading
    from magenv.scenarios import make_trial

    trial = make_trial("stationary_magnet", 1, duration=40.0)
    env = gym.make(KALMAN_ID, features="extended", scenario=[trial]).unwrapped
    obs, _ = env.reset(seed=0, options={"trial": trial})
    i_d, i_p, i_t, i_e = (EXTENDED.index(n) for n in ("d_still", "pull_still", "t_anchor", "innov_east"))
    done, seen = False, []
    while not done:
        obs, _, _, done, _ = env.step(np.zeros(1, np.float32))
        runner = env._runner
        since = round(obs[i_t] * kalman_memory.T_ANCHOR_SCALE_S / runner.params.dt)  # samples since a clean one
        if obs[i_t] > 0.0 and runner.pos - 1 - since > 0:
            q, anchor = runner.est[runner.pos - 1], runner.est[runner.pos - 1 - since]
            assert obs[i_d] == pytest.approx(_heading(*q, *anchor), abs=1e-4)
            assert obs[i_p] == pytest.approx(-np.sign(obs[i_d]) * np.rad2deg(obs[i_e]), rel=1e-4, abs=1e-4)
            seen.append((obs[i_d], _heading(*q, *trial.q_true[runner.pos - 1])))
    d_still, error = np.array(seen).T
    assert len(seen) > 500 and np.ptp(d_still) > 1.0  # the bias moved the estimate by more than 1°
    assert np.corrcoef(d_still, error)[0, 1] > 0.95
