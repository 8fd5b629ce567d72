"""``magenv demo``: the main job — train a PPO agent briefly, then compare it with the rules.

    magenv demo [--steps 150000] [--out runs/demo] [--seeds 0:5] [--csv results/demo.csv]

1. trains PPO on ``magenv/MagBlend-v0`` (training family ``random``, trial
   seeds at or above 10 000), with a progress bar; an existing ``--out`` run
   is resumed, or reused when it is complete;
2. runs the agent, the shipped DAgger agent (``pretrained:magenv/MagBlend-v0``),
   the rules at their published and CMA-tuned values (``baselines/tuned``),
   the original filters and the privileged ``oracle`` (the headroom row: it
   reads truth, an upper bound) on held-out ``dynamic_magnet`` and
   ``dynamic_clean`` seeds (below 10 000);
3. prints the table and writes it as CSV.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from magenv.agents.hyperparams import POSITIVE_INT
from magenv.envs import BLEND_ID as ENV_ID
from magenv.train.cli import CommandError, output_file, output_folder, rule_arg
from magenv.train.seeds import seeds_arg

RULES = ["mimu", "imu", "fan_lambda", "fan_lambda_tuned", "threshold", "threshold_tuned", "oracle"]
PRETRAINED = "pretrained:magenv/MagBlend-v0"  # the shipped agent, printed beside the one trained here


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--steps", type=rule_arg(POSITIVE_INT), default=150_000, help="PPO training steps (default %(default)s)"
    )
    p.add_argument("--out", type=Path, default=Path("runs/demo"), help="run folder (default %(default)s)")
    p.add_argument("--seeds", type=seeds_arg, default="0:5", help="held-out seeds per scenario (default %(default)s)")
    p.add_argument("--csv", default="results/demo.csv", help="CSV of the table (default %(default)s)")
    p.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from magenv import evaluation, registry
    from magenv.agents.hyperparams import ConfigError
    from magenv.agents.loading import RunError
    from magenv.agents.training import train
    from magenv.train.compare import (
        DEFAULT_REFERENCE,
        finish,
        headroom_names,
        make_trials,
        mark_headroom,
        run_comparison,
        select_methods,
    )

    args.out = output_folder(args.out, "--out")
    args.csv = output_file(args.csv, "--csv")
    print(f"[1/2] training PPO on {ENV_ID} for {args.steps} steps -> {args.out}")
    try:
        train(
            ENV_ID,
            "ppo",
            args.steps,
            args.out,
            eval_every=max(args.steps // 6, 2048),
            progress_bar=not args.no_progress,
            make_method=registry.make,
        )
    except (ConfigError, RunError) as exc:
        raise CommandError(str(exc)) from None
    available = set(registry.names())
    rules = [m for m in RULES if m in available]
    missing = sorted(set(RULES) - available)
    if missing:
        print(f"note: {', '.join(missing)} not available (run `magenv tune --rule ...` to make tuned rules)")
    print(f"[2/2] comparing on held-out dynamic_magnet and dynamic_clean seeds {args.seeds}")
    methods = select_methods(rules + [registry.AGENT_PREFIX + str(args.out), registry.AGENT_PREFIX + PRETRAINED])
    trials, labels = make_trials("dynamic_magnet,dynamic_clean", args.seeds, [])
    runs = run_comparison(methods, trials, labels, progress=not args.no_progress)
    rows = mark_headroom(evaluation.summarize(runs), headroom_names(methods))
    rows = evaluation.add_paired(rows, runs, DEFAULT_REFERENCE)
    return finish(rows, "learned vs hand-tuned magnetometer trust: orientation RMSE (°), held-out seeds", args.csv)
