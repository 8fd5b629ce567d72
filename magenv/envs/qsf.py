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
from typing import Any, NamedTuple

import numpy as np
from gymnasium import spaces
from numba import njit

from magenv.checks import check_choice, check_mapping
from magenv.envs import QSF_ID, lagged, qsf_memory
from magenv.envs.batch import ROWS, BatchVectorEnv, trial_rows
from magenv.envs.common import TrialRunner, TrustEnv, action_array, episode_view
from magenv.envs.features import DIP_SCALE_DEG, GYRO_SCALE, Feature, FeatureTable, document
from magenv.filters import qsf
from magenv.filters.linalg import clip
from magenv.filters.qsf import SIGNAL
from magenv.metrics import N_ERR, error_sums
from magenv.quaternion import GRAVITY, rotate3
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
#: features="extended": FEATURES, the extra causal features of ``magenv.envs.qsf_memory`` and their copies
#: ``qsf_memory.LAGS`` decisions earlier
EXTENDED = lagged.extended_table((*FEATURES.features, *qsf_memory.EXTRA.features), qsf_memory.LAGS)
_LOW, _HIGH = FEATURES.low64, FEATURES.high64
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


RAD_TO_DEG = 180.0 / math.pi  # as math.degrees


@njit(cache=True, inline="always")
def _norm3(v):
    return np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@njit(cache=True, inline="always")
def observed(pos, n):
    """The sample an observation reports after fusing up to ``pos`` of ``n``: the next to fuse, the last once
    all are fused."""
    return pos if pos < n else n - 1


@njit(cache=True)
def _features(p, state, inputs, codes, spread, sig, site, trust_prev, pos, feat):
    """``feat`` of sample j = ``pos``, the next to fuse (the last sample once all are fused), and of the last
    fused sample (``sig[pos − 1]``; zeros before any). ``site``: (m0 µT, θ0 degrees) of the trial."""
    gyr, acc, mag = inputs.gyr, inputs.acc, inputs.mag
    row = feat.reshape((1, feat.shape[0]))
    feature_row(p.sigma_mag, state, gyr, acc, mag, codes, spread, observed(pos, gyr.shape[0]), sig, pos - 1, site,
                trust_prev, row, 0)  # fmt: skip


@njit(cache=True)
def feature_row(sigma_m, state, gyr, acc, mag, codes, spread, j, sig, last, site, trust_prev, feat, row):
    """:func:`_features` from rows read by index (a view costs two atomic reference counts): the sample's row
    j of the sensors, ``codes`` and ``spread``, the last fused sample's row ``last`` of ``sig`` (−1: none),
    written to ``feat[row]``; ``sigma_m``: the filter's σ_m (µT)."""
    m0, dip0 = site
    x = state.x
    q = (x[0], x[1], x[2], x[3])  # qsf.ORIENTATION
    active = state.period_active[0]
    mj = (mag[j, 0], mag[j, 1], mag[j, 2])
    m_e = rotate3(q, mj)
    nm = _norm3(mj)
    if nm > 0:
        s = -m_e[2] / nm
        s = s if s < 1.0 else 1.0  # max(-1, min(1, s)) as Python evaluates it
        s = s if s > -1.0 else -1.0
        dip = math.asin(s) * RAD_TO_DEG
    else:
        dip = dip0
    innov, nis, hstd = 0.0, 0.0, 0.0
    if last >= 0:
        innov, nis, hstd = sig[last, SIGNAL.innov_norm], sig[last, SIGNAL.nis], sig[last, SIGNAL.heading_std]
    f = feat
    f[row, F.spread] = spread[j]
    f[row, F.det_start] = 1.0 if codes[j] == qsf.MAG_START else 0.0
    f[row, F.det_keep] = 1.0 if codes[j] == qsf.MAG_KEEP else 0.0
    if active:
        d0, d1, d2 = state.mag_ref[0] - m_e[0], state.mag_ref[1] - m_e[1], state.mag_ref[2] - m_e[2]
        f[row, F.ref_mismatch] = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) / sigma_m
    else:
        f[row, F.ref_mismatch] = 0.0
    f[row, F.innov_norm] = innov / sigma_m
    f[row, F.log_nis] = math.log10(1.0 + nis)
    f[row, F.age] = (state.period_age[0] / AGE_SCALE_S) if active else 0.0
    f[row, F.active] = 1.0 if active else 0.0
    f[row, F.gyro_norm] = _norm3((gyr[j, 0], gyr[j, 1], gyr[j, 2])) / GYRO_SCALE
    f[row, F.acc_dev] = (_norm3((acc[j, 0], acc[j, 1], acc[j, 2])) - GRAVITY) / GRAVITY
    f[row, F.mag_norm_dev] = (nm - m0) / m0
    f[row, F.dip_dev] = (dip - dip0) / DIP_SCALE_DEG
    f[row, F.heading_std] = hstd
    f[row, F.trust_prev] = trust_prev
    for k in range(f.shape[1]):
        f[row, k] = clip(f[row, k], _LOW[k], _HIGH[k])


