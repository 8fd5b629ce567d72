"""Hand-crafted trust rules as policies of ``magenv/MagKalman-v0``, acting on the observation alone.

Each rule returns the magnetometer trust γ ∈ [0, 1] (the Kalman-gain
multiplier of ``magenv.filters.kalman_trust``) and follows
``magenv.baselines.rules.RulePolicy``: parameters as constructor arguments,
``params``, ``PARAM_BOUNDS`` (for ``magenv tune``), ``from_params``. A rule
finds its features by name in the env's table (``magenv.envs.kalman.FEATURES``)
and reads physical values back through the fixed scales: ‖m‖ − m0 =
m0·norm_dev µT, dip deviation = 90·dip_dev degrees, ‖d̂‖ = m0·model_dist µT,
with the site's m0 = 50·field_ref µT (``FIELD_SCALE_UT``; also an
observation, so rules in µT are exact at any site).

* ``kf_nominal`` — :class:`ConstantTrust` (γ = 1): the plain Kalman filter.
* ``kf_gate`` — :class:`GateTrust`: the vector selector of Lee & Park 2009
  (survey A8, Table A1) as a policy:
  γ = 0 if | ‖m‖ − m0 | ≥ th_mag or |θ − θ0| ≥ th_α, else 1
  (th_mag = 1.20 µT, th_α = 5°). The accelerometer half of the selector (A7,
  th_acc = 0.08 m/s²) is the filter's own gate, active in every rule.
  The dip θ is taken below the filter's a-priori horizontal (after the
  accelerometer update of the same sample) — the survey's dip below the
  selected gravity up to the accelerometer noise. One difference is not a
  matter of γ: the survey's filter still runs its update with a replaced
  sample (innovation ≈ 0), which keeps P at its steady state, whereas γ = 0
  leaves P growing honestly (from P0 = (5°)² at the start), so the first
  sample accepted after a rejection spell moves the heading with a large
  gain. Where a disturbance turns the horizontal field while its norm and dip
  pass the tests (e.g. ``dynamic_magnet``), kf_gate therefore does worse than
  th_triad although both gates agree sample for sample.
* ``kf_adaptive`` — :class:`AdaptiveTrust`: measurement noise that grows with
  the measured deviation (Harada et al. 2007, survey ref. [38]):
  R_m ← R_m·(1 + (Δm/σ_m)² + (Δθ/σ_θ)²) with Δm = ‖m‖ − m0 (µT), Δθ = θ − θ0
  (°). When the measurement noise dominates S (the filter's steady state),
  scaling R by r scales the gain by ≈ 1/r, so
      γ = 1 / (1 + (Δm/σ_m)² + (Δθ/σ_θ)²).
  Default scales σ_m = 1.20 µT, σ_θ = 5° (Table A1's thresholds: γ = ½ at a
  threshold); [38]'s own constants are not in the survey.
* ``kf_model`` — :class:`ModelTrust`: trust from the model-based filter's
  disturbance estimate (Ligorio & Sabatini 2015, survey A.9–A.10). The env
  runs the Gauss–Markov split of the magnetometer causally and shows ‖d̂_j‖
  as ``model_dist``; the rule treats it as the adaptive rule treats the
  measured deviation:  γ = 1 / (1 + (‖d̂‖/σ_d)²),  σ_d = 1.20 µT by default.
* ``kf_still`` — :class:`StillPullTrust`: magenv's own rule (no paper's), the
  hand-written use of the still anchor that the extended observation gives
  the learned students (``magenv.envs.kalman_memory``: ``t_anchor``, the time
  since the field was last clean; ``pull_still``, a full update's heading
  correction toward the orientation held since then, ° > 0 toward it):
      γ = γ_a                          if the field is clean now (t_anchor = 0),
      γ = max(γ_a, γ_pull)             if pull_still > p_min,
      γ = 0                            otherwise,
  with γ_a kf_adaptive's γ (σ_m, σ_θ). The defaults (σ_m = 1.20 µT, σ_θ = 5°,
  p_min = 0°, γ_pull = 0) use the magnetometer only where it is clean or pulls
  toward the anchor. It measures how much of a student's gain a rule with the
  same information already has. Tuned, it is the best rule measured on
  ``stationary_magnet``, but the protocols' reference rules stay kf_model_tuned
  and kf_adaptive_tuned (the papers' rules).
* ``kf_perp`` — :class:`PerpPullTrust`: magenv's own rule on ``d_perp``, the
  causal estimate of the signed heading error that the extended observation
  reads from the field across the disturbance's sensor-frame direction
  (``magenv.envs.kalman_memory``; ``pull_perp``, a full update's heading
  correction against it, ° > 0: toward the truth as d_perp sees it;
  ``perp_info`` ∈ [0, 1], how much heading d_perp sees):
      γ = γ_m                          if perp_info < i_min,
      γ = max(γ_m, γ_pull)             if pull_perp > p_min,
      γ = 0                            otherwise,
  with γ_m kf_model's γ (σ_d). It is the hand-written use of the information
  the Kalman student's ``d_perp`` inputs carry, as kf_still is of the still
  anchor's; defaults σ_d = 1.20 µT, p_min = 0°, γ_pull = 0, i_min = 0.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import numpy as np

from magenv.baselines.rules import RulePolicy
from magenv.envs import KALMAN_ID as ENV_ID
from magenv.envs.features import DIP_SCALE_DEG
from magenv.envs.kalman import FEATURES, FIELD_SCALE_UT
from magenv.filters.kalman_threshold import TH_DIP, TH_MAG
from magenv.recordings import initial_rest
from magenv.trial import Trial


class KalmanRule(RulePolicy):
    """Base of the trust rules: MagKalman-v0 features; ``weight(obs)`` returns γ."""

    env_id = ENV_ID
    name = "kf_rule"
    #: run on ``prepare_trial(trial)`` instead of the trial (``magenv.evaluation.run_method``); see hand_moved
    prepare_trial: Callable[[Trial], Trial] | None = None

    def __init__(self, features: Sequence[str] | None = None):
        super().__init__(tuple(FEATURES.names if features is None else features))
        self.env_kwargs = {} if features is None else {"features": list(self.features)}
        if self.NEEDS and "field_ref" not in self.features:
            raise ValueError(f"{type(self).__name__} needs observation feature 'field_ref' (m0) to read µT")
        self._i_m0 = self.features.index("field_ref") if "field_ref" in self.features else None

    def _ut(self, obs: np.ndarray, feature: str) -> float:
        """A fraction-of-m0 feature in µT (m0 = 50 µT·field_ref)."""
        return FIELD_SCALE_UT * float(obs[self._i_m0]) * float(obs[self._ix[feature]])

    def _deg(self, obs: np.ndarray, feature: str) -> float:
        """A units-of-90° feature in degrees."""
        return DIP_SCALE_DEG * float(obs[self._ix[feature]])


class ConstantTrust(KalmanRule):
    """γ fixed (1 = the nominal Kalman filter, 0 = gyro-only heading)."""

    name = "kf_constant"
    PARAM_BOUNDS = {"gamma": (0.0, 1.0)}

    def __init__(self, gamma: float = 1.0, features: Sequence[str] | None = None):
        super().__init__(features)
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"γ must lie in [0, 1], got {gamma}")
        self.gamma = float(gamma)

    def weight(self, obs: np.ndarray) -> float:
        return self.gamma


class GateTrust(KalmanRule):
    """Vector selector (survey A8): γ = 0 if |‖m‖ − m0| ≥ th_mag_ut or |θ − θ0| ≥ th_dip_deg, else 1."""

    name = "kf_gate"
    PARAM_BOUNDS = {"th_mag_ut": (0.1, 20.0), "th_dip_deg": (0.5, 45.0)}
    NEEDS = ("norm_dev", "dip_dev")

    def __init__(self, th_mag_ut: float = TH_MAG, th_dip_deg: float = TH_DIP, features: Sequence[str] | None = None):
        super().__init__(features)
        if not (th_mag_ut > 0 and th_dip_deg > 0):
            raise ValueError(f"th_mag_ut and th_dip_deg must be positive, got {th_mag_ut}, {th_dip_deg}")
        self.th_mag_ut, self.th_dip_deg = float(th_mag_ut), float(th_dip_deg)

    def weight(self, obs: np.ndarray) -> float:
        ok = (
            abs(self._ut(obs, "norm_dev")) < self.th_mag_ut  # A8, norm test
            and abs(self._deg(obs, "dip_dev")) < self.th_dip_deg
        )  # A8, dip test
        return 1.0 if ok else 0.0


class AdaptiveTrust(KalmanRule):
    """Adaptive R (survey ref. [38]): γ = 1 / (1 + (Δm/σ_m)² + (Δθ/σ_θ)²), Δm µT, Δθ degrees."""

    name = "kf_adaptive"
    PARAM_BOUNDS = {"sigma_mag_ut": (0.1, 20.0), "sigma_dip_deg": (0.5, 45.0)}
    NEEDS: tuple[str, ...] = ("norm_dev", "dip_dev")

    def __init__(
        self, sigma_mag_ut: float = TH_MAG, sigma_dip_deg: float = TH_DIP, features: Sequence[str] | None = None
    ):
        super().__init__(features)
        if not (sigma_mag_ut > 0 and sigma_dip_deg > 0):
            raise ValueError(f"sigma_mag_ut and sigma_dip_deg must be positive, got {sigma_mag_ut}, {sigma_dip_deg}")
        self.sigma_mag_ut, self.sigma_dip_deg = float(sigma_mag_ut), float(sigma_dip_deg)

    def weight(self, obs: np.ndarray) -> float:
        a = self._ut(obs, "norm_dev") / self.sigma_mag_ut
        b = self._deg(obs, "dip_dev") / self.sigma_dip_deg
        return 1.0 / (1.0 + a * a + b * b)


class ModelTrust(KalmanRule):
    """Trust from the model-based disturbance estimate: γ = 1 / (1 + (‖d̂‖/σ_d)²), ‖d̂‖ µT."""

    name = "kf_model"
    PARAM_BOUNDS = {"sigma_dist_ut": (0.1, 20.0)}
    NEEDS: tuple[str, ...] = ("model_dist",)

    def __init__(self, sigma_dist_ut: float = TH_MAG, features: Sequence[str] | None = None):
        super().__init__(features)
        if not sigma_dist_ut > 0:
            raise ValueError(f"sigma_dist_ut must be positive, got {sigma_dist_ut}")
        self.sigma_dist_ut = float(sigma_dist_ut)

    def weight(self, obs: np.ndarray) -> float:
        a = self._ut(obs, "model_dist") / self.sigma_dist_ut
        return 1.0 / (1.0 + a * a)


def _check_pull(pull_min_deg: float, gamma_pull: float) -> tuple[float, float]:
    """The pull gate's (p_min °, γ_pull), checked: p_min finite, γ_pull in [0, 1]."""
    if not (math.isfinite(pull_min_deg) and 0.0 <= gamma_pull <= 1.0):
        raise ValueError(f"pull_min_deg must be finite and gamma_pull in [0, 1], got {pull_min_deg}, {gamma_pull}")
    return float(pull_min_deg), float(gamma_pull)


