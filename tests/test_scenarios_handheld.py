"""Hand-held scenarios, their kinematics and the static indoor field (issue 9)."""

from __future__ import annotations

import numpy as np
import pytest

from magenv import quaternion as quat
from magenv.scenarios import configure, get_scenario, handheld, make_trial
from magenv.sim.handheld import MODES, Motion, ideal_readings
from magenv.sim.indoor_field import IndoorField, random_indoor_field
from magenv.sim.magnet import dipole_field

EARTH = quat.earth_field(47.0, 61.0)


def _uniform(pos):
    return np.tile(EARTH, (len(pos), 1))


# ------------------------------------------------------------ indoor field


def test_dipole_matches_magnet_module():
    rng = np.random.default_rng(0)
    src, mom = np.array([[1.0, -2.0, 0.5]]), np.array([[30.0, -10.0, 50.0]])
    pos = rng.uniform(-3, 3, (50, 3)) + np.array([0.0, 0.0, 5.0])
    f = IndoorField(np.zeros(3), src, mom)
    expect = dipole_field(pos - src, np.repeat(mom, len(pos), 0))
    np.testing.assert_allclose(f(pos), expect, rtol=1e-12, atol=1e-12)


def test_wire_field_magnitude_and_right_hand_rule():
    f = IndoorField(np.zeros(3), wire_point=[[0.0, 0.0, 0.0]], wire_dir=[[0.0, 0.0, 1.0]], wire_current=[10.0])
    b = f(np.array([[2.0, 0.0, 7.0]]))[0]  # 2 m east of a wire carrying 10 A upwards
    np.testing.assert_allclose(b, [0.0, 0.2 * 10.0 / 2.0, 0.0], atol=1e-12)  # µ0 I/(2π d), pointing north


def test_random_field_keeps_sources_away_and_is_smooth():
    rng = np.random.default_rng(3)
    pts = np.stack([np.linspace(-3, 3, 200), np.zeros(200), np.full(200, 1.2)], 1)
    f = random_indoor_field(
        rng, EARTH, pts, n_dipoles=(6, 6), strength_ut=(5.0, 5.0), distance_m=(1.0, 2.0), n_wires=(2, 2)
    )
    assert f.min_source_distance(pts) >= 1.0 - 1e-9
    b = f(pts)
    step = np.linalg.norm(np.diff(b, axis=0), axis=1) / np.linalg.norm(np.diff(pts, axis=0), axis=1)
    assert step.max() < 60.0  # µT/m: a 5 µT source ≥ 1 m away cannot give more than ~3·B/r per source
    assert np.linalg.norm(b - EARTH, axis=1).max() > 1.0  # and the field is actually perturbed


def test_field_rejects_bad_input():
    with pytest.raises(ValueError):
        IndoorField(EARTH, wire_point=[[0, 0, 0]], wire_dir=[[0, 0, 2.0]], wire_current=[1.0])
    with pytest.raises(ValueError):
        IndoorField(EARTH)(np.array([[np.nan, 0, 0]]))


# ------------------------------------------------------------ kinematics


@pytest.mark.parametrize("modes", [("texting",), ("swinging",), MODES])
def test_ideal_gyro_integrates_to_the_true_orientation(modes):
    rng = np.random.default_rng(1)
    motion = Motion(rng, modes, 40.0, segment_s=(5.0, 10.0))
    t = np.arange(4000) / 100.0
    _, q, gyr, _, _, _ = ideal_readings(motion, t, _uniform)
    qi = q[0].copy()
    for i in range(1, len(t)):
        qi = quat.integrate_gyro1(qi, 0.5 * (gyr[i - 1] + gyr[i]), 0.01)
    err = np.rad2deg(np.linalg.norm(quat.to_rotvec(quat.mul(qi, quat.conj(q[-1])))))
    assert err < 0.2


def test_specific_force_averages_to_gravity_on_the_treadmill():
    motion = Motion(np.random.default_rng(2), ("swinging",), 30.0, travel=False)
    t = np.arange(3000) / 100.0
    _, q, _, acc, _, _ = ideal_readings(motion, t, _uniform)
    f_earth = quat.rotate(q, acc)
    np.testing.assert_allclose(f_earth.mean(0), [0.0, 0.0, quat.GRAVITY], atol=0.05)
    assert np.abs(np.linalg.norm(acc, axis=1) - quat.GRAVITY).max() > 3.0  # swinging: large accelerations


def test_walker_travels_at_the_configured_speed():
    motion = Motion(np.random.default_rng(4), ("texting",), 60.0, speed=1.39)
    p, _ = motion.pose(np.arange(0, 60, 0.5))
    dist = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1).sum()
    assert 1.3 * 60 < dist < 1.5 * 60


# ------------------------------------------------------------ scenarios


def test_scenarios_are_deterministic_and_seed_dependent():
    a = make_trial("handheld_random", 5, duration=10.0)
    b = make_trial("handheld_random", 5, duration=10.0)
    c = make_trial("handheld_random", 6, duration=10.0)
    for k in ("gyr", "acc", "mag", "q_true"):
        assert np.array_equal(getattr(a, k), getattr(b, k))
    assert not np.array_equal(a.mag, c.mag)


@pytest.mark.parametrize(
    "name,duration", [("handheld_texting", 120.0), ("handheld_swinging", 120.0), ("handheld_free", 780.0)]
)
def test_paper_scenarios_defaults(name, duration):
    cfg = get_scenario(name)
    assert cfg.rate == 100.0 and cfg.duration == duration and cfg.treadmill_prob == 1.0


def test_trial_channels_and_disturbance():
    tr = make_trial("handheld_texting", 0, duration=5.0)
    assert tr.n == 500 and tr.rate == 100.0
    # truth disturbance is the field minus the Earth field, in the sensor frame
    field_e = quat.rotate(tr.q_true, tr.truth["mag_disturbance"]) + quat.earth_field(tr.field_norm, tr.field_dip)
    assert np.linalg.norm(field_e - quat.earth_field(tr.field_norm, tr.field_dip), axis=1).mean() > 0.5
    mag_e = quat.rotate(tr.q_true, tr.mag)
    assert np.median(np.linalg.norm(mag_e - field_e, axis=1)) < 3.0  # sensor errors only


def test_bad_scenario_arguments_raise():
    with pytest.raises(ValueError, match="unknown hand-held scenario"):
        handheld.WORLD.make_trial("nope", 0)
    with pytest.raises(ValueError, match="unknown parameter"):
        make_trial("handheld_texting", 0, wobble=3)
    with pytest.raises(ValueError):
        make_trial("handheld_texting", -1)
    with pytest.raises(ValueError):
        configure("handheld_texting", modes=("dancing",))
