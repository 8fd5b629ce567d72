"""Small fixed-size linear algebra written out for the filters' sample loops: nothing is allocated.

* 3×3 matrices as 9-tuples, row-major (``m[3 * i + j]``), 3-vectors as 3-tuples (:func:`mat3` reads a
  (3, 3) array): products, the symmetric sandwich ``A P Aᵀ``, the inverse by the adjugate, the innovation
  covariance and the Joseph form of a 3-component update (:func:`joseph3`) — the pieces of the trust KF
  (``magenv.filters.kalman_trust``) and of the Gauss–Markov split (``magenv.filters.kalman_model``).
* :func:`inv4` — a 4×4 inverse by the adjugate (the threshold KF's ``S⁻¹``,
  ``magenv.filters.kalman_threshold``).
* Symmetric n×n covariances held in arrays, updated in place on their leading ``n`` rows and columns
  (``magenv.filters.qsf``'s 11 and 15 states): the Joseph update with a 3-row measurement through its
  low-rank factors (:func:`joseph_update`), the projection of a quaternion's rows and columns on the unit
  sphere's tangent (:func:`project_quaternion`), both O(n²).
* :func:`is_pd3` — the Cholesky test of a symmetric 3×3 in scalars, the same arithmetic as
  ``kalman_threshold.is_pd``.

Symmetric results are computed on one triangle and mirrored, so they are exactly symmetric.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def mat3(a):
    """The 9-tuple (row-major) of a (3, 3) array."""
    return (a[0, 0], a[0, 1], a[0, 2], a[1, 0], a[1, 1], a[1, 2], a[2, 0], a[2, 1], a[2, 2])


@njit(cache=True, inline="always")
def store3(m, out):
    """Write the 9-tuple ``m`` into the (3, 3) array ``out``."""
    out[0, 0], out[0, 1], out[0, 2] = m[0], m[1], m[2]
    out[1, 0], out[1, 1], out[1, 2] = m[3], m[4], m[5]
    out[2, 0], out[2, 1], out[2, 2] = m[6], m[7], m[8]


@njit(cache=True, inline="always")
def diag3(d):
    """d·I as a 9-tuple."""
    return (d, 0.0, 0.0, 0.0, d, 0.0, 0.0, 0.0, d)


@njit(cache=True, inline="always")
def clip(x, lo, hi):
    """``numpy.clip`` of one number: NaN stays NaN; ties and signed zeros as numpy gives them."""
    if x != x:
        return x
    m = x if x > lo else lo
    return m if m < hi else hi


@njit(cache=True, inline="always")
def skew3(v):
    """[v×] with ``[v×] u = v × u``, as a 9-tuple."""
    return (0.0, -v[2], v[1], v[2], 0.0, -v[0], -v[1], v[0], 0.0)


@njit(cache=True, inline="always")
def dot3(u, v):
    """``u · v`` of two 3-vectors, summed left to right (the order of every product below)."""
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


@njit(cache=True, inline="always")
def rows3(a):
    """The rows of a 9-tuple: three 3-tuples."""
    return (a[0], a[1], a[2]), (a[3], a[4], a[5]), (a[6], a[7], a[8])


@njit(cache=True, inline="always")
def t33(a):
    """``aᵀ`` of a 9-tuple."""
    return (a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8])


@njit(cache=True, inline="always")
def mul33t(a, b):
    """``a @ bᵀ`` of two 9-tuples: entry (i, j) is row i of a · row j of b."""
    a0, a1, a2 = rows3(a)
    b0, b1, b2 = rows3(b)
    return (
        dot3(a0, b0), dot3(a0, b1), dot3(a0, b2),
        dot3(a1, b0), dot3(a1, b1), dot3(a1, b2),
        dot3(a2, b0), dot3(a2, b1), dot3(a2, b2),
    )  # fmt: skip


@njit(cache=True, inline="always")
def mul33(a, b):
    """``a @ b`` of two 9-tuples, as ``a @ (bᵀ)ᵀ``."""
    return mul33t(a, t33(b))


@njit(cache=True, inline="always")
def mulsym33t(a, b):
    """``a @ bᵀ`` of two 9-tuples whose product is symmetric (e.g. ``(A P) Aᵀ``, ``K Kᵀ``): the upper
    triangle computed, the lower mirrored."""
    a0, a1, a2 = rows3(a)
    b0, b1, b2 = rows3(b)
    m01, m02, m12 = dot3(a0, b1), dot3(a0, b2), dot3(a1, b2)
    return (dot3(a0, b0), m01, m02, m01, dot3(a1, b1), m12, m02, m12, dot3(a2, b2))


@njit(cache=True, inline="always")
def sandwich3(a, p):
    """``a p aᵀ`` (symmetric p) as a symmetric 9-tuple: ``(a @ p) @ aᵀ`` on the upper triangle."""
    return mulsym33t(mul33(a, p), a)


@njit(cache=True, inline="always")
def add33(a, b):
    """``a + b`` of two 9-tuples."""
    return (
        a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3], a[4] + b[4], a[5] + b[5], a[6] + b[6], a[7] + b[7],
        a[8] + b[8],
    )  # fmt: skip


@njit(cache=True, inline="always")
def scale33(s, a):
    """``s·a`` of a 9-tuple."""
    return (s * a[0], s * a[1], s * a[2], s * a[3], s * a[4], s * a[5], s * a[6], s * a[7], s * a[8])


@njit(cache=True, inline="always")
def sub33(a, b):
    """``a − b`` of two 9-tuples (``a + (−1)·b``: the same numbers, negation is exact)."""
    return add33(a, scale33(-1.0, b))


@njit(cache=True, inline="always")
def mv3(a, v):
    """``a @ v`` of a 9-tuple and a 3-vector, as a 3-tuple."""
    a0, a1, a2 = rows3(a)
    return (dot3(a0, v), dot3(a1, v), dot3(a2, v))


@njit(cache=True, inline="always")
def quad3(v, a):
    """``(v @ a) @ v`` of a 3-vector and a 9-tuple."""
    return dot3(mv3(t33(a), v), v)


@njit(cache=True, inline="always")
def inv3(a):
    """Inverse of a 9-tuple by its adjugate over the determinant (a symmetric ``a`` gives an exactly symmetric
    inverse); NaN entries where ``a`` is singular (the filters then fail loudly on a non-finite state)."""
    c00 = a[4] * a[8] - a[5] * a[7]
    c01 = a[5] * a[6] - a[3] * a[8]
    c02 = a[3] * a[7] - a[4] * a[6]
    c10 = a[2] * a[7] - a[1] * a[8]
    c11 = a[0] * a[8] - a[2] * a[6]
    c12 = a[1] * a[6] - a[0] * a[7]
    c20 = a[1] * a[5] - a[2] * a[4]
    c21 = a[2] * a[3] - a[0] * a[5]
    c22 = a[0] * a[4] - a[1] * a[3]
    det = a[0] * c00 + a[1] * c01 + a[2] * c02
    d = 1.0 / det if det != 0.0 else np.nan
    return (c00 * d, c10 * d, c20 * d, c01 * d, c11 * d, c21 * d, c02 * d, c12 * d, c22 * d)


@njit(cache=True, inline="always")
def innovation_cov3(p, h, r):
    """``S = H P Hᵀ + r I`` of a 3×3 symmetric P and a 3-row H (9-tuples)."""
    s = sandwich3(h, p)
    return (s[0] + r, s[1], s[2], s[3], s[4] + r, s[5], s[6], s[7], s[8] + r)


@njit(cache=True, inline="always")
def joseph3(p, k, h, r):
    """Joseph form ``(I − K H) P (I − K H)ᵀ + r K Kᵀ`` (exact for any gain K) of 9-tuples, symmetric."""
    kh = mul33(k, h)
    a = (1.0 - kh[0], -kh[1], -kh[2], -kh[3], 1.0 - kh[4], -kh[5], -kh[6], -kh[7], 1.0 - kh[8])
    return add33(sandwich3(a, p), scale33(r, mulsym33t(k, k)))


@njit(cache=True, inline="always")
def is_pd3(p):
    """Cholesky test of the symmetric 9-tuple ``p``: True if positive definite (the arithmetic of
    ``kalman_threshold.is_pd``, so both decide alike)."""
    s = p[0]
    if not (s > 0.0):
        return False
    inv0 = 1.0 / np.sqrt(s)
    l10 = p[3] * inv0
    l20 = p[6] * inv0
    s = p[4] - l10 * l10
    if not (s > 0.0):
        return False
    l21 = (p[7] - l20 * l10) * (1.0 / np.sqrt(s))
    s = p[8] - l20 * l20 - l21 * l21
    return s > 0.0


@njit(cache=True)
def inv4(a, out):
    """``out`` (4, 4) ← the inverse of the (4, 4) array ``a`` by its adjugate over the determinant (Laplace
    expansion in the 2×2 minors of the first two and the last two rows); NaN where ``a`` is singular."""
    s, c = _minors2(a, 0, 1), _minors2(a, 2, 3)  # of the first two rows, of the last two
    det = s[0] * c[5] - s[1] * c[4] + s[2] * c[3] + s[3] * c[2] - s[4] * c[1] + s[5] * c[0]
    d = 1.0 / det if det != 0.0 else np.nan
    _inv4_row(a, 0, c, s, d, out)
    _inv4_row(a, 1, c, s, d, out)
    _inv4_row(a, 2, c, s, d, out)
    _inv4_row(a, 3, c, s, d, out)


@njit(cache=True, inline="always")
def _minors2(a, r0, r1):
    """The 2×2 minors of rows r0, r1 of the (4, 4) array ``a`` on the column pairs (0, 1), (0, 2), (0, 3),
    (1, 2), (1, 3), (2, 3)."""
    return (
        _minor2(a, r0, r1, 0, 1), _minor2(a, r0, r1, 0, 2), _minor2(a, r0, r1, 0, 3),
        _minor2(a, r0, r1, 1, 2), _minor2(a, r0, r1, 1, 3), _minor2(a, r0, r1, 2, 3),
    )  # fmt: skip


@njit(cache=True, inline="always")
def _minor2(a, r0, r1, j0, j1):
    """``a[r0, j0] a[r1, j1] − a[r1, j0] a[r0, j1]``."""
    return a[r0, j0] * a[r1, j1] - a[r1, j0] * a[r0, j1]


@njit(cache=True, inline="always")
def _inv4_row(a, r, c, s, d, out):
    """Row r of :func:`inv4`'s inverse: entry k is (−1)^(r+k) (row i of a without column r) · its complementary
    minors (``c`` of a's last two rows for k < 2, ``s`` of its first two for k ≥ 2), over the determinant."""
    j0, j1, j2 = _INV4_COLUMNS[r]
    m0, m1, m2 = _INV4_MINORS[r]
    for k in range(4):
        i = _INV4_ROWS[k]
        x0, x1, x2 = a[i, j0], a[i, j1], a[i, j2]
        if (r + k) % 2:
            x0, x1, x2 = -x0, -x1, -x2
        if k < 2:
            out[r, k] = (x0 * c[m0] - x1 * c[m1] + x2 * c[m2]) * d
        else:
            out[r, k] = (x0 * s[m0] - x1 * s[m1] + x2 * s[m2]) * d


# inv4's tables: for inverse row r, the columns of a other than r and the indices of their 2×2 minors (c, of the
# last two rows, for k < 2; s, of the first two, for k ≥ 2); for inverse column k, the row i of a it expands.
_INV4_COLUMNS = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))
_INV4_MINORS = ((5, 4, 3), (5, 2, 1), (4, 2, 0), (3, 1, 0))
_INV4_ROWS = (1, 0, 3, 2)


