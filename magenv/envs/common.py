"""Pieces every magenv trust environment shares: where trials come from, argument and action checks, a loop VectorEnv.

* :class:`TrialSource` — the ``scenario`` argument (a scenario name or a comma
  list of names, ``"recording:PATH"``, a Trial or a list of Trials) and the
  draw of one trial per ``reset`` from the env's ``np_random``.
* :func:`cut_trial` — the ``episode_seconds`` option.
* :func:`check_env_args` — ``decision_every``, ``episode_seconds``, ``render_mode``.
* :func:`select_features` — the ``features`` option → index array and Box bounds.
* :func:`scalar_action` — one trust value from an action: NaN / wrong shape →
  ValueError, finite out-of-range → clipped.
* :class:`LoopVectorEnv` — ``num_envs`` copies of a single env in one process
  (next-step autoreset), the ``vector_entry_point`` of an env.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import gymnasium as gym
import numpy as np

from magenv.seeding import draw_training_seed
from magenv.trial import Trial

RECORDING_PREFIX = "recording:"


def trial_source(scenario) -> tuple[str, Any]:
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


class TrialSource:
    """Where an env's trials come from; ``draw(rng)`` gives the trial of one reset.

    Args:
        scenario: see :func:`trial_source`.
        scenario_kwargs: overrides passed to ``magenv.scenarios.make_trial``.

    Draws (all from ``rng``, so ``reset(seed=s)`` fixes the trial): one of the
    given Trials; or, for scenarios, the scenario of a mixture and then a trial
    seed at or above ``magenv.seeding.HELD_OUT_BELOW`` (never an evaluation
    seed). A recording is loaded once and returned every time.
    """

    def __init__(self, scenario, scenario_kwargs: dict | None = None):
        self.kind, self.source = trial_source(scenario)
        self.label = scenario if isinstance(scenario, str) else "trials"
        self.scenario_kwargs = dict(scenario_kwargs or {})
        self._recording: Trial | None = None

    def draw(self, rng: np.random.Generator) -> Trial:
        if self.kind == "trials":
            return self.source[int(rng.integers(len(self.source)))]
        if self.kind == "recording":
            if self._recording is None:
                try:
                    from magenv.recordings import load_recording
                except ImportError as exc:
                    raise RuntimeError(f"'recording:' needs magenv.recordings ({exc})") from None
                self._recording = load_recording(self.source)
            return self._recording
        from magenv import scenarios

        names = self.source
        name = names[0] if len(names) == 1 else names[int(rng.integers(len(names)))]
        seed = draw_training_seed(rng)  # never a held-out evaluation seed
        return scenarios.make_trial(name, seed, **self.scenario_kwargs)


def cut_trial(trial: Trial, episode_seconds: float | None) -> Trial:
    """The first ``episode_seconds`` of ``trial`` (at least 2 samples); the trial itself if None or longer."""
    if episode_seconds is None:
        return trial
    n = min(trial.n, max(2, int(round(episode_seconds * trial.rate))))
    return trial if n == trial.n else trial.slice(0, n)


def check_env_args(env_name: str, decision_every, episode_seconds, render_mode) -> int:
    """Validate the options every trust env takes; returns ``decision_every`` as int."""
    if int(decision_every) != decision_every or decision_every < 1:
        raise ValueError(f"decision_every must be a positive integer, got {decision_every!r}")
    if episode_seconds is not None and not episode_seconds > 0:
        raise ValueError(f"episode_seconds must be positive or None, got {episode_seconds!r}")
    if render_mode is not None:
        # TypeError, like an unknown keyword: wrappers that try a render mode first
        # (stable-baselines3's make_vec_env) fall back to none.
        raise TypeError(f"{env_name} has no render modes, got render_mode={render_mode!r}")
    return int(decision_every)


def select_features(features: Sequence[str] | None, names: tuple[str, ...], low: np.ndarray,
                    high: np.ndarray) -> tuple[tuple[str, ...], np.ndarray, bool, gym.spaces.Box]:
    """The ``features`` option: (chosen names, their indices, all-in-order?, observation Box)."""
    chosen = names if features is None else tuple(features)
    unknown = [f for f in chosen if f not in names]
    if unknown or not chosen:
        raise ValueError(f"unknown observation feature(s) {unknown or '(none selected)'}; known: {', '.join(names)}")
    idx = np.array([names.index(f) for f in chosen])
    return chosen, idx, chosen == names, gym.spaces.Box(low[idx], high[idx], dtype=np.float32)


def scalar_action(action, symbol: str = "λ") -> tuple[float, bool]:
    """(value in [0, 1], clipped?) from an action of shape (1,) or ().

    NaN/inf or another shape raise ValueError; finite values outside [0, 1]
    are clipped (and reported as clipped).
    """
    if isinstance(action, np.ndarray) and action.shape == (1,):
        value = float(action[0])
    else:
        a = np.asarray(action, dtype=float)
        if a.shape not in ((1,), ()):
            raise ValueError(f"action must have shape (1,) holding {symbol} in [0, 1], got shape {a.shape}")
        value = float(a.reshape(-1)[0])
    if not math.isfinite(value):
        raise ValueError(f"action {symbol} must be a finite number in [0, 1], got {value}")
    if value < 0.0 or value > 1.0:
        return min(1.0, max(0.0, value)), True
    return value, False


class LoopVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` copies of ``env_class`` in one process, batched arrays in and out.

    Subclasses set ``env_class`` (a single env with a `(1,)` Box action whose
    step ``info`` has ``error_total``). Each sub-env keeps its own
    ``np_random`` (``reset(seed=s)`` seeds sub-env i with s + i), so sub-env i
    replays exactly the single env seeded s + i. Autoreset: next-step (the
    step after a truncation resets that sub-env, ignoring its action, and
    returns its first observation with reward 0). ``infos`` carries
    ``error_total`` (N,) (NaN on autoreset steps).
    """

    metadata = {"autoreset_mode": gym.vector.AutoresetMode.NEXT_STEP, "render_modes": []}
    env_class: type[gym.Env]

    def __init__(self, num_envs: int = 1, **kwargs):
        if int(num_envs) != num_envs or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.num_envs = int(num_envs)
        self.envs = [self.env_class(**kwargs) for _ in range(self.num_envs)]
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