def _pull_gate(gamma: float, pull_deg: float, pull_min_deg: float, gamma_pull: float) -> float:
    """max(γ, γ_pull) where a full update pulls the heading the right way by more than p_min (°), else 0."""
    return max(gamma, gamma_pull) if pull_deg > pull_min_deg else 0.0


class StillPullTrust(AdaptiveTrust):
    """kf_adaptive's γ where the field is clean or the magnetometer pulls toward the still anchor by more
    than ``pull_min_deg`` (there at least ``gamma_pull``), else 0; reads the extended observation."""

    name = "kf_still"
    PARAM_BOUNDS = {
        "sigma_mag_ut": (0.1, 20.0),
        "sigma_dip_deg": (0.5, 45.0),
        "pull_min_deg": (-5.0, 5.0),
        "gamma_pull": (0.0, 1.0),
    }
    NEEDS = ("norm_dev", "dip_dev", "t_anchor", "pull_still")
    #: the observation it reads: the base features and the two memory features it needs
    FEATURES = (*FEATURES.names, "t_anchor", "pull_still")

    def __init__(
        self,
        sigma_mag_ut: float = TH_MAG,
        sigma_dip_deg: float = TH_DIP,
        pull_min_deg: float = 0.0,
        gamma_pull: float = 0.0,
        features: Sequence[str] | None = None,
    ):
        super().__init__(sigma_mag_ut, sigma_dip_deg, self.FEATURES if features is None else features)
        self.pull_min_deg, self.gamma_pull = _check_pull(pull_min_deg, gamma_pull)

    def weight(self, obs: np.ndarray) -> float:
        gamma = super().weight(obs)
        if float(obs[self._ix["t_anchor"]]) <= 0.0:  # clean now: the anchor is this sample
            return gamma
        return _pull_gate(gamma, float(obs[self._ix["pull_still"]]), self.pull_min_deg, self.gamma_pull)


