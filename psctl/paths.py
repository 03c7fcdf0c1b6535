"""Where psctl looks for files it does not ship inside the package: its source checkout (a clone,
an editable install, an unpacked sdist) when it runs from one, else the user's data folder.

An installed wheel lives in site-packages: a folder ``weights/`` beside the package there would be
a top-level name shared with every other package, need root for a system install, and outlive
``pip uninstall`` (a packaging audit, session 52).
"""

from __future__ import annotations

import os
from pathlib import Path


def checkout_root() -> Path | None:
    """The source checkout psctl runs from: the folder above the package when it holds
    pyproject.toml; None for an installed wheel."""
    root = Path(__file__).resolve().parents[1]
    return root if (root / "pyproject.toml").is_file() else None


def user_data_dir() -> Path:
    """$XDG_DATA_HOME/psctl, else ~/.local/share/psctl: psctl's folder for a user's files."""
    base = os.environ.get("XDG_DATA_HOME") or "~/.local/share"
    try:
        return Path(base).expanduser() / "psctl"
    except RuntimeError:  # no $HOME and no passwd entry (a container run under an arbitrary user id): as
        return Path(base) / "psctl"  # written, a folder that is not there (messages name it so)
