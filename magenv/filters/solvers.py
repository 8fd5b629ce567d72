"""Single-frame attitude solvers (Wahba's problem for two vectors): TRIAD and QUEST.

Ligorio & Sabatini 2016 (survey, §2.2): given the gravity and Earth-field
directions measured in the sensor frame (accelerometer, magnetometer) and
known in the earth frame, find the orientation.

* **TRIAD** trusts gravity completely: the accelerometer fixes the
  inclination, the magnetometer only the heading (its projection on the
  horizontal plane). A magnetic disturbance can turn the heading but never
  tilts the estimate.
* **QUEST** weights both vectors (Davenport's q-method: maximise
  ``Σ wᵢ rᵢ·(R bᵢ)``); a disturbed magnetometer tilts the estimate too.

Reading of the survey in magenv's convention (``magenv.quaternion``): the
survey's ``q^bn`` maps NED → body, scalar last; here every solver returns the
scalar-first Hamilton quaternion that maps **sensor → ENU**
(``v_E = q ⊗ v_S ⊗ q*``), with ``w ≥ 0``. Reference vectors are given in ENU:
``gravity_up()`` (the specific force at rest points up) and
``earth_field(m0, θ0)``; only their directions matter.

QUEST for two vectors is solved in closed form: the largest eigenvalue of
Davenport's matrix is ``λ = sqrt(w₁² + w₂² + 2w₁w₂·cos(θ_b − θ_r))``
(θ the angle between the two vectors in each frame, Markley 1988 [29]), and
the quaternion is the dominant column of ``adj(N − λI)`` — exact, no
iteration, no 180° singularity. A symmetric eigensolver is the fallback for
degenerate input. Kernels return NaN for degenerate input (a zero vector, or
acc ∥ mag) — as 4-tuples (``*4``, allocation-free, for the filters' sample
loops) or (4,) arrays (``*1``); the array functions raise :class:`SolverError`.
Filters that pick a solver by name hold a :class:`Solver` and call :func:`solve1`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from magenv import quaternion as quat
from magenv.checks import check_choice, check_vector
from magenv.filters.linalg import mat3


class SolverError(ValueError):
    """Degenerate or non-finite input to a single-frame solver."""


QUEST_WEIGHTS = (0.5, 0.5)  # (w_acc, w_mag): the survey's "same belief to both" reading
TRIAD, QUEST = 0, 1
SOLVERS = {"triad": TRIAD, "quest": QUEST}


class Solver(NamedTuple):
    """A single-frame solver chosen by a filter: which one, and QUEST's relative weights."""

    kind: int  # TRIAD or QUEST
    w_acc: float  # QUEST weight of the gravity pair (relative)
    w_mag: float  # QUEST weight of the field pair (relative)


def make_solver(name: str, weights: tuple[float, float] = QUEST_WEIGHTS) -> Solver:
    """The :class:`Solver` named ``name`` (``"triad"`` or ``"quest"``) with QUEST ``weights`` (w_acc, w_mag):
    two finite numbers ≥ 0, not both zero. ValueError / TypeError naming the bad argument."""
    check_choice("solver", name, sorted(SOLVERS))
    w = check_vector("weights", weights, 2, nonzero=True)
    if np.any(w < 0):
        raise ValueError(f"weights must be two finite numbers ≥ 0 (w_acc, w_mag), not both zero, got {weights!r}")
    return Solver(SOLVERS[name], float(w[0]), float(w[1]))


@njit(cache=True, inline="always")
def _cross(a, b):
    return a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]


@njit(cache=True, inline="always")
def _norm3(v):
    return np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@njit(cache=True, inline="always")
def _div3(v, d):
    return v[0] / d, v[1] / d, v[2] / d


_NAN4 = (np.nan, np.nan, np.nan, np.nan)


