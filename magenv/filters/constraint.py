"""Constraint-combined adaptive complementary filter (Jung & Lee 2019) and its relatives.

One kernel, :func:`advance`, fuses samples ``start:stop`` of a two-link trial
for link i's orientation q_i (sensor i → ENU), given link j's orientation
q_j (the paper's §3.1: from the reference system). Per sample t, from the
previous estimate q = q_{i,t−1} and sample t's readings:

1. unit vectors in the sensor frame: a = y_A/‖y_A‖, m = y_M/‖y_M‖,
   h = h_i/‖h_i‖ with h_s = y_A + (ω̇̃ + ω̃ω̃) r_s (eq. 9; ω̇ by the backward
   difference of the gyro, causal), and the references in ENU: u = [0, 0, 1]
   (eq. 4, the accelerometer's "up"), n = m_E/‖m_E‖ (eq. 5), and
   p = C(q_j)h_j/‖C(q_j)h_j‖ (from link j, eq. 9);
2. f(q) = [C(q)a, C(q)m, C(q)h], f0 = [u, n, p], ε = f0 − f(q)  (eqs. 6–12);
3. one Gauss–Newton step  Δq = −(JᵀWJ)⁻¹JᵀWε,  J = ∂ε/∂q (4 columns, C(q)
   the quadratic form of eq. 2), W = diag(I, (1 − w)I, wI)       (eqs. 13–15);
4. w by eq. 16 (w = min(‖C(q)y_M − m_E‖/(m0·th1), 1)) or given;
   k by eq. 18 (from w and ‖Δq‖) or given;
5. q_t = normalise(q + ½ q ⊗ [0, ω] Δt + k Δq Δt)                  (eq. 17).

Readings of the paper taken here (ALGORITHMS.md §C):

* eq. 2 as printed has sign typos (C21, C13); C(q) is the standard
  sensor → earth matrix of ``magenv.quaternion.to_matrix``;
* §2.2 names the normalised *left* side of eq. 9 p and the right side p̂,
  yet puts p in f0 and p̂ in f(q_i); since f must depend on q_i, the
  q_i-side (C(q_i)h_i) is in f and the q_j-side in f0;
* eq. 16's ‖ᴵm̂ − ᴵm‖ is in the paper's arbitrary unit (local field = 1):
  ‖C(q)y_M − m_E‖/m0, with q the previous estimate;
* the step is taken at the previous estimate and applied once (eq. 17,
  "without additional iteration"). A singular JᵀWJ (e.g. w = 1 while the
  joint centre does not accelerate, so p ∥ u) is solved with a 1e-12
  relative ridge: the unobservable direction gets no step, a nearly
  unobservable one a large ‖Δq‖ — exactly what eq. 18's "abnormally large"
  branch (k = 0 for ‖Δq‖ ≥ 10) is for.

Special cases: the conventional CF (Bachmann 1999, the paper's comparison) is
w = 0 with a constant k; strapdown integration is k = 0.

Used by the estimators in ``magenv.baselines.constraint`` (whole trials) and by
``magenv/MagConstraint-v0`` (k samples per step) — same kernel.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from magenv.filters.common import TrialRunner
from magenv.metrics import N_ERR, add_errors
from magenv.filters.madgwick import ecompass1
from magenv.quaternion import GRAVITY, earth_field, normalize1, rotate, rotate1
from magenv.trial import Trial

#: The paper's parameters, found by CMA-ES (§3.1).
TH1, TH2, TH3, K_MIN, K_MAX = 0.15, 0.25, 0.2, 0.01, 0.2
#: eq. 18: a step at least this large is "abnormally large" (k = 0).
STEP_ABNORMAL = 10.0
#: Trial.extra keys a two-link trial must carry (``magenv.scenarios.twolink``).
EXTRA_KEYS = ("gyr_j", "acc_j", "q_j")

# Observation features: (name, low, high); see magenv.envs.constraint for meanings and units.
GYRO_SCALE = 2.0 * np.pi  # rad/s
DIP_SCALE_DEG = 90.0
FEATURES: tuple[tuple[str, float, float], ...] = (
    ("mag_dev", 0.0, 10.0),
    ("norm_dev", -1.0, 10.0),
    ("dip_dev", -2.0, 2.0),
    ("con_mismatch", 0.0, 10.0),
    ("joint_acc", 0.0, 10.0),
    ("gyro_norm", 0.0, 10.0),
    ("acc_dev", -1.0, 10.0),
    ("step_mag", 0.0, STEP_ABNORMAL),
    ("step_con", 0.0, STEP_ABNORMAL),
    ("con_heading", -1.0, 1.0),
    ("w_prev", 0.0, 1.0),
    ("k_prev", 0.0, 1.0),
    ("mag_dev_mean", 0.0, 10.0),
)
FEATURE_NAMES: tuple[str, ...] = tuple(f[0] for f in FEATURES)
N_FEATURES = len(FEATURES)
FEATURE_LOW = np.array([f[1] for f in FEATURES], np.float32)
FEATURE_HIGH = np.array([f[2] for f in FEATURES], np.float32)

# params layout
P_DT, P_M0, P_NX, P_NY, P_NZ, P_TH1, P_TH2, P_TH3, P_KMIN, P_KMAX, P_CON = range(11)
N_PARAMS = 11
# aux layout per sample: [mag_dev Au, ‖Δq‖, w, k, con_mismatch m/s²]
A_DEV, A_STEP, A_W, A_K, A_MIS = range(5)
N_AUX = 5
# err vector layout (E_*, N_ERR): magenv.metrics
# mode values for w_const / k_const
FROM_ARRAY = -1.0  # read w[i] / k[i]
BY_RULE = -2.0  # eq. 16 for w, eq. 18 for k (written into the array)


class MissingChannelsError(ValueError):
    """A trial lacks the second sensor's channels the constraint filter needs."""


