"""``magenv compare``: every method on the same trials, one RMSE table.

    magenv compare --scenario dynamic_magnet --seeds 0:10 [--methods mimu,imu,fan_lambda,threshold]
                   [--recordings FILE ...] [--every K] [--csv FILE] [--plot FILE]

Trials are ``magenv.scenarios.make_trial(scenario, seed)`` for every scenario
(comma list) and seed, plus each recording (``magenv.recordings.load_recording``;
its trial name goes in the ``scenario`` column). Errors are RMSE in degrees
over each trial's score mask, averaged over the trials of a scenario. The CSV
header is ``magenv.evaluation.CSV_COLUMNS``. ``--plot`` draws total error and
λ over time for the first trial.
"""

from __future__ import annotations

import argparse
import math
import sys

from magenv.envs import BLEND_ID
from magenv.train.cli import CommandError

DEFAULT_METHODS = "mimu,imu,fan_lambda,threshold"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default=None,
                   help="scenario name(s), comma list (default dynamic_magnet unless --recordings is given)")
    p.add_argument("--seeds", default="0:10", help="trial seeds: START:STOP, comma list or one (default %(default)s)")
    p.add_argument("--methods", default=DEFAULT_METHODS, help="comma list of methods (default %(default)s)")
    p.add_argument("--agent", action="append", default=[], metavar="RUN_DIR",
                   help="add a trained agent from its run folder (repeatable; also as method agent:RUN_DIR)")
    p.add_argument("--recordings", nargs="+", default=[], metavar="FILE", help="real recordings to add")
    p.add_argument("--every", type=int, default=None,
                   help="decision interval k (samples) for policies (default: the env's, 8)")
    p.add_argument("--no-hold", action="store_true", help="turn the stationary hold off for MagBlend-v0 policies")
    p.add_argument("--csv", default=None, metavar="FILE", help="write the table as CSV")
    p.add_argument("--plot", default=None, metavar="FILE", help="PNG of error and λ over time, first trial")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def make_trials(scenarios: str | None, seeds: str, recordings: list[str]) -> tuple[list, list[str]]:
    """Trials and their table labels: every scenario (comma list) × seed, then each recording."""
    from magenv.train.seeds import parse_seeds

    trials, labels = [], []
    names = [s.strip() for s in (scenarios or "").split(",") if s.strip()]
    if names:
        try:
            seed_list = parse_seeds(seeds)
        except ValueError as exc:
            raise CommandError(str(exc)) from None
        from magenv.scenarios import make_trial, scenario_names

        known = list(scenario_names())
        bad = [n for n in names if n not in known]
        if bad:
            raise CommandError(f"unknown scenario(s) {', '.join(bad)}; known: {', '.join(known)}")
        for name in names:
            for seed in seed_list:
                trials.append(make_trial(name, seed))
                labels.append(name)
    for path in recordings:
        from magenv.recordings import load_recording

        try:
            trial = load_recording(path)
        except (OSError, ValueError) as exc:
            raise CommandError(f"cannot load recording {path}: {exc}") from None
        trials.append(trial)
        labels.append(trial.name)
    if not trials:
        raise CommandError("no trials: give --scenario and/or --recordings")
    return trials, labels


def select_methods(names: list[str]) -> dict:
    """Method objects by name (registry names, ``RULE_tuned``, ``agent:RUN_DIR``); unknown names list the known ones."""
    from magenv import registry

    names = [m.strip() for m in names if m.strip()]
    if not names:
        raise CommandError("no methods given")
    known = registry.names()
    bad = [m for m in names if m not in known and not m.startswith(registry.AGENT_PREFIX)]
    if bad:
        raise CommandError(f"unknown method(s) {', '.join(bad)}; known methods: {', '.join(known)}")
    try:
        return {m: registry.make(m) for m in names}
    except (ImportError, ValueError) as exc:
        raise CommandError(str(exc)) from None


def _fmt(x: float) -> str:
    return "–" if math.isnan(x) else f"{x:.2f}"


def run_comparison(methods: dict, trials: list, labels: list[str], env_kwargs: dict | None = None,
                   progress: bool = True, console=None) -> list:
    """Every method on every trial with a progress bar; returns ``magenv.evaluation.Run`` objects."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from magenv import evaluation

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, disable=not progress, transient=True) as bar:
        task = bar.add_task("running methods", total=len(trials) * len(methods))

        def tick(method, trial):
            bar.update(task, advance=1, description=f"{method} on {trial.name}")

        return evaluation.evaluate(methods, trials, env_kwargs, labels, tick)


def print_table(rows: list[dict], console=None, title: str = "orientation RMSE (°), mean over trials") -> None:
    """The comparison rows as a table, best total RMSE first within each scenario."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console(width=None if sys.stdout.isatty() else 120)  # no squeezed columns in logs
    table = Table(title=title)
    for col, justify in (("method", "left"), ("scenario", "left"), ("n", "right"), ("total", "right"),
                         ("± std", "right"), ("heading", "right"), ("inclination", "right")):
        table.add_column(col, justify=justify, no_wrap=True)
    for r in sorted(rows, key=lambda r: (r["scenario"], r["total_rmse_mean"])):
        table.add_row(r["method"], r["scenario"], str(r["n"]), _fmt(r["total_rmse_mean"]),
                      _fmt(r["total_rmse_std"]), _fmt(r["heading_rmse_mean"]), _fmt(r["inclination_rmse_mean"]))
    console.print(table)


def run(args: argparse.Namespace) -> int:
    from magenv import registry
    from magenv import evaluation

    if args.every is not None and args.every < 1:
        raise CommandError(f"--every must be a positive number of samples, got {args.every}")
    methods = select_methods(args.methods.split(",") + [registry.AGENT_PREFIX + a for a in args.agent])
    env_kwargs = {}
    if args.every is not None:
        env_kwargs["decision_every"] = args.every
    if args.no_hold:  # an option of the blend env only
        for method in methods.values():
            if getattr(method, "env_id", None) == BLEND_ID:
                method.env_kwargs = {**method.env_kwargs, "stationary_hold": False}
    scenarios = args.scenario if args.scenario is not None else ("" if args.recordings else "dynamic_magnet")
    trials, labels = make_trials(scenarios, args.seeds, args.recordings)
    runs = run_comparison(methods, trials, labels, env_kwargs, progress=not args.no_progress)
    rows = evaluation.summarize(runs)
    print_table(rows)
    if args.csv:
        print(f"wrote {evaluation.write_csv(rows, args.csv)}")
    if args.plot:
        first = [r for r in runs if r.trial is trials[0]]
        print(f"wrote {evaluation.plot_runs(first, args.plot)}")
    return 0
