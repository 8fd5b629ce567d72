"""``magenv.scale``: evaluation over Ray workers gives the serial numbers; the envs in RLlib (the example).

One local Ray of 2 CPUs serves the module (``ray_2cpu``); without Ray the
module's Ray tests skip, naming the extra.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from magenv import evaluation, registry, scale
from magenv.envs import BLEND_ID
from magenv.train.cli import main as cli

ROOT = Path(__file__).resolve().parents[1]
#: a policy, a tuned rule, a Kalman-trust policy, an estimator, and a two-link estimator that fails on gimbal trials
METHODS = ["mimu", "fan_lambda_tuned", "kf_gate", "th_triad", "cf_constraint"]
SPECS = [scale.TrialSpec("dynamic_clean", 0), scale.TrialSpec("dynamic_magnet", 1), scale.TrialSpec("dynamic_clean", 2)]


@pytest.fixture(scope="module")
def agent_dir(tmp_path_factory):
    """A trained agent (128 PPO steps): its run folder is rebuilt by name (``agent:RUN_DIR``) on the workers."""
    import yaml

    from magenv.agents.training import train

    tmp = tmp_path_factory.mktemp("agent")
    section = {"n_envs": 2, "n_steps": 64, "batch_size": 64, "n_epochs": 1, "env_kwargs": {"episode_seconds": 3.0}}
    (tmp / "ppo.yaml").write_text(yaml.safe_dump({BLEND_ID: section}))
    kw = dict(eval_every=128, eval_scenarios=("dynamic_clean",), eval_seeds=(5000,), progress_bar=False)
    return train(BLEND_ID, "ppo", 128, tmp / "run", config=str(tmp / "ppo.yaml"), **kw)


def test_tasks_keep_a_trials_methods_together_unless_trials_are_too_few():
    names = ["a", "b", "c", "d"]
    assert scale._tasks(10, names, 2) == [(i, names) for i in range(10)]  # enough trials: one task per trial
    tasks = scale._tasks(1, names, 2)  # one trial, two workers: its methods split in groups
    assert [t[0] for t in tasks] == [0, 0, 0, 0] and sum(len(t[1]) for t in tasks) == 4
    assert sorted(m for t in scale._tasks(3, names, 4) for m in t[1]) == sorted(names * 3)


def test_without_ray_the_error_names_the_extra(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(scale.RayMissing, match=r"pip install 'magenv\[scale\]'"):
        scale.require_ray("distributed evaluation")
    with pytest.raises(scale.RayMissing, match=r"needs RLlib.*pip install 'magenv\[rllib\]'"):
        scale.require_ray("the example", rllib=True)
    assert cli(["compare", "--seeds", "0", "--methods", "mimu", "--workers", "2", "--no-progress"]) == 2
    assert "magenv compare --workers/--address needs Ray Tune" in capsys.readouterr().err


def test_distributed_evaluation_gives_the_serial_numbers(ray_2cpu, agent_dir):
    names = [*METHODS, f"agent:{agent_dir}"]
    builds = {n: n for n in names}
    labels = [s.scenario for s in SPECS]
    trials = [s.make() for s in SPECS]
    serial = evaluation.evaluate({n: registry.make(n) for n in names}, trials, None, labels, keep_going=True)
    spread = scale.evaluate(builds, SPECS, labels, workers=2, keep_going=True, keep=(0,))
    assert [(r.method, r.label) for r in spread] == [(r.method, r.label) for r in serial]
    for a, b in zip(serial, spread):
        assert a.error == b.error
        if a.error is None:
            assert (a.score.total, a.score.heading, a.score.inclination) == (
                b.score.total,
                b.score.heading,
                b.score.inclination,
            )
    assert sum(r.error is not None for r in spread) == len(SPECS)  # cf_constraint on every gimbal trial
    assert "MissingChannelsError" in spread[METHODS.index("cf_constraint")].error
    # the kept trial comes back whole, its estimates bit for bit; the others as scores only
    for a, b in zip(serial[: len(names)], spread[: len(names)]):
        assert b.trial.name == a.trial.name
        if a.error is None:
            np.testing.assert_array_equal(a.q, b.q)
    assert all(r.trial is None and r.q is None for r in spread[len(names) :])
    assert _same_rows(evaluation.summarize(spread), evaluation.summarize(serial))


def _same_rows(a: list[dict], b: list[dict]) -> bool:
    """Rows equal, NaN equal to NaN."""
    same = lambda x, y: x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y))
    return len(a) == len(b) and all(r.keys() == s.keys() and all(same(r[k], s[k]) for k in r) for r, s in zip(a, b))


def test_compare_with_workers_writes_the_serial_table(ray_2cpu, tmp_path, capsys):
    args = ["compare", "--scenario", "dynamic_clean", "--seeds", "0:2", "--methods", "mimu,imu,cf_constraint"]
    args += ["--no-hold", "--every", "4", "--no-progress"]
    assert cli([*args, "--csv", str(tmp_path / "serial.csv")]) == 1  # 1: cf_constraint is n/a
    serial = capsys.readouterr().out
    assert cli([*args, "--csv", str(tmp_path / "spread.csv"), "--workers", "2", "--plot", str(tmp_path / "p.png")]) == 1
    spread = capsys.readouterr().out
    assert (tmp_path / "serial.csv").read_text() == (tmp_path / "spread.csv").read_text()
    rows = lambda text: [line for line in text.splitlines() if "│" in line or line.startswith("n/a")]
    assert rows(serial) == rows(spread) and len(rows(serial)) == 4
    assert (tmp_path / "p.png").stat().st_size > 0


def _example():
    spec = importlib.util.spec_from_file_location("rllib_ppo", ROOT / "examples" / "rllib_ppo.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_rllib_trains_ppo_on_magblend_from_its_gymnasium_id(ray_2cpu):
    """The README's recipe: RLlib's PPO (new API stack) on ``magenv:magenv/MagBlend-v0``, sampled by one remote
    env runner, two iterations of 256 env steps."""
    pytest.importorskip("ray.rllib", reason="RLlib is the extra magenv[rllib]: pip install 'magenv[rllib]'")
    lines = []
    history = _example().train(iterations=2, env_runners=1, batch=256, log=lines.append)
    assert [h["env_steps"] for h in history] == [256, 512] and len(lines) == 2
    # a 10 s episode of 320 decisions (256 Hz, one every 8 samples): 512 steps end one episode at least, and
    # its return is minus the summed per-decision error in degrees, negative and of the order of a degree a step
    last = history[-1]
    assert last["episodes"] >= 1 and -30 * 320 < last["return_mean"] < 0
