"""``magenv/MagVQF-v0``: choose how far VQF (Laidig & Seel 2023) trusts the magnetometer, window by window.

The filter is VQF as numba kernels (``magenv.filters.vqf``, bit for bit the
``vqf`` package's C++ filter at trust 1); the env sets the trust u of its
magnetometer gain before each window of ``decision_every`` samples. Trust →
gain (``magenv.filters.vqf.trust_gain``): k(u) = u·k₁, k₁ = 1 − exp(−T_s/τ_mag),
so u = 0 ignores the magnetometer exactly and u = 1 is VQF's own gain. Two VQF
rules stay as VQF has them, whatever u: its fast initial convergence (the gain
is at least 1/N at the N-th magnetometer sample until N·T_s exceeds the
current τ, so the first sample aligns the heading) and, with
``rejection="on"``, its disturbance rejection (k = 0 while a disturbance is
detected, for at most 60 s of rejection, then k/2). ``rejection="off"`` runs
VQF's detector with its rejection neutral (``mag_max_rejection_time`` = −1 s,
``mag_rejection_factor`` = 1): the estimate is VQF's without rejection, while
the detector's flag and field reference stay in the observation.

:func:`advance` is the one kernel of the env: it fuses samples ``start:stop``
(``magenv.filters.vqf.step``), keeps the per-sample histories, the error sums
against truth and the observation of the next sample j = ``stop``
(:func:`window_features`). With ``features="extended"`` :func:`advance_extended`
adds the extra causal features of :data:`EXTRA` (EMAs over VQF's internal
signals, :func:`update_memory`) and the memory (copies of the base and extra
features ``LAGS`` decisions earlier, ``magenv.envs.lagged``). :class:`VQFRunner`
steps one trial; :class:`MagVQFVectorEnv` steps N of them in one compiled call.

``backend="cpp"`` runs the ``vqf`` package's C++ class instead (``setTauMag``
with τ(u), ``updateBatch`` per window), the reference the kernels are tested
against; base features only.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from magenv.checks import check_bool, check_number
from magenv.envs import VQF_ID, lagged
from magenv.envs.batch import BatchVectorEnv, trial_rows, window_rows
from magenv.envs.blend import NORM_RATE, NORM_RATE_SCALE, dip_deg, mag_heading, sample_features
from magenv.envs.common import TrialRunner, TrustEnv, episode_view
from magenv.envs.features import DIP_SCALE_DEG, GYRO_SCALE, Feature, FeatureTable, clipper, deviations, document
from magenv.filters import vqf
from magenv.filters.rules import fan_lambda
from magenv.filters.vqf import P, S, tau_of_trust
from magenv.metrics import N_ERR, error_sums
from magenv.quaternion import rotate1
from magenv.trial import Trial

REJECTION = ("off", "on")  # the rejection option: the policy replaces VQF's rejection, or acts on top of it
BACKENDS = ("numba", "cpp")  # the filter: magenv.filters.vqf, or the vqf package's C++ class
BIAS_SCALE_DPS = 1.0  # °/s: bias norms and uncertainties in °/s
DELTA_RATE_SCALE_DPS = 10.0  # °/s: the rate of δ in units of 10 °/s

FEATURES = FeatureTable(
    Feature("mag_dist", 0.0, 1.0, "0/1", "VQF's magnetic disturbance flag after the last fused sample"),
    Feature(
        "ref_norm_dev",
        -1.0,
        10.0,
        "fraction of the reference",
        "(‖m‖ − n_ref)/n_ref: VQF's low-pass field norm in its 6D earth frame against its reference norm "
        "(0 while VQF has no reference)",
    ),
    Feature(
        "ref_dip_dev",
        -2.0,
        2.0,
        f"units of {DIP_SCALE_DEG:g}°",
        "VQF's low-pass dip against its reference dip (0 while VQF has no reference)",
    ),
    Feature("ref_known", 0.0, 1.0, "0/1", "VQF has accepted a field reference"),
    Feature("rest", 0.0, 1.0, "0/1", "VQF's rest detection after the last fused sample"),
    Feature("bias_norm", 0.0, 10.0, f"units of {BIAS_SCALE_DPS:g} °/s", "‖b‖, VQF's gyro-bias estimate"),
    Feature("bias_sigma", 0.0, 10.0, f"units of {BIAS_SCALE_DPS:g} °/s", "VQF's bias uncertainty (std)"),
    Feature("delta", -1.0, 1.0, "units of 180°", "δ, the heading of the 9D estimate relative to the 6D one"),
    Feature("delta_rate", -10.0, 10.0, f"units of {DELTA_RATE_SCALE_DPS:g} °/s", "change of δ over the last step"),
    Feature(
        "dis_angle",
        -1.0,
        1.0,
        "units of 180°",
        "VQF's disagreement angle e of the last fused sample (field heading in the 6D frame − δ)",
    ),
    Feature("mag_dist_frac", 0.0, 1.0, "–", "fraction of the samples fused in the last step flagged disturbed"),
    Feature("norm_dev", -1.0, 10.0, "fraction of m0", "field-norm deviation (‖m_j‖ − m0)/m0 of the next sample j"),
    Feature(
        "dip_dev", -2.0, 2.0, f"units of {DIP_SCALE_DEG:g}°", "dip deviation (θ_dip − θ0) of m_j with the 9D estimate"
    ),
    Feature("gyro_norm", 0.0, 10.0, "units of 2π rad/s", "‖ω_j‖"),
    Feature("acc_dev", -1.0, 10.0, "fraction of g", "accelerometer-norm deviation (‖a_j‖ − g)/g"),
    *deviations("each with the estimate after the sample before it"),
    NORM_RATE,
    mag_heading("m_j in the 9D earth frame"),
    Feature("trust_prev", 0.0, 1.0, "–", "u applied in the last step (1 after reset)"),
)
F = FEATURES.ix
_LOW, _HIGH = FEATURES.low64, FEATURES.high64

# The extra causal features of the extended observation: VQF's own bookkeeping and EMAs (time constant τ: each
# step of T seconds moves the EMA by 1 − exp(−T/τ) towards the step's mean) of per-sample signals.
DIS_RATE_SCALE_DPS = 10.0  # °/s
EXTRA = FeatureTable(
    Feature("reject_frac", 0.0, 2.0, "of the limit", "VQF's rejection time used / its limit (60 s)"),
    Feature("undisturbed_s", 0.0, 6.0, "units of 10 s", "time since VQF last flagged a disturbance (at most 60 s)"),
    Feature("cand_frac", 0.0, 2.0, "of 20 s", "time a new field candidate has been steady in motion / VQF's 20 s"),
    Feature("converging", 0.0, 1.0, "0/1", "VQF's initial heading convergence still on (gain ≥ 1/N)"),
    Feature("dis_ema_1", -1.0, 1.0, "units of 180°", "EMA (τ 1 s) of the disagreement angle e"),
    Feature("dis_ema_10", -1.0, 1.0, "units of 180°", "EMA (τ 10 s) of e"),
    Feature(
        "dis_rate_2",
        0.0,
        10.0,
        f"units of {DIS_RATE_SCALE_DPS:g} °/s",
        "EMA (τ 2 s) of |ē − ē_prev| / T, ē the mean e of a step, T the time between the steps' middles",
    ),
    Feature("dist_ema_5", 0.0, 1.0, "–", "EMA (τ 5 s) of VQF's disturbance flag"),
    Feature("ref_norm_ema_2", 0.0, 10.0, "fraction of the reference", "EMA (τ 2 s) of |ref_norm_dev|"),
    Feature("gyro_ema_1", 0.0, 10.0, "units of 2π rad/s", "EMA (τ 1 s) of ‖ω‖"),
    Feature("rest_ema_5", 0.0, 1.0, "–", "EMA (τ 5 s) of VQF's rest flag"),
    Feature("gain_ema_10", 0.0, 1.0, "–", "EMA (τ 10 s) of the trust that reached VQF's gain (0 where rejected)"),
    Feature("gain_ema_60", 0.0, 1.0, "–", "EMA (τ 60 s) of that trust: how long the heading has gone uncorrected"),
    Feature("norm_dev_ema_10", 0.0, 10.0, "fraction of m0", "EMA (τ 10 s) of |norm_dev|, against the trial's site"),
    Feature(
        "dip_dev_ema_10", 0.0, 2.0, f"units of {DIP_SCALE_DEG:g}°", "EMA (τ 10 s) of |dip_dev| (estimate after it)"
    ),
    Feature(
        "psi_change_10",
        -1.0,
        1.0,
        "units of 180°",
        "the field's heading ψ in the 6D frame (= e + δ; steady in a clean field but for gyro drift) over the step, "
        "against its EMA (τ 10 s) before: how far the field has turned lately without the sensor turning",
    ),
    Feature("psi_change_60", -1.0, 1.0, "units of 180°", "the same against ψ's EMA of τ 60 s"),
)
X: Any = EXTRA.ix
_XLOW, _XHIGH = EXTRA.low64, EXTRA.high64
#: per-sample sums the kernel keeps over a step for the EMAs (indices of ``Outputs.sums``)
SUM_E, SUM_DIST, SUM_NORM, SUM_GYRO, SUM_REST, SUM_GAIN, SUM_NORM_DEV, SUM_DIP_DEV, SUM_PSI_C, SUM_PSI_S = range(10)
N_SUMS = 10
_EMA = (  # (feature, the sum it follows, τ s); dis_rate_2 follows the rate of the steps' mean e (update_memory)
    (X.dis_ema_1, SUM_E, 1.0),
    (X.dis_ema_10, SUM_E, 10.0),
    (X.dist_ema_5, SUM_DIST, 5.0),
    (X.ref_norm_ema_2, SUM_NORM, 2.0),
    (X.gyro_ema_1, SUM_GYRO, 1.0),
    (X.rest_ema_5, SUM_REST, 5.0),
    (X.gain_ema_10, SUM_GAIN, 10.0),
    (X.gain_ema_60, SUM_GAIN, 60.0),
    (X.norm_dev_ema_10, SUM_NORM_DEV, 10.0),
    (X.dip_dev_ema_10, SUM_DIP_DEV, 10.0),
)
_EMA_FEATURE = np.array([e[0] for e in _EMA], np.int64)
_EMA_SUM = np.array([e[1] for e in _EMA], np.int64)
_EMA_TAU = np.array([e[2] for e in _EMA])
_SUM_SCALE = np.ones(N_SUMS)  # sum → feature unit
_SUM_SCALE[SUM_E], _SUM_SCALE[SUM_GYRO], _SUM_SCALE[SUM_DIP_DEV] = 1.0 / np.pi, 1.0 / GYRO_SCALE, 1.0 / DIP_SCALE_DEG

LAGS = (4, 16)  # decisions: the memory of the extended observation
_CURRENT = (*FEATURES.features, *EXTRA.features)
EXTENDED = lagged.extended_table(_CURRENT, LAGS)
_LAGS = np.array(LAGS, np.int64)

# the VQF scalars window_features reads (indices of its ``vq`` vector; radians, rad/s, the field's unit)
V_DIST, V_REF_NORM, V_REF_DIP, V_NORM, V_DIP, V_REST, V_BIAS, V_SIGMA, V_DELTA, V_DELTA0, V_DIS = range(11)
N_VQ = 11


class Site(NamedTuple):
    """The trial's undisturbed field, the reference of the field features (``Trial.field_norm``/``field_dip``)."""

    m0: float  # field norm, µT
    dip0: float  # dip, degrees down


