"""Seeded fuzz of every loader: corrupted trial and recording HDF5 files, YAML configs, tuned-parameter JSON,
run folders (``run.yaml``, safetensors weights). Each corrupted file either loads or raises the loader's own
error (TrialError, ConfigError, TunedParamsError, RunError) — never another exception, and never runs code.

Corruptions: byte-level (cut short, bytes flipped, a span overwritten with random bytes or repeated) and
structural (a value of a YAML/JSON document or an attribute/dataset of an HDF5 file replaced by a value of
the wrong kind, or deleted). Seeds are fixed: the same corruptions on every run.
"""

from __future__ import annotations

import json
import os
import shutil
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from magenv import registry
from magenv.agents.hyperparams import ConfigError, load_hyperparams
from magenv.agents.loading import RunError, load_agent
from magenv.recordings import load_recording
from magenv.trial import Trial, TrialError
from tests.conftest import kinematic_trial
from tests.test_bad_input import ENV, fake_run, write_config
from tests.test_recordings import write_recording

N_BYTE = 25  # byte-level corruptions per file
N_VALUE = 25  # structural corruptions per file

# values of the wrong kind put in place of a document's value or an HDF5 attribute
BAD_VALUES = [None, "x", "", -1, 0, 1e308, float("nan"), float("inf"), [], {}, True, "1e-3", [1, "a"], {"a": 1}]
BAD_ARRAYS = [
    np.zeros(0),
    np.zeros((3, 2)),
    np.full((7, 4), np.nan),
    np.array(["a", "b"], dtype="S1"),
    np.arange(5),
    np.float64(3.0),
]


def byte_corruptions(data: bytes, rng: np.random.Generator, n: int):
    """``n`` corrupted copies of ``data``: (description, bytes)."""
    for _ in range(n):
        kind = rng.integers(4)
        pos = int(rng.integers(len(data)))
        if kind == 0:
            yield f"cut at byte {pos}", data[:pos]
        elif kind == 1:
            b = bytearray(data)
            for i in rng.integers(len(data), size=int(rng.integers(1, 9))):
                b[i] ^= 1 << int(rng.integers(8))
            yield "bits flipped", bytes(b)
        elif kind == 2:
            span = int(rng.integers(1, 65))
            yield f"bytes {pos}+{span} random", data[:pos] + rng.bytes(span) + data[pos + span :]
        else:
            span = int(rng.integers(1, 65))
            yield f"bytes {pos}+{span} repeated", data[: pos + span] + data[pos : pos + span] + data[pos + span :]


def _leaves(doc, path=()):
    """Paths of every value in a nested dict/list document."""
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for k, v in items:
        yield path + (k,)
        yield from _leaves(v, path + (k,))


def value_corruptions(doc, rng: np.random.Generator, n: int):
    """``n`` copies of the document ``doc`` with one value replaced by a wrong one, or deleted."""
    paths = list(_leaves(doc))
    for _ in range(n):
        path = paths[int(rng.integers(len(paths)))]
        new = json.loads(json.dumps(doc))
        parent = new
        for k in path[:-1]:
            parent = parent[k]
        if rng.random() < 0.2 and isinstance(parent, dict):
            del parent[path[-1]]
            yield f"{'.'.join(map(str, path))} deleted", new
        else:
            value = BAD_VALUES[int(rng.integers(len(BAD_VALUES)))]
            parent[path[-1]] = value
            yield f"{'.'.join(map(str, path))} = {value!r}", new


def hdf5_corruptions(path: Path, rng: np.random.Generator, n: int):
    """``n`` edits of the HDF5 file at ``path`` (in place; the caller restores it): an attribute set to a
    wrong value or deleted, a dataset replaced by a wrong array or deleted."""
    with h5py.File(path, "r") as f:
        names = [("attr", k) for k in f.attrs] + [("data", k) for k in _datasets(f)]
    for _ in range(n):
        kind, key = names[int(rng.integers(len(names)))]
        delete = rng.random() < 0.2
        pool = BAD_VALUES if kind == "attr" else BAD_ARRAYS
        value = pool[int(rng.integers(len(pool)))]
        yield f"{kind} {key} {'deleted' if delete else f'= {value!r}'}", (kind, key, delete, value)


def _datasets(f) -> list[str]:
    out = []
    f.visititems(lambda name, obj: out.append(name) if isinstance(obj, h5py.Dataset) else None)
    return out


def _edit_hdf5(path: Path, edit) -> bool:
    """Apply one :func:`hdf5_corruptions` edit; False where h5py cannot store the value at all."""
    kind, key, delete, value = edit
    with h5py.File(path, "a") as f:
        try:
            if kind == "attr":
                if delete:
                    del f.attrs[key]
                else:
                    f.attrs[key] = json.dumps(value) if isinstance(value, (list, dict)) or value is None else value
            else:
                del f[key]
                if not delete:
                    f.create_dataset(key, data=value)
        except (TypeError, ValueError):
            return False
    return True


