"""DAgger for ``magenv/MagVQF-v0``: an observation-only student imitating the privileged VQF oracle.

The teacher (``magenv.baselines.oracle_vqf.candidate_costs``, handed in by the
caller: this layer does not import baselines) gives, at any VQF state, the
cost of each candidate trust (Σ squared total error over its look-ahead). The
student is an MLP over the env's observation at the decision and its copies
``LAGS`` decisions earlier (before the start: the first observation),
standardised with the training data's mean and std; its logits score the
candidates and it acts with the probability-weighted mean trust.

Training (Ross et al. 2011, β = 1 in iteration 0, then 0): roll the policy
(teacher, then the latest student) through the training trials, label every
visited state with the candidate costs, aggregate, and refit a fresh student
on all the data with the cost-sensitive regret loss Σ_c softmax(z)_c · r_c,
r_c = (cost_c − min cost) / (H · MSE of VQF on that trial) (H = look-ahead
samples). Selection and reported figures come from trials the student never
trained on (leave-recordings-out: ``train/vqf_dagger.py``).

A run folder (weights only)::

    run.yaml          env id, algo "dagger_vqf", env kwargs, candidates, lags, the student's shape
    best.safetensors  the student's weights and standardisation
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from magenv.agents.weights import RunError, _write, read
from magenv.envs import VQF_ID
from magenv.envs.vqf import FEATURES, VQFRunner

ALGO = "dagger_vqf"
RUN_FILE, BEST = "run.yaml", "best.safetensors"
LAGS = (4, 16)  # decisions: the student's memory
CANDIDATES = (0.0, 0.25, 0.5, 0.75, 1.0)


class Student:
    """The MLP's forward pass in numpy (tanh hidden layers) and the lag memory that builds its input."""

    def __init__(self, weights: list[np.ndarray], mean: np.ndarray, std: np.ndarray, candidates, lags=LAGS):
        self.weights, self.mean, self.std = weights, mean, std
        self.candidates = np.asarray(candidates, float)
        self.lags = tuple(int(x) for x in lags)
        self.reset()

    def reset(self) -> None:
        self._history: list[np.ndarray] = []

    def inputs(self, obs: np.ndarray) -> np.ndarray:
        """The input of this decision: obs and its copies LAGS decisions earlier (memory updated)."""
        obs = np.asarray(obs, np.float64)
        self._history.append(obs)
        keep = max(self.lags) + 1
        if len(self._history) > keep:
            del self._history[0]
        h = self._history
        return np.concatenate([obs, *(h[max(0, len(h) - 1 - lag)] for lag in self.lags)])

    def logits(self, x: np.ndarray) -> np.ndarray:
        z = (x - self.mean) / self.std
        w = self.weights
        for i in range(0, len(w) - 2, 2):
            z = np.tanh(z @ w[i].T + w[i + 1])
        return z @ w[-2].T + w[-1]

    def act(self, x: np.ndarray) -> float:
        z = self.logits(x)
        p = np.exp(z - z.max())
        return float(p @ self.candidates / p.sum())


class StudentPolicy:
    """A trained student as a Policy of ``magenv/MagVQF-v0`` (``env_kwargs``: the options it was trained with)."""

    env_id = VQF_ID

    def __init__(self, student: Student, env_kwargs: dict, name: str = "dagger_vqf", source: str = ""):
        self.student, self.env_kwargs, self.name = student, dict(env_kwargs), name
        self.source, self.which = source, "best"  # the weights file, and which model (as a loaded SB3 agent)

    def reset(self) -> None:
        self.student.reset()

    def __call__(self, obs) -> np.ndarray:
        return np.array([self.student.act(self.student.inputs(obs))], np.float32)


def rollout(
    trial, env_kwargs: dict, teacher_costs: Callable, horizon_s: float, act: Callable | None, student: Student
) -> tuple[np.ndarray, np.ndarray, float]:
    """Roll a policy through ``trial`` (``act(x)`` on the student's input x; None = the teacher's argmin),
    labelling every decision: (inputs (M, D), candidate costs (M, C), H·MSE of VQF at u = 1 on the trial)."""
    kw = dict(env_kwargs)
    k = int(kw.pop("decision_every", 8))
    horizon = max(k, int(round(horizon_s * trial.rate)))
    runner = VQFRunner(trial, **kw)
    student.reset()
    xs, cs = [], []
    while not runner.done:
        x = student.inputs(runner.feat.astype(np.float32))
        costs = teacher_costs(runner, student.candidates, horizon)
        xs.append(x)
        cs.append(costs)
        u = float(student.candidates[int(np.argmin(costs))]) if act is None else act(x)
        runner.advance(k, u)
    ref = VQFRunner(trial, **kw)
    while not ref.done:
        ref.advance(k, 1.0)
    from magenv import metrics

    err = metrics.total_error(metrics.error_quaternion(ref.est, trial.q_true))
    mse = float(np.nanmean(err * err))
    return np.array(xs), np.array(cs), horizon * max(mse, 1e-6)


