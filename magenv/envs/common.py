"""Pieces every magenv trust environment shares: where trials come from, argument and action checks, a loop VectorEnv.

* :class:`TrialSource` — the ``scenario`` argument (a scenario name or a comma
  list of names, ``"recording:PATH"``, a Trial or a list of Trials; or only
  one world's scenarios and Trials with the channels an env needs) and the
  draw of one trial per ``reset`` from the env's ``np_random``.
* :func:`cut_trial` — the ``episode_seconds`` option.
* :func:`check_env_args` — ``decision_every``, ``episode_seconds``, ``render_mode``.
* :func:`check_reset_args` — ``reset``'s ``seed`` and ``options``.
* :func:`select_features` — the ``features`` option → index array and Box bounds.
* :func:`action_array` — an action as a float array (TypeError naming the action if it is no numbers).
* :func:`scalar_action` — one trust value from an action: NaN / wrong shape →
  ValueError, finite out-of-range → clipped.
* :class:`Truth`, :class:`TrialRunner` — the truth-only arrays of a trial
  and the base of each env's runner (one trial stepped k samples at a time).
* :class:`TrustEnv` — base single env: arguments, reset (trial draw and
  cut), step checks, reward and info from the runner's error sums, and the
  divergence policy: a non-finite estimate or observation raises
  ``FloatingPointError`` naming the step (never a NaN reward or observation).
* :class:`LoopVectorEnv` — ``num_envs`` copies of a single env in one process
  (next-step autoreset), the ``vector_entry_point`` of an env.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import gymnasium as gym
import numba
import numpy as np

from magenv.checks import check_bool, check_int, check_mapping, check_number
from magenv.filters.sensors import Sensors
from magenv.metrics import E_COUNT, E_DIST, E_HEADING, E_INCL, E_TOTAL
from magenv.seeding import draw_training_seed
from magenv.trial import Trial

RECORDING_PREFIX = "recording:"
RESET_OPTIONS = ("trial",)  # the keys ``reset(options=…)`` takes


def trial_source(scenario, world: str | None = None, require: Callable[[Trial], None] | None = None) -> tuple[str, Any]:
    """Classify the ``scenario`` argument: ("trials", [Trial…]), ("recording", path) or ("scenario", [names]).

    A comma list of scenario names is a mixture: each reset picks one at random. ``world`` (a key of
    ``magenv.scenarios.WORLDS``) admits only that world's scenario names (no recordings); ``require`` checks
    each given Trial (raising, e.g., ValueError naming the channels it lacks).
    """
    if isinstance(scenario, Trial):
        scenario = [scenario]
    if isinstance(scenario, (list, tuple)):
        if not scenario or not all(isinstance(t, Trial) for t in scenario):
            raise TypeError("scenario as a sequence must be a non-empty list of magenv.trial.Trial objects")
        for trial in scenario if require is not None else ():
            require(trial)
        return "trials", list(scenario)
    if not isinstance(scenario, str):
        what = "a scenario name, 'recording:PATH'" if world is None else f"a scenario name of the {world!r} world"
        raise TypeError(f"scenario must be {what}, a Trial or a list of Trials, got {type(scenario).__name__}")
    if world is None and scenario.startswith(RECORDING_PREFIX):
        return "recording", scenario[len(RECORDING_PREFIX) :]
    try:
        from magenv import scenarios
    except ImportError as exc:  # the simulator module is missing
        raise RuntimeError(
            f"scenario {scenario!r} needs magenv.scenarios, which cannot be imported ({exc}); "
            "pass a list of Trials or 'recording:PATH' instead"
        ) from None
    known = scenarios.scenario_names(world)
    names = [s.strip() for s in scenario.split(",")]
    bad = [n for n in names if n not in known]
    if bad:
        kind = "" if world is None else f"{scenarios.WORLDS[world].label} "
        only = "" if world is None else f" (this env takes only {kind}trials)"
        raise ValueError(
            f"unknown {kind}scenario(s) {', '.join(map(repr, bad))}; known {kind}scenarios: {', '.join(known)}{only}"
        )
    return "scenario", names


class TrialSource:
    """Where an env's trials come from; ``draw(rng)`` gives the trial of one reset.

    Args:
        scenario: see :func:`trial_source`.
        scenario_kwargs: overrides passed to ``magenv.scenarios.make_trial``.
        prefetch: make the next reset's trial ahead (below).
        world, require: restrict the source to one world's scenarios and check given Trials
            (see :func:`trial_source`).

    Draws (all from ``rng``, so ``reset(seed=s)`` fixes the trial): one of the
    given Trials; or, for scenarios, the scenario of a mixture and then a trial
    seed at or above ``magenv.seeding.HELD_OUT_BELOW`` (never an evaluation
    seed). A recording is loaded once and returned every time.

    With ``prefetch`` (scenarios only), the trial the *next* reset will draw
    (read off a copy of ``rng``) is simulated meanwhile in a worker process,
    so a reset costs little more than a copy. The trial is the same either
    way (``make_trial`` is bit-identical across processes); if the env is
    reseeded, the guess misses and the trial is made on the spot.
    """

    def __init__(
        self,
        scenario,
        scenario_kwargs: dict | None = None,
        prefetch: bool = False,
        world: str | None = None,
        require: Callable[[Trial], None] | None = None,
    ):
        self.kind, self.source = trial_source(scenario, world, require)
        self.label = scenario if isinstance(scenario, str) else "trials"
        self.scenario_kwargs = dict(scenario_kwargs or {})
        self._recording: Trial | None = None
        self.prefetch = bool(prefetch) and self.kind == "scenario"
        self._pending = None  # ((name, seed), Future) of the trial made ahead
        self._pool = None

    def _pick(self, rng: np.random.Generator) -> tuple[str, int]:
        names = self.source
        name = names[0] if len(names) == 1 else names[int(rng.integers(len(names)))]
        return name, draw_training_seed(rng)  # never a held-out evaluation seed

    def _ahead(self, key: tuple[str, int]):
        if self._pool is None:
            import concurrent.futures
            import multiprocessing

            self._pool = concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
        return self._pool.submit(_make_scenario_trial, key[0], key[1], self.scenario_kwargs)

    def close(self) -> None:
        """Stop the prefetch worker, if any."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool, self._pending = None, None

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
        key = self._pick(rng)
        pending, self._pending = self._pending, None
        trial = pending[1].result() if pending is not None and pending[0] == key else None
        if trial is None:
            if pending is not None:
                pending[1].cancel()
            trial = self.make_trial(*key)
        if self.prefetch:
            import copy

            nxt = self._pick(copy.deepcopy(rng))  # what the next reset draws unless the env is reseeded
            self._pending = (nxt, self._ahead(nxt))
        return trial

    def make_trial(self, name: str, seed: int) -> Trial:
        """Trial ``seed`` of scenario ``name`` (``magenv.scenarios.make_trial`` with ``scenario_kwargs``)."""
        from magenv import scenarios

        return scenarios.make_trial(name, seed, **self.scenario_kwargs)