def assert_refused_cleanly(load, error: type[Exception], what: str) -> None:
    """``load()`` returns or raises ``error``; any other exception fails, naming the corruption ``what``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            load()
        except error:
            pass
        except Exception as exc:
            pytest.fail(f"{what}: {type(exc).__name__}: {exc} (expected {error.__name__} or a load)")


# ----------------------------------------------------------------- HDF5: trials and recordings


HDF5_FILES = {  # name → (write a good file, load it)
    "trial": (lambda p: kinematic_trial(duration=0.5).save(p), Trial.load),
    "recording": (lambda p: write_recording(p, n=60), load_recording),
}


@pytest.mark.parametrize("name", list(HDF5_FILES))
def test_corrupt_hdf5_bytes_give_a_trial_error(name, tmp_path):
    write, load = HDF5_FILES[name]
    good = write(tmp_path / "good.h5")
    load(good)  # the uncorrupted file loads
    path = tmp_path / "bad.h5"
    for what, data in byte_corruptions(good.read_bytes(), np.random.default_rng(1), N_BYTE):
        path.write_bytes(data)
        assert_refused_cleanly(lambda: load(path), TrialError, f"{name} file, {what}")


@pytest.mark.parametrize("name", list(HDF5_FILES))
def test_wrong_hdf5_fields_give_a_trial_error(name, tmp_path):
    write, load = HDF5_FILES[name]
    good = write(tmp_path / "good.h5")
    path = tmp_path / "bad.h5"
    tried = 0
    for what, edit in hdf5_corruptions(good, np.random.default_rng(2), N_VALUE):
        shutil.copy(good, path)
        if _edit_hdf5(path, edit):
            tried += 1
            assert_refused_cleanly(lambda: load(path), TrialError, f"{name} file, {what}")
    assert tried >= N_VALUE // 2


# ----------------------------------------------------------------- YAML configs and tuned JSON


def _load_config(path: Path):
    return load_hyperparams("ppo", ENV, path)


def test_corrupt_configs_give_a_config_error(tmp_path):
    good = write_config(tmp_path / "good.yaml")
    _load_config(good)
    path = tmp_path / "bad.yaml"
    rng = np.random.default_rng(3)
    for what, data in byte_corruptions(good.read_bytes(), rng, N_BYTE):
        path.write_bytes(data)
        assert_refused_cleanly(lambda: _load_config(path), ConfigError, f"config, {what}")
    for what, doc in value_corruptions(yaml.safe_load(good.read_text()), rng, N_VALUE):
        path.write_text(yaml.safe_dump(doc))
        assert_refused_cleanly(lambda: _load_config(path), ConfigError, f"config, {what}")


@pytest.mark.parametrize(
    "tag",
    ["!!python/object/apply:os.system", "!!python/object/new:os.system", "!!python/name:os.system"],
)
def test_yaml_that_would_run_code_is_refused_and_runs_nothing(tag, tmp_path):
    marker = tmp_path / "ran"
    path = tmp_path / "evil.yaml"
    path.write_text(f"{ENV}:\n  learning_rate: {tag} ['touch {marker}']\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        _load_config(path)
    assert not marker.exists()


@pytest.fixture
def user_tuned(tmp_path):
    """The user's tuned-parameter folder, in a data folder of this test's own."""
    old = os.environ.get(registry.DATA_DIR_ENV)
    os.environ[registry.DATA_DIR_ENV] = str(tmp_path / "data")
    registry.user_tuned_dir().mkdir(parents=True)
    yield registry.user_tuned_dir()
    os.environ[registry.DATA_DIR_ENV] = old


def test_corrupt_tuned_json_gives_a_tuned_params_error(user_tuned):
    good = (registry.packaged_tuned_dir() / "fan_lambda.json").read_text()
    path = user_tuned / "fan_lambda.json"
    rng = np.random.default_rng(4)
    cases = list(byte_corruptions(good.encode(), rng, N_BYTE))
    cases += [(what, json.dumps(doc).encode()) for what, doc in value_corruptions(json.loads(good), rng, N_VALUE)]
    for what, data in cases:
        path.write_bytes(data)
        assert_refused_cleanly(
            lambda: registry.tuned_params("fan_lambda"), registry.TunedParamsError, f"tuned JSON, {what}"
        )


# ----------------------------------------------------------------- run folders


@pytest.fixture(scope="module")
def good_run(tmp_path_factory) -> Path:
    run = fake_run(tmp_path_factory.mktemp("fuzz") / "run", files=("best",))
    load_agent(run)
    return run


@pytest.mark.parametrize("file", ["run.yaml", "best.safetensors"])
def test_corrupt_run_folders_give_a_run_error(file, good_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(good_run, run)
    good = (good_run / file).read_bytes()
    rng = np.random.default_rng(5)
    cases = list(byte_corruptions(good, rng, N_BYTE))
    if file == "run.yaml":
        cases += [(w, yaml.safe_dump(d).encode()) for w, d in value_corruptions(yaml.safe_load(good), rng, N_VALUE)]
    for what, data in cases:
        (run / file).write_bytes(data)
        assert_refused_cleanly(lambda: load_agent(run), RunError, f"{file}, {what}")