def require_two_link(trial: Trial) -> None:
    """Raise MissingChannelsError naming what a constraint estimator needs and the trial lacks."""
    missing = [k for k in EXTRA_KEYS if k not in trial.extra]
    if missing:
        raise MissingChannelsError(
            f"trial {trial.name!r} has no second-sensor channel(s) {', '.join(f'extra[{k!r}]' for k in missing)}; "
            f"the constraint filter needs link j's gyroscope (gyr_j, rad/s), accelerometer (acc_j, m/s²) and true "
            f"orientation (q_j) — make two-link trials with magenv.scenarios.make_trial")
    for key, cols in (("gyr_j", 3), ("acc_j", 3), ("q_j", 4)):
        arr = np.asarray(trial.extra[key])
        if arr.shape != (trial.n, cols) or not np.all(np.isfinite(arr)):
            raise MissingChannelsError(f"trial {trial.name!r}: extra[{key!r}] must be finite with shape "
                                       f"({trial.n}, {cols}), got {arr.shape}")


def joint_vectors(gyr: np.ndarray, acc: np.ndarray, r: np.ndarray, rate: float) -> np.ndarray:
    """h_s = y_A + ω̇ × r + ω × (ω × r) (eq. 9), (N, 3) m/s², sensor frame; ω̇ by backward difference (0 at t = 0)."""
    dw = np.zeros_like(gyr)
    dw[1:] = (gyr[1:] - gyr[:-1]) * rate
    r = np.broadcast_to(np.asarray(r, float), gyr.shape)
    return acc + np.cross(dw, r) + np.cross(gyr, np.cross(gyr, r))


# ------------------------------------------------------------------ kernels


