"""AEKF, MAGYQ and Delay MAGYQ (Combettes & Renaudin 2016) and a quasi-static-field (QSF) detector.

One numba step kernel serves the three filters (``MODE_AEKF``, ``MODE_MAGYQ``,
``MODE_DELAY``); they share the state, the prediction and the accelerometer
update and differ only in the magnetic update, so a comparison isolates the
magnetic hypothesis. The kernels work on named structures — :class:`Params`
(floats, by value), :class:`State` (arrays updated in place), :class:`Inputs`
(a trial's per-sample sensors, magnetic actions and trusts) and
:class:`Outputs` (per-sample estimate and ``SIGNALS``) — so one env, N batched
envs or a whole offline trial (:func:`run_trial`) run the same :func:`step1`.

Reading of the paper in magenv's conventions
--------------------------------------------
The paper's ``q_b^n`` maps body → navigation frame with ``v^n = q ⊗ v^b ⊗ q̄``
and its navigation frame is ENU (§3.2): that *is* magenv's convention
(scalar-first Hamilton, sensor → ENU), so nothing is converted.

* State (eq. 16): ``x = [q (4), b_q (4), b_a (3)]`` — the orientation, the
  gyroscope *quaternion* bias of eq. 5 and the accelerometer bias of eq. 2.
* Prediction (eqs. 17–18): ``q_yg = exp(½ T_s ω̄)`` with ω̄ the trapezoidal
  mean of two causal gyro samples (eq. 17 as printed lacks the ``Δt/2`` that
  eq. 5's definition gives), ``q̂_ω = normalise(q_yg − b_q)``,
  ``q ← q ⊗ q̂_ω``; biases are random walks.
* Covariance (eqs. 19–20): ``F = [[C(q̂_ω), −M(q), 0], [0, I, 0], [0, 0, I]]``
  with ``q1 ⊗ q2 = M(q1) q2 = C(q2) q1``; ``G Q Gᵀ`` = ``(σ_g T_s/2)² M Mᵀ``
  for the gyro quaternion noise and ``σ_b² T_s`` per bias component (eq. 19's
  G prints ``T_s I`` twice; we read the bias blocks as random walks with
  densities σ_bq, σ_ba per √s).
* Accelerometer update (same in all three filters; not detailed in the
  paper): ``z = g_ENU``, ``h(x) = q ⊗ (y_a − b_a) ⊗ q̄``, R = σ_a² I, skipped
  when ``| |y_a| − g | ≥ th_acc``. The gate is off by default, as in the
  paper ("the linear acceleration sensed by the MIMU perturbs the
  orientation estimation for all filters", §6): in simulated arm swinging a
  norm gate keeps exactly the samples whose acceleration is *tangential*
  (norm ≈ g, direction wrong), and the accelerometer and gyro bias states
  then run away (tilt errors > 90° observed), while ungated updates average
  out over the swing. ``acc_adaptive`` = k inflates R_a by (k·(|y_a| − g))²
  (off by default; in simulated swinging it makes the tilt worse).
  Sensitivity found in simulation: with the paper's σ_a = 0.1 g, arm-swing
  accelerations corrupt the gyro-bias states of MAGYQ when few QSF periods
  are found (yaw errors of tens of degrees); σ_a ≈ 3 m/s² avoids it
  (``python -m magenv.baselines.qsf paper sigma_acc=3.0``).
* AEKF magnetic update: ``z = m_Earth`` (hypothesis H0), ``h = q ⊗ y_m ⊗ q̄``,
  R = σ_m² I. (Bar-Itzhack & Oshman's AEKF has no bias states; ours shares
  MAGYQ's 11 states so that only the magnetic hypothesis differs.)
* MAGYQ QSF update (eqs. 6–9): at the period start t0 the reference
  ``m_ref = q̂_t0 ⊗ y_m(t0) ⊗ q̄̂_t0`` (eq. 8); afterwards the innovation
  ``δz = m_ref − q̂ ⊗ y_m ⊗ q̄̂`` (eq. 9), gain eq. 27 with R = σ_m² I (the
  reference is treated as exact).
* Delay MAGYQ (eqs. 13–15, 21–28): the covariance is augmented with the
  estimate at t0 (stochastic cloning, ref. [10]): ``P̆ = [[P, Cov(δx, δq_t0)],
  [·, P_q,t0]]`` with ``Cov(δx_k, δq_t0) = Γ_{t0,k} [P_q,t0 P_(q,b),t0]ᵀ``
  (eq. 22) — propagated as ``C ← F C``; ``H̆ = [H_k 0 −H_t0]`` (eq. 13/23) with
  ``H_t0`` the Jacobian of eq. 8 at (q̂_t0, y_m(t0)); noise
  ``C_k R_m C_kᵀ + C_t0 R_m C_t0ᵀ = 2σ_m² I`` (eq. 15's ``M R_m Mᵀ`` read as
  the two independent magnetometer noises it combines); full augmented gain
  (eq. 23 ≡ eq. 28) and Joseph-form update of P̆ (eq. 25 ≡ eq. 26). The
  paper says the measurement error is "distributed not only on the estimate
  at the current time but also on the orientation at the first epoch"
  (§5.4.2): the t0 estimate is corrected by ``K_q,t0 δz`` too, and the
  reference recomputed from it (``update_reference``; off = eq. 24 read
  literally, only x_k corrected). While a period is active every update,
  the accelerometer's included, runs on the augmented system.
* The Jacobian of ``h(q) = q ⊗ v ⊗ q̄`` (eq. 12/14's ``2[A a·I − [A×]]``) is
  written here directly in q = [w, u]:
  ``∂h/∂w = 2(w v + u × v)``, ``∂h/∂u = 2((u·v) I + u vᵀ − v uᵀ − w [v×])``.
* After every update q (and q̂_t0) is renormalised and the covariance
  projected on the unit sphere's tangent (``(I − q qᵀ)``) plus a tiny radial
  variance ``eps`` keeping it positive definite; then
  ``kalman_threshold.repair_cov1`` symmetrises it and floors its eigenvalues
  if needed. A non-finite sample or covariance makes the kernel return −1
  and the Python wrappers raise ``FilterError`` — never a silent NaN.

Defaults (§5.3): accelerometer and magnetometer noise "10 % of the signal":
σ_a = 0.1 g, σ_m = 0.1 m0; gyro noise from the sensor.

QSF detector (the paper leaves the rule open; §7 says it should be improved)
------------------------------------------------------------------------------
Magnetometer/gyro consistency, independent of the filter: the field is
rotated into a *gyro-only* frame ``m_g = q_g ⊗ y_m ⊗ q̄_g`` (``q_g`` integrates
the raw gyro from the identity, so within seconds it differs from the earth
frame by a constant rotation plus bias drift). A steady field gives a steady
m_g whatever the motion. Per sample: ``spread`` = RMS distance of the last
``window`` samples of m_g from their mean (µT). Sample i is *steady* when the
window is full and ``spread < th_spread``. A period starts at the first
steady sample (code 1) and continues (code 2) while samples stay steady,
``|m_g(i) − m_g(t0)| < th_drift`` (slow drifts that pass the window test),
and the period is younger than ``max_period`` s; otherwise a new period
starts (code 1) or, if not steady, none (code 0). Codes depend only on
samples ≤ i (causal) and not on the filter, so they can be computed for a
whole trial up front.

Per-sample signals (``SIGNALS``, the columns of ``Outputs.sig``; truth-free,
for the §5.5 test and a policy) are listed in ``SIGNALS`` below.
"""

