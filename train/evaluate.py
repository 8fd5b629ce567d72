"""``magenv evaluate``: score a trained agent on scenarios or recordings.

    magenv evaluate runs/NAME [--scenario dynamic_magnet,dynamic_clean] [--seeds 0:10]
                    [--recordings FILE ...] [--which best|last] [--csv FILE] [--video FILE.mp4] [--trust-pickle]

Seeds below 10 000 are never used for training (``magenv train`` draws its
trials from ``random`` and above), so the default seeds are held out. The
first line says which model file was loaded. Exit status 1 if the agent
could not run some trial (its cell is n/a, the reason printed). ``--video``
records the agent on the first trial (``render_mode="rgb_array"``, one frame
per step; needs ``magenv[video]``).
"""

from __future__ import annotations

import argparse

from magenv.train.cli import TRUST_PICKLE_HELP, CommandError, output_file
from magenv.train.seeds import seeds_arg


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", help="run folder written by `magenv train`")
    p.add_argument(
        "--scenario", default=None, help="comma list (default dynamic_magnet,dynamic_clean unless --recordings)"
    )
    p.add_argument("--seeds", type=seeds_arg, default="0:10", help="held-out trial seeds (default %(default)s)")
    p.add_argument("--recordings", nargs="+", default=[], metavar="FILE")
    p.add_argument("--which", choices=("best", "last"), default="best", help="which saved model (default %(default)s)")
    p.add_argument("--csv", default=None, metavar="FILE")
    p.add_argument("--video", default=None, metavar="FILE.mp4", help="record the agent on the first trial (MP4)")
    p.add_argument("--trust-pickle", action="store_true", help=TRUST_PICKLE_HELP)
    p.add_argument("--no-progress", action="store_true")


def describe_loaded(agent, asked: str) -> str:
    """One line: which model file an agent came from (and why, if not the one asked for)."""
    note = f" (the run has no {asked} model yet)" if agent.which != asked else ""
    return f"{agent.name}: {agent.which} model from {agent.source}{note}"


def run(args: argparse.Namespace) -> int:
    from magenv import evaluation
    from magenv.agents.loading import RunError, load_agent
    from magenv.train.compare import finish, make_trials, run_comparison

    args.csv = output_file(args.csv, "--csv")
    args.video = output_file(args.video, "--video", (".mp4",))
    try:
        agent = load_agent(args.run_dir, which=args.which, trust_pickle=args.trust_pickle)
    except RunError as exc:
        raise CommandError(str(exc)) from None
    print(describe_loaded(agent, args.which))
    scenarios = (
        args.scenario if args.scenario is not None else ("" if args.recordings else "dynamic_magnet,dynamic_clean")
    )
    trials, labels = make_trials(scenarios, args.seeds, args.recordings)
    rows = evaluation.summarize(run_comparison({agent.name: agent}, trials, labels, progress=not args.no_progress))
    status = finish(rows, f"{agent.name} ({agent.which} model): orientation RMSE (°)", args.csv)
    if args.video is not None:
        path = evaluation.PolicyRunner().record(agent, trials[0], args.video)
        print(f"wrote {path} ({trials[0].name})")
    return status
