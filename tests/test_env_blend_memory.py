"""MagBlend-v0's extended observation (``features="extended"``): documented, seeded (causality and memory:
``test_env_extended.py``)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from conftest import check_seeded_replay

import magenv  # noqa: F401  (registers the envs)
from magenv.envs import BLEND_ID, blend_memory
from magenv.envs.blend import EXTENDED, FEATURES, MagBlendEnv


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