class Outputs(NamedTuple):
    """What :func:`advance` writes: per-sample histories (rows = samples; a vector env's windows hold a step's
    samples and one on each side), the step's error sums and sums for the EMAs, the VQF scalars and the
    observation."""

    est: np.ndarray  # (N, 4) 9D estimate after each sample, sensor → ENU (NaN where not fused yet)
    trust: np.ndarray  # (N,) u applied to each sample
    gain: np.ndarray  # (N,) u where the gain applied: 0 where rejection="on" and VQF flagged a disturbance
    flags: np.ndarray  # (N,) VQF's disturbance flag after each sample
    sums: np.ndarray  # (N_SUMS,) per-sample sums over the step (SUM_*)
    err: np.ndarray  # (N_ERR,) error sums of the step (magenv.metrics.E_*)
    vq: np.ndarray  # (N_VQ,) the VQF scalars after the step (V_*)
    feat: np.ndarray  # (len(FEATURES),) observation of the next sample j

    @classmethod
    def empty(cls, n: int) -> Outputs:
        return cls(np.full((n, 4), np.nan), np.full(n, np.nan), np.full(n, np.nan), np.zeros(n), np.zeros(N_SUMS),
                   np.zeros(N_ERR), np.zeros(N_VQ), np.zeros(len(FEATURES)))  # fmt: skip


