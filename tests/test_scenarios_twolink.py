"""The two-link world (``magenv.sim.twolink``) and its scenarios (``magenv.scenarios.twolink``)."""

from __future__ import annotations

import numpy as np
import pytest

from magenv import quaternion as quat
from magenv.filters.constraint import joint_vectors
from magenv.scenarios import make_trial, twolink
from magenv.sim import twolink as tl

#: every noise and bias of the sensor model off, and no deliberate gyro bias
NOISE_FREE = dict(gyr_noise_dps=0.0, gyr_drift_dps=0.0, acc_noise=0.0, acc_bias=0.0, gyro_bias=(0.0, 0.0, 0.0))


@pytest.fixture(scope="module")
def clean():
    """Test 2 motion, 20 s, noise-free sensors."""
    return make_trial("constraint_test2", 3, duration=20.0, **NOISE_FREE)


def test_lever_arms_are_the_papers():
    r_i, r_j = tl.lever_arms()
    np.testing.assert_allclose(r_i, [0.512, 0.003, -0.025], atol=1e-12)
    np.testing.assert_allclose(r_j, [0.506, 0.001, -0.029], atol=1e-12)


def _mismatch(trial, r_i, r_j):
    """|C(q_i)h_i − C(q_j)h_j| (N,), m/s², with the trial's truth orientations."""
    left = quat.rotate(trial.q_true, joint_vectors(trial.gyr, trial.acc, r_i, trial.rate))
    right = quat.rotate(trial.extra["q_j"], joint_vectors(trial.extra["gyr_j"], trial.extra["acc_j"], r_j, trial.rate))
    return np.linalg.norm(left - right, axis=1), right


def test_constraint_holds_with_noise_free_sensors(clean):
    """eq. 9 in the simulated world: the joint centre's specific force agrees from both links."""
    r_i, r_j = np.array(clean.meta["lever_i_m"]), np.array(clean.meta["lever_j_m"])
    mis, right = _mismatch(clean, r_i, r_j)
    joint_acc = np.linalg.norm(right - quat.gravity_up(), axis=1)
    moving = clean.t > 4.0
    assert np.sqrt(np.mean(joint_acc[moving] ** 2)) > 0.5  # the joint centre does accelerate
    # backward-difference ω̇ lags half a sample: a few cm/s² of mismatch, not more
    assert np.sqrt(np.mean(mis[1:] ** 2)) < 0.08
    # …and the check can fail: a wrong lever arm breaks it
    bad, _ = _mismatch(clean, r_i * np.array([-1.0, 1.0, 1.0]), r_j)
    assert np.sqrt(np.mean(bad[moving] ** 2)) > 5 * np.sqrt(np.mean(mis[moving] ** 2))


def test_joint_centre_geometry():
    """Both sensors' lever arms end at the joint centre MuJoCo reports."""
    rng = np.random.default_rng(0)
    n = int(5.0 * tl.PHYSICS_RATE)
    env = tl.envelope(np.arange(n) / tl.PHYSICS_RATE, [(0.5, 1.0)])
    cmd = tl.smooth_motion(rng, 5.0, tl.PHYSICS_RATE, env, np.array(twolink.BASE_AMPLITUDE), (0.2, 0.6))
    run = tl.simulate_twolink(cmd, 100.0, 499)
    r_i, r_j = tl.lever_arms()
    np.testing.assert_allclose(run.p_i + quat.rotate(run.q_i, np.broadcast_to(r_i, run.p_i.shape)), run.p_c, atol=1e-9)
    np.testing.assert_allclose(run.p_j + quat.rotate(run.q_j, np.broadcast_to(r_j, run.p_j.shape)), run.p_c, atol=1e-9)
    # at rest (before the envelope rises) the accelerometers read +g up in the world
    np.testing.assert_allclose(
        quat.rotate(run.q_i[:20], run.acc_i[:20]), np.tile(quat.gravity_up(), (20, 1)), atol=1e-3
    )


def test_paper_gyro_bias_is_added():
    kw = dict(duration=5.0, gyr_noise_dps=0.0, gyr_drift_dps=0.0)
    with_bias = make_trial("constraint_test1", 0, **kw)
    without = make_trial("constraint_test1", 0, gyro_bias=(0.0, 0.0, 0.0), **kw)
    np.testing.assert_allclose(
        with_bias.gyr - without.gyr, np.tile(twolink.PAPER_GYRO_BIAS, (with_bias.n, 1)), atol=1e-15
    )
    np.testing.assert_array_equal(with_bias.extra["gyr_j"], without.extra["gyr_j"])  # only link i's gyro


def test_same_name_and_seed_same_trial():
    a = make_trial("constraint_random", 11, duration=10.0)
    b = make_trial("constraint_random", 11, duration=10.0)
    c = make_trial("constraint_random", 12, duration=10.0)
    for key in ("gyr", "acc", "mag", "q_true"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    for group in ("extra", "truth"):
        assert getattr(a, group).keys() == getattr(b, group).keys()
        for key in getattr(a, group):
            np.testing.assert_array_equal(getattr(a, group)[key], getattr(b, group)[key])
    assert a.meta == b.meta
    assert not np.array_equal(a.gyr, c.gyr)


@pytest.mark.parametrize(
    "name,target,n_dist,dist_s",
    [("constraint_test1", 0.9, 5, 15.0), ("constraint_test2", 2.0, 5, 15.0), ("constraint_test3", 1.9, 1, 30.0)],
)
def test_table1_conditions(name, target, n_dist, dist_s):
    """Mean external acceleration and the tool's approaches after the paper's Table 1."""
    tr = make_trial(name, 0)
    assert tr.meta["mean_ext_acc"] == pytest.approx(target, rel=0.15)
    assert len(tr.meta["approach_starts_s"]) == n_dist
    assert sum(tr.meta["approach_holds_s"]) == pytest.approx(dist_s)
    tool = np.linalg.norm(tr.truth["tool_field"], axis=1) / tr.field_norm
    strong = tool > 0.15  # eq. 16's th1: the paper's filter then drops the magnetometer
    assert strong.sum() / tr.rate == pytest.approx(dist_s, rel=0.25)
    edges = np.flatnonzero(np.diff(strong.astype(int)) == 1)
    assert len(edges) >= n_dist
    # the lab alone: a weak inhomogeneity of a few hundredths of the Earth field
    lab = np.linalg.norm(tr.truth["mag_disturbance"] - tr.truth["tool_field"], axis=1) / tr.field_norm
    assert 0.01 < lab.mean() < 0.15
    assert tr.extra.keys() >= {"gyr_j", "acc_j", "mag_j", "q_j"}


def test_random_family_varies_and_has_still_stretches():
    trials = [make_trial("constraint_random", s, duration=40.0) for s in range(4)]
    still = [t.truth["stationary"][int(5 * t.rate) :].mean() for t in trials]  # after the start rest
    assert max(still) > 0.05
    assert len({round(t.meta["mean_ext_acc"], 3) for t in trials}) == 4
    assert len({t.field_dip for t in trials}) == 4


def test_bad_scenario_input():
    with pytest.raises(ValueError, match="unknown two-link scenario"):
        twolink.WORLD.make_trial("constraint_nope", 0)
    with pytest.raises(ValueError, match="unknown parameter"):
        make_trial("constraint_test1", 0, bogus=1)
    with pytest.raises(ValueError, match="seed"):
        make_trial("constraint_test1", -1)
    with pytest.raises(ValueError, match="tool_near"):
        make_trial("constraint_test1", 0, tool_near=-0.1)
