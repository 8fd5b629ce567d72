"""``magenv benchmark``: score a policy on magenv-bench v1 (``magenv.benchmark.suite``) and write its score card.

    magenv benchmark --agent AGENT [--tasks LIST] [--out DIR] [--seeds S] [--duration S] [--no-cache]
    magenv benchmark --sweep RUNS --out docs/benchmark [--scored-only] [--rows CSV]   (the baselines' table)
    magenv benchmark --summary CARD.json [CARD.json ...]    (one table of score cards: the README's results)

AGENT is a run folder (``magenv train``), ``pretrained:ENV_ID`` (a shipped agent), one weights-only file of an SB3
run folder (``RUN/best.safetensors``, ``RUN/checkpoints/step_T.safetensors``), or a Python callable
``module:function``: called once per env of the chosen tasks with the env id, it returns a policy for that env
(``policy(obs) -> action``, optionally ``reset()`` before each trial and ``env_kwargs``, the options of the env it
acts in) or None where it does not act. Nothing is unpickled; the callable's module is imported (its code runs, as
the user asked). ``--tasks``: a comma list of task names (``MagBlend-v0/dynamic_magnet``), env names (their tasks)
or ``sim`` (default: every task of the agent's envs). The agent, the tasks and the output folder are checked
before any trial runs.

OUT (default ``runs/benchmark``) receives ``card.md`` and ``card.json`` (per task: mean RMSE of the agent, the
rule and the oracle, the paired ratio to the rule with its 95 % interval and worst trial, the normalised score with
its interval and worst trial; over the tasks: rliable's IQM, optimality gap and probability of improvement over
the rule with stratified-bootstrap intervals) and ``profile.png`` (performance profiles of the agent, the rule
and the oracle). ``--seeds`` or ``--duration`` make a quick look that the card marks as outside the protocol.

The rules' and oracles' per-trial RMSEs are cached under the user data folder (``benchmark/``), keyed by a
hash of magenv's source and tuned files, so a change of code recomputes them (``--no-cache``: always).

``--sweep`` scores every finished run of ``magenv sweep`` folders (or of the sweep folders inside a folder, e.g.
``agents/configs/bench/train.sh``'s RUNS) on
its env's tasks and writes OUT/baselines.csv (env, task, method, training seed, RMSE, normalised score),
OUT/baselines.png and OUT/index.md (the protocol, the table with the number of training seeds finished of each
cell, the aggregates); a run's scores are kept beside it (``SWEEP/benchmark/NAME.json``, written whole) for the
next call. ``--scored-only`` scores nothing new: the table holds the runs scored before and names the finished
runs that are not. ``--rows CSV`` adds the runs of an earlier table (its ``baselines.csv``, read as text only)
that the sweeps do not hold, so that a table can be finished on another machine than the one that trained its
first runs; a run in both is taken from the sweeps. An SB3 agent acts on a task's trials together
(``magenv.evaluation``: one network forward per decision for all), with torch on one thread.

``--summary`` prints one Markdown table of the tasks of score cards (``card.json`` files, read as JSON only): per
task the rule, the ratio agent / rule and the normalised score with their 95 % intervals, and the worst trial's
ratio. The README's results table is this output for the shipped agents' cards (``docs/benchmark/shipped/``).
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from magenv.seeding import VALIDATION_START
from magenv.train.cli import CommandError, output_folder
from magenv.train.seeds import seeds_arg
from magenv.train.sweep import write_atomic

CARD = "card"
PROFILE = "profile.png"
BASELINES = "baselines"
ALGO_LABELS = {"ppo": "PPO", "sac": "SAC", "recurrent_ppo": "RecurrentPPO", "dagger": "DAgger"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--agent", help="run folder, pretrained:ENV_ID, RUN/FILE.safetensors, or module:function")
    what.add_argument("--sweep", nargs="+", type=Path, metavar="DIR", help="score the finished runs of sweeps")
    what.add_argument("--summary", nargs="+", type=Path, metavar="CARD", help="one table of score cards' tasks")
    p.add_argument("--tasks", default=None, help="comma list of tasks, envs or sim (default: the agent's envs)")
    p.add_argument("--out", type=Path, default=Path("runs/benchmark"), help="output folder (default %(default)s)")
    p.add_argument("--seeds", type=seeds_arg, default=None, help="quick look: other held-out seeds (below 5000)")
    p.add_argument("--duration", type=float, default=None, help="quick look: trials cut to S seconds")
    p.add_argument("--no-cache", action="store_true", help="recompute the rules' and oracles' RMSEs")
    p.add_argument("--scored-only", action="store_true", help="with --sweep: only runs scored before, no new scoring")
    p.add_argument("--rows", type=Path, default=None, metavar="CSV", help="with --sweep: an earlier baselines.csv")


# ----------------------------------------------------------------- the agent


class CallablePolicy:
    """A user's policy for one env: ``fn(obs) -> action``, its ``reset()`` and ``env_kwargs`` where it has them."""

    def __init__(self, fn, env_id: str, name: str):
        self.fn, self.env_id, self.name = fn, env_id, name
        self.env_kwargs = dict(getattr(fn, "env_kwargs", None) or {})

    def reset(self) -> None:
        reset = getattr(self.fn, "reset", None)
        if callable(reset):
            reset()

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.fn(obs)


