"""Run any method on the same trials and score it with ``magenv.metrics``.

A method is a **Policy** (``magenv.protocols.Policy``: acts inside the env
named by its ``env_id``, on observations only) or an **Estimator**
(``run(trial) -> Estimate``). Methods come in as objects (a dict name →
method); only ``magenv.registry`` turns names into methods. A policy is run on a given Trial by
``env.reset(options={"trial": trial})`` and stepped to the end of the trial;
its estimate is the env's per-sample estimate. A ``BatchPolicy`` (a trained agent) runs on all the trials
of a call together: one env per trial, one ``act_batch`` (one network forward) per decision for all the envs,
each env to its own trial's end (:meth:`PolicyRunner.run_all`); other methods run one trial after the other.
Scores are RMSEs (degrees) over the trial's ``score_mask`` (``magenv.metrics.score``).

Python use::

    from magenv import evaluation, registry
    methods = {name: registry.make(name) for name in ("mimu", "imu", "fan_lambda")}
    rows = evaluation.compare(methods, trials)   # list of dicts, CSV_COLUMNS
    evaluation.write_csv(rows, "out.csv")

A method that **diverges** on a trial — its estimate is not finite somewhere, or it stops with a
numerical error (``DIVERGED``: ZeroDivisionError, FloatingPointError, OverflowError, LinAlgError) —
scores ``magenv.metrics.WORST_DEG`` (180°) in every part on that trial, its Run carrying the reason in
``diverged``: its row is present and ranks below every method that kept a finite estimate, and
below none that diverged too (diverging later is no better). With ``keep_going=True`` a method that
cannot run a trial for any other reason (it raises) does not stop the others: its Run carries the
reason in ``error``, and its row in the table has NaN figures and the reason under ``"error"``.
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from magenv import metrics
from magenv.envs.render import magnetometer_trust, write_video
from magenv.protocols import BatchPolicy, is_policy
from magenv.stats import paired_ratio
from magenv.trial import META_SCENARIO, Trial

#: Errors that mean a method's arithmetic blew up on a trial (it diverged), not that it cannot run the trial.
DIVERGED = (ArithmeticError, np.linalg.LinAlgError)
#: The score of a diverged run (degrees): the worst there is, in every part.
DIVERGED_SCORE = metrics.Score(metrics.WORST_DEG, metrics.WORST_DEG, metrics.WORST_DEG)

CSV_COLUMNS = (
    "method",
    "scenario",
    "n",
    "total_rmse_mean",
    "total_rmse_std",
    "heading_rmse_mean",
    "inclination_rmse_mean",
)


@dataclass
class Run:
    """One method on one trial.

    Attributes:
        method: method name.
        trial: the Trial.
        label: the trial's group in tables (scenario name, or the recording's name).
        q: (N, 4) estimate sensor → ENU.
        lam: (N,) λ per sample for MagBlend policies, else None.
        trust: (N,) the method's magnetometer trust (1 − λ for MagBlend), or None.
        score: RMSE (°) over the trial's score mask; ``DIVERGED_SCORE`` if the method diverged.
        error: why the method could not run the trial (``evaluate(keep_going=True)``); q and score are then None.
        diverged: how the method diverged on the trial (a non-finite estimate from some sample, or its numerical
            error); None if it did not. q is then the estimate, or None if the method stopped.
    """

    method: str
    trial: Trial
    label: str
    q: np.ndarray | None
    lam: np.ndarray | None
    trust: np.ndarray | None
    score: metrics.Score | None
    error: str | None = None
    diverged: str | None = None

    def without_arrays(self) -> Run:
        """This run without its trial and arrays (what a worker sends back): scores and reasons only."""
        return Run(self.method, None, self.label, None, None, None, self.score, self.error, self.diverged)  # type: ignore[arg-type]

    @property
    def scored(self) -> metrics.Score:
        """The score of a run that ran; a RuntimeError naming the method and its error otherwise."""
        if self.score is None:
            raise RuntimeError(f"{self.method} did not run on {self.label}: {self.error}")
        return self.score


def trial_label(trial: Trial) -> str:
    """Default table group of a trial: its scenario name, else its own name."""
    return str(trial.meta.get(META_SCENARIO, trial.name))


#: trials a BatchPolicy runs together at most (one env each, with its per-sample histories)
MAX_TOGETHER = 64
#: what running a method on one trial gives: (estimate (N, 4), λ (N,) or None, trust (N,) or None), or the
#: exception that stopped it on that trial
Outcome = tuple[np.ndarray, np.ndarray | None, np.ndarray | None] | Exception


class PolicyRunner:
    """Keeps the envs of each (env_id, env options) so many trials are run without re-making them."""

    def __init__(self, env_id: str | None = None, env_kwargs: dict | None = None):
        self.env_id, self.env_kwargs = env_id, dict(env_kwargs or {})
        self._envs: dict[Any, list] = {}

    def envs(self, policy, trial: Trial, n: int = 1, render_mode: str | None = None) -> list:
        """``n`` envs that ``policy`` acts in for ``trial`` (made once per env id and options, kept)."""
        import gymnasium as gym

        import magenv  # noqa: F401  (registers the envs)

        env_id = self.env_id or policy.env_id
        kwargs = {**getattr(policy, "env_kwargs", {}), **self.env_kwargs}
        kwargs["scenario"] = [trial]  # never simulate: the trial comes through reset options
        if "episode_seconds" in kwargs:
            kwargs["episode_seconds"] = None  # evaluation scores whole trials
        key = (env_id, render_mode, repr(sorted((k, repr(v)) for k, v in kwargs.items() if k != "scenario")))
        kept = self._envs.setdefault(key, [])
        while len(kept) < n:
            kept.append(gym.make(env_id, disable_env_checker=True, render_mode=render_mode, **kwargs).unwrapped)
        return kept[:n]

    def env(self, policy, trial: Trial, render_mode: str | None = None):
        """The env ``policy`` acts in for ``trial`` (made once per env id and options, kept)."""
        return self.envs(policy, trial, 1, render_mode)[0]

    def run_all(self, policy, trials: Sequence[Trial]) -> list[Outcome]:
        """``policy`` over each whole trial: its :data:`Outcome` per trial. A ``BatchPolicy`` runs the trials
        together (up to ``MAX_TOGETHER`` at a time), one env each and one ``act_batch`` call per decision for all;
        any other policy one trial after the other (it has one memory, ``reset()`` before each trial)."""
        trials = list(trials)
        if isinstance(policy, BatchPolicy):
            chunks = [trials[k : k + MAX_TOGETHER] for k in range(0, len(trials), MAX_TOGETHER)]
            return [out for chunk in chunks for out in self._together(policy, chunk, batch=True)]
        return [out for t in trials for out in self._together(policy, [t], batch=False)]

    def run(self, policy, trial: Trial) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Run ``policy`` over the whole ``trial``; returns (estimate (N, 4), λ (N,) or None, trust (N,) or None)."""
        out = self.run_all(policy, [trial])[0]
        if isinstance(out, Exception):
            raise out
        return out

    def _together(self, policy, trials: list[Trial], batch: bool) -> list[Outcome]:
        """Step one env per trial until each trial's end, deciding for all the envs at once (``batch``: one
        ``act_batch`` call; else one trial and ``policy(obs)``); a trial whose env or decision raises keeps
        the exception and leaves the batch."""
        if not trials:
            return []
        envs = self.envs(policy, trials[0], len(trials))
        out: list[Outcome | None] = [None] * len(trials)
        obs: list = [np.zeros(envs[0].observation_space.shape, envs[0].observation_space.dtype)] * len(trials)
        for k, (env, trial) in enumerate(zip(envs, trials)):
            try:
                obs[k], _ = env.reset(seed=0, options={"trial": trial})
            except Exception as exc:  # this trial cannot run: the others go on
                out[k] = exc
        running = np.array([o is None for o in out])
        state = None
        if not batch:
            policy.reset()
        while running.any():
            try:
                if batch:
                    actions, state = policy.act_batch(np.stack(obs), state)
                else:
                    actions = [policy(obs[0])]
            except Exception as exc:  # the policy fails on every trial it was acting on
                for i in np.flatnonzero(running):
                    out[i] = exc
                break
            for i in np.flatnonzero(running):
                try:
                    obs[i], _, terminated, truncated, _ = envs[i].step(actions[i])
                except Exception as exc:
                    out[i], running[i] = exc, False
                    continue
                if terminated or truncated:
                    out[i], running[i] = _outcome(envs[i]), False
        return cast(list[Outcome], out)  # every entry set

    def record(self, policy, trial: Trial, path: str | Path) -> Path:
        """Run ``policy`` over ``trial`` with ``render_mode="rgb_array"`` and write one frame per step to the MP4
        file ``path`` (``magenv.envs.render.write_video``)."""
        env = self.env(policy, trial, render_mode="rgb_array")

        def frames():
            policy.reset()
            obs, _ = env.reset(seed=0, options={"trial": trial})
            yield env.render()
            truncated = terminated = False
            while not (truncated or terminated):
                obs, _, terminated, truncated, _ = env.step(policy(obs))
                yield env.render()

        return write_video(frames(), path)


