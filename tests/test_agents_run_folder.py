"""Training state that is always whole: the model saved after its update, faults injected at every kind of write,
during evaluation and during the update, the lock, checkpoints checked before any training, the rounded total.

The fault-injection test kills a short PPO run (three rollouts of 128 steps, evaluations at 256 and at the end)
at a point, runs the same call again, and requires what an uninterrupted run leaves: a consistent folder
(:func:`consistent`) at the same step count, with the same evaluations and no completed update lost. The default
suite takes one point of each kind in process (a crash is an exception nothing catches, as a kill leaves the
files); ``test_killed_at_every_point`` (slow) kills real ``magenv train`` processes with SIGKILL at every write.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from stable_baselines3 import PPO

from magenv.agents import run_folder, training, weights
from magenv.agents.loading import RunError, build_model, read_run
from magenv.agents.run_folder import RunFolder, digest
from magenv.agents.training import train
from tests.test_bad_input import ENV, write_config

MAGENV = [sys.executable, "-c", "import sys; from magenv.train.cli import main; sys.exit(main(sys.argv[1:]))"]
STEPS, EVERY = 384, 256  # three rollouts of 128 steps; evaluated at 256 and at 384 (the end)
EVALUATED = [256, 384]


def config(tmp_path: Path) -> Path:
    return write_config(tmp_path / "cfg.yaml")


def run_train(out: Path, cfg: Path | None, steps: int = STEPS, every: int = EVERY) -> Path:
    return train(
        ENV,
        "ppo",
        steps,
        out,
        config=cfg,
        eval_every=every,
        eval_scenarios=("dynamic_clean",),
        eval_seeds=(0,),
        progress_bar=False,
    )


def consistent(out: Path) -> dict:
    """The run folder's committed state, after checking that the folder is what it names: every file of the
    folder (but the lock and the TensorBoard logs) named with its digest, no left-over temporary file, the
    checkpoint, the evaluation record, the step checkpoints and the best model in agreement."""
    state = json.loads((out / "state.json").read_text())
    on_disk = {
        str(p.relative_to(out))
        for p in out.rglob("*")
        if p.is_file() and p.name not in ("state.json", ".lock") and "tb" not in p.relative_to(out).parts
    }
    assert on_disk == set(state["files"]), on_disk ^ set(state["files"])
    for name, sha in state["files"].items():
        assert digest(out / name) == sha, name
    meta = weights.read(out / "last.safetensors", "ppo")[1]
    assert meta["timesteps"] == state["timesteps"] and meta["state"]["evaluations"] == state["evaluations"]
    steps = [row[0] for row in state["evaluations"]]
    saved = sorted(p.name for p in (out / "checkpoints").iterdir()) if steps else []
    assert saved == sorted(f"step_{t}.safetensors" for t in steps)
    if steps:
        rows = [line.split(",") for line in (out / "evaluations.csv").read_text().splitlines()]
        assert [int(r[0]) for r in rows] == steps
        best = steps[int(np.argmin([row[1] for row in state["evaluations"]]))]
        assert state["best_timesteps"] == best and weights.read(out / "best.safetensors")[1]["timesteps"] == best
        assert digest(out / "best.safetensors") == digest(out / "checkpoints" / f"step_{best}.safetensors")
    return {**state, "n_updates": meta["n_updates"]}


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> dict:
    """The uninterrupted run's final state."""
    tmp = tmp_path_factory.mktemp("reference")
    return consistent(run_train(tmp / "run", config(tmp)))


def test_the_uninterrupted_run(reference):
    assert reference["timesteps"] == STEPS and [r[0] for r in reference["evaluations"]] == EVALUATED
    assert reference["n_updates"] == STEPS // 128  # one epoch per rollout


# ----------------------------------------------------------------- faults injected in process


class Crash(BaseException):
    """A kill, in process: nothing catches it, so no checkpoint is written on the way out."""


