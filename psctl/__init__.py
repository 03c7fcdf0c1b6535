"""psctl: photometric stereo from the command line and from Python.

The heavy modules (torch, OpenImageIO) are imported lazily so that ``import psctl`` and
``psctl --help`` stay instant.
"""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"

_LAZY = {
    "estimate_normals": "psctl.api",
    "estimate_lights": "psctl.api",
    "run_normals": "psctl.api",
    "integrate_normals": "psctl.depth",
    "run_lights": "psctl.lights",
    "run_benchmark": "psctl.eval",
    "run_depth": "psctl.depth",
    "open_capture": "psctl.io.capture",
    "load_images": "psctl.io.capture",
    "load_mask": "psctl.io.capture",
    "angular_error": "psctl.metrics",
    "PsctlError": "psctl.errors",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'psctl' has no attribute {name!r}")


__all__ = ["__version__", *_LAZY]
