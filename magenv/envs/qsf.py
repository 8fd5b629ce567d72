"""``magenv/MagQSF-v0``: decide when the magnetic field is quasi-static and how far to trust it (Delay MAGYQ)."""

from __future__ import annotations

from typing import Sequence

import numpy as np
from gymnasium import spaces

from magenv.envs import QSF_ID
from magenv.envs.common import LoopVectorEnv, TrustEnv
from magenv.filters import qsf
from magenv.filters.qsf_env import FEATURE_HIGH, FEATURE_LOW, FEATURE_NAMES, VARIANTS, QSFRunner
from magenv.trial import Trial

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


class MagQSFEnv(TrustEnv):
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

    | Num | Name           | Meaning                                                     | Unit / scale  | Min  | Max  |
    |-----|----------------|-------------------------------------------------------------|---------------|------|------|
    | 0   | `spread`       | RMS spread of the gyro-frame field over the detector window | th_spread     | 0    | 100  |
    | 1   | `det_start`    | the detector would start a period at j                      | 0/1           | 0    | 1    |
    | 2   | `det_keep`     | the detector would continue its period at j                 | 0/1           | 0    | 1    |
    | 3   | `ref_mismatch` | ‖m_ref − q̂ m_j q̂*‖ (0 without period)                       | σ_m           | 0    | 100  |
    | 4   | `innov_norm`   | ‖δz‖ (eq. 9) of the last fused sample                       | σ_m           | 0    | 100  |
    | 5   | `log_nis`      | log10(1 + NIS) of the last fused sample                     | –             | 0    | 10   |
    | 6   | `age`          | time since the current period started                       | 10 s          | 0    | 100  |
    | 7   | `active`       | a QSF period is active                                      | 0/1           | 0    | 1    |
    | 8   | `gyro_norm`    | ‖ω_j‖                                                       | 2π rad/s      | 0    | 10   |
    | 9   | `acc_dev`      | (‖a_j‖ − g)/g                                               | –             | -1   | 10   |
    | 10  | `mag_norm_dev` | (‖m_j‖ − m0)/m0                                             | –             | -1   | 20   |
    | 11  | `dip_dev`      | dip of q̂ m_j q̂* in the earth frame − θ0                     | 90°           | -2   | 2    |
    | 12  | `heading_std`  | sqrt of the filter's heading variance                       | rad           | 0    | 10   |
    | 13  | `trust_prev`   | trust applied in the last step (0 after reset)              | –             | 0    | 1    |

    th_spread is the detector's threshold (µT), σ_m the filter's magnetometer
    noise (µT, default 0.1 m0); values are clipped to range. Features are
    computed by ``magenv.filters.qsf_env.QSFRunner``.

    ## Rewards

    Minus the mean total orientation error (degrees) over the samples fused
    in the step that have truth (0 if none).

    ## Starting State

    A trial is drawn at ``reset`` (scenario + seed from ``self.np_random``,
    or from given Trials, or ``options={"trial": trial}``). The filter starts
    from TRIAD on the first sample against the trial's Earth field
    (``init="triad"``, truth-free) or, with ``init="truth"``, from the true
    first orientation as the paper did (§5.3; truth only sets the start).
    The default ``init="auto"`` follows the trial: truth for the hand-held
    scenarios (their walk starts in a disturbed field), TRIAD otherwise.
    MAGYQ has no absolute heading reference, so an initial heading error is
    never corrected.

    ## Episode End

    Never terminated; truncated when the trial (or its first
    ``episode_seconds``) is used up.

    ## Arguments

    - `scenario` (default `"handheld_random"`): any scenario name of ``magenv.scenarios`` (the
      hand-held world ``magenv.scenarios.handheld`` is the intended one) or a comma list of them,
      `"recording:PATH"`, a Trial or a list of Trials. Scenario trials use training seeds
      only (``magenv.seeding.draw_training_seed``).
    - `decision_every` (default 10): samples per step.
    - `episode_seconds` (default None): use only the first seconds of each trial.
    - `variant` (default `"delay_magyq"`): or `"magyq"`.
    - `init` (default `"auto"`): `"triad"`, `"truth"` or `"auto"` (``qsf.initial_orientation``).
    - `features` (default None = all): names of the features to keep, in order.
    - `detector` (default ``qsf.QSFDetector()``): a ``QSFDetector`` or a mapping of its thresholds
      (``window_s``, ``th_spread``, ``th_drift``, ``max_period_s``), e.g. from a YAML config.
    - `filter_kwargs`: keywords of ``qsf.make_params`` (noise levels, ``max_age_s`` …).
    - `scenario_kwargs`: overrides for the scenario's ``make_trial``.

    `info` of each step: `t`, `sample`, `decision` (name), `trust`, `action_clipped`,
    `error_total` / `error_heading` / `error_inclination` (means over the step, °), `disturbance_norm`
    (mean true ‖field − Earth field‖ at the sensor, µT; NaN if unknown), `qsf_active`, `q_est`, `q_true`.
    Per-sample arrays of the episode so far: ``estimate`` (N, 4), ``signals`` (N, NSIG), ``trust`` (N,).

    ## Version History

    - v0: initial version.
    """

    env_name = QSF_ID.split("/")[1]

    def __init__(self, scenario="handheld_random", decision_every: int = 10, episode_seconds: float | None = None,
                 variant: str = "delay_magyq", init: str = "auto", features: Sequence[str] | None = None,
                 detector: qsf.QSFDetector | dict | None = None, filter_kwargs: dict | None = None,
                 scenario_kwargs: dict | None = None, render_mode: str | None = None):
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        if init not in qsf.INITS:
            raise ValueError(f"init must be one of {qsf.INITS}, got {init!r}")
        self._setup(scenario, decision_every, episode_seconds, render_mode, scenario_kwargs, features,
                    FEATURE_NAMES, FEATURE_LOW, FEATURE_HIGH)
        self.action_space = spaces.Box(np.array([-1.0, 0.0], np.float32), np.array([1.0, 1.0], np.float32),
                                       dtype=np.float32)
        self.variant, self.init = variant, init
        if isinstance(detector, dict):
            detector = qsf.QSFDetector(**detector)
        elif detector is not None and not isinstance(detector, qsf.QSFDetector):
            raise TypeError(f"detector must be a QSFDetector or a mapping of its thresholds, got {detector!r}")
        self.detector = detector or qsf.QSFDetector()
        self.filter_kwargs = dict(filter_kwargs or {})
        qsf.make_params(50.0, 60.0, mode=variant, **self.filter_kwargs)  # bad keywords fail here, not at reset

    def _make_runner(self, trial: Trial) -> QSFRunner:
        return QSFRunner(trial, self.variant, self.detector, self.init, self.filter_kwargs)

    def step(self, action):
        runner = self._step_runner()
        code, trust, clipped = decode_action(action)
        runner.advance(self.k_steps, code, trust)
        return self._step_result(runner, {"decision": DECISIONS[code], "trust": trust, "action_clipped": clipped},
                                 {"qsf_active": bool(runner.ref[0] > 0.5)})

    # ------------------------------------------------------------ evaluation access

    @property
    def signals(self) -> np.ndarray:
        """(N, NSIG) per-sample filter signals (``qsf.SIGNALS``), zeros where not fused yet."""
        return self._need_reset().sig

    @property
    def trust(self) -> np.ndarray:
        """(N,) trust of the magnetic update per sample (0 where none ran or not fused yet)."""
        return self._need_reset().sig[:, qsf.SIGNALS.index("trust")]


class MagQSFVectorEnv(LoopVectorEnv):
    """``num_envs`` copies of :class:`MagQSFEnv` in one process (``magenv.envs.common.LoopVectorEnv``, next-step
    autoreset), with the env's `(2,)` action: ``actions`` of shape ``(num_envs, 2)``."""

    env_class = MagQSFEnv
