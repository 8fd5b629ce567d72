"""How magenv-bench scores a policy: per task from per-trial RMSEs, then over tasks with rliable.

Per task (:func:`score_task`), from the total RMSE (°, ``magenv.metrics``) of the agent, the task's rule and its
oracle on the same evaluation trials (entry i of each array is trial i):

* the **paired ratio** agent/rule (``magenv.stats.paired_ratio``: geometric mean of the per-trial ratios with its
  bootstrap 95 % interval, the win rate, the worst per-trial ratio);
* the **normalised score** (``magenv.stats.normalised_score``): per trial (rule_i − agent_i) / g, g the mean
  rule-to-oracle gap of the task, so the rule scores 0 on every trial, the oracle 1 on average, and the task's
  score is (mean rule − mean agent) / (mean rule − mean oracle), with its bootstrap interval and the worst trial.

Over tasks (:func:`aggregates`, Agarwal et al. 2021, the ``rliable`` package): a method's scores are a matrix
(runs × tasks) of normalised scores (runs: the evaluation trials of one agent, or the training seeds of a
baseline, each its mean over the trials); the interquartile mean (IQM), the optimality gap (the mean shortfall
below 1, the oracle's level) and the probability of improvement over the rule (whose scores are 0), each with a
stratified-bootstrap 95 % interval (runs resampled within each task); :func:`profile_png` draws the performance
profiles (the fraction of runs above each score τ).
"""

from __future__ import annotations

import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from magenv import stats

#: Bootstrap resamples of the rliable intervals (the per-task intervals take ``magenv.stats.DEFAULT_BOOT``)
AGGREGATE_REPS = 2000
AGGREGATE_SEED = 0
PROFILE_RANGE = (-1.0, 1.5)  # normalised scores on the profiles' axis


@dataclass(frozen=True)
class TaskScore:
    """One method on one task.

    Attributes:
        task: the task's name (``MagBlend-v0/dynamic_magnet``).
        rule, oracle: the reference methods ("" for no oracle).
        trials: the evaluation trials' names.
        agent, rule_rmse, oracle_rmse: per-trial total RMSE (°) of each (oracle_rmse empty without an oracle).
        paired: the paired ratio agent/rule.
        normalised: the normalised score, None without an oracle.
    """

    task: str
    rule: str
    oracle: str
    trials: tuple[str, ...]
    agent: tuple[float, ...]
    rule_rmse: tuple[float, ...]
    oracle_rmse: tuple[float, ...]
    paired: stats.PairedRatio
    normalised: stats.Normalised | None = field(default=None)

    def as_dict(self) -> dict:
        """The JSON record of the score card."""
        p, n = self.paired, self.normalised
        return {
            "task": self.task,
            "rule": self.rule,
            "oracle": self.oracle,
            "n": len(self.agent),
            "agent_rmse": float(np.mean(self.agent)),
            "rule_rmse": float(np.mean(self.rule_rmse)),
            "oracle_rmse": float(np.mean(self.oracle_rmse)) if self.oracle_rmse else None,
            "ratio": {"value": p.ratio, "low": p.low, "high": p.high, "win_rate": p.win_rate, "worst": p.worst},
            "normalised": None
            if n is None
            else {"value": n.score, "low": n.low, "high": n.high, "worst": n.worst, "gap_deg": n.gap},
            "per_trial": {
                "trials": list(self.trials),
                "agent": list(self.agent),
                "rule": list(self.rule_rmse),
                "oracle": list(self.oracle_rmse),
            },
        }


def score_task(task: str, rule: str, oracle: str, trials, agent, rule_rmse, oracle_rmse=()) -> TaskScore:
    """The :class:`TaskScore` of per-trial RMSEs (equal lengths; ``oracle_rmse`` empty for a task without an
    oracle). ValueError from ``magenv.stats`` naming a bad array."""
    agent, rule_rmse, oracle_rmse = (tuple(map(float, a)) for a in (agent, rule_rmse, oracle_rmse))
    paired = stats.paired_ratio(agent, rule_rmse)
    normalised = stats.normalised_score(agent, rule_rmse, oracle_rmse) if oracle_rmse else None
    return TaskScore(task, rule, oracle, tuple(trials), agent, rule_rmse, oracle_rmse, paired, normalised)