def _outcome(env) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(estimate, λ, trust) of an env at the end of its episode (copies)."""
    lam = getattr(env, "lambdas", None)
    trust = magnetometer_trust(env)
    return (
        env.estimate.copy(),
        None if lam is None else np.array(lam, copy=True),
        None if trust is None else trust.copy(),
    )


def outcomes(method, trials: Sequence[Trial], runner: PolicyRunner | None = None) -> list[Outcome]:
    """One Policy or Estimator over each whole trial (no truth needed): its :data:`Outcome` per trial (a
    ``BatchPolicy`` on all the trials together: :meth:`PolicyRunner.run_all`). A method with a
    ``prepare_trial(trial)`` attribute runs on what it returns (e.g. the gyro de-biased at rest)."""
    prepare = getattr(method, "prepare_trial", None)
    seen: list[Trial | Exception] = []
    for trial in trials:
        try:
            seen.append(trial if prepare is None else prepare(trial))
        except Exception as exc:  # this trial cannot run: the others go on
            seen.append(exc)
    ready = [t for t in seen if isinstance(t, Trial)]
    if is_policy(method):
        done = iter((runner or PolicyRunner()).run_all(method, ready))
    else:
        done = iter(_estimator_outcome(method, t) for t in ready)
    return [t if isinstance(t, Exception) else next(done) for t in seen]


def _estimator_outcome(method, trial: Trial) -> Outcome:
    try:
        est = method.run(trial)
    except Exception as exc:
        return exc
    return np.asarray(est.q, float), None, est.trust


def estimate(
    method, trial: Trial, runner: PolicyRunner | None = None
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """One Policy or Estimator over the whole ``trial`` (:func:`outcomes`): (estimate (N, 4), λ (N,) or None,
    trust (N,) or None); the exception that stopped it is raised."""
    out = outcomes(method, [trial], runner)[0]
    if isinstance(out, Exception):
        raise out
    return out


def scored_run(name: str, trial: Trial, label: str, outcome: Outcome) -> Run:
    """The Run of ``outcome`` (:func:`outcomes`) of method ``name`` on ``trial``, scored against its truth
    over its score mask (``magenv.metrics.score``). A method that diverged (see the module docstring) scores
    ``DIVERGED_SCORE``; any other exception is raised."""
    if isinstance(outcome, DIVERGED):
        exc = outcome
        return Run(name, trial, label, None, None, None, DIVERGED_SCORE, diverged=f"{type(exc).__name__}: {exc}")
    if isinstance(outcome, Exception):
        raise outcome
    q, lam, trust = outcome
    if q.shape != (trial.n, 4):
        raise ValueError(
            f"method {name!r} returned an estimate of shape {q.shape} for trial {trial.name!r} ({trial.n} samples)"
        )
    bad = np.flatnonzero(~np.isfinite(q).all(axis=1))
    if bad.size:
        diverged = f"non-finite estimate from sample {bad[0]} of trial {trial.name!r} ({bad.size} of {trial.n})"
        return Run(name, trial, label, q, lam, trust, DIVERGED_SCORE, diverged=diverged)
    score = metrics.score(q, trial.q_true, trial.score_mask)
    return Run(name, trial, label, q, lam, trust, score)


def run_method(name: str, method, trial: Trial, runner: PolicyRunner | None = None, label: str | None = None) -> Run:
    """Run one Policy or Estimator on one trial (:func:`outcomes`) and score it against ``trial``'s truth
    (:func:`scored_run`)."""
    return scored_run(name, trial, label or trial_label(trial), outcomes(method, [trial], runner)[0])


def run_policy_on_trials(
    policy, trials: Sequence[Trial], env_id: str | None = None, env_kwargs: dict | None = None
) -> list[metrics.Score]:
    """Scores of ``policy`` on each trial (env ``env_id`` or the policy's own, with ``env_kwargs``; a
    ``BatchPolicy`` on all of them together)."""
    name = getattr(policy, "name", "policy")
    done = outcomes(policy, trials, PolicyRunner(env_id, env_kwargs))
    return [scored_run(name, t, trial_label(t), o).scored for t, o in zip(trials, done)]


def named(methods) -> dict[str, Any]:
    """Methods as a dict name → method: a dict as it is, or a sequence of method objects named by their
    ``name`` attribute (else their class name). Names are the registry's business (``magenv.registry.make``)."""
    if isinstance(methods, dict):
        return dict(methods)
    out = {}
    for m in methods:
        if isinstance(m, str):
            raise TypeError(f"evaluation takes method objects, got the name {m!r}; use magenv.registry.make({m!r})")
        out[getattr(m, "name", type(m).__name__)] = m
    return out


