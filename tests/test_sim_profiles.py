"""Drive profiles, base paths and the hand-held magnet's path: commands that agree with themselves."""

from __future__ import annotations

import numpy as np
import pytest

from magenv.sim import base_paths, profiles
from magenv.sim.hand import Approach, hand_path

RATE = 200.0


def test_move_turns_by_the_requested_angle_with_peak_rate_twice_the_mean():
    p = profiles.empty_profile(5.0, RATE)
    profiles.add_move(p, 1, 1.0, 2.0, np.deg2rad(60.0))
    assert np.rad2deg(p.angles[-1, 1]) == pytest.approx(60.0, abs=0.01)
    assert np.rad2deg(p.omega[:, 1].max()) == pytest.approx(2 * 60.0 / 2.0, rel=1e-3)
    assert p.still()[: int(0.99 * RATE)].all() and not p.still()[int(1.5 * RATE)]
    np.testing.assert_array_equal(p.angles[:, [0, 2]], 0.0)


def test_spin_holds_its_rate_between_ramps():
    p = profiles.empty_profile(10.0, RATE, (0.1, 0.2, 0.3))
    profiles.add_spin(p, 2, 1.0, 9.0, np.deg2rad(360.0), ramp=0.5)
    mid = slice(int(2 * RATE), int(8 * RATE))
    np.testing.assert_allclose(np.rad2deg(p.omega[mid, 2]), 360.0)
    # Angle: 7 s at full rate + two half-cosine ramps of 0.5 s (mean rate ½).
    assert np.rad2deg(p.angles[-1, 2] - 0.3) == pytest.approx(360.0 * 7.5, rel=1e-3)


def _check_velocity_is_derivative(motion, rate, tol):
    num = np.gradient(motion[:, :3], axis=0) * rate
    np.testing.assert_allclose(motion[:, 3:][1:-1], num[1:-1], atol=tol)


def test_reach_velocity_matches_its_position_and_arrives():
    t = np.arange(int(20 * RATE)) / RATE
    target = np.array([0.3, -0.1, 0.0])
    m = base_paths.reach(t, 2.0, 1.5, 10.0, target, np.random.default_rng(0))
    _check_velocity_is_derivative(m, RATE, 2e-3)
    held = (t > 4.0) & (t < 13.0)
    np.testing.assert_allclose(m[held, :3], np.broadcast_to(target, (held.sum(), 3)), atol=0.003)  # tremor ≤ 2 mm
    np.testing.assert_allclose(m[t > 15.0], 0.0, atol=1e-12)  # back home, at rest


def test_figure_eight_starts_from_rest_and_velocity_matches_position():
    t = np.arange(int(30 * RATE)) / RATE
    m = base_paths.figure_eight(t, 1.5, 1.0, 16.0, 0.02, 1.8, 0.02)
    _check_velocity_is_derivative(m, RATE, 5e-3)
    assert np.abs(m[0, 3:]).max() == 0.0
    assert np.abs(m[:, 0]).max() == pytest.approx(1.5, abs=1e-3)
    psi, rate = base_paths.heading(m, RATE)
    assert np.isfinite(psi).all() and np.abs(rate).max() < np.deg2rad(400)


def test_hand_path_goes_between_far_and_near():
    t = np.arange(int(40 * RATE)) / RATE
    off, axis = hand_path(t, [Approach(5.0, 10.0, 2.0)], 0.7, 0.1, np.random.default_rng(1))
    dist = np.linalg.norm(off, axis=1)
    assert dist[t < 4].min() > 0.65 and dist[(t > 7.5) & (t < 16.5)].max() < 0.13
    np.testing.assert_allclose(np.linalg.norm(axis, axis=1), 1.0)
    assert (axis[:, 2] < -0.9).all()  # the disc's moment points roughly down
