"""The ``psctl`` command's entry point (and ``python -m psctl``'s): Ctrl-C while the command's
modules are still importing (about 0.1 s, before psctl.cli sets its own handling) exits 130
quietly, as Ctrl-C at any later moment does, instead of Python's KeyboardInterrupt traceback
(helper-177)."""
from __future__ import annotations

import sys


def main(prog_name: str | None = None) -> None:
    try:
        from psctl.cli import main as run
    except KeyboardInterrupt:
        sys.exit(130)
    run(prog_name=prog_name)