def _import_callable(spec: str):
    module_name, _, attr = spec.partition(":")
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # the user's module: whatever stops its import
        raise CommandError(
            f"--agent {spec}: cannot import module {module_name!r} ({type(exc).__name__}: {exc})"
        ) from None
    fn = getattr(module, attr, None)
    if not callable(fn):
        raise CommandError(f"--agent {spec}: module {module_name!r} has no callable {attr!r}")
    return fn


def load_policies(spec: str, env_ids: list[str]) -> dict[str, Any]:
    """Env id → the policy ``spec`` names for it, for the envs of ``env_ids`` it acts in; CommandError naming the
    spec and the problem (nothing run yet)."""
    from magenv.agents.loading import PRETRAINED_PREFIX, RunError, load_agent, load_weights_file

    path = Path(spec)
    is_callable = ":" in spec and not spec.startswith(PRETRAINED_PREFIX) and not path.exists()
    if is_callable:
        fn = _import_callable(spec)
        out: dict[str, Any] = {}
        for env_id in env_ids:
            try:
                policy = fn(env_id)
            except Exception as exc:  # the user's code
                raise CommandError(
                    f"--agent {spec}: calling it with {env_id!r} raised {type(exc).__name__}: {exc}"
                ) from None
            if policy is None:
                continue
            if not callable(policy):
                raise CommandError(f"--agent {spec}: returned {type(policy).__name__} for {env_id}, not a policy")
            out[env_id] = CallablePolicy(policy, env_id, spec)
        if not out:
            raise CommandError(f"--agent {spec}: returned None for every env of the tasks ({', '.join(env_ids)})")
        return out
    try:
        agent = load_weights_file(path) if path.suffix == ".safetensors" else load_agent(spec)
    except RunError as exc:
        raise CommandError(f"--agent {spec}: {exc}") from None
    return {agent.env_id: agent}


# ----------------------------------------------------------------- trials and references


def source_fingerprint() -> str:
    """A hash of every file that may decide a rule's or an oracle's RMSE: magenv's (but the suite's) and its
    baselines' source, the packaged and the user's tuned files."""
    from magenv import registry

    h = hashlib.sha256()
    roots = [Path(str(importlib.import_module(p).__file__)).parent for p in ("magenv", "magenv.baselines")]
    files = [f for r in roots for pattern in ("*.py", "*.json", "*.xml") for f in sorted(r.rglob(pattern))]
    suite_dir = Path(str(importlib.import_module("magenv.benchmark").__file__)).parent  # the suite: no method's RMSE
    files = [f for f in files if suite_dir not in f.parents]
    files += sorted(registry.user_tuned_dir().glob("*.json")) if registry.user_tuned_dir().is_dir() else []
    for f in files:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def task_trials(task, seeds: list[int], duration: float | None) -> list:
    """The evaluation trials of ``task``: its scenario at every seed, or the recordings."""
    from magenv.benchmark.suite import RECORDINGS
    from magenv.recordings import load_all
    from magenv.scenarios import make_trial

    if task.test == RECORDINGS:
        return load_all()
    return [make_trial(task.test, s, **({} if duration is None else {"duration": duration})) for s in seeds]


def _rmse(method_name: str, method, trials: list) -> list[float]:
    from magenv import evaluation

    runs = evaluation.evaluate({method_name: method}, trials)
    return [r.scored.total for r in runs]


class References:
    """The rules' and oracles' per-trial RMSEs, computed once per code version (``source_fingerprint``) and
    kept in ``folder`` (None: not kept)."""

    def __init__(self, folder: Path | None):
        self.folder = folder
        self.key = source_fingerprint()

    def _path(self, method: str, duration: float | None) -> Path | None:
        if self.folder is None:
            return None
        cut = "" if duration is None else f"-cut{duration:g}s"
        return self.folder / self.key / f"{method}{cut}.json"

    def rmse(self, method: str, trials: list, duration: float | None) -> list[float]:
        """``method``'s total RMSE on each trial (by trial name, from the cache where it holds them)."""
        from magenv import registry

        path = self._path(method, duration)
        stored: dict[str, float] = {}
        if path is not None and path.is_file():
            try:
                stored = {str(k): float(v) for k, v in json.loads(path.read_text()).items()}
            except (ValueError, AttributeError):
                stored = {}  # a corrupt cache file is recomputed
        todo = [t for t in trials if t.name not in stored]
        if todo:
            stored.update(zip((t.name for t in todo), _rmse(method, registry.make(method), todo)))
            if path is not None:
                write_atomic(path, json.dumps(stored))
        return [stored[t.name] for t in trials]


