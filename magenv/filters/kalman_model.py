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
    repair_cov1,
    skew1,
)
from magenv.filters.sensors import Sensors
from magenv.filters.solvers import Solver, make_solver, solve1
from magenv.quaternion import from_rotvec1, rotate_inv1

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


@njit(cache=True)
def vec_step1(vp, x, p, omega, y):
    """One predict (A9) + update (A10) of the reference/disturbance split with parameters ``vp`` (:class:`VecParams`).

    Args:
        x: (6,) state [r; d] (sensor frame). p: (6, 6) covariance.
        omega: (3,) rate, rad/s. y: (3,) sensor sample.
    Returns ``(x, P, gain_r, status)``: gain_r = trace of the reference-vector
    gain block / 3 (how strongly this sample moved r), status as repair_cov1.
    """
    dt, c_a, c_b, sigma_y = vp.dt, vp.c_a, vp.c_b, vp.sigma_y
    dq = from_rotvec1(omega * dt)
    # A9: rotation matrix of r ↦ δq* ⊗ r ⊗ δq (columns = images of the unit vectors)
    rot = np.empty((3, 3))
    e = np.zeros(3)
    for j in range(3):
        e[:] = 0.0
        e[j] = 1.0
        rot[:, j] = rotate_inv1(dq, e)
    f = np.zeros((6, 6))
    f[:3, :3] = rot
    for i in range(3):
        f[3 + i, 3 + i] = c_a
    gx = skew1(x[:3])
    qn = np.zeros((6, 6))
    sg = dt * vp.sigma_gyr
    qn[:3, :3] = (sg * sg) * (gx @ gx.T)  # A9: G_gyr = T_s [r×]
    for i in range(3):
        qn[3 + i, 3 + i] = c_b * c_b
    xp = f @ x
    pp = f @ p @ f.T + qn
    # A10: H = [I I]
    ph = pp[:, :3] + pp[:, 3:]  # P Hᵀ (6×3)
    s = ph[:3, :] + ph[3:, :]  # H P Hᵀ
    for i in range(3):
        s[i, i] += sigma_y * sigma_y
    k = ph @ np.linalg.inv(s)
    nu = y - xp[:3] - xp[3:]
    xn = xp + k @ nu
    ikh = np.eye(6)
    ikh[:, :3] -= k
    ikh[:, 3:] -= k
    pn = ikh @ pp @ ikh.T + (sigma_y * sigma_y) * (k @ k.T)  # Joseph form
    status = repair_cov1(pn, vp.cov_floor)
    gain_r = (k[0, 0] + k[1, 1] + k[2, 2]) / 3.0
    return xn, pn, gain_r, status


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
        omega = 0.5 * (gyr[k - 1] + gyr[k])
        xa, pa, _, sa = vec_step1(prm.acc, xa, pa, omega, acc[k])
        xm, pm, gm, sm = vec_step1(prm.mag, xm, pm, omega, mag[k])
        if sa < 0 or sm < 0:
            return k, repairs
        repairs += sa + sm
        qk = solve1(prm.solver, xa[:3], xm[:3], prm.g_ref, prm.h_ref)
        if not np.isfinite(qk[0]):
            return k, repairs
        q_out[k] = qk
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
