"""Model-based Kalman filter (Ligorio & Sabatini 2015; survey A.2).

Two identical linear Kalman filters split each sensor into a reference
vector and a disturbance, both in the sensor frame:

* accelerometer ``y = g^b + a^b + v`` (gravity + body acceleration);
* magnetometer ``y = h^b + d^b + v`` (Earth field + magnetic disturbance).

State ``x = [r; d]`` (6,), r the reference vector (gravity m/s² or Earth
field µT), d the disturbance. Dynamics (A9) and measurement (A10):

    r_k = exp(−[ω×] T_s) r_{k-1} + T_s [r_{k-1}×] n_gyr
    d_k = c_a d_{k-1} + c_b n_GM
    y_k = r_k + d_k + v_k                                  (A10, H = [I₃ I₃])

Reading of the survey in magenv's convention: a constant earth vector seen
from a body turning at ω (rad/s, sensor frame, q sensor → ENU) obeys
``ṙ = −ω × r`` (so the survey's ``exp([ω×]T_s)`` for its NED→body
quaternion becomes ``exp(−[ω×]T_s)`` here; we apply it as
``r_k = q̂δ* ⊗ r ⊗ q̂δ`` with ``δ = exp(½ ω T_s)``); the gyro noise enters
as an angle ``T_s·n_gyr`` (A9 prints ``−[g×] n_gyr`` without T_s; dimensions
require it). ``n_GM`` is white unit noise, so c_b is the per-sample std of
the disturbance innovation in the sensor's unit (m/s² or µT) and c_a the
per-sample correlation (survey: c_a = 0.1, c_b = 1 for both filters).
ω is the trapezoidal mean of two causal gyro samples.

The a-posteriori gravity and Earth field feed TRIAD (Ligorio & Sabatini's
choice: the magnetometer never tilts the estimate) or QUEST; the solver's
output is the orientation, as in the survey's Figure A2 — no further
quaternion Kalman filter, since the vector filters already fuse the gyro.
The disturbance estimate ``d̂`` (µT, sensor frame) is returned per sample.

Kernels take named parameters: :class:`VecParams` for one sensor's split,
:class:`Params` for the whole estimator (:meth:`ModelKF.params`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from magenv import quaternion as quat
from magenv.checks import check_noise, check_number, check_positive, check_site
from magenv.filters.kalman_threshold import (
    COV_FLOOR,
    OK,
    SIGMA_ACC,
    SIGMA_GYR,
    SIGMA_MAG,
    FilterError,
    finite3,
    repair_cov,
)
from magenv.filters.linalg import add33, diag3, inv3, mul33, mul33t, mulsym33t, mv3, sandwich3, scale33, skew3, sub33
from magenv.filters.sensors import Sensors
from magenv.filters.solvers import Solver, make_solver, solve1, solve4
from magenv.quaternion import from_rotvec4, rotate_inv3

C_A = 0.1  # GM correlation per sample (survey)
C_B = 1.0  # GM driving-noise std per sample, sensor unit (survey)


class VecParams(NamedTuple):
    """Constants of one sensor's reference/disturbance split (A9–A10)."""

    dt: float  # sample interval T_s, s
    sigma_gyr: float  # gyro noise std, rad/s
    sigma_y: float  # the sensor's noise std (m/s² or µT)
    c_a: float  # GM correlation per sample, in [0, 1)
    c_b: float  # GM driving-noise std per sample, sensor unit
    p0_ref: float  # initial variance of the reference vector, sensor unit²
    cov_floor: float  # eigenvalue floor of a repaired covariance


class Params(NamedTuple):
    """Constants of the model-based estimator over one trial (:meth:`ModelKF.params`)."""

    acc: VecParams  # the accelerometer split: gravity + body acceleration
    mag: VecParams  # the magnetometer split: Earth field + disturbance
    solver: Solver  # TRIAD or QUEST on the a-posteriori references
    g_ref: np.ndarray  # (3,) gravity reference, ENU (up), m/s²
    h_ref: np.ndarray  # (3,) Earth field, ENU, µT