from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from magenv import quaternion as quat
from magenv.checks import check_bool, check_choice, check_noise, check_number, check_positive, check_site, check_vector
from magenv.filters.kalman_threshold import COV_FLOOR, FilterError, finite3, is_pd, repair_sym
from magenv.filters.linalg import inv3, joseph_update, project_quaternion, quad3
from magenv.filters.solvers import triad1
from magenv.quaternion import GRAVITY, from_rotvec4, left_matrix4, mul4, normalize4, right_matrix4, rotate3
from magenv.trial import START_FROM_TRUTH

MODE_AEKF, MODE_MAGYQ, MODE_DELAY = 0, 1, 2
MODES = {"aekf": MODE_AEKF, "magyq": MODE_MAGYQ, "delay_magyq": MODE_DELAY}
# magnetic actions of a sample (detector code / policy decision)
MAG_NONE, MAG_START, MAG_KEEP = 0, 1, 2

# Layout of the state vector x (eq. 16) and of its clone q̂_t0 (Delay MAGYQ, eqs. 21–22).
ORIENTATION = slice(0, 4)  # q, sensor → ENU
GYRO_BIAS = slice(4, 8)  # b_q, the gyroscope quaternion bias (eq. 5)
ACC_BIAS = slice(8, 11)  # b_a, the accelerometer bias (eq. 2), m/s²
CLONE = slice(11, 15)  # q̂_t0, the estimate at the period's start
N_STATE = 11  # [q, b_q, b_a]
N_AUGMENTED = 15  # + the clone

SIGNALS = (
    "qsf_active",  # 1 while a QSF period is active after this sample (MAGYQ/Delay), else 0
    "innov_norm",  # |δz| of the magnetic update (or of the reference mismatch if gated off), µT
    "nis",  # δzᵀ S⁻¹ δz of the magnetic update (0 without one)
    "corr_norm",  # |K_q δz|: norm of the quaternion correction by the magnetic update (§5.5, Fig. 10)
    "age",  # time since the period's start, s (0 without period)
    "trust",  # gain multiplier applied to the magnetic update (0 if none ran)
    "heading_std",  # sqrt of the heading (earth z) variance from P, rad
    "acc_used",  # 1 if the accelerometer update ran
    "mag_updated",  # 1 if a magnetic update ran
)
N_SIGNALS = len(SIGNALS)
SIGNAL: Any = namedtuple("SignalIndex", SIGNALS)(*range(N_SIGNALS))  # SIGNAL.nis == 2, … (columns of Outputs.sig)

SIGMA_GYR = np.deg2rad(0.3)  # rad/s per sample, a smartphone-grade default
SIGMA_BIAS_WALK = np.deg2rad(0.01)  # rad/s per √s
SIGMA_ACC_BIAS_WALK = 1e-4  # m/s² per √s
TH_ACC = np.inf  # m/s², accelerometer norm gate: off by default (the paper gates nothing, §6)
P0_ANGLE = np.deg2rad(2.0)  # rad, initial orientation std (per error angle)
P0_GYR_BIAS = np.deg2rad(0.5)  # rad/s, initial gyro bias std
P0_ACC_BIAS = 0.01  # m/s², initial accelerometer bias std (small: with little rotation, e.g. walking on a
#                     treadmill, a loose b_a absorbs linear acceleration and drags the tilt off)
RADIAL_EPS = 1e-12  # variance kept along q after the tangent projection
CLONE_JITTER = 1e-10  # variance added to the clone at t0 (quaternion units², ~1e-5 rad)
MAX_AGE_S = 60.0  # a period older than this is restarted whatever the action


class Params(NamedTuple):
    """The filters' parameters (:func:`make_params`), passed to the kernels by value."""

    mode: int  # MODE_AEKF, MODE_MAGYQ or MODE_DELAY
    sigma_gyr: float  # gyroscope white noise σ_g, rad/s
    sigma_bias_walk: float  # gyroscope bias random walk σ_bq, rad/s per √s
    sigma_acc_bias_walk: float  # accelerometer bias random walk σ_ba, m/s² per √s
    sigma_acc: float  # accelerometer noise σ_a, m/s²
    sigma_mag: float  # magnetometer noise σ_m, µT
    th_acc: float  # accelerometer gate: update only while | |y_a| − g | < th_acc, m/s² (inf: never gated)
    gravity: tuple[float, float, float]  # g_ENU, the accelerometer's reference, m/s²
    earth_field: tuple[float, float, float]  # m_Earth in ENU, µT (the AEKF's reference, hypothesis H0)
    cov_floor: float  # eigenvalue floor of a repaired covariance (``kalman_threshold.repair_cov1``)
    radial_eps: float  # variance kept along q after the tangent projection
    update_reference: bool  # Delay MAGYQ also corrects q̂_t0 and the reference (else eq. 24 literally)
    max_age_s: float  # a period older than this is restarted whatever the action, s
    acc_adaptive: float  # k ≥ 0: R_a = σ_a² + (k·(|y_a| − g))² (0: the paper's constant R_a)


