"""Madgwick gradient-descent orientation filter, IMU and MIMU versions.

Fan et al. 2017, eqs. 2–10 (after Madgwick 2011). Conventions are magenv's
(``magenv.quaternion``): ``q = [w, x, y, z]`` maps sensor → ENU earth, so a
reference direction ``d`` (earth) is seen in the sensor frame as
``q* ⊗ d ⊗ q`` — exactly the first term of the objective, eq. 3:

    f(q, d, s) = q* ⊗ d ⊗ q − s          (d, s unit 3-vectors)

Madgwick derived f and its Jacobian for a north-x earth frame with
``b = [b_x, 0, b_z]``. magenv's earth frame is ENU (x east, y north, z up), so
here the references are

* gravity: the accelerometer's specific force at rest points **up**,
  ``d_g = [0, 0, 1]`` (the same as Madgwick's);
* magnetic: ``d_b = [0, b_y, b_z]``, horizontal part along **north = y**.

The Jacobian is written once for a general reference ``d`` (``_grad_add``)
and used for both, so there is no separate hand-expanded ENU formula to get
wrong (the test compares against the ``ahrs`` package, NWU frame, converted
at the edge). Note: f uses the unit-quaternion form of the rotation matrix,
so the gradient's radial part — and with it the normalised step of eq. 9 —
depends slightly on the earth frame; our ENU MIMU filter and a north-x one
agree to ~0.03° in orientation, not bit for bit (the IMU filters agree exactly).

MIMU reference field. Following the paper (which follows Madgwick, eqs. 7–8
there and Madgwick's §3.4), the magnetic reference is built **from the
measurement itself**: ``h = q ⊗ m̂ ⊗ q*`` (earth frame) and
``b = [0, sqrt(h_x² + h_y²), h_z]``. The magnetometer can therefore only
correct heading, never the dip; a field with the wrong dip still tilts the
estimate through the gradient. ``MODE_MIMU_REF`` (``mimu_ref_step1``) takes a
fixed, known reference instead (e.g. from ``Trial.field_norm``/``field_dip``);
it is provided for experiments, the blend uses ``MODE_MIMU``.

Update (eqs. 8–9): ``q̇ = ½ q ⊗ [0, ω] − β ∇f/‖∇f‖``, ``q_t = q_{t−1} + q̇ Δt``,
normalised. β in rad/s (paper: 0.1, eq. 10: β = sqrt(3/4)·ω̃_max).
A zero accelerometer (or magnetometer) reading skips that correction.

:func:`step` is the one update kernel (scalars in and out, inlined into its
callers); ``imu_step1``, ``mimu_step1``, ``mimu_ref_step1`` wrap it for arrays
and :func:`run_madgwick` runs a whole trial.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from magenv import quaternion as quat
from magenv.checks import check_number, check_vector
from magenv.filters.solvers import quat_from_dcm1

BETA_DEFAULT = 0.1  # rad/s, Fan et al. 2017 §3
BETA_MAX = 10.0  # rad/s, the largest gain accepted (eq. 10: a gyro error of 11.5 rad/s, far beyond any MEMS gyro)


def check_beta(beta) -> float:
    """The gain β as a float, rad/s: a finite number in [0, ``BETA_MAX``] (0: gyro integration only)."""
    return check_number("beta", beta, 0.0, BETA_MAX)


@njit(cache=True, inline="always")
def _grad(w, x, y, z, d0, d1, d2, s0, s1, s2):
    """``J(q, d)^T f(q, d, s)`` (4-tuple) with f = q*⊗d⊗q − s (eqs. 3–4), d, s unit.

    ``u = R(q)^T d`` with R the sensor→earth rotation matrix; the factors below
    are the rows ∂u_i/∂(w, x, y, z). Scalars only (no allocation: hot path).
    """
    f0 = (1.0 - 2.0 * (y * y + z * z)) * d0 + 2.0 * (x * y + w * z) * d1 + 2.0 * (x * z - w * y) * d2 - s0
    f1 = 2.0 * (x * y - w * z) * d0 + (1.0 - 2.0 * (x * x + z * z)) * d1 + 2.0 * (y * z + w * x) * d2 - s1
    f2 = 2.0 * (x * z + w * y) * d0 + 2.0 * (y * z - w * x) * d1 + (1.0 - 2.0 * (x * x + y * y)) * d2 - s2
    g0 = f0 * (2.0 * z * d1 - 2.0 * y * d2) + f1 * (-2.0 * z * d0 + 2.0 * x * d2) + f2 * (2.0 * y * d0 - 2.0 * x * d1)
    g1 = (
        f0 * (2.0 * y * d1 + 2.0 * z * d2)
        + f1 * (2.0 * y * d0 - 4.0 * x * d1 + 2.0 * w * d2)
        + f2 * (2.0 * z * d0 - 2.0 * w * d1 - 4.0 * x * d2)
    )
    g2 = (
        f0 * (-4.0 * y * d0 + 2.0 * x * d1 - 2.0 * w * d2)
        + f1 * (2.0 * x * d0 + 2.0 * z * d2)
        + f2 * (2.0 * w * d0 + 2.0 * z * d1 - 4.0 * y * d2)
    )
    g3 = (
        f0 * (-4.0 * z * d0 + 2.0 * w * d1 + 2.0 * x * d2)
        + f1 * (-2.0 * w * d0 - 4.0 * z * d1 + 2.0 * y * d2)
        + f2 * (2.0 * x * d0 + 2.0 * y * d1)
    )
    return g0, g1, g2, g3


MODE_IMU, MODE_MIMU, MODE_MIMU_REF = 0, 1, 2
NO_REF = (0.0, 0.0)  # b_ref of the modes that build (or need) no fixed magnetic reference
_NO_MAG = np.zeros(3)  # the magnetometer argument of MODE_IMU, which never reads it


@njit(cache=True, inline="always")
def step(q, gyr, acc, mag, mode, b_ref, beta, dt):
    """One Madgwick update (eqs. 8–9); returns the new unit quaternion as a 4-tuple.

    Args:
        q: 4-tuple (w, x, y, z), sensor → ENU.
        gyr: (3,) rad/s. acc: (3,) any unit. mag: (3,) any unit (not read in ``MODE_IMU``).
        mode: ``MODE_IMU`` (no magnetometer), ``MODE_MIMU`` (Madgwick's own reference from
            the measurement), ``MODE_MIMU_REF`` (the fixed unit reference ``b_ref = (b_n, b_u)``, ENU).
        beta: gain β, rad/s (eq. 10). dt: s.
    Scalars only (no allocation: hot path).
    """
    w, x, y, z = q
    gx, gy, gz = gyr[0], gyr[1], gyr[2]
    ax, ay, az = acc[0], acc[1], acc[2]
    b1, b2 = b_ref
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    g3 = 0.0
    an = np.sqrt(ax * ax + ay * ay + az * az)
    if an > 0.0:
        t0, t1, t2, t3 = _grad(w, x, y, z, 0.0, 0.0, 1.0, ax / an, ay / an, az / an)
        g0 += t0
        g1 += t1
        g2 += t2
        g3 += t3
        if mode != MODE_IMU:
            mx, my, mz = mag[0], mag[1], mag[2]
            mn = np.sqrt(mx * mx + my * my + mz * mz)
            if mn > 0.0:
                m0, m1, m2 = mx / mn, my / mn, mz / mn
                if mode == MODE_MIMU:
                    # h = q ⊗ m̂ ⊗ q* (earth), b = [0, |h_xy|, h_z]  (Madgwick's eqs. 45–46, ENU)
                    tx = y * m2 - z * m1 + w * m0
                    ty = z * m0 - x * m2 + w * m1
                    tz = x * m1 - y * m0 + w * m2
                    h0 = m0 + 2.0 * (y * tz - z * ty)
                    h1 = m1 + 2.0 * (z * tx - x * tz)
                    h2 = m2 + 2.0 * (x * ty - y * tx)
                    b1 = np.sqrt(h0 * h0 + h1 * h1)
                    b2 = h2
                t0, t1, t2, t3 = _grad(w, x, y, z, 0.0, b1, b2, m0, m1, m2)
                g0 += t0
                g1 += t1
                g2 += t2
                g3 += t3
    # eq. 9: q̇ = ½ q ⊗ [0, ω] − β ∇f/‖∇f‖
    dw = 0.5 * (-x * gx - y * gy - z * gz)
    dx = 0.5 * (w * gx + y * gz - z * gy)
    dy = 0.5 * (w * gy - x * gz + z * gx)
    dz = 0.5 * (w * gz + x * gy - y * gx)
    gn = np.sqrt(g0 * g0 + g1 * g1 + g2 * g2 + g3 * g3)
    if gn > 0.0:
        dw -= beta * g0 / gn
        dx -= beta * g1 / gn
        dy -= beta * g2 / gn
        dz -= beta * g3 / gn
    # eq. 8: integrate, then normalise
    w += dw * dt
    x += dx * dt
    y += dy * dt
    z += dz * dt
    n = np.sqrt(w * w + x * x + y * y + z * z)
    return w / n, x / n, y / n, z / n


@njit(cache=True, inline="always")
def _as_array(t):
    out = np.empty(4)
    out[0], out[1], out[2], out[3] = t
    return out


@njit(cache=True, inline="always")
def _as_tuple(q):
    return q[0], q[1], q[2], q[3]


@njit(cache=True)
def imu_step1(q, gyr, acc, beta, dt):
    """One IMU update (gyro + accelerometer). q (4,) unit, gyr rad/s, acc m/s² (any scale), β rad/s, dt s."""
    return _as_array(step(_as_tuple(q), gyr, acc, _NO_MAG, MODE_IMU, NO_REF, beta, dt))


@njit(cache=True)
def mimu_ref_step1(q, gyr, acc, mag, b_ref, beta, dt):
    """One MIMU update with a fixed unit earth-frame magnetic reference ``b_ref = [0, b_n, b_u]`` (ENU)."""
    return _as_array(step(_as_tuple(q), gyr, acc, mag, MODE_MIMU_REF, (b_ref[1], b_ref[2]), beta, dt))


@njit(cache=True)
def mimu_step1(q, gyr, acc, mag, beta, dt):
    """One MIMU update (gyro + accelerometer + magnetometer), Madgwick's own
    reference ``b = [0, |h_xy|, h_z]`` from ``h = q ⊗ m̂ ⊗ q*`` (ENU, north = y).

    mag in any unit (normalised here). A zero accelerometer reading skips all
    correction (as Madgwick's), a zero magnetometer reading the magnetic part.
    """
    return _as_array(step(_as_tuple(q), gyr, acc, mag, MODE_MIMU, NO_REF, beta, dt))


@njit(cache=True, inline="always")
def _unit3(v):
    n = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if n == 0.0:
        return v * 0.0, False
    return v / n, True


@njit(cache=True)
def ecompass1(acc, mag):
    """Orientation (sensor → ENU) from one accelerometer and magnetometer sample.

    up = â, east = m̂ × up (normalised), north = up × east; the rows of the
    sensor→earth matrix are those axes in sensor coordinates. Falls back to
    identity when acc is zero or mag is parallel to it.
    """
    up, ok = _unit3(acc)
    if not ok:
        return np.array([1.0, 0.0, 0.0, 0.0])
    east, ok = _unit3(np.cross(mag, up))
    if not ok:
        return np.array([1.0, 0.0, 0.0, 0.0])
    north = np.cross(up, east)
    r = np.empty((3, 3))
    r[0] = east
    r[1] = north
    r[2] = up
    return quat_from_dcm1(r)


@njit(cache=True)
def _run(q0, gyr, acc, mag, beta, dt, use_mag):
    n = gyr.shape[0]
    out = np.empty((n, 4))
    q = q0.copy()
    for i in range(n):
        if use_mag:
            q = mimu_step1(q, gyr[i], acc[i], mag[i], beta, dt)
        else:
            q = imu_step1(q, gyr[i], acc[i], beta, dt)
        out[i] = q
    return out


def run_madgwick(gyr, acc, mag=None, rate: float = 256.0, beta: float = BETA_DEFAULT, q0=None) -> np.ndarray:
    """Plain Madgwick over whole arrays (N, 3): IMU if ``mag`` is None, else MIMU.

    Returns (N, 4) estimates (after each sample). ``q0`` defaults to
    ``ecompass1`` of the first sample (identity for IMU with no mag given).
    """
    gyr = np.ascontiguousarray(gyr, float)
    acc = np.ascontiguousarray(acc, float)
    use_mag = mag is not None
    mag = np.ascontiguousarray(mag, float) if use_mag else np.zeros_like(acc)
    for name, a in (("gyr", gyr), ("acc", acc), ("mag", mag)):
        if a.ndim != 2 or a.shape[1] != 3 or len(a) != len(gyr) or len(a) == 0:
            raise ValueError(f"{name} must be (N, 3) with the N ≥ 1 rows of gyr, got shape {a.shape}")
    rate, beta = check_number("rate", rate, 0.0, lo_open=True), check_beta(beta)
    if q0 is None:
        q0 = ecompass1(acc[0], mag[0]) if use_mag else np.array([1.0, 0.0, 0.0, 0.0])
    q0 = quat.normalize(check_vector("q0", q0, 4, nonzero=True))
    return _run(q0, gyr, acc, mag, beta, 1.0 / rate, use_mag)
