"""Probe: how much would choosing the tuned constraint rule's parameters per trial, with hindsight, gain?

    python -m studies.hindsight_constraint [--tests constraint_test1,…] [--seeds 5000:5020]

For each trial it runs ``cf_constraint_tuned`` (eqs. 16 and 18 with the parameters of
``baselines/tuned/cf_constraint.json``) with th1 (eq. 16's weight threshold), k_max (eq. 18's largest gain), or
both (th1 × s, k_max / s) scaled by each of ``SCALES``, keeps the scale with the lowest total RMSE on that trial
(the truth chooses: an upper bound on adapting these parameters once per trial), and prints per test the
geometric mean over trials of best / rule and the chosen scales. Below the student's ratio, per-trial adaptation
of the rule is not where the student's gap lies; above it, the oracle's gain is in the timing within a trial.
Validation seeds by default (an analysis, not a reported figure); it prints figures, nothing here is a test.
"""

from __future__ import annotations

import argparse

import numpy as np

import magenv  # noqa: F401
from magenv import evaluation, registry
from magenv.baselines.constraint import ConstraintCF
from magenv.scenarios import make_trial
from magenv.train.seeds import seeds_arg

SCALES = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 4.0, 8.0)
K_MAX_LIMIT = ConstraintCF.PARAM_BOUNDS["k_max"][1]


def scaled(params: dict, which: str, s: float) -> dict:
    """``params`` with th1 × s ("th1"), k_max × s ("k_max"), or th1 × s and k_max / s ("both")."""
    p = dict(params)
    if which in ("th1", "both"):
        p["th1"] = params["th1"] * s
    if which in ("k_max", "both"):
        p["k_max"] = min(params["k_max"] * (s if which == "k_max" else 1.0 / s), K_MAX_LIMIT)
    return p


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tests", default="constraint_test1,constraint_test2,constraint_test3")
    ap.add_argument("--seeds", type=seeds_arg, default="5000:5020")
    args = ap.parse_args()
    params = registry.tuned_params("cf_constraint")
    for test in args.tests.split(","):
        trials = [make_trial(test, s) for s in args.seeds]
        totals = {  # (which, scale) → per-trial total RMSE
            (which, s): np.array(
                [
                    evaluation.run_method("rule", ConstraintCF(**scaled(params, which, s)), t).scored.total
                    for t in trials
                ]
            )
            for which in ("th1", "k_max", "both")
            for s in SCALES
        }
        rule = totals[("th1", 1.0)]
        for which in ("th1", "k_max", "both"):
            grid = np.stack([totals[(which, s)] for s in SCALES])  # (scales, trials)
            best = grid.min(0)
            chosen = [SCALES[i] for i in grid.argmin(0)]
            print(
                f"{test} {which}: hindsight per-trial best / rule {np.exp(np.mean(np.log(best / rule))):.3f} "
                f"(rule {rule.mean():.3f}°, best {best.mean():.3f}°); scales chosen {chosen}",
                flush=True,
            )


if __name__ == "__main__":
    main()
