"""Madgwick IMU/MIMU kernels: gradient, agreement with the ``ahrs`` package, convergence."""

from __future__ import annotations

import numpy as np
import pytest

from magenv import metrics
from magenv import quaternion as quat
from magenv.filters import madgwick as mg
from tests.conftest import kinematic_trial

# ahrs' Madgwick works in a north-x, up-z earth frame (NWU: x north, y west, z up);
# magenv's is ENU. The NWU → ENU rotation is +90° about z: q_ENU = q_z(90°) ⊗ q_NWU.
#
# Tolerances. Madgwick's objective (eq. 3) is written with the unit-quaternion
# form of the rotation matrix (1 − 2(y² + z²), …), so its gradient has a radial
# part that depends on the earth frame, and the normalised step ∇f/‖∇f‖ (eq. 9)
# differs slightly between a north-x (ahrs) and a north-y (ours) reference field.
# * IMU: the reference is gravity along z in both frames → identical up to
#   rounding: max |Δq| < 1e-9 over 1280 steps.
# * MIMU: same algorithm, different frame → orientations within 0.1° from a
#   correct start at up to 200 °/s (measured 0.03°), and within 0.1° once
#   both have converged from a 23° wrong start (measured 0.03°; during
#   convergence they differ by up to ~2°).
Q_NWU_TO_ENU = quat.from_axis_angle(np.array([0.0, 0.0, 1.0]), np.pi / 2)
IMU_TOL = 1e-9
MIMU_TOL_DEG = 0.1


def _ahrs_run(trial, q0_enu, use_mag):
    from ahrs.filters import Madgwick

    f = Madgwick(gain=mg.BETA_DEFAULT, Dt=trial.dt)
    q = quat.mul(quat.conj(Q_NWU_TO_ENU), q0_enu)  # ENU → NWU at the edge
    out = np.empty((trial.n, 4))
    for i in range(trial.n):
        if use_mag:
            q = np.asarray(f.updateMARG(q, gyr=trial.gyr[i], acc=trial.acc[i], mag=trial.mag[i]), float)
        else:
            q = np.asarray(f.updateIMU(q, gyr=trial.gyr[i], acc=trial.acc[i]), float)
        out[i] = q
    return quat.mul(Q_NWU_TO_ENU, out)  # back to ENU


def _wrong_start(trial):
    return quat.mul(quat.from_axis_angle(np.array([0.6, 0.0, 0.8]), 0.4), trial.q_true[0])


def test_imu_matches_ahrs_exactly():
    trial = kinematic_trial(seed=3, duration=5.0, max_rate_dps=200.0)
    q0 = _wrong_start(trial)
    ours = mg.run_madgwick(trial.gyr, trial.acc, None, trial.rate, q0=q0)
    ref = _ahrs_run(trial, q0, use_mag=False)
    ref = ref * np.sign(np.sum(ref * ours, axis=1))[:, None]
    assert np.max(np.abs(ours - ref)) < IMU_TOL


@pytest.mark.parametrize("wrong_start", [False, True])
def test_mimu_matches_ahrs(wrong_start):
    trial = kinematic_trial(seed=3, duration=10.0, max_rate_dps=200.0)
    q0 = _wrong_start(trial) if wrong_start else trial.q_true[0]
    ours = mg.run_madgwick(trial.gyr, trial.acc, trial.mag, trial.rate, q0=q0)
    ref = _ahrs_run(trial, q0, use_mag=True)
    diff = metrics.total_error(metrics.error_quaternion(ours, ref))
    judged = trial.t > 5.0 if wrong_start else slice(None)
    assert np.max(diff[judged]) < MIMU_TOL_DEG
    assert metrics.score(ours[judged], trial.q_true[judged]).total < 1.0  # and both are right


def test_gradient_is_jacobian_transpose_times_objective():
    """_grad equals the numerical gradient of ½‖q*⊗d⊗q − s‖² for arbitrary d, s (eq. 4)."""
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = quat.normalize(rng.normal(size=4))
        d, s = rng.normal(size=3), rng.normal(size=3)

        # R(q) in the unit-quaternion polynomial form, evaluated off the unit sphere too
        def u(qq):
            w, x, y, z = qq
            r = np.array(
                [
                    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
                ]
            )
            return r.T @ d

        num = np.array(
            [(0.5 * np.sum((u(q + e) - s) ** 2) - 0.5 * np.sum((u(q - e) - s) ** 2)) / 2e-6 for e in np.eye(4) * 1e-6]
        )
        ana = np.array(mg._grad(*q, *d, *s))
        assert np.allclose(ana, num, atol=1e-6)


def test_ecompass_recovers_true_orientation():
    trial = kinematic_trial(seed=1, duration=1.0, noise=False)
    for i in (0, 100, 200):
        q = mg.ecompass1(trial.acc[i], trial.mag[i])
        err = metrics.total_error(metrics.error_quaternion(q, trial.q_true[i]))
        assert err < 1e-6


def test_converges_from_wrong_start():
    """MIMU fixes a 30° error in tilt and heading; IMU fixes tilt but keeps the heading offset."""
    trial = kinematic_trial(seed=2, duration=20.0)
    wrong = quat.from_axis_angle(np.array([0.0, 0.0, 1.0]), np.deg2rad(30.0))
    tilt = quat.from_axis_angle(np.array([1.0, 0.0, 0.0]), np.deg2rad(20.0))
    q0 = quat.mul(quat.mul(wrong, tilt), trial.q_true[0])
    late = trial.t > 15.0
    mimu = mg.run_madgwick(trial.gyr, trial.acc, trial.mag, trial.rate, q0=q0)
    imu = mg.run_madgwick(trial.gyr, trial.acc, None, trial.rate, q0=q0)
    e0 = metrics.score(np.broadcast_to(q0, (1, 4)), trial.q_true[:1])
    assert e0.total > 30.0
    sm = metrics.score(mimu[late], trial.q_true[late])
    si = metrics.score(imu[late], trial.q_true[late])
    assert sm.total < 1.0
    assert si.inclination < 1.0
    assert si.heading > 20.0  # no magnetometer: heading is never corrected
