"""``magenv/MagConstraint-v0``: weigh a kinematic constraint against the magnetometer (Jung & Lee 2019)."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from magenv.envs import CONSTRAINT_ID
from magenv.envs.common import LoopVectorEnv, TrustEnv
from magenv.filters import constraint as cf
from magenv.trial import Trial


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

    | Num | Name           | Meaning                                                              | Unit / scale      | Min | Max |
    |-----|----------------|----------------------------------------------------------------------|-------------------|-----|-----|
    | 0   | `mag_dev`      | ‖C(q)y_M − m_E‖/m0: eq. 16's field deviation                         | fraction of m0    | 0   | 10  |
    | 1   | `norm_dev`     | (‖y_M‖ − m0)/m0                                                      | fraction of m0    | -1  | 10  |
    | 2   | `dip_dev`      | dip of C(q)y_M minus the undisturbed dip                             | units of 90°      | -2  | 2   |
    | 3   | `con_mismatch` | ‖C(q)h_i − C(q_j)h_j‖: joint-centre acceleration mismatch (eq. 9)   | units of g        | 0   | 10  |
    | 4   | `joint_acc`    | ‖C(q_j)h_j − g·up‖: joint-centre free acceleration seen from link j | units of g        | 0   | 10  |
    | 5   | `gyro_norm`    | ‖ω_i‖ of link i's gyroscope                                          | units of 2π rad/s | 0   | 10  |
    | 6   | `acc_dev`      | (‖y_A‖ − g)/g of link i's accelerometer                              | fraction of g     | -1  | 10  |
    | 7   | `step_mag`     | step with w = 0 (gravity + magnetometer)                             | quaternion units  | 0   | 10  |
    | 8   | `step_con`     | step with w = 1 (gravity + constraint)                               | quaternion units  | 0   | 10  |
    | 9   | `con_heading`  | heading of C(q)h_i minus heading of C(q_j)h_j (about ENU up)         | units of 180°     | -1  | 1   |
    | 10  | `w_prev`       | w applied in the last step (0 after reset)                           | –                 | 0   | 1   |
    | 11  | `k_prev`       | k applied to the last fused sample (0 after reset)                   | –                 | 0   | 1   |
    | 12  | `mag_dev_mean` | mean `mag_dev` over the samples fused in the last step and sample j | fraction of m0    | 0   | 10  |

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
    - `features` (default None = all): names of the observation features to keep, in order.
    - `scenario_kwargs` (default None): overrides for ``magenv.scenarios.make_trial``.

    `info` of each step: `t` (s), `sample`, `w`, `k` (mean over the step), `action_clipped`,
    `error_total` / `error_heading` / `error_inclination` (means over the step, °), `disturbance_norm`
    (mean true ‖lab + tool field‖ at link i's sensor, µT; NaN if unknown), `q_est`, `q_true`.
    Per-sample histories of the episode so far: ``env.unwrapped.estimate`` (N, 4),
    ``weights`` (N,) w, ``gains`` (N,) k (NaN where not fused yet); ``lambdas`` is ``weights``
    (for ``magenv.evaluation``: its "trust" 1 − λ is then the magnetometer's weight 1 − w).

    ## Version History

    - v0: initial version.
    """

    env_name = CONSTRAINT_ID.split("/")[1]

    def __init__(self, scenario="constraint_random", decision_every: int = 4, episode_seconds: float | None = None,
                 control_gain: bool = False, gain_max: float = 1.0, th2: float = cf.TH2, th3: float = cf.TH3,
                 k_min: float = cf.K_MIN, k_max: float = cf.K_MAX, features: Sequence[str] | None = None,
                 scenario_kwargs: dict | None = None, render_mode: str | None = None):
        if not (math.isfinite(gain_max) and gain_max > 0):
            raise ValueError(f"gain_max must be a positive number, got {gain_max!r}")
        self._setup(scenario, decision_every, episode_seconds, render_mode, scenario_kwargs, features,
                    cf.FEATURE_NAMES, cf.FEATURE_LOW, cf.FEATURE_HIGH, 2 if control_gain else 1,
                    world="twolink", require=cf.require_two_link)
        self.control_gain = bool(control_gain)
        self.gain_max = float(gain_max)
        self.filter_kwargs = dict(th2=float(th2), th3=float(th3), k_min=float(k_min), k_max=float(k_max))

    def _make_runner(self, trial: Trial) -> cf.ConstraintRunner:
        return cf.ConstraintRunner(trial, **self.filter_kwargs)  # checks link j's channels

    def _action(self, action) -> tuple[float, float, bool]:
        dim = self.action_space.shape[0]
        a = np.asarray(action, dtype=float)
        if a.shape != (dim,) and not (dim == 1 and a.shape == ()):
            what = "[w, k/gain_max]" if self.control_gain else "w"
            raise ValueError(f"action must have shape ({dim},) holding {what} in [0, 1], got shape {a.shape}")
        a = a.reshape(-1)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action must be finite numbers in [0, 1], got {a.tolist()}")
        c = np.clip(a, 0.0, 1.0)
        clipped = bool(np.any(c != a))
        w = float(c[0])
        k = float(c[1]) * self.gain_max if self.control_gain else cf.BY_RULE
        return w, k, clipped

    def step(self, action):
        runner = self._step_runner()
        w, k, clipped = self._action(action)
        start = runner.pos
        runner.advance(self.k_steps, w, k)
        return self._step_result(runner, {"w": w, "k": float(np.mean(runner.k[start:runner.pos])),
                                          "action_clipped": clipped})

    # ------------------------------------------------------------ evaluation access

    @property
    def weights(self) -> np.ndarray:
        """(N,) constraint weight w per sample (NaN where not fused yet)."""
        return self._need_reset().w

    @property
    def gains(self) -> np.ndarray:
        """(N,) gain k per sample (NaN where not fused yet)."""
        return self._need_reset().k

    @property
    def lambdas(self) -> np.ndarray:
        """Alias of ``weights`` for ``magenv.evaluation`` (trust 1 − w = the magnetometer's weight)."""
        return self.weights


class MagConstraintVectorEnv(LoopVectorEnv):
    """``num_envs`` copies of ``MagConstraintEnv`` in one process (see ``magenv.envs.common.LoopVectorEnv``).

    The ``vector_entry_point`` of ``magenv/MagConstraint-v0``; ``actions`` (N, 1), or (N, 2) with ``control_gain``.
    """

    env_class = MagConstraintEnv
