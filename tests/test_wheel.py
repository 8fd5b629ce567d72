"""The built wheel is the whole product: one import name, every data file, and tuned rules outside site-packages."""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow  # builds the wheel and a fresh virtualenv: `make test-slow`


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "--wheel-dir",
            str(out),
            str(ROOT),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    (path,) = out.glob("magenv-*.whl")
    return path


def test_wheel_has_one_top_level_name_and_its_data(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert tops == {"magenv"}
    for data in (
        "magenv/sim/gimbal.xml",
        "magenv/sim/twolink.xml",
        "magenv/agents/configs/ppo.yaml",
        "magenv/agents/configs/dagger.yaml",
        "magenv/agents/pretrained/MagBlend-v0/best.safetensors",
        "magenv/baselines/tuned/fan_lambda.json",
        "magenv/py.typed",
    ):
        assert data in names, data


def test_installed_wheel_runs_compare_with_a_tuned_rule_from_elsewhere(wheel, tmp_path):
    """A regular install into a fresh virtualenv (the dependencies come from this environment's site-packages,
    never the source tree): ``magenv compare --methods fan_lambda_tuned`` run from another directory."""
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    py = env_dir / "bin" / "python"
    site = subprocess.run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    (Path(site) / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run(
        [str(py), "-m", "pip", "install", "--quiet", "--no-deps", "--no-index", str(wheel)],
        check=True,
        capture_output=True,
        timeout=300,
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["MAGENV_DATA_DIR"] = str(tmp_path / "user-data")  # empty: the packaged tuned file is the one found
    where = subprocess.run(
        [
            str(py),
            "-c",
            "import magenv.baselines, magenv.registry as r; "
            "print(magenv.baselines.__file__); print(r.tuned_file('fan_lambda'))",
        ],
        cwd=elsewhere,
        env=env,
        check=True,
        capture_output=True,
        text=True,
    ).stdout.splitlines()
    assert all(line.startswith(site) for line in where), where
    result = subprocess.run(
        [
            str(env_dir / "bin" / "magenv"),
            "compare",
            "--scenario",
            "dynamic_magnet",
            "--seeds",
            "0",
            "--methods",
            "fan_lambda_tuned",
            "--no-progress",
        ],
        cwd=elsewhere,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "fan_lambda_tuned" in result.stdout and "dynamic_magnet" in result.stdout