# ------------------------------------------------------------ symmetric n×n in place


@njit(cache=True)
def joseph_update(p, n, hp, kt, s, work):
    """``P ← (I − K H) P (I − K H)ᵀ + K R Kᵀ`` on the leading n×n block of the symmetric ``p``, in place.

    The Joseph form (exact for any gain) written out through its low-rank factors: with C = P Hᵀ = (H P)ᵀ and
    S = H P Hᵀ + R, it is ``P − K Cᵀ − C Kᵀ + K S Kᵀ = P − K Cᵀ + G Kᵀ``, G = K S − C (n×3), computed row by
    row on the upper triangle and mirrored: O(n²) for a 3-row measurement instead of the O(n³) products.
    ``hp`` (3, ≥ n) = H P, ``kt`` (3, ≥ n) = Kᵀ, ``s`` the 9-tuple S, ``work`` (≥ 3, ≥ n) scratch for Gᵀ.
    """
    for i in range(n):
        k0, k1, k2 = kt[0, i], kt[1, i], kt[2, i]
        work[0, i] = (k0 * s[0] + k1 * s[3] + k2 * s[6]) - hp[0, i]
        work[1, i] = (k0 * s[1] + k1 * s[4] + k2 * s[7]) - hp[1, i]
        work[2, i] = (k0 * s[2] + k1 * s[5] + k2 * s[8]) - hp[2, i]
    h0, h1, h2, k0, k1, k2 = hp[0], hp[1], hp[2], kt[0], kt[1], kt[2]
    for i in range(n):
        a0, a1, a2 = k0[i], k1[i], k2[i]
        g0, g1, g2 = work[0, i], work[1, i], work[2, i]
        row = p[i]
        for j in range(i, n):
            row[j] = row[j] - (a0 * h0[j] + a1 * h1[j] + a2 * h2[j]) + (g0 * k0[j] + g1 * k1[j] + g2 * k2[j])
        for j in range(i + 1, n):
            p[j, i] = row[j]