def cache_folder(no_cache: bool) -> Path | None:
    from magenv.userdata import user_data_dir

    return None if no_cache else user_data_dir() / "benchmark"


# ----------------------------------------------------------------- scoring


def score_policy(policy, tasks, seeds, duration, refs: References, log=print) -> tuple[list, list[dict]]:
    """(TaskScores, skipped) of ``policy`` on ``tasks``: a recordings task without recordings is skipped with
    its reason."""
    from magenv.benchmark.score import score_task
    from magenv.trial import TrialError

    scores, skipped = [], []
    for task in tasks:
        t0 = time.perf_counter()
        try:
            trials = task_trials(task, seeds, duration)
        except TrialError as exc:
            trials, why = [], f"no recordings: {exc}"
        else:
            why = "no recordings: the folder holds no *.hdf5 file"
        if not trials:
            skipped.append({"task": task.name, "reason": why})
            log(f"{task.name}: skipped ({why})")
            continue
        agent = _rmse(getattr(policy, "name", "agent"), policy, trials)
        rule = refs.rmse(task.rule, trials, duration)
        oracle = refs.rmse(task.oracle, trials, duration) if task.oracle else []
        try:
            scores.append(score_task(task.name, task.rule, task.oracle, [t.name for t in trials], agent, rule, oracle))
        except ValueError as exc:  # e.g. trials cut so short that the oracle gains nothing over the rule
            raise CommandError(f"{task.name}: no score ({exc})") from None
        log(f"{task.name}: {time.perf_counter() - t0:.0f} s")
    return scores, skipped


def normalised_matrices(scores: list) -> dict[str, np.ndarray]:
    """(trials × tasks) per-trial normalised scores of the agent, the rule (0) and the oracle over the scores
    that have one (every simulated task has the same number of trials)."""
    have = [s for s in scores if s.normalised is not None]
    if not have:
        return {}
    agent = np.array([s.normalised.per_unit for s in have]).T
    oracle = np.array([(np.array(s.rule_rmse) - np.array(s.oracle_rmse)) / s.normalised.gap for s in have]).T
    return {"agent": agent, "rule": np.zeros_like(agent), "oracle": oracle}


def _fmt(x, digits: int = 2) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def _interval(point, low, high, digits: int = 2) -> str:
    return f"{_fmt(point, digits)} [{_fmt(low, digits)}, {_fmt(high, digits)}]"


def aggregate_lines(agg: dict, what: str) -> list[str]:
    """The Markdown table of :func:`magenv.benchmark.score.aggregates`."""
    lines = [
        f"| method | IQM [95 % CI] | optimality gap [95 % CI] | P(better than the rule) [95 % CI] | {what} |",
        "|---|---|---|---|---|",
    ]
    for m, a in agg.items():
        lines.append(
            f"| {m} | {_interval(*a['iqm'])} | {_interval(*a['optimality_gap'])} | {_interval(*a['improvement'])} "
            f"| {a['runs']} × {a['tasks']} |"
        )
    return lines


