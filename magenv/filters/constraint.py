"""Constraint-combined adaptive complementary filter (Jung & Lee 2019): kernels and an offline class.

Link i's orientation q_i (sensor i → ENU) is estimated given link j's
orientation q_j (the paper's §3.1: from the reference system). Per sample t,
from the previous estimate q = q_{i,t−1} and sample t's readings
(:func:`fuse`):

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

Readings of the paper taken here:

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

The kernels work on named structures: :class:`Params` (floats, by value),
:class:`Inputs` (a trial's arrays), the state q (4,) — the filter's only
memory — and :class:`Trace` (per-sample outputs), so that one env, N batched
envs or a whole offline trial (:class:`ConstraintFilter`) run the same
:func:`fuse`. Used by ``magenv.baselines.constraint`` (whole trials) and
``magenv.envs.constraint`` (k samples per step).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from magenv.checks import check_bool, check_number, check_positive, check_vector
from magenv.filters.madgwick import ecompass1
from magenv.quaternion import earth_field, normalize1, rotate, rotate3
from magenv.trial import Trial

#: The paper's parameters, found by CMA-ES (§3.1).
TH1, TH2, TH3, K_MIN, K_MAX = 0.15, 0.25, 0.2, 0.01, 0.2
#: eq. 18: a step at least this large is "abnormally large" (k = 0).
STEP_ABNORMAL = 10.0
#: Trial.extra keys a two-link trial must carry (``magenv.scenarios.twolink``).
EXTRA_KEYS = ("gyr_j", "acc_j", "q_j")
#: ENU "up", the accelerometer's reference direction u (eq. 4).
UP = (0.0, 0.0, 1.0)


class Params(NamedTuple):
    """The filter's parameters (eqs. 5, 15–18), floats passed to the kernels by value."""

    dt: float  # sample period Δt, s
    field_norm: float  # m0, the undisturbed field norm, µT
    field_dir: tuple[float, float, float]  # n = m_E/m0, the unit Earth field in ENU (eq. 5)
    th1: float  # eq. 16: w = dev/th1 below th1 (dev in units of m0), else 1
    th2: float  # eq. 18: k = k_max while w < th2
    th3: float  # eq. 18: k falls from k_max to k_min as ‖Δq‖ grows from 0 to th3
    k_min: float  # eq. 18, 1/s
    k_max: float  # eq. 18, 1/s
    use_constraint: bool  # False drops the constraint block from W (the ablation ``cf_gated``)


class Inputs(NamedTuple):
    """A two-link trial's arrays as the kernels read them: N rows, C-contiguous float64."""

    gyr: np.ndarray  # (N, 3) link i's gyroscope, rad/s, sensor i frame
    acc: np.ndarray  # (N, 3) link i's accelerometer y_A, m/s², sensor i frame
    mag: np.ndarray  # (N, 3) link i's magnetometer y_M, µT, sensor i frame
    joint_i: np.ndarray  # (N, 3) h_i, the joint centre's acceleration seen from link i (eq. 9), m/s², sensor i
    joint_j: np.ndarray  # (N, 3) C(q_j)h_j, the same seen from link j (eq. 9), m/s², ENU


class Trace(NamedTuple):
    """Per-sample outputs of :func:`fuse` (N rows; rows not fused yet: NaN, ``mag_dev`` 0)."""

    est: np.ndarray  # (N, 4) q_i after the sample, sensor i → ENU
    weight: np.ndarray  # (N,) the constraint weight w (eq. 15)
    gain: np.ndarray  # (N,) the scheduled gain k (eqs. 17–18; the step is dropped where ‖Δq‖ is not finite)
    mag_dev: np.ndarray  # (N,) eq. 16's deviation ‖C(q)y_M − m_E‖/m0 with the estimate before the sample

    @classmethod
    def empty(cls, n: int) -> Trace:
        return cls(np.full((n, 4), np.nan), np.full(n, np.nan), np.full(n, np.nan), np.zeros(n))


class Control(NamedTuple):
    """Weight and gain of the samples one :func:`fuse` call fuses: given, or by the paper's rules."""

    weight: float  # w ∈ [0, 1] (ignored if weight_by_rule)
    gain: float  # k ≥ 0, 1/s (ignored if gain_by_rule)
    weight_by_rule: bool  # w by eq. 16
    gain_by_rule: bool  # k by eq. 18

    @classmethod
    def of(cls, weight: float | None = None, gain: float | None = None) -> Control:
        """w and k as given; None = by eq. 16 / eq. 18."""
        return cls(
            0.0 if weight is None else float(weight), 0.0 if gain is None else float(gain), weight is None, gain is None
        )


