"""``magenv/MagConstraint-v0``: weigh a kinematic constraint against the magnetometer (Jung & Lee 2019).

The env module owns the runner, the observation features and the reward of one
decision; the filter itself (eqs. 4–18) is ``magenv.filters.constraint``.
:func:`advance` is the env's one kernel: it fuses samples ``start:stop`` with
``magenv.filters.constraint.fuse``, sums the interval's errors against truth
(``magenv.metrics.error_sums``) and computes the observation of the next sample
j = ``stop`` with the current estimate q_{j−1}, so eq. 16 as a policy with one
decision per sample reproduces the paper's filter.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from magenv.checks import check_bool, check_positive
from magenv.envs import CONSTRAINT_ID, constraint_memory, lagged
from magenv.envs.batch import ROWS, BatchVectorEnv, check_box_actions
from magenv.envs.common import EnvOptions, TrialRunner, TrustEnv, Truth, action_array, episode_view
from magenv.envs.features import DIP_SCALE_DEG, GYRO_SCALE, Feature, FeatureTable, clipper, document
from magenv.filters import constraint as cf
from magenv.metrics import N_ERR, error_sums
from magenv.quaternion import GRAVITY, rotate1
from magenv.trial import Trial

WINDOW = "the samples fused in the last step and sample j"
FEATURES = FeatureTable(
    Feature("mag_dev", 0.0, 10.0, "fraction of m0", "‖C(q)y_M − m_E‖/m0: eq. 16's field deviation"),
    Feature("norm_dev", -1.0, 10.0, "fraction of m0", "(‖y_M‖ − m0)/m0"),
    Feature("dip_dev", -2.0, 2.0, f"units of {DIP_SCALE_DEG:g}°", "dip of C(q)y_M minus the undisturbed dip"),
    Feature(
        "con_mismatch", 0.0, 10.0, "units of g", "‖C(q)h_i − C(q_j)h_j‖: joint-centre acceleration mismatch (eq. 9)"
    ),
    Feature(
        "joint_acc", 0.0, 10.0, "units of g", "‖C(q_j)h_j − g·up‖: joint-centre free acceleration seen from link j"
    ),
    Feature("gyro_norm", 0.0, 10.0, "units of 2π rad/s", "‖ω_i‖ of link i's gyroscope"),
    Feature("acc_dev", -1.0, 10.0, "fraction of g", "(‖y_A‖ − g)/g of link i's accelerometer"),
    Feature("step_mag", 0.0, cf.STEP_ABNORMAL, "quaternion units", "step with w = 0 (gravity + magnetometer)"),
    Feature("step_con", 0.0, cf.STEP_ABNORMAL, "quaternion units", "step with w = 1 (gravity + constraint)"),
    Feature("con_heading", -1.0, 1.0, "units of 180°", "heading of C(q)h_i minus heading of C(q_j)h_j (about ENU up)"),
    Feature("w_prev", 0.0, 1.0, "–", "w applied in the last step (0 after reset)"),
    Feature("k_prev", 0.0, 1.0, "–", "k applied to the last fused sample (0 after reset)"),
    Feature("mag_dev_mean", 0.0, 10.0, "fraction of m0", f"mean `mag_dev` over {WINDOW}"),
)
F = FEATURES.ix  # named kernel indices
#: features="extended": FEATURES, the extra causal features of ``magenv.envs.constraint_memory`` and their copies
#: ``constraint_memory.LAGS`` decisions earlier
EXTENDED = lagged.extended_table((*FEATURES.features, *constraint_memory.EXTRA.features), constraint_memory.LAGS)
_LOW, _HIGH = FEATURES.low64, FEATURES.high64


_clip = clipper(FEATURES)


@njit(cache=True, inline="always")
def _heading_of(v):
    """Heading of an ENU vector about up, rad (0 = north, + = east)."""
    return np.arctan2(v[0], v[1])


@njit(cache=True)
def advance(p, q, inputs, control, start, stop, trace, q_true, dist, err, feat):
    """Fuse samples ``start:stop`` (``magenv.filters.constraint.fuse``), then the observation of sample ``stop``.

    Args:
        p, q, inputs, control, trace: as ``magenv.filters.constraint.fuse`` (q updated, trace rows written).
        q_true: (N, 4) truth for the error sums (NaN rows allowed); dist: (N,) µT, summed into err.
        err: (N_ERR,) set to the interval's error sums (``magenv.metrics.E_*``).
        feat: (len(FEATURES),) set to the observation of sample ``stop`` (the last sample at the end).
    """
    cf.fuse(p, q, inputs, control, start, stop, trace)
    error_sums(trace.est, q_true, dist, start, stop, err)  # against truth, as magenv.metrics
    _features(p, inputs, q, trace, start, stop, feat)


@njit(cache=True)
def _features(p, inputs, q, trace, start, stop, feat):
    gyr, acc, mag, h_i, c_j = inputs.gyr, inputs.acc, inputs.mag, inputs.joint_i, inputs.joint_j
    n = gyr.shape[0]
    j = stop if stop < n else n - 1
    m0 = p.field_norm
    dev, mE = cf.mag_deviation(q, mag[j], p)
    mn = np.sqrt(mag[j, 0] ** 2 + mag[j, 1] ** 2 + mag[j, 2] ** 2)
    feat[F.mag_dev] = _clip(dev, F.mag_dev)
    feat[F.norm_dev] = _clip((mn - m0) / m0, F.norm_dev)
    dip = np.rad2deg(np.arcsin(min(1.0, max(-1.0, -mE[2] / mn)))) if mn > 0 else 0.0
    dip0 = np.rad2deg(np.arcsin(min(1.0, max(-1.0, -p.field_dir[2]))))
    feat[F.dip_dev] = _clip((dip - dip0) / DIP_SCALE_DEG, F.dip_dev)
    ch = rotate1(q, h_i[j])
    mis = np.sqrt((ch[0] - c_j[j, 0]) ** 2 + (ch[1] - c_j[j, 1]) ** 2 + (ch[2] - c_j[j, 2]) ** 2)
    feat[F.con_mismatch] = _clip(mis / GRAVITY, F.con_mismatch)
    ja = np.sqrt(c_j[j, 0] ** 2 + c_j[j, 1] ** 2 + (c_j[j, 2] - GRAVITY) ** 2)
    feat[F.joint_acc] = _clip(ja / GRAVITY, F.joint_acc)
    feat[F.gyro_norm] = _clip(np.sqrt(gyr[j, 0] ** 2 + gyr[j, 1] ** 2 + gyr[j, 2] ** 2) / GYRO_SCALE, F.gyro_norm)
    an = np.sqrt(acc[j, 0] ** 2 + acc[j, 1] ** 2 + acc[j, 2] ** 2)
    feat[F.acc_dev] = _clip((an - GRAVITY) / GRAVITY, F.acc_dev)
    seen, ref, con = cf.directions(p, inputs, j)
    jac, dq = np.empty((9, 4)), np.zeros(4)
    s_mag = cf.gn_step(q, seen, ref, 0.0, con, jac, dq)
    s_con = cf.gn_step(q, seen, ref, 1.0, con, jac, dq)
    feat[F.step_mag] = _clip(s_mag, F.step_mag) if np.isfinite(s_mag) else _HIGH[F.step_mag]
    feat[F.step_con] = _clip(s_con, F.step_con) if np.isfinite(s_con) else _HIGH[F.step_con]
    # heading (about ENU up) of the joint-centre acceleration seen from link i minus from link j
    dh = _heading_of(ch) - _heading_of(c_j[j])
    dh = (dh + np.pi) % (2.0 * np.pi) - np.pi
    feat[F.con_heading] = dh / np.pi
    feat[F.w_prev] = trace.weight[stop - 1] if stop > 0 else 0.0
    feat[F.k_prev] = _clip(trace.gain[stop - 1], F.k_prev) if stop > 0 else 0.0
    s = dev
    for i in range(start, stop):
        s += trace.mag_dev[i]
    feat[F.mag_dev_mean] = _clip(s / (stop - start + 1), F.mag_dev_mean)


@dataclass(frozen=True)
class Options:
    """The env's eq. 18 gain rule, checked once (``constraint.check_rule_params``): th2 (a weight), th3 (‖Δq‖),
    gains k_min ≤ k_max (1/s)."""

    th2: float = cf.TH2
    th3: float = cf.TH3
    k_min: float = cf.K_MIN
    k_max: float = cf.K_MAX

    def __post_init__(self):
        _, *checked = cf.check_rule_params(th2=self.th2, th3=self.th3, k_min=self.k_min, k_max=self.k_max)
        for name, value in zip(cf.RULE_PARAMS[1:], checked):
            object.__setattr__(self, name, value)


class ConstraintRunner(TrialRunner):
    """One two-link trial under link i's filter, stepped k samples at a time (the ``MagConstraint-v0`` runner).

    Args:
        trial: a two-link Trial; ``filter_kwargs``: those of ``magenv.filters.constraint.ConstraintFilter``
            (lever arms, th1 … k_max, q0, use_constraint). Raises ``MissingChannelsError`` if the trial
            lacks link j's channels or the lever arms.
        extended: ``feat`` is the EXTENDED observation (base, extra causal features, their lagged copies).

    Attributes as the other runners (``magenv.envs.common.TrustEnv``): ``feat``, ``err``, ``pos``,
    ``last_count``, ``has_dist``, ``est`` (N, 4), ``q_true``; and ``filter`` (the ``ConstraintFilter``),
    ``q`` (4,) the current estimate, ``trace`` (``magenv.filters.constraint.Trace``) the per-sample w, k, …
    """

    def __init__(self, trial: Trial, extended: bool = False, **filter_kwargs):
        self.filter = cf.ConstraintFilter(trial, **filter_kwargs)  # checks link j's channels
        super().__init__(trial)
        self.q = self.filter.q0.copy()
        self.trace = cf.Trace.empty(trial.n)
        self.est = self.trace.est
        self.err = np.zeros(N_ERR)
        self.feat = np.zeros(len(FEATURES))
        self._filter_args = (self.filter.params, self.q, self.filter.inputs)
        self._outputs = (self.trace, self.truth.q_true, self.truth.dist, self.err, self.feat)
        args = (*self._filter_args, cf.Control.of(0.0, 0.0), 0, 0, *self._outputs)
        self._advance = self.compiled(advance, *args)
        self._advance(*args)  # observation of sample 0
        self.extended = bool(extended)
        if self.extended:
            self.memory = constraint_memory.Memory.start(self.q, trial.n, trial.rate)
            self._ring = lagged.ring(constraint_memory.LAGS, len(FEATURES) + len(constraint_memory.EXTRA))
            self.feat = np.zeros(len(EXTENDED))
            self._compose(0, 0)

    def _fuse(self, start: int, stop: int, action) -> None:
        """``action`` = (w ∈ [0, 1], k ≥ 0 or None for eq. 18)."""
        w, k = action
        self._advance(*self._filter_args, cf.Control.of(w, k), start, stop, *self._outputs)
        if self.extended:
            self._compose(start, stop, k is None)

    def _compose(self, start: int, stop: int, gain_by_rule: bool = True) -> None:
        """The extended observation of sample ``stop`` after fusing start:stop (k by eq. 18 or as in ``trace``)."""
        base = self._outputs[-1]
        fed = (self.filter.params, self.filter.inputs, self.trace)
        constraint_memory.update(*fed, self.memory, start, stop, gain_by_rule)
        lagged.compose(base, self.memory.value, *self._ring, stop > start, self.feat)


@document(constraint_memory.EXTRA, "{extended_table}")
@document(FEATURES)
class MagConstraintEnv(TrustEnv):
    """
    ## Description

    Two links joined by a spherical joint each carry a MIMU; link j's
    orientation is known (Jung & Lee 2019 §3.1: from motion capture), link i's
    is estimated. A magnetised tool comes near link i's sensor now and then,
    and the lab's field is itself slightly inhomogeneous. Link i's filter is
    the paper's complementary filter: per sample, one Gauss–Newton step over
    three direction pairs — gravity, the Earth field, and the kinematic
    constraint C(q_i)h_i = C(q_j)h_j (the joint centre's acceleration is the
    same seen from either link, eq. 9) — weighted by
    W = diag(I, (1 − w)I, wI) (eq. 15), applied with gain k (eq. 17).

    The agent sets the constraint weight w once every ``decision_every``
    samples (and, with ``control_gain``, the gain k). The paper sets w by
    eq. 16 from the field deviation and k by eq. 18; its rule is the baseline
    ``magenv.baselines.constraint.ConstraintWeightRule``. w = 1 ignores the
    magnetometer (the heading then rests on the constraint, which only
    informs while the joint centre accelerates); w = 0 is the conventional CF.
    The world is fixed at ``reset()``; the policy changes only the estimate.

    ## Action Space

    `Box(0, 1, (1,), float32)`: w. With ``control_gain=True``:
    `Box(0, 1, (2,), float32)`: [w, k/gain_max]. Without it, k follows eq. 18
    (th2, th3, k_min, k_max) from w and the step size. Finite values outside
    [0, 1] are **clipped** (``info["action_clipped"]``); NaN/inf or a wrong
    shape raise `ValueError`.

    ## Observation Space

    `Box(float32)`, one entry per selected feature (default all, this order).
    Truth never enters it. "Sample j" is the next sample to be fused, read
    before fusing; q is the current estimate q_{j−1}; m0, m_E the trial's
    undisturbed field norm and vector; g = 9.81 m/s²; h_i, h_j the joint
    vectors of eq. 9 (sensor frames), q_j link j's given orientation.
    "Step" is ‖Δq‖ of eq. 14 at q for sample j. Values are clipped to range.

    {observation_table}

    With ``features="extended"`` (``EXTENDED``) the observation is those
    features, the extra causal features below (``magenv.envs.constraint_memory``,
    where the conventions are defined: signed mag and joint headings, parallel
    w = 0 / w = 1 filters, a gyro anchor, smoothed field deviations), and
    copies of both 25 and 100 decisions earlier (1 s and 4 s at k = 4):

    {extended_table}

    ## Rewards

    Minus the mean total orientation error of link i (2·acos|q_e,0|, degrees)
    over the samples fused in the step (0 if none has truth).

    ## Starting State

    A trial is drawn at ``reset``: simulated from the scenario with a seed
    drawn from ``self.np_random`` (``reset(seed=s)`` → the same episode bit for
    bit), or at random from the given Trials, or ``options={"trial": trial}``.
    The filter starts from the e-compass of the first sample (never truth).

    ## Episode End

    Never terminated; truncated when the trial (or its first
    ``episode_seconds``) is used up.

    ## Arguments

    - `scenario` (default `"constraint_random"`): a name from
      ``magenv.scenarios.scenario_names("twolink")`` or a comma list of them
      (a mixture: each reset picks one), trial seeds drawn at or above
      ``magenv.seeding.HELD_OUT_BELOW``; or a Trial or a list of Trials —
      each must carry link j's channels (``extra`` ``gyr_j``, ``acc_j``,
      ``q_j``) and lever arms (``meta`` ``lever_i_m``, ``lever_j_m``).
    - `decision_every` (default 4): samples fused per step (at 100 Hz: 40 ms).
    - `episode_seconds` (default None): only the first seconds of each trial.
    - `control_gain` (default False): the action also sets k.
    - `gain_max` (default 1.0): k = action[1]·gain_max with ``control_gain``.
    - `th2`, `th3`, `k_min`, `k_max` (defaults 0.25, 0.2, 0.01, 0.2): eq. 18 when k is not controlled.
    - `features` (default None = all): names of the observation features to keep, in order, or
      `"extended"` for the extended observation (all of the table below; the 13 above stay the default).
    - `scenario_kwargs` (default None): overrides for ``magenv.scenarios.make_trial``.

    `info` of each step: `t` (s), `sample`, `w`, `k` (mean over the step), `action_clipped`,
    `error_total` / `error_heading` / `error_inclination` (means over the step, °), `disturbance_norm`
    (mean true ‖lab + tool field‖ at link i's sensor, µT; NaN if unknown), `q_est`, `q_true`.
    Per-sample histories of the episode so far: ``env.unwrapped.estimate`` (N, 4),
    ``weights`` (N,) w, ``gains`` (N,) k (NaN where not fused yet); ``lambdas`` is ``weights``
    (for ``magenv.evaluation``: its "trust" 1 − λ is then the magnetometer's weight 1 − w).

    ## Version History

    - v0 (the id stays ``-v0`` until the first release; dates are of the commits):
      2026-12-01 first version (the two-link constraint filter, w per step), the batched vector env;
      2026-12-02 ``features="extended"``; 2026-12-05 gyro-bias features (bias from rest, drift, bias-corrected
      parallel filters); 2026-12-06 the bias-corrected twin applies the env's k where the action sets it.
    """

    action_symbol = action_key = "w"
    observation = (FEATURES, EXTENDED)
    env_name = CONSTRAINT_ID.split("/")[1]

    defaults = EnvOptions(scenario="constraint_random", decision_every=4)

    own_options = Options

    def __init__(self, control_gain: bool = False, gain_max: float = 1.0, **options):
        # bad arguments fail here, not at reset (ValueError / TypeError naming the argument)
        control_gain, gain_max = check_bool("control_gain", control_gain), check_positive("gain_max", gain_max)
        self._setup(action_dim=2 if control_gain else 1, world="twolink", require=cf.require_two_link, **options)
        self.control_gain, self.gain_max = control_gain, gain_max

    def _make_runner(self, trial: Trial) -> ConstraintRunner:
        return ConstraintRunner(trial, self.extended, **asdict(self.options))  # checks link j's channels

    def _decode(self, action) -> tuple[tuple[float, float | None], dict]:
        dim = 2 if self.control_gain else 1  # the action Box's length
        what = "[w, k/gain_max]" if self.control_gain else "w"
        a = action_array(action, f"{what} in [0, 1]")
        if a.shape != (dim,) and not (dim == 1 and a.shape == ()):
            raise ValueError(f"action must have shape ({dim},) holding {what} in [0, 1], got shape {a.shape}")
        a = a.reshape(-1)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action must be finite numbers in [0, 1], got {a.tolist()}")
        c = np.clip(a, 0.0, 1.0)
        clipped = bool(np.any(c != a))
        w = float(c[0])
        k = float(c[1]) * self.gain_max if self.control_gain else None  # None: eq. 18
        return (w, k), {"w": w, "action_clipped": clipped}

    def _step_info(self, runner, start: int) -> dict:
        return {"k": float(np.mean(runner.trace.gain[start : runner.pos]))}  # the mean gain over the step

    # ------------------------------------------------------------ evaluation access

    weights = episode_view("trace.weight", "(N,) constraint weight w per sample (NaN where not fused yet).")

    gains = episode_view("trace.gain", "(N,) gain k per sample (NaN where not fused yet).")

    @property
    def lambdas(self) -> np.ndarray:
        """Alias of ``weights`` for ``magenv.evaluation`` (trust 1 − w = the magnetometer's weight)."""
        return self.weights


class Batch(NamedTuple):
    """The arrays of :class:`MagConstraintVectorEnv`'s kernel: N envs (leading axis N) on the store's rows."""

    th1: float  # eqs. 16 and 18 (constraint.Params), the same for every env
    th2: float
    th3: float
    k_min: float
    k_max: float
    use_constraint: bool
    gain_by_rule: bool  # k by eq. 18 (else the action's)
    dt: np.ndarray  # (N,) per env: sample interval, s …
    m0: np.ndarray  # (N,) … field norm, µT …
    field_dir: np.ndarray  # (N, 3) … unit Earth field, ENU
    q: np.ndarray  # (N, 4) link i's estimates (the filter's state)
    joint_i: np.ndarray  # (M, 3) the store's rows of constraint.Inputs beyond the sensors (ROWS)
    joint_j: np.ndarray
    w: np.ndarray  # (N,) the step's constraint weight
    k: np.ndarray  # (N,) the step's gain (when not by eq. 18)
    est: np.ndarray  # (N, k + 2, 4) scratch Trace of the step's window (magenv.envs.batch.Window)
    weight: np.ndarray  # (N, k + 2)
    gain: np.ndarray  # (N, k + 2)
    mag_dev: np.ndarray  # (N, k + 2)


@njit(cache=True)
def _advance_env(b, s, i, w):
    """Env i of :class:`Batch` (``s``: ``magenv.envs.batch.Steps``) does its step: :func:`advance` on window
    ``w``."""
    fd = b.field_dir[i]
    p = cf.Params(b.dt[i], b.m0[i], (fd[0], fd[1], fd[2]), b.th1, b.th2, b.th3, b.k_min, b.k_max, b.use_constraint)
    r0, r1 = w.r0, w.r1
    inputs = cf.Inputs(s.gyr[r0:r1], s.acc[r0:r1], s.mag[r0:r1], b.joint_i[r0:r1], b.joint_j[r0:r1])
    control = cf.Control(b.w[i], b.k[i], False, b.gain_by_rule)
    trace = cf.Trace(b.est[i], b.weight[i], b.gain[i], b.mag_dev[i])
    advance(p, b.q[i], inputs, control, w.start, w.stop, trace, s.q_true[r0:r1], s.dist[r0:r1], s.err[i], s.feat[i])
    return -1


class MagConstraintVectorEnv(BatchVectorEnv):
    """``num_envs`` MagConstraint envs advanced together: one numba call per ``step`` fuses every env's samples.

    The ``vector_entry_point`` of ``magenv/MagConstraint-v0``; ``actions`` (N, 1), or (N, 2) with
    ``control_gain``. Sub-env i is the single env seeded s + i bit for bit; seeding, autoreset and ``infos``
    (with ``w``; the step's mean k is a single-env info only): see ``magenv.envs.batch.BatchVectorEnv``.
    """

    env_class = MagConstraintEnv
    features = FEATURES
    channels = {**ROWS, "joint_i": ((3,), float), "joint_j": ((3,), float)}
    advance_env = _advance_env

    def _alloc(self, n: int) -> None:
        env = self.template
        self.constants = dict(th1=cf.TH1, **asdict(env.options), use_constraint=True, gain_by_rule=not env.control_gain)
        rows = self.k_steps + 2
        self.dt, self.m0, self.field_dir = np.ones(n), np.ones(n), np.zeros((n, 3))
        self.q = np.zeros((n, 4))
        self.k = np.zeros(n)
        self.trace = cf.Trace(np.zeros((n, rows, 4)), np.zeros((n, rows)), np.zeros((n, rows)), np.zeros((n, rows)))

    def _prepare(self, trial: Trial):
        filt = cf.ConstraintFilter(trial, **asdict(self.template.options))  # checks link j's channels
        truth = Truth.of(trial)
        rows = {**filt.inputs._asdict(), "q_true": truth.q_true, "dist": truth.dist}
        return rows, (filt.params, filt.q0)

    def _start(self, i: int, description) -> None:
        params, q0 = description
        self.dt[i], self.m0[i], self.field_dir[i] = params.dt, params.field_norm, params.field_dir
        self.q[i] = q0

    def _check_actions(self, actions):
        env = self.template
        space = self.single_action_space
        low, high = space.low.astype(np.float64), space.high.astype(np.float64)
        values, clipped = check_box_actions(actions, self.num_envs, low, high)
        if env.control_gain:
            values = values * np.array([1.0, env.gain_max])
        return values, clipped

    def _set_actions(self, values, stepping) -> dict:
        if values is None:
            self.k[:] = 0.0
        elif self.template.control_gain:
            np.copyto(self.k, np.where(stepping, values[:, 1], 0.0))
        return super()._set_actions(values, stepping)  # w

    def _batch(self) -> Batch:
        t, a = self.trace, self.store.arrays
        return Batch(
            **self.constants, dt=self.dt, m0=self.m0, field_dir=self.field_dir, q=self.q, joint_i=a["joint_i"],
            joint_j=a["joint_j"], w=self.action, k=self.k, est=t.est, weight=t.weight, gain=t.gain, mag_dev=t.mag_dev,
        )  # fmt: skip
