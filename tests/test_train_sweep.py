"""``magenv sweep``: the sweep file, one run (train, resume, score), the table; end to end on a local Ray.

The sweep file and a single run need no Ray; the end-to-end tests start one
local Ray of 2 CPUs for the module (``ray_2cpu``) and skip, naming the
extra, where Ray is not installed.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from magenv import stats
from magenv.agents.hyperparams import ConfigError
from magenv.agents.training import train
from magenv.train.cli import main as cli
from magenv.train.sweep import run_trial, summary_rows
from magenv.train.sweep_config import configurations, load_sweep

ENV = "magenv/MagBlend-v0"
TINY = {"n_envs": 2, "n_steps": 64, "batch_size": 64, "n_epochs": 1, "env_kwargs": {"episode_seconds": 3.0}}
SEARCH = {
    "seeds": "0:2",
    "params": {"learning_rate": [1.0e-4, 3.0e-4]},
    "steps": 128,
    "eval_every": 128,
    "eval_scenarios": ["dynamic_clean"],
    "eval_seeds": [5000],
    "report": {"scenarios": ["dynamic_clean"], "seeds": [0]},
}


def sweep_file(tmp_path: Path, search: dict | None = None, section: dict | None = None, name="sweep.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump({ENV: {**TINY, **(section or {})}, "search": {**SEARCH, **(search or {})}}))
    return path


# ----------------------------------------------------------------- the sweep file


def test_a_grid_crosses_configurations_with_seeds_over_the_shipped_config(tmp_path):
    path = sweep_file(tmp_path, {"params": {"learning_rate": [1.0e-4, 3.0e-4], "policy_kwargs.net_arch": [[8], [16]]}})
    runs = load_sweep(path)
    assert [r.name for r in runs[:3]] == ["MagBlend-v0-ppo-c0-s0", "MagBlend-v0-ppo-c0-s1", "MagBlend-v0-ppo-c1-s0"]
    assert len(runs) == 4 * 2 and {r.seed for r in runs} == {0, 1}
    assert [r.params for r in runs[::2]] == [
        {"learning_rate": 1.0e-4, "policy_kwargs.net_arch": [8]},
        {"learning_rate": 1.0e-4, "policy_kwargs.net_arch": [16]},
        {"learning_rate": 3.0e-4, "policy_kwargs.net_arch": [8]},
        {"learning_rate": 3.0e-4, "policy_kwargs.net_arch": [16]},
    ]
    shipped = yaml.safe_load(open(Path(__file__).parents[1] / "agents/configs/ppo.yaml"))[ENV]
    section = runs[2].section
    assert section["learning_rate"] == 1.0e-4 and section["policy_kwargs"]["net_arch"] == [16]
    # the dotted key replaced one nested key; the rest of the shipped policy_kwargs and section stay
    assert section["policy_kwargs"]["activation_fn"] == shipped["policy_kwargs"]["activation_fn"]
    assert section["gae_lambda"] == shipped["gae_lambda"] and section["n_steps"] == 64  # the file's over the shipped
    assert all(r.steps == 128 and r.reference == "fan_lambda_tuned" and r.report_seeds == [0] for r in runs)


def test_random_search_draws_the_same_configurations_from_the_same_file():
    search = {
        "mode": "random",
        "samples": 6,
        "seed": 3,
        "params": {
            "learning_rate": {"loguniform": [1.0e-5, 1.0e-3]},
            "gamma": {"uniform": [0.9, 0.99]},
            "n_epochs": {"randint": [1, 3]},
            "batch_size": [32, 64],
            "ent_coef": 0.0,
        },
    }
    a, b = configurations("f", search), configurations("f", search)
    assert a == b and len(a) == 6
    assert configurations("f", {**search, "seed": 4}) != a
    assert all(1e-5 <= c["learning_rate"] <= 1e-3 and 0.9 <= c["gamma"] <= 0.99 for c in a)
    assert {c["n_epochs"] for c in a} <= {1, 2, 3} and {c["batch_size"] for c in a} <= {32, 64}
    assert all(c["ent_coef"] == 0.0 for c in a)


@pytest.mark.parametrize(
    ("search", "section", "message"),
    [
        ({"paralel": 2}, None, "unknown key(s) in search: paralel"),
        ({"params": {"learning_rate": ["fast"]}}, None, "configuration 0: {'learning_rate': 'fast'}]: learning_rate"),
        ({"params": {"n_envs": [0]}}, None, "n_envs must be an integer from 1 to 1024, got 0"),
        (
            {"algos": ["ppo", "sac"]},
            None,
            "sac, configuration 0: {'learning_rate': 0.0001}]: unknown key(s) n_epochs for sac",
        ),
        ({"algos": ["a2c"]}, None, "search.algos: unknown a2c"),
        ({"report": {"seeds": "5000:5002"}}, None, "must be below 5000"),
        ({"report": {"reference": "nothing"}}, None, "unknown method 'nothing'"),
        ({"params": {"gamma": {"uniform": [0.9, 0.99]}}}, None, "a distribution needs mode: random"),
        ({"mode": "random", "params": {"gamma": {"normal": [0, 1]}}}, None, "uniform, loguniform, randint, choice"),
        ({"mode": "random", "params": {"learning_rate": {"loguniform": [0, 1]}}}, None, "lo > 0"),
        ({"seeds": "5:3"}, None, "bad seed list '5:3'"),
        ({"eval_scenarios": ["nowhere"]}, None, "unknown nowhere"),
        ({}, {"seed": 3}, "seed (the seed is magenv train --seed"),
    ],
)
def test_a_bad_sweep_file_is_named_before_anything_runs(tmp_path, search, section, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        load_sweep(sweep_file(tmp_path, search, section))


def test_cli_dry_run_and_errors(tmp_path, capsys):
    assert cli(["sweep", str(sweep_file(tmp_path)), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "4 runs: 2 configuration(s) × 2 seed(s)" in out and "MagBlend-v0-ppo-c1-s1: 128 steps" in out
    (tmp_path / "nosearch.yaml").write_text(yaml.safe_dump({ENV: TINY}))
    assert cli(["sweep", str(tmp_path / "nosearch.yaml")]) == 2
    assert "needs a `search:` section" in capsys.readouterr().err
    assert cli(["sweep", str(tmp_path / "missing.yaml")]) == 2
    assert "no such sweep file" in capsys.readouterr().err


def test_without_ray_the_command_names_the_extra(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    assert cli(["sweep", str(sweep_file(tmp_path)), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "magenv sweep needs Ray Tune" in err and "pip install 'magenv[scale]'" in err


def test_null_drops_a_shipped_key_and_scenarios_may_differ_per_env(tmp_path):
    kalman = "magenv/MagKalman-v0"
    doc = {
        ENV: {**TINY, "pretrain": {"teacher": "fan_lambda", "steps": 64}},
        kalman: {**TINY, "pretrain": None},  # the shipped MagKalman-v0 section clones kf_model_tuned first
        "search": {
            **SEARCH,
            "params": {},
            "eval_scenarios": {ENV: ["dynamic_clean"], kalman: "stationary_magnet"},
            "report": {"seeds": [0]},  # its scenarios: each env's eval_scenarios
        },
    }
    path = tmp_path / "two.yaml"
    path.write_text(yaml.safe_dump(doc))
    runs = {r.env_id: r for r in load_sweep(path, seeds=[7])}
    assert "pretrain" in runs[ENV].section and "pretrain" not in runs[kalman].section
    assert runs[kalman].eval_scenarios == ["stationary_magnet"] == runs[kalman].report_scenarios
    assert runs[ENV].eval_scenarios == ["dynamic_clean"] and runs[ENV].seed == 7 and runs[ENV].name.endswith("-s7")
    doc["search"]["eval_scenarios"] = {ENV: ["dynamic_clean"]}
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="gives no scenarios for magenv/MagKalman-v0"):
        load_sweep(path)


def test_a_dagger_section_names_its_teacher_and_each_seed_draws_its_own_trials(tmp_path):
    search = {"algos": ["dagger"], "seeds": "0:2", "eval_scenarios": ["dynamic_clean"], "eval_seeds": "5000:5002"}
    path = tmp_path / "dagger.yaml"
    path.write_text(yaml.safe_dump({ENV: {"teacher": "oracle", "iterations": 1, "ensemble": 1}, "search": search}))
    first, second = load_sweep(path)
    assert first.section["teacher"] == "oracle" and first.section["val_seeds"] == [5000, 5002]
    assert first.section["train_seed"] != second.section["train_seed"] and second.section["seed"] == 1
    assert first.section["val_scenarios"] == ["dynamic_clean"]
    path.write_text(yaml.safe_dump({ENV: {"iterations": 1, "ensemble": 1}, "search": search}))
    with pytest.raises(ConfigError, match="a dagger section needs teacher"):
        load_sweep(path)
    path.write_text(yaml.safe_dump({ENV: {"teacher": "oracle", "iterations": 0}, "search": search}))
    with pytest.raises(ConfigError, match="'iterations' must be a positive integer"):
        load_sweep(path)


def test_a_dagger_run_trains_resumes_and_is_scored_like_the_others(tmp_path):
    search = {"algos": ["dagger"], "seeds": [0], "eval_scenarios": ["dynamic_clean"], "eval_seeds": [5000]}
    section = {"teacher": "oracle", "scenarios": ["dynamic_clean"], "iterations": 2, "trials_per_scenario": 1}
    path = tmp_path / "dagger.yaml"
    path.write_text(yaml.safe_dump({ENV: {**section, "fit_steps": 50, "ensemble": 1}, "search": search}))
    runs = {r.name: json.loads(json.dumps(r.as_dict())) for r in load_sweep(path)}
    (name,) = runs
    record = run_trial(name, str(tmp_path / "out"), runs)
    assert record["timesteps"] == 2 * 2240 and record["start_timesteps"] == 0  # 70 s at 256 Hz, k = 8, twice
    assert len(record["agent"]) == len(record["reference"]) == 5 and record["agent_rmse"] > 0  # report seeds 0:5
    (tmp_path / "out" / "results" / f"{name}.json").unlink()  # as if stopped after training: resumed, not redone
    again = run_trial(name, str(tmp_path / "out"), runs)
    assert again["start_timesteps"] == 2 * 2240 and again["agent"] == record["agent"]


# ----------------------------------------------------------------- one run, without Ray


@pytest.fixture(scope="module")
def one_run(tmp_path_factory):
    """A one-run sweep (seed 0, 256 steps) and the folder it runs in."""
    tmp = tmp_path_factory.mktemp("one")
    run = load_sweep(sweep_file(tmp, {"seeds": [0], "params": {}, "steps": 256}))[0]
    return {run.name: json.loads(json.dumps(run.as_dict()))}, tmp / "out"


def test_a_run_trains_a_normal_run_folder_resumes_it_and_scores_it_against_the_reference(one_run):
    runs, out = one_run
    (name,) = runs
    spec = runs[name]
    # an interrupted run: its first 128 steps done by magenv train itself, with the run's own config
    config = out / "configs" / f"{name}.yaml"
    config.parent.mkdir(parents=True)
    config.write_text(yaml.safe_dump({ENV: spec["section"]}, sort_keys=False))
    kw = dict(config=str(config), seed=0, eval_every=128, eval_scenarios=("dynamic_clean",), eval_seeds=(5000,))
    train(ENV, "ppo", 128, out / "runs" / name, progress_bar=False, **kw)
    first = (out / "runs" / name / "evaluations.csv").read_text().splitlines()
    record = run_trial(name, str(out), runs)
    assert record["start_timesteps"] == 128 and record["timesteps"] == 256  # resumed, not restarted
    rows = (out / "runs" / name / "evaluations.csv").read_text().splitlines()
    assert rows[: len(first)] == first and len(rows) == len(first) + 1
    # scored on the report trials: the agent's best model and the reference, the numbers of magenv compare
    from magenv import evaluation, registry
    from magenv.agents import load_agent
    from magenv.scenarios import make_trial

    trial = make_trial("dynamic_clean", 0)
    assert record["trials"] == [trial.name]
    agent = evaluation.run_method("agent", load_agent(out / "runs" / name), trial).score.total
    ref = evaluation.run_method("ref", registry.make("fan_lambda_tuned"), trial).score.total
    assert record["agent"] == [agent] and record["reference"] == [ref]
    assert record["agent_rmse"] == agent and record["reference_rmse"] == ref
    assert json.loads((out / "results" / f"{name}.json").read_text()) == record
    # again: the finished run is not run again
    mtime = (out / "runs" / name / "state.json").stat().st_mtime_ns
    assert run_trial(name, str(out), runs) == record
    assert (out / "runs" / name / "state.json").stat().st_mtime_ns == mtime
    # the run folder is a normal one: magenv evaluate takes it
    assert cli(["evaluate", str(out / "runs" / name), "--scenario", "dynamic_clean", "--seeds", "0"]) == 0


def test_the_table_pairs_each_configurations_seeds():
    def record(config, seed, agent, ref):
        spec = {"env_id": ENV, "algo": "ppo", "config": config, "seed": seed, "params": {"lr": config}}
        return {"run": {**spec, "reference": "fan_lambda_tuned"}, "agent_rmse": agent, "reference_rmse": ref}

    agents = [1.0, 1.2, 0.9, 1.5]
    records = [record(0, s, a, 1.25) for s, a in enumerate(agents)] + [record(1, 0, 2.0, 1.25)]
    failed = {"x": {"env_id": ENV, "algo": "ppo", "config": 1, "seed": 1}}
    rows = summary_rows(records, failed)
    assert [(r["config"], r["seeds"], r["failed"]) for r in rows] == [(0, 4, 0), (1, 1, 1)]
    expected = stats.paired_ratio(agents, [1.25] * 4)
    row = rows[0]
    assert row["agent_rmse_mean"] == pytest.approx(np.mean(agents))
    assert row["agent_rmse_std"] == pytest.approx(np.std(agents, ddof=1))
    assert (row["ratio"], row["ratio_low"], row["ratio_high"]) == (expected.ratio, expected.low, expected.high)
    assert row["win_rate"] == 0.75 and row["reference"] == "fan_lambda_tuned" and row["params"] == '{"lr":0}'
    assert math.isnan(rows[1]["ratio_low"]) and rows[1]["ratio"] == pytest.approx(2.0 / 1.25)


# ----------------------------------------------------------------- end to end on Ray


def test_a_sweep_on_two_workers_ends_with_the_table_and_a_rerun_runs_nothing(ray_2cpu, tmp_path, capsys):
    """Two configurations × two seeds of 128 steps on the module's Ray (2 CPUs)."""
    path, out = sweep_file(tmp_path), tmp_path / "out"
    assert cli(["sweep", str(path), "--out", str(out), "--workers", "2"]) == 0
    text = capsys.readouterr().out
    assert "0 run(s) finished before, 4 to run" in text and "ratio [95 % CI]" in text
    names = sorted(p.stem for p in (out / "results").glob("*.json"))
    assert names == [f"MagBlend-v0-ppo-c{c}-s{s}" for c in (0, 1) for s in (0, 1)]
    for name in names:
        assert (out / "runs" / name / "best.safetensors").is_file()
        run = yaml.safe_load((out / "runs" / name / "run.yaml").read_text())
        assert run["seed"] == int(name[-1]) and run["hyperparams"]["learning_rate"] == [1.0e-4, 3.0e-4][int(name[-4])]
    summary = list(csv.DictReader(open(out / "summary.csv")))
    assert [(r["config"], r["seeds"], r["failed"]) for r in summary] == [("0", "2", "0"), ("1", "2", "0")]
    records = [json.loads((out / "results" / f"{n}.json").read_text()) for n in names[:2]]
    expected = stats.paired_ratio([r["agent_rmse"] for r in records], [r["reference_rmse"] for r in records])
    assert float(summary[0]["ratio"]) == pytest.approx(expected.ratio, abs=1e-4)
    before = {n: (out / "results" / f"{n}.json").read_text() for n in names}
    assert cli(["sweep", str(path), "--out", str(out)]) == 0
    assert "4 run(s) finished before, 0 to run" in capsys.readouterr().out
    assert {n: (out / "results" / f"{n}.json").read_text() for n in names} == before
    # a sweep that changes a stored run is refused
    changed = sweep_file(tmp_path, {"steps": 256}, name="changed.yaml")
    assert cli(["sweep", str(changed), "--out", str(out)]) == 2
    assert "had other settings; use another --out" in capsys.readouterr().err


