"""``magenv/MagQSF-v0``: decide when the magnetic field is quasi-static and how far to trust it (Delay MAGYQ)."""

from __future__ import annotations

import math
from typing import Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from magenv import metrics
from magenv import quaternion as quat
from magenv.envs.common import (
    RECORDING_PREFIX, LoopVectorEnv, TrialSource, check_env_args, cut_trial, select_features,
)
from magenv.filters import qsf
from magenv.quaternion import GRAVITY
from magenv.seeding import draw_training_seed
from magenv.trial import Trial

# (name, low, high); physical units, documented in the env docstring
FEATURES: tuple[tuple[str, float, float], ...] = (
    ("spread", 0.0, 100.0),  # detector statistic at sample j: RMS spread of the gyro-frame field, µT
    ("det_start", 0.0, 1.0),  # the detector would start a period at j
    ("det_keep", 0.0, 1.0),  # the detector would keep the period at j
    ("ref_mismatch", 0.0, 200.0),  # |m_ref − q̂ ⊗ m_j ⊗ q̂*| with the current estimate, µT (0 without period)
    ("innov_norm", 0.0, 200.0),  # |δz| of the last fused sample, µT
    ("nis", 0.0, 1e4),  # δzᵀS⁻¹δz of the last fused sample
    ("age", 0.0, 1e4),  # time since the current period started, s (0 without period)
    ("active", 0.0, 1.0),  # a QSF period is active
    ("gyro_norm", 0.0, 50.0),  # |ω_j|, rad/s
    ("acc_dev", -1.0, 10.0),  # (|a_j| − g)/g
    ("mag_norm_dev", -1.0, 20.0),  # (|m_j| − m0)/m0
    ("dip_dev", -180.0, 180.0),  # dip of m_j in the estimated earth frame − θ0, degrees
    ("heading_std", 0.0, 10.0),  # sqrt of the filter's heading variance, rad
    ("trust_prev", 0.0, 1.0),  # trust applied in the last step
)
FEATURE_NAMES = tuple(f[0] for f in FEATURES)
FEATURE_LOW = np.array([f[1] for f in FEATURES], np.float32)
FEATURE_HIGH = np.array([f[2] for f in FEATURES], np.float32)
DECISIONS = ("none", "start", "keep")  # indexed by the qsf.MAG_* codes