class PerpPullTrust(ModelTrust):
    """kf_model's γ where d_perp sees little heading (``perp_info`` < ``info_min``); elsewhere that γ where the
    magnetometer pulls against d_perp's error by more than ``pull_min_deg`` (there at least ``gamma_pull``), else 0;
    reads the extended observation."""

    name = "kf_perp"
    PARAM_BOUNDS = {
        "sigma_dist_ut": (0.1, 20.0),
        "pull_min_deg": (-5.0, 5.0),
        "gamma_pull": (0.0, 1.0),
        "info_min": (0.0, 1.0),
    }
    NEEDS = ("model_dist", "pull_perp", "perp_info")
    #: the observation it reads: the base features and the two memory features it needs
    FEATURES = (*FEATURES.names, "pull_perp", "perp_info")

    def __init__(
        self,
        sigma_dist_ut: float = TH_MAG,
        pull_min_deg: float = 0.0,
        gamma_pull: float = 0.0,
        info_min: float = 0.0,
        features: Sequence[str] | None = None,
    ):
        super().__init__(sigma_dist_ut, self.FEATURES if features is None else features)
        self.pull_min_deg, self.gamma_pull = _check_pull(pull_min_deg, gamma_pull)
        if not 0.0 <= info_min <= 1.0:
            raise ValueError(f"info_min must be in [0, 1], got {info_min}")
        self.info_min = float(info_min)

    def weight(self, obs: np.ndarray) -> float:
        gamma = super().weight(obs)
        if float(obs[self._ix["perp_info"]]) < self.info_min:  # d_perp sees too little heading to judge
            return gamma
        return _pull_gate(gamma, float(obs[self._ix["pull_perp"]]), self.pull_min_deg, self.gamma_pull)


