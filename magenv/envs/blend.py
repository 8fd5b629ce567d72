"""``magenv/MagBlend-v0``: choose how far to trust the magnetometer (Fan et al. 2017 blend).

The env module owns the runner, the observation features and the reward of one
decision; the filter itself (one shared IMU/MIMU Madgwick state, eq. 14, and the
stationary hold) is ``magenv.filters.blend``.

:func:`advance` is the one kernel of the env: it fuses samples ``start:stop`` with
``magenv.filters.blend.step1``, keeps the per-sample histories, the interval's
error sums against truth (``magenv.metrics.error_sums``) and computes the
observation of the next sample j = ``stop`` — the one the next λ is applied to
first — with the current estimate q_{j−1}, so the λ rule of eqs. 15–18 is
reproduced exactly with one decision per sample. The env calls it once per step
(k samples), :meth:`BlendRunner.run_all` once for a whole trial. With the
extended observation (``features="extended"``) :func:`advance_extended` wraps
it: the extra causal features of ``magenv.envs.blend_memory`` and the memory
(copies of the base and extra features ``LAGS`` decisions earlier).
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from magenv.checks import check_bool
from magenv.envs import BLEND_ID, blend_memory, lagged
from magenv.envs.batch import BatchVectorEnv, trial_rows, window_rows
from magenv.envs.common import TrialRunner, TrustEnv, episode_view
from magenv.envs.features import DIP_SCALE_DEG, GYRO_SCALE, WINDOW, Feature, FeatureTable, clipper, deviations, document
from magenv.filters import blend, stationary
from magenv.filters.madgwick import BETA_DEFAULT
from magenv.metrics import N_ERR, error_sums
from magenv.quaternion import GRAVITY, rotate1
from magenv.trial import Trial

NORM_RATE_SCALE = 10.0  # 1/s: the relative field-norm rate in units of 10 /s
NORM_RATE = Feature(
    "norm_rate", -10.0, 10.0, f"units of {NORM_RATE_SCALE:g} /s", f"rate of change of ‖m‖/m0 over {WINDOW}"
)


def mag_heading(of: str) -> Feature:
    """The ``mag_heading`` feature: the heading of ``of`` (units of 180°, 0 = north, + = east)."""
    return Feature("mag_heading", -1.0, 1.0, "units of 180°", f"heading of {of} (0 = north, + = east)")


FEATURES = FeatureTable(
    Feature(
        "norm_dev",
        -1.0,
        10.0,
        "fraction of m0",
        "field-norm deviation (‖m_j‖ − m0)/m0 (its absolute value is eq. 15's λ1)",
    ),
    Feature(
        "dip_dev", -2.0, 2.0, f"units of {DIP_SCALE_DEG:g}°", "dip deviation (θ_dip − θ0), θ_dip by eq. 18 with q_{j−1}"
    ),
    Feature("gyro_norm", 0.0, 10.0, "units of 2π rad/s", "‖ω_j‖"),
    Feature("acc_dev", -1.0, 10.0, "fraction of g", "accelerometer-norm deviation (‖a_j‖ − g)/g"),
    Feature("stationary", 0.0, 1.0, "0/1", "sample j stationary by eqs. 11–13"),
    Feature(
        "cand_angle",
        0.0,
        2.0,
        "units of 4·β·Δt rad",
        "mean angle between the IMU and MIMU candidate updates over the samples fused in the last step",
    ),
    Feature("lambda_prev", 0.0, 1.0, "–", "λ applied in the last step (0 after reset)"),
    *deviations("each with its own prior estimate"),
    NORM_RATE,
    mag_heading("the measured horizontal field in the estimated earth frame"),
    Feature("stationary_frac", 0.0, 1.0, "–", f"fraction of {WINDOW} detected stationary"),
)
F = FEATURES.ix  # named kernel indices
_LOW, _HIGH = FEATURES.low64, FEATURES.high64

LAGS = (8, 32)  # decisions: the memory of the extended observation
WINDOW_ROWS = 64  # a runner's per-call rows to begin with (Outputs.dip, cand_angle); widened for longer calls
_CURRENT = (*FEATURES.features, *blend_memory.EXTRA.features)
EXTENDED = lagged.extended_table(_CURRENT, LAGS)
_LAGS = np.array(LAGS, np.int64)


class Site(NamedTuple):
    """The trial's undisturbed field, the reference of the field features (``Trial.field_norm``/``field_dip``)."""

    m0: float  # field norm, µT
    dip0: float  # dip, degrees down