@njit(cache=True)
def fill_decision(inputs, code, trust, start, stop):
    """``inputs.action`` and ``inputs.trust`` of samples start:stop for one decision: MAG_START starts a period
    at sample ``start`` and keeps it for the rest, MAG_KEEP keeps, MAG_NONE makes no magnetic update."""
    keep = qsf.MAG_NONE if code == qsf.MAG_NONE else qsf.MAG_KEEP
    for i in range(start, stop):
        inputs.action[i] = keep
        inputs.trust[i] = trust
    if code == qsf.MAG_START and stop > start:
        inputs.action[start] = qsf.MAG_START


@njit(cache=True)
def advance(p, state, inputs, out, detected, truth, dt, site, code, trust, start, stop, err, feat):
    """Fuse samples ``start:stop`` with one decision and one trust, then the observation of sample ``stop``.

    Args:
        p, state, inputs, out: ``qsf.Params``, ``State`` (updated in place), ``Inputs`` (its ``action`` and
            ``trust`` rows start:stop written), ``Outputs`` (rows start:stop written).
        detected: (codes (N,) int8, spread (N,) in units of th_spread) of the trial's QSF detector.
        truth: ``magenv.envs.common.Truth``, for the error sums only. dt: s. site: (m0 µT, θ0 degrees).
        code: MAG_START starts a period at sample ``start`` and keeps it for the rest, MAG_KEEP keeps,
            MAG_NONE makes no magnetic update (and ends any period); ``trust`` ∈ [0, 1] scales every magnetic gain.
        err: (N_ERR,) set to the error sums; feat: set to the observation of sample ``stop``.
    Returns ``(bad, repairs)`` of ``qsf.run_kernel`` (bad −1: every sample fused).
    """
    fill_decision(inputs, code, trust, start, stop)
    bad, repairs = qsf.run_kernel(p, state, inputs, dt, start, stop, out)
    if bad >= 0:
        return bad, repairs
    error_sums(out.q, truth.q_true, truth.dist, start, stop, err)
    _features(p, state, inputs, detected[0], detected[1], out.sig, site, trust, stop, feat)
    return bad, repairs


