"""Seed lists on the command line and the use each seed range is for (``magenv.seeding``)."""

import pytest

from magenv.train.seeds import check_report_seeds, parse_seeds


def test_parse_seeds_forms():
    assert parse_seeds("3:6") == [3, 4, 5]
    assert parse_seeds("3,5,8") == [3, 5, 8]
    assert parse_seeds("7") == [7]


@pytest.mark.parametrize("text", ["5:3", "a", "-1", "0:20000", ""])
def test_parse_seeds_rejects(text):
    with pytest.raises(ValueError, match="bad seed list"):
        parse_seeds(text)


def test_report_seeds_are_held_out_and_validation_seeds_select():
    check_report_seeds([0, 4999], validation=False)
    check_report_seeds([5000, 9999], validation=True)
    with pytest.raises(SystemExit, match="held-out seeds below 5000"):
        check_report_seeds([4999, 5000], validation=False)
    with pytest.raises(SystemExit, match="validation seeds lie in 5000–9999"):
        check_report_seeds([4999, 5000], validation=True)
    with pytest.raises(SystemExit, match="validation seeds lie in 5000–9999"):
        check_report_seeds([10000], validation=True)


def test_every_shipped_tuned_rule_was_tuned_on_training_trials_only():
    """A shipped tuned file names the trials its CMA-ES objective ran on (``SCENARIO#SEED``); none may be a trial
    that reports or model selection score on (seeds below ``HELD_OUT_BELOW``)."""
    import json

    from magenv import registry
    from magenv.seeding import HELD_OUT_BELOW

    files = sorted(registry.packaged_tuned_dir().glob("*.json"))
    assert files
    for path in files:
        trials = json.loads(path.read_text())["trials"]
        assert trials, path.name
        seeds = [int(name.rsplit("#", 1)[1]) for name in trials]
        assert min(seeds) >= HELD_OUT_BELOW, (path.name, min(seeds))
