"""``magenv/MagKalman-v0``: choose the Kalman gain of the magnetometer update (trust γ ∈ [0, 1]).

The env module owns the runner, the observation features and the reward of one
decision; the filter is ``magenv.filters.kalman_trust``.

:func:`advance` is the one kernel of the env: it fuses samples ``start:stop``
with the trust KF (``kalman_trust.run_k_kernel``, gain multiplier γ), keeps the
trust history and the interval's error sums against truth, then computes the
observation of the next sample j = ``stop``: it *peeks* at sample j — gyro
prediction and accelerometer update on copies of (q, P), then the
magnetometer innovation with γ = 0, so nothing is changed — which gives the
a-priori innovation, NIS, dip and heading std of exactly the sample the next
γ is applied to first.

The model-based feature ``model_dist`` is the magnetometer disturbance d̂
(µT, sensor frame) of the Gauss–Markov split of Ligorio & Sabatini 2015
(survey A.9–A.10, ``magenv.filters.kalman_model.vec_step1``), run on the
magnetometer alone. It depends on the sensors only, never on γ, so
:func:`model_disturbance` computes it once per trial at reset; row j uses
samples 0…j only (causal).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np
from numba import njit

from magenv.envs import KALMAN_ID, kalman_memory, lagged
from magenv.envs.batch import ROWS, BatchVectorEnv, trial_rows, window_rows
from magenv.envs.common import TrialRunner, TrustEnv, episode_view
from magenv.envs.features import DIP_SCALE_DEG, GYRO_SCALE, WINDOW, Feature, FeatureTable, clipper, deviations, document
from magenv.filters import kalman_trust as kt
from magenv.filters.kalman_model import C_A, C_B, VecParams, make_vec_params, vec_init, vec_step1
from magenv.filters.kalman_threshold import OK
from magenv.filters.kalman_trust import SIG
from magenv.filters.sensors import Sensors
from magenv.metrics import N_ERR, error_sums
from magenv.quaternion import GRAVITY
from magenv.trial import Trial

FIELD_SCALE_UT = 50.0  # µT: the unit of field_ref

FEATURES = FeatureTable(
    Feature("norm_dev", -1.0, 10.0, "fraction of m0", "field-norm deviation (‖m_j‖ − m0)/m0"),
    Feature(
        "dip_dev",
        -2.0,
        2.0,
        f"units of {DIP_SCALE_DEG:g}°",
        "(θ_j − θ0), θ_j the dip of m_j below the a-priori horizontal",
    ),
    Feature("gyro_norm", 0.0, 10.0, "units of 2π rad/s", "‖ω_j‖"),
    Feature("acc_dev", -1.0, 10.0, "fraction of g", "(‖a_j‖ − g)/g"),
    Feature("innov_norm", 0.0, 10.0, "fraction of m0", "‖ν_m,j‖, ν_m = q̂⁻ ⊗ m_j ⊗ q̂⁻* − h_ENU (a-priori innovation)"),
    Feature(
        "innov_east",
        -10.0,
        10.0,
        "m0·cos θ0 (≈ rad)",
        "east component of ν_m,j (≈ −heading correction of a full update)",
    ),
    Feature("log_nis", 0.0, 10.0, "decades", "log10(1 + ν_mᵀ S⁻¹ ν_m), NIS χ²₃-distributed if consistent"),
    Feature("heading_std", -4.0, 2.0, "decades of 1°", "log10 of the a-priori heading std sqrt(P_zz) at sample j"),
    Feature("trust_prev", 0.0, 1.0, "–", "γ applied in the last step (1 after reset: the TRIAD start uses m fully)"),
    *deviations("each with its own a-priori estimate"),
    Feature("acc_dev_max", 0.0, 10.0, "fraction of g", f"max of the absolute acc_dev over {WINDOW}"),
    Feature("gyro_norm_mean", 0.0, 10.0, "units of 2π rad/s", f"mean gyro_norm over {WINDOW}"),
    Feature("innov_norm_mean", 0.0, 10.0, "fraction of m0", f"mean innov_norm over {WINDOW}"),
    Feature("log_nis_mean", 0.0, 10.0, "decades", f"log10(1 + mean NIS over {WINDOW})"),
    Feature(
        "model_dist",
        0.0,
        10.0,
        "fraction of m0",
        "‖d̂_j‖, magnetometer disturbance of the model-based split (survey A.9–A.10, causal)",
    ),
    Feature("model_dist_max", 0.0, 10.0, "fraction of m0", f"max model_dist over {WINDOW}"),
    Feature(
        "field_ref",
        0.0,
        20.0,
        f"units of {FIELD_SCALE_UT:g} µT",
        "m0, the site's undisturbed field norm (constant per trial; not truth)",
    ),
)
F = FEATURES.ix  # named kernel indices
_LOW, _HIGH = FEATURES.low64, FEATURES.high64
LAGS = (8, 32)  # decisions: the memory of the extended observation
_CURRENT = (*FEATURES.features, *kalman_memory.EXTRA.features)
EXTENDED = lagged.extended_table(_CURRENT, LAGS)
_LAGS = np.array(LAGS, np.int64)


class Outputs(NamedTuple):
    """What :func:`advance` writes: per-sample histories (N rows) and the last step's sums and observation."""

    est: np.ndarray  # (N, 4) estimate after each sample, sensor → ENU (row 0: the TRIAD start; NaN not fused yet)
    sig: np.ndarray  # (N, NSIG) the filter's signals per sample (kalman_trust.SIGNALS)
    trust: np.ndarray  # (N,) γ applied to each sample (row 0: 1)
    err: np.ndarray  # (N_ERR,) error sums of the last step (magenv.metrics.E_*)
    feat: np.ndarray  # (len(FEATURES),) observation of the next sample j
    peek: np.ndarray  # (NSIG,) the a-priori signals of sample j

    @classmethod
    def empty(cls, n: int) -> Outputs:
        return cls(
            np.full((n, 4), np.nan),
            np.full((n, kt.NSIG), np.nan),
            np.full(n, np.nan),
            np.zeros(N_ERR),
            np.zeros(len(FEATURES)),
            np.zeros(kt.NSIG),
        )


