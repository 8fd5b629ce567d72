"""``magenv/MagVQF-v0``: choose how far VQF (Laidig & Seel 2023) trusts the magnetometer, window by window.

The filter is the ``vqf`` package's online C++ class ``vqf.VQF``, run as its
authors ship it; the env only sets its magnetometer gain before each window
(``setTauMag``) and steps the window with ``updateBatch`` (a loop of
``update`` inside C++). :class:`VQFRunner` owns one filter on one trial, its
histories, the error sums against truth and the observation of the next sample
(:func:`window_features`, one numba kernel); :class:`MagVQFVectorEnv` steps N of
them behind ``magenv.envs.batch.BatchVectorEnv``.

Trust → gain (:func:`tau_of_trust`). VQF's heading correction is the
first-order step δ ← δ + k·e of the disagreement angle e (its eq. 30: δ is the
heading offset of the 9D estimate from the 6D one, e the heading of the
measured field in the 6D earth frame minus δ), with k = 1 − exp(−T_s/τ_mag)
for τ_mag > 0, k = 1 for τ_mag = 0 and k = 0 for τ_mag < 0 (VQF's
``gainFromTau``: a negative τ disables the update). The trust u ∈ [0, 1]
scales the gain:

    k(u) = u · k₁,   k₁ = 1 − exp(−T_s/τ_mag)        τ(u) = −T_s / ln(1 − u·k₁)  (0 < u < 1)

with τ(1) = τ_mag exactly and τ(0) = −1 s (k = 0: the magnetometer is ignored
exactly). Two VQF rules stay as VQF has them, whatever u: its fast initial
convergence (the gain is at least 1/N at the N-th magnetometer sample until
N·T_s exceeds the current τ; so the first sample aligns the heading) and, with
``rejection="on"``, its disturbance rejection (k = 0 while a disturbance is
detected, for at most ``magMaxRejectionTime`` = 60 s, then k/2).

``rejection="off"`` runs VQF with its detector on but its rejection neutral
(``magMaxRejectionTime`` = −1 s, ``magRejectionFactor`` = 1): the gain is
never changed by the detector, so the estimate is bit for bit that of
``magDistRejectionEnabled=False`` (``tests/test_env_vqf.py``), while the
detector's flag and field reference stay in the observation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numba import njit

from magenv.checks import check_bool, check_number
from magenv.envs import VQF_ID
from magenv.envs.batch import BatchVectorEnv
from magenv.envs.blend import NORM_RATE_SCALE, dip_deg
from magenv.envs.common import TrialRunner, TrustEnv, scalar_action
from magenv.envs.features import DIP_SCALE_DEG, GYRO_SCALE, Feature, FeatureTable, document
from magenv.metrics import N_ERR, error_sums
from magenv.quaternion import GRAVITY, rotate1
from magenv.trial import Trial

REJECTION = ("off", "on")  # the rejection option: the policy replaces VQF's rejection, or acts on top of it
TAU_MAG_DEFAULT = 9.0  # s, VQF's default magnetometer time constant
TAU_ACC_DEFAULT = 3.0  # s, VQF's default accelerometer time constant
TAU_DISABLED = -1.0  # s, a negative τ: VQF's gain 0 (magnetometer ignored)
BIAS_SCALE_DPS = 1.0  # °/s: bias norms and uncertainties in °/s
DELTA_RATE_SCALE_DPS = 10.0  # °/s: the rate of δ in units of 10 °/s
#: vqf.VQF keyword arguments of rejection="off": detector running, its gain changes neutral
NEUTRAL_REJECTION = {"magMaxRejectionTime": -1.0, "magRejectionFactor": 1.0}
WINDOW = "the window"  # samples fused in the last step plus sample j

FEATURES = FeatureTable(
    Feature("mag_dist", 0.0, 1.0, "0/1", "VQF's magnetic disturbance flag after the last fused sample"),
    Feature(
        "ref_norm_dev",
        -1.0,
        10.0,
        "fraction of the reference",
        "(‖m‖ − n_ref)/n_ref: VQF's low-pass field norm in its 6D earth frame against its reference norm "
        "(0 while VQF has no reference)",
    ),
    Feature(
        "ref_dip_dev",
        -2.0,
        2.0,
        f"units of {DIP_SCALE_DEG:g}°",
        "VQF's low-pass dip against its reference dip (0 while VQF has no reference)",
    ),
    Feature("ref_known", 0.0, 1.0, "0/1", "VQF has accepted a field reference"),
    Feature("rest", 0.0, 1.0, "0/1", "VQF's rest detection after the last fused sample"),
    Feature("bias_norm", 0.0, 10.0, f"units of {BIAS_SCALE_DPS:g} °/s", "‖b‖, VQF's gyro-bias estimate"),
    Feature("bias_sigma", 0.0, 10.0, f"units of {BIAS_SCALE_DPS:g} °/s", "VQF's bias uncertainty (std)"),
    Feature("delta", -1.0, 1.0, "units of 180°", "δ, the heading of the 9D estimate relative to the 6D one"),
    Feature("delta_rate", -10.0, 10.0, f"units of {DELTA_RATE_SCALE_DPS:g} °/s", "change of δ over the last step"),
    Feature(
        "dis_angle",
        -1.0,
        1.0,
        "units of 180°",
        "VQF's disagreement angle e of the last fused sample (field heading in the 6D frame − δ)",
    ),
    Feature("mag_dist_frac", 0.0, 1.0, "–", "fraction of the samples fused in the last step flagged disturbed"),
    Feature("norm_dev", -1.0, 10.0, "fraction of m0", "field-norm deviation (‖m_j‖ − m0)/m0 of the next sample j"),
    Feature(
        "dip_dev", -2.0, 2.0, f"units of {DIP_SCALE_DEG:g}°", "dip deviation (θ_dip − θ0) of m_j with the 9D estimate"
    ),
    Feature("gyro_norm", 0.0, 10.0, "units of 2π rad/s", "‖ω_j‖"),
    Feature("acc_dev", -1.0, 10.0, "fraction of g", "accelerometer-norm deviation (‖a_j‖ − g)/g"),
    Feature("norm_dev_max", 0.0, 10.0, "fraction of m0", f"max of the absolute norm_dev over {WINDOW}"),
    Feature("norm_dev_mean", -1.0, 10.0, "fraction of m0", f"mean norm_dev over {WINDOW}"),
    Feature(
        "dip_dev_max",
        0.0,
        2.0,
        f"units of {DIP_SCALE_DEG:g}°",
        f"max of the absolute dip_dev over {WINDOW} (each with the estimate after the sample before it)",
    ),
    Feature("norm_rate", -10.0, 10.0, f"units of {NORM_RATE_SCALE:g} /s", f"rate of change of ‖m‖/m0 over {WINDOW}"),
    Feature(
        "mag_heading",
        -1.0,
        1.0,
        "units of 180°",
        "heading of m_j in the 9D earth frame (0 = north, + = east)",
    ),
    Feature("trust_prev", 0.0, 1.0, "–", "u applied in the last step (1 after reset)"),
)
F = FEATURES.ix
_LOW, _HIGH = FEATURES.low64, FEATURES.high64
# the VQF scalars the runner hands to window_features (indices of its ``vq`` array)
V_DIST, V_REF_NORM, V_REF_DIP, V_NORM, V_DIP, V_REST, V_BIAS, V_SIGMA, V_DELTA, V_DELTA0, V_DIS = range(11)


def tau_of_trust(u: float, tau_mag: float, ts: float) -> float:
    """τ (s) that gives VQF the gain k(u) = u·k₁ (module docstring): τ_mag at u = 1, −1 s (k = 0) at u = 0."""
    if u >= 1.0:
        return tau_mag
    if u <= 0.0:
        return TAU_DISABLED
    k1 = 1.0 if tau_mag == 0.0 else -math.expm1(-ts / tau_mag)
    return -ts / math.log1p(-u * k1)


@njit(cache=True, inline="always")
def _clip(x, i):
    return min(_HIGH[i], max(_LOW[i], x))


@njit(cache=True, inline="always")
def _norm3(v):
    return np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@njit(cache=True)
def window_features(m0, dip0, dt, gyr, acc, mag, est, flags, start, stop, q_now, vq, u_prev, feat):
    """``feat`` (len(FEATURES),) of sample j = ``stop`` (the last sample at the end) after samples start:stop.

    Args:
        m0, dip0: the trial's undisturbed field norm (µT) and dip (°). dt: sample interval, s.
        gyr, acc, mag: (n, 3) sensors (rad/s, m/s², µT) of the trial, or of a window holding rows start−1 … j.
        est: (n, 4) the 9D estimate after each sample (rows start−1 … stop−1 read). flags: (n,) VQF's
            disturbance flag per fused sample. q_now: (4,) the current 9D estimate (q_{j−1}).
        vq: the VQF scalars (``V_*`` indices; radians, rad/s, µT). u_prev: trust of the last step.
    """
    n = gyr.shape[0]
    j = stop if stop < n else n - 1
    feat[F.mag_dist] = vq[V_DIST]
    known = vq[V_REF_NORM] > 0.0
    feat[F.ref_known] = 1.0 if known else 0.0
    if known:
        feat[F.ref_norm_dev] = _clip((vq[V_NORM] - vq[V_REF_NORM]) / vq[V_REF_NORM], F.ref_norm_dev)
        feat[F.ref_dip_dev] = _clip(np.rad2deg(vq[V_DIP] - vq[V_REF_DIP]) / DIP_SCALE_DEG, F.ref_dip_dev)
    else:
        feat[F.ref_norm_dev] = 0.0
        feat[F.ref_dip_dev] = 0.0
    feat[F.rest] = vq[V_REST]
    feat[F.bias_norm] = _clip(np.rad2deg(vq[V_BIAS]) / BIAS_SCALE_DPS, F.bias_norm)
    feat[F.bias_sigma] = _clip(np.rad2deg(vq[V_SIGMA]) / BIAS_SCALE_DPS, F.bias_sigma)
    feat[F.delta] = vq[V_DELTA] / np.pi
    cnt = stop - start
    dd = vq[V_DELTA] - vq[V_DELTA0]
    if dd > np.pi:
        dd -= 2.0 * np.pi
    elif dd < -np.pi:
        dd += 2.0 * np.pi
    feat[F.delta_rate] = _clip(np.rad2deg(dd) / (cnt * dt) / DELTA_RATE_SCALE_DPS, F.delta_rate) if cnt > 0 else 0.0
    feat[F.dis_angle] = _clip(vq[V_DIS] / np.pi, F.dis_angle)
    # sensor features of sample j and the window, against the trial's site (as MagBlend-v0's)
    mj = _norm3(mag[j])
    nd = (mj - m0) / m0
    ddip = (dip_deg(q_now, mag[j]) - dip0) / DIP_SCALE_DEG
    feat[F.norm_dev] = _clip(nd, F.norm_dev)
    feat[F.dip_dev] = _clip(ddip, F.dip_dev)
    feat[F.gyro_norm] = _clip(_norm3(gyr[j]) / GYRO_SCALE, F.gyro_norm)
    feat[F.acc_dev] = _clip((_norm3(acc[j]) - GRAVITY) / GRAVITY, F.acc_dev)
    nmax, nsum, dmax, dist = abs(nd), nd, abs(ddip), 0.0
    for i in range(start, stop):
        ndi = (_norm3(mag[i]) - m0) / m0
        nmax = max(nmax, abs(ndi))
        nsum += ndi
        if i > 0:
            dmax = max(dmax, abs(dip_deg(est[i - 1], mag[i]) - dip0) / DIP_SCALE_DEG)
        dist += flags[i]
    feat[F.mag_dist_frac] = dist / cnt if cnt > 0 else 0.0
    feat[F.norm_dev_max] = _clip(nmax, F.norm_dev_max)
    feat[F.norm_dev_mean] = _clip(nsum / (cnt + 1), F.norm_dev_mean)
    feat[F.dip_dev_max] = _clip(dmax, F.dip_dev_max)
    if start > 0 and j > start - 1:
        rate = (mj - _norm3(mag[start - 1])) / m0 / ((j - start + 1) * dt)
        feat[F.norm_rate] = _clip(rate / NORM_RATE_SCALE, F.norm_rate)
    else:
        feat[F.norm_rate] = 0.0
    h = rotate1(q_now, mag[j])
    feat[F.mag_heading] = np.arctan2(h[0], h[1]) / np.pi
    feat[F.trust_prev] = u_prev


def make_vqf(ts: float, tau_acc: float, tau_mag: float, rejection: str, rest_bias: bool, motion_bias: bool):
    """A fresh ``vqf.VQF`` at sample interval ``ts`` (s) with the env's options (module docstring)."""
    import vqf

    extra = NEUTRAL_REJECTION if rejection == "off" else {}
    return vqf.VQF(
        ts,
        ts,
        ts,
        tauAcc=tau_acc,
        tauMag=tau_mag,
        restBiasEstEnabled=rest_bias,
        motionBiasEstEnabled=motion_bias,
        **extra,
    )


