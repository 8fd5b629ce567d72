"""Trial: one run of sensor data with its true orientation.

The same container holds a simulated trial (``magenv.scenarios``) and a real
recording (``magenv.recordings``). Frames and units follow
``magenv.quaternion``: sensor channels are in the sensor frame, the true
orientation maps sensor → ENU earth.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

FORMAT = "magenv-trial-1"

# Keys of ``Trial.meta`` that magenv reads (any other key is free-form description).
META_SCENARIO = "scenario"  # the scenario name; a trial's default group in tables
META_SEED = "seed"  # the trial seed of a simulated trial
START_FROM_TRUTH = "start_from_truth"  # True: the trial's protocol gives estimators the true initial orientation


class TrialError(ValueError):
    """A trial (or a file meant to hold one) is malformed."""


def open_hdf5(path: Path):
    """``h5py.File(path, "r")``; TrialError naming the file if it does not exist or is not HDF5."""
    import h5py

    if not path.is_file():
        raise TrialError(f"{path}: no such file")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise TrialError(f"{path}: not an HDF5 file ({exc})") from None


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
        field_norm: undisturbed local field magnitude m0, µT.
        field_dip: undisturbed local dip angle θ0, degrees (positive down).
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

    def __post_init__(self) -> None:
        if not (np.isfinite(self.rate) and self.rate > 0):
            raise TrialError(f"trial {self.name!r}: rate must be a positive number of Hz, got {self.rate!r}")
        n = len(self.gyr) if hasattr(self.gyr, "__len__") else -1
        for key, cols in (("gyr", 3), ("acc", 3), ("mag", 3), ("q_true", 4)):
            arr = np.ascontiguousarray(getattr(self, key), dtype=float)
            if arr.shape != (n, cols):
                raise TrialError(f"trial {self.name!r}: {key} must have shape ({n}, {cols}), got {arr.shape}")
            if key != "q_true" and not np.all(np.isfinite(arr)):
                raise TrialError(f"trial {self.name!r}: {key} contains NaN or inf")
            setattr(self, key, arr)
        if n < 2:
            raise TrialError(f"trial {self.name!r}: needs at least 2 samples, got {n}")
        mask = np.ones(n, bool) if self.score_mask is None else np.asarray(self.score_mask, bool)
        if mask.shape != (n,):
            raise TrialError(f"trial {self.name!r}: score_mask must have shape ({n},), got {mask.shape}")
        self.score_mask = mask
        for group in ("truth", "extra"):
            for key, value in getattr(self, group).items():
                value = np.asarray(value)
                if len(value) != n:
                    raise TrialError(f"trial {self.name!r}: {group} channel {key!r} has {len(value)} rows, expected {n}")
                getattr(self, group)[key] = value
        self.field_norm = float(self.field_norm)
        self.field_dip = float(self.field_dip)

    @property
    def n(self) -> int:
        """Number of samples."""
        return len(self.gyr)

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

    def slice(self, start: int, stop: int) -> "Trial":
        """Samples ``start:stop`` as a new Trial (same metadata)."""
        cut = lambda d: {k: v[start:stop] for k, v in d.items()}
        return dataclasses.replace(
            self, gyr=self.gyr[start:stop], acc=self.acc[start:stop], mag=self.mag[start:stop],
            q_true=self.q_true[start:stop], score_mask=self.score_mask[start:stop],
            truth=cut(self.truth), extra=cut(self.extra), meta=dict(self.meta),
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
            for key in ("gyr", "acc", "mag", "q_true", "score_mask"):
                f.create_dataset(key, data=getattr(self, key))
            for group in ("truth", "extra"):
                g = f.create_group(group)
                for key, value in getattr(self, group).items():
                    g.create_dataset(key, data=value)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "Trial":
        """Read a trial written by ``save``. Raises TrialError naming the file and the problem."""
        path = Path(path)
        with open_hdf5(path) as f:
            if f.attrs.get("format") != FORMAT:
                raise TrialError(f"{path}: not a magenv trial (attribute format={f.attrs.get('format')!r}, expected {FORMAT!r})")
            missing = [k for k in ("gyr", "acc", "mag", "q_true", "score_mask") if k not in f]
            if missing:
                raise TrialError(f"{path}: missing dataset(s) {', '.join(missing)}")
            try:
                return cls(
                    name=str(f.attrs["name"]), rate=float(f.attrs["rate"]),
                    gyr=f["gyr"][()], acc=f["acc"][()], mag=f["mag"][()], q_true=f["q_true"][()],
                    field_norm=float(f.attrs["field_norm"]), field_dip=float(f.attrs["field_dip"]),
                    score_mask=f["score_mask"][()],
                    truth={k: v[()] for k, v in f.get("truth", {}).items()},
                    extra={k: v[()] for k, v in f.get("extra", {}).items()},
                    meta=json.loads(f.attrs.get("meta", "{}")),
                )
            except TrialError as exc:
                raise TrialError(f"{path}: {exc}") from None
