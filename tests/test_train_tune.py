"""magenv tune: CMA-ES over a rule's parameters, saved and picked up by the registry."""

import json

import pytest

from magenv import registry
from magenv.baselines.tuning import _to_params, _to_unit, tune_rule
from magenv.scenarios import make_trial
from magenv.train.cli import main as cli


def test_unit_mapping_round_trips_linear_and_log_bounds():
    bounds = {"a": (0.0, 1.0), "b": (0.1, 90.0)}  # b spans > a decade: log scale
    params = {"a": 0.25, "b": 3.0}
    assert _to_params(_to_unit(params, bounds), bounds) == pytest.approx(params)
    assert _to_params([0.5, 0.5], bounds)["b"] == pytest.approx(3.0)  # geometric midpoint of 0.1…90


@pytest.mark.parametrize("rule", ["threshold", "constant"])  # two parameters (CMA-ES) and one (scalar search)
def test_tuning_improves_on_the_training_trials_and_registers(tmp_path, monkeypatch, rule):
    trials = [make_trial("dynamic_magnet", 10_000, duration=10.0)]
    record = tune_rule(rule, registry.rule_class(rule), trials, iterations=3, popsize=4, progress=False)
    assert set(record["params"]) == set(registry.rule_class(rule).PARAM_BOUNDS)
    assert record["objective_deg"] <= record["published_objective_deg"]
    monkeypatch.setenv(registry.DATA_DIR_ENV, str(tmp_path))
    registry.user_tuned_dir().mkdir(parents=True)
    (registry.user_tuned_dir() / f"{rule}.json").write_text(json.dumps(record))
    tuned = registry.make(f"{rule}_tuned")
    assert tuned.params == pytest.approx(record["params"])


def test_held_out_seeds_are_refused(capsys):
    assert cli(["tune", "--rule", "threshold", "--seeds", "0:3"]) == 2
    assert "held out for evaluation" in capsys.readouterr().err
    assert cli(["tune", "--rule", "nope", "--seeds", "10000:10001", "--scenarios", "dynamic_clean"]) == 2
    assert "unknown rule 'nope'" in capsys.readouterr().err


def test_tuning_starts_from_given_parameters_and_never_returns_worse():
    trials = [make_trial("dynamic_magnet", 10_000, duration=10.0)]
    cls = registry.rule_class("threshold")
    record = tune_rule("threshold", cls, trials, iterations=2, popsize=4, progress=False, start={"norm_th": 0.5})
    assert record["start_params"] == {**cls().params, "norm_th": 0.5}
    assert record["objective_deg"] <= min(record["start_objective_deg"], record["published_objective_deg"])
    with pytest.raises(ValueError, match="no parameter"):
        tune_rule("threshold", cls, trials, iterations=2, popsize=4, progress=False, start={"k_max": 0.5})


def test_start_from_needs_shared_tuned_parameters(capsys):
    args = ["tune", "--rule", "threshold", "--seeds", "10000:10001", "--scenarios", "dynamic_clean"]
    assert cli([*args, "--start-from", "kf_perp"]) == 2
    assert "shares no parameter" in capsys.readouterr().err
