"""DAgger for ``magenv/MagVQF-v0``: an observation-only student imitating the privileged VQF oracle.

The teacher (``magenv.baselines.oracle_vqf.candidate_costs``, handed in by the
caller: this layer does not import baselines) gives, at any VQF state, the
cost of each candidate trust (Σ squared total error over its look-ahead). The
student is an MLP over the env's observation at the decision and its copies
``LAGS`` decisions earlier (before the start: the first observation),
standardised with the training data's mean and std (optionally each block
followed by a tuned Fan rule's trust); each MLP's logits score the candidates,
and the student, an ensemble of MLPs fitted with different seeds, acts with the
mean of their probability-weighted trusts.

Training (Ross et al. 2011, β = 1 in iteration 0, then 0): roll the policy
(teacher, then the latest student) through the training trials, label every
visited state with the candidate costs, aggregate, and refit a fresh student
on all the data with the cost-sensitive regret loss Σ_c softmax(z)_c · r_c,
r_c = (cost_c − min cost) / (H · MSE of VQF on that trial) (H = look-ahead
samples). Selection and reported figures come from trials the student never
trained on (leave-recordings-out: ``train/vqf_dagger.py``).

A run folder (weights only)::

    run.yaml          env id, algo "dagger_vqf", env kwargs, candidates, lags, rule, the student's shape
    best.safetensors  the weights (member 0: w0…, member m ≥ 1: m{m}_w0…) and standardisation
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from magenv.agents.weights import RunError, _write, read
from magenv.envs import VQF_ID
from magenv.envs.features import DIP_SCALE_DEG
from magenv.envs.vqf import FEATURES, VQFRunner

ALGO = "dagger_vqf"
RUN_FILE, BEST = "run.yaml", "best.safetensors"
LAGS = (4, 16)  # decisions: the student's memory
CANDIDATES = (0.0, 0.25, 0.5, 0.75, 1.0)
_NORM_DEV, _DIP_DEV = (list(FEATURES.names).index(n) for n in ("norm_dev", "dip_dev"))  # rule_trust's columns


def rule_trust(obs: np.ndarray, rule: tuple[float, float]) -> np.ndarray:
    """The Fan rule's trust u = 1 − λ of observations (…, F) with rule = (norm_tol, th_dip_deg):
    λ1 = min(|norm_dev|/norm_tol, 1), λ2 = min(|θ_dip − θ0|/th_dip, 1), λ = (λ1 + λ2)/2 (Fan et al. 2017
    eqs. 15–17, the ``vqf_fan_lambda`` policy's reading)."""
    norm_tol, th_dip = rule
    lam1 = np.minimum(np.abs(obs[..., _NORM_DEV]) / norm_tol, 1.0)
    lam2 = np.minimum(np.abs(DIP_SCALE_DEG * obs[..., _DIP_DEV]) / th_dip, 1.0)
    return 1.0 - 0.5 * (lam1 + lam2)


class Student:
    """The MLP's forward pass in numpy (tanh hidden layers) and the lag memory that builds its input.

    ``rule`` (norm_tol, th_dip_deg), or None: each observation block of the input is followed by the
    Fan rule's trust of that block (:func:`rule_trust`), as the MagBlend student gets its rule's λ.
    ``more``: the weights of further MLPs fitted with other seeds; the student acts with the mean of the
    members' trusts (an ensemble: fits of one data set differ a lot from seed to seed)."""

    def __init__(
        self,
        weights: list[np.ndarray],
        mean: np.ndarray,
        std: np.ndarray,
        candidates,
        lags=LAGS,
        rule=None,
        more: Sequence = (),
    ):
        self.weights, self.mean, self.std = weights, mean, std
        self.more = [list(w) for w in more]  # further ensemble members' weights (same inputs and standardisation)
        self.candidates = np.asarray(candidates, float)
        self.lags = tuple(int(x) for x in lags)
        self.rule = None if rule is None else (float(rule[0]), float(rule[1]))
        self.reset()

    def augment(self, x: np.ndarray) -> np.ndarray:
        """Raw inputs (…, F·(1 + len(lags))) → the MLP's inputs (each block followed by its rule trust)."""
        if self.rule is None:
            return x
        blocks = np.split(np.asarray(x, np.float64), 1 + len(self.lags), axis=-1)
        return np.concatenate([p for b in blocks for p in (b, rule_trust(b, self.rule)[..., None])], axis=-1)

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

    def logits(self, x: np.ndarray, member: int = 0) -> np.ndarray:
        z = (self.augment(x) - self.mean) / self.std
        w = [self.weights, *self.more][member]
        for i in range(0, len(w) - 2, 2):
            z = np.tanh(z @ w[i].T + w[i + 1])
        return z @ w[-2].T + w[-1]

    def act(self, x: np.ndarray) -> float:
        """The mean over the members of the probability-weighted candidate trust."""
        u = 0.0
        for m in range(1 + len(self.more)):
            z = self.logits(x, m)
            p = np.exp(z - z.max())
            u += float(p @ self.candidates / p.sum())
        return u / (1 + len(self.more))


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


def fit(
    xs,
    costs,
    scale,
    hidden=(64, 64),
    steps=4000,
    lr=1e-3,
    batch=512,
    seed=0,
    candidates=CANDIDATES,
    rule=None,
    members: int = 1,
):
    """A fresh student fitted with the regret loss on (raw inputs, candidate costs, per-row cost scale):
    ``members`` MLPs with seeds seed, seed + 1, … (an ensemble when more than one)."""
    xs = Student([], np.zeros(1), np.ones(1), candidates, rule=rule).augment(xs)
    mean, std = xs.mean(0), xs.std(0) + 1e-6
    nets = [_fit_mlp((xs - mean) / std, costs, scale, hidden, steps, lr, batch, seed + m) for m in range(members)]
    return Student(nets[0], mean, std, candidates, rule=rule, more=nets[1:])


def _fit_mlp(z, costs, scale, hidden, steps, lr, batch, seed) -> list[np.ndarray]:
    """One tanh MLP's weights fitted on standardised inputs ``z`` with the regret loss."""
    import torch

    torch.set_num_threads(1)  # a small MLP: threads only contend (25× slower with 2 on the shared cores)
    torch.manual_seed(seed)
    x = torch.tensor(z, dtype=torch.float32)
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
    return [p.detach().numpy().astype(np.float64) for p in net.parameters()]


def save(run_dir: str | Path, student: Student, env_kwargs: dict, meta: dict) -> Path:
    """Write ``run.yaml`` and ``best.safetensors`` of ``student``."""
    import torch

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    arrays = {f"w{i}": w for i, w in enumerate(student.weights)}
    arrays.update({f"m{m}_w{i}": w for m, ws in enumerate(student.more, 1) for i, w in enumerate(ws)})
    arrays.update(mean=student.mean, std=student.std)
    tensors = {k: torch.from_numpy(np.ascontiguousarray(v, np.float64)) for k, v in arrays.items()}
    _write(run_dir / BEST, tensors, {"algo": ALGO})
    run = {
        "env_id": VQF_ID,
        "algo": ALGO,
        "env_kwargs": dict(env_kwargs),
        "candidates": [float(c) for c in student.candidates],
        "lags": list(student.lags),
        "rule": None if student.rule is None else list(student.rule),
        "n_layers": len(student.weights),
        "n_members": 1 + len(student.more),
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
    n, members = int(run["n_layers"]), int(run.get("n_members", 1))
    names = [[f"w{i}" if m == 0 else f"m{m}_w{i}" for i in range(n)] for m in range(members)]
    missing = [k for k in [*(k for ks in names for k in ks), "mean", "std"] if k not in tensors]
    if missing:
        raise RunError(f"{run_dir / BEST}: missing tensor(s) {missing}")
    arrays = {k: v.numpy().astype(np.float64) for k, v in tensors.items()}
    nets = [[arrays[k] for k in ks] for ks in names]
    student = Student(
        nets[0], arrays["mean"], arrays["std"], run["candidates"], run["lags"], run.get("rule"), more=nets[1:]
    )
    if student.mean.shape[0] != (len(FEATURES) + (student.rule is not None)) * (1 + len(student.lags)):
        raise RunError(f"{run_dir / BEST}: input size {student.mean.shape[0]} does not fit the features and lags")
    return StudentPolicy(student, run["env_kwargs"], name or f"agent:{run_dir.name}", str(run_dir / BEST))