class VQFRunner(TrialRunner):
    """One ``vqf.VQF`` on one trial, k samples per step at one trust u.

    Histories (N rows, NaN / 0 where not fused yet): ``est`` (9D estimate, sensor → ENU), ``est6d``,
    ``trust`` (u per sample), ``gain`` (u where the policy's gain applied: 0 where ``rejection="on"`` and VQF
    flagged a disturbance), ``dist_flag``, ``rest_flag``, ``delta`` (rad).
    """

    def __init__(
        self,
        trial: Trial,
        tau_acc: float = TAU_ACC_DEFAULT,
        tau_mag: float = TAU_MAG_DEFAULT,
        rejection: str = "off",
        rest_bias: bool = True,
        motion_bias: bool = True,
    ):
        super().__init__(trial)
        self.ts = float(trial.dt)
        self.tau_mag = tau_mag
        self.rejection = rejection
        self.filter = make_vqf(self.ts, tau_acc, tau_mag, rejection, rest_bias, motion_bias)
        n = trial.n
        self.site = (float(trial.field_norm), float(trial.field_dip))
        self.gyr, self.acc, self.mag = self.sensors
        self.est = np.full((n, 4), np.nan)
        self.est6d = np.full((n, 4), np.nan)
        self.trust = np.full(n, np.nan)
        self.gain = np.full(n, np.nan)
        self.dist_flag = np.zeros(n)
        self.rest_flag = np.zeros(n)
        self.delta = np.zeros(n)
        self.err = np.zeros(N_ERR)
        self.feat = np.zeros(len(FEATURES))
        self.vq = np.zeros(11)
        self.u_prev = 1.0
        self._observe(0, 0, self.filter.getDelta())

    def _observe(self, start: int, stop: int, delta_before: float) -> None:
        f, vq = self.filter, self.vq
        s = f.state
        bias, sigma = f.getBiasEstimate()
        vq[:] = (
            float(s["magDistDetected"]),
            s["magRefNorm"],
            s["magRefDip"],
            s["magNormDip"][0],
            s["magNormDip"][1],
            float(s["restDetected"]),
            math.sqrt(float(bias @ bias)),
            sigma,
            s["delta"],
            delta_before,
            s["lastMagDisAngle"],
        )
        q_now = f.getQuat9D()
        m0, dip0 = self.site
        window_features(
            m0, dip0, self.ts, self.gyr, self.acc, self.mag, self.est, self.dist_flag, start, stop, q_now, vq,
            self.u_prev, self.feat,
        )  # fmt: skip

    def _fuse(self, start: int, stop: int, u: float) -> None:
        f = self.filter
        delta_before = f.getDelta()
        f.setTauMag(tau_of_trust(u, self.tau_mag, self.ts))
        out = f.updateBatch(self.gyr[start:stop], self.acc[start:stop], self.mag[start:stop])
        self.est[start:stop] = out["quat9D"]
        self.est6d[start:stop] = out["quat6D"]
        flags = out["magDistDetected"]
        self.dist_flag[start:stop] = flags
        self.rest_flag[start:stop] = out["restDetected"]
        self.delta[start:stop] = out["delta"]
        self.trust[start:stop] = u
        self.gain[start:stop] = np.where(flags, 0.0, u) if self.rejection == "on" else u
        error_sums(self.est, self.truth.q_true, self.truth.dist, start, stop, self.err)
        self.u_prev = u
        self._observe(start, stop, delta_before)