_clip = clipper(FEATURES)
_sample_features = sample_features(FEATURES)


@njit(cache=True, inline="always")
def _norm3(v):
    return np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@njit(cache=True)
def window_features(m0, dip0, dt, gyr, acc, mag, est, flags, start, stop, q_now, vq, u_prev, feat):
    """``feat`` (len(FEATURES),) of sample j = ``stop`` (the last sample at the end) after samples start:stop.

    Args:
        m0, dip0: the trial's undisturbed field norm (µT) and dip (°). dt: sample interval, s.
        gyr, acc, mag: (n, 3) sensors (rad/s, m/s², µT) of the trial, or of a window holding rows start−1 … j.
        est: (n, 4) the 9D estimate after each sample (rows start−1 … stop−1 read). flags: (n,) VQF's
            disturbance flag per fused sample. q_now: (4,) the current 9D estimate (q_{j−1}).
        vq: the VQF scalars (``V_*`` indices; radians, rad/s, µT). u_prev: trust of the last step.
    """
    n = gyr.shape[0]
    j = stop if stop < n else n - 1
    feat[F.mag_dist] = vq[V_DIST]
    known = vq[V_REF_NORM] > 0.0
    feat[F.ref_known] = 1.0 if known else 0.0
    if known:
        feat[F.ref_norm_dev] = _clip((vq[V_NORM] - vq[V_REF_NORM]) / vq[V_REF_NORM], F.ref_norm_dev)
        feat[F.ref_dip_dev] = _clip(np.rad2deg(vq[V_DIP] - vq[V_REF_DIP]) / DIP_SCALE_DEG, F.ref_dip_dev)
    else:
        feat[F.ref_norm_dev] = 0.0
        feat[F.ref_dip_dev] = 0.0
    feat[F.rest] = vq[V_REST]
    feat[F.bias_norm] = _clip(np.rad2deg(vq[V_BIAS]) / BIAS_SCALE_DPS, F.bias_norm)
    feat[F.bias_sigma] = _clip(np.rad2deg(vq[V_SIGMA]) / BIAS_SCALE_DPS, F.bias_sigma)
    feat[F.delta] = vq[V_DELTA] / np.pi
    cnt = stop - start
    dd = vq[V_DELTA] - vq[V_DELTA0]
    if dd > np.pi:
        dd -= 2.0 * np.pi
    elif dd < -np.pi:
        dd += 2.0 * np.pi
    feat[F.delta_rate] = _clip(np.rad2deg(dd) / (cnt * dt) / DELTA_RATE_SCALE_DPS, F.delta_rate) if cnt > 0 else 0.0
    feat[F.dis_angle] = _clip(vq[V_DIS] / np.pi, F.dis_angle)
    # sensor features of sample j and the window, against the trial's site (as MagBlend-v0's)
    mj, nd, ddip = _sample_features(feat, q_now, gyr[j], acc[j], mag[j], m0, dip0)
    nmax, nsum, dmax, dist = abs(nd), nd, abs(ddip), 0.0
    for i in range(start, stop):
        ndi = (_norm3(mag[i]) - m0) / m0
        nmax = max(nmax, abs(ndi))
        nsum += ndi
        if i > 0:
            dmax = max(dmax, abs(dip_deg(est[i - 1], mag[i]) - dip0) / DIP_SCALE_DEG)
        dist += flags[i]
    feat[F.mag_dist_frac] = dist / cnt if cnt > 0 else 0.0
    feat[F.norm_dev_max] = _clip(nmax, F.norm_dev_max)
    feat[F.norm_dev_mean] = _clip(nsum / (cnt + 1), F.norm_dev_mean)
    feat[F.dip_dev_max] = _clip(dmax, F.dip_dev_max)
    if start > 0 and j > start - 1:
        rate = (mj - _norm3(mag[start - 1])) / m0 / ((j - start + 1) * dt)
        feat[F.norm_rate] = _clip(rate / NORM_RATE_SCALE, F.norm_rate)
    else:
        feat[F.norm_rate] = 0.0
    h = rotate1(q_now, mag[j])
    feat[F.mag_heading] = np.arctan2(h[0], h[1]) / np.pi
    feat[F.trust_prev] = u_prev


