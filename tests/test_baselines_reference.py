"""Outside reference estimators (VQF, x-io Fusion) on simulated and real trials."""

from __future__ import annotations

import numpy as np
import pytest

from magenv import metrics
from magenv.baselines.reference import FusionEstimator, VQFEstimator, methods
from magenv.protocols import Estimate, Estimator
from magenv.recordings import find_recording, load_recording

CONVERGED_S = 5.0  # s; Fusion's start-up ramp is 3 s, VQF converges faster


def _score_after(trial, q, start=CONVERGED_S):
    return metrics.score(q, trial.q_true, trial.t >= start)


def test_methods_registry():
    reg = methods()
    assert set(reg) == {"vqf", "fusion"}
    for factory in reg.values():
        assert isinstance(factory(), Estimator)


@pytest.mark.parametrize("name", ["vqf", "fusion"])
@pytest.mark.parametrize("rate", [100.0, 256.0])
def test_close_to_truth_on_kinematic_trial(make_kinematic_trial, name, rate):
    trial = make_kinematic_trial(seed=1, duration=20.0, rate=rate)
    est = methods()[name]().run(trial)
    assert isinstance(est, Estimate)
    assert est.q.shape == (trial.n, 4) and est.trust.shape == (trial.n,)
    np.testing.assert_allclose(np.linalg.norm(est.q, axis=1), 1.0, atol=1e-6)
    s = _score_after(trial, est.q)
    # measured: ≤ 0.37° total at 100 Hz, ≤ 0.15° at 256 Hz; a wrong frame gives ~90°
    assert s.total < 1.0 and s.heading < 1.0, s


def test_fusion_frame_is_enu_not_nwu(make_kinematic_trial):
    """A level sensor facing north (sensor y = north) at rest is the identity in ENU."""
    trial = make_kinematic_trial(seed=0, duration=6.0, rate=100.0, noise=False)
    trial.gyr[:] = 0.0
    trial.acc[:] = [0.0, 0.0, 9.81]
    trial.mag[:] = [0.0, 30.0, -35.0]
    q = FusionEstimator().run(trial).q[-1]
    assert abs(q[0]) == pytest.approx(1.0, abs=1e-3), q
    q = VQFEstimator().run(trial).q[-1]
    assert abs(q[0]) == pytest.approx(1.0, abs=1e-3), q


def test_rejection_helps_under_disturbance(make_kinematic_trial):
    """A 30 µT, 5 s disturbance: both filters with rejection stay < 1° RMSE and
    report trust 0 inside it; with rejection off their heading error is several degrees."""
    trial = make_kinematic_trial(seed=1, duration=30.0, disturbance_ut=30.0, disturbance_window=(15.0, 20.0))
    inside = (trial.t >= 15.0) & (trial.t < 20.0)
    for on, off in (
        (VQFEstimator(), VQFEstimator(magDistRejectionEnabled=False)),
        (FusionEstimator(), FusionEstimator(magnetic_rejection=0.0)),
    ):
        est_on, est_off = on.run(trial), off.run(trial)
        s_on, s_off = _score_after(trial, est_on.q), _score_after(trial, est_off.q)
        assert s_on.total < 1.0, (on, s_on)
        assert s_off.heading > 5.0, (off, s_off)
        assert est_on.trust[inside].mean() < 0.1 and np.all(est_off.trust == 1.0)


@pytest.fixture(scope="module")
def trial02(broad_dir):
    return load_recording(find_recording("02", broad_dir))


def test_vqf_estimator_on_real_recording(trial02):
    s = metrics.score(VQFEstimator().run(trial02).q, trial02.q_true, trial02.score_mask)
    assert s.total == pytest.approx(1.38, abs=0.05) and s.heading == pytest.approx(1.31, abs=0.05)
    s = metrics.score(VQFEstimator(magDistRejectionEnabled=False).run(trial02).q, trial02.q_true, trial02.score_mask)
    assert s.total == pytest.approx(1.40, abs=0.05)


def test_fusion_estimator_on_real_recording(trial02):
    # measured 1.37° total (VQF 1.38°): an undisturbed slow trial, both filters alike
    s = metrics.score(FusionEstimator().run(trial02).q, trial02.q_true, trial02.score_mask)
    assert s.total < 2.5 and s.inclination < 1.0, s


def test_clear_error_without_the_optional_packages(monkeypatch):
    import importlib

    real = importlib.import_module

    def fake_import_module(name, *args, **kwargs):
        if name in ("vqf", "imufusion"):
            raise ImportError(f"No module named {name!r}")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(importlib, "import_module", fake_import_module)
    for cls in (VQFEstimator, FusionEstimator):
        with pytest.raises(ImportError, match=r"pip install magenv\[reference\]"):
            cls()
