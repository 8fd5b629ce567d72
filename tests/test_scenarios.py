"""Named scenarios: API, determinism, physics of each protocol, HDF5 round trip, CLI."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from magenv import quaternion as quat
from magenv import scenarios
from magenv.sim.sensors import SensorConfig
from magenv.trial import META_SCENARIO, META_SEED, Trial

SHORT = dict(duration=12.0)
# The gimbal's own scenarios (the other worlds have their own tests).
GIMBAL = scenarios.scenario_names("gimbal")


def test_scenario_names_and_configs():
    names = scenarios.scenario_names()
    assert {"stationary_magnet", "dynamic_clean", "dynamic_magnet", "random"} <= set(names)
    for name in names:
        cfg = scenarios.get_scenario(name)
        assert dataclasses.is_dataclass(cfg)
        with pytest.raises(dataclasses.FrozenInstanceError):
            cfg.duration = 1.0


def test_unknown_scenario_lists_known_names():
    with pytest.raises(ValueError, match="unknown scenario 'nope'.*dynamic_magnet"):
        scenarios.make_trial("nope", 0)
    with pytest.raises(ValueError, match="stationary_magnet"):
        scenarios.get_scenario("Dynamic_Magnet")


def test_registry_lists_every_worlds_scenarios():
    names = scenarios.scenario_names()
    assert list(scenarios.WORLDS) == ["gimbal", "twolink", "handheld", "board"]
    assert names == [n for world in scenarios.WORLDS.values() for n in world.names()]
    assert len(set(names)) == len(names)
    assert {"dynamic_magnet", "constraint_test2", "handheld_texting"} <= set(names)
    for world in scenarios.WORLDS.values():
        assert scenarios.scenario_names(world.name) == world.names() != []
        for name in world.names():
            assert scenarios.world_of(name) == world.name
            assert scenarios.get_scenario(name) is world.get(name)


@pytest.mark.parametrize("name", ["dynamic_clean", "constraint_test1", "handheld_texting"])
def test_every_world_writes_the_trial_meta_keys(name):
    tr = scenarios.make_trial(name, 3, duration=4.0)
    assert tr.name == f"{name}#3"
    assert tr.meta[META_SCENARIO] == name and tr.meta[META_SEED] == 3
    assert json.loads(json.dumps(tr.meta)) == tr.meta  # plain JSON types
    assert tr.meta["config"]["duration"] == 4.0


def test_unknown_names_list_the_known_ones():
    with pytest.raises(
        ValueError,
        match="unknown scenario 'nope'; known scenarios: stationary_magnet, .*constraint_test1, .*handheld_random",
    ):
        scenarios.world_of("nope")
    with pytest.raises(ValueError, match="unknown world 'moon'; known worlds: gimbal, twolink, handheld, board"):
        scenarios.scenario_names("moon")
    with pytest.raises(ValueError, match="unknown two-link scenario 'dynamic_magnet'; known: constraint_test1, "):
        scenarios.WORLDS["twolink"].make_trial("dynamic_magnet", 0)


@pytest.mark.parametrize(
    "overrides, match",
    [
        (dict(durration=5.0), "durration"),
        (dict(duration=-1.0), "duration"),
        (dict(rate="fast"), "rate"),
        (dict(field_dip=120.0), "field_dip"),
        (dict(mag_noise_ut=-0.1), "mag_noise_ut"),
        (dict(rates_dps=(40.0, 70.0)), "rates_dps"),
    ],
)
def test_bad_overrides_are_named(overrides, match):
    with pytest.raises(ValueError, match=match):
        scenarios.make_trial("dynamic_magnet", 0, **overrides)


@pytest.mark.parametrize("seed", [-1, 1.5, "3", True])
def test_bad_seed(seed):
    with pytest.raises(ValueError, match="seed"):
        scenarios.make_trial("dynamic_clean", seed, duration=2.0)


@pytest.mark.parametrize("name", GIMBAL)
def test_same_seed_same_trial_bit_for_bit(name):
    a = scenarios.make_trial(name, 5, **SHORT)
    scenarios.make_trial(name, 6, **SHORT)  # another trial in between must not matter
    b = scenarios.make_trial(name, 5, **SHORT)
    for key in ("gyr", "acc", "mag", "q_true"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
    for key in a.truth:
        np.testing.assert_array_equal(a.truth[key], b.truth[key], err_msg=key)
    assert a.meta == b.meta
    c = scenarios.make_trial(name, 7, **SHORT)
    assert not np.array_equal(a.gyr, c.gyr)


@pytest.mark.parametrize("name", GIMBAL)
def test_trial_is_complete_and_consistent(name):
    tr = scenarios.make_trial(name, 1, **SHORT)
    assert tr.name == f"{name}#1"
    assert tr.rate == 256.0 and tr.n == 12 * 256
    assert tr.meta["scenario"] == name and tr.meta["seed"] == 1
    assert set(tr.truth) >= {"mag_disturbance", "stationary", "magnet_distance"}
    assert tr.truth["mag_disturbance"].shape == (tr.n, 3)
    assert tr.truth["stationary"].dtype == bool
    np.testing.assert_allclose(np.linalg.norm(tr.q_true, axis=1), 1.0, atol=1e-12)
    assert tr.score_mask.all()
    # Measured field ≈ Earth field rotated into the sensor frame + the magnet's field.
    expect = quat.rotate_inv(tr.q_true, np.broadcast_to(quat.earth_field(tr.field_norm, tr.field_dip), (tr.n, 3)))
    expect = expect + tr.truth["mag_disturbance"]
    lag = tr.meta["config"]["sensor"]["mag_lag_samples"]
    resid = np.linalg.norm(tr.mag[lag:] - expect[:-lag], axis=1)
    # Residual = noise + residual iron + held samples; larger only where the field changes fast.
    assert np.median(resid) < 2.0 + 0.03 * np.median(np.linalg.norm(expect, axis=1))


def test_accelerometer_norm_is_g_at_rest_and_stationary_truth():
    tr = scenarios.make_trial("dynamic_clean", 2, duration=30.0)
    st = tr.truth["stationary"]
    assert 0.2 < st.mean() < 0.9  # protocol 2: moves with pauses
    acc_norm = np.linalg.norm(tr.acc[st], axis=1)
    assert abs(np.mean(acc_norm) - 9.81) < 0.05  # bias ≤ ~0.05 m/s², noise averages out
    assert np.rad2deg(np.abs(tr.gyr[~st]).max()) > 5.0


def test_dynamic_magnet_field_passes_twice_earth_field():
    tr = scenarios.make_trial("dynamic_magnet", 0, duration=20.0)
    norm = np.linalg.norm(tr.mag, axis=1)
    assert norm.max() > 2 * tr.field_norm
    # The disturbance comes and goes (the magnet reciprocates): the field also
    # returns near m0 while moving.
    moving = ~tr.truth["stationary"]
    assert np.min(np.abs(norm[moving] - tr.field_norm)) < 5.0
    slide = tr.truth["magnet_slide"]
    assert np.ptp(slide) > 0.09  # travels (almost) the whole 10 cm tube
    # Protocol 3 rates: frame X at ~360 °/s dominates the gyro norm.
    rate = np.rad2deg(np.linalg.norm(tr.gyr[moving], axis=1))
    assert 300 < np.median(rate) < 450


def test_stationary_magnet_field_rises_as_the_magnet_approaches():
    tr = scenarios.make_trial("stationary_magnet", 0, duration=40.0)
    assert tr.truth["stationary"].all()
    d = tr.truth["magnet_distance"]
    dist_norm = np.linalg.norm(tr.truth["mag_disturbance"], axis=1)
    assert d.min() == pytest.approx(0.10, abs=0.01) and d.max() == pytest.approx(0.70, abs=0.01)
    # Disturbance falls with distance (a dipole: ∝ d⁻³): rank correlation strongly negative.
    rank = lambda x: np.argsort(np.argsort(x))
    assert np.corrcoef(rank(d), rank(dist_norm))[0, 1] < -0.9
    near, far = d < 0.12, d > 0.6
    assert dist_norm[near].mean() > 20.0  # tens of µT at 10 cm (0.35 A·m²: ~35–70 µT)
    assert dist_norm[far].mean() < 0.5
    norm = np.linalg.norm(tr.mag, axis=1)
    assert norm[near].mean() > norm[far].mean() + 20.0


def test_no_magnet_means_no_disturbance():
    tr = scenarios.make_trial("dynamic_clean", 0, **SHORT)
    assert np.all(tr.truth["mag_disturbance"] == 0.0)
    assert np.all(np.isinf(tr.truth["magnet_distance"]))


def test_overrides_change_only_what_they_name():
    a = scenarios.make_trial("random", 3, **SHORT)
    b = scenarios.make_trial("random", 3, mag_noise_ut=4 * SensorConfig().mag_noise_ut, **SHORT)
    np.testing.assert_array_equal(a.q_true, b.q_true)  # motion stream unchanged
    assert np.std(np.diff(b.mag[:256], axis=0)) > np.std(np.diff(a.mag[:256], axis=0))
    c = scenarios.make_trial("dynamic_clean", 0, field_norm=44.5, field_dip=69.0, **SHORT)
    assert (c.field_norm, c.field_dip) == (44.5, 69.0)
    assert c.meta["config"]["field_dip"] == 69.0


def test_random_family_varies_field_magnet_and_noise():
    trials = [scenarios.make_trial("random", s, duration=8.0) for s in range(12)]
    kinds = {t.meta["magnet"] for t in trials}
    assert kinds == {"none", "tube", "hand"}
    norms = [t.field_norm for t in trials]
    assert min(norms) >= 25.0 and max(norms) <= 65.0 and np.ptp(norms) > 10
    assert len({t.meta["noise_scale"] for t in trials}) == 12


def test_hdf5_round_trip(tmp_path):
    tr = scenarios.make_trial("dynamic_magnet", 2, duration=5.0)
    back = Trial.load(tr.save(tmp_path / "t.h5"))
    for key in ("gyr", "acc", "mag", "q_true", "score_mask"):
        np.testing.assert_array_equal(getattr(back, key), getattr(tr, key))
    for key in tr.truth:
        np.testing.assert_array_equal(back.truth[key], tr.truth[key])
    assert back.meta == tr.meta and back.name == tr.name and back.field_dip == tr.field_dip


def test_no_mujoco_instability_short_runs():
    # Stiff parts: a ~3 g magnet hitting its end stops on a gimbal at 360 °/s.
    # simulate_gimbal raises SimulationError on any MuJoCo warning or NaN.
    for name in GIMBAL:
        for seed in range(3):
            scenarios.make_trial(name, seed, duration=10.0)


@pytest.mark.slow
def test_no_mujoco_instability_many_seeds_full_length():
    for name in GIMBAL:
        for seed in range(25):
            tr = scenarios.make_trial(name, seed)
            assert np.all(np.isfinite(tr.mag))


def test_cli_simulate_and_plot(tmp_path):
    from magenv.train.cli import main

    out = tmp_path / "trial.h5"
    assert (
        main(["simulate", "--scenario", "dynamic_magnet", "--seed", "1", "--set", "duration=4", "--out", str(out)]) == 0
    )
    tr = Trial.load(out)
    assert tr.name == "dynamic_magnet#1" and tr.n == 4 * 256
    png = tmp_path / "trial.png"
    assert main(["plot", str(out), "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # User errors: exit status 2 and a message, no traceback.
    assert main(["simulate", "--scenario", "nope", "--out", str(out)]) == 2
    assert main(["simulate", "--scenario", "random", "--set", "bogus=1", "--out", str(out)]) == 2
    assert main(["plot", str(tmp_path / "missing.h5")]) == 2


def _runs(mask: np.ndarray) -> list[int]:
    """Lengths (samples) of the runs of True in ``mask``."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1))


