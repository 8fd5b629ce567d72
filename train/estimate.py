"""``magenv estimate``: the orientation of your own IMU log, with the magnetometer trust a method chose.

    magenv estimate LOG.csv (--method NAME | --agent AGENT) --out OUT.csv|OUT.h5 [--plot FILE.png]
                    [--time COL | --rate HZ] [--gyr X,Y,Z] [--acc X,Y,Z] [--mag X,Y,Z]
                    [--gyr-unit rad/s|deg/s] [--acc-unit m/s2|g] [--mag-unit uT|gauss|nT]
                    [--field-norm µT --field-dip °] [--delimiter ,] [--no-progress]

INPUT is a CSV file with a header row — by default the columns ``t,gx,gy,gz,ax,ay,az,mx,my,mz`` in s, rad/s,
m/s² and µT, sensor frame; ``--gyr/--acc/--mag`` name other columns, the ``--*-unit`` options declare other
units, ``--time`` another time column (s; its median step gives the rate, which must be steady) and ``--rate``
a rate for a file without one — or an HDF5 file: a BROAD recording or a magenv trial (``magenv simulate``),
whose truth, if any, is not used. The magnitudes are held to the declared units as the loaders do
(``magenv.recordings.check_physical``: refused naming the likely unit, or warned). The local Earth field is taken
from the initial rest (else the whole file) unless given (``magenv.streaming.site_field``; a BROAD file's own,
``magenv.recordings``).

The method is any name of ``magenv compare`` (rules, ``vqf``, ``fusion``, the ``_tuned`` rules),
``pretrained:ENV_ID`` (a shipped agent) or, with ``--agent``, a trained agent's run folder (or
``pretrained:ENV_ID``). OUT (``.csv``, or ``.h5``/``.hdf5``) holds per sample: ``t`` (s), the quaternion
``qw,qx,qy,qz`` (sensor → ENU), ZYX Euler angles ``yaw,pitch,roll`` (°, ENU: yaw from east, counter-clockwise),
``heading`` (° clockwise from magnetic north of the sensor's x axis, 90° − yaw), ``inclination`` (° between the
sensor's z axis and up) and ``trust``, the magnetometer trust the method applied (blank / NaN where the method
reports none). ``--plot`` draws heading, inclination and trust over time.
"""

from __future__ import annotations

import argparse
import csv
import os
import tempfile
from pathlib import Path

import numpy as np

from magenv.train.cli import IMAGE_SUFFIXES, CommandError, output_file

DEFAULT_COLUMNS = {"t": "t", "gyr": ("gx", "gy", "gz"), "acc": ("ax", "ay", "az"), "mag": ("mx", "my", "mz")}
#: unit → factor to magenv's units (rad/s, m/s², µT)
UNITS = {
    "gyr": {"rad/s": 1.0, "deg/s": np.pi / 180.0},
    "acc": {"m/s2": 1.0, "g": 9.80665},
    "mag": {"uT": 1.0, "gauss": 100.0, "nT": 1e-3},
}
MAX_JITTER = 0.05  # time steps further than this fraction from the median step: not a steady rate
PROGRESS_MIN_S = 60.0  # s of data from which a progress bar is drawn
HDF5_SUFFIXES = (".h5", ".hdf5")
OUT_COLUMNS = ("t", "qw", "qx", "qy", "qz", "yaw", "pitch", "roll", "heading", "inclination", "trust")


def _triple(text: str) -> tuple[str, str, str]:
    names = tuple(s.strip() for s in text.split(","))
    if len(names) != 3 or not all(names):
        raise argparse.ArgumentTypeError(f"must name three columns X,Y,Z, got {text!r}")
    return names[0], names[1], names[2]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", type=Path, help="the IMU log: a CSV file with a header row, or an HDF5 recording / trial")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--method", help="a method name of magenv compare, or pretrained:ENV_ID")
    which.add_argument("--agent", help="a trained agent's run folder (or pretrained:ENV_ID)")
    p.add_argument("--out", type=Path, required=True, help="output file: .csv, or .h5 / .hdf5")
    p.add_argument("--plot", type=Path, default=None, metavar="FILE.png", help="draw heading, inclination, trust")
    p.add_argument("--time", default=None, metavar="COL", help="the time column, s (default t, if present)")
    p.add_argument("--rate", type=float, default=None, metavar="HZ", help="sampling rate (for a file without time)")
    for key, default in (("gyr", "gx,gy,gz"), ("acc", "ax,ay,az"), ("mag", "mx,my,mz")):
        p.add_argument(f"--{key}", type=_triple, default=None, metavar="X,Y,Z", help=f"columns (default {default})")
        units = list(UNITS[key])
        p.add_argument(f"--{key}-unit", choices=units, default=units[0], help="unit (default %(default)s)")
    p.add_argument("--field-norm", type=float, default=None, metavar="µT", help="local Earth field norm")
    p.add_argument("--field-dip", type=float, default=None, metavar="DEG", help="local dip, positive down")
    p.add_argument("--delimiter", default=",", help="CSV delimiter (default %(default)r)")
    p.add_argument("--no-progress", action="store_true")


