"""magenv report: Markdown with the tables and the PNG plots."""

from magenv import evaluation, registry
from magenv.scenarios import make_trial
from magenv.train.report import write_report


def test_report_has_tables_and_plots(tmp_path):
    trials = [make_trial("dynamic_magnet", s, duration=8.0) for s in (0, 1)] + [
        make_trial("dynamic_clean", 0, duration=8.0)
    ]
    runs = evaluation.evaluate({n: registry.make(n) for n in ["mimu", "fan_lambda", "th_triad"]}, trials)
    path = write_report(runs, tmp_path / "report")
    text = path.read_text()
    assert "| dynamic_magnet | " in text and "| dynamic_clean | " in text
    for method in ("mimu", "fan_lambda", "th_triad"):
        assert f"| {method} |" in text
    pngs = sorted(p.name for p in (tmp_path / "report").glob("*.png"))
    assert pngs == ["rmse_bars.png", "trial_dynamic_clean.png", "trial_dynamic_magnet.png"]
    assert all((tmp_path / "report" / p).stat().st_size > 10_000 for p in pngs)
    assert (tmp_path / "report" / "comparison.csv").read_text().startswith(",".join(evaluation.CSV_COLUMNS))


def test_the_paired_columns_carry_the_ratio_win_rate_and_interquartile_mean(tmp_path):
    from magenv.stats import paired_ratio

    trials = [make_trial("dynamic_clean", s, duration=6.0) for s in (0, 1, 2, 3)]
    runs = evaluation.evaluate({n: registry.make(n) for n in ["mimu", "imu"]}, trials)
    text = write_report(runs, tmp_path / "report", reference="mimu").read_text()
    assert "÷ reference [95 % CI] | win | worst | IQM ÷ reference |" in text
    table = [line for line in text.splitlines() if line.startswith("|")]
    assert len({line.count("|") for line in table}) == 1  # header, separator and rows: the same columns
    total = {n: [r.scored.total for r in runs if r.method == n] for n in ("mimu", "imu")}
    p = paired_ratio(total["imu"], total["mimu"])
    row = next(line for line in text.splitlines() if line.startswith("| dynamic_clean | imu |"))
    iqm = f"{p.iqm:.2f} [{p.iqm_low:.2f}, {p.iqm_high:.2f}]"
    assert row.endswith(f"{p.ratio:.2f} [{p.low:.2f}, {p.high:.2f}] | {p.win_rate:.2f} | {p.worst:.2f} | {iqm} |")
