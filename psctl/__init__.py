"""psctl: photometric stereo from the command line and from Python.

The heavy modules (torch, OpenImageIO) are imported lazily so that ``import psctl`` and
``psctl --help`` stay instant.

The functions here wrap those of their modules (``psctl.run_normals`` calls
``psctl.api.run_normals``, available as its ``__wrapped__``): the same arguments and results,
except that their errors and report notes name options as Python arguments ("weights=FILE")
where the modules, which the command line shares, say "--weights FILE".
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from types import ModuleType

__version__ = "0.1.0"

_LAZY = {
    "estimate_normals": "psctl.api",
    "estimate_lights": "psctl.api",
    "estimate_albedo": "psctl.albedo",
    "run_normals": "psctl.api",
    "integrate_normals": "psctl.depth",
    "run_lights": "psctl.lights",
    "run_benchmark": "psctl.eval",
    "compare_methods": "psctl.eval",
    "run_depth": "psctl.depth",
    "run_calibrate": "psctl.calibrate",
    "calibrate_lights": "psctl.calibrate",
    "run_undistort": "psctl.undistort",
    "open_capture": "psctl.io.capture",
    "load_images": "psctl.io.capture",
    "load_mask": "psctl.io.capture",
    "angular_error": "psctl.metrics",
    "PsctlError": "psctl.errors",
    "PsctlWarning": "psctl.errors",
}

if TYPE_CHECKING:  # for type checkers and editors; at run time __getattr__ imports on first use
    from psctl.albedo import estimate_albedo
    from psctl.calibrate import calibrate_lights, run_calibrate
    from psctl.api import estimate_lights, estimate_normals, run_normals
    from psctl.depth import integrate_normals, run_depth
    from psctl.errors import PsctlError, PsctlWarning
    from psctl.eval import compare_methods, run_benchmark
    from psctl.io.capture import load_images, load_mask, open_capture
    from psctl.undistort import run_undistort
    from psctl.lights import run_lights
    from psctl.metrics import angular_error


def _python_notes(result: Any) -> Any:
    """A report's notes (and its objects' notes) in the Python wording; other results as they are."""
    from psctl.errors import python_wording

    if isinstance(result, dict):
        if isinstance(result.get("notes"), list):
            result["notes"] = [python_wording(n) if isinstance(n, str) else n for n in result["notes"]]
        for obj in [*(result.get("objects") or []), *(result.get("runs") or [])]:  # runs: compare_methods'
            _python_notes(obj)
    return result


def _for_python(fn: Any) -> Any:
    import functools

    from psctl import errors

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return _python_notes(fn(*args, **kwargs))
        except errors.PsctlError as e:
            raise errors.PsctlError(e.path, errors.python_wording(e.message)) from None

    # psctl.X is what pickle finds under this name (ProcessPoolExecutor.map(psctl.run_normals, ...))
    wrapper.__module__, wrapper.__qualname__ = "psctl", fn.__name__
    return wrapper


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        if name not in ("PsctlError", "PsctlWarning"):
            value = _for_python(value)
        globals()[name] = value  # imported once
        return value
    return _submodule(__name__, name)


def _submodule(package: str, name: str) -> "ModuleType":
    """``package``'s submodule ``name``, imported on first use: after ``import psctl``,
    ``psctl.infer.array_normals`` and ``psctl.io.capture.iter_images`` work as the docs write them
    (an AttributeError unless another call had imported the module: a docs check, session 73).
    Else the AttributeError of a missing attribute."""
    if name.isidentifier() and not name.startswith("_"):  # not "io.capture", "a.b" (a review: an import error)
        import importlib
        import importlib.util

        try:
            found = importlib.util.find_spec(f"{package}.{name}") is not None
        except (ImportError, ValueError):
            found = False
        if found:
            return importlib.import_module(f"{package}.{name}")
    raise AttributeError(f"module {package!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})


__all__ = ["__version__", "estimate_normals", "estimate_lights", "estimate_albedo", "run_normals", "integrate_normals", "run_undistort",
           "run_lights", "run_benchmark", "compare_methods", "run_depth",
           "run_calibrate", "calibrate_lights", "open_capture", "load_images", "load_mask",
           "angular_error", "PsctlError", "PsctlWarning"]