class State(NamedTuple):
    """The filter's state, updated in place by the kernels (:func:`initial_state`)."""

    x: np.ndarray  # (N_AUGMENTED,) [q, b_q, b_a] (eq. 16) and the clone q̂_t0 (slices ORIENTATION … CLONE)
    cov: np.ndarray  # (N_AUGMENTED, N_AUGMENTED) P̆; the clone's rows and columns are 0 outside a Delay period
    period_active: np.ndarray  # (1,) bool: a QSF period is active (never for the AEKF)
    period_age: np.ndarray  # (1,) time since the period started, s
    mag_t0: np.ndarray  # (3,) y_m(t0), the field measured at the period's start, µT, sensor frame
    mag_ref: np.ndarray  # (3,) m_ref = q̂_t0 ⊗ y_m(t0) ⊗ q̄̂_t0 (eq. 8), µT, ENU


class Inputs(NamedTuple):
    """A trial's per-sample inputs of the kernels: N rows."""

    gyr: np.ndarray  # (N, 3) rad/s, sensor frame
    acc: np.ndarray  # (N, 3) m/s², sensor frame
    mag: np.ndarray  # (N, 3) µT, sensor frame
    action: np.ndarray  # (N,) int8 magnetic action MAG_NONE / MAG_START / MAG_KEEP (ignored by the AEKF)
    trust: np.ndarray  # (N,) ∈ [0, 1], the gain multiplier of the magnetic update


class Outputs(NamedTuple):
    """Per-sample outputs of the kernels: N rows."""

    q: np.ndarray  # (N, 4) the estimate after each sample, sensor → ENU (NaN where not run)
    sig: np.ndarray  # (N, N_SIGNALS) the signals of each sample, columns SIGNALS (0 where not run)

    @classmethod
    def empty(cls, n: int) -> Outputs:
        return cls(np.full((n, 4), np.nan), np.zeros((n, N_SIGNALS)))


def make_params(
    field_norm: float,
    field_dip: float,
    mode="delay_magyq",
    sigma_gyr: float = SIGMA_GYR,
    sigma_acc: float | None = None,
    sigma_mag: float | None = None,
    th_acc: float = TH_ACC,
    sigma_bias_walk: float = SIGMA_BIAS_WALK,
    sigma_acc_bias_walk: float = SIGMA_ACC_BIAS_WALK,
    update_reference: bool = True,
    max_age_s: float = MAX_AGE_S,
    acc_adaptive: float = 0.0,
) -> Params:
    """:class:`Params` of the kernels; ValueError / TypeError naming a bad argument (``magenv.checks``).

    Args:
        field_norm: Earth field m0, µT; field_dip: ° down (used by the AEKF reference and TRIAD init;
            ``magenv.checks.check_site``).
        mode: "aekf", "magyq" or "delay_magyq".
        sigma_gyr: gyro white noise, rad/s. sigma_acc: m/s² (default 0.1 g, §5.3).
        sigma_mag: µT (default 0.1·m0, §5.3). th_acc: accelerometer norm gate, m/s² > 0 (inf = never gated).
        sigma_bias_walk: gyro bias random walk, rad/s per √s. sigma_acc_bias_walk: m/s² per √s.
            Every σ finite > 0.
        update_reference: Delay MAGYQ corrects the t0 estimate (and the reference) too (a bool).
        max_age_s: a QSF period is restarted once older than this, s (finite > 0).
        acc_adaptive: k ≥ 0; the accelerometer variance becomes σ_a² + (k·(|y_a| − g))² (0 = the paper's
            constant R_a).
    """
    check_choice("mode", mode, tuple(MODES))
    field_norm, field_dip = check_site(field_norm, field_dip)
    sigma_acc = 0.1 * GRAVITY if sigma_acc is None else sigma_acc
    sigma_mag = 0.1 * field_norm if sigma_mag is None else sigma_mag
    vector = lambda v: (float(v[0]), float(v[1]), float(v[2]))
    return Params(
        MODES[mode],
        check_noise("sigma_gyr", sigma_gyr, "gyr"),
        check_positive("sigma_bias_walk", sigma_bias_walk),
        check_positive("sigma_acc_bias_walk", sigma_acc_bias_walk),
        check_noise("sigma_acc", sigma_acc, "acc"),
        check_noise("sigma_mag", sigma_mag, "mag"),
        check_positive("th_acc (m/s²; inf disables the gate)", th_acc, inf_ok=True),
        vector(quat.gravity_up()),
        vector(quat.earth_field(field_norm, field_dip)),
        float(COV_FLOOR),
        float(RADIAL_EPS),
        check_bool("update_reference", update_reference),
        check_positive("max_age_s", max_age_s),
        check_number("acc_adaptive", acc_adaptive, 0.0),
    )


# ------------------------------------------------------------ small matrices


@njit(cache=True, inline="always")
def jacobian34(q, v, sign):
    """``sign ·`` the 3×4 Jacobian of ``h(q) = q ⊗ v ⊗ q̄`` with respect to q = [w, u] (eqs. 12, 14), a 12-tuple
    (row-major): ``∂h/∂w = 2(w v + u × v)``, ``∂h/∂u = 2((u·v) I + u vᵀ − v uᵀ − w [v×])``."""
    w, ux, uy, uz = q[0], q[1], q[2], q[3]
    v0, v1, v2 = v[0], v[1], v[2]
    cx = uy * v2 - uz * v1
    cy = uz * v0 - ux * v2
    cz = ux * v1 - uy * v0
    uv = ux * v0 + uy * v1 + uz * v2
    s2 = 2.0 * sign
    return (
        s2 * (w * v0 + cx), s2 * (ux * v0 - v0 * ux + uv), s2 * (ux * v1 - v0 * uy) + s2 * w * v2,
        s2 * (ux * v2 - v0 * uz) - s2 * w * v1,
        s2 * (w * v1 + cy), s2 * (uy * v0 - v1 * ux) - s2 * w * v2, s2 * (uy * v1 - v1 * uy + uv),
        s2 * (uy * v2 - v1 * uz) + s2 * w * v0,
        s2 * (w * v2 + cz), s2 * (uz * v0 - v2 * ux) + s2 * w * v1, s2 * (uz * v1 - v2 * uy) - s2 * w * v0,
        s2 * (uz * v2 - v2 * uz + uv),
    )  # fmt: skip


