"""The extra causal features of ``magenv/MagConstraint-v0``'s extended observation (``features="extended"``).

What the oracle (``magenv.baselines.oracle_constraint``) uses and today's
observation lacks is the *sign* of link i's heading error and of each
correction: the magnetometer pulls the heading one way, the constraint
another, and which one is right changes over seconds. These features are
computed from the sensors, link j's given orientation and the env's own
estimate history only — never truth — by :func:`update`, called after each
step on the samples just fused (``start:stop``); they describe the decision
at sample ``stop``, the timing of the base features.

Conventions (ENU earth frame, degrees, signed, wrapped to ±180): "heading(a ⊗
b*)" is the rotation about earth-up from orientation b to a
(``magenv.envs.blend_memory``'s convention); the *mag heading* of sample i is
the heading of its field C(q_i)y_M (q_i the estimate after the sample) minus
that of the Earth field m_E (≈ −heading error in an undisturbed field); the
*joint heading* is `con_heading` of the base table (heading of C(q)h_i minus
that of C(q_j)h_j, ≈ the heading error while the joint centre accelerates
horizontally). An EMA of time constant τ takes each sample with weight Δt/τ.
"Parallel" filters run the env's filter (``magenv.filters.constraint.fuse``)
from the start on the same samples with a fixed w (k by eq. 18). A sample is
*clean* when eq. 16's deviation ‖C(q)y_M − m_E‖/m0 < 0.03.

Gyro bias: link i's gyroscope carries a constant bias (the paper adds one on
purpose, §3.1) that the filter does not model; where the gain k is small its
heading drifts with it. b̂ is the mean of link i's gyro over every sample at
rest so far (0 before any): at rest when Fan et al. 2017's detector
(``magenv.filters.stationary``, eqs. 11–13, its thresholds) has flagged the
samples of the last ``REST_HOLD_S``. A bias of a component at or above the
detector's gyro threshold is never learned (rest is never flagged). The
*bias-corrected* filters run the env's filter on ω_i − b̂: one with the w
(and k) the env applied at each sample, k by eq. 18 where the env took it so
(the estimate had the gyro been corrected); one with w = 1 (the constraint
alone, k by eq. 18).

Constraint error estimate: the *error* of an orientation q is the earth-frame
rotation vector δθ of q ⊗ q_true* (° , components east, north, up), so a
correction r (an earth-frame rotation applied as exp(r) ⊗ q) takes it to
≈ δθ + r. Link j's orientation is known, so eq. 9's mismatch is
C(q)h_i − C(q_j)h_j ≈ δθ × v with v = C(q)h_i (m/s²): each sample gives the
two components of δθ across v (tilt, since v ≈ g·up; heading only as far as
the joint centre accelerates horizontally). The mismatch is taken against a
*gyro frame* q_g — the bias-corrected gyro (ω_i − b̂) integrated from the
start q0 — whose error changes only with the gyro's noise and residual bias,
and solved by least squares with forgetting: δθ_g = (Σ SᵀS)⁻¹ Σ −Sᵀ(C(q_g)h_i
− C(q_j)h_j), S = [C(q_g)h_i]×, each sum an EMA of time constant τ (per
sample weight Δt/τ; a ridge of 10⁻³ (m/s²)² keeps it solvable before any
motion). The estimate's own error is then that of (q ⊗ q_g*) ⊗ exp(δθ_g),
exact given δθ_g. The *steps* are eq. 14's Gauss–Newton step Δq at the
estimate with the next sample's directions, as the earth-frame rotation
2·vec(Δq ⊗ q*) (° per unit gain): where one points against δθ, it corrects.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from magenv.envs import lagged
from magenv.envs.blend_memory import _ema, _heading
from magenv.envs.features import DEG, HEADING, SHARED, Feature, FeatureTable
from magenv.envs.headings import dip_deg, norm3, planar_heading, wrap_deg
from magenv.filters import constraint as cf
from magenv.filters import stationary
from magenv.quaternion import GRAVITY, conj1, from_rotvec1, integrate_gyro1, mul1, rotate1, to_rotvec1

_ERR = -30.0, 30.0  # degrees: the range of the error estimates
EXTRA = FeatureTable(
    SHARED["mh_ema_025"],
    SHARED["mh_ema_1"],
    SHARED["mh_ema_4"],
    Feature(
        "jh_ema_025",
        *HEADING,
        DEG,
        "EMA (τ 0.25 s) of the joint heading, each sample weighted by min(a_h/(0.2 g), 1), a_h the horizontal "
        "joint-centre acceleration ‖C(q_j)h_j‖ in the ENU plane",
    ),
    Feature("jh_ema_1", *HEADING, DEG, "as `jh_ema_025` with τ 1 s"),
    Feature("jh_ema_4", *HEADING, DEG, "as `jh_ema_025` with τ 4 s"),
    Feature("ja_h_ema_1", 0.0, 10.0, "units of g", "EMA (τ 1 s) of a_h (how much the constraint sees the heading)"),
    Feature("d_mag", *HEADING, DEG, "heading(q_mag ⊗ q*), q_mag the parallel w = 0 filter (magnetometer)"),
    Feature("d_con", *HEADING, DEG, "heading(q_con ⊗ q*), q_con the parallel w = 1 filter (constraint)"),
    Feature("d_anchor", *HEADING, DEG, "heading(q ⊗ q_anc*), q_anc the gyro (k = 0) re-anchored to q on clean samples"),
    SHARED["t_clean"],
    Feature("dev_ema_05", 0.0, 10.0, "fraction of m0", "EMA (τ 0.5 s) of eq. 16's deviation"),
    Feature("dev_ema_2", 0.0, 10.0, "fraction of m0", "EMA (τ 2 s) of eq. 16's deviation"),
    Feature("nd_ema_2", -1.0, 10.0, "fraction of m0", "EMA (τ 2 s) of (‖y_M‖ − m0)/m0"),
    Feature("dd_ema_2", *HEADING, DEG, "EMA (τ 2 s) of the signed dip deviation of C(q)y_M"),
    Feature("gyro_ema_1", 0.0, 100.0, "rad/s", "EMA (τ 1 s) of ‖ω_i‖"),
    SHARED["clean_ema_4"],
    Feature("d_btwin", *HEADING, DEG, "heading(q_bt ⊗ q*), q_bt the parallel filter on ω_i − b̂ with the w applied"),
    Feature("d_bcon", *HEADING, DEG, "heading(q_bc ⊗ q*), q_bc the parallel w = 1 filter on ω_i − b̂"),
    Feature("drift", -5.0, 5.0, "°/s", "C(q)b̂'s up component: the heading drift b̂ causes (+ anticlockwise, as d_*)"),
    Feature("cerr_e_05", *_ERR, DEG, "constraint error estimate of q (τ 0.5 s), east component (tilt)"),
    Feature("cerr_n_05", *_ERR, DEG, "as `cerr_e_05`, north component (tilt)"),
    Feature("cerr_e_2", *_ERR, DEG, "constraint error estimate of q (τ 2 s), east component"),
    Feature("cerr_n_2", *_ERR, DEG, "as `cerr_e_2`, north component"),
    Feature("cerr_e_30", *_ERR, DEG, "constraint error estimate of q (τ 30 s), east component"),
    Feature("cerr_n_30", *_ERR, DEG, "as `cerr_e_30`, north component"),
    Feature("cerr_u_30", *_ERR, DEG, "as `cerr_e_30`, up component (heading: only as the joint centre accelerates)"),
    Feature("step0_e", *HEADING, "° per unit gain", "step with w = 0 (gravity + magnetometer), east component"),
    Feature("step0_n", *HEADING, "° per unit gain", "as `step0_e`, north component"),
    Feature("step0_u", *HEADING, "° per unit gain", "as `step0_e`, up component"),
    Feature("step1_e", *HEADING, "° per unit gain", "step with w = 1 (gravity + constraint), east component"),
    Feature("step1_n", *HEADING, "° per unit gain", "as `step1_e`, north component"),
    Feature("step1_u", *HEADING, "° per unit gain", "as `step1_e`, up component"),
    Feature("step0_dot", -1.0e3, 1.0e3, "°²", "step0 · (cerr_e_05, cerr_n_05), east/north: < 0 corrects tilt"),
    Feature("step1_dot", -1.0e3, 1.0e3, "°²", "as `step0_dot` for step1"),
)
X = EXTRA.ix
_LOW, _HIGH = EXTRA.low64, EXTRA.high64
LAGS = (25, 100)  # decisions: 1 s and 4 s at the env's default k = 4, 100 Hz
ERR_TAUS = (0.5, 2.0, 30.0)  # s, forgetting time constants of the constraint error estimates
ERR_RIDGE = 1.0e-3  # (m/s²)², keeps the normal equations solvable before any motion

# layout of the state vector: six quaternions, the bias sums (3), the scalars, then per ERR_TAUS the forgetting
# sums of the error estimate's normal equations (SᵀS row-major (9), −Sᵀ·mismatch (3))
Q_MAG, Q_CON, Q_ANC, Q_BTWIN, Q_BCON, Q_GYRO = 0, 4, 8, 12, 16, 20
B_SUM = 24  # (3,) sum of link i's gyro over the rest samples, rad/s
(S_MH025, S_MH1, S_MH4, S_JH025, S_JH1, S_JH4, S_JA1, S_DEV05, S_DEV2, S_ND2, S_DD2, S_G1, S_TCLEAN,
 S_CLEAN4, S_NREST, S_RUN) = range(27, 43)  # fmt: skip
LS = 43  # start of the normal equations' sums, 12 per time constant
N_STATE = LS + 12 * len(ERR_TAUS)
CLEAN_DEV = 0.03  # fraction of m0
JOINT_FULL = 0.2 * GRAVITY  # m/s², horizontal joint acceleration at which the joint heading counts fully
REST_HOLD_S = 0.25  # s the stationary detector must have flagged in a row before a sample counts as rest
_TH_ACC, _TH_GYRO = stationary.thresholds()  # Fan et al. 2017's, m/s² and rad/s per axis


class Memory(NamedTuple):
    """The streaming state of the extra features of one trial (arrays updated in place)."""

    state: np.ndarray  # (N_STATE,) see the layout constants
    scratch: cf.Trace  # the parallel filters' trace rows (trial length)
    gyr_c: np.ndarray  # (n, 3) ω_i − b̂ of the samples fused so far, rad/s (the bias-corrected filters' gyro)
    rest: stationary.State  # Fan et al. 2017's detector on link i
    value: np.ndarray  # (len(EXTRA),) the features of the next decision (zeros before any sample is fused)

    @classmethod
    def start(cls, q0: np.ndarray, n: int, rate: float) -> Memory:
        """Memory at the start of an ``n``-sample trial at ``rate`` Hz: every parallel filter at the start ``q0``."""
        state = lagged.anchored(N_STATE, q0, (Q_MAG, Q_CON, Q_ANC, Q_BTWIN, Q_BCON, Q_GYRO))
        return cls(state, cf.Trace.empty(n), np.zeros((n, 3)), stationary.make_state(rate), np.zeros(len(EXTRA)))


@njit(cache=True)
def update(p, inputs, trace, mem, start, stop, gain_by_rule):
    """Advance ``mem`` (:class:`Memory`) over the fused samples start:stop of ``trace`` (the env's
    ``constraint.Trace``) and write ``mem.value``. ``p``: the env's ``constraint.Params``; ``gain_by_rule``:
    the env took k by eq. 18 over these samples (else it applied ``trace.gain``, and so does the twin filter)."""
    s, sc, out = mem.state, mem.scratch, mem.value
    if stop <= start:
        return
    dt, m0, n_e = p.dt, p.field_norm, p.field_dir
    rest_hold = np.floor(REST_HOLD_S / dt + 0.5)  # samples
    h_e = np.rad2deg(np.arctan2(n_e[0], n_e[1]))
    dip0 = np.rad2deg(np.arcsin(min(1.0, max(-1.0, -n_e[2]))))
    q_anc = s[Q_ANC : Q_ANC + 4]
    gyro_only = cf.Control(0.0, 0.0, False, False)  # k = 0: eq. 17 with the gyro alone
    corrected = cf.Inputs(mem.gyr_c, inputs.acc, inputs.mag, inputs.joint_i, inputs.joint_j)
    for i in range(start, stop):
        q = trace.est[i]
        me = rotate1(q, inputs.mag[i])
        mn = norm3(me)
        mh = wrap_deg(planar_heading(me) - h_e)
        s[S_MH025] = _ema(s[S_MH025], mh, min(dt / 0.25, 1.0))
        s[S_MH1] = _ema(s[S_MH1], mh, dt)
        s[S_MH4] = _ema(s[S_MH4], mh, dt / 4.0)
        cj = inputs.joint_j[i]
        a_h = np.sqrt(cj[0] * cj[0] + cj[1] * cj[1])
        wgt = min(a_h / JOINT_FULL, 1.0)
        jh = wrap_deg(planar_heading(rotate1(q, inputs.joint_i[i])) - planar_heading(cj))
        s[S_JH025] = _ema(s[S_JH025], jh, wgt * min(dt / 0.25, 1.0))
        s[S_JH1] = _ema(s[S_JH1], jh, wgt * dt)
        s[S_JH4] = _ema(s[S_JH4], jh, wgt * dt / 4.0)
        s[S_JA1] = _ema(s[S_JA1], a_h / GRAVITY, dt)
        dev = trace.mag_dev[i]
        s[S_DEV05] = _ema(s[S_DEV05], dev, dt / 0.5)
        s[S_DEV2] = _ema(s[S_DEV2], dev, dt / 2.0)
        s[S_ND2] = _ema(s[S_ND2], (mn - m0) / m0, dt / 2.0)
        dip = dip_deg(me, mn, dip0)
        s[S_DD2] = _ema(s[S_DD2], dip - dip0, dt / 2.0)
        g = inputs.gyr[i]
        s[S_G1] = _ema(s[S_G1], norm3(g), dt)
        s[S_RUN] = s[S_RUN] + 1.0 if stationary.step1(mem.rest, inputs.acc[i], g, _TH_ACC, _TH_GYRO) else 0.0
        if s[S_RUN] >= rest_hold:
            s[S_NREST] += 1.0
            s[B_SUM : B_SUM + 3] += g
        for k in range(3):
            mem.gyr_c[i, k] = g[k] - (s[B_SUM + k] / s[S_NREST] if s[S_NREST] > 0 else 0.0)
        if i > 0:
            s[Q_GYRO : Q_GYRO + 4] = integrate_gyro1(s[Q_GYRO : Q_GYRO + 4], mem.gyr_c[i], dt)
        _accumulate(s, rotate1(s[Q_GYRO : Q_GYRO + 4], inputs.joint_i[i]), inputs.joint_j[i], dt)
        cf.fuse(
            p,
            s[Q_BTWIN : Q_BTWIN + 4],
            corrected,
            cf.Control(trace.weight[i], trace.gain[i], False, gain_by_rule),
            i,
            i + 1,
            sc,
        )
        clean = dev < CLEAN_DEV
        s[S_CLEAN4] = _ema(s[S_CLEAN4], 1.0 if clean else 0.0, dt / 4.0)
        if clean:
            q_anc[:] = q
            s[S_TCLEAN] = 0.0
        else:
            cf.fuse(p, q_anc, inputs, gyro_only, i, i + 1, sc)
            s[S_TCLEAN] += dt
    cf.fuse(p, s[Q_MAG : Q_MAG + 4], inputs, cf.Control(0.0, 0.0, False, True), start, stop, sc)
    cf.fuse(p, s[Q_CON : Q_CON + 4], inputs, cf.Control(1.0, 0.0, False, True), start, stop, sc)
    cf.fuse(p, s[Q_BCON : Q_BCON + 4], corrected, cf.Control(1.0, 0.0, False, True), start, stop, sc)
    q = trace.est[stop - 1]
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    out[X.mh_ema_025], out[X.mh_ema_1], out[X.mh_ema_4] = s[S_MH025], s[S_MH1], s[S_MH4]
    out[X.jh_ema_025], out[X.jh_ema_1], out[X.jh_ema_4] = s[S_JH025], s[S_JH1], s[S_JH4]
    out[X.ja_h_ema_1] = s[S_JA1]
    out[X.d_mag] = _heading(s[Q_MAG], s[Q_MAG + 1], s[Q_MAG + 2], s[Q_MAG + 3], qw, qx, qy, qz)
    out[X.d_con] = _heading(s[Q_CON], s[Q_CON + 1], s[Q_CON + 2], s[Q_CON + 3], qw, qx, qy, qz)
    out[X.d_anchor] = _heading(qw, qx, qy, qz, q_anc[0], q_anc[1], q_anc[2], q_anc[3])
    out[X.t_clean] = s[S_TCLEAN] / 10.0
    out[X.dev_ema_05], out[X.dev_ema_2] = s[S_DEV05], s[S_DEV2]
    out[X.nd_ema_2], out[X.dd_ema_2], out[X.gyro_ema_1] = s[S_ND2], s[S_DD2], s[S_G1]
    out[X.clean_ema_4] = s[S_CLEAN4]
    out[X.d_btwin] = _heading(s[Q_BTWIN], s[Q_BTWIN + 1], s[Q_BTWIN + 2], s[Q_BTWIN + 3], qw, qx, qy, qz)
    out[X.d_bcon] = _heading(s[Q_BCON], s[Q_BCON + 1], s[Q_BCON + 2], s[Q_BCON + 3], qw, qx, qy, qz)
    b_up = 0.0
    if s[S_NREST] > 0:
        b_up = rotate1(q, s[B_SUM : B_SUM + 3])[2] / s[S_NREST]
    out[X.drift] = np.rad2deg(b_up)
    _error_features(p, inputs, s, q, stop, out)
    for k in range(out.shape[0]):
        out[k] = min(max(out[k], _LOW[k]), _HIGH[k])


@njit(cache=True)
def _accumulate(s, v, c_j, dt):
    """Add one sample to each time constant's forgetting sums: SᵀS = ‖v‖²I − vvᵀ and −Sᵀ·mis = v × mis,
    v = C(q_g)h_i, mis = v − C(q_j)h_j (m/s², ENU)."""
    mis = v - c_j
    vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    cross = (v[1] * mis[2] - v[2] * mis[1], v[2] * mis[0] - v[0] * mis[2], v[0] * mis[1] - v[1] * mis[0])
    for t in range(len(ERR_TAUS)):
        keep = 1.0 - min(dt / ERR_TAUS[t], 1.0)
        o = LS + 12 * t
        for r in range(3):
            for c in range(3):
                s[o + 3 * r + c] = keep * s[o + 3 * r + c] + ((vv if r == c else 0.0) - v[r] * v[c])
            s[o + 9 + r] = keep * s[o + 9 + r] + cross[r]


@njit(cache=True)
def _error_features(p, inputs, s, q, stop, out):
    """The constraint error estimates of ``q`` and the w = 0 / w = 1 steps at sample ``stop`` (module docstring)."""
    to_q = mul1(q, conj1(s[Q_GYRO : Q_GYRO + 4]))  # q ⊗ q_g*
    cols = ((X.cerr_e_05, X.cerr_n_05, -1), (X.cerr_e_2, X.cerr_n_2, -1), (X.cerr_e_30, X.cerr_n_30, X.cerr_u_30))
    err = np.zeros(3)
    for t in range(len(ERR_TAUS)):
        o = LS + 12 * t
        normal = s[o : o + 9].reshape(3, 3) + ERR_RIDGE * np.eye(3)  # positive definite: SᵀS ⪰ 0 plus the ridge
        d = np.rad2deg(to_rotvec1(mul1(to_q, from_rotvec1(np.linalg.solve(normal, s[o + 9 : o + 12])))))
        ie, i_n, iu = cols[t]
        out[ie], out[i_n] = d[0], d[1]
        if iu >= 0:
            out[iu] = d[2]
        if t == 0:
            err[:] = d
    n = inputs.gyr.shape[0]
    seen, ref, con = cf.directions(p, inputs, stop if stop < n else n - 1)
    jac, dq = np.empty((9, 4)), np.zeros(4)
    firsts = (X.step0_e, X.step1_e)
    dots = (X.step0_dot, X.step1_dot)
    for c in range(2):
        cf.gn_step(q, seen, ref, float(c), con, jac, dq)
        r = mul1(dq, conj1(q))
        for k in range(3):
            v = np.rad2deg(2.0 * r[k + 1])
            out[firsts[c] + k] = v if np.isfinite(v) else 0.0
        out[dots[c]] = out[firsts[c]] * err[0] + out[firsts[c] + 1] * err[1]