_clip = clipper(FEATURES, neutral_nan=True)


@dataclass(frozen=True)
class Options(kt.Options):
    """The env's filter options, checked once: the trust KF's (``kalman_trust.Options``: σ's, accelerometer
    threshold, heading-only update) and the Gauss–Markov split of ``model_dist`` (:func:`make_model_params`)."""

    model_c_a: float = C_A
    model_c_b: float = C_B

    def __post_init__(self):
        probe = kt.make_params(46.0, 49.6, 1.0 / 256.0, self)  # ValueError / TypeError naming one
        make_model_params(probe, self.model_c_a, self.model_c_b)
        for f in fields(self):  # held as Python numbers (the checks take ints and numpy scalars too)
            value = getattr(self, f.name)
            object.__setattr__(self, f.name, bool(value) if f.name == "heading_only" else float(value))

    def params(self, trial: Trial | None = None) -> kt.Params:
        """The trust KF's parameters on ``trial``'s field and rate (None: a 46 µT, 49.6° field at 1 Hz, for the
        constants alone)."""
        field = (46.0, 49.6, 1.0) if trial is None else (trial.field_norm, trial.field_dip, trial.dt)
        return kt.make_params(*field, self)


def make_model_params(params: kt.Params, model_c_a=C_A, model_c_b=C_B, model_p0=1.0) -> VecParams:
    """The Gauss–Markov split of ``model_dist`` on the magnetometer (``kalman_model.make_vec_params``) with
    the trust KF's Δt and noise; ``model_c_a`` in [0, 1), ``model_c_b`` µT and ``model_p0`` µT² finite > 0."""
    return make_vec_params(
        params.dt,
        params.sigma_gyr,
        params.sigma_mag,
        model_c_a,
        model_c_b,
        model_p0,
        ("sigma_mag", "model_c_a", "model_c_b", "model_p0"),
    )


