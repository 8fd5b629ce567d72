"""Learning targets: does a trained agent beat the best hand-tuned rule, and how fast?

    .venv/bin/python benchmarks/bench_learning.py [--algo ppo] [--steps 300000] [--out runs/bench_ppo]
                                                   [--seeds 0:10] [--eval-seeds 5000:5003]

Trains (or resumes) an agent with ``magenv train`` while recording held-out
RMSE and wall-clock time at each evaluation, then scores it beside every
rule on held-out ``dynamic_magnet`` and ``dynamic_clean`` seeds and prints:

* the agent's mean total RMSE against ``fan_lambda_tuned`` on
  ``dynamic_magnet`` (target: lower) and against the best rule on
  ``dynamic_clean`` (target: within 5 %);
* the wall-clock training time until the agent's held-out score first
  matched ``fan_lambda_tuned``'s on the same evaluation trials (2 CPU cores;
  target under 2 minutes), with and without the time the evaluations took;
* the training throughput in env-steps/s, evaluations excluded (target
  ≥ 10 k on 2 cores), and per CPU-second of the process (what one free core
  gives: robust to other jobs on the machine; torch runs one thread).

``--config`` trains with another config file (the shipped one by default).

It prints what it measures, whatever it is; nothing here is a pass/fail test.
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

import magenv  # noqa: F401
from magenv import evaluation, registry
from magenv.agents import training
from magenv.agents.training import held_out_trials, train
from magenv.train.compare import make_trials, print_table, select_methods
from magenv.train.seeds import parse_seeds

ENV_ID = "magenv/MagBlend-v0"
RULES = ["mimu", "imu", "fan_lambda", "fan_lambda_tuned", "threshold", "threshold_tuned"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--algo", default="ppo")
    p.add_argument("--steps", type=int, default=300_000)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--seeds", default="0:10", help="held-out seeds for the final table")
    p.add_argument(
        "--eval-seeds", default="5000:5003", help="held-out validation seeds for evaluations during training"
    )
    p.add_argument("--eval-every", type=int, default=25_000)
    p.add_argument("--config", default=None, help="config file (default: the shipped one of --algo)")
    args = p.parse_args()
    out = args.out or Path(f"runs/bench_{args.algo}")

    eval_seeds = tuple(parse_seeds(args.eval_seeds))
    scenarios = ("dynamic_magnet", "dynamic_clean")
    evaluations = []  # (timesteps, wall-clock seconds) of each held-out evaluation during training
    evaluate = training.HeldOutEvaluation.evaluate_and_checkpoint

    eval_cpu = [0.0]  # CPU seconds in the evaluations

    def timed_evaluation(self):
        t, c = time.perf_counter(), time.process_time()
        score = evaluate(self)
        evaluations.append((self.num_timesteps, time.perf_counter() - t))
        eval_cpu[0] += time.process_time() - c
        return score

    training.HeldOutEvaluation.evaluate_and_checkpoint = timed_evaluation
    t0, c0 = time.perf_counter(), time.process_time()
    train(
        ENV_ID,
        args.algo,
        args.steps,
        out,
        config=args.config,
        eval_every=args.eval_every,
        eval_scenarios=scenarios,
        eval_seeds=eval_seeds,
        progress_bar=True,
        make_method=registry.make,
    )
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0

    # fan_lambda_tuned on the same evaluation trials the callback used
    trials = held_out_trials(list(scenarios), list(eval_seeds))
    tuned = registry.make("fan_lambda_tuned")
    ref = float(np.mean([s.total for s in evaluation.run_policy_on_trials(tuned, trials)]))
    history = [(int(r[0]), float(r[1]), float(r[2])) for r in csv.reader(open(out / "evaluations.csv"))]
    matched = next(((steps, secs) for steps, score, secs in history if score <= ref), None)

    if matched:
        before = sum(secs for steps, secs in evaluations if steps <= matched[0])
        print(
            f"matched fan_lambda_tuned ({ref:.3f}° on the evaluation trials) after {matched[0]} steps, "
            f"{matched[1]:.0f} s of training wall-clock ({matched[1] - before:.0f} s without the evaluations; "
            "target < 120 s)"
        )
    else:
        print(f"did not match fan_lambda_tuned ({ref:.3f}° on the evaluation trials) within {args.steps} steps")
    spent = sum(secs for _, secs in evaluations)
    steps = history[-1][0] if history else 0
    print(
        f"this run's training wall-clock: {wall:.0f} s, of which {spent:.0f} s in {len(evaluations)} evaluations; "
        f"{steps / (wall - spent):.0f} env-steps/s without them (target >= 10000)"
    )
    print(
        f"CPU time of the training without the evaluations: {cpu - eval_cpu[0]:.0f} s, "
        f"{steps / (cpu - eval_cpu[0]):.0f} env-steps per CPU-second (the rate on one free core; set-up included)"
    )

    methods = select_methods(RULES + [registry.AGENT_PREFIX + str(out)])
    trials, labels = make_trials(",".join(scenarios), list(parse_seeds(args.seeds)), [])
    rows = evaluation.compare(methods, trials, labels=labels)
    print_table(rows, title=f"held-out seeds {args.seeds}: orientation RMSE (°)")
    agent = registry.AGENT_PREFIX + str(out)
    get = lambda m, s: next(r["total_rmse_mean"] for r in rows if r["method"] == m and r["scenario"] == s)
    a_mag, t_mag = get(agent, "dynamic_magnet"), get("fan_lambda_tuned", "dynamic_magnet")
    best_clean = min((get(m, "dynamic_clean"), m) for m in RULES)
    a_clean = get(agent, "dynamic_clean")
    print(
        f"dynamic_magnet: agent {a_mag:.3f}° vs fan_lambda_tuned {t_mag:.3f}° (ratio {a_mag / t_mag:.3f}; target < 1)"
    )
    print(
        f"dynamic_clean:  agent {a_clean:.3f}° vs best rule {best_clean[1]} {best_clean[0]:.3f}° "
        f"(ratio {a_clean / best_clean[0]:.3f}; target <= 1.05)"
    )


if __name__ == "__main__":
    main()
