"""``MagQSF-v0``'s batch kernel: the envs' Delay MAGYQ / MAGYQ filters in lock-step, the env axis innermost.

:func:`lockstep` advances every env of a :class:`magenv.envs.qsf.Batch` by its ``todo`` samples, as
``magenv.envs.qsf.advance`` does for one env, but ``LANES`` envs at a time: a block's filter states are
copied into arrays whose last axis is the env (structure of arrays), and each sample runs once for the
whole block, so the covariance arithmetic (``qsf._predict_cov``, ``qsf._kalman_update`` with its Joseph
form, the tangent projections, the health check's Cholesky test) is a loop over envs that LLVM turns into
SIMD; the per-env quaternion algebra, decisions and signals stay scalar loops over the block. A block of fewer
than ``NARROW`` envs runs them one by one through ``advance`` instead (the loops' fixed cost outweighs their
vectors there).

Bit for bit ``qsf.step_work``: every quantity of an env is computed by the same operations in the same
order (no fused multiply-add, no reassociation), so the lanes give exactly what the single env gives
(``tests/test_env_qsf_lockstep.py`` checks outputs, covariances and repairs against ``qsf.run_kernel``).
Where the envs differ the work is masked, never reordered:

* every lane runs on the 15 augmented states; an env without a clone (11 states) has zeros in the clone's
  rows and columns of its working covariance, and every operation keeps its 11×11 block apart from them
  (the clone's entries never enter it), while the writes the 11-state kernel does not do (the state's
  clone entries, the clone's normalisation) are masked and the store zeroes the clone block as
  ``qsf._commit_healthy`` does;
* sums over H's nonzero columns stop after q's four for an env whose magnetic H has no clone columns
  (the four-term sum is selected, so the order of additions is the 11-state kernel's);
* updates, predictions and commits are selected per env (no prediction at an episode's first sample, the
  accelerometer gate, no magnetic update, an env with fewer samples left or failed);
* the Cholesky test runs to 15 rows for every env and decides on the env's own rows; an env that fails it
  (or has a non-finite diagonal) is repaired by ``kalman_threshold.repair_sym`` on a copy of its matrix, the
  per-env code path;
* a lane's committed covariance is its working one; a lane that fails after its covariance changed makes the
  block fuse again, that lane stopping before the failed sample (:func:`_block`).

Loops over the lanes use unsigned indices (numba's signed ones carry a negative-index wrap that stops
LLVM's vectoriser).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange, uint64

from magenv.envs.batch import window
from magenv.envs.common import Truth
from magenv.envs.qsf import advance, feature_row, fill_decision, observed
from magenv.filters import qsf
from magenv.filters.kalman_threshold import finite3, repair_sym
from magenv.filters.linalg import inv3, quad3
from magenv.filters.qsf import (
    CLONE_JITTER,
    MAG_KEEP,
    MAG_START,
    MODE_AEKF,
    MODE_DELAY,
    N_AUGMENTED,
    N_STATE,
    SIGNAL,
    heading_row4,
    jacobian34,
)
from magenv.metrics import N_ERR, error_sums
from magenv.quaternion import from_rotvec4, left_matrix4, mul4, normalize4, right_matrix4, rotate3

LANES = 128  # envs per block at most: the block's working arrays stay in the core's second-level cache
NARROW = 8  # a block of fewer envs runs them one by one (qsf.advance): the lock-step loops cost more than they gain
_N = uint64(N_AUGMENTED)
_C0 = uint64(N_STATE)  # the clone's first row (qsf.CLONE.start)


class Lanes(NamedTuple):
    """A block's working arrays, the env (lane) axis last; ``qsf.Work``'s, plus what the scalar parts hand the
    vector parts."""

    x: np.ndarray  # (15, L) the state being updated (qsf.Work.x)
    p: np.ndarray  # (15, 15, L) its covariance
    cx: np.ndarray  # (15, L) the committed state (qsf.State.x; its covariance is p's: see _block)
    h: np.ndarray  # (3, 15, L) measurement Jacobian
    hp: np.ndarray  # (3, 15, L) H P
    kt: np.ndarray  # (3, 15, L) the gain, transposed
    r: np.ndarray  # (4, 15, L) the prediction's rows of F P; the Joseph update's G (3 rows)
    lo: np.ndarray  # (15, 15, L) Cholesky factor of the health test
    cm: np.ndarray  # (4, 4, L) C(q̂_ω) of the prediction
    mm: np.ndarray  # (4, 4, L) M(q)
    nu: np.ndarray  # (3, L) innovation
    s_inv: np.ndarray  # (9, L) S⁻¹ of the last update
    f: np.ndarray  # (_F, L) per-lane numbers (rows _RD …)
    on: np.ndarray  # (_M, L) int8 per-lane masks (rows _GO …)
    size: np.ndarray  # (1,) uint64: the lanes in use, the first ones (the block's envs)


# rows of Lanes.f: R's diagonal, the gain, the radial eps, |Δq| of the update, a sum being formed, then the
# env's Δt, σ_g, σ_bq, σ_ba, σ_a, th_acc, acc_adaptive, g_ENU (3), the sample's accelerometer (3) and gyro
# quaternion (4)
_RD, _GAIN, _EPS, _CORR, _SUM = range(5)
_DT, _SG, _SBW, _SABW, _SACC, _THACC, _ADAPT, _G, _A = 5, 6, 7, 8, 9, 10, 11, 12, 15
_QY = 18  # the sample's gyro quaternion q_yg (4)
_F = _QY + 4
# rows of Lanes.on: the lane fuses this sample, predicts, updates, has the clone (15 states), H has clone
# columns, starts a clone, passes the health test, renormalises its clone, commits
_GO, _PRED, _UPD, _CL, _HCL, _START, _OK, _BOTH, _COMMIT = range(9)
_M = 9


@njit(cache=True)
def lanes(L) -> Lanes:
    """Working arrays for blocks of up to L lanes."""
    n = N_AUGMENTED
    return Lanes(
        np.zeros((n, L)), np.zeros((n, n, L)), np.zeros((n, L)), np.zeros((3, n, L)),
        np.zeros((3, n, L)), np.zeros((3, n, L)), np.zeros((4, n, L)), np.zeros((n, n, L)), np.zeros((4, 4, L)),
        np.zeros((4, 4, L)), np.zeros((3, L)), np.zeros((9, L)), np.zeros((_F, L)), np.zeros((_M, L), np.int8),
        np.full(1, L, np.uint64),
    )  # fmt: skip


# ------------------------------------------------------------ vector parts (loops over the lanes innermost)


@njit(cache=True, error_model="numpy")
def _predict_cov(w):
    """``qsf._predict_cov`` on every lane with ``_PRED``, over 15 states."""
    p, r, c, m, pred = w.p, w.r, w.cm, w.mm, w.on[_PRED]
    for a in range(4):
        for j in range(_N):
            for e in range(w.size[0]):
                cq = (
                    c[a, 0, e] * p[0, j, e]
                    + c[a, 1, e] * p[1, j, e]
                    + c[a, 2, e] * p[2, j, e]
                    + c[a, 3, e] * p[3, j, e]
                )
                mb = (
                    m[a, 0, e] * p[4, j, e]
                    + m[a, 1, e] * p[5, j, e]
                    + m[a, 2, e] * p[6, j, e]
                    + m[a, 3, e] * p[7, j, e]
                )
                r[a, j, e] = cq - mb
    for a in range(4):
        for b in range(a, 4):
            for e in range(w.size[0]):
                v = (r[a, 0, e] * c[b, 0, e] + r[a, 1, e] * c[b, 1, e] + r[a, 2, e] * c[b, 2, e]
                     + r[a, 3, e] * c[b, 3, e]) - (r[a, 4, e] * m[b, 0, e] + r[a, 5, e] * m[b, 1, e]
                                                   + r[a, 6, e] * m[b, 2, e] + r[a, 7, e] * m[b, 3, e])  # fmt: skip
                v = v if pred[e] else p[a, b, e]
                p[a, b, e] = v
                p[b, a, e] = v
    for a in range(4):
        for j in range(4, _N):
            for e in range(w.size[0]):
                v = r[a, j, e] if pred[e] else p[a, j, e]
                p[a, j, e] = v
                p[j, a, e] = v


@njit(cache=True, error_model="numpy", inline="always")
def _kalman_update(w, c2, n2):
    """``qsf._kalman_update`` on every lane with ``_UPD``: H's nonzero columns are q's and ``n2`` from ``c2``
    (only q's where ``_HCL`` is 0), R = ``f[_RD]``·I, the gain ``f[_GAIN]``; writes ``s_inv`` and
    ``f[_CORR]``. The state's clone entries change only where ``_CL``."""
    _hp(w, c2, n2)
    _gain(w, c2, n2)
    _joseph(w)


@njit(cache=True, error_model="numpy")
def _hp(w, c2, n2):
    """H P of ``qsf._kalman_update`` (each entry summed over H's nonzero columns in order, from 0.0): q's four,
    then ``n2`` (3 or 4) from ``c2`` on the lanes with ``_HCL``."""
    p, h, hp, hcl = w.p, w.h, w.hp, w.on[_HCL]
    for mm in range(3):
        for j in range(_N):
            for e in range(w.size[0]):
                v = 0.0
                v += h[mm, 0, e] * p[0, j, e]
                v += h[mm, 1, e] * p[1, j, e]
                v += h[mm, 2, e] * p[2, j, e]
                v += h[mm, 3, e] * p[3, j, e]
                u = v
                u += h[mm, c2, e] * p[c2, j, e]
                u += h[mm, c2 + 1, e] * p[c2 + 1, j, e]
                u += h[mm, c2 + 2, e] * p[c2 + 2, j, e]
                if n2 == 4:
                    u += h[mm, c2 + 3, e] * p[c2 + 3, j, e]
                hp[mm, j, e] = u if hcl[e] else v


@njit(cache=True, inline="always")
def _add_hph(hp, h, e, c0, n, s):
    """The 6-tuple ``s`` (S's triangle: 00 01 02 11 12 22) plus the terms ``(H P)[a, col] H[b, col]`` of lane e's
    ``n`` columns from ``c0``, added column by column as ``qsf._kalman_update`` sums them."""
    s00, s01, s02, s11, s12, s22 = s
    for t in range(n):
        col = c0 + t
        s00 += hp[0, col, e] * h[0, col, e]
        s01 += hp[0, col, e] * h[1, col, e]
        s02 += hp[0, col, e] * h[2, col, e]
        s11 += hp[1, col, e] * h[1, col, e]
        s12 += hp[1, col, e] * h[2, col, e]
        s22 += hp[2, col, e] * h[2, col, e]
    return s00, s01, s02, s11, s12, s22


@njit(cache=True, error_model="numpy")
def _gain(w, c2, n2):
    """S, S⁻¹, the gain, the state."""
    h, hp, kt, x, on, f = w.h, w.hp, w.kt, w.x, w.on, w.f
    upd, hcl, cl = on[_UPD], on[_HCL], on[_CL]
    for e in range(w.size[0]):
        s = _add_hph(hp, h, e, 0, 4, (0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
        u = _add_hph(hp, h, e, c2, n2, s)
        s00, s01, s02, s11, s12, s22 = u if hcl[e] else s
        rd = f[_RD, e]
        a0, a1, a2, a3, a4, a5, a6, a7, a8 = s00 + rd, s01, s02, s01, s11 + rd, s12, s02, s12, s22 + rd
        inv = inv3((a0, a1, a2, a3, a4, a5, a6, a7, a8))
        for k in range(9):
            w.s_inv[k, e] = inv[k]
        # the Joseph form's G = K S − C needs S: the six entries of its triangle in r[3] (G's rows are r[0:3])
        w.r[3, 0, e], w.r[3, 1, e], w.r[3, 2, e] = a0, a1, a2
        w.r[3, 3, e], w.r[3, 4, e], w.r[3, 5, e] = a4, a5, a8
    si = w.s_inv
    for j in range(_N):
        for e in range(w.size[0]):
            g = f[_GAIN, e]
            h0, h1, h2 = hp[0, j, e], hp[1, j, e], hp[2, j, e]
            kt[0, j, e] = g * (h0 * si[0, e] + h1 * si[3, e] + h2 * si[6, e])
            kt[1, j, e] = g * (h0 * si[1, e] + h1 * si[4, e] + h2 * si[7, e])
            kt[2, j, e] = g * (h0 * si[2, e] + h1 * si[5, e] + h2 * si[8, e])
    nu = w.nu
    for e in range(w.size[0]):
        f[_CORR, e] = 0.0
    for j in range(_N):
        for e in range(w.size[0]):
            before = x[j, e]
            after = before + (kt[0, j, e] * nu[0, e] + kt[1, j, e] * nu[1, e] + kt[2, j, e] * nu[2, e])
            keep = (upd[e] != 0) & ((j < _C0) | (cl[e] != 0))
            x[j, e] = after if keep else before
            if j < 4:
                f[_CORR, e] += (after - before) ** 2
    for e in range(w.size[0]):
        f[_CORR, e] = np.sqrt(f[_CORR, e])


@njit(cache=True, error_model="numpy")
def _joseph(w):
    """``linalg.joseph_update`` on every lane with ``_UPD``, S from ``r[3]`` (s00 s01 s02 s11 s12 s22)."""
    p, hp, kt, g, upd = w.p, w.hp, w.kt, w.r, w.on[_UPD]
    s = g[3]
    for i in range(_N):
        for e in range(w.size[0]):
            k0, k1, k2 = kt[0, i, e], kt[1, i, e], kt[2, i, e]
            s0, s1, s2, s4, s5, s8 = s[0, e], s[1, e], s[2, e], s[3, e], s[4, e], s[5, e]
            g[0, i, e] = (k0 * s0 + k1 * s1 + k2 * s2) - hp[0, i, e]
            g[1, i, e] = (k0 * s1 + k1 * s4 + k2 * s5) - hp[1, i, e]
            g[2, i, e] = (k0 * s2 + k1 * s5 + k2 * s8) - hp[2, i, e]
    for i in range(_N):
        for e in range(w.size[0]):  # the diagonal entry apart: its store and its mirror's are one
            p[i, i, e] = _joseph_entry(p, hp, kt, g, upd, i, i, e)
        for j in range(i + 1, _N):  # the upper triangle is read, the lower written (its mirror)
            for e in range(w.size[0]):
                v = _joseph_entry(p, hp, kt, g, upd, i, j, e)
                p[i, j, e] = v
                p[j, i, e] = v


@njit(cache=True, inline="always")
def _joseph_entry(p, hp, kt, g, upd, i, j, e):
    """Entry (i, j) of lane e after ``linalg.joseph_update`` (where ``upd[e]``), i ≤ j."""
    old = p[i, j, e]
    new = (
        old
        - (kt[0, i, e] * hp[0, j, e] + kt[1, i, e] * hp[1, j, e] + kt[2, i, e] * hp[2, j, e])
        + (g[0, i, e] * kt[0, j, e] + g[1, i, e] * kt[1, j, e] + g[2, i, e] * kt[2, j, e])
    )
    return new if upd[e] else old


@njit(cache=True, error_model="numpy", inline="always")
def _renormalise(w, mask, off):
    """``qsf._renormalise``'s step for the quaternion at row ``off`` on the lanes with ``mask``: normalise it,
    project the covariance (``linalg.project_quaternion``, 15 states)."""
    x, p, eps = w.x, w.p, w.f[_EPS]
    for e in range(w.size[0]):
        qn = np.sqrt(x[off, e] ** 2 + x[off + 1, e] ** 2 + x[off + 2, e] ** 2 + x[off + 3, e] ** 2)
        for i in range(4):
            v = x[off + i, e] / qn
            x[off + i, e] = v if mask[e] else x[off + i, e]
    for j in range(_N):
        for e in range(w.size[0]):
            q0, q1, q2, q3 = x[off, e], x[off + 1, e], x[off + 2, e], x[off + 3, e]
            d = q0 * p[off, j, e] + q1 * p[off + 1, j, e] + q2 * p[off + 2, j, e] + q3 * p[off + 3, j, e]
            m = mask[e]
            p[off, j, e] = p[off, j, e] - q0 * d if m else p[off, j, e]
            p[off + 1, j, e] = p[off + 1, j, e] - q1 * d if m else p[off + 1, j, e]
            p[off + 2, j, e] = p[off + 2, j, e] - q2 * d if m else p[off + 2, j, e]
            p[off + 3, j, e] = p[off + 3, j, e] - q3 * d if m else p[off + 3, j, e]
    for i in range(_N):
        for e in range(w.size[0]):
            q0, q1, q2, q3 = x[off, e], x[off + 1, e], x[off + 2, e], x[off + 3, e]
            d = q0 * p[i, off, e] + q1 * p[i, off + 1, e] + q2 * p[i, off + 2, e] + q3 * p[i, off + 3, e]
            m = mask[e]
            p[i, off, e] = p[i, off, e] - q0 * d if m else p[i, off, e]
            p[i, off + 1, e] = p[i, off + 1, e] - q1 * d if m else p[i, off + 1, e]
            p[i, off + 2, e] = p[i, off + 2, e] - q2 * d if m else p[i, off + 2, e]
            p[i, off + 3, e] = p[i, off + 3, e] - q3 * d if m else p[i, off + 3, e]
    for a in range(4):
        for b in range(a, 4):
            for e in range(w.size[0]):
                v = 0.5 * (p[off + a, off + b, e] + p[off + b, off + a, e]) + eps[e] * x[off + a, e] * x[off + b, e]
                v = v if mask[e] else p[off + a, off + b, e]
                p[off + a, off + b, e] = v
                p[off + b, off + a, e] = v


@njit(cache=True, error_model="numpy")
def _renormalise_both(w):
    """``qsf._renormalise`` after an update: q on the lanes with ``_UPD``, the clone where also ``_CL``."""
    on = w.on
    _renormalise(w, on[_UPD], 0)
    both = on[_BOTH]
    for e in range(w.size[0]):
        both[e] = on[_UPD, e] & on[_CL, e]
    _renormalise(w, both, N_STATE)


@njit(cache=True, error_model="numpy")
def _clone(w):
    """Delay MAGYQ's period start on the lanes with ``_START``: the clone's rows and columns of P ← q's
    (Cov(δq_t0) = P_qq, Cov(δx, δq_t0) = P[:, q]), plus the jitter on its diagonal (``qsf.step_work``)."""
    p, st = w.p, w.on[_START]
    for a in range(4):
        for c in range(N_STATE):
            for e in range(w.size[0]):
                if st[e]:
                    p[N_STATE + a, c, e] = p[a, c, e]
                    p[c, N_STATE + a, e] = p[c, a, e]
        for b in range(4):
            for e in range(w.size[0]):
                if st[e]:
                    p[N_STATE + a, N_STATE + b, e] = p[a, b, e]
    for r in range(N_STATE, N_AUGMENTED):
        for e in range(w.size[0]):
            if st[e]:
                p[r, r, e] += CLONE_JITTER


@njit(cache=True, error_model="numpy")
def _healthy(w):
    """``on[_OK]`` ← the Cholesky test of ``kalman_threshold.is_pd`` on each lane's 11 or 15 (``_CL``) rows and
    a finite diagonal there (every lane factors 15 rows; a lane without clone ignores the clone's)."""
    p, lo, ok, cl, s = w.p, w.lo, w.on[_OK], w.on[_CL], w.f[_SUM]
    for e in range(w.size[0]):
        ok[e] = 1
    for j in range(_N):
        _residual(p, lo, s, j, j, w.size[0])
        for e in range(w.size[0]):
            lo[j, j, e] = 1.0 / np.sqrt(s[e])
            d = p[j, j, e]
            good = (s[e] > 0.0) & (d - d == 0.0)
            ok[e] = ok[e] & (good | ((j >= _C0) & (cl[e] == 0)))
        for i in range(j + 1, _N):
            _residual(p, lo, s, i, j, w.size[0])
            for e in range(w.size[0]):
                lo[i, j, e] = s[e] * lo[j, j, e]


@njit(cache=True, inline="always")
def _residual(p, lo, s, i, j, n):
    """``s[e]`` ← p[i, j, e] − Σ_{k<j} lo[i, k, e] lo[j, k, e] on the first ``n`` lanes: a Cholesky entry before
    its scaling (the diagonal's for i = j)."""
    for e in range(n):
        s[e] = p[i, j, e]
    m = np.int64(j)  # the sum's terms, four a pass over the lanes (subtracted in the sum's order), then one
    for k in range(0, m - 3, 4):
        for e in range(n):
            v = s[e] - lo[i, k, e] * lo[j, k, e]
            v = v - lo[i, k + 1, e] * lo[j, k + 1, e]
            v = v - lo[i, k + 2, e] * lo[j, k + 2, e]
            s[e] = v - lo[i, k + 3, e] * lo[j, k + 3, e]
    for k in range(m - m % 4, m):
        for e in range(n):
            s[e] -= lo[i, k, e] * lo[j, k, e]


@njit(cache=True, error_model="numpy")
def _commit(w, commit):
    """``qsf._commit_healthy``'s copy of x on the lanes with ``commit`` (its covariance is p: see :func:`_block`)."""
    x, cx = w.x, w.cx
    for r in range(_N):
        for e in range(w.size[0]):
            cx[r, e] = x[r, e] if commit[e] else cx[r, e]


# ------------------------------------------------------------ a block of envs

# columns of a block's int64 lane table: env, its window (batch.Window: start, stop, base, r0, r1), samples to
# fuse, the window's sample where it failed (−1), its state not finite at the load (1), still fusing (1), the
# samples committed, whether the last had the clone (15 states), failed after its covariance changed (1)
_ENV, _WSTART, _WSTOP, _WBASE, _R0, _R1, _CNT, _BAD, _BADLOAD, _LIVE, _DONE, _CLONED, _DIRTY = range(13)
# rows of a block's per-lane numbers: committed period on, age, m_t0 (3), m_ref (3); the same being updated;
# then the sample's active, keep_clone, acc_used, innovation norm, NIS, |K_q δz|, mag updated, action, trust
_CON, _CAGE, _CT0, _CREF, _ON, _AGE, _T0, _REF = 0, 1, 2, 5, 8, 9, 10, 13
_ACT, _KEEPC, _ACCU, _INNOV, _NIS, _CORRM, _UPDATED, _ACTION, _TRUST = range(16, 25)
_V = 25


@njit(cache=True)
def _load(b, s, w, lane, v, e, i):
    """Lane e ← env i: its window, decision and period state."""
    win = window(s, i)
    lane[e, _ENV], lane[e, _WSTART], lane[e, _WSTOP], lane[e, _WBASE], lane[e, _R0], lane[e, _R1] = (
        i, win.start, win.stop, win.base, win.r0, win.r1,
    )  # fmt: skip
    lane[e, _CNT] = win.stop - win.start
    lane[e, _LIVE] = 1
    fill_decision(qsf.Inputs(s.gyr, s.acc, s.mag, b.action_h[i], b.trust_h[i]), b.code[i], b.trust[i],
                  win.start, win.stop)  # fmt: skip
    on = b.active[i, 0]
    v[_CON, e], v[_CAGE, e] = 1.0 if on else 0.0, b.age[i, 0]
    for k in range(3):
        v[_CT0 + k, e], v[_CREF + k, e] = b.mag_t0[i, k], b.mag_ref[i, k]
    f, pf = w.f, b.pf
    f[_EPS, e], f[_DT, e], f[_SG, e], f[_SBW, e], f[_SABW, e] = pf[i, 7], b.dt[i], pf[i, 0], pf[i, 1], pf[i, 2]
    f[_SACC, e], f[_THACC, e], f[_ADAPT, e] = pf[i, 3], pf[i, 5], pf[i, 9]
    for k in range(3):
        f[_G + k, e] = b.grav[i, k]
    w.on[_CL, e] = 1 if (b.mode == MODE_DELAY and on) else 0


@njit(cache=True, error_model="numpy")
def _load_states(b, w, e0, n):
    """Lanes 0 … n−1 ← envs e0 … : the committed state, and, as ``qsf._load`` at a call's first sample, the
    working copy (P symmetrised); ``on[_OK]`` ← 0 where x or the env's leading 11 or 15 (``_CL``) rows and
    columns of P are not finite."""
    x, p, cx, ok, cl = w.x, w.p, w.cx, w.on[_OK], w.on[_CL]
    bx, bc = b.x, b.cov
    for e in range(n):
        ok[e] = 1
    for r in range(_N):
        for e in range(n):
            val = bx[r, e0 + e]
            x[r, e] = val
            cx[r, e] = val
            ok[e] = ok[e] & (val - val == 0.0)
    for r in range(_N):
        for c in range(_N):
            for e in range(n):
                a_, b_ = bc[r, c, e0 + e], bc[c, r, e0 + e]
                p[r, c, e] = 0.5 * (a_ + b_)
                outside = (cl[e] == 0) & ((r >= _C0) | (c >= _C0))
                ok[e] = ok[e] & ((a_ - a_ == 0.0) | outside)


@njit(cache=True, error_model="numpy")
def _store_states(b, w, e0, n):
    """Envs e0 … ← the committed states of lanes 0 … n−1 that committed a sample (``on[_COMMIT]``): x and P,
    its clone block zeroed where the last sample had no clone (``on[_CL]`` 0), as ``qsf._commit_healthy``."""
    bx, bc, cx, p, done, cl = b.x, b.cov, w.cx, w.p, w.on[_COMMIT], w.on[_CL]
    for r in range(_N):
        for e in range(n):
            bx[r, e0 + e] = cx[r, e] if done[e] else bx[r, e0 + e]
    for r in range(_N):
        for c in range(_N):
            for e in range(n):
                v = p[r, c, e] if ((cl[e] != 0) | ((r < _C0) & (c < _C0))) else 0.0
                bc[r, c, e0 + e] = v if done[e] else bc[r, c, e0 + e]


@njit(cache=True)
def _fail(lane, e, sample):
    lane[e, _BAD] = sample
    lane[e, _LIVE] = 0


@njit(cache=True)
def _predict_quaternions(b, s, w, lane, v, t):
    """``qsf.step_work`` to the prediction's covariance, each lane: the input checks, the period's state, the
    prediction of q (eqs. 17–18) and the rows of F it needs."""
    on = w.on
    on[:, :] = 0
    for e in range(w.size[0]):
        if lane[e, _LIVE] == 0 or t >= lane[e, _CNT]:
            continue
        i = lane[e, _ENV]
        iw = lane[e, _WSTART] + t
        row = lane[e, _R0] + iw
        prev = row - 1 if iw > 0 else row
        g = s.gyr  # rows read by index, not as views (a view costs two atomic reference counts)
        gyr_prev, gyr = (g[prev, 0], g[prev, 1], g[prev, 2]), (g[row, 0], g[row, 1], g[row, 2])
        acc, mag = (s.acc[row, 0], s.acc[row, 1], s.acc[row, 2]), (s.mag[row, 0], s.mag[row, 1], s.mag[row, 2])
        trust = b.trust_h[i, iw]
        if not (finite3(gyr_prev) and finite3(gyr) and finite3(acc) and finite3(mag) and np.isfinite(trust)):
            _fail(lane, e, iw)
            continue
        if t == 0 and lane[e, _BADLOAD]:
            _fail(lane, e, iw)
            continue
        on[_GO, e] = 1
        w.f[_A, e], w.f[_A + 1, e], w.f[_A + 2, e] = acc[0], acc[1], acc[2]
        v[_ACTION, e], v[_TRUST, e] = b.action_h[i, iw], trust
        for k in range(8):
            v[_ON + k, e] = v[_CON + k, e]
        active = v[_ON, e] != 0.0 and b.mode != MODE_AEKF
        v[_ACT, e] = 1.0 if active else 0.0
        v[_KEEPC, e] = 1.0 if (b.mode == MODE_DELAY and active and not b.update_reference) else 0.0
        on[_CL, e] = 1 if (b.mode == MODE_DELAY and active) else 0
        if iw > 0:
            dt = b.dt[i]
            q_yg = from_rotvec4(
                (0.5 * (gyr_prev[0] + gyr[0]) * dt, 0.5 * (gyr_prev[1] + gyr[1]) * dt,
                 0.5 * (gyr_prev[2] + gyr[2]) * dt)
            )  # fmt: skip
            for k in range(4):
                w.f[_QY + k, e] = q_yg[k]
            on[_PRED, e] = 1
    _predict_q(w)


@njit(cache=True, error_model="numpy")
def _predict_q(w):
    """The prediction of q (eq. 18) from ``f[_QY]`` on the lanes with ``_PRED``: ``q ← q ⊗ normalise(q_yg − b_q)``,
    and the rows of C(q̂_ω) and M(q) that ``_predict_cov`` needs."""
    x, f, pred = w.x, w.f, w.on[_PRED]
    for e in range(w.size[0]):
        q = (x[0, e], x[1, e], x[2, e], x[3, e])
        qy = (f[_QY, e], f[_QY + 1, e], f[_QY + 2, e], f[_QY + 3, e])
        q_w = normalize4((qy[0] - x[4, e], qy[1] - x[5, e], qy[2] - x[6, e], qy[3] - x[7, e]))
        qn = mul4(q, q_w)
        for k in range(4):
            x[k, e] = qn[k] if pred[e] else q[k]
        c, m = right_matrix4(q_w), left_matrix4(q)
        for a in range(4):
            for k in range(4):
                w.cm[a, k, e], w.mm[a, k, e] = c[a][k], m[a][k]


@njit(cache=True, error_model="numpy")
def _acc_setup(w, v):
    """``qsf.step_work`` from the prediction's noise to the accelerometer update's H, innovation and R, on every
    lane (the noise where ``_PRED``, the update where ``_GO`` and the gate passes)."""
    x, p, on, f, h, nu = w.x, w.p, w.on, w.f, w.h, w.nu
    for e in range(w.size[0]):
        pred = on[_PRED, e] != 0
        dt = f[_DT, e]
        qg = (0.5 * f[_SG, e] * dt) ** 2
        qb = (0.5 * dt * f[_SBW, e]) ** 2 * dt
        qa = f[_SABW, e] ** 2 * dt
        for r in range(4):
            p[r, r, e] = p[r, r, e] + qg if pred else p[r, r, e]
            p[4 + r, 4 + r, e] = p[4 + r, 4 + r, e] + qb if pred else p[4 + r, 4 + r, e]
        for r in range(3):
            p[8 + r, 8 + r, e] = p[8 + r, 8 + r, e] + qa if pred else p[8 + r, 8 + r, e]
        v[_AGE, e] = v[_AGE, e] + dt if (pred & (v[_ACT, e] != 0.0)) else v[_AGE, e]
        g0, g1, g2 = f[_G, e], f[_G + 1, e], f[_G + 2, e]
        a0, a1, a2 = f[_A, e], f[_A + 1, e], f[_A + 2, e]
        g_norm = np.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        na_ = np.sqrt(a0**2 + a1**2 + a2**2)
        used = (abs(na_ - g_norm) < f[_THACC, e]) & (on[_GO, e] != 0)
        v[_ACCU, e] = 1.0 if used else 0.0
        q = (x[0, e], x[1, e], x[2, e], x[3, e])
        vv = (a0 - x[8, e], a1 - x[9, e], a2 - x[10, e])
        j = jacobian34(q, vv, 1.0)
        for r in range(3):
            for c in range(4):
                h[r, c, e] = j[4 * r + c]
        for c in range(3):  # ∂/∂b_a of q ⊗ (y_a − b_a) ⊗ q̄ = −R(q), column c = −R e_c
            u = rotate3(q, (1.0 if c == 0 else 0.0, 1.0 if c == 1 else 0.0, 1.0 if c == 2 else 0.0))
            h[0, 8 + c, e], h[1, 8 + c, e], h[2, 8 + c, e] = -u[0], -u[1], -u[2]
        dev = f[_ADAPT, e] * (na_ - g_norm)
        a_e = rotate3(q, vv)
        nu[0, e], nu[1, e], nu[2, e] = g0 - a_e[0], g1 - a_e[1], g2 - a_e[2]
        f[_RD, e] = f[_SACC, e] ** 2 + dev * dev
        f[_GAIN, e] = 1.0
        on[_UPD, e] = 1 if used else 0
        on[_HCL, e] = 1


@njit(cache=True)
def _mag_setup(b, s, w, lane, v, t):
    """``qsf.step_work``'s magnetic decision: the reference after the accelerometer update, a period started,
    kept or ended (Delay MAGYQ's clone of x; its covariance by :func:`_clone`), the innovation and, where an
    update runs, its H and R."""
    x, on, f = w.x, w.on, w.f
    mode = b.mode
    for e in range(w.size[0]):
        on[_UPD, e], on[_HCL, e], on[_START, e] = 0, 0, 0
        if not on[_GO, e]:
            continue
        i = lane[e, _ENV]
        active = v[_ACT, e] != 0.0
        m_t0 = (v[_T0, e], v[_T0 + 1, e], v[_T0 + 2, e])
        if v[_ACCU, e] != 0.0 and active and mode == MODE_DELAY and b.update_reference:
            v[_REF, e], v[_REF + 1, e], v[_REF + 2, e] = rotate3((x[11, e], x[12, e], x[13, e], x[14, e]), m_t0)
        row = lane[e, _R0] + lane[e, _WSTART] + t
        mag = (s.mag[row, 0], s.mag[row, 1], s.mag[row, 2])
        action, trust = v[_ACTION, e], v[_TRUST, e]
        sm2 = b.pf[i, 4] ** 2
        v[_INNOV, e] = v[_NIS, e] = v[_CORRM, e] = v[_UPDATED, e] = 0.0
        if mode == MODE_AEKF:
            z = (b.earth[i, 0], b.earth[i, 1], b.earth[i, 2])
            do = trust > 0.0
            r_diag = sm2
        else:
            if action == MAG_START or (action == MAG_KEEP and active and v[_AGE, e] > b.pf[i, 8]):
                v[_ON, e], v[_AGE, e] = 1.0, 0.0
                m_t0 = (mag[0], mag[1], mag[2])
                v[_T0, e], v[_T0 + 1, e], v[_T0 + 2, e] = m_t0
                v[_REF, e], v[_REF + 1, e], v[_REF + 2, e] = rotate3((x[0, e], x[1, e], x[2, e], x[3, e]), mag)
                if mode == MODE_DELAY:
                    on[_CL, e] = 1
                    on[_START, e] = 1
                    for a in range(4):
                        x[N_STATE + a, e] = x[a, e]
                active = True
                do = False
            elif action == MAG_KEEP and active:
                do = trust > 0.0
            else:
                if active:
                    v[_ON, e], v[_AGE, e] = 0.0, 0.0
                    active = False
                    on[_CL, e] = 0
                do = False
            z = (v[_REF, e], v[_REF + 1, e], v[_REF + 2, e])
            r_diag = 2.0 * sm2 if mode == MODE_DELAY else sm2
        v[_ACT, e] = 1.0 if active else 0.0
        if mode == MODE_AEKF or active:
            q = (x[0, e], x[1, e], x[2, e], x[3, e])
            m_e = rotate3(q, mag)
            nu = (z[0] - m_e[0], z[1] - m_e[1], z[2] - m_e[2])
            v[_INNOV, e] = np.sqrt(nu[0] * nu[0] + nu[1] * nu[1] + nu[2] * nu[2])
            if do:
                j = jacobian34(q, mag, 1.0)
                for r in range(3):
                    for c in range(4):
                        w.h[r, c, e] = j[4 * r + c]
                if on[_CL, e]:
                    j = jacobian34((x[11, e], x[12, e], x[13, e], x[14, e]), m_t0, -1.0)
                    for r in range(3):
                        for c in range(4):
                            w.h[r, N_STATE + c, e] = j[4 * r + c]
                    on[_HCL, e] = 1
                w.nu[0, e], w.nu[1, e], w.nu[2, e] = nu
                f[_RD, e], f[_GAIN, e] = r_diag, trust
                on[_UPD, e] = 1


@njit(cache=True)
def _mag_after(b, w, v):
    """``qsf.step_work`` after the magnetic update: NIS, the reference from the corrected clone, eq. 24's
    literal clone."""
    x, on = w.x, w.on
    for e in range(w.size[0]):
        if not on[_GO, e]:
            continue
        if on[_UPD, e]:
            si = w.s_inv
            s_inv = (si[0, e], si[1, e], si[2, e], si[3, e], si[4, e], si[5, e], si[6, e], si[7, e], si[8, e])
            v[_NIS, e] = quad3((w.nu[0, e], w.nu[1, e], w.nu[2, e]), s_inv)
            v[_CORRM, e] = w.f[_CORR, e]
            if on[_CL, e] and b.update_reference:
                m_t0 = (v[_T0, e], v[_T0 + 1, e], v[_T0 + 2, e])
                v[_REF, e], v[_REF + 1, e], v[_REF + 2, e] = rotate3((x[11, e], x[12, e], x[13, e], x[14, e]), m_t0)
            v[_UPDATED, e] = 1.0
        if v[_KEEPC, e] != 0.0 and v[_ACT, e] != 0.0 and on[_CL, e] and v[_AGE, e] > 0.0:
            for a in range(4):
                x[N_STATE + a, e] = w.cx[N_STATE + a, e]


@njit(cache=True)
def _repair(b, w, lane, t):
    """``qsf._commit_healthy``'s decision, each lane: the lanes failing the vector test are repaired by
    ``kalman_threshold.repair_sym`` on a copy; ``_COMMIT`` where the state is committed (else the lane fails)."""
    on, p = w.on, w.p
    pm = np.empty((N_AUGMENTED, N_AUGMENTED))
    lo = np.empty((N_AUGMENTED, N_AUGMENTED))
    for e in range(w.size[0]):
        on[_COMMIT, e] = 0
        if not on[_GO, e]:
            continue
        na = N_AUGMENTED if on[_CL, e] else N_STATE
        if not on[_OK, e]:
            for r in range(na):
                for c in range(na):
                    pm[r, c] = p[r, c, e]
            if repair_sym(pm, na, b.pf[lane[e, _ENV], 6], lo) < 0:
                _fail(lane, e, lane[e, _WSTART] + t)
                lane[e, _DIRTY] = 1
                on[_GO, e] = 0
                continue
            for r in range(na):
                for c in range(na):
                    p[r, c, e] = pm[r, c]
        good = True
        for r in range(na):
            good = good and np.isfinite(w.x[r, e])
        on[_COMMIT, e] = 1 if good else 0


@njit(cache=True)
def _signals(b, w, lane, v, t):
    """``qsf.step_work``'s end and ``qsf.run_kernel``'s output row, each committed lane: the period's state,
    the estimate and the signals."""
    on, cx, cp = w.on, w.cx, w.p  # p: the committed covariance
    mode = b.mode
    for e in range(w.size[0]):
        if not on[_GO, e]:
            continue
        iw = lane[e, _WSTART] + t
        if not on[_COMMIT, e]:
            _fail(lane, e, iw)
            lane[e, _DIRTY] = 1
            continue
        lane[e, _DONE] += 1
        lane[e, _CLONED] = on[_CL, e]
        i = lane[e, _ENV]
        for k in range(8):
            v[_CON + k, e] = v[_ON + k, e]
        q = (cx[0, e], cx[1, e], cx[2, e], cx[3, e])
        b.q_h[i, iw, 0], b.q_h[i, iw, 1], b.q_h[i, iw, 2], b.q_h[i, iw, 3] = q
        hr = heading_row4(q)
        var = 0.0
        for a in range(4):
            var += hr[a] * (cp[a, 0, e] * hr[0] + cp[a, 1, e] * hr[1] + cp[a, 2, e] * hr[2] + cp[a, 3, e] * hr[3])
        active = v[_ACT, e] != 0.0
        updated = v[_UPDATED, e] != 0.0
        sig = b.sig_h
        sig[i, iw, SIGNAL.qsf_active] = 1.0 if (active and mode != MODE_AEKF) else 0.0
        sig[i, iw, SIGNAL.innov_norm] = v[_INNOV, e]
        sig[i, iw, SIGNAL.nis] = v[_NIS, e]
        sig[i, iw, SIGNAL.corr_norm] = v[_CORRM, e]
        sig[i, iw, SIGNAL.age] = v[_AGE, e] if active else 0.0
        sig[i, iw, SIGNAL.trust] = v[_TRUST, e] if updated else 0.0
        sig[i, iw, SIGNAL.heading_std] = np.sqrt(max(0.0, var))
        sig[i, iw, SIGNAL.acc_used] = v[_ACCU, e]
        sig[i, iw, SIGNAL.mag_updated] = 1.0 if updated else 0.0


@njit(cache=True)
def _sample(b, s, w, lane, v, t):
    """Sample t of every lane's step (``qsf.step_work``)."""
    _predict_quaternions(b, s, w, lane, v, t)
    _predict_cov(w)
    _acc_setup(w, v)
    _kalman_update(w, uint64(8), uint64(3))
    _renormalise_both(w)
    _mag_setup(b, s, w, lane, v, t)
    _clone(w)
    _kalman_update(w, uint64(N_STATE), uint64(4))
    _renormalise_both(w)
    _mag_after(b, w, v)
    _healthy(w)
    _repair(b, w, lane, t)
    _commit(w, w.on[_COMMIT])
    _signals(b, w, lane, v, t)


@njit(cache=True)
def _fuse(b, s, w, lane, v, e0, n, cap):
    """Lanes 0 … n−1 ← envs e0 …, then their ``todo`` samples in lock-step, lane e's stopping before its step's
    sample ``cap[e]``."""
    most = 0
    for e in range(n):
        w.on[_CL, e] = 0
        lane[e, _BAD] = -1
        lane[e, _DONE] = lane[e, _CLONED] = lane[e, _DIRTY] = 0
        if s.todo[e0 + e] >= 0:
            _load(b, s, w, lane, v, e, e0 + e)
            lane[e, _CNT] = min(lane[e, _CNT], cap[e])
            most = max(most, lane[e, _CNT])
    _load_states(b, w, uint64(e0), uint64(n))
    for e in range(n):
        lane[e, _BADLOAD] = 1 - w.on[_OK, e]
    for t in range(most):
        _sample(b, s, w, lane, v, t)


@njit(cache=True)
def _block(b, s, e0, e1, w):
    """Envs ``e0 … e1−1`` (at most ``w``'s lanes) of :class:`magenv.envs.qsf.Batch` ``b`` (``s``: ``batch.Steps``) do
    their ``todo`` in lock-step, each as :func:`magenv.envs.qsf.advance` does it.

    A lane's committed covariance is its working one (no copy per sample): a lane that fails after its
    covariance changed (a failed repair, a non-finite state) makes the block fuse again from the envs' states,
    that lane stopping before the failed sample, so that it keeps the state it had there."""
    width = w.x.shape[1]
    lane = np.zeros((width, 13), np.int64)
    v = np.zeros((_V, width))
    n = e1 - e0
    w.size[0] = n
    cap = np.full(width, np.iinfo(np.int64).max)
    _fuse(b, s, w, lane, v, e0, n, cap)
    again = False
    for e in range(n):
        if lane[e, _DIRTY]:
            cap[e], again = lane[e, _BAD] - lane[e, _WSTART], True
    if again:  # rare: the vector env raises FilterError on any failure
        bad = lane[:, _BAD].copy()
        _fuse(b, s, w, lane, v, e0, n, cap)
        lane[:, _BAD] = bad
    for e in range(n):
        w.on[_COMMIT, e], w.on[_CL, e] = lane[e, _DONE] > 0, lane[e, _CLONED]
    _store_states(b, w, uint64(e0), uint64(n))
    # env i's state for feature_row (which reads no P), in arrays of this block: no views of the batch's rows
    st = qsf.State(
        np.empty(N_AUGMENTED), np.empty((1, 1)), np.empty(1, np.bool_), np.empty(1), np.empty(3), np.empty(3)
    )
    rows = b.sig_h.shape[1]  # env i's window sample iw: row i·rows + iw of sig and est
    sig = b.sig_h.reshape((b.sig_h.shape[0] * rows, b.sig_h.shape[2]))
    est = b.q_h.reshape((b.q_h.shape[0] * rows, 4))
    err = np.empty(N_ERR)
    for e in range(n):
        i = e0 + e
        if s.todo[i] < 0:
            continue
        st.period_active[0], st.period_age[0] = v[_CON, e] != 0.0, v[_CAGE, e]
        b.active[i, 0], b.age[i, 0] = st.period_active[0], st.period_age[0]
        for k in range(3):
            st.mag_t0[k], st.mag_ref[k] = v[_CT0 + k, e], v[_CREF + k, e]
            b.mag_t0[i, k], b.mag_ref[i, k] = st.mag_t0[k], st.mag_ref[k]
        start, stop, base, r0, r1 = lane[e, _WSTART], lane[e, _WSTOP], lane[e, _WBASE], lane[e, _R0], lane[e, _R1]
        if lane[e, _BAD] >= 0:
            s.failed[i] = base + lane[e, _BAD]
            continue
        s.pos[i] = base + stop
        error_sums(est, s.q_true, s.dist, start, stop, err, i * rows, r0)
        for k in range(N_ERR):
            s.err[i, k] = err[k]
        for r in range(N_AUGMENTED):
            st.x[r] = w.cx[r, e]
        last = i * rows + stop - 1 if stop > 0 else -1
        feature_row(b.pf[i, 4], st, s.gyr, s.acc, s.mag, b.codes, b.spread, r0 + observed(stop, r1 - r0), sig, last,
                    (b.m0[i], b.dip0[i]), b.trust[i], s.feat, i)  # fmt: skip


@njit(cache=True, inline="always")
def params(b, i):
    """``qsf.Params`` of env i of :class:`magenv.envs.qsf.Batch` ``b``."""
    f, g, e = b.pf, b.grav, b.earth  # read by index: no views
    return qsf.Params(
        b.mode, f[i, 0], f[i, 1], f[i, 2], f[i, 3], f[i, 4], f[i, 5], (g[i, 0], g[i, 1], g[i, 2]),
        (e[i, 0], e[i, 1], e[i, 2]), f[i, 6], f[i, 7], b.update_reference, f[i, 8], f[i, 9],
    )  # fmt: skip


@njit(cache=True)
def _env_by_env(b, s, e0, e1):
    """Envs ``e0 … e1−1`` as :func:`_block`, one after the other through the single env's kernel
    (:func:`magenv.envs.qsf.advance`), on copies of their states (the batch's have the env axis last)."""
    na = N_AUGMENTED
    st = qsf.State(np.empty(na), np.empty((na, na)), np.empty(1, np.bool_), np.empty(1), np.empty(3), np.empty(3))
    for i in range(e0, e1):
        if s.todo[i] < 0:
            continue
        for r in range(na):
            st.x[r] = b.x[r, i]
            for c in range(na):
                st.cov[r, c] = b.cov[r, c, i]
        st.period_active[0], st.period_age[0] = b.active[i, 0], b.age[i, 0]
        for k in range(3):
            st.mag_t0[k], st.mag_ref[k] = b.mag_t0[i, k], b.mag_ref[i, k]
        w = window(s, i)
        r0, r1 = w.r0, w.r1
        bad, _ = advance(
            params(b, i), st, qsf.Inputs(s.gyr[r0:r1], s.acc[r0:r1], s.mag[r0:r1], b.action_h[i], b.trust_h[i]),
            qsf.Outputs(b.q_h[i], b.sig_h[i]), (b.codes[r0:r1], b.spread[r0:r1]), Truth(s.q_true[r0:r1], s.dist[r0:r1]),
            b.dt[i], (b.m0[i], b.dip0[i]), b.code[i], b.trust[i], w.start, w.stop, s.err[i], s.feat[i],
        )  # fmt: skip
        for r in range(na):  # as committed (up to the failed sample, if any)
            b.x[r, i] = st.x[r]
            for c in range(na):
                b.cov[r, c, i] = st.cov[r, c]
        b.active[i, 0], b.age[i, 0] = st.period_active[0], st.period_age[0]
        for k in range(3):
            b.mag_t0[i, k], b.mag_ref[i, k] = st.mag_t0[k], st.mag_ref[k]
        if bad < 0:
            s.pos[i] = w.base + w.stop
        else:
            s.failed[i] = w.base + bad


@njit(cache=True)
def _blocks(b, s, e0, e1, w):
    """Envs ``e0 … e1−1`` (at most LANES) in lock-step (``w``: lanes for them), or one by one when fewer than
    NARROW."""
    if e1 - e0 < NARROW:
        _env_by_env(b, s, e0, e1)
    else:
        _block(b, s, e0, e1, w)


@njit(cache=True)
def lockstep(b, s):
    """Every env of ``b`` (:class:`magenv.envs.qsf.Batch`; ``s``: ``magenv.envs.batch.Steps``) with ``todo ≥ 0``
    does it, LANES envs at a time (``magenv.envs.batch.each_env``'s contract: ``s.pos`` advanced, or
    ``s.failed`` set to the sample where the env's filter failed)."""
    n = s.todo.shape[0]
    w = lanes(min(LANES, n) if n >= NARROW else 1)
    for e0 in range(0, n, LANES):
        _blocks(b, s, e0, min(e0 + LANES, n), w)


@njit(cache=True, parallel=True)
def lockstep_threads(b, s):
    """:func:`lockstep` with the blocks spread over numba's threads."""
    n = s.todo.shape[0]
    for k in prange((n + LANES - 1) // LANES):
        e0 = k * LANES
        e1 = min(e0 + LANES, n)
        _blocks(b, s, e0, e1, lanes(e1 - e0 if e1 - e0 >= NARROW else 1))
