"""``magenv/MagKalman-v0``: choose the Kalman gain of the magnetometer update (trust γ ∈ [0, 1])."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from magenv.envs import KALMAN_ID
from magenv.envs.common import LoopVectorEnv, TrustEnv, scalar_action
from magenv.filters import kalman_trust as kt
from magenv.filters.kalman_env import FEATURE_HIGH, FEATURE_LOW, FEATURE_NAMES, KalmanRunner
from magenv.filters.kalman_model import C_A, C_B
from magenv.filters.kalman_threshold import SIGMA_ACC, SIGMA_GYR, SIGMA_MAG, TH_ACC
from magenv.trial import Trial


class MagKalmanEnv(TrustEnv):
    """
    ## Description

    A magnetic/inertial sensor moves while magnets or iron disturb the field
    it measures. Its orientation is estimated by a multiplicative quaternion
    Kalman filter (``magenv.filters.kalman_trust``): the gyroscope predicts,
    the accelerometer corrects the tilt (skipped when | |a| − g | ≥ th_acc,
    survey A7), and the magnetometer corrects the heading with the gain

        δθ = γ · K ν_m,    P ← (I − γKH) P (I − γKH)ᵀ + γ² K R_m Kᵀ

    where ν_m is the earth-frame field innovation, K the Kalman gain (heading
    row only by default) and γ the agent's **trust**, set once every
    ``decision_every`` samples. γ = 1 is the nominal filter, γ = 0 ignores the
    magnetometer exactly (heading from the gyro alone); the Joseph form keeps
    P the covariance of the filter actually run, so its signals stay honest
    observations. Sample 0 initialises the filter (TRIAD on the first
    accelerometer and magnetometer sample); steps fuse samples 1 … N−1. The
    sensor stream and the true orientation are fixed at ``reset()`` (the
    policy changes the estimate, never the world).

    ## Action Space

    `Box(0, 1, (1,), float32)`: γ, the magnetometer trust (gain multiplier; 0
    = ignore the magnetometer, 1 = nominal Kalman gain). Finite values
    outside [0, 1] are **clipped** (``info["action_clipped"]`` says so);
    NaN/inf and any shape other than `(1,)` or `()` raise `ValueError`.

    ## Observation Space

    `Box(float32)`, one entry per selected feature (default: all, in this
    order). Truth never enters it. "Sample j" is the next sample to be fused —
    the one the chosen γ is applied to first — read before fusing: the filter
    *peeks* at it (gyro prediction and accelerometer update on a copy of the
    state, then the magnetometer innovation; nothing is changed), so the
    innovation, NIS, dip and heading std are the a-priori ones of sample j.
    m0 and θ0 are the trial's undisturbed field norm and dip
    (``Trial.field_norm``, ``Trial.field_dip``); g = 9.81 m/s². The window is
    the samples fused in the last step plus sample j. Every value is clipped
    to its range (NaN, e.g. from a zero field, reads 0).

    | Num | Name              | Meaning                                                                  | Unit / scale            | Min | Max |
    |-----|-------------------|--------------------------------------------------------------------------|-------------------------|-----|-----|
    | 0   | `norm_dev`        | field-norm deviation (‖m_j‖ − m0)/m0                                     | fraction of m0          | -1  | 10  |
    | 1   | `dip_dev`         | (θ_j − θ0), θ_j the dip of m_j below the a-priori horizontal             | units of 90°            | -2  | 2   |
    | 2   | `gyro_norm`       | ‖ω_j‖                                                                    | units of 2π rad/s       | 0   | 10  |
    | 3   | `acc_dev`         | (‖a_j‖ − g)/g                                                            | fraction of g           | -1  | 10  |
    | 4   | `innov_norm`      | ‖ν_m,j‖, ν_m = q̂⁻ ⊗ m_j ⊗ q̂⁻* − h_ENU (a-priori innovation)             | fraction of m0          | 0   | 10  |
    | 5   | `innov_east`      | east component of ν_m,j (≈ −heading correction of a full update)         | m0·cos θ0 (≈ rad)       | -10 | 10  |
    | 6   | `log_nis`         | log10(1 + ν_mᵀ S⁻¹ ν_m), NIS χ²₃-distributed if consistent               | decades                 | 0   | 10  |
    | 7   | `heading_std`     | log10 of the a-priori heading std sqrt(P_zz) at sample j                 | decades of 1°           | -4  | 2   |
    | 8   | `trust_prev`      | γ applied in the last step (1 after reset: the TRIAD start uses m fully) | –                       | 0   | 1   |
    | 9   | `norm_dev_max`    | max |norm_dev| over the window                                           | fraction of m0          | 0   | 10  |
    | 10  | `norm_dev_mean`   | mean norm_dev over the window                                            | fraction of m0          | -1  | 10  |
    | 11  | `dip_dev_max`     | max |dip_dev| over the window (each with its own a-priori estimate)      | units of 90°            | 0   | 2   |
    | 12  | `acc_dev_max`     | max |acc_dev| over the window                                            | fraction of g           | 0   | 10  |
    | 13  | `gyro_norm_mean`  | mean gyro_norm over the window                                           | units of 2π rad/s       | 0   | 10  |
    | 14  | `innov_norm_mean` | mean innov_norm over the window                                          | fraction of m0          | 0   | 10  |
    | 15  | `log_nis_mean`    | log10(1 + mean NIS over the window)                                      | decades                 | 0   | 10  |
    | 16  | `model_dist`      | ‖d̂_j‖, magnetometer disturbance of the model-based split (survey A.9–A.10, causal) | fraction of m0 | 0   | 10  |
    | 17  | `model_dist_max`  | max model_dist over the window                                           | fraction of m0          | 0   | 10  |
    | 18  | `field_ref`       | m0, the site's undisturbed field norm (constant per trial; not truth)    | units of 50 µT          | 0   | 20  |

    Physical values are recoverable: m0 = 50·obs[18] µT, ‖m_j‖ − m0 = m0·obs[0]
    µT, dip deviation = 90·obs[1] degrees, NIS = 10^obs[6] − 1, ‖d̂_j‖ =
    m0·obs[16] µT
    (``magenv.baselines.kalman_policies`` relies on this). ``model_dist`` comes from
    a Gauss–Markov reference/disturbance Kalman filter on the magnetometer
    alone (Ligorio & Sabatini 2015, parameters ``model_c_a``, ``model_c_b``),
    which depends on the sensors only, so it is computed once per trial at
    reset; row j uses samples 0 … j only.

    ## Rewards

    Minus the mean total orientation error Δθ = 2·acos(|q_e,0|), degrees, over
    the samples fused in the step (those with truth; 0 if none has truth).

    ## Starting State

    A trial is drawn at ``reset``: from the scenario with a trial seed drawn
    from ``self.np_random`` (``reset(seed=s)`` → the same trial and the same
    episode, bit for bit), at random from the given Trials, or the Trial in
    ``options={"trial": trial}``. The filter starts from TRIAD on sample 0
    (never truth) with P = p0·I (5° per axis).

    ## Episode End

    Never terminated. Truncated when the trial's samples (or the first
    ``episode_seconds`` of them) are used up; the last step may fuse fewer
    than ``decision_every`` samples. An episode has ⌈(N − 1)/k⌉ steps.

    ## Arguments

    - `scenario` (default `"random"`): a name from ``magenv.scenarios.scenario_names()`` or a comma
      list of names (a mixture), trial seeds drawn at or above ``magenv.seeding.HELD_OUT_BELOW``,
      `"recording:PATH"`, a Trial or a list of Trials.
    - `decision_every` (default 8): samples fused per step (k); 1 = a γ per sample.
    - `episode_seconds` (default None): use only the first seconds of each trial; None = whole trial.
    - `features` (default None = all): names of the observation features to keep, in the given order.
    - `sigma_gyr`, `sigma_acc`, `sigma_mag` (defaults 0.5 °/s in rad/s, 0.02 m/s², 0.15 µT: the
      survey's sensor noise): the filter's noise model.
    - `th_acc` (default 0.08 m/s², Table A1): accelerometer gate; ``math.inf`` disables it.
    - `heading_only` (default True): the magnetometer corrects the heading only (Schmidt gain).
    - `model_c_a`, `model_c_b` (defaults 0.1, 1 µT: the survey's): Gauss–Markov parameters of
      the ``model_dist`` feature.
    - `scenario_kwargs` (default None): overrides passed to ``magenv.scenarios.make_trial``.
    - `prefetch` (default False): simulate the next reset's trial meanwhile in a worker process
      (same trials, bit for bit; hides the reset cost when a core is free). ``close()`` stops it.

    `info` of each step: `t` (s, last fused sample), `sample` (index after the step), `trust` (γ),
    `action_clipped`, `error_total` / `error_heading` / `error_inclination` (mean over the step, °,
    NaN without truth), `disturbance_norm` (mean true disturbance ‖·‖ over the step, µT, NaN if the
    trial has none), `q_est`, `q_true` (last fused sample), `repairs` (covariance repairs so far).
    The episode so far, per sample: ``env.unwrapped.estimate`` (N, 4), ``env.unwrapped.trust`` (N,)
    γ, ``env.unwrapped.lambdas`` (N,) = 1 − γ (the MagBlend convention, 0 = full trust, so
    ``magenv.evaluation``'s ``trust = 1 − λ`` is γ), ``env.unwrapped.signals`` (N, 13) the
    filter's signals (``kalman_trust.SIGNALS``); NaN where not fused yet; sample 0 is the start.

    ## Vectorised use

    ``gymnasium.make_vec("magenv/MagKalman-v0", num_envs=n, vectorization_mode="vector_entry_point")``
    gives ``MagKalmanVectorEnv`` (n envs in one process, next-step autoreset).

    ## Version History

    - v0: initial version.
    """

    env_name = KALMAN_ID.split("/")[1]

    def __init__(self, scenario="random", decision_every: int = 8, episode_seconds: float | None = None,
                 features: Sequence[str] | None = None, sigma_gyr: float = SIGMA_GYR, sigma_acc: float = SIGMA_ACC,
                 sigma_mag: float = SIGMA_MAG, th_acc: float = TH_ACC, heading_only: bool = True,
                 model_c_a: float = C_A, model_c_b: float = C_B, scenario_kwargs: dict | None = None,
                 prefetch: bool = False, render_mode: str | None = None):
        self._setup(scenario, decision_every, episode_seconds, render_mode, scenario_kwargs, features,
                    FEATURE_NAMES, FEATURE_LOW, FEATURE_HIGH, prefetch=prefetch)
        if not 0.0 <= model_c_a < 1.0 or not model_c_b > 0.0:
            raise ValueError(f"model_c_a must be in [0, 1) and model_c_b > 0, got {model_c_a!r}, {model_c_b!r}")
        if not th_acc > 0:
            raise ValueError(f"th_acc must be positive (math.inf disables the gate), got {th_acc!r}")
        self.filter_kwargs = dict(sigma_gyr=float(sigma_gyr), sigma_acc=float(sigma_acc), sigma_mag=float(sigma_mag),
                                  th_acc=float(th_acc), heading_only=bool(heading_only))
        kt.make_params(46.0, 49.6, **self.filter_kwargs)  # validate the noise model now, not at the first reset
        self.model_kwargs = dict(model_c_a=float(model_c_a), model_c_b=float(model_c_b))

    def _make_runner(self, trial: Trial) -> KalmanRunner:
        params = kt.make_params(trial.field_norm, trial.field_dip, **self.filter_kwargs)
        return KalmanRunner(trial, params, **self.model_kwargs)

    def step(self, action):
        runner = self._step_runner()
        gamma, clipped = scalar_action(action, "γ")
        runner.advance(self.k_steps, gamma)
        return self._step_result(runner, {"trust": gamma, "action_clipped": clipped}, {"repairs": runner.repairs})

    # ------------------------------------------------------------ evaluation access

    @property
    def trust(self) -> np.ndarray:
        """(N,) γ used per sample (sample 0, the TRIAD start, is 1; NaN where not fused yet)."""
        return self._need_reset().trust

    @property
    def lambdas(self) -> np.ndarray:
        """(N,) 1 − γ: the MagBlend-style "IMU weight" view of the trust, for ``magenv.evaluation``."""
        return 1.0 - self._need_reset().trust

    @property
    def signals(self) -> np.ndarray:
        """(N, 13) the filter's per-sample signals, columns ``kalman_trust.SIGNALS`` (NaN where not fused)."""
        return self._need_reset().sig

    @property
    def model_disturbance(self) -> np.ndarray:
        """(N,) ‖d̂‖ of the model-based split, µT (the ``model_dist`` feature before scaling)."""
        return self._need_reset().mdist


class MagKalmanVectorEnv(LoopVectorEnv):
    """``num_envs`` copies of ``MagKalmanEnv`` in one process (see ``magenv.envs.common.LoopVectorEnv``).

    Registered as the ``vector_entry_point`` of ``magenv/MagKalman-v0``.
    """

    env_class = MagKalmanEnv
