"""``magenv compare``: every method on the same trials, one RMSE table.

    magenv compare --scenario dynamic_magnet --seeds 0:10 [--methods mimu,imu,fan_lambda,threshold]
                   [--recordings FILE ...] [--every K] [--csv FILE] [--plot FILE] [--trust-pickle]
                   [--workers N] [--address ADDR]

Trials are ``magenv.scenarios.make_trial(scenario, seed)`` for every scenario
(comma list) and seed, plus each recording (``magenv.recordings.load_recording``;
its trial name goes in the ``scenario`` column). Errors are RMSE in degrees
over each trial's score mask, averaged over the trials of a scenario. The CSV
header is ``magenv.evaluation.CSV_COLUMNS``. ``--plot`` draws total error and
λ over time for the first trial.

With two or more recordings, every method also gets a row over all of them (``all recordings``): the
paired ratio over the recordings, each one a unit, and the worst recording's ratio (the ``worst`` column,
per row the largest per-trial ratio to the reference).

A method that cannot run a trial (say a two-link estimator on a one-sensor
trial) does not stop the others: its cell is ``n/a`` (NaN in the CSV), the
reason is printed under the table, and the exit status is 1.

``--workers N`` (or ``--address ADDR``) spreads the (method × trial) cells
over N Ray workers (``magenv.scale.evaluate``; the extra ``magenv[scale]``):
each worker rebuilds the methods from their names and the trials from
(scenario, seed) or the recording's path, so the table is the serial one,
number for number.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import sys
from pathlib import Path

from magenv.agents.hyperparams import POSITIVE_INT
from magenv.envs import BLEND_ID
from magenv.train.cli import IMAGE_SUFFIXES, PARTIAL, TRUST_PICKLE_HELP, CommandError, output_file, rule_arg
from magenv.train.seeds import seeds_arg

DEFAULT_METHODS = "mimu,imu,fan_lambda,threshold"
DEFAULT_REFERENCE = "fan_lambda_tuned"  # the paired column's reference when it is among the methods
ALL_RECORDINGS = "all recordings"  # the group of every recording's runs (two or more recordings)


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
    p.add_argument(
        "--reference",
        default=DEFAULT_REFERENCE,
        help="method every other is paired with, trial by trial (ratio, 95 %% interval, win rate; default %(default)s)",
    )
    p.add_argument(
        "--workers",
        type=rule_arg(POSITIVE_INT),
        default=None,
        help="spread the (method × trial) cells over N Ray workers (magenv[scale]; default: one process, no Ray)",
    )
    p.add_argument(
        "--address",
        default=None,
        help="run the workers on the Ray cluster at ADDR (auto, HOST:PORT); default with --workers: a local Ray",
    )


def plan_trials(scenarios: str | None, seeds: list[int], recordings: list[str]) -> tuple[list, list[str], dict]:
    """The trials by name (``magenv.scale.TrialSpec``: every scenario (comma list) × seed, then each recording,
    its path made absolute), their table labels, and the recordings loaded on the way (index → Trial; a
    recording is loaded here to check it and to label it)."""
    from magenv.scale import TrialSpec

    specs, labels, loaded = [], [], {}
    names = [s.strip() for s in (scenarios or "").split(",") if s.strip()]
    if names:
        from magenv.scenarios import scenario_names

        known = list(scenario_names())
        bad = [n for n in names if n not in known]
        if bad:
            raise CommandError(f"unknown scenario(s) {', '.join(bad)}; known: {', '.join(known)}")
        for name in names:
            for seed in seeds:
                specs.append(TrialSpec(scenario=name, seed=seed))
                labels.append(name)
    for path in recordings:
        from magenv.recordings import load_recording

        try:
            trial = load_recording(path)
        except (OSError, ValueError) as exc:
            raise CommandError(f"cannot load recording {path}: {exc}") from None
        loaded[len(specs)] = trial
        specs.append(TrialSpec(recording=str(Path(path).resolve())))
        labels.append(trial.name)
    if not specs:
        raise CommandError("no trials: give --scenario and/or --recordings")
    return specs, labels, loaded


def make_trials(scenarios: str | None, seeds: list[int], recordings: list[str]) -> tuple[list, list[str]]:
    """Trials and their table labels: every scenario (comma list) × seed, then each recording."""
    specs, labels, loaded = plan_trials(scenarios, seeds, recordings)
    return [loaded[i] if i in loaded else spec.make() for i, spec in enumerate(specs)], labels


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


HEADROOM_NOTE = "headroom"
HEADROOM_FOOTNOTE = "headroom: a privileged method that reads truth, an upper bound, never a baseline"


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


def score_cells(row: dict) -> list[str]:
    """A table row's total RMSE, ± std, heading and inclination cells (°, 2 decimals; "–" for NaN), "n/a" in
    each where the method failed."""
    if "error" in row:
        return ["n/a"] * 4
    cols = ("total_rmse_mean", "total_rmse_std", "heading_rmse_mean", "inclination_rmse_mean")
    return ["–" if math.isnan(row[c]) else f"{row[c]:.2f}" for c in cols]


def table_order(rows: list[dict]) -> list[dict]:
    """Rows by scenario, best total RMSE first, then the headroom rows (privileged methods), n/a rows last."""
    return sorted(rows, key=lambda r: (r["scenario"], "error" in r, bool(r.get("headroom")), r["total_rmse_mean"]))


def failure_notes(rows: list[dict]) -> list[str]:
    """One line per n/a cell: the method, the trials' group and why."""
    return [f"n/a: {r['method']} on {r['scenario']}: {r['error']}" for r in rows if "error" in r]


