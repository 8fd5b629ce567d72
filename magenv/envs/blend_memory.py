"""The extended observation of ``magenv/MagBlend-v0`` (``features="extended"``): extra causal features with memory.

All are computed from the sensor stream, the env's own estimate history and
its stationary flags — never truth — by :func:`update`, which the env's
kernel calls after each step on the samples just fused (``start:stop``); the
values describe the decision at sample ``stop``, the same timing as the
13 base features. ``magenv.envs.blend`` appends to [base, extra] their copies
8 and 32 decisions earlier (the memory).

Conventions (ENU earth frame, angles in degrees, signed, wrapped to ±180):

* "heading(a ⊗ b*)" is the signed rotation about earth-up from orientation b
  to a, 2·atan2(z, w) of the earth-frame quaternion a ⊗ b* (w ≥ 0), the sign
  convention of ``magenv.metrics``' heading error.
* "mag heading" of sample i is the heading of its measured horizontal field
  in the earth frame of the estimate after that sample, atan2(east, north).
* An EMA of time constant τ takes each sample with weight Δt/τ.
* "Parallel" filters run the env's blend (eq. 14, with the stationary hold)
  from the e-compass start with a fixed λ on the same samples.
* A sample is *clean* when |norm_dev| < 0.03 and its dip deviation < 1.5°;
  the gyro bias b̂ is an EMA (τ 4 s) of the gyro over samples with
  ‖ω‖ < 1.5 °/s and |‖a‖ − g| < 0.05 g.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from magenv.envs import lagged
from magenv.envs.features import DEG, HEADING, SHARED, Feature, FeatureTable
from magenv.filters.madgwick import MODE_IMU, MODE_MIMU, NO_REF, step
from magenv.quaternion import GRAVITY

_DIFF = -360.0, 360.0

EXTRA = FeatureTable(
    Feature("mh_ema_025", *HEADING, DEG, "EMA (τ 0.25 s) of the mag heading (≈ −heading error in a clean field)"),
    SHARED["mh_ema_1"],
    SHARED["mh_ema_4"],
    Feature(
        "pull_h",
        -100.0,
        100.0,
        "units of β·Δt",
        "mean signed heading part of the MIMU candidate relative to the IMU one, q_MIMU ⊗ q_IMU*, over the step",
    ),
    Feature("pull_tilt", 0.0, 100.0, "units of β·Δt", "mean tilt part magnitude of q_MIMU ⊗ q_IMU* over the step"),
    Feature("pull_h_ema_1", -100.0, 100.0, "units of β·Δt", "EMA (τ 1 s) of pull_h"),
    Feature("d_imu", *HEADING, DEG, "heading(q ⊗ q_IMU*), q_IMU the parallel λ = 1 filter"),
    Feature("d_mimu", *HEADING, DEG, "heading(q_MIMU ⊗ q*), q_MIMU the parallel λ = 0 filter"),
    Feature("d_slow", *HEADING, DEG, "heading(q_slow ⊗ q*), q_slow a parallel filter with λ = 0.9 when clean, else 1"),
    Feature(
        "d_anchor",
        *HEADING,
        DEG,
        "heading(q ⊗ q_anc*), q_anc the IMU filter re-anchored to the estimate on clean samples",
    ),
    Feature("t_anchor", 0.0, 3.0, "units of 10 s", "time since the last clean sample (clipped)"),
    SHARED["nd_ema_05"],
    SHARED["nd_ema_2"],
    SHARED["nd_ema_8"],
    SHARED["dd_ema_05"],
    SHARED["dd_ema_2"],
    SHARED["gyro_ema_1"],
    Feature(
        "resid_ema",
        0.0,
        100.0,
        "fraction of m0",
        "EMA (τ 0.25 s) of ‖m − m_pred‖/m0, m_pred the field propagated by the gyro (dv/dt = −ω × v) "
        "and pulled to m with τ 0.5 s",
    ),
    Feature("still_ema_1", 0.0, 1.0, "–", "EMA (τ 1 s) of the stationary flag"),
    Feature("t_still", 0.0, 3.0, "units of 10 s", "time since the last stationary sample (clipped)"),
    Feature("d_imu_d1", *_DIFF, DEG, "change of d_imu over the last 32 decisions (1 s at k = 8, 256 Hz)"),
    Feature("d_imu_d4", *_DIFF, DEG, "change of d_imu over the last 128 decisions (4 s at k = 8, 256 Hz)"),
    Feature("mh_raw", *HEADING, DEG, "mag heading of the next sample j with the current estimate q_{j−1}"),
    Feature("clean_frac_4", 0.0, 1.0, "–", "EMA (τ 4 s) of the clean flag"),
    Feature("b_up", -1000.0, 1000.0, "°/s", "earth-up component of the gyro-bias estimate b̂ rotated by q"),
    Feature(
        "d_bc_anchor",
        *HEADING,
        DEG,
        "heading(q ⊗ q_bca*), q_bca the bias-corrected (ω − b̂) IMU filter re-anchored to q on clean samples",
    ),
    Feature("d_bc_imu", *HEADING, DEG, "heading(q ⊗ q_bci*), q_bci the parallel bias-corrected IMU filter"),
    Feature("mh_clean", *HEADING, DEG, "EMA (τ 1 s) of the mag heading over clean samples only"),
    Feature("b_norm", 0.0, 1000.0, "°/s", "‖b̂‖"),
)
X = EXTRA.ix
_LOW, _HIGH = EXTRA.low64, EXTRA.high64

# layout of the state vector: six quaternions, the predicted field, then the scalars
Q_IMU, Q_MIMU, Q_SLOW, Q_ANC, Q_BCA, Q_BCI = 0, 4, 8, 12, 16, 20
V_PRED = 24  # (3,) gyro-propagated field, µT
B_GYRO = 27  # (3,) gyro-bias estimate b̂, rad/s
(S_MH025, S_MH1, S_MH4, S_PH1, S_ND05, S_ND2, S_ND8, S_DD05, S_DD2, S_G1, S_RES, S_ST1, S_TST, S_TANC, S_CLEAN4,
 S_MHC) = range(30, 46)  # fmt: skip
N_STATE = 46
QUATERNIONS = (Q_IMU, Q_MIMU, Q_SLOW, Q_ANC, Q_BCA, Q_BCI)
D_IMU_HISTORY = 129  # decisions of d_imu kept (d_imu_d4 looks back 128)
LAG_1S, LAG_4S = 32, 128  # decisions
CLEAN_NORM, CLEAN_DIP_DEG = 0.03, 1.5
BIAS_STILL_GYRO = np.deg2rad(1.5)  # rad/s
BIAS_STILL_ACC = 0.05 * GRAVITY  # m/s²
BIAS_TAU_S = 4.0
SLOW_LAMBDA = 0.9


class Memory(NamedTuple):
    """The streaming state of the extra features of one trial (arrays updated in place)."""

    state: np.ndarray  # (N_STATE,) see the layout constants
    d_imu: np.ndarray  # (D_IMU_HISTORY,) ring of d_imu per decision
    decisions: np.ndarray  # (1,) int64: decisions written to d_imu
    value: np.ndarray  # (len(EXTRA),) the features of the next decision (zeros before any sample is fused)

    @classmethod
    def start(cls, q0: np.ndarray) -> Memory:
        """Memory at the start of a trial: every parallel filter at the e-compass orientation ``q0``."""
        state = lagged.anchored(N_STATE, q0, QUATERNIONS)
        return cls(state, np.zeros(D_IMU_HISTORY), np.zeros(1, np.int64), np.zeros(len(EXTRA)))


@njit(cache=True, inline="always")
def _heading(aw, ax, ay, az, bw, bx, by, bz):
    """Signed heading (deg) of a ⊗ b* (rotation about earth-up from b to a)."""
    w = aw * bw + ax * bx + ay * by + az * bz
    z = -aw * bz + bw * az - (ax * by - ay * bx)
    if w < 0.0:
        w, z = -w, -z
    return np.rad2deg(2.0 * np.arctan2(z, w))


@njit(cache=True, inline="always")
def _heading_of(s, a, qw, qx, qy, qz):
    """heading(q ⊗ s[a:a+4]*)."""
    return _heading(qw, qx, qy, qz, s[a], s[a + 1], s[a + 2], s[a + 3])


@njit(cache=True, inline="always")
def _ema(old, new, a):
    return old + a * (new - old)


@njit(cache=True, inline="always")
def _mag_heading(qw, qx, qy, qz, mx, my, mz):
    """Heading (deg) of field (mx, my, mz) in the earth frame of q: atan2(east, north)."""
    tx = qy * mz - qz * my + qw * mx
    ty = qz * mx - qx * mz + qw * my
    tz = qx * my - qy * mx + qw * mz
    hx = mx + 2.0 * (qy * tz - qz * ty)
    hy = my + 2.0 * (qz * tx - qx * tz)
    return np.rad2deg(np.arctan2(hx, hy))


@njit(cache=True)
def _blend(s, o, lam, gyr, acc, mag, beta, dt, still, hold):
    """The env's blend step (eq. 14 with the hold) of the parallel filter at s[o:o+4] with a fixed λ."""
    q = (s[o], s[o + 1], s[o + 2], s[o + 3])
    iw, ix, iy, iz = step(q, gyr, acc, mag, MODE_IMU, NO_REF, beta, dt)
    if lam < 1.0:
        mw, mx, my, mz = step(q, gyr, acc, mag, MODE_MIMU, NO_REF, beta, dt)
        if iw * mw + ix * mx + iy * my + iz * mz < 0.0:
            mw, mx, my, mz = -mw, -mx, -my, -mz
    else:
        mw, mx, my, mz = iw, ix, iy, iz
    if not (hold and still):
        bw = lam * iw + (1.0 - lam) * mw
        bx = lam * ix + (1.0 - lam) * mx
        by = lam * iy + (1.0 - lam) * my
        bz = lam * iz + (1.0 - lam) * mz
        nb = np.sqrt(bw * bw + bx * bx + by * by + bz * bz)
        s[o], s[o + 1], s[o + 2], s[o + 3] = bw / nb, bx / nb, by / nb, bz / nb