@njit(cache=True)
def model_disturbance(vp, sensors, out):
    """‖d̂‖ per sample (µT) of the magnetometer's reference/disturbance split (survey A.9–A.10) with
    ``vp`` (``kalman_model.VecParams``), initialised as ``ModelKF.run``. Writes ``out`` (N,); returns OK (−1)
    or the first bad sample."""
    gyr, mag = sensors.gyr, sensors.mag
    x, p = vec_init(vp, mag[0])
    lo = np.empty((6, 6))
    out[0] = 0.0
    for k in range(1, gyr.shape[0]):
        g0, g1 = gyr[k - 1], gyr[k]
        omega = (0.5 * (g0[0] + g1[0]), 0.5 * (g0[1] + g1[1]), 0.5 * (g0[2] + g1[2]))
        _, st = vec_step1(vp, x, p, omega, mag[k], lo)
        if st < 0:
            return k
        out[k] = np.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5])
    return OK


@njit(cache=True)
def advance(params, state, sensors, truth, mdist, out, gamma, start, stop):
    """Fuse samples ``start:stop`` (1 ≤ start ≤ stop ≤ N) at trust γ; then the observation of sample ``stop``.

    Args:
        params: ``kalman_trust.Params``. state: ``kalman_trust.State``, updated in place.
        sensors: ``magenv.filters.sensors.Sensors`` of the whole trial.
        truth: ``magenv.envs.common.Truth``, for the error sums only.
        mdist: (N,) model-based disturbance norm ‖d̂‖, µT (:func:`model_disturbance`).
        out: :class:`Outputs`; rows start:stop of the histories, ``err``, ``feat`` and ``peek`` written.
    Returns ``(status, repairs)``; status OK (−1) or the first sample that failed.
    """
    n = sensors.gyr.shape[0]
    status, repairs = kt.run_k_kernel(params, state, sensors, start, stop, gamma, out.est, out.sig)
    if status != OK:
        for k in range(N_ERR):
            out.err[k] = 0.0
        return status, repairs
    out.trust[start:stop] = gamma
    error_sums(out.est, truth.q_true, truth.dist, start, stop, out.err)  # against truth, as magenv.metrics
    # peek at the next sample: prediction + acc update + mag innovation, γ = 0, state unchanged
    if stop < n:
        gyr, acc, mag = sensors
        st = kt.peek1(params, state, gyr[stop - 1], gyr[stop], acc[stop], mag[stop], out.peek)
        if st < 0:
            return stop, repairs
        j = stop
    else:
        out.peek[:] = out.sig[n - 1]
        j = n - 1
    _features(params, sensors, mdist, out, start, stop, j)
    return OK, repairs