def card_markdown(card: dict) -> str:
    """The score card as Markdown."""
    lines = [f"# {card['suite']} score card: `{card['agent']}`", ""]
    if not card["protocol"]:
        lines += [f"**A quick look, not a {card['suite']} score**: {card['deviation']}.", ""]
    lines += [
        f"Evaluation seeds {card['seeds'][0]}–{card['seeds'][-1]} ({len(card['seeds'])} trials per simulated "
        "task); total RMSE (°), mean over trials; ratio: agent/rule, geometric mean of the per-trial ratios; "
        "normalised: 0 = the task's best tuned rule, 1 = the privileged oracle; 95 % bootstrap intervals.",
        "",
        "| task | rule | agent | rule RMSE | oracle RMSE | agent RMSE | ratio [95 % CI] | win | worst ratio "
        "| normalised [95 % CI] | worst trial |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for t in card["tasks"]:
        r, n = t["ratio"], t["normalised"]
        lines.append(
            f"| {t['task']} | {t['rule']} | {card['agent_name']} | {_fmt(t['rule_rmse'], 3)} | "
            f"{_fmt(t['oracle_rmse'], 3)} | {_fmt(t['agent_rmse'], 3)} | "
            f"{_interval(r['value'], r['low'], r['high'], 3)} | {_fmt(r['win_rate'])} | {_fmt(r['worst'], 2)} | "
            + ("– | – |" if n is None else f"{_interval(n['value'], n['low'], n['high'])} | {_fmt(n['worst'])} |")
        )
    for s in card["skipped"]:
        lines.append(f"| {s['task']} | skipped: {s['reason']} |" + " |" * 9)
    if card["aggregates"]:
        lines += ["", "Over the tasks with a normalised score (rliable, stratified bootstrap):", ""]
        lines += aggregate_lines(card["aggregates"], "trials × tasks")
        lines += ["", f"![performance profiles]({PROFILE})"]
    return "\n".join(lines) + "\n"


def _deviation(seeds, duration, suite_seeds) -> str:
    parts = []
    if list(seeds) != list(suite_seeds):
        parts.append(f"seeds {seeds[0]}–{seeds[-1]} ({len(seeds)}) instead of the suite's")
    if duration is not None:
        parts.append(f"trials cut to {duration:g} s")
    return "; ".join(parts)


def run_agent(args: argparse.Namespace) -> int:
    from magenv.benchmark import score, suite

    out = output_folder(args.out, "--out")
    try:
        tasks = suite.select(args.tasks)
    except ValueError as exc:
        raise CommandError(f"--tasks: {exc}") from None
    if args.duration is not None and not args.duration > 0:
        raise CommandError(f"--duration must be > 0 s, got {args.duration:g}")
    seeds = list(args.seeds) if args.seeds is not None else list(suite.EVAL_SEEDS)
    if max(seeds) >= VALIDATION_START:
        raise CommandError(f"--seeds: held-out seeds lie below {VALIDATION_START} (above: model selection)")
    policies = load_policies(args.agent, list(dict.fromkeys(t.env_id for t in tasks)))
    if args.tasks is None:
        tasks = [t for t in tasks if t.env_id in policies]
    missing = [t.name for t in tasks if t.env_id not in policies]
    if missing:
        raise CommandError(f"--agent {args.agent} does not act in the env of task(s) {', '.join(missing)}")
    refs = References(cache_folder(args.no_cache))
    print(f"{suite.VERSION}: {args.agent} on {len(tasks)} task(s)", flush=True)
    scores, skipped = [], []
    for env_id, policy in policies.items():
        got, why = score_policy(policy, [t for t in tasks if t.env_id == env_id], seeds, args.duration, refs)
        scores += got
        skipped += why
    matrices = normalised_matrices(scores)
    deviation = _deviation(seeds, args.duration, suite.EVAL_SEEDS)
    card = {
        "suite": suite.VERSION,
        "agent": args.agent,
        "agent_name": next(iter(policies.values())).name if len(policies) == 1 else "agent",
        "protocol": not deviation,
        "deviation": deviation,
        "seeds": seeds,
        "duration": args.duration,
        "tasks": [s.as_dict() for s in scores],
        "skipped": skipped,
        "aggregates": score.aggregates(matrices) if matrices else {},
    }
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / f"{CARD}.json", json.dumps(card, indent=1))
    write_atomic(out / f"{CARD}.md", card_markdown(card))
    if matrices:
        score.profile_png(matrices, out / PROFILE, f"{args.agent} on {suite.VERSION}")
    print(card_markdown(card))
    print(f"wrote {out / (CARD + '.md')}, {out / (CARD + '.json')}" + (f", {out / PROFILE}" if matrices else ""))
    return 0


# ----------------------------------------------------------------- the baselines' table


def sweep_folders(given: list[Path]) -> list[Path]:
    """The sweep folders of ``--sweep``: each folder given that holds a ``sweep.json``, else its subfolders that
    do (``RUNS`` for ``RUNS/ppo``, ``RUNS/sac`` …); CommandError naming a folder with none."""
    found = []
    for folder in given:
        inside = (
            [folder] if (folder / "sweep.json").is_file() else sorted(p.parent for p in folder.glob("*/sweep.json"))
        )
        if not inside:
            raise CommandError(f"--sweep {folder}: not a magenv sweep folder (no sweep.json in it or its subfolders)")
        found += inside
    return found


def _finished_runs(sweeps: list[Path]) -> list[tuple[Path, dict]]:
    """(sweep folder, its results record) of every finished run of ``sweeps``."""
    from magenv.train.sweep import finished_record

    found = []
    for sweep in sweeps:
        runs = json.loads((sweep / "sweep.json").read_text())["runs"]
        for name, spec in runs.items():
            record = finished_record(sweep, name, spec)
            if record is not None:
                found.append((sweep, record))
    return found


def _kept(sweep: Path, record: dict) -> tuple[Path, str]:
    """Where a run's scores are kept (SWEEP/benchmark/NAME.json) and the stamp of its results record."""
    stamp = hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()[:16]
    return sweep / "benchmark" / f"{record['name']}.json", stamp