class Directions(NamedTuple):
    """The three direction pairs of eqs. 6–12: unit vectors in one frame, each a (3,) array or 3-tuple —
    in sensor i (a, m, h) or their references in ENU (u, n, p)."""

    gravity: np.ndarray  # a = y_A/‖y_A‖ ↔ u = UP (eq. 4)
    field: np.ndarray  # m = y_M/‖y_M‖ ↔ n = Params.field_dir (eq. 5)
    joint: np.ndarray  # h = h_i/‖h_i‖ ↔ p = C(q_j)h_j/‖C(q_j)h_j‖ (eq. 9)


class MissingChannelsError(ValueError):
    """A trial lacks the second sensor's channels the constraint filter needs."""


def require_two_link(trial: Trial) -> None:
    """Raise MissingChannelsError naming what a constraint estimator needs and the trial lacks."""
    missing = [k for k in EXTRA_KEYS if k not in trial.extra]
    if missing:
        raise MissingChannelsError(
            f"trial {trial.name!r} has no second-sensor channel(s) {', '.join(f'extra[{k!r}]' for k in missing)}; "
            f"the constraint filter needs link j's gyroscope (gyr_j, rad/s), accelerometer (acc_j, m/s²) and true "
            f"orientation (q_j) — make two-link trials with magenv.scenarios.make_trial"
        )
    for key, cols in (("gyr_j", 3), ("acc_j", 3), ("q_j", 4)):
        arr = np.asarray(trial.extra[key])
        if arr.shape != (trial.n, cols) or not np.all(np.isfinite(arr)):
            raise MissingChannelsError(
                f"trial {trial.name!r}: extra[{key!r}] must be finite with shape ({trial.n}, {cols}), got {arr.shape}"
            )


def joint_vectors(gyr: np.ndarray, acc: np.ndarray, r: np.ndarray, rate: float) -> np.ndarray:
    """h_s = y_A + ω̇ × r + ω × (ω × r) (eq. 9), (N, 3) m/s², sensor frame; ω̇ by backward difference (0 at t = 0)."""
    dw = np.zeros_like(gyr)
    dw[1:] = (gyr[1:] - gyr[:-1]) * rate
    r = np.broadcast_to(np.asarray(r, float), gyr.shape)
    return acc + np.cross(dw, r) + np.cross(gyr, np.cross(gyr, r))


# ------------------------------------------------------------------ kernels


