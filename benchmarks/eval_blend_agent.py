"""Held-out evaluation of a MagBlend-v0 agent against the tuned Fan rule, with the oracle as headroom.

    .venv/bin/python benchmarks/eval_blend_agent.py --agent pretrained:magenv/MagBlend-v0 [--seeds 0:40]
        [--scenarios dynamic_magnet,stationary_magnet,dynamic_clean] [--json FILE]

For every scenario and held-out seed it runs the agent, ``fan_lambda_tuned``,
``mimu`` and the privileged ``oracle`` on the same trial and prints a Markdown
table: mean total RMSE (°) of each, the paired agent/rule ratio with its
bootstrap 95 % interval and the agent's win rate over the rule
(``magenv.stats.paired_ratio``: geometric mean of the per-trial ratios,
10 000 resamples of the trials, seed 0), and the share of the
rule-to-oracle gap of the mean RMSEs the agent closes ("headroom
captured"). ``--json`` writes every per-trial RMSE. It prints what it
measures; nothing here is a test.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import magenv  # noqa: F401
from magenv import evaluation, registry
from magenv.scenarios import make_trial
from magenv.stats import paired_ratio
from magenv.train.seeds import REPORT_SEEDS, check_report_seeds, seeds_arg

RULE, BASE, ORACLE = "fan_lambda_tuned", "mimu", "oracle"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--agent", required=True, help="run folder or pretrained:ENV_ID")
    p.add_argument("--seeds", type=seeds_arg, default=REPORT_SEEDS)
    p.add_argument("--scenarios", default="dynamic_magnet,stationary_magnet,dynamic_clean")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    check_report_seeds(args.seeds, validation=False)
    methods = {"agent": registry.make(registry.AGENT_PREFIX + args.agent), RULE: registry.make(RULE)}
    methods.update({BASE: registry.make(BASE), ORACLE: registry.make(ORACLE)})
    per_trial: dict = {}
    t0 = time.time()
    for sc in args.scenarios.split(","):
        runs = evaluation.evaluate(methods, [make_trial(sc, s) for s in args.seeds])
        per_trial[sc] = {m: [r.scored.total for r in runs if r.method == m] for m in methods}
    print(f"agent {args.agent}, held-out seeds {args.seeds[0]}:{args.seeds[-1] + 1} ({len(args.seeds)} per scenario)")
    print(
        f"| scenario | {BASE} | {RULE} | agent | {ORACLE} (headroom) | agent/rule paired ratio [95% CI] "
        "| win rate | interquartile-mean ratio [95% CI] | headroom captured |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for sc, res in per_trial.items():
        a, r, o = (np.array(res[m]) for m in ("agent", RULE, ORACLE))
        pr = paired_ratio(a, r)
        captured = (r.mean() - a.mean()) / (r.mean() - o.mean())
        print(
            f"| {sc} | {np.mean(res[BASE]):.3f} | {r.mean():.3f} | {a.mean():.3f} | {o.mean():.3f} | "
            f"{pr.ratio_text()} | {pr.win_rate:.2f} | {pr.iqm_text()} | {captured:.2f} |"
        )
    print(f"({time.time() - t0:.0f} s)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"agent": args.agent, "seeds": list(args.seeds), "per_trial_rmse": per_trial}, f, indent=1)


if __name__ == "__main__":
    main()
