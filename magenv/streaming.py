"""Orientation from your own IMU data with any method's magnetometer trust: whole arrays, or sample by sample.

A method is any name of ``magenv.registry`` (a rule, VQF, Fusion, a shipped ``pretrained:ENV_ID`` or a trained
``agent:RUN`` agent) or a method object. Your data need no truth: :func:`own_trial` wraps gyroscope (rad/s),
accelerometer (m/s²) and magnetometer (µT) samples, sensor frame, at ``rate`` Hz, in a ``Trial`` whose truth
is missing, with the local Earth field (norm µT, dip °) given or estimated from the data (:func:`site_field`);
:func:`estimate` runs the method over it exactly as ``magenv compare`` runs it on a trial (a policy inside its
env, ``magenv.evaluation.estimate``). ``magenv estimate`` (``magenv.train.estimate``) is this on a file.

:class:`TrustFilter` is the same estimate as a streaming filter::

    f = TrustFilter("pretrained:magenv/MagVQF-v0", rate=100.0, field_norm=49.0, field_dip=64.0)
    for g, a, m in samples:
        q = f.update(g, a, m)     # (0, 4) or (k, 4): the quaternions the sample completed
    q_last = f.finish()           # the rest
    f.estimate, f.trust           # (N, 4), (N,) so far

A policy decides once per window of k samples (its env's ``decision_every``) from the observation of the
window's first sample; the env fuses the window and computes the next observation from the sample after it.
So a window's quaternions are final when the sample after the window arrives: ``update`` returns them then
(k rows), else an empty (0, 4) array; the latency is k samples (k / rate s). The numbers are the env's on the
same samples bit for bit (and :func:`estimate`'s). Streaming runs the env on a buffer that grows by doubling
(re-stepping the recorded decisions into the larger one), so envs whose runners read each sample only when
they fuse it stream (:data:`STREAMING_ENVS`); the others precompute causal signals over the whole trial at
reset (MagKalman-v0's model disturbance, MagQSF-v0's detector) and run on whole arrays only (:func:`estimate`,
``TrustFilter.run``), as do complete estimators (``vqf``, ``fusion``: no env).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from magenv import evaluation, registry
from magenv.envs import BLEND_ID, VQF_ID
from magenv.protocols import is_policy
from magenv.recordings import REST_MIN_SECONDS, check_physical, dip_angle, initial_rest
from magenv.trial import Trial

#: envs whose runners read each sample only when they fuse it: a growing buffer streams them exactly
STREAMING_ENVS = (BLEND_ID, VQF_ID)
PROBE_FIELD = (50.0, 60.0)  # (µT, °): the field of a trial checked before its own field is estimated from it
START_CAPACITY = 1 << 12  # samples of the first streaming buffer


@dataclass
class Estimation:
    """A method's output on one input: ``q`` (N, 4) sensor → ENU ``[w, x, y, z]``; ``trust`` (N,) the
    magnetometer trust it applied per sample (the policy's, 1 − λ for MagBlend-v0; an estimator's own, or
    None); the ``method`` name and the ``trial`` it ran on (rate, field)."""

    method: str
    trial: Trial
    q: np.ndarray
    trust: np.ndarray | None


def site_field(gyr, acc, mag, rate: float) -> tuple[float, float, str]:
    """The local Earth field (norm µT, dip °, source) of data without a known site: the medians over the
    initial rest (``magenv.recordings.initial_rest``) if it lasts at least 1 s, else over all samples."""
    rest = initial_rest(gyr, rate)
    rows = rest if rest.stop - rest.start >= REST_MIN_SECONDS * rate else slice(0, len(gyr))
    m, a = np.asarray(mag[rows], float), np.asarray(acc[rows], float)
    norm, dip = float(np.median(np.linalg.norm(m, axis=1))), float(np.median(dip_angle(a, m)))
    return norm, dip, "initial_rest" if rows is rest else "all_samples"


def own_trial(gyr, acc, mag, rate: float, field_norm: float | None = None, field_dip: float | None = None,
              name: str = "own", check: bool = True) -> Trial:  # fmt: skip
    """Samples of your own as a Trial without truth (``q_true`` NaN, nothing scored): gyr rad/s, acc m/s²,
    mag µT, (N, 3) each, sensor frame, at ``rate`` Hz; the field given (norm µT, dip °) or :func:`site_field`
    (``meta["field_source"]`` says which). With ``check``, the magnitudes are held to the declared units first
    (``magenv.recordings.check_physical``: a ValueError naming the likely unit, or warnings). TrialError /
    ValueError naming the problem."""
    gyr, acc, mag = (np.ascontiguousarray(x, float) for x in (gyr, acc, mag))
    if (field_norm is None) != (field_dip is None):
        raise ValueError("give both field_norm (µT) and field_dip (°), or neither (estimated from the data)")
    n = len(gyr)
    trial = Trial(name=name, rate=rate, gyr=gyr, acc=acc, mag=mag, q_true=np.full((n, 4), np.nan),
                  field_norm=PROBE_FIELD[0] if field_norm is None else field_norm,
                  field_dip=PROBE_FIELD[1] if field_dip is None else field_dip, score_mask=np.zeros(n, bool),
                  meta={"source": "own", "field_source": "given"})  # fmt: skip
    if check:
        for warning in check_physical(trial, name):
            warnings.warn(warning, stacklevel=2)
    if field_norm is None:
        norm, dip, source = site_field(gyr, acc, mag, rate)
        trial = dataclasses.replace(trial, field_norm=norm, field_dip=dip, meta={**trial.meta, "field_source": source})
    return trial


def method_of(method):
    """A method object: ``method`` itself, or ``registry.make(method)`` for a name."""
    return registry.make(method) if isinstance(method, str) else method


class _Counted:
    """A policy that reports each of its decisions to ``tick`` (a progress bar); acts as the policy."""

    def __init__(self, policy, tick: Callable[[], None]):
        self._policy, self._tick = policy, tick

    def __getattr__(self, name):
        return getattr(self._policy, name)

    def __call__(self, obs):
        self._tick()
        return self._policy(obs)


def estimate(method, trial: Trial, progress: Callable[[int, int], None] | None = None) -> Estimation:
    """``method`` (a name or object) over ``trial`` (``magenv.evaluation.estimate``); ``progress(done, total)``
    is called at each decision of a policy, in samples."""
    name = method if isinstance(method, str) else getattr(method, "name", type(method).__name__)
    method = method_of(method)
    runner = evaluation.PolicyRunner()
    if progress is not None and is_policy(method) and getattr(method, "prepare_trial", None) is None:
        k = runner.env(method, trial).k_steps
        done = [0]

        def tick():
            progress(done[0], trial.n)
            done[0] = min(trial.n, done[0] + k)

        method = _Counted(method, tick)
    q, _, trust = evaluation.estimate(method, trial, runner)
    if progress is not None:
        progress(trial.n, trial.n)
    return Estimation(name, trial, q, trust)


class TrustFilter:
    """``method`` (a name or a policy object) as a streaming filter at ``rate`` Hz with the local field
    ``field_norm`` µT, ``field_dip`` ° (see the module docstring). ``update`` streams the envs of
    :data:`STREAMING_ENVS`; ``run`` takes whole arrays of any method (the field estimated if not given)."""

    def __init__(self, method, rate: float = 100.0, field_norm: float | None = None, field_dip: float | None = None):
        self.name = method if isinstance(method, str) else getattr(method, "name", type(method).__name__)
        self.method = method_of(method)
        self.rate, self.field_norm, self.field_dip = rate, field_norm, field_dip
        self._n = 0
        self._buf = [np.zeros((0, 3)) for _ in range(3)]  # gyr, acc, mag: the env's trial reads these arrays
        self._actions: list[np.ndarray] = []
        self._env: Any = None  # the env the policy streams in, once the first sample is in
        self._obs: Any = None
        self._out = 0  # samples returned so far
        self._finished = False
        self._result: Estimation | None = None  # the last run()

    def run(self, gyr, acc, mag) -> np.ndarray:
        """(N, 4) the estimate of whole arrays (:func:`estimate`); ``trust`` holds the trust it applied."""
        trial = own_trial(gyr, acc, mag, self.rate, self.field_norm, self.field_dip, name=self.name)
        result = estimate(self.method, trial)
        self._result = result
        return result.q

    # ------------------------------------------------------------------ streaming

    def _check_streamable(self) -> None:
        if not is_policy(self.method):
            raise ValueError(f"{self.name} is a complete estimator (no env): run it on whole arrays with run()")
        if self.method.env_id not in STREAMING_ENVS or getattr(self.method, "prepare_trial", None) is not None:
            raise ValueError(
                f"{self.name} acts in {self.method.env_id}, whose runner precomputes signals over the whole "
                f"trial (or the method prepares the trial first); stream only {', '.join(STREAMING_ENVS)} "
                "methods, or run it on whole arrays with run()"
            )
        if self.field_norm is None or self.field_dip is None:
            raise ValueError("streaming needs the local field: TrustFilter(…, field_norm=µT, field_dip=°)")

    def _restart(self, capacity: int) -> None:
        """The env reset on a buffer trial of ``capacity`` samples (≥ those so far, which it holds) and stepped
        through the decisions made so far: bit for bit the state before, in a larger buffer."""
        bufs = [np.zeros((capacity, 3)) for _ in range(3)]
        for new, old in zip(bufs, self._buf):
            new[: self._n] = old[: self._n]
        self._buf = bufs
        trial = own_trial(bufs[0], bufs[1], bufs[2], self.rate, self.field_norm, self.field_dip, self.name, False)
        self._env = evaluation.PolicyRunner().env(self.method, trial)
        self._obs, _ = self._env.reset(seed=0, options={"trial": trial})
        for action in self._actions:
            self._obs = self._env.step(action)[0]

    def _decide(self) -> None:
        """The policy's action on the current observation, stepped (one window fused)."""
        action = np.asarray(self.method(self._obs), np.float64)
        self._actions.append(action)
        self._obs = self._env.step(action)[0]

    def update(self, gyr, acc, mag) -> np.ndarray:
        """Add one sample (gyr rad/s, acc m/s², mag µT, (3,) each); returns the quaternions it completed,
        (k, 4) at the end of a window, else (0, 4)."""
        if self._finished:
            raise RuntimeError("this TrustFilter has finished; make a new one")
        if self._env is None and self._n == 0:
            self._check_streamable()
            self.method.reset()
        sample = np.array([gyr, acc, mag], float)
        if sample.shape != (3, 3) or not np.all(np.isfinite(sample)):
            raise ValueError(f"update takes three finite (3,) vectors (gyr, acc, mag), got {sample.tolist()}")
        grow = self._n == len(self._buf[0])
        if grow:
            self._buf = [np.concatenate([b, np.zeros((max(START_CAPACITY, len(b)), 3))]) for b in self._buf]
        for b, v in zip(self._buf, sample):
            b[self._n] = v
        self._n += 1
        if grow or self._env is None:  # (the first reset reads the first sample: it is in place)
            self._restart(len(self._buf[0]))
        runner = self._env._runner
        if self._n >= runner.pos + self._env.k_steps + 1:  # the window and the sample after it are in
            self._decide()
        return self._take(runner.pos)

    def finish(self) -> np.ndarray:
        """Fuse the last (possibly short) window; returns its quaternions (m, 4). The env is stepped on a
        trial of exactly the samples given, so that its end is the env's end of a trial."""
        if self._finished or self._env is None:
            self._finished = True
            return np.zeros((0, 4))
        self._finished = True
        if self._env._runner.pos < self._n:
            action = np.asarray(self.method(self._obs), np.float64)
            self._restart(self._n)
            self._actions.append(action)
            self._env.step(action)
        return self._take(self._env._runner.pos)

    def _take(self, upto: int) -> np.ndarray:
        out = self._env.estimate[self._out : upto].copy()
        self._out = upto
        return out

    @property
    def estimate(self) -> np.ndarray:
        """(n, 4) the quaternions final so far (streaming), or of the last ``run``."""
        if self._env is None:
            return self._result.q if self._result is not None else np.zeros((0, 4))
        return self._env.estimate[: self._out].copy()

    @property
    def trust(self) -> np.ndarray | None:
        """(n,) the magnetometer trust applied to those quaternions (None if the method reports none)."""
        if self._env is None:
            return self._result.trust if self._result is not None else None
        from magenv.envs.render import magnetometer_trust

        trust = magnetometer_trust(self._env)
        return None if trust is None else trust[: self._out].copy()
