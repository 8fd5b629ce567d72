"""Stable-Baselines3 on the batched vector envs: SB3's ``VecEnv`` interface over ``magenv.envs.batch``.

:func:`make_train_env` is what ``magenv train`` steps: for an env whose
``vector_entry_point`` is a :class:`~magenv.envs.batch.BatchVectorEnv`, a
:class:`BatchVecEnv` around ``gymnasium.make_vec(…, vectorization_mode=
"vector_entry_point")`` — all ``n_envs`` envs advanced by one numba call per
step; otherwise SB3's own ``make_vec_env`` of single envs. Both act in
[-1, 1] (``magenv.agents.wrappers.normalized_actions``), seed env i with
seed + i and give each finished episode the ``info`` SB3 expects from its
``Monitor`` and ``DummyVecEnv`` (``episode`` return / length / time,
``terminal_observation``, ``TimeLimit.truncated``), so PPO's bootstrapping
on truncation and its logs work unchanged.
"""

from __future__ import annotations

import time
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from magenv.envs.batch import BatchVectorEnv


class BatchVecEnv(VecEnv):
    """SB3 ``VecEnv`` over a magenv :class:`~magenv.envs.batch.BatchVectorEnv`, acting in [-1, 1].

    Actions a ∈ [-1, 1] map onto the env's box as ``low + (a + 1)·(high − low)/2``. An episode that ends in a
    step is reset in the same step (SB3's convention; ``BatchVectorEnv.reset_done``): the returned
    observation is the next episode's first, the last one is ``infos[i]["terminal_observation"]``. The
    episodes are those of the vector env with next-step autoreset, i.e. of the single envs seeded seed + i.
    """

    def __init__(self, venv: BatchVectorEnv):
        self.venv = venv
        space = venv.single_action_space
        assert isinstance(space, gym.spaces.Box) and space.shape is not None  # every magenv env acts in a Box
        self._low, self._high = space.low.astype(np.float64), space.high.astype(np.float64)
        box = gym.spaces.Box(-1.0, 1.0, space.shape, dtype=np.float32)
        super().__init__(venv.num_envs, venv.single_observation_space, box)
        self._actions = np.zeros((venv.num_envs, *space.shape), np.float32)
        self._t0 = time.time()

    def reset(self):
        seeds = self._seeds if any(s is not None for s in self._seeds) else None
        obs, self.reset_infos = self.venv.reset(seed=seeds)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self):
        a = np.asarray(self._actions, np.float64).reshape(self.num_envs, -1)
        obs, rewards, terminated, truncated, _ = self.venv.step(self._low + (a + 1.0) * 0.5 * (self._high - self._low))
        dones = terminated | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if dones.any():
            returns, lengths = self.venv.episode_statistics()
            elapsed = round(time.time() - self._t0, 6)
            idx = np.flatnonzero(dones)
            for i in idx:
                infos[i] = {
                    "terminal_observation": obs[i].copy(),
                    "TimeLimit.truncated": bool(truncated[i] and not terminated[i]),
                    "episode": {"r": float(returns[i]), "l": int(lengths[i]), "t": elapsed},
                }
            obs[idx] = self.venv.reset_done()
        return obs, rewards.astype(np.float32), dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return [getattr(self.venv, attr_name)] * len(list(self._get_indices(indices)))

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        raise AttributeError(f"the {self.num_envs} envs of a batched vector env share their attributes")

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        raise AttributeError(f"a batched vector env has no per-env method {method_name!r}")

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False] * len(list(self._get_indices(indices)))


def make_train_env(env_id: str, n_envs: int, seed: int, env_kwargs: dict) -> VecEnv:
    """The training env of ``magenv train``: ``n_envs`` envs of ``env_id`` acting in [-1, 1], env i seeded
    ``seed + i`` — batched (:class:`BatchVecEnv`) where the env has a batched ``vector_entry_point``, else
    SB3's ``make_vec_env`` of single envs."""
    import magenv  # noqa: F401  (registers the envs)

    spec = gym.spec(env_id)
    entry: Any = spec.vector_entry_point
    if isinstance(entry, str):
        from gymnasium.envs.registration import load_env_creator

        entry = load_env_creator(entry)
    if isinstance(entry, type) and issubclass(entry, BatchVectorEnv):
        vector = gym.make_vec(env_id, num_envs=n_envs, vectorization_mode="vector_entry_point", **env_kwargs)
        venv = BatchVecEnv(vector.unwrapped)
    else:
        from stable_baselines3.common.env_util import make_vec_env

        from magenv.agents.wrappers import normalized_actions

        return make_vec_env(env_id, n_envs=n_envs, seed=seed, env_kwargs=env_kwargs, wrapper_class=normalized_actions)
    venv.seed(seed)
    return venv
