"""``magenv compare``: every method on the same trials, one RMSE table.

    magenv compare --scenario dynamic_magnet --seeds 0:10 [--methods mimu,imu,fan_lambda,threshold]
                   [--recordings FILE ...] [--every K] [--csv FILE] [--plot FILE] [--trust-pickle]

Trials are ``magenv.scenarios.make_trial(scenario, seed)`` for every scenario
(comma list) and seed, plus each recording (``magenv.recordings.load_recording``;
its trial name goes in the ``scenario`` column). Errors are RMSE in degrees
over each trial's score mask, averaged over the trials of a scenario. The CSV
header is ``magenv.evaluation.CSV_COLUMNS``. ``--plot`` draws total error and
λ over time for the first trial.

A method that cannot run a trial (say a two-link estimator on a one-sensor
trial) does not stop the others: its cell is ``n/a`` (NaN in the CSV), the
reason is printed under the table, and the exit status is 1.
"""

from __future__ import annotations

import argparse
import math
import sys

from magenv.agents.hyperparams import POSITIVE_INT
from magenv.envs import BLEND_ID
from magenv.train.cli import PARTIAL, TRUST_PICKLE_HELP, CommandError, rule_arg
from magenv.train.seeds import seeds_arg

DEFAULT_METHODS = "mimu,imu,fan_lambda,threshold"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--scenario",
        default=None,
        help="scenario name(s), comma list (default dynamic_magnet unless --recordings is given)",
    )
    p.add_argument(
        "--seeds",
        type=seeds_arg,
        default="0:10",
        help="trial seeds: START:STOP, comma list or one (default %(default)s)",
    )
    p.add_argument("--methods", default=DEFAULT_METHODS, help="comma list of methods (default %(default)s)")
    p.add_argument(
        "--agent",
        action="append",
        default=[],
        metavar="RUN_DIR",
        help="add a trained agent from its run folder (repeatable; also as method agent:RUN_DIR)",
    )
    p.add_argument("--recordings", nargs="+", default=[], metavar="FILE", help="real recordings to add")
    p.add_argument(
        "--every",
        type=rule_arg(POSITIVE_INT),
        default=None,
        help="decision interval k (samples) for policies (default: the env's, 8)",
    )
    p.add_argument("--no-hold", action="store_true", help="turn the stationary hold off for MagBlend-v0 policies")
    p.add_argument("--csv", default=None, metavar="FILE", help="write the table as CSV")
    p.add_argument("--plot", default=None, metavar="FILE", help="PNG of error and λ over time, first trial")
    p.add_argument("--trust-pickle", action="store_true", help=TRUST_PICKLE_HELP)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def make_trials(scenarios: str | None, seeds: list[int], recordings: list[str]) -> tuple[list, list[str]]:
    """Trials and their table labels: every scenario (comma list) × seed, then each recording."""
    trials, labels = [], []
    names = [s.strip() for s in (scenarios or "").split(",") if s.strip()]
    if names:
        from magenv.scenarios import make_trial, scenario_names

        known = list(scenario_names())
        bad = [n for n in names if n not in known]
        if bad:
            raise CommandError(f"unknown scenario(s) {', '.join(bad)}; known: {', '.join(known)}")
        for name in names:
            for seed in seeds:
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


def select_methods(names: list[str], trust_pickle: bool = False) -> dict:
    """Method objects by name (registry names, ``RULE_tuned``, ``agent:RUN_DIR``); unknown names list the known
    ones. ``trust_pickle`` lets agents load from SB3 ``.zip`` files (``magenv.agents.load_agent``)."""
    from magenv import registry

    names = [m.strip() for m in names if m.strip()]
    if not names:
        raise CommandError("no methods given")
    known = registry.names()
    bad = [m for m in names if m not in known and not m.startswith(registry.AGENT_PREFIX)]
    if bad:
        raise CommandError(f"unknown method(s) {', '.join(bad)}; known methods: {', '.join(known)}")
    try:
        return {m: registry.make(m, trust_pickle=trust_pickle) for m in names}
    except (ImportError, ValueError) as exc:
        raise CommandError(str(exc)) from None


