"""``magenv evaluate``: score a trained agent on scenarios or recordings.

    magenv evaluate runs/NAME [--scenario dynamic_magnet,dynamic_clean] [--seeds 0:10]
                    [--recordings FILE ...] [--which best|last] [--csv FILE]

Seeds below 10 000 are never used for training (``magenv train`` draws its
trials from ``random`` and above), so the default seeds are held out.
"""

from __future__ import annotations

import argparse

from magenv.train.cli import CommandError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", help="run folder written by `magenv train`")
    p.add_argument("--scenario", default=None, help="comma list (default dynamic_magnet,dynamic_clean unless --recordings)")
    p.add_argument("--seeds", default="0:10", help="held-out trial seeds (default %(default)s)")
    p.add_argument("--recordings", nargs="+", default=[], metavar="FILE")
    p.add_argument("--which", choices=("best", "last"), default="best", help="which saved model (default %(default)s)")
    p.add_argument("--csv", default=None, metavar="FILE")
    p.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from magenv.agents.loading import RunError, load_agent
    from magenv import evaluation
    from magenv.train.compare import make_trials, print_table, run_comparison

    try:
        agent = load_agent(args.run_dir, which=args.which)
    except RunError as exc:
        raise CommandError(str(exc)) from None
    scenarios = args.scenario if args.scenario is not None else ("" if args.recordings else "dynamic_magnet,dynamic_clean")
    trials, labels = make_trials(scenarios, args.seeds, args.recordings)
    rows = evaluation.summarize(run_comparison({agent.name: agent}, trials, labels, progress=not args.no_progress))
    print_table(rows, title=f"{agent.name} ({args.which} model): orientation RMSE (°)")
    if args.csv:
        print(f"wrote {evaluation.write_csv(rows, args.csv)}")
    return 0
