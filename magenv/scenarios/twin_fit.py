"""A recording's sensor errors and magnetic disturbance, fitted against its own optical truth.

Everything here is fitted once per recording (:func:`fit_recording`) and stored as a :class:`TwinFit` of
plain arrays (saved by ``magenv.scenarios.twin`` as ``.npz``, read back without pickles). The truth used is
:class:`Motion`: the gap-bridged, smoothed optical orientation ``qs`` (``magenv.sim.truth_motion``); only
samples where the optical truth is real (not bridged) enter a fit.

Gyroscope (:func:`fit_gyro`), over windows of T = 1 s (half overlapping): the real gyro, rest bias b0
removed, is integrated from qs[s] over the window and compared with qs[s+W]; the sensor-frame error
rotation e of each window is regressed, per axis, on

    e ≈ δb·T + K·θ + L_g·(ω_end − R(θ)ᵀ ω_start)/rate                                         (1)

(θ the true rotation vector over the window, K a 3×3 scale/misalignment, L_g the gyro's delay behind the
truth in samples, δb the mean bias change from rest). Each window's residual bias is median filtered
into a bias trajectory b(t) (rad/s), b0 added back.

Magnetometer (:func:`fit_mag`), on new (not held) samples whose residual is below 4 µT:

    m(t) = M·R(qs(t − L_m))ᵀ·h_E + o                                                           (2)

h_E (µT, the truth's ENU frame, with its east component), M (3×3, residual soft iron and scale, ridge
pulled towards I), o (µT, hard iron), L_m (samples, grid 2…6 by 0.25 with a parabola refinement).
Alternating least squares (M, o | h_E); gauge |h_E| = the median |m| at rest. Noise: the per-axis std at
rest over new samples. The hold mask is the recording's own (a sample equal to the one before).

Disturbance (``kind``): ``"attached"`` — a magnet fixed to the board, a constant sensor-frame offset d
(median residual of (2) over :func:`attached_interval`) times a profile s(t) ∈ [0, 1] (the residual's
projection on d, 0.3 s smoothed; 1 from 3 s after the interval's start to 3 s before its end);
``"dipole"`` — a magnet at rest in the room, a point dipole (position p_m, m; moment μ, A·m², ENU) fitted
to the earth-frame residual R(q)·M⁻¹(m − o) − h_E near the samples where it exceeds 3 µT (a grid of
positions, each a linear least-squares problem in μ, then a robust nonlinear refinement); ``"none"``.
:func:`choose_disturbance` picks one from the data (see there).

Accelerometer (:func:`fit_acc`): a = R(q)ᵀ(p̈ + g e_up) + α × r + ω × (ω × r) + b_a, lever arm r (sensor
frame, m, from the optical marker to the IMU) and bias b_a by linear least squares, delay L_a on a grid.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from magenv import quaternion as quat
from magenv.recordings import initial_rest
from magenv.sensor_stats import rest_autocorr
from magenv.sim import truth_motion as tm
from magenv.sim.magnet import dipole_field
from magenv.trial import Trial

#: Bump when a fit changes: cached fits of another version are not used.
FIT_VERSION = 1
#: Delay of the BROAD gyro behind the optical truth used to bridge the truth's gaps, samples.
BRIDGE_GYR_LAG = 1.17
DISTURBANCES = ("auto", "none", "attached", "dipole")


@dataclasses.dataclass(frozen=True)
class Motion:
    """Truth-derived motion every fit and every twin uses (``magenv.sim.truth_motion``)."""

    rate: float  # Hz
    qs: np.ndarray  # (N, 4) bridged, smoothed orientation, sensor → ENU
    bridged: np.ndarray  # (N,) bool: optical truth missing
    w: np.ndarray  # (N, 3) body rate of qs, rad/s
    pos: np.ndarray  # (N, 3) gap-filled marker position, m
    lin_acc: np.ndarray  # (N, 3) earth-frame p̈, m/s²
    rest: slice  # the initial rest (``magenv.recordings.initial_rest``)
    gyr_bias0: np.ndarray  # (3,) rest mean of the gyro, rad/s


def motion_of(rec: Trial, fc_quat: float = 30.0, fc_pos: float = 15.0) -> Motion:
    """The :class:`Motion` of recording ``rec`` (needs ``rec.truth["opt_pos"]``)."""
    if "opt_pos" not in rec.truth:
        raise ValueError(f"trial {rec.name!r} has no truth['opt_pos']: a twin needs a recording's optical position")
    rest = initial_rest(rec.gyr, rec.rate)
    b0 = rec.gyr[rest].mean(0)
    qb, bridged = tm.bridge_gaps(rec.q_true, rec.gyr, rec.rate, b0, BRIDGE_GYR_LAG)
    qs = tm.smooth_quat(qb, rec.rate, fc_quat)
    pos = rec.truth["opt_pos"]
    return Motion(
        rate=rec.rate,
        qs=qs,
        bridged=bridged,
        w=tm.body_rate(qs, rec.rate),
        pos=tm.fill_linear(pos),
        lin_acc=tm.linear_acc(pos, rec.rate, fc_pos),
        rest=rest,
        gyr_bias0=b0,
    )


@dataclasses.dataclass(frozen=True)
class TwinFit:
    """One recording's fitted sensor and disturbance model (module docstring; arrays and numbers only)."""

    n: int
    gyr_lag: float  # samples behind the truth
    gyr_K: np.ndarray  # (3, 3) scale / misalignment, ω_meas = (I + K) ω
    gyr_bias: np.ndarray  # (N, 3) bias trajectory, rad/s
    gyr_noise: np.ndarray  # (3,) white noise std at rest, rad/s
    mag_lag: float  # samples behind the truth
    mag_h_E: np.ndarray  # (3,) earth-frame field, µT
    mag_M: np.ndarray  # (3, 3)
    mag_o: np.ndarray  # (3,) µT
    mag_noise: np.ndarray  # (3,) std at rest over new samples, µT
    mag_rho1: float  # lag-1 autocorrelation of that noise (the colour check)
    mag_held: np.ndarray  # (N,) bool hold mask of the recording
    acc_lever: np.ndarray  # (3,) m, sensor frame
    acc_bias: np.ndarray  # (3,) m/s²
    acc_lag: float  # samples
    acc_noise: np.ndarray  # (3,) m/s²
    disturbance: str  # "none" | "attached" | "dipole"
    attached_offset: np.ndarray  # (3,) µT sensor frame (zeros unless attached)
    attached_profile: np.ndarray  # (N,) in [0, 1] (zeros unless attached)
    dipole_pos: np.ndarray  # (3,) m (NaN unless dipole)
    dipole_moment: np.ndarray  # (3,) A·m² ENU (NaN unless dipole)
    version: int = FIT_VERSION

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The fields as numpy arrays (``disturbance`` as a 0-d unicode array), for ``np.savez``."""
        return {f.name: np.asarray(getattr(self, f.name)) for f in dataclasses.fields(self)}

    @classmethod
    def from_arrays(cls, arrays) -> TwinFit:
        """Inverse of :meth:`to_arrays`; ValueError naming a missing field."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(cls):
            if f.name not in arrays:
                raise ValueError(f"twin fit file lacks the field {f.name!r}")
            v = np.asarray(arrays[f.name])
            out[f.name] = v.item() if v.ndim == 0 else v
        out["disturbance"] = str(out["disturbance"])
        for k in ("n", "version"):
            out[k] = int(out[k])
        return cls(**out)