HEADROOM_NOTE = "headroom: reads truth, an upper bound"


def headroom_names(methods: dict) -> set[str]:
    """Names of the privileged methods (``privileged = True``: they read truth, e.g. ``oracle``)."""
    return {name for name, m in methods.items() if getattr(m, "privileged", False)}


def mark_headroom(rows: list[dict], names: set[str]) -> list[dict]:
    """Flag the rows of privileged methods (``row["headroom"]``): tables list them last, as upper bounds."""
    for r in rows:
        if r["method"] in names:
            r["headroom"] = True
    return rows


def method_label(row: dict) -> str:
    """The method cell of a table row: a privileged method's name carries the headroom note."""
    return f"{row['method']} ({HEADROOM_NOTE})" if row.get("headroom") else row["method"]


def _fmt(x: float) -> str:
    return "–" if math.isnan(x) else f"{x:.2f}"


def table_order(rows: list[dict]) -> list[dict]:
    """Rows by scenario, best total RMSE first, then the headroom rows (privileged methods), n/a rows last."""
    return sorted(rows, key=lambda r: (r["scenario"], "error" in r, bool(r.get("headroom")), r["total_rmse_mean"]))


def failure_notes(rows: list[dict]) -> list[str]:
    """One line per n/a cell: the method, the trials' group and why."""
    return [f"n/a: {r['method']} on {r['scenario']}: {r['error']}" for r in rows if "error" in r]


def run_comparison(
    methods: dict, trials: list, labels: list[str], env_kwargs: dict | None = None, progress: bool = True, console=None
) -> list:
    """Every method on every trial with a progress bar, going on past a method that fails on a trial
    (``magenv.evaluation.evaluate(keep_going=True)``); returns ``magenv.evaluation.Run`` objects."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from magenv import evaluation

    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        disable=not progress,
        transient=True,
    ) as bar:
        task = bar.add_task("running methods", total=len(trials) * len(methods))

        def tick(method, trial):
            bar.update(task, advance=1, description=f"{method} on {trial.name}")

        return evaluation.evaluate(methods, trials, env_kwargs, labels, tick, keep_going=True)


def print_table(rows: list[dict], console=None, title: str = "orientation RMSE (°), mean over trials") -> None:
    """The comparison rows as a table, best total RMSE first within each scenario."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console(width=None if sys.stdout.isatty() else 120)  # no squeezed columns in logs
    table = Table(title=title)
    for col, justify in (
        ("method", "left"),
        ("scenario", "left"),
        ("n", "right"),
        ("total", "right"),
        ("± std", "right"),
        ("heading", "right"),
        ("inclination", "right"),
    ):
        table.add_column(col, justify=justify, no_wrap=True)
    for r in table_order(rows):
        cells = (
            ["n/a"] * 4
            if "error" in r
            else [
                _fmt(r[c]) for c in ("total_rmse_mean", "total_rmse_std", "heading_rmse_mean", "inclination_rmse_mean")
            ]
        )
        table.add_row(method_label(r), r["scenario"], str(r["n"]), *cells)
    console.print(table)


def finish(rows: list[dict], title: str, csv_path: str | None) -> int:
    """Print the table and the reasons for its n/a cells, write the CSV; the exit status (``PARTIAL`` if a
    cell is n/a)."""
    from magenv import evaluation

    print_table(rows, title=title)
    notes = failure_notes(rows)
    for line in notes:
        print(line)
    if csv_path:
        print(f"wrote {evaluation.write_csv(rows, csv_path)}")
    return PARTIAL if notes else 0


def run(args: argparse.Namespace) -> int:
    from magenv import evaluation, registry

    methods = select_methods(
        args.methods.split(",") + [registry.AGENT_PREFIX + a for a in args.agent], args.trust_pickle
    )
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
    rows = mark_headroom(evaluation.summarize(runs), headroom_names(methods))
    status = finish(rows, "orientation RMSE (°), mean over trials", args.csv)
    if args.plot:
        first = [r for r in runs if r.trial is trials[0]]
        print(f"wrote {evaluation.plot_runs(first, args.plot)}")
    return status
