"""Probe: do a DAgger student's causal inputs say when departing from the rule pays, on trials it was not fitted on?

    python -m studies.probe_advantage [--env qsf|constraint|kalman] [--trials 24] [--folds 8] [--history]
        [--horizon S] [--label-every N] [--truth] [--json FILE]

It rolls the teacher's continuation rule on ``--trials`` training trials
(seeds 10000, …) of the test where the student misses its target and labels,
at every decision where the rule takes the given candidate, the teacher's
advantage of one departure over the rule (the regret of the rule's candidate
minus that of the departure, in ``magenv.agents.dagger``'s unit: % of the
trial's rule MSE per look-ahead; clipped at ±20; > 0: the departure pays):

* ``qsf`` — ``handheld_texting``, ``oracle_qsf``: starting a new QSF period, refusing the magnetometer (none)
  and keeping the period with trust 0.3 where the tuned detector keeps its period with trust 1 (candidates none,
  keep .3, keep 1, start);
* ``constraint`` — ``constraint_test1``, ``oracle_constraint_rules``: the magnetometer alone (w = 0, eq. 15's
  weights (1 − w) on it, w on the constraint) and the constraint alone (w = 1, the magnetometer refused) instead
  of the rule's own w (candidates w 0, .25, .5, .75, 1, the rule's w);
* ``kalman`` — ``dynamic_magnet``, ``oracle_kalman_still``: the magnetometer's Kalman update skipped (γ = 0) and
  taken in full (γ = 1) instead of kf_model_tuned's γ (candidates γ 0, .25, .5, 1, then the γ of kf_model_tuned,
  kf_adaptive_tuned and kf_still_tuned at that state).

It then predicts each advantage from the student's inputs
(``magenv.agents.student_inputs``) with ridge regressions and a small MLP,
trained on the trials of all folds but one and tested on the held-out fold's
(trials, not decisions, are held out: a student acts on trials it was not
fitted on), and prints per model the mean R² and correlation over the folds
and the advantage summed where the prediction is positive (a student departing
there) against where the truth is (the oracle's choice) and everywhere. With
``--history`` the inputs also carry their causal exponential moving averages
over ``HISTORY_DECISIONS`` decisions along the trial (a proxy for what a
recurrent student could draw from a longer past; time constants in labelled
decisions). ``--horizon S`` labels with a look-ahead of S seconds (cut short
at a trial's end) instead of the teacher's own (what a start or a refusal
costs over longer than the teacher sees), ``--label-every N`` only every N-th
decision (long look-aheads are expensive). ``--truth`` also fits on privileged
inputs alone: the estimate's true signed heading error (yaw of q̂ ⊗ q_true*,
°, ``magenv.metrics.euler_error``) at the decision and ``TRUTH_LAGS``
decisions earlier, and its magnitude — if even these do not predict the
advantage, what the student lacks is not its own error. This is a measurement
(it prints figures), not a test.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import magenv  # noqa: F401
from magenv import metrics, registry
from magenv.agents import dagger
from magenv.agents.student_inputs import inputs_for
from magenv.scenarios import make_trial

#: env → (scenario, teacher, the rule's candidate, {departure name: its candidate}); the probed decisions are those
#: where the rule's candidate is the given one (``dagger.Labelled.rule``; constraint: the rule's w is the last;
#: kalman: kf_model_tuned's γ, the first of the three rules' γ)
PROBES = {
    "qsf": ("handheld_texting", "oracle_qsf", 2, {"start": 3, "none": 0, "keep, trust 0.3": 1}),
    "constraint": ("constraint_test1", "oracle_constraint_rules", 5, {"w = 0": 0, "w = 1": 4}),
    "kalman": ("dynamic_magnet", "oracle_kalman_still", 4, {"γ = 0": 0, "γ = 1": 3}),
}
CLIP = 20.0  # units: a few diverged roll-outs otherwise decide the fits
RIDGES = (1.0, 100.0, 1.0e4)
HISTORY_DECISIONS = (10.0, 40.0, 160.0)  # EMA time constants of --history, in decisions
TRUTH_LAGS = (10, 40)  # decisions: the true heading error this many decisions earlier is a --truth input too


def with_history(x: np.ndarray) -> np.ndarray:
    """``x`` (decisions of one trial in order, n_in) followed by its EMAs over each of ``HISTORY_DECISIONS``
    (m_t = m_{t−1} + (x_t − m_{t−1}) / τ, m_0 = x_0)."""
    out = [x]
    for tau in HISTORY_DECISIONS:
        m, ema = x[0].copy(), np.empty_like(x)
        for t in range(len(x)):
            m += (x[t] - m) / tau
            ema[t] = m
        out.append(ema)
    return np.concatenate(out, 1)


def labelled(env: str, n_trials: int, history: bool = False, horizon_s: float | None = None, label_every: int = 1):
    """(inputs (D, n_in), {departure: its advantage over the rule (D,)}, trial index (D,), privileged inputs (D, 4))
    at the probed decisions. ``history``: the inputs followed by their EMAs (:func:`with_history`, over the labelled
    decisions of a trial: with ``label_every`` N each time constant spans N times as many decisions);
    ``horizon_s``: the teacher's look-ahead, s (None: its own; cut short at the trial's end, as the teacher's is);
    ``label_every``: one decision in that many is labelled. The privileged inputs: the true signed heading error (°)
    at the decision and ``TRUTH_LAGS`` decisions earlier (the first decision's value before it), and its
    magnitude."""
    scenario, name, rule_col, departures = PROBES[env]
    teacher = registry.make(name)
    if horizon_s is not None:
        teacher.horizon_s = horizon_s  # every oracle reads its look-ahead from this attribute at each search
    inputs = inputs_for(teacher.env_id)
    meta = inputs.meta(teacher)
    kwargs = dagger.student_env_kwargs(inputs, teacher, teacher.decision_every)
    episodes = dagger.teacher_episodes(teacher.env_id, kwargs, teacher, inputs, meta, teacher.candidates)
    horizon = int(round(teacher.horizon_s * make_trial(scenario, 10000).rate))
    if horizon < 1:
        raise ValueError(f"a look-ahead of {teacher.horizon_s} s is under one sample")

    xs, groups, ys, privileged = [], [], {d: [] for d in departures}, []
    for i in range(n_trials):
        trial = make_trial(scenario, 10000 + i)
        fused = []  # samples fused before each decision

        def rule(o, runner, costs, fused=fused):
            fused.append(runner.pos)
            return teacher.continuation_action(runner)

        lab = episodes.run(trial, rule, label_every)
        yaw = metrics.euler_error(episodes.env(trial).estimate, trial.q_true)[:, 0]
        yaw = np.nan_to_num(yaw)[np.maximum(np.array(fused) - 1, 0)]  # at the last sample fused (0 before any)
        d = np.arange(0, len(fused), label_every)
        truth = np.c_[yaw[d], *(yaw[np.maximum(d - lag, 0)] for lag in TRUTH_LAGS), np.abs(yaw[d])]
        regret = dagger.regret_units(lab.costs, horizon, lab.rmse**2)
        at = lab.rule == rule_col
        x = np.asarray(inputs(lab.obs, meta), np.float64)
        xs.append((with_history(x) if history else x)[at])  # EMAs over the labelled decisions
        privileged.append(truth[at])
        groups.append(np.full(int(at.sum()), i))
        for dep, col in departures.items():
            ys[dep].append(np.clip(regret[at, rule_col] - regret[at, col], -CLIP, CLIP))
    ys = {dep: np.concatenate(y) for dep, y in ys.items()}
    return np.concatenate(xs), ys, np.concatenate(groups), np.concatenate(privileged)


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


def probe(x, y, fold, folds: int) -> dict:
    """Per model: mean held-out R² and correlation over the folds, and the advantage summed on the held-out trials
    where the prediction is positive (``gain``) and where the truth is (``truth_gain``)."""
    models = {f"ridge λ={lam:g}": ridge(lam) for lam in RIDGES}
    models["MLP 64 tanh"] = mlp
    result = {}
    for name, fit_predict in models.items():
        r2, corr, gain, best = [], [], 0.0, 0.0
        for k in range(folds):
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
        print(f"  {name:14s} held-out R² {np.mean(r2):6.2f}, correlation {np.mean(corr):5.2f} "
              f"(folds {min(corr):.2f}…{max(corr):.2f}); departing where predicted > 0 saves {gain:8.0f} units "
              f"(the truth's choice {best:.0f})")  # fmt: skip
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--env", choices=sorted(PROBES), default="qsf")
    ap.add_argument("--trials", type=int, default=24)
    ap.add_argument("--folds", type=int, default=8)
    taus = ", ".join(f"{t:g}" for t in HISTORY_DECISIONS)
    ap.add_argument("--history", action="store_true", help=f"the inputs' EMAs over {taus} labelled decisions too")
    ap.add_argument("--horizon", type=float, default=None, help="look-ahead of the labels, s (default: the teacher's)")
    ap.add_argument("--label-every", type=int, default=1, help="label one decision in N")
    ap.add_argument("--truth", action="store_true", help="also fit on the true signed heading error (privileged)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    if args.trials < 2 or not 2 <= args.folds <= args.trials:
        ap.error("need --trials ≥ 2 and 2 ≤ --folds ≤ --trials")
    if args.label_every < 1 or (args.horizon is not None and not args.horizon > 0):
        ap.error("need --label-every ≥ 1 and --horizon > 0")
    t = time.time()
    x, advantages, trial, truth = labelled(args.env, args.trials, args.history, args.horizon, args.label_every)
    fold = trial % args.folds
    scenario = PROBES[args.env][0]
    print(f"{scenario}: {len(x)} decisions of the rule's probed candidate on {args.trials} trials "
          f"({time.time() - t:.0f} s)")  # fmt: skip
    result: dict = {}
    for departure, y in advantages.items():
        print(f"{departure} instead of the rule: it pays at {np.mean(y > 0):.0%} of them; departing at every one "
              f"saves {y.sum():.0f} units")  # fmt: skip
        result[departure] = {"always": float(y.sum()), **probe(x, y, fold, args.folds)}
        if args.truth:
            lags = ", ".join(str(lag) for lag in TRUTH_LAGS)
            print(f" from the true signed heading error (now, {lags} decisions earlier) and its magnitude:")
            result[departure]["truth"] = probe(truth, y, fold, args.folds)
    if args.json:
        options = {"horizon_s": args.horizon, "label_every": args.label_every, "history": args.history}
        with open(args.json, "w") as f:
            json.dump({"scenario": scenario, "trials": args.trials, "folds": args.folds, **options, **result}, f,
                      indent=1)  # fmt: skip


if __name__ == "__main__":
    main()