def divergence_notes(rows: list[dict]) -> list[str]:
    """One line per row whose method diverged on some trial (scored 180° there): the method, the group, how."""
    return [f"{r['method']} on {r['scenario']}: {r['diverged']}" for r in rows if "diverged" in r]


@contextlib.contextmanager
def _progress_bar(total: int, progress: bool = True, console=None):
    """A transient progress bar over ``total`` runs; yields ``advance(n, description)``."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        disable=not progress,
        transient=True,
    ) as bar:
        task = bar.add_task("running methods", total=total)
        yield lambda n, description: bar.update(task, advance=n, description=description)


def run_comparison(
    methods: dict, trials: list, labels: list[str], env_kwargs: dict | None = None, progress: bool = True, console=None
) -> list:
    """Every method on every trial with a progress bar, going on past a method that fails on a trial
    (``magenv.evaluation.evaluate(keep_going=True)``); returns ``magenv.evaluation.Run`` objects."""
    from magenv import evaluation

    with _progress_bar(len(trials) * len(methods), progress, console) as advance:
        return evaluation.evaluate(
            methods, trials, env_kwargs, labels, lambda m, t: advance(1, f"{m} on {t.name}"), True
        )


def run_distributed(
    names: list[str],
    specs: list,
    labels: list[str],
    env_kwargs: dict | None,
    overrides: dict | None,
    workers: int | None,
    address: str | None,
    trust_pickle: bool = False,
    progress: bool = True,
) -> list:
    """``run_comparison`` over Ray workers (``magenv.scale.evaluate``, keep_going): the same Runs, the first
    trial's with their arrays (for ``--plot``), the others with scores only."""
    from magenv import registry, scale

    builds = {
        n: registry.AGENT_PREFIX + str(Path(n[len(registry.AGENT_PREFIX) :]).resolve())
        if n.startswith(registry.AGENT_PREFIX)
        else n
        for n in names
    }
    try:
        started = scale.start(address, workers, "magenv compare --workers/--address")
    except scale.RayMissing as exc:
        raise CommandError(str(exc)) from None
    try:
        with _progress_bar(len(specs) * len(names), progress) as advance:
            return scale.evaluate(
                builds,
                specs,
                labels,
                env_kwargs,
                overrides,
                workers,
                keep_going=True,
                trust_pickle=trust_pickle,
                progress=lambda runs: advance(len(runs), f"{runs[-1].method} on {runs[-1].label}"),
            )
    finally:
        scale.stop(started)


