"""A recording's true motion as smooth, gap-free signals: what a twin trial's sensors measure.

The optical truth of a recording (orientation ``q`` sensor → ENU, ``[w,x,y,z]``; position ``p``, m) has
dropouts (NaN rows) and optical noise. From it, offline (the whole track is known):

1. :func:`bridge_gaps` — each NaN run of ``q`` is bridged by integrating an angular rate (the recording's
   own gyroscope, rest bias removed and advanced by its lag behind the truth) forward from the sample
   before the run and backward from the sample after it; the two are blended linearly in the tangent
   space, q = q_f ⊗ exp(w·log(q_f* ⊗ q_b)), w = k/(m+1) for the k-th of m bridged rows, so the bridge
   meets both ends. A leading run is integrated backward only, a trailing one forward only.
2. :func:`smooth_quat` — zero-phase 4th-order Butterworth low-pass (default 30 Hz) of the sign-continuous
   components, renormalised.
3. :func:`body_rate` — sensor-frame angular rate ω_i = log(q_{i−1}* ⊗ q_{i+1})/(2Δt), rad/s.
4. :func:`linear_acc` — p gap-filled linearly, low-passed (default 15 Hz), second derivative by centred
   differences: earth-frame p̈, m/s². :func:`specific_force` gives the sensor-frame f = R(q)ᵀ(p̈ + g e_up).

:func:`delay` and :func:`delay_quat` shift a track by a fractional number of samples (linear interpolation,
edges held), the way the twin's sensors lag behind the truth.
"""

from __future__ import annotations

import numpy as np

