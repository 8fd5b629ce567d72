"""The batched vector env of the trust envs: N envs' filter states as arrays, one compiled call per ``step``.

* :class:`TrialStore` — the per-sample arrays of the episodes a vector env
  has in use, concatenated (one array per channel, rows = samples), each
  episode at an offset; episodes are shared by key between the envs.
* :class:`BatchVectorEnv` — the base of each env's ``vector_entry_point``:
  seeding, trial draws, next-step autoreset, action checks, rewards and
  ``info`` arrays; a subclass holds its filter's state and parameters as
  arrays with a leading axis of N and advances every env in one numba call.

Sub-env i is, bit for bit, the single env seeded s + i: it draws its
trials from its own ``np_random`` with the single env's
:class:`~magenv.envs.common.TrialSource` (the same keys, the same trials),
starts its filter with the runner's own functions, and its kernel runs the
single env's kernel ``advance`` on *windows* of the arrays — the samples of
the step plus the one before and the one after — with scratch outputs of a
few rows instead of per-sample histories, so a vector env keeps no history
(``estimate`` and the other per-sample views are single-env features). An
env may instead give a ``lockstep`` kernel that advances all its envs at once
(MagQSF-v0: ``magenv.envs.qsf_lockstep``, the same numbers as its ``advance``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding
from numba import njit, prange

from magenv.checks import check_int
from magenv.envs.common import TrialRunner, TrustEnv, Truth, check_reset_args, cut_trial
from magenv.filters.sensors import Sensors
from magenv.metrics import N_ERR, N_STEP, S_DIST, S_HEADING, S_INCL, S_REWARD, S_TOTAL, step_means_rows
from magenv.trial import Trial


class TrialStore:
    """Per-sample arrays of the episodes in use, concatenated: one array per channel, an episode's rows at an
    offset.

    Args:
        channels: channel name → (shape of one row, dtype).
        capacity: initial rows.

    :meth:`acquire` gives the offset of an episode (its rows copied in on first use) and counts its users;
    :meth:`release` uncounts one. Episodes nobody uses stay until their rows are needed (oldest first).
    When no free run of rows is long enough, the arrays double (rows keep their offsets; ``version``
    counts the reallocations, so holders of the arrays know to fetch them again).
    """

    def __init__(self, channels: dict[str, tuple[tuple[int, ...], Any]], capacity: int = 1 << 14):
        self.channels = dict(channels)
        self.capacity = int(capacity)
        self.arrays = {k: np.zeros((self.capacity, *shape), dtype) for k, (shape, dtype) in self.channels.items()}
        self.free = [(0, self.capacity)]  # sorted, coalesced runs of free rows (start, length)
        self.entries: dict = {}  # key → [offset, rows, users, description], least recently released first
        self.version = 0

    def __contains__(self, key) -> bool:
        return key in self.entries

    @property
    def rows_used(self) -> int:
        """Rows held by episodes (in use or kept)."""
        return sum(e[1] for e in self.entries.values())

    def get(self, key):
        """(offset, description) of a stored episode, counted as one more user."""
        entry = self.entries[key]
        entry[2] += 1
        return entry[0], entry[3]

    def add(self, key, rows: dict[str, np.ndarray], description) -> int:
        """Store a new episode: ``rows`` holds an (n, …) array per channel; returns its offset (one user)."""
        n = len(next(iter(rows.values())))
        offset = self._allocate(n)
        for name, arr in self.arrays.items():
            arr[offset : offset + n] = rows[name]
        self.entries[key] = [offset, n, 1, description]
        return offset

    def release(self, key) -> None:
        """One user fewer; an episode nobody uses is kept (most recently released last) until evicted."""
        entry = self.entries.get(key)
        if entry is not None:
            entry[2] -= 1
            if entry[2] <= 0:
                self.entries[key] = self.entries.pop(key)  # to the end of the eviction order

    def _allocate(self, n: int) -> int:
        while True:
            for k, (start, length) in enumerate(self.free):
                if length >= n:
                    self.free[k] = (start + n, length - n)
                    if length == n:
                        del self.free[k]
                    return start
            idle = next((key for key, e in self.entries.items() if e[2] <= 0), None)
            if idle is None:
                break
            offset, rows = self.entries.pop(idle)[:2]
            self._free(offset, rows)
        self._grow(n)
        return self._allocate(n)

    def _free(self, start: int, length: int) -> None:
        runs = sorted([*self.free, (start, length)])
        merged = [runs[0]]
        for s, m in runs[1:]:
            if merged[-1][0] + merged[-1][1] == s:
                merged[-1] = (merged[-1][0], merged[-1][1] + m)
            else:
                merged.append((s, m))
        self.free = merged

    def _grow(self, n: int) -> None:
        old = self.capacity
        self.capacity = max(2 * old, old + n)
        for name, (shape, dtype) in self.channels.items():
            arr = np.zeros((self.capacity, *shape), dtype)
            arr[:old] = self.arrays[name]
            self.arrays[name] = arr
        self._free(old, self.capacity - old)
        self.version += 1


def check_box_actions(actions, num_envs: int, low: np.ndarray, high: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(values (N, d) float64 clipped to [low, high], clipped (N,) bool) from ``actions`` (N, d), or (N,) when
    d = 1. A wrong shape or a non-finite value is a ValueError naming the env, actions that are no numbers a
    TypeError."""
    d = low.shape[0]
    try:
        a = np.asarray(actions, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"actions must be numbers, shape ({num_envs}, {d}), got {actions!r}") from None
    if a.shape != (num_envs, d) and not (d == 1 and a.shape == (num_envs,)):
        raise ValueError(f"actions must have shape ({num_envs}, {d}), got {a.shape}")
    a = a.reshape(num_envs, d)
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"actions must be finite; env {i} got {a[i].tolist()}")
    values = np.minimum(np.maximum(a, low), high)
    return values, (values != a).any(axis=1)