@njit(cache=True)
def _features(params, sensors, mdist, out, start, stop, j):
    """``out.feat`` of sample j from its a-priori signals ``out.peek`` and the window's signals."""
    gyr = sensors.gyr
    peek, sig, feat = out.peek, out.sig, out.feat
    m0 = params.m0
    hh = m0 * np.cos(params.dip0)
    nd = peek[SIG.mag_norm_dev] / m0
    dd = peek[SIG.dip_dev] / DIP_SCALE_DEG
    ad = peek[SIG.acc_norm_dev] / GRAVITY
    gn = np.sqrt(gyr[j, 0] ** 2 + gyr[j, 1] ** 2 + gyr[j, 2] ** 2) / GYRO_SCALE
    inn = peek[SIG.nu_norm] / m0
    md = mdist[j] / m0
    feat[F.norm_dev] = _clip(nd, F.norm_dev)
    feat[F.dip_dev] = _clip(dd, F.dip_dev)
    feat[F.gyro_norm] = _clip(gn, F.gyro_norm)
    feat[F.acc_dev] = _clip(ad, F.acc_dev)
    feat[F.innov_norm] = _clip(inn, F.innov_norm)
    feat[F.innov_east] = _clip(peek[SIG.nu_e] / hh, F.innov_east) if hh > 0.0 else 0.0
    feat[F.log_nis] = _clip(np.log10(1.0 + peek[SIG.nis]), F.log_nis)
    feat[F.heading_std] = _clip(np.log10(max(np.rad2deg(peek[SIG.heading_std]), 1e-12)), F.heading_std)
    feat[F.trust_prev] = out.trust[stop - 1]
    # window: samples start … stop−1 just fused, plus sample j
    nmax, nsum = abs(nd), nd
    dmax = abs(dd) if dd == dd else 0.0
    amax, gsum = abs(ad), gn
    isum, nis_sum, mmax = inn, peek[SIG.nis], md
    for i in range(start, stop):
        ndi = sig[i, SIG.mag_norm_dev] / m0
        nmax = max(nmax, abs(ndi))
        nsum += ndi
        ddi = sig[i, SIG.dip_dev] / DIP_SCALE_DEG
        if ddi == ddi:
            dmax = max(dmax, abs(ddi))
        amax = max(amax, abs(sig[i, SIG.acc_norm_dev] / GRAVITY))
        gsum += np.sqrt(gyr[i, 0] ** 2 + gyr[i, 1] ** 2 + gyr[i, 2] ** 2) / GYRO_SCALE
        isum += sig[i, SIG.nu_norm] / m0
        nis_sum += sig[i, SIG.nis]
        mmax = max(mmax, mdist[i] / m0)
    cnt = stop - start + 1
    feat[F.norm_dev_max] = _clip(nmax, F.norm_dev_max)
    feat[F.norm_dev_mean] = _clip(nsum / cnt, F.norm_dev_mean)
    feat[F.dip_dev_max] = _clip(dmax, F.dip_dev_max)
    feat[F.acc_dev_max] = _clip(amax, F.acc_dev_max)
    feat[F.gyro_norm_mean] = _clip(gsum / cnt, F.gyro_norm_mean)
    feat[F.innov_norm_mean] = _clip(isum / cnt, F.innov_norm_mean)
    feat[F.log_nis_mean] = _clip(np.log10(1.0 + nis_sum / cnt), F.log_nis_mean)
    feat[F.model_dist] = _clip(md, F.model_dist)
    feat[F.model_dist_max] = _clip(mmax, F.model_dist_max)
    feat[F.field_ref] = _clip(m0 / FIELD_SCALE_UT, F.field_ref)


@njit(cache=True)
def advance_extended(params, state, sensors, truth, mdist, out, gamma, start, stop, memory, rows, count, feat):
    """:func:`advance`, then the extended observation ``feat`` (len(EXTENDED)) of sample ``stop``.

    ``memory``: ``magenv.envs.kalman_memory.Memory`` (updated on the samples fused); ``rows``
    (max(LAGS) + 1, len(FEATURES) + len(EXTRA)): ring of the current features by decision; ``count`` (1,)
    int64: decisions so far (0 until the first step)."""
    status, repairs = advance(params, state, sensors, truth, mdist, out, gamma, start, stop)
    if status != OK:
        return status, repairs
    if stop > start:
        kalman_memory.update(params, sensors, mdist, out.est, out.sig, out.trust, out.peek, memory, start, stop)
    lagged.compose(out.feat, memory.value, rows, count, _LAGS, stop > start, feat)
    return status, repairs


def trial_disturbance(trial: Trial, params: kt.Params, model_c_a: float, model_c_b: float, model_p0: float = 1.0):
    """(N,) ‖d̂‖ of ``trial`` (:func:`model_disturbance`) with the Gauss–Markov parameters of the ``model_dist``
    feature and the filter's noise model ``params``; FilterError if the split fails."""
    model = make_model_params(params, model_c_a, model_c_b, model_p0)
    mdist = np.empty(trial.n)
    try:
        st = model_disturbance(model, Sensors.of(trial), mdist)
    except np.linalg.LinAlgError as exc:  # a covariance the noise model left singular
        raise kt.FilterError(f"model-based disturbance split of trial {trial.name!r}: {exc}") from None
    if st != OK:
        raise kt.FilterError(f"model-based disturbance split failed at sample {st} of trial {trial.name!r}")
    return mdist


