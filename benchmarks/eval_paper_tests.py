"""Held-out evaluation on the paper tests of MagConstraint-v0 or MagQSF-v0: tuned rule, oracle headroom, an agent.

    .venv/bin/python benchmarks/eval_paper_tests.py --env constraint|qsf [--seeds 0:40] [--agent RUN|pretrained:ID]
        [--scenarios a,b] [--no-oracle] [--no-others] [--json FILE] [--validation]

For every paper test (``constraint_test1–3``; ``handheld_texting/swinging/corridor/free``) and held-out seed it
runs, on the same trial, the env's tuned rule (the reference: ``cf_constraint_tuned``; ``qsf_detector_tuned``),
the other rules listed in ``OTHERS``, the privileged oracle (``oracle_constraint``; ``oracle_qsf``: an upper
bound that reads truth) and, with ``--agent``, a trained agent; it prints a Markdown table of mean total RMSE
(°) and, for every other method, the paired ratio to the rule (``magenv.stats.paired_ratio``: geometric
mean of the per-trial ratios, bootstrap 95 % interval over the trials, 10 000 resamples, seed 0) with the win
rate and the interquartile-mean ratio (the middle half of the per-trial log ratios) with its interval.
With the hand rule on the constraint student's own information among the methods (``SAME_INFORMATION``:
``cf_cerr_tuned``, which reads the constraint error estimate) each agent's paired ratio to that rule follows:
how much of the agent's gain is learning rather than information.
``--agent`` may be given more than once (each compared on the same trials; named by its argument).
``--json`` writes every per-trial RMSE. ``--validation`` takes validation seeds (5000–9999) instead, for model
selection (never reported figures). It prints what it measures; nothing here is a test.
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

TESTS = {
    "constraint": ("constraint_test1", "constraint_test2", "constraint_test3"),
    "qsf": ("handheld_texting", "handheld_swinging", "handheld_corridor", "handheld_free"),
}
RULE = {"constraint": "cf_constraint_tuned", "qsf": "qsf_detector_tuned"}
#: per env, the hand rule on its student's own extended inputs (baselines/constraint.py: cf_cerr)
SAME_INFORMATION = {"constraint": "cf_cerr_tuned"}
OTHERS = {"constraint": ("cf_constraint", SAME_INFORMATION["constraint"]), "qsf": ("delay_magyq_tuned", "qsf_hold")}
ORACLE = {"constraint": "oracle_constraint", "qsf": "oracle_qsf"}


def _cell(pr) -> str:
    return f"{pr.ratio_text()} ({pr.win_rate:.2f}; IQM {pr.iqm_text()})"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", required=True, choices=sorted(TESTS))
    p.add_argument("--seeds", type=seeds_arg, default=REPORT_SEEDS)
    p.add_argument("--agent", action="append", default=[], help="run folder or pretrained:ENV_ID (repeatable)")
    p.add_argument("--scenarios", default=None, help="comma list (default: the env's paper tests)")
    p.add_argument("--no-oracle", action="store_true")
    p.add_argument("--no-others", action="store_true", help=f"only the tuned rule of {sorted(RULE.values())}")
    p.add_argument("--validation", action="store_true", help="validation seeds 5000–9999 (model selection)")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    check_report_seeds(args.seeds, args.validation)
    rule, oracle = RULE[args.env], ORACLE[args.env]
    names = [rule, *([] if args.no_others else OTHERS[args.env])] + ([] if args.no_oracle else [oracle])
    methods = {m: registry.make(m) for m in names}
    agents = {("agent" if len(args.agent) == 1 else a): a for a in args.agent}
    for name, agent in agents.items():
        methods[name] = registry.make(registry.AGENT_PREFIX + agent)
    scenarios = args.scenarios.split(",") if args.scenarios else TESTS[args.env]
    per_trial: dict = {}
    t0 = time.time()
    for sc in scenarios:
        t = time.time()
        runs = evaluation.evaluate(methods, [make_trial(sc, s) for s in args.seeds])
        per_trial[sc] = {m: [r.scored.total for r in runs if r.method == m] for m in methods}
        print(f"{sc}: {time.time() - t:.0f} s", flush=True)
        if args.json:  # after each test, so that a long run keeps what it has
            with open(args.json, "w") as f:
                json.dump(
                    {"env": args.env, "agent": args.agent, "seeds": list(args.seeds), "per_trial_rmse": per_trial}, f
                )
    same = SAME_INFORMATION.get(args.env)
    pairs = [(m, rule) for m in methods if m != rule] + [(a, same) for a in agents if same in methods]
    kind = "validation" if args.validation else "held-out"
    print(f"{kind} seeds {args.seeds[0]}:{args.seeds[-1] + 1} ({len(args.seeds)} per test); RMSE °, mean over trials")
    head = " | ".join([*methods, *(f"{m}/{ref} [95% CI] (win; IQM [95% CI])" for m, ref in pairs)])
    print(f"| test | {head} |")
    print("|---" * (1 + len(methods) + len(pairs)) + "|")
    for sc, res in per_trial.items():
        cells = [f"{np.mean(res[m]):.3f}" for m in methods]
        cells += [_cell(paired_ratio(np.array(res[m]), np.array(res[ref]))) for m, ref in pairs]
        print(f"| {sc} | {' | '.join(cells)} |")
    print(f"({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
