"""Behaviour-cloning diagnostic on MagKalman-v0: which inputs carry ``oracle_kalman``'s decisions?

    python -m studies.bc_kalman_diagnostic [--train 4] [--val 2] [--label-every 2] [--fit-steps 3000]
        [--json FILE]

It rolls ``kf_model_tuned`` (the oracle's continuation rule) on ``--train``
training trials (seeds 10000, …) and ``--val`` validation trials (seeds 5000,
…) of each of ``dynamic_magnet`` and ``stationary_magnet``, labels one
decision in ``--label-every`` with the oracle's candidate costs (as
``magenv.agents.dagger`` does: regret r_c in % of the trial's rule MSE), fits
the DAgger student (``dagger.fit``, the regret loss) on the training labels
with several input sets and prints, on the validation labels, the expected
regret Σ_c p_c·r_c of each (lower = closer to the oracle; 0 = its choices):

* ``rule γ`` — the base observation's two rule proposals only (kf_model_tuned, kf_adaptive_tuned γ);
* ``base`` — the 19 base features and both proposals;
* ``extended`` — the student's inputs without the kf_adaptive proposal (the old student);
* ``extended+proposals`` — the student's inputs (``KalmanInputs`` with the packaged oracle);
* ``+ true heading error`` — those and the privileged signed heading error of the estimate (truth, °):
  an upper bound on what a causal estimate of that error could add.

Fixed references: the best single candidate, and the candidate nearest each rule's γ. This is a
measurement (it prints figures), not a test.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

import magenv  # noqa: F401
from magenv import registry
from magenv.agents import dagger
from magenv.agents.student_inputs import inputs_for
from magenv.envs import KALMAN_ID
from magenv.envs.blend_memory import _heading
from magenv.scenarios import make_trial

SCENARIOS = ("dynamic_magnet", "stationary_magnet")


class Recorder:
    """The oracle, also recording the privileged signed heading error (°) at each labelled decision."""

    def __init__(self, oracle):
        self.oracle, self.errors = oracle, []
        for a in dagger.TEACHER_NEEDS:
            if not hasattr(self, a):
                setattr(self, a, getattr(oracle, a))

    def candidate_costs(self, runner):
        q, t = runner.state.q, runner.q_true[runner.pos - 1]
        self.errors.append(_heading(q[0], q[1], q[2], q[3], t[0], t[1], t[2], t[3]))
        return self.oracle.candidate_costs(runner)


def collect(oracle, seeds, label_every):
    """(inputs (D, n_in), privileged heading error (D,), regret (D, C), scenario index (D,)) over ``seeds``."""
    inputs = inputs_for(KALMAN_ID)
    meta = inputs.meta(oracle)
    rec = Recorder(oracle)
    episodes = dagger.Episodes(KALMAN_ID, dagger.student_env_kwargs(inputs, oracle, oracle.decision_every), rec)

    def rule(o, runner, costs):
        return oracle.continuation_action(runner)

    xs, es, rs, ss = [], [], [], []
    for k, sc in enumerate(SCENARIOS):
        for s in seeds:
            trial = make_trial(sc, s)
            rec.errors = []
            obs, costs, _, rmse = episodes.run(trial, rule, label_every)
            horizon = int(round(oracle.horizon_s * trial.rate))
            xs.append(inputs(obs, meta))
            es.append(np.array(rec.errors))
            rs.append(dagger.regret_units(costs, horizon, rmse**2))
            ss.append(np.full(len(obs), k))
    return np.concatenate(xs), np.concatenate(es), np.concatenate(rs), np.concatenate(ss), meta


def column_sets(meta, n_in):
    """Input set name → column indices of KalmanInputs' output (blocks of [features, γ_model, γ_adaptive])."""
    block, n_rules = int(meta["block"]), 1 + len(meta.get("proposals", []))
    width = block + n_rules
    n_blocks = n_in // width
    everything = np.arange(n_in)
    no_adaptive = np.array([i for i in everything if i % width < block + 1])
    rules0 = np.arange(block, width)
    base = np.r_[np.arange(19), rules0]
    return {
        "rule γ": rules0,
        "base": base,
        "extended": no_adaptive,
        "extended+proposals": everything,
        "+ true heading error": np.r_[everything, n_in],
    }, n_blocks


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--train", type=int, default=4, help="training trials per scenario")
    p.add_argument("--val", type=int, default=2, help="validation trials per scenario")
    p.add_argument("--label-every", type=int, default=2)
    p.add_argument("--fit-steps", type=int, default=3000)
    p.add_argument("--json", default=None)
    args = p.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    oracle = registry.make("oracle_kalman")
    t0 = time.time()
    tr = collect(oracle, range(10000, 10000 + args.train), args.label_every)
    va = collect(oracle, range(5000, 5000 + args.val), args.label_every)
    print(f"labels: {len(tr[0])} train, {len(va[0])} validation, {time.time() - t0:.0f} s")
    meta = tr[4]
    sets, _ = column_sets(meta, tr[0].shape[1])
    full_tr, full_va = (np.c_[d[0], d[1][:, None] / 10.0].astype(np.float32) for d in (tr, va))
    cfg = {**dagger.DEFAULTS, "fit_steps": args.fit_steps}
    levels = oracle.levels
    r_va, s_va = va[2], va[3]

    def per_scenario(regret_rows):
        return {sc: float(regret_rows[s_va == k].mean()) for k, sc in enumerate(SCENARIOS)}

    result = {"labels": [len(tr[0]), len(va[0])], "fixed": {}, "fitted": {}}
    best_const = int(np.argmin(tr[2].mean(0)))
    result["fixed"][f"constant γ={levels[best_const]:g}"] = per_scenario(r_va[:, best_const])
    for j, name in enumerate(("kf_model_tuned", "kf_adaptive_tuned")):
        col = va[0][:, int(meta["block"]) + j]
        near = np.abs(col[:, None] - levels[None, :]).argmin(1)
        result["fixed"][f"nearest to {name}"] = per_scenario(r_va[np.arange(len(near)), near])
    result["fixed"]["oracle"] = per_scenario(np.zeros(len(r_va)))
    for name, cols in sets.items():
        t = time.time()
        st = dagger.fit(full_tr[:, cols], tr[2].astype(np.float32), cfg, 0, oracle.candidates, None, {})
        prob = st.probabilities(full_va[:, cols])
        result["fitted"][name] = per_scenario((prob * r_va).sum(1))
        print(f"  fit {name}: {time.time() - t:.0f} s")
    print("\nexpected regret on validation labels (% of the trial's kf_model_tuned MSE per look-ahead; 0 = oracle)")
    print("| inputs | " + " | ".join(SCENARIOS) + " |\n|---|" + "---|" * len(SCENARIOS))
    for group in ("fixed", "fitted"):
        for name, v in result[group].items():
            print(f"| {name} | " + " | ".join(f"{v[sc]:.3f}" for sc in SCENARIOS) + " |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
