"""The sweep file of ``magenv sweep``: an rl-zoo3 config (one section per env id) with a ``search:`` section.

::

    magenv/MagBlend-v0:              # base hyperparameters, merged over agents/configs/ALGO.yaml's section
      n_timesteps: 20000
      n_envs: 2
      pretrain: null                 # null: the shipped section's key dropped
    search:
      envs: [magenv/MagBlend-v0]     # default: every env section of this file
      algos: [ppo]                   # default [ppo]
      seeds: "0:10"                  # training seeds: START:STOP, a list, or one
      mode: grid                     # grid: every combination of params; random: `samples` draws
      samples: 8                     # random only: hyperparameter configurations drawn (with `seed`)
      seed: 0                        # random only: the draws' seed
      params:                        # searched keys; a dotted key sets a nested one
        learning_rate: [1.0e-4, 3.0e-4]                   # grid: the values; random: a list is a choice
        policy_kwargs.net_arch: [[64, 64], [128, 128]]
        gamma: {uniform: [0.95, 0.999]}                   # random only: uniform, loguniform, randint, choice
      steps: 20000                   # optional: total steps per run (default: the section's n_timesteps)
      eval_every: 10000              # held-out evaluation and checkpoint cadence of each run
      eval_scenarios: [dynamic_magnet, dynamic_clean]     # validation (model selection), as magenv train;
                                                          # or a mapping env id → scenarios
      eval_seeds: "5000:5002"
      report:                        # the table: every run and the reference on the same held-out trials
        reference: fan_lambda_tuned  # or a mapping env id → method (default DEFAULT_REFERENCE)
        scenarios: [dynamic_magnet, dynamic_clean]        # default: eval_scenarios (a mapping too)
        seeds: "0:5"                 # seeds below 5000 (magenv.seeding)

A *configuration* is one set of searched values; the same configurations
are crossed with every env × algorithm × training seed, so the seeds of a
configuration pair up (``magenv.stats.paired_ratio``). Each run's section
is checked like any config file (``magenv.agents.hyperparams.check_section``)
when the file is read, so a bad value stops the sweep before anything runs;
a key that one algorithm of the search does not take is an error naming it.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from magenv.agents.hyperparams import (
    CONFIG_DIR,
    DEFAULT_EVAL_EVERY,
    DEFAULT_EVAL_SCENARIOS,
    DEFAULT_EVAL_SEEDS,
    POSITIVE_INT,
    SEED_RULE,
    ConfigError,
    algorithm_class,
    check_section,
    check_value,
    read_yaml,
)
from magenv.envs import BLEND_ID, CONSTRAINT_ID, KALMAN_ID, QSF_ID, VQF_ID
from magenv.seeding import HELD_OUT_BELOW, VALIDATION_START
from magenv.train.seeds import parse_seeds

SEARCH = "search"
DAGGER = "dagger"  # DAgger from a privileged teacher (magenv.agents.dagger): its section holds the teacher too
SEARCH_KEYS = {
    "envs",
    "algos",
    "seeds",
    "mode",
    "samples",
    "seed",
    "params",
    "steps",
    "eval_every",
    "eval_scenarios",
    "eval_seeds",
    "report",
}
REPORT_KEYS = {"reference", "scenarios", "seeds"}
MODES = ("grid", "random")
DISTRIBUTIONS = ("uniform", "loguniform", "randint", "choice")
#: Each env's reference: the tuned rule its learned agents are scored against (sweeps, unless ``report.reference``
#: says otherwise; the studies of docs/results.md, where MagKalman-v0's stationary_magnet has a rule of its own).
DEFAULT_REFERENCE = {
    BLEND_ID: "fan_lambda_tuned",
    KALMAN_ID: "kf_model_tuned",
    CONSTRAINT_ID: "cf_constraint_tuned",
    QSF_ID: "qsf_detector_tuned",
    VQF_ID: "vqf_fan_lambda_tuned",
}
DEFAULT_REPORT_SEEDS = "0:5"


@dataclass(frozen=True)
class SweepRun:
    """One run of a sweep: a ``magenv train`` run (``section`` is its checked config section) and how the
    table scores it (``reference`` on ``report_scenarios`` × ``report_seeds``)."""

    name: str
    env_id: str
    algo: str
    config: int
    params: dict
    seed: int
    section: dict
    steps: int
    eval_every: int
    eval_scenarios: list
    eval_seeds: list
    reference: str
    report_scenarios: list
    report_seeds: list

    def as_dict(self) -> dict:
        return asdict(self)


def _seeds(where: str, key: str, value, below: int | None = None) -> list[int]:
    """A seed list from YAML: ``"START:STOP"``, a comma string, one integer, or a list of integers."""
    try:
        if isinstance(value, str):
            seeds = parse_seeds(value)
        else:
            items = value if isinstance(value, list) else [value]
            seeds = [check_value(where, f"{key} entry", s, SEED_RULE) for s in items]
            if not seeds:
                raise ValueError(f"{key}: needs at least one seed")
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{where}: {key}: {exc}") from None
    if below is not None and max(seeds) >= below:
        raise ConfigError(f"{where}: {key} must be below {below} (held-out seeds for reported figures), got {seeds}")
    return seeds


def _names(where: str, key: str, value, known) -> list[str]:
    items = [value] if isinstance(value, str) else value
    if not isinstance(items, list) or not items or not all(isinstance(x, str) for x in items):
        raise ConfigError(f"{where}: {key} must be a name or a list of names, got {value!r}")
    bad = [x for x in items if x not in known]
    if bad:
        raise ConfigError(f"{where}: {key}: unknown {', '.join(bad)}; known: {', '.join(known)}")
    return list(dict.fromkeys(items))


def _per_env(where: str, key: str, value, envs: list[str], known) -> dict[str, list[str]]:
    """Env id → scenario names: ``value`` a name or list for every env, or a mapping env id → name or list
    (every env of the sweep given)."""
    if not isinstance(value, dict):
        names = _names(where, key, value, known)
        return dict.fromkeys(envs, names)
    missing = [e for e in envs if e not in value]
    if missing:
        raise ConfigError(f"{where}: {key} gives no scenarios for {', '.join(missing)}")
    return {e: _names(where, f"{key}[{e}]", value[e], known) for e in envs}


def _set(section: dict, dotted: str, value) -> dict:
    """``section`` with ``dotted`` (``a.b.c``) set to ``value``, nested mappings copied on the way."""
    head, _, rest = dotted.partition(".")
    out = dict(section)
    if rest:
        inner = out.get(head) or {}
        if not isinstance(inner, dict):
            raise ConfigError(f"search.params: {dotted}: {head} is not a mapping in the base section")
        out[head] = _set(inner, rest, value)
    else:
        out[head] = value
    return out


def _draw(where: str, key: str, spec, rng: np.random.Generator):
    """One random value of ``spec``: ``{uniform: [lo, hi]}``, ``{loguniform: [lo, hi]}`` (lo > 0),
    ``{randint: [lo, hi]}`` (both ends included), ``{choice: [...]}`` or a list (a choice); else ``spec``."""
    if isinstance(spec, list):
        spec = {"choice": spec}
    if not isinstance(spec, dict):
        return spec
    if len(spec) != 1 or next(iter(spec)) not in DISTRIBUTIONS:
        raise ConfigError(f"{where}: search.params.{key} must be one of {', '.join(DISTRIBUTIONS)}, got {spec!r}")
    ((kind, args),) = spec.items()
    if kind == "choice":
        if not isinstance(args, list) or not args:
            raise ConfigError(f"{where}: search.params.{key}: choice needs a non-empty list, got {args!r}")
        return args[int(rng.integers(len(args)))]
    ok = isinstance(args, list) and len(args) == 2 and all(isinstance(a, (int, float)) for a in args)
    if not ok or not args[0] < args[1] or (kind == "loguniform" and args[0] <= 0):
        raise ConfigError(
            f"{where}: search.params.{key}: {kind} needs [lo, hi] with lo < hi{' and lo > 0' * (kind == 'loguniform')}"
            f", got {args!r}"
        )
    lo, hi = args
    if kind == "uniform":
        return float(rng.uniform(lo, hi))
    if kind == "loguniform":
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    return int(rng.integers(math.ceil(lo), math.floor(hi) + 1))


def configurations(where: str, search: dict) -> list[dict]:
    """The searched configurations (dotted key → value): the grid's product in file order, or ``samples``
    draws from ``numpy.random.default_rng(seed)`` (the same file, the same draws)."""
    params = search.get("params") or {}
    if not isinstance(params, dict) or not all(isinstance(k, str) for k in params):
        raise ConfigError(f"{where}: search.params must be a mapping of keys to values, got {params!r}")
    mode = search.get("mode", "grid")
    if mode not in MODES:
        raise ConfigError(f"{where}: search.mode must be {' or '.join(MODES)}, got {mode!r}")
    if mode == "grid":
        if "samples" in search or "seed" in search:
            raise ConfigError(f"{where}: search.samples and search.seed are for mode: random")
        keys = list(params)
        values = []
        for k in keys:
            v = params[k]
            if isinstance(v, dict):
                raise ConfigError(f"{where}: search.params.{k}: a distribution needs mode: random, got {v!r}")
            values.append(v if isinstance(v, list) else [v])
            if not values[-1]:
                raise ConfigError(f"{where}: search.params.{k}: an empty list of values")
        return [dict(zip(keys, combo)) for combo in itertools.product(*values)]
    samples = check_value(where, "search.samples", search.get("samples", 10), POSITIVE_INT)
    rng = np.random.default_rng(check_value(where, "search.seed", search.get("seed", 0), SEED_RULE))
    return [{k: _draw(where, k, spec, rng) for k, spec in params.items()} for _ in range(samples)]


def _base_section(algo: str, env_id: str, sweep_section: dict | None) -> dict:
    """The shipped config's section of ``env_id`` (``agents/configs/ALGO.yaml``; none: empty) with the sweep
    file's section over it (unchecked YAML)."""
    shipped = yaml.safe_load((CONFIG_DIR / f"{algo}.yaml").read_text()) or {}
    merged = {**(shipped.get(env_id) or {}), **(sweep_section or {})}
    return {k: v for k, v in merged.items() if v is not None}  # a key set to null drops the shipped one


