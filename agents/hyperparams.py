"""Hyperparameters from plain YAML files, one file per algorithm with one section per env id.

This follows the rl-zoo3 convention (``agents/configs/ppo.yaml``)::

    magenv/MagBlend-v0:
      n_timesteps: 100000   # default for `magenv train --steps`
      n_envs: 4             # parallel environments
      normalize_reward: true  # scale rewards by a running std of the return (VecNormalize)
      env_kwargs: {decision_every: 8}
      pretrain: {teacher: fan_lambda, steps: 20000}  # optional: behaviour cloning first (agents/imitation.py)
      policy: MlpPolicy
      learning_rate: 3.0e-4
      policy_kwargs: {net_arch: [64, 64], activation_fn: tanh}

Every other key must be an argument of the algorithm's constructor; an
unknown key is an error that names it. Unlike rl-zoo3, nothing is evaluated
as Python: ``activation_fn`` is a name (``tanh``, ``relu``, ``elu``).
"""

from __future__ import annotations

import inspect
from pathlib import Path

import yaml

CONFIG_DIR = Path(__file__).resolve().parent / "configs"
# Keys of a config section that are not constructor arguments of the algorithm.
RUN_KEYS = {"n_timesteps", "n_envs", "env_kwargs", "normalize_reward", "pretrain"}
ACTIVATIONS = ("tanh", "relu", "elu", "leaky_relu")


class ConfigError(ValueError):
    """A hyperparameter file or section is missing or malformed."""


def _algorithm_classes() -> dict:
    from sb3_contrib import RecurrentPPO
    from stable_baselines3 import PPO, SAC

    return {"ppo": PPO, "sac": SAC, "recurrent_ppo": RecurrentPPO}


ALGORITHMS = ("ppo", "sac", "recurrent_ppo")


def algorithm_class(algo: str):
    """The SB3 class of an algorithm name (``ppo``, ``sac``, ``recurrent_ppo``)."""
    classes = _algorithm_classes()
    if algo not in classes:
        raise ConfigError(f"unknown algorithm {algo!r}; known: {', '.join(ALGORITHMS)}")
    return classes[algo]


def load_hyperparams(algo: str, env_id: str, config_file: str | Path | None = None) -> dict:
    """The validated config section for ``env_id`` from ``config_file`` (default: the shipped file of ``algo``)."""
    cls = algorithm_class(algo)
    path = Path(config_file) if config_file else CONFIG_DIR / f"{algo}.yaml"
    if not path.is_file():
        raise ConfigError(f"{path}: no such config file")
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(doc, dict) or env_id not in doc:
        known = ", ".join(doc) if isinstance(doc, dict) else "none"
        raise ConfigError(f"{path}: no section for env {env_id!r} (sections: {known})")
    section = dict(doc[env_id] or {})
    allowed = set(inspect.signature(cls.__init__).parameters) - {"self", "env", "_init_setup_model"}
    unknown = sorted(set(section) - allowed - RUN_KEYS)
    if unknown:
        raise ConfigError(f"{path} [{env_id}]: unknown key(s) {', '.join(unknown)} for {algo}")
    section.setdefault("policy", "MlpLstmPolicy" if algo == "recurrent_ppo" else "MlpPolicy")
    section.setdefault("n_envs", 1)
    section.setdefault("env_kwargs", {})
    if not isinstance(section["env_kwargs"], dict):
        raise ConfigError(f"{path} [{env_id}]: env_kwargs must be a mapping")
    if "pretrain" in section:
        from magenv.agents.imitation import check_pretrain

        if algo != "ppo":
            raise ConfigError(f"{path} [{env_id}]: pretrain works with ppo only, not {algo}")
        try:
            section["pretrain"] = check_pretrain(section["pretrain"], env_id)
        except ConfigError as exc:
            raise ConfigError(f"{path} [{env_id}]: {exc}") from None
    return section


def constructor_kwargs(section: dict) -> dict:
    """The algorithm constructor's arguments of a config section (torch objects built from names)."""
    import torch.nn as nn

    kwargs = {k: v for k, v in section.items() if k not in RUN_KEYS}
    policy_kwargs = dict(kwargs.get("policy_kwargs") or {})
    if "activation_fn" in policy_kwargs:
        name = policy_kwargs["activation_fn"]
        if name not in ACTIVATIONS:
            raise ConfigError(f"policy_kwargs.activation_fn {name!r} unknown; known: {', '.join(ACTIVATIONS)}")
        policy_kwargs["activation_fn"] = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU, "leaky_relu": nn.LeakyReLU}[name]
    if policy_kwargs:
        kwargs["policy_kwargs"] = policy_kwargs
    return kwargs
