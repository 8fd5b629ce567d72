"""studies/: the per-env tables of docs/results.md come from one engine (studies/study.py)."""

from __future__ import annotations

import numpy as np
import pytest

from studies import blend, constraint, kalman, qsf, vqf
from studies.study import RECORDINGS, main, parse, table

STUDIES = [blend.STUDY, kalman.STUDY, constraint.STUDY, qsf.STUDY, vqf.STUDY]


@pytest.mark.parametrize("study", STUDIES, ids=lambda s: s.env_id)
def test_every_study_names_registered_methods_and_its_shipped_agent(study):
    from magenv import registry
    from magenv.agents.loading import pretrained_agents

    names = set(registry.names())
    assert [m for m in [*study.rules(), study.oracle] if m not in names] == []
    assert study.env_id in pretrained_agents()
    assert parse(study, []).agent == [f"pretrained:{study.env_id}"]


def test_reported_figures_refuse_validation_seeds_and_recordings_where_they_cannot_run():
    with pytest.raises(SystemExit, match="held-out seeds below 5000"):
        parse(blend.STUDY, ["--seeds", "5000:5002"])
    with pytest.raises(SystemExit):
        parse(constraint.STUDY, ["--recordings"])
    assert parse(kalman.STUDY, ["--agent", "none"]).agent == []


def test_table_pairs_each_agent_with_the_reference_of_its_test_and_the_same_information_rule():
    per_trial = {
        "stationary_magnet": {
            "kf_model_tuned": [4.0, 6.0],
            "kf_adaptive_tuned": [2.0, 3.0],
            "kf_perp_tuned": [4.0, 6.0],
            "kf_still_tuned": [1.0, 1.5],
            "agent": [1.0, 1.5],
            "oracle_kalman": [0.5, 0.75],
        }
    }
    head, rule, row = table(kalman.STUDY, per_trial, ["pretrained:magenv/MagKalman-v0"])[1:]
    assert "agent / reference" in head and "agent / kf_still_tuned" in head and rule.startswith("|---")
    cells = row.split(" | ")
    assert cells[1] == "kf_adaptive_tuned" and cells[-1] == "0.67 |"  # (2.5 - 1.25) / (2.5 - 0.625)
    assert cells[8].startswith("0.500 [0.500, 0.500]") and cells[10].startswith("1.000")  # agent / rule, / still


def test_pooled_ratio_pairs_every_simulated_trial_with_its_own_tests_reference():
    per_trial = {
        "dynamic_magnet": {"kf_model_tuned": [2.0, 4.0], "agent": [1.0, 4.0]},
        "stationary_magnet": {"kf_adaptive_tuned": [1.0, 1.0], "kf_model_tuned": [9.0, 9.0], "agent": [2.0, 0.5]},
        RECORDINGS: {"kf_model_tuned": [1.0], "agent": [100.0]},  # not pooled
    }
    lines = table(kalman.STUDY, per_trial, ["pretrained:magenv/MagKalman-v0"])
    assert lines[-2].startswith("over all 4 trials of dynamic_magnet, stationary_magnet")
    assert lines[-1].startswith("- agent: 0.841 [")  # (0.5 · 1 · 2 · 0.5)^(1/4), not against kf_model_tuned
    assert table(kalman.STUDY, {"dynamic_magnet": per_trial["dynamic_magnet"]}, ["x"])[-1].startswith("| dynamic")


def test_a_short_study_runs_end_to_end(capsys):
    assert main(blend.STUDY, ["--seeds", "0", "--duration", "2", "--no-oracle", "--scenarios", "dynamic_magnet"]) == 0
    out = capsys.readouterr().out
    assert "| dynamic_magnet | fan_lambda_tuned |" in out and "trials cut to 2 s" in out and RECORDINGS == "recordings"


def test_the_real_vqf_table_groups_the_recordings_and_names_the_worst():
    from studies import vqf_real

    assert vqf_real.group_of("33_disturbed_attached_magnet_2cm") == "magnet"
    assert vqf_real.group_of("26_disturbed_phone_vibration_A") == "tapping"
    assert vqf_real.group_of("11_undisturbed_slow_translation_B") == "undisturbed"
    recs = ["02_undisturbed_a", "29_disturbed_stationary_magnet_b", "32_disturbed_attached_magnet_c"]
    scores = {
        "vqf": dict(zip(recs, [1.0, 2.0, 4.0])),
        "vqf_fan_lambda_tuned": dict(zip(recs, [1.0, 1.0, 2.0])),
        "agent": dict(zip(recs, [0.5, 1.0, 6.0])),
    }
    lines = vqf_real.table(scores, list(scores))
    row = next(line for line in lines if line.startswith("| `agent` |"))
    assert row.endswith("| 32 1.50 |")  # the worst recording: 6 / 4
    cells = row.split(" | ")
    assert cells[1].startswith("3.50 · 0.87 [") and cells[2] == "0.50 · 0.50"  # magnet: √(0.5·1.5); undisturbed
    assert any(line.startswith("agent / vqf_fan_lambda_tuned on the magnet recordings: 1.73") for line in lines)


def test_the_nested_choice_never_scores_a_recording_with_the_agent_chosen_on_it():
    from studies import vqf_real

    # a is better on r1 and r2, b by far on r3: on all three b wins; without r3, a does.
    scores = {
        "vqf": {"r1": 1.0, "r2": 1.0, "r3": 1.0},
        "a": {"r1": 0.5, "r2": 0.5, "r3": 2.0},
        "b": {"r1": 0.8, "r2": 0.8, "r3": 0.1},
    }
    held, picked = vqf_real.nested_selection(scores, ["a", "b"])
    assert picked == {"r1": "b", "r2": "b", "r3": "a"}
    assert held == {"r1": 0.8, "r2": 0.8, "r3": 2.0}  # r3 gets a's 2.0, not b's 0.1 that chose b
    assert vqf_real.choice(scores, ["a", "b"]) == "b"
    with pytest.raises(ValueError, match="no score of agent 'c'"):
        vqf_real.nested_selection(scores, ["a", "c"])
    with pytest.raises(ValueError, match="≥ 2 recordings"):
        vqf_real.nested_selection({"vqf": {"r1": 1.0}, "a": {"r1": 1.0}}, ["a"])


def test_recordings_needed_grows_with_the_spread_of_the_per_recording_ratios():
    from studies import vqf_real

    ratios = np.exp([0.2, -0.2, 0.2, -0.2])  # log ratios of SD 0.2309
    scores = {"vqf": dict.fromkeys("abcd", 1.0), "x": dict(zip("abcd", ratios)), "y": dict.fromkeys("abcd", 1.0)}
    sigma, n = vqf_real.recordings_needed(scores, "x", "y")
    assert sigma == pytest.approx(0.2309, abs=1e-4) and n == 19  # (1.96 · 0.2309 / ln(1/0.9))² = 18.2
    lines = vqf_real.power_lines(scores, ["x"], rule="y")
    assert lines[-1] == "- x / y: σ 0.23, 19 recordings"
    assert vqf_real.power_lines(scores, ["x"], rule="z") == []  # nothing to pair x with