def evaluate(
    methods,
    trials: Iterable[Trial],
    env_kwargs: dict | None = None,
    labels: Sequence[str] | None = None,
    progress: Callable[[str, Trial], None] | None = None,
    keep_going: bool = False,
) -> list[Run]:
    """Every method on every trial (same trials for all), as Runs in the order trial by trial, method by method.
    A ``BatchPolicy`` runs on all the trials together (:meth:`PolicyRunner.run_all`), the other methods trial
    by trial. ``progress(method, trial)`` is called after each run.

    ``env_kwargs`` are applied to every policy's env (e.g. ``{"decision_every": 1}``);
    ``labels`` gives each trial's table group (default ``trial_label``). With ``keep_going``, a method
    that raises on a trial gets a Run with the reason in ``error`` and the others go on.
    """
    methods = named(methods)
    trials = list(trials)
    labels = [trial_label(t) for t in trials] if labels is None else list(labels)
    runner = PolicyRunner(None, env_kwargs)
    together = {}
    for name, method in methods.items():
        if isinstance(method, BatchPolicy):
            together[name] = outcomes(method, trials, runner)
            for trial in trials:
                if progress is not None:
                    progress(name, trial)
    runs = []
    for k, (trial, label) in enumerate(zip(trials, labels)):
        for name, method in methods.items():
            try:
                outcome = together[name][k] if name in together else outcomes(method, [trial], runner)[0]
                runs.append(scored_run(name, trial, label, outcome))
            except Exception as exc:  # keep_going: whatever stops this method on this trial, the rest go on
                if not keep_going:
                    raise
                runs.append(Run(name, trial, label, None, None, None, None, f"{type(exc).__name__}: {exc}"))
            if progress is not None and name not in together:
                progress(name, trial)
    return runs


