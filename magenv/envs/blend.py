"""``magenv/MagBlend-v0``: choose how far to trust the magnetometer (Fan et al. 2017 blend)."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from magenv.envs import BLEND_ID
from magenv.envs.common import LoopVectorEnv, TrustEnv, scalar_action
from magenv.filters import stationary as stat
from magenv.filters.blend import FEATURE_HIGH, FEATURE_LOW, FEATURE_NAMES, BlendRunner
from magenv.filters.madgwick import BETA_DEFAULT
from magenv.trial import Trial


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

    | Num | Name              | Meaning                                                         | Unit / scale          | Min  | Max |
    |-----|-------------------|-----------------------------------------------------------------|-----------------------|------|-----|
    | 0   | `norm_dev`        | field-norm deviation (‖m_j‖ − m0)/m0 (|·| is eq. 15's λ1)       | fraction of m0        | -1   | 10  |
    | 1   | `dip_dev`         | dip deviation (θ_dip − θ0), θ_dip by eq. 18 with q_{j−1}        | units of 90°          | -2   | 2   |
    | 2   | `gyro_norm`       | ‖ω_j‖                                                           | units of 2π rad/s     | 0    | 10  |
    | 3   | `acc_dev`         | accelerometer-norm deviation (‖a_j‖ − g)/g                      | fraction of g         | -1   | 10  |
    | 4   | `stationary`      | sample j stationary by eqs. 11–13                               | 0/1                   | 0    | 1   |
    | 5   | `cand_angle`      | mean angle between the IMU and MIMU candidate updates           | units of 4·β·Δt rad   | 0    | 2   |
    | 6   | `lambda_prev`     | λ applied in the last step (0 after reset)                      | –                     | 0    | 1   |
    | 7   | `norm_dev_max`    | max |norm_dev| over the window                                  | fraction of m0        | 0    | 10  |
    | 8   | `norm_dev_mean`   | mean norm_dev over the window                                   | fraction of m0        | -1   | 10  |
    | 9   | `dip_dev_max`     | max |dip_dev| over the window (each with its own prior estimate) | units of 90°          | 0    | 2   |
    | 10  | `norm_rate`       | rate of change of ‖m‖/m0 over the window                        | units of 10 /s        | -10  | 10  |
    | 11  | `mag_heading`     | heading of the measured horizontal field in the estimated earth frame (0 = north, + = east) | units of 180° | -1 | 1 |
    | 12  | `stationary_frac` | fraction of window samples detected stationary                  | –                     | 0    | 1   |

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
    - `features` (default None = all): names of the observation features to keep, in the given order.
    - `beta` (default 0.1 rad/s): Madgwick gain β (eq. 10).
    - `t0`, `th_acc_g`, `th_gyro_dps` (defaults 0.5 s, 0.04 g, 0.5 °/s): stationary detection (eqs. 11–13).
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

    - v0: initial version.
    """

    env_name = BLEND_ID.split("/")[1]

    def __init__(self, scenario="random", decision_every: int = 8, episode_seconds: float | None = None,
                 stationary_hold: bool = True, features: Sequence[str] | None = None,
                 beta: float = BETA_DEFAULT, t0: float = stat.T0_S, th_acc_g: float = stat.TH_ACC_G,
                 th_gyro_dps: float = stat.TH_GYRO_DPS, scenario_kwargs: dict | None = None,
                 prefetch: bool = False, render_mode: str | None = None):
        self._setup(scenario, decision_every, episode_seconds, render_mode, scenario_kwargs, features,
                    FEATURE_NAMES, FEATURE_LOW, FEATURE_HIGH, prefetch=prefetch)
        self.stationary_hold = bool(stationary_hold)
        self.filter_kwargs = dict(beta=float(beta), hold=self.stationary_hold, t0=float(t0),
                                  th_acc_g=float(th_acc_g), th_gyro_dps=float(th_gyro_dps))

    def _make_runner(self, trial: Trial) -> BlendRunner:
        return BlendRunner(trial, **self.filter_kwargs)

    def step(self, action):
        runner = self._step_runner()
        lam, clipped = scalar_action(action, "λ")
        runner.advance(self.k_steps, lam)
        return self._step_result(runner, {"lambda": lam, "action_clipped": clipped})

    # ------------------------------------------------------------ evaluation access

    @property
    def lambdas(self) -> np.ndarray:
        """(N,) λ used per sample (NaN where not fused yet)."""
        return self._need_reset().lam

    @property
    def stationary(self) -> np.ndarray:
        """(N,) bool, samples the detector flagged stationary (False where not fused yet)."""
        return self._need_reset().aux[:, 2] > 0.5


class MagBlendVectorEnv(LoopVectorEnv):
    """``num_envs`` copies of ``MagBlendEnv`` in one process, batched arrays in and out.

    Registered as the ``vector_entry_point`` of ``magenv/MagBlend-v0``:
    ``gymnasium.make_vec("magenv/MagBlend-v0", num_envs=8, vectorization_mode="vector_entry_point")``.
    Seeding, next-step autoreset and ``infos["error_total"]``: see ``magenv.envs.common.LoopVectorEnv``.
    """

    env_class = MagBlendEnv
