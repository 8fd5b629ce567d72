"""magenv.fidelity and `magenv fidelity`: ρ, ratios, CSV, plot, and one real recording end to end."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from magenv import fidelity
from magenv.recordings import find_recording
from magenv.train.cli import main


def _rows(real: dict, twin: dict) -> list[fidelity.Row]:
    """Rows from {recording: [RMSE per method]} (methods m0, m1, …), each twin value given for two seeds."""
    return [
        fidelity.Row(rec, f"m{i}", r, r / 2, (t * 0.9, t * 1.1), (t / 2, t / 2))
        for rec in real
        for i, (r, t) in enumerate(zip(real[rec], twin[rec]))
    ]


def test_summary_ranks_and_ratios():
    real = {"02_undisturbed_a": [1.0, 2.0, 3.0, 4.0], "29_stationary_magnet_b": [2.0, 1.0, 8.0, 9.0]}
    twin = {"02_undisturbed_a": [1.0, 2.0, 3.0, 4.0], "29_stationary_magnet_b": [9.0, 8.0, 1.0, 2.0]}
    s = fidelity.summarize(_rows(real, twin))
    assert s.rho_recording == {"02_undisturbed_a": pytest.approx(1.0), "29_stationary_magnet_b": pytest.approx(-0.6)}
    assert set(s.rho_group) == {"undisturbed", "stationary_magnet"}
    assert s.rho_group["undisturbed"] == pytest.approx(1.0)
    assert s.real_mean["m2"] == pytest.approx(5.5) and s.twin_mean["m2"] == pytest.approx(2.0)
    assert s.ratio("m0") == pytest.approx(1.5 / 5.0)
    assert s.in_band(["m0", "m1"]) == (0, 2)
    assert math.isnan(fidelity.spearman([1, 2], [1, 2]))
    assert fidelity.group_of("32_disturbed_attached_magnet_1cm") == "attached_magnet"


def test_csv_and_plot(tmp_path):
    rows = _rows({"07_undisturbed": [1.0, 2.0, 4.0]}, {"07_undisturbed": [1.5, 2.0, 3.0]})
    path = fidelity.write_csv(rows, tmp_path / "f.csv")
    with open(path) as f:
        got = list(csv.DictReader(f))
    assert tuple(got[0]) == fidelity.CSV_COLUMNS
    assert float(got[2]["twin_total"]) == pytest.approx(3.0) and float(got[2]["real_heading"]) == pytest.approx(2.0)
    assert fidelity.plot(rows, tmp_path / "f.png").stat().st_size > 1000


def test_cli_on_one_recording(broad_dir, tmp_path, capsys):
    rec = find_recording("07", broad_dir)
    out = tmp_path / "f.csv"
    code = main(
        ["fidelity", "--recordings", str(rec), "--methods", "mimu,imu,fan_lambda", "--seeds", "1", "--csv", str(out)]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "Spearman ρ" in text and "fan_lambda" in text
    with open(out) as f:
        rows = list(csv.DictReader(f))
    assert [r["method"] for r in rows] == ["mimu", "imu", "fan_lambda"]
    real, twin = (np.array([float(r[k]) for r in rows]) for k in ("real_total", "twin_total"))
    assert np.all(np.isfinite(real)) and np.all(twin > 0)
    assert np.all(np.abs(np.log(real / twin)) < np.log(3.0))  # an undisturbed twin is close to its recording


def test_cli_bad_arguments(tmp_path, capsys):
    assert main(["fidelity", "--recordings", str(tmp_path / "none.hdf5")]) == 2
    assert "no such recording" in capsys.readouterr().err
    assert main(["fidelity", "--recordings", "x", "--methods", "nope"]) == 2
    assert main(["fidelity", "--recordings", "x", "--seeds", "0"]) == 2