class KalmanRunner(TrialRunner):
    """One trial under the trust KF, stepped k samples at a time (``advance(k, γ)``).

    Sample 0 initialises the filter (TRIAD on acc[0], mag[0], never truth);
    ``est[0]`` is that orientation and ``trust[0] = 1`` (the magnetometer sets
    the initial heading fully). Steps then fuse samples 1 … N−1; the observation
    of sample 1 is ready after construction.

    Args:
        trial: the Trial.
        params: ``kalman_trust.make_params``; None = survey defaults for the trial's site.
        model_c_a, model_c_b, model_p0: Gauss–Markov parameters of the ``model_dist`` feature
            (per-sample correlation, driving std µT, initial reference variance µT²).
        extended: ``feat`` is the EXTENDED observation (base, extra causal features, their lagged copies).
    """

    def __init__(
        self,
        trial: Trial,
        params: kt.Params | None = None,
        model_c_a: float = C_A,
        model_c_b: float = C_B,
        model_p0: float = 1.0,
        extended: bool = False,
    ):
        super().__init__(trial, first=1)
        self.params = kt.make_params(trial.field_norm, trial.field_dip, trial.dt) if params is None else params
        self.mdist = trial_disturbance(trial, self.params, model_c_a, model_c_b, model_p0)
        self.state = kt.init(self.params, trial.acc[0], trial.mag[0])
        self.out = Outputs.empty(trial.n)
        self.est, self.sig, self.trust = self.out.est, self.out.sig, self.out.trust
        self.err, self.feat = self.out.err, self.out.feat
        self.est[0] = self.state.q
        self.trust[0] = 1.0
        self.repairs = 0
        self._args = (self.params, self.state, self.sensors, self.truth, self.mdist, self.out)
        self.extended = bool(extended)
        if self.extended:
            self.memory = kalman_memory.Memory.start(self.state.q)
            rows = np.zeros((max(LAGS) + 1, len(_CURRENT)))
            self.feat = np.zeros(len(EXTENDED))
            self._start(advance_extended, 1.0, self.memory, rows, np.zeros(1, np.int64), self.feat)
        else:
            self._start(advance, 1.0)

    def _fuse(self, start: int, stop: int, gamma: float) -> None:
        status, repairs = self._advance(*self._args, gamma, start, stop, *self._more)
        if status != OK:
            raise kt.FilterError(
                f"trust KF: non-finite sample or covariance at sample {status} of trial "
                f"{self.trial.name!r} (trust {gamma})"
            )
        self.repairs += repairs


