"""A training run folder that is always whole: files written as one transaction, the state file last, and a lock.

:meth:`RunFolder.commit` writes a set of files in three steps:

1. each file to ``NAME.tmp`` (flushed to disk);
2. ``state.json`` (as ``state.json.tmp``, then renamed over the old one: the commit point), naming every file
   of the run (``files``: name → SHA-256 of its content);
3. each ``NAME.tmp`` renamed over ``NAME``.

A kill at any moment leaves either the old state, whose files are untouched (the new ones wait, unnamed, as
``.tmp``), or the new state, each of whose files is either in place or still waiting as ``NAME.tmp``.
:meth:`RunFolder.recover`, run before a run continues, finishes the renames that the state names (a ``.tmp``
whose digest the state holds) and removes every other ``.tmp``. ``tb/`` (TensorBoard's event logs, appended
as training goes) is no part of the state.

:meth:`RunFolder.locked` holds an exclusive lock on ``.lock`` (``fcntl.flock``; ``msvcrt.locking`` on Windows)
while a run writes to the folder: a second run into the same folder stops at once with a RunError naming the
first one's process. The operating system releases the lock when the process ends, however it ends.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from collections.abc import Callable, Iterator
from pathlib import Path

from magenv.agents.weights import RunError

STATE_FILE = "state.json"
LOCK_FILE = ".lock"
TMP = ".tmp"


def digest(path: Path) -> str:
    """SHA-256 of a file's content, hex."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _tmp(path: Path) -> Path:
    return path.with_name(path.name + TMP)


def _flush(path: Path) -> None:
    """Flush a written file to disk (a power cut after the rename then finds its content)."""
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def _rename(src: Path, dst: Path) -> None:
    """Replace ``dst`` by ``src`` (atomic: a reader sees the old file or the new one, never a mix)."""
    os.replace(src, dst)


def _lock(handle) -> bool:
    """Take an exclusive lock on the open file ``handle`` without waiting; False if another process holds it."""
    try:
        import fcntl
    except ImportError:  # Windows
        import msvcrt

        try:
            msvcrt.locking(handle.fileno(), msvcrt.LK_NBLCK, 1)  # type: ignore[attr-defined]
        except OSError:
            return False
        return True
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False
    return True


class RunFolder:
    """The files of one training run (see the module docstring). ``files`` holds what the committed state names."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.files: dict[str, str] = {}

    @contextlib.contextmanager
    def locked(self) -> Iterator[RunFolder]:
        """Hold the folder's lock (the folder is created if missing); RunError at once if another process holds
        it."""
        self.path.mkdir(parents=True, exist_ok=True)
        handle = open(self.path / LOCK_FILE, "a+")
        handle.seek(0)  # msvcrt locks bytes from here
        try:
            if not _lock(handle):
                handle.seek(0)
                holder = handle.read().strip() or "unknown"
                raise RunError(
                    f"{self.path}: another run is writing to this folder (process {holder}); "
                    "wait for it to finish, or use another --out"
                )
            handle.seek(0)
            handle.truncate()
            handle.write(str(os.getpid()))
            handle.flush()
            yield self
        finally:
            handle.close()  # closing releases the lock

    def read_state(self) -> dict | None:
        """The committed state (``state.json``), or None if there is none; RunError if it is corrupt."""
        path = self.path / STATE_FILE
        if not path.is_file():
            return None
        try:
            state = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise RunError(f"{path}: corrupt ({type(exc).__name__}: {exc})") from None
        files = state.get("files", {}) if isinstance(state, dict) else None
        if not isinstance(files, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in files.items()):
            raise RunError(f"{path}: corrupt (a JSON object with 'files', name → digest, expected)")
        return state

    def recover(self) -> dict | None:
        """Bring the folder to its committed state (see the module docstring) and return that state (None for a
        folder without one). RunError if a file the state names is missing."""
        state = self.read_state()
        self.files = dict(state.get("files", {})) if state else {}
        for name, sha in self.files.items():
            path = self.path / name
            if _tmp(path).is_file() and digest(_tmp(path)) == sha:
                _rename(_tmp(path), path)
            if not path.is_file():
                raise RunError(f"{path}: missing, though {self.path / STATE_FILE} names it")
        for folder in (self.path, *(p for p in self.path.iterdir() if p.is_dir() and p.name != "tb")):
            for leftover in [*folder.glob("*" + TMP), *folder.glob("*.tmp.zip")]:  # .tmp.zip: older magenv
                leftover.unlink()
        return state

    def commit(self, writers: dict[str, Callable[[Path], object]], state: dict) -> None:
        """Write the files of ``writers`` (name relative to the folder → function writing that file at the path
        it is given) and then ``state`` (with ``files`` set to every file of the run and its digest) as one
        transaction (see the module docstring)."""
        staged = {}
        for name, write in writers.items():
            tmp = _tmp(self.path / name)
            tmp.parent.mkdir(parents=True, exist_ok=True)
            write(tmp)
            _flush(tmp)
            staged[name] = digest(tmp)
        files = {**self.files, **staged}
        state_tmp = _tmp(self.path / STATE_FILE)
        state_tmp.write_text(json.dumps({**state, "files": files}, indent=1))
        _flush(state_tmp)
        _rename(state_tmp, self.path / STATE_FILE)
        for name in staged:
            _rename(_tmp(self.path / name), self.path / name)
        self.files = files