@njit(cache=True, inline="always")
def _put_jacobian(h, col, q, v, sign):
    """``h[:, col:col+4] =`` :func:`jacobian34`."""
    j = jacobian34(q, v, sign)
    for r in range(3):
        for c in range(4):
            h[r, col + c] = j[4 * r + c]


@njit(cache=True)
def rot_jacobian1(q, v):
    """3×4 Jacobian of ``h(q) = q ⊗ v ⊗ q̄`` with respect to q = [w, u] (eqs. 12, 14)."""
    j = np.empty((3, 4))
    _put_jacobian(j, 0, q, v, 1.0)
    return j


@njit(cache=True, inline="always")
def heading_row4(q):
    """Row e (4-tuple) with earth-frame heading error ≈ e · δq (δθ_E = 2 vec(δq ⊗ q̄))."""
    return -2.0 * q[3], -2.0 * q[2], 2.0 * q[1], 2.0 * q[0]


# ------------------------------------------------------------ kernel pieces


class Work(NamedTuple):
    """Scratch of the step kernel, allocated once per :func:`run_kernel` call (:func:`work`)."""

    x: np.ndarray  # (N_AUGMENTED,) the state being updated, committed to State if healthy
    p: np.ndarray  # (N_AUGMENTED, N_AUGMENTED) its covariance
    h: np.ndarray  # (3, N_AUGMENTED) measurement Jacobian (nonzero columns: q and one more block)
    hp: np.ndarray  # (3, N_AUGMENTED) H P
    kt: np.ndarray  # (3, N_AUGMENTED) the gain, transposed
    m: np.ndarray  # (4, N_AUGMENTED) the prediction's rows of F P; the Joseph update's G (3 rows)
    lo: np.ndarray  # (N_AUGMENTED, N_AUGMENTED) Cholesky factor of the health test


_N = N_AUGMENTED
_WORK_ENDS = np.cumsum(np.array((_N, _N * _N, 3 * _N, 3 * _N, 3 * _N, 4 * _N, _N * _N)))


@njit(cache=True)
def work():
    """A :class:`Work` (one allocation, carved into views; not initialised: each step writes before it reads)."""
    n, o = _N, _WORK_ENDS
    buf = np.empty(o[-1])
    return Work(
        buf[0 : o[0]],
        buf[o[0] : o[1]].reshape(n, n),
        buf[o[1] : o[2]].reshape(3, n),
        buf[o[2] : o[3]].reshape(3, n),
        buf[o[3] : o[4]].reshape(3, n),
        buf[o[4] : o[5]].reshape(4, n),
        buf[o[5] : o[6]].reshape(n, n),
    )


@njit(cache=True, inline="always")
def _hcol(t, c2):
    """Column of H's t-th nonzero column: q (0…3), then the block starting at c2."""
    return t if t < 4 else c2 + t - 4


@njit(cache=True)
def _predict_cov(w, na, q, q_w):
    """``P ← F P Fᵀ`` of eqs. 19–20 on the leading na×na block of ``w.p`` (symmetric), in place: F is the
    identity but for the q rows ``[C(q̂_ω), −M(q), 0]``, so only q's rows and columns change."""
    p, r = w.p, w.m
    c, m = right_matrix4(q_w), left_matrix4(q)  # q1 ⊗ q2 = C(q2) q1 = M(q1) q2 (eq. 20), rows
    for a in range(4):  # rows of F P: r[a, j] = C[a] · P[q, j] − M[a] · P[b_q, j]
        ca, ma = c[a], m[a]
        for j in range(na):
            r[a, j] = (ca[0] * p[0, j] + ca[1] * p[1, j] + ca[2] * p[2, j] + ca[3] * p[3, j]) - (
                ma[0] * p[4, j] + ma[1] * p[5, j] + ma[2] * p[6, j] + ma[3] * p[7, j]
            )
    for a in range(4):  # the q block of (F P) Fᵀ, upper triangle
        for b in range(a, 4):
            cb, mb = c[b], m[b]
            v = (r[a, 0] * cb[0] + r[a, 1] * cb[1] + r[a, 2] * cb[2] + r[a, 3] * cb[3]) - (
                r[a, 4] * mb[0] + r[a, 5] * mb[1] + r[a, 6] * mb[2] + r[a, 7] * mb[3]
            )
            p[a, b] = v
            p[b, a] = v
    for a in range(4):
        for j in range(4, na):
            v = r[a, j]
            p[a, j] = v
            p[j, a] = v


@njit(cache=True)
def _kalman_update(w, na, c2, n2, nu, r_diag, gain):
    """Joseph-form EKF update of the first na states of ``w.x``, ``w.p`` by a 3-component measurement with
    innovation ``nu`` (3-tuple), R = r_diag·I and gain ``gain``·K; ``w.h`` holds H, nonzero only in the q
    columns and ``n2`` columns from ``c2``. Returns ``(S⁻¹, |Δq|)`` (9-tuple; the norm of q's correction)."""
    p, h, hp, kt = w.p, w.h, w.hp, w.kt
    for mm in range(3):  # H P, row by row, summed over H's nonzero columns in order (from 0.0, in a register)
        for j in range(na):
            v = 0.0
            for t in range(4 + n2):
                col = _hcol(t, c2)
                v += h[mm, col] * p[col, j]
            hp[mm, j] = v
    s00 = s01 = s02 = s11 = s12 = s22 = 0.0
    for t in range(4 + n2):  # S = H P Hᵀ + R, upper triangle
        col = _hcol(t, c2)
        s00 += hp[0, col] * h[0, col]
        s01 += hp[0, col] * h[1, col]
        s02 += hp[0, col] * h[2, col]
        s11 += hp[1, col] * h[1, col]
        s12 += hp[1, col] * h[2, col]
        s22 += hp[2, col] * h[2, col]
    s = (s00 + r_diag, s01, s02, s01, s11 + r_diag, s12, s02, s12, s22 + r_diag)
    s_inv = inv3(s)
    for j in range(na):  # Kᵀ = gain · S⁻¹ H P (K = gain · P Hᵀ S⁻¹, P Hᵀ = (H P)ᵀ)
        h0, h1, h2 = hp[0, j], hp[1, j], hp[2, j]
        kt[0, j] = gain * (h0 * s_inv[0] + h1 * s_inv[3] + h2 * s_inv[6])
        kt[1, j] = gain * (h0 * s_inv[1] + h1 * s_inv[4] + h2 * s_inv[7])
        kt[2, j] = gain * (h0 * s_inv[2] + h1 * s_inv[5] + h2 * s_inv[8])
    x = w.x
    corr = 0.0
    for j in range(na):
        before = x[j]
        x[j] += kt[0, j] * nu[0] + kt[1, j] * nu[1] + kt[2, j] * nu[2]
        if j < 4:
            corr += (x[j] - before) ** 2
    joseph_update(p, na, hp, kt, s, w.m)
    return s_inv, np.sqrt(corr)