@document(kalman_memory.EXTRA, "{extended_table}")
@document(FEATURES)
class MagKalmanEnv(TrustEnv):
    """
    ## Description

    A magnetic/inertial sensor moves while magnets or iron disturb the field
    it measures. Its orientation is estimated by a multiplicative quaternion
    Kalman filter (``magenv.filters.kalman_trust``): the gyroscope predicts,
    the accelerometer corrects the tilt (skipped when | |a| − g | ≥ th_acc,
    survey A7), and the magnetometer corrects the heading with the gain

        δθ = γ · K ν_m,    P ← (I − γKH) P (I − γKH)ᵀ + γ² K R_m Kᵀ

    where ν_m is the earth-frame field innovation, K the Kalman gain (heading
    row only by default) and γ the agent's **trust**, set once every
    ``decision_every`` samples. γ = 1 is the nominal filter, γ = 0 ignores the
    magnetometer exactly (heading from the gyro alone); the Joseph form keeps
    P the covariance of the filter actually run, so its signals stay honest
    observations. Sample 0 initialises the filter (TRIAD on the first
    accelerometer and magnetometer sample); steps fuse samples 1 … N−1. The
    sensor stream and the true orientation are fixed at ``reset()`` (the
    policy changes the estimate, never the world).

    ## Action Space

    `Box(0, 1, (1,), float32)`: γ, the magnetometer trust (gain multiplier; 0
    = ignore the magnetometer, 1 = nominal Kalman gain). Finite values
    outside [0, 1] are **clipped** (``info["action_clipped"]`` says so);
    NaN/inf and any shape other than `(1,)` or `()` raise `ValueError`.

    ## Observation Space

    `Box(float32)`, one entry per selected feature (default: all, in this
    order). Truth never enters it. "Sample j" is the next sample to be fused —
    the one the chosen γ is applied to first — read before fusing: the filter
    *peeks* at it (gyro prediction and accelerometer update on a copy of the
    state, then the magnetometer innovation; nothing is changed), so the
    innovation, NIS, dip and heading std are the a-priori ones of sample j.
    m0 and θ0 are the trial's undisturbed field norm and dip
    (``Trial.field_norm``, ``Trial.field_dip``); g = 9.81 m/s². The window is
    the samples fused in the last step plus sample j. Every value is clipped
    to its range (NaN, e.g. from a zero field, reads 0).

    {observation_table}

    With ``features="extended"`` (``EXTENDED``, 129 features) the observation
    is these 19, then the extra causal features below
    (``magenv.envs.kalman_memory``: signed mag headings and their EMAs, a
    gyro-only anchor re-set on clean samples and the heading the magnetometer
    added since, smoothed norm, dip and disturbance trends, the still anchor,
    the heading error seen across the disturbance's direction), then the
    copies of all 43 as they were 8 and 32 decisions earlier (``NAME_lag8``,
    ``NAME_lag32``: the memory). They are computed from the sensors, the
    filter's signals and estimates — never truth.

    {extended_table}

    Physical values are recoverable: m0 = 50·obs[18] µT, ‖m_j‖ − m0 = m0·obs[0]
    µT, dip deviation = 90·obs[1] degrees, NIS = 10^obs[6] − 1, ‖d̂_j‖ =
    m0·obs[16] µT
    (``magenv.baselines.kalman_policies`` relies on this). ``model_dist`` comes from
    a Gauss–Markov reference/disturbance Kalman filter on the magnetometer
    alone (Ligorio & Sabatini 2015, parameters ``model_c_a``, ``model_c_b``),
    which depends on the sensors only, so it is computed once per trial at
    reset; row j uses samples 0 … j only.

    ## Rewards

    Minus the mean total orientation error Δθ = 2·acos(|q_e,0|), degrees, over
    the samples fused in the step (those with truth; 0 if none has truth).

    ## Starting State

    A trial is drawn at ``reset``: from the scenario with a trial seed drawn
    from ``self.np_random`` (``reset(seed=s)`` → the same trial and the same
    episode, bit for bit), at random from the given Trials, or the Trial in
    ``options={"trial": trial}``. The filter starts from TRIAD on sample 0
    (never truth) with P = p0·I (5° per axis).

    ## Episode End

    Never terminated. Truncated when the trial's samples (or the first
    ``episode_seconds`` of them) are used up; the last step may fuse fewer
    than ``decision_every`` samples. An episode has ⌈(N − 1)/k⌉ steps.

    ## Arguments

    - `scenario` (default `"random"`): a name from ``magenv.scenarios.scenario_names()`` or a comma
      list of names (a mixture), trial seeds drawn at or above ``magenv.seeding.HELD_OUT_BELOW``,
      `"recording:PATH"`, a Trial or a list of Trials.
    - `decision_every` (default 8): samples fused per step (k); 1 = a γ per sample.
    - `episode_seconds` (default None): use only the first seconds of each trial; None = whole trial.
    - `features` (default None = the 19 above): names of the observation features to keep, in the given
      order, or `"extended"` for the extended observation (all 120; today's 19 stay the default).
    - `sigma_gyr`, `sigma_acc`, `sigma_mag` (defaults 0.5 °/s in rad/s, 0.02 m/s², 0.15 µT: the
      survey's sensor noise): the filter's noise model.
    - `th_acc` (default 0.08 m/s², Table A1): accelerometer gate; ``math.inf`` disables it.
    - `heading_only` (default True): the magnetometer corrects the heading only (Schmidt gain).
    - `model_c_a`, `model_c_b` (defaults 0.1, 1 µT: the survey's): Gauss–Markov parameters of
      the ``model_dist`` feature.
    - `scenario_kwargs` (default None): overrides passed to ``magenv.scenarios.make_trial``.
    - `prefetch` (default False): simulate the next reset's trial meanwhile in a worker process
      (same trials, bit for bit; hides the reset cost when a core is free). ``close()`` stops it.

    `info` of each step: `t` (s, last fused sample), `sample` (index after the step), `trust` (γ),
    `action_clipped`, `error_total` / `error_heading` / `error_inclination` (mean over the step, °,
    NaN without truth), `disturbance_norm` (mean true disturbance ‖·‖ over the step, µT, NaN if the
    trial has none), `q_est`, `q_true` (last fused sample), `repairs` (covariance repairs so far).
    The episode so far, per sample: ``env.unwrapped.estimate`` (N, 4), ``env.unwrapped.trust`` (N,)
    γ, ``env.unwrapped.lambdas`` (N,) = 1 − γ (the MagBlend convention, 0 = full trust, so
    ``magenv.evaluation``'s ``trust = 1 − λ`` is γ), ``env.unwrapped.signals`` (N, 13) the
    filter's signals (``kalman_trust.SIGNALS``); NaN where not fused yet; sample 0 is the start.

    ## Vectorised use

    ``gymnasium.make_vec("magenv/MagKalman-v0", num_envs=n, vectorization_mode="vector_entry_point")``
    gives ``MagKalmanVectorEnv`` (n envs in one process, next-step autoreset).

    ## Version History

    - v0 (the id stays ``-v0`` until the first release; dates are of the commits):
      2026-12-01 first version (the trust Kalman filter, γ per step), the batched vector env;
      2026-12-02 the extended observation on the shared lag memory; 2026-12-03 still-anchor features
      (``d_still``, ``pull_still``); 2026-12-05 ``d_perp`` (signed heading error across the disturbance);
      2026-12-07 kernels without allocation (per-trial RMSEs unchanged to 1e-9°).
    """

    action_symbol, action_key = "γ", "trust"
    observation = (FEATURES, EXTENDED)
    env_name = KALMAN_ID.split("/")[1]

    own_options = Options

    def __init__(self, **options):
        self._setup(**options)

    def _make_runner(self, trial: Trial) -> KalmanRunner:
        o = self.options
        return KalmanRunner(trial, o.params(trial), o.model_c_a, o.model_c_b, extended=self.extended)

    def _step_info(self, runner, start: int) -> dict:
        return {"repairs": runner.repairs}

    # ------------------------------------------------------------ evaluation access

    trust = episode_view("trust", "(N,) γ used per sample (sample 0, the TRIAD start, is 1; NaN where not fused yet).")

    @property
    def lambdas(self) -> np.ndarray:
        """(N,) 1 − γ: the MagBlend-style "IMU weight" view of the trust, for ``magenv.evaluation``."""
        return 1.0 - self._need_reset().trust

    signals = episode_view(
        "sig", "(N, 13) the filter's per-sample signals, columns ``kalman_trust.SIGNALS`` (NaN where not fused)."
    )

    model_disturbance = episode_view(
        "mdist", "(N,) ‖d̂‖ of the model-based split, µT (the ``model_dist`` feature before scaling)."
    )