class QSFRunner(TrialRunner):
    """One trial under MAGYQ / Delay MAGYQ with per-step decisions (the ``MagQSF-v0`` runner), stepped through
    the kernel :func:`advance`.

    Args:
        trial: the trial (any sensor trial).
        variant: "delay_magyq" or "magyq".
        detector: the QSF detector whose codes and spread the features report.
        init: the start, ``magenv.filters.qsf.initial_orientation`` ("auto", "triad" or "truth").
        filter_kwargs: keywords of ``magenv.filters.qsf.make_params``.
        extended: ``feat`` is the EXTENDED observation (base, extra causal features, their lagged copies).

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
        extended: bool = False,
    ):
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        super().__init__(trial)
        self.params, self.detected, self.state = episode_start(trial, variant, detector, init, filter_kwargs)
        self.detector = detector or qsf.QSFDetector()
        self.codes, self.spread = self.detected
        n = trial.n
        self.inputs = qsf.Inputs(trial.gyr, trial.acc, trial.mag, np.zeros(n, np.int8), np.zeros(n))
        self.out = qsf.Outputs.empty(n)
        self.est = self.out.q
        self.err = np.zeros(N_ERR)
        self.trust_prev = 0.0
        self.feat = np.zeros(len(FEATURES))
        site = (trial.field_norm, trial.field_dip)
        self._args = (self.params, self.state, self.inputs, self.out, self.detected, self.truth, trial.dt, site)
        self._advance = self.compiled(advance, *self._args, 0, 0.0, 0, 0, self.err, self.feat)
        self._advance(*self._args, qsf.MAG_NONE, 0.0, 0, 0, self.err, self.feat)  # the observation of sample 0
        self._base = self.feat
        self.extended = bool(extended)
        if self.extended:
            self.memory = qsf_memory.Memory.start(self.state.x[qsf.ORIENTATION])
            self._ring = lagged.ring(qsf_memory.LAGS, len(FEATURES) + len(qsf_memory.EXTRA))
            self.feat = np.zeros(len(EXTENDED))
            self._compose(0, 0)

    def _fuse(self, i0: int, i1: int, action) -> None:
        """``action`` = (code, trust) of :func:`advance`."""
        code, trust = action
        result = self._advance(*self._args, int(code), float(trust), i0, i1, self.err, self._base)
        qsf.checked(result, self.inputs)  # FilterError on a non-finite sample
        self.trust_prev = float(trust)
        if self.extended:
            self._compose(i0, i1)

    def _compose(self, start: int, stop: int) -> None:
        """The extended observation of sample ``stop`` after fusing start:stop."""
        site = (self.trial.field_norm, self.trial.field_dip)
        qsf_memory.update(
            self.params, self.state, self.inputs, self.out, self.spread, site, self.trial.dt, self.memory, start, stop
        )
        lagged.compose(self._base, self.memory.value, *self._ring, stop > start, self.feat)


def episode_start(trial: Trial, variant: str, detector, init: str, filter_kwargs: dict | None):
    """(params, (codes, spread), initial state) of an episode on ``trial``: the filter's parameters for the
    trial's site, the detector's codes and spread (in units of th_spread, 0 while its window fills) and the
    start (``qsf.initial_orientation``)."""
    params = qsf.make_params(trial.field_norm, trial.field_dip, mode=variant, **(filter_kwargs or {}))
    detector = detector or qsf.QSFDetector()
    codes, spread = detector.detect(trial.gyr, trial.mag, trial.rate)
    spread = np.nan_to_num(spread, nan=0.0) / detector.th_spread
    state = qsf.initial_state(qsf.initial_orientation(trial, init, params), trial.dt)
    return params, (codes, spread), state


@document(qsf_memory.EXTRA, "{extended_table}")
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

    With ``features="extended"`` (``EXTENDED``) the observation is those
    features, the extra causal features below (``magenv.envs.qsf_memory``,
    where the conventions are defined: signed mag and reference headings,
    gyro anchors, smoothed field and motion statistics), and copies of both
    10 and 40 decisions earlier (1 s and 4 s at k = 10):

    {extended_table}

    ## Rewards

    Minus the mean total orientation error (degrees) over the samples fused
    in the step that have truth (0 if none).

    ## Starting State

    A trial is drawn at ``reset`` (scenario + seed from ``self.np_random``,
    or from given Trials, or ``options={"trial": trial}``). The filter starts
    from TRIAD on the mean of the still samples at the start against the
    trial's Earth field (``init="triad"``, truth-free,
    ``magenv.filters.qsf.still_start``) or, with ``init="truth"``, from the true
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
    - `features` (default None = all): names of the features to keep, in order, or `"extended"` for
      the extended observation (all of the table below; the 14 above stay the default).
    - `detector` (default ``qsf.QSFDetector()``): a ``QSFDetector`` or a mapping of its thresholds
      (``window_s``, ``th_spread``, ``th_drift``, ``max_period_s``), e.g. from a YAML config.
    - `filter_kwargs`: keywords of ``qsf.make_params`` (noise levels, ``max_age_s`` …).
    - `scenario_kwargs`: overrides for the scenario's ``make_trial``.

    `info` of each step: `t`, `sample`, `decision` (name), `trust`, `action_clipped`,
    `error_total` / `error_heading` / `error_inclination` (means over the step, °), `disturbance_norm`
    (mean true ‖field − Earth field‖ at the sensor, µT; NaN if unknown), `qsf_active`, `q_est`, `q_true`.
    Per-sample arrays of the episode so far: ``estimate`` (N, 4), ``signals`` (N, N_SIGNALS), ``trust`` (N,).

    ## Version History

    - v0 (the id stays ``-v0`` until the first release; dates are of the commits):
      2026-12-01 first version (the hand-held QSF filters, trust of each quasi-static period), the batched vector
      env; 2026-12-02 ``features="extended"``; 2026-12-07 kernels rewritten without allocation (per-trial RMSEs
      unchanged to 1e-9°), the batched vector env's filters in lock-step (``magenv.envs.qsf_lockstep``; the same
      numbers bit for bit).
    """

    observation = (FEATURES, EXTENDED)
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
        trial_pool=None,
        render_mode: str | None = None,
    ):
        check_choice("variant", variant, VARIANTS)
        check_choice("init", init, qsf.INITS)
        filter_kwargs = check_mapping("filter_kwargs", filter_kwargs)
        self._setup(
            scenario=scenario, decision_every=decision_every, episode_seconds=episode_seconds, render_mode=render_mode,
            scenario_kwargs=scenario_kwargs, features=features, trial_pool=trial_pool,
        )  # fmt: skip
        self.action_space = spaces.Box(
            np.array([-1.0, 0.0], np.float32), np.array([1.0, 1.0], np.float32), dtype=np.float32
        )
        self.variant, self.init = variant, init
        if isinstance(detector, dict):
            detector = qsf.QSFDetector(**detector)
        elif detector is not None and not isinstance(detector, qsf.QSFDetector):
            raise TypeError(f"detector must be a QSFDetector or a mapping of its thresholds, got {detector!r}")
        self.detector = detector or qsf.QSFDetector()
        self.filter_kwargs: dict[str, Any] = filter_kwargs
        qsf.make_params(50.0, 60.0, mode=variant, **self.filter_kwargs)  # bad keywords fail here, not at reset

    def _make_runner(self, trial: Trial) -> QSFRunner:
        return QSFRunner(trial, self.variant, self.detector, self.init, self.filter_kwargs, self.extended)

    def _decode(self, action) -> tuple[tuple[int, float], dict]:
        code, trust, clipped = decode_action(action)
        return (code, trust), {"decision": DECISIONS[code], "trust": trust, "action_clipped": clipped}

    def _step_info(self, runner, start: int) -> dict:
        return {"qsf_active": bool(runner.state.period_active[0])}

    # ------------------------------------------------------------ evaluation access

    signals = episode_view(
        "out.sig", "(N, N_SIGNALS) per-sample filter signals (``qsf.SIGNALS``), zeros where not fused yet."
    )

    @property
    def trust(self) -> np.ndarray:
        """(N,) trust of the magnetic update per sample (0 where none ran or not fused yet)."""
        return self._need_reset().out.sig[:, SIGNAL.trust]