@njit(cache=True)
def state_scalars(p, s, delta0, vq):
    """``vq`` (N_VQ,) from the kernel state ``s`` (``magenv.filters.vqf.STATE``); ``delta0``: δ before the step."""
    b = S.bias
    vq[V_DIST] = s[S.mag_dist]
    vq[V_REF_NORM] = s[S.ref_norm]
    vq[V_REF_DIP] = s[S.ref_dip]
    vq[V_NORM] = s[S.norm_dip]
    vq[V_DIP] = s[S.norm_dip + 1]
    vq[V_REST] = s[S.rest]
    vq[V_BIAS] = np.sqrt(s[b] * s[b] + s[b + 1] * s[b + 1] + s[b + 2] * s[b + 2])
    vq[V_SIGMA] = vqf.bias_sigma(p, s)
    vq[V_DELTA] = s[S.delta]
    vq[V_DELTA0] = delta0
    vq[V_DIS] = s[S.dis_angle]


@njit(cache=True)
def advance(p, s, w, reject, site, sensors, truth, out, u, start, stop, memory):
    """Fuse samples ``start:stop`` with trust ``u``, then the observation of sample ``stop``; with ``memory`` also
    the per-sample sums of the extended observation's EMAs (``out.sums``).

    Args:
        p, s, w: ``magenv.filters.vqf`` parameters, state (updated in place) and scratch vectors.
        reject: VQF's rejection acts (``rejection="on"``): the ``gain`` history is 0 where it flagged.
        site: :class:`Site`. sensors: ``Sensors`` (rows of the trial, or of a window holding start−1 … stop).
        truth: ``magenv.envs.common.Truth`` (same rows), for the error sums only.
        out: :class:`Outputs`; rows start:stop of the histories, the sums, ``err``, ``vq`` and ``feat`` written.
    """
    gyr, acc, mag = sensors
    k, tau = vqf.trust_gain(p, u)
    delta0 = s[S.delta]
    sums = out.sums
    for m in range(N_SUMS):
        sums[m] = 0.0
    for i in range(start, stop):
        delta_prev = s[S.delta]
        vqf.step(p, s, w, gyr[i], acc[i], mag[i], k, tau)
        out.est[i, 0], out.est[i, 1], out.est[i, 2], out.est[i, 3] = vqf.quat9d(s)
        flag = s[S.mag_dist]
        out.flags[i] = flag
        out.trust[i] = u
        gain = 0.0 if (reject and flag) else u
        out.gain[i] = gain
        if not memory:
            continue
        sums[SUM_GAIN] += gain
        sums[SUM_E] += s[S.dis_angle]
        sums[SUM_DIST] += flag
        ref = s[S.ref_norm]
        sums[SUM_NORM] += abs(s[S.norm_dip] - ref) / ref if ref > 0.0 else 0.0
        sums[SUM_GYRO] += _norm3(gyr[i])
        sums[SUM_REST] += s[S.rest]
        sums[SUM_NORM_DEV] += abs(_norm3(mag[i]) - site.m0) / site.m0
        sums[SUM_DIP_DEV] += abs(dip_deg(out.est[i], mag[i]) - site.dip0)
        psi = s[S.dis_angle] + delta_prev  # e = ψ − δ before the sample's step
        sums[SUM_PSI_C] += np.cos(psi)
        sums[SUM_PSI_S] += np.sin(psi)
    error_sums(out.est, truth.q_true, truth.dist, start, stop, out.err)
    state_scalars(p, s, delta0, out.vq)
    q_now = w[vqf.W_E : vqf.W_E + 4]  # the scratch's last rows, free after the samples
    q_now[0], q_now[1], q_now[2], q_now[3] = vqf.quat9d(s)
    u_prev = u if stop > start else 1.0
    window_features(site.m0, site.dip0, p[P.ts], gyr, acc, mag, out.est, out.flags, start, stop, q_now, out.vq,
                    u_prev, out.feat)  # fmt: skip


PSI_TAUS = (10.0, 60.0)  # s, the EMAs of ψ's direction (cos, sin) behind psi_change_10 and psi_change_60
#: the EMAs, then the dis-rate EMA, the last step's mean e and its step length, then ψ's EMAs (cos, sin each)
N_MEMORY = len(_EMA) + 3 + 2 * len(PSI_TAUS)