@njit(cache=True)
def _imu_unbiased(s, o, gyr, acc, beta, dt, still, hold):
    """IMU Madgwick step of s[o:o+4] with the bias-corrected gyro ω − b̂ (held when stationary)."""
    if hold and still:
        return
    w = (gyr[0] - s[B_GYRO], gyr[1] - s[B_GYRO + 1], gyr[2] - s[B_GYRO + 2])
    q = (s[o], s[o + 1], s[o + 2], s[o + 3])
    s[o], s[o + 1], s[o + 2], s[o + 3] = step(q, w, acc, (0.0, 0.0, 0.0), MODE_IMU, NO_REF, beta, dt)


@njit(cache=True)
def update(p, site, sensors, est, dip, still_flags, q0, mem, start, stop):
    """Consume samples ``start:stop`` (``stop`` > ``start``) just fused; ``mem.value`` = the extra features at
    sample ``stop``.

    Args:
        p: ``magenv.filters.blend.Params``. site: ``magenv.envs.blend.Site`` (m0 µT, θ0 °).
        sensors: the trial's ``magenv.filters.sensors.Sensors``.
        est: (N, 4) the env's estimates; dip: dip of each sample fused with the estimate before it (°), sample
            i at row i − start;
        still_flags: (N,) bool, stationary samples. q0: (4,) the initial estimate (before sample 0).
        mem: :class:`Memory`, updated in place.
    """
    gyr, acc, mag = sensors.gyr, sensors.acc, sensors.mag
    s, out = mem.state, mem.value
    beta, dt, hold, m0, dip0 = p.beta, p.dt, p.hold, site.m0, site.dip0
    n = gyr.shape[0]
    a025, a05, a1, a2, a4, a8 = dt / 0.25, dt / 0.5, dt, dt / 2.0, dt / 4.0, dt / 8.0
    ph_sum = 0.0
    pt_sum = 0.0
    for i in range(start, stop):
        q_prev = (
            (q0[0], q0[1], q0[2], q0[3]) if i == 0 else (est[i - 1, 0], est[i - 1, 1], est[i - 1, 2], est[i - 1, 3])
        )
        still = still_flags[i]
        m = mag[i]
        mx, my, mz = m[0], m[1], m[2]
        nd = (np.sqrt(mx * mx + my * my + mz * mz) - m0) / m0
        dd = dip[i - start] - dip0
        # pull of the MIMU candidate relative to the IMU one, q_M ⊗ q_I* (earth frame), from q_{i−1}
        iw, ix, iy, iz = step(q_prev, gyr[i], acc[i], m, MODE_IMU, NO_REF, beta, dt)
        mw, mx_, my_, mz_ = step(q_prev, gyr[i], acc[i], m, MODE_MIMU, NO_REF, beta, dt)
        rx = -mw * ix + iw * mx_ - (my_ * iz - mz_ * iy)
        ry = -mw * iy + iw * my_ - (mz_ * ix - mx_ * iz)
        rz = -mw * iz + iw * mz_ - (mx_ * iy - my_ * ix)
        if mw * iw + mx_ * ix + my_ * iy + mz_ * iz < 0.0:
            rx, ry, rz = -rx, -ry, -rz
        ph_sum += 2.0 * rz
        pt_sum += 2.0 * np.sqrt(rx * rx + ry * ry)
        qw, qx, qy, qz = est[i, 0], est[i, 1], est[i, 2], est[i, 3]
        mh = _mag_heading(qw, qx, qy, qz, mx, my, mz)
        s[S_MH025] = _ema(s[S_MH025], mh, a025)
        s[S_MH1] = _ema(s[S_MH1], mh, a1)
        s[S_MH4] = _ema(s[S_MH4], mh, a4)
        s[S_ND05] = _ema(s[S_ND05], nd, a05)
        s[S_ND2] = _ema(s[S_ND2], nd, a2)
        s[S_ND8] = _ema(s[S_ND8], abs(nd), a8)
        s[S_DD05] = _ema(s[S_DD05], abs(dd), a05)
        s[S_DD2] = _ema(s[S_DD2], dd, a2)
        g = gyr[i]
        gn = np.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
        s[S_G1] = _ema(s[S_G1], gn, a1)
        s[S_ST1] = _ema(s[S_ST1], 1.0 if still else 0.0, a1)
        s[S_TST] = 0.0 if still else s[S_TST] + dt
        clean = abs(nd) < CLEAN_NORM and abs(dd) < CLEAN_DIP_DEG
        s[S_CLEAN4] = _ema(s[S_CLEAN4], 1.0 if clean else 0.0, a4)
        # gyro-propagated field (sensor frame): dv/dt = −ω × v, then pulled toward m with τ 0.5 s
        v0, v1, v2 = (mx, my, mz) if i == 0 else (s[V_PRED], s[V_PRED + 1], s[V_PRED + 2])
        c0 = g[1] * v2 - g[2] * v1
        c1 = g[2] * v0 - g[0] * v2
        c2 = g[0] * v1 - g[1] * v0
        v0, v1, v2 = v0 - c0 * dt, v1 - c1 * dt, v2 - c2 * dt
        res = np.sqrt((mx - v0) ** 2 + (my - v1) ** 2 + (mz - v2) ** 2) / m0
        s[S_RES] = _ema(s[S_RES], res, a025)
        s[V_PRED], s[V_PRED + 1], s[V_PRED + 2] = v0 + a05 * (mx - v0), v1 + a05 * (my - v1), v2 + a05 * (mz - v2)
        # parallel filters
        _blend(s, Q_IMU, 1.0, g, acc[i], m, beta, dt, still, hold)
        _blend(s, Q_MIMU, 0.0, g, acc[i], m, beta, dt, still, hold)
        _blend(s, Q_SLOW, SLOW_LAMBDA if clean else 1.0, g, acc[i], m, beta, dt, still, hold)
        if clean:  # re-anchor the gyro reference to the estimate
            s[Q_ANC], s[Q_ANC + 1], s[Q_ANC + 2], s[Q_ANC + 3] = qw, qx, qy, qz
            s[S_TANC] = 0.0
        else:
            _blend(s, Q_ANC, 1.0, g, acc[i], m, beta, dt, still, hold)
            s[S_TANC] += dt
        # gyro bias on loosely still samples; bias-corrected references
        a = acc[i]
        an = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
        if gn < BIAS_STILL_GYRO and abs(an - GRAVITY) < BIAS_STILL_ACC:
            for k in range(3):
                s[B_GYRO + k] = _ema(s[B_GYRO + k], g[k], dt / BIAS_TAU_S)
        _imu_unbiased(s, Q_BCI, g, a, beta, dt, still, hold)
        if clean:
            s[Q_BCA], s[Q_BCA + 1], s[Q_BCA + 2], s[Q_BCA + 3] = qw, qx, qy, qz
            s[S_MHC] = _ema(s[S_MHC], mh, a1)
        else:
            _imu_unbiased(s, Q_BCA, g, a, beta, dt, still, hold)
    cnt = stop - start
    j = stop if stop < n else n - 1
    qw, qx, qy, qz = est[stop - 1, 0], est[stop - 1, 1], est[stop - 1, 2], est[stop - 1, 3]
    d_imu = _heading_of(s, Q_IMU, qw, qx, qy, qz)
    hist = mem.d_imu
    length = hist.shape[0]
    c = mem.decisions[0]
    hist[c % length] = d_imu
    mem.decisions[0] = c + 1
    lag1 = LAG_1S if c >= LAG_1S else c
    lag4 = length - 1 if c >= length - 1 else c
    scale = np.rad2deg(beta * dt)
    out[X.mh_ema_025] = s[S_MH025]
    out[X.mh_ema_1] = s[S_MH1]
    out[X.mh_ema_4] = s[S_MH4]
    out[X.pull_h] = np.rad2deg(ph_sum / cnt) / scale
    out[X.pull_tilt] = np.rad2deg(pt_sum / cnt) / scale
    s[S_PH1] = _ema(s[S_PH1], out[X.pull_h], min(1.0, cnt * a1))
    out[X.pull_h_ema_1] = s[S_PH1]
    out[X.d_imu] = d_imu
    out[X.d_mimu] = _heading(s[Q_MIMU], s[Q_MIMU + 1], s[Q_MIMU + 2], s[Q_MIMU + 3], qw, qx, qy, qz)
    out[X.d_slow] = _heading(s[Q_SLOW], s[Q_SLOW + 1], s[Q_SLOW + 2], s[Q_SLOW + 3], qw, qx, qy, qz)
    out[X.d_anchor] = _heading_of(s, Q_ANC, qw, qx, qy, qz)
    out[X.t_anchor] = min(3.0, s[S_TANC] / 10.0)
    out[X.nd_ema_05] = s[S_ND05]
    out[X.nd_ema_2] = s[S_ND2]
    out[X.nd_ema_8] = s[S_ND8]
    out[X.dd_ema_05] = s[S_DD05]
    out[X.dd_ema_2] = s[S_DD2]
    out[X.gyro_ema_1] = s[S_G1]
    out[X.resid_ema] = s[S_RES]
    out[X.still_ema_1] = s[S_ST1]
    out[X.t_still] = min(3.0, s[S_TST] / 10.0)
    out[X.d_imu_d1] = d_imu - hist[(c - lag1) % length]
    out[X.d_imu_d4] = d_imu - hist[(c - lag4) % length]
    out[X.mh_raw] = _mag_heading(qw, qx, qy, qz, mag[j, 0], mag[j, 1], mag[j, 2])
    out[X.clean_frac_4] = s[S_CLEAN4]
    b0, b1, b2 = s[B_GYRO], s[B_GYRO + 1], s[B_GYRO + 2]
    up = 2.0 * (qx * qz - qw * qy) * b0 + 2.0 * (qy * qz + qw * qx) * b1 + (1.0 - 2.0 * (qx * qx + qy * qy)) * b2
    out[X.b_up] = np.rad2deg(up)
    out[X.d_bc_anchor] = _heading_of(s, Q_BCA, qw, qx, qy, qz)
    out[X.d_bc_imu] = _heading_of(s, Q_BCI, qw, qx, qy, qz)
    out[X.mh_clean] = s[S_MHC]
    out[X.b_norm] = np.rad2deg(np.sqrt(b0 * b0 + b1 * b1 + b2 * b2))
    for k in range(out.shape[0]):
        out[k] = min(_HIGH[k], max(_LOW[k], out[k]))