def test_a_run_whose_worker_dies_is_retried_and_one_that_keeps_dying_is_named(ray_2cpu, tmp_path):
    """A lost worker: the run's process exits in the middle (``os._exit``); Tune starts the run again on a
    fresh worker (``retries`` times), where ``run_one`` picks up from its own files."""
    from magenv import scale

    def run_one(name: str) -> dict:  # a closure, so Ray ships it by value to the workers
        marker = tmp_path / f"{name}.started"
        if name == "always" or not marker.exists():
            marker.touch()
            os._exit(1)
        return {"value": 1.0, "name": name}

    ended = []
    results = scale.tune_runs(
        ["once", "always"], run_one, tmp_path / "out", workers=2, retries=1, on_done=lambda *a: ended.append(a)
    )
    assert results["once"]["value"] == 1.0
    assert isinstance(results["always"], str) and "always" not in {a[0] for a in ended if a[2] is None}
    assert sorted(a[0] for a in ended) == ["always", "once"]


@pytest.mark.slow
def test_an_interrupted_sweep_resumes_where_it_stopped(tmp_path):
    """Ctrl-C in the middle of a sweep (its own local Ray, in a subprocess), then the same command again:
    finished runs are kept, an interrupted one resumes from its checkpoint, and every run ends. About 90 s.

    Tune lets a running trial go on for up to 10 s after SIGINT before it kills the actor, so each run trains
    for about 30 s: one signalled at its first checkpoint is still training when it is killed."""
    steps = 16384
    path = sweep_file(tmp_path, {"steps": steps, "eval_every": 256, "params": {}, "seeds": "0:3"})
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "magenv.train.cli", "sweep", str(path), "--out", str(out), "--workers", "2"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    def progress():
        for state in (out / "runs").glob("*/state.json"):
            try:
                yield json.loads(state.read_text())["timesteps"]
            except ValueError:  # being replaced
                pass

    deadline = time.time() + 240
    while time.time() < deadline and not any(0 < t < steps for t in progress()):
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    log = proc.communicate(timeout=120)[0]
    assert proc.returncode == 130 and "interrupted; run the same command again to resume" in log, log
    finished_before = len(list((out / "results").glob("*.json")))
    assert finished_before < 3, log
    assert any(0 < t < steps for t in progress()), f"no run was stopped between its checkpoints\n{log}"
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=400)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert f"{finished_before} run(s) finished before, {3 - finished_before} to run" in done.stdout
    records = [json.loads(p.read_text()) for p in (out / "results").glob("*.json")]
    assert len(records) == 3 and all(r["timesteps"] == steps for r in records)
    assert any(0 < r["start_timesteps"] < steps for r in records), "no run resumed from its checkpoint"