def check_rejection(value) -> str:
    """The ``rejection`` option: "off" or "on" (ValueError / TypeError naming it)."""
    if not isinstance(value, str):
        raise TypeError(f"rejection must be one of {REJECTION}, got {value!r}")
    if value not in REJECTION:
        raise ValueError(f"rejection must be one of {REJECTION}, got {value!r}")
    return value


@document(FEATURES)
class MagVQFEnv(TrustEnv):
    """
    ## Description

    A magnetic/inertial sensor moves while a magnet — or anything
    ferromagnetic — disturbs the field it measures. The orientation filter is
    VQF (Laidig & Seel 2023, the ``vqf`` package's C++ implementation, run as
    shipped): a 6D gyro/accelerometer estimate with rest detection and
    gyro-bias estimation, and a 9D estimate that corrects the 6D heading by δ
    with the magnetometer (δ ← δ + k·e each sample, e the disagreement angle).
    The agent sets the trust u of that correction once every
    ``decision_every`` samples: k(u) = u·k₁ with k₁ = 1 − exp(−T_s/τ_mag)
    (``tau_of_trust``: u = 0 ignores the magnetometer exactly, u = 1 is VQF's
    own gain). With ``rejection="off"`` (default) the policy replaces VQF's
    magnetic disturbance rejection; with ``"on"`` it acts on top of it. The
    sensor stream and the true orientation are fixed at ``reset()``, so a
    trial can be replayed for any policy.

    ## Action Space

    `Box(0, 1, (1,), float32)`: u, the trust of the magnetometer (0 = ignored,
    1 = VQF's gain). Finite values outside [0, 1] are **clipped**
    (``info["action_clipped"]``); NaN/inf and any shape other than `(1,)` or
    `()` raise `ValueError`.

    ## Observation Space

    `Box(float32)`, one entry per selected feature (default: all, in this
    order). Truth never enters it. The VQF features are read from the filter
    after the last fused sample (its state, ``getBiasEstimate``, ``getDelta``);
    "sample j" is the next sample to be fused, read from the sensor before
    fusing, with the current 9D estimate q_{j−1}; m0 and θ0 are the trial's
    undisturbed field norm and dip (``Trial.field_norm``/``field_dip``), as in
    ``magenv/MagBlend-v0`` (same names, same scales: ‖m_j‖ = m0·(1 + obs
    ``norm_dev``), dip deviation in degrees = 90·obs ``dip_dev``). Window
    statistics cover the samples fused in the last step plus sample j. Every
    value is clipped to its range.

    {observation_table}

    ## Rewards

    Minus the mean total orientation error Δθ = 2·acos(|q_e,0|), degrees, of
    the 9D estimate over the samples fused in the step (those with truth; 0 if
    none has truth).

    ## Starting State

    A trial is drawn at ``reset`` as in the other magenv envs (``reset(seed=s)``
    → the same trial and episode, bit for bit; ``options={"trial": trial}``).
    VQF starts from its own initial state (identity, no reference field, bias
    0 with σ = 0.5 °/s) and converges by its own rules; the first sample's
    magnetometer aligns the heading whatever u (VQF's initial gain 1).

    ## Episode End

    Never terminated. Truncated when the trial's samples (or the first
    ``episode_seconds``) are used up; the last step may fuse fewer samples.

    ## Arguments

    - `scenario` (default `"random"`): a scenario name, a comma list (a mixture), `"recording:PATH"`,
      `"recording:GLOB"` (recordings in a mixture, see ``magenv.envs.common.trial_source``), a Trial or a list.
    - `decision_every` (default 8): samples per step (k).
    - `episode_seconds` (default None): only the first seconds of each trial.
    - `rejection` (default `"off"`): `"off"` — the policy replaces VQF's disturbance rejection (VQF's
      detector still runs and feeds the observation); `"on"` — VQF's rejection acts on top of u.
    - `tau_acc`, `tau_mag` (defaults 3 s, 9 s, VQF's): accelerometer and magnetometer time constants,
      finite in (0, 1000] s; u = 1 is VQF at `tau_mag`.
    - `rest_bias`, `motion_bias` (default True): VQF's gyro-bias estimation at rest and in motion.
    - `features` (default None = all): names of the observation features to keep, in order.
    - `scenario_kwargs`, `prefetch`, `trial_pool`, `render_mode`: as for ``magenv/MagBlend-v0``.

    A bad argument raises ValueError / TypeError naming it at construction.

    `info` of each step: `t`, `sample`, `trust` (u), `action_clipped`, `error_total` / `error_heading` /
    `error_inclination` (°, NaN without truth), `disturbance_norm` (µT), `q_est`, `q_true`, `mag_dist`
    (VQF's flag after the step). Per-sample histories: ``env.unwrapped.estimate`` (N, 4), ``trust`` (N,),
    ``vqf_gain`` (N,: u where the gain applied, 0 where VQF's rejection zeroed it),
    ``mag_dist_detected`` (N,).

    ## Vectorised use

    ``gymnasium.make_vec("magenv/MagVQF-v0", num_envs=n, vectorization_mode="vector_entry_point")``
    gives ``MagVQFVectorEnv`` (n VQF filters stepped one window each per step, next-step autoreset).

    ## Version History

    - v0: initial version.
    """

    env_name = VQF_ID.split("/")[1]

    def __init__(
        self,
        scenario="random",
        decision_every: int = 8,
        episode_seconds: float | None = None,
        rejection: str = "off",
        tau_acc: float = TAU_ACC_DEFAULT,
        tau_mag: float = TAU_MAG_DEFAULT,
        rest_bias: bool = True,
        motion_bias: bool = True,
        features: Sequence[str] | None = None,
        scenario_kwargs: dict | None = None,
        prefetch: bool = False,
        trial_pool=None,
        render_mode: str | None = None,
    ):
        self._setup(
            scenario,
            decision_every,
            episode_seconds,
            render_mode,
            scenario_kwargs,
            features,
            FEATURES.names,
            FEATURES.low,
            FEATURES.high,
            prefetch=prefetch,
            trial_pool=trial_pool,
        )
        self.filter_kwargs: dict[str, Any] = dict(
            tau_acc=check_number("tau_acc", tau_acc, 0.0, 1000.0, lo_open=True),
            tau_mag=check_number("tau_mag", tau_mag, 0.0, 1000.0, lo_open=True),
            rejection=check_rejection(rejection),
            rest_bias=check_bool("rest_bias", rest_bias),
            motion_bias=check_bool("motion_bias", motion_bias),
        )
        self.rejection = self.filter_kwargs["rejection"]

    def _make_runner(self, trial: Trial) -> VQFRunner:
        return VQFRunner(trial, **self.filter_kwargs)

    def step(self, action):
        runner = self._step_runner()
        u, clipped = scalar_action(action, "u")
        runner.advance(self.k_steps, u)
        extra = {"mag_dist": bool(runner.vq[V_DIST])}
        return self._step_result(runner, {"trust": u, "action_clipped": clipped}, extra)

    @property
    def trust(self) -> np.ndarray:
        """(N,) u applied to each sample (NaN where not fused yet)."""
        return self._need_reset().trust

    @property
    def vqf_gain(self) -> np.ndarray:
        """(N,) the trust that reached VQF's gain: u, or 0 where ``rejection="on"`` zeroed it."""
        return self._need_reset().gain

    @property
    def mag_dist_detected(self) -> np.ndarray:
        """(N,) VQF's disturbance flag per fused sample (0 where not fused yet)."""
        return self._need_reset().dist_flag


