"""``magenv data broad``: fetch the BROAD recordings from their public repository, checked file by file.

    magenv data broad [--dest DIR] [--url BASE] [--manifest FILE] [--force]

The files, their sources and their SHA-256 are listed in the manifest shipped with magenv
(``magenv/data/broad.json``); each is downloaded from ``BASE`` + its ``source`` (default: the dataset's
repository at a fixed commit, so the bytes cannot change under the checksums), written to a temporary file
beside its destination, checked, and only then renamed into place — a failed check leaves nothing behind.
A file already there whose checksum matches is kept (``--force`` fetches it again).

Two kinds of entry: ``sha256`` checks the downloaded file's bytes (an HDF5 file of the dataset, stored as
it is); ``convert: mat`` with ``content_sha256`` fetches the dataset's MATLAB file of a trial, converts it to
the HDF5 layout the loader reads (:func:`mat_to_hdf5`) and checks the digest of the recording's content
(:func:`content_sha256`: its arrays and sampling rate), which does not depend on how an HDF5 library lays
out the bytes. The default destination is the user data folder's ``broad/``
(``magenv.recordings.default_broad_dirs``), where the loader looks before ``../shared/data/broad``;
``MAGENV_BROAD_DIR`` overrides both.

BROAD: D. Laidig, M. Caruso, A. Cereatti, T. Seel, "BROAD — A Benchmark for Robust Inertial Orientation
Estimation", *Data* 6(7):72, 2021, doi:10.3390/data6070072; CC-BY-4.0 — cite it when you use or pass on the
files (a ``SOURCE.md`` saying so is written beside them).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import tempfile
import urllib.error
import urllib.request
from importlib import resources
from pathlib import Path

from magenv.train.cli import CommandError, output_folder

DATASETS = ("broad",)
CHUNK = 1 << 16  # bytes per read of a download
TIMEOUT_S = 60.0  # s, a connection or read that stalls longer fails


def manifest_path() -> Path:
    """The manifest shipped with magenv (``magenv/data/broad.json``)."""
    return Path(str(resources.files("magenv") / "data" / "broad.json"))


def read_manifest(path: Path) -> dict:
    """The manifest in ``path``, checked: ``base_url`` and a non-empty list ``files`` whose entries have a
    plain file ``name``, a ``source`` path and either ``sha256`` or ``convert: mat`` with ``content_sha256``
    (64 hex digits). CommandError naming the file and the entry otherwise."""
    try:
        manifest = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CommandError(f"{path}: not a readable manifest ({type(exc).__name__}: {exc})") from None
    files = manifest.get("files") if isinstance(manifest, dict) else None
    if not isinstance(manifest, dict) or not isinstance(manifest.get("base_url"), str) or not files:
        raise CommandError(f"{path}: a manifest needs 'base_url' and a non-empty list 'files'")
    for entry in files:
        ok = isinstance(entry, dict) and isinstance(entry.get("name"), str) and isinstance(entry.get("source"), str)
        ok = ok and Path(entry["name"]).name == entry["name"] and entry["name"].endswith(".hdf5")
        digest = entry.get("content_sha256") if ok and entry.get("convert") == "mat" else (entry or {}).get("sha256")
        if not ok or not _is_digest(digest) or entry.get("convert") not in (None, "mat"):
            raise CommandError(
                f"{path}: bad entry {entry!r} (needs name FILE.hdf5, source, and sha256 — or convert: mat with "
                "content_sha256 — of 64 hex digits)"
            )
    return manifest


def _is_digest(value) -> bool:
    return isinstance(value, str) and len(value) == 64 and all(c in "0123456789abcdef" for c in value)


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes, hex."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def content_sha256(path: Path) -> str:
    """SHA-256 (hex) of a BROAD recording's content as the loader reads it: for each dataset of
    ``magenv.recordings.REQUIRED`` in order its name, dtype, shape and C-order bytes (sensor and truth arrays
    as float64, ``movement`` as bool), then the ``sampling_rate`` as a float64."""
    import h5py
    import numpy as np

    from magenv.recordings import REQUIRED

    h = hashlib.sha256()
    with h5py.File(path, "r") as f:
        for key in REQUIRED:
            arr = np.ascontiguousarray(f[key][()], bool if key == "movement" else np.float64)
            h.update(f"{key}|{arr.dtype.str}|{arr.shape}|".encode())
            h.update(arr.tobytes())
        h.update(np.float64(f.attrs["sampling_rate"]).tobytes())
    return h.hexdigest()


def mat_to_hdf5(mat: Path, out: Path) -> None:
    """A BROAD trial's MATLAB file (``data_mat/NAME.mat``: the same arrays, ``movement`` as an (N, 1) column,
    ``sampling_rate`` and ``info``) written in the dataset's HDF5 layout (``magenv.recordings``)."""
    import h5py
    import numpy as np
    import scipy.io

    from magenv.recordings import REQUIRED

    try:
        data = scipy.io.loadmat(mat)
    except Exception as exc:  # scipy raises several kinds on a file that is not MATLAB
        raise CommandError(f"{mat}: not a MATLAB file of the dataset ({type(exc).__name__}: {exc})") from None
    missing = [k for k in (*REQUIRED, "sampling_rate") if k not in data]
    if missing:
        raise CommandError(f"{mat}: missing variable(s) {', '.join(missing)}")
    info = data.get("info")
    text = "" if info is None else "".join(str(s) for s in np.ravel(info))
    with h5py.File(out, "w") as f:
        for key in REQUIRED:
            arr = np.asarray(data[key])
            arr = arr.reshape(-1).astype(bool) if key == "movement" else np.ascontiguousarray(arr, np.float64)
            f.create_dataset(key, data=arr, compression="gzip")
        f.attrs["sampling_rate"] = float(np.asarray(data["sampling_rate"], float).reshape(()))
        f.attrs["info"] = text


