"""Jung & Lee 2019's three methods as Estimators, and its eq. 16 rule as a Policy.

Estimators (``run(trial) -> Estimate``; a two-link trial, ``magenv.scenarios.twolink``):

* ``strapdown`` — gyroscope integration only (eq. 17 with k = 0);
* ``cf_conventional`` — the conventional CF (Bachmann 1999): one Gauss–Newton
  step on gravity and magnetometer per sample, constant gain k (eq. 17 with
  w = 0; default k = k_max = 0.2);
* ``cf_constraint`` — the proposed constraint-combined adaptive CF (eqs. 4–18,
  published th1 = 0.15, th2 = 0.25, th3 = 0.2, k_min = 0.01, k_max = 0.2).
  Its five parameters are constructor arguments, listed with search bounds
  in ``PARAM_BOUNDS`` and read back by ``params`` (for CMA-ES tuning);
* ``cf_gated`` — ablation, not in the paper: ``cf_constraint`` with the
  constraint block removed from W (eqs. 16–18 still drop the magnetometer
  and schedule k), to measure what the constraint itself contributes.

All start from the e-compass of the first sample (never truth) and take the
lever arms r_i, r_j from ``trial.meta`` unless given. ``trust`` is the
magnetometer's weight 1 − w (eq. 15; 1 for the conventional CF, NaN-free).

Policies (act in ``magenv/MagConstraint-v0`` on the observation alone; the env
applies eq. 18 for k):

* ``constraint_rule`` — ``ConstraintWeightRule``: w by eq. 16 from the
  ``mag_dev`` feature. With one decision per sample (``decision_every=1``) it
  is the ``cf_constraint`` estimator up to float32 rounding of the observation.
* ``cf_cerr`` — ``ErrorStepRule``: magenv's own rule (no paper's), eq. 16
  overruled by the constraint error estimate of the extended observation
  (``magenv.envs.constraint_memory``: ``step0_dot``, ``step1_dot`` — eq. 14's
  step at w = 0 and at w = 1 against the estimated tilt error, °², < 0
  corrects). With d = step0_dot − step1_dot (< 0: the magnetometer's step
  corrects more than the constraint's):
      w = min(w₁₆, w_mag)    if d < −d_min,
      w = max(w₁₆, w_con)    if d > d_min,
      w = w₁₆                otherwise,
  w₁₆ eq. 16's weight (th1), one decision per sample, k by eq. 18 (th2, th3,
  k_min, k_max, tuned with it). It is the hand-written use of the information
  the constraint student's ``cerr_*``/``step*`` inputs add, as ``kf_perp`` is
  for the Kalman student's ``d_perp``. Defaults: the published eq. 16/18
  values and w_mag = 1, w_con = 0, d_min = 1 °², i.e. ``cf_constraint`` itself.

Paper check (Table 2): ``magenv paper constraint --seeds 0:5``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from magenv.checks import check_number
from magenv.envs import CONSTRAINT_ID as ENV_ID
from magenv.envs.constraint import FEATURES
from magenv.filters import constraint as cf
from magenv.protocols import Estimate, Tunable
from magenv.trial import Trial


class _Base:
    """Shared: lever arms and initial orientation."""

    name = "constraint"

    def __init__(self, lever_i=None, lever_j=None, q0=None):
        self.lever_i, self.lever_j, self.q0 = lever_i, lever_j, q0

    def _filter(self, trial: Trial, **kw) -> cf.ConstraintFilter:
        return cf.ConstraintFilter(trial, self.lever_i, self.lever_j, q0=self.q0, **kw)


class Strapdown(_Base):
    """Gyroscope integration from the e-compass start (eq. 17, k = 0)."""

    name = "strapdown"

    def run(self, trial: Trial) -> Estimate:
        return Estimate(q=self._filter(trial).run(0.0, 0.0).est, trust=np.zeros(trial.n))


class ConventionalCF(Tunable, _Base):
    """Gravity + magnetometer Gauss–Newton CF without the constraint (w = 0), constant gain k."""

    name = "cf_conventional"
    PARAM_BOUNDS = {"k": (0.001, 2.0)}

    def __init__(self, k: float = cf.K_MAX, lever_i=None, lever_j=None, q0=None):
        super().__init__(lever_i, lever_j, q0)
        if not k >= 0:
            raise ValueError(f"gain k must be ≥ 0, got {k!r}")
        self.k = float(k)

    def run(self, trial: Trial) -> Estimate:
        return Estimate(q=self._filter(trial).run(0.0, self.k).est, trust=np.ones(trial.n))


class ConstraintCF(Tunable, _Base):
    """The constraint-combined adaptive CF (eqs. 4–18); ``rule``: th1 … k_max by keyword
    (``magenv.filters.constraint.check_rule_params``, whose defaults are the published parameters)."""

    name = "cf_constraint"
    PARAM_BOUNDS = {
        "th1": (0.02, 1.0),
        "th2": (0.0, 1.0),
        "th3": (0.01, 2.0),
        "k_min": (0.0, 0.2),
        "k_max": (0.02, 1.0),
    }

    def __init__(self, lever_i=None, lever_j=None, q0=None, use_constraint: bool = True, **rule):
        super().__init__(lever_i, lever_j, q0)
        self.use_constraint = bool(use_constraint)
        self.th1, self.th2, self.th3, self.k_min, self.k_max = cf.check_rule_params(**rule, sort_gains=True)

    def run(self, trial: Trial) -> Estimate:
        trace = self._filter(trial, use_constraint=self.use_constraint, **self.params).run()  # eqs. 16 and 18
        return Estimate(q=trace.est, trust=1.0 - trace.weight)

    def __repr__(self) -> str:
        extra = "" if self.use_constraint else ", use_constraint=False"
        return f"ConstraintCF({', '.join(f'{k}={v:g}' for k, v in self.params.items())}{extra})"


def gated(**kw) -> ConstraintCF:
    """Ablation: the proposed filter without its constraint block (eqs. 16–18 gating only)."""
    est = ConstraintCF(use_constraint=False, **kw)
    est.name = "cf_gated"
    return est


class ConstraintWeightRule(Tunable):
    """eq. 16 as a policy of ``magenv/MagConstraint-v0``: w = min(mag_dev/th1, 1).

    With the env's ``control_gain`` option the action also carries k by eq. 18,
    using ‖Δq‖ interpolated between the observed steps at w = 0 and w = 1
    (``step_mag``, ``step_con``), an approximation: the filter's own step at w
    is only known once w is chosen. ``gain_max`` must match the env's. ``rule``: th1 … k_max by keyword
    (``magenv.filters.constraint.check_rule_params``, published defaults).
    """

    env_id = ENV_ID
    name = "constraint_rule"
    PARAM_BOUNDS = {"th1": (0.02, 1.0)}

    def __init__(
        self, control_gain: bool = False, gain_max: float = 1.0, features: Sequence[str] | None = None, **rule
    ):
        self.th1, *gain_params = cf.check_rule_params(**rule)
        self.gain_params = tuple(gain_params)  # eq. 18's th2, th3, k_min, k_max
        self.control_gain = bool(control_gain)
        self.gain_max = float(gain_max)
        self.features = tuple(FEATURES.names if features is None else features)
        need = ("mag_dev", "step_mag", "step_con") if control_gain else ("mag_dev",)
        missing = [f for f in need if f not in self.features]
        if missing:
            raise ValueError(
                f"ConstraintWeightRule needs observation feature(s) {missing}; "
                f"the env's features are {list(self.features)}"
            )
        self._ix = {f: self.features.index(f) for f in need}
        self.env_kwargs: dict[str, Any] = {} if features is None else {"features": list(self.features)}
        if control_gain:
            self.env_kwargs.update(control_gain=True, gain_max=self.gain_max)

    def reset(self) -> None:
        """Memoryless."""

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        w = float(cf.weight_rule(float(obs[self._ix["mag_dev"]]), self.th1))  # eq. 16
        if not self.control_gain:
            return np.array([w], dtype=np.float32)
        step = (1.0 - w) * float(obs[self._ix["step_mag"]]) + w * float(obs[self._ix["step_con"]])
        k = float(cf.gain_rule(w, step, *self.gain_params))  # eq. 18
        return np.array([w, min(k / self.gain_max, 1.0)], dtype=np.float32)


class ErrorStepRule(Tunable):
    """eq. 16's w, overruled where eq. 14's steps at w = 0 and w = 1 differ in how far they correct the constraint
    error estimate (see the module docstring); one decision per sample, k by eq. 18 with this rule's parameters
    (``rule``: th1 … k_max by keyword, ``magenv.filters.constraint.check_rule_params``)."""

    env_id = ENV_ID
    name = "cf_cerr"
    PARAM_BOUNDS = {
        **ConstraintCF.PARAM_BOUNDS,
        "d_min": (0.01, 100.0),
        "w_mag": (0.0, 1.0),
        "w_con": (0.0, 1.0),
    }
    FEATURES = ("mag_dev", "step0_dot", "step1_dot")  # the observation it reads (extended table)

    def __init__(self, d_min: float = 1.0, w_mag: float = 1.0, w_con: float = 0.0, **rule):
        self.th1, self.th2, self.th3, self.k_min, self.k_max = cf.check_rule_params(**rule, sort_gains=True)
        self.d_min = check_number("d_min (°²)", d_min, 0.0)
        self.w_mag = check_number("w_mag", w_mag, 0.0, 1.0)
        self.w_con = check_number("w_con", w_con, 0.0, 1.0)
        self.env_kwargs: dict[str, Any] = {
            "features": list(self.FEATURES),
            "decision_every": 1,
            "th2": self.th2,
            "th3": self.th3,
            "k_min": self.k_min,
            "k_max": self.k_max,
        }

    def reset(self) -> None:
        """Memoryless."""

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=float)
        if obs.shape != (len(self.FEATURES),):
            raise ValueError(f"cf_cerr reads the observation {self.FEATURES}, got one of shape {obs.shape}")
        dev, step0_dot, step1_dot = obs
        w = float(cf.weight_rule(dev, self.th1))  # eq. 16
        d = step0_dot - step1_dot
        if d < -self.d_min:  # the magnetometer's step corrects the estimated error more
            w = min(w, self.w_mag)
        elif d > self.d_min:  # the constraint's step does
            w = max(w, self.w_con)
        return np.array([w], dtype=np.float32)

    def __repr__(self) -> str:
        return f"ErrorStepRule({', '.join(f'{k}={v:g}' for k, v in self.params.items())})"


def methods() -> dict:
    """Name → factory for ``magenv compare`` (picked up by ``magenv.registry``)."""
    return {
        "strapdown": Strapdown,
        "cf_conventional": ConventionalCF,
        "cf_constraint": ConstraintCF,
        "cf_gated": gated,
        "constraint_rule": ConstraintWeightRule,
        "cf_cerr": ErrorStepRule,
    }
