"""Where magenv keeps the user's own data: tuned-rule files (``magenv tune``) and fetched recordings
(``magenv data broad``).

The folder is ``$MAGENV_DATA_DIR`` if set, else ``$XDG_DATA_HOME/magenv`` (default ``~/.local/share/magenv``).
"""

from __future__ import annotations

import os
from pathlib import Path

DATA_DIR_ENV = "MAGENV_DATA_DIR"


def user_data_dir() -> Path:
    """Where magenv writes user data: ``$MAGENV_DATA_DIR``, else ``$XDG_DATA_HOME/magenv``
    (default ``~/.local/share/magenv``)."""
    if os.environ.get(DATA_DIR_ENV):
        return Path(os.environ[DATA_DIR_ENV])
    base = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(base) / "magenv"