def make_vec_params(
    dt, sigma_gyr, sigma_y, c_a=C_A, c_b=C_B, p0_ref=1.0, names=("sigma_y", "c_a", "c_b", "p0_ref")
) -> VecParams:
    """:class:`VecParams` of one split: ``dt`` s, ``sigma_gyr`` rad/s, the sensor's ``sigma_y``, ``c_b`` and
    ``p0_ref`` finite > 0, ``c_a`` in [0, 1) (a stable Gauss–Markov model); ``names`` are the caller's names
    of (sigma_y, c_a, c_b, p0_ref) in the ValueError / TypeError of a bad one."""
    n_sigma, n_ca, n_cb, n_p0 = names
    return VecParams(
        check_positive("dt", dt),
        check_noise("sigma_gyr", sigma_gyr, "gyr"),
        check_positive(n_sigma, sigma_y),
        check_number(f"{n_ca} (a stable Gauss–Markov correlation)", c_a, 0.0, 1.0, hi_open=True),
        check_positive(n_cb, c_b),
        check_positive(n_p0, p0_ref),
        COV_FLOOR,
    )


@njit(cache=True)
def vec_init(vp, y0):
    """Initial ``(x (6,), P (6, 6))`` of a split from the first sample ``y0``: r = y0, d = 0,
    P = diag(p0_ref·I, c_b²/(1 − c_a²)·I) (the disturbance at its stationary GM variance)."""
    x = np.zeros(6)
    x[:3] = y0
    p = np.zeros((6, 6))
    vd = vp.c_b**2 / max(1.0 - vp.c_a**2, 1e-12)
    for i in range(3):
        p[i, i] = vp.p0_ref
        p[3 + i, 3 + i] = vd
    return x, p


@njit(cache=True, inline="always")
def _block(p, r0, c0):
    """The 3×3 block of ``p`` at rows r0…r0+2, columns c0…c0+2, as a 9-tuple."""
    return (
        p[r0, c0], p[r0, c0 + 1], p[r0, c0 + 2], p[r0 + 1, c0], p[r0 + 1, c0 + 1], p[r0 + 1, c0 + 2], p[r0 + 2, c0],
        p[r0 + 2, c0 + 1], p[r0 + 2, c0 + 2],
    )  # fmt: skip


@njit(cache=True, inline="always")
def _put_block(m, p, r0, c0):
    for i in range(3):
        for j in range(3):
            p[r0 + i, c0 + j] = m[3 * i + j]