@njit(cache=True)
def update_memory(p, s, sums, cnt, memory, count, extra):
    """The extra features ``extra`` (len(EXTRA),) after a step of ``cnt`` samples with per-sample ``sums``: VQF's
    bookkeeping from the state ``s`` and the EMAs in ``memory`` (N_MEMORY,: started at the first step's means);
    ``count`` (1,): decisions so far, before this one."""
    ts = p[P.ts]
    lim = p[P.mag_max_rejection_time]
    extra[X.reject_frac] = min(_XHIGH[X.reject_frac], max(0.0, s[S.reject_t] / lim)) if lim > 0.0 else 0.0
    extra[X.undisturbed_s] = min(60.0, s[S.undisturbed_t]) / 10.0
    extra[X.cand_frac] = min(_XHIGH[X.cand_frac], s[S.cand_t] / max(p[P.mag_new_time], ts))
    extra[X.converging] = 1.0 if s[S.k_mag_init] != 0.0 else 0.0
    n_ema = _EMA_FEATURE.shape[0]
    if cnt > 0:
        first = count[0] == 0
        for m in range(n_ema):
            mean = sums[_EMA_SUM[m]] / cnt * _SUM_SCALE[_EMA_SUM[m]]
            a = 1.0 if first else -np.expm1(-cnt * ts / _EMA_TAU[m])
            memory[m] += a * (mean - memory[m])
        e = sums[SUM_E] / cnt
        if not first:
            de = e - memory[n_ema + 1]
            if de > np.pi:
                de -= 2.0 * np.pi
            elif de < -np.pi:
                de += 2.0 * np.pi
            rate = np.rad2deg(abs(de)) / (0.5 * (cnt + memory[n_ema + 2]) * ts) / DIS_RATE_SCALE_DPS
            a = 1.0 if count[0] == 1 else -np.expm1(-cnt * ts / 2.0)
            memory[n_ema] += a * (rate - memory[n_ema])
        memory[n_ema + 1], memory[n_ema + 2] = e, cnt
        c, sn = sums[SUM_PSI_C] / cnt, sums[SUM_PSI_S] / cnt
        psi = np.arctan2(sn, c)
        for j in range(len(PSI_TAUS)):
            o = n_ema + 3 + 2 * j
            if first:
                memory[o], memory[o + 1] = c, sn
            d = psi - np.arctan2(memory[o + 1], memory[o])
            if d > np.pi:
                d -= 2.0 * np.pi
            elif d < -np.pi:
                d += 2.0 * np.pi
            extra[X.psi_change_10 + j] = d / np.pi
            a = -np.expm1(-cnt * ts / PSI_TAUS[j])
            memory[o] += a * (c - memory[o])
            memory[o + 1] += a * (sn - memory[o + 1])
    for m in range(n_ema):
        f = _EMA_FEATURE[m]
        extra[f] = min(_XHIGH[f], max(_XLOW[f], memory[m]))
    extra[X.dis_rate_2] = min(_XHIGH[X.dis_rate_2], memory[n_ema])


@njit(cache=True)
def advance_extended(p, s, w, reject, site, sensors, truth, out, u, start, stop, memory, extra, rows, count, feat):
    """:func:`advance`, then the extended observation ``feat`` (len(EXTENDED)) of sample ``stop``: the extra
    features (:func:`update_memory`; ``memory`` its EMAs, ``extra`` its values) and the memory ``rows`` (ring of
    the current blocks by decision), ``count`` (1,) decisions so far."""
    advance(p, s, w, reject, site, sensors, truth, out, u, start, stop, True)
    update_memory(p, s, out.sums, stop - start, memory, count, extra)
    lagged.compose(out.feat, extra, rows, count, _LAGS, stop > start, feat)


def fan_trust(norm_dev, dip_dev, norm_tol: float, th_dip_deg: float):
    """u = 1 − λ of Fan et al. 2017's rule (``magenv.filters.rules.fan_lambda``) on MagVQF-v0's ``norm_dev`` and
    ``dip_dev`` (features of the observation, numbers or arrays, read as float64) — the ``vqf_fan_lambda`` rule's
    trust, computed once for the rule's teacher and its student."""
    return 1.0 - fan_lambda(np.float64(norm_dev), DIP_SCALE_DEG * np.float64(dip_dev), norm_tol, th_dip_deg)


def filter_options(rejection: str, tau_acc: float, tau_mag: float, rest_bias: bool, motion_bias: bool):
    """The ``magenv.filters.vqf.Options`` of the env's arguments (module docstring: ``rejection``)."""
    neutral: dict[str, Any] = (
        {"mag_max_rejection_time": -1.0, "mag_rejection_factor": 1.0} if rejection == "off" else {}
    )
    return vqf.Options(tau_acc=tau_acc, tau_mag=tau_mag, rest_bias=rest_bias, motion_bias=motion_bias, **neutral)


class VQFRunner(TrialRunner):
    """One trial under VQF, k samples per step at one trust u (``advance(k, u)``), through :func:`advance`.

    Histories (N rows, NaN / 0 where not fused yet): ``est`` (9D estimate, sensor → ENU), ``trust`` (u per
    sample), ``gain`` (u where the policy's gain applied: 0 where ``rejection="on"`` and VQF flagged a
    disturbance), ``dist_flag``. ``state`` is the filter's state vector (``magenv.filters.vqf.STATE``; a
    copy is a fork of the filter), ``params`` its parameters; ``vq`` the VQF scalars after the last step.
    """

    def __init__(
        self,
        trial: Trial,
        options: vqf.Options | None = None,
        extended: bool = False,
    ):
        super().__init__(trial)
        self.options = options or vqf.Options()
        self.reject = bool(self.options.mag_rejection and self.options.mag_max_rejection_time >= 0.0)
        self.params = vqf.make_params(trial.dt, self.options)
        self.state = vqf.init_state(self.params)
        self.work = vqf.work()
        self.site = Site(float(trial.field_norm), float(trial.field_dip))
        self.out = Outputs.empty(trial.n)
        self.est, self.trust, self.gain, self.dist_flag = self.out.est, self.out.trust, self.out.gain, self.out.flags
        self.err, self.vq, self.feat = self.out.err, self.out.vq, self.out.feat
        self._args = (self.params, self.state, self.work, self.reject, self.site, self.sensors, self.truth, self.out)
        self.extended = bool(extended)
        if self.extended:
            self.memory, self.extra = np.zeros(N_MEMORY), np.zeros(len(EXTRA))
            rows = np.zeros((max(LAGS) + 1, len(_CURRENT)))
            self.feat = np.zeros(len(EXTENDED))
            self._start(advance_extended, 1.0, self.memory, self.extra, rows, np.zeros(1, np.int64), self.feat)
        else:
            self._start(advance, 1.0, False)  # no memory sums

    @property
    def mag_dist(self) -> bool:
        """VQF's disturbance flag after the last fused sample."""
        return bool(self.vq[V_DIST])

    def _fuse(self, start: int, stop: int, u: float) -> None:
        self._advance(*self._args, u, start, stop, *self._more)


