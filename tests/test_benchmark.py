"""magenv-bench v1 (``magenv.benchmark``) and ``magenv benchmark``: the suite's tasks, seeds and budget, the
normalised score, a user's callable scored in one command, bad agents refused before any work, the baselines'
table with its missing cells shown."""

from __future__ import annotations

import json
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml

from magenv import stats
from magenv.benchmark import suite
from magenv.seeding import HELD_OUT_BELOW, VALIDATION_START
from magenv.train import benchmark
from magenv.train.cli import main as cli
from magenv.train.seeds import REPORT_SEEDS, parse_seeds
from magenv.train.sweep_config import load_sweep

ROOT = Path(__file__).resolve().parents[1]
BENCH_CONFIGS = sorted((ROOT / "agents" / "configs" / "bench").glob("*.yaml"))


# ----------------------------------------------------------------- the suite


def test_the_suite_holds_the_issues_tasks():
    by_env = {}
    for t in suite.TASKS:
        by_env.setdefault(t.env.short, []).append(t.test)
    assert by_env == {
        "MagBlend-v0": ["dynamic_magnet", "stationary_magnet", "dynamic_clean"],
        "MagKalman-v0": ["dynamic_magnet", "stationary_magnet"],
        "MagConstraint-v0": ["constraint_test1", "constraint_test2", "constraint_test3"],
        "MagQSF-v0": ["handheld_texting", "handheld_swinging", "handheld_corridor", "handheld_free"],
        "MagVQF-v0": ["dynamic_magnet", "stationary_magnet", suite.RECORDINGS],
    }
    assert [t.name for t in suite.TASKS if not t.normalised] == ["MagVQF-v0/recordings"]


def test_every_rule_and_oracle_of_the_suite_is_a_method_and_every_test_a_scenario():
    from magenv import registry
    from magenv.scenarios import scenario_names

    names, scenarios = registry.names(), scenario_names()
    assert [t.name for t in suite.TASKS if t.rule not in names or (t.oracle and t.oracle not in names)] == []
    assert [t.name for t in suite.TASKS if t.test != suite.RECORDINGS and t.test not in scenarios] == []
    assert [e.short for e in suite.ENVS if not set(e.mixture) <= set(scenarios)] == []


def test_evaluation_seeds_are_held_out_and_unused_by_training_validation_and_the_projects_reports():
    seeds = set(suite.EVAL_SEEDS)
    assert max(seeds) < VALIDATION_START < HELD_OUT_BELOW
    assert not seeds & set(parse_seeds(REPORT_SEEDS))
    used = []  # every seed a shipped config names (training, validation)
    for path in (ROOT / "agents" / "configs").rglob("*.yaml"):
        text = path.read_text()
        used += [int(x) for x in __import__("re").findall(r"\b\d{4,5}\b", text) if 4000 <= int(x) < 4100]
    assert used == []


@pytest.mark.parametrize("path", BENCH_CONFIGS, ids=[p.stem for p in BENCH_CONFIGS])
def test_the_baseline_configs_train_every_env_on_its_mixture_at_the_budget(path):
    runs = load_sweep(path)
    assert {r.env_id for r in runs} == {e.env_id for e in suite.ENVS}
    assert {r.seed for r in runs} == set(range(suite.BASELINE_SEEDS))
    for r in runs:
        spec = suite.env_spec(r.env_id)
        if r.algo == "dagger":
            assert r.section["scenarios"] == list(spec.mixture)
            assert r.section["train_seed"] >= HELD_OUT_BELOW and r.section["val_seeds"][0] >= VALIDATION_START
        else:
            assert r.section["env_kwargs"]["scenario"].split(",") == list(spec.mixture)
            assert r.steps == spec.steps_at(r.section["env_kwargs"].get("decision_every", spec.decision_every))
            assert "pretrain" not in r.section  # from scratch
        # validation on the suite's tests (MagQSF-v0's 13-minute free walk left out), never on their seeds
        assert set(r.eval_scenarios) <= {t.test for t in suite.TASKS if t.env is spec}
        assert max(r.eval_seeds) < HELD_OUT_BELOW and min(r.eval_seeds) >= VALIDATION_START


def test_select_takes_tasks_envs_and_sim_and_names_what_matches_nothing():
    assert [t.name for t in suite.select("MagKalman-v0")] == [
        "MagKalman-v0/dynamic_magnet",
        "MagKalman-v0/stationary_magnet",
    ]
    assert len(suite.select("sim")) == len(suite.TASKS) - 1
    assert suite.select("MagBlend-v0/dynamic_clean,magenv/MagBlend-v0")[0].test == "dynamic_clean"
    with pytest.raises(ValueError, match="unknown task 'MagBlend-v0/nope'.*MagBlend-v0/dynamic_magnet"):
        suite.select("MagBlend-v0/nope")


