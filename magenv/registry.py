"""The one place that turns a method name into a method object (``magenv compare``, ``train``, ``tune``, ``report``).

A *method* is anything ``magenv.evaluation`` can run on a Trial: a **Policy**
(acts inside its env, ``magenv.protocols.Policy``) or an **Estimator**
(``run(trial) -> Estimate``). A factory is a zero-argument callable returning
a fresh one. ``names()`` lists them all:

* every ``methods()`` table of the baseline modules in ``METHOD_MODULES``
  (``mimu``, ``imu``, ``fan_lambda``, ``threshold``, the survey Kalman
  filters, the Kalman-trust rules, the constraint and QSF filters, the
  outside references ``vqf`` and ``fusion``, and the MagVQF-v0 policies
  ``vqf_rejection``, ``vqf_no_rejection``, ``vqf_fan_lambda``, ``vqf_threshold``) — adding a method is one line
  in its module's table;
* ``RULE_tuned`` for every tunable rule with a tuned-parameter file
  ``RULE.json`` (written by ``magenv tune``): looked up first in the user's
  data directory (:func:`user_tuned_dir`), then among the files shipped in
  the package (``magenv/baselines/tuned``);
* ``oracle`` — the privileged receding-horizon search of MagBlend-v0
  (``magenv.baselines.oracle``, continuing with ``fan_lambda_tuned``): it
  reads truth, so it is an upper bound (compare's headroom row), never a
  baseline; likewise ``oracle_kalman`` for MagKalman-v0 (``magenv.baselines.oracle_kalman``, continuing with
  ``kf_model_tuned``; its DAgger teachers ``oracle_kalman_rules``, ``oracle_kalman_still``,
  ``oracle_kalman_skip`` and ``oracle_kalman_perp`` also search the tuned rules' γ), ``oracle_constraint``
  (MagConstraint-v0, continuing with ``cf_constraint_tuned``,
  ``magenv.baselines.oracle_constraint``; ``oracle_constraint_rules`` also searches the rule's w),
  ``oracle_qsf`` (MagQSF-v0, continuing with
  ``qsf_detector_tuned``, ``magenv.baselines.oracle_qsf``; ``oracle_qsf_hold`` with ``qsf_hold``) and
  ``oracle_vqf`` for MagVQF-v0 (``magenv.baselines.oracle_vqf``; ``oracle_vqf_rule`` also searches and
  continues with ``vqf_fan_lambda_tuned``'s trust on top of VQF's rejection, the teacher of its student;
  ``oracle_vqf_tail`` adds a terminal cost for the error the look-ahead leaves);
* ``register(name, factory)`` at run time (one line anywhere);
* ``agent:RUN_DIR`` — a trained agent loaded with ``magenv.agents.load_agent``; ``pretrained:ENV_ID`` (or
  ``agent:pretrained:ENV_ID``) — the agent shipped for that env.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any

from magenv.baselines import (
    constraint,
    kalman,
    kalman_policies,
    oracle,
    oracle_constraint,
    oracle_kalman,
    oracle_qsf,
    oracle_vqf,
    qsf,
    reference,
    rules,
    vqf_rules,
)
from magenv.envs.kalman import EXTENDED as KALMAN_EXTENDED
from magenv.protocols import Tunable
from magenv.userdata import DATA_DIR_ENV as DATA_DIR_ENV  # the one definition (tests, magenv.scale read it here)
from magenv.userdata import user_data_dir

AGENT_PREFIX = "agent:"
PRETRAINED_PREFIX = "pretrained:"  # pretrained:ENV_ID, the agent shipped for that env (magenv.agents.loading)
TUNED_SUFFIX = "_tuned"
METHOD_MODULES = (rules, kalman, kalman_policies, constraint, qsf, reference, vqf_rules)


def _kalman_proposals() -> tuple:
    """(kf_adaptive_tuned,) when a tuned kf_adaptive file exists, else ()."""
    adaptive = kalman_policies.AdaptiveTrust
    return (adaptive.from_params(tuned_params("kf_adaptive")),) if tuned_file("kf_adaptive") else ()


def _kalman_oracle(params: dict) -> oracle_kalman.KalmanOracle:
    """``oracle_kalman``: continuing with kf_model at ``params``; its student also sees kf_adaptive_tuned's γ
    (when a tuned kf_adaptive file exists), so that it can fall back on the best rule of each protocol."""
    return oracle_kalman.KalmanOracle.from_model_params(params, _kalman_proposals())


RULES_ORACLE_HORIZON_S = 1.0  # s, look-ahead of oracle_kalman_rules


def _kalman_rules_oracle(params: dict) -> oracle_kalman.KalmanOracle:
    """``oracle_kalman_rules``: ``oracle_kalman`` that also searches the γ of kf_model_tuned and
    kf_adaptive_tuned at each state (``rule_candidates``), continuing with the cheaper of the two rules, with a
    1 s look-ahead (0.25 s does not see what refusing the magnetometer costs in gyro drift). Without a tuned
    kf_adaptive it is not itself: TunedParamsError."""
    proposals = (kalman_policies.AdaptiveTrust.from_params(tuned_params("kf_adaptive")),)
    return oracle_kalman.KalmanOracle.from_model_params(
        params, proposals, rule_candidates=True, continuations=proposals, horizon_s=RULES_ORACLE_HORIZON_S
    )


def _kalman_still_oracle(params: dict) -> oracle_kalman.KalmanOracle:
    """``oracle_kalman_still``: ``oracle_kalman_rules`` that also searches kf_still_tuned's γ at each state (on
    the extended observation; a candidate, not a continuation), so that its student can fall back on the best
    rule measured on ``stationary_magnet`` too (the teacher of the MagKalman-v0 student shipped before). Needs
    tuned kf_adaptive and kf_still files (else TunedParamsError)."""
    rules = _kalman_rules_oracle(params)
    still = kalman_policies.StillPullTrust.from_params(tuned_params("kf_still"), features=KALMAN_EXTENDED.names)
    return oracle_kalman.KalmanOracle.from_model_params(
        params,
        rules.proposals,
        rule_candidates=True,
        continuations=rules.proposals,
        horizon_s=rules.horizon_s,
        still=still,
    )


SKIP_LEVELS = (0.0,)  # γ levels of oracle_kalman_skip: the magnetometer's update skipped
STILL_SCENARIOS = ("stationary_magnet",)  # where oracle_kalman_skip offers kf_still_tuned's γ


def _kalman_skip_oracle(params: dict, **extra) -> oracle_kalman.KalmanOracle:
    """``oracle_kalman_skip``: three candidates at each state, γ = 0 (the magnetometer's update skipped),
    kf_model_tuned's γ and kf_still_tuned's γ (on ``stationary_magnet`` trials only: elsewhere it costs inf),
    searched 1 s ahead continuing with the cheaper of kf_model_tuned and kf_adaptive_tuned; the DAgger teacher of
    the shipped MagKalman-v0 student. Per decision on ``dynamic_magnet`` the advantage of skipping over
    kf_model_tuned's γ is partly predictable from the student's causal inputs, that of a full update (γ = 1) is
    not (``studies/probe_advantage.py --env kalman``); and there kf_still_tuned's γ often looks cheapest
    over 1 s, yet students that take it follow that rule, which loses to kf_model_tuned over whole trials.
    Needs tuned kf_adaptive and kf_still files (else TunedParamsError). ``extra``: further options of the
    oracle (``perp``, ``perp_scenarios``)."""
    still = _kalman_still_oracle(params)
    return oracle_kalman.KalmanOracle.from_model_params(
        params,
        candidates=SKIP_LEVELS,
        rule_candidates=True,
        continuations=still.proposals,
        horizon_s=still.horizon_s,
        still=still.still,
        still_scenarios=STILL_SCENARIOS,
        **extra,
    )


PERP_SCENARIOS = ("dynamic_magnet",)  # where oracle_kalman_perp offers kf_perp_tuned's γ


def _kalman_perp_oracle(params: dict) -> oracle_kalman.KalmanOracle:
    """``oracle_kalman_perp``: ``oracle_kalman_skip`` with a fourth candidate, kf_perp_tuned's γ (the hand rule
    on ``d_perp``; on ``dynamic_magnet`` trials only, elsewhere it costs inf), so that a student can fall back on
    the best rule with its own information on either protocol. Needs tuned kf_adaptive, kf_still and kf_perp
    files (else TunedParamsError)."""
    perp = kalman_policies.PerpPullTrust.from_params(tuned_params("kf_perp"), features=KALMAN_EXTENDED.names)
    return _kalman_skip_oracle(params, perp=perp, perp_scenarios=PERP_SCENARIOS)


def _constraint_rules_oracle(params: dict) -> oracle_constraint.ConstraintOracle:
    """``oracle_constraint_rules``: ``oracle_constraint`` that also searches cf_constraint_tuned's own w at each
    state (``rule_candidates``), so that its DAgger student can fall back on the rule exactly."""
    return oracle_constraint.ConstraintOracle.from_constraint_params(params, rule_candidates=True)


#: methods that act with another rule's tuned parameters: name → (the rule whose file, factory(params))
TUNED_VARIANTS: dict[str, tuple[str, Callable[[dict], Any]]] = {
    "qsf_detector_tuned": ("delay_magyq", qsf.tuned_detector_policy),
    # privileged (reads truth): an upper bound shown as the headroom row, never a baseline
    "oracle": ("fan_lambda", oracle.BlendOracle.from_fan_params),
    "oracle_kalman": ("kf_model", _kalman_oracle),
    "oracle_kalman_rules": ("kf_model", _kalman_rules_oracle),
    "oracle_kalman_still": ("kf_model", _kalman_still_oracle),
    "oracle_kalman_skip": ("kf_model", _kalman_skip_oracle),
    "oracle_kalman_perp": ("kf_model", _kalman_perp_oracle),
    "oracle_constraint": ("cf_constraint", oracle_constraint.ConstraintOracle.from_constraint_params),
    "oracle_constraint_rules": ("cf_constraint", _constraint_rules_oracle),
    "oracle_qsf": ("delay_magyq", oracle_qsf.QSFOracle.from_detector_params),
    "oracle_qsf_hold": ("delay_magyq", oracle_qsf.QSFOracle.holding),
    "vqf_fan_rejection_tuned": ("vqf_fan_lambda", vqf_rules.fan_on_rejection),
    "oracle_vqf_rule": ("vqf_fan_lambda", oracle_vqf.VQFOracle.from_fan_params),
    "oracle_vqf_tail": ("vqf_fan_lambda", oracle_vqf.VQFOracle.with_tail),
}

_REGISTERED: dict[str, tuple[Callable[[], Any], str]] = {}


class TunedParamsError(ValueError):
    """A tuned-parameter file is missing, corrupt, or does not fit its rule."""


def user_tuned_dir() -> Path:
    """The default output folder of ``magenv tune`` (read before the packaged files)."""
    return user_data_dir() / "tuned"


def packaged_tuned_dir() -> Path:
    """The tuned-parameter files shipped with magenv (``magenv/baselines/tuned``)."""
    return Path(str(resources.files("magenv.baselines") / "tuned"))


def register(name: str, factory: Callable[[], Any], description: str = "", overwrite: bool = False) -> None:
    """Add a method. Raises ValueError if the name is taken (unless ``overwrite``)."""
    if not overwrite and name in _REGISTERED:
        raise ValueError(f"method {name!r} is already registered")
    _REGISTERED[name] = (factory, description)


def tunable_rules() -> dict[str, type[Tunable]]:
    """Every method with tunable parameters (``PARAM_BOUNDS``, ``params``, ``from_params``), by name:
    the λ rules, the Kalman-trust rules and cf_cerr (policies), the constraint filter and Delay MAGYQ's QSF
    detector (estimators)."""
    return {
        **rules.RULES,
        **kalman_policies.RULES,
        **vqf_rules.RULES,
        "cf_constraint": constraint.ConstraintCF,
        "cf_cerr": constraint.ErrorStepRule,
        "delay_magyq": qsf.DetectedDelayMAGYQ,
    }


def rule_class(name: str) -> type[Tunable]:
    """The class of a tunable rule name (``fan_lambda``, ``threshold``, ``kf_gate``, …)."""
    table = tunable_rules()
    try:
        return table[name]
    except KeyError:
        raise ValueError(f"unknown rule {name!r}; known rules: {', '.join(table)}") from None


def tuned_file(rule: str) -> Path | None:
    """The tuned-parameter file of ``rule``: the user's, else the packaged one, else None."""
    for folder in (user_tuned_dir(), packaged_tuned_dir()):
        path = folder / f"{rule}.json"
        if path.is_file():
            return path
    return None


