"""Threshold-based Kalman filter with vector selector (Lee & Park 2009; survey A.1).

A linear Kalman filter whose state is the orientation quaternion: the
gyroscope predicts it (A1, A3–A6), a single-frame solver (QUEST or TRIAD)
measures it directly (A2), and a **vector selector** (A7–A8) first replaces an
accelerometer or magnetometer sample that looks disturbed by its prediction
from the a-priori quaternion.

Reading of the survey in magenv's convention (scalar-first Hamilton ``q``,
sensor → ENU; the survey's ``q^bn`` is scalar-last, NED → body):

* A1/A3: ``q_k = Φ q_{k-1}`` with ``Φ`` the matrix of right multiplication
  by ``δq = exp(½ ω T_s)``: ``q_k = q_{k-1} ⊗ δq``. Reordered to scalar
  first, the survey's ``[[−[ω×], ω], [−ωᵀ, 0]]`` is exactly the matrix of
  ``q ↦ q ⊗ [0, ω]``; we use its exact exponential (the survey's first-order
  ``I + T_s·Ω`` lacks the ½ of ``q̇ = ½ q ⊗ ω``). ω is the trapezoidal mean
  ``½(ω_{k-1} + ω_k)`` of two causal samples.
* A4/A6: ``w = (T_s/2) Ξ(q_{k-1}) n_gyr`` with ``Ξ(q) n = q ⊗ [0, n]``,
  i.e. scalar-first ``Ξ = [−q̄ᵀ; q₀I + [q̄×]]`` — the survey's A6 reordered
  (its extra −T_s/2 inside Ξ double-counts the factor). ``Q = (T_s/2)² σ_g² Ξ Ξᵀ``.
* A2: ``z_k = q_k + v_k``, ``H = I₄``, ``R = (σ_θ²/4)·I₄`` where σ_θ (rad) is
  the solver's angular noise; ``z`` is put on the hemisphere of the prior.
* A7: gravity input ``s_g = acc/|acc|`` if ``| |acc| − g | < th_acc``, else the
  prediction ``q̂* ⊗ g_ENU ⊗ q̂`` (direction).
* A8: field input ``s_h = mag/|mag|`` if ``| |mag| − m0 | < th_mag`` (the
  survey prints th_acc here — a typo, Table A1 gives th_mag) and
  ``|θ_k − θ0| < th_α``, else ``q̂* ⊗ h_ENU ⊗ q̂``. The dip θ_k (° down) is
  the angle of mag below the horizontal plane defined by the *selected*
  gravity s_g: ``θ_k = asin(−ŝ_g·m̂)``; the survey's α (angle between h and
  down) is ``90° − θ`` so ``|α_k − α0| = |θ_k − θ0|``.

As in the survey, a replaced sample still feeds the solver and the update
(its innovation is then ~0); P keeps its usual steady-state value.

Defaults: Table A1 thresholds (0.08 m/s², 1.20 µT, 5°) and the survey's
sensor noise (gyro 0.5 °/s, acc 0.02 m/s², mag 0.15 µT).

Kernels take :class:`Params` (named constants, :meth:`ThresholdKF.params`)
and return a new :class:`State`. This module also holds the covariance-health
kernel shared by the other Kalman filters (:func:`repair_cov1`) and
:class:`FilterError`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from magenv import quaternion as quat
from magenv.checks import check_noise, check_positive, check_site
from magenv.filters.linalg import inv4, is_pd3, mat3, store3
from magenv.filters.sensors import Sensors
from magenv.filters.solvers import Solver, make_solver, solve1, solve4
from magenv.quaternion import GRAVITY, from_rotvec4, mul4, normalize4, right_matrix4, rotate_inv3

# Survey noise (§4) and Table A1.
SIGMA_GYR = np.deg2rad(0.5)  # rad/s
SIGMA_ACC = 0.02  # m/s²
SIGMA_MAG = 0.15  # µT
TH_ACC = 0.08  # m/s²
TH_MAG = 1.20  # µT
TH_DIP = 5.0  # degrees
COV_FLOOR = 1e-14  # eigenvalue floor of a repaired covariance (state units²)

# Status codes of the kernels (>= 0: index of the offending sample).
OK = -1


class FilterError(FloatingPointError, RuntimeError):
    """A filter met a non-finite input or an unrecoverable covariance (a ``FloatingPointError``, as the envs'
    divergence, and a ``RuntimeError``)."""


class Params(NamedTuple):
    """Constants of the threshold KF over one trial (:meth:`ThresholdKF.params`)."""

    dt: float  # sample interval T_s, s
    sigma_gyr: float  # gyro noise std, rad/s (A6)
    r: float  # variance of each component of the solver's quaternion, σ_θ²/4 (A2)
    m0: float  # undisturbed field norm, µT
    dip0: float  # undisturbed dip, rad (positive down)
    th_acc: float  # gate on | |acc| − g |, m/s² (A7)
    th_mag: float  # gate on | |mag| − m0 |, µT (A8)
    th_dip: float  # gate on |θ − θ0|, rad (A8)
    solver: Solver  # TRIAD or QUEST and its weights
    g_ref: np.ndarray  # (3,) gravity reference, ENU (up), m/s²
    h_ref: np.ndarray  # (3,) Earth field, ENU, µT
    cov_floor: float  # eigenvalue floor of a repaired covariance
    p0: float  # initial covariance P₀ = p0·I₄


class State(NamedTuple):
    """The filter's state (each step returns a new one)."""

    q: np.ndarray  # (4,) orientation quaternion, sensor → ENU
    p: np.ndarray  # (4, 4) its covariance


