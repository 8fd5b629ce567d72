"""The written-out linear algebra of the filters (magenv/filters/linalg.py) against numpy's dense products, and
the sample loops of the Kalman-family and QSF kernels allocate nothing per sample."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from magenv import quaternion as quat
from magenv.filters import linalg
from magenv.filters.kalman_threshold import is_pd

RNG = np.random.default_rng(0)


def spd(n, scale=1.0):
    a = RNG.normal(size=(n, n))
    return scale * (a @ a.T + n * np.eye(n))


def tup(m):
    return tuple(float(v) for v in np.asarray(m).ravel())


def arr(t, n=3):
    return np.array(t).reshape(n, -1)


def test_3x3_products_and_inverse():
    a, b, p = RNG.normal(size=(3, 3)), RNG.normal(size=(3, 3)), spd(3)
    v = RNG.normal(size=3)
    np.testing.assert_allclose(arr(linalg.mul33(tup(a), tup(b))), a @ b, rtol=1e-14)
    np.testing.assert_allclose(arr(linalg.mul33t(tup(a), tup(b))), a @ b.T, rtol=1e-14)
    np.testing.assert_allclose(linalg.mv3(tup(a), tuple(v)), a @ v, rtol=1e-14)
    np.testing.assert_allclose(linalg.quad3(tuple(v), tup(p)), v @ p @ v, rtol=1e-14)
    sw = arr(linalg.sandwich3(tup(a), tup(p)))
    np.testing.assert_allclose(sw, a @ p @ a.T, rtol=1e-13)
    np.testing.assert_array_equal(sw, sw.T)  # one triangle, mirrored
    np.testing.assert_allclose(arr(linalg.inv3(tup(a))), np.linalg.inv(a), rtol=1e-12)
    inv = arr(linalg.inv3(tup(p)))
    np.testing.assert_array_equal(inv, inv.T)  # a symmetric matrix's adjugate is exactly symmetric
    np.testing.assert_allclose(arr(linalg.skew3(tuple(v))) @ b[0], np.cross(v, b[0]), rtol=1e-14)


def test_joseph3_is_the_joseph_form_for_any_gain():
    p, h, k, r = spd(3), RNG.normal(size=(3, 3)), RNG.normal(size=(3, 3)), 0.3
    ikh = np.eye(3) - k @ h
    want = ikh @ p @ ikh.T + r * k @ k.T
    got = arr(linalg.joseph3(tup(p), tup(k), tup(h), r))
    np.testing.assert_allclose(got, want, rtol=1e-12)
    np.testing.assert_array_equal(got, got.T)
    np.testing.assert_allclose(arr(linalg.innovation_cov3(tup(p), tup(h), r)), h @ p @ h.T + r * np.eye(3), rtol=1e-13)


def test_inv4():
    for a in (RNG.normal(size=(4, 4)), spd(4, 1e-6)):
        out = np.empty((4, 4))
        linalg.inv4(a, out)
        np.testing.assert_allclose(out @ a, np.eye(4), atol=1e-10)
    out = np.empty((4, 4))
    linalg.inv4(np.ones((4, 4)), out)
    assert not np.all(np.isfinite(out))  # singular: not a silent finite answer


@pytest.mark.parametrize("n", [11, 15])
def test_joseph_update_low_rank_equals_the_dense_product(n):
    p, h = spd(n, 1e-3), RNG.normal(size=(3, n))
    k = RNG.normal(size=(n, 3)) * 1e-2
    r = 0.7
    s = h @ p @ h.T + r * np.eye(3)
    ikh = np.eye(n) - k @ h
    want = ikh @ p @ ikh.T + r * k @ k.T
    big = np.zeros((15, 15))
    big[:n, :n] = p
    hp = np.zeros((3, 15))
    hp[:, :n] = h @ p
    kt = np.zeros((3, 15))
    kt[:, :n] = k.T
    linalg.joseph_update(big, n, hp, kt, tup(s), np.empty((4, 15)))
    np.testing.assert_allclose(big[:n, :n], want, rtol=1e-10, atol=1e-16)
    np.testing.assert_array_equal(big, big.T)
    assert np.all(big[n:, :] == 0.0) and np.all(big[:, n:] == 0.0)  # outside the leading block: untouched


def test_project_quaternion_equals_the_dense_projection():
    n, off, eps = 15, 11, 1e-12
    p = spd(n, 1e-4)
    q = quat.normalize1(RNG.normal(size=4))
    t = np.eye(n)
    t[off : off + 4, off : off + 4] -= np.outer(q, q)
    want = t @ p @ t.T
    want[off : off + 4, off : off + 4] += eps * np.outer(q, q)
    got = p.copy()
    linalg.project_quaternion(got, n, q, off, eps)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-18)
    np.testing.assert_array_equal(got, got.T)
    assert abs(q @ got[off : off + 4, off : off + 4] @ q - eps) < 1e-15  # only eps left along q


def test_is_pd3_decides_as_the_cholesky_test():
    lo = np.empty((3, 3))
    for _ in range(200):
        a = RNG.normal(size=(3, 3))
        p = a @ a.T - RNG.uniform(0.0, 1.0) * np.eye(3)  # about half of them not positive definite
        assert linalg.is_pd3(tup(p)) == is_pd(p, 3, lo) == (np.linalg.eigvalsh(p).min() > 0)


def test_tuple_quaternion_kernels_are_the_array_kernels():
    a, b, v = quat.normalize1(RNG.normal(size=4)), quat.normalize1(RNG.normal(size=4)), RNG.normal(size=3)
    np.testing.assert_array_equal(quat.mul4(a, b), quat.mul1(a, b))
    np.testing.assert_array_equal(quat.rotate3(a, v), quat.rotate1(a, v))
    np.testing.assert_array_equal(quat.rotate_inv3(a, v), quat.rotate_inv1(a, v))
    np.testing.assert_array_equal(quat.from_rotvec4(v), quat.from_rotvec1(v))
    np.testing.assert_array_equal(quat.normalize4(3.0 * a), quat.normalize1(3.0 * a))
    np.testing.assert_allclose(np.array(quat.left_matrix4(a)) @ b, quat.mul1(a, b), rtol=1e-14)
    np.testing.assert_allclose(np.array(quat.right_matrix4(b)) @ a, quat.mul1(a, b), rtol=1e-14)


ALLOCATIONS = textwrap.dedent(
    """
    import json
    import numpy as np
    from numba.core.runtime import rtsys
    from magenv.envs import kalman as ek
    from magenv.filters import kalman_model as km, kalman_threshold as kth, kalman_trust as kt, qsf
    from magenv.filters.sensors import Sensors
    from tests_conftest_trial import trial

    def allocations(f):
        f()
        a = rtsys.get_allocation_stats().alloc
        f()
        return rtsys.get_allocation_stats().alloc - a

    counts = {}
    for n in (300, 1200):
        t = trial(n)
        s = Sensors.of(t)
        kp = kt.make_params(t.field_norm, t.field_dip, t.dt)
        q, sig = np.empty((n, 4)), np.empty((n, kt.NSIG))
        vp, md = ek.make_model_params(kp), np.empty(n)
        tp = kth.ThresholdKF("quest").params(t.field_norm, t.field_dip, t.dt)
        ok1, ok2 = np.zeros(n, bool), np.zeros(n, bool)
        mp = km.ModelKF("triad").params(t.field_norm, t.field_dip, t.dt)
        xa, xm, gm = np.empty((n, 6)), np.empty((n, 6)), np.empty(n)
        codes = np.where(np.arange(n) % 8 == 0, 1, 2).astype(np.int8)
        inputs, out = qsf.Inputs(t.gyr, t.acc, t.mag, codes, np.full(n, 0.5)), qsf.Outputs.empty(n)
        qp = qsf.make_params(t.field_norm, t.field_dip)
        code, spread = np.zeros(n, np.int8), np.empty(n)
        counts[n] = [
            allocations(lambda: kt.run_k_kernel(kp, kt.init(kp, t.acc[0], t.mag[0]), s, 1, n, 0.5, q, sig)),
            allocations(lambda: ek.model_disturbance(vp, s, md)),
            allocations(lambda: kth.run_kernel(tp, s, q, ok1, ok2)),
            allocations(lambda: km.run_kernel(mp, s, q, xa, xm, gm)),
            allocations(lambda: qsf.run_kernel(qp, qsf.initial_state(t.q_true[0], t.dt), inputs, t.dt, 0, n, out)),
            allocations(lambda: qsf.detect_kernel(t.gyr, t.mag, t.dt, 50, 1.0, 2.0, 1000, code, spread)),
        ]
    print(json.dumps([counts[300], counts[1200]]))
    """
)


def test_sample_loops_allocate_nothing_per_sample(tmp_path):
    """The NRT allocation count of each kernel over a trial does not grow with the trial's length (numba's
    allocation statistics need NUMBA_NRT_STATS at start-up: a subprocess)."""
    (tmp_path / "tests_conftest_trial.py").write_text(
        "from conftest import kinematic_trial\n\n"
        "def trial(n):\n"
        "    return kinematic_trial(seed=3, duration=n / 100.0, rate=100.0, disturbance_ut=20.0)\n"
    )
    tests = os.path.dirname(os.path.abspath(__file__))
    env = {**os.environ, "NUMBA_NRT_STATS": "1", "PYTHONPATH": os.pathsep.join([str(tmp_path), tests])}
    done = subprocess.run([sys.executable, "-c", ALLOCATIONS], capture_output=True, text=True, env=env, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    short, long = json.loads(done.stdout.strip().splitlines()[-1])
    assert short == long, f"allocations over 300 and 1200 samples: {short} vs {long}"