class VQFCppRunner(TrialRunner):
    """:class:`VQFRunner` on the ``vqf`` package's C++ filter (``backend="cpp"``: the reference; base features
    only). ``filter`` is the ``vqf.VQF`` object."""

    def __init__(self, trial: Trial, options: vqf.Options | None = None):
        import vqf as vqf_cpp

        super().__init__(trial)
        self.options = options or vqf.Options()
        self.reject = bool(self.options.mag_rejection and self.options.mag_max_rejection_time >= 0.0)
        self.ts = float(trial.dt)
        self.filter = vqf_cpp.VQF(self.ts, self.ts, self.ts, **self.options.cpp_kwargs())
        self.site = Site(float(trial.field_norm), float(trial.field_dip))
        self.gyr, self.acc, self.mag = self.sensors
        self.out = Outputs.empty(trial.n)
        self.est, self.trust, self.gain, self.dist_flag = self.out.est, self.out.trust, self.out.gain, self.out.flags
        self.err, self.vq, self.feat = self.out.err, self.out.vq, self.out.feat
        self.u_prev = 1.0
        self._observe(0, 0, self.filter.getDelta())

    @property
    def mag_dist(self) -> bool:
        return bool(self.vq[V_DIST])

    def _observe(self, start: int, stop: int, delta_before: float) -> None:
        f, vq = self.filter, self.vq
        s = f.state
        bias, sigma = f.getBiasEstimate()
        vq[:] = (float(s["magDistDetected"]), s["magRefNorm"], s["magRefDip"], s["magNormDip"][0],
                 s["magNormDip"][1], float(s["restDetected"]), math.sqrt(float(bias @ bias)), sigma, s["delta"],
                 delta_before, s["lastMagDisAngle"])  # fmt: skip
        window_features(*self.site, self.ts, self.gyr, self.acc, self.mag, self.est, self.dist_flag, start, stop,
                        f.getQuat9D(), vq, self.u_prev, self.feat)  # fmt: skip

    def _fuse(self, start: int, stop: int, u: float) -> None:
        f = self.filter
        delta_before = f.getDelta()
        f.setTauMag(tau_of_trust(u, self.options.tau_mag, self.ts))
        out = f.updateBatch(self.gyr[start:stop], self.acc[start:stop], self.mag[start:stop])
        self.est[start:stop] = out["quat9D"]
        flags = out["magDistDetected"]
        self.dist_flag[start:stop] = flags
        self.trust[start:stop] = u
        self.gain[start:stop] = np.where(flags, 0.0, u) if self.reject else u
        error_sums(self.est, self.truth.q_true, self.truth.dist, start, stop, self.err)
        self.u_prev = u
        self._observe(start, stop, delta_before)


def check_choice(name: str, value, choices: tuple[str, ...]) -> str:
    """``value`` if it is one of ``choices`` (ValueError / TypeError naming ``name`` otherwise)."""
    if not isinstance(value, str):
        raise TypeError(f"{name} must be one of {choices}, got {value!r}")
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")
    return value