from magenv import quaternion as quat


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of each run of True in the (N,) bool ``mask``."""
    d = np.diff(np.r_[0, np.asarray(mask, bool).astype(np.int8), 0])
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def continuous_sign(q: np.ndarray) -> np.ndarray:
    """``q`` (N, 4) with signs flipped so each finite row has a positive dot product with the previous finite one."""
    q = np.array(q, float, copy=True)
    prev = None
    for i in range(len(q)):
        if not np.isfinite(q[i, 0]):
            continue
        if prev is not None and q[i] @ prev < 0:
            q[i] = -q[i]
        prev = q[i]
    return q


def delay(x: np.ndarray, lag: float) -> np.ndarray:
    """``x`` (N, k) delayed by ``lag`` samples (fractional; linear interpolation; edges held): y_i = x(i − lag)."""
    n = len(x)
    t = np.clip(np.arange(n) - float(lag), 0, n - 1)
    i0 = np.floor(t).astype(int)
    i1 = np.minimum(i0 + 1, n - 1)
    w = (t - i0)[:, None]
    return (1.0 - w) * x[i0] + w * x[i1]


def delay_quat(q: np.ndarray, lag: float) -> np.ndarray:
    """Orientation track (N, 4) delayed by ``lag`` samples (normalised linear interpolation)."""
    y = delay(continuous_sign(q), lag)
    return y / np.linalg.norm(y, axis=1, keepdims=True)


def _integrate(q0: np.ndarray, omega: np.ndarray, dt: float, sign: float) -> np.ndarray:
    """q0 followed by q_{k+1} = q_k ⊗ exp(sign·ω_k·dt) for each row of ``omega`` (M, 3) rad/s: (M+1, 4)."""
    out = np.empty((len(omega) + 1, 4))
    out[0] = q = np.asarray(q0, float)
    for k in range(len(omega)):
        q = quat.normalize1(quat.mul1(q, quat.from_rotvec1(sign * dt * omega[k])))
        out[k + 1] = q
    return out


def bridge_gaps(
    q_opt: np.ndarray, gyr: np.ndarray, rate: float, gyr_bias, gyr_lag: float
) -> tuple[np.ndarray, np.ndarray]:
    """Gap-free orientation track (N, 4) and the (N,) mask of bridged rows (module docstring, step 1).

    Args:
        q_opt: (N, 4) optical truth with NaN rows.
        gyr: (N, 3) the recording's gyroscope, rad/s; ``gyr_bias`` (3,) rad/s is removed from it and it is
            advanced by ``gyr_lag`` samples (its delay behind the truth).
    """
    q = continuous_sign(q_opt)
    bad = ~np.all(np.isfinite(q), axis=1)
    n = len(q)
    if bad.all():
        raise ValueError("the recording has no finite optical truth")
    g = delay(np.asarray(gyr, float) - np.asarray(gyr_bias, float), -float(gyr_lag))
    mid = 0.5 * (g[:-1] + g[1:])  # rate between samples k and k+1
    dt = 1.0 / rate
    out = q.copy()
    for a, b in true_runs(bad):
        if a == 0:  # leading: backward from q[b]
            out[:b] = _integrate(q[b], mid[:b][::-1], dt, -1.0)[1:][::-1]
        elif b == n:  # trailing: forward from q[a-1]
            out[a:] = _integrate(q[a - 1], mid[a - 1 :], dt, 1.0)[1:]
        else:
            seg = mid[a - 1 : b]
            fwd = _integrate(q[a - 1], seg, dt, 1.0)[1:-1]
            back = _integrate(q[b], seg[::-1], dt, -1.0)[1:-1][::-1]
            m = b - a
            for k in range(m):
                d = quat.mul1(quat.conj1(fwd[k]), back[k])
                r = quat.to_rotvec1(d if d[0] >= 0 else -d)
                out[a + k] = quat.normalize1(quat.mul1(fwd[k], quat.from_rotvec1((k + 1) / (m + 1) * r)))
    return continuous_sign(out), bad


def lowpass(x: np.ndarray, rate: float, fc: float, order: int = 4) -> np.ndarray:
    """Zero-phase Butterworth low-pass of ``x`` along axis 0 (cut-off ``fc`` Hz; a copy if fc ≥ rate/2)."""
    if not 0 < fc < 0.5 * rate:
        return np.array(x, float, copy=True)
    from scipy.signal import butter, filtfilt  # here: scipy.signal's import is ~40 MB

    b, a = butter(order, fc / (0.5 * rate))
    return filtfilt(b, a, x, axis=0)


def smooth_quat(q: np.ndarray, rate: float, fc: float = 30.0) -> np.ndarray:
    """Gap-free orientation track low-passed at ``fc`` Hz (zero phase), renormalised."""
    y = lowpass(continuous_sign(q), rate, fc)
    return y / np.linalg.norm(y, axis=1, keepdims=True)


def body_rate(q: np.ndarray, rate: float) -> np.ndarray:
    """Sensor-frame angular rate (N, 3), rad/s, of a gap-free track (centred difference; ends repeated)."""
    w = np.zeros((len(q), 3))
    w[1:-1] = quat.to_rotvec(quat.mul(quat.conj(q[:-2]), q[2:])) * (0.5 * rate)
    w[0], w[-1] = w[1], w[-2]
    return w


def fill_linear(x: np.ndarray) -> np.ndarray:
    """(N, k) with NaN rows filled by linear interpolation over the sample index (edges held)."""
    x = np.array(x, float, copy=True)
    bad = ~np.all(np.isfinite(x), axis=1)
    if bad.all():
        raise ValueError("no finite rows to interpolate from")
    i = np.arange(len(x))
    for j in range(x.shape[1]):
        x[bad, j] = np.interp(i[bad], i[~bad], x[~bad, j])
    return x


def linear_acc(pos: np.ndarray, rate: float, fc: float = 15.0) -> np.ndarray:
    """Earth-frame linear acceleration p̈ (N, 3), m/s², from positions (N, 3) m with NaN rows allowed."""
    p = lowpass(fill_linear(pos), rate, fc)
    dt = 1.0 / rate
    return np.gradient(np.gradient(p, dt, axis=0), dt, axis=0)


def specific_force(q: np.ndarray, lin_acc: np.ndarray) -> np.ndarray:
    """Sensor-frame specific force R(q)ᵀ(p̈ + g e_up), m/s²."""
    return quat.rotate_inv(q, lin_acc + quat.gravity_up())