@njit(cache=True, inline="always")
def _dfdq(q, v, jac, row):
    """Rows ``row:row+3`` of jac = ∂(C(q)v)/∂q (3×4), C(q) the quadratic form of eq. 2."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    rv = x * v[0] + y * v[1] + z * v[2]
    cx = y * v[2] - z * v[1]  # r × v
    cy = z * v[0] - x * v[2]
    cz = x * v[1] - y * v[0]
    jac[row, 0] = 2.0 * (w * v[0] + cx)
    jac[row + 1, 0] = 2.0 * (w * v[1] + cy)
    jac[row + 2, 0] = 2.0 * (w * v[2] + cz)
    r = (x, y, z)
    for k in range(3):
        # −2 r_k v + 2 (r·v) e_k + 2 v_k r + 2 w (e_k × v)
        for a in range(3):
            val = -2.0 * r[k] * v[a] + 2.0 * v[k] * r[a]
            if a == k:
                val += 2.0 * rv
            jac[row + a, 1 + k] = val
        # e_k × v
        if k == 0:
            jac[row + 1, 1] += -2.0 * w * v[2]
            jac[row + 2, 1] += 2.0 * w * v[1]
        elif k == 1:
            jac[row, 2] += 2.0 * w * v[2]
            jac[row + 2, 2] += -2.0 * w * v[0]
        else:
            jac[row, 3] += -2.0 * w * v[1]
            jac[row + 1, 3] += 2.0 * w * v[0]


@njit(cache=True, inline="always")
def _unit(v):
    """(v/‖v‖ as a 3-tuple, ‖v‖); (0, 0) for a zero vector."""
    n = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if n == 0.0:
        return (v[0] * 0.0, v[1] * 0.0, v[2] * 0.0), 0.0
    return (v[0] / n, v[1] / n, v[2] / n), n


@njit(cache=True)
def gn_step(q, seen, ref, w, con, jac, dq):
    """One Gauss–Newton step (eqs. 10–15) at q; writes Δq into ``dq`` (4,), returns ‖Δq‖.

    seen: :class:`Directions` in the sensor frame (a, m, h); ref: their unit ENU
    references (u, n, p). ``w`` weighs the constraint against the magnetometer
    (eq. 15): W = diag(I, (1 − w)I, con·w·I); con = 1 is the paper, con = 0
    drops the constraint block. jac is (9, 4) scratch.
    """
    _dfdq(q, seen.gravity, jac, 0)
    _dfdq(q, seen.field, jac, 3)
    _dfdq(q, seen.joint, jac, 6)
    fa = rotate3(q, seen.gravity)  # C(q)v for a unit q
    fm = rotate3(q, seen.field)
    fh = rotate3(q, seen.joint)
    u, nref, p = ref.gravity, ref.field, ref.joint
    eps = (u[0] - fa[0], u[1] - fa[1], u[2] - fa[2], nref[0] - fm[0], nref[1] - fm[1], nref[2] - fm[2],
           p[0] - fh[0], p[1] - fh[1], p[2] - fh[2])  # fmt: skip
    wm, wc = 1.0 - w, con * w
    wt = (1.0, 1.0, 1.0, wm, wm, wm, wc, wc, wc)
    # J = −jac, so −(JᵀWJ)⁻¹JᵀWε = (jacᵀW jac)⁻¹ jacᵀWε   (eq. 14)
    A = np.zeros((4, 5))
    for r in range(4):
        for c in range(4):
            s = 0.0
            for e in range(9):
                s += jac[e, r] * wt[e] * jac[e, c]
            A[r, c] = s
        s = 0.0
        for e in range(9):
            s += jac[e, r] * wt[e] * eps[e]
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
def mag_deviation(q, mag, p):
    """eq. 16's field deviation ‖C(q)y_M − m_E‖/m0 of one magnetometer sample ``mag`` (3,) µT; and C(q)y_M
    (a 3-tuple)."""
    m0 = p.field_norm
    n = p.field_dir
    mE = rotate3(q, mag)
    dev = np.sqrt((mE[0] - n[0] * m0) ** 2 + (mE[1] - n[1] * m0) ** 2 + (mE[2] - n[2] * m0) ** 2) / m0
    return dev, mE


@njit(cache=True, inline="always")
def directions(p, inputs, i):
    """Sample i's unit :class:`Directions` in sensor i and their ENU references (u = UP, n =
    ``p.field_dir``, p from link j), and the constraint factor: 1 if ``p.use_constraint``, but 0 where h_i
    or C(q_j)h_j is zero (free fall: no direction)."""
    a_s, _ = _unit(inputs.acc[i])
    m_s, _ = _unit(inputs.mag[i])
    h_s, hn = _unit(inputs.joint_i[i])
    p_j, pn = _unit(inputs.joint_j[i])
    con = 1.0 if (p.use_constraint and hn > 0.0 and pn > 0.0) else 0.0
    return Directions(a_s, m_s, h_s), Directions(UP, p.field_dir, p_j), con


@njit(cache=True)
def fuse(p, q, inputs, control, start, stop, trace):
    """Fuse samples ``start:stop`` (eqs. 4–18) into the state q (4,), updated in place.

    Args:
        p: :class:`Params`.
        q: (4,) the state, the estimate q_{i, start−1}; overwritten with q_{i, stop−1}.
        inputs: :class:`Inputs` of the trial.
        control: :class:`Control`, w and k of every sample (given or by eqs. 16 / 18).
        trace: :class:`Trace`, rows start:stop written.
    """
    dt = p.dt
    jac = np.empty((9, 4))
    dq = np.zeros(4)
    gyr, est = inputs.gyr, trace.est
    for i in range(start, stop):
        seen, ref, con = directions(p, inputs, i)
        dev, _ = mag_deviation(q, inputs.mag[i], p)
        trace.mag_dev[i] = dev
        w = weight_rule(dev, p.th1) if control.weight_by_rule else control.weight  # eq. 16
        trace.weight[i] = w
        step = 0.0
        if control.gain_by_rule or control.gain != 0.0:
            step = gn_step(q, seen, ref, w, con, jac, dq)  # eq. 14
        k = gain_rule(w, step, p.th2, p.th3, p.k_min, p.k_max) if control.gain_by_rule else control.gain  # eq. 18
        trace.gain[i] = k
        if not np.isfinite(step):
            k = 0.0
            dq[:] = 0.0
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


# ------------------------------------------------------------------ offline use


def make_params(trial: Trial, use_constraint: bool = True, **rule) -> Params:
    """:class:`Params` for ``trial`` (its Δt and Earth field) and the rules' parameters ``rule`` (th1 … k_max by
    keyword, :func:`check_rule_params`); ValueError / TypeError naming a bad one."""
    th1, th2, th3, k_min, k_max = check_rule_params(**rule)
    n = earth_field(trial.field_norm, trial.field_dip) / trial.field_norm
    return Params(
        float(trial.dt),
        float(trial.field_norm),
        (float(n[0]), float(n[1]), float(n[2])),
        th1,
        th2,
        th3,
        k_min,
        k_max,
        check_bool("use_constraint", use_constraint),
    )


RULE_PARAMS = ("th1", "th2", "th3", "k_min", "k_max")  # eqs. 16 and 18's parameters, in check_rule_params' order


def check_rule_params(
    th1=TH1, th2=TH2, th3=TH3, k_min=K_MIN, k_max=K_MAX, sort_gains: bool = False
) -> tuple[float, float, float, float, float]:
    """The parameters of eqs. 16 and 18 (:data:`RULE_PARAMS`, defaults the published ones) as floats: ``th1``
    (field deviation, fraction of m0) and ``th3`` (‖Δq‖) finite > 0, ``th2`` (a weight) in [0, 1], gains
    ``k_min`` finite ≥ 0 and ``k_max`` finite ≥ k_min (1/s); ValueError / TypeError naming a bad one. With
    ``sort_gains`` the larger gain is k_max whichever was given as which (CMA-ES may propose k_min > k_max;
    eq. 18 needs k_max ≥ k_min)."""
    th1, th3 = check_positive("th1", th1), check_positive("th3", th3)
    th2, k_min = check_number("th2", th2, 0.0, 1.0), check_number("k_min", k_min, 0.0)
    if sort_gains:
        k_min, k_max = sorted((k_min, check_number("k_max", k_max, 0.0)))
    k_max = check_number(f"k_max (≥ k_min = {k_min:g})", k_max, k_min)
    return th1, th2, th3, k_min, k_max


def _lever(trial: Trial, given, key: str) -> np.ndarray:
    """Lever arm r (3,) m, sensor → joint centre: ``given`` or ``trial.meta[key]``."""
    name = f"{key.removesuffix('_m')} (lever arm, m)"
    if given is None:
        if key not in trial.meta:
            raise MissingChannelsError(
                f"trial {trial.name!r} has no meta[{key!r}] (sensor → joint centre, m); "
                f"pass lever_i / lever_j to the filter"
            )
        given, name = trial.meta[key], f"trial {trial.name!r} meta[{key!r}] (lever arm, m)"
    return check_vector(name, given, 3)


def make_inputs(trial: Trial, lever_i: np.ndarray, lever_j: np.ndarray) -> Inputs:
    """:class:`Inputs` of a two-link trial: link i's readings and both joint vectors (eq. 9)."""
    h_j = joint_vectors(
        np.asarray(trial.extra["gyr_j"], float), np.asarray(trial.extra["acc_j"], float), lever_j, trial.rate
    )
    joint_j = np.ascontiguousarray(rotate(np.ascontiguousarray(trial.extra["q_j"], float), h_j))
    return Inputs(trial.gyr, trial.acc, trial.mag, joint_vectors(trial.gyr, trial.acc, lever_i, trial.rate), joint_j)


