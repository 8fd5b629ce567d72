"""VQF (Laidig & Seel 2023) as numba kernels: the filter of ``magenv/MagVQF-v0``, one array per filter state.

VQF splits the orientation into three parts, each estimated by its own loop
(sensor frame S, earth frame E, ENU; quaternions scalar first, sensor → earth):

* **strapdown integration** (paper §3.1, eq. 4): the gyro rate, minus the bias
  estimate b̂, is integrated into ``gyr_q`` = q(S_t → I_t), the inertial
  frame I drifting with the gyro errors: q ← q ⊗ [cos(‖ω‖T_s/2), sin(‖ω‖T_s/2)·ω/‖ω‖];
* **inclination correction** (§3.2, eqs. 6–9): the accelerometer, rotated into
  I and low-passed there by a second-order Butterworth filter of time constant
  τ_acc (eq. 7: the low-pass in the almost-inertial frame removes the
  acceleration of motion, not the gravity), is rotated into the 6D earth
  frame E_i by ``acc_q`` and tilt-corrected in one step: ``acc_q`` ←
  q([0, a_y, −a_x]/…) ⊗ ``acc_q`` (the smallest rotation taking the low-passed
  acceleration to vertical). q6D = ``acc_q`` ⊗ ``gyr_q``;
* **heading correction** (§3.4, eqs. 27–30): the magnetometer, rotated into
  E_i with q6D, gives the disagreement angle e = atan2(m_E, m_N) − δ, and the
  heading offset δ of the 9D estimate follows it with a first-order step
  δ ← δ + k·e, k = 1 − exp(−T_s/τ_mag) (eq. 30). q9D = q_z(δ) ⊗ q6D.

Gyro bias (§3.3, eqs. 10–26): a three-state Kalman filter on b̂ whose
measurement is, in motion, the inclination correction the accelerometer asks
for as an angular rate, mapped back through the low-passed rotation matrix
(eqs. 18–21; the vertical axis weakly observed, weight ``bias_vertical_forgetting_factor``)
and, at rest, the low-passed gyro itself (eqs. 22–26); its covariance grows
by V each sample (``bias_forgetting_time``). Rest is detected where the
deviation of gyro and accelerometer from their low-passed values stays below
thresholds for ``rest_min_t`` seconds (eqs. 22–23).

Magnetic disturbance (§3.5, eqs. 31–36): the field's norm and dip in E_i,
low-passed with τ = ``mag_current_tau``, are compared with a reference
(learned slowly while undisturbed); a sample off by more than
``mag_norm_th`` (relative) or ``mag_dip_th`` (°) is disturbed. While
disturbed, k = 0 for at most ``mag_max_rejection_time`` seconds of
rejection (then k / ``mag_rejection_factor``); a new field steady for
``mag_new_time`` seconds of motion (``mag_new_first_time`` for the first) is
accepted as the reference. Until t exceeds τ_mag, k is at least 1/N at the
N-th magnetometer sample (fast initial convergence: the first sample aligns
the heading).

Readings where the paper leaves implementation choices open, taken as the
authors' reference implementation (the ``vqf`` package) has them, so that
this kernel and that one agree to rounding (``tests/test_filters_vqf.py``):
each Butterworth low-pass starts as the running mean of its inputs until τ
has passed, then continues from the steady state of that mean; its
coefficients from the bilinear transform with f_c = √2/(2πτ) (a pass-through
where τ < T_s/2); the bias update's 3×3 inverse by the adjugate (zero where
|det| ≤ ε); all-zero accelerometer or magnetometer samples are skipped.

**Trust.** The magnetometer gain of each sample is k = 1 − exp(−T_s/τ) with
τ = τ(u) (:func:`tau_of_trust`) for a trust u ∈ [0, 1] chosen from outside:
k(u) = u·k₁ with k₁ = 1 − exp(−T_s/τ_mag), τ(1) = τ_mag, τ(0) = −1 s (k = 0:
the magnetometer is ignored exactly). τ(u) also decides when the initial
convergence ends (N·T_s > τ(u)), as VQF's own ``setTauMag`` does.

**Layout.** Parameters and state are each one float64 vector whose fields are
named once (:data:`PARAMS`, :data:`STATE`; kernels index them as ``p[P.ts]``,
``s[S.delta]``), so that N filters are an (N, len) array, a fork of a filter
(the oracle's look-ahead) is an array copy, and nothing in the sample loop
allocates. :func:`step` is the one per-sample kernel; :func:`run` fuses a run
of samples at given trusts; :class:`VQFFilter` runs whole trials offline.
"""

from __future__ import annotations

import math
from collections import namedtuple
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
from numba import njit

from magenv.checks import check_bool, check_number
from magenv.filters.linalg import clip

EPS = float(np.finfo(float).eps)
DEG = math.pi / 180.0  # rad per degree
TAU_DISABLED = -1.0  # s: a negative τ gives the gain 0 (the magnetometer ignored)


class Layout:
    """Named fields of one float64 vector: ``ix`` (a namedtuple of offsets numba reads as constants), sizes."""

    def __init__(self, *spec: tuple[str, int, str]):
        self.names = tuple(n for n, _, _ in spec)
        self.sizes = {n: int(k) for n, k, _ in spec}
        self.meaning = {n: m for n, _, m in spec}
        sizes = [int(k) for _, k, _ in spec]
        self.size = sum(sizes)
        names = [n for n, _, _ in spec]
        offsets = np.cumsum([0, *sizes[:-1]]).tolist()
        self.ix: Any = namedtuple("LayoutIndex", names)(*offsets)

    def view(self, vec: np.ndarray) -> dict[str, np.ndarray | float]:
        """The fields of ``vec`` by name (scalars as floats, longer fields as copies)."""
        out: dict[str, np.ndarray | float] = {}
        for name in self.names:
            off, k = int(getattr(self.ix, name)), self.sizes[name]
            out[name] = float(vec[off]) if k == 1 else vec[off : off + k].copy()
        return out


