"""One exception type for everything a user can get wrong.

The CLI prints ``str(err)`` as a single line and exits with code 2; library users catch
``PsctlError`` (a ``ValueError``) like any other bad-argument error.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import math
import numbers
import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any

# errno values that say the disk (or a quota, or a size limit) has no room: the user's to fix,
# even where no file name comes with them (a write to stdout redirected to a full disk)
NO_ROOM = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def visible(text: str, newlines: bool = True) -> str:
    """``text`` with its control characters written out (ESC as \\x1b), tabs and, with
    ``newlines``, line breaks kept: a file or folder name is printed in messages, and one holding
    an escape sequence (a downloaded capture's filenames.txt) would retitle or clear the user's
    terminal (a hostile-input audit)."""
    keep = "\t\n" if newlines else "\t"
    return "".join(c if c in keep or not (ord(c) < 32 or 127 <= ord(c) < 160) else f"\\x{ord(c):02x}" for c in text)


@functools.cache
def _console_class() -> type:
    # made on first use, not at import: rich stays unimported for library users who never print
    from rich.console import Console

    class _Console(Console):
        def print(self, *objects: Any, **kwargs: Any) -> None:
            isatty = getattr(self.file, "isatty", None)
            if not (isatty and isatty()) and not os.environ.get("COLUMNS") and objects and \
                    all(isinstance(o, str) for o in objects):
                # into a pipe or a file a line stays one line (Rich would break it at 80 columns,
                # and a grep for a note's words would miss it), FORCE_COLOR or not, unless COLUMNS
                # asks for a width; a terminal wraps it at words
                kwargs.setdefault("soft_wrap", True)
            super().print(*(visible(o) if isinstance(o, str) else o for o in objects), **kwargs)

    return _Console


def console(stderr: bool = False) -> Any:
    """A Rich console for psctl's messages and summaries: every string it prints has its control
    characters written out (``visible``)."""
    return _console_class()(stderr=stderr)


class PsctlError(ValueError):
    """A user error: bad folder, missing or malformed file, mismatched sizes, ...

    Args:
        path: the file or folder at fault (may be None when no file is involved).
        message: what is wrong, in a few words.
    """

    def __init__(self, path: str | os.PathLike | None, message: str):
        self.path = None if path is None else os.fspath(path)
        self.message = message
        super().__init__(f"{self.path}: {message}" if self.path else message)

    def __reduce__(self):
        # pickled and copied by (path, message), not by the formatted line: a worker process of
        # a ProcessPoolExecutor hands it back whole (else its pool breaks on the first bad folder)
        return type(self), (self.path, self.message)


class PsctlWarning(UserWarning):
    """A note of psctl normals that the array API, which has no report, gives as a warning
    (``estimate_normals``: a network on fewer than 3 images or coplanar lights); silence or raise
    it with Python's warning filters."""


@contextlib.contextmanager
def naming(path: str | os.PathLike) -> Iterator[None]:
    """Errors raised inside that name no file get ``path`` (the capture folder being read), so
    that a message like "all images are black inside the mask" says where."""
    try:
        yield
    except PsctlError as e:
        if e.path is not None:
            raise
        raise PsctlError(path, e.message) from None


def few(names: Sequence[str], n: int = 3) -> str:
    """The first ``n`` names, then " ..." when there are more: how notes and errors list files."""
    names = list(names)
    return ", ".join(names[:n]) + (" ..." if len(names) > n else "")


def is_number(value: Any) -> bool:
    """A finite real number that is not a bool (YAML's true is an int to Python); numpy scalars
    count."""
    if not isinstance(value, numbers.Real) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value) and math.isfinite(float(value))  # an int of 400 digits is no float
    except OverflowError:
        return False


def like_default(where: str, value: Any, default: Any, text_hint: str = "") -> Any:
    """``value`` checked against the kind of ``default`` (a setting's default: bool, int, float,
    list of numbers or str) and returned in that kind (whole floats such as 2.5e+6 as ints,
    tuples as lists of floats); otherwise a one-line error naming ``where``, with ``text_hint``
    added when a number was given as text."""
    if isinstance(default, bool):
        ok, want = isinstance(value, bool), "true or false"
    elif isinstance(default, int):
        ok, want = is_number(value) and float(value).is_integer(), "a finite integer"
    elif isinstance(default, float):
        ok, want = is_number(value), "a finite number"
        if isinstance(value, str):
            want += text_hint
    elif isinstance(default, list):
        ok = isinstance(value, (list, tuple)) and len(value) == len(default) and all(map(is_number, value))
        want = f"a list of {len(default)} numbers"
    else:
        ok, want = isinstance(value, type(default)), f"a {type(default).__name__}"
    if not ok:
        raise PsctlError(None, f"{where} must be {want}, not {value!r}")
    if isinstance(default, bool):
        return value
    if isinstance(default, int):
        return int(value)
    if isinstance(default, float):
        return float(value)
    if isinstance(default, list):
        return [float(v) for v in value]
    return value


