"""Quaternion Kalman filter whose magnetometer trust is set from outside (the filter of ``magenv/MagKalman-v0``).

A multiplicative (error-state) Kalman filter: the estimate ``q̂`` (sensor →
ENU) is corrected by an **earth-frame** small rotation δθ,
``q = exp(δθ) ⊗ q̂``, with covariance P (3×3, rad²). Per sample:

1. Gyro prediction: ``q̂ ← q̂ ⊗ exp(½ ω T_s)``, ω the trapezoidal mean of
   two causal samples; ``P ← P + (σ_g T_s)² I`` (white gyro noise mapped to
   the earth frame is isotropic).
2. Accelerometer update (gated as in survey A7: skipped when
   ``| |acc| − g | ≥ th_acc``): ``ν_a = q̂ ⊗ acc ⊗ q̂* − g_ENU ≈ [g_ENU×] δθ``,
   ``R_a = σ_a² I``. ``[g_ENU×]`` has a zero z column, so gravity never
   touches the heading.
3. Magnetometer update scaled by ``trust`` γ ∈ [0, 1]:
   ``ν_m = q̂ ⊗ mag ⊗ q̂* − h_ENU ≈ [h_ENU×] δθ``, ``R_m = σ_m² I``,
   ``S = H P Hᵀ + R_m``, ``K = P Hᵀ S⁻¹``; with ``heading_only`` (default,
   the survey's conclusion that the magnetometer should stay out of the
   attitude) only K's z row is kept — the Schmidt (consider) gain, optimal
   among gains that leave the tilt alone. Then ``δθ = γ K ν_m`` and
   ``P ← (I − γKH) P (I − γKH)ᵀ + γ² K R_m Kᵀ`` (Joseph form, exact for any
   gain).

**Why a gain multiplier in [0, 1] and not a log-scale R multiplier.**
``R_m·10^(−s·a)`` can only approach "ignore" asymptotically, so trust = 0
could not switch the magnetometer off, and its scale s is one more
hyper-parameter of the action space. A gain multiplier γ is bounded (a
natural Box action), γ = 0 ignores the magnetometer *exactly* (heading then
moves with the gyro alone), γ = 1 is the nominal Kalman filter, and the
Joseph form keeps P the true error covariance of the filter actually run
(whatever γ the policy picks), so trace P and S stay meaningful
observations. A log-R policy can still be emulated inside (0, 1].

Signals (columns of ``sig``, named by ``SIGNALS`` and indexed by ``SIG``, e.g.
``sig[SIG.nis]``; what a policy may observe, truth-free):

==  =================  =====  ===============================================
 0  nu_e               µT     magnetometer innovation, earth frame, east
 1  nu_n               µT     … north
 2  nu_u               µT     … up
 3  nu_norm            µT     |ν_m|
 4  nis                –      ν_mᵀ S⁻¹ ν_m (normalised innovation squared, χ²₃ if consistent)
 5  s_trace            µT²    trace S (a-priori innovation covariance)
 6  p_trace            rad²   trace P after the step
 7  heading_std        rad    sqrt(P_zz) after the step
 8  mag_norm_dev       µT     |mag| − m0
 9  dip_dev            deg    dip of mag below the estimated horizontal − θ0
10  acc_norm_dev       m/s²   |acc| − g
11  acc_used           –      1 if the accelerometer update ran, else 0
12  trust              –      the γ applied
==  =================  =====  ===============================================

ν_m of a heading error ε about the vertical points mostly east
(≈ ε·|h_horizontal|); a magnetic disturbance shows as a change of its norm
or dip too. The same ν_m is the filter's disturbance estimate in µT (earth
frame): the model-based split is not used here.

Kernels take :class:`Params` (named constants) and :class:`State` (named
arrays, updated in place); :func:`run_trial` runs a whole trial offline.
"""

from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from magenv import quaternion as quat
from magenv.checks import check_bool, check_noise, check_positive, check_site
from magenv.filters.kalman_threshold import (
    COV_FLOOR,
    OK,
    SIGMA_ACC,
    SIGMA_GYR,
    SIGMA_MAG,
    TH_ACC,
    FilterError,
    finite3,
    repair_cov3,
)
from magenv.filters.linalg import (
    add33,
    diag3,
    innovation_cov3,
    inv3,
    joseph3,
    mat3,
    mul33,
    mul33t,
    mv3,
    quad3,
    scale33,
    skew3,
    store3,
)
from magenv.filters.sensors import Sensors
from magenv.filters.solvers import triad1
from magenv.quaternion import from_rotvec4, mul4, normalize4, rotate3