def paired_cells(row: dict) -> list[str]:
    """The paired columns of a row (``evaluation.add_paired``): "ratio [low, high]", the win rate and the
    interquartile-mean ratio "iqm [low, high]"; blank without."""
    p = row.get("paired")
    if not p:
        return ["", "", "", ""]
    return [p.ratio_text(2) if p.n > 1 else f"{p.ratio:.2f}", f"{p.win_rate:.2f}", f"{p.worst:.2f}",
            p.iqm_text(2) if p.n > 1 else ""]  # fmt: skip


def print_table(rows: list[dict], console=None, title: str = "orientation RMSE (°), mean over trials") -> None:
    """The comparison rows as a table, best total RMSE first within each scenario."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console(width=None if sys.stdout.isatty() else 160)  # no squeezed columns in logs
    table = Table(title=title)
    for col in ("method", "scenario"):
        table.add_column(col, justify="left", no_wrap=True)
    for col in ("n", "total", "± std", "heading", "inclination"):
        table.add_column(col, justify="right", no_wrap=True)
    paired = any("paired" in r for r in rows)
    if paired:
        table.add_column("÷ ref [95 % CI]", justify="right", no_wrap=True)
        table.add_column("win", justify="right", no_wrap=True)
        table.add_column("worst", justify="right", no_wrap=True)
        table.add_column("IQM ÷ ref", justify="right", no_wrap=True)
    for r in table_order(rows):
        cells = score_cells(r)
        if paired:
            cells += paired_cells(r)
        table.add_row(method_label(r), r["scenario"], str(r["n"]), *cells)
    console.print(table)


def finish(rows: list[dict], title: str, csv_path: str | Path | None) -> int:
    """Print the table, the reasons for its n/a cells and the divergences, write the CSV; the exit status
    (``PARTIAL`` if a cell is n/a)."""
    from magenv import evaluation

    print_table(rows, title=title)
    if any(r.get("headroom") for r in rows):
        print(HEADROOM_FOOTNOTE)
    notes = failure_notes(rows)
    for line in notes + divergence_notes(rows):
        print(line)
    if csv_path:
        print(f"wrote {evaluation.write_csv(rows, csv_path)}")
    return PARTIAL if notes else 0


def run(args: argparse.Namespace) -> int:
    from magenv import evaluation, registry, scale

    args.csv = output_file(args.csv, "--csv")
    args.plot = output_file(args.plot, "--plot", IMAGE_SUFFIXES)
    methods = select_methods(
        args.methods.split(",") + [registry.AGENT_PREFIX + a for a in args.agent], args.trust_pickle
    )
    if args.reference not in methods and args.reference != DEFAULT_REFERENCE:
        raise CommandError(f"--reference {args.reference!r} is not among the methods: {', '.join(methods)}")
    env_kwargs = {}
    if args.every is not None:
        env_kwargs["decision_every"] = args.every
    overrides = {BLEND_ID: {"stationary_hold": False}} if args.no_hold else None  # a blend env option only
    scale.override_env_kwargs(methods, overrides)
    scenarios = args.scenario if args.scenario is not None else ("" if args.recordings else "dynamic_magnet")
    if args.workers or args.address:
        specs, labels, _ = plan_trials(scenarios, args.seeds, args.recordings)
        runs = run_distributed(
            list(methods),
            specs,
            labels,
            env_kwargs,
            overrides,
            args.workers,
            args.address,
            args.trust_pickle,
            not args.no_progress,
        )
    else:
        trials, labels = make_trials(scenarios, args.seeds, args.recordings)
        runs = run_comparison(methods, trials, labels, env_kwargs, progress=not args.no_progress)
    recorded = {Path(p).stem for p in args.recordings}
    if len(recorded) > 1:  # every recording's runs once more, as one group
        runs = [*runs, *(dataclasses.replace(r, label=ALL_RECORDINGS) for r in runs if r.label in recorded)]
    rows = mark_headroom(evaluation.summarize(runs), headroom_names(methods))
    rows = evaluation.add_paired(rows, runs, args.reference)
    title = "orientation RMSE (°), mean over trials"
    if any("paired" in row for row in rows):  # the reference ran beside another method
        title += f"; ÷ {args.reference}: paired ratio"
    status = finish(rows, title, args.csv)
    if args.plot:  # runs are trial by trial, every method once per trial
        print(f"wrote {evaluation.plot_runs(runs[: len(methods)], args.plot)}")
    return status
