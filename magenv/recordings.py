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

Physical sense (:func:`check_physical`, run by :func:`load_recording`): the
magnitudes must fit the units the layout declares — gravity ≈ 9.81 m/s² at
rest, the Earth's field 20–70 µT at the initial rest, gyro rates a gyroscope
can measure, and a sampling rate at which the gyro turns as far as the truth
(or, without truth, as far as the accelerometer tilts). A value that another
unit explains (nT, mG, G, T; g, mg; °/s; a sampling rate N× off) is refused
naming that unit; one slightly off is loaded with a warning.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from magenv import quaternion as quat
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

# Physical sense (check_physical). Each channel's magnitude against the band its declared unit gives it; outside
# the band by at most ``WARN_FACTOR``: a warning; farther: refused, naming the unit that explains it, if one does.
EARTH_FIELD_UT = (20.0, 70.0)  # µT, the undisturbed field anywhere on Earth (≈ 22–67 µT)
GRAVITY_BAND = (0.9 * quat.GRAVITY, 1.1 * quat.GRAVITY)  # m/s², the specific force at rest
WARN_FACTOR = 2.0
#: A channel's value in units it may be in by mistake: unit → the size of magenv's unit in it.
MAG_UNITS = {"nT": 1e3, "mG": 10.0, "G": 1e-2, "T": 1e-6}  # per µT
ACC_UNITS = {"g": 1.0 / quat.GRAVITY, "mg": 1e3 / quat.GRAVITY}  # per m/s²
DEG_PER_RAD = 180.0 / math.pi  # °/s per rad/s
GYR_MAX = math.radians(4000.0)  # rad/s, the largest full scale of MEMS gyroscopes (4000 °/s)
GYR_P99_MAX = math.radians(2000.0)  # rad/s, sustained rates beyond it (99th percentile of |ω|): no human motion
# The sampling rate: the gyro integrated at it must turn as far as the truth over windows of WINDOW_S in which the
# truth turns at least MIN_TURN_DEG (median ratio; in [0.9, 1.1] on the nine BROAD recordings: 0.993–0.999), or
# without truth as far as the accelerometer tilts at rest-like windows (|a| within 5 % of g; a cruder 0.9–2.3).
WINDOW_S, MIN_TURN_DEG, MIN_WINDOWS = 0.1, 5.0, 20
TURN_OK = (0.9, 1.1)  # gyro turn ÷ truth turn: quiet inside, a warning up to ×/÷ 1.5, refused beyond
TURN_WARN = (2.0 / 3.0, 1.5)
TILT_OK = (0.3, 5.0)  # gyro tilt ÷ accelerometer tilt without truth: refused outside
REST_ACC_STD = 0.2  # m/s², |a| steadier than this over 0.2 s (with the gyro quiet): at rest

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


def _magnitude_problem(
    what: str, value: float, band: tuple[float, float], unit: str, others: dict, at_rest: bool
) -> str | None:
    """None if ``value`` (in ``unit``) is inside ``band`` — or, not measured ``at_rest``, within ``WARN_FACTOR``
    of it; else the warning (prefixed "warn: ") or the refusal: all zero, another unit of ``others`` (name → the
    size of ``unit`` in it) that puts it inside the band, or implausible in any unit."""
    lo, hi = band
    near = lo / WARN_FACTOR <= value <= hi * WARN_FACTOR
    if lo <= value <= hi or (near and not at_rest):
        return None
    if value == 0.0:
        return f"{what} is all zero: no data in this channel?"
    if near:
        return f"warn: {what} {value:.3g} {unit} is outside the expected {lo:.3g}–{hi:.3g} {unit}"
    for other, size in others.items():
        if lo * size / WARN_FACTOR <= value <= hi * size * WARN_FACTOR:
            return f"{what} {value:.2g} looks like {other}, expected {unit} ({lo:.3g}–{hi:.3g} {unit})"
    return f"{what} {value:.3g} {unit} is implausible in any unit (expected {lo:.3g}–{hi:.3g} {unit})"


def _turn_windows(trial: Trial, angle) -> tuple[np.ndarray, np.ndarray]:
    """(gyro angle, reference angle) of back-to-back windows, radians: ``angle(i, k)`` gives the reference's
    angle (NaN: no reference) over samples i … i+k, the gyro's is that of its rotation vector ``Σ ω / rate``
    (small-angle: windows are short), projected by ``angle``'s second output if it returns one. Windows start at
    ``WINDOW_S`` seconds and double in length (a wrong rate makes them too short in real time) until
    ``MIN_WINDOWS`` turn at least ``MIN_TURN_DEG``."""
    summed = np.cumsum(np.vstack([np.zeros(3), trial.gyr]), axis=0)
    k = max(1, int(round(WINDOW_S * trial.rate)))
    while True:
        i = np.arange(0, max(trial.n - k, 0), k)
        reference, gyro = angle(i, k, (summed[i + k] - summed[i]) / trial.rate)
        turned = np.isfinite(reference) & (np.maximum(reference, gyro) > math.radians(MIN_TURN_DEG))
        if turned.sum() >= MIN_WINDOWS or 2 * k * MIN_WINDOWS > trial.n:
            return gyro[turned], reference[turned]
        k *= 2