def check_int(where: str, value: Any) -> int | None:
    """None, or a whole number (an int, a numpy integer or a float such as 4.0; not a bool, not
    text) returned as an int; otherwise a one-line error naming ``where``. The range is the
    caller's to check."""
    if value is None:
        return None
    if not (is_number(value) and float(value).is_integer()):
        raise PsctlError(None, f"{where} must be a whole number, not {value!r}")
    return int(value)


def caller_level(frames: int = 1) -> int:
    """The ``stacklevel`` of a warning raised ``frames`` calls below a public function (1: in it),
    so that it points at the user's line: one more where the call came through the package's
    wrapper (``psctl.X``)."""
    import sys

    caller = sys._getframe(frames + 1).f_globals.get("__name__")
    return frames + (2 if caller == "psctl" else 1)


def check_bool(where: str, value: Any) -> bool:
    """True or False (numpy's too); anything else, such as the truthy text "no", is an error."""
    import numpy as np

    if not isinstance(value, (bool, np.bool_)):
        raise PsctlError(None, f"{where} must be True or False, not {value!r}")
    return bool(value)


def quoted_tilde(path: str | os.PathLike) -> str:
    """For a missing path's message: a leading ~ that names an existing place in the home folder
    (a quoted '~/cap' reaches psctl as it is: only the shell expands ~, helper-174)."""
    text = os.fspath(path)
    if not isinstance(text, str) or not text.startswith("~"):
        return ""
    home = os.path.expanduser(text)
    return f" (a ~ in quotes is not your home folder: {home})" if home != text and os.path.exists(home) else ""


def not_a_file(path: str | os.PathLike, missing: str, folder: str | None = None) -> str:
    """Why ``path``, which is not a regular file, cannot be read as one: ``folder`` for a folder,
    a device, FIFO or socket said as such (/dev/zero, a named pipe: not "missing"), else
    ``missing``."""
    import stat

    try:
        mode = os.stat(path).st_mode
    except OSError:
        return missing + quoted_tilde(path)
    if stat.S_ISDIR(mode):
        if folder is None and missing.endswith(" is missing"):  # "camera file is missing": "is a folder, not a camera file"
            thing = missing[:-len(" is missing")]
            folder = f"is a folder, not {'an' if thing[:1] in 'aeiou' else 'a'} {thing}"
        return folder or f"is a folder; {missing}"
    return f"is {special_kind(mode)}, not a regular file"


def special_kind(mode: int) -> str:
    """What a file that is neither a regular file nor a folder is, by its ``st_mode``."""
    import stat

    return "a FIFO" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode) else "a device"


def check_path(where: str, value: Any, optional: bool = False) -> Any:
    """A path argument given as something else (None where one is needed, a number, a list) or as
    an empty string is a one-line error naming ``where``, not Python's TypeError from deep inside
    or the current folder; returns ``value``."""
    if value is None and optional:
        return None
    if isinstance(value, str) and not value.strip():  # Path("") would be "." (the current folder)
        raise PsctlError(None, f"{where} is an empty path")
    if isinstance(value, (str, os.PathLike)) and not isinstance(value, bytes):
        return value
    hint = "; pass capture.path" if type(value).__name__ == "Capture" else ""
    raise PsctlError(None, f"{where} must be a path (str or os.PathLike), not {_short(value)}{hint}")


def _short(value: Any) -> str:
    """A value for a one-line message: a scalar's repr, else its type (an array, a Capture)."""
    import reprlib

    if value is None or isinstance(value, (str, bytes, numbers.Number, list, tuple, set, frozenset, dict)):
        return reprlib.repr(value)  # cut to a few dozen characters
    return f"a value of type {type(value).__name__}"


def check_formats(value: Any) -> str:
    """Output formats as text ("png16,exr") or any collection of names -> the text form."""
    if isinstance(value, str):
        return value
    if not isinstance(value, (bytes, dict)) and hasattr(value, "__iter__"):
        names = list(value)
        if all(isinstance(v, str) for v in names):
            return ",".join(names)
    raise PsctlError(None, f"formats must be text such as 'png16,exr' or a list of names, not {_short(value)}")


# C libraries (libpng) print their own line on file descriptor 2 for a broken file, beside the
# error OpenImageIO returns, which psctl's message carries. The command line promises one line,
# so psctl.cli.main sets "silence"; a library caller's fd 2 is left alone, since silencing it is
# process-wide: another thread's stderr would be lost while an image is read (an audit found a
# service's log gone to /dev/null).
C_STDERR = {"silence": False}

