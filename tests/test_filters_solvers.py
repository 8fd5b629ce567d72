"""TRIAD and QUEST: exact on ideal vectors, noise statistics as predicted, disturbance behaviour."""

from __future__ import annotations

import numpy as np
import pytest

from magenv import metrics
from magenv import quaternion as quat
from magenv.filters import solvers
from magenv.filters.solvers import SolverError

M0, DIP = 46.0, 49.6
H_REF = quat.earth_field(M0, DIP)
G_REF = quat.gravity_up()


def random_orientations(n, seed=0):
    q = quat.normalize(np.random.default_rng(seed).normal(size=(n, 4)))
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def ideal_vectors(q, field=H_REF):
    n = len(q)
    return (quat.rotate_inv(q, np.broadcast_to(G_REF, (n, 3))), quat.rotate_inv(q, np.broadcast_to(field, (n, 3))))


@pytest.mark.parametrize("solve", [solvers.triad, solvers.quest])
def test_exact_on_known_rotations(solve):
    q = random_orientations(500)
    acc, mag = ideal_vectors(q)
    est = solve(acc, mag, H_REF)
    assert est.shape == (500, 4)
    assert np.all(est[:, 0] >= 0)
    np.testing.assert_allclose(est, q, atol=1e-9)


def test_quest_weights_are_relative_and_exact():
    q = random_orientations(50, seed=1)
    acc, mag = ideal_vectors(q)
    for w in [(0.9, 0.1), (3.0, 7.0), (1.0, 1e-6)]:
        np.testing.assert_allclose(solvers.quest(acc, mag, H_REF, weights=w), q, atol=1e-9)


def test_quest_matches_eigensolver_on_noisy_vectors():
    _, acc, mag = _noisy(200, 1.0, 5.0, seed=2)
    est = solvers.quest(acc, mag, H_REF, weights=(0.3, 0.7))
    for i in range(200):
        n = solvers.davenport_matrix1(acc[i], mag[i], G_REF, H_REF, 0.3, 0.7)
        vals, vecs = np.linalg.eigh(n)
        ref = vecs[:, 3] * np.sign(vecs[0, 3])
        np.testing.assert_allclose(est[i], ref, atol=1e-9)
        # and it really is the maximiser of the weighted gain q^T N q
        assert est[i] @ n @ est[i] == pytest.approx(vals[3], abs=1e-12)


def test_quest_tends_to_triad_when_gravity_dominates():
    _, acc, mag = _noisy(200, 0.1, 2.0, seed=3)
    err = metrics.total_error(
        metrics.error_quaternion(solvers.quest(acc, mag, H_REF, weights=(1.0, 1e-7)), solvers.triad(acc, mag, H_REF))
    )
    assert err.max() < 1e-3  # degrees


def _noisy(n, sigma_acc, sigma_mag, seed):
    rng = np.random.default_rng(seed)
    q = random_orientations(n, seed=seed)
    acc, mag = ideal_vectors(q)
    return q, acc + rng.normal(0, sigma_acc, acc.shape), mag + rng.normal(0, sigma_mag, mag.shape)


def test_triad_noise_statistics_match_first_order_prediction():
    sa, sm, n = 0.05, 0.5, 20000
    q, acc, mag = _noisy(n, sa, sm, seed=4)
    qe = metrics.error_quaternion(solvers.triad(acc, mag, H_REF), q)
    a = sa / quat.GRAVITY  # angular noise of the gravity direction per axis, rad
    h_n, dip = M0 * np.cos(np.deg2rad(DIP)), np.deg2rad(DIP)
    # inclination: two horizontal axes of gravity-direction noise;
    # heading: east noise of the horizontal field + tilt error leaking through the vertical field
    incl_pred = np.rad2deg(np.sqrt(2.0) * a)
    head_pred = np.rad2deg(np.sqrt((sm / h_n) ** 2 + (np.tan(dip) * a) ** 2))
    assert metrics.rmse(metrics.inclination_error(qe)) == pytest.approx(incl_pred, rel=0.05)
    assert metrics.rmse(metrics.heading_error(qe)) == pytest.approx(head_pred, rel=0.05)


def test_quest_noise_statistics_match_qmethod_covariance():
    sa, sm, n = 0.05, 0.5, 20000
    q, acc, mag = _noisy(n, sa, sm, seed=5)
    s_g, s_h = sa / quat.GRAVITY, sm / M0  # angular noise per axis, rad
    w = (1 / s_g**2, 1 / s_h**2)  # optimal weights
    qe = metrics.error_quaternion(solvers.quest(acc, mag, H_REF, weights=w), q)
    r1, r2 = G_REF / quat.GRAVITY, H_REF / M0
    info = w[0] * (np.eye(3) - np.outer(r1, r1)) + w[1] * (np.eye(3) - np.outer(r2, r2))
    cov = np.linalg.inv(info)  # earth-frame error-angle covariance, rad² (Shuster's QUEST model)
    assert metrics.rmse(metrics.heading_error(qe)) == pytest.approx(np.rad2deg(np.sqrt(cov[2, 2])), rel=0.05)
    assert metrics.rmse(metrics.inclination_error(qe)) == pytest.approx(
        np.rad2deg(np.sqrt(cov[0, 0] + cov[1, 1])), rel=0.05
    )


def test_magnetic_disturbance_tilts_quest_but_not_triad():
    q = random_orientations(200, seed=6)
    disturbed = H_REF + np.array([8.0, -5.0, 15.0])  # µT, changes norm, dip and heading
    acc, mag = ideal_vectors(q, field=disturbed)
    e_triad = metrics.error_quaternion(solvers.triad(acc, mag, H_REF), q)
    e_quest = metrics.error_quaternion(solvers.quest(acc, mag, H_REF), q)
    assert metrics.inclination_error(e_triad).max() < 1e-4  # degrees (acos resolution ~2e-6°)
    assert metrics.heading_error(e_triad).min() > 1.0
    assert metrics.inclination_error(e_quest).min() > 1.0


def test_broadcasts_over_leading_axes():
    q = random_orientations(12, seed=7).reshape(3, 4, 4)
    acc, mag = ideal_vectors(q.reshape(-1, 4))
    out = solvers.quest(acc.reshape(3, 4, 3), mag.reshape(3, 4, 3), H_REF)
    assert out.shape == (3, 4, 4)
    np.testing.assert_allclose(out, q, atol=1e-9)


@pytest.mark.parametrize("solve", [solvers.triad, solvers.quest])
@pytest.mark.parametrize("bad", ["zero", "parallel", "nan"])
def test_degenerate_input_raises(solve, bad):
    acc = np.tile(G_REF, (3, 1))
    mag = np.tile(H_REF, (3, 1))
    if bad == "zero":
        acc[1] = 0.0
    elif bad == "parallel":
        mag[1] = 2.0 * acc[1]
    else:
        mag[1, 2] = np.nan
    with pytest.raises(SolverError, match="row 1"):
        solve(acc, mag, H_REF)


def test_bad_shapes_and_weights_raise():
    with pytest.raises(SolverError, match="shape"):
        solvers.triad(np.zeros((3, 3)), np.zeros((4, 3)), H_REF)
    with pytest.raises(SolverError, match="weights"):
        solvers.quest(np.tile(G_REF, (2, 1)), np.tile(H_REF, (2, 1)), H_REF, weights=(-1, 1))