def gyro_turn_ratio(trial: Trial) -> tuple[float, int]:
    """(median over windows of the angle the gyro turns ÷ the angle the truth turns, number of windows; NaN and 0
    without enough truth): the sampling rate and the gyro's unit checked against the truth (``_turn_windows``)."""
    q = trial.q_true

    def angle(i, k, rotvec):
        rel = quat.mul(quat.conj(q[i]), q[i + k])
        return 2.0 * np.arccos(np.clip(np.abs(rel[:, 0]), 0.0, 1.0)), np.linalg.norm(rotvec, axis=1)

    gyro, truth = _turn_windows(trial, angle)
    return (float(np.median(gyro / truth)) if truth.size >= MIN_WINDOWS else math.nan), int(truth.size)


def gyro_tilt_ratio(trial: Trial) -> tuple[float, int]:
    """Without truth: (median over windows of the tilt the gyro predicts ÷ the tilt the accelerometer shows,
    number of windows): windows with |a| within 5 % of g at both ends (little linear acceleration), the gyro's
    rotation vector r tilting the measured gravity direction â by |r × â| (``_turn_windows``)."""
    norm = np.linalg.norm(trial.acc, axis=1)
    quiet = np.abs(norm - quat.GRAVITY) < 0.05 * quat.GRAVITY
    unit = trial.acc / np.maximum(norm, 1e-12)[:, None]

    def angle(i, k, rotvec):
        shown = np.arccos(np.clip(np.sum(unit[i] * unit[i + k], axis=1), -1.0, 1.0))
        shown[~(quiet[i] & quiet[i + k]) | (shown == 0.0)] = np.nan
        return shown, np.linalg.norm(np.cross(rotvec, unit[i]), axis=1)

    predicted, shown = _turn_windows(trial, angle)
    return (float(np.median(predicted / shown)) if shown.size >= MIN_WINDOWS else math.nan), int(shown.size)


def _rate_problem(trial: Trial) -> str | None:
    """The sampling rate and the gyro's unit against the truth's turns (else the accelerometer's tilt); None if
    they fit or cannot be told (too few windows that turn)."""
    ratio, windows = gyro_turn_ratio(trial)
    against, ok, warn = "the truth", TURN_OK, TURN_WARN
    if windows < MIN_WINDOWS:
        ratio, windows = gyro_tilt_ratio(trial)
        against, ok, warn = "the accelerometer tilts", TILT_OK, TILT_OK
    if windows < MIN_WINDOWS or ok[0] <= ratio <= ok[1]:
        return None
    turns = f"the gyro turns {ratio:.3g}× as far as {against} ({windows} windows)"
    if ratio == 0.0:
        return f"the gyroscope is all zero: {turns}"
    if warn[0] <= ratio <= warn[1]:
        return f"warn: {turns}: a gyro scale or sampling-rate error?"
    if abs(math.log(ratio / DEG_PER_RAD)) < math.log(1.25):
        return f"gyro rates look like °/s, expected rad/s: {turns}"
    how = f"{1 / ratio:.3g}× too high" if ratio < 1 else f"{ratio:.3g}× too low"
    return f"sampling rate {trial.rate:g} Hz looks {how}: {turns}; about {trial.rate * ratio:.3g} Hz fits"


def rest_samples(trial: Trial) -> np.ndarray:
    """(N,) bool: the samples at rest — |ω| below ``REST_GYR_THRESHOLD``·5 (0.17 rad/s) and |a| steady (its
    std over 0.2 s below ``REST_ACC_STD``)."""
    k = max(1, int(round(0.2 * trial.rate)))
    norm = np.linalg.norm(trial.acc, axis=1)
    box = np.ones(k) / k
    mean, square = np.convolve(norm, box, "same"), np.convolve(norm * norm, box, "same")
    steady = np.sqrt(np.maximum(square - mean * mean, 0.0)) < REST_ACC_STD
    return steady & (np.linalg.norm(trial.gyr, axis=1) < 5 * REST_GYR_THRESHOLD)