def fit(xs, costs, scale, hidden=(64, 64), steps=4000, lr=1e-3, batch=512, seed=0, candidates=CANDIDATES):
    """A fresh student fitted with the regret loss on (inputs, candidate costs, per-row cost scale)."""
    import torch

    torch.set_num_threads(1)  # a small MLP: threads only contend (25× slower with 2 on the shared cores)
    torch.manual_seed(seed)
    mean, std = xs.mean(0), xs.std(0) + 1e-6
    x = torch.tensor((xs - mean) / std, dtype=torch.float32)
    r = torch.tensor((costs - costs.min(1, keepdims=True)) / scale[:, None], dtype=torch.float32)
    layers: list[Any] = []
    d = x.shape[1]
    for h in hidden:
        layers += [torch.nn.Linear(d, h), torch.nn.Tanh()]
        d = h
    layers.append(torch.nn.Linear(d, costs.shape[1]))
    net = torch.nn.Sequential(*layers)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        idx = torch.randint(0, x.shape[0], (min(batch, x.shape[0]),), generator=gen)
        loss = (torch.softmax(net(x[idx]), 1) * r[idx]).sum(1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    weights = [p.detach().numpy().astype(np.float64) for p in net.parameters()]
    return Student(weights, mean, std, candidates)


def save(run_dir: str | Path, student: Student, env_kwargs: dict, meta: dict) -> Path:
    """Write ``run.yaml`` and ``best.safetensors`` of ``student``."""
    import torch

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    arrays = {f"w{i}": w for i, w in enumerate(student.weights)}
    arrays.update(mean=student.mean, std=student.std)
    tensors = {k: torch.from_numpy(np.ascontiguousarray(v, np.float64)) for k, v in arrays.items()}
    _write(run_dir / BEST, tensors, {"algo": ALGO})
    run = {
        "env_id": VQF_ID,
        "algo": ALGO,
        "env_kwargs": dict(env_kwargs),
        "candidates": [float(c) for c in student.candidates],
        "lags": list(student.lags),
        "n_layers": len(student.weights),
        "n_inputs": int(student.mean.shape[0]),
        "features": list(FEATURES.names),
        **meta,
    }
    (run_dir / RUN_FILE).write_text(yaml.safe_dump(run, sort_keys=False))
    return run_dir


def _run_file(run_dir: str | Path) -> dict:
    """The run.yaml of ``run_dir`` as a mapping (RunError if missing or corrupt)."""
    path = Path(run_dir) / RUN_FILE
    try:
        run = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as exc:
        raise RunError(f"{path}: unreadable ({type(exc).__name__})") from None
    if not isinstance(run, dict):
        raise RunError(f"{path}: not a mapping")
    return run


def is_run(run_dir: str | Path) -> bool:
    """``run_dir`` holds a run of this module (``algo: dagger_vqf``)."""
    try:
        return _run_file(run_dir).get("algo") == ALGO
    except RunError:
        return False


def load_policy(run_dir: str | Path, name: str | None = None) -> StudentPolicy:
    """The student of a run folder as a Policy (RunError naming the file and the problem)."""
    run_dir = Path(run_dir)
    run = _run_file(run_dir)
    if run.get("features") != list(FEATURES.names):
        raise RunError(f"{run_dir / RUN_FILE}: trained on other observation features than {VQF_ID}'s")
    tensors, _ = read(run_dir / BEST, ALGO)
    n = int(run["n_layers"])
    missing = [k for k in [*(f"w{i}" for i in range(n)), "mean", "std"] if k not in tensors]
    if missing:
        raise RunError(f"{run_dir / BEST}: missing tensor(s) {missing}")
    arrays = {k: v.numpy().astype(np.float64) for k, v in tensors.items()}
    weights = [arrays[f"w{i}"] for i in range(n)]
    student = Student(weights, arrays["mean"], arrays["std"], run["candidates"], run["lags"])
    if student.mean.shape[0] != len(FEATURES) * (1 + len(student.lags)):
        raise RunError(f"{run_dir / BEST}: input size {student.mean.shape[0]} does not fit the features and lags")
    return StudentPolicy(student, run["env_kwargs"], name or f"agent:{run_dir.name}", str(run_dir / BEST))
