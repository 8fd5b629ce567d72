"""The extended observation of ``magenv/MagKalman-v0`` (``features="extended"``): extra causal features with memory.

All are computed from the sensor stream, the filter's own signals and
estimates (``magenv.filters.kalman_trust.SIGNALS``) and the model-based
disturbance ‖d̂‖ — never truth — by :func:`update`, which the env's kernel
calls after each step on the samples just fused (``start:stop``); the values
describe the decision at sample ``stop``, the same timing as the 19 base
features. ``magenv.envs.kalman`` appends to [base, extra] their copies 8 and
32 decisions earlier (the memory).

Conventions (ENU earth frame, angles in degrees, signed, wrapped to ±180):

* "heading(a ⊗ b*)" is the signed rotation about earth-up from orientation b
  to a (``magenv.envs.blend_memory``'s convention, that of ``magenv.metrics``).
* "mag heading" of sample i is atan2(east, north) of its field in the earth
  frame of the a-priori estimate (after the gyro prediction and accelerometer
  update of sample i, before its magnetometer update): ν_m,i + h_ENU; ≈ minus
  the heading error in a clean field.
* An EMA of time constant τ takes each sample with weight Δt/τ.
* A sample is *clean* when | ‖m‖ − m0 | < 1 µT, its dip deviation < 1° and
  ‖d̂‖ < 1 µT; the "anchor" is a gyro-only propagation of the orientation
  (q ← q ⊗ exp(½(ω_{i−1} + ω_i)Δt)) reset to the estimate on clean samples, so
  heading(q̂ ⊗ q_anc*) is the heading the magnetometer has added since the
  field was last clean.
* The "still anchor" q_still is the anchor propagated only by samples whose
  ‖ω_i‖ ≥ 2 °/s (``STILL_RATE_DPS``: far above the gyro noise, 0.1–0.5 °/s
  per axis, and its bias, 0.2 °/s): while the MIMU is still it holds the
  orientation of the last clean sample, so the gyro bias (which the filter
  does not estimate, and which drifts a refused-magnetometer heading by up to
  ~0.5 °/s) does not enter it. heading(q̂ ⊗ q_still*) is then a causal estimate
  of the signed heading error of a still MIMU under a steady disturbance, and
  ``pull_still`` says whether the magnetometer pulls the estimate toward the
  anchor (> 0) or away from it.
* ``d_perp`` reads the heading error from the field components a disturbance
  fixed in the sensor frame leaves alone. The residual r = m − q̄*⊗h_ENU⊗q̄
  (sensor frame; q̄ the estimate at the magnetometer's sample time,
  ``MAG_DELAY_SAMPLES`` before the current sample: the sensor's sampling lag
  and FIR delay) is dominated by the disturbance; its principal direction u
  (EMA τ 2 s of rrᵀ, power iteration) is the disturbance's. Projected across
  u, r ≈ δ·g with g the field's change per radian of heading, so the
  least-squares δ = Σ(P_u g)·(P_u r)/Σ‖P_u g‖² (EMAs τ 0.25 s) estimates the
  signed heading error, heading(q̂ ⊗ q_true*), without truth. The delay (3,
  4, 4.5 or 5 samples) and time constants were chosen on ``dynamic_magnet``
  training trials (seeds 10000–10005; correlation with the true error 0.83,
  0.7° rms off an error of 1.4° rms). A magnet that moves relative to the
  sensor (``stationary_magnet``'s hand-held one) changes u: there it
  correlates only ≈ 0.3 with the error, and ``perp_info`` (how much of the
  heading's signal is left across u) tells the student how far to read it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from magenv.envs import lagged
from magenv.envs.blend_memory import _heading
from magenv.envs.features import DEG, HEADING, SHARED, Feature, FeatureTable, clipper
from magenv.filters.kalman_trust import SIG
from magenv.quaternion import from_rotvec1, mul1, normalize1, rotate_inv1

EXTRA = FeatureTable(
    SHARED["mh_ema_025"],
    SHARED["mh_ema_1"],
    SHARED["mh_ema_4"],
    Feature("mh_clean", *HEADING, DEG, "EMA (τ 1 s) of the mag heading over clean samples only"),
    Feature("mh_j", *HEADING, DEG, "mag heading of the next sample j (the peek's a-priori innovation)"),
    Feature("d_anchor", *HEADING, DEG, "heading(q̂ ⊗ q_anc*), q_anc the gyro-only anchor re-set on clean samples"),
    Feature("t_anchor", 0.0, 3.0, "units of 10 s", "time since the last clean sample (clipped)"),
    Feature("d_gyro", *HEADING, DEG, "heading(q̂ ⊗ q_gyr*), q_gyr the gyro-only propagation from the start"),
    SHARED["nd_ema_05"],
    SHARED["nd_ema_2"],
    SHARED["nd_ema_8"],
    SHARED["dd_ema_05"],
    SHARED["dd_ema_2"],
    Feature("md_ema_1", 0.0, 10.0, "fraction of m0", "EMA (τ 1 s) of ‖d̂‖/m0"),
    Feature("md_ema_4", 0.0, 10.0, "fraction of m0", "EMA (τ 4 s) of ‖d̂‖/m0"),
    SHARED["gyro_ema_1"],
    Feature("trust_ema_1", 0.0, 1.0, "–", "EMA (τ 1 s) of the trust γ applied"),
    Feature("nis_ema_1", 0.0, 10.0, "decades", "log10(1 + EMA (τ 1 s) of the NIS)"),
    SHARED["clean_ema_4"],
    Feature("d_still", *HEADING, DEG, "heading(q̂ ⊗ q_still*), q_still the still anchor"),
    Feature(
        "pull_still",
        *HEADING,
        DEG,
        "−sign(d_still)·ν_m,j,east/(m0 cos θ0): a full update's heading correction toward the still anchor",
    ),
    Feature("d_perp", *HEADING, DEG, "heading error seen by the field across the disturbance direction u"),
    Feature("perp_info", 0.0, 1.0, "–", "EMA (τ 0.25 s) of ‖P_u g‖²/(m0 cos θ0)²: how much heading d_perp sees"),
    Feature(
        "pull_perp",
        *HEADING,
        DEG,
        "−sign(d_perp)·ν_m,j,east/(m0 cos θ0): a full update's heading correction against d_perp",
    ),
)
X = EXTRA.ix
_LOW, _HIGH = EXTRA.low64, EXTRA.high64
CLEAN_NORM_UT, CLEAN_DIP_DEG, CLEAN_DIST_UT = 1.0, 1.0, 1.0
T_ANCHOR_SCALE_S = 10.0
STILL_RATE_DPS = 2.0  # °/s: a sample with a smaller ‖ω‖ leaves the still anchor where it is
_STILL_RATE = np.deg2rad(STILL_RATE_DPS)
MAG_DELAY_SAMPLES = 4.5  # the magnetometer's sample lags the estimate's by this many samples (d_perp)
DIRECTION_TAU_S, PERP_TAU_S = 2.0, 0.25  # EMAs of the residual's second moment (u) and of d_perp's sums

# layout of the state vector: two quaternions, the EMAs and the time since clean, then the still anchor
Q_ANC, Q_GYR = 0, 4
(S_MH025, S_MH1, S_MH4, S_MHC, S_ND05, S_ND2, S_ND8, S_DD05, S_DD2, S_MD1, S_MD4, S_G1, S_TR1, S_NIS1, S_CLEAN4,
 S_TANC) = range(8, 24)  # fmt: skip
Q_STILL = 24
U_DIR, C_RES = 28, 31  # the disturbance direction u (3) and the residual's second moment (3 × 3, row-major)
S_PN, S_PD = 40, 41  # EMAs of (P_u g)·(P_u r) and ‖P_u g‖²
N_STATE = 42


class Memory(lagged.Memory):
    """The streaming state of the extra features of one trial (``lagged.Memory``: state and value)."""

    @classmethod
    def start(cls, q0: np.ndarray) -> Memory:
        """Memory at the start of a trial: the gyro-only references at the initial estimate ``q0``."""
        state = lagged.anchored(N_STATE, q0, (Q_ANC, Q_GYR, Q_STILL))
        state[U_DIR : U_DIR + 3] = 1.0 / np.sqrt(3.0)  # any start off the axes: the power iteration turns it
        state[S_TR1] = 1.0
        return cls(state, np.zeros(len(EXTRA)))


@njit(cache=True, inline="always")
def _ema(old, new, a):
    return old + a * (new - old)


_clip = clipper(EXTRA, neutral_nan=True)


@njit(cache=True, inline="always")
def _mag_heading(sig, h_ref):
    """Mag heading (deg) from a signal row: atan2 of the east and north components of ν_m + h_ENU."""
    return np.rad2deg(np.arctan2(sig[SIG.nu_e] + h_ref[0], sig[SIG.nu_n] + h_ref[1]))


@njit(cache=True)
def _propagate(s, o, w, dt):
    """s[o:o+4] ← s[o:o+4] ⊗ exp(w·dt) (w rad/s, sensor frame)."""
    q = normalize1(mul1(s[o : o + 4].copy(), from_rotvec1(w * dt)))
    s[o : o + 4] = q


@njit(cache=True, inline="always")
def _pull(d, peek, hh):
    """A full update's heading correction (°) against the signed heading error ``d``: −sign(d)·ν_m,j,east/hh,
    ``peek`` the a-priori signals of sample j, hh = m0·cos θ0 (µT; 0 if hh ≤ 0)."""
    return -np.sign(d) * np.rad2deg(peek[SIG.nu_e] / hh) if hh > 0.0 else 0.0


@njit(cache=True)
def _perp_sums(s, mag, qa, qb, h_ref, turn, a_u, a_p):
    """One sample of ``d_perp``'s sums: the residual r = m − q̄* ⊗ h_ENU ⊗ q̄ (sensor frame, µT) at the
    magnetometer's sample time, q̄ the normalised mean of the estimates ``qa``, ``qb`` on either side of it; its
    second moment C (EMA, weight ``a_u``) and C's principal direction u (one power-iteration step a sample); the
    EMAs (weight ``a_p``) of (P_u g)·(P_u r) and ‖P_u g‖², P_u = I − uuᵀ, g = q̄* ⊗ ``turn`` ⊗ q̄ the field's
    change per radian of heading (``turn`` = up × h_ENU). A disturbance along u moves no component P_u sees, so
    their ratio is the heading error (rad) the undisturbed components show (least squares, linearised)."""
    sign = 1.0 if qa[0] * qb[0] + qa[1] * qb[1] + qa[2] * qb[2] + qa[3] * qb[3] >= 0.0 else -1.0
    qm = normalize1(qa + sign * qb)
    pred = rotate_inv1(qm, h_ref)
    g = rotate_inv1(qm, turn)
    r = mag - pred
    u = s[U_DIR : U_DIR + 3].copy()
    gp = g - np.dot(g, u) * u
    rp = r - np.dot(r, u) * u
    s[S_PN] = _ema(s[S_PN], np.dot(gp, rp), a_p)
    s[S_PD] = _ema(s[S_PD], np.dot(gp, gp), a_p)
    c = s[C_RES : C_RES + 9].reshape(3, 3)
    for k in range(3):
        for m in range(3):
            c[k, m] = _ema(c[k, m], r[k] * r[m], a_u)
    cu = c @ u
    norm = np.sqrt(np.dot(cu, cu))
    if norm > 0.0:
        s[U_DIR : U_DIR + 3] = cu / norm


@njit(cache=True)
def update(params, sensors, mdist, est, sig, trust, peek, mem, start, stop):
    """Consume samples ``start:stop`` (1 ≤ ``start`` < ``stop``) just fused; ``mem.value`` = the extra features at
    sample ``stop``.

    Args:
        params: ``magenv.filters.kalman_trust.Params``. sensors: the trial's ``Sensors``.
        mdist: (N,) ‖d̂‖, µT. est: (N, 4) the env's estimates. sig: (N, NSIG) the filter's signals per sample.
        trust: (N,) γ per sample. peek: (NSIG,) the a-priori signals of sample ``stop``. mem: :class:`Memory`.
    """
    gyr, mag = sensors.gyr, sensors.mag
    s, out = mem.state, mem.value
    dt, m0, h_ref = params.dt, params.m0, params.h_ref
    a025, a05, a1, a2, a4, a8 = dt / 0.25, dt / 0.5, dt, dt / 2.0, dt / 4.0, dt / 8.0
    a_u, a_p = dt / DIRECTION_TAU_S, dt / PERP_TAU_S
    turn = np.array([-h_ref[1], h_ref[0], 0.0])  # up × h_ENU
    for i in range(start, stop):
        row = sig[i]
        mh = _mag_heading(row, h_ref)
        dm = row[SIG.mag_norm_dev]
        dd = row[SIG.dip_dev]
        if dd != dd:
            dd = 0.0
        md = mdist[i]
        clean = abs(dm) < CLEAN_NORM_UT and abs(dd) < CLEAN_DIP_DEG and md < CLEAN_DIST_UT
        w = 0.5 * (gyr[i - 1] + gyr[i])
        w_norm = np.sqrt(gyr[i, 0] ** 2 + gyr[i, 1] ** 2 + gyr[i, 2] ** 2)  # ‖ω_i‖, rad/s
        _propagate(s, Q_GYR, w, dt)
        if clean:
            s[Q_ANC : Q_ANC + 4] = est[i]
            s[Q_STILL : Q_STILL + 4] = est[i]
            s[S_TANC] = 0.0
            s[S_MHC] = _ema(s[S_MHC], mh, a1)
        else:
            _propagate(s, Q_ANC, w, dt)
            if w_norm >= _STILL_RATE:
                _propagate(s, Q_STILL, w, dt)
            s[S_TANC] += dt
        s[S_MH025] = _ema(s[S_MH025], mh, a025)
        s[S_MH1] = _ema(s[S_MH1], mh, a1)
        s[S_MH4] = _ema(s[S_MH4], mh, a4)
        s[S_ND05] = _ema(s[S_ND05], dm / m0, a05)
        s[S_ND2] = _ema(s[S_ND2], dm / m0, a2)
        s[S_ND8] = _ema(s[S_ND8], abs(dm) / m0, a8)
        s[S_DD05] = _ema(s[S_DD05], abs(dd), a05)
        s[S_DD2] = _ema(s[S_DD2], dd, a2)
        s[S_MD1] = _ema(s[S_MD1], md / m0, a1)
        s[S_MD4] = _ema(s[S_MD4], md / m0, a4)
        s[S_G1] = _ema(s[S_G1], w_norm, a1)
        s[S_TR1] = _ema(s[S_TR1], trust[i], a1)
        s[S_NIS1] = _ema(s[S_NIS1], row[SIG.nis], a1)
        s[S_CLEAN4] = _ema(s[S_CLEAN4], 1.0 if clean else 0.0, a4)
        lag = i - MAG_DELAY_SAMPLES
        _perp_sums(s, mag[i], est[max(int(np.ceil(lag)), 0)], est[max(int(np.floor(lag)), 0)], h_ref, turn, a_u, a_p)
    q = est[stop - 1]
    out[X.mh_ema_025] = _clip(s[S_MH025], X.mh_ema_025)
    out[X.mh_ema_1] = _clip(s[S_MH1], X.mh_ema_1)
    out[X.mh_ema_4] = _clip(s[S_MH4], X.mh_ema_4)
    out[X.mh_clean] = _clip(s[S_MHC], X.mh_clean)
    out[X.mh_j] = _clip(_mag_heading(peek, h_ref), X.mh_j)
    a, g = Q_ANC, Q_GYR
    out[X.d_anchor] = _clip(_heading(q[0], q[1], q[2], q[3], s[a], s[a + 1], s[a + 2], s[a + 3]), X.d_anchor)
    out[X.t_anchor] = _clip(s[S_TANC] / T_ANCHOR_SCALE_S, X.t_anchor)
    out[X.d_gyro] = _clip(_heading(q[0], q[1], q[2], q[3], s[g], s[g + 1], s[g + 2], s[g + 3]), X.d_gyro)
    out[X.nd_ema_05] = _clip(s[S_ND05], X.nd_ema_05)
    out[X.nd_ema_2] = _clip(s[S_ND2], X.nd_ema_2)
    out[X.nd_ema_8] = _clip(s[S_ND8], X.nd_ema_8)
    out[X.dd_ema_05] = _clip(s[S_DD05], X.dd_ema_05)
    out[X.dd_ema_2] = _clip(s[S_DD2], X.dd_ema_2)
    out[X.md_ema_1] = _clip(s[S_MD1], X.md_ema_1)
    out[X.md_ema_4] = _clip(s[S_MD4], X.md_ema_4)
    out[X.gyro_ema_1] = _clip(s[S_G1], X.gyro_ema_1)
    out[X.trust_ema_1] = _clip(s[S_TR1], X.trust_ema_1)
    out[X.nis_ema_1] = _clip(np.log10(1.0 + s[S_NIS1]), X.nis_ema_1)
    out[X.clean_ema_4] = _clip(s[S_CLEAN4], X.clean_ema_4)
    c = Q_STILL
    d_still = _heading(q[0], q[1], q[2], q[3], s[c], s[c + 1], s[c + 2], s[c + 3])
    out[X.d_still] = _clip(d_still, X.d_still)
    hh = m0 * np.cos(params.dip0)
    out[X.pull_still] = _clip(_pull(d_still, peek, hh), X.pull_still)
    d_perp = np.rad2deg(s[S_PN] / s[S_PD]) if s[S_PD] > 0.0 else 0.0
    out[X.d_perp] = _clip(d_perp, X.d_perp)
    out[X.perp_info] = _clip(s[S_PD] / hh**2, X.perp_info) if hh > 0.0 else 0.0
    out[X.pull_perp] = _clip(_pull(d_perp, peek, hh), X.pull_perp)
