"""Tuning a hand-crafted rule's (or filter's) parameters with CMA-ES (the engine of ``magenv tune``).

The objective is the mean total-orientation RMSE (degrees) of the rule over
given training trials. Parameters are searched in [0, 1] per dimension,
mapped linearly (or logarithmically where the rule's bounds span more than a
decade) onto the rule's ``PARAM_BOUNDS``. The search starts from the
published values (the constructor's defaults), or from given values of some
parameters (``start``: e.g. another rule's tuned parameters that this rule
shares; then with a smaller first step, ``SIGMA_START``), and never returns worse than where it started.
"""

from __future__ import annotations

import time

import numpy as np

from magenv import evaluation
from magenv.protocols import Tunable

SIGMA = 0.25  # CMA-ES's initial step in the unit cube: a search from the published values
SIGMA_START = 0.1  # from given values (e.g. another rule's tuned ones): a refinement around them


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


def tune_rule(
    rule: str,
    cls: type[Tunable],
    trials: list,
    iterations: int = 30,
    popsize: int = 8,
    seed: int = 0,
    progress: bool = True,
    start: dict[str, float] | None = None,
) -> dict:
    """CMA-ES over the parameters of ``cls`` (the tunable rule named ``rule``; a bounded scalar search for
    one parameter) from the published values, those named in ``start`` replaced; returns the record
    ``magenv tune`` saves as ``RULE.json``."""
    import cma
    from tqdm import tqdm

    bounds = cls.PARAM_BOUNDS
    published = cls()  # the published parameter values are the constructor defaults

    def objective(params: dict) -> float:
        method = cls(**params)  # a policy (run in its env) or an estimator (run on the trial)
        runner = evaluation.PolicyRunner()
        return float(np.mean([evaluation.run_method(rule, method, t, runner).scored.total for t in trials]))

    unknown = sorted(set(start or {}) - set(bounds))
    if unknown:
        raise ValueError(f"{cls.__name__} has no parameter(s) {unknown} to start from; known: {list(bounds)}")
    first = {**published.params, **(start or {})}
    x0 = _to_unit(first, bounds)
    if len(bounds) == 1:  # CMA-ES needs two dimensions or more: bounded scalar search instead
        from scipy.optimize import minimize_scalar

        res = minimize_scalar(
            lambda x: objective(_to_params(np.array([x]), bounds)),
            bounds=(0.0, 1.0),
            method="bounded",
            options={"maxiter": iterations * popsize},
        )
        xbest, fbest = np.array([res.x]), float(res.fun)
    else:
        es = cma.CMAEvolutionStrategy(
            np.clip(x0, 0.05, 0.95),
            SIGMA_START if start else SIGMA,
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
    first_deg = objective(first) if start else published_deg
    for where, deg in ((first, first_deg), (published.params, published_deg)):
        if deg <= fbest:  # the search never returns worse than where it started
            best, fbest = where, deg
    return {
        "rule": rule,
        "params": best,
        "objective_deg": fbest,
        "published_params": published.params,
        "published_objective_deg": published_deg,
        **({"start_params": first, "start_objective_deg": first_deg} if start else {}),
        "trials": [t.name for t in trials],
        "cma": {"iterations": iterations, "popsize": popsize, "seed": seed},
        "date": time.strftime("%Y-%m-%d"),
    }
