"""``magenv/MagQSF-v0``: decide when the magnetic field is quasi-static and how far to trust it (Delay MAGYQ).

The env module owns the runner, the observation features and the reward of one
decision; the filters and the QSF detector are ``magenv.filters.qsf``.
:class:`QSFRunner` holds one trial, the filter state and the detector's codes
and spread (computed once at reset: they depend on the sensors only, row j on
samples ≤ j). ``advance`` fuses the next samples with one decision (none /
start / keep) and one trust, sums the errors against truth
(``magenv.metrics.error_sums``) and computes the features of the next sample
j (read before it is fused).

Features are dimensionless so that one scale suits every site: field
quantities in units of the filter's magnetometer noise σ_m (µT) or of the
detector threshold, the dip deviation in units of 90°, the gyro in
revolutions per second (the heading std stays in rad).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from gymnasium import spaces

from magenv.checks import check_choice, check_mapping
from magenv.envs import QSF_ID
from magenv.envs.common import LoopVectorEnv, TrialRunner, TrustEnv, action_array
from magenv.envs.features import DIP_SCALE_DEG, GYRO_SCALE, Feature, FeatureTable, document
from magenv.filters import qsf
from magenv.filters.qsf import SIGNAL
from magenv.metrics import N_ERR, error_sums
from magenv.quaternion import GRAVITY, rotate1
from magenv.trial import Trial

AGE_SCALE_S = 10.0  # period age in units of 10 s
FEATURES = FeatureTable(
    Feature(
        "spread",
        0.0,
        100.0,
        "th_spread",
        "RMS spread of the gyro-frame field over the detector window (0 while it fills)",
    ),
    Feature("det_start", 0.0, 1.0, "0/1", "the detector would start a period at j"),
    Feature("det_keep", 0.0, 1.0, "0/1", "the detector would continue its period at j"),
    Feature("ref_mismatch", 0.0, 100.0, "σ_m", "‖m_ref − q̂ m_j q̂*‖ (0 without period)"),
    Feature("innov_norm", 0.0, 100.0, "σ_m", "‖δz‖ (eq. 9) of the last fused sample"),
    Feature("log_nis", 0.0, 10.0, "–", "log10(1 + NIS) of the last fused sample"),
    Feature("age", 0.0, 100.0, f"{AGE_SCALE_S:g} s", "time since the current period started (0 without period)"),
    Feature("active", 0.0, 1.0, "0/1", "a QSF period is active"),
    Feature("gyro_norm", 0.0, 10.0, "2π rad/s", "‖ω_j‖"),
    Feature("acc_dev", -1.0, 10.0, "–", "(‖a_j‖ − g)/g"),
    Feature("mag_norm_dev", -1.0, 20.0, "–", "(‖m_j‖ − m0)/m0"),
    Feature("dip_dev", -2.0, 2.0, f"{DIP_SCALE_DEG:g}°", "dip of q̂ m_j q̂* in the earth frame − θ0"),
    Feature("heading_std", 0.0, 10.0, "rad", "sqrt of the filter's heading variance"),
    Feature("trust_prev", 0.0, 1.0, "–", "trust applied in the last step (0 after reset)"),
)
F = FEATURES.ix  # named kernel indices
VARIANTS = ("delay_magyq", "magyq")
DECISIONS = ("none", "start", "keep")  # indexed by the qsf.MAG_* codes


def decode_action(action) -> tuple[int, float, bool]:
    """(magnetic action code, trust, clipped) of an action ``[a0, a1]`` (see MagQSFEnv docstring)."""
    what = "[decision in [-1, 1], trust in [0, 1]]"
    a = action_array(action, what)
    if a.shape != (2,):  # exactly (2,): a (2, 1) or (1, 2) array is refused, not flattened
        raise ValueError(f"action must have shape (2,) = {what}, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"action must be finite numbers {what}, got {a.tolist()}")
    clipped = bool(a[0] < -1 or a[0] > 1 or a[1] < 0 or a[1] > 1)
    d = min(1.0, max(-1.0, a[0]))
    trust = min(1.0, max(0.0, a[1]))
    code = qsf.MAG_NONE if d < -1.0 / 3.0 else (qsf.MAG_KEEP if d < 1.0 / 3.0 else qsf.MAG_START)
    return code, trust, clipped


class QSFRunner(TrialRunner):
    """One trial under MAGYQ / Delay MAGYQ with per-step decisions (the ``MagQSF-v0`` runner).

    Args:
        trial: the trial (any sensor trial).
        variant: "delay_magyq" or "magyq".
        detector: the QSF detector whose codes and spread the features report.
        init: the start, ``magenv.filters.qsf.initial_orientation`` ("auto", "triad" or "truth").
        filter_kwargs: keywords of ``magenv.filters.qsf.make_params``.

    Attributes as the other runners (``magenv.envs.common.TrustEnv``): ``feat``, ``err``, ``pos``,
    ``last_count``, ``has_dist``, ``est`` (N, 4), ``q_true``; and ``params``, ``state``, ``inputs``
    (whose ``action`` and ``trust`` hold the magnetic action code and the trust used per sample) and ``out``
    (``magenv.filters.qsf.Params``, ``State``, ``Inputs``, ``Outputs``: ``out.sig`` the filter's signals).
    """

    def __init__(
        self,
        trial: Trial,
        variant: str = "delay_magyq",
        detector: qsf.QSFDetector | None = None,
        init: str = "auto",
        filter_kwargs: dict | None = None,
    ):
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        super().__init__(trial)
        self.params = qsf.make_params(trial.field_norm, trial.field_dip, mode=variant, **(filter_kwargs or {}))
        self.detector = detector or qsf.QSFDetector()
        self.codes, spread = self.detector.detect(trial.gyr, trial.mag, trial.rate)
        self.spread = np.nan_to_num(spread, nan=0.0) / self.detector.th_spread
        self.state = qsf.initial_state(qsf.initial_orientation(trial, init, self.params), trial.dt)
        n = trial.n
        self.inputs = qsf.Inputs(trial.gyr, trial.acc, trial.mag, np.zeros(n, np.int8), np.zeros(n))
        self.out = qsf.Outputs.empty(n)
        self.est = self.out.q
        self.err = np.zeros(N_ERR)
        self.trust_prev = 0.0
        self.feat = np.zeros(len(FEATURES))
        self._args = (self.params, self.state, self.inputs, trial.dt)
        self._run = self.compiled(qsf.run_kernel, *self._args, 0, 0, self.out)
        self._features(0)

    def _fuse(self, i0: int, i1: int, action) -> None:
        """``action`` = (code, trust): ``code`` MAG_START starts a period at sample i0 and keeps it for the
        rest, MAG_KEEP keeps, MAG_NONE makes no magnetic update (and ends any period); ``trust`` ∈ [0, 1]
        scales every magnetic gain."""
        code, trust = action
        actions = self.inputs.action
        actions[i0:i1] = qsf.MAG_NONE if code == qsf.MAG_NONE else qsf.MAG_KEEP
        if code == qsf.MAG_START and i1 > i0:
            actions[i0] = qsf.MAG_START
        self.inputs.trust[i0:i1] = trust
        qsf.checked(self._run(*self._args, i0, i1, self.out), self.inputs)  # FilterError on a non-finite sample
        error_sums(self.est, self.truth.q_true, self.truth.dist, i0, i1, self.err)
        self.trust_prev = float(trust)
        self._features(i1)

    def _features(self, pos: int) -> None:
        """Features of sample j = ``pos``, the next to fuse (the last sample once all are fused), and of the
        last fused sample."""
        tr, state = self.trial, self.state
        j = min(pos, tr.n - 1)
        q = state.x[qsf.ORIENTATION]
        last = self.out.sig[pos - 1] if pos > 0 else np.zeros(qsf.N_SIGNALS)
        active = bool(state.period_active[0])
        m_e = rotate1(q, tr.mag[j])
        sigma_m = self.params.sigma_mag
        nm = float(np.linalg.norm(tr.mag[j]))
        dip = math.degrees(math.asin(max(-1.0, min(1.0, -m_e[2] / nm)))) if nm > 0 else tr.field_dip
        f = self.feat
        f[F.spread] = self.spread[j]
        f[F.det_start] = float(self.codes[j] == qsf.MAG_START)
        f[F.det_keep] = float(self.codes[j] == qsf.MAG_KEEP)
        f[F.ref_mismatch] = float(np.linalg.norm(state.mag_ref - m_e)) / sigma_m if active else 0.0
        f[F.innov_norm] = last[SIGNAL.innov_norm] / sigma_m
        f[F.log_nis] = math.log10(1.0 + last[SIGNAL.nis])
        f[F.age] = (state.period_age[0] / AGE_SCALE_S) if active else 0.0
        f[F.active] = float(active)
        f[F.gyro_norm] = float(np.linalg.norm(tr.gyr[j])) / GYRO_SCALE
        f[F.acc_dev] = (float(np.linalg.norm(tr.acc[j])) - GRAVITY) / GRAVITY
        f[F.mag_norm_dev] = (nm - tr.field_norm) / tr.field_norm
        f[F.dip_dev] = (dip - tr.field_dip) / DIP_SCALE_DEG
        f[F.heading_std] = last[SIGNAL.heading_std]
        f[F.trust_prev] = self.trust_prev
        np.clip(f, FEATURES.low, FEATURES.high, out=f)


@document(FEATURES)
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

    {observation_table}

    th_spread is the detector's threshold (µT), σ_m the filter's magnetometer
    noise (µT, default 0.1 m0); values are clipped to range. Features are
    computed by ``magenv.envs.qsf.QSFRunner``.

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
    Per-sample arrays of the episode so far: ``estimate`` (N, 4), ``signals`` (N, N_SIGNALS), ``trust`` (N,).

    ## Version History

    - v0: initial version.
    """

    env_name = QSF_ID.split("/")[1]

    def __init__(
        self,
        scenario="handheld_random",
        decision_every: int = 10,
        episode_seconds: float | None = None,
        variant: str = "delay_magyq",
        init: str = "auto",
        features: Sequence[str] | None = None,
        detector: qsf.QSFDetector | dict | None = None,
        filter_kwargs: dict | None = None,
        scenario_kwargs: dict | None = None,
        render_mode: str | None = None,
    ):
        check_choice("variant", variant, VARIANTS)
        check_choice("init", init, qsf.INITS)
        filter_kwargs = check_mapping("filter_kwargs", filter_kwargs)
        self._setup(
            scenario,
            decision_every,
            episode_seconds,
            render_mode,
            scenario_kwargs,
            features,
            FEATURES.names,
            FEATURES.low,
            FEATURES.high,
        )
        self.action_space = spaces.Box(
            np.array([-1.0, 0.0], np.float32), np.array([1.0, 1.0], np.float32), dtype=np.float32
        )
        self.variant, self.init = variant, init
        if isinstance(detector, dict):
            detector = qsf.QSFDetector(**detector)
        elif detector is not None and not isinstance(detector, qsf.QSFDetector):
            raise TypeError(f"detector must be a QSFDetector or a mapping of its thresholds, got {detector!r}")
        self.detector = detector or qsf.QSFDetector()
        self.filter_kwargs = filter_kwargs
        qsf.make_params(50.0, 60.0, mode=variant, **self.filter_kwargs)  # bad keywords fail here, not at reset

    def _make_runner(self, trial: Trial) -> QSFRunner:
        return QSFRunner(trial, self.variant, self.detector, self.init, self.filter_kwargs)

    def step(self, action):
        runner = self._step_runner()
        code, trust, clipped = decode_action(action)
        runner.advance(self.k_steps, (code, trust))
        return self._step_result(
            runner,
            {"decision": DECISIONS[code], "trust": trust, "action_clipped": clipped},
            {"qsf_active": bool(runner.state.period_active[0])},
        )

    # ------------------------------------------------------------ evaluation access

    @property
    def signals(self) -> np.ndarray:
        """(N, N_SIGNALS) per-sample filter signals (``qsf.SIGNALS``), zeros where not fused yet."""
        return self._need_reset().out.sig

    @property
    def trust(self) -> np.ndarray:
        """(N,) trust of the magnetic update per sample (0 where none ran or not fused yet)."""
        return self._need_reset().out.sig[:, SIGNAL.trust]


class MagQSFVectorEnv(LoopVectorEnv):
    """``num_envs`` copies of :class:`MagQSFEnv` in one process (``magenv.envs.common.LoopVectorEnv``, next-step
    autoreset), with the env's `(2,)` action: ``actions`` of shape ``(num_envs, 2)``."""

    env_class = MagQSFEnv