class ConstraintFilter:
    """Link i's filter on one two-link trial: its parameters, kernel inputs and start, for offline use.

    Args:
        trial: a two-link Trial (``extra`` gyr_j, acc_j, q_j; see ``magenv.scenarios.twolink``).
        lever_i, lever_j: r_i, r_j (m, sensor frames); None = ``trial.meta['lever_i_m'/'lever_j_m']``.
        q0: initial orientation; None = e-compass of the first sample (never truth).
        use_constraint: False drops the constraint block from W (ablation: eqs. 16–18 gating only).
        rule: th1, th2, th3, k_min, k_max of eqs. 16 and 18 by keyword (:func:`check_rule_params`).

    Attributes ``params`` (:class:`Params`), ``inputs`` (:class:`Inputs`), ``q0`` (4,).
    Raises MissingChannelsError if the trial lacks link j's channels or the lever arms.
    """

    def __init__(
        self,
        trial: Trial,
        lever_i=None,
        lever_j=None,
        q0=None,
        use_constraint: bool = True,
        **rule,
    ):
        require_two_link(trial)
        self.lever_i, self.lever_j = _lever(trial, lever_i, "lever_i_m"), _lever(trial, lever_j, "lever_j_m")
        self.params = make_params(trial, use_constraint, **rule)
        self.trial = trial
        self.inputs = make_inputs(trial, self.lever_i, self.lever_j)
        self.q0 = ecompass1(trial.acc[0], trial.mag[0]) if q0 is None else normalize1(check_vector("q0", q0, 4, True))

    def run(self, weight: float | None = None, gain: float | None = None) -> Trace:
        """The whole trial from ``q0`` with constant w ∈ [0, 1] and k ≥ 0 1/s (None = eq. 16 / eq. 18); returns its
        :class:`Trace`. ValueError / TypeError naming a bad w or k."""
        weight = None if weight is None else check_number("weight", weight, 0.0, 1.0)
        gain = None if gain is None else check_number("gain", gain, 0.0)
        trace = Trace.empty(self.trial.n)
        fuse(self.params, self.q0.copy(), self.inputs, Control.of(weight, gain), 0, self.trial.n, trace)
        return trace