def _optimality_gap(scores: np.ndarray) -> float:
    from rliable import metrics

    return metrics.aggregate_optimality_gap(scores, gamma=1.0)


@contextmanager
def _global_numpy_seed(seed: int):
    """numpy's global generator seeded with ``seed`` inside, restored after: rliable draws its bootstrap indices
    from it (``np.random.choice``), whatever ``random_state`` it is given."""
    saved = np.random.get_state()  # noqa: NPY002
    np.random.seed(seed)  # noqa: NPY002
    try:
        yield
    finally:
        np.random.set_state(saved)  # noqa: NPY002


def aggregates(matrices: dict[str, np.ndarray], reps: int = AGGREGATE_REPS, seed: int = AGGREGATE_SEED) -> dict:
    """rliable's aggregates of each method's (runs × tasks) normalised-score matrix: ``{method: {"iqm": (point,
    low, high), "optimality_gap": …, "improvement": …}}``, ``improvement`` the probability of improvement over
    the rule (a matrix of zeros), all with stratified-bootstrap intervals (``reps`` resamples, ``seed``)."""
    from rliable import library as rly
    from rliable import metrics

    def funcs(x: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(x), _optimality_gap(x)])

    def improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.array([metrics.probability_of_improvement(x, y)])

    checked = {m: _matrix(m, x) for m, x in matrices.items()}
    pairs = {m: [x, np.zeros_like(x)] for m, x in checked.items()}
    with warnings.catch_warnings():  # arch's notice that it will change its default generator
        warnings.simplefilter("ignore", FutureWarning)
        with _global_numpy_seed(seed):
            points, cis = rly.get_interval_estimates(
                checked, funcs, reps=reps, random_state=np.random.RandomState(seed)
            )
        with _global_numpy_seed(seed):
            p_points, p_cis = rly.get_interval_estimates(
                pairs, improvement, reps=reps, random_state=np.random.RandomState(seed)
            )
    out = {}
    for m in checked:
        out[m] = {
            "iqm": (float(points[m][0]), float(cis[m][0, 0]), float(cis[m][1, 0])),
            "optimality_gap": (float(points[m][1]), float(cis[m][0, 1]), float(cis[m][1, 1])),
            "improvement": (float(p_points[m][0]), float(p_cis[m][0, 0]), float(p_cis[m][1, 0])),
            "runs": int(checked[m].shape[0]),
            "tasks": int(checked[m].shape[1]),
        }
    return out


def _matrix(name: str, x) -> np.ndarray:
    x = np.asarray(x, float)
    if x.ndim != 2 or 0 in x.shape or not np.all(np.isfinite(x)):
        raise ValueError(f"{name}: the normalised scores must be a finite (runs × tasks) matrix, got shape {x.shape}")
    return x


def profile_png(matrices: dict[str, np.ndarray], path: str | Path, title: str = "") -> Path:
    """The performance profiles of each method's (runs × tasks) matrix, with stratified-bootstrap bands, as a
    PNG at ``path``: the fraction of (run, task) scores above τ, τ over ``PROFILE_RANGE`` (the same axis on every
    card; a score below its start counts below every τ)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from rliable import library as rly
    from rliable import plot_utils

    checked = {m: _matrix(m, x) for m, x in matrices.items()}
    taus = np.linspace(*PROFILE_RANGE, 101)
    with _global_numpy_seed(AGGREGATE_SEED):
        profiles, cis = rly.create_performance_profile(checked, taus, reps=AGGREGATE_REPS)
    colors = dict(zip(checked, plt.get_cmap("tab10")(np.arange(10)).tolist()))
    fig, ax = plt.subplots(figsize=(7, 4.5))
    plot_utils.plot_performance_profiles(
        profiles,
        taus,
        performance_profile_cis=cis,
        ax=ax,
        colors=colors,
        xlabel="normalised score τ (0: best tuned rule, 1: oracle)",
        ylabel="fraction of runs with score > τ",
    )
    ax.axvline(0.0, color="0.6", lw=0.8, ls="--")
    ax.axvline(1.0, color="0.6", lw=0.8, ls="--")
    handles = [Line2D([0], [0], color=c, lw=2) for c in colors.values()]
    ax.legend(handles, list(colors), loc="upper right", fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
