"""The agent shipped with magenv: ``--agent pretrained:magenv/MagBlend-v0``, listed by ``magenv agents``."""

from __future__ import annotations

import numpy as np
import pytest

from magenv import evaluation, registry
from magenv.agents.loading import RunError, load_agent, pretrained_agents
from magenv.train.cli import main

NAME = "pretrained:magenv/MagBlend-v0"


@pytest.mark.parametrize("env_id", ["magenv/MagBlend-v0", "magenv/MagKalman-v0", "magenv/MagConstraint-v0"])
def test_shipped_folder_is_small_and_pickle_free(env_id):
    folder = pretrained_agents()[env_id]
    files = {p.relative_to(folder).as_posix(): p.stat().st_size for p in folder.rglob("*") if p.is_file()}
    assert {"run.yaml", "best.safetensors", "card.md"} <= set(files)
    assert not [n for n in files if n.endswith((".zip", ".pkl", ".pt"))]
    assert sum(files.values()) < 1_000_000
    assert "held-out" in (folder / "card.md").read_text()


def test_pretrained_agent_acts_in_compare(make_kinematic_trial):
    agent = registry.make("agent:" + NAME)
    assert agent.name == "agent:" + NAME and agent.env_kwargs["features"] == "extended"
    run = evaluation.run_method(agent.name, agent, make_kinematic_trial(seed=3, duration=3.0, disturbance_ut=20.0))
    assert np.isfinite(run.score.total) and np.all((run.lam >= 0) & (run.lam <= 1))


def test_shipped_student_scores_as_when_it_was_trained(make_kinematic_trial):
    """The figures of the shipped MagBlend-v0 student on one trial, recorded when it was shipped (an ensemble of
    four DAgger iterations trained on the corrected sensor model): the student still loads and acts the same.
    The student's λ is float32 arithmetic through BLAS, whose kernels round differently on other CPUs (an AMD
    machine gives the λ sum 1e-8 apart), so the pins allow float32 rounding; other weights or inputs move them
    by orders of magnitude more."""
    agent = registry.make("agent:" + NAME)
    run = evaluation.run_method(agent.name, agent, make_kinematic_trial(seed=3, duration=4.0, disturbance_ut=40.0))
    assert run.score.total == pytest.approx(0.19725064989505714, rel=1e-6)
    assert float(np.sum(run.lam)) == pytest.approx(79.84507237715201, rel=1e-6)


def test_unknown_pretrained_env_names_the_shipped_ones():
    with pytest.raises(RunError, match="magenv/MagBlend-v0"):
        load_agent("pretrained:magenv/Nope-v0")


def test_magenv_agents_lists_it(capsys):
    assert main(["agents"]) == 0
    out = capsys.readouterr().out
    assert NAME in out and "pretrained:magenv/MagKalman-v0" in out


def test_pretrained_kalman_student_acts_in_its_env(make_kinematic_trial):
    agent = registry.make("agent:pretrained:magenv/MagKalman-v0")
    assert agent.env_id == "magenv/MagKalman-v0" and agent.env_kwargs["features"] == "extended"
    run = evaluation.run_method(agent.name, agent, make_kinematic_trial(seed=3, duration=3.0, disturbance_ut=20.0))
    assert np.isfinite(run.score.total) and np.all((run.trust[1:] >= 0) & (run.trust[1:] <= 1))