# A low-pass's state (``lp_*``: 2 entries per channel, VQF's layout): during its first τ seconds entry 0 is NaN,
# entry 1 counts the samples and entries 2… hold the running sums; then the filter's two delay values per channel.
STATE = Layout(
    ("gyr_q", 4, "q(S → I): strapdown integration of the de-biased gyro (eq. 4)"),
    ("acc_q", 4, "q(I → E_i): inclination correction (eqs. 6–9)"),
    ("delta", 1, "δ, rad: heading of E (9D) relative to E_i (6D) (eq. 30)"),
    ("rest", 1, "1 while rest is detected (eqs. 22–23)"),
    ("mag_dist", 1, "1 while a magnetic disturbance is detected (eqs. 31–33)"),
    ("acc_lp_last", 3, "the low-passed accelerometer in I, m/s² (eq. 7)"),
    ("lp_acc", 6, "its low-pass state"),
    ("acc_corr_rate", 1, "angular rate of the last inclination correction, rad/s"),
    ("k_mag_init", 1, "1/N of the initial convergence (0 once over)"),
    ("dis_angle", 1, "e, rad: the last disagreement angle (eq. 29)"),
    ("mag_corr_rate", 1, "angular rate of the last heading correction, rad/s"),
    ("bias", 3, "b̂, rad/s: gyro bias estimate"),
    ("bias_p", 9, "P (3×3 row-major), (0.01 °/s)²: its covariance"),
    ("lp_motion_r", 18, "low-pass state of the rotation matrix of q6D (eq. 19)"),
    ("lp_motion_b", 4, "low-pass state of (R b̂)_xy (eq. 20)"),
    ("rest_sq_dev", 2, "squared deviations of gyro ((rad/s)²) and accelerometer ((m/s²)²) from their low-pass"),
    ("rest_t", 1, "s at rest so far"),
    ("rest_gyr_last", 3, "the low-passed gyro, rad/s"),
    ("lp_rest_gyr", 6, "its low-pass state"),
    ("rest_acc_last", 3, "the low-passed accelerometer (sensor frame), m/s²"),
    ("lp_rest_acc", 6, "its low-pass state"),
    ("ref_norm", 1, "accepted reference field norm (0: none yet), the magnetometer's unit"),
    ("ref_dip", 1, "accepted reference dip, rad"),
    ("undisturbed_t", 1, "s undisturbed so far"),
    ("reject_t", 1, "s of rejection budget used"),
    ("cand_norm", 1, "candidate new field norm (−1: none)"),
    ("cand_dip", 1, "candidate new field dip, rad"),
    ("cand_t", 1, "s in motion the candidate has been steady"),
    ("norm_dip", 2, "low-passed norm and dip (rad) of the field in E_i"),
    ("lp_norm_dip", 4, "their low-pass state"),
)
S: Any = STATE.ix

# The Butterworth coefficients of a low-pass (``*_lp``: b0, b1, b2, a1, a2) and every derived constant.
PARAMS = Layout(
    ("ts", 1, "T_s, s: sample interval"),
    ("tau_acc", 1, "τ_acc, s"),
    ("tau_mag", 1, "τ_mag, s (the gain at trust 1)"),
    ("k_mag", 1, "k₁ = 1 − exp(−T_s/τ_mag)"),
    ("acc_lp", 5, "low-pass of τ_acc"),
    ("motion_bias", 1, "1: bias estimation in motion"),
    ("rest_bias", 1, "1: bias estimation at rest"),
    ("mag_rejection", 1, "1: magnetic disturbance detection and rejection"),
    ("bias_p0", 1, "initial bias variance, (0.01 °/s)²"),
    ("bias_v", 1, "bias variance added per sample"),
    ("bias_motion_w", 1, "measurement variance of the motion update"),
    ("bias_vertical_w", 1, "… of its vertical axis"),
    ("bias_rest_w", 1, "measurement variance of the rest update"),
    ("bias_clip", 1, "rad/s: bias and its innovations clipped to ±"),
    ("rest_lp", 5, "low-pass of the rest detection (τ = rest_filter_tau)"),
    ("rest_tau", 1, "rest_filter_tau, s"),
    ("rest_th_gyr_sq", 1, "(rad/s)²"),
    ("rest_th_acc_sq", 1, "(m/s²)²"),
    ("rest_min_t", 1, "s"),
    ("mag_current_tau", 1, "s (≤ 0: no low-pass of norm and dip)"),
    ("norm_dip_lp", 5, "low-pass of mag_current_tau"),
    ("k_mag_ref", 1, "gain of the reference update (τ = mag_ref_tau)"),
    ("mag_norm_th", 1, "relative"),
    ("mag_dip_th", 1, "rad"),
    ("mag_new_time", 1, "s"),
    ("mag_new_first_time", 1, "s"),
    ("mag_new_min_gyr", 1, "rad/s"),
    ("mag_min_undisturbed_time", 1, "s"),
    ("mag_max_rejection_time", 1, "s"),
    ("mag_rejection_factor", 1, "–"),
)
P: Any = PARAMS.ix