# ------------------------------------------------------------ covariance health


@njit(cache=True)
def is_pd(p, n, lo):
    """Cholesky test: True if the leading n×n block of the symmetric matrix ``p`` is positive definite;
    ``lo`` (≥ n, ≥ n) is scratch for the factor (its diagonal holds the reciprocals of L's)."""
    for j in range(n):
        lj = lo[j]
        s = p[j, j]
        for k in range(j):
            s -= lj[k] * lj[k]
        if not (s > 0.0):
            return False
        inv = 1.0 / np.sqrt(s)
        lj[j] = inv
        for i in range(j + 1, n):
            li = lo[i]
            s = p[i, j]
            for k in range(j):
                s -= li[k] * lj[k]
            li[j] = s * inv
    return True


@njit(cache=True)
def repair_sym(p, n, floor, lo):
    """:func:`repair_cov` of a leading block that is exactly symmetric already (the written-out updates mirror
    one triangle): its lower triangle checked, nothing to symmetrise. Returns 0, 1 or −1 as repair_cov."""
    for i in range(n):
        for j in range(i + 1):
            if not np.isfinite(p[i, j]):
                return -1
    if is_pd(p, n, lo):
        return 0
    vals, vecs = np.linalg.eigh(p[:n, :n].copy())
    for k in range(n):
        if vals[k] < floor:
            vals[k] = floor
    p[:n, :n] = (vecs * vals) @ vecs.T
    for i in range(n):
        for j in range(i + 1, n):
            m = 0.5 * (p[i, j] + p[j, i])
            p[i, j] = m
            p[j, i] = m
    return 1


@njit(cache=True)
def repair_cov(p, n, floor, lo):
    """Keep the covariance on the leading n×n block of ``p`` healthy, in place (``lo`` (≥ n, ≥ n) scratch).

    Symmetrises it; if it is then not positive definite, floors its eigenvalues at ``floor``. Returns 0
    (healthy), 1 (repaired) or −1 (non-finite: cannot be repaired — the caller must fail loudly).
    """
    for i in range(n):
        for j in range(i + 1, n):
            a, b = p[i, j], p[j, i]
            if not (np.isfinite(a) and np.isfinite(b)):
                return -1
            m = 0.5 * (a + b)
            p[i, j] = m
            p[j, i] = m
    return repair_sym(p, n, floor, lo)


@njit(cache=True)
def repair_cov1(p, floor):
    """:func:`repair_cov` of the whole square matrix ``p``."""
    return repair_cov(p, p.shape[0], floor, np.empty_like(p))