def read_csv(path: Path, args: argparse.Namespace):
    """(gyr, acc, mag (N, 3) in rad/s, m/s², µT; rate Hz) of a CSV log (see the module docstring)."""
    try:
        with open(path, newline="") as f:
            header = [h.strip() for h in next(csv.reader(f, delimiter=args.delimiter))]
    except (OSError, UnicodeDecodeError) as exc:
        raise CommandError(f"{path}: cannot read ({type(exc).__name__}: {exc})") from None
    except StopIteration:
        raise CommandError(f"{path}: empty file (a CSV log needs a header row)") from None
    cols = {k: getattr(args, k) or DEFAULT_COLUMNS[k] for k in ("gyr", "acc", "mag")}
    time_col = args.time or (DEFAULT_COLUMNS["t"] if args.rate is None else None)
    wanted = [*cols["gyr"], *cols["acc"], *cols["mag"], *([time_col] if time_col else [])]
    missing = [c for c in wanted if c not in header]
    if missing:
        hint = " (or give --rate for a file without time)" if time_col in missing and not args.time else ""
        raise CommandError(f"{path}: no column(s) {', '.join(missing)} in the header {header}{hint}")
    try:
        table = np.loadtxt(path, delimiter=args.delimiter, skiprows=1, usecols=[header.index(c) for c in wanted],
                           ndmin=2)  # fmt: skip
    except ValueError as exc:
        raise CommandError(f"{path}: not all numbers ({exc})") from None
    bad = np.flatnonzero(~np.isfinite(table).all(axis=1))
    if bad.size:
        raise CommandError(f"{path}: NaN/inf in {bad.size} row(s), first at data row {bad[0] + 1}")
    if len(table) < 2:
        raise CommandError(f"{path}: {len(table)} data row(s); a log needs at least 2")
    gyr, acc, mag = (table[:, 3 * i : 3 * i + 3] * UNITS[k][getattr(args, f"{k}_unit")] for i, k in
                     enumerate(("gyr", "acc", "mag")))  # fmt: skip
    if args.rate is not None:
        return gyr, acc, mag, args.rate
    return gyr, acc, mag, rate_of(table[:, 9], path)


def rate_of(t: np.ndarray, path: Path) -> float:
    """The sampling rate (Hz) of time stamps ``t`` (s): 1 / their median step to 9 significant digits (time
    stamps i·0.01 s give 100 Hz exactly), which every step must match within ``MAX_JITTER`` (CommandError
    naming the first that does not)."""
    step = np.diff(t)
    median = float(np.median(step))
    if not median > 0:
        raise CommandError(f"{path}: the time column does not increase (median step {median:g} s)")
    off = np.flatnonzero(np.abs(step - median) > MAX_JITTER * median)
    if off.size:
        raise CommandError(
            f"{path}: uneven sampling: {off.size} time step(s) differ from the median {median:g} s by more than "
            f"{MAX_JITTER:.0%}, first after data row {off[0] + 1} ({step[off[0]]:g} s); resample the log, or give "
            "--rate to take the rows as evenly spaced"
        )
    return float(f"{1.0 / median:.9g}")


def load_input(args: argparse.Namespace):
    """The input as a Trial without (or with unused) truth."""
    from magenv.streaming import own_trial
    from magenv.trial import TrialError

    path = args.input
    if not path.is_file():
        raise CommandError(f"{path}: no such file")
    try:
        if path.suffix.lower() in HDF5_SUFFIXES:
            from magenv.recordings import load_trial_file

            trial = load_trial_file(path)
            if args.field_norm is not None or args.field_dip is not None:
                raise CommandError("--field-norm/--field-dip are for CSV logs; an HDF5 file carries its field")
            return trial
        gyr, acc, mag, rate = read_csv(path, args)
        return own_trial(gyr, acc, mag, rate, args.field_norm, args.field_dip, name=path.stem)
    except (TrialError, ValueError) as exc:
        raise CommandError(f"{path}: {exc}") from None


