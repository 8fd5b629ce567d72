"""``magenv data broad``: fetching recordings against a local HTTP server (127.0.0.1 only), the checksums, the
folders the loader reads, and the shipped manifest against the recordings at hand."""

from __future__ import annotations

import functools
import http.server
import json
import threading

import h5py
import numpy as np
import pytest
import scipy.io

from magenv import recordings
from magenv.recordings import BROAD_DIR_ENV, broad_dir, load_recording
from magenv.train import data
from magenv.train.cli import CommandError, main
from magenv.trial import TrialError


def _arrays(seed: int, n: int = 400):
    """A small recording's arrays (BROAD layout): a kinematic trial, 100 Hz, moving after 1 s."""
    from tests.conftest import kinematic_trial

    t = kinematic_trial(seed=seed, duration=n / 100.0, rate=100.0, field_norm=44.5, field_dip=69.0)
    movement = np.arange(n) >= 100
    return {"imu_gyr": t.gyr, "imu_acc": t.acc, "imu_mag": t.mag, "opt_quat": t.q_true,
            "opt_pos": np.zeros((n, 3)), "movement": movement}  # fmt: skip


@pytest.fixture
def served(tmp_path):
    """A folder served on 127.0.0.1 holding one trial as HDF5 and one as MATLAB, and a manifest of both:
    (root folder, base URL, manifest dict, list of requested paths)."""
    root = tmp_path / "served"
    (root / "h5").mkdir(parents=True)
    (root / "mat").mkdir()
    a = _arrays(0)
    with h5py.File(root / "h5" / "01_a.hdf5", "w") as f:
        for k, v in a.items():
            f.create_dataset(k, data=v)
        f.attrs["sampling_rate"] = 100.0
        f.attrs["info"] = "trial a"
    b = _arrays(1)
    scipy.io.savemat(root / "mat" / "02_b.mat", {**b, "movement": b["movement"][:, None], "sampling_rate": 100.0,
                                                 "info": "trial b"})  # fmt: skip
    converted = tmp_path / "converted.hdf5"
    data.mat_to_hdf5(root / "mat" / "02_b.mat", converted)
    manifest = {
        "dataset": "fixture",
        "citation": "none",
        "base_url": "http://127.0.0.1:9/unused/",
        "files": [
            {"name": "01_a.hdf5", "source": "h5/01_a.hdf5", "sha256": data.file_sha256(root / "h5" / "01_a.hdf5")},
            {"name": "02_b.hdf5", "source": "mat/02_b.mat", "convert": "mat",
             "content_sha256": data.content_sha256(converted)},
        ],
    }  # fmt: skip
    requested: list[str] = []

    class Handler(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            requested.append(self.path)

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=str(root)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield root, f"http://127.0.0.1:{server.server_address[1]}/", manifest, requested
    server.shutdown()
    server.server_close()


def test_fetch_stores_checked_files_the_loader_reads(served, tmp_path, monkeypatch):
    root, url, manifest, requested = served
    dest = tmp_path / "dest"
    paths = data.fetch(dest, manifest, url, progress=False, log=lambda s: None)
    assert [p.name for p in paths] == ["01_a.hdf5", "02_b.hdf5"]
    assert sorted(p.name for p in dest.iterdir()) == ["01_a.hdf5", "02_b.hdf5", "SOURCE.md"]  # no temporaries
    a, b = load_recording(paths[0]), load_recording(paths[1])
    np.testing.assert_array_equal(a.gyr, _arrays(0)["imu_gyr"])
    np.testing.assert_array_equal(b.mag, _arrays(1)["imu_mag"])  # the MATLAB file converted, content unchanged
    np.testing.assert_array_equal(b.score_mask, _arrays(1)["movement"])
    monkeypatch.setenv(BROAD_DIR_ENV, str(dest))
    assert [p.name for p in recordings.list_recordings()] == ["01_a.hdf5", "02_b.hdf5"]
    # a second run finds both verified and downloads nothing; --force downloads again
    n = len(requested)
    data.fetch(dest, manifest, url, progress=False, log=lambda s: None)
    assert len(requested) == n
    data.fetch(dest, manifest, url, force=True, progress=False, log=lambda s: None)
    assert len(requested) == n + 2


def test_a_file_that_fails_its_check_is_not_stored(served, tmp_path):
    root, url, manifest, _ = served
    with h5py.File(root / "h5" / "01_a.hdf5", "a") as f:  # the served file changes under its checksum
        f["imu_gyr"][0, 0] += 1e-3
    dest = tmp_path / "dest"
    with pytest.raises(CommandError, match=r"01_a.hdf5: checksum mismatch .*expected [0-9a-f]{64}, got"):
        data.fetch(dest, manifest, url, progress=False, log=lambda s: None)
    assert list(dest.iterdir()) == []
    scipy.io.savemat(root / "mat" / "02_b.mat", {**_arrays(2), "sampling_rate": 100.0})  # other content
    manifest = {**manifest, "files": manifest["files"][1:]}
    with pytest.raises(CommandError, match="02_b.hdf5: checksum mismatch"):
        data.fetch(dest, manifest, url, progress=False, log=lambda s: None)
    assert list(dest.iterdir()) == []


def test_unreachable_source_and_bad_manifest_are_clear_errors(served, tmp_path):
    root, url, manifest, _ = served
    missing = {**manifest, "files": [{**manifest["files"][0], "source": "h5/none.hdf5"}]}
    with pytest.raises(CommandError, match="cannot fetch http://127.0.0.1:.*/h5/none.hdf5"):
        data.fetch(tmp_path / "d", missing, url, progress=False, log=lambda s: None)
    bad = tmp_path / "bad.json"
    for content in ("{", json.dumps({"base_url": "x", "files": [{"name": "../a.hdf5", "source": "a", "sha256": "0"}]}),
                    json.dumps({"files": []})):  # fmt: skip
        bad.write_text(content)
        with pytest.raises(CommandError, match="bad.json"):
            data.read_manifest(bad)


def test_cli_fetches_into_dest(served, tmp_path, capsys):
    root, url, manifest, _ = served
    path = tmp_path / "m.json"
    path.write_text(json.dumps(manifest))
    dest = tmp_path / "dest"
    argv = ["data", "broad", "--dest", str(dest), "--url", url, "--manifest", str(path), "--no-progress"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "2 recording(s) in" in out and f"set {BROAD_DIR_ENV}={dest}" in out
    assert main([*argv[:-1], "--url", "http://127.0.0.1:1/"]) == 0  # present and verified: no connection needed


def test_loader_folders_in_order(tmp_path, monkeypatch):
    user, shared = tmp_path / "user", tmp_path / "shared"
    monkeypatch.delenv(BROAD_DIR_ENV, raising=False)
    monkeypatch.setenv("MAGENV_DATA_DIR", str(user))
    monkeypatch.setattr(recordings, "_CHECKOUT_DIR", shared)
    with pytest.raises(TrialError, match="fetch them with `magenv data broad`"):
        broad_dir()
    shared.mkdir()
    (shared / "x.hdf5").write_bytes(b"")
    assert broad_dir() == shared
    (user / "broad").mkdir(parents=True)
    assert broad_dir() == shared  # an empty user folder does not hide the recordings
    (user / "broad" / "y.hdf5").write_bytes(b"")
    assert broad_dir() == user / "broad"
    monkeypatch.setenv(BROAD_DIR_ENV, str(tmp_path / "elsewhere"))
    with pytest.raises(TrialError, match="elsewhere"):
        broad_dir()


def test_shipped_manifest_matches_the_recordings(broad_dir):
    """The checksums shipped with magenv are those of the recordings the tests read."""
    manifest = data.read_manifest(data.manifest_path())
    assert {e["name"] for e in manifest["files"]} == {p.name for p in broad_dir.glob("*.hdf5")}
    for entry in manifest["files"]:
        assert data._verified(broad_dir / entry["name"], entry), entry["name"]


@pytest.mark.parametrize("ci, outcome", [(None, "1 skipped"), ("true", "1 error")])
def test_tests_without_recordings_skip_naming_the_command_or_fail_under_ci(ci, outcome, tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {k: v for k, v in os.environ.items() if k != "CI"}
    env[BROAD_DIR_ENV] = str(tmp_path / "none")  # no recordings anywhere
    if ci is not None:
        env["CI"] = ci
    test = "tests/test_train_data.py::test_shipped_manifest_matches_the_recordings"
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:xdist", "-p", "no:cacheprovider",
                           test], cwd=root, env=env, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert outcome in done.stdout, done.stdout[-2000:]
    assert "magenv data broad" in done.stdout
