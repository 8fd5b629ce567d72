"""``magenv estimate`` and ``magenv.TrustFilter``: your own IMU data, no truth; the same numbers as the env."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from magenv import evaluation, registry
from magenv.streaming import START_CAPACITY, TrustFilter, estimate, own_trial
from magenv.train.cli import main
from tests.conftest import kinematic_trial

BLEND_AGENT = "pretrained:magenv/MagBlend-v0"
VQF_AGENT = "pretrained:magenv/MagVQF-v0"


@pytest.fixture(scope="module")
def log():
    """60 s at 100 Hz (beyond the first streaming buffer), a 25 µT disturbance from 20 to 30 s."""
    return kinematic_trial(seed=5, duration=60.0, rate=100.0, disturbance_ut=25.0, disturbance_window=(20.0, 30.0),
                           field_norm=49.0, field_dip=64.0)  # fmt: skip


def write_csv(path, trial, header=("t", "gx", "gy", "gz", "ax", "ay", "az", "mx", "my", "mz"), scale=(1, 1, 1)):
    table = np.column_stack([trial.t, trial.gyr * scale[0], trial.acc * scale[1], trial.mag * scale[2]])
    np.savetxt(path, table, delimiter=",", header=",".join(header), comments="", fmt="%.17g")
    return path


def read_h5(path):
    with h5py.File(path) as f:
        return {k: f[k][()] for k in f}, dict(f.attrs)


@pytest.mark.parametrize("method", [VQF_AGENT, BLEND_AGENT])
def test_streaming_is_the_env_and_estimate(log, method, tmp_path):
    assert log.n > START_CAPACITY  # the buffer grows once: the decisions are re-stepped into the larger one
    f = TrustFilter(method, rate=log.rate, field_norm=log.field_norm, field_dip=log.field_dip)
    parts = [f.update(g, a, m) for g, a, m in zip(log.gyr, log.acc, log.mag)]
    k = registry.make(method).env_kwargs["decision_every"]
    assert {len(p) for p in parts} == {0, k} and sum(len(p) for p in parts) < log.n
    q = np.concatenate([*parts, f.finish()])
    trial = own_trial(log.gyr, log.acc, log.mag, log.rate, log.field_norm, log.field_dip)
    env_q, _, env_trust = evaluation.estimate(registry.make(method), trial)  # the policy stepped in its env
    np.testing.assert_array_equal(q, env_q)
    np.testing.assert_array_equal(f.trust, env_trust)
    np.testing.assert_array_equal(TrustFilter(method, log.rate, log.field_norm, log.field_dip).run(
        log.gyr, log.acc, log.mag), env_q)  # fmt: skip
    assert np.all(np.isfinite(q)) and 0.0 <= env_trust.min() and env_trust.max() <= 1.0
    # the command on a CSV log of the same samples, given the same field
    path = write_csv(tmp_path / "log.csv", log)
    out = tmp_path / "out.h5"
    argv = ["estimate", str(path), "--method", method, "--out", str(out), "--field-norm", "49", "--field-dip", "64"]
    assert main(argv) == 0
    cols, attrs = read_h5(out)
    np.testing.assert_array_equal(np.column_stack([cols[c] for c in ("qw", "qx", "qy", "qz")]), env_q)
    np.testing.assert_array_equal(cols["trust"], env_trust)
    assert attrs["method"] == method and attrs["field_source"] == "given"


def test_units_and_columns_are_declared(log, tmp_path, capsys):
    """°/s, g and Gauss in columns of other names, the rate given: the same estimate as SI units."""
    header = ("time", "wx", "wy", "wz", "fx", "fy", "fz", "bx", "by", "bz")
    path = write_csv(tmp_path / "units.csv", log, header, scale=(180 / np.pi, 1 / 9.80665, 0.01))
    out = tmp_path / "o.csv"
    argv = ["estimate", str(path), "--method", "vqf_rejection", "--out", str(out), "--rate", "100",
            "--gyr", "wx,wy,wz", "--acc", "fx,fy,fz", "--mag", "bx,by,bz",
            "--gyr-unit", "deg/s", "--acc-unit", "g", "--mag-unit", "gauss",
            "--plot", str(tmp_path / "p.png")]  # fmt: skip
    assert main(argv) == 0
    assert (tmp_path / "p.png").stat().st_size > 1000
    got = np.genfromtxt(out, delimiter=",", names=True)
    assert got.dtype.names == ("t", "qw", "qx", "qy", "qz", "yaw", "pitch", "roll", "heading", "inclination", "trust")
    ref = estimate("vqf_rejection", own_trial(log.gyr, log.acc, log.mag, 100.0))
    np.testing.assert_allclose(np.column_stack([got[c] for c in ("qw", "qx", "qy", "qz")]), ref.q, atol=1e-6)
    np.testing.assert_allclose(got["trust"], ref.trust)
    assert "(initial_rest)" in capsys.readouterr().out or ref.trial.meta["field_source"] == "all_samples"
    # the angles are those of the quaternion: heading = 90° − yaw, inclination of the z axis
    np.testing.assert_allclose(np.mod(90 - got["yaw"], 360), got["heading"], atol=1e-6)
    assert np.all((got["inclination"] >= 0) & (got["inclination"] <= 180))


def test_every_kind_of_method_runs(log, tmp_path):
    trial = own_trial(log.gyr[:1500], log.acc[:1500], log.mag[:1500], log.rate, 49.0, 64.0)
    for name in ("fan_lambda_tuned", "vqf", "kf_model_tuned", "pretrained:magenv/MagKalman-v0"):
        result = estimate(name, trial)
        assert result.q.shape == (1500, 4) and np.all(np.isfinite(result.q)), name
    assert estimate("vqf", trial).trust.shape == (1500,)  # VQF's own rejection: 0 where it rejects
    blend = estimate("fan_lambda_tuned", trial)
    np.testing.assert_allclose(blend.trust, 1.0 - evaluation.estimate(registry.make("fan_lambda_tuned"), trial)[1])


def test_hdf5_inputs(tmp_path, broad_dir):
    sim = kinematic_trial(seed=1, duration=8.0, rate=100.0)
    sim.save(tmp_path / "sim.h5")
    for src in (tmp_path / "sim.h5", broad_dir / "29_disturbed_stationary_magnet_B.hdf5"):
        out = tmp_path / f"{src.stem}.csv"
        assert main(["estimate", str(src), "--method", "vqf_rejection", "--out", str(out), "--no-progress"]) == 0
        assert len(np.genfromtxt(out, delimiter=",", skip_header=1)) > 500


def test_bad_input_is_named_before_any_work(log, tmp_path, capsys):
    good = write_csv(tmp_path / "good.csv", log)
    uneven = log.slice(0, 500)
    uneven_t = uneven.t.copy()
    uneven_t[200:] += 0.05
    rows = np.column_stack([uneven_t, uneven.gyr, uneven.acc, uneven.mag])
    np.savetxt(tmp_path / "uneven.csv", rows, delimiter=",", header="t,gx,gy,gz,ax,ay,az,mx,my,mz", comments="")
    nt = write_csv(tmp_path / "nt.csv", log, scale=(1, 1, 1000))  # nT, declared as µT
    out = str(tmp_path / "o.csv")
    cases = [
        (["estimate", str(tmp_path / "none.csv"), "--method", "vqf", "--out", out], "no such file"),
        (["estimate", str(good), "--method", "nope", "--out", out], "unknown method 'nope'"),
        (["estimate", str(good), "--method", "vqf", "--out", str(tmp_path / "o.txt")], "must name a .csv, .h5"),
        (["estimate", str(good), "--method", "vqf", "--out", out, "--mag", "a,b,c"], "no column(s) a, b, c"),
        (["estimate", str(tmp_path / "uneven.csv"), "--method", "vqf", "--out", out], "uneven sampling"),
        (["estimate", str(nt), "--method", "vqf", "--out", out], "looks like nT"),
        (["estimate", str(good), "--agent", str(tmp_path), "--out", out], "not a magenv run folder"),
        (["estimate", str(good), "--method", "cf_constraint", "--out", out], "no second-sensor channel"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        assert message in capsys.readouterr().err, message
    assert not list(tmp_path.glob("o.*"))


def test_streaming_refuses_what_it_cannot_stream(log):
    for name, message in (("vqf", "complete estimator"), ("kf_model_tuned", "precomputes"),
                          ("pretrained:magenv/MagQSF-v0", "precomputes")):  # fmt: skip
        with pytest.raises(ValueError, match=message):
            TrustFilter(name, 100.0, 49.0, 64.0).update(log.gyr[0], log.acc[0], log.mag[0])
    with pytest.raises(ValueError, match="local field"):
        TrustFilter(VQF_AGENT, 100.0).update(log.gyr[0], log.acc[0], log.mag[0])
    f = TrustFilter(VQF_AGENT, 100.0, 49.0, 64.0)
    with pytest.raises(ValueError, match="three finite"):
        f.update([0, 0, np.nan], log.acc[0], log.mag[0])
    f.finish()
    with pytest.raises(RuntimeError, match="finished"):
        f.update(log.gyr[0], log.acc[0], log.mag[0])
