"""Hand-crafted λ rules and the method registry."""

from __future__ import annotations

import numpy as np
import pytest

from magenv import registry
from magenv.baselines import rules
from magenv.envs.blend import FEATURES, MagBlendEnv
from magenv.protocols import Estimator, Policy
from tests.conftest import kinematic_trial

IX = {f: i for i, f in enumerate(FEATURES.names)}


def _obs(norm_dev=0.0, dip_dev_deg=0.0):
    o = np.zeros(len(FEATURES.names), np.float32)
    o[IX["norm_dev"]] = norm_dev
    o[IX["dip_dev"]] = dip_dev_deg / 90.0
    return o


def test_fan_lambda_equations_15_to_17():
    fan = rules.FanLambda()  # m0-relative norm tolerance 1, th_dip = 20°
    assert fan(_obs()) == pytest.approx([0.0])
    # λ1 = 0.23, λ2 = 10/20 = 0.5 → λ = 0.365
    assert fan(_obs(norm_dev=-0.23, dip_dev_deg=10.0))[0] == pytest.approx(0.365, abs=1e-6)
    # each part saturates at 1
    assert fan(_obs(norm_dev=3.0, dip_dev_deg=-45.0))[0] == pytest.approx(1.0)
    assert fan(_obs(norm_dev=0.0, dip_dev_deg=80.0))[0] == pytest.approx(0.5)
    tight = rules.FanLambda(norm_tol=0.1, th_dip_deg=5.0)
    assert tight(_obs(norm_dev=0.05, dip_dev_deg=2.5))[0] == pytest.approx(0.5, abs=1e-6)


def test_threshold_rule():
    th = rules.Threshold(norm_th=0.05, dip_th_deg=5.0)
    assert th(_obs(0.04, 4.9))[0] == 0.0
    assert th(_obs(-0.06, 0.0))[0] == 1.0
    assert th(_obs(0.0, -5.1))[0] == 1.0


def test_constant_and_protocol():
    for lam in (0.0, 0.4, 1.0):
        p = rules.ConstantLambda(lam)
        assert isinstance(p, Policy) and p.env_id == "magenv/MagBlend-v0"
        out = p(_obs(5.0, 50.0))
        assert out.dtype == np.float32 and out.shape == (1,) and out[0] == np.float32(lam)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        rules.ConstantLambda(1.5)


def test_params_round_trip_and_bounds():
    for cls in (rules.FanLambda, rules.Threshold, rules.ConstantLambda):
        default = cls()
        assert set(default.params) == set(cls.PARAM_BOUNDS)
        for name, (lo, hi) in cls.PARAM_BOUNDS.items():
            assert lo <= default.params[name] <= hi  # published values lie inside the tuning box
        again = cls.from_params(default.params)
        assert again.params == default.params
    with pytest.raises(ValueError, match="no parameter"):
        rules.FanLambda.from_params({"th_dip_deg": 10.0, "bogus": 1.0})


def test_rules_work_on_a_feature_subset():
    fan = rules.FanLambda(features=["dip_dev", "norm_dev"])
    assert fan.env_kwargs == {"features": ["dip_dev", "norm_dev"]}
    assert fan(np.array([10 / 90, 0.23], np.float32))[0] == pytest.approx(0.365, abs=1e-6)
    with pytest.raises(ValueError, match="needs observation feature"):
        rules.FanLambda(features=["norm_dev"])


def test_fan_lambda_in_env_reproduces_the_paper_rule_per_sample():
    """With one decision per sample, λ_t is eqs. 15–18 on sample t's field with the estimate q_{t−1}."""
    trial = kinematic_trial(seed=4, duration=4.0, disturbance_ut=25.0, disturbance_window=(1.0, 3.0))
    env = MagBlendEnv(scenario=[trial], decision_every=1, stationary_hold=False)
    fan = rules.FanLambda()
    obs, _ = env.reset(seed=0)
    trunc = False
    while not trunc:
        obs, _, _, trunc, _ = env.step(fan(obs))
    q_prev = np.vstack([env.unwrapped._runner.q0[None], env.estimate[:-1]])
    from magenv import quaternion as quat

    h = quat.rotate(q_prev, trial.mag)
    dip = np.rad2deg(np.arcsin(-h[:, 2] / np.linalg.norm(h, axis=1)))
    lam1 = np.minimum(np.abs(np.linalg.norm(trial.mag, axis=1) - 46.0) / 46.0, 1.0)
    lam2 = np.minimum(np.abs(dip - 49.6) / 20.0, 1.0)
    expected = 0.5 * (lam1 + lam2)
    np.testing.assert_allclose(env.lambdas, expected, atol=1e-6)  # float32 action
    assert expected.max() > 0.2  # the disturbance does raise λ


def test_fan_lambda_reduces_the_disturbance_error():
    trial = kinematic_trial(seed=6, duration=10.0, disturbance_ut=30.0, disturbance_window=(3.0, 8.0))
    from magenv.evaluation import run_policy_on_trials

    (fan,) = run_policy_on_trials(rules.FanLambda(), [trial])
    (mimu,) = run_policy_on_trials(registry.make("mimu"), [trial])
    (imu,) = run_policy_on_trials(registry.make("imu"), [trial])
    assert fan.total < mimu.total
    assert imu.total < fan.total  # a strong disturbance: the IMU filter is best on this short trial


def test_registry_names_make_and_errors():
    names = registry.names()
    for n in ("mimu", "imu", "fan_lambda", "threshold"):
        assert n in names
        assert isinstance(registry.make(n), Policy)
    assert registry.make("mimu").env_kwargs == {"stationary_hold": False}
    with pytest.raises(ValueError, match="known methods: .*fan_lambda"):
        registry.make("no_such_method")
    assert registry.rule_class("fan_lambda") is rules.FanLambda
    with pytest.raises(ValueError, match="known rules"):
        registry.rule_class("nope")


def test_register_is_one_line():
    from magenv.filters.blend import BlendEstimator

    registry.register("test_blend_half", lambda: BlendEstimator(0.5), overwrite=True)
    try:
        assert "test_blend_half" in registry.names()
        assert isinstance(registry.make("test_blend_half"), Estimator)
        with pytest.raises(ValueError, match="already registered"):
            registry.register("test_blend_half", lambda: BlendEstimator(0.5))
    finally:
        registry._REGISTERED.pop("test_blend_half", None)


def test_tuned_rules_are_discovered(tmp_path, monkeypatch):
    import json

    monkeypatch.setenv(registry.DATA_DIR_ENV, str(tmp_path))
    registry.user_tuned_dir().mkdir(parents=True)
    (registry.user_tuned_dir() / "fan_lambda.json").write_text(
        json.dumps({"params": {"norm_tol": 0.2, "th_dip_deg": 7.0}})
    )
    assert "fan_lambda_tuned" in registry.names()
    tuned = registry.make("fan_lambda_tuned")
    assert tuned.params == {"norm_tol": 0.2, "th_dip_deg": 7.0}
