"""Wrappers applied to environments while an agent trains."""

from __future__ import annotations

import gymnasium as gym
import numpy as np


def normalized_actions(env: gym.Env) -> gym.Env:
    """The env with its Box action space rescaled to [-1, 1].

    PPO's Gaussian policy starts with mean 0 and clips to the bounds, so on
    λ ∈ [0, 1] half of its early actions would be clipped to 0; on [-1, 1]
    it starts in the middle (λ = 0.5). Stable-Baselines3 recommends this
    normalisation for every algorithm. ``AgentPolicy`` maps actions back.
    """
    space = env.action_space
    if not isinstance(space, gym.spaces.Box):
        raise TypeError(f"normalized_actions needs a Box action space, got {space}")
    shape = space.shape
    return gym.wrappers.RescaleAction(
        env, min_action=np.full(shape, -1.0, np.float32), max_action=np.full(shape, 1.0, np.float32)
    )


def action_bounds(env_id: str, env_kwargs: dict) -> list[list[float]]:
    """(low, high) of an env's action space, as lists for run.yaml."""
    env = gym.make(env_id, **env_kwargs)
    space = env.action_space
    env.close()
    if not isinstance(space, gym.spaces.Box):
        raise TypeError(f"{env_id}: needs a Box action space, got {space}")
    return [np.asarray(space.low).tolist(), np.asarray(space.high).tolist()]