@dataclass(frozen=True)
class Options:
    """VQF's parameters (the ``vqf`` package's ``VQFParams``, its defaults; units as there)."""

    tau_acc: float = 3.0  # s
    tau_mag: float = 9.0  # s
    motion_bias: bool = True  # motionBiasEstEnabled
    rest_bias: bool = True  # restBiasEstEnabled
    mag_rejection: bool = True  # magDistRejectionEnabled
    bias_sigma_init: float = 0.5  # °/s
    bias_forgetting_time: float = 100.0  # s
    bias_clip: float = 2.0  # °/s
    bias_sigma_motion: float = 0.1  # °/s
    bias_vertical_forgetting_factor: float = 0.0001
    bias_sigma_rest: float = 0.03  # °/s
    rest_min_t: float = 1.5  # s
    rest_filter_tau: float = 0.5  # s
    rest_th_gyr: float = 2.0  # °/s
    rest_th_acc: float = 0.5  # m/s²
    mag_current_tau: float = 0.05  # s
    mag_ref_tau: float = 20.0  # s
    mag_norm_th: float = 0.1  # relative
    mag_dip_th: float = 10.0  # °
    mag_new_time: float = 20.0  # s
    mag_new_first_time: float = 5.0  # s
    mag_new_min_gyr: float = 20.0  # °/s
    mag_min_undisturbed_time: float = 0.5  # s
    mag_max_rejection_time: float = 60.0  # s
    mag_rejection_factor: float = 2.0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if f.type == "bool":
                check_bool(f.name, v)
            else:
                # the rejection's neutral setting uses a negative time (never reject)
                lo = -1e9 if f.name == "mag_max_rejection_time" else 0.0
                check_number(f.name, v, lo, 1e9)
        for name in ("tau_acc", "tau_mag", "rest_filter_tau"):
            check_number(name, getattr(self, name), 0.0, 1e9, lo_open=True)

    def cpp_kwargs(self) -> dict:
        """The same parameters as keyword arguments of the ``vqf`` package's ``vqf.VQF``."""
        names = {"motion_bias": "motionBiasEstEnabled", "rest_bias": "restBiasEstEnabled",
                 "mag_rejection": "magDistRejectionEnabled"}  # fmt: skip
        out = {}
        for key, value in asdict(self).items():
            head, *rest = key.split("_")
            out[names.get(key, head + "".join(w[:1].upper() + w[1:] for w in rest))] = value
        return out


def lowpass_coefficients(tau: float, ts: float) -> tuple[float, float, float, float, float]:
    """(b0, b1, b2, a1, a2) of the second-order Butterworth low-pass of time constant ``tau`` (s) at interval
    ``ts`` (s): cut-off f_c = √2/(2πτ), bilinear transform with C = tan(π f_c T_s); a pass-through where τ < T_s/2
    (f_c beyond 90 % of Nyquist)."""
    if tau < ts / 2:
        return 1.0, 0.0, 0.0, 0.0, 0.0
    fc = (math.sqrt(2.0) / (2.0 * math.pi)) / tau
    c = math.tan(math.pi * fc * ts)
    d = c * c + math.sqrt(2.0) * c + 1.0
    b0 = c * c / d
    return b0, 2.0 * b0, b0, 2.0 * (c * c - 1.0) / d, (1.0 - math.sqrt(2.0) * c + c * c) / d


def gain_from_tau(tau: float, ts: float) -> float:
    """First-order gain k = 1 − exp(−T_s/τ); k = 1 for τ = 0, k = 0 for τ < 0 (update disabled)."""
    if tau < 0.0:
        return 0.0
    if tau == 0.0:
        return 1.0
    return 1.0 - math.exp(-ts / tau)


def make_params(ts: float, options: Options | None = None) -> np.ndarray:
    """The parameter vector (:data:`PARAMS`) of VQF at sample interval ``ts`` (s) with ``options``."""
    o = options or Options()
    ts = check_number("ts", ts, 0.0, 10.0, lo_open=True)
    p = np.zeros(PARAMS.size)
    p[P.ts], p[P.tau_acc], p[P.tau_mag] = ts, o.tau_acc, o.tau_mag
    p[P.k_mag] = gain_from_tau(o.tau_mag, ts)
    p[P.acc_lp : P.acc_lp + 5] = lowpass_coefficients(o.tau_acc, ts)
    p[P.motion_bias], p[P.rest_bias], p[P.mag_rejection] = o.motion_bias, o.rest_bias, o.mag_rejection
    p[P.bias_p0] = (o.bias_sigma_init * 100.0) ** 2
    # the system noise raises the variance from 0 to (0.1 °/s)² in bias_forgetting_time
    bias_v = (0.1 * 100.0) ** 2 * ts / o.bias_forgetting_time
    p_motion = (o.bias_sigma_motion * 100.0) ** 2
    p[P.bias_v] = bias_v
    p[P.bias_motion_w] = p_motion**2 / bias_v + p_motion
    p[P.bias_vertical_w] = p[P.bias_motion_w] / max(o.bias_vertical_forgetting_factor, 1e-10)
    p_rest = (o.bias_sigma_rest * 100.0) ** 2
    p[P.bias_rest_w] = p_rest**2 / bias_v + p_rest
    p[P.bias_clip] = o.bias_clip * DEG
    p[P.rest_lp : P.rest_lp + 5] = lowpass_coefficients(o.rest_filter_tau, ts)
    p[P.rest_tau] = o.rest_filter_tau
    p[P.rest_th_gyr_sq] = (o.rest_th_gyr * DEG) * (o.rest_th_gyr * DEG)
    p[P.rest_th_acc_sq] = o.rest_th_acc * o.rest_th_acc
    p[P.rest_min_t] = o.rest_min_t
    p[P.mag_current_tau] = o.mag_current_tau
    if o.mag_current_tau > 0:
        p[P.norm_dip_lp : P.norm_dip_lp + 5] = lowpass_coefficients(o.mag_current_tau, ts)
    p[P.k_mag_ref] = gain_from_tau(o.mag_ref_tau, ts)
    p[P.mag_norm_th], p[P.mag_dip_th] = o.mag_norm_th, o.mag_dip_th * DEG
    p[P.mag_new_time], p[P.mag_new_first_time] = o.mag_new_time, o.mag_new_first_time
    p[P.mag_new_min_gyr] = o.mag_new_min_gyr * DEG
    p[P.mag_min_undisturbed_time] = o.mag_min_undisturbed_time
    p[P.mag_max_rejection_time], p[P.mag_rejection_factor] = o.mag_max_rejection_time, o.mag_rejection_factor
    return p


