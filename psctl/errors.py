"""One exception type for everything a user can get wrong.

The CLI prints ``str(err)`` as a single line and exits with code 2; library users catch
``PsctlError`` (a ``ValueError``) like any other bad-argument error.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator


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
