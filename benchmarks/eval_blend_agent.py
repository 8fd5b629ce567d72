"""Held-out evaluation of a MagBlend-v0 agent against the tuned Fan rule, with the oracle as headroom.

    .venv/bin/python benchmarks/eval_blend_agent.py --agent pretrained:magenv/MagBlend-v0 [--seeds 0:40]
        [--scenarios dynamic_magnet,stationary_magnet,dynamic_clean] [--json FILE]

For every scenario and held-out seed it runs the agent, ``fan_lambda_tuned``,
``mimu`` and the privileged ``oracle`` on the same trial and prints a Markdown
table: mean total RMSE (°) of each, the agent/rule **ratio of means** with a
paired percentile-bootstrap 95 % interval (10 000 resamples of the trials,
seed 0), the agent's win rate over the rule (fraction of trials with lower
RMSE) and the share of the rule-to-oracle gap the agent closes ("headroom
captured"). ``--json`` writes every per-trial RMSE, so other statistics
(``magenv.stats.paired_ratio``'s geometric-mean ratio, say) can be computed
from the same runs. It prints what it measures; nothing here is a test.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import magenv  # noqa: F401
from magenv import evaluation, registry
from magenv.scenarios import make_trial
from magenv.train.seeds import seeds_arg

RULE, BASE, ORACLE = "fan_lambda_tuned", "mimu", "oracle"


def ratio_of_means(agent: np.ndarray, rule: np.ndarray, n_boot: int = 10_000, seed: int = 0) -> tuple:
    """mean(agent)/mean(rule) and its paired bootstrap 95 % interval (trials resampled in pairs)."""
    idx = np.random.default_rng(seed).integers(0, len(agent), (n_boot, len(agent)))
    boot = agent[idx].mean(1) / rule[idx].mean(1)
    return agent.mean() / rule.mean(), *np.percentile(boot, [2.5, 97.5])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--agent", required=True, help="run folder or pretrained:ENV_ID")
    p.add_argument("--seeds", type=seeds_arg, default="0:40")
    p.add_argument("--scenarios", default="dynamic_magnet,stationary_magnet,dynamic_clean")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    if max(args.seeds) >= 5000:
        raise SystemExit("reported figures use held-out seeds below 5000")
    methods = {"agent": registry.make(registry.AGENT_PREFIX + args.agent), RULE: registry.make(RULE)}
    methods.update({BASE: registry.make(BASE), ORACLE: registry.make(ORACLE)})
    per_trial: dict = {}
    t0 = time.time()
    for sc in args.scenarios.split(","):
        runs = evaluation.evaluate(methods, [make_trial(sc, s) for s in args.seeds])
        per_trial[sc] = {m: [r.score.total for r in runs if r.method == m] for m in methods}
    print(f"agent {args.agent}, held-out seeds {args.seeds[0]}:{args.seeds[-1] + 1} ({len(args.seeds)} per scenario)")
    print(
        f"| scenario | {BASE} | {RULE} | agent | {ORACLE} (headroom) | agent/rule ratio of means [95% CI] "
        "| win rate | headroom captured |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for sc, res in per_trial.items():
        a, r, o = (np.array(res[m]) for m in ("agent", RULE, ORACLE))
        ratio, low, high = ratio_of_means(a, r)
        captured = (r.mean() - a.mean()) / (r.mean() - o.mean())
        print(
            f"| {sc} | {np.mean(res[BASE]):.3f} | {r.mean():.3f} | {a.mean():.3f} | {o.mean():.3f} | "
            f"{ratio:.3f} [{low:.3f}, {high:.3f}] | {np.mean(a < r):.2f} | {captured:.2f} |"
        )
    print(f"({time.time() - t0:.0f} s)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"agent": args.agent, "seeds": list(args.seeds), "per_trial_rmse": per_trial}, f, indent=1)


if __name__ == "__main__":
    main()
