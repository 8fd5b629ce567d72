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
unknown key is an error that names it. Every value is checked against
``VALUE_RULES`` (``POLICY_RULES`` inside ``policy_kwargs``): a value of the
wrong type or out of range is a ConfigError naming the key, what it must be
and the value (booleans only as YAML booleans: ``"no"`` in quotes is text,
not false). Unlike rl-zoo3, nothing is evaluated as Python:
``activation_fn`` is a name (``tanh``, ``relu``, ``elu``), and constructor
arguments that only a Python object can fill (classes, noise objects) are refused.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from magenv.checks import check_yaml
from magenv.seeding import SEED_LIMIT, VALIDATION_START

CONFIG_DIR = Path(__file__).resolve().parent / "configs"
ACTIVATIONS = ("tanh", "relu", "elu", "leaky_relu")
N_ENVS_RANGE = (1, 1024)  # environments of one run (a batched vector env steps them in one kernel call)
SEED_RANGE = (0, SEED_LIMIT)  # training seeds (numpy, torch and the envs take them)
# What a new run gets when magenv train / train() is not told otherwise.
DEFAULT_SEED = 0
DEFAULT_EVAL_EVERY = 10_000
DEFAULT_EVAL_SCENARIOS = ("dynamic_magnet", "dynamic_clean")
DEFAULT_EVAL_SEEDS = (VALIDATION_START, VALIDATION_START + 1)  # validation seeds (magenv.seeding)


class ConfigError(ValueError):
    """A hyperparameter file or section is missing or malformed."""


# ----------------------------------------------------------------- value rules


@dataclass(frozen=True)
class Rule:
    """What a config value must be: ``expected`` (for messages) and ``convert(value)``, which returns the
    value as the algorithm takes it or raises ValueError."""

    expected: str
    convert: Callable[[Any], Any]


