"""The one metric module: error parts and RMSE, checked on known rotations."""

import numpy as np

from magenv import metrics
from magenv import quaternion as quat


def test_pure_heading_error_is_heading_only():
    q_true = quat.from_euler_zyx(0.3, 0.2, -0.5)
    q_est = quat.mul(quat.from_axis_angle([0, 0, 1], np.deg2rad(10)), q_true)  # earth-frame yaw offset
    e = metrics.error_quaternion(q_est, q_true)
    assert np.isclose(metrics.total_error(e), 10)
    assert np.isclose(metrics.heading_error(e), 10)
    assert np.isclose(metrics.inclination_error(e), 0, atol=1e-6)
    assert np.allclose(metrics.euler_error(q_est, q_true), [10, 0, 0], atol=1e-9)


def test_pure_tilt_error_is_inclination_only():
    q_true = quat.from_euler_zyx(1.0, 0.0, 0.0)
    q_est = quat.mul(quat.from_axis_angle([1, 0, 0], np.deg2rad(4)), q_true)  # earth-frame tilt
    e = metrics.error_quaternion(q_est, q_true)
    assert np.isclose(metrics.heading_error(e), 0, atol=1e-9)
    assert np.isclose(metrics.inclination_error(e), 4)
    assert np.isclose(metrics.total_error(e), 4)


def test_sign_of_quaternion_does_not_matter():
    q = quat.from_euler_zyx(0.1, 0.2, 0.3)
    e = metrics.error_quaternion(-q, q)
    assert np.isclose(metrics.total_error(e), 0, atol=1e-6)


def test_rmse_ignores_nan_and_respects_mask():
    err = np.array([3.0, 4.0, np.nan, 100.0])
    assert np.isclose(metrics.rmse(err, mask=[True, True, True, False]), np.sqrt(12.5))
    assert np.isnan(metrics.rmse(err, mask=[False, False, True, False]))


def test_score_of_constant_offset():
    n = 100
    q_true = quat.from_euler_zyx(np.linspace(0, 3, n), np.zeros(n), np.zeros(n))
    q_est = quat.mul(quat.from_axis_angle([0, 0, 1], np.deg2rad(5)), q_true)
    q_true[10] = np.nan  # lost ground truth is skipped
    s = metrics.score(q_est, q_true)
    assert np.isclose(s.total, 5) and np.isclose(s.heading, 5) and s.inclination < 1e-3
