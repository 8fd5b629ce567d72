"""Shared test helpers.

``kinematic_trial`` builds a small Trial without MuJoCo: orientation
integrated from a smooth random body rate, ideal sensor readings from that
orientation plus white noise, and an optional magnetic disturbance window.
Filter tests use it where the physics of the gimbal does not matter.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magenv import quaternion as quat
from magenv.trial import Trial

BROAD_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "broad"


def kinematic_trial(
    seed: int = 0,
    duration: float = 20.0,
    rate: float = 256.0,
    max_rate_dps: float = 60.0,
    disturbance_ut: float = 0.0,
    disturbance_window: tuple[float, float] = (8.0, 12.0),
    field_norm: float = 46.0,
    field_dip: float = 49.6,
    noise: bool = True,
) -> Trial:
    """A Trial with known truth: smooth random rotation, optional constant
    magnetic disturbance (µT, earth-frame east) inside ``disturbance_window`` (s)."""
    rng = np.random.default_rng(seed)
    n = int(round(duration * rate))
    dt = 1.0 / rate
    t = np.arange(n) * dt
    # Smooth body rate: a few random sinusoids per axis, rad/s.
    freqs = rng.uniform(0.05, 0.4, size=(3, 3))
    phases = rng.uniform(0, 2 * np.pi, size=(3, 3))
    amp = np.deg2rad(max_rate_dps) / 3
    gyr = amp * np.sin(2 * np.pi * freqs[None] * t[:, None, None] + phases[None]).sum(-1)
    q = np.empty((n, 4))
    q[0] = quat.from_euler_zyx(rng.uniform(-np.pi, np.pi), rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3))
    for i in range(1, n):
        q[i] = quat.integrate_gyro1(q[i - 1], 0.5 * (gyr[i - 1] + gyr[i]), dt)
    field = np.broadcast_to(quat.earth_field(field_norm, field_dip), (n, 3)).copy()
    disturbed = (t >= disturbance_window[0]) & (t < disturbance_window[1])
    field[disturbed, 0] += disturbance_ut
    acc = quat.rotate_inv(q, np.broadcast_to(quat.gravity_up(), (n, 3)))
    mag = quat.rotate_inv(q, field)
    if noise:
        gyr = gyr + rng.normal(0, np.deg2rad(0.5), (n, 3))
        acc = acc + rng.normal(0, 0.02, (n, 3))
        mag = mag + rng.normal(0, 0.15, (n, 3))
    mag_dist = quat.rotate_inv(q, field - quat.earth_field(field_norm, field_dip))
    return Trial(
        name=f"kinematic_{seed}", rate=rate, gyr=gyr, acc=acc, mag=mag, q_true=q,
        field_norm=field_norm, field_dip=field_dip,
        truth={"mag_disturbance": mag_dist, "stationary": np.zeros(n, bool)},
        meta={"scenario": "kinematic", "seed": seed},
    )


@pytest.fixture
def make_kinematic_trial():
    """Factory fixture: ``make_kinematic_trial(seed=…, duration=…, …)``."""
    return kinematic_trial


@pytest.fixture(scope="session")
def broad_dir() -> Path:
    """Folder of the real BROAD recordings (../shared/data/broad)."""
    if not BROAD_DIR.is_dir():
        pytest.fail(f"BROAD recordings not found at {BROAD_DIR}; they live in ../shared/data/broad")
    return BROAD_DIR