@njit(cache=True)
def quat_from_dcm4(m):
    """Unit quaternion (w ≥ 0, a 4-tuple) of a rotation matrix ``m`` (9-tuple, row-major) with
    ``v_E = m @ v_S`` (Shepperd)."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m
    tr = m00 + m11 + m22
    if tr >= m00 and tr >= m11 and tr >= m22:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = (0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s)
    elif m00 >= m11 and m00 >= m22:
        s = 2.0 * np.sqrt(1.0 + 2.0 * m00 - tr)
        q = ((m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s)
    elif m11 >= m22:
        s = 2.0 * np.sqrt(1.0 + 2.0 * m11 - tr)
        q = ((m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s)
    else:
        s = 2.0 * np.sqrt(1.0 + 2.0 * m22 - tr)
        q = ((m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s)
    if q[0] < 0.0:
        q = (-q[0], -q[1], -q[2], -q[3])
    return quat.normalize4(q)


@njit(cache=True)
def quat_from_dcm1(m):
    """Unit quaternion (w ≥ 0) of a rotation matrix ``m`` with ``v_E = m @ v_S`` (Shepperd)."""
    return np.array(quat_from_dcm4(mat3(m)))


@njit(cache=True)
def triad4(acc, mag, g_ref, h_ref):
    """TRIAD orientation (sensor → ENU, a 4-tuple) from body ``acc``, ``mag`` and ENU ``g_ref``, ``h_ref``.

    Gravity is the primary vector: ``R·acĉ = ĝ_ref`` exactly; the magnetometer
    only sets the rotation about it. NaN for a zero vector or acc ∥ mag.
    """
    na = _norm3(acc)
    c_b = _cross(acc, mag)
    nc_b = _norm3(c_b)
    c_r = _cross(g_ref, h_ref)
    nc_r = _norm3(c_r)
    ng = _norm3(g_ref)
    if not (na > 0.0 and nc_b > 1e-12 * na * _norm3(mag) and nc_r > 0.0 and ng > 0.0):
        return _NAN4
    t1 = _div3(acc, na)
    t2 = _div3(c_b, nc_b)
    t3 = _cross(t1, t2)
    r1 = _div3(g_ref, ng)
    r2 = _div3(c_r, nc_r)
    r3 = _cross(r1, r2)
    m = (
        r1[0] * t1[0] + r2[0] * t2[0] + r3[0] * t3[0],
        r1[0] * t1[1] + r2[0] * t2[1] + r3[0] * t3[1],
        r1[0] * t1[2] + r2[0] * t2[2] + r3[0] * t3[2],
        r1[1] * t1[0] + r2[1] * t2[0] + r3[1] * t3[0],
        r1[1] * t1[1] + r2[1] * t2[1] + r3[1] * t3[1],
        r1[1] * t1[2] + r2[1] * t2[2] + r3[1] * t3[2],
        r1[2] * t1[0] + r2[2] * t2[0] + r3[2] * t3[0],
        r1[2] * t1[1] + r2[2] * t2[1] + r3[2] * t3[1],
        r1[2] * t1[2] + r2[2] * t2[2] + r3[2] * t3[2],
    )
    return quat_from_dcm4(m)


@njit(cache=True)
def triad1(acc, mag, g_ref, h_ref):
    """:func:`triad4` as a (4,) array."""
    return np.array(triad4(acc, mag, g_ref, h_ref))


@njit(cache=True, inline="always")
def _det3(a, r, c):
    """Determinant of the 3×3 submatrix of the 16-tuple ``a`` (4×4 row-major) on rows ``r`` and columns ``c``
    (3-tuples)."""
    r0, r1, r2 = 4 * r[0], 4 * r[1], 4 * r[2]
    c0, c1, c2 = c[0], c[1], c[2]
    return (
        a[r0 + c0] * (a[r1 + c1] * a[r2 + c2] - a[r1 + c2] * a[r2 + c1])
        - a[r0 + c1] * (a[r1 + c0] * a[r2 + c2] - a[r1 + c2] * a[r2 + c0])
        + a[r0 + c2] * (a[r1 + c0] * a[r2 + c1] - a[r1 + c1] * a[r2 + c0])
    )


@njit(cache=True)
def davenport16(acc, mag, g_ref, h_ref, w_acc, w_mag):
    """:func:`davenport_matrix1` as a 16-tuple (row-major)."""
    b1 = _div3(acc, _norm3(acc))
    b2 = _div3(mag, _norm3(mag))
    r1 = _div3(g_ref, _norm3(g_ref))
    r2 = _div3(h_ref, _norm3(h_ref))
    s00 = w_acc * b1[0] * r1[0] + w_mag * b2[0] * r2[0]
    s01 = w_acc * b1[0] * r1[1] + w_mag * b2[0] * r2[1]
    s02 = w_acc * b1[0] * r1[2] + w_mag * b2[0] * r2[2]
    s10 = w_acc * b1[1] * r1[0] + w_mag * b2[1] * r2[0]
    s11 = w_acc * b1[1] * r1[1] + w_mag * b2[1] * r2[1]
    s12 = w_acc * b1[1] * r1[2] + w_mag * b2[1] * r2[2]
    s20 = w_acc * b1[2] * r1[0] + w_mag * b2[2] * r2[0]
    s21 = w_acc * b1[2] * r1[1] + w_mag * b2[2] * r2[1]
    s22 = w_acc * b1[2] * r1[2] + w_mag * b2[2] * r2[2]
    n00 = s00 + s11 + s22
    n01 = s12 - s21
    n02 = s20 - s02
    n03 = s01 - s10
    n11 = s00 - s11 - s22
    n12 = s01 + s10
    n13 = s20 + s02
    n22 = -s00 + s11 - s22
    n23 = s12 + s21
    n33 = -s00 - s11 + s22
    return (n00, n01, n02, n03, n01, n11, n12, n13, n02, n12, n22, n23, n03, n13, n23, n33)


@njit(cache=True)
def davenport_matrix1(acc, mag, g_ref, h_ref, w_acc, w_mag):
    """Symmetric 4×4 matrix N (scalar-first) whose top eigenvector is the q-method solution.

    ``q^T N q = Σ wᵢ rᵢ·(q ⊗ bᵢ ⊗ q*)`` for unit body vectors bᵢ and unit
    reference vectors rᵢ (Horn's form of Davenport's K for the Hamilton
    sensor → earth quaternion).
    """
    return np.array(davenport16(acc, mag, g_ref, h_ref, w_acc, w_mag)).reshape(4, 4)


_OTHERS = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))  # the rows (columns) of a 4×4 without row j


@njit(cache=True)
def quest4(acc, mag, g_ref, h_ref, w_acc, w_mag):
    """QUEST (q-method) orientation (sensor → ENU, a 4-tuple) from two weighted vector pairs.

    Weights are relative (only w_acc : w_mag matters). NaN for a zero vector
    or acc ∥ mag.
    """
    na = _norm3(acc)
    nm = _norm3(mag)
    ng = _norm3(g_ref)
    nh = _norm3(h_ref)
    if not (na > 0.0 and nm > 0.0 and ng > 0.0 and nh > 0.0 and w_acc >= 0.0 and w_mag >= 0.0 and w_acc + w_mag > 0.0):
        return _NAN4
    b1 = _div3(acc, na)
    b2 = _div3(mag, nm)
    r1 = _div3(g_ref, ng)
    r2 = _div3(h_ref, nh)
    sb = _norm3(_cross(b1, b2))
    sr = _norm3(_cross(r1, r2))
    if sb < 1e-9 or sr < 1e-9:
        return _NAN4
    cos_d = (b1[0] * b2[0] + b1[1] * b2[1] + b1[2] * b2[2]) * (r1[0] * r2[0] + r1[1] * r2[1] + r1[2] * r2[2]) + sb * sr
    lam = np.sqrt(max(w_acc * w_acc + w_mag * w_mag + 2.0 * w_acc * w_mag * cos_d, 0.0))
    d = davenport16(b1, b2, r1, r2, w_acc, w_mag)
    n = (d[0] - lam, d[1], d[2], d[3], d[4], d[5] - lam, d[6], d[7], d[8], d[9], d[10] - lam, d[11], d[12], d[13],
         d[14], d[15] - lam)  # fmt: skip
    # Columns of adj(N − λI) (symmetric, so rows = columns) are ∝ the eigenvector of λ.
    best = (0.0, 0.0, 0.0, 0.0)
    best_n = -1.0
    for j in range(4):
        rows = _OTHERS[j]
        # cofactor C_ji = (-1)^(i+j) · minor(row j, col i); adj[i, j] = C_ji
        c0 = (1.0 if j % 2 == 0 else -1.0) * _det3(n, rows, _OTHERS[0])
        c1 = (1.0 if j % 2 == 1 else -1.0) * _det3(n, rows, _OTHERS[1])
        c2 = (1.0 if j % 2 == 0 else -1.0) * _det3(n, rows, _OTHERS[2])
        c3 = (1.0 if j % 2 == 1 else -1.0) * _det3(n, rows, _OTHERS[3])
        cn = c0 * c0 + c1 * c1 + c2 * c2 + c3 * c3
        if cn > best_n:
            best_n = cn
            best = (c0, c1, c2, c3)
    scale = (w_acc + w_mag) ** 3
    if best_n > (1e-10 * scale) ** 2:
        r = np.sqrt(best_n)
        q = (best[0] / r, best[1] / r, best[2] / r, best[3] / r)
    else:  # near-degenerate spectrum: fall back to the eigensolver
        a = np.array(n).reshape(4, 4)
        for i in range(4):
            a[i, i] += lam
        _, vecs = np.linalg.eigh(a)
        q = (vecs[0, 3], vecs[1, 3], vecs[2, 3], vecs[3, 3])
    if q[0] < 0.0:
        q = (-q[0], -q[1], -q[2], -q[3])
    return q


@njit(cache=True)
def quest1(acc, mag, g_ref, h_ref, w_acc, w_mag):
    """:func:`quest4` as a (4,) array."""
    return np.array(quest4(acc, mag, g_ref, h_ref, w_acc, w_mag))


@njit(cache=True)
def solve4(solver, acc, mag, g_ref, h_ref):
    """Orientation (sensor → ENU, a 4-tuple) by ``solver`` (:class:`Solver`) from body ``acc``, ``mag`` and ENU
    references."""
    if solver.kind == TRIAD:
        return triad4(acc, mag, g_ref, h_ref)
    return quest4(acc, mag, g_ref, h_ref, solver.w_acc, solver.w_mag)


@njit(cache=True)
def solve1(solver, acc, mag, g_ref, h_ref):
    """:func:`solve4` as a (4,) array."""
    return np.array(solve4(solver, acc, mag, g_ref, h_ref))


@njit(cache=True)
def _triad_many(acc, mag, g_ref, h_ref, out):
    for i in range(acc.shape[0]):
        out[i] = triad1(acc[i], mag[i], g_ref, h_ref)


@njit(cache=True)
def _quest_many(acc, mag, g_ref, h_ref, w_acc, w_mag, out):
    for i in range(acc.shape[0]):
        out[i] = quest1(acc[i], mag[i], g_ref, h_ref, w_acc, w_mag)


def _prepare(acc, mag, h_ref, g_ref):
    acc = np.ascontiguousarray(acc, dtype=float)
    mag = np.ascontiguousarray(mag, dtype=float)
    if acc.shape != mag.shape or acc.shape[-1:] != (3,):
        raise SolverError(f"acc and mag must both have shape (..., 3), got {acc.shape} and {mag.shape}")
    g_ref = quat.gravity_up() if g_ref is None else np.asarray(g_ref, dtype=float)
    h_ref = np.asarray(h_ref, dtype=float)
    if g_ref.shape != (3,) or h_ref.shape != (3,):
        raise SolverError(f"reference vectors must have shape (3,), got {g_ref.shape} and {h_ref.shape}")
    shape = acc.shape[:-1]
    return acc.reshape(-1, 3), mag.reshape(-1, 3), h_ref, g_ref, shape


def _check(q, acc, mag, name):
    bad = ~np.all(np.isfinite(q), axis=-1)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise SolverError(
            f"{name}: degenerate or non-finite input at row {i} (acc={acc[i]}, mag={mag[i]}): "
            "a zero vector, NaN, or acc parallel to mag"
        )


def triad(acc, mag, h_ref, g_ref=None) -> np.ndarray:
    """TRIAD orientations (..., 4), sensor → ENU, of body vectors (..., 3).

    Args:
        acc: accelerometer (any unit), sensor frame; trusted for inclination.
        mag: magnetometer (any unit), sensor frame; sets heading only.
        h_ref: Earth field in ENU, e.g. ``quat.earth_field(m0, θ0)``.
        g_ref: gravity reference in ENU (default ``quat.gravity_up()``).
    """
    a, m, h_ref, g_ref, shape = _prepare(acc, mag, h_ref, g_ref)
    out = np.empty((len(a), 4))
    _triad_many(a, m, g_ref, h_ref, out)
    _check(out, a, m, "triad")
    return out.reshape(shape + (4,))


def quest(acc, mag, h_ref, g_ref=None, weights=QUEST_WEIGHTS) -> np.ndarray:
    """QUEST orientations (..., 4), sensor → ENU; ``weights = (w_acc, w_mag)`` (relative)."""
    a, m, h_ref, g_ref, shape = _prepare(acc, mag, h_ref, g_ref)
    w_acc, w_mag = (float(w) for w in weights)
    if not (w_acc >= 0 and w_mag >= 0 and w_acc + w_mag > 0):
        raise SolverError(f"quest: weights must be non-negative and not both zero, got {weights}")
    out = np.empty((len(a), 4))
    _quest_many(a, m, g_ref, h_ref, w_acc, w_mag, out)
    _check(out, a, m, "quest")
    return out.reshape(shape + (4,))