def init_state(p: np.ndarray) -> np.ndarray:
    """VQF's initial state (:data:`STATE`): identity orientation, δ = 0, no bias (σ = bias_sigma_init), no field
    reference, disturbed until a field is accepted, every low-pass in its averaging start."""
    s = np.zeros(STATE.size)
    s[S.gyr_q] = s[S.acc_q] = 1.0
    s[S.mag_dist] = 1.0
    s[S.k_mag_init] = 1.0
    for name in STATE.names:
        if name.startswith("lp_"):
            off = getattr(S, name)
            s[off : off + STATE.sizes[name]] = np.nan
    s[S.bias_p] = s[S.bias_p + 4] = s[S.bias_p + 8] = p[P.bias_p0]
    s[S.reject_t] = p[P.mag_max_rejection_time]
    s[S.cand_norm] = -1.0
    return s


# ----------------------------------------------------------------- small pieces


@njit(cache=True, inline="always")
def _qmul(a0, a1, a2, a3, b0, b1, b2, b3):
    """Hamilton product a ⊗ b of two quaternions given by their components."""
    return (
        a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
        a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
        a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
        a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0,
    )


@njit(cache=True, inline="always")
def _rotate(q0, q1, q2, q3, v0, v1, v2):
    """q ⊗ [0, v] ⊗ q* for a unit quaternion q."""
    x = (1 - 2 * q2 * q2 - 2 * q3 * q3) * v0 + 2 * v1 * (q2 * q1 - q0 * q3) + 2 * v2 * (q0 * q2 + q3 * q1)
    y = 2 * v0 * (q0 * q3 + q2 * q1) + v1 * (1 - 2 * q1 * q1 - 2 * q3 * q3) + 2 * v2 * (q2 * q3 - q1 * q0)
    z = 2 * v0 * (q3 * q1 - q0 * q2) + 2 * v1 * (q0 * q1 + q3 * q2) + v2 * (1 - 2 * q1 * q1 - 2 * q2 * q2)
    return x, y, z


@njit(cache=True, inline="always")
def _normalize(v, off, k):
    """v[off:off + k] scaled to unit norm in place (left alone if its norm is below ε)."""
    acc = 0.0
    for i in range(k):
        acc += v[off + i] * v[off + i]
    n = np.sqrt(acc)
    if n >= EPS:
        for i in range(k):
            v[off + i] /= n


@njit(cache=True, inline="always")
def quat6d(s):
    """q6D = acc_q ⊗ gyr_q (sensor → E_i), as a tuple."""
    a, g = S.acc_q, S.gyr_q
    return _qmul(s[a], s[a + 1], s[a + 2], s[a + 3], s[g], s[g + 1], s[g + 2], s[g + 3])


@njit(cache=True, inline="always")
def quat9d(s):
    """q9D = [cos(δ/2), 0, 0, sin(δ/2)] ⊗ q6D (sensor → ENU), as a tuple."""
    w, x, y, z = quat6d(s)
    c, sn = np.cos(s[S.delta] / 2), np.sin(s[S.delta] / 2)
    return c * w - sn * z, c * x - sn * y, c * y + sn * x, c * z + sn * w


@njit(cache=True)
def bias_sigma(p, s):
    """σ of the bias estimate, rad/s: the square root of an upper bound of P's largest eigenvalue (its largest
    absolute row sum, Gershgorin), at most bias_sigma_init."""
    b = S.bias_p
    top = 0.0
    for r in range(3):
        top = max(top, abs(s[b + 3 * r]) + abs(s[b + 3 * r + 1]) + abs(s[b + 3 * r + 2]))
    return np.sqrt(min(top, p[P.bias_p0])) * (np.pi / 100.0 / 180.0)


@njit(cache=True, inline="always")
def _lowpass(p, c, tau, s, lp, x, n, out):
    """One step of the low-pass with coefficients p[c:c + 5] and state s[lp:lp + 2n] on ``x[:n]`` → ``out[:n]``
    (``out`` may be ``x``). For its first τ seconds its output is the mean of its inputs; then it starts from the
    steady state of that mean."""
    if np.isnan(s[lp]):
        if np.isnan(s[lp + 1]):
            s[lp + 1] = 0.0
            for i in range(n):
                s[lp + 2 + i] = 0.0
        s[lp + 1] += 1.0
        for i in range(n):
            s[lp + 2 + i] += x[i]
            out[i] = s[lp + 2 + i] / s[lp + 1]
        if s[lp + 1] * p[P.ts] >= tau:
            b0, b2, a2 = p[c], p[c + 2], p[c + 4]
            for i in range(n):
                s[lp + 2 * i] = out[i] * (1.0 - b0)
                s[lp + 2 * i + 1] = out[i] * (b2 - a2)
        return
    b0, b1, b2, a1, a2 = p[c], p[c + 1], p[c + 2], p[c + 3], p[c + 4]
    for i in range(n):
        xi = x[i]
        y = b0 * xi + s[lp + 2 * i]
        s[lp + 2 * i] = b1 * xi - a1 * y + s[lp + 2 * i + 1]
        s[lp + 2 * i + 1] = b2 * xi - a2 * y
        out[i] = y


