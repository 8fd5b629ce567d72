"""VQF as numba kernels (``magenv.filters.vqf``) against the ``vqf`` package's C++ filter, the reference."""

from __future__ import annotations

import numpy as np
import pytest
import vqf as vqf_cpp

from magenv import metrics
from magenv.envs.vqf import MagVQFEnv
from magenv.filters import vqf
from magenv.recordings import load_recording
from magenv.scenarios import make_trial
from tests.conftest import BROAD_NAMES, kinematic_trial

OPTIONS = {  # VQF as published, without its rejection, and with the rejection neutral (MagVQF-v0's "off")
    "on": vqf.Options(),
    "disabled": vqf.Options(mag_rejection=False),
    "neutral": vqf.Options(mag_max_rejection_time=-1.0, mag_rejection_factor=1.0),
}
TOL_RAD = 1e-6  # the parity target (in fact the kernels agree bit for bit on these inputs)


def _cpp(trial, options, trust=None, k=32):
    """The C++ filter over ``trial``: one updateBatch, or windows of ``k`` samples at the trusts ``trust``."""
    f = vqf_cpp.VQF(trial.dt, trial.dt, trial.dt, **options.cpp_kwargs())
    g, a, m = (np.ascontiguousarray(x) for x in (trial.gyr, trial.acc, trial.mag))
    if trust is None:
        return f.updateBatch(g, a, m)["quat9D"]
    out = []
    for w, start in enumerate(range(0, trial.n, k)):
        f.setTauMag(vqf.tau_of_trust(trust[w], options.tau_mag, trial.dt))
        out.append(f.updateBatch(g[start : start + k], a[start : start + k], m[start : start + k])["quat9D"])
    return np.concatenate(out)


def _angle_rad(q, ref):
    """Largest angle (rad) between two quaternion histories, from the components (no acos floor)."""
    d = np.abs(np.sum(q * ref, axis=1)).clip(max=1.0)
    return float(np.max(2.0 * np.sqrt(np.maximum(0.0, 2.0 * (1.0 - d)))))


@pytest.mark.parametrize("name", BROAD_NAMES, ids=lambda n: n[:2])
def test_the_kernels_are_the_cpp_filter_on_every_shared_recording(name, broad_dir):
    trial = load_recording(broad_dir / name)
    for name, options in OPTIONS.items():
        out = vqf.VQFFilter(options).run(trial.gyr, trial.acc, trial.mag, trial.dt)
        assert _angle_rad(out["quat9D"], _cpp(trial, options)) <= TOL_RAD, name


@pytest.mark.parametrize("scenario", ["dynamic_magnet", "stationary_magnet", "random", "handheld_free"])
def test_the_kernels_are_the_cpp_filter_on_simulated_trials(scenario):
    trial = make_trial(scenario, 3, duration=20.0)
    for name, options in OPTIONS.items():
        out = vqf.VQFFilter(options).run(trial.gyr, trial.acc, trial.mag, trial.dt)
        assert _angle_rad(out["quat9D"], _cpp(trial, options)) <= TOL_RAD, (scenario, name)