def _real(value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError
    return value


def integer(lo: int | None = None, hi: int | None = None, also: tuple = ()) -> Rule:
    """An integer in [lo, hi] (an integral float such as ``1.0e5`` counts), or one of the values ``also``."""
    span = (f" ≥ {lo}" if hi is None else f" from {lo} to {hi}") if lo is not None else ""
    extra = "".join(f" or {a}" for a in also)

    def convert(v):
        if v in also and not isinstance(v, bool):
            return v
        x = _real(v)
        if x != int(x) or (lo is not None and x < lo) or (hi is not None and x > hi):
            raise ValueError
        return int(x)

    return Rule(f"an integer{span}{extra}", convert)


def number(lo: float | None = None, hi: float | None = None, lo_open: bool = False) -> Rule:
    """A finite number in [lo, hi] (or (lo, hi] with ``lo_open``)."""
    if lo is None:
        span = ""
    elif hi is None:
        span = f" {'>' if lo_open else '≥'} {lo}"
    else:
        span = f" in {'(' if lo_open else '['}{lo}, {hi}]"

    def convert(v):
        x = _real(v)
        if (lo is not None and (x < lo or (lo_open and x == lo))) or (hi is not None and x > hi):
            raise ValueError
        return float(x)

    return Rule(f"a number{span}", convert)


def _bool(v):
    if not isinstance(v, bool):
        raise ValueError
    return v


def _mapping(v):
    if not isinstance(v, dict):
        raise ValueError
    return dict(v)


def one_of(*rules: Rule) -> Rule:
    """The first of ``rules`` that accepts the value."""

    def convert(v):
        for r in rules:
            try:
                return r.convert(v)
            except ValueError:
                pass
        raise ValueError

    return Rule(" or ".join(r.expected for r in rules), convert)


def word(*choices: str, prefix: bool = False) -> Rule:
    """One of the strings ``choices`` (with ``prefix``: a string starting with one)."""

    def convert(v):
        if not isinstance(v, str) or not any(v.startswith(c) if prefix else v == c for c in choices):
            raise ValueError
        return v

    return Rule(" or ".join(repr(c) + ("…" if prefix else "") for c in choices), convert)


def _layers(v):
    if not isinstance(v, list) or not v or any(isinstance(x, bool) or not isinstance(x, int) or x < 1 for x in v):
        raise ValueError
    return list(v)


def _net_arch(v):
    if isinstance(v, dict):
        if not v or set(v) - {"pi", "vf", "qf"}:
            raise ValueError
        return {k: _layers(x) for k, x in v.items()}
    return _layers(v)


def _none(v):
    if v is not None:
        raise ValueError
    return v


def _text(v):
    if not isinstance(v, str) or not v:
        raise ValueError
    return v


def _train_freq(v):
    if not (isinstance(v, list) and len(v) == 2):
        raise ValueError
    return [POSITIVE_INT.convert(v[0]), word("step", "episode").convert(v[1])]


BOOL = Rule("true or false", _bool)
MAPPING = Rule("a mapping", _mapping)
NONE = Rule("null", _none)
NAME = Rule("a name", _text)
POSITIVE_INT = integer(1)
#: The most environment steps a run may ask for: 10¹⁰ is months of training at magenv's ~20 k steps/s.
MAX_TIMESTEPS = 10**10
SEED_RULE = integer(*SEED_RANGE)
POSITIVE = number(0, lo_open=True)
UNIT = number(0, 1, lo_open=True)

#: Keys of a config section that are not constructor arguments of the algorithm.
RUN_RULES = {
    "n_timesteps": integer(1, MAX_TIMESTEPS),
    "n_envs": integer(*N_ENVS_RANGE),
    "env_kwargs": MAPPING,
    "normalize_reward": BOOL,
    "pretrain": MAPPING,  # its keys: magenv.agents.imitation.check_pretrain
}
RUN_KEYS = set(RUN_RULES)

#: Constructor arguments of PPO, SAC and RecurrentPPO that a config may set, and what each must be.
VALUE_RULES = {
    "policy": NAME,
    "learning_rate": POSITIVE,
    "n_steps": POSITIVE_INT,
    "batch_size": integer(2),
    "n_epochs": POSITIVE_INT,
    "gamma": UNIT,
    "gae_lambda": number(0, 1),
    "clip_range": POSITIVE,
    "clip_range_vf": one_of(NONE, POSITIVE),
    "normalize_advantage": BOOL,
    "ent_coef": one_of(number(0), word("auto", prefix=True)),
    "vf_coef": number(0),
    "max_grad_norm": POSITIVE,
    "use_sde": BOOL,
    "sde_sample_freq": integer(-1),
    "target_kl": one_of(NONE, POSITIVE),
    "stats_window_size": POSITIVE_INT,
    "verbose": integer(0, 2),
    "buffer_size": POSITIVE_INT,
    "learning_starts": integer(0),
    "tau": UNIT,
    "train_freq": one_of(POSITIVE_INT, Rule("[n, 'step' or 'episode']", _train_freq)),
    "gradient_steps": integer(1, also=(-1,)),
    "optimize_memory_usage": BOOL,
    "target_update_interval": POSITIVE_INT,
    "target_entropy": one_of(word("auto"), number()),
    "use_sde_at_warmup": BOOL,
    "rollout_buffer_kwargs": one_of(NONE, MAPPING),
    "replay_buffer_kwargs": one_of(NONE, MAPPING),
    "policy_kwargs": one_of(NONE, MAPPING),
}
#: Inside ``policy_kwargs`` (each must also be an argument of the policy class).
POLICY_RULES = {
    "net_arch": Rule("a list of layer sizes (positive integers), or a mapping pi/vf/qf → such a list", _net_arch),
    "activation_fn": word(*ACTIVATIONS),
    "ortho_init": BOOL,
    "use_sde": BOOL,
    "log_std_init": number(),
    "full_std": BOOL,
    "use_expln": BOOL,
    "squash_output": BOOL,
    "share_features_extractor": BOOL,
    "normalize_images": BOOL,
    "clip_mean": POSITIVE,
    "n_critics": POSITIVE_INT,
    "lstm_hidden_size": POSITIVE_INT,
    "n_lstm_layers": POSITIVE_INT,
    "shared_lstm": BOOL,
    "enable_critic_lstm": BOOL,
    "optimizer_kwargs": MAPPING,
    "lstm_kwargs": MAPPING,
    "features_extractor_kwargs": MAPPING,
}
#: Constructor arguments a config may not set, and why.
NOT_IN_CONFIG = {
    "seed": "the seed is magenv train --seed (train(seed=…)), not a config key",
    "device": "magenv trains on the CPU",
    "tensorboard_log": "TensorBoard logs go to RUN/tb",
}
for _key in (
    "rollout_buffer_class",
    "replay_buffer_class",
    "action_noise",
    "features_extractor_class",
    "optimizer_class",
):
    NOT_IN_CONFIG[_key] = "it takes a Python object, which a YAML config cannot name"


def _hint(value) -> str:
    """Why a YAML value that looks right is not: quoted booleans, numbers YAML 1.1 reads as text."""
    if isinstance(value, str):
        if value.lower() in ("yes", "no", "on", "off", "true", "false", "y", "n"):
            return " (text, not a boolean: write true or false without quotes)"
        try:
            float(value)
        except ValueError:
            return ""
        return " (text, not a number" + (": YAML reads 3e-4 as text, write 3.0e-4)" if "e" in value.lower() else ")")
    return ""


def check_value(where: str, key: str, value, rule: Rule):
    """``value`` converted by ``rule``; ConfigError naming ``where``, the key, what it must be and the value."""
    try:
        return rule.convert(value)
    except (ValueError, TypeError, IndexError, KeyError):
        raise ConfigError(f"{where}: {key} must be {rule.expected}, got {value!r}{_hint(value)}") from None


# ----------------------------------------------------------------- files and sections


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


def check_section(algo: str, section, where: str) -> dict:
    """A config section checked key by key and value by value (defaults filled in); ConfigError naming
    ``where`` (file and section, or the run folder's run.yaml), the key and the problem."""
    cls = algorithm_class(algo)
    if section is None:
        section = {}
    if not isinstance(section, dict):
        raise ConfigError(f"{where}: a section must be a mapping of keys to values, got {section!r}")
    refused = [f"{k} ({NOT_IN_CONFIG[k]})" for k in section if k in NOT_IN_CONFIG]
    if refused:
        raise ConfigError(f"{where}: key(s) not allowed in a config: {'; '.join(refused)}")
    allowed = (set(inspect.signature(cls.__init__).parameters) & set(VALUE_RULES)) | RUN_KEYS
    unknown = sorted(set(section) - allowed)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(map(str, unknown))} for {algo}")
    out = {key: check_value(where, key, value, {**VALUE_RULES, **RUN_RULES}[key]) for key, value in section.items()}
    out.setdefault("policy", "MlpLstmPolicy" if algo == "recurrent_ppo" else "MlpPolicy")
    out.setdefault("n_envs", 1)
    out.setdefault("env_kwargs", {})
    if out["policy"] not in cls.policy_aliases:
        raise ConfigError(f"{where}: policy must be one of {', '.join(cls.policy_aliases)}, got {out['policy']!r}")
    if out.get("policy_kwargs"):
        policy_args = set(inspect.signature(cls.policy_aliases[out["policy"]].__init__).parameters)
        kwargs = out["policy_kwargs"]
        refused = [f"{k} ({NOT_IN_CONFIG[k]})" for k in kwargs if k in NOT_IN_CONFIG]
        unknown = sorted(set(kwargs) - (policy_args & set(POLICY_RULES)) - set(NOT_IN_CONFIG))
        if refused or unknown:
            raise ConfigError(
                f"{where}: policy_kwargs: unknown key(s) {', '.join(map(str, unknown)) or 'none'}"
                f"{'; not allowed: ' + '; '.join(refused) if refused else ''} for {out['policy']}"
            )
        out["policy_kwargs"] = {
            k: check_value(where, f"policy_kwargs.{k}", v, POLICY_RULES[k]) for k, v in kwargs.items()
        }
    if "n_steps" in out and algo != "sac" and out["n_steps"] * out["n_envs"] < 2:
        raise ConfigError(f"{where}: n_steps × n_envs must be at least 2, got {out['n_steps']} × {out['n_envs']}")
    if "pretrain" in out:
        from magenv.agents.imitation import check_pretrain

        if algo != "ppo":
            raise ConfigError(f"{where}: pretrain works with ppo only, not {algo}")
        try:
            out["pretrain"] = check_pretrain(out["pretrain"])
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
    return out