class Outputs(NamedTuple):
    """What :func:`advance` writes: per-sample histories (N rows), the per-sample values of the samples fused by
    the last call only (row r: sample start + r; read within the call), the last step's sums and observation."""

    est: np.ndarray  # (N, 4) estimate after each sample, sensor → ENU (NaN where not fused yet)
    lam: np.ndarray  # (N,) λ applied to each sample (NaN where not fused yet)
    dip: np.ndarray  # (W,) dip of m_i with the estimate before it (eq. 18), degrees; W ≥ the samples of a call
    cand_angle: np.ndarray  # (W,) angle between the IMU and MIMU candidates, degrees
    stationary: np.ndarray  # (N,) bool, sample detected stationary (eqs. 11–13)
    err: np.ndarray  # (N_ERR,) error sums of the last step (magenv.metrics.E_*)
    feat: np.ndarray  # (len(FEATURES),) observation of the next sample j

    @classmethod
    def empty(cls, n: int, window: int) -> Outputs:
        """Outputs of a trial of ``n`` samples fused at most ``window`` samples a call."""
        return cls(
            np.full((n, 4), np.nan),
            np.full(n, np.nan),
            np.zeros(window),
            np.zeros(window),
            np.zeros(n, np.bool_),
            np.zeros(N_ERR),
            np.zeros(len(FEATURES)),
        )


@njit(cache=True, inline="always")
def _norm3(v):
    return np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


_clip = clipper(FEATURES)