def _dagger_section(where: str, section: dict, methods: list[str]) -> dict:
    """A DAgger section (the keys of ``agents/configs/dagger.yaml`` and ``teacher``, the oracle's registry name)
    checked with ``magenv.agents.dagger.check_config``; ConfigError naming ``where``."""
    from magenv.agents import dagger

    section = dict(section)
    teacher = section.pop("teacher", None)
    if teacher not in methods:
        raise ConfigError(f"{where}: a dagger section needs teacher: the oracle's method name, got {teacher!r}")
    try:
        dagger.check_config(section)
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    return {**section, "teacher": teacher}


#: DAgger's training seed s draws its trials from train_seed + s × DAGGER_SEED_STRIDE (each seed its own trials)
DAGGER_SEED_STRIDE = 1_000_000


def dagger_seeded(section: dict, seed: int, scenarios: list[str], val_seeds: list[int]) -> dict:
    """The DAgger section of training seed ``seed``: its fit seed, its own training trials, validated on
    ``scenarios`` × ``val_seeds`` (model selection, as the other algorithms' ``eval_*``)."""
    return {
        **section,
        "seed": seed,
        "train_seed": section.get("train_seed", HELD_OUT_BELOW) + seed * DAGGER_SEED_STRIDE,
        "val_seeds": [min(val_seeds), max(val_seeds) + 1],
        "val_scenarios": list(scenarios),
    }


