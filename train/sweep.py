"""``magenv sweep``: many ``magenv train`` runs on Ray Tune, then one table per configuration against a tuned rule.

    magenv sweep CONFIG.yaml [--out runs/sweep] [--workers N] [--address ADDR] [--seeds 0:5] [--dry-run]

The sweep file (``magenv.train.sweep_config``) crosses env ids × algorithms
× searched hyperparameter configurations × training seeds; each run is one
Ray Tune trial of one CPU, at most ``--workers`` at a time (default: every
CPU of the local machine, or of the cluster at ``--address``). A run trains
with ``magenv.agents.training.train`` into a normal run folder, then scores
its best model and the reference rule on the same held-out trials. OUT holds::

    sweep.json           the runs (written first; a rerun may add runs, never change one)
    configs/NAME.yaml    each run's config section (its magenv train --config)
    runs/NAME/           each run's magenv train run folder (magenv evaluate, compare --agent take it)
    results/NAME.json    each finished run: per-trial RMSE of the agent and the reference, wall and CPU timings
    logs/NAME.log        what each run printed
    summary.csv          the table (SUMMARY_COLUMNS)
    tune/                Ray Tune's own files (never read back by magenv)

Resuming: run the same command again. A finished run (its results file) is
not run again; an interrupted one resumes from its run folder's last
checkpoint (``train``'s resume; at most ``eval_every`` steps are lost); a
lost Ray worker's run is retried the same way, twice. The table pairs the
seeds of each configuration: the mean over seeds of each seed's mean RMSE,
and ``magenv.stats.paired_ratio`` of the per-seed means of the agent and
of the reference (ratio < 1: the agent is better). Exit status 1 if some run
failed (the reasons are printed), 130 if interrupted.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import functools
import json
import math
import sys
import time
from pathlib import Path

import yaml

from magenv.agents.hyperparams import POSITIVE_INT
from magenv.train.cli import PARTIAL, CommandError, output_folder, rule_arg
from magenv.train.seeds import seeds_arg
from magenv.train.sweep_config import DAGGER

SUMMARY_COLUMNS = (
    "env",
    "algo",
    "config",
    "params",
    "seeds",
    "agent_rmse_mean",
    "agent_rmse_std",
    "reference",
    "reference_rmse_mean",
    "ratio",
    "ratio_low",
    "ratio_high",
    "win_rate",
    "failed",
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=Path, help="sweep file: rl-zoo3 sections plus a search: section")
    p.add_argument("--out", type=Path, default=Path("runs/sweep"), help="sweep folder (default %(default)s)")
    p.add_argument(
        "--workers",
        type=rule_arg(POSITIVE_INT),
        default=None,
        help="runs at a time, one CPU each (default: every CPU of the local machine or the cluster)",
    )
    p.add_argument("--address", default=None, help="an existing Ray cluster (e.g. auto, or HOST:6379); default local")
    p.add_argument(
        "--seeds", type=seeds_arg, default=None, help="training seeds, replacing the file's search.seeds (e.g. 0:2)"
    )
    p.add_argument("--dry-run", action="store_true", help="list the runs and stop (Ray not needed)")


# ----------------------------------------------------------------- one run (on a Ray worker)


def write_atomic(path: Path, text: str) -> None:
    """``text`` into ``path`` (its folder made), written whole beside it and then renamed: a kill leaves no half
    file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


def finished_record(out: Path, name: str, spec: dict) -> dict | None:
    """The results record of run ``name`` in sweep folder ``out`` if it finished with these settings, else None."""
    path = out / "results" / f"{name}.json"
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and record.get("run") == spec else None


def _train_dagger(spec: dict, run_dir: Path) -> None:
    """DAgger run ``spec`` into ``run_dir``, or its continuation where the folder holds it."""
    from magenv import registry
    from magenv.agents import dagger

    config = dict(spec["section"])
    teacher = registry.make(config.pop("teacher"))
    resume = dagger.is_run(run_dir)
    dagger.train(
        run_dir,
        teacher,
        {"iterations": config["iterations"]} if resume else config,
        env_id=spec["env_id"],
        resume=resume,
    )