class Batch(NamedTuple):
    """The arrays of :class:`MagKalmanVectorEnv`'s kernel: N envs (leading axis N) on the store's rows."""

    sigma_gyr: float  # the noise model (kalman_trust.Params), the same for every env
    sigma_acc: float
    sigma_mag: float
    th_acc: float
    heading_only: bool
    g_ref: np.ndarray  # (3,)
    cov_floor: float
    p0: float
    dt: np.ndarray  # (N,) per env: sample interval, s …
    h_ref: np.ndarray  # (N, 3) … Earth field, µT …
    m0: np.ndarray  # (N,) … field norm, µT …
    dip0: np.ndarray  # (N,) … dip, rad
    q: np.ndarray  # (N, 4) estimates (kalman_trust.State)
    p: np.ndarray  # (N, 3, 3) covariances
    mdist: np.ndarray  # (M,) the store's rows of ‖d̂‖, µT (model_disturbance)
    gamma: np.ndarray  # (N,) γ of the step
    est: np.ndarray  # (N, k + 2, 4) scratch Outputs of the step's window (magenv.envs.batch.Window)
    sig: np.ndarray  # (N, k + 2, NSIG)
    trust: np.ndarray  # (N, k + 2)
    peek: np.ndarray  # (N, NSIG)
    repairs: np.ndarray  # (N,) covariance repairs of each episode so far