@document(EXTRA, "{extended_table}")
@document(FEATURES)
class MagVQFEnv(TrustEnv):
    """
    ## Description

    A magnetic/inertial sensor moves while a magnet — or anything
    ferromagnetic — disturbs the field it measures. The orientation filter is
    VQF (Laidig & Seel 2023; ``magenv.filters.vqf``, bit for bit the ``vqf``
    package's C++ filter): a 6D gyro/accelerometer estimate with rest
    detection and gyro-bias estimation, and a 9D estimate that corrects the 6D
    heading by δ with the magnetometer (δ ← δ + k·e each sample, e the
    disagreement angle). The agent sets the trust u of that correction once
    every ``decision_every`` samples: k(u) = u·k₁ with k₁ = 1 − exp(−T_s/τ_mag)
    (u = 0 ignores the magnetometer exactly, u = 1 is VQF's own gain). With
    ``rejection="off"`` (default) the policy replaces VQF's magnetic
    disturbance rejection; with ``"on"`` it acts on top of it (u = 1 is then
    VQF as published). The sensor stream and the true orientation are fixed at
    ``reset()``, so a trial can be replayed for any policy.

    ## Action Space

    `Box(0, 1, (1,), float32)`: u, the trust of the magnetometer (0 = ignored,
    1 = VQF's gain). Finite values outside [0, 1] are **clipped**
    (``info["action_clipped"]``); NaN/inf and any shape other than `(1,)` or
    `()` raise `ValueError`.

    ## Observation Space

    `Box(float32)`, one entry per selected feature (default: all, in this
    order). Truth never enters it. The VQF features are read from the filter
    after the last fused sample; "sample j" is the next sample to be fused,
    read from the sensor before fusing, with the current 9D estimate q_{j−1};
    m0 and θ0 are the trial's undisturbed field norm and dip
    (``Trial.field_norm``/``field_dip``), as in ``magenv/MagBlend-v0`` (same
    names, same scales: ‖m_j‖ = m0·(1 + obs ``norm_dev``), dip deviation in
    degrees = 90·obs ``dip_dev``). Window statistics cover the samples fused
    in the last step plus sample j. Every value is clipped to its range.

    {observation_table}

    With ``features="extended"`` (``EXTENDED``) the observation is the 21
    above, then these extra causal features (VQF's bookkeeping, and EMAs of
    time constant τ: a step of T seconds moves one by 1 − exp(−T/τ) towards
    the step's mean), then both groups 4 decisions earlier (``NAME_lag4``)
    and 16 decisions earlier (``NAME_lag16``; before the start, the first
    observation):

    {extended_table}

    ## Rewards

    Minus the mean total orientation error Δθ = 2·acos(|q_e,0|), degrees, of
    the 9D estimate over the samples fused in the step (those with truth; 0 if
    none has truth).

    ## Starting State

    A trial is drawn at ``reset`` as in the other magenv envs (``reset(seed=s)``
    → the same trial and episode, bit for bit; ``options={"trial": trial}``).
    VQF starts from its own initial state (identity, no reference field, bias
    0 with σ = 0.5 °/s) and converges by its own rules; the first sample's
    magnetometer aligns the heading whatever u (VQF's initial gain 1).

    ## Episode End

    Never terminated. Truncated when the trial's samples (or the first
    ``episode_seconds``) are used up; the last step may fuse fewer samples.

    ## Arguments

    - `scenario` (default `"random"`): a scenario name, a comma list (a mixture), `"recording:PATH"`,
      `"recording:GLOB"` (recordings in a mixture, see ``magenv.envs.common.trial_source``), a Trial or a list.
    - `decision_every` (default 8): samples per step (k).
    - `episode_seconds` (default None): only the first seconds of each trial.
    - `rejection` (default `"off"`): `"off"` — the policy replaces VQF's disturbance rejection (VQF's
      detector still runs and feeds the observation); `"on"` — VQF's rejection acts on top of u.
    - `tau_acc`, `tau_mag` (defaults 3 s, 9 s, VQF's): accelerometer and magnetometer time constants,
      finite in (0, 1000] s; u = 1 is VQF at `tau_mag`.
    - `rest_bias`, `motion_bias` (default True): VQF's gyro-bias estimation at rest and in motion.
    - `features` (default None = the 21 base features): names of the observation features to keep, in order,
      or `"extended"` for the extended observation.
    - `backend` (default `"numba"`): `"cpp"` runs the ``vqf`` package's C++ filter (base features only; the
      reference the kernels are tested against).
    - `scenario_kwargs`, `prefetch`, `trial_pool`, `render_mode`: as for ``magenv/MagBlend-v0``.

    A bad argument raises ValueError / TypeError naming it at construction.

    `info` of each step: `t`, `sample`, `trust` (u), `action_clipped`, `error_total` / `error_heading` /
    `error_inclination` (°, NaN without truth), `disturbance_norm` (µT), `q_est`, `q_true`, `mag_dist`
    (VQF's flag after the step). Per-sample histories: ``env.unwrapped.estimate`` (N, 4), ``trust`` (N,),
    ``vqf_gain`` (N,: u where the gain applied, 0 where VQF's rejection zeroed it),
    ``mag_dist_detected`` (N,).

    ## Vectorised use

    ``gymnasium.make_vec("magenv/MagVQF-v0", num_envs=n, vectorization_mode="vector_entry_point")``
    gives ``MagVQFVectorEnv`` (n VQF filters advanced in one compiled call per step, next-step autoreset;
    extended features too).

    ## Version History

    - v0 (the id stays ``-v0`` until the first release; dates are of the commits):
      2026-12-02 first version (trust u of VQF's magnetometer gain on the ``vqf`` package, rejection off/on);
      2026-12-07 VQF as numba kernels (orientation equal to the C++ filter's to 1e-6 rad; ``backend="cpp"``
      keeps the package), the batched vector env in one compiled call, the extended observation (ψ-change,
      field-deviation and applied-gain EMAs; zeroed at every autoreset of the vector env).
    """

    action_symbol, action_key = "u", "trust"
    observation = (FEATURES, EXTENDED)
    env_name = VQF_ID.split("/")[1]

    def __init__(
        self,
        rejection: str = "off",
        tau_acc: float = vqf.Options.tau_acc,
        tau_mag: float = vqf.Options.tau_mag,
        rest_bias: bool = True,
        motion_bias: bool = True,
        backend: str = "numba",
        **options,
    ):
        self._setup(**options)
        self.rejection = check_choice("rejection", rejection, REJECTION)
        self.backend = check_choice("backend", backend, BACKENDS)
        if self.extended and self.backend == "cpp":
            raise ValueError('features="extended" needs backend="numba"')
        self.options = filter_options(
            self.rejection,
            check_number("tau_acc", tau_acc, 0.0, 1000.0, lo_open=True),
            check_number("tau_mag", tau_mag, 0.0, 1000.0, lo_open=True),
            check_bool("rest_bias", rest_bias),
            check_bool("motion_bias", motion_bias),
        )

    def _make_runner(self, trial: Trial) -> VQFRunner | VQFCppRunner:
        if self.backend == "cpp":
            return VQFCppRunner(trial, self.options)
        return VQFRunner(trial, self.options, self.extended)

    def _step_info(self, runner, start: int) -> dict:
        return {"mag_dist": runner.mag_dist}

    trust = episode_view("trust", "(N,) u applied to each sample (NaN where not fused yet).")

    vqf_gain = episode_view(
        "gain", """(N,) the trust that reached VQF's gain: u, or 0 where ``rejection="on"`` zeroed it."""
    )

    mag_dist_detected = episode_view(
        "dist_flag", "(N,) VQF's disturbance flag per fused sample (0 where not fused yet)."
    )