@njit(cache=True, inline="always")
def _dfdq(q, v, F, row):
    """Rows ``row:row+3`` of F = ∂(C(q)v)/∂q (3×4), C(q) the quadratic form of eq. 2."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    rv = x * v[0] + y * v[1] + z * v[2]
    cx = y * v[2] - z * v[1]  # r × v
    cy = z * v[0] - x * v[2]
    cz = x * v[1] - y * v[0]
    F[row, 0] = 2.0 * (w * v[0] + cx)
    F[row + 1, 0] = 2.0 * (w * v[1] + cy)
    F[row + 2, 0] = 2.0 * (w * v[2] + cz)
    r = (x, y, z)
    for k in range(3):
        # −2 r_k v + 2 (r·v) e_k + 2 v_k r + 2 w (e_k × v)
        for a in range(3):
            val = -2.0 * r[k] * v[a] + 2.0 * v[k] * r[a]
            if a == k:
                val += 2.0 * rv
            F[row + a, 1 + k] = val
        # e_k × v
        if k == 0:
            F[row + 1, 1] += -2.0 * w * v[2]
            F[row + 2, 1] += 2.0 * w * v[1]
        elif k == 1:
            F[row, 2] += 2.0 * w * v[2]
            F[row + 2, 2] += -2.0 * w * v[0]
        else:
            F[row, 3] += -2.0 * w * v[1]
            F[row + 1, 3] += 2.0 * w * v[0]


@njit(cache=True, inline="always")
def _unit(v):
    n = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if n == 0.0:
        return v * 0.0, 0.0
    return v / n, n


@njit(cache=True)
def gn_step(q, a_s, m_s, h_s, u, nref, p, w, con, F, dq):
    """One Gauss–Newton step (eqs. 10–15) at q; writes Δq into ``dq`` (4,), returns ‖Δq‖.

    a_s, m_s, h_s: unit sensor-frame vectors (accelerometer, magnetometer,
    joint vector h_i); u, nref, p: their unit ENU references. ``w`` weighs
    the constraint against the magnetometer (eq. 15): W = diag(I, (1 − w)I,
    con·w·I); con = 1 is the paper, con = 0 drops the constraint block (the
    ablation ``cf_gated``). F is (9, 4) scratch.
    """
    _dfdq(q, a_s, F, 0)
    _dfdq(q, m_s, F, 3)
    _dfdq(q, h_s, F, 6)
    fa = rotate1(q, a_s)  # C(q)v for a unit q
    fm = rotate1(q, m_s)
    fh = rotate1(q, h_s)
    eps = np.empty(9)
    for a in range(3):
        eps[a] = u[a] - fa[a]
        eps[3 + a] = nref[a] - fm[a]
        eps[6 + a] = p[a] - fh[a]
    wt = np.empty(9)
    for a in range(3):
        wt[a] = 1.0
        wt[3 + a] = 1.0 - w
        wt[6 + a] = con * w
    # J = −F, so −(JᵀWJ)⁻¹JᵀWε = (FᵀWF)⁻¹FᵀWε   (eq. 14)
    A = np.zeros((4, 5))
    for r in range(4):
        for c in range(4):
            s = 0.0
            for e in range(9):
                s += F[e, r] * wt[e] * F[e, c]
            A[r, c] = s
        s = 0.0
        for e in range(9):
            s += F[e, r] * wt[e] * eps[e]
        A[r, 4] = s
    ridge = 1e-12 * (A[0, 0] + A[1, 1] + A[2, 2] + A[3, 3]) + 1e-300
    for r in range(4):
        A[r, r] += ridge
    # Gauss–Jordan with partial pivoting on the augmented 4×5 system
    for c in range(4):
        piv = c
        for r in range(c + 1, 4):
            if abs(A[r, c]) > abs(A[piv, c]):
                piv = r
        if piv != c:
            for k in range(5):
                A[c, k], A[piv, k] = A[piv, k], A[c, k]
        d = A[c, c]
        for k in range(c, 5):
            A[c, k] /= d
        for r in range(4):
            if r != c:
                f = A[r, c]
                if f != 0.0:
                    for k in range(c, 5):
                        A[r, k] -= f * A[c, k]
    nrm = 0.0
    for r in range(4):
        dq[r] = A[r, 4]
        nrm += dq[r] * dq[r]
    return np.sqrt(nrm)


@njit(cache=True, inline="always")
def weight_rule(dev, th1):
    """eq. 16: w = dev/th1 below th1, else 1 (dev = ‖C(q)y_M − m_E‖/m0)."""
    return dev / th1 if dev < th1 else 1.0


@njit(cache=True, inline="always")
def gain_rule(w, step, th2, th3, kmin, kmax):
    """eq. 18: gain k from the constraint weight w and ‖Δq‖."""
    if w < th2:
        return kmax
    if step < th3:
        return kmax - (kmax - kmin) / th3 * step
    if step < STEP_ABNORMAL:
        return kmin
    return 0.0


@njit(cache=True, inline="always")
def _heading_of(v):
    return np.arctan2(v[0], v[1])


@njit(cache=True)
def advance(q, gyr, acc, mag, h_i, c_j, q_true, dist, w_arr, w_const, k_arr, k_const, start, stop, params,
            est, aux, err, feat):
    """Fuse samples ``start:stop`` (eqs. 4–18); q (4,) is updated in place.

    Args:
        q: (4,) estimate q_{i, start−1}, overwritten with q_{i, stop−1}.
        gyr, acc, mag: (N, 3) link i's readings (rad/s, m/s², µT), sensor i frame.
        h_i: (N, 3) joint vectors of link i (eq. 9), sensor i frame, m/s².
        c_j: (N, 3) C(q_j)h_j, ENU, m/s² (link j's side of eq. 9).
        q_true: (N, 4) truth for the error sums (NaN rows allowed); dist: (N,) µT, summed into err.
        w_arr, k_arr: (N,) weight and gain per sample; w_const / k_const ≥ 0 writes
            that constant, FROM_ARRAY reads the array, BY_RULE applies eq. 16 / eq. 18
            and writes the result.
        params: (N_PARAMS,) Δt s, m0 µT, n (unit ENU Earth field), th1, th2, th3, k_min, k_max,
            constraint block on (1) / off (0).
        est: (N, 4) estimates (rows start:stop written); aux: (N, N_AUX) per-sample diagnostics.
        err: (N_ERR,) set to the interval's error sums; feat: (N_FEATURES,) set to sample
            ``stop``'s observation.
    """
    dt = params[P_DT]
    m0 = params[P_M0]
    nref = params[P_NX:P_NZ + 1].copy()
    mref = nref * m0
    u = np.array([0.0, 0.0, 1.0])
    F = np.empty((9, 4))
    dq = np.zeros(4)
    for e in range(N_ERR):
        err[e] = 0.0
    for i in range(start, stop):
        a_s, _ = _unit(acc[i])
        m_s, _ = _unit(mag[i])
        h_s, hn = _unit(h_i[i])
        p, pn = _unit(c_j[i])
        mE = rotate1(q, mag[i])
        dev = np.sqrt((mE[0] - mref[0]) ** 2 + (mE[1] - mref[1]) ** 2 + (mE[2] - mref[2]) ** 2) / m0
        if w_const >= 0.0:
            w_arr[i] = w_const
        elif w_const == BY_RULE:
            w_arr[i] = weight_rule(dev, params[P_TH1])  # eq. 16
        w = w_arr[i]
        con = params[P_CON] if (hn > 0.0 and pn > 0.0) else 0.0  # no direction in free fall: drop the block
        step = 0.0
        if k_const != 0.0:
            step = gn_step(q, a_s, m_s, h_s, u, nref, p, w, con, F, dq)  # eq. 14
        if k_const >= 0.0:
            k_arr[i] = k_const
        elif k_const == BY_RULE:
            k_arr[i] = gain_rule(w, step, params[P_TH2], params[P_TH3], params[P_KMIN], params[P_KMAX])  # eq. 18
        k = k_arr[i]
        if not np.isfinite(step):
            k = 0.0
            dq[:] = 0.0
        ch = rotate1(q, h_i[i])
        aux[i, A_DEV] = dev
        aux[i, A_STEP] = step
        aux[i, A_W] = w
        aux[i, A_K] = k
        aux[i, A_MIS] = np.sqrt((ch[0] - c_j[i, 0]) ** 2 + (ch[1] - c_j[i, 1]) ** 2 + (ch[2] - c_j[i, 2]) ** 2)
        # eq. 17 (eq. 3 for q̇), then normalise
        gx, gy, gz = gyr[i, 0], gyr[i, 1], gyr[i, 2]
        w0, x0, y0, z0 = q[0], q[1], q[2], q[3]
        hd = 0.5 * dt
        nw = w0 + hd * (-x0 * gx - y0 * gy - z0 * gz) + k * dq[0] * dt
        nx = x0 + hd * (w0 * gx + y0 * gz - z0 * gy) + k * dq[1] * dt
        ny = y0 + hd * (w0 * gy - x0 * gz + z0 * gx) + k * dq[2] * dt
        nz = z0 + hd * (w0 * gz + x0 * gy - y0 * gx) + k * dq[3] * dt
        nn = np.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
        q[0], q[1], q[2], q[3] = nw / nn, nx / nn, ny / nn, nz / nn
        est[i, 0], est[i, 1], est[i, 2], est[i, 3] = q[0], q[1], q[2], q[3]
        add_errors(err, q, q_true[i], dist[i])  # against truth, as magenv.metrics
    _features(q, gyr, acc, mag, h_i, c_j, w_arr, k_arr, start, stop, params, aux, feat, F, dq)


@njit(cache=True)
def _features(q, gyr, acc, mag, h_i, c_j, w_arr, k_arr, start, stop, params, aux, feat, F, dq):
    n = gyr.shape[0]
    j = stop if stop < n else n - 1
    m0 = params[P_M0]
    nref = params[P_NX:P_NZ + 1].copy()
    u = np.array([0.0, 0.0, 1.0])
    mE = rotate1(q, mag[j])
    dev = np.sqrt((mE[0] - nref[0] * m0) ** 2 + (mE[1] - nref[1] * m0) ** 2 + (mE[2] - nref[2] * m0) ** 2) / m0
    mn = np.sqrt(mag[j, 0] ** 2 + mag[j, 1] ** 2 + mag[j, 2] ** 2)
    feat[0] = min(dev, 10.0)
    feat[1] = min(max((mn - m0) / m0, -1.0), 10.0)
    dip = np.rad2deg(np.arcsin(min(1.0, max(-1.0, -mE[2] / mn)))) if mn > 0 else 0.0
    dip0 = np.rad2deg(np.arcsin(min(1.0, max(-1.0, -nref[2]))))
    feat[2] = min(max((dip - dip0) / DIP_SCALE_DEG, -2.0), 2.0)
    ch = rotate1(q, h_i[j])
    mis = np.sqrt((ch[0] - c_j[j, 0]) ** 2 + (ch[1] - c_j[j, 1]) ** 2 + (ch[2] - c_j[j, 2]) ** 2)
    feat[3] = min(mis / GRAVITY, 10.0)
    ja = np.sqrt(c_j[j, 0] ** 2 + c_j[j, 1] ** 2 + (c_j[j, 2] - GRAVITY) ** 2)
    feat[4] = min(ja / GRAVITY, 10.0)
    feat[5] = min(np.sqrt(gyr[j, 0] ** 2 + gyr[j, 1] ** 2 + gyr[j, 2] ** 2) / GYRO_SCALE, 10.0)
    an = np.sqrt(acc[j, 0] ** 2 + acc[j, 1] ** 2 + acc[j, 2] ** 2)
    feat[6] = min(max((an - GRAVITY) / GRAVITY, -1.0), 10.0)
    a_s, _ = _unit(acc[j])
    m_s, _ = _unit(mag[j])
    h_s, hn = _unit(h_i[j])
    p, pn = _unit(c_j[j])
    con = params[P_CON] if (hn > 0.0 and pn > 0.0) else 0.0
    s_mag = gn_step(q, a_s, m_s, h_s, u, nref, p, 0.0, con, F, dq)
    s_con = gn_step(q, a_s, m_s, h_s, u, nref, p, 1.0, con, F, dq)
    feat[7] = min(s_mag, STEP_ABNORMAL) if np.isfinite(s_mag) else STEP_ABNORMAL
    feat[8] = min(s_con, STEP_ABNORMAL) if np.isfinite(s_con) else STEP_ABNORMAL
    # heading (about ENU up) of the joint-centre acceleration seen from link i minus from link j
    dh = _heading_of(ch) - _heading_of(c_j[j])
    dh = (dh + np.pi) % (2.0 * np.pi) - np.pi
    feat[9] = dh / np.pi
    feat[10] = w_arr[stop - 1] if stop > 0 else 0.0
    feat[11] = min(max(k_arr[stop - 1], 0.0), 1.0) if stop > 0 else 0.0
    s = dev
    for i in range(start, stop):
        s += aux[i, A_DEV]
    feat[12] = min(s / (stop - start + 1), 10.0)


# ------------------------------------------------------------------ runner


class ConstraintRunner(TrialRunner):
    """One two-link trial's arrays and the filter state; steps it k samples at a time.

    Args:
        trial: a two-link Trial (``extra`` gyr_j, acc_j, q_j; see ``magenv.scenarios.twolink``).
        lever_i, lever_j: r_i, r_j (m, sensor frames); None = ``trial.meta['lever_i_m'/'lever_j_m']``.
        th1, th2, th3, k_min, k_max: eqs. 16 and 18.
        q0: initial orientation; None = e-compass of the first sample (never truth).
        use_constraint: False drops the constraint block from W (ablation: eqs. 16–18 gating only).

    Raises MissingChannelsError if the trial lacks link j's channels or the lever arms.
    """

    def __init__(self, trial: Trial, lever_i=None, lever_j=None, th1: float = TH1, th2: float = TH2,
                 th3: float = TH3, k_min: float = K_MIN, k_max: float = K_MAX, q0=None,
                 use_constraint: bool = True):
        require_two_link(trial)
        levers = []
        for given, key in ((lever_i, "lever_i_m"), (lever_j, "lever_j_m")):
            if given is None:
                if key not in trial.meta:
                    raise MissingChannelsError(f"trial {trial.name!r} has no meta[{key!r}] (sensor → joint centre, m); "
                                               f"pass lever_i / lever_j to the filter")
                given = trial.meta[key]
            r = np.asarray(given, float)
            if r.shape != (3,) or not np.all(np.isfinite(r)):
                raise ValueError(f"lever arm {key} must be 3 finite numbers (m), got {given!r}")
            levers.append(r)
        for name, v in (("th1", th1), ("th3", th3)):
            if not v > 0:
                raise ValueError(f"{name} must be > 0, got {v!r}")
        if not (0 <= th2 <= 1 and 0 <= k_min <= k_max):
            raise ValueError(f"need 0 ≤ th2 ≤ 1 and 0 ≤ k_min ≤ k_max, got th2={th2}, k_min={k_min}, k_max={k_max}")
        self.trial = trial
        n = trial.n
        self.lever_i, self.lever_j = levers
        self.gyr, self.acc, self.mag, self.q_true = trial.gyr, trial.acc, trial.mag, trial.q_true
        q_j = np.ascontiguousarray(trial.extra["q_j"], float)
        self.h_i = joint_vectors(trial.gyr, trial.acc, self.lever_i, trial.rate)
        h_j = joint_vectors(np.asarray(trial.extra["gyr_j"], float), np.asarray(trial.extra["acc_j"], float),
                            self.lever_j, trial.rate)
        self.c_j = np.ascontiguousarray(rotate(q_j, h_j))
        dist = trial.truth.get("mag_disturbance")
        self.has_dist = dist is not None
        self.dist = np.ascontiguousarray(np.linalg.norm(np.asarray(dist, float), axis=-1) if self.has_dist
                                         else np.zeros(n))
        nref = earth_field(trial.field_norm, trial.field_dip) / trial.field_norm
        self.params = np.array([trial.dt, trial.field_norm, *nref, th1, th2, th3, k_min, k_max,
                                1.0 if use_constraint else 0.0], float)
        self.q = (ecompass1(self.acc[0], self.mag[0]) if q0 is None else normalize1(np.asarray(q0, float)).copy())
        self.q0 = self.q.copy()
        self.est = np.full((n, 4), np.nan)
        self.w = np.full(n, np.nan)
        self.k = np.full(n, np.nan)
        self.aux = np.zeros((n, N_AUX))
        self.err = np.zeros(N_ERR)
        self.feat = np.zeros(N_FEATURES)
        self.pos = 0
        self.last_count = 0
        self._advance(0, 0.0, 0.0)  # observation of sample 0

    def _advance(self, stop: int, w_const: float, k_const: float) -> None:
        advance(self.q, self.gyr, self.acc, self.mag, self.h_i, self.c_j, self.q_true, self.dist, self.w, w_const,
                self.k, k_const, self.pos, stop, self.params, self.est, self.aux, self.err, self.feat)

    def advance(self, count: int, w: float = BY_RULE, k: float = BY_RULE) -> int:
        """Fuse the next ``count`` samples (fewer at the end) with weight w ∈ [0, 1] (or BY_RULE: eq. 16)
        and gain k ≥ 0 (or BY_RULE: eq. 18); returns the samples fused."""
        stop = min(self.pos + int(count), self.trial.n)
        self._advance(stop, float(w), float(k))
        self.last_count = stop - self.pos
        self.pos = stop
        return self.last_count

    def run_all(self, w: float = BY_RULE, k: float = BY_RULE) -> np.ndarray:
        """Fuse all remaining samples; returns the estimate (N, 4)."""
        self.advance(self.trial.n - self.pos, w, k)
        return self.est
