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
degenerate input. Kernels (``*1``) return NaN for degenerate input (a zero
vector, or acc ∥ mag); the array functions raise :class:`SolverError`.
Filters that pick a solver by name hold a :class:`Solver` and call :func:`solve1`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from magenv import quaternion as quat
from magenv.checks import check_choice, check_vector


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
    out = np.empty(3)
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]
    return out


@njit(cache=True, inline="always")
def _norm3(v):
    return np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@njit(cache=True)
def quat_from_dcm1(m):
    """Unit quaternion (w ≥ 0) of a rotation matrix ``m`` with ``v_E = m @ v_S`` (Shepperd)."""
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    q = np.empty(4)
    if tr >= m[0, 0] and tr >= m[1, 1] and tr >= m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + tr)
        q[0] = 0.25 * s
        q[1] = (m[2, 1] - m[1, 2]) / s
        q[2] = (m[0, 2] - m[2, 0]) / s
        q[3] = (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + 2.0 * m[0, 0] - tr)
        q[0] = (m[2, 1] - m[1, 2]) / s
        q[1] = 0.25 * s
        q[2] = (m[0, 1] + m[1, 0]) / s
        q[3] = (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] >= m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + 2.0 * m[1, 1] - tr)
        q[0] = (m[0, 2] - m[2, 0]) / s
        q[1] = (m[0, 1] + m[1, 0]) / s
        q[2] = 0.25 * s
        q[3] = (m[1, 2] + m[2, 1]) / s
    else:
        s = 2.0 * np.sqrt(1.0 + 2.0 * m[2, 2] - tr)
        q[0] = (m[1, 0] - m[0, 1]) / s
        q[1] = (m[0, 2] + m[2, 0]) / s
        q[2] = (m[1, 2] + m[2, 1]) / s
        q[3] = 0.25 * s
    if q[0] < 0.0:
        q = -q
    return quat.normalize1(q)


@njit(cache=True)
def triad1(acc, mag, g_ref, h_ref):
    """TRIAD orientation (sensor → ENU) from body ``acc``, ``mag`` and ENU ``g_ref``, ``h_ref``.

    Gravity is the primary vector: ``R·acĉ = ĝ_ref`` exactly; the magnetometer
    only sets the rotation about it. NaN for a zero vector or acc ∥ mag.
    """
    na = _norm3(acc)
    c_b = _cross(acc, mag)
    nc_b = _norm3(c_b)
    c_r = _cross(g_ref, h_ref)
    nc_r = _norm3(c_r)
    ng = _norm3(g_ref)
    if not (na > 0.0 and nc_b > 1e-12 * na * _norm3(mag) and nc_r > 0.0 and ng > 0.0):
        return np.full(4, np.nan)
    t1 = acc / na
    t2 = c_b / nc_b
    t3 = _cross(t1, t2)
    r1 = g_ref / ng
    r2 = c_r / nc_r
    r3 = _cross(r1, r2)
    m = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            m[i, j] = r1[i] * t1[j] + r2[i] * t2[j] + r3[i] * t3[j]
    return quat_from_dcm1(m)


@njit(cache=True, inline="always")
def _det3(a, r0, r1, r2, c0, c1, c2):
    return (
        a[r0, c0] * (a[r1, c1] * a[r2, c2] - a[r1, c2] * a[r2, c1])
        - a[r0, c1] * (a[r1, c0] * a[r2, c2] - a[r1, c2] * a[r2, c0])
        + a[r0, c2] * (a[r1, c0] * a[r2, c1] - a[r1, c1] * a[r2, c0])
    )