#: the store's channels every env has: sensors (rad/s, m/s², µT) and truth (:func:`trial_rows`)
ROWS: dict[str, tuple[tuple[int, ...], Any]] = {
    "gyr": ((3,), float), "acc": ((3,), float), "mag": ((3,), float), "q_true": ((4,), float), "dist": ((), float),
}  # fmt: skip


def trial_rows(trial: Trial) -> dict[str, np.ndarray]:
    """The :data:`ROWS` of ``trial``: its sensors and truth (``magenv.envs.common.Truth``)."""
    truth = Truth.of(trial)
    return {"gyr": trial.gyr, "acc": trial.acc, "mag": trial.mag, "q_true": truth.q_true, "dist": truth.dist}


class Steps(NamedTuple):
    """What every env's batch kernel reads and writes besides its own ``Batch``: N envs on the store's M rows."""

    gyr: np.ndarray  # (M, 3) the store's rows (ROWS): sensors …
    acc: np.ndarray
    mag: np.ndarray
    q_true: np.ndarray  # (M, 4) … and truth
    dist: np.ndarray  # (M,)
    off: np.ndarray  # (N,) each env's first row in the store
    n: np.ndarray  # (N,) samples of each env's episode
    pos: np.ndarray  # (N,) next sample to fuse
    todo: np.ndarray  # (N,) samples to fuse now (0: observation only, −1: nothing)
    err: np.ndarray  # (N, N_ERR) error sums of the step
    feat: np.ndarray  # (N, len(FEATURES)) observations
    failed: np.ndarray  # (N,) −1, or the sample where the env's filter failed


class Window(NamedTuple):
    """Env i's rows for one kernel call: the sample before its step, the step's samples, the one after (so that
    the env's kernel reads and writes exactly what it does for the single env)."""

    start: int  # the step's first sample, counted from the window's first
    stop: int  # one past its last
    base: int  # the window's first sample in the episode
    r0: int  # the window's rows in the store, r0:r1
    r1: int


@njit(cache=True, inline="always")
def window(s, i):
    """The :class:`Window` of env i's ``todo[i]`` samples (:class:`Steps` ``s``)."""
    start = s.pos[i]
    stop = min(start + s.todo[i], s.n[i])
    base, end = max(start - 1, 0), min(stop + 1, s.n[i])
    return Window(start - base, stop - base, base, s.off[i] + base, s.off[i] + end)


@njit(cache=True, inline="always")
def window_rows(s, w):
    """(``Sensors``, ``Truth``) of the rows of window ``w``."""
    return Sensors(s.gyr[w.r0 : w.r1], s.acc[w.r0 : w.r1], s.mag[w.r0 : w.r1]), Truth(
        s.q_true[w.r0 : w.r1], s.dist[w.r0 : w.r1]
    )


@njit
def _advance(advance_env, b, s, i):
    w = window(s, i)
    bad = advance_env(b, s, i, w)
    if bad < 0:
        s.pos[i] = w.base + w.stop
    else:
        s.failed[i] = w.base + bad


@njit
def each_env(advance_env, b, s):
    """The batch kernel of every vector env: each env i with ``todo[i] ≥ 0`` does it, ``advance_env(b, s, i,
    window(s, i))`` → −1, or the window's sample where its filter failed (recorded in ``s.failed``; the env stays
    where it was). Compiled once per process and env (numba caches no function taking a function);
    ``advance_env``, the part that takes long to compile, comes from its cache."""
    for i in range(s.todo.shape[0]):
        if s.todo[i] >= 0:
            _advance(advance_env, b, s, i)