def crash_at(monkeypatch, module, name: str, at: int, before: bool = False) -> None:
    """Make ``module.name`` crash at its ``at``-th call: after it did its work (a file written, an update run), or
    ``before``."""
    original = getattr(module, name)
    calls = [0]

    def wrapped(*args, **kwargs):
        calls[0] += 1
        if before and calls[0] == at:
            raise Crash
        result = original(*args, **kwargs)
        if calls[0] == at:
            raise Crash
        return result

    monkeypatch.setattr(module, name, wrapped)


# (where, module attribute, call): the calls of a run are, in order, the first commit (run.yaml,
# last.safetensors, last_model.zip, state), the commit at 256 (step_256, evaluations.csv, best.safetensors,
# best_model.zip, last.safetensors, last_model.zip, state) and the commit at 384 (its files, then state).
FAULTS = {
    "after writing run.yaml": (run_folder, "_flush", 1),
    "after writing the first checkpoint": (run_folder, "_flush", 2),
    "after writing the first state": (run_folder, "_flush", 4),
    "after the first commit point": (run_folder, "_rename", 1),
    "after writing a step checkpoint": (run_folder, "_flush", 5),
    "after writing evaluations.csv": (run_folder, "_flush", 6),
    "after writing best.safetensors": (run_folder, "_flush", 7),
    "after writing a later state": (run_folder, "_flush", 11),
    "after a later commit point": (run_folder, "_rename", 5),
    "between the renames of a commit": (run_folder, "_rename", 6),
    "during an evaluation": (training, "run_policy_on_trials", 1),
    "during the last evaluation": (training, "run_policy_on_trials", 2),
    "during an update": (PPO, "train", 2),
}


@pytest.mark.parametrize("fault", list(FAULTS))
def test_a_crash_loses_no_completed_update(fault, reference, tmp_path, monkeypatch):
    module, name, at = FAULTS[fault]
    cfg, out = config(tmp_path), tmp_path / "run"
    crash_at(monkeypatch, module, name, at, before=name == "run_policy_on_trials")
    with pytest.raises(Crash):
        run_train(out, cfg)
    monkeypatch.undo()
    if (out / "state.json").is_file():  # what a kill left, once recovered, is a whole state
        RunFolder(out).recover()
        consistent(out)
    state = consistent(run_train(out, cfg))
    assert state["timesteps"] == reference["timesteps"] and state["n_updates"] == reference["n_updates"]
    assert [r[0] for r in state["evaluations"]] == EVALUATED


def test_the_same_call_again_reports_a_finished_run(reference, tmp_path, capsys):
    cfg, out = config(tmp_path), tmp_path / "run"
    run_train(out, cfg, steps=300)  # 384 in whole rollouts
    assert consistent(out)["timesteps"] == STEPS
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and "tb" not in p.parts}
    capsys.readouterr()
    run_train(out, cfg, steps=300)
    assert "already trained for 384 steps (asked 300, which ppo trains as 384)" in capsys.readouterr().out
    assert before == {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and "tb" not in p.parts}


# ----------------------------------------------------------------- Ctrl-C and SIGTERM


def signal_at(monkeypatch, module, name: str, at: int, signum=signal.SIGINT) -> None:
    """Send ``signum`` to this process inside the ``at``-th call of ``module.name``."""
    original = getattr(module, name)
    calls = [0]

    def wrapped(*args, **kwargs):
        calls[0] += 1
        if calls[0] == at:
            os.kill(os.getpid(), signum)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, wrapped)