@njit(cache=True)
def _advance_env(b, s, i, w):
    """Env i of :class:`Batch` (``s``: ``magenv.envs.batch.Steps``) does its step: :func:`advance` on window ``w``;
    returns −1 (``OK``) or the window's sample where the filter failed."""
    params = kt.Params(
        b.dt[i], b.sigma_gyr, b.sigma_acc, b.sigma_mag, b.th_acc, b.heading_only, b.g_ref, b.h_ref[i], b.m0[i],
        b.dip0[i], b.cov_floor, b.p0,
    )  # fmt: skip
    sensors, truth = window_rows(s, w)
    out = Outputs(b.est[i], b.sig[i], b.trust[i], s.err[i], s.feat[i], b.peek[i])
    status, repairs = advance(
        params, kt.State(b.q[i], b.p[i]), sensors, truth, b.mdist[w.r0 : w.r1], out, b.gamma[i], w.start, w.stop
    )
    if status == OK:
        b.repairs[i] += repairs
    return status


class MagKalmanVectorEnv(BatchVectorEnv):
    """``num_envs`` MagKalman envs advanced together: one numba call per ``step`` fuses every env's k samples.

    Registered as the ``vector_entry_point`` of ``magenv/MagKalman-v0`` (``gymnasium.make_vec(…,
    vectorization_mode="vector_entry_point")`` with the single env's arguments). Sub-env i is the single env
    seeded s + i bit for bit; seeding, autoreset and ``infos`` (with ``trust``, ``repairs``): see
    ``magenv.envs.batch.BatchVectorEnv``. A filter failure raises ``FilterError`` naming the env.
    """

    env_class = MagKalmanEnv
    features = FEATURES
    channels = {**ROWS, "mdist": ((), float)}
    advance_env = _advance_env
    first = 1
    idle_action = 1.0

    def _alloc(self, n: int) -> None:
        self.params = self.template.options.params()  # the env-wide constants
        rows = self.k_steps + 2
        self.dt, self.h_ref, self.m0, self.dip0 = np.ones(n), np.zeros((n, 3)), np.ones(n), np.zeros(n)
        self.q, self.p = np.zeros((n, 4)), np.zeros((n, 3, 3))
        self.scratch = Outputs(
            np.zeros((n, rows, 4)), np.zeros((n, rows, kt.NSIG)), np.zeros((n, rows)), self.err, self.feat,
            np.zeros((n, kt.NSIG)),
        )  # fmt: skip
        self.repairs = np.zeros(n, np.int64)

    def _prepare(self, trial: Trial):
        env = self.template
        o = env.options
        params = o.params(trial)
        mdist = trial_disturbance(trial, params, o.model_c_a, o.model_c_b)
        return {**trial_rows(trial), "mdist": mdist}, (params, kt.init(params, trial.acc[0], trial.mag[0]))

    def _start(self, i: int, description) -> None:
        params, state = description
        self.dt[i], self.h_ref[i], self.m0[i], self.dip0[i] = params.dt, params.h_ref, params.m0, params.dip0
        self.q[i], self.p[i] = state.q, state.p
        self.scratch.trust[i, 0] = 1.0  # sample 0, the TRIAD start, uses the magnetometer fully
        self.repairs[i] = 0

    def _step_info(self) -> dict:
        return {"repairs": self.repairs.copy()}

    def _failure(self, i: int, sample: int) -> Exception:
        return kt.FilterError(
            f"trust KF: non-finite sample or covariance at sample {sample} of trial {self._names[i]!r} "
            f"(env {i}, trust {self.action[i]})"
        )

    def _batch(self) -> Batch:
        p, s = self.params, self.scratch
        return Batch(
            sigma_gyr=p.sigma_gyr, sigma_acc=p.sigma_acc, sigma_mag=p.sigma_mag, th_acc=p.th_acc,
            heading_only=p.heading_only, g_ref=p.g_ref, cov_floor=p.cov_floor, p0=p.p0, dt=self.dt, h_ref=self.h_ref,
            m0=self.m0, dip0=self.dip0, q=self.q, p=self.p, mdist=self.store.arrays["mdist"], gamma=self.action,
            est=s.est, sig=s.sig, trust=s.trust, peek=s.peek, repairs=self.repairs,
        )  # fmt: skip