# scratch rows of the work vector (:func:`work`): low-pass inputs and outputs, the rotation matrix, free rows
W_X, W_R, W_E = 0, 9, 18
W_SIZE = 24


def work() -> np.ndarray:
    """A scratch vector for :func:`step` (one per caller; nothing in the sample loop allocates)."""
    return np.zeros(W_SIZE)


@njit(cache=True, inline="always")
def _mm(a, b):
    """a·b of 3×3 row-major 9-tuples, each entry summed left to right."""
    return (
        a[0] * b[0] + a[1] * b[3] + a[2] * b[6], a[0] * b[1] + a[1] * b[4] + a[2] * b[7],
        a[0] * b[2] + a[1] * b[5] + a[2] * b[8], a[3] * b[0] + a[4] * b[3] + a[5] * b[6],
        a[3] * b[1] + a[4] * b[4] + a[5] * b[7], a[3] * b[2] + a[4] * b[5] + a[5] * b[8],
        a[6] * b[0] + a[7] * b[3] + a[8] * b[6], a[6] * b[1] + a[7] * b[4] + a[8] * b[7],
        a[6] * b[2] + a[7] * b[5] + a[8] * b[8],
    )  # fmt: skip


@njit(cache=True, inline="always")
def _transpose(a):
    return a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8]


@njit(cache=True, inline="always")
def _inverse3(m):
    """The inverse of a 3×3 row-major 9-tuple by the adjugate; all zeros where |det| ≤ ε."""
    a, b, c, d, e, f, g, h, i = m
    aa, dd, gg = e * i - f * h, c * h - b * i, b * f - c * e
    bb, ee, hh = f * g - d * i, a * i - c * g, c * d - a * f
    cc, ff, ii = d * h - e * g, b * g - a * h, a * e - b * d
    det = a * aa + b * bb + c * cc
    if -EPS <= det <= EPS:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return aa / det, dd / det, gg / det, bb / det, ee / det, hh / det, cc / det, ff / det, ii / det


# ----------------------------------------------------------------- the three updates


@njit(cache=True, inline="always")
def _update_gyr(p, s, w, g0, g1, g2):
    """Rest detection on the gyro, then the strapdown step with the de-biased rate (eq. 4)."""
    if p[P.rest_bias] or p[P.mag_rejection]:
        w[W_X], w[W_X + 1], w[W_X + 2] = g0, g1, g2
        _lowpass(p, P.rest_lp, p[P.rest_tau], s, S.lp_rest_gyr, w, 3, w[W_X + 3 :])
        lp0, lp1, lp2 = w[W_X + 3], w[W_X + 4], w[W_X + 5]
        s[S.rest_gyr_last], s[S.rest_gyr_last + 1], s[S.rest_gyr_last + 2] = lp0, lp1, lp2
        dev = (g0 - lp0) * (g0 - lp0) + (g1 - lp1) * (g1 - lp1) + (g2 - lp2) * (g2 - lp2)
        s[S.rest_sq_dev] = dev
        lim = p[P.bias_clip]
        if dev >= p[P.rest_th_gyr_sq] or abs(lp0) > lim or abs(lp1) > lim or abs(lp2) > lim:
            s[S.rest_t] = 0.0
            s[S.rest] = 0.0
    x, y, z = g0 - s[S.bias], g1 - s[S.bias + 1], g2 - s[S.bias + 2]
    norm = np.sqrt(x * x + y * y + z * z)
    if norm > EPS:
        angle = norm * p[P.ts]
        c, sn = np.cos(angle / 2), np.sin(angle / 2) / norm
        q = S.gyr_q
        s[q], s[q + 1], s[q + 2], s[q + 3] = _qmul(s[q], s[q + 1], s[q + 2], s[q + 3], c, sn * x, sn * y, sn * z)
        _normalize(s, q, 4)