@njit(cache=True)
def davenport_matrix1(acc, mag, g_ref, h_ref, w_acc, w_mag):
    """Symmetric 4×4 matrix N (scalar-first) whose top eigenvector is the q-method solution.

    ``q^T N q = Σ wᵢ rᵢ·(q ⊗ bᵢ ⊗ q*)`` for unit body vectors bᵢ and unit
    reference vectors rᵢ (Horn's form of Davenport's K for the Hamilton
    sensor → earth quaternion).
    """
    s = np.zeros((3, 3))
    b1 = acc / _norm3(acc)
    b2 = mag / _norm3(mag)
    r1 = g_ref / _norm3(g_ref)
    r2 = h_ref / _norm3(h_ref)
    for i in range(3):
        for j in range(3):
            s[i, j] = w_acc * b1[i] * r1[j] + w_mag * b2[i] * r2[j]
    n = np.empty((4, 4))
    n[0, 0] = s[0, 0] + s[1, 1] + s[2, 2]
    n[0, 1] = s[1, 2] - s[2, 1]
    n[0, 2] = s[2, 0] - s[0, 2]
    n[0, 3] = s[0, 1] - s[1, 0]
    n[1, 1] = s[0, 0] - s[1, 1] - s[2, 2]
    n[1, 2] = s[0, 1] + s[1, 0]
    n[1, 3] = s[2, 0] + s[0, 2]
    n[2, 2] = -s[0, 0] + s[1, 1] - s[2, 2]
    n[2, 3] = s[1, 2] + s[2, 1]
    n[3, 3] = -s[0, 0] - s[1, 1] + s[2, 2]
    for i in range(4):
        for j in range(i):
            n[i, j] = n[j, i]
    return n


@njit(cache=True)
def quest1(acc, mag, g_ref, h_ref, w_acc, w_mag):
    """QUEST (q-method) orientation (sensor → ENU) from two weighted vector pairs.

    Weights are relative (only w_acc : w_mag matters). NaN for a zero vector
    or acc ∥ mag.
    """
    na = _norm3(acc)
    nm = _norm3(mag)
    ng = _norm3(g_ref)
    nh = _norm3(h_ref)
    if not (na > 0.0 and nm > 0.0 and ng > 0.0 and nh > 0.0 and w_acc >= 0.0 and w_mag >= 0.0 and w_acc + w_mag > 0.0):
        return np.full(4, np.nan)
    b1 = acc / na
    b2 = mag / nm
    r1 = g_ref / ng
    r2 = h_ref / nh
    sb = _norm3(_cross(b1, b2))
    sr = _norm3(_cross(r1, r2))
    if sb < 1e-9 or sr < 1e-9:
        return np.full(4, np.nan)
    cos_d = (b1[0] * b2[0] + b1[1] * b2[1] + b1[2] * b2[2]) * (r1[0] * r2[0] + r1[1] * r2[1] + r1[2] * r2[2]) + sb * sr
    lam = np.sqrt(max(w_acc * w_acc + w_mag * w_mag + 2.0 * w_acc * w_mag * cos_d, 0.0))
    n = davenport_matrix1(b1, b2, r1, r2, w_acc, w_mag)
    for i in range(4):
        n[i, i] -= lam
    # Columns of adj(N − λI) (symmetric, so rows = columns) are ∝ the eigenvector of λ.
    idx = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    best = np.zeros(4)
    best_n = -1.0
    for j in range(4):
        col = np.empty(4)
        for i in range(4):
            sign = 1.0 if (i + j) % 2 == 0 else -1.0
            # cofactor C_ji = (-1)^(i+j) · minor(row j, col i); adj[i, j] = C_ji
            col[i] = sign * _det3(n, idx[j, 0], idx[j, 1], idx[j, 2], idx[i, 0], idx[i, 1], idx[i, 2])
        cn = col[0] * col[0] + col[1] * col[1] + col[2] * col[2] + col[3] * col[3]
        if cn > best_n:
            best_n = cn
            best = col
    scale = (w_acc + w_mag) ** 3
    if best_n > (1e-10 * scale) ** 2:
        q = best / np.sqrt(best_n)
    else:  # near-degenerate spectrum: fall back to the eigensolver
        for i in range(4):
            n[i, i] += lam
        _, vecs = np.linalg.eigh(n)
        q = vecs[:, 3].copy()
    if q[0] < 0.0:
        q = -q
    return q


@njit(cache=True)
def solve1(solver, acc, mag, g_ref, h_ref):
    """Orientation (sensor → ENU) by ``solver`` (:class:`Solver`) from body ``acc``, ``mag`` and ENU references."""
    if solver.kind == TRIAD:
        return triad1(acc, mag, g_ref, h_ref)
    return quest1(acc, mag, g_ref, h_ref, solver.w_acc, solver.w_mag)


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