# progress(description, total) -> advance(n) (psctl.api.ProgressFactory): defined here, where the
# modules that take one can import it at run time (typing.get_type_hints resolves it)
ProgressFactory = Callable[[str, int], Callable[[int], None]]


def check_progress(progress: Any) -> Any:
    """A progress factory ``(label, total) -> advance(k)``, or a no-op one for None; anything
    else (a number, True) is a one-line error, not "'int' object is not callable" mid-run."""
    if progress is None:
        return lambda label, total: (lambda k: None)
    if not callable(progress):
        raise PsctlError(None, f"progress must be None or a callable (label, total) -> advance(k), "
                               f"not {_short(progress)}")
    import inspect

    try:
        inspect.signature(progress).bind("label", 1)
    except TypeError:  # an advance(k) itself (psctl.load_images took one until session 75): a TypeError mid-run
        raise PsctlError(None, "progress must be a factory (label, total) -> advance(k), called once per stage; "
                               "this callable does not take (label, total)") from None
    except ValueError:  # no signature to read (some builtins): called as it is
        pass
    return progress


# --- messages for Python callers ---------------------------------------------------------------
# The library words its messages for the command line, which most users meet first ("--weights
# FILE"). psctl's top-level functions (psctl.run_normals, ...) reword them for Python callers:
# each option of those functions is named as its argument ("weights=FILE").
PYTHON_ARGS = {
    "--method": "method", "--weights": "weights", "--lcnet": "lcnet", "--device": "device",
    "--views": "views", "--images": "n_images", "--seed": "seed", "--encoding": "encoding",
    "--format": "formats", "--out": "out", "--light-distance": "light_distance", "--falloff": "falloff",
    "--normals-weights": "normals_weights", "--normals": "normals", "--root": "root",
    "--benchmark": "benchmark", "--decode": "decode", "--K": "K", "--downsample": "downsample",
    "--precision": "precision", "--sphere": "sphere", "--circle": "circle", "--offset": "offset",
    "--focal": "focal", "--principal": "principal",
}
_SWITCHES = {"--no-refine": "refine=False", "--refine": "refine=True", "--no-roll": "roll=False",
             "--roll/--no-roll": "roll", "--roll": "roll=True", "`psctl lights`": "psctl.estimate_lights",
             "`psctl eval`": "psctl.run_benchmark", "--albedo": "albedo=True"}
# values an option may have in a message: quoted in the Python wording (method='sdps')
_WORDS = ("auto|l2|ps-fcn-dagger|ps-fcn-n|ps-fcn|ensemble|ups-fcn|sdps|lcnet|cpu|cuda(?::\\d+)?|diligent|folder|"
          "linear|srgb|chrome|matte|shifted|lambertian|soft|argmax|poisson|bilateral|float32|bf16|fp16")


def python_wording(text: str) -> str:
    """A message worded for the command line, with its options named as Python arguments:
    "use --method l2" -> "use method='l2'", "--weights FILE" -> "weights=FILE",
    "--light-distance must be ..." -> "light_distance must be ...", "--no-refine" -> "refine=False".
    Other text (file names, `psctl train ...`, options of commands without a Python twin) stays."""
    import re

    # an option stands alone: not inside a word or a path (/data/my--weights/, light--out.txt)
    alone = r"(?<![\w/.\\-])"
    for cli, py in sorted(_SWITCHES.items(), key=lambda kv: -len(kv[0])):  # --roll/--no-roll before --roll
        text = re.sub(alone + re.escape(cli) + r"(?![\w-])", py, text)
    flags = "|".join(re.escape(f) for f in sorted(PYTHON_ARGS, key=len, reverse=True))

    def one(m: re.Match) -> str:
        name, value = PYTHON_ARGS[m.group(1)], m.group(2)
        if value is None:
            return name
        if re.fullmatch(_WORDS, value):
            return f"{name}={value!r}"
        return f"{name}={value}"  # a number, or a placeholder such as FILE or DIR

    value = rf"(?: ({_WORDS}|[A-Z]+|-?\d+(?:\.\d+)?)(?![\w-]))?"
    return re.sub(rf"{alone}({flags})(?![\w-]){value}", one, text)


def moved_names(old: str, *new: str) -> Callable[[str], Any]:
    """A module ``__getattr__`` for ``old`` that finds the names (in their ``__all__``) that moved
    from it to the ``new`` modules, the same objects, with a DeprecationWarning: code written
    against the old module keeps working, and says where to look."""
    def __getattr__(name: str) -> Any:
        import importlib
        import warnings

        for module in new:
            mod = importlib.import_module(module)
            if name in mod.__all__:
                warnings.warn(f"psctl: {old}.{name} is now {module}.{name}", DeprecationWarning, stacklevel=2)
                return getattr(mod, name)
        raise AttributeError(f"module {old!r} has no attribute {name!r}")

    return __getattr__
