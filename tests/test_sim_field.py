"""The magnet's closed-form dipole field against magpylib's exact cylinder field.

Claim (stated in magenv.sim.magnet and the report): for the paper's disc
(Ø15 mm × 2 mm, Br 1.25 T), over all directions, the dipole agrees with the
exact field within 3.5 % beyond 5 cm, 2 % beyond 7 cm and 1 % beyond 10 cm.
The error of a point dipole for a finite axisymmetric magnet falls as
(R/r)² (the next multipole, the octupole), which the last test checks.
"""

from __future__ import annotations

import numpy as np
import pytest

from magenv import quaternion as quat
from magenv.sim import earth
from magenv.sim.magnet import MU0, DiscMagnet, dipole_field

magpy = pytest.importorskip("magpylib")


def _directions(n=400, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _rel_error(magnet: DiscMagnet, r: float, axis=(0.0, 0.0, 1.0)) -> float:
    """Max relative error |B_dip − B_exact| / |B_exact| over directions at distance r."""
    pts = _directions() * r
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    exact = magpy.magnet.Cylinder(polarization=(0, 0, magnet.remanence), dimension=(magnet.diameter, magnet.thickness))
    # Rotate the cylinder so that its axis points along `axis`.
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, axis)
    if np.linalg.norm(v) > 1e-12:
        from scipy.spatial.transform import Rotation

        exact.rotate(Rotation.from_rotvec(v / np.linalg.norm(v) * np.arccos(np.clip(axis @ z, -1, 1))))
    b_exact = exact.getB(pts) * 1e6  # T → µT
    b_dip = dipole_field(pts, np.broadcast_to(magnet.moment * axis, pts.shape).copy())
    return float(np.max(np.linalg.norm(b_dip - b_exact, axis=1) / np.linalg.norm(b_exact, axis=1)))


@pytest.mark.parametrize("r, tol", [(0.05, 0.035), (0.07, 0.02), (0.10, 0.01), (0.30, 0.002)])
def test_dipole_matches_exact_cylinder_beyond_distance(r, tol):
    assert _rel_error(DiscMagnet(), r) < tol


def test_dipole_fails_close_to_the_magnet():
    # At 2 cm (1.3 magnet diameters) a point dipole is a poor model: > 15 % off.
    assert _rel_error(DiscMagnet(), 0.02) > 0.15


def test_dipole_error_falls_as_inverse_square_of_distance():
    e1, e2 = _rel_error(DiscMagnet(), 0.08), _rel_error(DiscMagnet(), 0.16)
    assert e1 / e2 == pytest.approx(4.0, rel=0.15)


def test_dipole_agrees_for_a_tilted_magnet():
    assert _rel_error(DiscMagnet(remanence=1.3), 0.1, axis=(1.0, -0.5, 0.3)) < 0.01


def test_moment_from_remanence_and_volume():
    m = DiscMagnet(diameter=0.015, thickness=0.002, remanence=1.25)
    volume = np.pi * 0.0075**2 * 0.002
    assert m.moment == pytest.approx(1.25 * volume / MU0)
    assert 0.3 < m.moment < 0.4  # A·m², a ~N40 disc of this size
    assert 2.0e-3 < m.mass < 3.0e-3  # "a 3 g magnet"


def test_dipole_axial_field_is_twice_the_equatorial():
    m = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    b = dipole_field(np.array([[0.0, 0.0, 0.1], [0.1, 0.0, 0.0]]), m)
    assert b[0, 2] == pytest.approx(-2.0 * b[1, 2])
    assert b[0, 2] == pytest.approx(1e-7 * 2 / 0.1**3 * 1e6)  # µ0/(4π)·2m/r³ in µT


@pytest.mark.parametrize("bad", [dict(diameter=0.0), dict(thickness=-1.0), dict(remanence=float("nan"))])
def test_disc_magnet_rejects_bad_sizes(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        DiscMagnet(**bad)


def test_earth_field_presets_have_the_stated_dip():
    for norm, dip in (earth.PAPER, earth.BERLIN):
        b = quat.earth_field(norm, dip)
        assert np.linalg.norm(b) == pytest.approx(norm)
        assert earth.dip_angle(b) == pytest.approx(dip)