def read_yaml(path: Path, kind: str = "config file"):
    """The YAML document in ``path`` (``magenv.checks.check_yaml``); ConfigError naming ``path`` if it is missing
    (``no such KIND``), not YAML, or an alias bomb."""
    if not path.is_file():
        raise ConfigError(f"{path}: no such {kind}")
    try:
        return check_yaml(path.read_text(), str(path))
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from None
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def load_hyperparams(algo: str, env_id: str, config_file: str | Path | None = None) -> dict:
    """The validated config section for ``env_id`` from ``config_file`` (default: the shipped file of ``algo``)."""
    algorithm_class(algo)
    path = Path(config_file) if config_file else CONFIG_DIR / f"{algo}.yaml"
    doc = read_yaml(path)
    if not isinstance(doc, dict) or env_id not in doc:
        known = ", ".join(map(str, doc)) if isinstance(doc, dict) else "none"
        raise ConfigError(f"{path}: no section for env {env_id!r} (sections: {known})")
    return check_section(algo, doc[env_id], f"{path} [{env_id}]")


def constructor_kwargs(section: dict) -> dict:
    """The algorithm constructor's arguments of a checked config section (torch objects built from names)."""
    import torch.nn as nn

    kwargs = {k: v for k, v in section.items() if k not in RUN_KEYS}
    policy_kwargs = dict(kwargs.get("policy_kwargs") or {})
    if "activation_fn" in policy_kwargs:
        policy_kwargs["activation_fn"] = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU, "leaky_relu": nn.LeakyReLU}[
            policy_kwargs["activation_fn"]
        ]
    if policy_kwargs:
        kwargs["policy_kwargs"] = policy_kwargs
    if isinstance(kwargs.get("train_freq"), list):
        kwargs["train_freq"] = tuple(kwargs["train_freq"])
    return kwargs