class Batch(NamedTuple):
    """The arrays of :class:`MagQSFVectorEnv`'s kernel: N envs (leading axis N) on the store's rows."""

    mode: int  # qsf.Params.mode, the same for every env
    update_reference: bool  # qsf.Params.update_reference
    pf: np.ndarray  # (N, 10) per env, the float fields of qsf.Params in order (sigma_gyr … th_acc, cov_floor,
    grav: np.ndarray  # (N, 3)                                                radial_eps, max_age_s, acc_adaptive)
    earth: np.ndarray  # (N, 3)
    dt: np.ndarray  # (N,) sample interval, s
    m0: np.ndarray  # (N,) the trial's field norm, µT
    dip0: np.ndarray  # (N,) … and dip, degrees
    x: np.ndarray  # (N_AUGMENTED, N) qsf.State … (x and cov with the env axis last: magenv.envs.qsf_lockstep)
    cov: np.ndarray  # (N_AUGMENTED, N_AUGMENTED, N)
    active: np.ndarray  # (N, 1) bool
    age: np.ndarray  # (N, 1)
    mag_t0: np.ndarray  # (N, 3)
    mag_ref: np.ndarray  # (N, 3)
    codes: np.ndarray  # (M,) int8 the store's rows of the detector's codes and spread
    spread: np.ndarray  # (M,)
    code: np.ndarray  # (N,) the step's decision (qsf.MAG_*)
    trust: np.ndarray  # (N,) the step's trust
    action_h: np.ndarray  # (N, k + 2) int8 scratch Inputs.action / trust of the step's window (batch.Window)
    trust_h: np.ndarray  # (N, k + 2)
    q_h: np.ndarray  # (N, k + 2, 4) scratch Outputs
    sig_h: np.ndarray  # (N, k + 2, N_SIGNALS)


