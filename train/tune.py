"""``magenv tune``: optimise a hand-crafted rule's (or filter's) parameters with CMA-ES.

    magenv tune --rule fan_lambda [--scenarios random] [--seeds 10000:10016] [--iterations 30]

The objective is the mean total-orientation RMSE (degrees) of the rule over
fixed training trials (seeds at or above ``TRAIN_SEED_START``, so never the
held-out seeds that ``compare`` reports). The result is written to
``baselines/tuned/RULE.json`` and appears in ``compare`` as ``RULE_tuned``.
Parameters are searched in [0, 1] per dimension, mapped linearly (or
logarithmically where the rule's bounds span more than a decade) onto the
rule's ``PARAM_BOUNDS``.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from train.cli import CommandError
from magenv.scenarios import TRAINING_MIX
from magenv.seeding import HELD_OUT_BELOW as TRAIN_SEED_START
from train.seeds import parse_seeds



def _to_params(x: np.ndarray, bounds: dict[str, tuple[float, float]]) -> dict[str, float]:
    params = {}
    for xi, (name, (lo, hi)) in zip(np.clip(x, 0.0, 1.0), bounds.items()):
        log = lo > 0 and hi / lo > 10
        params[name] = float(np.exp(np.log(lo) + xi * np.log(hi / lo)) if log else lo + xi * (hi - lo))
    return params


def _to_unit(params: dict[str, float], bounds: dict[str, tuple[float, float]]) -> np.ndarray:
    x = []
    for name, (lo, hi) in bounds.items():
        v = float(np.clip(params[name], lo, hi))
        log = lo > 0 and hi / lo > 10
        x.append(np.log(v / lo) / np.log(hi / lo) if log else (v - lo) / (hi - lo))
    return np.array(x)


def tune_rule(rule: str, trials: list, iterations: int = 30, popsize: int = 8, seed: int = 0,
              progress: bool = True) -> dict:
    """CMA-ES over the rule's parameters (a bounded scalar search for one parameter); returns the
    record saved as ``baselines/tuned/RULE.json``."""
    import cma
    from tqdm import tqdm

    from baselines.registry import rule_class
    from magenv import evaluation

    cls = rule_class(rule)
    bounds = cls.PARAM_BOUNDS
    published = cls()  # the published parameter values are the constructor defaults

    def objective(params: dict) -> float:
        method = cls(**params)  # a policy (run in its env) or an estimator (run on the trial)
        runner = evaluation.PolicyRunner()
        return float(np.mean([evaluation.run_method(rule, method, t, runner).score.total for t in trials]))

    x0 = _to_unit(published.params, bounds)
    if len(bounds) == 1:  # CMA-ES needs two dimensions or more: bounded scalar search instead
        from scipy.optimize import minimize_scalar

        res = minimize_scalar(lambda x: objective(_to_params(np.array([x]), bounds)), bounds=(0.0, 1.0),
                              method="bounded", options={"maxiter": iterations * popsize})
        xbest, fbest = np.array([res.x]), float(res.fun)
    else:
        es = cma.CMAEvolutionStrategy(
            np.clip(x0, 0.05, 0.95), 0.25,
            {"bounds": [0, 1], "popsize": popsize, "seed": seed + 1, "verbose": -9, "maxiter": iterations},
        )
        bar = tqdm(total=iterations, desc=f"tune {rule}", disable=not progress)
        while not es.stop():
            xs = es.ask()
            es.tell(xs, [objective(_to_params(x, bounds)) for x in xs])
            bar.update(1)
            bar.set_postfix(best=f"{es.result.fbest:.3f}°")
        bar.close()
        xbest, fbest = es.result.xbest, float(es.result.fbest)
    best = _to_params(xbest, bounds)
    published_deg = objective(published.params)
    if published_deg <= fbest:  # the search never returns worse than where it started
        best, fbest = published.params, published_deg
    return {
        "rule": rule, "params": best, "objective_deg": fbest,
        "published_params": published.params, "published_objective_deg": published_deg,
        "trials": [t.name for t in trials], "cma": {"iterations": iterations, "popsize": popsize, "seed": seed},
        "date": time.strftime("%Y-%m-%d"),
    }


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rule", required=True, help="rule to tune (e.g. fan_lambda, threshold)")
    p.add_argument("--scenarios", default=TRAINING_MIX, help="comma list of training scenarios (default %(default)s)")
    p.add_argument("--seeds", default=f"{TRAIN_SEED_START}:{TRAIN_SEED_START + 12}",
                   help=f"training trial seeds, all >= {TRAIN_SEED_START} (default %(default)s)")
    p.add_argument("--iterations", type=int, default=30, help="CMA-ES generations")
    p.add_argument("--popsize", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from baselines.registry import TUNED_DIR
    from magenv.scenarios import make_trial

    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    if min(seeds) < TRAIN_SEED_START:
        raise CommandError(f"training seeds must be >= {TRAIN_SEED_START}; lower seeds are held out for evaluation")
    try:
        trials = [make_trial(s, seed) for s in args.scenarios.split(",") for seed in seeds]
        record = tune_rule(args.rule, trials, args.iterations, args.popsize, args.seed, not args.no_progress)
    except (KeyError, ValueError) as exc:
        raise CommandError(str(exc)) from None
    TUNED_DIR.mkdir(parents=True, exist_ok=True)
    path = TUNED_DIR / f"{args.rule}.json"
    path.write_text(json.dumps(record, indent=2) + "\n")
    print(f"{args.rule}: published {record['published_objective_deg']:.3f}° -> tuned {record['objective_deg']:.3f}° "
          f"on {len(trials)} training trials; params {record['params']} -> {path}")
    return 0