def tuned_params(rule: str) -> dict[str, float]:
    """The parameters ``magenv tune`` wrote for ``rule``, checked name by name against the rule's
    ``PARAM_BOUNDS`` (every one present, none unknown, each a finite number within its bounds). Raises
    TunedParamsError."""
    path = tuned_file(rule)
    if path is None:
        raise TunedParamsError(
            f"no tuned parameters for {rule!r} (looked in {user_tuned_dir()} and "
            f"{packaged_tuned_dir()}); run magenv tune --rule {rule}"
        )
    try:
        params = json.loads(path.read_text())["params"]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise TunedParamsError(f"{path}: corrupt tuned-parameter file ({type(exc).__name__}: {exc})") from None
    if not isinstance(params, dict):
        raise TunedParamsError(f"{path}: 'params' must be a mapping of parameter name to number")
    bounds = rule_class(rule).PARAM_BOUNDS
    missing, unknown = sorted(set(bounds) - set(params)), sorted(set(params) - set(bounds))
    if missing or unknown:
        raise TunedParamsError(
            f"{path}: parameters do not fit rule {rule!r}: missing {missing}, unknown {unknown}; "
            f"expected {sorted(bounds)}"
        )
    for key, value in params.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise TunedParamsError(f"{path}: parameter {key!r} must be a finite number, got {value!r}")
        lo, hi = bounds[key]
        if not lo <= value <= hi:
            raise TunedParamsError(
                f"{path}: parameter {key!r} = {value!r} is outside the bounds of rule {rule!r}, [{lo:g}, {hi:g}]"
            )
    return {k: float(v) for k, v in params.items()}