RULES: dict[str, type[KalmanRule]] = {
    "kf_constant": ConstantTrust,
    "kf_gate": GateTrust,
    "kf_adaptive": AdaptiveTrust,
    "kf_model": ModelTrust,
    "kf_still": StillPullTrust,
    "kf_perp": PerpPullTrust,
}


#: MagKalman-v0 options for a hand-moved board, found on the BROAD recordings (issue 17's probe): the
#: survey's σ_acc = 0.02 m/s² with the 0.08 m/s² accelerometer gate suits a gimbal turning about its centre,
#: but a board moved by hand has 1–3 m/s² RMS of linear and centripetal acceleration; the gate then passes
#: samples with |a| ≈ g pointing the wrong way, and the tiny σ_acc gives them a gain near 1, tilting the
#: estimate, and the magnetometer update (which needs the tilt) follows it. With σ_acc = 0.5 m/s² and no
#: gate, the accelerometer corrects only the slow tilt drift.
HAND_MOVED_OPTIONS = {"sigma_acc": 0.5, "th_acc": math.inf}
#: The suffix of the rules run with :data:`HAND_MOVED_OPTIONS` and the gyro de-biased at rest.
HAND_SUFFIX = "_hand"


def debias_at_rest(trial: Trial) -> Trial:
    """``trial`` with the gyro's mean over its initial rest (``magenv.recordings.initial_rest``, rad/s)
    subtracted — the bias initialisation at rest that MagKalman-v0's filter (no bias state) lacks. A trial
    with under 1 s of initial rest is returned as it is. The rest lies before any scored sample of BROAD."""
    rest = initial_rest(trial.gyr, trial.rate)
    if rest.stop - rest.start < trial.rate:
        return trial
    return dataclasses.replace(trial, gyr=trial.gyr - trial.gyr[rest].mean(0), meta=dict(trial.meta))


def hand_moved(rule: KalmanRule) -> KalmanRule:
    """``rule`` set up for a hand-moved board: env options :data:`HAND_MOVED_OPTIONS` and its trials
    de-biased at rest (:func:`debias_at_rest`, applied by ``magenv.evaluation`` through ``prepare_trial``)."""
    rule.env_kwargs = {**rule.env_kwargs, **HAND_MOVED_OPTIONS}
    rule.prepare_trial = debias_at_rest
    return rule


def methods() -> dict:
    """Name → factory of the trust rules at their published / default values, for ``compare``."""
    return {
        "kf_nominal": ConstantTrust,
        "kf_gate": GateTrust,
        "kf_adaptive": AdaptiveTrust,
        "kf_model": ModelTrust,
        "kf_still": StillPullTrust,
        "kf_perp": PerpPullTrust,
    }
