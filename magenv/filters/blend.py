"""Blend of the IMU and MIMU Madgwick filters by a weight λ (Fan et al. 2017 §2.3).

Per sample t, from the previous **blended** estimate q_{t−1} (one shared
state, ALGORITHMS.md §A reading):

1. q_IMU  = imu_step1(q_{t−1}, ω_t, a_t)           (eqs. 8–9, IMU)
2. q_MIMU = mimu_step1(q_{t−1}, ω_t, a_t, m_t)     (eqs. 8–9, MIMU)
3. align the sign of q_MIMU to q_IMU, then
   q_t = normalise(λ q_IMU + (1 − λ) q_MIMU)        (eq. 14)
4. if stationary hold is on and the sample is stationary (eqs. 11–13):
   q_t = q_{t−1} (the estimate is held unchanged).

λ = 1 is the pure IMU filter, λ = 0 the pure MIMU filter.

``advance`` is the one kernel: it fuses samples ``start:stop`` of whole-trial
arrays, writes the per-sample estimates, the interval's error sums against
truth and the observation features of the next sample. The environment calls
it once per step (k samples); ``BlendRunner.run_all`` calls it once for a
whole trial (offline replay). Same code, two granularities.

Observation features (all computed here, names in ``FEATURES``): see
``magenv.envs.blend.MagBlendEnv`` for the table with units and ranges. The
"current" features describe sample j = ``stop`` — the next sample, to which the
next λ is applied first — using the current estimate q_{j−1} (so the λ rule of
eqs. 15–18 is reproduced exactly with one decision per sample). Window
statistics cover samples ``start … j``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from magenv.filters.common import TrialRunner
from magenv.metrics import N_ERR, add_errors
from magenv.filters import stationary as stat
from magenv.filters.stationary import stationary_peek1, stationary_step1
from magenv.filters.madgwick import BETA_DEFAULT, MODE_IMU, MODE_MIMU, ecompass1, step_scalar
from magenv.quaternion import GRAVITY, normalize1, rotate1
from magenv.trial import Trial

# Observation features: (name, low, high). Scales are fixed constants so a
# rule can recover physical values (e.g. dip deviation in degrees = 90·obs).
DIP_SCALE_DEG = 90.0  # dip deviations are given in units of 90°
GYRO_SCALE = 2.0 * np.pi  # rad/s; gyro norm in revolutions per second
NORM_RATE_SCALE = 10.0  # 1/s; relative field-norm rate in units of 10 /s
FEATURES: tuple[tuple[str, float, float], ...] = (
    ("norm_dev", -1.0, 10.0),  # (|m_j| − m0)/m0
    ("dip_dev", -2.0, 2.0),  # (dip_j − θ0)/90°, dip by eq. 18 with q_{j−1}
    ("gyro_norm", 0.0, 10.0),  # |ω_j| / (2π rad/s)
    ("acc_dev", -1.0, 10.0),  # (|a_j| − g)/g
    ("stationary", 0.0, 1.0),  # eqs. 11–13 for sample j (1 = stationary)
    ("cand_angle", 0.0, 2.0),  # mean angle(q_IMU, q_MIMU) over the interval / (4 β Δt)
    ("lambda_prev", 0.0, 1.0),  # λ applied over the interval just fused
    ("norm_dev_max", 0.0, 10.0),  # max |norm_dev| over samples start … j
    ("norm_dev_mean", -1.0, 10.0),  # mean norm_dev over samples start … j
    ("dip_dev_max", 0.0, 2.0),  # max |dip_dev| over samples start … j
    ("norm_rate", -10.0, 10.0),  # (|m_j| − |m_{start−1}|)/m0 per s, / 10 /s
    ("mag_heading", -1.0, 1.0),  # heading of the measured horizontal field in the estimated earth frame / 180°
    ("stationary_frac", 0.0, 1.0),  # fraction of samples start … j detected stationary
)
FEATURE_NAMES: tuple[str, ...] = tuple(f[0] for f in FEATURES)
N_FEATURES = len(FEATURES)
FEATURE_LOW = np.array([f[1] for f in FEATURES], np.float32)
FEATURE_HIGH = np.array([f[2] for f in FEATURES], np.float32)

# params vector layout (float64)
P_BETA, P_DT, P_TH_A, P_TH_G, P_HOLD, P_M0, P_DIP0 = range(7)
N_PARAMS = 7
# err vector layout (E_*, N_ERR): magenv.metrics


@njit(cache=True, inline="always")
def _up(w, x, y, z, mx, my, mz):
    """Earth-up (ENU z) component of the sensor vector m rotated by q (sensor → earth)."""
    return 2.0 * (x * z - w * y) * mx + 2.0 * (y * z + w * x) * my + (1.0 - 2.0 * (x * x + y * y)) * mz


@njit(cache=True, inline="always")
def _dip_deg(w, x, y, z, mx, my, mz):
    """Dip angle, degrees (positive down), of field m (sensor) seen with orientation q (eq. 18, ENU)."""
    n = np.sqrt(mx * mx + my * my + mz * mz)
    if n == 0.0:
        return 0.0
    s = -_up(w, x, y, z, mx, my, mz) / n
    s = min(1.0, max(-1.0, s))
    return np.rad2deg(np.arcsin(s))


@njit(cache=True, inline="always")
def _norm3(v):
    return np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@njit(cache=True, inline="always")
def _clip(x, lo, hi):
    return min(hi, max(lo, x))


@njit(cache=True)
def advance(q, buf, ctr, gyr, acc, mag, q_true, dist, lam, lam_const, start, stop, params, est, aux, err, feat):
    """Fuse samples ``start:stop``; update q (4,) and the detector (buf, ctr) in place.

    Args:
        q: (4,) blended state, overwritten with q_{stop−1}.
        buf, ctr: stationary detector state (``stationary.make_state``).
        gyr, acc, mag: (N, 3) whole-trial sensor arrays (rad/s, m/s², µT).
        q_true: (N, 4) truth (NaN rows allowed), for the error sums only.
        dist: (N,) true disturbance norm, µT (zeros if unknown), for ``err`` only.
        lam: (N,) λ per sample; written with ``lam_const`` if that is ≥ 0,
            else read.
        params: (N_PARAMS,) β rad/s, Δt s, th_a m/s², th_gyro rad/s, hold (0/1),
            m0 µT, θ0 deg.
        est: (N, 4) estimates, rows start:stop written.
        aux: (N, 3) per sample [dip deg (eq. 18 with q_{t−1}), angle(q_IMU, q_MIMU) deg,
            stationary 0/1], rows start:stop written.
        err: (N_ERR,) set to the interval's sums of total / heading /
            inclination error (deg), count of samples with truth, sum of dist.
        feat: (N_FEATURES,) set to the observation features of sample ``stop``.
    """
    beta = params[P_BETA]
    dt = params[P_DT]
    th_a = params[P_TH_A]
    th_g = params[P_TH_G]
    hold = params[P_HOLD] > 0.5
    for k in range(N_ERR):
        err[k] = 0.0
    for i in range(start, stop):
        if lam_const >= 0.0:
            lam[i] = lam_const
        lam_i = lam[i]
        still = stationary_step1(buf, ctr, acc[i], gyr[i], th_a, th_g)  # eqs. 11–13
        w0, x0, y0, z0 = q[0], q[1], q[2], q[3]
        gx, gy, gz = gyr[i, 0], gyr[i, 1], gyr[i, 2]
        ax, ay, az = acc[i, 0], acc[i, 1], acc[i, 2]
        mx, my, mz = mag[i, 0], mag[i, 1], mag[i, 2]
        aux[i, 0] = _dip_deg(w0, x0, y0, z0, mx, my, mz)  # eq. 18 with the current estimate
        iw, ix, iy, iz = step_scalar(w0, x0, y0, z0, gx, gy, gz, ax, ay, az, mx, my, mz, MODE_IMU, 0.0, 0.0, beta, dt)
        mw, mx_, my_, mz_ = step_scalar(w0, x0, y0, z0, gx, gy, gz, ax, ay, az, mx, my, mz, MODE_MIMU, 0.0, 0.0,
                                        beta, dt)
        d = iw * mw + ix * mx_ + iy * my_ + iz * mz_
        if d < 0.0:  # align signs before blending
            mw, mx_, my_, mz_ = -mw, -mx_, -my_, -mz_
        aux[i, 1] = np.rad2deg(2.0 * np.arccos(min(1.0, abs(d))))
        aux[i, 2] = 1.0 if still else 0.0
        if not (hold and still):  # eq. 14, normalised
            bw = lam_i * iw + (1.0 - lam_i) * mw
            bx = lam_i * ix + (1.0 - lam_i) * mx_
            by = lam_i * iy + (1.0 - lam_i) * my_
            bz = lam_i * iz + (1.0 - lam_i) * mz_
            nb = np.sqrt(bw * bw + bx * bx + by * by + bz * bz)
            q[0], q[1], q[2], q[3] = bw / nb, bx / nb, by / nb, bz / nb
        est[i, 0], est[i, 1], est[i, 2], est[i, 3] = q[0], q[1], q[2], q[3]
        add_errors(err, q, q_true[i], dist[i])  # against truth, as magenv.metrics
    _features(q, buf, ctr, gyr, acc, mag, lam, start, stop, params, aux, feat)


@njit(cache=True)
def _features(q, buf, ctr, gyr, acc, mag, lam, start, stop, params, aux, feat):
    n = gyr.shape[0]
    j = stop if stop < n else n - 1
    m0 = params[P_M0]
    dip0 = params[P_DIP0]
    mj = _norm3(mag[j])
    nd = (mj - m0) / m0
    dipj = _dip_deg(q[0], q[1], q[2], q[3], mag[j, 0], mag[j, 1], mag[j, 2])
    dd = (dipj - dip0) / DIP_SCALE_DEG
    feat[0] = _clip(nd, -1.0, 10.0)
    feat[1] = _clip(dd, -2.0, 2.0)
    feat[2] = _clip(_norm3(gyr[j]) / GYRO_SCALE, 0.0, 10.0)
    feat[3] = _clip((_norm3(acc[j]) - GRAVITY) / GRAVITY, -1.0, 10.0)
    still = stationary_peek1(buf, ctr, acc[j], gyr[j], params[P_TH_A], params[P_TH_G])
    feat[4] = 1.0 if still else 0.0
    # window statistics over processed samples start:stop plus sample j
    ang = 0.0
    nmax = abs(nd)
    nsum = nd
    dmax = abs(dd)
    sfrac = feat[4]
    for i in range(start, stop):
        ang += aux[i, 1]
        ndi = (_norm3(mag[i]) - m0) / m0
        nmax = max(nmax, abs(ndi))
        nsum += ndi
        dmax = max(dmax, abs(aux[i, 0] - dip0) / DIP_SCALE_DEG)
        sfrac += aux[i, 2]
    cnt = stop - start
    ang_scale = np.rad2deg(4.0 * params[P_BETA] * params[P_DT])
    feat[5] = _clip(ang / cnt / ang_scale, 0.0, 2.0) if cnt > 0 and ang_scale > 0 else 0.0
    feat[6] = lam[stop - 1] if stop > 0 else 0.0
    feat[7] = _clip(nmax, 0.0, 10.0)
    feat[8] = _clip(nsum / (cnt + 1), -1.0, 10.0)
    feat[9] = _clip(dmax, 0.0, 2.0)
    if start > 0 and j > start - 1:
        rate = (mj - _norm3(mag[start - 1])) / m0 / ((j - start + 1) * params[P_DT])
        feat[10] = _clip(rate / NORM_RATE_SCALE, -10.0, 10.0)
    else:
        feat[10] = 0.0
    h = rotate1(q, mag[j])
    feat[11] = np.arctan2(h[0], h[1]) / np.pi  # east over north: 0 when the field points north
    feat[12] = sfrac / (cnt + 1)


class BlendRunner(TrialRunner):
    """Holds one trial's arrays and the blend state; steps it k samples at a time.

    Used by the environment (``advance(k, λ)`` per step) and for offline replay
    (``run_all(λ)``); both go through the one kernel ``advance``.

    Args:
        trial: the Trial to filter.
        beta: Madgwick gain β, rad/s.
        hold: hold the estimate on stationary samples.
        t0, th_acc_g, th_gyro_dps: stationary detection (s, g, °/s).
        q0: initial orientation; None = ``ecompass1`` of the first sample
            (never truth).
    """

    def __init__(self, trial: Trial, beta: float = BETA_DEFAULT, hold: bool = True,
                 t0: float = stat.T0_S, th_acc_g: float = stat.TH_ACC_G,
                 th_gyro_dps: float = stat.TH_GYRO_DPS, q0=None):
        self.trial = trial
        n = trial.n
        self.gyr, self.acc, self.mag, self.q_true = trial.gyr, trial.acc, trial.mag, trial.q_true
        dist = trial.truth.get("mag_disturbance")
        self.has_dist = dist is not None
        self.dist = (np.linalg.norm(np.asarray(dist, float), axis=-1) if self.has_dist else np.zeros(n))
        self.dist = np.ascontiguousarray(self.dist, float)
        th_a, th_g = stat.thresholds(th_acc_g, th_gyro_dps)
        self.params = np.array([beta, trial.dt, th_a, th_g, 1.0 if hold else 0.0,
                                trial.field_norm, trial.field_dip], float)
        self.buf, self.ctr = stat.make_state(trial.rate, t0)
        self.q = (ecompass1(self.acc[0], self.mag[0]) if q0 is None
                  else np.array(normalize1(np.asarray(q0, float)), float))
        self.q0 = self.q.copy()
        self.est = np.full((n, 4), np.nan)
        self.lam = np.full(n, np.nan)
        self.aux = np.zeros((n, 3))
        self.err = np.zeros(N_ERR)
        self.feat = np.zeros(N_FEATURES)
        self.pos = 0
        self.last_count = 0
        # observation of sample 0 before anything is fused
        advance(self.q, self.buf, self.ctr, self.gyr, self.acc, self.mag, self.q_true, self.dist,
                self.lam, 0.0, 0, 0, self.params, self.est, self.aux, self.err, self.feat)

    def advance(self, k: int, lam: float) -> int:
        """Fuse the next ``k`` samples (fewer at the end) with weight ``lam`` ∈ [0, 1]; returns samples fused."""
        start = self.pos
        stop = min(start + k, self.trial.n)
        advance(self.q, self.buf, self.ctr, self.gyr, self.acc, self.mag, self.q_true, self.dist,
                self.lam, lam, start, stop, self.params, self.est, self.aux, self.err, self.feat)
        self.pos = stop
        self.last_count = stop - start
        return stop - start

    def run_all(self, lam) -> np.ndarray:
        """Fuse all remaining samples with λ a constant or an (N,) array; returns est (N, 4)."""
        if np.ndim(lam) == 0:
            self.advance(self.trial.n - self.pos, float(lam))
        else:
            lam = np.asarray(lam, float)
            if lam.shape != (self.trial.n,):
                raise ValueError(f"λ array must have shape ({self.trial.n},), got {lam.shape}")
            if not np.all((lam >= 0) & (lam <= 1)):
                raise ValueError("λ array must lie in [0, 1]")
            self.lam[self.pos:] = lam[self.pos:]
            start = self.pos
            advance(self.q, self.buf, self.ctr, self.gyr, self.acc, self.mag, self.q_true, self.dist,
                    self.lam, -1.0, start, self.trial.n, self.params, self.est, self.aux, self.err, self.feat)
            self.pos = self.trial.n
        return self.est


class BlendEstimator:
    """Offline blend with a fixed λ (or an (N,) λ series per trial via ``lam_fn``); an ``Estimator``.

    ``BlendEstimator(0.0)`` is the pure MIMU filter, ``BlendEstimator(1.0)`` the pure IMU filter.
    """

    def __init__(self, lam: float = 0.0, hold: bool = True, beta: float = BETA_DEFAULT, **kwargs):
        if not 0.0 <= lam <= 1.0:
            raise ValueError(f"λ must lie in [0, 1], got {lam}")
        self.lam, self.hold, self.beta, self.kwargs = float(lam), hold, beta, kwargs

    def run(self, trial: Trial):
        from magenv.protocols import Estimate

        runner = BlendRunner(trial, beta=self.beta, hold=self.hold, **self.kwargs)
        est = runner.run_all(self.lam)
        return Estimate(q=est.copy(), trust=1.0 - runner.lam)