@njit(cache=True)
def _renormalise(x, cov, na, eps):
    """Normalise q (and the clone) and project the covariance on the unit-sphere tangent
    (``linalg.project_quaternion``)."""
    for off in (ORIENTATION.start, CLONE.start):
        if off + 4 > na:
            continue
        qn = np.sqrt(x[off] ** 2 + x[off + 1] ** 2 + x[off + 2] ** 2 + x[off + 3] ** 2)
        for i in range(4):
            x[off + i] /= qn
        project_quaternion(cov, na, x[off : off + 4], off, eps)


@njit(cache=True)
def _load(state, w, na):
    """``w.x`` ← ``state.x``, ``w.p`` ← the leading na×na block of ``state.cov`` symmetrised (the rest is 0 by
    construction); False (``w`` partly written) if any of it is not finite."""
    xs, ps = w.x, w.p
    for r in range(N_AUGMENTED):
        xs[r] = state.x[r]
        if not np.isfinite(xs[r]):
            return False
    for r in range(na):
        for c in range(r, na):
            a, b = state.cov[r, c], state.cov[c, r]
            if not (np.isfinite(a) and np.isfinite(b)):
                return False
            v = 0.5 * (a + b)
            ps[r, c] = v
            ps[c, r] = v
    return True


@njit(cache=True)
def _commit_healthy(state, w, na, cov_floor):
    """Covariance health of ``w`` (``kalman_threshold.repair_sym``), then ``w`` → ``state``. Returns the status
    (−1: nothing committed).

    The Cholesky test comes first: when it passes and the diagonal is finite, every entry of the lower triangle
    is finite (a non-finite p_ij, i > j, makes l_ij and then the pivot of row i non-finite or negative, which
    fails the test), so ``repair_sym``'s finiteness pass would pass and its own Cholesky test (the same
    arithmetic) would too: status 0 without them; otherwise ``repair_sym`` decides."""
    p = w.p
    healthy = is_pd(p, na, w.lo)  # every update mirrors one triangle: exactly symmetric
    for r in range(na):
        healthy = healthy and np.isfinite(p[r, r])
    status = 0 if healthy else repair_sym(p, na, cov_floor, w.lo)
    if status < 0:
        return -1
    for r in range(na):
        if not np.isfinite(w.x[r]):
            return -1
    x, cov = state.x, state.cov
    for r in range(N_AUGMENTED):
        x[r] = w.x[r]
    for r in range(na):
        for c in range(na):
            cov[r, c] = w.p[r, c]
    if na == N_STATE:  # keep the unused clone block tidy
        for r in range(N_STATE, N_AUGMENTED):
            for c in range(N_AUGMENTED):
                cov[r, c] = 0.0
                cov[c, r] = 0.0
    return status


