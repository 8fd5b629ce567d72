"""``magenv.evaluation`` and ``magenv compare``."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from magenv import evaluation, metrics, registry
from magenv.filters.blend import BlendEstimator
from magenv.train.cli import main
from tests.conftest import kinematic_trial

HEADER = "method,scenario,n,total_rmse_mean,total_rmse_std,heading_rmse_mean,inclination_rmse_mean"


@pytest.fixture(scope="module")
def trials():
    return [kinematic_trial(seed=s, duration=4.0, disturbance_ut=25.0, disturbance_window=(1.0, 3.0)) for s in range(3)]


def test_compare_rows_and_csv(trials, tmp_path):
    rows = evaluation.compare({n: registry.make(n) for n in ["mimu", "imu", "fan_lambda"]}, trials)
    assert {r["method"] for r in rows} == {"mimu", "imu", "fan_lambda"}
    assert all(r["n"] == 3 and r["scenario"] == "kinematic" for r in rows)
    # the table's numbers are the metrics module's, trial by trial
    mimu = registry.make("mimu")
    per_trial = [evaluation.run_method("mimu", mimu, t).score.total for t in trials]
    row = next(r for r in rows if r["method"] == "mimu")
    assert row["total_rmse_mean"] == pytest.approx(np.mean(per_trial))
    assert row["total_rmse_std"] == pytest.approx(np.std(per_trial, ddof=1))
    path = evaluation.write_csv(rows, tmp_path / "t.csv")
    lines = path.read_text().splitlines()
    assert lines[0] == HEADER
    assert len(lines) == 4


def test_policy_and_estimator_paths_agree(trials):
    """A constant-λ policy in the env and the offline estimator give the same estimate."""
    from magenv.baselines.rules import ConstantLambda

    runs = evaluation.evaluate({"pol": ConstantLambda(0.0), "est": BlendEstimator(0.0)}, trials[:1])
    np.testing.assert_array_equal(runs[0].q, runs[1].q)
    assert runs[0].lam is not None and runs[1].lam is None
    s = metrics.score(runs[1].q, trials[0].q_true, trials[0].score_mask)
    assert runs[1].score == s


def test_each_method_is_paired_with_the_reference_trial_by_trial(trials):
    """``add_paired``: the paired ratio of a method's per-trial totals to the reference's (``magenv.stats``), none for
    the reference itself; a method that failed on a trial of the group gets none."""
    from magenv.stats import paired_ratio

    methods = {n: registry.make(n) for n in ["mimu", "imu", "fan_lambda"]}
    runs = evaluation.evaluate(methods, trials)
    rows = evaluation.add_paired(evaluation.summarize(runs), runs, "fan_lambda")
    total = {n: [r.scored.total for r in runs if r.method == n] for n in methods}
    by = {r["method"]: r for r in rows}
    assert "paired" not in by["fan_lambda"]
    for n in ("mimu", "imu"):
        assert by[n]["paired"] == paired_ratio(total[n], total["fan_lambda"])
    runs[0] = evaluation.Run(runs[0].method, runs[0].trial, runs[0].label, None, None, None, None, "failed")
    rows = evaluation.add_paired(evaluation.summarize(runs), runs, "fan_lambda")
    assert "paired" not in next(r for r in rows if r["method"] == runs[0].method)


def test_the_table_shows_the_paired_ratio_win_rate_and_interquartile_mean(trials):
    from rich.console import Console

    from magenv.train.compare import print_table

    methods = {n: registry.make(n) for n in ["mimu", "fan_lambda"]}
    runs = evaluation.evaluate(methods, trials)
    rows = evaluation.add_paired(evaluation.summarize(runs), runs, "fan_lambda")
    console = Console(record=True, width=200)
    print_table(rows, console=console)
    text = console.export_text()
    p = next(r for r in rows if r["method"] == "mimu")["paired"]
    assert "IQM ÷ ref" in text and "win" in text
    line = next(ln for ln in text.splitlines() if "mimu" in ln)
    assert (
        f"{p.ratio:.2f} [{p.low:.2f}, {p.high:.2f}]" in line
        and f"{p.iqm:.2f} [{p.iqm_low:.2f}, {p.iqm_high:.2f}]" in line
    )


def test_the_title_names_the_reference_only_where_it_ran(capsys):
    args = ["compare", "--scenario", "dynamic_clean", "--seeds", "10000:10002", "--no-progress"]
    assert main([*args, "--methods", "mimu,imu"]) == 0  # the default reference fan_lambda_tuned did not run
    assert "fan_lambda_tuned" not in capsys.readouterr().out
    assert main([*args, "--methods", "mimu,imu", "--reference", "imu"]) == 0
    assert "÷ imu: paired ratio" in capsys.readouterr().out


def test_an_unknown_reference_is_a_clear_error(capsys):
    code = main(["compare", "--methods", "mimu,imu", "--reference", "fan", "--seeds", "0:1", "--no-progress"])
    assert code == 2 and "--reference 'fan' is not among the methods: mimu, imu" in capsys.readouterr().err


def test_unknown_method_is_a_clear_error(capsys):
    code = main(["compare", "--methods", "mimu,not_a_method", "--seeds", "0:1", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2
    assert "unknown method(s) not_a_method" in err and "fan_lambda" in err


def test_unknown_scenario_is_a_clear_error(capsys):
    pytest.importorskip("magenv.scenarios")
    code = main(["compare", "--scenario", "nowhere", "--seeds", "0:1", "--no-progress"])
    assert code == 2 and "known:" in capsys.readouterr().err


def test_cli_on_a_recording(broad_dir, tmp_path, capsys):
    out = tmp_path / "r.csv"
    png = tmp_path / "r.png"
    path = broad_dir / "29_disturbed_stationary_magnet_B.hdf5"
    code = main(
        [
            "compare",
            "--recordings",
            str(path),
            "--methods",
            "mimu,fan_lambda",
            "--csv",
            str(out),
            "--plot",
            str(png),
            "--no-progress",
        ]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "fan_lambda" in text and "29_disturbed_stationary_magnet_B" in text
    with open(out) as f:
        rows = list(csv.DictReader(f))
    assert ",".join(rows[0].keys()) == HEADER
    assert [r["scenario"] for r in rows] == ["29_disturbed_stationary_magnet_B"] * 2
    assert all(np.isfinite(float(r["total_rmse_mean"])) for r in rows)
    assert png.stat().st_size > 10_000


def test_cli_on_a_simulated_scenario(tmp_path, capsys):
    pytest.importorskip("magenv.scenarios")
    out = tmp_path / "s.csv"
    code = main(
        [
            "compare",
            "--scenario",
            "dynamic_clean",
            "--seeds",
            "0",
            "--methods",
            "mimu,imu",
            "--csv",
            str(out),
            "--no-progress",
        ]
    )
    assert code == 0
    lines = out.read_text().splitlines()
    assert lines[0] == HEADER and len(lines) == 3
    assert all(line.split(",")[1] == "dynamic_clean" for line in lines[1:])


def test_compare_keeps_going_past_a_method_that_cannot_run(tmp_path, capsys):
    """A two-link estimator on a one-sensor trial: its cell is n/a with the reason, the rest is complete, exit 1."""
    out = tmp_path / "k.csv"
    code = main(
        [
            "compare",
            "--scenario",
            "dynamic_clean",
            "--seeds",
            "0,1",
            "--methods",
            "mimu,cf_constraint,imu",
            "--csv",
            str(out),
            "--no-progress",
        ]
    )
    text = capsys.readouterr().out
    assert code == 1
    assert "n/a: cf_constraint on dynamic_clean: failed on 2 of 2 trial(s): MissingChannelsError" in text
    with open(out) as f:
        rows = {r["method"]: r for r in csv.DictReader(f)}
    assert ",".join(next(iter(rows.values())).keys()) == HEADER and set(rows) == {"mimu", "imu", "cf_constraint"}
    assert np.isfinite(float(rows["mimu"]["total_rmse_mean"])) and np.isfinite(float(rows["imu"]["total_rmse_mean"]))
    assert np.isnan(float(rows["cf_constraint"]["total_rmse_mean"])) and rows["cf_constraint"]["n"] == "2"
    with pytest.raises(Exception, match="gyr_j"):  # without keep_going, evaluation raises as before
        evaluation.evaluate({"cf": registry.make("cf_constraint")}, [kinematic_trial(duration=1.0)])


def test_a_method_that_diverges_scores_180_and_ranks_below_every_finite_one(capsys):
    """Two trials; on the second a 1e300 gyro burst early (sample 100) or late (sample 900): whichever sample a
    method diverges at, its trial scores 180° in every part, its row is present, and it is not ahead of another
    method that diverged elsewhere."""
    from magenv.train.compare import divergence_notes, finish, table_order

    good = kinematic_trial(seed=0, duration=4.0)
    early, late = kinematic_trial(seed=1, duration=4.0), kinematic_trial(seed=1, duration=4.0)
    early.gyr[100], late.gyr[900] = 1e300, 1e300
    names = ["mimu", "imu", "fan_lambda", "vqf"]
    for burst in (early, late):
        runs = evaluation.evaluate({n: registry.make(n) for n in names}, [good, burst], keep_going=True)
        diverged = [r for r in runs if r.trial is burst]
        assert all(r.score == evaluation.DIVERGED_SCORE and r.diverged and r.error is None for r in diverged)
        assert all(r.diverged is None and r.score.total < 10 for r in runs if r.trial is good)
        rows = evaluation.summarize(runs)
        assert [r["method"] for r in rows] == names and not any("error" in r for r in rows)
        for r in rows:
            finite = next(run.score.total for run in runs if run.method == r["method"] and run.trial is good)
            assert r["total_rmse_mean"] == pytest.approx((finite + 180.0) / 2)
            assert r["diverged"].startswith("diverged on 1 of 2 trial(s), scored 180°: ")
    # a method with a finite estimate on every trial ranks ahead of every one that diverged
    rows = [
        {"method": "a", "scenario": "s", "n": 1, "total_rmse_mean": 180.0, "diverged": "diverged on 1 of 1 trial(s)"},
        {"method": "b", "scenario": "s", "n": 1, "total_rmse_mean": 120.0},
    ]
    assert [r["method"] for r in table_order(rows)] == ["b", "a"]
    assert divergence_notes(rows) == ["a on s: diverged on 1 of 1 trial(s)"]
    for r in rows:
        r.update(total_rmse_std=float("nan"), heading_rmse_mean=180.0, inclination_rmse_mean=180.0)
    assert finish(rows, "t", None) == 0  # a divergence is a result, not an n/a cell
    out = capsys.readouterr().out
    assert "180.00" in out and "a on s: diverged on 1 of 1 trial(s)" in out and "n/a" not in out


def test_a_non_finite_estimate_is_a_divergence():
    class NaNAfter100:
        def run(self, trial):
            q = np.tile([1.0, 0, 0, 0], (trial.n, 1))
            q[100:] = np.nan
            return type("Estimate", (), {"q": q, "trust": None})()

    trial = kinematic_trial(duration=2.0)
    run = evaluation.run_method("nan", NaNAfter100(), trial)
    assert run.score == evaluation.DIVERGED_SCORE and run.q is not None
    assert run.diverged == f"non-finite estimate from sample 100 of trial {trial.name!r} ({trial.n - 100} of {trial.n})"