@njit(cache=True)
def project_quaternion(p, n, q, off, eps):
    """``P ← T P Tᵀ + eps·q qᵀ`` on the rows and columns ``off … off+3`` of the symmetric n×n ``p``, in place:
    ``T = I − q qᵀ`` (q unit, (4,) or a 4-tuple) projects the quaternion's error on the unit sphere's
    tangent and ``eps`` keeps a small radial variance."""
    q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
    for j in range(n):  # rows: P[q, j] -= q (qᵀ P[q, j])
        d = q0 * p[off, j] + q1 * p[off + 1, j] + q2 * p[off + 2, j] + q3 * p[off + 3, j]
        p[off, j] -= q0 * d
        p[off + 1, j] -= q1 * d
        p[off + 2, j] -= q2 * d
        p[off + 3, j] -= q3 * d
    for i in range(n):  # columns, likewise
        d = q0 * p[i, off] + q1 * p[i, off + 1] + q2 * p[i, off + 2] + q3 * p[i, off + 3]
        p[i, off] -= q0 * d
        p[i, off + 1] -= q1 * d
        p[i, off + 2] -= q2 * d
        p[i, off + 3] -= q3 * d
    qq = (q0, q1, q2, q3)
    for a in range(4):
        for b in range(a, 4):
            v = 0.5 * (p[off + a, off + b] + p[off + b, off + a]) + eps * qq[a] * qq[b]
            p[off + a, off + b] = v
            p[off + b, off + a] = v