@njit(cache=True, inline="always")
def _update_acc(p, s, w, a0, a1, a2):
    """Rest detection on the accelerometer, the inclination correction (eqs. 6–9) and the bias update (eqs.
    10–26). An all-zero sample is skipped."""
    if a0 == 0.0 and a1 == 0.0 and a2 == 0.0:
        return
    ts = p[P.ts]
    if p[P.rest_bias]:
        w[W_X], w[W_X + 1], w[W_X + 2] = a0, a1, a2
        _lowpass(p, P.rest_lp, p[P.rest_tau], s, S.lp_rest_acc, w, 3, w[W_X + 3 :])
        lp0, lp1, lp2 = w[W_X + 3], w[W_X + 4], w[W_X + 5]
        s[S.rest_acc_last], s[S.rest_acc_last + 1], s[S.rest_acc_last + 2] = lp0, lp1, lp2
        dev = (a0 - lp0) * (a0 - lp0) + (a1 - lp1) * (a1 - lp1) + (a2 - lp2) * (a2 - lp2)
        s[S.rest_sq_dev + 1] = dev
        if dev >= p[P.rest_th_acc_sq]:
            s[S.rest_t] = 0.0
            s[S.rest] = 0.0
        else:
            s[S.rest_t] += ts
            if s[S.rest_t] >= p[P.rest_min_t]:
                s[S.rest] = 1.0
    g = S.gyr_q
    w[W_X], w[W_X + 1], w[W_X + 2] = _rotate(s[g], s[g + 1], s[g + 2], s[g + 3], a0, a1, a2)  # into I
    _lowpass(p, P.acc_lp, p[P.tau_acc], s, S.lp_acc, w, 3, w[W_X + 3 :])  # eq. 7
    la = S.acc_lp_last
    s[la], s[la + 1], s[la + 2] = w[W_X + 3], w[W_X + 4], w[W_X + 5]
    q = S.acc_q
    w[W_X], w[W_X + 1], w[W_X + 2] = _rotate(s[q], s[q + 1], s[q + 2], s[q + 3], s[la], s[la + 1], s[la + 2])
    _normalize(w, W_X, 3)
    e0, e1, e2 = w[W_X], w[W_X + 1], w[W_X + 2]  # the low-passed acceleration in E_i, unit
    qw = np.sqrt((e2 + 1) / 2)  # eq. 8: the tilt correction taking it to vertical
    if qw > 1e-6:
        c0, c1, c2 = qw, 0.5 * e1 / qw, -0.5 * e0 / qw
    else:  # within 1e-4° of upside down
        c0, c1, c2 = 0.0, 1.0, 0.0
    s[q], s[q + 1], s[q + 2], s[q + 3] = _qmul(c0, c1, c2, 0.0, s[q], s[q + 1], s[q + 2], s[q + 3])
    _normalize(s, q, 4)
    s[S.acc_corr_rate] = np.arccos(e2) / ts
    if p[P.motion_bias] or p[P.rest_bias]:
        _update_bias(p, s, w, e0, e1)


@njit(cache=True, inline="always")
def _update_bias(p, s, w, e0, e1):
    """The bias Kalman filter (eqs. 10–26): at rest the measurement is the low-passed gyro (eq. 24), in motion
    the inclination correction the low-passed accelerometer (e0, e1: its unit x, y in E_i) asks for, as a rate,
    through the low-passed rotation matrix (eqs. 18–21)."""
    ts, lim, b = p[P.ts], p[P.bias_clip], S.bias
    q0, q1, q2, q3 = quat6d(s)
    r = W_R  # R of q6D, then low-passed (eq. 19)
    w[r] = 1 - 2 * q2 * q2 - 2 * q3 * q3
    w[r + 1] = 2 * (q2 * q1 - q0 * q3)
    w[r + 2] = 2 * (q0 * q2 + q3 * q1)
    w[r + 3] = 2 * (q0 * q3 + q2 * q1)
    w[r + 4] = 1 - 2 * q1 * q1 - 2 * q3 * q3
    w[r + 5] = 2 * (q2 * q3 - q1 * q0)
    w[r + 6] = 2 * (q3 * q1 - q0 * q2)
    w[r + 7] = 2 * (q0 * q1 + q3 * q2)
    w[r + 8] = 1 - 2 * q1 * q1 - 2 * q2 * q2
    bx, by, bz = s[b], s[b + 1], s[b + 2]
    w[W_E] = w[r] * bx + w[r + 1] * by + w[r + 2] * bz  # (R b̂)_xy, low-passed (eq. 20)
    w[W_E + 1] = w[r + 3] * bx + w[r + 4] * by + w[r + 5] * bz
    _lowpass(p, P.acc_lp, p[P.tau_acc], s, S.lp_motion_r, w[r:], 9, w[r:])
    _lowpass(p, P.acc_lp, p[P.tau_acc], s, S.lp_motion_b, w[W_E:], 2, w[W_E:])
    update = True
    if s[S.rest] and p[P.rest_bias]:  # eq. 24
        g = S.rest_gyr_last
        y0, y1, y2 = s[g] - bx, s[g + 1] - by, s[g + 2] - bz
        for k in range(9):
            w[r + k] = 0.0
        w[r] = w[r + 4] = w[r + 8] = 1.0
        wx = wy = wz = p[P.bias_rest_w]
    elif p[P.motion_bias]:  # eq. 21
        y0 = -e1 / ts + w[W_E] - w[r] * bx - w[r + 1] * by - w[r + 2] * bz
        y1 = e0 / ts + w[W_E + 1] - w[r + 3] * bx - w[r + 4] * by - w[r + 5] * bz
        y2 = -w[r + 6] * bx - w[r + 7] * by - w[r + 8] * bz
        wx = wy = p[P.bias_motion_w]
        wz = p[P.bias_vertical_w]
    else:
        update = False
    bp = S.bias_p
    for d in range(3):  # P ← P + V, up to P0, also without a measurement
        if s[bp + 4 * d] < p[P.bias_p0]:
            s[bp + 4 * d] += p[P.bias_v]
    if not update:
        return
    y0, y1, y2 = clip(y0, -lim, lim), clip(y1, -lim, lim), clip(y2, -lim, lim)
    rm = (w[r], w[r + 1], w[r + 2], w[r + 3], w[r + 4], w[r + 5], w[r + 6], w[r + 7], w[r + 8])
    pm = (s[bp], s[bp + 1], s[bp + 2], s[bp + 3], s[bp + 4], s[bp + 5], s[bp + 6], s[bp + 7], s[bp + 8])
    k = _mm(rm, _mm(pm, _transpose(rm)))  # R P Rᵀ
    k = (k[0] + wx, k[1], k[2], k[3], k[4] + wy, k[5], k[6], k[7], k[8] + wz)
    k = _mm(pm, _mm(_transpose(rm), _inverse3(k)))  # K = P Rᵀ (W + R P Rᵀ)⁻¹
    s[b] += k[0] * y0 + k[1] * y1 + k[2] * y2
    s[b + 1] += k[3] * y0 + k[4] * y1 + k[5] * y2
    s[b + 2] += k[6] * y0 + k[7] * y1 + k[8] * y2
    krp = _mm(_mm(k, rm), pm)  # K R P
    for i in range(9):
        s[bp + i] = pm[i] - krp[i]
    for i in range(3):
        s[b + i] = clip(s[b + i], -lim, lim)


