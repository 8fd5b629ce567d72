"""Kernel of ``magenv/MagKalman-v0``: the trust Kalman filter stepped k samples at a time, plus observation features.

``advance`` fuses samples ``start:stop`` of whole-trial arrays with the trust
KF (``magenv.filters.kalman_trust.run_k_kernel``, gain multiplier γ), writes
the trust history and the interval's error sums against truth, then computes
the observation features of the next sample j = ``stop``: it *peeks* at
sample j — gyro prediction and accelerometer update on copies of (q, P),
then the magnetometer innovation with γ = 0, so nothing is changed — which
gives the a-priori innovation, NIS, dip and heading std of exactly the sample
the next γ is applied to first. The same kernel serves the env (one call per
step) and :class:`KalmanRunner.run_all` (one call per trial).

The model-based feature ``model_dist`` is the magnetometer disturbance d̂
(µT, sensor frame) of the Gauss–Markov split of Ligorio & Sabatini 2015
(survey A.9–A.10, ``magenv.filters.kalman_model.vec_step1``), run on the
magnetometer alone. It depends on the sensors only, never on γ, so it is
computed once per trial at reset; row j uses samples 0…j only (causal).

Feature table with units and ranges: ``magenv.envs.kalman.MagKalmanEnv``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from magenv.filters.common import TrialRunner
from magenv.metrics import N_ERR, add_errors
from magenv.filters import kalman_trust as kt
from magenv.filters.kalman_trust import run_k_kernel, step_kernel
from magenv.filters.kalman_model import C_A, C_B, vec_step1
from magenv.filters.kalman_threshold import OK
from magenv.quaternion import GRAVITY
from magenv.trial import Trial

DIP_SCALE_DEG = 90.0  # dip deviations in units of 90° (as MagBlend-v0)
GYRO_SCALE = 2.0 * np.pi  # rad/s; gyro norm in revolutions per second
FEATURES: tuple[tuple[str, float, float], ...] = (
    ("norm_dev", -1.0, 10.0),  # (|m_j| − m0)/m0
    ("dip_dev", -2.0, 2.0),  # (dip_j − θ0)/90°, dip below the a-priori horizontal of sample j
    ("gyro_norm", 0.0, 10.0),  # |ω_j| / (2π rad/s)
    ("acc_dev", -1.0, 10.0),  # (|a_j| − g)/g
    ("innov_norm", 0.0, 10.0),  # |ν_m,j| / m0, a-priori earth-frame innovation of sample j
    ("innov_east", -10.0, 10.0),  # ν_m,j east / (m0 cos θ0) ≈ −(heading correction of a full update), rad
    ("log_nis", 0.0, 10.0),  # log10(1 + ν_mᵀ S⁻¹ ν_m) of sample j
    ("heading_std", -4.0, 2.0),  # log10(sqrt(P_zz) / 1°), a-priori for sample j
    ("trust_prev", 0.0, 1.0),  # γ applied in the last step (1 after reset: TRIAD init uses mag fully)
    ("norm_dev_max", 0.0, 10.0),  # max |norm_dev| over the window
    ("norm_dev_mean", -1.0, 10.0),  # mean norm_dev over the window
    ("dip_dev_max", 0.0, 2.0),  # max |dip_dev| over the window
    ("acc_dev_max", 0.0, 10.0),  # max |acc_dev| over the window
    ("gyro_norm_mean", 0.0, 10.0),  # mean gyro_norm over the window
    ("innov_norm_mean", 0.0, 10.0),  # mean innov_norm over the window
    ("log_nis_mean", 0.0, 10.0),  # log10(1 + mean NIS over the window)
    ("model_dist", 0.0, 10.0),  # |d̂_j| / m0, model-based disturbance estimate (A.9–A.10)
    ("model_dist_max", 0.0, 10.0),  # max model_dist over the window
    ("field_ref", 0.0, 20.0),  # m0 / 50 µT, the site's undisturbed field norm (constant per trial)
)
FEATURE_NAMES: tuple[str, ...] = tuple(f[0] for f in FEATURES)
N_FEATURES = len(FEATURES)
FEATURE_LOW = np.array([f[1] for f in FEATURES], np.float32)
FEATURE_HIGH = np.array([f[2] for f in FEATURES], np.float32)
(F_NORM, F_DIP, F_GYRO, F_ACC, F_INNOV, F_EAST, F_NIS, F_HSTD, F_TRUST, F_NORM_MAX, F_NORM_MEAN, F_DIP_MAX,
 F_ACC_MAX, F_GYRO_MEAN, F_INNOV_MEAN, F_NIS_MEAN, F_MODEL, F_MODEL_MAX, F_FIELD) = range(N_FEATURES)
FIELD_SCALE_UT = 50.0  # field_ref unit, µT

# err vector layout (E_*, N_ERR): magenv.metrics
# trust-KF params indices used here (kalman_trust.make_params layout)
_P_M0, _P_DIP0 = 11, 12


@njit(cache=True, inline="always")
def _clip(x, lo, hi):
    if x != x:  # NaN (e.g. a zero field): report the neutral value
        return 0.0 if lo <= 0.0 <= hi else lo
    return min(hi, max(lo, x))


@njit(cache=True)
def model_disturbance(gyr, mag, dt, sigma_gyr, sigma_mag, c_a, c_b, p0_ref, floor, out):
    """|d̂| per sample (µT) of the magnetometer's reference/disturbance split (survey A.9–A.10).

    Initialised as ``ModelKF.run``: r = mag[0], d = 0, P = diag(p0_ref·I,
    c_b²/(1 − c_a²)·I). Writes ``out`` (N,); returns OK (−1) or the first bad sample.
    """
    n = gyr.shape[0]
    x = np.zeros(6)
    x[:3] = mag[0]
    p = np.zeros((6, 6))
    vd = c_b * c_b / max(1.0 - c_a * c_a, 1e-12)
    for i in range(3):
        p[i, i] = p0_ref
        p[3 + i, 3 + i] = vd
    out[0] = 0.0
    for k in range(1, n):
        x, p, _, st = vec_step1(x, p, 0.5 * (gyr[k - 1] + gyr[k]), mag[k], dt, sigma_gyr, sigma_mag, c_a, c_b, floor)
        if st < 0:
            return k
        out[k] = np.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5])
    return OK


@njit(cache=True)
def advance(q, p, gyr, acc, mag, dt, q_true, dist, mdist, trust, gamma, start, stop, params, est, sig, err, feat,
            peek):
    """Fuse samples ``start:stop`` (1 ≤ start ≤ stop ≤ N) at trust γ; features of sample ``stop``.

    Args:
        q (4,), p (3, 3): trust-KF state, updated in place.
        gyr, acc, mag: (N, 3) trial arrays (rad/s, m/s², µT). dt: s.
        q_true: (N, 4) truth (NaN rows allowed), for ``err`` only.
        dist: (N,) true disturbance norm, µT (zeros if unknown), for ``err`` only.
        mdist: (N,) model-based disturbance norm |d̂|, µT (:func:`model_disturbance`).
        trust: (N,) γ history, rows start:stop set to ``gamma``.
        params: ``kalman_trust.make_params``.
        est: (N, 4), sig: (N, NSIG): rows start:stop written by ``run_k_kernel``.
        err: (N_ERR,) the interval's error sums (deg), count with truth, Σ dist.
        feat: (N_FEATURES,) observation of sample ``stop``. peek: (NSIG,) its a-priori signals.
    Returns ``(status, repairs)``; status OK (−1) or the first sample that failed.
    """
    n = gyr.shape[0]
    for k in range(N_ERR):
        err[k] = 0.0
    status, repairs = run_k_kernel(q, p, gyr, acc, mag, dt, start, stop, gamma, params, est, sig)
    if status != OK:
        return status, repairs
    for i in range(start, stop):
        trust[i] = gamma
        add_errors(err, est[i], q_true[i], dist[i])  # as magenv.metrics
    # peek at the next sample: prediction + acc update + mag innovation, γ = 0, on copies
    if stop < n:
        qc = q.copy()
        pc = p.copy()
        st = step_kernel(qc, pc, gyr[stop - 1], gyr[stop], acc[stop], mag[stop], dt, 0.0, params, peek)
        if st < 0:
            return stop, repairs
        j = stop
    else:
        peek[:] = sig[n - 1]
        j = n - 1
    _features(gyr, mag, dt, mdist, trust, start, stop, j, params, sig, peek, feat)
    return OK, repairs


@njit(cache=True)
def _features(gyr, mag, dt, mdist, trust, start, stop, j, params, sig, peek, feat):
    m0 = params[_P_M0]
    hh = m0 * np.cos(params[_P_DIP0])
    nd = peek[8] / m0
    dd = peek[9] / DIP_SCALE_DEG
    ad = peek[10] / GRAVITY
    gn = np.sqrt(gyr[j, 0] ** 2 + gyr[j, 1] ** 2 + gyr[j, 2] ** 2) / GYRO_SCALE
    inn = peek[3] / m0
    md = mdist[j] / m0
    feat[F_NORM] = _clip(nd, -1.0, 10.0)
    feat[F_DIP] = _clip(dd, -2.0, 2.0)
    feat[F_GYRO] = _clip(gn, 0.0, 10.0)
    feat[F_ACC] = _clip(ad, -1.0, 10.0)
    feat[F_INNOV] = _clip(inn, 0.0, 10.0)
    feat[F_EAST] = _clip(peek[0] / hh, -10.0, 10.0) if hh > 0.0 else 0.0
    feat[F_NIS] = _clip(np.log10(1.0 + peek[4]), 0.0, 10.0)
    feat[F_HSTD] = _clip(np.log10(max(np.rad2deg(peek[7]), 1e-12)), -4.0, 2.0)
    feat[F_TRUST] = trust[stop - 1]
    # window: samples start … stop−1 just fused, plus sample j
    nmax, nsum = abs(nd), nd
    dmax = abs(dd) if dd == dd else 0.0
    amax, gsum = abs(ad), gn
    isum, nis_sum, mmax = inn, peek[4], md
    for i in range(start, stop):
        ndi = sig[i, 8] / m0
        nmax = max(nmax, abs(ndi))
        nsum += ndi
        ddi = sig[i, 9] / DIP_SCALE_DEG
        if ddi == ddi:
            dmax = max(dmax, abs(ddi))
        amax = max(amax, abs(sig[i, 10] / GRAVITY))
        gsum += np.sqrt(gyr[i, 0] ** 2 + gyr[i, 1] ** 2 + gyr[i, 2] ** 2) / GYRO_SCALE
        isum += sig[i, 3] / m0
        nis_sum += sig[i, 4]
        mmax = max(mmax, mdist[i] / m0)
    cnt = stop - start + 1
    feat[F_NORM_MAX] = _clip(nmax, 0.0, 10.0)
    feat[F_NORM_MEAN] = _clip(nsum / cnt, -1.0, 10.0)
    feat[F_DIP_MAX] = _clip(dmax, 0.0, 2.0)
    feat[F_ACC_MAX] = _clip(amax, 0.0, 10.0)
    feat[F_GYRO_MEAN] = _clip(gsum / cnt, 0.0, 10.0)
    feat[F_INNOV_MEAN] = _clip(isum / cnt, 0.0, 10.0)
    feat[F_NIS_MEAN] = _clip(np.log10(1.0 + nis_sum / cnt), 0.0, 10.0)
    feat[F_MODEL] = _clip(md, 0.0, 10.0)
    feat[F_MODEL_MAX] = _clip(mmax, 0.0, 10.0)
    feat[F_FIELD] = _clip(m0 / FIELD_SCALE_UT, 0.0, 20.0)


class KalmanRunner(TrialRunner):
    """One trial's arrays and the trust-KF state; stepped k samples at a time.

    Sample 0 initialises the filter (TRIAD on acc[0], mag[0], never truth);
    ``est[0]`` is that orientation and ``trust[0] = 1`` (the magnetometer sets
    the initial heading fully). Steps then fuse samples 1 … N−1.

    Args:
        trial: the Trial.
        params: ``kalman_trust.make_params`` vector; None = survey defaults for the trial's site.
        model_c_a, model_c_b, model_p0: Gauss–Markov parameters of the ``model_dist`` feature
            (per-sample correlation, driving std µT, initial reference variance µT²).
    """

    def __init__(self, trial: Trial, params: np.ndarray | None = None, model_c_a: float = C_A,
                 model_c_b: float = C_B, model_p0: float = 1.0):
        self.trial = trial
        n = trial.n
        self.params = kt.make_params(trial.field_norm, trial.field_dip) if params is None else params
        self.gyr, self.acc, self.mag, self.q_true = trial.gyr, trial.acc, trial.mag, trial.q_true
        dist = trial.truth.get("mag_disturbance")
        self.has_dist = dist is not None
        self.dist = np.ascontiguousarray(np.linalg.norm(np.asarray(dist, float), axis=-1) if self.has_dist
                                         else np.zeros(n), float)
        if not 0.0 <= model_c_a < 1.0 or not model_c_b > 0.0:
            raise ValueError(f"model_c_a must be in [0, 1) and model_c_b > 0, got {model_c_a}, {model_c_b}")
        self.mdist = np.empty(n)
        st = model_disturbance(self.gyr, self.mag, trial.dt, self.params[0], self.params[2], float(model_c_a),
                               float(model_c_b), float(model_p0), self.params[13], self.mdist)
        if st != OK:
            raise kt.FilterError(f"model-based disturbance split failed at sample {st} of trial {trial.name!r}")
        self.q, self.p = kt.init(self.acc[0], self.mag[0], self.params)
        self.est = np.full((n, 4), np.nan)
        self.est[0] = self.q
        self.sig = np.full((n, kt.NSIG), np.nan)
        self.trust = np.full(n, np.nan)
        self.trust[0] = 1.0
        self.err = np.zeros(N_ERR)
        self.feat = np.zeros(N_FEATURES)
        self.peek = np.zeros(kt.NSIG)
        self.pos = 1
        self.last_count = 0
        self.repairs = 0
        self._advance(1, 1, 1.0)  # features of sample 1, nothing fused

    def _advance(self, start: int, stop: int, gamma: float) -> None:
        status, repairs = advance(self.q, self.p, self.gyr, self.acc, self.mag, self.trial.dt, self.q_true,
                                  self.dist, self.mdist, self.trust, gamma, start, stop, self.params, self.est,
                                  self.sig, self.err, self.feat, self.peek)
        if status != OK:
            raise kt.FilterError(f"trust KF: non-finite sample or covariance at sample {status} of trial "
                                 f"{self.trial.name!r} (trust {gamma})")
        self.repairs += repairs

    def advance(self, k: int, gamma: float) -> int:
        """Fuse the next ``k`` samples (fewer at the end) at trust γ ∈ [0, 1]; returns samples fused."""
        start = self.pos
        stop = min(start + k, self.trial.n)
        self._advance(start, stop, float(gamma))
        self.pos = stop
        self.last_count = stop - start
        return stop - start
