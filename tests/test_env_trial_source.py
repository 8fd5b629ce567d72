"""Where an env's trials come from (``magenv.envs.common.TrialSource``): any world, or one world only."""

from __future__ import annotations

import numpy as np
import pytest

from magenv import scenarios
from magenv.envs.common import TrialSource, trial_source
from magenv.filters.constraint import MissingChannelsError, require_two_link
from tests.conftest import kinematic_trial


def test_names_of_any_world_and_recordings():
    assert trial_source("dynamic_clean, constraint_test1") == ("scenario", ["dynamic_clean", "constraint_test1"])
    assert trial_source("recording:a.hdf5") == ("recording", "a.hdf5")
    with pytest.raises(ValueError, match="unknown scenario\\(s\\) 'nope'; known scenarios: stationary_magnet"):
        trial_source("dynamic_clean,nope")


def test_one_world_names_its_scenarios_and_checks_trials():
    assert trial_source("constraint_random", world="twolink") == ("scenario", ["constraint_random"])
    known = ", ".join(scenarios.scenario_names("twolink"))
    for bad in ("random", "recording:a.hdf5"):
        with pytest.raises(
            ValueError, match=f"unknown two-link scenario\\(s\\) '{bad}'; known two-link scenarios: {known} "
        ):
            trial_source(bad, world="twolink")
    with pytest.raises(MissingChannelsError, match="gyr_j"):
        trial_source([kinematic_trial()], world="twolink", require=require_two_link)
    with pytest.raises(TypeError, match="'twolink' world"):
        trial_source(3, world="twolink")


def test_a_world_source_draws_that_worlds_trials():
    source = TrialSource("constraint_test1", {"duration": 4.0}, world="twolink", require=require_two_link)
    trial = source.draw(np.random.default_rng(0))
    assert trial.meta["scenario"] == "constraint_test1" and "q_j" in trial.extra
