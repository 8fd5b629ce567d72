"""Method names → factories, for ``magenv compare`` and ``magenv.evaluation``.

A *method* is anything ``magenv.evaluation`` can run on a Trial: a **Policy**
(acts inside its env, ``baselines.protocol.Policy``) or an **Estimator**
(``run(trial) -> Estimate``). A factory is a zero-argument callable returning
a fresh one.

Where methods come from (``names()`` lists them all):

* built in: ``mimu`` (λ = 0), ``imu`` (λ = 1) — the original filters, no
  stationary hold — and ``fan_lambda`` (the paper's proposed method: λ rule +
  hold), ``threshold`` (``baselines.rules``, published parameters);
* ``RULE_tuned`` for every ``baselines/tuned/RULE.json`` written by
  ``magenv tune`` (its ``params`` given to the rule);
* every module of the ``baselines`` package that defines
  ``methods() -> dict[name, factory]`` (e.g. ``baselines.reference``: ``vqf``,
  ``fusion``) — adding a method there is one line in that dict;
* ``register(name, factory)`` at run time (one line anywhere);
* ``agent:RUN_DIR`` — a trained agent loaded with ``agents.loading.load_agent``.
"""

from __future__ import annotations

import importlib
import json
import pkgutil
from pathlib import Path
from typing import Any, Callable

from baselines import rules

TUNED_DIR = Path(__file__).resolve().parent / "tuned"
AGENT_PREFIX = "agent:"
_SKIP_MODULES = {"protocol", "registry", "rules"}

_REGISTERED: dict[str, tuple[Callable[[], Any], str]] = {}


def register(name: str, factory: Callable[[], Any], description: str = "", overwrite: bool = False) -> None:
    """Add a method. Raises ValueError if the name is taken (unless ``overwrite``)."""
    if not overwrite and name in _REGISTERED:
        raise ValueError(f"method {name!r} is already registered")
    _REGISTERED[name] = (factory, description)


def tunable_rules() -> dict[str, type]:
    """Every method with tunable parameters (``PARAM_BOUNDS``, ``params``, ``from_params``), by name:
    the λ rules, the Kalman-trust rules (policies), the constraint filter and Delay MAGYQ's QSF detector
    (estimators)."""
    from baselines import constraint, kalman_policies, qsf

    return {**rules.RULES, **kalman_policies.RULES, "cf_constraint": constraint.ConstraintCF,
            "delay_magyq": qsf.DetectedDelayMAGYQ}


def rule_class(name: str) -> type[rules.RulePolicy]:
    """The rule class of a tunable rule name (``fan_lambda``, ``threshold``, ``kf_gate``, …)."""
    table = tunable_rules()
    try:
        return table[name]
    except KeyError:
        raise ValueError(f"unknown rule {name!r}; known rules: {', '.join(table)}") from None


def _builtin() -> dict[str, tuple[Callable[[], Any], str]]:
    return {
        "mimu": (lambda: rules.ConstantLambda(0.0, stationary_hold=False), "original MIMU Madgwick filter (λ = 0, no hold)"),
        "imu": (lambda: rules.ConstantLambda(1.0, stationary_hold=False), "original IMU Madgwick filter (λ = 1, no hold)"),
        "fan_lambda": (rules.FanLambda, "Fan et al. 2017 λ rule, eqs. 15–17, published values"),
        "threshold": (rules.Threshold, "all-or-nothing magnetometer gate on norm / dip deviation"),
    }


def tuned_params(rule: str) -> dict[str, float]:
    """The parameters ``magenv tune`` wrote for ``rule`` (``baselines/tuned/RULE.json``)."""
    path = TUNED_DIR / f"{rule}.json"
    try:
        return dict(json.loads(path.read_text())["params"])
    except FileNotFoundError:
        raise ValueError(f"{path}: no tuned parameters for {rule!r}; run magenv tune --rule {rule}") from None
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: corrupt tuned-parameter file ({exc})") from None


def _tuned() -> dict[str, tuple[Callable[[], Any], str]]:
    out = {}
    table = tunable_rules()
    if TUNED_DIR.is_dir():
        for path in sorted(TUNED_DIR.glob("*.json")):
            rule = path.stem
            if rule not in table:
                continue

            def factory(path=path, rule=rule):
                policy = table[rule].from_params(tuned_params(rule))
                policy.name = f"{rule}_tuned"
                return policy

            out[f"{rule}_tuned"] = (factory, f"{rule} with parameters tuned by magenv tune ({path.name})")
    return out


def _plugins() -> dict[str, tuple[Callable[[], Any], str]]:
    import baselines

    out = {}
    for info in pkgutil.iter_modules(baselines.__path__):
        if info.name in _SKIP_MODULES or info.name.startswith("_"):
            continue
        try:
            module = importlib.import_module(f"baselines.{info.name}")
        except Exception as exc:
            raise RuntimeError(f"method module baselines.{info.name} failed to import: {exc}") from exc
        methods = getattr(module, "methods", None)
        if callable(methods):
            for name, factory in methods().items():
                out[name] = (factory, f"from baselines.{info.name}")
    return out


def _all() -> dict[str, tuple[Callable[[], Any], str]]:
    table = _builtin()
    table.update(_plugins())
    table.update(_tuned())
    table.update(_REGISTERED)
    return table


def names() -> list[str]:
    """All known method names (``agent:RUN_DIR`` is accepted besides these)."""
    return list(_all())


def describe() -> dict[str, str]:
    """Method name → one-line description."""
    return {k: v[1] for k, v in _all().items()}


def make(name: str):
    """A fresh Policy or Estimator for a method name. Unknown names raise ValueError listing the known ones."""
    if name.startswith(AGENT_PREFIX):
        from agents.loading import load_agent

        return load_agent(name[len(AGENT_PREFIX):])
    table = _all()
    if name not in table:
        raise ValueError(f"unknown method {name!r}; known methods: {', '.join(table)} "
                         f"(or {AGENT_PREFIX}RUN_DIR for a trained agent)")
    method = table[name][0]()
    if not hasattr(method, "name"):
        try:
            method.name = name
        except AttributeError:
            pass
    return method
