"""The one place for quaternion conventions and maths.

Conventions (used everywhere in magenv, converted only at the edges):

* order: scalar first, ``q = [w, x, y, z]``; Hamilton product;
* an orientation ``q`` maps **sensor → earth**: ``v_E = q ⊗ [0, v_S] ⊗ q*``;
* earth frame **ENU** (x east, y north, z up). At rest the accelerometer
  reads ``[0, 0, +g]`` in the earth frame; the Earth field is
  ``[0, B·cos(dip), −B·sin(dip)]`` (northern hemisphere, dip > 0 points down);
* Euler angles are **ZYX** (yaw ψ about z, pitch θ about y, roll φ about x):
  ``q = q_z(ψ) ⊗ q_y(θ) ⊗ q_x(φ)``.

Each operation exists once, as a numba kernel on single quaternions (names
ending in ``1``, for use inside other kernels), and as a broadcasting NumPy
ufunc built from that kernel (for arrays ``(..., 4)``). The kernels the
filters' sample loops call most also come as tuple kernels (names ending in
the tuple's length: ``mul4``, ``normalize4``, ``rotate3``, ``rotate_inv3``,
``from_rotvec4``, and the product matrices ``left_matrix4``, ``right_matrix4``),
which allocate nothing; the ``1`` kernels are built on them.
"""

from __future__ import annotations

import numpy as np
from numba import guvectorize, njit

GRAVITY = 9.81  # m/s², magnitude used throughout magenv


# ---------------------------------------------------------------- kernels


@njit(cache=True, inline="always")
def mul4(a, b):
    """Hamilton product ``a ⊗ b`` of two quaternions (4-tuples or (4,) arrays) as a 4-tuple (no allocation)."""
    return (
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    )


@njit(cache=True, inline="always")
def left_matrix4(q):
    """Rows (a 4-tuple of 4-tuples) of the 4×4 M(q) with ``q ⊗ p = M(q) p``."""
    return (
        (q[0], -q[1], -q[2], -q[3]),
        (q[1], q[0], -q[3], q[2]),
        (q[2], q[3], q[0], -q[1]),
        (q[3], -q[2], q[1], q[0]),
    )


@njit(cache=True, inline="always")
def right_matrix4(p):
    """Rows (a 4-tuple of 4-tuples) of the 4×4 C(p) with ``q ⊗ p = C(p) q``."""
    return (
        (p[0], -p[1], -p[2], -p[3]),
        (p[1], p[0], p[3], -p[2]),
        (p[2], -p[3], p[0], p[1]),
        (p[3], p[2], -p[1], p[0]),
    )


@njit(cache=True, inline="always")
def mul1(a, b):
    """Hamilton product ``a ⊗ b`` of two quaternions (4,)."""
    out = np.empty(4)
    out[0], out[1], out[2], out[3] = mul4(a, b)
    return out


@njit(cache=True, inline="always")
def conj1(q):
    """Conjugate (inverse of a unit quaternion)."""
    return np.array([q[0], -q[1], -q[2], -q[3]])


@njit(cache=True, inline="always")
def normalize4(q):
    """Unit quaternion along ``q`` (4-tuple or (4,) array) as a 4-tuple; a zero quaternion gives identity."""
    n = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if n == 0.0:
        return 1.0, 0.0, 0.0, 0.0
    return q[0] / n, q[1] / n, q[2] / n, q[3] / n


@njit(cache=True, inline="always")
def normalize1(q):
    """Unit quaternion along ``q``; a zero quaternion gives identity."""
    n = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if n == 0.0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return q / n


