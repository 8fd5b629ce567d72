"""Physics of the MuJoCo gimbal: servos follow the commands, MuJoCo's sensors
agree with its own orientation, the magnet slides as the paper describes."""

from __future__ import annotations

import numpy as np
import pytest

from magenv import quaternion as quat
from magenv.sim import gimbal, profiles
from magenv.sim.gimbal import SimulationError, Tube, simulate_gimbal

RATE = 256.0
G = 9.81


def _spin_profile(
    duration=8.0, rates_dps=(40.0, 70.0, 360.0), phys=gimbal.PHYSICS_RATE, start=1.0, angle0=(0.3, 0.0, 0.0)
):
    p = profiles.empty_profile(duration + 0.1, phys, angle0)
    for axis, r in enumerate(rates_dps):
        if r:
            profiles.add_spin(p, axis, start, duration - 1.0, np.deg2rad(r), ramp=0.5)
    return p


def _run(p, duration, tube=None):
    return simulate_gimbal(p, tube or Tube(), RATE, int(duration * RATE))


def _body_rate(angles, rates):
    """Body-frame rate of the ZYX gimbal: ω = φ̇ e_x + R_x(φ)ᵀ θ̇ e_y + R_x(φ)ᵀ R_y(θ)ᵀ ψ̇ e_z."""
    psi_d, th_d, phi_d = rates.T
    th, phi = angles[:, 1], angles[:, 2]
    return np.stack(
        [
            phi_d - np.sin(th) * psi_d,
            np.cos(phi) * th_d + np.sin(phi) * np.cos(th) * psi_d,
            -np.sin(phi) * th_d + np.cos(phi) * np.cos(th) * psi_d,
        ],
        axis=1,
    )


def _commanded_at_samples(p, n):
    """Commanded angles and rates (n, 3) each at the sensor sample times."""
    both = gimbal.resample_cubic(np.concatenate([p.angles, p.omega], axis=1), p.rate, RATE, n, 0.0)
    return both[:, :3], both[:, 3:]


def test_gyro_equals_commanded_rates_seen_in_frame_x():
    p = _spin_profile()
    run = _run(p, 8.0)
    expected = _body_rate(*_commanded_at_samples(p, len(run.gyr)))
    err = np.rad2deg(np.linalg.norm(run.gyr - expected, axis=1))
    t = np.arange(len(err)) / RATE
    steady = (t > 2.5) & (t < 6.5)  # after the 0.5 s ramp has settled (servo ω_n ≈ 60 rad/s)
    # |ω| ≈ 370 °/s here; velocity feed-forward leaves only coupling torques: < 0.5 % of the rate.
    assert err[steady].max() < 2.0
    assert np.sqrt(np.mean(err[steady] ** 2)) < 0.5
    # During the ramps the servo lags but stays close.
    assert err.max() < 20.0


def test_joint_angles_follow_the_commanded_angles():
    p = _spin_profile()
    run = _run(p, 8.0)
    cmd = _commanded_at_samples(p, len(run.joints))[0]
    err = np.angle(np.exp(1j * (run.joints - cmd)))
    assert np.rad2deg(np.abs(err)).max() < 1.0


def test_accelerometer_reads_gravity_at_rest():
    p = profiles.empty_profile(2.1, gimbal.PHYSICS_RATE, (1.0, 0.4, -0.7))
    run = _run(p, 2.0)
    np.testing.assert_allclose(np.linalg.norm(run.acc, axis=1), G, atol=1e-4)
    # ...and points up in the world: q maps sensor → ENU.
    up = quat.rotate(run.q, run.acc)
    np.testing.assert_allclose(up, np.tile([0, 0, G], (len(up), 1)), atol=1e-3)
    # Holds the commanded angles; the servo (kp ≈ 57 N·m/rad on Y) sags under the
    # ~5 mN·m weight of tube and magnet by ~1e-4 rad: well under 0.02°.
    np.testing.assert_allclose(np.rad2deg(quat.to_euler_zyx(run.q[-1])), np.rad2deg([1.0, 0.4, -0.7]), atol=0.02)


def test_gyro_integrates_to_the_true_orientation():
    p = _spin_profile(duration=6.0)
    run = _run(p, 6.0)
    q = run.q[0].copy()
    dt = 1.0 / RATE
    for i in range(1, len(run.gyr)):
        q = quat.integrate_gyro1(q, 0.5 * (run.gyr[i - 1] + run.gyr[i]), dt)
    err = np.rad2deg(2 * np.arccos(min(1.0, abs(np.dot(q, run.q[-1])))))
    # 6 s at up to ~370 °/s with spin-up and spin-down: if gyro and orientation
    # were half a physics step apart (see gimbal._centre_gyro) this would be ~2°;
    # trapezoid integration of consistent rates at 256 Hz drifts < 0.1°.
    assert err < 0.1


def test_magnet_reciprocates_when_frame_y_turns():
    tube = Tube(length=0.1)
    p = profiles.empty_profile(12.1, gimbal.PHYSICS_RATE, (0.0, np.deg2rad(-35.0), 0.0))
    for k in range(5):  # pitch sways between −35° and +35° five times
        profiles.add_move(p, 1, 1.0 + 2 * k, 1.0, np.deg2rad(70.0))
        profiles.add_move(p, 1, 2.0 + 2 * k, 1.0, -np.deg2rad(70.0))
    run = _run(p, 12.0, tube)
    s = run.slide
    at_far, at_near = s > 0.09, s < 0.01
    assert at_far.any() and at_near.any()
    # Count end-to-end trips: ≥ 2 per sway cycle minus slack.
    state = np.where(at_far, 1, np.where(at_near, -1, 0))
    state = state[state != 0]
    trips = np.count_nonzero(np.diff(state))
    assert trips >= 8