def _dagger_progress(run_dir: Path) -> dict | None:
    """A DAgger run's progress as ``train``'s: ``timesteps`` = decisions labelled so far (its iterations.csv
    ``samples``), ``best_score`` = its best validation score (its mean ratio to the rule, not an RMSE); None before
    its first iteration."""
    path = run_dir / "iterations.csv"
    if not path.is_file():
        return None
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return None
    return {"timesteps": int(rows[-1]["samples"]), "best_score": float(rows[-1]["best"])}


def run_trial(name: str, out: str, runs: dict[str, dict]) -> dict:
    """Train run ``name`` of the sweep in ``out`` (``runs``: name → ``SweepRun.as_dict()``) or resume it, score
    its best model and the reference on the report trials, write ``results/NAME.json``; returns that record.
    A run whose results file holds the same run is not run again."""
    from magenv import evaluation, registry
    from magenv.agents import load_agent
    from magenv.agents.training import progress, train
    from magenv.scenarios import make_trial

    spec, out_dir = runs[name], Path(out)
    done = finished_record(out_dir, name, spec)
    if done is not None:
        return done
    run_dir, config = out_dir / "runs" / name, out_dir / "configs" / f"{name}.yaml"
    write_atomic(config, yaml.safe_dump({spec["env_id"]: spec["section"]}, sort_keys=False))
    dagger_run = spec["algo"] == DAGGER
    before = _dagger_progress(run_dir) if dagger_run else progress(run_dir, spec["algo"])
    start = before["timesteps"] if before is not None else 0
    (out_dir / "logs").mkdir(parents=True, exist_ok=True)
    t0, c0 = time.perf_counter(), time.process_time()
    with open(out_dir / "logs" / f"{name}.log", "a") as log, contextlib.redirect_stdout(log):
        if dagger_run:
            _train_dagger(spec, run_dir)
        else:
            train(
                spec["env_id"],
                spec["algo"],
                spec["steps"],
                run_dir,
                config=str(config),
                seed=spec["seed"],
                eval_every=spec["eval_every"],
                eval_scenarios=tuple(spec["eval_scenarios"]),
                eval_seeds=tuple(spec["eval_seeds"]),
                progress_bar=False,
                make_method=registry.make,
            )
    t1, c1 = time.perf_counter(), time.process_time()
    trials = [make_trial(s, seed) for s in spec["report_scenarios"] for seed in spec["report_seeds"]]
    reference = spec["reference"]
    runs_ = evaluation.evaluate({"agent": load_agent(run_dir), reference: registry.make(reference)}, trials)
    scores = {m: [r.scored.total for r in runs_ if r.method == m] for m in ("agent", reference)}
    trained = _dagger_progress(run_dir) if dagger_run else progress(run_dir, spec["algo"])
    if trained is None:
        raise CommandError(f"{run_dir}: training left no checkpoint")
    record = {
        "name": name,
        "run": spec,
        "run_dir": str(run_dir),
        "trials": [t.name for t in trials],
        "agent": scores["agent"],
        "reference": scores[reference],
        "agent_rmse": sum(scores["agent"]) / len(trials),
        "reference_rmse": sum(scores[reference]) / len(trials),
        "validation_rmse": trained["best_score"],
        "start_timesteps": start,
        "timesteps": trained["timesteps"],
        "train_s": t1 - t0,
        "eval_s": time.perf_counter() - t1,
        "train_cpu_s": c1 - c0,  # this process's CPU seconds: what a free core would take
        "eval_cpu_s": time.process_time() - c1,
    }
    write_atomic(out_dir / "results" / f"{name}.json", json.dumps(record, indent=1))
    return record


# ----------------------------------------------------------------- the table