@njit(cache=True, inline="always")
def rotate3(q, v):
    """``q ⊗ v ⊗ q*`` (sensor → earth) of a 3-vector as a 3-tuple; q, v tuples or arrays (no allocation)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    # v + 2·r × (r × v + w·v), r = (x, y, z)
    tx = y * v[2] - z * v[1] + w * v[0]
    ty = z * v[0] - x * v[2] + w * v[1]
    tz = x * v[1] - y * v[0] + w * v[2]
    return v[0] + 2.0 * (y * tz - z * ty), v[1] + 2.0 * (z * tx - x * tz), v[2] + 2.0 * (x * ty - y * tx)


@njit(cache=True, inline="always")
def rotate1(q, v):
    """Rotate a 3-vector from the sensor to the earth frame: ``q ⊗ v ⊗ q*``."""
    out = np.empty(3)
    out[0], out[1], out[2] = rotate3(q, v)
    return out


@njit(cache=True, inline="always")
def rotate_inv3(q, v):
    """``q* ⊗ v ⊗ q`` (earth → sensor) of a 3-vector as a 3-tuple (no allocation)."""
    return rotate3((q[0], -q[1], -q[2], -q[3]), v)


@njit(cache=True, inline="always")
def rotate_inv1(q, v):
    """Rotate a 3-vector from the earth to the sensor frame: ``q* ⊗ v ⊗ q``."""
    return rotate1((q[0], -q[1], -q[2], -q[3]), v)


@njit(cache=True, inline="always")
def from_rotvec4(r):
    """Quaternion of the rotation vector ``r`` (axis · angle, rad; 3-tuple or array) as a 4-tuple."""
    angle = np.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
    # sin(a/2)/a → 1/2 for small a (Taylor to 4th order)
    if angle < 1e-6:
        s = 0.5 - angle * angle / 48.0
    else:
        s = np.sin(0.5 * angle) / angle
    return np.cos(0.5 * angle), r[0] * s, r[1] * s, r[2] * s


@njit(cache=True, inline="always")
def from_rotvec1(r):
    """Quaternion of the rotation vector ``r`` (axis · angle, rad)."""
    out = np.empty(4)
    out[0], out[1], out[2], out[3] = from_rotvec4(r)
    return out


@njit(cache=True, inline="always")
def to_rotvec1(q):
    """Rotation vector (rad) of a unit quaternion, angle in [0, π]."""
    w = q[0]
    sgn = 1.0 if w >= 0.0 else -1.0
    vn = np.sqrt(q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if vn < 1e-12:
        return 2.0 * sgn * q[1:4].copy()
    angle = 2.0 * np.arctan2(vn, abs(w))
    return sgn * q[1:4] * (angle / vn)


@njit(cache=True, inline="always")
def align1(q, ref):
    """``q`` or ``−q``, whichever is on the same hemisphere as ``ref``."""
    if q[0] * ref[0] + q[1] * ref[1] + q[2] * ref[2] + q[3] * ref[3] < 0.0:
        return -q
    return q.copy()


@njit(cache=True, inline="always")
def integrate_gyro1(q, gyr, dt):
    """Propagate ``q`` by the body rate ``gyr`` (rad/s, sensor frame) over ``dt`` s."""
    return normalize1(mul1(q, from_rotvec1(gyr * dt)))


# --------------------------------------------------- broadcasting ufuncs


@guvectorize(["void(f8[:], f8[:], f8[:])"], "(n),(n)->(n)", cache=True)
def mul(a, b, out):
    """Hamilton product ``a ⊗ b`` of quaternion arrays (..., 4)."""
    out[:] = mul1(a, b)


@guvectorize(["void(f8[:], f8[:])"], "(n)->(n)", cache=True)
def conj(q, out):
    """Conjugate of quaternion arrays (..., 4)."""
    out[:] = conj1(q)


@guvectorize(["void(f8[:], f8[:])"], "(n)->(n)", cache=True)
def normalize(q, out):
    """Unit quaternions (..., 4)."""
    out[:] = normalize1(q)


@guvectorize(["void(f8[:], f8[:], f8[:])"], "(n),(m)->(m)", cache=True)
def rotate(q, v, out):
    """Vectors (..., 3) from sensor to earth frame by orientations (..., 4)."""
    out[:] = rotate1(q, v)


@guvectorize(["void(f8[:], f8[:], f8[:])"], "(n),(m)->(m)", cache=True)
def rotate_inv(q, v, out):
    """Vectors (..., 3) from earth to sensor frame by orientations (..., 4)."""
    out[:] = rotate_inv1(q, v)


@guvectorize(["void(f8[:], f8[:], f8[:])"], "(m),(n)->(n)", cache=True)
def _from_rotvec(r, dummy, out):
    out[:] = from_rotvec1(r)


def from_rotvec(r):
    """Quaternions (..., 4) of rotation vectors (..., 3), rad."""
    r = np.asarray(r, dtype=float)
    return _from_rotvec(r, np.empty(4))


@guvectorize(["void(f8[:], f8[:], f8[:])"], "(n),(m)->(m)", cache=True)
def _to_rotvec(q, dummy, out):
    out[:] = to_rotvec1(q)


def to_rotvec(q):
    """Rotation vectors (..., 3), rad, of unit quaternions (..., 4)."""
    q = np.asarray(q, dtype=float)
    return _to_rotvec(q, np.empty(3))


def from_axis_angle(axis, angle):
    """Quaternions of rotations by ``angle`` (rad) about unit ``axis`` (..., 3)."""
    axis = np.asarray(axis, dtype=float)
    angle = np.asarray(angle, dtype=float)[..., None]
    half = 0.5 * angle
    return np.concatenate([np.cos(half), np.sin(half) * axis], axis=-1)


_EX, _EY, _EZ = np.eye(3)


def from_euler_zyx(yaw, pitch, roll):
    """Quaternions from ZYX Euler angles (rad): ``q_z(yaw) ⊗ q_y(pitch) ⊗ q_x(roll)``."""
    return mul(
        mul(from_axis_angle(_EZ, yaw), from_axis_angle(_EY, pitch)),
        from_axis_angle(_EX, roll),
    )


def to_euler_zyx(q):
    """ZYX Euler angles (..., 3) = [yaw, pitch, roll] in rad of quaternions (..., 4)."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    pitch = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    return np.stack([yaw, pitch, roll], axis=-1)