def decode_action(action) -> tuple[int, float, bool]:
    """(magnetic action code, trust, clipped) of an action ``[a0, a1]`` (see MagQSFEnv docstring)."""
    a = np.asarray(action, dtype=float).reshape(-1)
    if a.shape != (2,):
        raise ValueError(f"action must have shape (2,) = [decision in [-1, 1], trust in [0, 1]], got {np.shape(action)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"action must be finite, got {a}")
    clipped = bool(a[0] < -1 or a[0] > 1 or a[1] < 0 or a[1] > 1)
    d = min(1.0, max(-1.0, a[0]))
    trust = min(1.0, max(0.0, a[1]))
    code = qsf.MAG_NONE if d < -1.0 / 3.0 else (qsf.MAG_KEEP if d < 1.0 / 3.0 else qsf.MAG_START)
    return code, trust, clipped


class _HandheldSource:
    """Trials of hand-held scenarios (a name or a comma list) while they are not yet registered in
    ``magenv.scenarios``; draws like ``magenv.envs.common.TrialSource`` (training seeds only)."""

    def __init__(self, names, scenario_kwargs):
        self.names, self.scenario_kwargs = names, dict(scenario_kwargs or {})

    def draw(self, rng):
        from magenv import handheld_scenarios

        name = self.names[0] if len(self.names) == 1 else self.names[int(rng.integers(len(self.names)))]
        return handheld_scenarios.make_trial(name, draw_training_seed(rng), **self.scenario_kwargs)


def _source(scenario, scenario_kwargs):
    """A ``TrialSource`` for ``scenario``; hand-held names work whether or not ``magenv.scenarios`` knows them."""
    from magenv import handheld_scenarios

    if isinstance(scenario, str) and not scenario.startswith(RECORDING_PREFIX):
        names = [s.strip() for s in scenario.split(",")]
        if all(n in handheld_scenarios.SCENARIOS for n in names):
            return _HandheldSource(names, scenario_kwargs)
    return TrialSource(scenario, scenario_kwargs)


class MagQSFEnv(gym.Env):
    """
    ## Description

    A hand-held magnetic/inertial sensor is carried through an indoor field
    that is perturbed but, at times, steady (Combettes & Renaudin 2016). The
    estimate comes from the Delay MAGYQ filter (``magenv.filters.qsf``;
    ``variant="magyq"`` for plain MAGYQ): gyro prediction and accelerometer
    update always run; the magnetic update uses a *quasi-static field*
    reference taken at the start of a period (eq. 8). Once every
    ``decision_every`` samples the agent decides whether to start a new QSF
    period (new reference from the current estimate and field), keep the
    current reference, or make no magnetic update, and how much to trust the
    update (a gain multiplier, Joseph form keeps the covariance honest). The
    sensor stream and truth are fixed at ``reset()``.

    ## Action Space

    `Box([-1, 0], [1, 1], (2,), float32)`:
    `a[0]` the decision — `< −1/3` none (ends any period), `[−1/3, 1/3)` keep
    (no update if no period is active), `≥ 1/3` start a new period at the
    first sample of the step and keep it for the step's other samples;
    `a[1]` the trust γ ∈ [0, 1] applied to every magnetic update of the step.
    Finite values outside the box are clipped (``info["action_clipped"]``);
    NaN/inf or another shape raise `ValueError`. A period older than
    ``max_age_s`` is restarted whatever the action.

    ## Observation Space

    `Box(float32)`, one entry per selected feature (default all). "Sample j"
    is the next sample to be fused, read before fusing; q̂ is the current
    estimate. Truth never enters it. The detector (``qsf.QSFDetector``) works
    on the gyroscope and magnetometer only.

    | Num | Name           | Meaning                                                     | Unit   | Min  | Max  |
    |-----|----------------|-------------------------------------------------------------|--------|------|------|
    | 0   | `spread`       | RMS spread of the gyro-frame field over the detector window | µT     | 0    | 100  |
    | 1   | `det_start`    | the detector would start a period at j                      | 0/1    | 0    | 1    |
    | 2   | `det_keep`     | the detector would continue its period at j                 | 0/1    | 0    | 1    |
    | 3   | `ref_mismatch` | |m_ref − q̂ m_j q̂*| (0 without period)                       | µT     | 0    | 200  |
    | 4   | `innov_norm`   | |δz| (eq. 9) of the last fused sample                       | µT     | 0    | 200  |
    | 5   | `nis`          | normalised innovation squared of the last fused sample      | –      | 0    | 1e4  |
    | 6   | `age`          | time since the current period started                       | s      | 0    | 1e4  |
    | 7   | `active`       | a QSF period is active                                      | 0/1    | 0    | 1    |
    | 8   | `gyro_norm`    | |ω_j|                                                       | rad/s  | 0    | 50   |
    | 9   | `acc_dev`      | (|a_j| − g)/g                                               | –      | -1   | 10   |
    | 10  | `mag_norm_dev` | (|m_j| − m0)/m0                                             | –      | -1   | 20   |
    | 11  | `dip_dev`      | dip of m_j in the estimated earth frame − θ0                | °      | -180 | 180  |
    | 12  | `heading_std`  | sqrt of the filter's heading variance                       | rad    | 0    | 10   |
    | 13  | `trust_prev`   | trust applied in the last step                              | –      | 0    | 1    |

    ## Rewards

    Minus the mean total orientation error (degrees) over the samples fused
    in the step that have truth (0 if none).

    ## Starting State

    A trial is drawn at ``reset`` (scenario + seed from ``self.np_random``,
    or from given Trials, or ``options={"trial": trial}``). The filter starts
    from TRIAD on the first sample against the trial's Earth field
    (``init="ecompass"``, truth-free) or, with ``init="truth"``, from the true
    first orientation as the paper did (§5.3; truth only sets the start).
    MAGYQ has no absolute heading reference, so an initial heading error is
    never corrected.

    ## Episode End

    Never terminated; truncated when the trial (or its first
    ``episode_seconds``) is used up.

    ## Arguments

    - `scenario` (default `"handheld_random"`): a hand-held scenario name (or a comma list
      of them; ``magenv.handheld_scenarios``), any name (or comma list) of ``magenv.scenarios``,
      `"recording:PATH"`, a Trial or a list of Trials. Scenario trials use training seeds
      only (``magenv.seeding.draw_training_seed``).
    - `decision_every` (default 10): samples per step.
    - `episode_seconds` (default None): use only the first seconds of each trial.
    - `variant` (default `"delay_magyq"`): or `"magyq"`.
    - `init` (default `"ecompass"`): or `"truth"`.
    - `features` (default None = all): names of the features to keep, in order.
    - `detector` (default ``qsf.QSFDetector()``): its thresholds.
    - `filter_kwargs`: keywords of ``qsf.make_params`` (noise levels, ``max_age_s`` …).
    - `scenario_kwargs`: overrides for the scenario's ``make_trial``.

    `info` of each step: `t`, `sample`, `decision` (name), `trust`, `action_clipped`,
    `error_total`/`error_heading` (mean over the step, °), `qsf_active`, `q_est`, `q_true`.
    Per-sample arrays of the episode so far: ``estimate`` (N, 4), ``signals`` (N, NSIG).

    ## Version History

    - v0: initial version.
    """

    metadata = {"render_modes": []}

    def __init__(self, scenario="handheld_random", decision_every: int = 10, episode_seconds: float | None = None,
                 variant: str = "delay_magyq", init: str = "ecompass", features: Sequence[str] | None = None,
                 detector: qsf.QSFDetector | None = None, filter_kwargs: dict | None = None,
                 scenario_kwargs: dict | None = None, render_mode: str | None = None):
        self.k = check_env_args("MagQSF-v0", decision_every, episode_seconds, render_mode)
        if variant not in ("delay_magyq", "magyq"):
            raise ValueError(f"variant must be 'delay_magyq' or 'magyq', got {variant!r}")
        if init not in ("ecompass", "truth"):
            raise ValueError(f"init must be 'ecompass' or 'truth', got {init!r}")
        self._source = _source(scenario, scenario_kwargs)
        self.episode_seconds = episode_seconds
        self.variant, self.init = variant, init
        self.detector = detector or qsf.QSFDetector()
        self.filter_kwargs = dict(filter_kwargs or {})
        self.scenario_kwargs = dict(scenario_kwargs or {})
        self.features, self._idx, _, self.observation_space = select_features(features, FEATURE_NAMES, FEATURE_LOW,
                                                                              FEATURE_HIGH)
        self.action_space = spaces.Box(np.array([-1.0, 0.0], np.float32), np.array([1.0, 1.0], np.float32),
                                       dtype=np.float32)
        self.render_mode = None
        self.trial: Trial | None = None

    # ------------------------------------------------------------ trials

    def _draw_trial(self) -> Trial:
        return self._source.draw(self.np_random)

    # ------------------------------------------------------------ API

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        trial = options.get("trial")
        if trial is None:
            trial = self._draw_trial()
        elif not isinstance(trial, Trial):
            raise TypeError(f"options['trial'] must be a magenv.trial.Trial, got {type(trial).__name__}")
        trial = cut_trial(trial, self.episode_seconds)
        self.trial = trial
        self._params = qsf.make_params(trial.field_norm, trial.field_dip, mode=self.variant, **self.filter_kwargs)
        self._codes, self._spread = self.detector.detect(trial.gyr, trial.mag, trial.rate)
        if self.init == "truth":
            q0 = trial.q_true[0]
            if not np.all(np.isfinite(q0)):
                raise ValueError(f"trial {trial.name!r}: init='truth' needs a finite q_true[0]")
        else:
            q0 = qsf.triad_init(trial.acc[0], trial.mag[0], self._params)
        self._x, self._pa, self._ref = qsf.initial_state(q0, trial.dt)
        self._est = np.full((trial.n, 4), np.nan)
        self._sig = np.zeros((trial.n, qsf.NSIG))
        self._actions = np.zeros(trial.n, np.int8)
        self._trusts = np.zeros(trial.n)
        self._pos = 0
        self._trust_prev = 0.0
        self._h_earth = quat.earth_field(trial.field_norm, trial.field_dip)
        info = {"trial": trial.name, "rate": trial.rate, "n_samples": trial.n, "field_norm": trial.field_norm,
                "field_dip": trial.field_dip, "sample": 0}
        return self._obs(), info

    def _obs(self) -> np.ndarray:
        tr, j = self.trial, min(self._pos, self.trial.n - 1)
        q = self._x[0:4]
        last = self._sig[self._pos - 1] if self._pos > 0 else np.zeros(qsf.NSIG)
        active = self._ref[0] > 0.5
        m_e = quat.rotate1(q, tr.mag[j])
        mismatch = float(np.linalg.norm(self._ref[6:9] - m_e)) if active else 0.0
        nm = float(np.linalg.norm(tr.mag[j]))
        dip = math.degrees(math.asin(max(-1.0, min(1.0, -m_e[2] / nm)))) if nm > 0 else 0.0
        spread = self._spread[j]
        feat = np.array([
            0.0 if not np.isfinite(spread) else spread,
            float(self._codes[j] == qsf.MAG_START), float(self._codes[j] == qsf.MAG_KEEP),
            mismatch, last[1], last[2], self._ref[1] if active else 0.0, float(active),
            float(np.linalg.norm(tr.gyr[j])), (float(np.linalg.norm(tr.acc[j])) - GRAVITY) / GRAVITY,
            (nm - tr.field_norm) / tr.field_norm, dip - tr.field_dip, last[6], self._trust_prev,
        ])
        return np.clip(feat[self._idx], self.observation_space.low, self.observation_space.high).astype(np.float32)

    def step(self, action):
        if self.trial is None:
            raise RuntimeError("MagQSFEnv.step() called before reset(); call env.reset() first")
        tr = self.trial
        if self._pos >= tr.n:
            raise RuntimeError("MagQSFEnv.step() called after the episode was truncated; call env.reset()")
        code, trust, clipped = decode_action(action)
        i0, i1 = self._pos, min(tr.n, self._pos + self.k)
        self._actions[i0:i1] = qsf.MAG_KEEP if code != qsf.MAG_NONE else qsf.MAG_NONE
        if code == qsf.MAG_START:
            self._actions[i0] = qsf.MAG_START
        self._trusts[i0:i1] = trust
        qsf.run(self._x, self._pa, self._ref, tr.gyr, tr.acc, tr.mag, tr.dt, i0, i1, self._actions, self._trusts,
                self._params, self._est, self._sig)
        self._pos = i1
        self._trust_prev = trust
        q_err = metrics.error_quaternion(self._est[i0:i1], tr.q_true[i0:i1])
        tot = metrics.total_error(q_err)
        ok = np.isfinite(tot)
        if ok.any():
            total = float(tot[ok].mean())
            heading = float(metrics.heading_error(q_err)[ok].mean())
            reward = -total
        else:
            total = heading = math.nan
            reward = 0.0
        info = {"t": (i1 - 1) / tr.rate, "sample": i1, "decision": DECISIONS[code], "trust": trust,
                "action_clipped": clipped, "error_total": total, "error_heading": heading,
                "qsf_active": bool(self._ref[0] > 0.5), "q_est": self._est[i1 - 1].copy(),
                "q_true": tr.q_true[i1 - 1].copy()}
        return self._obs(), float(reward), False, i1 >= tr.n, info

    # ------------------------------------------------------------ evaluation access

    @property
    def estimate(self) -> np.ndarray:
        """(N, 4) per-sample estimate of the current episode (NaN rows not fused yet)."""
        if self.trial is None:
            raise RuntimeError("no episode yet; call env.reset() first")
        return self._est

    @property
    def signals(self) -> np.ndarray:
        """(N, NSIG) per-sample filter signals (``qsf.SIGNALS``), zeros where not fused yet."""
        if self.trial is None:
            raise RuntimeError("no episode yet; call env.reset() first")
        return self._sig


class DetectorPolicy:
    """The QSF detector as a policy of ``magenv/MagQSF-v0``: start where the detector starts, keep where it
    keeps (start if no period is active), else no update; trust 1. With ``decision_every=1`` it reproduces
    the ``delay_magyq`` estimator sample for sample."""

    env_id = "magenv/MagQSF-v0"

    def __init__(self, features: Sequence[str] | None = None):
        names = FEATURE_NAMES if features is None else tuple(features)
        for f in ("det_start", "det_keep", "active"):
            if f not in names:
                raise ValueError(f"DetectorPolicy needs the observation feature {f!r}")
        self._i = {f: names.index(f) for f in ("det_start", "det_keep", "active")}

    def reset(self) -> None:
        pass

    def __call__(self, obs) -> np.ndarray:
        obs = np.asarray(obs)
        if obs[self._i["det_start"]] > 0.5:
            d = 1.0
        elif obs[self._i["det_keep"]] > 0.5:
            d = 0.0 if obs[self._i["active"]] > 0.5 else 1.0
        else:
            d = -1.0
        return np.array([d, 1.0], np.float32)


class MagQSFVectorEnv(LoopVectorEnv):
    """``num_envs`` copies of :class:`MagQSFEnv` in one process (``magenv.envs.common.LoopVectorEnv``, next-step
    autoreset), with the env's `(2,)` action: ``actions`` of shape ``(num_envs, 2)``."""

    env_class = MagQSFEnv