# ----------------------------------------------------------------- the normalised score


def test_the_normalised_score_is_zero_for_the_rule_one_for_the_oracle_and_pairs_trials():
    rng = np.random.default_rng(0)
    rule = rng.uniform(1.0, 3.0, 30)
    oracle = rule * rng.uniform(0.3, 0.9, 30)
    assert stats.normalised_score(rule, rule, oracle).score == 0.0
    assert stats.normalised_score(oracle, rule, oracle).score == pytest.approx(1.0)
    half = (rule + oracle) / 2
    s = stats.normalised_score(half, rule, oracle)
    assert s.score == pytest.approx(0.5) and s.low < 0.5 < s.high
    assert s.worst == pytest.approx(min(s.per_unit))
    assert stats.normalised_score(half, rule, oracle).low == s.low  # same seed, same interval
    with pytest.raises(ValueError, match="not better than the reference"):
        stats.normalised_score(half, oracle, rule)
    with pytest.raises(ValueError, match="pair unit by unit"):
        stats.normalised_score(half[:3], rule, oracle)


# ----------------------------------------------------------------- the command


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    """A user's module on the path: ``bench_user:rule`` acts as fan_lambda_tuned in MagBlend-v0 only."""
    (tmp_path / "bench_user.py").write_text(
        textwrap.dedent(
            """
            from magenv import registry

            def rule(env_id):
                return registry.make("fan_lambda_tuned") if env_id == "magenv/MagBlend-v0" else None

            not_callable = 3
            """
        )
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "bench_user"
    sys.modules.pop("bench_user", None)


def test_a_users_callable_is_scored_in_one_command(tmp_path, user_module, capsys):
    out = tmp_path / "card"
    argv = ["benchmark", "--agent", f"{user_module}:rule", "--tasks", "MagBlend-v0/dynamic_clean"]
    assert cli([*argv, "--seeds", "0:3", "--duration", "8", "--out", str(out)]) == 0
    card = json.loads((out / "card.json").read_text())
    assert card["suite"] == suite.VERSION and not card["protocol"] and "instead of the suite's" in card["deviation"]
    (task,) = card["tasks"]
    # the callable is the rule itself: ratio 1 and normalised score 0 on every trial, the oracle's scores above
    assert task["ratio"]["value"] == pytest.approx(1.0) and task["normalised"]["value"] == pytest.approx(0.0)
    assert task["per_trial"]["agent"] == pytest.approx(task["per_trial"]["rule"])
    assert task["oracle_rmse"] < task["rule_rmse"]
    assert card["aggregates"]["oracle"]["iqm"][0] > 0.0 == pytest.approx(card["aggregates"]["agent"]["iqm"][0])
    assert (out / "profile.png").stat().st_size > 0
    assert "| MagBlend-v0/dynamic_clean | fan_lambda_tuned |" in (out / "card.md").read_text()


def test_the_recordings_track_is_skipped_saying_so_where_there_are_none(tmp_path, monkeypatch, capsys):
    (tmp_path / "vqf_user.py").write_text(
        "from magenv import registry\n\ndef rule(env_id):\n    return registry.make('vqf_fan_lambda_tuned')\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("MAGENV_BROAD_DIR", str(tmp_path / "empty"))
    (tmp_path / "empty").mkdir()
    out = tmp_path / "card"
    assert cli(["benchmark", "--agent", "vqf_user:rule", "--tasks", "MagVQF-v0/recordings", "--out", str(out)]) == 0
    card = json.loads((out / "card.json").read_text())
    assert card["tasks"] == [] and card["skipped"] == [
        {"task": "MagVQF-v0/recordings", "reason": "no recordings: the folder holds no *.hdf5 file"}
    ]
    assert "| MagVQF-v0/recordings | skipped: no recordings" in (out / "card.md").read_text()
    assert "MagVQF-v0/recordings: skipped (no recordings" in capsys.readouterr().out
    sys.modules.pop("vqf_user", None)


@pytest.mark.parametrize(
    "agent, message",
    [
        ("no_such_module_xyz:fn", "cannot import module 'no_such_module_xyz'"),
        ("bench_user:missing", "has no callable 'missing'"),
        ("bench_user:not_callable", "has no callable 'not_callable'"),
        ("pretrained:magenv/Nope-v0", "no pretrained agent for 'magenv/Nope-v0'"),
        ("no/such/run", "no such run folder"),
        ("no/such/best.safetensors", "not a .safetensors weights file"),
    ],
)
def test_a_bad_agent_is_named_before_any_work(tmp_path, user_module, capsys, agent, message):
    out = tmp_path / "card"
    assert cli(["benchmark", "--agent", agent, "--tasks", "MagBlend-v0/dynamic_clean", "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_bad_tasks_seeds_and_outputs_are_named_before_any_work(tmp_path, user_module, capsys):
    agent = ["benchmark", "--agent", f"{user_module}:rule"]
    assert cli([*agent, "--tasks", "MagBlend-v0/nope"]) == 2
    assert "unknown task 'MagBlend-v0/nope'" in capsys.readouterr().err
    assert cli([*agent, "--tasks", "MagKalman-v0", "--out", str(tmp_path / "o")]) == 2
    assert "returned None for every env" in capsys.readouterr().err
    assert cli([*agent, "--seeds", "5000:5002", "--out", str(tmp_path / "o")]) == 2
    assert "held-out seeds lie below 5000" in capsys.readouterr().err
    (tmp_path / "file").write_text("")
    assert cli([*agent, "--out", str(tmp_path / "file")]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err
    assert cli(["benchmark", "--sweep", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "not a magenv sweep folder" in capsys.readouterr().err


def test_a_summary_names_what_is_not_a_score_card(tmp_path, capsys):
    (tmp_path / "text.json").write_text("not json")
    (tmp_path / "other.json").write_text('{"tasks": [{"task": "x"}]}')
    for name, message in (("none.json", "no file"), ("text.json", "is not a JSON score card"),
                          ("other.json", "is not a score card of `magenv benchmark --agent`")):  # fmt: skip
        assert cli(["benchmark", "--summary", str(tmp_path / name)]) == 2
        err = capsys.readouterr().err
        assert message in err and name in err


# ----------------------------------------------------------------- the baselines' table


def test_the_aggregates_are_the_same_whatever_numpy_drew_before():
    """rliable draws its bootstrap from numpy's global generator: the aggregates seed it, and leave it as found."""
    from magenv.benchmark import score

    rng = np.random.default_rng(3)
    matrices = {"a": rng.normal(0.3, 1.0, (5, 4)), "b": rng.normal(-1.0, 1.0, (5, 4))}
    np.random.seed(1)  # noqa: NPY002
    first = score.aggregates(matrices, reps=200)
    after = np.random.rand()  # noqa: NPY002
    np.random.seed(2)  # noqa: NPY002
    assert score.aggregates(matrices, reps=200) == first
    np.random.seed(1)  # noqa: NPY002
    assert np.random.rand() == after  # noqa: NPY002  (the caller's generator is untouched)
    assert first["a"]["iqm"][1] < first["a"]["iqm"][0] < first["a"]["iqm"][2]


def test_the_baselines_table_shows_what_did_not_finish():
    rows = [
        {"env": suite.BLEND.env_id, "task": t, "method": m, "seed": s, "rmse": 1.0 + s, "normalised": 0.1 * s + n}
        for t in ("MagBlend-v0/dynamic_magnet", "MagBlend-v0/dynamic_clean")
        for m, n in (("PPO", 0.0), ("DAgger", 0.5))
        for s in (0, 1)
    ]
    names = [t.name for t in suite.TASKS if t.normalised]
    matrices, covered = benchmark.baseline_matrices(rows, names)
    assert matrices["DAgger"].shape == (2, 2) and covered["PPO"] == f"2 of {len(names)} tasks, seeds 0, 1"
    assert list(matrices) == ["DAgger", "PPO"]  # the rows' order does not reach the bootstrap
    assert list(benchmark.baseline_matrices(rows[::-1], names)[0]) == ["DAgger", "PPO"]
    records = [
        {"run": {"env_id": suite.BLEND.env_id, "algo": "ppo"}, "train_s": 600.0, "eval_s": 60.0},
        {"run": {"env_id": suite.BLEND.env_id, "algo": "dagger"}, "train_s": 9.0, "eval_s": 1.0,
         "train_cpu_s": 1140.0, "eval_cpu_s": 60.0},
    ] * 2  # fmt: skip
    page = benchmark.index_markdown(rows, records, 100, {}, covered)
    assert "**4 of 100 runs finished and scored**: the table is incomplete" in page
    assert "| MagBlend-v0/dynamic_magnet | 0.05 (1.50°) n = 2 | – | – | 0.55 (1.50°) n = 2 |" in page
    assert "| MagKalman-v0/dynamic_magnet | – | – | – | – |" in page
    # minutes per run: CPU where recorded, else wall (*); 5 seeds × (11 + 20) min = 2.6 CPU-hours
    assert (
        "| MagBlend-v0 | 11* | – | – | 20 |" in page
        and "The 2 of 20 (env, method) cells measured would take 2.6" in page
    )
    for t in suite.TASKS:
        assert f"| {t.name} | {', '.join(t.env.mixture)} | `{t.rule}` |" in page


def test_runs_not_yet_scored_are_named_and_a_bad_kept_score_is_scored_again(tmp_path):
    records = [{"name": n, "run": {"env_id": suite.BLEND.env_id, "algo": "ppo"}, "train_s": 60.0, "eval_s": 6.0}
               for n in ("run-a", "run-b")]  # fmt: skip
    page = benchmark.index_markdown([], records[:1], 100, {}, {}, unscored=records[1:])
    assert "**2 of 100 runs finished, 1 of them scored** (not yet scored: run-b)" in page

    class Refs:
        key = "k"

    assert benchmark.kept_rows(tmp_path, records[0], Refs()) is None  # none kept
    keep, stamp = benchmark._kept(tmp_path, records[0])
    keep.parent.mkdir()
    keep.write_text('{"stamp": "')  # a half-written file from an older version
    assert benchmark.kept_rows(tmp_path, records[0], Refs()) is None
    keep.write_text(json.dumps({"stamp": stamp, "suite": suite.VERSION, "refs": "k", "rows": [{"x": 1}]}))
    assert benchmark.kept_rows(tmp_path, records[0], Refs()) == [{"x": 1}]
    Refs.key = "other"  # other references (another code version): scored again
    assert benchmark.kept_rows(tmp_path, records[0], Refs()) is None


def test_a_run_is_scored_only_on_the_tasks_it_has_no_kept_rows_for(tmp_path, monkeypatch):
    """A task skipped before (the recordings track without recordings) is scored once alone, then kept."""
    from types import SimpleNamespace

    import magenv.agents.loading

    env_id = suite.VQF.env_id
    tasks = [t for t in suite.TASKS if t.env_id == env_id]
    record = {"name": "run-v", "run_dir": "nowhere", "run": {"env_id": env_id, "algo": "ppo", "seed": 3}}

    class Refs:
        key = "k"

    keep, stamp = benchmark._kept(tmp_path, record)
    keep.parent.mkdir()
    first = [{"task": t.name, "rmse": 1.0} for t in tasks[:-1]]
    keep.write_text(json.dumps({"stamp": stamp, "suite": suite.VERSION, "refs": "k", "rows": first}))
    asked = []

    def score_policy(policy, todo, seeds, duration, refs, log):
        asked.append([t.name for t in todo])
        return [SimpleNamespace(task=t.name, agent=[2.0], normalised=None) for t in todo], []

    monkeypatch.setattr(benchmark, "score_policy", score_policy)
    monkeypatch.setattr(magenv.agents.loading, "load_agent", lambda run_dir: "policy")
    rows = benchmark._run_scores(tmp_path, record, list(suite.TASKS), Refs())
    assert asked == [[tasks[-1].name]] and [r["task"] for r in rows] == [t.name for t in tasks]
    assert rows[-1]["rmse"] == 2.0 and rows[-1]["seed"] == 3 and rows[0] == first[0]
    assert benchmark.kept_rows(tmp_path, record, Refs()) == rows
    assert benchmark._run_scores(tmp_path, record, list(suite.TASKS), Refs()) == rows and len(asked) == 1


def test_scored_only_goes_with_sweep(capsys):
    assert cli(["benchmark", "--summary", "x.json", "--scored-only"]) == 2
    assert "--scored-only and --rows go with --sweep" in capsys.readouterr().err


def test_an_earlier_table_reads_back_and_fills_the_runs_the_sweeps_lack(tmp_path):
    """A table finished on another machine: the earlier baselines.csv's runs join those scored now; a run in both
    is the sweep's."""
    rows = [
        {"env": suite.BLEND.env_id, "task": "MagBlend-v0/dynamic_magnet", "method": m, "seed": s, "rmse": 1.5 + s,
         "normalised": None if m == "SAC" else 0.25 * s, "per_trial": None}
        for m in ("PPO", "SAC") for s in (0, 1)
    ]  # fmt: skip
    path = benchmark.baselines_csv(rows, tmp_path / "baselines.csv")
    assert benchmark.read_rows(path) == sorted(rows, key=lambda r: (r["method"], r["seed"]))
    page = benchmark.index_markdown(rows, [], 100, {}, {}, n_earlier=4)
    assert "**4 of 100 runs finished and scored** (4 of them read from an earlier table" in page
    assert "timed here (not the runs read from the earlier table)" not in page  # no run timed here: no cost table


@pytest.mark.parametrize(
    "text, message",
    [
        ("env,task\n", "is not a baselines.csv"),
        (",".join(benchmark.CSV_HEADER) + "\nmagenv/MagBlend-v0,MagBlend-v0/dynamic_magnet,PPO,x,1,0\n", "line 2"),
        (",".join(benchmark.CSV_HEADER) + "\nmagenv/MagBlend-v0,MagBlend-v0/nowhere,PPO,0,1,0\n", "not a task"),
        (",".join(benchmark.CSV_HEADER) + "\nmagenv/MagBlend-v0,MagBlend-v0/dynamic_magnet,PPO,0,nan,0\n", "finite"),
        (
            ",".join(benchmark.CSV_HEADER) + "\n" + "magenv/MagBlend-v0,MagBlend-v0/dynamic_clean,SAC,0,1,\n" * 2,
            "twice",
        ),
    ],
)
def test_a_bad_earlier_table_is_named_before_any_work(tmp_path, capsys, text, message):
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "sweep.json").write_text('{"runs": {}}')
    (tmp_path / "old.csv").write_text(text)
    args = ["benchmark", "--sweep", str(tmp_path / "runs"), "--out", str(tmp_path / "out")]
    assert cli([*args, "--rows", str(tmp_path / "old.csv")]) == 2
    assert message in capsys.readouterr().err and not (tmp_path / "out").exists()


def test_the_baseline_configs_are_what_train_sh_runs():
    script = (ROOT / "agents" / "configs" / "bench" / "train.sh").read_text()
    algos = yaml.safe_load("[" + script.split("for algo in ")[1].split(";")[0].replace(" ", ", ") + "]")
    assert sorted(algos) == sorted(p.stem for p in BENCH_CONFIGS) == sorted(benchmark.ALGO_LABELS)


def test_train_sh_trains_every_seed_of_every_method_then_scores_the_table(tmp_path):
    """One command reproduces the table: 5 seeds × 4 methods of ``magenv sweep``, then ``magenv benchmark``."""
    import subprocess

    log, fake = tmp_path / "calls.txt", tmp_path / "magenv"
    fake.write_text(f'#!/usr/bin/env bash\necho "$*" >> {log}\n')
    fake.chmod(0o755)
    script = ROOT / "agents" / "configs" / "bench" / "train.sh"
    env = {"PATH": "/usr/bin:/bin", "MAGENV": str(fake)}
    subprocess.run(["bash", str(script), str(tmp_path / "runs"), "1"], env=env, check=True, timeout=60)
    calls = log.read_text().splitlines()
    sweeps = [c.split() for c in calls[:-1]]
    assert len(sweeps) == 5 * 4 and all(c[0] == "sweep" and c[-4:-1] == ["--workers", "1", "--seeds"] for c in sweeps)
    assert sorted((Path(c[1]).stem, c[-1]) for c in sweeps) == sorted(
        (algo, str(seed)) for algo in benchmark.ALGO_LABELS for seed in range(suite.BASELINE_SEEDS)
    )
    runs = tmp_path / "runs"
    assert calls[-1] == f"benchmark --sweep {runs} --out {runs}/table"


def test_a_weights_file_acts_as_its_run_folders_model(tmp_path):
    from magenv.agents.loading import RunError, load_agent, load_weights_file
    from magenv.agents.training import train

    env_id = suite.BLEND.env_id
    config = tmp_path / "ppo.yaml"
    section = {"n_envs": 2, "n_steps": 64, "batch_size": 64, "n_epochs": 1, "env_kwargs": {"episode_seconds": 3.0}}
    config.write_text(yaml.safe_dump({env_id: section}))
    run = train(env_id, "ppo", 128, tmp_path / "run", config=str(config), eval_every=128,
                eval_scenarios=["dynamic_clean"], eval_seeds=[5000], progress_bar=False)  # fmt: skip
    (step,) = sorted((run / "checkpoints").glob("step_*.safetensors"))
    from_file, from_folder = load_weights_file(step), load_agent(run, which="last")
    assert from_file.env_id == env_id and from_file.which == step.stem
    obs = np.random.default_rng(0).uniform(-1, 1, (20, 13)).astype(np.float32)
    assert np.array_equal([from_file(o) for o in obs], [from_folder(o) for o in obs])
    (tmp_path / "loose.safetensors").write_bytes(step.read_bytes())  # no run.yaml beside it
    with pytest.raises(RunError, match="not a magenv run folder"):
        load_weights_file(tmp_path / "loose.safetensors")