def summary_rows(records: list[dict], failed: dict[str, str] | None = None, seed: int = 0) -> list[dict]:
    """One row per (env, algo, configuration) over its finished seeds (``SUMMARY_COLUMNS``): mean and sample
    std over seeds of the agent's per-seed mean RMSE, the reference's mean, and the paired ratio of the
    per-seed means (``magenv.stats.paired_ratio``, bootstrap ``seed``); ``failed`` (name → reason) counts the
    runs of each configuration that did not finish."""
    import numpy as np

    from magenv import stats

    failed = failed or {}
    groups: dict[tuple, list[dict]] = {}
    for r in records:
        spec = r["run"]
        groups.setdefault((spec["env_id"], spec["algo"], spec["config"]), []).append(r)
    failed_by: dict[tuple, int] = {}
    for spec in failed.values():
        if isinstance(spec, dict):
            key = (spec["env_id"], spec["algo"], spec["config"])
            failed_by[key] = failed_by.get(key, 0) + 1
    rows = []
    for key in sorted(set(groups) | set(failed_by), key=lambda k: (k[0], k[1], k[2])):
        group = sorted(groups.get(key, []), key=lambda r: r["run"]["seed"])
        row = {"env": key[0], "algo": key[1], "config": key[2], "failed": failed_by.get(key, 0)}
        if not group:
            rows.append({**row, "params": "", "seeds": 0, "reference": ""})
            continue
        agent = np.array([r["agent_rmse"] for r in group])
        ref = np.array([r["reference_rmse"] for r in group])
        paired = stats.paired_ratio(agent, ref, seed=seed)
        rows.append(
            {
                **row,
                "params": json.dumps(group[0]["run"]["params"], separators=(",", ":")),
                "seeds": len(group),
                "agent_rmse_mean": float(agent.mean()),
                "agent_rmse_std": float(agent.std(ddof=1)) if len(agent) > 1 else float("nan"),
                "reference": group[0]["run"]["reference"],
                "reference_rmse_mean": float(ref.mean()),
                "ratio": paired.ratio,
                "ratio_low": paired.low,
                "ratio_high": paired.high,
                "win_rate": paired.win_rate,
            }
        )
    return rows


