"""The one quaternion convention: scalar first, Hamilton, sensor → ENU earth."""

import numpy as np
import pytest

from magenv import quaternion as quat

RNG = np.random.default_rng(42)


def random_quats(n):
    return quat.normalize(RNG.normal(size=(n, 4)))


def test_hamilton_product_basis():
    i, j, k = np.eye(4)[1], np.eye(4)[2], np.eye(4)[3]
    assert np.allclose(quat.mul(i, j), k)  # i ⊗ j = k (Hamilton, not JPL)
    assert np.allclose(quat.mul(j, i), -k)
    assert np.allclose(quat.mul(i, i), [-1, 0, 0, 0])


def test_rotation_maps_sensor_to_earth():
    # 90° about earth z (yaw): the sensor x axis points north (ENU y) in the earth frame.
    q = quat.from_axis_angle([0, 0, 1], np.pi / 2)
    assert np.allclose(quat.rotate(q, [1.0, 0, 0]), [0, 1, 0])
    assert np.allclose(quat.rotate_inv(q, [0, 1.0, 0]), [1, 0, 0])


def test_rotate_matches_matrix_and_sandwich_product():
    q = random_quats(50)
    v = RNG.normal(size=(50, 3))
    sandwich = quat.mul(quat.mul(q, np.concatenate([np.zeros((50, 1)), v], 1)), quat.conj(q))[:, 1:]
    assert np.allclose(quat.rotate(q, v), sandwich)
    assert np.allclose(np.einsum("nij,nj->ni", quat.to_matrix(q), v), sandwich)
    assert np.allclose(quat.rotate_inv(q, quat.rotate(q, v)), v)


def test_matrix_round_trip_all_branches():
    q = random_quats(2000)
    back = quat.from_matrix(quat.to_matrix(q))
    assert np.allclose(np.abs(np.sum(back * q, axis=1)), 1.0)
    # near-180° rotations exercise the x/y/z branches of Shepperd's method
    q180 = quat.from_axis_angle(np.eye(3), np.full(3, np.pi - 1e-9))
    assert np.allclose(np.abs(np.sum(quat.from_matrix(quat.to_matrix(q180)) * q180, 1)), 1.0)


def test_euler_zyx_round_trip_and_order():
    yaw, pitch, roll = 0.7, -0.4, 1.1
    q = quat.from_euler_zyx(yaw, pitch, roll)
    assert np.allclose(quat.to_euler_zyx(q), [yaw, pitch, roll])
    # ZYX: yaw applied last in the sensor→earth map
    expected = quat.mul(
        quat.from_axis_angle([0, 0, 1], yaw),
        quat.mul(quat.from_axis_angle([0, 1, 0], pitch), quat.from_axis_angle([1, 0, 0], roll)),
    )
    assert np.allclose(q, expected)


def test_rotvec_round_trip_and_small_angles():
    r = RNG.normal(size=(100, 3))
    r *= np.minimum(1.0, 3.0 / np.linalg.norm(r, axis=1))[:, None]  # angles below π
    assert np.allclose(quat.to_rotvec(quat.from_rotvec(r)), r)
    tiny = np.array([1e-9, -2e-9, 3e-9])
    assert np.allclose(quat.to_rotvec(quat.from_rotvec(tiny)), tiny, atol=1e-15)


def test_integrate_gyro_constant_rate():
    q = np.array([1.0, 0, 0, 0])
    rate = np.array([0.0, 0.0, np.deg2rad(90)])
    for _ in range(100):
        q = quat.integrate_gyro1(q, rate, 0.01)
    assert np.allclose(q, quat.from_axis_angle([0, 0, 1], np.pi / 2))


def test_align_picks_same_hemisphere():
    q = random_quats(1)[0]
    assert np.allclose(quat.align1(-q, q), q)
    assert np.allclose(quat.align1(q, q), q)


def test_earth_field_and_gravity_in_enu():
    b = quat.earth_field(46.0, 49.6)
    assert b[0] == 0 and b[1] > 0 and b[2] < 0  # north and down
    assert np.isclose(np.linalg.norm(b), 46.0)
    assert np.isclose(np.rad2deg(np.arctan2(-b[2], b[1])), 49.6)
    assert np.allclose(quat.gravity_up(), [0, 0, quat.GRAVITY])


@pytest.mark.parametrize("bad", [np.zeros(4)])
def test_normalize_zero_gives_identity(bad):
    assert np.allclose(quat.normalize(bad), [1, 0, 0, 0])