@pytest.mark.parametrize(
    ("where", "module", "name", "at", "committed"),
    [
        # the second update finishes, then it is committed: 256 steps, not the 128 of the last commit
        ("in an update", PPO, "train", 2, 256),
        # the evaluation at 256 is dropped, the model after the update that ends there committed
        ("in an evaluation", training, "run_policy_on_trials", 1, 256),
        # the commit at 256 finishes first
        ("in a commit", run_folder, "_flush", 6, 256),
        # the rollout after 128 is dropped: the model after the first update committed, with the reward
        # statistics of the rollout's start
        ("in a rollout", training.Checkpoints, "after_update", 2, 128),
    ],
)
def test_an_interrupt_commits_the_last_complete_update(where, module, name, at, committed, tmp_path, monkeypatch):
    cfg, out = config(tmp_path), tmp_path / "run"
    at_start = {}
    if where == "in a rollout":  # a few steps into the rollout that begins with the at-th call
        original = training.Checkpoints.after_update
        calls = [0]

        def after_update(self):
            original(self)
            calls[0] += 1
            if calls[0] == at:
                rms = self.model.env.ret_rms
                at_start.update(mean=rms.mean.copy(), var=rms.var.copy(), count=rms.count)
                self.model.env.step_async = _interrupting(self.model.env.step_async)

        monkeypatch.setattr(training.Checkpoints, "after_update", after_update)
    else:
        signal_at(monkeypatch, module, name, at, signal.SIGTERM if where == "in a commit" else signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        run_train(out, cfg)
    monkeypatch.undo()
    state = consistent(out)
    tensors, meta = weights.read(out / "last.safetensors", "ppo")
    assert state["timesteps"] == committed and meta["n_updates"] == committed // 128
    for key, value in at_start.items():
        np.testing.assert_array_equal(tensors[f"vecnormalize/ret_rms/{key}"].numpy(), value)
    final = consistent(run_train(out, cfg))
    assert final["timesteps"] == STEPS and [r[0] for r in final["evaluations"]] == EVALUATED
    assert final["n_updates"] == STEPS // 128


def _interrupting(step_async):
    calls = [0]

    def wrapped(actions):
        calls[0] += 1
        if calls[0] == 5:  # a few steps into the rollout
            os.kill(os.getpid(), signal.SIGINT)
        return step_async(actions)

    return wrapped


# ----------------------------------------------------------------- the model saved is the model after its update


def _policy(path: Path) -> dict:
    return {k: v for k, v in weights.read(path)[0].items() if k.startswith("policy/")}


def test_each_evaluation_saves_the_model_after_its_update(tmp_path):
    cfg, out = config(tmp_path), tmp_path / "run"
    run_train(out, cfg, steps=128, every=64)  # one rollout: the model saved is not the initial policy
    run = read_run(out)
    initial = {f"policy/{k}": v for k, v in build_model(run, seed=run["seed"]).policy.state_dict().items()}
    saved = _policy(out / "checkpoints" / "step_128.safetensors")
    assert saved.keys() == initial.keys() and any(not torch.equal(saved[k], initial[k]) for k in saved)
    assert weights.read(out / "last.safetensors")[1]["n_updates"] == 1
    run_train(out, cfg, steps=256, every=64)  # resumed: the next update is in step_256
    later = _policy(out / "checkpoints" / "step_256.safetensors")
    assert any(not torch.equal(later[k], saved[k]) for k in saved)
    assert weights.read(out / "last.safetensors")[1]["n_updates"] == 2


def test_resume_aims_at_the_total_a_fresh_run_trains(tmp_path, monkeypatch, capsys):
    """--steps 200 trains 256 in whole rollouts of 128; a run stopped at 128 resumes to 256, not 'already
    trained' because 128 < 200 < 256 was compared unrounded."""
    cfg, out = config(tmp_path), tmp_path / "run"
    crash_at(monkeypatch, PPO, "train", 2)
    with pytest.raises(Crash):
        run_train(out, cfg, steps=200, every=128)
    monkeypatch.undo()
    assert json.loads((out / "state.json").read_text())["timesteps"] == 128
    run_train(out, cfg, steps=200, every=128)
    assert "training 256 steps in all, not 200" in capsys.readouterr().out
    assert consistent(out)["timesteps"] == 256


# ----------------------------------------------------------------- the lock


def test_a_second_run_into_a_locked_folder_stops_at_once(tmp_path):
    cfg, out = config(tmp_path), tmp_path / "run"
    with RunFolder(out).locked():
        with pytest.raises(RunError, match=rf"another run is writing to this folder \(process {os.getpid()}\)"):
            run_train(out, cfg)
    assert sorted(p.name for p in out.iterdir()) == [".lock"]  # nothing written
    run_train(out, cfg, steps=128, every=128)  # the lock is free once its holder is done
    assert consistent(out)["timesteps"] == 128


def test_two_processes_into_one_folder(tmp_path):
    """A second ``magenv train`` into a folder another one is training in exits 2 at once, naming it."""
    cfg, out = config(tmp_path), tmp_path / "run"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"import time; from magenv.agents.run_folder import RunFolder\n"
            f"with RunFolder({str(out)!r}).locked():\n    print('locked', flush=True); time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        args = ["train", "--config", str(cfg), "--out", str(out), "--steps", "128", "--no-progress"]
        second = subprocess.run([*MAGENV, *args], capture_output=True, text=True)
        assert second.returncode == 2, second.stderr
        assert f"another run is writing to this folder (process {holder.pid})" in second.stderr
    finally:
        holder.kill()
        holder.wait()


# ----------------------------------------------------------------- checkpoints checked on load


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("trained")
    return run_train(tmp / "run", config(tmp), steps=128, every=128)


def _tamper(run: Path, tensors=None, meta=None) -> None:
    """Rewrite ``last.safetensors`` with ``tensors`` / ``meta`` changed, and state.json to match it."""
    old_tensors, old_meta = weights.read(run / "last.safetensors")
    new_tensors = {**old_tensors, **(tensors or {})}
    new_meta = {k: v for k, v in {**old_meta, **(meta or {})}.items() if k != "format"}
    weights._write(run / "last.safetensors", {k: v for k, v in new_tensors.items() if v is not None}, new_meta)
    state = json.loads((run / "state.json").read_text())
    state["files"]["last.safetensors"] = digest(run / "last.safetensors")
    state["timesteps"] = new_meta["state"]["timesteps"]
    (run / "state.json").write_text(json.dumps(state))


def _meta(run: Path) -> dict:
    return weights.read(run / "last.safetensors")[1]


def _moment(run: Path, key: str) -> str:
    return next(k for k in weights.read(run / "last.safetensors")[0] if k.startswith("optim/") and k.endswith(key))


CORRUPTIONS = {
    "timesteps -5000": (
        lambda r: (None, {"timesteps": -5000, "state": {**_meta(r)["state"], "timesteps": -5000}}),
        "timesteps must be an integer ≥ 0, got -5000",
    ),
    "an exp_avg of another shape": (
        lambda r: ({_moment(r, "/exp_avg"): torch.zeros(3)}, None),
        "has shape (3,), expected",
    ),
    "a negative exp_avg_sq": (
        lambda r: ({(k := _moment(r, "/exp_avg_sq")): -weights.read(r / "last.safetensors")[0][k] - 1}, None),
        "holds negative entries",
    ),
    "a NaN weight": (
        lambda r: (
            {(k := "policy/action_net.weight"): weights.read(r / "last.safetensors")[0][k] * float("nan")},
            None,
        ),
        "policy/action_net.weight holds NaN or inf",
    ),
    "a moment of a parameter the model lacks": (
        lambda r: ({"optim/policy.optimizer/99/exp_avg": torch.zeros(2)}, None),
        "no parameter 99 in the optimizer",
    ),
    "n_updates -1": (lambda r: (None, {"n_updates": -1}), "n_updates must be an integer ≥ 0"),
    "best_timesteps after the end": (
        lambda r: (None, {"state": {**_meta(r)["state"], "best_timesteps": 10**6}}),
        "best_timesteps 1000000 is after the 128 steps trained",
    ),
}


@pytest.mark.parametrize("corruption", list(CORRUPTIONS))
def test_a_corrupt_checkpoint_is_refused_before_any_training(corruption, trained, tmp_path):
    import shutil

    make, message = CORRUPTIONS[corruption]
    run = Path(shutil.copytree(trained, tmp_path / "run"))
    tensors, meta = make(run)
    _tamper(run, tensors, meta)
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file() and "tb" not in p.parts and p.name != ".lock"}
    with pytest.raises(RunError, match=message.replace("(", r"\(").replace(")", r"\)")):
        run_train(run, None, steps=256, every=128)
    after = {p: p.read_bytes() for p in run.rglob("*") if p.is_file() and "tb" not in p.parts and p.name != ".lock"}
    assert before == after  # nothing trained, nothing written


