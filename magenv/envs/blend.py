"""``magenv/MagBlend-v0``: choose how far to trust the magnetometer (Fan et al. 2017 blend)."""

from __future__ import annotations

import math
from typing import Any, Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from magenv.filters import stationary as stat
from magenv.filters.blend import (
    E_COUNT, E_DIST, E_HEADING, E_INCL, E_TOTAL, FEATURE_HIGH, FEATURE_LOW, FEATURE_NAMES, BlendRunner,
)
from magenv.filters.madgwick import BETA_DEFAULT
from magenv.seeding import draw_training_seed
from magenv.trial import Trial

RECORDING_PREFIX = "recording:"


def _trial_source(scenario) -> tuple[str, Any]:
    """Classify the ``scenario`` argument: ("trials", [Trial…]), ("recording", path) or ("scenario", [names]).

    A comma list of scenario names is a mixture: each reset picks one at random.
    """
    if isinstance(scenario, Trial):
        return "trials", [scenario]
    if isinstance(scenario, (list, tuple)):
        if not scenario or not all(isinstance(t, Trial) for t in scenario):
            raise TypeError("scenario as a sequence must be a non-empty list of magenv.trial.Trial objects")
        return "trials", list(scenario)
    if not isinstance(scenario, str):
        raise TypeError(f"scenario must be a scenario name, 'recording:PATH', a Trial or a list of Trials, "
                        f"got {type(scenario).__name__}")
    if scenario.startswith(RECORDING_PREFIX):
        return "recording", scenario[len(RECORDING_PREFIX):]
    try:
        from magenv import scenarios
    except ImportError as exc:  # the simulator module is missing
        raise RuntimeError(f"scenario {scenario!r} needs magenv.scenarios, which cannot be imported ({exc}); "
                           "pass a list of Trials or 'recording:PATH' instead") from None
    known = list(scenarios.scenario_names())
    names = [s.strip() for s in scenario.split(",")]
    bad = [n for n in names if n not in known]
    if bad:
        raise ValueError(f"unknown scenario(s) {', '.join(map(repr, bad))}; known scenarios: {', '.join(known)}")
    return "scenario", names