@njit(parallel=True)
def each_env_threads(advance_env, b, s):
    """:func:`each_env` with the envs spread over numba's threads."""
    for i in prange(s.todo.shape[0]):
        if s.todo[i] >= 0:
            _advance(advance_env, b, s, i)


class BatchVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` envs of ``env_class`` advanced together: their state as arrays, one kernel call per step.

    Args:
        num_envs: N.
        parallel: numba threads over the envs (``prange``). Off by default: on the shared 2-core machine the
            threaded kernel made 256 envs 1.5–10× slower than the serial one (``benchmarks/bench_vector.py
            --parallel``); it may pay where cores are free.
        kwargs: the single env's arguments (checked by constructing one, whose spaces and options the vector
            env uses).

    Seeding as for N single envs: ``reset(seed=s)`` seeds sub-env i with s + i (or a list of seeds), and
    sub-env i then replays the single env seeded s + i exactly (same trials, observations, rewards).
    ``reset(options={"trial": trial})`` starts every sub-env on ``trial``. Autoreset: next-step — the step
    after a sub-env's truncation resets it (its action is ignored) and returns its first observation with
    reward 0. ``infos`` (a dict of (N,) arrays; the ``_key`` masks mark the sub-envs that stepped):
    ``error_total``, ``error_heading``, ``error_inclination`` (means over the step, °), ``disturbance_norm``
    (µT), ``action_clipped``, ``sample`` and the env's action value(s); ``reset`` gives ``trial`` (names),
    ``n_samples``, ``sample``.

    Subclasses set ``env_class``, ``features`` (its FeatureTable), ``channels`` (the store's per-sample
    channels: :data:`ROWS` and the env's own), ``first`` (the first sample a step fuses), ``advance_env`` (the
    numba kernel ``(batch, steps, i, window) → −1 or the failing sample`` that does env i's ``todo``;
    :func:`each_env` runs it for every env) or ``lockstep`` (a serial and a threaded kernel ``(batch, steps)``
    doing every env's ``todo`` with :func:`each_env`'s contract, e.g. all envs in lock-step), ``extended_batched``
    (it also computes ``features="extended"``), ``idle_action`` (the action value of an env that does not step)
    and implement ``_alloc(n)``, ``_prepare(trial) → (rows, description)`` (rows: :func:`trial_rows` and the env's
    own), ``_start(i, description)``, ``_batch()`` (the kernel's env arrays, a ``Batch``), ``_failure(i, sample)``
    (the error of a failing filter, if its filter can fail) and, for an action of more than one number,
    ``_set_actions(values, stepping) → action infos``. ``todo[i]`` tells the kernel what env i does: fuse that
    many samples (≥ 1), only compute its observation (0), or nothing (−1).
    """

    metadata = {"autoreset_mode": gym.vector.AutoresetMode.NEXT_STEP, "render_modes": []}
    env_class: type[TrustEnv]
    features: Any  # the env's magenv.envs.features.FeatureTable
    channels: dict[str, tuple[tuple[int, ...], Any]] = ROWS
    idle_action = 0.0  # the action value of the envs that do not step (the single action of _set_actions)
    advance_env: Any  # numba kernel (the _batch() tuple, i): env i does todo[i]
    lockstep: Any = None  # or (serial, threaded) numba kernels (the _batch() tuple, steps): every env does its todo
    extended_batched = False  # the kernel also computes the memory of features="extended"
    first = 0

    def __init__(self, num_envs: int = 1, parallel: bool = False, **kwargs):
        self.num_envs = n = check_int("num_envs", num_envs, 1)
        self.template: Any = self.env_class(**kwargs)  # the env subclass's options (its typed ``options``, …)
        env = self.template
        if env.extended and not self.extended_batched:
            raise ValueError(
                'features="extended" is not batched: use single envs (gym.make, or gym.make_vec with '
                'vectorization_mode="sync")'
            )
        self.env_kwargs = dict(kwargs)
        self.trials = env.trials
        self.trials.cache_size = 0  # the store keeps the trials in use
        self.trials.max_pending = n
        self.k_steps, self.episode_seconds = env.k_steps, env.episode_seconds
        self.single_observation_space = env.observation_space
        self.single_action_space = env.action_space
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, n)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, n)
        self.render_mode = None
        if not isinstance(parallel, (bool, np.bool_)):
            raise TypeError(f"parallel must be True or False, got {parallel!r}")
        self.parallel = bool(parallel)
        self.store = TrialStore(self.channels)
        self._rngs: list[np.random.Generator | None] = [None] * n
        self._episode = np.zeros(n, np.int64)  # episodes since the sub-env's last seeded reset
        self._keys: list = [None] * n
        self._names = np.empty(n, object)
        self._needs_reset = np.zeros(n, bool)
        self._started = False
        self.off = np.zeros(n, np.int64)  # first row of each env's episode in the store
        self.n = np.zeros(n, np.int64)  # samples of each env's episode
        self.pos = np.zeros(n, np.int64)  # next sample to fuse
        self.todo = np.zeros(n, np.int64)  # what the next kernel call does per env (see class docstring)
        self.err = np.zeros((n, N_ERR))  # the last step's error sums (magenv.metrics.E_*)
        self._means = np.zeros((n, N_STEP))  # the last step's rewards and mean errors (magenv.metrics.S_*)
        self.feat = np.zeros((n, len(self.features)))  # observations, all features, float64
        self.has_dist = np.zeros(n, bool)  # the episode's trial has a true disturbance
        self.action = np.full(n, self.idle_action)  # the step's action (the default _set_actions)
        self.failed = np.full(n, -1, np.int64)  # −1, or the sample where the env's filter failed
        self._returns = np.zeros(n)
        self._lengths = np.zeros(n, np.int64)
        self._alloc(n)
        self._args: Any = None
        self._args_version = -1
        self._entry: Any = None

    # ------------------------------------------------------------ subclass interface

    def _alloc(self, n: int) -> None:
        raise NotImplementedError

    def _prepare(self, trial: Trial) -> tuple[dict[str, np.ndarray], Any]:
        raise NotImplementedError

    def _start(self, i: int, description) -> None:
        raise NotImplementedError

    def _set_actions(self, values: np.ndarray | None, stepping: np.ndarray) -> dict:
        """``action`` ← the stepping envs' single action value (``idle_action`` elsewhere, and everywhere when
        ``values`` is None); the ``infos`` entry named as the single env's."""
        if values is None:
            self.action[:] = self.idle_action
            return {}
        np.copyto(self.action, np.where(stepping, values[:, 0], self.idle_action))
        return {self.template.action_key: self.action.copy()}

    def _batch(self) -> tuple:
        raise NotImplementedError

    def _failure(self, i: int, sample: int) -> Exception:
        raise NotImplementedError

    def _run(self) -> None:
        """The one compiled call: every env does ``todo``; then raises ``_failure`` of the first failing env."""
        if self._args_version != self.store.version:
            a = self.store.arrays
            steps = Steps(a["gyr"], a["acc"], a["mag"], a["q_true"], a["dist"], self.off, self.n, self.pos,
                          self.todo, self.err, self.feat, self.failed)  # fmt: skip
            self._args_version = self.store.version
            if self.lockstep is None:
                kernel = each_env_threads if self.parallel else each_env
                self._args = (self.advance_env, self._batch(), steps)
            else:
                kernel, self._args = self.lockstep[1 if self.parallel else 0], (self._batch(), steps)
            self._entry = TrialRunner.compiled(kernel, *self._args)
        self._entry(*self._args)
        bad = np.flatnonzero(self.failed >= 0)
        if bad.size:
            i = int(bad[0])
            sample, self.failed[:] = int(self.failed[i]), -1
            raise self._failure(i, sample)

    def _step_info(self) -> dict:
        """The env's own ``infos`` arrays after a step (beyond the action's)."""
        return {}

    # ------------------------------------------------------------ episodes

    def _begin(self, i: int, trial: Trial | None = None) -> None:
        """Sub-env i starts an episode: on ``trial``, or on the next trial of its own draws."""
        if trial is None:
            rng = self._rngs[i]
            assert rng is not None  # seeded by reset() before any episode
            key = self.trials.pick(rng, int(self._episode[i]))
        else:
            key = ("given", id(trial))
        if key in self.store:
            offset, entry = self.store.get(key)
        else:
            cut = cut_trial(self.trials.trial(key) if trial is None else trial, self.episode_seconds)
            rows, description = self._prepare(cut)
            entry = (cut.n, cut.name, "mag_disturbance" in cut.truth, description, trial)
            offset = self.store.add(key, rows, entry)
        if self._keys[i] is not None:
            self.store.release(self._keys[i])
        self._keys[i] = key
        n, self._names[i], self.has_dist[i], description, _ = entry
        self.off[i], self.n[i], self.pos[i], self.todo[i] = offset, n, self.first, 0
        self._returns[i], self._lengths[i] = 0.0, 0
        self._start(i, description)
        if trial is None and self.trials.prefetch:
            import copy

            rng = self._rngs[i]
            assert rng is not None
            nxt = self.trials.pick(copy.deepcopy(rng), int(self._episode[i]) + 1)
            if nxt not in self.store:
                self.trials.prepare(nxt)

    def _autoreset(self, idx: np.ndarray) -> None:
        for i in idx:
            self._episode[i] += 1
            self._begin(int(i))

    def reset(self, *, seed=None, options=None):
        """``seed`` (None, an integer ≥ 0, or one such per sub-env) and ``options`` are checked as the single env
        checks them (``magenv.envs.common.check_reset_args``), before any sub-env is reset."""
        n = self.num_envs
        if isinstance(seed, (list, tuple, np.ndarray)):
            seeds = list(seed)
            if len(seeds) != n:
                raise ValueError(f"seed: got {len(seeds)} seeds for {n} envs")
            for s in seeds:
                check_reset_args(s, None)
        else:
            check_reset_args(seed, None)
            seeds = [None if seed is None else int(seed) + i for i in range(n)]
        trial = check_reset_args(None, options).get("trial")
        if trial is not None and not isinstance(trial, Trial):
            raise TypeError(f"options['trial'] must be a magenv.trial.Trial, got {type(trial).__name__}")
        for i, s in enumerate(seeds):
            if s is not None or self._rngs[i] is None:
                self._rngs[i], _ = seeding.np_random(s)
                self._episode[i] = 0
            elif self._started:
                self._episode[i] += 1
            self._begin(i, trial)
        self._started = True
        self._needs_reset[:] = False
        self.todo[:] = 0
        self._set_actions(None, np.zeros(n, bool))
        self._run()
        return self._obs(), {"trial": self._names.copy(), "n_samples": self.n.copy(), "sample": self.pos.copy()}

    def _obs(self) -> np.ndarray:
        env = self.template
        return (self.feat if env._all else self.feat[:, env._idx]).astype(np.float32)

    def step(self, actions):
        if not self._started:
            raise RuntimeError(f"{type(self).__name__}.step() called before reset(); call reset() first")
        values, clipped = self._check_actions(actions)
        resetting = self._needs_reset
        stepping = ~resetting
        if resetting.any():
            self._autoreset(np.flatnonzero(resetting))
        np.copyto(self.todo, np.where(stepping, self.k_steps, 0))
        before = self.pos.copy()
        action_info = self._set_actions(values, stepping)
        self._run()
        fused = np.maximum(self.pos - before, 1)
        means = self._means
        step_means_rows(self.err, fused, self.has_dist & stepping, means)
        rewards = means[:, S_REWARD].copy()
        truncated = stepping & (self.pos >= self.n)
        self._needs_reset = truncated.copy()
        self._returns += rewards
        self._lengths += stepping
        infos = {
            "error_total": means[:, S_TOTAL].copy(),
            "error_heading": means[:, S_HEADING].copy(),
            "error_inclination": means[:, S_INCL].copy(),
            "disturbance_norm": means[:, S_DIST].copy(),
            "action_clipped": clipped & stepping,
            "sample": self.pos.copy(),
            **action_info,
            **self._step_info(),
        }
        for key in list(infos):
            infos["_" + key] = stepping
        return self._obs(), rewards, np.zeros(self.num_envs, bool), truncated, infos

    def _check_actions(self, actions) -> tuple[np.ndarray, np.ndarray]:
        space = self.single_action_space
        assert isinstance(space, gym.spaces.Box)
        return check_box_actions(actions, self.num_envs, space.low.astype(np.float64), space.high.astype(np.float64))

    def reset_done(self) -> np.ndarray:
        """Reset now the sub-envs whose episode ended in the last step (instead of at the next step) and return
        their first observations (rows of ``np.flatnonzero`` of the last step's truncations): the same-step
        autoreset that Stable-Baselines3 expects (``magenv.agents.vec_env``). The episodes are the same."""
        idx = np.flatnonzero(self._needs_reset)
        if idx.size:
            self._autoreset(idx)
            self.todo[:] = -1
            self.todo[idx] = 0
            self._set_actions(None, np.zeros(self.num_envs, bool))
            self._run()  # the new episodes' first observations; the other envs do nothing
            self._needs_reset[:] = False
        return self._obs()[idx]

    def episode_statistics(self) -> tuple[np.ndarray, np.ndarray]:
        """(return, steps) of each sub-env's current episode so far."""
        return self._returns.copy(), self._lengths.copy()

    def close_extras(self, **kwargs) -> None:
        if hasattr(self, "template"):  # not when __init__ refused its arguments
            self.template.close()