class Batch(NamedTuple):
    """The arrays of :class:`MagVQFVectorEnv`'s kernel: N envs (leading axis N) on the store's rows."""

    reject: bool  # VQF's rejection acts (the same for every env)
    extended: bool  # the extended observation
    p: np.ndarray  # (N, len(PARAMS)) each env's filter parameters (its trial's rate)
    s: np.ndarray  # (N, len(STATE)) filter states
    w: np.ndarray  # (N, W_SIZE) scratch
    m0: np.ndarray  # (N,) undisturbed field norm, µT (Site)
    dip0: np.ndarray  # (N,) undisturbed dip, degrees (Site)
    u: np.ndarray  # (N,) trust of the step
    est: np.ndarray  # (N, k + 2, 4) scratch Outputs of the step's window (magenv.envs.batch.Window)
    trust: np.ndarray  # (N, k + 2)
    gain: np.ndarray  # (N, k + 2)
    flags: np.ndarray  # (N, k + 2)
    sums: np.ndarray  # (N, N_SUMS)
    vq: np.ndarray  # (N, N_VQ)
    memory: np.ndarray  # (N, N_MEMORY) extended only (else (0, …) …)
    extra: np.ndarray  # (N, len(EXTRA))
    rows: np.ndarray  # (N, max(LAGS) + 1, len(_CURRENT))
    decisions: np.ndarray  # (N, 1) decisions so far (``lagged.compose``'s count)
    feat_ext: np.ndarray  # (N, len(EXTENDED))


@njit(cache=True)
def _advance_env(b, s, i, w):
    """Env i of :class:`Batch` (``s``: ``magenv.envs.batch.Steps``) does its step: :func:`advance` (or
    :func:`advance_extended`) on window ``w``."""
    sensors, truth = window_rows(s, w)
    out = Outputs(b.est[i], b.trust[i], b.gain[i], b.flags[i], b.sums[i], s.err[i], b.vq[i], s.feat[i])
    if w.start > 0:  # not the episode's first sample: the window's first row holds the current estimate
        q = out.est[0]
        q[0], q[1], q[2], q[3] = vqf.quat9d(b.s[i])
    site = Site(b.m0[i], b.dip0[i])
    if b.extended:
        advance_extended(b.p[i], b.s[i], b.w[i], b.reject, site, sensors, truth, out, b.u[i], w.start, w.stop,
                         b.memory[i], b.extra[i], b.rows[i], b.decisions[i], b.feat_ext[i])  # fmt: skip
    else:
        advance(b.p[i], b.s[i], b.w[i], b.reject, site, sensors, truth, out, b.u[i], w.start, w.stop, False)
    return -1


class MagVQFVectorEnv(BatchVectorEnv):
    """``num_envs`` MagVQF envs advanced together: one numba call per ``step`` fuses every env's k samples.

    Registered as the ``vector_entry_point`` of ``magenv/MagVQF-v0``. Seeding, trial draws, next-step
    autoreset, action checks and ``infos`` (with ``trust``, ``mag_dist``) are
    ``magenv.envs.batch.BatchVectorEnv``'s; sub-env i is the single env seeded s + i bit for bit. The N filter
    states are the rows of one array (``magenv.filters.vqf.STATE``), and :func:`_advance_env` hands env i's
    rows to :func:`advance`.
    """

    env_class = MagVQFEnv
    features = FEATURES
    advance_env = _advance_env
    extended_batched = True
    idle_action = 1.0

    def _alloc(self, n: int) -> None:
        env = self.template
        if env.backend == "cpp":
            raise ValueError('backend="cpp" is not batched: use single envs')
        self.extended = env.extended
        rows = self.k_steps + 2
        self.p = np.tile(vqf.make_params(1.0, env.options), (n, 1))
        self.s = np.tile(vqf.init_state(self.p[0]), (n, 1))
        self.w = np.zeros((n, vqf.W_SIZE))
        self.m0, self.dip0 = np.ones(n), np.zeros(n)
        self.scratch = Outputs(np.zeros((n, rows, 4)), np.zeros((n, rows)), np.zeros((n, rows)), np.zeros((n, rows)),
                               np.zeros((n, N_SUMS)), self.err, np.zeros((n, N_VQ)), self.feat)  # fmt: skip
        e = n if self.extended else 0
        self.memory, self.extra = np.zeros((e, N_MEMORY)), np.zeros((e, len(EXTRA)))
        self.rows, self.count = np.zeros((e, max(LAGS) + 1, len(_CURRENT))), np.zeros((e, 1), np.int64)
        self.feat_ext = np.zeros((e, len(EXTENDED)))

    def _prepare(self, trial: Trial):
        p = vqf.make_params(trial.dt, self.template.options)
        return trial_rows(trial), (p, float(trial.field_norm), float(trial.field_dip))

    def _start(self, i: int, description) -> None:
        p, self.m0[i], self.dip0[i] = description
        self.p[i] = p
        self.s[i] = vqf.init_state(p)
        self.action[i] = 1.0
        if self.extended:  # as a single env's reset: fresh memory, extra features, lag rows and count
            self.memory[i] = 0.0
            self.extra[i] = 0.0
            self.rows[i] = 0.0
            self.count[i] = 0

    def _obs(self) -> np.ndarray:
        env = self.template
        feat = self.feat_ext if self.extended else self.feat
        return (feat if env._all else feat[:, env._idx]).astype(np.float32)

    def _step_info(self) -> dict:
        return {"mag_dist": self.scratch.vq[:, V_DIST] > 0}

    def _batch(self) -> Batch:
        o, options = self.scratch, self.template.options
        return Batch(
            reject=options.mag_rejection and options.mag_max_rejection_time >= 0.0, extended=self.extended, p=self.p,
            s=self.s, w=self.w, m0=self.m0, dip0=self.dip0, u=self.action, est=o.est, trust=o.trust, gain=o.gain,
            flags=o.flags, sums=o.sums, vq=o.vq, memory=self.memory, extra=self.extra, rows=self.rows,
            decisions=self.count, feat_ext=self.feat_ext,
        )  # fmt: skip