@njit(cache=True)
def repair_cov3(p, floor):
    """:func:`repair_cov1` of a 3×3 covariance given as a 9-tuple ``p`` (``magenv.filters.linalg``).
    Returns ``(status, p')``, p' a 9-tuple (``p`` where not finite, status −1)."""
    for v in p:
        if not np.isfinite(v):
            return -1, p
    m01, m02, m12 = 0.5 * (p[1] + p[3]), 0.5 * (p[2] + p[6]), 0.5 * (p[5] + p[7])
    m = (p[0], m01, m02, m01, p[4], m12, m02, m12, p[8])
    if is_pd3(m):
        return 0, m
    out = np.empty((3, 3))
    store3(m, out)
    status = repair_cov1(out, floor)
    return status, mat3(out)


@njit(cache=True, inline="always")
def finite3(v):
    return np.isfinite(v[0]) and np.isfinite(v[1]) and np.isfinite(v[2])


# ------------------------------------------------------------------ kernels


@njit(cache=True, inline="always")
def _xi_rows(q):
    """Rows of the 4×3 matrix Ξ(q) with ``q ⊗ [0, n] = Ξ n`` (survey A6, scalar first)."""
    return (-q[1], -q[2], -q[3]), (q[0], -q[3], q[2]), (q[3], q[0], -q[1]), (-q[2], q[1], q[0])


@njit(cache=True)
def xi1(q):
    """4×3 matrix Ξ(q) with ``q ⊗ [0, n] = Ξ n`` (survey A6, scalar first)."""
    x = np.empty((4, 3))
    for i, row in enumerate(_xi_rows(q)):
        x[i, 0], x[i, 1], x[i, 2] = row
    return x


@njit(cache=True)
def predict_into(q, p, gyr, dt, sigma_gyr, p_out, t):
    """Gyro prediction (A1, A3–A6) written out: ``p_out`` (4, 4) ← Φ P Φᵀ + (T_s/2)² σ² Ξ Ξᵀ (``p_out`` may be
    ``p``; ``t`` (4, 4) scratch); returns the a-priori q as a 4-tuple. ``gyr`` rad/s, sensor frame."""
    dq = from_rotvec4((gyr[0] * dt, gyr[1] * dt, gyr[2] * dt))
    phi = right_matrix4(dq)  # A3: q ⊗ δq = Φ q (exact)
    xi = _xi_rows(q)  # A6
    g = 0.5 * dt * sigma_gyr
    q_new = normalize4(mul4(q, dq))  # A1
    for i in range(4):
        fi = phi[i]
        for j in range(4):
            t[i, j] = fi[0] * p[0, j] + fi[1] * p[1, j] + fi[2] * p[2, j] + fi[3] * p[3, j]
    for i in range(4):  # A4: Q = (Ts/2)² σ² Ξ Ξᵀ
        xa = xi[i]
        for j in range(i, 4):
            fj, xb = phi[j], xi[j]
            v = (t[i, 0] * fj[0] + t[i, 1] * fj[1] + t[i, 2] * fj[2] + t[i, 3] * fj[3]) + (g * g) * (
                xa[0] * xb[0] + xa[1] * xb[1] + xa[2] * xb[2]
            )
            p_out[i, j] = v
            p_out[j, i] = v
    return q_new


@njit(cache=True)
def predict1(q, p, gyr, dt, sigma_gyr):
    """Gyro prediction (A1, A3–A6): returns the a-priori ``(q, P)``; ``gyr`` rad/s, sensor frame."""
    p_new = np.empty((4, 4))
    q_new = predict_into(q, p, gyr, dt, sigma_gyr, p_new, np.empty((4, 4)))
    return np.array(q_new), p_new


