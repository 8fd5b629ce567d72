"""Trial: one run of sensor data with its true orientation.

The same container holds a simulated trial (``magenv.scenarios``) and a real
recording (``magenv.recordings``). Frames and units follow
``magenv.quaternion``: sensor channels are in the sensor frame, the true
orientation maps sensor → ENU earth.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from magenv.checks import check_site

FORMAT = "magenv-trial-1"
RATE_RANGE = (1.0, 100_000.0)  # Hz: the sampling rates a trial may have
UNIT_TOL = 1e-3  # truth quaternions this close to unit norm are normalised (with a warning); farther: refused
UNIT_QUIET = 1e-6  # deviations below this (float rounding) are left as they are, silently

# Keys of ``Trial.meta`` that magenv reads (any other key is free-form description).
META_SCENARIO = "scenario"  # the scenario name; a trial's default group in tables
META_SEED = "seed"  # the trial seed of a simulated trial
START_FROM_TRUTH = "start_from_truth"  # True: the trial's protocol gives estimators the true initial orientation
DATASETS = ("gyr", "acc", "mag", "q_true", "score_mask")  # the per-sample arrays of a trial file


class TrialError(ValueError):
    """A trial (or a file meant to hold one) is malformed."""


def check_rate(rate, what: str) -> float:
    """``rate`` as Hz, a finite number in ``RATE_RANGE``; else TrialError naming ``what`` (e.g. the attribute)."""
    lo, hi = RATE_RANGE
    try:
        value = float(np.asarray(rate, dtype=float).reshape(()))
    except (TypeError, ValueError):
        raise TrialError(f"{what} must be a sampling rate in Hz, got {rate!r}") from None
    if not (np.isfinite(value) and lo <= value <= hi):
        raise TrialError(f"{what} must be a sampling rate from {lo:g} to {hi:g} Hz, got {value!r}")
    return value


def _row_norms(q: np.ndarray) -> np.ndarray:
    """Norm of each row of ``q`` (m, 4); 1 for a row with a NaN (missing truth)."""
    present = ~np.isnan(q).any(axis=1)
    if present.all():  # the common case: truth everywhere, the masks change nothing
        return np.linalg.norm(q, axis=1)
    return np.where(present, np.linalg.norm(np.where(present[:, None], q, 0.0), axis=1), 1.0)


def unit_truth(q: np.ndarray, what: str) -> np.ndarray:
    """True orientations ``q`` (N, 4) checked for unit norm. A row with a NaN is missing truth and stays;
    a row off unit norm by more than ``UNIT_QUIET`` and at most ``UNIT_TOL`` is normalised, with a warning;
    farther off, or ±inf, is a TrialError naming ``what`` and the first bad row.

    In blocks of 65 536 rows: a long trial's temporaries stay small. Deviations are rounded to 12 decimals
    (a truth scaled by exactly 1 + UNIT_TOL is within it); rounding keeps their order, so the largest is
    rounded alone."""
    q = np.asarray(q, float)
    blocks = range(0, len(q), 1 << 16)
    worst = 0.0
    for a in blocks:
        block = q[a : a + (1 << 16)]
        if np.isinf(block).any():
            row = a + int(np.flatnonzero(np.isinf(block).any(axis=1))[0])
            raise TrialError(f"{what}: truth quaternion row {row} is infinite ({q[row].tolist()})")
        worst = max(worst, float(np.round(np.abs(_row_norms(block) - 1.0).max(initial=0.0), 12)))
    if worst <= UNIT_QUIET:
        return q
    norm = np.concatenate([_row_norms(q[a : a + (1 << 16)]) for a in blocks])
    if worst > UNIT_TOL:
        dev = np.round(np.abs(norm - 1.0), 12)
        row = int(np.argmax(dev))
        raise TrialError(
            f"{what}: truth quaternions must have unit norm; row {row} has norm {norm[row]:.6g} "
            f"({int((dev > UNIT_TOL).sum())} row(s) off by more than {UNIT_TOL:g})"
        )
    warnings.warn(f"{what}: truth quaternions off unit norm by up to {worst:.2g}; normalised", stacklevel=3)
    return q / norm[:, None]


def read_datasets(f, path: Path, keys) -> dict:
    """``{key: f[key][()]}`` for an open HDF5 file or group; one that cannot be read is a TrialError naming it."""
    out = {}
    for key in keys:
        try:
            out[key] = f[key][()]
        except (OSError, KeyError, RuntimeError, TypeError, AttributeError) as exc:
            raise TrialError(f"{path}: cannot read dataset {key} ({type(exc).__name__}: {exc})") from None
    return out


def as_text(value) -> str:
    """An HDF5 attribute (str or bytes) as text."""
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)


@contextlib.contextmanager
def open_hdf5(path: Path):
    """``with open_hdf5(path) as f``: the file open for reading. A missing file, a file that is not HDF5, and
    a read that fails inside the block (a corrupt file) are TrialErrors naming the file."""
    import h5py

    if not path.is_file():
        raise TrialError(f"{path}: no such file")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise TrialError(f"{path}: not an HDF5 file ({exc})") from None
    try:
        with f:
            yield f
    except (OSError, KeyError, RuntimeError) as exc:
        raise TrialError(f"{path}: cannot read the file (corrupt? {type(exc).__name__}: {exc})") from None


@dataclasses.dataclass(eq=False)
class Trial:
    """Sensor data and truth of one trial, all arrays with N rows at ``rate`` Hz.

    Attributes:
        name: trial name (scenario and seed, or the recording's file stem).
        rate: sampling rate, Hz.
        gyr: (N, 3) angular rate, rad/s, sensor frame.
        acc: (N, 3) specific force, m/s², sensor frame.
        mag: (N, 3) magnetic field, µT, sensor frame.
        q_true: (N, 4) true orientation sensor → ENU, ``[w, x, y, z]``;
            NaN rows where truth is missing.
        field_norm: undisturbed local field magnitude m0, µT, in (0, ``magenv.checks.FIELD_NORM_MAX_UT``].
        field_dip: undisturbed local dip angle θ0, degrees (positive down), in [-90, 90].
        score_mask: (N,) bool, samples over which errors are scored.
        truth: truth-only channels, never shown to a policy, each with N rows
            (e.g. ``mag_disturbance`` (N, 3) µT sensor frame, ``stationary``
            (N,) bool, ``magnet_distance`` (N,) m).
        extra: further sensor channels visible to estimators (e.g. a second
            sensor's ``gyr_j``), each with N rows.
        meta: JSON-serialisable description (scenario, seed, parameters).
    """

    name: str
    rate: float
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    q_true: np.ndarray
    field_norm: float
    field_dip: float
    score_mask: np.ndarray | None = None
    truth: dict = dataclasses.field(default_factory=dict)
    extra: dict = dataclasses.field(default_factory=dict)
    meta: dict = dataclasses.field(default_factory=dict)

    def __setattr__(self, name: str, value) -> None:
        """``field_norm`` and ``field_dip`` are checked whenever they are set (at construction and after):
        every env and filter reads them from the trial, so none is handed a field that cannot exist."""
        if name in ("field_norm", "field_dip"):
            norm, dip = (value, 45.0) if name == "field_norm" else (45.0, value)
            try:
                value = check_site(norm, dip)[name == "field_dip"]
            except (TypeError, ValueError) as exc:
                raise TrialError(f"trial {getattr(self, 'name', '?')!r}: {exc}") from None
        super().__setattr__(name, value)

    def __post_init__(self) -> None:
        self.rate = check_rate(self.rate, f"trial {self.name!r}: rate")
        n = len(self.gyr) if hasattr(self.gyr, "__len__") else -1
        for key, cols in (("gyr", 3), ("acc", 3), ("mag", 3), ("q_true", 4)):
            try:
                arr = np.ascontiguousarray(getattr(self, key), dtype=float)
            except (TypeError, ValueError):
                raise TrialError(
                    f"trial {self.name!r}: {key} must be numbers, got {getattr(self, key)!r:.80}"
                ) from None
            if arr.shape != (n, cols):
                raise TrialError(f"trial {self.name!r}: {key} must have shape ({n}, {cols}), got {arr.shape}")
            if key != "q_true" and not np.all(np.isfinite(arr)):
                raise TrialError(f"trial {self.name!r}: {key} contains NaN or inf")
            setattr(self, key, arr)
        self.q_true = unit_truth(self.q_true, f"trial {self.name!r}: q_true")
        if n < 2:
            raise TrialError(f"trial {self.name!r}: needs at least 2 samples, got {n}")
        mask = np.ones(n, bool) if self.score_mask is None else np.asarray(self.score_mask, bool)
        if mask.shape != (n,):
            raise TrialError(f"trial {self.name!r}: score_mask must have shape ({n},), got {mask.shape}")
        self.score_mask = mask
        for group in ("truth", "extra"):
            for key, value in getattr(self, group).items():
                value = np.asarray(value)
                rows = len(value) if value.ndim else "no"  # a scalar has no rows
                if rows != n:
                    raise TrialError(f"trial {self.name!r}: {group} channel {key!r} has {rows} rows, expected {n}")
                getattr(self, group)[key] = value

    @property
    def n(self) -> int:
        """Number of samples."""
        return len(self.gyr)

    @property
    def n_scored(self) -> int:
        """Samples that count in a score: inside ``score_mask`` and with truth (no NaN in ``q_true``)."""
        return int(np.count_nonzero(self.score_mask & ~np.isnan(self.q_true).any(axis=1)))

    @property
    def dt(self) -> float:
        """Sample interval, s."""
        return 1.0 / self.rate

    @property
    def t(self) -> np.ndarray:
        """(N,) sample times, s, starting at 0."""
        return np.arange(self.n) / self.rate

    @property
    def duration(self) -> float:
        """Length of the trial, s."""
        return self.n / self.rate

    def slice(self, start: int, stop: int) -> Trial:
        """Samples ``start:stop`` as a new Trial (same metadata)."""
        cut = lambda d: {k: v[start:stop] for k, v in d.items()}
        return dataclasses.replace(
            self,
            gyr=self.gyr[start:stop],
            acc=self.acc[start:stop],
            mag=self.mag[start:stop],
            q_true=self.q_true[start:stop],
            score_mask=None if self.score_mask is None else self.score_mask[start:stop],
            truth=cut(self.truth),
            extra=cut(self.extra),
            meta=dict(self.meta),
        )

    # ------------------------------------------------------------ HDF5

    def save(self, path: str | Path) -> Path:
        """Write the trial to an HDF5 file (magenv's own layout, see ``load``)."""
        import h5py

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with h5py.File(path, "w") as f:
            f.attrs["format"] = FORMAT
            f.attrs["name"] = self.name
            f.attrs["rate"] = self.rate
            f.attrs["field_norm"] = self.field_norm
            f.attrs["field_dip"] = self.field_dip
            f.attrs["meta"] = json.dumps(self.meta)
            for key in DATASETS:
                f.create_dataset(key, data=getattr(self, key))
            for group in ("truth", "extra"):
                g = f.create_group(group)
                for key, value in getattr(self, group).items():
                    g.create_dataset(key, data=value)
        return path

    @classmethod
    def load(cls, path: str | Path) -> Trial:
        """Read a trial written by ``save``. Raises TrialError naming the file and the problem: a missing or
        malformed attribute or dataset, a corrupt file, a bad rate or truth, no sample to score."""
        path = Path(path)
        with open_hdf5(path) as f:
            fmt = f.attrs.get("format")
            if fmt is None or as_text(fmt) != FORMAT:
                raise TrialError(
                    f"{path}: not a magenv trial (attribute format={fmt!r}, expected {FORMAT!r}; "
                    "a BROAD recording loads with magenv.recordings.load_recording)"
                )
            missing = [f"dataset {k}" for k in DATASETS if k not in f]
            missing += [f"attribute {k}" for k in ("name", "rate", "field_norm", "field_dip") if k not in f.attrs]
            if missing:
                raise TrialError(f"{path}: missing {', '.join(missing)}")
            numbers: dict[str, float] = {}
            for key in ("field_norm", "field_dip"):
                try:
                    numbers[key] = float(np.asarray(f.attrs[key], dtype=float).reshape(()))
                except (TypeError, ValueError):
                    raise TrialError(f"{path}: attribute {key} is not a number: {f.attrs[key]!r}") from None
            rate = check_rate(f.attrs["rate"], f"{path}: attribute rate")
            try:
                meta = json.loads(as_text(f.attrs.get("meta", "{}")))
            except json.JSONDecodeError as exc:
                raise TrialError(f"{path}: attribute meta is not valid JSON ({exc})") from None
            if not isinstance(meta, dict):
                raise TrialError(f"{path}: attribute meta must be a JSON object, got {type(meta).__name__}")
            data = read_datasets(f, path, DATASETS)
            groups: dict[str, dict[str, np.ndarray]] = {}
            for group in ("truth", "extra"):
                g = f.get(group, {})
                if not hasattr(g, "keys"):
                    raise TrialError(f"{path}: {group} must be a group of datasets")
                groups[group] = read_datasets(g, path, list(g.keys()))
            name = as_text(f.attrs["name"])
        try:
            fields: dict[str, Any] = {**data, **numbers, **groups}
            trial = cls(name=name, rate=rate, **fields, meta=meta)
        except TrialError as exc:
            raise TrialError(f"{path}: {exc}") from None
        if trial.n_scored == 0:
            raise TrialError(
                f"{path}: no sample to score (score_mask and the rows of q_true with truth have none in common)"
            )
        return trial
