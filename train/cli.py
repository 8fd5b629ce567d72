"""``magenv`` command: one subcommand per module of this package.

Each subcommand module defines ``add_arguments(parser)`` and ``run(args) -> int``.
Modules are imported only when their command runs, so ``magenv --help`` is fast.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import tempfile
from pathlib import Path
from typing import overload

COMMANDS = {
    "simulate": ("magenv.train.simulate", "make one simulated trial and write it to HDF5"),
    "plot": ("magenv.train.plot", "draw a trial file: orientation, rates, field norm and dip, magnet distance"),
    "compare": ("magenv.train.compare", "run every method on the same trials and print the RMSE table"),
    "fidelity": ("magenv.train.fidelity", "each method on real recordings beside their twins: RMSEs, Spearman rho"),
    "train": ("magenv.train.train", "train a learning agent on an environment"),
    "sweep": ("magenv.train.sweep", "train many runs (envs × algorithms × seeds × hyperparameters) on Ray Tune"),
    "agents": ("magenv.train.agents", "list the trained agents shipped with magenv (--agent pretrained:ENV_ID)"),
    "estimate": (
        "magenv.train.estimate",
        "orientation of your own IMU log (CSV or HDF5) with a method's magnetometer trust",
    ),
    "evaluate": ("magenv.train.evaluate", "score a trained agent on scenarios or recordings"),
    "export": ("magenv.train.export", "a DAgger student as an ONNX model with a JSON sidecar (features, lags, action)"),
    "benchmark": ("magenv.train.benchmark", "score a policy on the benchmark suite (magenv-bench v1): its score card"),
    "datasets": ("magenv.train.datasets", "offline datasets (Minari) of the oracles' and tuned rules' rollouts"),
    "tune": ("magenv.train.tune", "optimise the hand-crafted rules' parameters with CMA-ES"),
    "pictures": ("magenv.train.pictures", "draw the README's pictures: a rendered frame and trust over time"),
    "report": ("magenv.train.report", "write a Markdown report with tables and plots"),
    "paper": ("magenv.train.paper", "print a paper check: the papers' tables reproduced in simulation"),
    "data": ("magenv.train.data", "fetch the real recordings (BROAD) from their public repository, checked by SHA-256"),
    "demo": ("magenv.train.demo", "the main job: train briefly, then compare learned against hand-tuned weighting"),
}


class CommandError(Exception):
    """A user-facing error: printed without a traceback, exit status 2."""


#: Exit statuses: 0 all done; 1 done, but some cell of a table is n/a (the reasons are printed);
#: 2 a bad command line, file or config (nothing run; the message names it); 130 interrupted.
PARTIAL = 1
TRUST_PICKLE_HELP = (
    "also load agents from SB3 .zip files, which carry pickles that can run code: only for run "
    "folders whose author you trust (default: weights-only files)"
)


#: What ``--plot`` and the like may write (matplotlib's formats; a name without a suffix gets the first).
IMAGE_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg")


def _check_writable_folder(folder: Path, option: str, path: Path) -> None:
    """CommandError unless ``folder`` exists as a folder one can write in, or can be made (its nearest existing
    ancestor is one): a file is made and removed there to find out."""
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise CommandError(f"{option} {path}: {probe} is a file, not a folder")
    try:
        handle, name = tempfile.mkstemp(dir=probe, prefix=".magenv-write-check-")
        os.close(handle)
        os.unlink(name)
    except OSError as exc:
        raise CommandError(f"{option} {path}: cannot write in {probe} ({exc.strerror})") from None


@overload
def output_file(path: None, option: str, suffixes: tuple[str, ...] = ()) -> None: ...
@overload
def output_file(path: str | Path, option: str, suffixes: tuple[str, ...] = ()) -> Path: ...
def output_file(path: str | Path | None, option: str, suffixes: tuple[str, ...] = ()) -> Path | None:
    """The file an output option (``--csv``, ``--plot`` …) names, checked before any work is done: not a folder,
    writable, in a folder that exists or can be made. ``suffixes``: the kinds of file it may be (a name without a
    suffix gets the first, and the name returned is the one to write and print). None stays None. CommandError
    naming the option and the problem."""
    if path is None:
        return None
    path = Path(path)
    if path.is_dir():
        raise CommandError(f"{option} {path}: is a folder; give a file name")
    if suffixes and path.suffix.lower() not in suffixes:
        if path.suffix:
            raise CommandError(f"{option} must name a {', '.join(suffixes)} file, got {path}")
        path = path.with_name(path.name + suffixes[0])
        if path.is_dir():
            raise CommandError(f"{option} {path}: is a folder; give a file name")
    if path.exists():
        try:
            open(path, "ab").close()  # appends nothing: the file stays as it is until it is written
        except OSError as exc:
            raise CommandError(f"{option} {path}: cannot write it ({exc.strerror})") from None
    _check_writable_folder(path.parent, option, path)
    return path


@overload
def output_folder(path: None, option: str) -> None: ...
@overload
def output_folder(path: str | Path, option: str) -> Path: ...
def output_folder(path: str | Path | None, option: str) -> Path | None:
    """The folder an output option (``--out``) names, checked before any work is done: a folder one can write
    in, or one that can be made. None stays None. CommandError naming the option and the problem."""
    if path is None:
        return None
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise CommandError(f"{option} {path}: is a file, not a folder")
    _check_writable_folder(path, option, path)
    return path


def rule_arg(rule):
    """An argparse ``type`` checking a number against ``rule`` (a ``magenv.agents.hyperparams.Rule``);
    argparse names the flag in the error, e.g. ``argument --steps: must be an integer ≥ 1, got '0'``."""

    def parse(text: str):
        value: int | float | str
        try:
            value = int(text)
        except ValueError:
            try:
                value = float(text)
            except ValueError:
                value = text
        try:
            return rule.convert(value)
        except (ValueError, TypeError):
            raise argparse.ArgumentTypeError(f"must be {rule.expected}, got {text!r}") from None

    return parse


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="magenv", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        # Arguments are added lazily below, only for the command being run.
    return parser


def one_torch_thread() -> None:
    """Agents act with torch on ``TORCH_THREADS`` (one) in every command: their small networks' decisions take
    many times longer on torch's default threads of a loaded machine (``benchmarks/bench_scoring.py``)."""
    import torch

    from magenv.agents.training import TORCH_THREADS

    torch.set_num_threads(TORCH_THREADS)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser()
    if argv and argv[0] in COMMANDS:
        module = importlib.import_module(COMMANDS[argv[0]][0])
        p = argparse.ArgumentParser(prog=f"magenv {argv[0]}", description=COMMANDS[argv[0]][1])
        module.add_arguments(p)
        try:
            args = p.parse_args(argv[1:])
        except SystemExit as exc:  # argparse has printed the usage and the error (or the help)
            return int(exc.code or 0)
        one_torch_thread()
        try:
            return int(module.run(args) or 0)
        except CommandError as exc:
            print(f"magenv {argv[0]}: error: {exc}", file=sys.stderr)
            return 2
    try:
        parser.parse_args(argv)  # prints help / errors for unknown commands
    except SystemExit as exc:
        return int(exc.code or 0)
    return 2


if __name__ == "__main__":
    sys.exit(main())