def test_magnet_stays_when_only_frame_x_spins():
    # The tube lies along frame X's axis: spinning X leaves gravity across the tube.
    p = _spin_profile(rates_dps=(0.0, 0.0, 360.0))
    run = _run(p, 8.0, Tube(start_at=0.5))
    assert np.ptp(run.slide) < 1e-3


def test_coarse_physics_agrees_with_fine_physics():
    coarse = _run(_spin_profile(), 8.0)  # default physics rate
    fine = _run(_spin_profile(phys=1024.0), 8.0)
    t = np.arange(len(coarse.gyr)) / RATE
    steady = (t > 2.5) & (t < 6.5)
    gyr_err = np.rad2deg(np.linalg.norm(coarse.gyr - fine.gyr, axis=1))
    assert gyr_err[steady].max() < 0.5  # °/s, at ~370 °/s
    assert gyr_err.max() < 8.0  # ramps: servo lag differs with the timestep
    q_err = np.rad2deg(2 * np.arccos(np.clip(np.abs(np.sum(coarse.q * fine.q, axis=1)), 0, 1)))
    assert q_err.max() < 0.5
    np.testing.assert_allclose(np.linalg.norm(coarse.acc, axis=1), np.linalg.norm(fine.acc, axis=1), atol=0.2)


def test_skipping_settled_pauses_changes_nothing(monkeypatch):
    p = profiles.empty_profile(10.1, gimbal.PHYSICS_RATE, (0.2, 0.3, 0.1))
    profiles.add_move(p, 1, 1.0, 1.5, np.deg2rad(60.0))
    profiles.add_move(p, 0, 6.0, 1.0, np.deg2rad(-30.0))
    fast = _run(p, 10.0)
    monkeypatch.setattr(gimbal, "SETTLE_S", 1e9)  # never skip
    full = _run(p, 10.0)
    assert fast.physics_steps < 0.7 * full.physics_steps
    for key in ("gyr", "acc", "q", "p_magnet", "slide"):
        np.testing.assert_allclose(getattr(fast, key), getattr(full, key), atol=1e-6, err_msg=key)


def test_instability_is_reported():
    p = _spin_profile(duration=3.0)
    p.omega[200, 0] = np.nan  # a NaN command: MuJoCo flags bad controls
    with pytest.raises(SimulationError, match="warnings"):
        _run(p, 3.0)


def test_profile_too_short_is_an_error():
    p = profiles.empty_profile(1.0, gimbal.PHYSICS_RATE)
    with pytest.raises(ValueError, match="needs"):
        _run(p, 2.0)


@pytest.mark.parametrize("bad", [dict(length=0.0), dict(start_at=1.5), dict(dipole=(0, 0, 0)), dict(friction=-1.0)])
def test_bad_tube_is_named(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        Tube(**bad)


def test_accelerometer_sees_the_base_acceleration():
    # Mobile variant: the base runs a circle of radius R at ω; the specific force
    # in the world is the centripetal acceleration −ω²·r plus +g up.
    r, w, rate = 1.0, 1.0, gimbal.PHYSICS_RATE
    p = profiles.empty_profile(10.1, rate)
    t = np.arange(p.n) / rate
    base = np.stack(
        [r * np.cos(w * t), r * np.sin(w * t), 0 * t, -r * w * np.sin(w * t), r * w * np.cos(w * t), 0 * t], 1
    )
    run = simulate_gimbal(p, Tube(), RATE, int(10.0 * RATE), base=base)
    ts = np.arange(len(run.acc)) / RATE
    later = ts > 3.0  # the servos have caught up with the start from rest
    f_world = quat.rotate(run.q, run.acc)[later]
    expect = np.stack([-r * w**2 * np.cos(w * ts), -r * w**2 * np.sin(w * ts), np.full_like(ts, G)], 1)[later]
    np.testing.assert_allclose(f_world, expect, atol=0.01)
    np.testing.assert_allclose(
        run.p_imu[later, :2], (r * np.stack([np.cos(w * ts), np.sin(w * ts)], 1))[later], atol=2e-3
    )


@pytest.mark.parametrize("block_rows", [1, 7, 64, 250])
def test_blocks_of_any_size_give_the_same_run_bit_for_bit(block_rows):
    """gimbal_blocks in small blocks (rollouts split, gyro centring and resampling across block edges,
    settled pauses repeated in pieces) equals the run made in one block, every array bit for bit."""
    p = profiles.empty_profile(12.1, gimbal.PHYSICS_RATE, (0.3, 0.1, -0.2))
    profiles.add_spin(p, 0, 1.0, 4.0, np.deg2rad(200.0), ramp=0.5)
    profiles.add_move(p, 1, 7.5, 2.0, 0.6)  # a settled pause (4 … 7.5 s) before it
    n = int(12.0 * RATE)
    whole = simulate_gimbal(p, Tube(), RATE, n)
    parts = list(gimbal.gimbal_blocks(p, Tube(), RATE, n, block_rows=block_rows))
    assert len(parts) > 1 and [i0 for i0, _ in parts] == sorted({i0 for i0, _ in parts})
    assert parts[-1][1].physics_steps == whole.physics_steps
    for key in ("gyr", "acc", "q", "p_imu", "p_magnet", "m_axis", "joints", "slide"):
        joined = np.concatenate([getattr(run, key) for _, run in parts])
        assert np.array_equal(joined, getattr(whole, key)), key
