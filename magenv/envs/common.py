"""Pieces every magenv trust environment shares: where trials come from, argument and action checks, a loop VectorEnv.

* :class:`TrialSource` — the ``scenario`` argument (a scenario name or a comma
  list of names, each possibly ``"twin:PATH"`` or ``"twins:DIR"``, the twins of DIR's recordings;
  ``"recording:PATH"``, a Trial or a list of Trials; or only one world's scenarios and Trials with the
  channels an env needs) and the draw of one trial per ``reset`` from the env's ``np_random``.
* :func:`cut_trial` — the ``episode_seconds`` option.
* :func:`check_env_args` — ``decision_every``, ``episode_seconds``, ``render_mode`` (rendering: ``magenv.envs.render``).
* :func:`check_reset_args` — ``reset``'s ``seed`` and ``options``.
* :func:`select_features` — the ``features`` option → index array and Box bounds.
* :func:`action_array` — an action as a float array (TypeError naming the action if it is no numbers).
* :func:`scalar_action` — one trust value from an action: NaN / wrong shape →
  ValueError, finite out-of-range → clipped.
* :class:`Truth`, :class:`TrialRunner` — the truth-only arrays of a trial
  and the base of each env's runner (one trial stepped k samples at a time).
* :class:`EnvOptions` — the options every env takes by keyword (its defaults per env: ``TrustEnv.defaults``).
* :class:`TrustEnv` — base single env: arguments, reset (trial draw and
  cut), step checks, reward and info from the runner's error sums, and the
  divergence policy: a non-finite estimate or observation raises
  ``FloatingPointError`` naming the step (never a NaN reward or observation).
* :class:`TrialPool` — the ``trial_pool`` option: reset trials from a seeded pool.

The batched vector env every env module builds its ``vector_entry_point`` on is ``magenv.envs.batch``.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import operator
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import gymnasium as gym
import numba
import numpy as np
from numba.core.dispatcher import Dispatcher

from magenv.checks import check_bool, check_int, check_mapping, check_number
from magenv.envs import lagged
from magenv.envs.features import FeatureTable
from magenv.envs.render import RenderMixin, check_render_mode
from magenv.filters.sensors import Sensors
from magenv.metrics import N_STEP, step_means
from magenv.seeding import draw_training_seed
from magenv.trial import Trial

RECORDING_PREFIX = "recording:"
RESET_OPTIONS = ("trial",)  # the keys ``reset(options=…)`` takes
TWIN_PREFIXES = ("twin:", "rtwin:")  # a twin or randomised twin scenario "twin:PATH": made by make_trial like any


def trial_source(scenario, world: str | None = None, require: Callable[[Trial], None] | None = None) -> tuple[str, Any]:
    """Classify the ``scenario`` argument: ("trials", [Trial…]), ("recording", path) or ("scenario", [names]).

    A comma list of scenario names is a mixture: each reset picks one at random. An entry
    ``"recording:GLOB"`` (``magenv.recordings.match_recordings``: ``recording:2*`` matches the shipped
    recordings whose names start with 2) is one family of the mixture, held as the tuple of its paths: a
    reset that picks it draws one of its recordings uniformly (``"recording:*"`` alone: every recording).
    ``world`` (a key of ``magenv.scenarios.WORLDS``) admits only that world's scenario names (no
    recordings); ``require`` checks each given Trial (raising, e.g., ValueError naming the channels it lacks).
    """
    if isinstance(scenario, Trial):
        scenario = [scenario]
    if isinstance(scenario, (list, tuple)):
        if not scenario or not all(isinstance(t, Trial) for t in scenario):
            raise TypeError("scenario as a sequence must be a non-empty list of magenv.trial.Trial objects")
        if require is not None:
            for trial in scenario:
                require(trial)
        return "trials", list(scenario)
    if not isinstance(scenario, str):
        what = "a scenario name, 'recording:PATH'" if world is None else f"a scenario name of the {world!r} world"
        raise TypeError(f"scenario must be {what}, a Trial or a list of Trials, got {type(scenario).__name__}")
    if world is None and scenario.startswith(RECORDING_PREFIX) and "," not in scenario:
        pattern = scenario[len(RECORDING_PREFIX) :]
        if not any(c in pattern for c in "*?["):
            return "recording", pattern
    try:
        from magenv import scenarios
    except ImportError as exc:  # the simulator module is missing
        raise RuntimeError(
            f"scenario {scenario!r} needs magenv.scenarios, which cannot be imported ({exc}); "
            "pass a list of Trials or 'recording:PATH' instead"
        ) from None
    known = scenarios.scenario_names(world)
    names: list = [s.strip() for s in scenario.split(",")]
    if world is None:
        names = scenarios.expand_mixture(names)  # "twins:DIR": the twins of DIR's recordings
        names = [recording_family(n) if n.startswith(RECORDING_PREFIX) else n for n in names]
    bad = [
        n
        for n in names
        if isinstance(n, str) and n not in known and not (world is None and n.startswith(TWIN_PREFIXES))
    ]
    if bad:
        kind = "" if world is None else f"{scenarios.WORLDS[world].label} "
        only = "" if world is None else f" (this env takes only {kind}trials)"
        raise ValueError(
            f"unknown {kind}scenario(s) {', '.join(map(repr, bad))}; known {kind}scenarios: {', '.join(known)}{only}"
        )
    return "scenario", names


def recording_family(entry: str) -> tuple[str, ...]:
    """A ``"recording:GLOB"`` entry of a mixture: the paths it matches (``magenv.recordings.match_recordings``),
    one family of the mixture whose reset draws one of them uniformly."""
    try:
        from magenv.recordings import match_recordings
    except ImportError as exc:
        raise RuntimeError(f"'recording:' needs magenv.recordings ({exc})") from None
    return tuple(str(p) for p in match_recordings(entry[len(RECORDING_PREFIX) :]))


class TrialPool(NamedTuple):
    """The ``trial_pool`` option: reset trials drawn from a seeded pool of simulated trials, reused across resets.

    Generation g is ``size`` trial keys (scenario of the mixture and training seed, as a reset without a pool
    draws them) drawn from ``numpy.random.default_rng([seed, g])``; an env's e-th episode since its last
    seeded reset (e = 0, 1, …) draws from generation ⌊e / reuse⌋ the slot ``np_random.integers(size)``. The
    pool therefore depends on the option alone and the draw on the env's ``np_random`` alone: same seed, same
    episodes, whether the trial was simulated for this reset, made ahead by the worker, or already made for
    another env of a vector env. ``reuse`` episodes per generation keep the simulation cost per episode at
    most ``size / (reuse · num_envs)`` trials in a vector env of ``num_envs`` envs.
    """

    size: int  # trials per generation
    reuse: int = 1  # episodes an env draws from one generation before the next
    seed: int = 0  # seed of the pool's trial keys

    @classmethod
    def of(cls, value) -> TrialPool | None:
        """The option as given: None (no pool), a size, a mapping of the fields, or a TrialPool."""
        if value is None or isinstance(value, TrialPool):
            return value
        if isinstance(value, dict):
            unknown = sorted(set(value) - set(cls._fields))
            if unknown:
                raise ValueError(f"trial_pool: unknown key(s) {unknown}; known: {', '.join(cls._fields)}")
            value = cls(**value)
        elif isinstance(value, (int, np.integer)) and not isinstance(value, bool):
            value = cls(int(value))
        elif not isinstance(value, tuple):
            raise TypeError(f"trial_pool must be None, a size, or a mapping {{size, reuse, seed}}, got {value!r}")
        else:
            value = cls(*value)
        for name, lo in (("size", 1), ("reuse", 1), ("seed", 0)):
            v = getattr(value, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ValueError(f"trial_pool {name} must be an integer ≥ {lo}, got {v!r}")
        return cls(int(value.size), int(value.reuse), int(value.seed))


class TrialSource:
    """Where an env's trials come from; ``draw(rng, episode)`` gives the trial of one reset.

    Args:
        scenario: see :func:`trial_source`.
        scenario_kwargs: overrides passed to ``magenv.scenarios.make_trial``.
        prefetch: make the next reset's trial ahead (below).
        world, require: restrict the source to one world's scenarios and check given Trials
            (see :func:`trial_source`).
        trial_pool: scenario trials from a seeded pool (:class:`TrialPool`); None: a new trial every reset.

    Draws (all from ``rng``, so ``reset(seed=s)`` fixes the trial): one of the
    given Trials; or, for scenarios, the scenario of a mixture and then a trial
    seed at or above ``magenv.seeding.HELD_OUT_BELOW`` (never an evaluation
    seed), or with a pool a slot of the episode's generation. A recording is
    loaded once and returned every time. A draw is split in two: :meth:`pick`,
    the key of the trial (``("trials", i)``, ``("recording", path)`` or
    ``("scenario", name, seed)``), and :meth:`trial`, the trial of a key
    (a batched vector env keeps trials by key and shares them between its envs).

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
        trial_pool=None,
    ):
        self.kind, self.source = trial_source(scenario, world, require)
        self.label = scenario if isinstance(scenario, str) else "trials"
        self.scenario_kwargs = dict(scenario_kwargs or {})
        self.pool = TrialPool.of(trial_pool)
        self._recordings: dict[str, Trial] = {}  # path → recording, each loaded once
        self.prefetch = bool(prefetch) and self.kind == "scenario"
        self._pending: dict = {}  # key → Future of the trials being made ahead, oldest first
        self.max_pending = 1  # guesses kept; a vector env raises it to its number of envs
        self._pool: Any = None  # a ProcessPoolExecutor once prefetching starts
        self._generations: dict[int, list] = {}  # the pool's generations drawn so far (the latest few)
        self._cache: dict = {}  # key → pool trial, most recently used last
        self.cache_size = 0 if self.pool is None else self.pool.size  # pool trials kept (0: none)

    def _pick(self, rng: np.random.Generator) -> tuple:
        names = self.source
        name = names[0] if len(names) == 1 else names[int(rng.integers(len(names)))]
        if isinstance(name, tuple):  # a recording family ("recording:GLOB"): one of its files
            return "recording", name[0] if len(name) == 1 else name[int(rng.integers(len(name)))]
        return "scenario", name, draw_training_seed(rng)  # never a held-out evaluation seed

    def generation(self, g: int) -> list:
        """The keys of the pool's generation ``g`` (:class:`TrialPool`)."""
        keys = self._generations.get(g)
        pool = self.pool
        if keys is None:
            if pool is None:
                raise RuntimeError("generation() needs a trial_pool")
            rng = np.random.default_rng([pool.seed, g])
            keys = self._generations[g] = [self._pick(rng) for _ in range(pool.size)]
            while len(self._generations) > 8:
                del self._generations[min(self._generations)]
        return keys

    def pick(self, rng: np.random.Generator, episode: int = 0) -> tuple:
        """The key of the trial of an env's reset: ``episode`` counts its episodes since its last seeded reset
        (it matters with a pool only)."""
        if self.kind == "trials":
            return "trials", int(rng.integers(len(self.source)))
        if self.kind == "recording":
            return "recording", self.source
        if self.pool is None:
            return self._pick(rng)
        keys = self.generation(episode // self.pool.reuse)
        return keys[int(rng.integers(len(keys)))]

    def _ahead(self, key: tuple):
        if self._pool is None:
            import concurrent.futures
            import multiprocessing

            self._pool = concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
        return self._pool.submit(_make_scenario_trial, key[1], key[2], self.scenario_kwargs)

    def prepare(self, key: tuple) -> None:
        """With ``prefetch``: start making the trial of scenario ``key`` in the worker (the oldest guess beyond
        ``max_pending`` is dropped)."""
        if not self.prefetch or key[0] != "scenario" or key in self._pending or key in self._cache:
            return
        self._pending[key] = self._ahead(key)
        while len(self._pending) > self.max_pending:
            self._pending.pop(next(iter(self._pending))).cancel()

    def close(self) -> None:
        """Stop the prefetch worker, if any."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool, self._pending = None, {}

    def trial(self, key: tuple) -> Trial:
        """The trial of ``key`` (:meth:`pick`): a given Trial, the recording, or the scenario trial — from the
        pool's cache, from the worker, or made now."""
        if key[0] == "trials":
            return self.source[key[1]]
        if key[0] == "recording":
            trial = self._recordings.get(key[1])
            if trial is None:
                try:
                    from magenv.recordings import load_recording
                except ImportError as exc:
                    raise RuntimeError(f"'recording:' needs magenv.recordings ({exc})") from None
                trial = self._recordings[key[1]] = load_recording(key[1])
            return trial
        trial = self._cache.pop(key, None)
        if trial is None:
            pending = self._pending.pop(key, None)
            trial = pending.result() if pending is not None else self.make_trial(key[1], key[2])
        if self.cache_size > 0:
            self._cache[key] = trial  # most recently used last
            while len(self._cache) > self.cache_size:
                del self._cache[next(iter(self._cache))]
        return trial

    def draw(self, rng: np.random.Generator, episode: int = 0) -> Trial:
        """The trial of a reset (:meth:`pick` then :meth:`trial`); with ``prefetch``, the next reset's trial is
        started in the worker."""
        trial = self.trial(self.pick(rng, episode))
        if self.prefetch:
            import copy

            self.prepare(self.pick(copy.deepcopy(rng), episode + 1))  # unless the env is reseeded
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
    seconds > 0; ``render_mode`` None or one of ``magenv.envs.render``'s modes. ValueError or TypeError
    naming the argument (``magenv.checks``).
    """
    check_int("decision_every", decision_every, 1)
    if episode_seconds is not None:
        check_number("episode_seconds (None = the whole trial)", episode_seconds, 0.0, lo_open=True)
    check_render_mode(env_name, render_mode)
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
    if isinstance(value, Dispatcher):  # a numba function as an argument: its type is the function itself
        return value
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
    _args: tuple  # the kernel's leading arguments (the filter's state and the trial's arrays)

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

    def _start(self, kernel, action, *more) -> None:
        """``_advance``: ``kernel`` compiled for ``(*self._args, action, start, stop, *more)`` (``_more`` keeps
        ``more``); then the observation of sample ``pos``, nothing fused, with the action value ``action``."""
        self._more = more
        self._advance = self.compiled(kernel, *self._args, action, self.pos, self.pos, *more)
        self._fuse(self.pos, self.pos, action)

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


def episode_view(path: str, doc: str) -> Any:
    """A read-only property of an env: its current episode's runner's attribute ``path`` (dotted), RuntimeError
    before the first ``reset()``."""
    get = operator.attrgetter(path)
    return property(lambda env: get(env._need_reset()), doc=doc)


@dataclasses.dataclass(frozen=True, kw_only=True)
class EnvOptions:
    """The options every trust env takes, by keyword (``gymnasium.make(env_id, **options)``).

    Attributes:
        scenario: where the trials come from (:func:`trial_source`).
        decision_every: samples fused per step (k ≥ 1).
        episode_seconds: each trial cut to this long, s (:func:`cut_trial`; None: the whole trial).
        features: the observation (names, ``"extended"`` for the memory features; None: the env's FEATURES).
        scenario_kwargs: overrides passed to ``magenv.scenarios.make_trial``.
        prefetch: make the next reset's trial ahead in a worker process (:class:`TrialSource`).
        trial_pool: reset trials from a seeded pool (:class:`TrialPool`; None: a new trial every reset).
        render_mode: ``"rgb_array"`` or None (``magenv.envs.render``).
    """

    scenario: Any = "random"
    decision_every: int = 8
    episode_seconds: float | None = None
    features: Sequence[str] | None = None
    scenario_kwargs: dict | None = None
    prefetch: bool = False
    trial_pool: Any = None
    render_mode: str | None = None


def options_signature(init: Callable, defaults: EnvOptions, own_options: type | None = None) -> inspect.Signature:
    """``init``'s signature with its ``**options`` spelled out, keyword-only: the fields of the env's
    ``own_options`` dataclass (if any) at their defaults, then the :class:`EnvOptions` fields at the env's
    ``defaults``."""
    sig = inspect.signature(init)
    given = [p for p in sig.parameters.values() if p.kind is not inspect.Parameter.VAR_KEYWORD]
    keyword = [(f, f.default) for f in dataclasses.fields(own_options)] if own_options else []
    keyword += [(f, getattr(defaults, f.name)) for f in dataclasses.fields(EnvOptions)]
    return sig.replace(
        parameters=given
        + [inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=d, annotation=f.type) for f, d in keyword]
    )


class TrustEnv(RenderMixin, gym.Env):
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

    env_name = "TrustEnv"  # registered id without the namespace, for messages
    action_symbol = "λ"  # the scalar action's symbol in messages (:meth:`_decode`)
    action_key = "lambda"  # and its ``info`` key
    observation: tuple[FeatureTable, FeatureTable]  # the env's FEATURES and EXTENDED tables (``features`` option)
    extended = False  # the observation is EXTENDED's (memory features)
    defaults = EnvOptions()  # this env's defaults of the shared options (its scenario, decision_every)
    own_options: type | None = None  # a dataclass of the env's own options that ``**options`` also takes

    def __init_subclass__(cls, **kwargs):
        """An env whose ``__init__`` ends in ``**options`` shows the options it takes there (``own_options``, then
        :class:`EnvOptions` with the env's ``defaults``) in its signature, for ``help``, the docs and the
        argument tests."""
        super().__init_subclass__(**kwargs)
        init = cls.__dict__.get("__init__")
        if init is not None and "options" in inspect.signature(init).parameters:
            init.__signature__ = options_signature(init, cls.defaults, cls.own_options)

    def _setup(
        self,
        *,
        action_dim: int = 1,
        world: str | None = None,
        require: Callable[[Trial], None] | None = None,
        **options,
    ) -> None:
        """Check the options every env shares (:class:`EnvOptions` by keyword, over the env's ``defaults``;
        ``features`` selects from the env's ``observation`` tables, ``magenv.envs.lagged.observation_table``);
        set ``k_steps``, ``trials`` (a :class:`TrialSource`), ``scenario``, ``features``, ``extended``, the
        spaces; then, for an env with ``own_options``, ``options`` (that dataclass of the keywords it names)."""
        own = {f.name for f in dataclasses.fields(self.own_options)} if self.own_options else set()
        o = dataclasses.replace(self.defaults, **{k: v for k, v in options.items() if k not in own})  # TypeError
        self.k_steps = check_env_args(self.env_name, o.decision_every, o.episode_seconds, o.render_mode)
        self.trials = TrialSource(
            o.scenario,
            check_mapping("scenario_kwargs", o.scenario_kwargs),
            prefetch=check_bool("prefetch", o.prefetch),
            world=world,
            require=require,
            trial_pool=o.trial_pool,
        )
        self.episode = 0  # episodes since the last seeded reset (a trial pool's generation counts them)
        self.scenario = self.trials.label
        self.episode_seconds = o.episode_seconds
        features, table = lagged.observation_table(o.features, *self.observation)
        self.extended = table is self.observation[1]
        self.features, self._idx, self._all, self.observation_space = select_features(
            features, table.names, table.low, table.high
        )
        self.action_space = gym.spaces.Box(0.0, 1.0, (action_dim,), dtype=np.float32)
        self.render_mode = o.render_mode
        self._runner: Any = None  # the env's TrialRunner subclass after reset
        self._steps = 0  # steps since the last reset, for the divergence message
        self._means = np.zeros(N_STEP)  # the last step's reward and mean errors (magenv.metrics.step_means)
        self.trial: Trial | None = None
        if self.own_options:  # checked now, not at reset (ValueError / TypeError naming the argument)
            self.options = self.own_options(**{k: v for k, v in options.items() if k in own})

    def _make_runner(self, trial: Trial):
        raise NotImplementedError

    def close(self) -> None:
        self.trials.close()
        self._close_view()
        super().close()

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        options = check_reset_args(seed, options)
        super().reset(seed=seed)
        self.episode = 0 if seed is not None else self.episode + (self._runner is not None)
        trial = options.get("trial")
        if trial is None:
            trial = self.trials.draw(self.np_random, self.episode)
        elif not isinstance(trial, Trial):
            raise TypeError(f"options['trial'] must be a magenv.trial.Trial, got {type(trial).__name__}")
        self.trial = cut_trial(trial, self.episode_seconds)
        self._runner = self._make_runner(self.trial)
        self._steps = 0
        self._step_means = TrialRunner.compiled(step_means, self._runner.err, 1, self._runner.has_dist, self._means)
        info = {
            "trial": self.trial.name,
            "rate": self.trial.rate,
            "n_samples": self.trial.n,
            "field_norm": self.trial.field_norm,
            "field_dip": self.trial.field_dip,
            "sample": self._runner.pos,
        }
        if self.render_mode == "human":
            self.render()
        return self._obs(), info

    def _obs(self) -> np.ndarray:
        feat = self._runner.feat
        return (feat if self._all else feat[self._idx]).astype(np.float32)

    def _decode(self, action) -> tuple[Any, dict]:
        """Hook: (the runner's action, its ``info`` entries) from ``step``'s ``action``. By default one trust
        value in [0, 1] (:func:`scalar_action`, named ``action_symbol`` in messages, ``action_key`` in info)."""
        value, clipped = scalar_action(action, self.action_symbol)
        return value, {self.action_key: value, "action_clipped": clipped}

    def _step_info(self, runner, start: int) -> dict:
        """Hook: the env's own ``info`` entries after a step that fused samples ``start`` … ``runner.pos``−1."""
        return {}

    def step(self, action):
        """Fuse the next ``decision_every`` samples with ``action`` (the hooks :meth:`_decode` and
        :meth:`_step_info` are what an env adds); RuntimeError before ``reset()`` or after truncation.

        Returns reward −(mean total error, °) over the step (0 if no sample had truth;
        ``magenv.metrics.step_means``); info ``t``, ``sample``, the action's entries, the mean errors (°),
        ``disturbance_norm`` (µT), ``q_est``, ``q_true`` (last fused sample), the env's entries."""
        runner = self._runner
        name = type(self).__name__
        if runner is None:
            raise RuntimeError(f"{name}.step() called before reset(); call env.reset() first")
        if runner.done:
            raise RuntimeError(f"{name}.step() called after the episode was truncated; call env.reset()")
        value, action_info = self._decode(action)
        start = runner.pos
        runner.advance(self.k_steps, value)
        means = self._means
        self._step_means(runner.err, runner.last_count, runner.has_dist, means)
        reward, total, heading, incl, dist = means.tolist()
        last = runner.pos - 1
        trial = self.trial
        assert trial is not None  # set with the runner by reset()
        self._steps += 1
        obs, q_est = self._obs(), runner.est[last].copy()
        # x·x is finite exactly when every entry is (no overflow: a unit quaternion, and features clipped to
        # ranges within ±1e3), at a quarter of the cost of np.isfinite(x).all()
        if not (math.isfinite(reward) and math.isfinite(q_est.dot(q_est)) and math.isfinite(obs.dot(obs))):
            raise FloatingPointError(
                f"{name}: the filter diverged in step {self._steps} after reset (samples "
                f"{runner.pos - runner.last_count}…{last} of trial {trial.name!r}): non-finite "
                f"{'observation' if np.isfinite(q_est).all() else 'estimate'}; check the env's filter arguments"
            )
        info = {
            "t": last / trial.rate,
            "sample": runner.pos,
            **action_info,
            "error_total": total,
            "error_heading": heading,
            "error_inclination": incl,
            "disturbance_norm": dist,
            "q_est": q_est,
            "q_true": runner.q_true[last].copy(),
            **self._step_info(runner, start),
        }
        if self.render_mode == "human":
            self.render()
        return obs, reward, False, runner.done, info

    def _need_reset(self):
        """The runner of the current episode (RuntimeError before the first ``reset()``)."""
        if self._runner is None:
            raise RuntimeError("no episode yet; call env.reset() first")
        return self._runner

    estimate = episode_view(
        "est", "(N, 4) per-sample estimate sensor → ENU of the current episode (NaN rows not fused yet)."
    )