class MagBlendEnv(gym.Env):
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
    degrees = 90·obs[1] (``baselines.rules.FanLambda`` relies on this).

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

    metadata = {"render_modes": []}

    def __init__(self, scenario="random", decision_every: int = 8, episode_seconds: float | None = None,
                 stationary_hold: bool = True, features: Sequence[str] | None = None,
                 beta: float = BETA_DEFAULT, t0: float = stat.T0_S, th_acc_g: float = stat.TH_ACC_G,
                 th_gyro_dps: float = stat.TH_GYRO_DPS, scenario_kwargs: dict | None = None,
                 render_mode: str | None = None):
        if int(decision_every) != decision_every or decision_every < 1:
            raise ValueError(f"decision_every must be a positive integer, got {decision_every!r}")
        if episode_seconds is not None and not episode_seconds > 0:
            raise ValueError(f"episode_seconds must be positive or None, got {episode_seconds!r}")
        if render_mode is not None:
            # TypeError, like an unknown keyword: wrappers that try a render mode first
            # (stable-baselines3's make_vec_env) fall back to none.
            raise TypeError(f"MagBlend-v0 has no render modes, got render_mode={render_mode!r}")
        self._source_kind, self._source = _trial_source(scenario)
        self._recording: Trial | None = None
        self.scenario = scenario if isinstance(scenario, str) else "trials"
        self.k = int(decision_every)
        self.episode_seconds = episode_seconds
        self.stationary_hold = bool(stationary_hold)
        self.filter_kwargs = dict(beta=float(beta), hold=self.stationary_hold, t0=float(t0),
                                  th_acc_g=float(th_acc_g), th_gyro_dps=float(th_gyro_dps))
        self.scenario_kwargs = dict(scenario_kwargs or {})
        names = FEATURE_NAMES if features is None else tuple(features)
        unknown = [f for f in names if f not in FEATURE_NAMES]
        if unknown or not names:
            raise ValueError(f"unknown observation feature(s) {unknown or '(none selected)'}; "
                             f"known: {', '.join(FEATURE_NAMES)}")
        self.features = names
        self._idx = np.array([FEATURE_NAMES.index(f) for f in names])
        self._all = names == FEATURE_NAMES
        self.observation_space = spaces.Box(FEATURE_LOW[self._idx], FEATURE_HIGH[self._idx], dtype=np.float32)
        self.action_space = spaces.Box(0.0, 1.0, (1,), dtype=np.float32)
        self.render_mode = None
        self._runner: BlendRunner | None = None
        self.trial: Trial | None = None

    # ------------------------------------------------------------ trials

    def _draw_trial(self) -> Trial:
        if self._source_kind == "trials":
            return self._source[int(self.np_random.integers(len(self._source)))]
        if self._source_kind == "recording":
            if self._recording is None:
                try:
                    from magenv.recordings import load_recording
                except ImportError as exc:
                    raise RuntimeError(f"'recording:' needs magenv.recordings ({exc})") from None
                self._recording = load_recording(self._source)
            return self._recording
        from magenv import scenarios

        names = self._source
        name = names[0] if len(names) == 1 else names[int(self.np_random.integers(len(names)))]
        seed = draw_training_seed(self.np_random)  # never a held-out evaluation seed
        return scenarios.make_trial(name, seed, **self.scenario_kwargs)

    def _cut(self, trial: Trial) -> Trial:
        if self.episode_seconds is None:
            return trial
        n = min(trial.n, max(2, int(round(self.episode_seconds * trial.rate))))
        return trial if n == trial.n else trial.slice(0, n)

    # ------------------------------------------------------------ API

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        trial = options.get("trial")
        if trial is None:
            trial = self._draw_trial()
        elif not isinstance(trial, Trial):
            raise TypeError(f"options['trial'] must be a magenv.trial.Trial, got {type(trial).__name__}")
        self.trial = self._cut(trial)
        self._runner = BlendRunner(self.trial, **self.filter_kwargs)
        self._has_truth_dist = self._runner.has_dist
        info = {"trial": self.trial.name, "rate": self.trial.rate, "n_samples": self.trial.n,
                "field_norm": self.trial.field_norm, "field_dip": self.trial.field_dip, "sample": 0}
        return self._obs(), info

    def _obs(self) -> np.ndarray:
        feat = self._runner.feat
        return (feat if self._all else feat[self._idx]).astype(np.float32)

    def _lambda(self, action) -> tuple[float, bool]:
        if isinstance(action, np.ndarray) and action.shape == (1,):
            lam = float(action[0])
        else:
            a = np.asarray(action, dtype=float)
            if a.shape not in ((1,), ()):
                raise ValueError(f"action must have shape (1,) holding λ in [0, 1], got shape {a.shape}")
            lam = float(a.reshape(-1)[0])
        if not math.isfinite(lam):
            raise ValueError(f"action λ must be a finite number in [0, 1], got {lam}")
        if lam < 0.0 or lam > 1.0:
            return min(1.0, max(0.0, lam)), True
        return lam, False

    def step(self, action):
        runner = self._runner
        if runner is None:
            raise RuntimeError("MagBlendEnv.step() called before reset(); call env.reset() first")
        if runner.done:
            raise RuntimeError("MagBlendEnv.step() called after the episode was truncated; call env.reset()")
        lam, clipped = self._lambda(action)
        runner.advance(self.k, lam)
        err = runner.err
        cnt = err[E_COUNT]
        if cnt > 0:
            total, heading, incl = err[E_TOTAL] / cnt, err[E_HEADING] / cnt, err[E_INCL] / cnt
            reward = -total
        else:
            total = heading = incl = math.nan
            reward = 0.0
        last = runner.pos - 1
        info = {
            "t": last / self.trial.rate, "sample": runner.pos, "lambda": lam, "action_clipped": clipped,
            "error_total": total, "error_heading": heading, "error_inclination": incl,
            "disturbance_norm": (err[E_DIST] / runner.last_count) if self._has_truth_dist else math.nan,
            "q_est": runner.est[last].copy(), "q_true": runner.q_true[last].copy(),
        }
        return self._obs(), float(reward), False, runner.done, info

    # ------------------------------------------------------------ evaluation access

    @property
    def estimate(self) -> np.ndarray:
        """(N, 4) per-sample blended estimate of the current episode (NaN rows not fused yet)."""
        self._need_reset()
        return self._runner.est

    @property
    def lambdas(self) -> np.ndarray:
        """(N,) λ used per sample (NaN where not fused yet)."""
        self._need_reset()
        return self._runner.lam

    @property
    def stationary(self) -> np.ndarray:
        """(N,) bool, samples the detector flagged stationary (False where not fused yet)."""
        self._need_reset()
        return self._runner.aux[:, 2] > 0.5

    def _need_reset(self):
        if self._runner is None:
            raise RuntimeError("no episode yet; call env.reset() first")


class MagBlendVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` copies of ``MagBlendEnv`` in one process, batched arrays in and out.

    Registered as the ``vector_entry_point`` of ``magenv/MagBlend-v0``:
    ``gymnasium.make_vec("magenv/MagBlend-v0", num_envs=8, vectorization_mode="vector_entry_point")``.
    Each sub-env keeps its own ``np_random`` (``reset(seed=s)`` seeds sub-env
    i with s + i), so sub-env i replays exactly the single env seeded s + i.
    Autoreset: next-step (the step after a truncation resets that sub-env,
    ignoring its action, and returns its first observation with reward 0).
    Steps the sub-envs in one Python loop (each one numba call); ``infos``
    carries ``error_total`` (N,) (NaN on autoreset steps).
    """

    metadata = {"autoreset_mode": gym.vector.AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 1, **kwargs):
        if int(num_envs) != num_envs or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.num_envs = int(num_envs)
        self.envs = [MagBlendEnv(**kwargs) for _ in range(self.num_envs)]
        self.single_observation_space = self.envs[0].observation_space
        self.single_action_space = self.envs[0].action_space
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self.render_mode = None
        self._needs_reset = np.zeros(self.num_envs, bool)

    def reset(self, *, seed=None, options=None):
        if seed is None or isinstance(seed, (int, np.integer)):
            seeds = [None if seed is None else int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"got {len(seeds)} seeds for {self.num_envs} envs")
        obs = np.stack([env.reset(seed=s, options=options)[0] for env, s in zip(self.envs, seeds)])
        self._needs_reset[:] = False
        return obs, {}

    def step(self, actions):
        actions = np.asarray(actions, dtype=np.float32)
        if actions.shape not in ((self.num_envs, 1), (self.num_envs,)):
            raise ValueError(f"actions must have shape ({self.num_envs}, 1), got {actions.shape}")
        actions = actions.reshape(self.num_envs, 1)
        n, f = self.num_envs, self.single_observation_space.shape[0]
        obs = np.empty((n, f), np.float32)
        rewards = np.zeros(n)
        terminated = np.zeros(n, bool)
        truncated = np.zeros(n, bool)
        error = np.full(n, np.nan)
        for i, env in enumerate(self.envs):
            if self._needs_reset[i]:
                obs[i] = env.reset()[0]
                self._needs_reset[i] = False
                continue
            obs[i], rewards[i], terminated[i], truncated[i], info = env.step(actions[i])
            error[i] = info["error_total"]
            self._needs_reset[i] = terminated[i] or truncated[i]
        return obs, rewards, terminated, truncated, {"error_total": error}
