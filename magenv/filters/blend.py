"""Blend of the IMU and MIMU Madgwick filters by a weight λ (Fan et al. 2017 §2.3, eq. 14).

Per sample t, from the previous **blended** estimate q_{t−1}:

1. q_IMU  = Madgwick step from q_{t−1} with gyro + accelerometer      (eqs. 8–9, IMU)
2. q_MIMU = Madgwick step from q_{t−1}, magnetometer added            (eqs. 8–9, MIMU)
3. align the sign of q_MIMU to q_IMU, then
   q_t = normalise(λ q_IMU + (1 − λ) q_MIMU)                           (eq. 14)
4. with the stationary hold on and sample t stationary (eqs. 11–13):
   q_t = q_{t−1} (the estimate is held unchanged, whatever λ is).

Reading of §2.3: one shared state. Both candidate updates start from the
blended estimate of the previous sample (the fused output is fed back into
both filters), so λ = 1 is exactly the IMU filter and λ = 0 exactly the
MIMU filter, and any λ in between pulls one estimate between the two.

:func:`step1` is the one per-sample kernel (parameters :class:`Params`, state
:class:`State`, both named tuples that numba passes by value / by reference).
``magenv.envs.blend`` steps it k samples at a time with one λ per step;
:class:`BlendEstimator` runs it over a whole trial with a fixed λ.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from magenv.checks import check_bool, check_number, check_vector
from magenv.filters import stationary
from magenv.filters.madgwick import BETA_DEFAULT, MODE_IMU, MODE_MIMU, NO_REF, check_beta, ecompass1, step
from magenv.filters.sensors import Sensors
from magenv.protocols import Estimate
from magenv.quaternion import normalize1
from magenv.trial import Trial


class Params(NamedTuple):
    """Constants of the blend over one trial."""

    beta: float  # Madgwick gain β, rad/s (eq. 10)
    dt: float  # sample interval, s
    th_acc: float  # stationary threshold on |a_t − a_{t−t0}| per axis, m/s² (eqs. 11–12)
    th_gyro: float  # stationary threshold on |ω_t| per axis, rad/s (eq. 13)
    hold: bool  # hold the estimate on stationary samples


class State(NamedTuple):
    """The blend's state, arrays updated in place by :func:`step1`.

    N envs stepped together keep the same fields with a leading axis of N and hand env i's views,
    ``State(q[i], stationary.State(buf[i], ctr[i]))``, to the same per-sample kernel.
    """

    q: np.ndarray  # (4,) blended estimate q_{t−1}, sensor → ENU
    detector: stationary.State  # eqs. 11–13


@dataclass(frozen=True)
class Options:
    """The blend's options for every trial (an env's arguments, checked once): gain β rad/s, the stationary hold,
    the detector's interval t0 s and thresholds (g, °/s). :meth:`params` gives a trial's :class:`Params`."""

    beta: float = BETA_DEFAULT
    hold: bool = True
    t0: float = stationary.T0_S
    th_acc_g: float = stationary.TH_ACC_G
    th_gyro_dps: float = stationary.TH_GYRO_DPS

    def __post_init__(self):
        p = self.params(1.0)  # ValueError / TypeError naming a bad option
        stationary.make_state(1.0, self.t0)
        for name, value in (("beta", p.beta), ("t0", float(self.t0)), ("th_acc_g", float(self.th_acc_g))):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "th_gyro_dps", float(self.th_gyro_dps))

    def params(self, dt: float) -> Params:
        """The :class:`Params` of a trial sampled every ``dt`` s."""
        return make_params(dt, self.beta, self.hold, self.th_acc_g, self.th_gyro_dps)


def make_params(
    dt: float,
    beta: float = BETA_DEFAULT,
    hold: bool = True,
    th_acc_g: float = stationary.TH_ACC_G,
    th_gyro_dps: float = stationary.TH_GYRO_DPS,
) -> Params:
    """Parameters for sample interval ``dt`` s > 0, gain β rad/s (``madgwick.check_beta``), the stationary hold
    (a bool) and the stationary thresholds (g, °/s; ``stationary.thresholds``). Raises ValueError or
    TypeError naming a bad one."""
    th_acc, th_gyro = stationary.thresholds(th_acc_g, th_gyro_dps)
    dt = check_number("dt", dt, 0.0, lo_open=True)
    return Params(check_beta(beta), dt, float(th_acc), float(th_gyro), check_bool("hold", hold))


def make_state(trial: Trial, t0: float = stationary.T0_S, q0=None) -> State:
    """Initial state: ``q0`` (4 finite numbers, not all zero; normalised) or, if None, ``ecompass1`` of the
    first sample (never truth); an empty stationary detector of interval ``t0`` s."""
    q = (
        ecompass1(trial.acc[0], trial.mag[0])
        if q0 is None
        else np.array(normalize1(check_vector("q0", q0, 4, nonzero=True)), float)
    )
    return State(q, stationary.make_state(trial.rate, t0))


@njit(cache=True, inline="always")
def step1(p, s, gyr, acc, mag, lam):
    """Fuse one sample (gyr rad/s, acc m/s², mag µT; (3,) each) with weight ``lam`` = λ ∈ [0, 1], in place on ``s``.

    Returns ``(angle, still)``: the angle between the IMU and MIMU candidates (degrees) and
    whether the sample is stationary (eqs. 11–13).
    """
    q, detector = s.q, s.detector
    q_prev = (q[0], q[1], q[2], q[3])
    iw, ix, iy, iz = step(q_prev, gyr, acc, mag, MODE_IMU, NO_REF, p.beta, p.dt)
    mw, mx, my, mz = step(q_prev, gyr, acc, mag, MODE_MIMU, NO_REF, p.beta, p.dt)
    d = iw * mw + ix * mx + iy * my + iz * mz
    if d < 0.0:  # align signs before blending
        mw, mx, my, mz = -mw, -mx, -my, -mz
    angle = np.rad2deg(2.0 * np.arccos(min(1.0, abs(d))))
    # eqs. 11–13; independent of the candidates, and tested after them, which compiles to faster code
    still = stationary.step1(detector, acc, gyr, p.th_acc, p.th_gyro)
    if not (p.hold and still):  # eq. 14, normalised
        bw = lam * iw + (1.0 - lam) * mw
        bx = lam * ix + (1.0 - lam) * mx
        by = lam * iy + (1.0 - lam) * my
        bz = lam * iz + (1.0 - lam) * mz
        nb = np.sqrt(bw * bw + bx * bx + by * by + bz * bz)
        q[0], q[1], q[2], q[3] = bw / nb, bx / nb, by / nb, bz / nb
    return angle, still


@njit(cache=True)
def run_kernel(p, s, sensors, lam, est):
    """Fuse every sample i with weight ``lam[i]`` (N,); writes the estimates ``est`` (N, 4)."""
    for i in range(lam.shape[0]):
        step1(p, s, sensors.gyr[i], sensors.acc[i], sensors.mag[i], lam[i])
        est[i] = s.q


class BlendEstimator:
    """Offline blend with a fixed λ over whole trials; an ``Estimator`` (``magenv.protocols``).

    ``BlendEstimator(0.0)`` is the pure MIMU filter, ``BlendEstimator(1.0)`` the pure IMU filter.

    Args:
        lam: λ ∈ [0, 1], the weight of the IMU filter.
        q0: initial orientation; None = ``ecompass1`` of the first sample.
        options: :class:`Options` by keyword (β rad/s, the hold, the stationary detection s, g, °/s).
    """

    def __init__(self, lam: float = 0.0, q0=None, **options):
        self.lam = check_number("lam", lam, 0.0, 1.0)
        self.options = Options(**options)  # bad values fail here, not in run()
        self.q0 = None if q0 is None else check_vector("q0", q0, 4, nonzero=True)

    def run(self, trial: Trial) -> Estimate:
        params = self.options.params(trial.dt)
        lam = np.full(trial.n, self.lam)
        est = np.empty((trial.n, 4))
        run_kernel(params, make_state(trial, self.options.t0, self.q0), Sensors.of(trial), lam, est)
        return Estimate(q=est, trust=1.0 - lam)
