"""Policies of ``magenv/MagVQF-v0``: VQF's own rejection, no rejection, and the λ rules mapped to VQF's gain.

Each acts on the observation alone and carries the env options it runs with
(``env_kwargs``). The trust u scales VQF's magnetometer gain
(``magenv.envs.vqf.tau_of_trust``: k = u·k₁).

* ``vqf_rejection`` (:class:`VQFTrust` u = 1, ``rejection="on"``): VQF as
  shipped — reproduces the ``vqf`` reference estimator bit for bit.
* ``vqf_no_rejection`` (u = 1, ``rejection="off"``): VQF with its
  disturbance rejection off (``magDistRejectionEnabled=False``).
* ``vqf_fan_lambda`` — Fan et al. 2017 eqs. 15–17 (``magenv.filters.rules.fan_lambda``) on the env's
  ``norm_dev`` and ``dip_dev`` (same names and scales as MagBlend-v0's), u = 1 − λ, VQF's rejection off
  (the rule replaces it).

* ``oracle_vqf`` — the privileged search of ``magenv.baselines.oracle_vqf`` on
  top of VQF's rejection: an upper bound (it reads truth), never a baseline.
* ``vqf_fan_rejection_tuned`` — ``vqf_fan_lambda_tuned``'s trust on top of
  VQF's rejection (:func:`fan_on_rejection`).
* ``vqf_threshold`` — u = 0 when |‖m‖ − m0|/m0 > norm_th or |θ_dip − θ0| >
  dip_th_deg, else 1 (the gate of ``magenv.baselines.rules.Threshold``),
  rejection off.

The two rules are tunable (``magenv tune --rule vqf_fan_lambda``); their
parameters, bounds and published defaults are those of
``magenv.baselines.rules``.
"""

from __future__ import annotations

import numpy as np

from magenv.baselines.oracle_vqf import DECISION_EVERY, VQFOracle
from magenv.baselines.rules import FanLambda, Threshold
from magenv.envs import VQF_ID
from magenv.envs.vqf import FEATURES
from magenv.filters import rules


class VQFTrust:
    """Constant trust ``u`` with VQF's rejection ``"on"`` or ``"off"``."""

    env_id = VQF_ID

    def __init__(self, u: float = 1.0, rejection: str = "on"):
        if not 0.0 <= u <= 1.0:
            raise ValueError(f"u must lie in [0, 1], got {u}")
        self.u = float(u)
        self.env_kwargs = {"rejection": rejection}
        self._action = np.array([self.u], np.float32)

    def reset(self) -> None:
        """Memoryless."""

    def __call__(self, obs) -> np.ndarray:
        return self._action.copy()

    def __repr__(self) -> str:
        return f"VQFTrust(u={self.u:g}, rejection={self.env_kwargs['rejection']!r})"


class VQFRule:
    """Mixin: a MagBlend λ rule acting on MagVQF-v0's observation with u = 1 − λ, VQF's rejection off."""

    env_id = VQF_ID

    def _vqf_setup(self) -> None:
        self.env_kwargs = {"rejection": "off"}

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return np.array([1.0 - self.weight(obs)], dtype=np.float32)  # type: ignore[attr-defined]


class VQFFanLambda(VQFRule, FanLambda):
    """Fan et al. 2017 eqs. 15–17 as VQF's trust u = 1 − λ (module docstring)."""

    name = "vqf_fan_lambda"

    def __init__(self, norm_tol: float = rules.FAN_NORM_TOL, th_dip_deg: float = rules.FAN_TH_DIP_DEG):
        super().__init__(norm_tol, th_dip_deg, features=FEATURES.names)
        self._vqf_setup()


class VQFThreshold(VQFRule, Threshold):
    """The all-or-nothing gate as VQF's trust: u = 0 beyond either threshold, else 1."""

    name = "vqf_threshold"

    def __init__(self, norm_th: float = rules.GATE_NORM_TH, dip_th_deg: float = rules.GATE_DIP_TH_DEG):
        super().__init__(norm_th, dip_th_deg, features=FEATURES.names)
        self._vqf_setup()


RULES = {"vqf_fan_lambda": VQFFanLambda, "vqf_threshold": VQFThreshold}


def fan_on_rejection(params: dict) -> VQFFanLambda:
    """``vqf_fan_rejection_tuned``: ``vqf_fan_lambda_tuned``'s trust u = 1 − λ on top of VQF's own rejection
    (``rejection="on"``), decided every ``oracle_vqf.DECISION_EVERY`` samples — the rule ``oracle_vqf_rule``
    continues with and its guarded student falls back on (the hand rule the learned agent departs from)."""
    rule = VQFFanLambda.from_params(params)
    rule.env_kwargs = {"rejection": "on", "decision_every": DECISION_EVERY}
    return rule


def vqf_rejection() -> VQFTrust:
    """VQF as shipped: u = 1, its own magnetic disturbance rejection on (reproduces the vqf estimator)."""
    return VQFTrust(1.0, "on")


def vqf_no_rejection() -> VQFTrust:
    """VQF with its disturbance rejection off: u = 1 always."""
    return VQFTrust(1.0, "off")


def oracle_vqf() -> VQFOracle:
    """Privileged receding-horizon trust search over VQF (reads truth: the headroom, never a baseline)."""
    return VQFOracle(rejection="on")


def methods() -> dict:
    """Name → factory for ``magenv.registry``: VQF with and without its rejection, the two rules, and the
    privileged ``oracle_vqf`` (``magenv.baselines.oracle_vqf``)."""
    return {
        "oracle_vqf": oracle_vqf,
        "vqf_rejection": vqf_rejection,
        "vqf_no_rejection": vqf_no_rejection,
        "vqf_fan_lambda": VQFFanLambda,
        "vqf_threshold": VQFThreshold,
    }
