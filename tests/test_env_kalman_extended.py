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
