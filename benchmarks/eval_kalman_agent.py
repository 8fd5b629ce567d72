"""Held-out evaluation on MagKalman-v0: an agent against the best Kalman rule of each protocol, the oracle as headroom.

    .venv/bin/python benchmarks/eval_kalman_agent.py [--agent pretrained:magenv/MagKalman-v0] [--seeds 0:40]
        [--scenarios dynamic_magnet,stationary_magnet]
        [--methods kf_model_tuned,kf_adaptive_tuned,kf_still_tuned,kf_perp_tuned,oracle_kalman]
        [--json FILE] [--validation]

For every scenario and held-out seed it runs the agent (if given) and the
methods on the same trial and prints a Markdown table: mean total RMSE (°) of
each and, for the agent and the oracle, the paired ratio to the protocol's
best rule (``kf_model_tuned`` on dynamic_magnet, ``kf_adaptive_tuned`` on
stationary_magnet; ``magenv.stats.paired_ratio``: geometric mean of the
per-trial ratios, bootstrap 95 % interval over the trials, win rate), and the
share of the rule-to-oracle gap of the mean RMSEs the agent closes. With the
scenario's hand rule on the students' own information among the methods (the
default: ``kf_perp_tuned``, which reads ``d_perp``, on dynamic_magnet;
``kf_still_tuned``, which reads the still anchor, on stationary_magnet) it
also gives the agent's paired ratio to that rule: how much of the agent's gain
is learning rather than information.
``--json`` writes every per-trial RMSE; with an existing file, methods already
in it are read back instead of run again (the oracle is the slow one).
``--validation`` takes validation seeds (5000–9999) instead, for model
selection. It prints what it measures; nothing here is a test.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

import magenv  # noqa: F401
from magenv import evaluation, registry
from magenv.scenarios import make_trial
from magenv.stats import paired_ratio
from magenv.train.seeds import REPORT_SEEDS, check_report_seeds, seeds_arg

BEST_RULE = {"dynamic_magnet": "kf_model_tuned", "stationary_magnet": "kf_adaptive_tuned"}
ORACLE = "oracle_kalman"
#: per scenario, the hand rule on the students' own information (baselines/kalman_policies.py): d_perp, still anchor
SAME_INFORMATION = {"dynamic_magnet": "kf_perp_tuned", "stationary_magnet": "kf_still_tuned"}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--agent", default=None, help="run folder or pretrained:ENV_ID")
    p.add_argument("--seeds", type=seeds_arg, default=REPORT_SEEDS)
    p.add_argument("--scenarios", default="dynamic_magnet,stationary_magnet")
    same = ",".join(dict.fromkeys(SAME_INFORMATION.values()))
    p.add_argument("--methods", default=f"kf_model_tuned,kf_adaptive_tuned,{same},{ORACLE}")
    p.add_argument("--json", default=None)
    p.add_argument("--validation", action="store_true", help="validation seeds 5000–9999 (model selection)")
    args = p.parse_args()
    check_report_seeds(args.seeds, args.validation)
    seeds = list(args.seeds)
    old = {}
    if args.json and os.path.exists(args.json):
        with open(args.json) as f:
            old = json.load(f)
        if old.get("seeds") != seeds:
            raise SystemExit(f"{args.json} holds seeds {old.get('seeds')}, not {seeds}")
    per_trial: dict = old.get("per_trial_rmse", {})
    names = args.methods.split(",") + (["agent"] if args.agent else [])
    t0 = time.time()
    for sc in args.scenarios.split(","):
        have = per_trial.setdefault(sc, {})
        todo = {m: registry.make(m) for m in names if m != "agent" and m not in have}
        if args.agent:
            todo["agent"] = registry.make(registry.AGENT_PREFIX + args.agent)
        if todo:
            runs = evaluation.evaluate(todo, [make_trial(sc, s) for s in seeds])
            have.update({m: [r.scored.total for r in runs if r.method == m] for m in todo})
        if args.json:
            with open(args.json, "w") as f:
                json.dump({"agent": args.agent, "seeds": seeds, "per_trial_rmse": per_trial}, f, indent=1)
    kind = "validation" if args.validation else "held-out"
    print(f"agent {args.agent}, {kind} seeds {seeds[0]}:{seeds[-1] + 1} ({len(seeds)} per scenario)")
    cols = [m for m in names if m != ORACLE] + ([ORACLE] if ORACLE in names else [])
    print(
        "| scenario | " + " | ".join(cols) + " | best rule | paired ratio to it [95% CI], win rate; interquartile-mean "
        "ratio [95% CI] | captured |"
    )
    print("|---|" + "---|" * (len(cols) + 3))
    for sc in args.scenarios.split(","):
        res = {m: np.array(v) for m, v in per_trial[sc].items()}
        rule = BEST_RULE.get(sc, "kf_model_tuned")
        cells = []
        same = SAME_INFORMATION.get(sc, "")
        for m, ref, label in (("agent", rule, "agent"), (ORACLE, rule, ORACLE), ("agent", same, f"agent/{same}")):
            if m in res and ref in res:
                pr = paired_ratio(res[m], res[ref])
                cells.append(f"{label}: {pr.ratio_text()}, {pr.win_rate:.2f}; IQM {pr.iqm_text()}")
        captured = ""
        if "agent" in res and ORACLE in res:
            r, a, o = res[rule].mean(), res["agent"].mean(), res[ORACLE].mean()
            captured = f"{(r - a) / (r - o):.2f}"
        means = " | ".join(f"{res[m].mean():.3f}" for m in cols)
        print(f"| {sc} | {means} | {rule} | {'; '.join(cells)} | {captured} |")
    print(f"({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