def test_manual_routines_two_second_pauses_and_one_long_strong_reach():
    tr = scenarios.make_trial("manual_routines", 0)
    st = tr.truth["stationary"]
    pauses = np.array(_runs(st)[1:-1]) / tr.rate  # inner pauses (not the start/end rest)
    assert len(pauses) >= 5
    # 2 s pauses, give or take the servos' settling after a move (ω_n ≈ 60 rad/s)
    # and the few ms at each end of a raised-cosine move whose rate is still
    # below the 0.06 °/s stationarity threshold.
    assert 1.6 < np.median(pauses) < 2.2
    dist = np.linalg.norm(tr.truth["mag_disturbance"], axis=1)
    strong = dist > 100.0  # µT: a small magnet a few cm away
    assert _runs(strong) and max(_runs(strong)) / tr.rate == pytest.approx(10.0, abs=1.5)
    assert dist[~strong].max() < 20.0 or np.mean(dist < 5.0) > 0.5  # elsewhere the magnet is far
    assert tr.truth["magnet_distance"].min() < 0.06


def test_gait_field_moves_continuously_through_a_smooth_field():
    tr = scenarios.make_trial("gait_field", 0, duration=40.0)
    t = tr.t
    assert not tr.truth["stationary"][t > 2.5].any()  # no pauses once walking
    d = tr.truth["mag_disturbance"]
    assert np.ptp(np.linalg.norm(d, axis=1)) > 1.0  # the field changes along the path (µT)
    # Smooth in space: in the world frame the sources' field changes by about
    # Σ 3|B_i|/r_i · v/rate ≈ 3·(5 µT)/(3.5 m) · (1 m/s)/(256 Hz) ≈ 0.02 µT per sample.
    d_world = quat.rotate(tr.q_true, d)
    assert np.abs(np.diff(d_world, axis=0)).max() < 0.05
    assert tr.truth["magnet_distance"].min() > 2.0
    # Gait: the accelerometer sees the bounce (±bounce·(2π f_step)² ≈ ±2.5 m/s²).
    acc_norm = np.linalg.norm(tr.acc, axis=1)[t > 3.0]
    assert 1.5 < np.percentile(acc_norm, 99) - 9.81 < 5.0