@njit(cache=True, inline="always")
def dip_deg(q, m):
    """Dip angle, degrees (positive down), of field m (3,) in the sensor frame seen with orientation q (eq. 18, ENU)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    mx, my, mz = m[0], m[1], m[2]
    n = np.sqrt(mx * mx + my * my + mz * mz)
    if n == 0.0:
        return 0.0
    up = 2.0 * (x * z - w * y) * mx + 2.0 * (y * z + w * x) * my + (1.0 - 2.0 * (x * x + y * y)) * mz
    s = -up / n
    s = min(1.0, max(-1.0, s))
    return np.rad2deg(np.arcsin(s))


def sample_features(table: FeatureTable):
    """The numba function ``write(feat, q, gyr_j, acc_j, mag_j, m0, dip0) → (‖m_j‖ µT, norm_dev, dip_dev)`` of an
    env whose ``table`` has MagBlend-v0's sensor features of sample j: it writes them, clipped, into ``feat``
    (``norm_dev`` = (‖m_j‖ − m0)/m0, ``dip_dev`` = (dip of m_j with estimate q − dip0)/DIP_SCALE_DEG, ``gyro_norm``
    = ‖ω_j‖/GYRO_SCALE, ``acc_dev`` = (‖a_j‖ − g)/g) and returns the first two unclipped."""
    clip = clipper(table)
    ix: Any = table.ix
    i_nd, i_dd, i_gn, i_ad = ix.norm_dev, ix.dip_dev, ix.gyro_norm, ix.acc_dev

    @njit(cache=True, inline="always")
    def write(feat, q, gyr_j, acc_j, mag_j, m0, dip0):
        mj = _norm3(mag_j)
        nd = (mj - m0) / m0
        dd = (dip_deg(q, mag_j) - dip0) / DIP_SCALE_DEG
        feat[i_nd] = clip(nd, i_nd)
        feat[i_dd] = clip(dd, i_dd)
        feat[i_gn] = clip(_norm3(gyr_j) / GYRO_SCALE, i_gn)
        feat[i_ad] = clip((_norm3(acc_j) - GRAVITY) / GRAVITY, i_ad)
        return mj, nd, dd

    return write


_sample_features = sample_features(FEATURES)


@njit(cache=True)
def advance(p, site, state, sensors, truth, out, lam_const, start, stop):
    """Fuse samples ``start:stop`` with ``magenv.filters.blend.step1``, then the observation of sample ``stop``.

    Args:
        p: ``magenv.filters.blend.Params``. site: :class:`Site`.
        state: ``magenv.filters.blend.State``, updated in place.
        sensors: ``magenv.filters.sensors.Sensors`` of the whole trial.
        truth: ``magenv.envs.common.Truth``, for the error sums only.
        out: :class:`Outputs`; rows start:stop of the histories, ``err`` and ``feat`` written.
        lam_const: λ of every sample fused, written to ``out.lam``; if < 0, ``out.lam`` is read instead.
    """
    q = state.q
    gyr, acc, mag = sensors
    est, lam, dip, cand_angle, still = out.est, out.lam, out.dip, out.cand_angle, out.stationary
    for i in range(start, stop):
        if lam_const >= 0.0:
            lam[i] = lam_const
        m = mag[i]
        dip[i - start] = dip_deg(q, m)  # eq. 18 with the current estimate
        cand_angle[i - start], still[i] = blend.step1(p, state, gyr[i], acc[i], m, lam[i])
        est[i, 0], est[i, 1], est[i, 2], est[i, 3] = q[0], q[1], q[2], q[3]
    error_sums(est, truth.q_true, truth.dist, start, stop, out.err)  # against truth, as magenv.metrics
    _features(p, site, state, sensors, out, start, stop)


@njit(cache=True)
def _features(p, site, state, sensors, out, start, stop):
    """``out.feat`` of sample j = ``stop`` (the last sample at the end) with the current estimate q_{j−1}."""
    gyr, acc, mag, feat = sensors.gyr, sensors.acc, sensors.mag, out.feat
    n = gyr.shape[0]
    j = stop if stop < n else n - 1
    m0, dip0 = site.m0, site.dip0
    q = state.q
    mj, nd, dd = _sample_features(feat, q, gyr[j], acc[j], mag[j], m0, dip0)
    still = stationary.peek1(state.detector, acc[j], gyr[j], p.th_acc, p.th_gyro)
    feat[F.stationary] = 1.0 if still else 0.0
    # window statistics over the fused samples start:stop plus sample j
    ang = 0.0
    nmax = abs(nd)
    nsum = nd
    dmax = abs(dd)
    sfrac = feat[F.stationary]
    cand_angle, dip, still_i = out.cand_angle, out.dip, out.stationary
    for i in range(start, stop):
        ang += cand_angle[i - start]
        ndi = (_norm3(mag[i]) - m0) / m0
        nmax = max(nmax, abs(ndi))
        nsum += ndi
        dmax = max(dmax, abs(dip[i - start] - dip0) / DIP_SCALE_DEG)
        sfrac += 1.0 if still_i[i] else 0.0
    cnt = stop - start
    ang_scale = np.rad2deg(4.0 * p.beta * p.dt)
    feat[F.cand_angle] = _clip(ang / cnt / ang_scale, F.cand_angle) if cnt > 0 and ang_scale > 0 else 0.0
    feat[F.lambda_prev] = out.lam[stop - 1] if stop > 0 else 0.0
    feat[F.norm_dev_max] = _clip(nmax, F.norm_dev_max)
    feat[F.norm_dev_mean] = _clip(nsum / (cnt + 1), F.norm_dev_mean)
    feat[F.dip_dev_max] = _clip(dmax, F.dip_dev_max)
    if start > 0 and j > start - 1:
        rate = (mj - _norm3(mag[start - 1])) / m0 / ((j - start + 1) * p.dt)
        feat[F.norm_rate] = _clip(rate / NORM_RATE_SCALE, F.norm_rate)
    else:
        feat[F.norm_rate] = 0.0
    h = rotate1(q, mag[j])
    feat[F.mag_heading] = np.arctan2(h[0], h[1]) / np.pi  # east over north: 0 when the field points north
    feat[F.stationary_frac] = sfrac / (cnt + 1)


@njit(cache=True)
def advance_extended(p, site, state, sensors, truth, out, lam_const, start, stop, q0, memory, rows, count, feat):
    """:func:`advance`, then the extended observation ``feat`` (len(EXTENDED)) of sample ``stop``.

    ``memory``: ``magenv.envs.blend_memory.Memory`` (updated on the samples fused; ``q0`` the initial
    estimate); ``rows`` (max(LAGS) + 1, len(FEATURES) + len(EXTRA)): ring of the current features by
    decision; ``count`` (1,) int64: decisions so far (0 until the first step)."""
    advance(p, site, state, sensors, truth, out, lam_const, start, stop)
    if stop > start:
        blend_memory.update(p, site, sensors, out.est, out.dip, out.stationary, q0, memory, start, stop)
    lagged.compose(out.feat, memory.value, rows, count, _LAGS, stop > start, feat)


class BlendRunner(TrialRunner):
    """One trial under the blend, stepped k samples at a time (``advance(k, λ)``) or replayed whole (``run_all``).

    Both go through the one kernel :func:`advance`; the observation of sample 0 is ready after construction.

    Args:
        trial: the Trial to filter.
        q0: initial orientation; None = ``ecompass1`` of the first sample (never truth).
        extended: ``feat`` is the EXTENDED observation (base, extra causal features, their lagged copies).
        options: ``magenv.filters.blend.Options`` by keyword (β rad/s, the hold, the stationary detection).
    """

    def __init__(self, trial: Trial, q0=None, extended: bool = False, **options):
        super().__init__(trial)
        o = blend.Options(**options)
        self.params = o.params(trial.dt)
        self.site = Site(trial.field_norm, trial.field_dip)
        self.state = blend.make_state(trial, o.t0, q0)
        self.q0 = self.state.q.copy()
        self.out = Outputs.empty(trial.n, WINDOW_ROWS)
        self.est, self.lam, self.err, self.feat = self.out.est, self.out.lam, self.out.err, self.out.feat
        self._args = (self.params, self.site, self.state, self.sensors, self.truth, self.out)
        self.extended = bool(extended)
        if self.extended:
            self.memory = blend_memory.Memory.start(self.q0)
            rows = np.zeros((max(LAGS) + 1, len(_CURRENT)))
            self.feat = np.zeros(len(EXTENDED))
            self._start(advance_extended, 0.0, self.q0, self.memory, rows, np.zeros(1, np.int64), self.feat)
        else:
            self._start(advance, 0.0)

    def _fuse(self, start: int, stop: int, lam: float) -> None:
        if stop - start > len(self.out.dip):  # a call of more samples than ever (run_all): wider per-call rows
            rows = max(stop - start, 2 * len(self.out.dip))
            self.out = self.out._replace(dip=np.zeros(rows), cand_angle=np.zeros(rows))
            self._args = (*self._args[:-1], self.out)
        self._advance(*self._args, lam, start, stop, *self._more)

    def run_all(self, lam) -> np.ndarray:
        """Fuse all remaining samples with λ a constant or an (N,) array; returns est (N, 4)."""
        if np.ndim(lam) == 0:
            self.advance(self.n - self.pos, float(lam))
            return self.est
        lam = np.asarray(lam, float)
        if lam.shape != (self.n,):
            raise ValueError(f"λ array must have shape ({self.n},), got {lam.shape}")
        if not np.all((lam >= 0) & (lam <= 1)):
            raise ValueError("λ array must lie in [0, 1]")
        self.lam[self.pos :] = lam[self.pos :]
        self.advance(self.n - self.pos, -1.0)  # λ < 0: the kernel reads the λ history
        return self.est


@document(blend_memory.EXTRA, "{extended_table}")
@document(FEATURES)
class MagBlendEnv(TrustEnv):
    """
    ## Description

    A magnetic/inertial sensor (gyroscope, accelerometer, magnetometer) moves
    while a magnet — or anything ferromagnetic — disturbs the field it
    measures. Two Madgwick gradient-descent filters (Fan et al. 2017, eqs.
    2–10) are stepped each sample from one shared, blended estimate: the IMU
    filter (gyro + accelerometer; immune to magnetic disturbance, drifts in
    heading) and the MIMU filter (adds the magnetometer; absolute heading,
    pulled off by disturbances). The agent sets the blend weight λ (eq. 14):

        q_t = normalise(λ · q_IMU,t + (1 − λ) · q_MIMU,t)

    once every ``decision_every`` samples; the filters run in between. With
    ``stationary_hold`` (default) the estimate is held unchanged on samples the
    causal stationary detector (eqs. 11–13) flags, whatever λ is. The sensor
    stream and the true orientation are fixed at ``reset()`` (the policy
    changes the estimate, never the world), so a trial can be replayed for any
    policy.

    ## Action Space

    `Box(0, 1, (1,), float32)`: λ, the weight of the IMU filter (1 = ignore
    the magnetometer, 0 = pure MIMU filter). Finite values outside [0, 1] are
    **clipped** to [0, 1] (``info["action_clipped"]`` says so); NaN/inf and
    any shape other than `(1,)` or `()` raise `ValueError`.

    ## Observation Space

    `Box(float32)`, one entry per selected feature (default: all, in this
    order). Truth never enters it. "Sample j" is the next sample to be
    fused — the one the chosen λ is applied to first — read from the sensor
    before fusing; the estimate used is the current one, q_{j−1}. m0 and θ0
    are the trial's undisturbed field norm and dip (``Trial.field_norm``,
    ``Trial.field_dip``; for the paper's protocols 46 µT and 49.6°). Window
    statistics cover the samples fused in the last step plus sample j. Every
    value is clipped to its range.

    {observation_table}

    With ``features="extended"`` (``EXTENDED``, 126 features) the observation
    is the 13 above, then these 29 extra causal features
    (``magenv.envs.blend_memory``, where the conventions are defined: "mag
    heading", EMAs, the parallel filters, clean samples), then the 42 of
    both groups 8 decisions earlier (``NAME_lag8``) and 32 decisions earlier
    (``NAME_lag32``; before the start, the first observation):

    {extended_table}

    Physical values are recoverable: ‖m_j‖ = m0·(1 + obs[0]), dip deviation in
    degrees = 90·obs[1] (``magenv.baselines.rules.FanLambda`` relies on this).

    ## Rewards

    Minus the mean total orientation error Δθ = 2·acos(|q_e,0|) (eq. 22), in
    degrees, over the samples fused in the step (those with truth; 0 if none
    has truth). An episode's return is thus −(mean error) × (number of steps).

    ## Starting State

    A trial is drawn at ``reset``: from the scenario with a trial seed drawn
    from ``self.np_random`` (``reset(seed=s)`` → the same trial and the same
    episode, bit for bit), or at random from the given Trials, or the Trial
    in ``options={"trial": trial}``. The filter starts from the e-compass
    orientation of the first sample (accelerometer + magnetometer, never
    truth); the stationary detector starts empty (nothing stationary during
    the first t0).

    ## Episode End

    Never terminated. Truncated when the trial's samples (or the first
    ``episode_seconds`` of them) are used up; the last step may fuse fewer
    than ``decision_every`` samples.

    ## Arguments

    - `scenario` (default `"random"`): a name from ``magenv.scenarios.scenario_names()`` or a comma
      list of names (a mixture: each reset picks one), trial seeds drawn at or above
      ``magenv.seeding.HELD_OUT_BELOW`` (lower seeds are kept for evaluation),
      `"recording:PATH"` (``magenv.recordings.load_recording``), a Trial or a list of Trials.
    - `decision_every` (default 8): samples fused per step (k); 1 = a λ per sample.
    - `episode_seconds` (default None): use only the first seconds of each trial; None = whole trial.
    - `stationary_hold` (default True): hold the estimate on stationary samples (eqs. 11–13).
    - `features` (default None = the 13 base features): names of the observation features to keep, in the
      given order, or `"extended"` for the extended observation (all 126; today's 13 stay the default).
    - `beta` (default 0.1 rad/s): Madgwick gain β (eq. 10), finite in [0, 10].
    - `t0`, `th_acc_g`, `th_gyro_dps` (defaults 0.5 s, 0.04 g, 0.5 °/s): stationary detection (eqs. 11–13);
      t0 in [0, 60] s, thresholds finite ≥ 0.

    A bad argument (NaN, inf, out of range, wrong type) raises ValueError / TypeError naming it at
    construction.
    - `scenario_kwargs` (default None): overrides passed to ``magenv.scenarios.make_trial``.
    - `prefetch` (default False): simulate the next reset's trial meanwhile in a worker process
      (same trials, bit for bit; hides the reset cost when a core is free). ``close()`` stops it.

    `info` of each step: `t` (s, last fused sample), `sample` (index after the step), `lambda`,
    `action_clipped`, `error_total` / `error_heading` / `error_inclination` (mean over the step, °,
    NaN without truth), `disturbance_norm` (mean true disturbance ‖·‖ over the step, µT, NaN if
    the trial has none), `q_est`, `q_true` (last fused sample). The full per-sample estimate and
    λ of the episode so far: ``env.unwrapped.estimate`` (N, 4), ``env.unwrapped.lambdas`` (N,)
    (NaN where not fused yet).

    ## Vectorised use

    ``gymnasium.make_vec("magenv/MagBlend-v0", num_envs=n, vectorization_mode="vector_entry_point")``
    gives ``MagBlendVectorEnv`` (n envs in one process, next-step autoreset).

    ## Version History

    - v0 (the id stays ``-v0`` until the first release; dates are of the commits):
      2026-12-01 first version (Fan et al.'s complementary blend on the MuJoCo gimbal), the batched vector env
      on the same kernel, ``features="extended"`` (29 causal features, lags of 8 and 32 decisions);
      2026-12-02 long episodes held in bounded memory (no change to any observation or reward).
    """

    observation = (FEATURES, EXTENDED)
    env_name = BLEND_ID.split("/")[1]

    def __init__(
        self,
        stationary_hold: bool = True,
        beta: float = BETA_DEFAULT,
        t0: float = stationary.T0_S,
        th_acc_g: float = stationary.TH_ACC_G,
        th_gyro_dps: float = stationary.TH_GYRO_DPS,
        **options,
    ):
        self._setup(**options)
        # bad filter arguments fail here, not at reset (ValueError / TypeError naming the argument)
        hold = check_bool("stationary_hold", stationary_hold)
        self.options = blend.Options(beta, hold, t0, th_acc_g, th_gyro_dps)
        self.stationary_hold = hold

    def _make_runner(self, trial: Trial) -> BlendRunner:
        return BlendRunner(trial, extended=self.extended, **asdict(self.options))

    # ------------------------------------------------------------ evaluation access

    lambdas = episode_view("lam", "(N,) λ used per sample (NaN where not fused yet).")

    @property
    def stationary(self) -> np.ndarray:
        """(N,) bool, samples the detector flagged stationary (False where not fused yet)."""
        return self._need_reset().out.stationary.copy()


class Batch(NamedTuple):
    """The arrays of :class:`MagBlendVectorEnv`'s kernel: N envs (leading axis N) on the store's rows."""

    beta: float  # Madgwick gain β, rad/s (the same for every env)
    th_acc: float  # stationary thresholds, m/s² and rad/s (magenv.filters.blend.Params)
    th_gyro: float
    hold: bool
    dt: np.ndarray  # (N,) sample interval of each env's trial, s
    m0: np.ndarray  # (N,) undisturbed field norm, µT (Site)
    dip0: np.ndarray  # (N,) undisturbed dip, degrees (Site)
    q: np.ndarray  # (N, 4) blended estimate (blend.State.q)
    buf: np.ndarray  # (N, L_max, 3) stationary ring buffers, first ``blen[i]`` rows used (stationary.State.buf)
    blen: np.ndarray  # (N,) ring length of each env
    ctr: np.ndarray  # (N, 2) ring counters (stationary.State.ctr)
    lam: np.ndarray  # (N,) λ of the step
    est: np.ndarray  # (N, k + 2, 4) scratch Outputs of the step's window (magenv.envs.batch.Window)
    lam_h: np.ndarray  # (N, k + 2)
    dip: np.ndarray  # (N, k + 2)
    cand: np.ndarray  # (N, k + 2)
    still: np.ndarray  # (N, k + 2) bool


@njit(cache=True)
def _advance_env(b, s, i, w):
    """Env i of :class:`Batch` (``s``: ``magenv.envs.batch.Steps``) does its step: :func:`advance` on window
    ``w``."""
    p = blend.Params(b.beta, b.dt[i], b.th_acc, b.th_gyro, b.hold)
    state = blend.State(b.q[i], stationary.State(b.buf[i, : b.blen[i]], b.ctr[i]))
    sensors, truth = window_rows(s, w)
    out = Outputs(b.est[i], b.lam_h[i], b.dip[i], b.cand[i], b.still[i], s.err[i], s.feat[i])
    advance(p, Site(b.m0[i], b.dip0[i]), state, sensors, truth, out, b.lam[i], w.start, w.stop)
    return -1


class MagBlendVectorEnv(BatchVectorEnv):
    """``num_envs`` MagBlend envs advanced together: one numba call per ``step`` fuses every env's k samples.

    Registered as the ``vector_entry_point`` of ``magenv/MagBlend-v0``:
    ``gymnasium.make_vec("magenv/MagBlend-v0", num_envs=256, vectorization_mode="vector_entry_point", …)``
    with the single env's arguments. Sub-env i is the single env seeded s + i bit for bit; seeding, next-step
    autoreset and ``infos`` (with ``lambda``): see ``magenv.envs.batch.BatchVectorEnv``. The filter state
    (``blend.State``) of the N envs is held as arrays with a leading axis N, and :func:`_advance_env` hands env
    i's views to :func:`advance`.
    """

    env_class = MagBlendEnv
    features = FEATURES
    advance_env = _advance_env

    def _alloc(self, n: int) -> None:
        self.params = self.template.options.params(1.0)
        rows = self.k_steps + 2
        self.dt, self.m0, self.dip0 = np.ones(n), np.ones(n), np.zeros(n)
        self.q = np.zeros((n, 4))
        self.buf, self.blen, self.ctr = np.zeros((n, 1, 3)), np.ones(n, np.int64), np.zeros((n, 2), np.int64)
        self.scratch = Outputs(
            np.zeros((n, rows, 4)), np.zeros((n, rows)), np.zeros((n, rows)), np.zeros((n, rows)),
            np.zeros((n, rows), np.bool_), self.err, self.feat,
        )  # fmt: skip

    def _prepare(self, trial: Trial):
        state = blend.make_state(trial, self.template.options.t0)
        description = (float(trial.dt), trial.field_norm, trial.field_dip, state.q, state.detector.buf.shape[0])
        return trial_rows(trial), description

    def _start(self, i: int, description) -> None:
        self.dt[i], self.m0[i], self.dip0[i], q0, length = description
        if length > self.buf.shape[1]:
            buf = np.zeros((self.num_envs, length, 3))
            buf[:, : self.buf.shape[1]] = self.buf
            self.buf, self._args_version = buf, -1
        self.q[i] = q0
        self.buf[i] = 0.0
        self.blen[i] = length
        self.ctr[i] = 0

    def _batch(self) -> Batch:
        p, s = self.params, self.scratch
        return Batch(
            beta=p.beta, th_acc=p.th_acc, th_gyro=p.th_gyro, hold=p.hold, dt=self.dt, m0=self.m0, dip0=self.dip0,
            q=self.q, buf=self.buf, blen=self.blen, ctr=self.ctr, lam=self.action, est=s.est, lam_h=s.lam, dip=s.dip,
            cand=s.cand_angle, still=s.stationary,
        )  # fmt: skip