def columns(result) -> dict[str, np.ndarray]:
    """The output columns (``OUT_COLUMNS``) of an ``Estimation``."""
    from magenv import quaternion as quat

    q, n = result.q, len(result.q)
    yaw, pitch, roll = np.rad2deg(quat.to_euler_zyx(q)).T
    w, x, y, z = q.T
    inclination = np.rad2deg(np.arccos(np.clip(1.0 - 2.0 * (x * x + y * y), -1.0, 1.0)))
    trust = np.full(n, np.nan) if result.trust is None else np.asarray(result.trust, float)
    out = {"t": result.trial.t, "qw": w, "qx": x, "qy": y, "qz": z, "yaw": yaw, "pitch": pitch, "roll": roll}
    out.update({"heading": np.mod(90.0 - yaw, 360.0), "inclination": inclination, "trust": trust})
    return out


def write(path: Path, result, source: Path) -> None:
    """The output file, written whole and then renamed (an interrupted run leaves none)."""
    cols = columns(result)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    os.close(fd)
    try:
        if path.suffix.lower() in HDF5_SUFFIXES:
            import h5py

            with h5py.File(tmp, "w") as f:
                for k, v in cols.items():
                    f.create_dataset(k, data=v)
                trial = result.trial
                f.attrs.update({"method": result.method, "input": str(source), "rate": trial.rate,
                                "field_norm": trial.field_norm, "field_dip": trial.field_dip,
                                "field_source": str(trial.meta.get("field_source", "")),
                                "columns": "t s; q sensor→ENU [w,x,y,z]; angles °; trust"})  # fmt: skip
        else:
            table = np.column_stack([cols[k] for k in OUT_COLUMNS])
            np.savetxt(tmp, table, delimiter=",", header=",".join(OUT_COLUMNS), comments="", fmt="%.9g")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def draw(path: Path, result) -> None:
    """Heading, inclination and trust over time (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = columns(result)
    fig, ax = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
    for a, key, label in zip(ax, ("heading", "inclination", "trust"), ("heading, °", "inclination, °", "trust")):
        a.plot(cols["t"], cols[key], lw=0.7)
        a.set_ylabel(label)
    ax[2].set_ylim(-0.05, 1.05)
    ax[2].set_xlabel("t, s")
    ax[0].set_title(f"{result.method} on {result.trial.name}")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    from magenv.streaming import estimate, method_of

    args.out = output_file(args.out, "--out", (".csv", *HDF5_SUFFIXES))
    args.plot = output_file(args.plot, "--plot", IMAGE_SUFFIXES)
    if args.rate is not None and not (np.isfinite(args.rate) and args.rate > 0):
        raise CommandError(f"--rate must be a positive number of Hz, got {args.rate}")
    name = args.method if args.method is not None else "agent:" + args.agent
    try:
        method = method_of(name)
    except ValueError as exc:  # unknown names, unreadable run folders (RunError is a ValueError)
        raise CommandError(str(exc)) from None
    trial = load_input(args)
    bar = None
    if not args.no_progress and trial.duration >= PROGRESS_MIN_S:
        from tqdm import tqdm

        bar = tqdm(total=trial.n, unit="sample", desc=name, leave=False)
    progress = None if bar is None else lambda done, total: bar.update(done - bar.n)
    try:
        result = estimate(method, trial, progress)
        result.method = name
    except ValueError as exc:  # the method's own refusal of this input (e.g. a two-link filter on one IMU)
        raise CommandError(f"{name} cannot run on {args.input}: {exc}") from None
    finally:
        if bar is not None:
            bar.close()
    write(args.out, result, args.input)
    print(f"{name} on {trial.name}: {trial.n} samples at {trial.rate:g} Hz, field {trial.field_norm:.1f} µT "
          f"dip {trial.field_dip:.1f}° ({trial.meta.get('field_source', 'file')}) → {args.out}")  # fmt: skip
    if args.plot is not None:
        draw(args.plot, result)
        print(f"wrote {args.plot}")
    return 0