def test_state_and_checkpoint_must_agree(trained, tmp_path):
    import shutil

    run = Path(shutil.copytree(trained, tmp_path / "run"))
    state = json.loads((run / "state.json").read_text())
    state["timesteps"] = 256  # the state claims more than the checkpoint holds
    (run / "state.json").write_text(json.dumps(state))
    with pytest.raises(RunError, match="holds 128 steps, state.json 256"):
        run_train(run, None, steps=512, every=128)


# ----------------------------------------------------------------- real processes, killed at every point


HARNESS = textwrap.dedent(
    """
    import os, signal, sys
    from magenv.agents import run_folder, training
    from stable_baselines3 import PPO
    from magenv.train.cli import main

    module, name, at, signum = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    target = {"run_folder": run_folder, "training": training, "PPO": PPO}[module]
    original, calls = getattr(target, name), [0]

    def wrapped(*args, **kwargs):
        calls[0] += 1
        if calls[0] == at and name == "run_policy_on_trials":
            os.kill(os.getpid(), signum)
        result = original(*args, **kwargs)
        if calls[0] == at:
            os.kill(os.getpid(), signum)
        return result

    setattr(target, name, wrapped)
    sys.exit(main(sys.argv[5:]))
    """
)


def _kill_points() -> list[tuple[str, str, int, int]]:
    """Every file write and rename of the three commits (the first: run.yaml, last.safetensors, last_model.zip,
    state; at 256 and at 384 up to six files and the state each), both evaluations, every update."""
    writes = 4 + 7 + 7
    points = [("run_folder", step, k, signal.SIGKILL) for step in ("_flush", "_rename") for k in range(1, writes + 1)]
    points += [("training", "run_policy_on_trials", k, s) for k in (1, 2) for s in (signal.SIGKILL, signal.SIGINT)]
    points += [("PPO", "train", k, signal.SIGKILL) for k in (1, 2, 3)]
    points += [("PPO", "train", 2, s) for s in (signal.SIGINT, signal.SIGTERM)]
    return points


@pytest.mark.slow
@pytest.mark.parametrize("point", _kill_points(), ids=lambda p: f"{p[1]}{p[2]}-{signal.Signals(p[3]).name}")
def test_killed_at_every_point(point, reference, tmp_path):
    """``magenv train`` killed (SIGKILL, or stopped by SIGINT / SIGTERM) at a write, an evaluation or an update,
    then run again with the same command: the folder ends as the uninterrupted run's."""
    cfg, out = config(tmp_path), tmp_path / "run"
    harness = tmp_path / "harness.py"
    harness.write_text(HARNESS)
    args = ["train", "--config", str(cfg), "--out", str(out), "--steps", str(STEPS), "--eval-every", str(EVERY)]
    args += ["--eval-scenarios", "dynamic_clean", "--eval-seeds", "0", "--no-progress"]
    subprocess.run([sys.executable, str(harness), *map(str, point), *args], capture_output=True, text=True)
    again = subprocess.run([*MAGENV, *args], capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    state = consistent(out)
    assert state["timesteps"] == reference["timesteps"] and state["n_updates"] == reference["n_updates"]
    assert [r[0] for r in state["evaluations"]] == EVALUATED
