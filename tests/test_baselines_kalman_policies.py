"""Trust rules of ``magenv/MagKalman-v0`` (``magenv.baselines.kalman_policies``)."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from magenv import evaluation, registry
from magenv.baselines import kalman_policies as kp
from magenv.envs.kalman import FEATURES
from magenv.protocols import Policy
from tests.conftest import kinematic_trial

M0 = 40.0  # µT, deliberately not the default 46: rules must read m0 from the observation


def _obs(norm_ut=0.0, dip_deg=0.0, dist_ut=0.0, m0=M0, names=FEATURES.names, **extra) -> np.ndarray:
    """An observation over ``names`` (the base table by default); ``extra`` sets further features by name."""
    IX = {f: i for i, f in enumerate(names)}
    o = np.zeros(len(names), np.float32)
    for name, value in extra.items():
        o[IX[name]] = value
    o[IX["field_ref"]] = m0 / 50.0
    o[IX["norm_dev"]] = norm_ut / m0
    o[IX["dip_dev"]] = dip_deg / 90.0
    o[IX["model_dist"]] = dist_ut / m0
    return o


def _gamma(policy, obs) -> float:
    a = policy(obs)
    assert a.shape == (1,) and a.dtype == np.float32
    return float(a[0])


def test_nominal_is_full_trust():
    p = registry.make("kf_nominal")
    assert _gamma(p, _obs(norm_ut=30.0, dip_deg=40.0, dist_ut=30.0)) == 1.0


def test_gate_is_the_vector_selector_with_table_a1_thresholds():
    p = kp.GateTrust()
    assert (p.th_mag_ut, p.th_dip_deg) == (1.20, 5.0)
    assert _gamma(p, _obs(norm_ut=1.1, dip_deg=4.9)) == 1.0
    assert _gamma(p, _obs(norm_ut=-1.1, dip_deg=-4.9)) == 1.0
    assert _gamma(p, _obs(norm_ut=1.3)) == 0.0
    assert _gamma(p, _obs(norm_ut=-1.3)) == 0.0
    assert _gamma(p, _obs(dip_deg=-5.1)) == 0.0
    # the threshold is in µT at the trial's site: 1.3 µT of a 40 µT field is rejected, read via field_ref
    assert _gamma(p, _obs(norm_ut=1.3, m0=60.0)) == 0.0


def test_adaptive_formula():
    p = kp.AdaptiveTrust(sigma_mag_ut=2.0, sigma_dip_deg=4.0)
    for dm, dt in ((0.0, 0.0), (2.0, 0.0), (0.0, -4.0), (3.0, 6.0), (-10.0, 1.0)):
        expected = 1.0 / (1.0 + (dm / 2.0) ** 2 + (dt / 4.0) ** 2)
        assert _gamma(p, _obs(norm_ut=dm, dip_deg=dt)) == pytest.approx(expected, rel=1e-5)
    # defaults: γ = ½ at a Table A1 threshold
    assert _gamma(kp.AdaptiveTrust(), _obs(norm_ut=1.2)) == pytest.approx(0.5, rel=1e-5)


def test_model_formula():
    p = kp.ModelTrust(sigma_dist_ut=3.0)
    for d in (0.0, 1.5, 3.0, 12.0):
        assert _gamma(p, _obs(dist_ut=d, norm_ut=50.0)) == pytest.approx(1.0 / (1.0 + (d / 3.0) ** 2), rel=1e-5)


PULL_RULES = [  # (rule, its base rule's input, observation where it takes the base γ, where the pull gate judges)
    (
        kp.StillPullTrust(sigma_mag_ut=2.0, sigma_dip_deg=4.0, pull_min_deg=0.5, gamma_pull=0.6),
        "norm_ut",
        {"t_anchor": 0.0},  # clean now: the anchor is this sample
        {"t_anchor": 0.5},
    ),
    (
        kp.PerpPullTrust(sigma_dist_ut=2.0, pull_min_deg=0.5, gamma_pull=0.6, info_min=0.2),
        "dist_ut",
        {"perp_info": 0.1},  # d_perp sees too little heading to judge
        {"perp_info": 0.2},  # at i_min it judges
    ),
]


@pytest.mark.parametrize(("rule", "term", "base", "judged"), PULL_RULES, ids=["kf_still", "kf_perp"])
def test_pull_gated_rules(rule, term, base, judged):
    """kf_still and kf_perp: their base rule's γ (kf_adaptive's, kf_model's) where the gate is open, else at least
    γ_pull where a full update pulls the heading the right way by more than p_min, else 0."""
    assert rule.env_kwargs == {"features": list(type(rule).FEATURES)}
    pull_feature = "pull_perp" if isinstance(rule, kp.PerpPullTrust) else "pull_still"

    def gamma(at, pull, size=3.0):
        return _gamma(rule, _obs(names=rule.features, **{term: size, **at, pull_feature: pull}))

    assert gamma(base, -20.0) == pytest.approx(1.0 / (1.0 + (3.0 / 2.0) ** 2), rel=1e-5)
    assert gamma(judged, 0.6) == pytest.approx(0.6, rel=1e-5)  # pulled the right way: γ_pull ≥ the base γ
    assert gamma(judged, 0.6, size=0.5) == pytest.approx(1.0 / (1.0 + 0.25**2), rel=1e-5)  # base γ > γ_pull
    assert gamma(judged, 0.5) == 0.0 and gamma(judged, -3.0) == 0.0  # a pull of p_min or less: refused
    with pytest.raises(ValueError, match="gamma_pull"):
        type(rule)(gamma_pull=1.5)
    with pytest.raises(ValueError, match=pull_feature):
        type(rule)(features=list(FEATURES.names))


def test_perp_info_must_be_a_fraction():
    with pytest.raises(ValueError, match="info_min"):
        kp.PerpPullTrust(info_min=1.5)


@pytest.mark.parametrize("cls", list(kp.RULES.values()))
def test_params_round_trip_and_protocol(cls):
    p = cls()
    extended = getattr(cls, "FEATURES", None)  # a rule reading memory features asks the env for them
    assert isinstance(p, Policy) and p.env_id == "magenv/MagKalman-v0"
    assert p.env_kwargs == ({} if extended is None else {"features": list(extended)})
    for k, (lo, hi) in cls.PARAM_BOUNDS.items():
        assert lo <= p.params[k] <= hi
    q = cls.from_params(p.params)
    assert q.params == p.params
    rng = np.random.default_rng(0)
    for _ in range(20):
        o = _obs(norm_ut=rng.normal(0, 5), dip_deg=rng.normal(0, 10), dist_ut=abs(rng.normal(0, 5)), names=p.features)
        g = _gamma(p, o)
        assert 0.0 <= g <= 1.0 and g == _gamma(q, o)
    with pytest.raises(ValueError, match="no parameter"):
        cls.from_params({"bogus": 1.0})


def test_bad_parameters_and_missing_features():
    with pytest.raises(ValueError):
        kp.GateTrust(th_mag_ut=0.0)
    with pytest.raises(ValueError):
        kp.AdaptiveTrust(sigma_dip_deg=-1.0)
    with pytest.raises(ValueError):
        kp.ConstantTrust(gamma=1.5)
    with pytest.raises(ValueError, match="model_dist"):
        kp.ModelTrust(features=["norm_dev", "field_ref"])
    with pytest.raises(ValueError, match="field_ref"):
        kp.GateTrust(features=["norm_dev", "dip_dev"])
    sub = kp.GateTrust(features=["dip_dev", "field_ref", "norm_dev"])
    assert sub.env_kwargs == {"features": ["dip_dev", "field_ref", "norm_dev"]}
    o = np.array([6.0 / 90.0, 0.92, 0.0], np.float32)
    assert _gamma(sub, o) == 0.0


def test_registry_lists_the_methods():
    names = registry.names()
    for n in ("kf_nominal", "kf_gate", "kf_adaptive", "kf_model", "kf_still", "kf_perp"):
        assert n in names


def test_compare_runs_the_rules_and_gating_beats_nominal():
    """On a short strong disturbance the gate and the adaptive rule beat the nominal filter by far."""
    trials = [
        kinematic_trial(seed=s, duration=8.0, disturbance_ut=25.0, disturbance_window=(3.0, 6.0)) for s in range(2)
    ]
    runs = evaluation.evaluate(
        {n: registry.make(n) for n in ["kf_nominal", "kf_gate", "kf_adaptive", "kf_model"]}, trials
    )
    rows = {r["method"]: r for r in evaluation.summarize(runs)}
    assert set(rows) == {"kf_nominal", "kf_gate", "kf_adaptive", "kf_model"}
    assert all(r["n"] == 2 for r in rows.values())
    assert rows["kf_gate"]["total_rmse_mean"] < 0.3 * rows["kf_nominal"]["total_rmse_mean"]
    assert rows["kf_adaptive"]["total_rmse_mean"] < rows["kf_nominal"]["total_rmse_mean"]
    for r in runs:  # evaluation's trust (1 − λ) is the γ history, in [0, 1]
        assert r.trust.shape == (r.trial.n,) and np.all((r.trust >= 0) & (r.trust <= 1))
        if r.method == "kf_nominal":
            assert np.all(r.trust == 1.0)
        if r.method == "kf_gate":  # the gate closes during the disturbance and is open before it
            t = r.trial.t
            assert np.mean(r.trust[(t > 3.1) & (t < 6.0)] == 0.0) > 0.95
            assert np.mean(r.trust[t < 2.9] == 1.0) > 0.95


def test_magenv_compare_cli_runs_the_rules(tmp_path):
    """``magenv compare`` with the trust rules on a simulated trial: one row each; all three beat γ = 1 by far."""
    pytest.importorskip("magenv.scenarios")
    from magenv.train.cli import main

    path = tmp_path / "kf.csv"
    code = main(
        [
            "compare",
            "--scenario",
            "dynamic_magnet",
            "--seeds",
            "0:1",
            "--no-progress",
            "--csv",
            str(path),
            "--methods",
            "kf_nominal,kf_gate,kf_adaptive,kf_model",
        ]
    )
    assert code == 0
    with open(path) as f:
        rows = {r["method"]: float(r["total_rmse_mean"]) for r in csv.DictReader(f)}
    assert set(rows) == {"kf_nominal", "kf_gate", "kf_adaptive", "kf_model"}
    for m in ("kf_gate", "kf_adaptive", "kf_model"):  # the sliding magnet pulls the nominal filter's heading off
        assert rows[m] < 0.5 * rows["kf_nominal"]


def test_debias_at_rest_removes_the_rest_mean():
    import dataclasses

    trial = kinematic_trial(seed=0, duration=3.0)
    bias = np.array([0.01, -0.02, 0.005])  # rad/s, below the rest detector's 2 °/s
    gyr = np.tile(bias, (trial.n, 1))
    gyr[trial.n // 2 :, 2] += 1.0  # at rest for 1.5 s, then turning
    out = kp.debias_at_rest(dataclasses.replace(trial, gyr=gyr))
    assert np.allclose(out.gyr, gyr - bias, atol=1e-12)
    short = dataclasses.replace(trial, gyr=gyr + [0.0, 0.0, 1.0])  # no rest at all: unchanged
    assert kp.debias_at_rest(short) is short


def test_hand_moved_rules_fix_the_kalman_collapse_on_a_real_recording(broad_dir):
    """BROAD 29 (a magnet at rest, a board moved by hand): the survey's accelerometer model makes the
    tuned model-based rule lose ~18°; the hand-moved options bring it to a few degrees."""
    from magenv.recordings import find_recording, load_recording

    rec = load_recording(find_recording("29", broad_dir))
    plain, hand = (registry.make(n) for n in ("kf_model_tuned", "kf_model_tuned_hand"))
    assert hand.env_kwargs["th_acc"] == float("inf") and hand.prepare_trial is kp.debias_at_rest
    runner = evaluation.PolicyRunner()
    e_plain = evaluation.run_method("p", plain, rec, runner).score.total
    e_hand = evaluation.run_method("h", hand, rec, runner).score.total
    assert e_hand < 0.5 * e_plain