def _build_tuned(rule: str, build: Callable[[dict], Any], name: str) -> Any:
    """``build`` given the tuned parameters of ``rule``, named ``name``."""
    return _named(build(tuned_params(rule)), name)


def _tuned() -> dict[str, tuple[Callable[[], Any], str]]:
    """``RULE_tuned`` for every tunable rule with a tuned file, and the ``TUNED_VARIANTS``."""
    builds: dict[str, tuple[str, Callable[[dict], Any]]] = {
        rule + TUNED_SUFFIX: (rule, cls.from_params) for rule, cls in tunable_rules().items()
    }
    builds.update(TUNED_VARIANTS)
    out: dict[str, tuple[Callable[[], Any], str]] = {}
    for name, (rule, build) in builds.items():
        path = tuned_file(rule)
        if path is not None:
            out[name] = (
                functools.partial(_build_tuned, rule, build, name),
                f"{rule} with the parameters tuned by magenv tune ({path})"
                if name == rule + TUNED_SUFFIX
                else f"{(build.__doc__ or name).strip().splitlines()[0]} (tuned {rule}: {path})",
            )
    return out


def _named(method, name: str):
    method.name = name
    return method


def _hand_moved(base: Callable[[], Any], name: str) -> Any:
    return _named(kalman_policies.hand_moved(base()), name)