def _make_scenario_trial(name: str, seed: int, scenario_kwargs: dict) -> Trial:
    """``magenv.scenarios.make_trial`` in a prefetch worker process."""
    from magenv import scenarios

    return scenarios.make_trial(name, seed, **scenario_kwargs)


def cut_trial(trial: Trial, episode_seconds: float | None) -> Trial:
    """The first ``episode_seconds`` of ``trial`` (at least 2 samples); the trial itself if None or longer."""
    if episode_seconds is None:
        return trial
    n = min(trial.n, max(2, int(round(episode_seconds * trial.rate))))
    return trial if n == trial.n else trial.slice(0, n)


def check_env_args(env_name: str, decision_every, episode_seconds, render_mode) -> int:
    """Validate the options every trust env takes; returns ``decision_every`` as int.

    ``decision_every`` an integer ≥ 1; ``episode_seconds`` None (the whole trial) or a finite number of
    seconds > 0; ``render_mode`` None. ValueError or TypeError naming the argument (``magenv.checks``).
    """
    check_int("decision_every", decision_every, 1)
    if episode_seconds is not None:
        check_number("episode_seconds (None = the whole trial)", episode_seconds, 0.0, lo_open=True)
    if render_mode is not None:
        # TypeError, like an unknown keyword: wrappers that try a render mode first
        # (stable-baselines3's make_vec_env) fall back to none.
        raise TypeError(f"{env_name} has no render modes, got render_mode={render_mode!r}")
    return int(decision_every)


def check_reset_args(seed, options) -> dict:
    """``reset``'s arguments: ``seed`` None or an integer ≥ 0, ``options`` None or a dict with keys of
    ``RESET_OPTIONS``; returns the options as a dict. TypeError / ValueError naming the argument."""
    if seed is not None:
        if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool):
            raise TypeError(f"seed must be None or an integer ≥ 0, got {seed!r}")
        if seed < 0:
            raise ValueError(f"seed must be None or an integer ≥ 0, got {seed!r}")
    options = check_mapping("options", options)
    unknown = [k for k in options if k not in RESET_OPTIONS]
    if unknown:
        raise ValueError(f"options: unknown key(s) {', '.join(map(repr, unknown))}; known: {', '.join(RESET_OPTIONS)}")
    return options


