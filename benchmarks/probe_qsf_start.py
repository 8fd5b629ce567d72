"""Probe on MagQSF-v0 ``handheld_texting``: do the student's causal inputs say when starting a new QSF period pays?

    .venv/bin/python benchmarks/probe_qsf_start.py [--trials 24] [--folds 8] [--json FILE]

It rolls the tuned detector policy (``oracle_qsf``'s continuation rule) on
``--trials`` training trials of ``handheld_texting`` (seeds 10000, …) and, at
every decision where the rule keeps its period, labels the advantage of
starting a new one over keeping it — the oracle's regret of "keep, trust 1"
minus that of "start" (``magenv.agents.dagger``'s unit: % of the trial's rule
MSE per 0.5 s look-ahead; clipped at ±20; > 0: the start pays). It then
predicts that advantage from the DAgger student's inputs
(``magenv.agents.student_inputs``) with ridge regressions and a small MLP,
trained on the trials of all folds but one and tested on the held-out fold's
trials (trials, not decisions, are held out: a student acts on trials it was
not fitted on), and prints per model the mean R² and correlation over the
folds and the advantage summed where the prediction is positive (a student
starting there) against where the truth is (the oracle's choice). This is a
measurement (it prints figures), not a test.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import magenv  # noqa: F401
from magenv import registry
from magenv.agents import dagger
from magenv.agents.student_inputs import inputs_for
from magenv.scenarios import make_trial

SCENARIO = "handheld_texting"
KEEP, START = 2, 3  # oracle_qsf's candidates: none, keep .3, keep 1, start
CLIP = 20.0  # units: a few diverged roll-outs otherwise decide the fits
RIDGES = (1.0, 100.0, 1.0e4)


def labelled(n_trials: int):
    """(inputs (D, n_in), advantage of start over keep (D,), trial index (D,)) at the rule's keep decisions."""
    teacher = registry.make("oracle_qsf")
    inputs = inputs_for(teacher.env_id)
    meta = inputs.meta(teacher)
    episodes = dagger.Episodes(teacher.env_id, dagger.student_env_kwargs(inputs, teacher, teacher.decision_every),
                               teacher)  # fmt: skip
    horizon = int(round(teacher.horizon_s * make_trial(SCENARIO, 10000).rate))

    def rule(o, runner, costs):
        return teacher.continuation_action(runner)

    xs, ys, groups = [], [], []
    for i in range(n_trials):
        trial = make_trial(SCENARIO, 10000 + i)
        lab = episodes.run(trial, rule)
        regret = dagger.REGRET_UNIT * (lab.costs - lab.costs.min(1, keepdims=True)) / (horizon * lab.rmse**2)
        keep = lab.rule == KEEP
        xs.append(inputs(lab.obs[keep], meta))
        ys.append(np.clip(regret[keep, KEEP] - regret[keep, START], -CLIP, CLIP))
        groups.append(np.full(int(keep.sum()), i))
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(groups)


def ridge(lam: float):
    def fit_predict(x, y, x_test):
        a = np.c_[x, np.ones(len(x))]
        w = np.linalg.solve(a.T @ a + lam * np.eye(a.shape[1]), a.T @ y)
        return np.c_[x_test, np.ones(len(x_test))] @ w

    return fit_predict


def mlp(x, y, x_test, hidden: int = 64, epochs: int = 30, seed: int = 0):
    import torch

    torch.manual_seed(seed)
    torch.set_num_threads(1)
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], hidden), torch.nn.Tanh(), torch.nn.Linear(hidden, 1))
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    xt, yt = torch.as_tensor(x, dtype=torch.float32), torch.as_tensor(y, dtype=torch.float32)
    for _ in range(epochs):
        perm = torch.randperm(len(xt))
        for b in range(0, len(xt), 512):
            ix = perm[b : b + 512]
            loss = ((net(xt[ix])[:, 0] - yt[ix]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    with torch.no_grad():
        return net(torch.as_tensor(x_test, dtype=torch.float32))[:, 0].numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=24)
    ap.add_argument("--folds", type=int, default=8)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    if args.trials < 2 or not 2 <= args.folds <= args.trials:
        ap.error("need --trials ≥ 2 and 2 ≤ --folds ≤ --trials")
    t = time.time()
    x, y, trial = labelled(args.trials)
    fold = trial % args.folds
    print(f"{SCENARIO}: {len(y)} decisions where the rule keeps, on {args.trials} trials; a start pays at "
          f"{np.mean(y > 0):.0%} of them ({time.time() - t:.0f} s)")  # fmt: skip
    models = {f"ridge λ={lam:g}": ridge(lam) for lam in RIDGES}
    models["MLP 64 tanh"] = mlp
    result = {}
    for name, fit_predict in models.items():
        r2, corr, gain, best = [], [], 0.0, 0.0
        for k in range(args.folds):
            train, test = fold != k, fold == k
            mu, sd = x[train].mean(0), x[train].std(0) + 1e-6
            p = fit_predict((x[train] - mu) / sd, y[train], (x[test] - mu) / sd)
            yt = y[test]
            r2.append(1.0 - np.mean((p - yt) ** 2) / np.var(yt))
            corr.append(float(np.corrcoef(p, yt)[0, 1]))
            gain += float(yt[p > 0].sum())
            best += float(yt[yt > 0].sum())
        result[name] = {"r2": float(np.mean(r2)), "corr": float(np.mean(corr)), "corr_by_fold": corr,
                        "gain": gain, "truth_gain": best}  # fmt: skip
        print(f"{name:14s} held-out R² {np.mean(r2):6.2f}, correlation {np.mean(corr):5.2f} "
              f"(folds {min(corr):.2f}…{max(corr):.2f}); starting where predicted > 0 saves {gain:8.0f} units "
              f"(the truth's choice {best:.0f})")  # fmt: skip
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"scenario": SCENARIO, "trials": args.trials, "folds": args.folds, **result}, f, indent=1)


if __name__ == "__main__":
    main()