@njit(cache=True)
def step_work(p, state, inputs, i, dt, sig, w, synced=False):
    """:func:`step1` with the scratch ``w`` (:class:`Work`). ``synced``: ``w`` holds ``state`` already (the last
    step committed it), so the copy and its checks are skipped — the committed state is finite and exactly
    symmetric (every update mirrors one triangle), which the copy would reproduce bit for bit."""
    gyr_prev, gyr = inputs.gyr[i - 1 if i > 0 else 0], inputs.gyr[i]
    acc, mag, action, trust = inputs.acc[i], inputs.mag[i], inputs.action[i], inputs.trust[i]
    if not (finite3(gyr_prev) and finite3(gyr) and finite3(acc) and finite3(mag) and np.isfinite(trust)):
        return -1
    mode = p.mode
    on, age = state.period_active[0], state.period_age[0]
    m_t0 = (state.mag_t0[0], state.mag_t0[1], state.mag_t0[2])
    m_ref = (state.mag_ref[0], state.mag_ref[1], state.mag_ref[2])
    active = on and mode != MODE_AEKF
    keep_clone = mode == MODE_DELAY and active and not p.update_reference  # eq. 24 literally
    na = N_AUGMENTED if (mode == MODE_DELAY and active) else N_STATE
    xs, ps = w.x, w.p
    if not synced and not _load(state, w, na):
        return -1
    # 1. prediction, eqs. 17–19
    if i > 0:
        q = (xs[0], xs[1], xs[2], xs[3])
        q_yg = from_rotvec4(
            (0.5 * (gyr_prev[0] + gyr[0]) * dt, 0.5 * (gyr_prev[1] + gyr[1]) * dt, 0.5 * (gyr_prev[2] + gyr[2]) * dt)
        )
        q_w = normalize4((q_yg[0] - xs[4], q_yg[1] - xs[5], q_yg[2] - xs[6], q_yg[3] - xs[7]))
        xs[0], xs[1], xs[2], xs[3] = mul4(q, q_w)
        _predict_cov(w, na, q, q_w)
        qg = (0.5 * p.sigma_gyr * dt) ** 2
        for r in range(4):
            ps[r, r] += qg
            ps[GYRO_BIAS.start + r, GYRO_BIAS.start + r] += (0.5 * dt * p.sigma_bias_walk) ** 2 * dt
        for r in range(3):
            ps[ACC_BIAS.start + r, ACC_BIAS.start + r] += p.sigma_acc_bias_walk**2 * dt
        if active:
            age += dt
    # 2. accelerometer update (gated)
    g = p.gravity
    g_norm = np.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
    na_ = np.sqrt(acc[0] ** 2 + acc[1] ** 2 + acc[2] ** 2)
    acc_used = abs(na_ - g_norm) < p.th_acc
    h = w.h
    if acc_used:
        q = (xs[0], xs[1], xs[2], xs[3])
        v = (acc[0] - xs[8], acc[1] - xs[9], acc[2] - xs[10])
        _put_jacobian(h, 0, q, v, 1.0)
        for c in range(3):  # ∂/∂b_a of q ⊗ (y_a − b_a) ⊗ q̄ = −R(q), column c = −R e_c
            e = rotate3(q, (1.0 if c == 0 else 0.0, 1.0 if c == 1 else 0.0, 1.0 if c == 2 else 0.0))
            h[0, ACC_BIAS.start + c], h[1, ACC_BIAS.start + c], h[2, ACC_BIAS.start + c] = -e[0], -e[1], -e[2]
        dev = p.acc_adaptive * (na_ - g_norm)
        a_e = rotate3(q, v)
        nu = (g[0] - a_e[0], g[1] - a_e[1], g[2] - a_e[2])  # z − h(x), z = g_ENU
        _kalman_update(w, na, ACC_BIAS.start, 3, nu, p.sigma_acc**2 + dev * dev, 1.0)
        _renormalise(xs, ps, na, p.radial_eps)
        if active and mode == MODE_DELAY and p.update_reference:
            m_ref = rotate3(xs[CLONE], m_t0)
    # 3. magnetic update
    sm2 = p.sigma_mag**2
    innov = 0.0
    nis = 0.0
    corr = 0.0
    updated = False
    if mode == MODE_AEKF:
        z = p.earth_field
        do = trust > 0.0
        r_diag = sm2
    else:
        if action == MAG_START or (action == MAG_KEEP and active and age > p.max_age_s):
            # eq. 8: the reference is the field at t0 rotated by the estimate at t0
            on, age = True, 0.0
            m_t0 = (mag[0], mag[1], mag[2])
            m_ref = rotate3(xs[ORIENTATION], mag)
            if mode == MODE_DELAY:  # clone: Cov(δq_t0) = P_qq, Cov(δx, δq_t0) = P[:, q]
                na = N_AUGMENTED
                for a in range(4):
                    xs[CLONE.start + a] = xs[a]
                    for c in range(N_STATE):
                        ps[CLONE.start + a, c] = ps[a, c]
                        ps[c, CLONE.start + a] = ps[c, a]
                    for b in range(4):
                        ps[CLONE.start + a, CLONE.start + b] = ps[a, b]
                for r in range(N_STATE, N_AUGMENTED):  # the exact clone is singular; a tiny jitter keeps P̆ pos. def.
                    ps[r, r] += CLONE_JITTER
            active = True
            do = False  # δz ≡ 0 at t0
        elif action == MAG_KEEP and active:
            do = trust > 0.0
        else:
            if active:  # the period ends
                on, age = False, 0.0
                active = False
                na = N_STATE
            do = False
        z = m_ref
        r_diag = 2.0 * sm2 if mode == MODE_DELAY else sm2
    if mode == MODE_AEKF or active:
        q = (xs[0], xs[1], xs[2], xs[3])
        m_e = rotate3(q, mag)
        nu = (z[0] - m_e[0], z[1] - m_e[1], z[2] - m_e[2])
        innov = np.sqrt(nu[0] * nu[0] + nu[1] * nu[1] + nu[2] * nu[2])
        if do:
            _put_jacobian(h, 0, q, mag, 1.0)
            n2 = 0
            if na == N_AUGMENTED:
                _put_jacobian(h, CLONE.start, xs[CLONE], m_t0, -1.0)
                n2 = 4
            s_inv, corr = _kalman_update(w, na, CLONE.start, n2, nu, r_diag, trust)
            nis = quad3(nu, s_inv)
            _renormalise(xs, ps, na, p.radial_eps)
            if na == N_AUGMENTED and p.update_reference:
                m_ref = rotate3(xs[CLONE], m_t0)
            updated = True
    if keep_clone and active and na == N_AUGMENTED and age > 0.0:  # eq. 24 read literally: q̂_t0 stays
        for a in range(4):
            xs[CLONE.start + a] = state.x[CLONE.start + a]
    # 4. covariance health, commit
    status = _commit_healthy(state, w, na, p.cov_floor)
    if status < 0:
        return -1
    state.period_active[0], state.period_age[0] = on, age
    state.mag_t0[0], state.mag_t0[1], state.mag_t0[2] = m_t0
    state.mag_ref[0], state.mag_ref[1], state.mag_ref[2] = m_ref
    e = heading_row4(xs)
    pq = state.cov
    var = 0.0
    for a in range(4):
        var += e[a] * (pq[a, 0] * e[0] + pq[a, 1] * e[1] + pq[a, 2] * e[2] + pq[a, 3] * e[3])
    sig[SIGNAL.qsf_active] = 1.0 if (active and mode != MODE_AEKF) else 0.0
    sig[SIGNAL.innov_norm] = innov
    sig[SIGNAL.nis] = nis
    sig[SIGNAL.corr_norm] = corr
    sig[SIGNAL.age] = age if active else 0.0
    sig[SIGNAL.trust] = trust if updated else 0.0
    sig[SIGNAL.heading_std] = np.sqrt(max(0.0, var))
    sig[SIGNAL.acc_used] = 1.0 if acc_used else 0.0
    sig[SIGNAL.mag_updated] = 1.0 if updated else 0.0
    return status


@njit(cache=True)
def step1(p, state, inputs, i, dt, sig):
    """Sample i of ``inputs`` (:class:`Inputs`) in place on ``state`` (:class:`State`); writes ``sig`` (N_SIGNALS,).

    The gyro prediction runs from sample i − 1 (none for i = 0). ``inputs.action[i]`` is MAG_NONE /
    MAG_START / MAG_KEEP (ignored by the AEKF, which always updates), ``inputs.trust[i]`` ∈ [0, 1] scales
    the magnetic gain. Returns 0 ok, 1 covariance repaired, −1 non-finite input or covariance (state unchanged).
    Loops over many samples call :func:`step_work` with one scratch (:func:`run_kernel`).
    """
    return step_work(p, state, inputs, i, dt, sig, work())


@njit(cache=True)
def run_kernel(p, state, inputs, dt, start, stop, out):
    """Samples ``start … stop−1`` of ``inputs`` in place on ``state`` (:func:`step1`); writes their rows of
    ``out`` (:class:`Outputs`). Returns (first bad sample or −1, covariance repairs)."""
    repairs = 0
    w = work()
    for i in range(start, stop):
        st = step_work(p, state, inputs, i, dt, out.sig[i], w, i > start)  # after a commit, w holds the state
        if st < 0:
            return i, repairs
        repairs += st
        q = out.q[i]
        q[0], q[1], q[2], q[3] = state.x[0], state.x[1], state.x[2], state.x[3]
    return -1, repairs