@njit(cache=True)
def vec_step1(vp, x, p, omega, y, lo):
    """One predict (A9) + update (A10) of the reference/disturbance split with parameters ``vp`` (:class:`VecParams`),
    in place.

    Args:
        x: (6,) state [r; d] (sensor frame). p: (6, 6) covariance. Both updated in place (left undefined
            when the step fails).
        omega: (3,) rate, rad/s. y: (3,) sensor sample. lo: (6, 6) scratch.
    Returns ``(gain_r, status)``: gain_r = trace of the reference-vector gain block / 3 (how strongly this
    sample moved r), status as ``repair_cov``. Written out in 3×3 blocks (``magenv.filters.linalg``): P =
    [[A, B], [Bᵀ, D]], K = [K_r; K_d]; nothing is allocated.
    """
    dt, c_a, c_b, sigma_y = vp.dt, vp.c_a, vp.c_b, vp.sigma_y
    dq = from_rotvec4((omega[0] * dt, omega[1] * dt, omega[2] * dt))
    # A9: rotation matrix of r ↦ δq* ⊗ r ⊗ δq (columns = images of the unit vectors)
    c0, c1, c2 = rotate_inv3(dq, (1.0, 0.0, 0.0)), rotate_inv3(dq, (0.0, 1.0, 0.0)), rotate_inv3(dq, (0.0, 0.0, 1.0))
    rot = (c0[0], c1[0], c2[0], c0[1], c1[1], c2[1], c0[2], c1[2], c2[2])
    gx = skew3((x[0], x[1], x[2]))
    sg = dt * vp.sigma_gyr
    xr = mv3(rot, (x[0], x[1], x[2]))
    xd = (c_a * x[3], c_a * x[4], c_a * x[5])
    # F P Fᵀ + Q: F = diag(rot, c_a I), Q = diag((T_s σ_g)² [r×][r×]ᵀ, c_b² I)   (A9: G_gyr = T_s [r×])
    a = add33(sandwich3(rot, _block(p, 0, 0)), scale33(sg * sg, mulsym33t(gx, gx)))
    b = scale33(c_a, mul33(rot, _block(p, 0, 3)))
    d = add33(scale33(c_a, scale33(c_a, _block(p, 3, 3))), diag3(c_b * c_b))
    bt = (b[0], b[3], b[6], b[1], b[4], b[7], b[2], b[5], b[8])
    # A10: H = [I I]; C = P Hᵀ = [A + B; Bᵀ + D]
    cr, cd = add33(a, b), add33(bt, d)
    s = add33(add33(cr, cd), diag3(sigma_y * sigma_y))
    s_inv = inv3(s)
    kr, kd = mul33(cr, s_inv), mul33(cd, s_inv)
    nu = (y[0] - xr[0] - xd[0], y[1] - xr[1] - xd[1], y[2] - xr[2] - xd[2])
    dr, dd = mv3(kr, nu), mv3(kd, nu)
    x[0], x[1], x[2] = xr[0] + dr[0], xr[1] + dr[1], xr[2] + dr[2]
    x[3], x[4], x[5] = xd[0] + dd[0], xd[1] + dd[1], xd[2] + dd[2]
    # Joseph form through its factors: M = P − K Cᵀ (= (I − KH) P), P' = M − (M Hᵀ) Kᵀ + σ² K Kᵀ
    r2 = sigma_y * sigma_y
    m_rr, m_rd = sub33(a, mul33t(kr, cr)), sub33(b, mul33t(kr, cd))
    m_dr, m_dd = sub33(bt, mul33t(kd, cr)), sub33(d, mul33t(kd, cd))
    n_r, n_d = add33(m_rr, m_rd), add33(m_dr, m_dd)
    _put_block(add33(sub33(m_rr, mulsym33t(n_r, kr)), scale33(r2, mulsym33t(kr, kr))), p, 0, 0)
    p_rd = add33(sub33(m_rd, mul33t(n_r, kd)), scale33(r2, mul33t(kr, kd)))
    _put_block(p_rd, p, 0, 3)
    _put_block((p_rd[0], p_rd[3], p_rd[6], p_rd[1], p_rd[4], p_rd[7], p_rd[2], p_rd[5], p_rd[8]), p, 3, 0)
    _put_block(add33(sub33(m_dd, mulsym33t(n_d, kd)), scale33(r2, mulsym33t(kd, kd))), p, 3, 3)
    status = repair_cov(p, 6, vp.cov_floor, lo)
    gain_r = (kr[0] + kr[4] + kr[8]) / 3.0
    return gain_r, status


@njit(cache=True)
def run_kernel(prm, sensors, q_out, x_acc, x_mag, gain_mag):
    """Whole trial: two vector KFs feeding the solver.

    Writes q_out (N, 4), x_acc (N, 6) = [ĝ; â], x_mag (N, 6) = [ĥ; d̂],
    gain_mag (N,). Returns ``(status, repairs)``.
    """
    gyr, acc, mag = sensors
    n = gyr.shape[0]
    if not (finite3(acc[0]) and finite3(mag[0]) and finite3(gyr[0])):
        return 0, 0
    xa, pa = vec_init(prm.acc, acc[0])
    xm, pm = vec_init(prm.mag, mag[0])
    lo = np.empty((6, 6))
    q = solve1(prm.solver, xa[:3], xm[:3], prm.g_ref, prm.h_ref)
    if not np.isfinite(q[0]):
        return 0, 0
    q_out[0] = q
    x_acc[0] = xa
    x_mag[0] = xm
    gain_mag[0] = 1.0
    repairs = 0
    for k in range(1, n):
        if not (finite3(gyr[k]) and finite3(acc[k]) and finite3(mag[k])):
            return k, repairs
        g0, g1 = gyr[k - 1], gyr[k]
        omega = (0.5 * (g0[0] + g1[0]), 0.5 * (g0[1] + g1[1]), 0.5 * (g0[2] + g1[2]))
        _, sa = vec_step1(prm.acc, xa, pa, omega, acc[k], lo)
        gm, sm = vec_step1(prm.mag, xm, pm, omega, mag[k], lo)
        if sa < 0 or sm < 0:
            return k, repairs
        repairs += sa + sm
        qk = solve4(prm.solver, xa[:3], xm[:3], prm.g_ref, prm.h_ref)
        if not np.isfinite(qk[0]):
            return k, repairs
        q_out[k, 0], q_out[k, 1], q_out[k, 2], q_out[k, 3] = qk
        x_acc[k] = xa
        x_mag[k] = xm
        gain_mag[k] = gm
    return OK, repairs


