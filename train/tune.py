"""``magenv tune``: optimise a hand-crafted rule's (or filter's) parameters with CMA-ES.

    magenv tune --rule fan_lambda [--scenarios random] [--seeds 10000:10016] [--iterations 30]
    magenv tune --rule vqf_fan_lambda --scenarios dynamic_magnet,recording:2*   # simulated and real trials
    magenv tune --rule cf_cerr --start-from cf_constraint   # start from the parameters it shares with a tuned rule

The objective is the mean total-orientation RMSE (degrees) of the rule over
fixed training trials (seeds at or above ``TRAIN_SEED_START``, so never the
held-out seeds that ``compare`` reports); the search is
``magenv.baselines.tuning``. The result is written to ``--out`` (default:
the user's data directory, ``magenv.registry.user_tuned_dir()``, never the
installed package) as ``RULE.json``; ``compare`` then finds it as
``RULE_tuned``, reading the user's files before the ones shipped with magenv.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from magenv.agents.hyperparams import POSITIVE_INT, SEED_RULE, integer
from magenv.scenarios import TRAINING_MIX
from magenv.seeding import HELD_OUT_BELOW as TRAIN_SEED_START
from magenv.train.cli import CommandError, output_file, output_folder, rule_arg
from magenv.train.seeds import seeds_arg


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rule", required=True, help="rule to tune (e.g. fan_lambda, threshold)")
    p.add_argument(
        "--scenarios",
        default=TRAINING_MIX,
        help="comma list of training scenarios, recording:GLOB entries allowed (default %(default)s)",
    )
    p.add_argument(
        "--seeds",
        type=seeds_arg,
        default=f"{TRAIN_SEED_START}:{TRAIN_SEED_START + 12}",
        help=f"training trial seeds, all >= {TRAIN_SEED_START} (default %(default)s)",
    )
    p.add_argument("--iterations", type=rule_arg(POSITIVE_INT), default=30, help="CMA-ES generations")
    p.add_argument("--popsize", type=rule_arg(integer(2)), default=8, help="CMA-ES population (default %(default)s)")
    p.add_argument("--seed", type=rule_arg(SEED_RULE), default=0)
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="folder for RULE.json (default: the user's data directory, see magenv.registry)",
    )
    p.add_argument(
        "--start-from",
        default=None,
        metavar="RULE",
        help="start from RULE's tuned parameters where this rule shares them (e.g. cf_cerr from cf_constraint)",
    )
    p.add_argument("--no-progress", action="store_true")


def training_trials(scenarios: str, seeds) -> list:
    """The trials of ``--scenarios``: each simulated scenario at every seed, each ``recording:GLOB`` entry's
    recordings once (``magenv.recordings.match_recordings``; a recording tuned on is then no evaluation trial)."""
    from magenv.envs.common import RECORDING_PREFIX
    from magenv.recordings import load_recording, match_recordings
    from magenv.scenarios import make_trial

    trials = []
    for name in (s.strip() for s in scenarios.split(",")):
        if name.startswith(RECORDING_PREFIX):
            trials += [load_recording(p) for p in match_recordings(name[len(RECORDING_PREFIX) :])]
        else:
            trials += [make_trial(name, seed) for seed in seeds]
    return trials


def run(args: argparse.Namespace) -> int:
    from magenv import registry
    from magenv.baselines.tuning import tune_rule

    folder = output_folder(args.out or registry.user_tuned_dir(), "--out")
    path = output_file(folder / f"{args.rule}.json", "--out")
    seeds = args.seeds
    if min(seeds) < TRAIN_SEED_START:
        raise CommandError(f"training seeds must be >= {TRAIN_SEED_START}; lower seeds are held out for evaluation")
    try:
        trials = training_trials(args.scenarios, seeds)
        cls = registry.rule_class(args.rule)
        start = None
        if args.start_from is not None:
            shared = registry.tuned_params(args.start_from)
            start = {k: v for k, v in shared.items() if k in cls.PARAM_BOUNDS}
            if not start:
                raise CommandError(f"{args.start_from} shares no parameter with {args.rule}")
        record = tune_rule(
            args.rule, cls, trials, args.iterations, args.popsize, args.seed, not args.no_progress, start
        )
    except (KeyError, ValueError) as exc:  # TunedParamsError is a ValueError
        raise CommandError(str(exc)) from None
    folder.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=2) + "\n")
    print(
        f"{args.rule}: published {record['published_objective_deg']:.3f}° -> tuned {record['objective_deg']:.3f}° "
        f"on {len(trials)} training trials; params {record['params']} -> {path}"
    )
    return 0