@njit(cache=True)
def update_into(q, p, z, r, k, t):
    """Kalman update with a measured quaternion ``z`` (A2: H = I₄, R = r·I₄), Joseph form, written out: P
    (4, 4) updated in place (``k``, ``t`` (4, 4) scratch); returns the normalised a-posteriori q (4-tuple)."""
    if q[0] * z[0] + q[1] * z[1] + q[2] * z[2] + q[3] * z[3] < 0.0:  # z on the hemisphere of the prior
        z = (-z[0], -z[1], -z[2], -z[3])
    for i in range(4):  # S = P + r I, into k
        for j in range(4):
            k[i, j] = p[i, j] + (r if i == j else 0.0)
    inv4(k, t)  # t = S⁻¹
    for i in range(4):  # K = P S⁻¹
        for j in range(4):
            k[i, j] = p[i, 0] * t[0, j] + p[i, 1] * t[1, j] + p[i, 2] * t[2, j] + p[i, 3] * t[3, j]
    dz = (z[0] - q[0], z[1] - q[1], z[2] - q[2], z[3] - q[3])
    q_new = (
        q[0] + (k[0, 0] * dz[0] + k[0, 1] * dz[1] + k[0, 2] * dz[2] + k[0, 3] * dz[3]),
        q[1] + (k[1, 0] * dz[0] + k[1, 1] * dz[1] + k[1, 2] * dz[2] + k[1, 3] * dz[3]),
        q[2] + (k[2, 0] * dz[0] + k[2, 1] * dz[1] + k[2, 2] * dz[2] + k[2, 3] * dz[3]),
        q[3] + (k[3, 0] * dz[0] + k[3, 1] * dz[1] + k[3, 2] * dz[2] + k[3, 3] * dz[3]),
    )
    for i in range(4):  # T = (I − K) P
        for j in range(4):
            t[i, j] = (
                ((1.0 if i == 0 else 0.0) - k[i, 0]) * p[0, j]
                + ((1.0 if i == 1 else 0.0) - k[i, 1]) * p[1, j]
                + ((1.0 if i == 2 else 0.0) - k[i, 2]) * p[2, j]
                + ((1.0 if i == 3 else 0.0) - k[i, 3]) * p[3, j]
            )
    for i in range(4):  # P' = T (I − K)ᵀ + r K Kᵀ, upper triangle
        for j in range(i, 4):
            v = (
                t[i, 0] * ((1.0 if j == 0 else 0.0) - k[j, 0])
                + t[i, 1] * ((1.0 if j == 1 else 0.0) - k[j, 1])
                + t[i, 2] * ((1.0 if j == 2 else 0.0) - k[j, 2])
                + t[i, 3] * ((1.0 if j == 3 else 0.0) - k[j, 3])
            ) + r * (k[i, 0] * k[j, 0] + k[i, 1] * k[j, 1] + k[i, 2] * k[j, 2] + k[i, 3] * k[j, 3])
            p[i, j] = v
            p[j, i] = v
    return normalize4(q_new)


@njit(cache=True)
def update1(q, p, z, r):
    """Kalman update with a measured quaternion ``z`` (A2: H = I₄, R = r·I₄), Joseph form."""
    p_new = p.copy()
    q_new = update_into(q, p_new, z, r, np.empty((4, 4)), np.empty((4, 4)))
    return np.array(q_new), p_new


@njit(cache=True)
def select1(prm, q_prior, acc, mag):
    """Vector selector (A7–A8) for ``prm`` (:class:`Params`). Returns ``(s_g, s_h, acc_ok, mag_ok)``, unit
    vectors (3-tuples), sensor frame."""
    g_ref, h_ref = prm.g_ref, prm.h_ref
    na = np.sqrt(acc[0] ** 2 + acc[1] ** 2 + acc[2] ** 2)
    nm = np.sqrt(mag[0] ** 2 + mag[1] ** 2 + mag[2] ** 2)
    ng = np.sqrt(g_ref[0] ** 2 + g_ref[1] ** 2 + g_ref[2] ** 2)
    nh = np.sqrt(h_ref[0] ** 2 + h_ref[1] ** 2 + h_ref[2] ** 2)
    acc_ok = abs(na - ng) < prm.th_acc  # A7
    if acc_ok:
        s_g = (acc[0] / na, acc[1] / na, acc[2] / na)
    else:
        g = rotate_inv3(q_prior, g_ref)
        s_g = (g[0] / ng, g[1] / ng, g[2] / ng)
    mag_ok = abs(nm - prm.m0) < prm.th_mag and nm > 0.0  # A8, norm test
    if mag_ok:
        m_hat = (mag[0] / nm, mag[1] / nm, mag[2] / nm)
        sd = -(s_g[0] * m_hat[0] + s_g[1] * m_hat[1] + s_g[2] * m_hat[2])
        dip = np.arcsin(min(1.0, max(-1.0, sd)))
        mag_ok = abs(dip - prm.dip0) < prm.th_dip  # A8, dip test
    if mag_ok:
        s_h = (mag[0] / nm, mag[1] / nm, mag[2] / nm)
    else:
        h = rotate_inv3(q_prior, h_ref)
        s_h = (h[0] / nh, h[1] / nh, h[2] / nh)
    return s_g, s_h, acc_ok, mag_ok