SIGNALS = (
    "nu_e",
    "nu_n",
    "nu_u",
    "nu_norm",
    "nis",
    "s_trace",
    "p_trace",
    "heading_std",
    "mag_norm_dev",
    "dip_dev",
    "acc_norm_dev",
    "acc_used",
    "trust",
)
SIG = namedtuple("SignalIndex", SIGNALS)(*range(len(SIGNALS)))  # SIG.nu_e == 0, … (column of a signal)
NSIG = len(SIGNALS)
P0 = np.deg2rad(5.0) ** 2  # initial variance per axis, rad²


class Params(NamedTuple):
    """Constants of the trust KF over one trial (:func:`make_params`)."""

    dt: float  # sample interval T_s, s
    sigma_gyr: float  # gyro noise std σ_g, rad/s
    sigma_acc: float  # accelerometer noise std σ_a, m/s²
    sigma_mag: float  # magnetometer noise std σ_m, µT
    th_acc: float  # accelerometer gate on | |a| − g |, m/s² (inf: never gated)
    heading_only: bool  # the magnetometer corrects the heading only (Schmidt gain)
    g_ref: np.ndarray  # (3,) gravity reference g_ENU (specific force at rest, up), m/s²
    h_ref: np.ndarray  # (3,) Earth field h_ENU, µT
    m0: float  # undisturbed field norm, µT
    dip0: float  # undisturbed dip, rad (positive down)
    cov_floor: float  # eigenvalue floor of a repaired covariance, rad²
    p0: float  # initial variance of each error angle, rad²


class State(NamedTuple):
    """The filter's state, updated in place."""

    q: np.ndarray  # (4,) estimate q̂, sensor → ENU
    p: np.ndarray  # (3, 3) covariance of the earth-frame error angle δθ, rad²


@dataclass(frozen=True)
class Options:
    """The trust KF's noise model and gates, checked by :func:`make_params`.

    Attributes:
        sigma_gyr: rad/s. sigma_acc: m/s². sigma_mag: µT (survey noise by default); each finite > 0.
        th_acc: accelerometer gate, m/s² > 0 (Table A1); ``np.inf`` disables it.
        heading_only: the magnetometer corrects the heading only (Schmidt gain); a bool.
    """

    sigma_gyr: float = SIGMA_GYR
    sigma_acc: float = SIGMA_ACC
    sigma_mag: float = SIGMA_MAG
    th_acc: float = TH_ACC
    heading_only: bool = True


def make_params(
    field_norm: float, field_dip: float, dt: float, options: Options | None = None, p0: float = P0
) -> Params:
    """Parameters for a site and sample interval; ValueError / TypeError naming a bad one (``magenv.checks``).

    Args:
        field_norm: m0, µT (``magenv.checks.check_site``). field_dip: θ0, degrees down. dt: s > 0.
        options: the noise model and gates (:class:`Options`; None: its defaults).
        p0: initial variance of each error angle, rad², finite > 0.
    """
    field_norm, field_dip = check_site(field_norm, field_dip)
    o = Options() if options is None else options
    return Params(
        check_positive("dt", dt),
        check_noise("sigma_gyr", o.sigma_gyr, "gyr"),
        check_noise("sigma_acc", o.sigma_acc, "acc"),
        check_noise("sigma_mag", o.sigma_mag, "mag"),
        check_positive("th_acc", o.th_acc, inf_ok=True),
        check_bool("heading_only", o.heading_only),
        quat.gravity_up(),
        quat.earth_field(field_norm, field_dip),
        field_norm,
        float(np.deg2rad(field_dip)),
        COV_FLOOR,
        check_positive("p0", p0),
    )


@njit(cache=True)
def init_kernel(params, acc0, mag0, state):
    """Initialise ``state``: q by TRIAD on the first sample, ``P = p0·I``, in place. Returns False if degenerate."""
    q0 = triad1(acc0, mag0, params.g_ref, params.h_ref)
    if not np.isfinite(q0[0]):
        return False
    state.q[:] = q0
    p = state.p
    p[:, :] = 0.0
    for i in range(3):
        p[i, i] = params.p0
    return True


@njit(cache=True, inline="always")
def _apply(q, dtheta):
    """q ← exp(δθ) ⊗ q (earth-frame correction), 4-tuples."""
    return normalize4(mul4(from_rotvec4(dtheta), q))


