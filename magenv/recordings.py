"""Real recordings: the BROAD HDF5 files as ``Trial`` objects.

BROAD (Laidig, Caruso, Cereatti, Seel, "BROAD — A Benchmark for Robust
Inertial Orientation Estimation", *Data* 6(7):72, 2021, CC-BY-4.0) stores each
trial as one HDF5 file (layout: ``../shared/data/broad/README.md``):

=============  =======  ==========================================================
dataset        shape    meaning
=============  =======  ==========================================================
``imu_gyr``    (N, 3)   angular rate, rad/s, sensor frame      → ``Trial.gyr``
``imu_acc``    (N, 3)   specific force, m/s², sensor frame     → ``Trial.acc``
``imu_mag``    (N, 3)   magnetic field, µT, sensor frame       → ``Trial.mag``
``opt_quat``   (N, 4)   sensor → ENU, ``[w,x,y,z]``, NaN rows  → ``Trial.q_true``
``opt_pos``    (N, 3)   board position, m                      → ``truth["opt_pos"]``
``movement``   (N,)     samples to score                       → ``Trial.score_mask``
=============  =======  ==========================================================

plus the attributes ``sampling_rate`` (Hz → ``Trial.rate``) and ``info``
(free text → ``meta["info"]``). BROAD's frames and quaternion order are
magenv's own (``magenv.quaternion``), so nothing is converted. The truth's
north is the trial's own undisturbed magnetic north, so an estimate made with
the magnetometer is scored directly (``magenv.metrics.score(q, trial.q_true,
trial.score_mask)`` is the authors' protocol).

Earth field (``Trial.field_norm``, ``Trial.field_dip``): estimated from the
file itself, over the *initial rest* (see ``initial_rest``): the median field
magnitude |m| and the median dip ``asin(−m̂·â)`` (tilt-independent: the
accelerometer points up at rest). If that window is shorter than 1 s, or the
field in it is not steady (|m| or dip spread beyond ``REST_MAX_NORM_STD`` /
``REST_MAX_DIP_STD``), or the result is implausible (more than
``MAX_FIELD_DEVIATION`` from the documented Berlin values), the documented
constants ``BERLIN_FIELD_NORM`` = 44.5 µT and ``BERLIN_FIELD_DIP`` = 69° are used
instead. ``meta["field_source"]`` says which ("initial_rest" or "documented").
On the nine shipped trials the estimate is always taken from the file
(|m| ≈ 41.6–44.4 µT, dip ≈ 67.5–71.5°; trial 10 was recorded at a
different spot of the room).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from magenv.trial import Trial, TrialError, as_text, check_rate, open_hdf5, read_datasets, unit_truth
from magenv.userdata import user_data_dir

BERLIN_FIELD_NORM = 44.5  # µT, documented local field (README of the data)
BERLIN_FIELD_DIP = 69.0  # degrees, positive down

REST_GYR_THRESHOLD = np.deg2rad(2.0)  # rad/s, smoothed |ω| above this ends the initial rest
REST_MAX_SECONDS = 10.0  # s, longest stretch of the initial rest used for the field
REST_MIN_SECONDS = 1.0  # s, shorter rests fall back to the documented field
REST_MAX_NORM_STD = 2.0  # µT, |m| spread beyond this: field not steady, fall back
REST_MAX_DIP_STD = 3.0  # degrees
MAX_FIELD_DEVIATION = (8.0, 8.0)  # (µT, degrees) from the Berlin values, beyond: fall back

SENSOR_KEYS = ("imu_gyr", "imu_acc", "imu_mag")
REQUIRED = (*SENSOR_KEYS, "opt_quat", "opt_pos", "movement")

BROAD_DIR_ENV = "MAGENV_BROAD_DIR"  # a folder of BROAD recordings, read instead of the default places
BROAD_SUBDIR = "broad"  # where ``magenv data broad`` stores them in the user data folder
FETCH_COMMAND = "magenv data broad"  # the command that fetches them
_CHECKOUT_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "broad"  # beside a development checkout


def default_broad_dirs() -> list[Path]:
    """Where the BROAD recordings are looked for, in order: ``$MAGENV_BROAD_DIR`` alone if set; else the user
    data folder's ``broad/`` (``magenv.userdata.user_data_dir``, where ``magenv data broad`` stores them), then
    ``<checkout>/../shared/data/broad``."""
    import os

    if os.environ.get(BROAD_DIR_ENV):
        return [Path(os.environ[BROAD_DIR_ENV])]
    return [user_data_dir() / BROAD_SUBDIR, _CHECKOUT_DIR]


def broad_dir() -> Path:
    """The folder of the BROAD recordings: the first of :func:`default_broad_dirs` that holds ``*.hdf5`` files
    (``$MAGENV_BROAD_DIR``, when set, only has to exist). TrialError naming the places looked in and
    ``magenv data broad`` if none does."""
    places = default_broad_dirs()
    for folder in places:
        if folder.is_dir() and (len(places) == 1 or any(folder.glob("*.hdf5"))):
            return folder
    raise TrialError(
        f"BROAD recordings folder not found (looked in {', '.join(map(str, places))}); "
        f"fetch them with `{FETCH_COMMAND}` or set {BROAD_DIR_ENV}"
    )


def list_recordings(folder: str | Path | None = None) -> list[Path]:
    """Sorted ``*.hdf5`` files in ``folder`` (default ``broad_dir()``)."""
    folder = broad_dir() if folder is None else Path(folder)
    if not folder.is_dir():
        raise TrialError(f"{folder}: no such folder")
    return sorted(folder.glob("*.hdf5"))


def find_recording(key: str, folder: str | Path | None = None) -> Path:
    """The recording whose file name starts with ``key`` (e.g. ``"29"``, ``"02_undisturbed"``)."""
    hits = [p for p in list_recordings(folder) if p.stem.startswith(key)]
    if len(hits) != 1:
        raise TrialError(f"recording {key!r}: {len(hits)} files match in {folder or broad_dir()}")
    return hits[0]


GLOB_CHARS = "*?["


def match_recordings(pattern: str, folder: str | Path | None = None) -> list[Path]:
    """The recordings a ``recording:`` pattern names, sorted: an existing file itself; a glob with a folder
    part (``data/*.hdf5``) matched as a path; a bare glob (``2*``, ``*magnet*``) matched against the file
    names in ``folder`` (default ``broad_dir()``), ``.hdf5`` appended if the pattern has no suffix.
    TrialError if nothing matches."""
    import glob

    path = Path(pattern)
    if path.is_file():
        return [path]
    if not any(c in pattern for c in GLOB_CHARS):
        raise TrialError(f"{pattern}: no such recording file")
    if path.parent != Path("."):
        hits = sorted(Path(p) for p in glob.glob(pattern) if Path(p).is_file())
    else:
        base = broad_dir() if folder is None else Path(folder)
        hits = sorted(base.glob(pattern if Path(pattern).suffix else pattern + ".hdf5"))
    if not hits:
        raise TrialError(f"recording pattern {pattern!r} matches no file")
    return hits


def initial_rest(
    gyr: np.ndarray, rate: float, threshold: float = REST_GYR_THRESHOLD, max_seconds: float = REST_MAX_SECONDS
) -> slice:
    """Samples ``0:k`` of the initial rest: until the 0.1 s moving average of
    |ω| (rad/s) first exceeds ``threshold``, at most ``max_seconds`` s."""
    gyr = np.asarray(gyr, float)
    n_max = min(len(gyr), int(round(max_seconds * rate)))
    win = max(1, int(round(0.1 * rate)))
    speed = np.linalg.norm(gyr[:n_max], axis=1)
    smooth = np.convolve(speed, np.ones(win) / win, mode="same")
    moving = np.flatnonzero(smooth > threshold)
    return slice(0, int(moving[0]) if moving.size else n_max)


def dip_angle(acc: np.ndarray, mag: np.ndarray) -> np.ndarray:
    """Dip angle (degrees, positive down) of ``mag`` below the horizontal plane
    defined by ``acc`` (both (..., 3), sensor frame; valid where acc ≈ gravity)."""
    acc = np.asarray(acc, float)
    mag = np.asarray(mag, float)
    cosang = np.sum(acc * mag, -1) / (np.linalg.norm(acc, axis=-1) * np.linalg.norm(mag, axis=-1))
    return np.rad2deg(np.arcsin(np.clip(-cosang, -1.0, 1.0)))


def estimate_field(
    gyr, acc, mag, rate: float, documented: tuple[float, float] = (BERLIN_FIELD_NORM, BERLIN_FIELD_DIP)
) -> tuple[float, float, str]:
    """Earth field ``(norm µT, dip °, source)`` from the initial rest, or the
    ``documented`` site field (µT, °; default Berlin's) with ``source="documented"`` when the rest is too
    short, unsteady or implausible (more than ``MAX_FIELD_DEVIATION`` from it; see the module docstring)."""
    rest = initial_rest(gyr, rate)
    m, a = np.asarray(mag[rest], float), np.asarray(acc[rest], float)
    if len(m) >= REST_MIN_SECONDS * rate:
        norm = np.linalg.norm(m, axis=1)
        dip = dip_angle(a, m)
        steady = norm.std() <= REST_MAX_NORM_STD and dip.std() <= REST_MAX_DIP_STD
        est_norm, est_dip = float(np.median(norm)), float(np.median(dip))
        plausible = (
            abs(est_norm - documented[0]) <= MAX_FIELD_DEVIATION[0]
            and abs(est_dip - documented[1]) <= MAX_FIELD_DEVIATION[1]
        )
        if steady and plausible:
            return est_norm, est_dip, "initial_rest"
    return float(documented[0]), float(documented[1]), "documented"


def load_recording(path: str | Path) -> Trial:
    """Read one BROAD HDF5 file into a ``Trial`` (see the module docstring).

    ``Trial.name`` is the file stem; ``meta`` holds ``source`` ("BROAD"),
    ``file``, ``info``, ``field_source`` and ``initial_rest_s`` (length of the
    rest used for the field, s). NaN rows of ``opt_quat`` stay NaN; rows off
    unit norm by at most ``magenv.trial.UNIT_TOL`` are normalised, with a warning.

    Raises:
        TrialError: naming the file and the problem — missing file, not HDF5 or
            corrupt, a missing dataset or ``sampling_rate``, fewer than 2 rows,
            wrong shapes or lengths, NaN/inf in a sensor channel, a rate outside
            ``magenv.trial.RATE_RANGE``, truth off unit norm, no sample to score.
    """
    import h5py

    path = Path(path)
    with open_hdf5(path) as f:
        missing = [k for k in REQUIRED if k not in f or not isinstance(f[k], h5py.Dataset)]
        if missing:
            raise TrialError(
                f"{path}: missing dataset(s) {', '.join(missing)} (a BROAD file needs {', '.join(REQUIRED)})"
            )
        if "sampling_rate" not in f.attrs:
            raise TrialError(f"{path}: missing attribute sampling_rate")
        rate = check_rate(f.attrs["sampling_rate"], f"{path}: attribute sampling_rate")
        data = read_datasets(f, path, REQUIRED)
        info = as_text(f.attrs.get("info", ""))

    n = len(data["imu_gyr"]) if np.ndim(data["imu_gyr"]) else -1
    if 0 <= n < 2:
        raise TrialError(f"{path}: dataset imu_gyr has {n} row(s); a recording needs at least 2")
    shapes = {
        "imu_gyr": (n, 3),
        "imu_acc": (n, 3),
        "imu_mag": (n, 3),
        "opt_quat": (n, 4),
        "opt_pos": (n, 3),
        "movement": (n,),
    }
    bad = [f"{k} {np.shape(data[k])} (expected {shapes[k]})" for k in REQUIRED if np.shape(data[k]) != shapes[k]]
    if bad:
        raise TrialError(f"{path}: mismatched shapes or lengths: {'; '.join(bad)}")
    for k in (*SENSOR_KEYS, "opt_quat", "opt_pos"):
        if not np.issubdtype(data[k].dtype, np.number):
            raise TrialError(f"{path}: dataset {k} is not numeric (dtype {data[k].dtype})")
        data[k] = np.asarray(data[k], float)
    for k in SENSOR_KEYS:
        bad_rows = np.flatnonzero(~np.all(np.isfinite(data[k]), axis=1))
        if bad_rows.size:
            raise TrialError(
                f"{path}: sensor channel {k} has NaN/inf in {bad_rows.size} row(s), first at row {bad_rows[0]}"
            )
    movement = data["movement"]
    if not (movement.dtype == bool or np.all(np.isin(movement, (0, 1)))):
        raise TrialError(f"{path}: dataset movement must be boolean, got dtype {movement.dtype}")
    movement = movement.astype(bool)
    q_true = unit_truth(data["opt_quat"], f"{path}: dataset opt_quat")
    truth_rows = ~np.isnan(q_true).any(axis=1)
    if not np.any(movement & truth_rows):
        raise TrialError(
            f"{path}: no sample to score: dataset movement marks {int(movement.sum())} of {n} "
            f"samples and opt_quat has truth in {int(truth_rows.sum())}, none in common"
        )

    field_norm, field_dip, field_source = estimate_field(data["imu_gyr"], data["imu_acc"], data["imu_mag"], rate)
    rest = initial_rest(data["imu_gyr"], rate)
    try:
        return Trial(
            name=path.stem,
            rate=rate,
            gyr=data["imu_gyr"],
            acc=data["imu_acc"],
            mag=data["imu_mag"],
            q_true=q_true,
            field_norm=field_norm,
            field_dip=field_dip,
            score_mask=movement,
            truth={"opt_pos": data["opt_pos"]},
            meta={
                "source": "BROAD",
                "file": str(path),
                "info": info,
                "field_source": field_source,
                "initial_rest_s": (rest.stop - rest.start) / rate,
            },
        )
    except TrialError as exc:
        raise TrialError(f"{path}: {exc}") from None


def load_trial_file(path: str | Path) -> Trial:
    """A trial file of either kind: magenv's own (``Trial.save``, told by its ``format`` attribute) or a
    BROAD recording. Raises TrialError naming the file and the problem."""
    path = Path(path)
    with open_hdf5(path) as f:
        own, broad = "format" in f.attrs, any(k in f for k in REQUIRED)
    if not own and not broad:
        raise TrialError(
            f"{path}: neither a magenv trial (no attribute format) nor a BROAD recording "
            f"(none of the datasets {', '.join(REQUIRED)})"
        )
    return Trial.load(path) if own else load_recording(path)


def load_all(folder: str | Path | None = None) -> list[Trial]:
    """Every recording in ``folder`` (default ``broad_dir()``), sorted by name."""
    return [load_recording(p) for p in list_recordings(folder)]