def write_summary(rows: list[dict], path: Path) -> Path:
    """``rows`` as CSV with the header ``SUMMARY_COLUMNS`` (floats to 4 decimals, ``nan`` where none finished)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(SUMMARY_COLUMNS)
        for row in rows:
            cells = [row.get(c, float("nan")) for c in SUMMARY_COLUMNS]
            w.writerow([f"{c:.4f}" if isinstance(c, float) else c for c in cells])
    return path


def print_summary(rows: list[dict]) -> None:
    from rich.console import Console
    from rich.table import Table

    fmt = lambda x, digits=2: "–" if isinstance(x, float) and math.isnan(x) else f"{x:.{digits}f}"
    fmt3 = lambda x: fmt(x, 3)
    table = Table(title="sweep: total RMSE (°) on the report trials, per configuration over training seeds")
    for col in ("env", "algo", "config", "params", "seeds", "agent ± std", "reference", "ratio [95 % CI]", "win"):
        table.add_column(col, justify="right" if col in ("config", "seeds", "win") else "left")
    for r in rows:
        if not r["seeds"]:
            table.add_row(r["env"], r["algo"], str(r["config"]), "", "0", "n/a", "", "", "")
            continue
        table.add_row(
            r["env"],
            r["algo"],
            str(r["config"]),
            r["params"],
            str(r["seeds"]) + (f" ({r['failed']} failed)" if r["failed"] else ""),
            f"{fmt(r['agent_rmse_mean'])} ± {fmt(r['agent_rmse_std'])}",
            f"{r['reference']} {fmt(r['reference_rmse_mean'])}",
            f"{fmt3(r['ratio'])} [{fmt3(r['ratio_low'])}, {fmt3(r['ratio_high'])}]",
            f"{r['win_rate']:.2f}",
        )
    Console(width=None if sys.stdout.isatty() else 160).print(table)


# ----------------------------------------------------------------- the command


def _stored_runs(out: Path, runs: dict[str, dict]) -> None:
    """Write ``out/sweep.json``; a run already stored there under the same name with other settings is a
    CommandError (its folder would mix two runs)."""
    path = out / "sweep.json"
    if path.is_file():
        stored = json.loads(path.read_text())["runs"]
        changed = [n for n in stored if n in runs and stored[n] != runs[n]]
        if changed:
            raise CommandError(
                f"{out} holds a sweep whose run(s) {', '.join(changed[:3])}{' …' if len(changed) > 3 else ''} "
                "had other settings; use another --out for a new sweep"
            )
        runs = {**stored, **runs}
    write_atomic(path, json.dumps({"runs": runs}, indent=1))


def run(args: argparse.Namespace) -> int:
    from magenv import scale
    from magenv.agents.hyperparams import ConfigError
    from magenv.train.sweep_config import load_sweep

    if not args.dry_run:
        output_folder(args.out, "--out")
    try:
        sweep = load_sweep(args.config, args.seeds)
    except ConfigError as exc:
        raise CommandError(str(exc)) from None
    runs = {r.name: json.loads(json.dumps(r.as_dict())) for r in sweep}
    configs = len({(r.env_id, r.algo, r.config) for r in sweep})
    print(f"{len(runs)} runs: {configs} configuration(s) × {len({r.seed for r in sweep})} seed(s) -> {args.out}")
    if args.dry_run:
        for r in sweep:
            print(f"  {r.name}: {r.steps:,} steps, {json.dumps(r.params)}, scored against {r.reference}")
        return 0
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    _stored_runs(out, runs)
    try:
        t0 = time.perf_counter()
        started = scale.start(args.address, args.workers, "magenv sweep")
    except scale.RayMissing as exc:
        raise CommandError(str(exc)) from None
    t1 = time.perf_counter()
    workers = args.workers or scale.cluster_cpus()
    print(f"Ray up in {t1 - t0:.1f} s; {workers} run(s) at a time")

    def done(name, result, error):
        if error:
            print(f"  failed {name}: {error}")
        elif result:
            print(f"  done {name}: agent {result['agent_rmse']:.2f}°, reference {result['reference_rmse']:.2f}°")

    todo = [name for name in runs if finished_record(out, name, runs[name]) is None]
    print(f"{len(runs) - len(todo)} run(s) finished before, {len(todo)} to run")
    interrupted, outcome = False, {}
    try:
        if todo:
            outcome = scale.tune_runs(
                todo, functools.partial(run_trial, out=str(out), runs=runs), out, workers, on_done=done
            )
    except KeyboardInterrupt:
        interrupted = True
    finally:
        scale.stop(started)
    wall = time.perf_counter() - t1
    records, failed, fresh = [], {}, []
    for name in runs:
        record = finished_record(out, name, runs[name])
        if record is not None:
            records.append(record)
            if name in todo:
                fresh.append(record)
        else:
            failed[name] = runs[name]
            reason = outcome.get(name)
            interrupted |= reason is None  # neither finished nor failed: Ctrl-C stopped the sweep first
            print(f"not finished: {name}" + (f": {reason}" if isinstance(reason, str) else ""))
    rows = summary_rows(records, failed)
    print_summary(rows)
    print(f"wrote {write_summary(rows, out / 'summary.csv')}")
    work = sum(r["train_s"] + r["eval_s"] for r in fresh)
    print(
        f"sweep wall time {wall:.1f} s with {workers} worker(s); training and scoring inside the "
        f"{len(fresh)} run(s) done now: {work:.1f} s"
    )
    if interrupted:
        print("interrupted; run the same command again to resume")
        return 130
    if failed:
        print("some runs did not finish; run the same command again to retry them (finished runs are kept)")
        return PARTIAL
    return 0
