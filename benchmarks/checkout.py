"""Import magenv from another checkout of this repository (e.g. the commit before a change) in this process.

    git -C REPO archive COMMIT | tar -x -C DIR      # or: git worktree add --detach DIR COMMIT
    python -c "import checkout; checkout.use(DIR); import magenv; …"

Call :func:`use` before anything imports magenv: ``import magenv`` then loads ``DIR/magenv`` and the
subpackages the installed package maps to the repository's top-level folders (``magenv.agents`` →
``DIR/agents``, ``magenv.baselines``, ``magenv.train``), whatever magenv is installed. The benchmarks time
such an older checkout in a subprocess beside the current code (``bench_kernels.py --baseline DIR``), and
``tests/kernel_rmse.py --checkout DIR`` records the per-trial RMSEs of that code as a test fixture.
"""

from __future__ import annotations

import importlib.abc
import importlib.util
import sys
from pathlib import Path

SUBPACKAGES = {"magenv": "magenv", "magenv.agents": "agents", "magenv.baselines": "baselines", "magenv.train": "train"}


class _CheckoutFinder(importlib.abc.MetaPathFinder):
    """Finds magenv and its folder-mapped subpackages in one checkout (the rest through their ``__path__``)."""

    def __init__(self, root: Path):
        self.root = root

    def find_spec(self, name, path=None, target=None):
        folder = SUBPACKAGES.get(name)
        if folder is None:
            return None
        d = self.root / folder
        return importlib.util.spec_from_file_location(name, d / "__init__.py", submodule_search_locations=[str(d)])


def use(root) -> Path:
    """Make ``import magenv`` load the checkout at ``root`` (a folder with magenv/, agents/, baselines/,
    train/); ValueError if it is none or magenv is already imported from elsewhere."""
    root = Path(root).resolve()
    missing = [f for f in SUBPACKAGES.values() if not (root / f / "__init__.py").is_file()]
    if missing:
        raise ValueError(f"{root} is no magenv checkout: it lacks {', '.join(f + '/__init__.py' for f in missing)}")
    loaded = sys.modules.get("magenv")
    if loaded is not None and Path(loaded.__file__ or "").resolve().parent != root / "magenv":
        raise ValueError(f"magenv is already imported from {loaded.__file__}; call use() before importing it")
    sys.meta_path.insert(0, _CheckoutFinder(root))
    return root
