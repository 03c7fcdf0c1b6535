"""Write files under a temporary name and rename them into place.

A crash or a user error never leaves a half-written ``normal.png`` behind: readers only ever
see complete files.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from psctl.errors import PsctlError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it to ``path`` if the block succeeds.

    The temporary name keeps the final suffix so that format-by-extension writers (OpenImageIO)
    pick the right format.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual file mode
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    write_bytes_atomic(path, text.encode("utf-8"))


def ensure_writable_dir(path: str | os.PathLike) -> Path:
    """Create ``path`` if needed and check that files can be created in it.

    Raises PsctlError naming the folder when it cannot be used, before any work is done.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise PsctlError(path, "output path exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".psctl-write-test.", dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise PsctlError(path, f"output folder is not writable ({e.strerror or e})") from None
    return path


def check_output_dir(path: str | os.PathLike) -> Path:
    """Fail early (before minutes of work) when ``path`` cannot become a writable folder.

    Nothing is created here; ``staged_outputs`` creates the folder when results are ready.
    """
    path = Path(path)
    probe = path
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if not probe.is_dir():
        raise PsctlError(path, f"cannot create output folder: {probe} is not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise PsctlError(path, "output folder is not writable")
    return path


@contextlib.contextmanager
def staged_outputs(out_dir: str | os.PathLike) -> Iterator[Path]:
    """Yield a hidden staging folder inside ``out_dir``; when the block succeeds, move every file
    written there into ``out_dir``. On error nothing appears in ``out_dir`` (and ``out_dir``
    itself is removed again if this call created it): a run gives all of its files or none."""
    out_dir = Path(out_dir)
    created = not out_dir.exists()
    out_dir = ensure_writable_dir(out_dir)
    stage = Path(tempfile.mkdtemp(prefix=".psctl-staging.", dir=out_dir))
    ok = False
    try:
        yield stage
        for f in sorted(stage.iterdir()):
            os.replace(f, out_dir / f.name)
        ok = True
    finally:
        for f in stage.iterdir():
            f.unlink()
        stage.rmdir()
        if not ok and created:
            with contextlib.suppress(OSError):
                out_dir.rmdir()