# ---------------------------------------------------------------- gyroscope


def fit_gyro(rec: Trial, mo: Motion, window_s: float = 1.0):
    """(lag samples, K (3, 3), bias trajectory (N, 3) rad/s) by eq. (1) of the module docstring."""
    from scipy.signal import medfilt  # here: scipy.signal's import is ~40 MB, needed by twin fits only

    n, rate = rec.n, rec.rate
    W = int(round(window_s * rate))
    g = rec.gyr - mo.gyr_bias0
    rows, y, starts = [], [], []
    for s in range(0, n - W - 1, max(W // 2, 10)):
        e = s + W
        if mo.bridged[s] or mo.bridged[e]:
            continue
        q = mo.qs[s].copy()
        for k in range(s, e):
            q = quat.normalize1(quat.mul1(q, quat.from_rotvec1(0.5 * (g[k] + g[k + 1]) / rate)))
        err = quat.mul1(quat.conj1(q), mo.qs[e])
        d = quat.mul1(quat.conj1(mo.qs[s]), mo.qs[e])
        err, d = (err if err[0] >= 0 else -err), (d if d[0] >= 0 else -d)
        theta = quat.to_rotvec1(d)
        dlag = (g[e] - quat.rotate_inv1(d, g[s])) / rate
        ev = quat.to_rotvec1(err)
        for ax in range(3):
            r = np.zeros(13)
            r[ax] = window_s
            r[3 + 3 * ax : 6 + 3 * ax] = theta
            r[12] = dlag[ax]
            rows.append(r)
            y.append(ev[ax])
        starts.append(s)
    if len(starts) < 13:
        raise ValueError(f"recording {rec.name!r}: too little optical truth to fit the gyroscope")
    A, yv = np.array(rows), np.array(y)
    cf, *_ = np.linalg.lstsq(A, yv, rcond=None)
    res = (yv - A @ cf).reshape(-1, 3)
    per_window = res / window_s + cf[:3]  # rad/s, each window's bias change
    k = 9 if len(starts) > 20 else 3
    smooth = np.stack([medfilt(per_window[:, j], k) for j in range(3)], 1)
    centres = np.array(starts) + W // 2
    idx = np.arange(n)
    bias = mo.gyr_bias0 + np.stack([np.interp(idx, centres, smooth[:, j]) for j in range(3)], 1)
    return float(cf[12]), cf[3:12].reshape(3, 3), bias


# ---------------------------------------------------------------- magnetometer


def held_mask(x: np.ndarray) -> np.ndarray:
    """(N,) True where a row repeats the previous one exactly (sample-and-hold)."""
    x = np.asarray(x)
    return np.r_[False, np.all(x[1:] == x[:-1], axis=1)]


def mag_model(mo: Motion, h_E, M, o, lag: float) -> np.ndarray:
    """Eq. (2): M·R(qs(t − lag))ᵀ h_E + o at every sample, µT."""
    u = quat.rotate_inv(tm.delay_quat(mo.qs, lag), np.broadcast_to(h_E, (len(mo.qs), 3)))
    return u @ np.asarray(M).T + o


def _fit_iron(U, Y, ridge: float = 0.02, scale: float = 44.0):
    """Y ≈ U Mᵀ + o by least squares with ``ridge``·len(U) pseudo-rows pulling M towards I (decisive only
    where the orientations are not diverse, e.g. a translation-only recording)."""
    lam = np.sqrt(ridge * len(U)) * scale
    X = np.r_[np.c_[U, np.ones(len(U))], np.c_[lam * np.eye(3), np.zeros(3)]]
    cf, *_ = np.linalg.lstsq(X, np.r_[Y, lam * np.eye(3)], rcond=None)
    return cf[:3].T, cf[3]


def fit_mag(rec: Trial, mo: Motion, exclude=None, robust_ut: float = 4.0, iters: int = 4):
    """(lag samples, h_E, M, o) of eq. (2) on new samples (``exclude``: (N,) bool to leave out); each pass
    keeps the samples with a residual below ``robust_ut`` µT (or the better half, if that is fewer)."""
    n, Y = rec.n, rec.mag
    ok = ~held_mask(Y) & ~mo.bridged
    ok[:20] = ok[-20:] = False
    if exclude is not None:
        ok &= ~exclude
    m0 = np.median(np.linalg.norm(Y[mo.rest], axis=1))
    h0 = np.median(quat.rotate(mo.qs[mo.rest], Y[mo.rest]), axis=0)
    h0 *= m0 / np.linalg.norm(h0)

    def solve(lag, h):
        q = tm.delay_quat(mo.qs, lag)
        use = ok.copy()
        for _ in range(iters):
            M, o = _fit_iron(quat.rotate_inv(q, np.broadcast_to(h, (n, 3)))[use], Y[use])
            h = np.mean(quat.rotate(q[use], (Y[use] - o) @ np.linalg.inv(M).T), axis=0)
            h *= m0 / np.linalg.norm(h)
            r = Y - (quat.rotate_inv(q, np.broadcast_to(h, (n, 3))) @ M.T + o)
            rn = np.linalg.norm(r, axis=1)
            use = ok & (rn < max(robust_ut, float(np.median(rn[ok]))))  # at least half of the samples
        M, o = _fit_iron(quat.rotate_inv(q, np.broadcast_to(h, (n, 3)))[use], Y[use])
        r = Y - (quat.rotate_inv(q, np.broadcast_to(h, (n, 3))) @ M.T + o)
        return float(np.mean(np.sum(r[use] ** 2, 1))), h, M, o, use

    lags = np.arange(2.0, 6.01, 0.25)
    sols = [solve(lag, h0) for lag in lags]
    cost = np.array([s[0] for s in sols])
    j = int(np.argmin(cost))
    lag = float(lags[j])
    if 0 < j < len(lags) - 1:
        den = cost[j - 1] - 2 * cost[j] + cost[j + 1]
        if den > 0:
            lag += 0.5 * (lags[1] - lags[0]) * (cost[j - 1] - cost[j + 1]) / den
    _, h, M, o, _ = solve(lag, sols[j][1])
    return lag, h, M, o


# ---------------------------------------------------------------- disturbances


def attached_interval(rec: Trial, th_ut: float = 3.0, merge_s: float = 15.0, pad_s: float = 2.0):
    """Samples (a, b) from the first to the last time the 1 s-smoothed |‖m‖ − field_norm| exceeds ``th_ut``
    µT in the longest cluster of such runs (runs closer than ``merge_s`` s merged), padded by ``pad_s`` s;
    None where it never does."""
    dn = np.abs(np.linalg.norm(rec.mag, axis=1) - rec.field_norm)
    w = max(1, int(round(rec.rate)))
    runs = tm.true_runs(np.convolve(dn, np.ones(w) / w, mode="same") > th_ut)
    if not runs:
        return None
    clusters = [list(runs[0])]
    for a, b in runs[1:]:
        if a - clusters[-1][1] < merge_s * rec.rate:
            clusters[-1][1] = b
        else:
            clusters.append([a, b])
    a, b = max(clusters, key=lambda c: c[1] - c[0])
    pad = int(pad_s * rec.rate)
    return max(0, a - pad), min(rec.n, b + pad)


def attached_profile(resid: np.ndarray, offset: np.ndarray, interval, rate: float, smooth_s: float = 0.3):
    """s(t) ∈ [0, 1]: the residual's projection on ``offset``, smoothed, 1 inside the interval's core
    (3 s in from each end), 0 outside the interval."""
    n = len(resid)
    a, b = interval
    proj = resid @ offset / (offset @ offset)
    w = max(1, int(smooth_s * rate))
    proj = np.convolve(proj, np.ones(w) / w, mode="same")
    s = np.zeros(n)
    s[a:b] = np.clip(proj[a:b], 0.0, 1.0)
    edge = int(3 * rate)
    if b - a > 2 * edge:
        s[a + edge : b - edge] = 1.0
    return s


def earth_residual(rec: Trial, mo: Motion, lag, h_E, M, o):
    """(earth-frame residual R(q)·M⁻¹(m − o) − h_E (N, 3) µT, positions at the same delay (N, 3) m)."""
    q = tm.delay_quat(mo.qs, lag)
    r = quat.rotate(q, (rec.mag - o) @ np.linalg.inv(M).T) - h_E
    return r, tm.delay(mo.pos, lag)


def dipole_e(p: np.ndarray, p_m: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """Field (N, 3) µT at positions ``p`` (N, 3) m of a point dipole at ``p_m`` with moment ``mu`` (A·m², ENU)."""
    r = np.ascontiguousarray(p - p_m, float)
    return dipole_field(r, np.ascontiguousarray(np.broadcast_to(mu, r.shape), float))


def fit_dipole(rE: np.ndarray, p: np.ndarray, ok: np.ndarray, rate: float, thresh_ut: float = 3.0, pad_s: float = 1.0):
    """(p_m (3,) m, μ (3,) A·m²) of a point dipole at rest fitted to the earth-frame residual ``rE`` at
    positions ``p`` over the ``ok`` samples near those where |rE| > ``thresh_ut`` (module docstring)."""
    from scipy.optimize import least_squares  # here: scipy's import is large, needed by twin fits only

    rn = np.linalg.norm(rE, axis=1)
    strong = (rn > thresh_ut) & ok
    if strong.sum() < 10:
        raise ValueError("no magnet field to fit a dipole to (residual never above the threshold)")
    pad = int(pad_s * rate)
    idx = np.flatnonzero((np.convolve(strong.astype(float), np.ones(2 * pad + 1), mode="same") > 0) & ok)
    idx = idx[:: len(idx) // 20000 + 1]
    pi, ri = p[idx], rE[idx]
    top = np.flatnonzero(strong)[np.argsort(rn[strong])[-5:]]
    g = np.arange(-0.20, 0.2001, 0.04)
    grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    scored = []
    for c in p[top]:
        for pm in c + grid:
            if np.linalg.norm(pi - pm, axis=1).min() < 0.01:
                continue
            A = np.c_[np.stack([dipole_e(pi, pm, e).ravel() for e in np.eye(3)], 1), np.tile(np.eye(3), (len(pi), 1))]
            cf, *_ = np.linalg.lstsq(A, ri.ravel(), rcond=None)
            scored.append((float(np.sum((ri.ravel() - A @ cf) ** 2)), pm, cf))
    scored.sort(key=lambda z: z[0])

    def fun(x):
        return (dipole_e(pi, x[:3], x[3:6]) + x[6:9] - ri).ravel()

    sols = [least_squares(fun, np.r_[pm, cf], loss="soft_l1", f_scale=1.0, max_nfev=300) for _, pm, cf in scored[:5]]
    best = min(sols, key=lambda s: s.cost)
    return best.x[:3].copy(), best.x[3:6].copy()


def choose_disturbance(resid: np.ndarray, interval, rate: float, th_ut: float = 3.0, steady_ratio: float = 0.5) -> str:
    """The disturbance model of a recording from the sensor-frame residual ``resid`` (N, 3) µT of eq. (2)
    (fitted without ``interval``, the samples of :func:`attached_interval`):

    ``"none"`` where there is no interval, or where the 1 s-smoothed |resid| stays below ``th_ut`` over 90 %
    of it (the field's norm changed but eq. (2) explains it: a different spot of the room);
    ``"attached"`` where the residual there is steady (its RMS spread about its median below
    ``steady_ratio`` × |median|: the offset turns with the board); else ``"dipole"`` (a magnet at rest in the
    room: the offset depends on where the board is)."""
    if interval is None:
        return "none"
    a, b = interval
    w = max(1, int(round(rate)))
    rn = np.convolve(np.linalg.norm(resid, axis=1), np.ones(w) / w, mode="same")[a:b]
    if np.quantile(rn, 0.9) < th_ut:
        return "none"
    off = np.median(resid[a:b], axis=0)
    spread = np.sqrt(np.mean(np.sum((resid[a:b] - off) ** 2, 1)))
    return "attached" if spread < steady_ratio * np.linalg.norm(off) else "dipole"


# ---------------------------------------------------------------- accelerometer


def _cross_mats(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) matrices [v×]."""
    z = np.zeros((len(v), 3, 3))
    z[:, 0, 1], z[:, 0, 2], z[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    z[:, 1, 0], z[:, 2, 0], z[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return z


def acc_model(mo: Motion, lever, bias, lag: float) -> np.ndarray:
    """R(q)ᵀ(p̈ + g e_up) + α × r + ω × (ω × r) + b_a at every sample, all at delay ``lag`` samples, m/s²."""
    q, la, w = tm.delay_quat(mo.qs, lag), tm.delay(mo.lin_acc, lag), tm.delay(mo.w, lag)
    alpha = np.gradient(w, 1.0 / mo.rate, axis=0)
    return tm.specific_force(q, la) + np.cross(alpha, lever) + np.cross(w, np.cross(w, lever)) + bias


def fit_acc(rec: Trial, mo: Motion, lags=(0.0, 0.5, 1.0, 1.5, 2.0)):
    """(lever (3,) m, bias (3,) m/s², lag samples) of :func:`acc_model` by linear least squares per lag."""
    use = ~mo.bridged & rec.score_mask
    best: tuple[float, float, np.ndarray] | None = None
    for lag in lags:
        q, la, w = tm.delay_quat(mo.qs, lag), tm.delay(mo.lin_acc, lag), tm.delay(mo.w, lag)
        alpha = np.gradient(w, 1.0 / mo.rate, axis=0)
        Wx = _cross_mats(w[use])
        A = _cross_mats(alpha[use]) + Wx @ Wx
        A = np.concatenate([A, np.broadcast_to(np.eye(3), A.shape)], axis=2).reshape(-1, 6)
        y = (rec.acc[use] - tm.specific_force(q, la)[use]).ravel()
        cf, *_ = np.linalg.lstsq(A, y, rcond=None)
        c = float(np.mean((y - A @ cf) ** 2))
        if best is None or c < best[0]:
            best = (c, float(lag), cf)
    if best is None:
        raise ValueError("fit_acc needs at least one lag")
    _, lag, cf = best
    return cf[:3].copy(), cf[3:6].copy(), lag


# ---------------------------------------------------------------- everything


def fit_recording(rec: Trial, mo: Motion | None = None, disturbance: str = "auto") -> TwinFit:
    """The :class:`TwinFit` of recording ``rec`` (5–90 s; the dipole search is the slow part).

    ``disturbance``: ``"auto"`` (:func:`choose_disturbance`), or force ``"none"``, ``"attached"``, ``"dipole"``.
    """
    if disturbance not in DISTURBANCES:
        raise ValueError(f"disturbance must be one of {', '.join(DISTURBANCES)}, got {disturbance!r}")
    mo = mo or motion_of(rec)
    n = rec.n
    gyr_lag, K, gyr_bias = fit_gyro(rec, mo)
    interval = attached_interval(rec)
    lag, h, M, o = fit_mag(rec, mo)
    resid = rec.mag - mag_model(mo, h, M, o, lag)
    if choose_disturbance(resid, interval, rec.rate) != "none":  # refit without the disturbed samples
        disturbed = np.zeros(n, bool)
        disturbed[interval[0] : interval[1]] = True
        lag, h, M, o = fit_mag(rec, mo, exclude=disturbed)
        resid = rec.mag - mag_model(mo, h, M, o, lag)
    kind = choose_disturbance(resid, interval, rec.rate) if disturbance == "auto" else disturbance
    if kind != "none" and interval is None:
        raise ValueError(f"recording {rec.name!r}: no magnetic disturbance found to fit a {kind!r} model to")
    held = held_mask(rec.mag)
    offset, profile = np.zeros(3), np.zeros(n)
    p_m = mu = np.full(3, np.nan)
    if kind == "attached":
        offset = np.median(resid[interval[0] : interval[1]], axis=0)
        profile = attached_profile(resid, offset, interval, rec.rate)
    elif kind == "dipole":
        rE, p = earth_residual(rec, mo, lag, h, M, o)
        p_m, mu = fit_dipole(rE, p, ~held & ~mo.bridged, rec.rate)
    rest_new = rec.mag[mo.rest][~held[mo.rest]]
    rho1 = rest_autocorr(rec, "mag", 1, distinct=True)
    lever, acc_bias, acc_lag = fit_acc(rec, mo)
    return TwinFit(
        n=n,
        gyr_lag=gyr_lag,
        gyr_K=K,
        gyr_bias=gyr_bias,
        gyr_noise=rec.gyr[mo.rest].std(0),
        mag_lag=lag,
        mag_h_E=h,
        mag_M=M,
        mag_o=o,
        mag_noise=rest_new.std(0),
        mag_rho1=rho1,
        mag_held=held,
        acc_lever=lever,
        acc_bias=acc_bias,
        acc_lag=acc_lag,
        acc_noise=rec.acc[mo.rest].std(0),
        disturbance=kind,
        attached_offset=offset,
        attached_profile=profile,
        dipole_pos=p_m,
        dipole_moment=mu,
    )