def kept_rows(sweep: Path, record: dict, refs: References) -> list[dict] | None:
    """A run's rows as kept by an earlier call with the same results, suite and references; None where there are
    none (or the file is unreadable: it is scored again)."""
    from magenv.benchmark import suite

    keep, stamp = _kept(sweep, record)
    try:
        kept = json.loads(keep.read_text())
    except (OSError, ValueError):
        return None
    if isinstance(kept, dict) and (kept.get("stamp"), kept.get("suite"), kept.get("refs")) == (
        stamp,
        suite.VERSION,
        refs.key,
    ):
        return kept.get("rows")
    return None


def _run_scores(sweep: Path, record: dict, tasks, refs: References) -> list[dict]:
    """Rows of one finished run on its env's tasks, kept in SWEEP/benchmark/NAME.json for the next call: only the
    tasks without kept rows are scored (a task skipped before — the recordings track where the recordings were
    missing — is scored once they are there)."""
    from magenv.agents.loading import load_agent
    from magenv.benchmark import suite

    spec = record["run"]
    kept = kept_rows(sweep, record, refs) or []
    todo = [t for t in tasks if t.env_id == spec["env_id"] and t.name not in {r["task"] for r in kept}]
    if not todo:
        return kept
    name = record["name"]
    keep, stamp = _kept(sweep, record)
    policy = load_agent(record["run_dir"])
    scores, _ = score_policy(policy, todo, list(suite.EVAL_SEEDS), None, refs,
                             log=lambda line: print(f"  {name} {line}", flush=True))  # fmt: skip
    order = [t.name for t in tasks]
    rows = kept + [
        {
            "env": spec["env_id"],
            "task": s.task,
            "method": ALGO_LABELS.get(spec["algo"], spec["algo"]),
            "seed": spec["seed"],
            "rmse": float(np.mean(s.agent)),
            "normalised": None if s.normalised is None else s.normalised.score,
            "per_trial": None if s.normalised is None else list(s.normalised.per_unit),
        }
        for s in scores
    ]
    rows.sort(key=lambda row: order.index(row["task"]))
    write_atomic(keep, json.dumps({"stamp": stamp, "suite": suite.VERSION, "refs": refs.key, "rows": rows}))
    return rows


CSV_HEADER = ["env", "task", "method", "training_seed", "rmse_deg", "normalised_score"]


def baselines_csv(rows: list[dict], path: Path) -> Path:
    import csv

    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_HEADER)
        for r in sorted(rows, key=lambda r: (r["task"], r["method"], r["seed"])):
            n = "" if r["normalised"] is None else f"{r['normalised']:.4f}"
            w.writerow([r["env"], r["task"], r["method"], r["seed"], f"{r['rmse']:.4f}", n])
    return path


def read_rows(path: Path) -> list[dict]:
    """The rows of an earlier ``baselines.csv`` (:func:`baselines_csv`), read as text; CommandError naming the
    file and line where it is not one of the suite's tables."""
    import csv

    from magenv.benchmark import suite

    tasks = {t.name: t for t in suite.TASKS}
    try:
        with open(path, newline="") as f:
            lines = list(csv.reader(f))
    except FileNotFoundError:
        raise CommandError(f"--rows: no file {path}") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise CommandError(f"--rows: {path} is not a CSV file ({exc})") from None
    if not lines or lines[0] != CSV_HEADER:
        raise CommandError(f"--rows: {path} is not a baselines.csv (its header is not {','.join(CSV_HEADER)})")
    rows: list[dict] = []
    for number, line in enumerate(lines[1:], start=2):
        try:
            env, task, method, seed, rmse_text, norm_text = line
            rmse, norm = float(rmse_text), float(norm_text) if norm_text else None
            row = {"env": env, "task": task, "method": method, "seed": int(seed), "rmse": rmse, "normalised": norm,
                   "per_trial": None}  # fmt: skip
        except ValueError:
            raise CommandError(f"--rows: {path} line {number} is not env,task,method,seed,rmse,score") from None
        task_of = tasks.get(task)
        if task_of is None or task_of.env_id != env or method not in ALGO_LABELS.values():
            raise CommandError(f"--rows: {path} line {number}: {env} {task} {method} is not a task and method of "
                               f"{suite.VERSION}")  # fmt: skip
        if not math.isfinite(rmse) or (norm is not None and not math.isfinite(norm)):
            raise CommandError(f"--rows: {path} line {number}: a score that is not a finite number")
        if any((r["task"], r["method"], r["seed"]) == (task, method, row["seed"]) for r in rows):
            raise CommandError(f"--rows: {path} line {number}: {task} {method} seed {seed} is there twice")
        rows.append(row)
    return rows


def _run_key(row: dict) -> tuple:
    return row["env"], row["method"], row["seed"]


