"""The board world (``magenv.scenarios.board``): BROAD-like trials randomised wide, for sim-to-real training."""

from __future__ import annotations

import numpy as np
import pytest

from magenv import quaternion as quat
from magenv import scenarios
from magenv.scenarios.board import BROAD_RATE, FAMILIES
from magenv.sim import board

SHORT = {"duration": 30.0}


@pytest.mark.parametrize("family", FAMILIES)
def test_same_seed_same_trial_and_the_truth_drives_the_sensors(family):
    name = f"board_{family}"
    a = scenarios.make_trial(name, 10003, **SHORT)
    b = scenarios.make_trial(name, 10003, **SHORT)
    for key in ("gyr", "acc", "mag", "q_true"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    assert a.meta == b.meta and a.meta["family"] == family
    assert not np.array_equal(a.mag, scenarios.make_trial(name, 10004, **SHORT).mag)
    assert a.n == round((a.meta["rest_s"] + 30.0) * a.rate) and np.allclose(np.linalg.norm(a.q_true, axis=1), 1.0)
    rest = a.t < a.meta["rest_s"] - 0.2
    np.testing.assert_array_equal(a.score_mask, a.t >= a.meta["rest_s"])  # BROAD's movement mask
    # at rest: the accelerometer reads g, the gyro its bias, the field the site's (no disturbance at the start)
    assert abs(np.median(np.linalg.norm(a.acc[rest], axis=1)) - quat.GRAVITY) < 0.1
    assert np.linalg.norm(a.gyr[rest].mean(0)) < np.deg2rad(2.0)
    earth = quat.earth_field(a.meta["site_norm"], a.meta["site_dip"])
    field = quat.rotate_inv(a.q_true, np.broadcast_to(earth, (a.n, 3))) + a.truth["mag_disturbance"]
    assert (
        abs(np.median(np.linalg.norm(a.mag[rest], axis=1) - np.linalg.norm(field[rest], axis=1))) < 4.0
    )  # residual iron
    # the gyro is the truth's body rate (lag, bias, noise and the sensor's errors aside)
    moving = ~rest
    w_true = quat.to_rotvec(quat.mul(quat.conj(a.q_true[:-1]), a.q_true[1:])) * a.rate
    lag = a.meta["sensor"]["gyr_lag_samples"]
    err = np.linalg.norm(a.gyr[1 + lag :][moving[1 + lag :]] - w_true[: len(w_true) - lag][moving[1 + lag :]], axis=1)
    if family != "shocks":
        assert np.median(err) < 0.05 * np.median(np.linalg.norm(w_true[moving[1:]], axis=1)) + 0.02


def test_each_family_disturbs_what_it_says():
    clean = scenarios.make_trial("board_clean", 10010, **SHORT)
    assert np.abs(clean.truth["mag_disturbance"]).max() < 1e-9
    irons = set()
    for seed in range(10010, 10020):
        att = scenarios.make_trial("board_attached", seed, duration=60.0)
        d = att.truth["mag_disturbance"]
        on = (att.t > att.meta["attached_on_s"] + 4.0) & (att.t < min(att.meta["attached_off_s"], att.t[-1]) - 4.0)
        assert on.any() and np.abs(d[att.t < 1.0]).max() < 1e-9
        if not att.meta["iron"]:  # a magnet: a constant offset in the sensor frame, of the drawn size
            np.testing.assert_allclose(np.linalg.norm(d[on], axis=1), att.meta["attached_ut"], rtol=1e-9)
        else:  # iron: its soft part turns with the board
            assert np.ptp(np.linalg.norm(d[on], axis=1)) > 0
        irons.add(att.meta["iron"])
    assert irons == {True, False}
    sta = scenarios.make_trial("board_stationary", 10011, duration=90.0)
    assert sta.meta["visits"] and np.linalg.norm(sta.truth["mag_disturbance"], axis=1).max() > 1.0
    shock = scenarios.make_trial("board_shocks", 10012, duration=60.0)
    start, stop = shock.meta["bursts"][0]
    inside = (shock.t >= start) & (shock.t < stop)
    resid = np.abs(np.linalg.norm(shock.acc, axis=1) - quat.GRAVITY)
    assert resid[inside].max() > 0.5 * shock.meta["shock_amp"] and np.abs(shock.truth["mag_disturbance"]).max() == 0


def test_the_random_family_spans_families_rates_and_sites():
    trials = [scenarios.make_trial("board_random", 10100 + s, duration=10.0) for s in range(30)]
    rests = [t.meta["rest_s"] for t in trials]
    assert min(rests) < 10.0 and max(rests) > 25.0  # short rests and BROAD's long ones
    assert {t.meta["family"] for t in trials} == set(FAMILIES)
    rates = {t.rate for t in trials}
    assert BROAD_RATE in rates and len(rates) > 5
    assert np.ptp([t.meta["site_norm"] for t in trials]) > 10.0
    assert len({(t.meta["motion"], t.meta["speed"]) for t in trials}) >= 6


def test_the_spinning_board_turns_steadily_in_one_sense_and_the_other_scenarios_do_not():
    spun = scenarios.make_trial("board_spinning", 10005, **SHORT)
    plain = scenarios.make_trial("board_random", 10005, **SHORT)
    spin = np.deg2rad(spun.meta["spin_dps"])
    assert 20.0 <= np.rad2deg(np.linalg.norm(spin)) <= 200.0 and "spin_dps" not in plain.meta
    moving = spun.score_mask & (spun.t > spun.meta["rest_s"] + 1.0)
    # the same motion plus the spin: the gyros differ by the spin while the board moves (the sensor's scale
    # errors of ≤ 1 % aside), with nothing else drawn differently (the spin has its own stream)
    assert not spun.meta["breaks"]
    diff = (spun.gyr[moving] - plain.gyr[moving]).mean(0)
    assert np.linalg.norm(diff - spin) < 0.02 * np.linalg.norm(spin)
    assert {k: v for k, v in spun.meta.items() if k not in ("spin_dps", "scenario", "config")} == {
        k: v for k, v in plain.meta.items() if k not in ("scenario", "config")
    }


def test_motion_pieces():
    t = np.arange(0, 20, 0.01)
    e = board.envelope(t, 2.0, [(8.0, 12.0)])
    assert e[t < 2.0].max() == 0 and e[(t > 3.0) & (t < 7.0)].min() == 1.0 and e[(t > 8.0) & (t < 12.0)].max() == 0
    prof = board.attached_profile(t, 5.0, 15.0, 1.0)
    assert prof[t < 5].max() == 0 and prof[(t > 6) & (t < 14)].min() == 1.0 and prof[t > 15].max() == 0
    q = board.integrate(np.array([1.0, 0, 0, 0]), np.tile([0.0, 0.0, np.pi / 2], (101, 1)), 0.01)
    np.testing.assert_allclose(q[100], quat.from_axis_angle(np.array([0, 0, 1.0]), np.pi / 2), atol=1e-9)


def test_bad_board_configs_are_named():
    with pytest.raises(ValueError, match="family"):
        scenarios.make_trial("board_random", 10000, family="moon")
    with pytest.raises(ValueError, match="attached_ut"):
        scenarios.make_trial("board_attached", 10000, attached_ut=(5.0, 1.0))


def test_a_randomised_twin_keeps_the_recordings_truth_and_draws_the_rest(broad_dir):
    path = sorted(broad_dir.glob("32_*.hdf5"))[0]
    names = scenarios.expand_mixture(f"rtwins:{broad_dir}")
    assert f"rtwin:{path.resolve()}" in names and len(names) == len(list(broad_dir.glob("*.hdf5")))
    a = scenarios.make_trial(f"rtwin:{path}", 10001)
    b = scenarios.make_trial(f"rtwin:{path}", 10001)
    rec = scenarios.make_trial(f"twin:{path}", 0)
    np.testing.assert_array_equal(a.q_true, rec.q_true)  # the recording's truth, NaN rows and all
    np.testing.assert_array_equal(a.score_mask, rec.score_mask)
    np.testing.assert_array_equal(a.mag, b.mag)
    assert a.meta["recording"] == str(path.resolve()) and a.meta["family"] in FAMILIES
    assert scenarios.world_of(f"rtwin:{path}") == "board"
    fams = {scenarios.make_trial(f"rtwin:{path}", s).meta["family"] for s in range(10002, 10012)}
    assert len(fams) >= 3  # never the recording's own disturbance: drawn per seed