def _hand(table: dict[str, tuple[Callable[[], Any], str]]) -> dict[str, tuple[Callable[[], Any], str]]:
    """``NAME_hand`` for every Kalman-trust rule ``NAME`` of ``table`` (``kalman_policies.hand_moved``)."""
    return {
        name + kalman_policies.HAND_SUFFIX: (
            functools.partial(_hand_moved, factory, name + kalman_policies.HAND_SUFFIX),
            f"{name} for a hand-moved board: sigma_acc 0.5 m/s², no accelerometer gate, gyro de-biased at rest",
        )
        for name, (factory, _) in table.items()
        if name.startswith("kf_") and name.split("_")[1] in ("nominal", "gate", "adaptive", "model")
    }


def _all() -> dict[str, tuple[Callable[[], Any], str]]:
    table: dict[str, tuple[Callable[[], Any], str]] = {}
    for module in METHOD_MODULES:
        for name, factory in module.methods().items():
            table[name] = (factory, (factory.__doc__ or module.__name__).strip().splitlines()[0])
    table.update(_tuned())
    table.update(_hand(table))
    table.update(_REGISTERED)
    return table


def names() -> list[str]:
    """All known method names (``agent:RUN_DIR`` is accepted besides these)."""
    return list(_all())


def describe() -> dict[str, str]:
    """Method name → one-line description."""
    return {k: v[1] for k, v in _all().items()}


def make(name: str, trust_pickle: bool = False):
    """A fresh Policy or Estimator for a method name. Unknown names raise ValueError listing the known ones.
    ``trust_pickle`` is for ``agent:RUN_DIR`` only: see ``magenv.agents.load_agent``."""
    if name.startswith((AGENT_PREFIX, PRETRAINED_PREFIX)):
        from magenv.agents.loading import load_agent

        return load_agent(name.removeprefix(AGENT_PREFIX), trust_pickle=trust_pickle)
    table = _all()
    if name not in table:
        raise ValueError(
            f"unknown method {name!r}; known methods: {', '.join(table)} (or {AGENT_PREFIX}RUN_DIR for a trained "
            f"agent, {PRETRAINED_PREFIX}ENV_ID for a shipped one)"
        )
    method = table[name][0]()
    if not hasattr(method, "name"):
        try:
            method.name = name
        except AttributeError:
            pass
    return method
