"""Hand-crafted λ rules as policies of ``magenv/MagBlend-v0``, acting on the observation alone.

Every rule follows ``magenv.protocols.Policy``, takes its parameters as
constructor arguments (the defaults are the published values), exposes them
as ``params`` and ``PARAM_BOUNDS`` (for ``magenv tune``), and rebuilds from
them with ``from_params``. A rule finds its features by name in the env's
table (``magenv.envs.blend.FEATURES``) and reads physical values back through
the fixed scales: field-norm deviation as a fraction of m0 (``norm_dev``), dip
deviation in units of ``DIP_SCALE_DEG`` = 90° (``dip_dev``). m0 and θ0 are
the trial's undisturbed field (``Trial.field_norm``/``field_dip``), which the
env applies.

* ``ConstantLambda(lam)`` — the registry's ``mimu`` (λ = 0) and ``imu``
  (λ = 1) are the paper's *original* filters, so they run with the
  stationary hold off (``stationary_hold=False``); the rules below keep the
  env's default hold (on), as in the paper's proposed method.
* ``FanLambda`` — Fan et al. 2017 eqs. 15–17. Reading of eq. 16: its
  divisor, printed as θ_dip, is read as a dip threshold th_dip = 20° (a fixed
  tolerance, like eq. 15's m0), not the measured dip itself.
* ``Threshold`` — all-or-nothing gate: λ = 1 when the field-norm or the dip
  deviation exceeds its threshold, else 0 (the vector-selector idea of
  Lee & Park 2009 in Ligorio & Sabatini 2016 Table A1: th_mag = 1.20 µT of
  m0 = 46 µT ⇒ 0.026, th_α = 5°).

The formulas, their published parameters and tuning ranges are ``magenv.filters.rules`` (shared with the
oracles, the students' inputs and the ONNX export).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from magenv.envs import BLEND_ID as ENV_ID
from magenv.envs.blend import FEATURES
from magenv.envs.features import DIP_SCALE_DEG
from magenv.filters import rules
from magenv.protocols import Tunable


class RulePolicy(Tunable):
    """Base class: feature lookup, params, reset. Subclasses define ``PARAM_BOUNDS`` and ``weight(obs)``."""

    env_id = ENV_ID
    name = "rule"
    NEEDS: tuple[str, ...] = ()

    def __init__(self, features: Sequence[str] | None = None, stationary_hold: bool | None = None):
        self.features = tuple(FEATURES.names if features is None else features)
        missing = [f for f in self.NEEDS if f not in self.features]
        if missing:
            raise ValueError(
                f"{type(self).__name__} needs observation feature(s) {missing}; "
                f"the env's features are {list(self.features)}"
            )
        self._ix = {f: self.features.index(f) for f in self.NEEDS}
        # env options this policy runs with: non-default features; the stationary
        # hold if set (None = the env's default, on)
        self.env_kwargs: dict[str, Any] = {} if features is None else {"features": list(self.features)}
        if stationary_hold is not None:
            self.env_kwargs["stationary_hold"] = bool(stationary_hold)

    def reset(self) -> None:
        """Rules are memoryless."""

    def weight(self, obs: np.ndarray) -> float:
        """λ ∈ [0, 1] for one observation."""
        raise NotImplementedError

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return np.array([self.weight(obs)], dtype=np.float32)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}={v:g}' for k, v in self.params.items())})"


class ConstantLambda(RulePolicy):
    """λ fixed: 0 = pure MIMU filter, 1 = pure IMU filter."""

    name = "constant"
    PARAM_BOUNDS = {"lam": (0.0, 1.0)}

    def __init__(self, lam: float = 0.0, features: Sequence[str] | None = None, stationary_hold: bool | None = None):
        super().__init__(features, stationary_hold)
        if not 0.0 <= lam <= 1.0:
            raise ValueError(f"λ must lie in [0, 1], got {lam}")
        self.lam = float(lam)
        self._action = np.array([self.lam], dtype=np.float32)

    def weight(self, obs: np.ndarray) -> float:
        return self.lam

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self._action.copy()


class DeviationRule(RulePolicy):
    """A rule on the observation's ``norm_dev`` and ``dip_dev`` with two thresholds > 0, the parameters named by
    ``PARAM_BOUNDS`` (the field-norm one, fraction of m0; the dip one, °); ``common``: :class:`RulePolicy`'s."""

    NEEDS = ("norm_dev", "dip_dev")

    def __init__(self, norm: float, dip: float, **common):
        super().__init__(**common)
        names = tuple(self.PARAM_BOUNDS)
        if not (norm > 0 and dip > 0):
            raise ValueError(f"{names[0]} and {names[1]} must be positive, got {norm}, {dip}")
        for name, value in zip(names, (norm, dip)):
            setattr(self, name, float(value))

    @property
    def thresholds(self) -> tuple[float, float]:
        """The two thresholds, in ``PARAM_BOUNDS``' order."""
        norm, dip = (getattr(self, name) for name in self.PARAM_BOUNDS)
        return norm, dip

    def deviations(self, obs: np.ndarray) -> tuple[float, float]:
        """(field-norm deviation (‖m‖ − m0)/m0, dip deviation θ_dip − θ0 in °) of one observation."""
        return float(obs[self._ix["norm_dev"]]), DIP_SCALE_DEG * float(obs[self._ix["dip_dev"]])


class FanLambda(DeviationRule):
    """Fan et al. 2017 eqs. 15–17 (``magenv.filters.rules.fan_lambda``) on the observation's ``norm_dev`` and
    ``dip_dev`` (eq. 18 for θ_dip)."""

    name = "fan_lambda"
    PARAM_BOUNDS = rules.FAN_BOUNDS

    def __init__(self, norm_tol: float = rules.FAN_NORM_TOL, th_dip_deg: float = rules.FAN_TH_DIP_DEG, **common):
        super().__init__(norm_tol, th_dip_deg, **common)

    def weight(self, obs: np.ndarray) -> float:
        return float(rules.fan_lambda(*self.deviations(obs), *self.thresholds))


class Threshold(DeviationRule):
    """λ = 1 when |‖m‖ − m0|/m0 > norm_th or |θ_dip − θ0| > dip_th_deg, else λ = 0 (``magenv.filters.rules.gate``)."""

    name = "threshold"
    PARAM_BOUNDS = rules.GATE_BOUNDS

    def __init__(self, norm_th: float = rules.GATE_NORM_TH, dip_th_deg: float = rules.GATE_DIP_TH_DEG, **common):
        super().__init__(norm_th, dip_th_deg, **common)

    def weight(self, obs: np.ndarray) -> float:
        return 1.0 if rules.gate(*self.deviations(obs), *self.thresholds) else 0.0


RULES: dict[str, type[RulePolicy]] = {"constant": ConstantLambda, "fan_lambda": FanLambda, "threshold": Threshold}


def methods() -> dict:
    """Name → factory of the blend rules for ``magenv compare``: the original filters and the published rules."""
    return {
        "mimu": lambda: ConstantLambda(0.0, stationary_hold=False),
        "imu": lambda: ConstantLambda(1.0, stationary_hold=False),
        "fan_lambda": FanLambda,
        "threshold": Threshold,
    }