def baseline_matrices(rows: list[dict], tasks: list[str]) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Method → (training seeds × tasks) mean normalised scores over the ``tasks`` where the method has runs,
    the seeds that finished on every one of them; method → which tasks and seeds (for the table's caption).
    Methods in name order, so that the bootstrap (one generator drawn method after method) depends on the rows,
    not on their order."""
    matrices, covered = {}, {}
    for method in sorted({r["method"] for r in rows}):
        mine = [r for r in rows if r["method"] == method and r["normalised"] is not None]
        have = [t for t in tasks if any(r["task"] == t for r in mine)]
        seeds = sorted(set.intersection(*[{r["seed"] for r in mine if r["task"] == t} for t in have])) if have else []
        if not seeds:
            continue
        value = {(r["task"], r["seed"]): r["normalised"] for r in mine}
        matrices[method] = np.array([[value[(t, s)] for t in have] for s in seeds])
        covered[method] = f"{len(have)} of {len(tasks)} tasks, seeds {', '.join(map(str, seeds))}"
    return matrices, covered


def cost_lines(records: list[dict]) -> list[str]:
    """The Markdown table of the minutes a finished run took (training and its sweep's scoring), per env and
    method: CPU minutes where the sweep recorded them, else wall minutes (marked *, on the loaded machine), and
    the CPU-hours the table's runs would take at those costs."""
    from magenv.benchmark import suite

    methods = list(ALGO_LABELS)
    lines = ["| env | " + " | ".join(ALGO_LABELS[m] for m in methods) + " |", "|---|" + "---|" * len(methods)]
    total, cells = 0.0, 0
    for env in suite.ENVS:
        row = []
        for m in methods:
            mine = [r for r in records if r["run"]["env_id"] == env.env_id and r["run"]["algo"] == m]
            cpu = [r["train_cpu_s"] + r["eval_cpu_s"] for r in mine if "train_cpu_s" in r]
            wall = [r["train_s"] + r["eval_s"] for r in mine]
            if not mine:
                row.append("–")
                continue
            minutes = float(np.mean(cpu if cpu else wall)) / 60
            row.append(f"{minutes:.0f}" + ("" if cpu else "*"))
            total += minutes * suite.BASELINE_SEEDS / 60
            cells += 1
        lines.append(f"| {env.short} | " + " | ".join(row) + " |")
    n_cells = len(suite.ENVS) * len(methods)
    lines += [
        "",
        f"The {cells} of {n_cells} (env, method) cells measured would take {total:.1f} CPU-hours for their "
        f"{suite.BASELINE_SEEDS} seeds each ({total / 2:.1f} h on two free cores)"
        + ("." if cells == n_cells else "; the others are not measured yet."),
    ]
    return lines


def index_markdown(
    rows: list[dict],
    records: list[dict],
    n_planned: int,
    agg: dict,
    covered: dict,
    unscored: Sequence[dict] = (),
    n_earlier: int = 0,
) -> str:
    """docs/benchmark/index.md: the protocol (from the suite) and the baselines' table of the scored runs
    (``records``; ``unscored``: finished runs not scored yet; ``n_earlier``: runs read from an earlier table,
    ``--rows``, whose timings are not known here)."""
    from magenv.benchmark import suite

    methods = list(ALGO_LABELS.values())
    n_scored = len(records) + n_earlier
    lines = [
        f"# Benchmark: {suite.VERSION}",
        "",
        "<!-- written by `magenv benchmark --sweep RUNS --out docs/benchmark`: edit magenv/benchmark/suite.py "
        "or train/benchmark.py, not this page -->",
        "",
        "Score any policy on the suite in one command (a run folder, `pretrained:ENV_ID`, a weights file or your "
        "own callable `module:function`):",
        "",
        "```bash",
        "magenv benchmark --agent pretrained:magenv/MagBlend-v0 --out runs/card",
        "magenv benchmark --agent mypackage.policies:make_policy --tasks MagBlend-v0",
        "magenv benchmark --summary runs/card/card.json other/card.json   # score cards' tasks in one table",
        "```",
        "",
        "The shipped students' score cards: [shipped](shipped.md).",
        "",
        "## Protocol",
        "",
        f"* **Tasks**: {len(suite.TASKS)}, each an env with one held-out test (below); the real-recordings track "
        "has no oracle, so no normalised score (it is scored against the rule only).",
        f"* **Evaluation seeds** {suite.EVAL_SEEDS[0]}–{suite.EVAL_SEEDS[-1]} ({len(suite.EVAL_SEEDS)} trials "
        "per simulated task), disjoint from every training (≥ 10 000) and validation (5000–9999) seed of the project "
        "and from the seeds 0–39 its own figures were read on.",
        f"* **Budget**: {suite.BUDGET_STEPS:,} env-steps of training per run at each env's default "
        "`decision_every` (the same sensor samples at another one); an imitation learner counts the env-steps of "
        "the rollouts it labels.",
        "* **Score**: per task, the total RMSE (°) and, paired per trial, the ratio to the task's best tuned rule "
        "and the normalised score (rule_i − agent_i) / mean(rule − oracle): 0 = the rule, 1 = the privileged "
        "oracle (it reads truth; an upper bound, never a baseline). Over tasks: rliable's IQM, optimality gap and "
        "probability of improvement over the rule, with stratified-bootstrap 95 % intervals, and performance "
        "profiles.",
        "",
        "* **Rule** of a task: the tuned rule of lowest mean RMSE on the project's seeds 0–39 "
        "([results](../results.md)); MagKalman-v0's and MagConstraint-v0's act on the extended observation.",
        "",
        "| task | training mixture | rule (score 0) | oracle (score 1) |",
        "|---|---|---|---|",
    ]
    for t in suite.TASKS:
        lines.append(f"| {t.name} | {', '.join(t.env.mixture)} | `{t.rule}` | {f'`{t.oracle}`' if t.oracle else '–'} |")
    lines += [
        "",
        "## Offline datasets",
        "",
        "`magenv datasets build [--envs …] [--episodes N]` rolls the oracle and the tuned rules out on each env's "
        "training mixture (training seeds) into Minari datasets (`magenv/blend-oracle-v0`, …; `magenv datasets "
        "list`): observations, actions, rewards and the truth-only channels (errors against the true orientation, "
        "the disturbance's size, the true quaternion) in the step infos; `dataset.recover_environment()` and an "
        "episode's reset seed replay it to the same rewards. Needs `pip install 'magenv[datasets]'`.",
        "",
        "## Baselines",
        "",
        "PPO, SAC and RecurrentPPO (Stable-Baselines3, sb3-contrib) from scratch, and DAgger from the oracle, each "
        f"at the budget with {suite.BASELINE_SEEDS} training seeds (configs: `agents/configs/bench/`), trained by "
        "`nice -n 19 agents/configs/bench/train.sh RUNS` (`magenv sweep`, resumable; the budget was chosen so "
        "that the 100 runs train within a day on two free cores: the cost table below says how far the runs "
        "measured so far bear that out), which ends by scoring them into RUNS/table (`magenv benchmark --sweep RUNS "
        "--out RUNS/table`: this page, its CSV and its profile; with `--rows docs/benchmark/baselines.csv` the runs "
        "of the table before, whose folders are on another machine, are kept).",
        "",
        "Scoring an SB3 run: the agent acts on a task's trials together, one env per trial and one forward of its "
        "network per decision for all (`magenv.evaluation`), with torch on one thread; a trial's score does not "
        "depend on the trials scored with it, bit for bit. On the loaded two-core machine (load 6, 2026-12-07) "
        "a RecurrentPPO run took 1.6 s per task instead of 285 s trial by trial (18 s with torch on one thread "
        "alone), a PPO run 1.8 s instead of 13 s (MagBlend-v0/dynamic_magnet, 20 trials of 60 s, wall, median of "
        "2 alternating rounds; `python benchmarks/bench_scoring.py --agent RUN`). DAgger students and callables "
        "act trial by trial.",
        "",
        (
            f"**{n_scored} of {n_planned} runs finished and scored**"
            if not unscored
            else f"**{n_scored + len(unscored)} of {n_planned} runs finished, {n_scored} of them scored** "
            f"(not yet scored: {', '.join(sorted(r['name'] for r in unscored))})"
        )
        + (
            f" ({n_earlier} of them read from an earlier table, `--rows`, trained and scored on another machine "
            f"under the same {suite.VERSION})"
            if n_earlier
            else ""
        )
        + (
            "; the table is complete."
            if n_scored == n_planned
            else ": the table is incomplete. A cell shows the mean over the training seeds scored (n = how "
            "many); – where none did."
        ),
        "",
        "Normalised score (mean over training seeds of each seed's mean over the evaluation trials; RMSE ° in "
        "brackets; raw rows: [baselines.csv](baselines.csv)):",
        "",
        "| task | " + " | ".join(methods) + " |",
        "|---|" + "---|" * len(methods),
    ]
    for t in suite.TASKS:
        cells = []
        for m in methods:
            mine = [r for r in rows if r["task"] == t.name and r["method"] == m]
            if not mine:
                cells.append("–")
                continue
            rmse = np.mean([r["rmse"] for r in mine])
            norm = [r["normalised"] for r in mine if r["normalised"] is not None]
            cells.append((f"{np.mean(norm):.2f} " if norm else "") + f"({rmse:.2f}°) n = {len(mine)}")
        lines.append(f"| {t.name} | " + " | ".join(cells) + " |")
    if agg:
        lines += ["", "Over tasks (each method over the tasks and training seeds scored):", ""]
        lines += aggregate_lines(agg, "seeds × tasks")
        lines += ["", "| method | covered |", "|---|---|"] + [f"| {m} | {c} |" for m, c in covered.items()]
        lines += ["", f"![performance profiles of the baselines]({BASELINES}.png)"]
    if records or unscored:
        lines += [
            "",
            "Minutes per run (training, validation and the sweep's own scoring), mean over the finished runs"
            + (" timed here (not the runs read from the earlier table):" if n_earlier else ":"),
        ]
        lines += ["", *cost_lines([*records, *unscored])]
    return "\n".join(lines) + "\n"


def run_sweeps(args: argparse.Namespace) -> int:
    from magenv.benchmark import score, suite

    out = output_folder(args.out, "--out")
    sweeps = sweep_folders(args.sweep)
    if args.tasks is not None or args.seeds is not None or args.duration is not None:
        raise CommandError("--sweep scores the baselines on the whole suite: drop --tasks, --seeds and --duration")
    planned = len(suite.ENVS) * len(ALGO_LABELS) * suite.BASELINE_SEEDS
    earlier = read_rows(args.rows) if args.rows is not None else []
    finished = _finished_runs(sweeps)
    print(f"{len(finished)} finished run(s) in {len(sweeps)} sweep folder(s)", flush=True)
    refs = References(cache_folder(args.no_cache))
    if args.scored_only:
        kept = [(record, kept_rows(sweep, record, refs)) for sweep, record in finished]
        scored = [(record, rows) for record, rows in kept if rows is not None]
        unscored = [record for record, rows in kept if rows is None]
    else:
        scored = [(record, _run_scores(sweep, record, list(suite.TASKS), refs)) for sweep, record in finished]
        unscored = []
    rows = [row for _, run_rows in scored for row in run_rows]
    have = {_run_key(row) for row in rows}
    earlier = [row for row in earlier if _run_key(row) not in have]
    rows += earlier
    out.mkdir(parents=True, exist_ok=True)
    baselines_csv(rows, out / f"{BASELINES}.csv")
    names = [t.name for t in suite.TASKS if t.normalised]
    matrices, covered = baseline_matrices(rows, names)
    agg = score.aggregates(matrices) if matrices else {}
    if matrices:
        score.profile_png(matrices, out / f"{BASELINES}.png", f"{suite.VERSION} baselines")
    records = [record for record, _ in scored]
    n_earlier = len({_run_key(row) for row in earlier})
    write_atomic(out / "index.md", index_markdown(rows, records, planned, agg, covered, unscored, n_earlier))
    print(f"wrote {out / (BASELINES + '.csv')}, {out / 'index.md'}" + (f", {out / BASELINES}.png" if agg else ""))
    return 0


# ----------------------------------------------------------------- a summary of score cards

CARD_TASK_KEYS = ("task", "rule", "ratio", "normalised")


def read_card(path: Path) -> dict:
    """A score card (``card.json``) read as JSON; CommandError naming the file where it is not one."""
    try:
        card = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise CommandError(f"--summary: no file {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CommandError(f"--summary: {path} is not a JSON score card ({exc})") from None
    tasks = card.get("tasks") if isinstance(card, dict) else None
    if not isinstance(tasks, list) or not all(
        isinstance(t, dict) and all(k in t for k in CARD_TASK_KEYS) for t in tasks
    ):
        raise CommandError(f"--summary: {path} is not a score card of `magenv benchmark --agent` (no tasks)")
    return card


def summary_lines(cards: list[dict]) -> list[str]:
    """The tasks of ``cards`` as one Markdown table (module docstring)."""
    lines = [
        "| task | rule (score 0) | agent / rule [95 % CI] | normalised [95 % CI] | worst trial's ratio |",
        "|---|---|---|---|---|",
    ]
    for card in cards:
        for t in card["tasks"]:
            r, n = t["ratio"], t["normalised"]
            norm = "–" if n is None else _interval(n["value"], n["low"], n["high"])
            lines.append(
                f"| {t['task']} | `{t['rule']}` | {_interval(r['value'], r['low'], r['high'], 3)} | {norm} "
                f"| {_fmt(r['worst'])} |"
            )
    return lines


def run_summary(args: argparse.Namespace) -> int:
    cards = [read_card(p) for p in args.summary]
    print("\n".join(summary_lines(cards)))
    return 0


def run(args: argparse.Namespace) -> int:
    if (args.scored_only or args.rows is not None) and not args.sweep:
        raise CommandError("--scored-only and --rows go with --sweep")
    if args.summary:
        return run_summary(args)
    return run_sweeps(args) if args.sweep else run_agent(args)