@dataclass
class ModelResult:
    """Output of :meth:`ModelKF.run`.

    Attributes:
        q: (N, 4) orientation sensor → ENU.
        gravity: (N, 3) ĝ, m/s², sensor frame. body_acc: (N, 3) â, m/s².
        earth_field: (N, 3) ĥ, µT, sensor frame.
        disturbance: (N, 3) d̂, µT, sensor frame (magnetometer − Earth field).
        gain_mag: (N,) mean diagonal Kalman gain of ĥ on the magnetometer
            innovation — how far each sample moved the Earth-field estimate.
        repairs: steps whose covariance had to be repaired.
    """

    q: np.ndarray
    gravity: np.ndarray
    body_acc: np.ndarray
    earth_field: np.ndarray
    disturbance: np.ndarray
    gain_mag: np.ndarray
    repairs: int


@dataclass
class ModelKF:
    """Model-based estimator (survey A.2): acc and mag split by GM-model KFs, then TRIAD/QUEST.

    Attributes:
        solver: "triad" (Ligorio & Sabatini's choice) or "quest".
        sigma_gyr, sigma_acc, sigma_mag: sensor noise std (rad/s, m/s², µT).
        c_a, c_b: GM parameters of the body acceleration (per sample; c_b m/s²).
        c_a_mag, c_b_mag: GM parameters of the magnetic disturbance (c_b µT).
        weights: QUEST weights (w_acc, w_mag).
        p0_acc, p0_mag: initial variance of the reference vector (m²/s⁴, µT²);
            the disturbance starts at its stationary GM variance.
    """

    solver: str = "triad"
    sigma_gyr: float = SIGMA_GYR
    sigma_acc: float = SIGMA_ACC
    sigma_mag: float = SIGMA_MAG
    c_a: float = C_A
    c_b: float = C_B
    c_a_mag: float = C_A
    c_b_mag: float = C_B
    weights: tuple[float, float] = (0.5, 0.5)
    p0_acc: float = 1.0
    p0_mag: float = 1.0

    def __post_init__(self) -> None:
        self.params(46.0, 49.6, 1.0 / 256.0)  # bad attributes fail here, not in run()

    def params(self, field_norm: float, field_dip: float, dt: float) -> Params:
        """Kernel parameters for a site (m0 µT, θ0 degrees) and sample interval ``dt`` s (each split by
        :func:`make_vec_params`); ValueError / TypeError naming a bad attribute."""
        solver = make_solver(self.solver, self.weights)
        field_norm, field_dip = check_site(field_norm, field_dip)
        acc = make_vec_params(
            dt, self.sigma_gyr, self.sigma_acc, self.c_a, self.c_b, self.p0_acc, ("sigma_acc", "c_a", "c_b", "p0_acc")
        )
        mag = make_vec_params(
            dt,
            self.sigma_gyr,
            self.sigma_mag,
            self.c_a_mag,
            self.c_b_mag,
            self.p0_mag,
            ("sigma_mag", "c_a_mag", "c_b_mag", "p0_mag"),
        )
        return Params(acc, mag, solver, quat.gravity_up(), quat.earth_field(field_norm, field_dip))

    def run(self, trial) -> ModelResult:
        """Run causally over a Trial; raises FilterError on non-finite or degenerate data."""
        prm = self.params(trial.field_norm, trial.field_dip, trial.dt)
        n = trial.n
        q = np.empty((n, 4))
        xa = np.empty((n, 6))
        xm = np.empty((n, 6))
        gm = np.empty(n)
        status, repairs = run_kernel(prm, Sensors.of(trial), q, xa, xm, gm)
        if status != OK:
            raise FilterError(
                f"model-based KF ({self.solver}) on trial {trial.name!r}: non-finite or degenerate sample or "
                f"covariance at sample {status} (gyr={trial.gyr[status]}, acc={trial.acc[status]}, "
                f"mag={trial.mag[status]})"
            )
        return ModelResult(
            q=q,
            gravity=xa[:, :3],
            body_acc=xa[:, 3:],
            earth_field=xm[:, :3],
            disturbance=xm[:, 3:],
            gain_mag=gm,
            repairs=int(repairs),
        )