@njit(cache=True, inline="always")
def _update(p, h, nu, s_inv, r, gain, heading_only):
    """Kalman update of the error δθ (P 9-tuple) by a 3-component measurement (H 9-tuple, innovation ν, S⁻¹
    of S = H P Hᵀ + r I) with gain ``gain``·K (only K's z row with ``heading_only``). Returns ``(δθ, P')``,
    Joseph form."""
    k = mul33(mul33t(p, h), s_inv)
    if heading_only:
        k = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, k[6], k[7], k[8])
    k = scale33(gain, k)
    return mv3(k, nu), joseph3(p, k, h, r)


@njit(cache=True)
def _step(params, q, p, gyr_prev, gyr, acc, mag, trust, sig):
    """One sample from the estimate ``q`` (4,) and covariance ``p`` (3, 3) (read only); writes ``sig``.
    Returns ``(status, q', P')`` (4- and 9-tuples), status as :func:`step1`. Allocates nothing
    (``magenv.filters.linalg``) but in a covariance repair."""
    if not (finite3(gyr_prev) and finite3(gyr) and finite3(acc) and finite3(mag) and np.isfinite(trust)):
        return -1, (1.0, 0.0, 0.0, 0.0), diag3(0.0)
    sg, sa, sm, dt = params.sigma_gyr, params.sigma_acc, params.sigma_mag, params.dt
    g_ref, h_ref = params.g_ref, params.h_ref
    pt = mat3(p)
    # 1. prediction
    w = (0.5 * (gyr_prev[0] + gyr[0]) * dt, 0.5 * (gyr_prev[1] + gyr[1]) * dt, 0.5 * (gyr_prev[2] + gyr[2]) * dt)
    qn = normalize4(mul4(q, from_rotvec4(w)))
    pt = add33(pt, diag3((sg * dt) ** 2))
    # 2. accelerometer update (gated, A7)
    na = np.sqrt(acc[0] ** 2 + acc[1] ** 2 + acc[2] ** 2)
    ng = np.sqrt(g_ref[0] ** 2 + g_ref[1] ** 2 + g_ref[2] ** 2)
    acc_used = abs(na - ng) < params.th_acc
    if acc_used:
        h = skew3(g_ref)
        a_e = rotate3(qn, acc)
        nu = (a_e[0] - g_ref[0], a_e[1] - g_ref[1], a_e[2] - g_ref[2])
        dtheta, pt = _update(pt, h, nu, inv3(innovation_cov3(pt, h, sa * sa)), sa * sa, 1.0, False)
        qn = _apply(qn, dtheta)
    # 3. magnetometer update scaled by trust
    h = skew3(h_ref)
    m_e = rotate3(qn, mag)
    nu = (m_e[0] - h_ref[0], m_e[1] - h_ref[1], m_e[2] - h_ref[2])
    s = innovation_cov3(pt, h, sm * sm)
    s_inv = inv3(s)
    if trust > 0.0:
        dtheta, pt = _update(pt, h, nu, s_inv, sm * sm, trust, params.heading_only)
        qn = _apply(qn, dtheta)
    status, pt = repair_cov3(pt, params.cov_floor)
    if status < 0:
        return -1, qn, pt
    nm = np.sqrt(mag[0] ** 2 + mag[1] ** 2 + mag[2] ** 2)
    sig[SIG.nu_e] = nu[0]
    sig[SIG.nu_n] = nu[1]
    sig[SIG.nu_u] = nu[2]
    sig[SIG.nu_norm] = np.sqrt(nu[0] ** 2 + nu[1] ** 2 + nu[2] ** 2)
    sig[SIG.nis] = quad3(nu, s_inv)
    sig[SIG.s_trace] = s[0] + s[4] + s[8]
    sig[SIG.p_trace] = pt[0] + pt[4] + pt[8]
    sig[SIG.heading_std] = np.sqrt(pt[8])
    sig[SIG.mag_norm_dev] = nm - params.m0
    sig[SIG.dip_dev] = np.rad2deg(np.arcsin(min(1.0, max(-1.0, -m_e[2] / nm))) - params.dip0) if nm > 0.0 else np.nan
    sig[SIG.acc_norm_dev] = na - ng
    sig[SIG.acc_used] = 1.0 if acc_used else 0.0
    sig[SIG.trust] = trust
    return status, qn, pt


@njit(cache=True)
def step1(params, state, gyr_prev, gyr, acc, mag, trust, sig):
    """One sample (gyr_prev, gyr rad/s; acc m/s²; mag µT; (3,) each) at trust γ, in place on ``state``.

    Writes ``sig`` (NSIG,). Returns 0 ok, 1 covariance repaired, −1 non-finite input or covariance
    (``state`` then stays at the previous sample).
    """
    status, qn, pt = _step(params, state.q, state.p, gyr_prev, gyr, acc, mag, trust, sig)
    if status >= 0:
        q = state.q
        q[0], q[1], q[2], q[3] = qn
        store3(pt, state.p)
    return status