# ------------------------------------------------------------ detector


@njit(cache=True)
def detect_kernel(gyr, mag, dt, window, th_spread, th_drift, max_len, code, spread):
    """QSF detector over whole arrays (see module docstring); writes code (N,) int8 and spread (N,) µT.
    The spread is summed over the window in two passes (mean, then squared distances), in scalars."""
    n = gyr.shape[0]
    qg = (1.0, 0.0, 0.0, 0.0)
    mg = np.empty((n, 3))
    start = -1
    for i in range(n):
        if i > 0:
            g0, g1 = gyr[i - 1], gyr[i]
            w = (0.5 * (g0[0] + g1[0]) * dt, 0.5 * (g0[1] + g1[1]) * dt, 0.5 * (g0[2] + g1[2]) * dt)
            qg = normalize4(mul4(qg, from_rotvec4(w)))
        mg[i, 0], mg[i, 1], mg[i, 2] = rotate3(qg, mag[i])
        if i + 1 < window:
            spread[i] = np.nan
            code[i] = 0
            start = -1
            continue
        m0 = m1 = m2 = 0.0
        for j in range(i - window + 1, i + 1):
            m0 += mg[j, 0]
            m1 += mg[j, 1]
            m2 += mg[j, 2]
        m0, m1, m2 = m0 / window, m1 / window, m2 / window
        s = 0.0
        for j in range(i - window + 1, i + 1):
            d0, d1, d2 = mg[j, 0] - m0, mg[j, 1] - m1, mg[j, 2] - m2
            s += d0 * d0 + d1 * d1 + d2 * d2
        spread[i] = np.sqrt(s / window)
        if spread[i] < th_spread:
            if start >= 0:
                d0, d1, d2 = mg[i, 0] - mg[start, 0], mg[i, 1] - mg[start, 1], mg[i, 2] - mg[start, 2]
                if np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) < th_drift and i - start < max_len:
                    code[i] = MAG_KEEP
                    continue
            start = i
            code[i] = MAG_START
        else:
            start = -1
            code[i] = MAG_NONE


@dataclass(frozen=True)
class QSFDetector:
    """Quasi-static field detector (magnetometer/gyro consistency; module docstring).

    Attributes:
        window_s: window of the spread test, s. th_spread: µT (RMS spread of the gyro-frame field).
        th_drift: µT, largest drift of the gyro-frame field from its value at the period start.
        max_period_s: a period is restarted (new reference) after this long, s.
    """

    window_s: float = 0.5
    th_spread: float = 1.0
    th_drift: float = 2.0
    max_period_s: float = 10.0

    def __post_init__(self) -> None:
        for k in ("window_s", "th_spread", "th_drift", "max_period_s"):
            check_positive(f"QSFDetector.{k}", getattr(self, k))

    @classmethod
    def for_noise(cls, sigma_ut: float, **kw) -> QSFDetector:
        """Thresholds scaled to a magnetometer's white noise σ (µT per axis): the 3D spread of pure noise is
        ≈ √3·σ, so th_spread = 2√3·σ and th_drift = 4√3·σ (σ = 0.3 µT gives the defaults 1.0 / 2.0 µT)."""
        sigma_ut = check_positive("sigma_ut (µT)", sigma_ut)
        return cls(th_spread=2.0 * np.sqrt(3.0) * sigma_ut, th_drift=4.0 * np.sqrt(3.0) * sigma_ut, **kw)

    def detect(self, gyr, mag, rate: float) -> tuple[np.ndarray, np.ndarray]:
        """Codes (N,) int8 (0 none, 1 start, 2 keep) and spread (N,) µT for gyr (N, 3) rad/s, mag (N, 3) µT."""
        gyr = np.ascontiguousarray(gyr, float)
        mag = np.ascontiguousarray(mag, float)
        if gyr.shape != mag.shape or gyr.ndim != 2 or gyr.shape[1] != 3:
            raise ValueError(f"gyr and mag must both be (N, 3), got {gyr.shape} and {mag.shape}")
        if not (np.all(np.isfinite(gyr)) and np.all(np.isfinite(mag))):
            raise ValueError("QSF detector: gyr and mag must be finite")
        n = len(gyr)
        code = np.zeros(n, np.int8)
        spread = np.empty(n)
        window = max(1, int(round(self.window_s * rate)))
        detect_kernel(
            gyr,
            mag,
            1.0 / rate,
            window,
            self.th_spread,
            self.th_drift,
            max(1, int(round(self.max_period_s * rate))),
            code,
            spread,
        )
        return code, spread


# ------------------------------------------------------------ Python wrappers


def initial_state(
    q0, dt: float, p0_angle: float = P0_ANGLE, p0_gyr_bias: float = P0_GYR_BIAS, p0_acc_bias: float = P0_ACC_BIAS
) -> State:
    """:class:`State` at orientation q0 (4,): zero biases, no QSF period.

    p0_angle: rad (quaternion variance (p0/2)² per component); p0_gyr_bias: rad/s (quaternion bias
    std dt/2 · p0_gyr_bias); p0_acc_bias: m/s²; each finite > 0 (ValueError / TypeError naming it).
    """
    q0 = check_vector("q0", q0, 4, nonzero=True)
    dt = check_positive("dt", dt)
    p0_angle, p0_gyr_bias = check_positive("p0_angle", p0_angle), check_positive("p0_gyr_bias", p0_gyr_bias)
    p0_acc_bias = check_positive("p0_acc_bias", p0_acc_bias)
    x = np.zeros(N_AUGMENTED)
    x[ORIENTATION] = q0 / np.linalg.norm(q0)
    cov = np.zeros((N_AUGMENTED, N_AUGMENTED))
    cov[ORIENTATION, ORIENTATION] = (0.5 * p0_angle) ** 2 * np.eye(4)
    cov[GYRO_BIAS, GYRO_BIAS] = (0.5 * dt * p0_gyr_bias) ** 2 * np.eye(4)
    cov[ACC_BIAS, ACC_BIAS] = p0_acc_bias**2 * np.eye(3)
    _renormalise(x, cov, N_STATE, RADIAL_EPS)
    return State(x, cov, np.zeros(1, np.bool_), np.zeros(1), np.zeros(3), np.zeros(3))


