"""Causal stationary detection (Fan et al. eqs. 11–13)."""

from __future__ import annotations

import numpy as np

from magenv.filters import stationary as stat
from magenv.quaternion import GRAVITY

RATE = 100.0


def _reference(acc, gyr, length, th_a, th_g):
    """Eqs. 11 and 13 written directly on whole arrays (look-back only)."""
    out = np.zeros(len(acc), bool)
    for t in range(length, len(acc)):
        out[t] = np.all(np.abs(acc[t] - acc[t - length]) < th_a) and np.all(np.abs(gyr[t]) < th_g)
    return out


def test_paper_thresholds_in_si_units():
    th_a, th_g = stat.thresholds()
    assert np.isclose(th_a, 0.04 * GRAVITY)
    assert np.isclose(th_g, np.deg2rad(0.5))
    buf, ctr = stat.make_state(256.0)
    assert buf.shape == (128, 3) and list(ctr) == [0, 0]  # t0 = 0.5 s at 256 Hz


def test_still_then_moving_then_still():
    n = 400
    rng = np.random.default_rng(0)
    acc = np.tile([0.0, 0.0, GRAVITY], (n, 1)) + rng.normal(0, 0.02, (n, 3))
    gyr = rng.normal(0, np.deg2rad(0.05), (n, 3))
    acc[150:200, 0] += 2.0  # a push: acceleration changes
    gyr[250:260, 2] = np.deg2rad(5.0)  # a turn about z: only the gyro sees it
    flags = stat.detect(acc, gyr, RATE)
    length = int(0.5 * RATE)
    assert not flags[:length].any()  # no history yet
    assert flags[length:150].all()
    assert not flags[150:200].any()  # moving
    assert not flags[200 : 200 + length].any()  # a_t − a_{t−t0} still spans the push
    assert not flags[250:260].any()  # turning
    assert flags[200 + length + 1 : 250].all() and flags[260:].all()


def test_streaming_equals_reference_on_noisy_data():
    rng = np.random.default_rng(1)
    n = 600
    acc = np.tile([0.0, 0.0, GRAVITY], (n, 1)) + rng.normal(0, 0.2, (n, 3))
    gyr = rng.normal(0, np.deg2rad(0.4), (n, 3))
    th_a, th_g = stat.thresholds()
    expected = _reference(acc, gyr, 50, th_a, th_g)
    got = stat.detect(acc, gyr, RATE)
    assert 0 < expected.sum() < n - 50  # the data exercises both outcomes
    np.testing.assert_array_equal(got, expected)


def test_peek_does_not_change_state():
    state = stat.make_state(RATE)
    buf, ctr = state
    th_a, th_g = stat.thresholds()
    a = np.array([0.0, 0.0, GRAVITY])
    w = np.zeros(3)
    for _ in range(60):
        stat.step1(state, a, w, th_a, th_g)
    before = (buf.copy(), ctr.copy())
    assert stat.peek1(state, a, w, th_a, th_g)
    assert not stat.peek1(state, a + 1.0, w, th_a, th_g)
    np.testing.assert_array_equal(buf, before[0])
    np.testing.assert_array_equal(ctr, before[1])