@njit(cache=True)
def step1(prm, state, gyr_prev, gyr, acc, mag, lo, k, t):
    """One full step (gyr_prev, gyr rad/s; acc m/s²; mag µT): predict, select, solve, update — in place on
    ``state`` (``lo``, ``k``, ``t`` (4, 4) scratch; on a failure the state is left undefined).

    Returns ``(acc_ok, mag_ok, status)``; status 0 ok, 1 covariance repaired, −1 non-finite input/covariance,
    −2 degenerate solver input (the prediction is kept).
    """
    if not (finite3(gyr_prev) and finite3(gyr) and finite3(acc) and finite3(mag)):
        return False, False, -1
    p = state.p
    w = (0.5 * (gyr_prev[0] + gyr[0]), 0.5 * (gyr_prev[1] + gyr[1]), 0.5 * (gyr_prev[2] + gyr[2]))
    qp = predict_into(state.q, p, w, prm.dt, prm.sigma_gyr, p, t)
    s_g, s_h, acc_ok, mag_ok = select1(prm, qp, acc, mag)
    z = solve4(prm.solver, s_g, s_h, prm.g_ref, prm.h_ref)
    if not np.isfinite(z[0]):
        # degenerate pair (e.g. acc ∥ mag): keep the prediction, as if both were replaced
        q = qp
        status = -2 if repair_sym(p, 4, prm.cov_floor, lo) >= 0 else -1
    else:
        q = update_into(qp, p, z, prm.r, k, t)
        status = repair_sym(p, 4, prm.cov_floor, lo)
    state.q[0], state.q[1], state.q[2], state.q[3] = q
    return acc_ok, mag_ok, status


@njit(cache=True)
def run_kernel(prm, sensors, q_out, acc_ok, mag_ok):
    """Whole trial. Sample 0 initialises q by the solver on the raw vectors, P = p0·I₄.

    Writes q_out (N, 4), acc_ok, mag_ok (N,). Returns ``(status, repairs)``: status OK (−1) or the
    index of the first sample with a non-finite input or covariance.
    """
    gyr, acc, mag = sensors
    n = gyr.shape[0]
    if not (finite3(acc[0]) and finite3(mag[0])):
        return 0, 0
    q = solve1(prm.solver, acc[0], mag[0], prm.g_ref, prm.h_ref)
    if not np.isfinite(q[0]):
        return 0, 0
    state = State(q, np.eye(4) * prm.p0)
    lo, k, t = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4))
    q_out[0] = q
    acc_ok[0] = True
    mag_ok[0] = True
    repairs = 0
    for i in range(1, n):
        a_ok, m_ok, status = step1(prm, state, gyr[i - 1], gyr[i], acc[i], mag[i], lo, k, t)
        if status == -1:
            return i, repairs
        if status == 1:
            repairs += 1
        q_out[i] = state.q
        acc_ok[i] = a_ok
        mag_ok[i] = m_ok
    return OK, repairs


# --------------------------------------------------------------- wrapper


@dataclass
class ThresholdResult:
    """Output of :meth:`ThresholdKF.run` on one trial.

    Attributes:
        q: (N, 4) orientation sensor → ENU.
        acc_ok, mag_ok: (N,) bool, sample accepted by the vector selector.
        repairs: number of steps whose covariance had to be repaired.
    """

    q: np.ndarray
    acc_ok: np.ndarray
    mag_ok: np.ndarray
    repairs: int