class MagQSFVectorEnv(BatchVectorEnv):
    """``num_envs`` MagQSF envs advanced together: one numba call per ``step`` fuses every env's samples.

    The ``vector_entry_point`` of ``magenv/MagQSF-v0``, with the env's `(2,)` action: ``actions`` of shape
    ``(num_envs, 2)``. Sub-env i is the single env seeded s + i bit for bit; seeding, autoreset and ``infos``
    (with ``decision``, the ``qsf.MAG_*`` code, ``trust`` and ``qsf_active``): see
    ``magenv.envs.batch.BatchVectorEnv``. A filter failure raises ``FilterError`` naming the env.
    """

    env_class = MagQSFEnv
    features = FEATURES
    channels = {**ROWS, "codes": ((), np.int8), "spread": ((), float)}
    _floats = ("sigma_gyr", "sigma_bias_walk", "sigma_acc_bias_walk", "sigma_acc", "sigma_mag", "th_acc",
               "cov_floor", "radial_eps", "max_age_s", "acc_adaptive")  # fmt: skip

    @property
    def lockstep(self):
        """The batch kernels: every env's filter in lock-step (``magenv.envs.qsf_lockstep``, which imports this
        module's kernels)."""
        from magenv.envs import qsf_lockstep

        return qsf_lockstep.lockstep, qsf_lockstep.lockstep_threads

    def _alloc(self, n: int) -> None:
        env = self.template
        p = qsf.make_params(50.0, 60.0, mode=env.variant, **env.filter_kwargs)
        self.constants = (p.mode, p.update_reference)
        rows, na = self.k_steps + 2, qsf.N_AUGMENTED
        self.pf, self.grav, self.earth = np.ones((n, len(self._floats))), np.zeros((n, 3)), np.zeros((n, 3))
        self.dt, self.m0, self.dip0 = np.ones(n), np.ones(n), np.zeros(n)
        self.state = qsf.State(
            np.zeros((na, n)), np.zeros((na, na, n)), np.zeros((n, 1), np.bool_), np.zeros((n, 1)),
            np.zeros((n, 3)), np.zeros((n, 3)),
        )  # fmt: skip
        self.code, self.trust = np.zeros(n, np.int64), np.zeros(n)
        self.scratch = (
            np.zeros((n, rows), np.int8), np.zeros((n, rows)), np.zeros((n, rows, 4)),
            np.zeros((n, rows, qsf.N_SIGNALS)),
        )  # fmt: skip

    def _prepare(self, trial: Trial):
        env = self.template
        params, (codes, spread), state = episode_start(trial, env.variant, env.detector, env.init, env.filter_kwargs)
        return {**trial_rows(trial), "codes": codes, "spread": spread}, (
            params,
            state,
            float(trial.dt),
            trial.field_norm,
            trial.field_dip,
        )

    def _start(self, i: int, description) -> None:
        p, state, self.dt[i], self.m0[i], self.dip0[i] = description
        self.pf[i] = [getattr(p, name) for name in self._floats]
        self.grav[i], self.earth[i] = p.gravity, p.earth_field
        st = self.state
        st.x[:, i], st.cov[:, :, i] = state.x, state.cov  # env axis last
        for mine, theirs in zip(st[2:], state[2:]):
            mine[i] = theirs

    def _set_actions(self, values, stepping) -> dict:
        if values is None:
            self.code[:], self.trust[:] = qsf.MAG_NONE, 0.0
            return {}
        d = values[:, 0]
        code = np.where(d < -1.0 / 3.0, qsf.MAG_NONE, np.where(d < 1.0 / 3.0, qsf.MAG_KEEP, qsf.MAG_START))
        np.copyto(self.code, np.where(stepping, code, qsf.MAG_NONE))
        np.copyto(self.trust, np.where(stepping, values[:, 1], 0.0))
        return {"decision": self.code.copy(), "trust": self.trust.copy()}

    def _step_info(self) -> dict:
        return {"qsf_active": self.state.period_active[:, 0].copy()}

    def _failure(self, i: int, sample: int) -> Exception:
        return qsf.FilterError(
            f"QSF filter: non-finite sample or covariance at sample {sample} of trial {self._names[i]!r} (env {i})"
        )

    def _batch(self) -> Batch:
        a, st, (action_h, trust_h, q_h, sig_h) = self.store.arrays, self.state, self.scratch
        return Batch(
            mode=self.constants[0], update_reference=self.constants[1], pf=self.pf, grav=self.grav, earth=self.earth,
            dt=self.dt, m0=self.m0, dip0=self.dip0, x=st.x, cov=st.cov, active=st.period_active, age=st.period_age,
            mag_t0=st.mag_t0, mag_ref=st.mag_ref, codes=a["codes"], spread=a["spread"], code=self.code,
            trust=self.trust, action_h=action_h, trust_h=trust_h, q_h=q_h, sig_h=sig_h,
        )  # fmt: skip