def test_a_trust_per_window_is_the_cpp_filter_with_its_tau():
    """Trust u per window of k samples: the kernel's k(u) = u·k₁ and τ(u) are VQF's setTauMag(τ(u))."""
    trial = kinematic_trial(seed=3, duration=12.0, disturbance_ut=25.0, disturbance_window=(4.0, 8.0))
    k = 32
    windows = -(-trial.n // k)
    trust = np.random.default_rng(0).choice([0.0, 0.1, 0.5, 1.0], windows)
    for name, options in OPTIONS.items():
        u = np.repeat(trust, k)[: trial.n]
        out = vqf.VQFFilter(options).run(trial.gyr, trial.acc, trial.mag, trial.dt, trust=u)
        assert _angle_rad(out["quat9D"], _cpp(trial, options, trust, k)) <= TOL_RAD, name
    ts = trial.dt
    p = vqf.make_params(ts)
    k1 = p[vqf.P.k_mag]
    assert vqf.trust_gain(p, 1.0) == (k1, 9.0) and vqf.trust_gain(p, 0.0) == (0.0, vqf.TAU_DISABLED)
    for u in (1e-6, 0.3, 0.999):
        assert vqf.trust_gain(p, u)[0] == pytest.approx(u * k1, rel=1e-12)


def test_the_env_on_the_kernels_is_the_env_on_the_cpp_filter():
    """MagVQF-v0's numba and C++ backends: the same observations, rewards and estimates at random trusts."""
    trial = make_trial("dynamic_magnet", 4, duration=15.0)
    for rejection in ("on", "off"):
        kw = {"scenario": [trial], "rejection": rejection, "decision_every": 16}
        envs = [MagVQFEnv(**kw, backend=b) for b in ("numba", "cpp")]
        obs = [e.reset(seed=0)[0] for e in envs]
        np.testing.assert_array_equal(*obs)
        rng, done = np.random.default_rng(1), False
        while not done:
            a = np.array([rng.uniform(-0.2, 1.2)], np.float32)
            (o1, r1, _, done, i1), (o2, r2, *_, i2) = (e.step(a) for e in envs)
            np.testing.assert_array_equal(o1, o2)
            assert r1 == r2 and i1["mag_dist"] == i2["mag_dist"]
        for attr in ("estimate", "trust", "vqf_gain", "mag_dist_detected"):
            np.testing.assert_array_equal(*(getattr(e.unwrapped, attr) for e in envs))


def test_state_and_parameters_are_named_vectors():
    p = vqf.make_params(0.01)
    s = vqf.init_state(p)
    assert p.shape == (vqf.PARAMS.size,) and s.shape == (vqf.STATE.size,)
    fields = vqf.STATE.view(s)
    np.testing.assert_array_equal(fields["gyr_q"], [1, 0, 0, 0])
    assert fields["mag_dist"] == 1.0 and fields["cand_norm"] == -1.0 and np.isnan(fields["lp_acc"]).all()
    assert vqf.PARAMS.view(p)["ts"] == 0.01
    assert vqf.Options().cpp_kwargs()["magDistRejectionEnabled"] is True
    assert set(vqf.Options().cpp_kwargs()) <= set(vqf_cpp.PyVQF(0.01).params.__dict__)
    for bad in ({"tau_acc": 0.0}, {"rest_th_gyr": float("nan")}, {"motion_bias": 1}):
        with pytest.raises((ValueError, TypeError), match=next(iter(bad))):
            vqf.Options(**bad)
    with pytest.raises(ValueError, match="ts"):
        vqf.make_params(0.0)


def test_a_fork_of_the_state_replays_the_same_future():
    """A copy of the state vector is a fork of the filter: both continue bit for bit alike."""
    trial = kinematic_trial(seed=4, duration=4.0)
    p, w = vqf.make_params(trial.dt), vqf.work()
    s = vqf.init_state(p)
    n = trial.n // 2
    u = np.ones(trial.n)
    bufs = lambda m: (np.empty((m, 4)), np.empty((m, 4)), np.empty(m), np.empty(m), np.empty(m))
    vqf.run(p, s, w, trial.gyr[:n], trial.acc[:n], trial.mag[:n], u[:n], *bufs(n))
    fork = s.copy()
    a, b = bufs(trial.n - n), bufs(trial.n - n)
    rest = (trial.gyr[n:], trial.acc[n:], trial.mag[n:], u[n:])
    vqf.run(p, s, w, *rest, *a)
    vqf.run(p, fork, vqf.work(), *rest, *b)
    np.testing.assert_array_equal(a[0], b[0])
    err = metrics.total_error(metrics.error_quaternion(a[0], trial.q_true[n:]))
    assert np.nanmax(err) < 5.0