class MagVQFVectorEnv(BatchVectorEnv):
    """``num_envs`` MagVQF envs: each step advances every sub-env's ``vqf.VQF`` by one window.

    Registered as the ``vector_entry_point`` of ``magenv/MagVQF-v0``. Seeding, trial draws, next-step
    autoreset, action checks and ``infos`` (with ``trust``) are ``magenv.envs.batch.BatchVectorEnv``'s; the
    filter is C++, so instead of one numba kernel over arrays, :meth:`_run` steps the N sub-envs'
    :class:`VQFRunner` objects (each ``updateBatch`` over its window), and sub-env i is the single env seeded
    s + i bit for bit. The runners keep their per-sample histories (a few MB per long recording).
    """

    env_class = MagVQFEnv
    features = FEATURES
    channels = {"n": ((), np.int64)}  # the store only shares trials by key; the runners hold the samples
    kernels = ()

    def _alloc(self, n: int) -> None:
        self.runners: list[VQFRunner | None] = [None] * n
        self.u = np.ones(n)

    def _prepare(self, trial: Trial):
        return {"n": np.zeros(trial.n, np.int64)}, trial

    def _start(self, i: int, description) -> None:
        self.runners[i] = VQFRunner(description, **self.template.filter_kwargs)

    def _set_actions(self, values, stepping) -> dict:
        if values is None:
            return {}
        np.copyto(self.u, np.where(stepping, values[:, 0], 1.0))
        return {"trust": self.u.copy()}

    def _run(self) -> None:
        for i, runner in enumerate(self.runners):
            assert runner is not None
            todo = int(self.todo[i])
            if todo > 0:
                runner.advance(todo, float(self.u[i]))
                self.err[i] = runner.err
            elif todo == 0:
                self.err[i] = 0.0  # a reset: no samples fused, reward 0
            if todo >= 0:
                self.feat[i] = runner.feat
                self.pos[i] = runner.pos

    def _step_info(self) -> dict:
        return {"mag_dist": np.array([bool(r.vq[V_DIST]) for r in self.runners if r is not None])}