def select_features(
    features: Sequence[str] | None, names: tuple[str, ...], low: np.ndarray, high: np.ndarray
) -> tuple[tuple[str, ...], np.ndarray, bool, gym.spaces.Box]:
    """The ``features`` option: (chosen names, their indices, all-in-order?, observation Box)."""
    if features is not None and (isinstance(features, str) or not isinstance(features, Sequence)):
        raise TypeError(f"features must be None or a list of feature names, got {features!r}")
    chosen = names if features is None else tuple(features)
    unknown = [f for f in chosen if f not in names]
    if unknown or not chosen:
        raise ValueError(
            f"features: unknown observation feature(s) {unknown or '(none selected)'}; known: {', '.join(names)}"
        )
    idx = np.array([names.index(f) for f in chosen])
    return chosen, idx, chosen == names, gym.spaces.Box(low[idx], high[idx], dtype=np.float32)


def action_array(action, what: str) -> np.ndarray:
    """``action`` as a float array; TypeError naming the action (``what`` it must hold) if it is no numbers."""
    try:
        return np.asarray(action, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(f"action must be numbers ({what}), got {action!r}") from None


def scalar_action(action, symbol: str = "λ") -> tuple[float, bool]:
    """(value in [0, 1], clipped?) from an action of shape (1,) or ().

    NaN/inf or another shape raise ValueError, no numbers TypeError; finite values outside [0, 1]
    are clipped (and reported as clipped).
    """
    if isinstance(action, np.ndarray) and action.shape == (1,) and action.dtype.kind == "f":
        value = float(action[0])
    else:
        a = action_array(action, f"{symbol} in [0, 1]")
        if a.shape not in ((1,), ()):
            raise ValueError(f"action must have shape (1,) holding {symbol} in [0, 1], got shape {a.shape}")
        value = float(a.reshape(-1)[0])
    if not math.isfinite(value):
        raise ValueError(f"action {symbol} must be a finite number in [0, 1], got {value}")
    if value < 0.0 or value > 1.0:
        return min(1.0, max(0.0, value)), True
    return value, False


class Truth(NamedTuple):
    """A trial's truth-only arrays, for the error sums of the reward and ``info`` (never the observation)."""

    q_true: np.ndarray  # (N, 4) true orientation sensor → ENU; NaN rows where unknown
    dist: np.ndarray  # (N,) norm of the true magnetic disturbance, µT (zeros where the trial has none)

    @classmethod
    def of(cls, trial: Trial) -> Truth:
        dist = trial.truth.get("mag_disturbance")
        norm = np.zeros(trial.n) if dist is None else np.linalg.norm(np.asarray(dist, float), axis=-1)
        return cls(trial.q_true, np.ascontiguousarray(norm, float))


_ENTRY_POINTS: dict = {}  # (kernel, _type_key(args)) → the kernel's compiled entry point (TrialRunner.compiled)


def _type_key(value):
    """What numba's type of ``value`` depends on: an array's dtype, dimensions, layout, flags; a tuple's
    class and items; else the Python type."""
    if isinstance(value, np.ndarray):
        flags = value.flags
        return value.dtype.str, value.ndim, flags.c_contiguous, flags.f_contiguous, flags.writeable, flags.aligned
    if isinstance(value, tuple):
        return type(value), tuple(_type_key(v) for v in value)
    return type(value)


class TrialRunner:
    """Base of the env runners: one trial stepped k samples at a time, one action per step.

    Holds ``trial``, its ``sensors`` (:class:`magenv.filters.sensors.Sensors`), ``truth``
    (:class:`Truth`; ``q_true`` is ``truth.q_true``), ``pos`` (the next sample to fuse) and
    ``last_count`` (samples fused by the last step). A subclass builds its filter state in
    ``__init__`` and implements ``_fuse(start, stop, action)``: fuse samples start … stop−1, set
    ``err`` (the error sums, indexed by ``magenv.metrics.E_*``) and ``feat`` (the observation of
    sample ``stop``), and keep ``est`` (N, 4) the estimates so far. ``first`` is the first sample a
    step fuses (1 where sample 0 initialises the filter).
    """

    err: np.ndarray
    feat: np.ndarray
    est: np.ndarray

    def __init__(self, trial: Trial, first: int = 0):
        self.trial = trial
        self.sensors = Sensors.of(trial)
        self.truth = Truth.of(trial)
        self.q_true = self.truth.q_true
        self.has_dist = "mag_disturbance" in trial.truth
        self.pos = first
        self.last_count = 0

    @property
    def n(self) -> int:
        """Samples in the trial."""
        return self.trial.n

    @property
    def done(self) -> bool:
        """All samples fused."""
        return self.pos >= self.trial.n

    @staticmethod
    def compiled(kernel, *args):
        """The numba ``kernel`` compiled (or loaded from its cache) for the types of ``args``, as a callable
        that skips numba's per-call type dispatch (about 0.1 µs per named-tuple field, several µs per
        step for a runner's structures). Call it only with arguments of exactly these types.

        Looked up by :func:`_type_key` (a few µs), not ``numba.typeof`` (hundreds of µs per reset)."""
        key = (kernel, _type_key(args))
        entry = _ENTRY_POINTS.get(key)
        if entry is None:
            entry = _ENTRY_POINTS[key] = kernel.compile(tuple(numba.typeof(a) for a in args))
        return entry

    def _fuse(self, start: int, stop: int, action) -> None:
        raise NotImplementedError

    def advance(self, k: int, action) -> int:
        """Fuse the next ``k`` samples (fewer at the end) with one ``action``; returns the samples fused."""
        start = self.pos
        stop = min(start + k, self.trial.n)
        self._fuse(start, stop, action)
        self.pos = stop
        self.last_count = stop - start
        return stop - start


class TrustEnv(gym.Env):
    """Bookkeeping every trust env shares: arguments, trial per ``reset``, step checks, errors, histories.

    Subclasses call :meth:`_setup` in ``__init__`` and implement
    ``_make_runner(trial)``. A runner has ``feat`` (observation of the next
    sample), ``err`` (the last step's sums, indexed by
    ``magenv.metrics.E_*``), ``pos`` (next sample), ``done``,
    ``last_count``, ``has_dist``, ``est`` (N, 4) and ``q_true`` (N, 4).

    Divergence: should the estimate after a step, or the next observation, hold NaN or inf, ``step``
    raises ``FloatingPointError`` naming the step, its samples and the trial, so no reward, ``info`` or
    observation ever carries a non-finite number (and a NaN estimate never scores as a small error;
    offline, ``magenv.metrics`` charges it 180°).
    """

    metadata = {"render_modes": []}
    env_name = "TrustEnv"  # registered id without the namespace, for messages

    def _setup(
        self,
        scenario,
        decision_every,
        episode_seconds,
        render_mode,
        scenario_kwargs,
        features,
        names: tuple[str, ...],
        low: np.ndarray,
        high: np.ndarray,
        action_dim: int = 1,
        prefetch: bool = False,
        world: str | None = None,
        require: Callable[[Trial], None] | None = None,
    ) -> None:
        """Check the common arguments; set ``k_steps``, ``trials`` (a :class:`TrialSource`), ``scenario``,
        ``features``, the spaces."""
        self.k_steps = check_env_args(self.env_name, decision_every, episode_seconds, render_mode)
        scenario_kwargs = check_mapping("scenario_kwargs", scenario_kwargs)
        prefetch = check_bool("prefetch", prefetch)
        self.trials = TrialSource(scenario, scenario_kwargs, prefetch=prefetch, world=world, require=require)
        self.scenario = self.trials.label
        self.episode_seconds = episode_seconds
        self.features, self._idx, self._all, self.observation_space = select_features(features, names, low, high)
        self.action_space = gym.spaces.Box(0.0, 1.0, (action_dim,), dtype=np.float32)
        self.render_mode = None
        self._runner = None
        self._steps = 0  # steps since the last reset, for the divergence message
        self.trial: Trial | None = None

    def _make_runner(self, trial: Trial):
        raise NotImplementedError

    def close(self) -> None:
        self.trials.close()
        super().close()

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        options = check_reset_args(seed, options)
        super().reset(seed=seed)
        trial = options.get("trial")
        if trial is None:
            trial = self.trials.draw(self.np_random)
        elif not isinstance(trial, Trial):
            raise TypeError(f"options['trial'] must be a magenv.trial.Trial, got {type(trial).__name__}")
        self.trial = cut_trial(trial, self.episode_seconds)
        self._runner = self._make_runner(self.trial)
        self._steps = 0
        info = {
            "trial": self.trial.name,
            "rate": self.trial.rate,
            "n_samples": self.trial.n,
            "field_norm": self.trial.field_norm,
            "field_dip": self.trial.field_dip,
            "sample": self._runner.pos,
        }
        return self._obs(), info

    def _obs(self) -> np.ndarray:
        feat = self._runner.feat
        return (feat if self._all else feat[self._idx]).astype(np.float32)

    def _step_runner(self):
        """The runner, checked for ``step()``: RuntimeError before ``reset()`` or after truncation."""
        runner = self._runner
        name = type(self).__name__
        if runner is None:
            raise RuntimeError(f"{name}.step() called before reset(); call env.reset() first")
        if runner.done:
            raise RuntimeError(f"{name}.step() called after the episode was truncated; call env.reset()")
        return runner

    def _step_result(self, runner, action_info: dict, extra_info: dict | None = None):
        """``step()``'s return after ``runner`` advanced: reward −(mean total error, °) over the step (0 if none
        had truth); info ``t``, ``sample``, ``action_info``, the mean errors (°), ``disturbance_norm`` (µT),
        ``q_est``, ``q_true`` (last fused sample), ``extra_info``."""
        err = runner.err
        cnt = err[E_COUNT]
        if cnt > 0:
            total, heading, incl = err[E_TOTAL] / cnt, err[E_HEADING] / cnt, err[E_INCL] / cnt
            reward = -total
        else:
            total = heading = incl = math.nan
            reward = 0.0
        last = runner.pos - 1
        self._steps += 1
        obs, q_est = self._obs(), runner.est[last].copy()
        if not (math.isfinite(reward) and np.isfinite(q_est).all() and np.isfinite(obs).all()):
            raise FloatingPointError(
                f"{type(self).__name__}: the filter diverged in step {self._steps} after reset (samples "
                f"{runner.pos - runner.last_count}…{last} of trial {self.trial.name!r}): non-finite "
                f"{'observation' if np.isfinite(q_est).all() else 'estimate'}; check the env's filter arguments"
            )
        info = {
            "t": last / self.trial.rate,
            "sample": runner.pos,
            **action_info,
            "error_total": total,
            "error_heading": heading,
            "error_inclination": incl,
            "disturbance_norm": (err[E_DIST] / runner.last_count) if runner.has_dist else math.nan,
            "q_est": q_est,
            "q_true": runner.q_true[last].copy(),
            **(extra_info or {}),
        }
        return obs, float(reward), False, runner.done, info

    def _need_reset(self):
        """The runner of the current episode (RuntimeError before the first ``reset()``)."""
        if self._runner is None:
            raise RuntimeError("no episode yet; call env.reset() first")
        return self._runner

    @property
    def estimate(self) -> np.ndarray:
        """(N, 4) per-sample estimate sensor → ENU of the current episode (NaN rows not fused yet)."""
        return self._need_reset().est


class LoopVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` copies of ``env_class`` in one process, batched arrays in and out.

    Subclasses set ``env_class`` (a single env with a `(d,)` Box action whose
    step ``info`` has ``error_total``; ``actions`` (N, d), or (N,) when d = 1). Each sub-env keeps its own
    ``np_random`` (``reset(seed=s)`` seeds sub-env i with s + i), so sub-env i
    replays exactly the single env seeded s + i. Autoreset: next-step (the
    step after a truncation resets that sub-env, ignoring its action, and
    returns its first observation with reward 0). ``infos`` carries
    ``error_total`` (N,) (NaN on autoreset steps).
    """

    metadata = {"autoreset_mode": gym.vector.AutoresetMode.NEXT_STEP, "render_modes": []}
    env_class: type[gym.Env]

    def __init__(self, num_envs: int = 1, **kwargs):
        self.num_envs = check_int("num_envs", num_envs, 1)
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
        for s in seeds:  # every argument checked before any sub-env resets
            check_reset_args(s, options)
        obs = np.stack([env.reset(seed=s, options=options)[0] for env, s in zip(self.envs, seeds)])
        self._needs_reset[:] = False
        return obs, {}

    def step(self, actions):
        dim = self.single_action_space.shape[0]
        try:
            actions = np.asarray(actions, dtype=np.float32)
        except (TypeError, ValueError):
            raise TypeError(f"actions must be numbers, shape ({self.num_envs}, {dim}), got {actions!r}") from None
        if actions.shape not in ((self.num_envs, dim),) + (((self.num_envs,),) if dim == 1 else ()):
            raise ValueError(f"actions must have shape ({self.num_envs}, {dim}), got {actions.shape}")
        actions = actions.reshape(self.num_envs, dim)
        bad = np.flatnonzero(~np.isfinite(actions).all(axis=1))
        if bad.size:  # refused before any sub-env steps, so none is left a step ahead
            raise ValueError(f"actions must be finite; row(s) {bad.tolist()} hold NaN or inf")
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