@njit(cache=True)
def peek1(params, state, gyr_prev, gyr, acc, mag, sig):
    """The a-priori signals of a sample: :func:`step1` at γ = 0 writing only ``sig``, ``state`` unchanged.
    Returns the status."""
    return _step(params, state.q, state.p, gyr_prev, gyr, acc, mag, 0.0, sig)[0]


@njit(cache=True)
def run_k_kernel(params, state, sensors, i0, i1, trust, q_out, sig_out):
    """Samples ``i0 … i1−1`` (i0 ≥ 1) at constant ``trust``, in place on ``state``.

    Step i uses gyr[i−1], gyr[i], acc[i], mag[i]; writes q_out[i] (4,) and
    sig_out[i] (NSIG,). Returns ``(status, repairs)``: status OK (−1), or the
    index of the first bad sample (state left at the previous sample).
    """
    gyr, acc, mag = sensors
    q = state.q
    repairs = 0
    for i in range(i0, i1):
        st = step1(params, state, gyr[i - 1], gyr[i], acc[i], mag[i], trust, sig_out[i])
        if st < 0:
            return i, repairs
        repairs += st
        q_out[i] = q
    return OK, repairs


def init(params: Params, acc0, mag0) -> State:
    """Initial state from the first accelerometer (m/s²) and magnetometer (µT) sample."""
    state = State(np.empty(4), np.empty((3, 3)))
    acc0 = np.ascontiguousarray(acc0, dtype=float)
    mag0 = np.ascontiguousarray(mag0, dtype=float)
    if not (np.all(np.isfinite(acc0)) and np.all(np.isfinite(mag0)) and init_kernel(params, acc0, mag0, state)):
        raise FilterError(f"trust KF: cannot initialise from acc={acc0}, mag={mag0} (non-finite, zero or parallel)")
    return state


def run_k(params: Params, state: State, sensors: Sensors, i0: int, i1: int, trust: float, q_out, sig_out) -> int:
    """Advance the filter over samples ``i0 … i1−1`` at magnetometer trust ``trust`` ∈ [0, 1].

    Args:
        params: from :func:`make_params`. state: from :func:`init`, updated in place.
        sensors: the trial's arrays (rad/s, m/s², µT). i0, i1: sample range, 1 ≤ i0 ≤ i1 ≤ N.
        trust: gain multiplier of the magnetometer update (0 = ignore, 1 = nominal).
        q_out: (N, 4) written at rows i0…i1−1. sig_out: (N, NSIG) likewise.
    Returns the number of covariance repairs. Raises FilterError on a
    non-finite sample or covariance, ValueError on a bad trust or range.
    """
    if not 0.0 <= trust <= 1.0:
        raise ValueError(f"trust must be in [0, 1], got {trust!r}")
    n = len(sensors.gyr)
    if not 1 <= i0 <= i1 <= n:
        raise ValueError(f"need 1 <= i0 <= i1 <= N={n}, got i0={i0}, i1={i1}")
    status, repairs = run_k_kernel(params, state, sensors, i0, i1, float(trust), q_out, sig_out)
    if status != OK:
        raise FilterError(
            f"trust KF: non-finite sample or covariance at sample {status} (gyr={sensors.gyr[status]}, "
            f"acc={sensors.acc[status]}, mag={sensors.mag[status]}, trust={trust})"
        )
    return repairs


def run_trial(trial, trust, params: Params | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Whole trial with a constant trust or a per-sample (N,) trust array. Returns ``(q (N, 4), sig (N, NSIG))``."""
    if params is None:
        params = make_params(trial.field_norm, trial.field_dip, trial.dt)
    n = trial.n
    try:
        trust = np.broadcast_to(np.asarray(trust, dtype=float), (n,))
    except (TypeError, ValueError):
        raise ValueError(f"trust must be a number in [0, 1] or one per sample ({n},), got {trust!r:.80}") from None
    sensors = Sensors.of(trial)
    state = init(params, trial.acc[0], trial.mag[0])
    q_out = np.empty((n, 4))
    sig = np.full((n, NSIG), np.nan)
    q_out[0] = state.q
    # run in blocks of constant trust
    change = np.flatnonzero(np.diff(trust[1:]) != 0) + 2
    bounds = np.concatenate([[1], change, [n]])
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b > a:
            run_k(params, state, sensors, int(a), int(b), trust[a], q_out, sig)
    return q_out, sig