def _verified(path: Path, entry: dict) -> bool:
    """``path`` holds the file of ``entry`` (its checksum matches)."""
    if not path.is_file():
        return False
    try:
        if entry.get("convert") == "mat":
            return content_sha256(path) == entry["content_sha256"]
        return file_sha256(path) == entry["sha256"]
    except (OSError, KeyError, ValueError):  # an unreadable or foreign file: fetch it again
        return False


def _download(url: str, out: Path, label: str, progress: bool) -> None:
    """``url`` into the file ``out``, with a progress bar; CommandError naming the URL on failure."""
    from tqdm import tqdm

    try:
        with urllib.request.urlopen(url, timeout=TIMEOUT_S) as response, open(out, "wb") as f:
            total = int(response.headers.get("Content-Length") or 0) or None
            with tqdm(total=total, unit="B", unit_scale=True, desc=label, disable=not progress, leave=False) as bar:
                for block in iter(lambda: response.read(CHUNK), b""):
                    f.write(block)
                    bar.update(len(block))
    except (urllib.error.URLError, OSError, ValueError) as exc:
        raise CommandError(f"cannot fetch {url} ({type(exc).__name__}: {exc})") from None


def fetch(dest: Path, manifest: dict, base_url: str | None = None, force: bool = False, progress: bool = True,
          log=print) -> list[Path]:  # fmt: skip
    """Every file of ``manifest`` in ``dest`` (created if needed), downloaded from ``base_url`` (default the
    manifest's) unless already there and verified; returns their paths. Each is checked before it is renamed
    into place; a mismatch is a CommandError naming the file, the expected and the received digest."""
    base = (base_url or manifest["base_url"]).rstrip("/") + "/"
    dest.mkdir(parents=True, exist_ok=True)
    paths = []
    for entry in manifest["files"]:
        path = dest / entry["name"]
        paths.append(path)
        if not force and _verified(path, entry):
            log(f"{entry['name']}: present, checksum matches")
            continue
        url = base + entry["source"]
        with tempfile.TemporaryDirectory(dir=dest, prefix=".fetch-") as tmp:
            raw = Path(tmp) / Path(entry["source"]).name
            _download(url, raw, entry["name"], progress)
            if entry.get("convert") == "mat":
                stored, expected = Path(tmp) / entry["name"], entry["content_sha256"]
                mat_to_hdf5(raw, stored)
                got = content_sha256(stored)
            else:
                stored, expected, got = raw, entry["sha256"], file_sha256(raw)
            if got != expected:
                raise CommandError(
                    f"{entry['name']}: checksum mismatch for {url} (expected {expected}, got {got}); nothing stored"
                )
            os.replace(stored, path)
        log(f"{entry['name']}: fetched from {url}, checksum matches")
    if "citation" in manifest:
        (dest / "SOURCE.md").write_text(
            f"# {manifest.get('dataset', 'recordings')}\n\nFetched by `magenv data broad` from {base}.\n\n"
            f"Licence: {manifest.get('licence', 'see the source')}. Cite: {manifest['citation']}\n"
        )
    return paths


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", choices=DATASETS, help="which recordings (broad: the BROAD trials magenv uses)")
    p.add_argument(
        "--dest", default=None, metavar="DIR", help="where to store them (default: the user data folder's broad/)"
    )
    p.add_argument("--url", default=None, metavar="BASE", help="fetch from this base URL instead (a mirror)")
    p.add_argument("--manifest", default=None, metavar="FILE", help="a manifest of your own (default: magenv's)")
    p.add_argument("--force", action="store_true", help="fetch files again even where present and verified")
    p.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from magenv.recordings import BROAD_DIR_ENV, BROAD_SUBDIR, default_broad_dirs
    from magenv.userdata import user_data_dir

    manifest = read_manifest(Path(args.manifest) if args.manifest else manifest_path())
    dest = output_folder(Path(args.dest) if args.dest else user_data_dir() / BROAD_SUBDIR, "--dest")
    paths = fetch(dest, manifest, args.url, args.force, progress=not args.no_progress)
    print(f"{len(paths)} recording(s) in {dest}")
    if dest.resolve() not in [p.resolve() for p in default_broad_dirs()]:
        print(f"the loader does not look there: set {BROAD_DIR_ENV}={dest}")
    return 0