def to_matrix(q):
    """Rotation matrices (..., 3, 3) with ``v_E = R @ v_S``."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def from_matrix(m):
    """Unit quaternions (..., 4), w ≥ 0, of rotation matrices (..., 3, 3) (``v_E = R @ v_S``)."""
    m = np.asarray(m, dtype=float)
    tr = np.trace(m, axis1=-2, axis2=-1)
    # Shepperd's method: branch on the largest of 4w²−1, 4x²−1, 4y²−1, 4z²−1.
    cand = np.stack([tr, 2 * m[..., 0, 0] - tr, 2 * m[..., 1, 1] - tr, 2 * m[..., 2, 2] - tr], -1)
    k = np.argmax(cand, axis=-1)
    s2 = 1.0 + np.max(cand, axis=-1)  # 4·c², c the largest component
    d21, d02, d10 = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    s01, s02, s12 = m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1]
    branches = np.stack(
        [
            np.stack([s2, d21, d02, d10], -1),
            np.stack([d21, s2, s01, s02], -1),
            np.stack([d02, s01, s2, s12], -1),
            np.stack([d10, s02, s12, s2], -1),
        ],
        axis=0,
    )
    q = np.take_along_axis(branches, k[None, ..., None], 0)[0] / (2.0 * np.sqrt(s2))[..., None]
    return q * np.where(q[..., :1] < 0, -1.0, 1.0)


def earth_field(norm_ut: float, dip_deg: float) -> np.ndarray:
    """Earth magnetic field in ENU (µT) for a field magnitude and dip angle (° down)."""
    dip = np.deg2rad(dip_deg)
    return np.array([0.0, norm_ut * np.cos(dip), -norm_ut * np.sin(dip)])


def gravity_up() -> np.ndarray:
    """Specific force at rest in ENU (m/s²): the accelerometer reads +g upward."""
    return np.array([0.0, 0.0, GRAVITY])