@njit(cache=True, inline="always")
def field_step(p, s, m0, m1, m2):
    """The magnetometer sample's part of VQF that does not depend on the trust: disturbance detection,
    new-field acceptance and the rejection's bookkeeping (eqs. 31–36). Returns (ψ, d): ψ the heading of the field
    in E_i, atan2(east, north) (rad), and d the divisor of this sample's gain (1; ``mag_rejection_factor``
    beyond the rejection time; inf while rejected: gain 0); d = 0 for an all-zero sample, which is skipped.
    :func:`heading_step` then moves δ."""
    if m0 == 0.0 and m1 == 0.0 and m2 == 0.0:
        return 0.0, 0.0
    ts = p[P.ts]
    q0, q1, q2, q3 = quat6d(s)
    h0, h1, h2 = _rotate(q0, q1, q2, q3, m0, m1, m2)  # the field in E_i
    if p[P.mag_rejection]:
        nd = S.norm_dip
        norm = np.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
        s[nd], s[nd + 1] = norm, -np.arcsin(h2 / norm)
        if p[P.mag_current_tau] > 0:
            _lowpass(p, P.norm_dip_lp, p[P.mag_current_tau], s, S.lp_norm_dip, s[nd:], 2, s[nd:])
        th_n, th_d, k_ref = p[P.mag_norm_th], p[P.mag_dip_th], p[P.k_mag_ref]
        if abs(s[nd] - s[S.ref_norm]) < th_n * s[S.ref_norm] and abs(s[nd + 1] - s[S.ref_dip]) < th_d:
            s[S.undisturbed_t] += ts
            if s[S.undisturbed_t] >= p[P.mag_min_undisturbed_time]:
                s[S.mag_dist] = 0.0
                s[S.ref_norm] += k_ref * (s[nd] - s[S.ref_norm])
                s[S.ref_dip] += k_ref * (s[nd + 1] - s[S.ref_dip])
        else:
            s[S.undisturbed_t] = 0.0
            s[S.mag_dist] = 1.0
        if abs(s[nd] - s[S.cand_norm]) < th_n * s[S.cand_norm] and abs(s[nd + 1] - s[S.cand_dip]) < th_d:
            g = S.rest_gyr_last
            if np.sqrt(s[g] * s[g] + s[g + 1] * s[g + 1] + s[g + 2] * s[g + 2]) >= p[P.mag_new_min_gyr]:
                s[S.cand_t] += ts
            s[S.cand_norm] += k_ref * (s[nd] - s[S.cand_norm])
            s[S.cand_dip] += k_ref * (s[nd + 1] - s[S.cand_dip])
            if s[S.mag_dist] and (
                s[S.cand_t] >= p[P.mag_new_time] or (s[S.ref_norm] == 0.0 and s[S.cand_t] >= p[P.mag_new_first_time])
            ):
                s[S.ref_norm], s[S.ref_dip] = s[S.cand_norm], s[S.cand_dip]
                s[S.mag_dist] = 0.0
                s[S.undisturbed_t] = p[P.mag_min_undisturbed_time]
        else:
            s[S.cand_t] = 0.0
            s[S.cand_norm], s[S.cand_dip] = s[nd], s[nd + 1]
    divisor = 1.0
    if p[P.mag_rejection]:
        if s[S.mag_dist]:
            if s[S.reject_t] <= p[P.mag_max_rejection_time]:
                s[S.reject_t] += ts
                divisor = np.inf
            else:
                divisor = p[P.mag_rejection_factor]
        else:
            s[S.reject_t] = max(s[S.reject_t] - p[P.mag_rejection_factor] * ts, 0.0)
    return np.arctan2(h0, h1), divisor


@njit(cache=True, inline="always")
def heading_update(delta, init, psi, divisor, k, tau, ts):
    """(δ, 1/N, e) after the heading step of one sample (eqs. 29–30): e = ψ − δ wrapped to ±π, the gain
    k/``divisor`` raised to at least 1/N = ``init`` while the initial convergence lasts (it ends once
    1/N·τ < T_s), δ ← δ + gain·e wrapped to ±π."""
    e = psi - delta
    if e > np.pi:
        e -= 2 * np.pi
    elif e < -np.pi:
        e += 2 * np.pi
    k = k / divisor
    if init != 0.0:
        if k < init:
            k = init
        init = init / (init + 1)
        if init * tau < ts:
            init = 0.0
    d = delta + k * e
    if d > np.pi:
        d -= 2 * np.pi
    elif d < -np.pi:
        d += 2 * np.pi
    return d, init, e, k