def summarize(runs: Sequence[Run]) -> list[dict]:
    """One row per (method, label) with ``CSV_COLUMNS``; std is the sample std (ddof 1; NaN for n = 1).

    A group where the method failed on some trial has NaN figures (a mean over fewer trials would not pair
    with the other methods') and the reasons under ``"error"``; one where it diverged on some trial counts
    those trials at 180° and says how under ``"diverged"``."""
    groups: dict[tuple[str, str], list[Run]] = {}
    for r in runs:
        groups.setdefault((r.method, r.label), []).append(r)
    rows = []
    for (method, label), group in groups.items():
        failed = [r.error for r in group if r.error is not None]
        if failed:
            nan = float("nan")
            rows.append(
                {
                    "method": method,
                    "scenario": label,
                    "n": len(group),
                    "total_rmse_mean": nan,
                    "total_rmse_std": nan,
                    "heading_rmse_mean": nan,
                    "inclination_rmse_mean": nan,
                    "error": f"failed on {len(failed)} of {len(group)} trial(s): " + "; ".join(dict.fromkeys(failed)),
                }
            )
            continue
        scores = [r.scored for r in group]
        tot = np.array([s.total for s in scores])
        row = {
            "method": method,
            "scenario": label,
            "n": len(scores),
            "total_rmse_mean": float(np.mean(tot)),
            "total_rmse_std": float(np.std(tot, ddof=1)) if len(tot) > 1 else float("nan"),
            "heading_rmse_mean": float(np.mean([s.heading for s in scores])),
            "inclination_rmse_mean": float(np.mean([s.inclination for s in scores])),
        }
        diverged = [r.diverged for r in group if r.diverged]
        if diverged:
            row["diverged"] = f"diverged on {len(diverged)} of {len(group)} trial(s), scored 180°: " + "; ".join(
                dict.fromkeys(diverged)
            )
        rows.append(row)
    return rows


