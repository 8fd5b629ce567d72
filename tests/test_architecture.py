"""The structure of the house: dependencies run one way (import-linter), and the package installs as one name.

``magenv.agents``, ``magenv.baselines`` and ``magenv.train`` live in the
repository's top-level folders (setuptools ``package-dir``), so the checks
run on a staged copy laid out as the installed package is.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def stage(dest: Path) -> Path:
    """Copy the sources into ``dest`` as the installed layout (``pyproject.toml``'s package-dir); returns ``dest``."""
    package_dir = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    for name, folder in sorted(package_dir.items()):  # parents before children
        target = dest.joinpath(*name.split("."))
        shutil.copytree(
            ROOT / folder, target, ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"), dirs_exist_ok=True
        )
    return dest


def lint_imports(staged: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(staged)}
    return subprocess.run(
        [str(BIN / "lint-imports"), "--no-cache", str(ROOT / "pyproject.toml")],
        cwd=staged,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_layers_are_kept(tmp_path):
    result = lint_imports(stage(tmp_path))
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert "Contracts: 1 kept, 0 broken." in result.stdout


def test_an_upward_import_breaks_the_layers(tmp_path):
    staged = stage(tmp_path)
    (staged / "magenv" / "filters" / "upward.py").write_text("from magenv import evaluation  # filters -> evaluation\n")
    result = lint_imports(staged)
    assert result.returncode != 0
    assert "magenv.filters.upward -> magenv.evaluation" in result.stdout


def test_types_check(tmp_path):
    """mypy over the whole package (``[tool.mypy]`` in pyproject.toml), on the installed layout."""
    staged = stage(tmp_path)
    result = subprocess.run(
        [
            str(BIN / "mypy"),
            "--config-file",
            str(ROOT / "pyproject.toml"),
            "--cache-dir",
            str(tmp_path / ".mypy"),
            "-p",
            "magenv",
        ],
        cwd=staged,
        env={**os.environ, "PYTHONPATH": str(staged)},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]


@pytest.mark.parametrize("folder", ["agents", "baselines", "train"])
def test_repository_folders_are_subpackages_of_magenv(folder):
    import importlib

    module = importlib.import_module(f"magenv.{folder}")
    assert Path(module.__file__).resolve().parent == ROOT / folder
    assert folder not in sys.modules or sys.modules[folder] is module  # no top-level name of its own