@njit(cache=True, inline="always")
def heading_step(p, s, psi, divisor, k, tau):
    """The trust's part of a magnetometer sample: :func:`heading_update` on the state (``divisor`` 0: no
    sample, nothing moves)."""
    if divisor == 0.0:
        return
    ts = p[P.ts]
    d, init, e, k = heading_update(s[S.delta], s[S.k_mag_init], psi, divisor, k, tau, ts)
    s[S.delta], s[S.k_mag_init], s[S.dis_angle] = d, init, e
    s[S.mag_corr_rate] = k * e / ts


@njit(cache=True, inline="always")
def six_d_step(p, s, w, gyr, acc):
    """The gyroscope and accelerometer part of a sample (rest, strapdown, inclination, bias): q6D."""
    _update_gyr(p, s, w, gyr[0], gyr[1], gyr[2])
    _update_acc(p, s, w, acc[0], acc[1], acc[2])


@njit(cache=True)
def step(p, s, w, gyr, acc, mag, k, tau):
    """Fuse one sample (gyr rad/s, acc m/s², mag in any unit; (3,) each) in place on ``s``, the heading step
    with gain ``k`` and time constant ``tau`` (s) (:func:`trust_gain`); ``w`` a scratch vector (:func:`work`).

    Only δ and the initial convergence depend on the trust (:func:`heading_step`); everything else —
    orientation q6D, bias, rest, disturbance detection — is :func:`six_d_step` and :func:`field_step`, the
    same whatever the trust (what the oracle's look-ahead uses to roll many trusts at the cost of one)."""
    six_d_step(p, s, w, gyr, acc)
    psi, divisor = field_step(p, s, mag[0], mag[1], mag[2])
    heading_step(p, s, psi, divisor, k, tau)


@njit(cache=True)
def tau_of_trust(u, tau_mag, ts):
    """τ (s) whose gain is u·k₁, k₁ = 1 − exp(−T_s/τ_mag): τ_mag at u ≥ 1, −1 s (gain 0) at u ≤ 0, else
    −T_s / ln(1 − u·k₁)."""
    if u >= 1.0:
        return tau_mag
    if u <= 0.0:
        return TAU_DISABLED
    k1 = 1.0 if tau_mag == 0.0 else -np.expm1(-ts / tau_mag)
    return -ts / np.log1p(-u * k1)


@njit(cache=True)
def trust_gain(p, u):
    """(k, τ) of trust u: the gain 1 − exp(−T_s/τ(u)) (0 for τ < 0, 1 for τ = 0) and τ(u) (:func:`tau_of_trust`)."""
    ts = p[P.ts]
    tau = tau_of_trust(u, p[P.tau_mag], ts)
    if tau < 0.0:
        return 0.0, tau
    if tau == 0.0:
        return 1.0, tau
    return 1.0 - np.exp(-ts / tau), tau


@njit(cache=True)
def run(p, s, w, gyr, acc, mag, u, q9, q6, dist, rest, delta):
    """Fuse rows 0…n−1 of gyr, acc, mag (n, 3) with trust ``u[i]`` (n,) each, in place on ``s``; writes per sample
    q9D and q6D (n, 4), the disturbance and rest flags and δ (n,)."""
    u_now, k, tau = -1.0, 0.0, 0.0
    for i in range(gyr.shape[0]):
        if u[i] != u_now:
            u_now = u[i]
            k, tau = trust_gain(p, u_now)
        step(p, s, w, gyr[i], acc[i], mag[i], k, tau)
        q9[i, 0], q9[i, 1], q9[i, 2], q9[i, 3] = quat9d(s)
        q6[i, 0], q6[i, 1], q6[i, 2], q6[i, 3] = quat6d(s)
        dist[i], rest[i], delta[i] = s[S.mag_dist], s[S.rest], s[S.delta]


class VQFFilter:
    """VQF over whole arrays offline (the kernels above), with the options of :class:`Options` and a trust.

    ``run(gyr, acc, mag, ts, trust=1.0)`` → dict of arrays like the ``vqf`` package's ``updateBatch``:
    ``quat9D``, ``quat6D`` (n, 4), ``delta`` (n,), ``magDistDetected``, ``restDetected`` (n,) bool; ``trust`` a
    number or an (n,) array in [0, 1] (1: VQF as published)."""

    def __init__(self, options: Options | None = None):
        self.options = options or Options()

    def run(self, gyr, acc, mag, ts: float, trust=1.0) -> dict[str, np.ndarray]:
        gyr, acc, mag = (np.ascontiguousarray(a, np.float64) for a in (gyr, acc, mag))
        n = gyr.shape[0]
        if gyr.shape != (n, 3) or acc.shape != (n, 3) or mag.shape != (n, 3):
            raise ValueError(f"gyr, acc and mag must be (n, 3) arrays of one n, got {gyr.shape}, {acc.shape}, "
                             f"{mag.shape}")  # fmt: skip
        u = np.broadcast_to(np.asarray(trust, np.float64), (n,)).copy()
        if not np.all((u >= 0.0) & (u <= 1.0)):
            raise ValueError("trust must lie in [0, 1]")
        p = make_params(ts, self.options)
        s = init_state(p)
        q9, q6 = np.empty((n, 4)), np.empty((n, 4))
        dist, rest, delta = np.empty(n), np.empty(n), np.empty(n)
        run(p, s, work(), gyr, acc, mag, u, q9, q6, dist, rest, delta)
        return {"quat9D": q9, "quat6D": q6, "delta": delta, "magDistDetected": dist.astype(bool),
                "restDetected": rest.astype(bool)}  # fmt: skip