def compare(methods, trials: Iterable[Trial], **options) -> list[dict]:
    """``summarize(evaluate(methods, trials, **options))``: the comparison table as a list of dicts
    (``CSV_COLUMNS``); ``options``: :func:`evaluate`'s ``env_kwargs``, ``labels``, ``progress``, ``keep_going``."""
    return summarize(evaluate(methods, trials, **options))


def add_paired(rows: list[dict], runs: Sequence[Run], reference: str) -> list[dict]:
    """``rows`` (of :func:`summarize`) with ``row["paired"]``, the paired ratio of the row's method to ``reference``
    over the trials of its group (``magenv.stats.paired_ratio``: geometric mean of the per-trial ratios of total
    RMSE, bootstrap 95 % interval, win rate, the worst per-trial ratio), where both ran on every trial of the
    group (one trial: its ratio, no interval). Runs pair by position within a group: :func:`evaluate` runs every
    method on the same trials in order."""
    totals: dict[tuple[str, str], list] = {}
    for r in runs:
        totals.setdefault((r.method, r.label), []).append(None if r.score is None else r.score.total)
    for row in rows:
        mine, ref = totals.get((row["method"], row["scenario"])), totals.get((reference, row["scenario"]))
        if row["method"] == reference or not mine or not ref or len(mine) != len(ref):
            continue
        if None not in mine and None not in ref:
            row["paired"] = paired_ratio(mine, ref)
    return rows


def write_csv(rows: Sequence[dict], path: str | Path) -> Path:
    """Write rows with exactly the header ``CSV_COLUMNS`` (floats to 4 decimals, degrees; ``nan`` where a
    method failed — the reason is in the row's ``"error"``, not in the file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for row in rows:
            w.writerow([f"{row[c]:.4f}" if isinstance(row[c], float) else row[c] for c in CSV_COLUMNS])
    return path


def plot_runs(runs: Sequence[Run], path: str | Path, title: str | None = None) -> Path:
    """Total error over time (top) and λ over time (bottom) of runs on one trial."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    runs = [r for r in runs if r.q is not None]
    fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(9, 6))
    for r in runs:
        t = r.trial.t
        err = metrics.total_error(metrics.error_quaternion(r.q, r.trial.q_true))
        ax1.plot(t, err, lw=0.8, label=f"{r.method} ({r.scored.total:.2f}°)")
        if r.lam is not None:
            ax2.plot(t, r.lam, lw=0.8, label=r.method)
        elif r.trust is not None:
            ax2.plot(t, 1.0 - np.asarray(r.trust, float), lw=0.8, ls="--", label=f"{r.method} (1 − trust)")
    ax1.set_ylabel("total error (°)")
    ax1.legend(fontsize=8)
    ax2.set_ylabel("λ (IMU weight)")
    ax2.set_xlabel("time (s)")
    ax2.set_ylim(-0.05, 1.05)
    ax2.legend(fontsize=8)
    if title or runs:
        ax1.set_title(title or runs[0].trial.name)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