def _short(env_id: str) -> str:
    return env_id.rsplit("/", 1)[-1]


def load_sweep(path: str | Path, seeds: list[int] | None = None) -> list[SweepRun]:
    """Every run of the sweep file ``path``, checked (ConfigError naming the file, the key and the problem);
    ``seeds`` replaces the file's ``search.seeds``."""
    import gymnasium as gym

    from magenv import registry
    from magenv.scenarios import scenario_names

    path = Path(path)
    doc = read_yaml(path, "sweep file")
    if not isinstance(doc, dict) or not isinstance(doc.get(SEARCH), dict):
        raise ConfigError(f"{path}: a sweep file needs a `{SEARCH}:` section (a mapping; see magenv sweep --help)")
    search = doc[SEARCH]
    where = str(path)
    unknown = sorted(set(search) - SEARCH_KEYS)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) in search: {', '.join(map(str, unknown))}")
    sections = {k: v for k, v in doc.items() if k != SEARCH}
    envs_known = [k for k in gym.registry if k.startswith("magenv/")]
    bad = [k for k in sections if k not in envs_known]
    if bad:
        raise ConfigError(
            f"{where}: unknown env section(s) {', '.join(map(str, bad))}; magenv envs: {', '.join(envs_known)}"
        )
    envs = search.get("envs", list(sections))
    if not envs:
        raise ConfigError(f"{where}: no env to train: give search.envs or an env section")
    envs = _names(where, "search.envs", envs, envs_known)
    algos = _names(where, "search.algos", search.get("algos", ["ppo"]), ["ppo", "sac", "recurrent_ppo", DAGGER])
    for algo in algos:
        if algo != DAGGER:
            algorithm_class(algo)
    seeds = _seeds(where, "search.seeds", search.get("seeds", 0)) if seeds is None else seeds
    steps = search.get("steps")
    steps = None if steps is None else check_value(where, "search.steps", steps, POSITIVE_INT)
    eval_every = check_value(where, "search.eval_every", search.get("eval_every", DEFAULT_EVAL_EVERY), POSITIVE_INT)
    known_scenarios = scenario_names()
    eval_scenarios = _per_env(
        where,
        "search.eval_scenarios",
        search.get("eval_scenarios", list(DEFAULT_EVAL_SCENARIOS)),
        envs,
        known_scenarios,
    )
    eval_seeds = _seeds(where, "search.eval_seeds", search.get("eval_seeds", list(DEFAULT_EVAL_SEEDS)))
    report = search.get("report") or {}
    if not isinstance(report, dict) or set(report) - REPORT_KEYS:
        raise ConfigError(f"{where}: search.report must be a mapping with keys {', '.join(sorted(REPORT_KEYS))}")
    report_scenarios = (
        _per_env(where, "search.report.scenarios", report["scenarios"], envs, known_scenarios)
        if "scenarios" in report
        else eval_scenarios
    )
    report_seeds = _seeds(where, "search.report.seeds", report.get("seeds", DEFAULT_REPORT_SEEDS), VALIDATION_START)
    reference = report.get("reference", DEFAULT_REFERENCE)
    references: dict[str, Any] = {  # checked below: each a known method name
        e: reference.get(e, DEFAULT_REFERENCE.get(e)) if isinstance(reference, dict) else reference for e in envs
    }
    methods = registry.names()
    for env_id, ref in references.items():
        if ref not in methods:
            raise ConfigError(
                f"{where}: search.report.reference for {env_id}: unknown method {ref!r} "
                f"(a tuned rule needs its file from magenv tune); known: {', '.join(methods)}"
            )
    configs = configurations(where, search)
    runs = []
    for env_id, algo in itertools.product(envs, algos):
        base = _base_section(algo, env_id, sections.get(env_id))
        for c, params in enumerate(configs):
            section = base
            for key, value in params.items():
                section = _set(section, key, value)
            label = f"{where} [{env_id}, {algo}, configuration {c}: {params}]"
            if algo == DAGGER:
                checked = _dagger_section(label, section, registry.names())
                run_steps = 0  # DAgger's size is its iterations × trials (its section)
            else:
                checked = check_section(algo, section, label)
                run_steps = steps or int(checked.get("n_timesteps", 100_000))
            for seed in seeds:
                if algo == DAGGER:
                    checked = dagger_seeded(checked, seed, eval_scenarios[env_id], eval_seeds)
                runs.append(
                    SweepRun(
                        f"{_short(env_id)}-{algo}-c{c}-s{seed}",
                        env_id,
                        algo,
                        c,
                        params,
                        seed,
                        checked,
                        run_steps,
                        eval_every,
                        eval_scenarios[env_id],
                        eval_seeds,
                        references[env_id],
                        report_scenarios[env_id],
                        report_seeds,
                    )
                )
    return runs