def triad_init(acc0, mag0, params) -> np.ndarray:
    """Orientation from one accelerometer and magnetometer reading (3,) by TRIAD against g and the Earth field
    of ``params``."""
    q = triad1(
        np.ascontiguousarray(acc0, float),
        np.ascontiguousarray(mag0, float),
        np.array(params.gravity),
        np.array(params.earth_field),
    )
    if not np.all(np.isfinite(q)):
        raise FilterError(f"QSF filters: cannot initialise by TRIAD from acc={acc0}, mag={mag0}")
    return q


INITS = ("auto", "triad", "truth")
#: TRIAD starts from the mean of the samples before the gyro first exceeds ``START_STILL_RAD_S`` (rad/s),
#: at most ``START_WINDOW_S`` s: one magnetometer sample (σ ≈ 0.7 µT on BROAD's unit, a horizontal field of
#: ~16 µT) puts a random 2–5° into the start heading, which MAGYQ never corrects.
START_WINDOW_S = 0.5
START_STILL_RAD_S = 0.05


def still_start(gyr, rate: float) -> slice:
    """Samples ``0:k`` the TRIAD start averages: before ‖ω‖ (rad/s, gyr (N, 3)) first exceeds
    ``START_STILL_RAD_S``, at most ``START_WINDOW_S`` s, at least sample 0."""
    speed = np.linalg.norm(np.asarray(gyr, float)[: max(1, int(round(START_WINDOW_S * rate)))], axis=1)
    moving = np.flatnonzero(speed > START_STILL_RAD_S)
    return slice(0, max(1, int(moving[0]) if moving.size else len(speed)))


def initial_orientation(trial, init: str, params) -> np.ndarray:
    """The filters' start q0 (4,) on ``trial``: ``"triad"`` — TRIAD on the mean accelerometer and
    magnetometer over the still start (:func:`still_start`) against the trial's Earth field (truth-free);
    ``"truth"`` — ``trial.q_true[0]``, the paper's protocol (§5.3: the optical reference sets the start,
    nothing after); ``"auto"`` — truth where ``trial.meta[START_FROM_TRUTH]`` (the hand-held scenarios,
    whose walk starts in a disturbed field), else TRIAD."""
    if init not in INITS:
        raise ValueError(f"init must be one of {INITS}, got {init!r}")
    why = f"init={init!r}"
    if init == "auto":
        init = "truth" if trial.meta.get(START_FROM_TRUTH) else "triad"
        why = f"init='auto' and meta[{START_FROM_TRUTH!r}]"
    if init == "triad":
        still = still_start(trial.gyr, trial.rate)
        return triad_init(trial.acc[still].mean(0), trial.mag[still].mean(0), params)
    q0 = np.asarray(trial.q_true[0], float)
    if not np.all(np.isfinite(q0)):
        raise ValueError(f"trial {trial.name!r}: starting from truth ({why}) needs a finite q_true[0]")
    return q0


def run(p: Params, state: State, inputs: Inputs, dt: float, start: int, stop: int, out: Outputs) -> int:
    """Samples ``start … stop−1`` (:func:`run_kernel`; Δt = ``dt`` s); returns the number of covariance
    repairs; raises FilterError on a non-finite sample or covariance (state left at the previous sample)."""
    if not 0 <= start <= stop <= len(inputs.gyr):
        raise ValueError(f"need 0 <= start <= stop <= N={len(inputs.gyr)}, got {start}, {stop}")
    return checked(run_kernel(p, state, inputs, dt, start, stop, out), inputs)


def checked(result: tuple[int, int], inputs: Inputs) -> int:
    """The repairs of a :func:`run_kernel` result ``(bad, repairs)``; FilterError naming sample ``bad`` if ≥ 0."""
    bad, repairs = result
    if bad >= 0:
        raise FilterError(
            f"QSF filter: non-finite sample or covariance at sample {bad} "
            f"(gyr={inputs.gyr[bad]}, acc={inputs.acc[bad]}, mag={inputs.mag[bad]})"
        )
    return repairs


@dataclass
class QSFResult:
    """Output of :func:`run_trial`: q (N, 4), sig (N, N_SIGNALS), codes (N,) the magnetic actions used,
    spread (N,) detector statistic µT, repairs (count of covariance repairs)."""

    q: np.ndarray
    sig: np.ndarray
    codes: np.ndarray
    spread: np.ndarray
    repairs: int


def run_trial(
    trial,
    mode="delay_magyq",
    detector: QSFDetector | None = None,
    q0=None,
    trust=1.0,
    params=None,
    actions=None,
    p0: dict | None = None,
    init: str = "auto",
    **param_kw,
) -> QSFResult:
    """Whole trial. ``q0``: initial orientation (4,); default :func:`initial_orientation` by ``init``.
    ``actions`` (N,) overrides the detector's codes. ``p0``: keywords of :func:`initial_state`. Extra
    keywords go to :func:`make_params`."""
    if params is None:
        params = make_params(trial.field_norm, trial.field_dip, mode=mode, **param_kw)
    detector = QSFDetector() if detector is None else detector
    codes, spread = detector.detect(trial.gyr, trial.mag, trial.rate)
    if actions is not None:
        codes = np.ascontiguousarray(actions, np.int8)
        if codes.shape != (trial.n,) or np.any((codes < 0) | (codes > 2)):
            raise ValueError(f"actions must be (N,) = ({trial.n},) with values 0, 1, 2")
    q_init = initial_orientation(trial, init, params) if q0 is None else check_vector("q0", q0, 4, nonzero=True)
    state = initial_state(q_init, trial.dt, **(p0 or {}))
    try:
        trusts = np.broadcast_to(np.asarray(trust, float), (trial.n,)).copy()
    except (TypeError, ValueError):
        trusts = np.full(trial.n, np.nan)  # refused just below, with the trust named
    if not np.all((trusts >= 0) & (trusts <= 1)):
        raise ValueError(f"trust must be in [0, 1] (a number or one per sample), got {trust!r}")
    out = Outputs.empty(trial.n)
    repairs = run(params, state, Inputs(trial.gyr, trial.acc, trial.mag, codes, trusts), trial.dt, 0, trial.n, out)
    return QSFResult(out.q, out.sig, codes, spread, repairs)