def check_physical(trial: Trial, source: str = "") -> list[str]:
    """Whether ``trial``'s sensor magnitudes make physical sense in magenv's units (rad/s, m/s², µT, Hz; see
    the module docstring); returns the warnings (text, empty if none), raises ValueError (a TrialError) naming
    the problem and the likely unit, e.g. "magnetometer norm 4.6e+04 looks like nT, expected µT". ``source``
    (a file name) starts each message.

    * accelerometer: the median |a| at rest (:func:`rest_samples`) within ``GRAVITY_BAND``; with less than 1 s
      at rest, the median over all samples, within ``WARN_FACTOR`` of it (motion biases it: no warning);
    * magnetometer: the median |m| over the initial rest (:func:`initial_rest`) within ``EARTH_FIELD_UT``; with
      less than 1 s of it, the median over all samples, within ``WARN_FACTOR`` of it (a magnet may be near);
    * gyroscope: the 99th percentile of |ω| at most ``GYR_P99_MAX``, every sample at most ``GYR_MAX``;
    * sampling rate (and gyro unit): :func:`gyro_turn_ratio` in ``TURN_OK`` (a warning within
      ``TURN_WARN``), or without truth :func:`gyro_tilt_ratio` within ``TILT_OK``.
    """
    with np.errstate(over="ignore", invalid="ignore"):  # a corrupt 1e300 is refused, not warned about twice
        return _check_physical(trial, f"{source}: " if source else "")


def _check_physical(trial: Trial, prefix: str) -> list[str]:
    second = max(2, int(round(trial.rate)))
    at_rest = rest_samples(trial)
    acc_rest = int(at_rest.sum()) >= second
    acc = np.linalg.norm(trial.acc[at_rest] if acc_rest else trial.acc, axis=1)
    rest = initial_rest(trial.gyr, trial.rate)
    mag_rest = rest.stop - rest.start >= second
    mag = np.linalg.norm(trial.mag[rest] if mag_rest else trial.mag, axis=1)
    problems = [
        _magnitude_problem(
            f"accelerometer norm{' at rest' if acc_rest else ''}",
            float(np.median(acc)),
            GRAVITY_BAND,
            "m/s²",
            ACC_UNITS,
            acc_rest,
        ),
        _magnitude_problem("magnetometer norm", float(np.median(mag)), EARTH_FIELD_UT, "µT", MAG_UNITS, mag_rest),
    ]
    largest = np.abs(trial.gyr).max(axis=1)  # no overflow for a corrupt 1e300
    speed = np.linalg.norm(np.minimum(np.abs(trial.gyr), 1e100), axis=1)
    p99 = float(np.percentile(speed, 99))
    if p99 > GYR_P99_MAX:
        unit = "look like °/s, expected rad/s" if p99 / DEG_PER_RAD <= GYR_P99_MAX else "are implausible in any unit"
        problems.append(f"gyro rates {unit} (99th percentile of |ω| {p99:.3g} rad/s; at most {GYR_P99_MAX:.3g})")
    elif largest.max() > GYR_MAX:
        row = int(np.argmax(largest))
        problems.append(
            f"gyro rate {largest[row]:.3g} rad/s at row {row} is beyond any gyroscope's range "
            f"({GYR_MAX:.3g} rad/s = 4000 °/s): a corrupt sample"
        )
    else:
        problems.append(_rate_problem(trial))
    refusals = [p for p in problems if p is not None and not p.startswith("warn: ")]
    if refusals:
        raise TrialError(prefix + "; ".join(refusals))
    return [prefix + p[len("warn: ") :] for p in problems if p is not None]


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
            ``magenv.trial.RATE_RANGE``, truth off unit norm, no sample to score, magnitudes that make no
            physical sense in the declared units (:func:`check_physical`; a UserWarning for slightly off ones).
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

    try:
        trial = Trial(
            name=path.stem,
            rate=rate,
            gyr=data["imu_gyr"],
            acc=data["imu_acc"],
            mag=data["imu_mag"],
            q_true=q_true,
            field_norm=BERLIN_FIELD_NORM,  # until estimated from data that make physical sense
            field_dip=BERLIN_FIELD_DIP,
            score_mask=movement,
            truth={"opt_pos": data["opt_pos"]},
            meta={"source": "BROAD", "file": str(path), "info": info},
        )
    except TrialError as exc:
        raise TrialError(f"{path}: {exc}") from None
    for warning in check_physical(trial, str(path)):
        warnings.warn(warning, stacklevel=2)
    trial.field_norm, trial.field_dip, trial.meta["field_source"] = estimate_field(
        trial.gyr, trial.acc, trial.mag, rate
    )
    rest = initial_rest(trial.gyr, rate)
    trial.meta["initial_rest_s"] = (rest.stop - rest.start) / rate
    return trial


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
