"""Behaviour cloning: start an agent from a hand-crafted rule before reinforcement learning.

A config section may hold (see ``agents/configs/ppo.yaml``)::

    pretrain: {teacher: constraint_rule, steps: 20000, epochs: 20}

``magenv train`` then, before the first RL update, rolls the teacher (a
Policy of the same env, by its ``magenv compare`` name) through ``steps``
steps of the *training* env (training seeds only), and fits the agent's mean
action to the teacher's by least squares. Only the actor is fitted: its
exploration noise (``log_std``) and the critic keep their initial values, so
RL starts from the rule's behaviour with the config's exploration. PPO only
(its policy exposes the action distribution's mean).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from magenv.agents.hyperparams import NAME, POSITIVE, POSITIVE_INT, ConfigError, check_value
from magenv.protocols import is_policy

RULES = {
    "teacher": NAME,
    "steps": POSITIVE_INT,
    "epochs": POSITIVE_INT,
    "learning_rate": POSITIVE,
    "batch_size": POSITIVE_INT,
}
DEFAULTS = {"epochs": 20, "learning_rate": 1e-3, "batch_size": 256}


def check_pretrain(spec) -> dict:
    """The validated ``pretrain`` mapping of a config section (defaults filled in)."""
    if not isinstance(spec, dict):
        raise ConfigError(f"pretrain must be a mapping with keys {sorted(RULES)}, got {spec!r}")
    unknown = sorted(map(str, set(spec) - set(RULES)))
    if unknown or "teacher" not in spec or "steps" not in spec:
        raise ConfigError(f"pretrain: needs 'teacher' and 'steps'; unknown key(s) {unknown}; known {sorted(RULES)}")
    return {key: check_value("pretrain", key, value, RULES[key]) for key, value in {**DEFAULTS, **spec}.items()}


def check_teacher(teacher, name: str, env_id: str, env_kwargs: dict):
    """``teacher`` (the method the config's ``pretrain.teacher`` names), checked: a Policy acting in ``env_id``
    that can act in the env made with ``env_kwargs`` (the options it needs, e.g. its features, must be among
    them). Returns it; raises ConfigError naming the problem."""
    if not is_policy(teacher) or teacher.env_id != env_id:
        where = getattr(teacher, "env_id", "no env (an estimator)")
        raise ConfigError(f"pretrain.teacher {name!r} must be a policy of {env_id}; it acts in {where}")
    clash = {k: v for k, v in getattr(teacher, "env_kwargs", {}).items() if env_kwargs.get(k) != v}
    if clash:
        raise ConfigError(f"pretrain.teacher {name!r} needs env options {clash}, which the config's env_kwargs lack")
    return teacher


def demonstrations(
    env_id: str, env_kwargs: dict, teacher, steps: int, seed: int, bounds
) -> tuple[np.ndarray, np.ndarray]:
    """(observations (M, F), teacher actions rescaled to [-1, 1] (M, A)) over ``steps`` steps of the env
    (``teacher`` checked by :func:`check_teacher`)."""
    low, high = (np.asarray(b, np.float64) for b in bounds)
    env = gym.make(env_id, disable_env_checker=True, **env_kwargs)
    obs_list: list[np.ndarray] = []
    act_list: list[np.ndarray] = []
    obs, _ = env.reset(seed=seed)
    teacher.reset()
    while len(obs_list) < steps:
        action = np.asarray(teacher(obs), np.float64).reshape(low.shape)
        obs_list.append(obs)
        act_list.append(2.0 * (np.clip(action, low, high) - low) / (high - low) - 1.0)
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            obs, _ = env.reset()
            teacher.reset()
    env.close()
    return np.asarray(obs_list, np.float32), np.asarray(act_list, np.float32)


def clone(
    model, obs: np.ndarray, actions: np.ndarray, epochs: int, learning_rate: float, batch_size: int, seed: int = 0
) -> float:
    """Fit the actor's mean action to ``actions`` (least squares, Adam); returns the final mean squared error."""
    import torch
    from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
    from stable_baselines3.common.policies import ActorCriticPolicy

    policy = model.policy
    if not isinstance(policy, ActorCriticPolicy) or isinstance(policy, RecurrentActorCriticPolicy):
        raise ConfigError(f"pretrain works with PPO's feed-forward policies, not {type(policy).__name__}")
    actor = [p for n, p in policy.named_parameters() if n.startswith(("mlp_extractor.policy_net", "action_net"))]
    opt = torch.optim.Adam(actor, lr=learning_rate)
    gen = torch.Generator().manual_seed(seed)
    x = torch.as_tensor(obs, dtype=torch.float32)
    y = torch.as_tensor(actions, dtype=torch.float32)

    def mean_action(batch):
        return policy.get_distribution(batch).distribution.mean

    policy.set_training_mode(True)
    for _ in range(int(epochs)):
        perm = torch.randperm(len(x), generator=gen)
        for i in range(0, len(perm), int(batch_size)):
            idx = perm[i : i + int(batch_size)]
            loss = ((mean_action(x[idx]) - y[idx]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    policy.set_training_mode(False)
    with torch.no_grad():
        return float(((mean_action(x) - y) ** 2).mean())