@dataclass
class ThresholdKF:
    """Threshold-based quaternion KF (survey A.1) with TRIAD or QUEST measurement.

    Attributes:
        solver: "quest" (Lee & Park's choice) or "triad".
        sigma_gyr: gyro noise std, rad/s (survey: 0.5 °/s).
        sigma_acc: accelerometer noise std, m/s² (0.02).
        sigma_mag: magnetometer noise std, µT (0.15).
        th_acc, th_mag, th_dip: Table A1 thresholds (m/s², µT, degrees).
        weights: QUEST weights (w_acc, w_mag), relative.
        sigma_meas: angular noise std of the solver's quaternion, rad; None →
            ``sqrt((σ_acc/g)² + (σ_mag/(m0·cos θ0))²)`` from the sensor noise.
        p0: initial covariance P₀ = p0·I₄.
    """

    solver: str = "quest"
    sigma_gyr: float = SIGMA_GYR
    sigma_acc: float = SIGMA_ACC
    sigma_mag: float = SIGMA_MAG
    th_acc: float = TH_ACC
    th_mag: float = TH_MAG
    th_dip: float = TH_DIP
    weights: tuple[float, float] = (0.5, 0.5)
    sigma_meas: float | None = None
    p0: float = 1e-2

    def __post_init__(self) -> None:
        self.params(46.0, 49.6, 1.0 / 256.0)  # bad attributes fail here, not in run()

    def params(self, field_norm: float, field_dip: float, dt: float) -> Params:
        """Kernel parameters for a site (m0 µT, θ0 degrees) and sample interval ``dt`` s. Noise stds,
        ``sigma_meas`` (or None) and ``p0`` finite > 0, thresholds > 0 (inf: never gated); ValueError /
        TypeError naming a bad one."""
        solver = make_solver(self.solver, self.weights)
        field_norm, field_dip = check_site(field_norm, field_dip)
        sigma_acc, sigma_mag = (
            check_noise("sigma_acc", self.sigma_acc, "acc"),
            check_noise("sigma_mag", self.sigma_mag, "mag"),
        )
        if self.sigma_meas is None:
            sig = np.hypot(sigma_acc / GRAVITY, sigma_mag / (field_norm * np.cos(np.deg2rad(field_dip))))
        else:
            sig = check_positive("sigma_meas", self.sigma_meas)
        return Params(
            check_positive("dt", dt),
            check_noise("sigma_gyr", self.sigma_gyr, "gyr"),
            float(0.25 * sig * sig),
            field_norm,
            float(np.deg2rad(field_dip)),
            check_positive("th_acc", self.th_acc, inf_ok=True),
            check_positive("th_mag", self.th_mag, inf_ok=True),
            float(np.deg2rad(check_positive("th_dip", self.th_dip, inf_ok=True))),
            solver,
            quat.gravity_up(),
            quat.earth_field(field_norm, field_dip),
            COV_FLOOR,
            check_positive("p0", self.p0),
        )

    def run(self, trial) -> ThresholdResult:
        """Run causally over a :class:`magenv.trial.Trial`; raises FilterError on non-finite data."""
        prm = self.params(trial.field_norm, trial.field_dip, trial.dt)
        n = trial.n
        q = np.empty((n, 4))
        acc_ok = np.zeros(n, bool)
        mag_ok = np.zeros(n, bool)
        status, repairs = run_kernel(prm, Sensors.of(trial), q, acc_ok, mag_ok)
        if status != OK:
            raise FilterError(
                f"threshold KF ({self.solver}) on trial {trial.name!r}: non-finite or degenerate sample or "
                f"covariance at sample {status} (gyr={trial.gyr[status]}, acc={trial.acc[status]}, "
                f"mag={trial.mag[status]})"
            )
        return ThresholdResult(q=q, acc_ok=acc_ok, mag_ok=mag_ok, repairs=repairs)
