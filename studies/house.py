"""The house in figures: lines per package, repeated code, and the files a new env touches — of the tree or a commit.

    python -m studies.house                 # this checkout
    python -m studies.house --rev cbd04e5   # a commit (extracted to a temporary folder with ``git archive``)

Prints one Markdown table (the one of ``docs/ARCHITECTURE.md``'s section "The house in figures"):

* lines of the Python files of each top-level package (every line, blank and comment lines too);
* pairs of places that share six or more lines of the same shape: the first line of the ``duplicates`` tool
  (``duplicates --min-lines 6``), over the whole tree and with both places inside ``magenv/``;
* the files a new env touches: the distinct paths (back-quoted, with a ``/``) in the "file" column of
  ``docs/ARCHITECTURE.md``'s table "The files a new env touches", and the README if a row names it.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

PACKAGES = ("magenv", "agents", "baselines", "train", "studies", "benchmarks", "tests")
TABLE_HEAD = "## The files a new env touches"


def package_lines(root: Path) -> dict[str, int]:
    """Lines of the ``.py`` files below each of :data:`PACKAGES`."""
    return {
        p: sum(len(f.read_text(encoding="utf-8").splitlines()) for f in sorted((root / p).rglob("*.py")))
        for p in PACKAGES
    }


def duplicate_pairs(root: Path, seconds: int = 300) -> tuple[int, int]:
    """(pairs in the whole tree, pairs with both places in ``magenv/``) from ``duplicates --most 200``."""
    out = subprocess.run(
        ["duplicates", "--repo", str(root), "--most", "200", "--seconds", str(seconds)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    first = out.splitlines()[0]
    if first.startswith("no duplicates"):
        return 0, 0
    if "incomplete:" in out:
        raise SystemExit(f"duplicates did not finish in {seconds} s: {out.splitlines()[-1]}")
    total = int(first.split()[0])
    rows = [re.match(r"D\d+ (\S+?):\d+-\d+ ~ (\S+?):\d+-\d+", line) for line in out.splitlines()]
    inside = sum(1 for m in rows if m and m.group(1).startswith("magenv/") and m.group(2).startswith("magenv/"))
    if sum(1 for m in rows if m) != total:
        raise SystemExit(f"duplicates listed {sum(1 for m in rows if m)} of {total} pairs; raise --most")
    return total, inside


def env_files(root: Path) -> int:
    """The files a new env touches: distinct back-quoted paths of the table's "file" column, the README counted
    once if named."""
    text = (root / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    if TABLE_HEAD not in text:
        raise SystemExit(f"docs/ARCHITECTURE.md has no section {TABLE_HEAD!r}")
    section = text.split(TABLE_HEAD, 1)[1].split("\n## ", 1)[0]
    paths, readme = set(), False
    for line in section.splitlines():
        cells = line.split("|")
        if len(cells) < 4 or set(cells[2].strip()) <= {"-"} or cells[2].strip() == "file":
            continue
        paths |= {p for p in re.findall(r"`([^`]+)`", cells[2]) if "/" in p}
        readme |= "README" in cells[2]
    return len(paths) + readme


def measure(root: Path) -> dict[str, int]:
    """Every figure of the table for the tree at ``root``."""
    total, inside = duplicate_pairs(root)
    return {
        **{f"lines {p}/": n for p, n in package_lines(root).items()},
        "pairs repeating ≥ 6 lines (whole tree)": total,
        "of them inside magenv/": inside,
        "files a new env touches": env_files(root),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rev", action="append", default=[], help="a commit to measure (repeatable); none: this tree")
    args = ap.parse_args(argv)
    root = Path(__file__).resolve().parent.parent
    columns: dict[str, dict[str, int]] = {}
    for rev in args.rev:
        with tempfile.TemporaryDirectory() as tmp:
            archive = subprocess.run(["git", "-C", str(root), "archive", rev], capture_output=True, check=True).stdout
            subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
            columns[rev] = measure(Path(tmp))
    if not args.rev:
        columns["this tree"] = measure(root)
    print("| figure | " + " | ".join(columns) + " |")
    print("|---|" + "---:|" * len(columns))
    for key in next(iter(columns.values())):
        print(f"| {key} | " + " | ".join(str(c[key]) for c in columns.values()) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
