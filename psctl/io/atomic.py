"""Write files under a temporary name and rename them into place.

A crash or a user error never leaves a half-written ``normal.png`` behind: readers only ever
see complete files.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from psctl.errors import NO_ROOM, PsctlError


def utf8_path(path: Path, message: str) -> str:
    """The path as OpenImageIO takes it: UTF-8 text. A name with bytes that are not UTF-8
    (Python keeps them as lone surrogates) would be a TypeError inside its binding; here it is
    one line naming the path and saying ``message``."""
    name = str(path)
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        raise PsctlError(path, message) from None
    return name


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it to ``path`` if the block succeeds.

    The temporary name keeps the final suffix so that format-by-extension writers (OpenImageIO)
    pick the right format.
    """
    path = Path(path)
    # the stem cut short: a name of 242-255 characters is a valid output, its temporary name must be too
    stem = os.fsencode(path.stem)[:64].decode(errors="ignore") if os.name != "nt" else path.stem[:64]  # bytes: NAME_MAX counts bytes
    fd, tmp = tempfile.mkstemp(prefix=f".{stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        try:
            yield tmp
        except OSError as e:
            if e.filename is not None and os.fspath(e.filename) != str(tmp):
                raise  # about another path (an input read inside the block): its own name
            # a full disk, a quota: name the output, not its temporary name (or none, from write())
            why = e.strerror.lower() if e.strerror else f"{e}; a full disk or a quota?"  # numpy: "N requested and M written"
            raise PsctlError(path, f"cannot write ({why})") from None
        os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp makes 0600; give the usual file mode
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def current_umask() -> int:
    """The process's umask, read without changing it where the system says it (Linux 4.7+:
    /proc/self/status): setting it to 0 and back, the only portable way, leaves a moment in
    which files another thread creates are open to everyone (an audit made 6 in 40 s)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o077)  # elsewhere: a moment at the strictest common mask, not at 0
    os.umask(mask)
    return mask


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """``data`` into ``path`` through a temporary name beside it (no half-written file)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """``text`` as UTF-8 into ``path``, atomically (``write_bytes_atomic``)."""
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
        # a file without a name where the system has them (O_TMPFILE): a signal between making a
        # named probe and removing it left it in the output folder for good (helper-177)
        with tempfile.TemporaryFile(prefix=".psctl-write-test.", dir=path):
            pass
    except OSError as e:
        raise PsctlError(path, f"output folder is not writable ({e.strerror or e})") from None
    return path


def output_folder(out: str | os.PathLike | None, capture: Path) -> Path:
    """The output folder for a capture: ``out``, or ``capture/psctl`` when None. An empty
    ``out`` is an error (it would quietly mean the current folder)."""
    if out is None:
        return capture / "psctl"
    if not os.fspath(out).strip():
        raise PsctlError(None, "--out is empty; name a folder (the default is PATH/psctl)")
    return Path(out)


def check_output_dir(path: str | os.PathLike) -> Path:
    """Fail early (before minutes of work) when ``path`` cannot become a writable folder.

    Nothing is created here; ``staged_outputs`` creates the folder when results are ready.
    """
    path = Path(path)
    utf8_path(path, "the output folder's path is not valid UTF-8 text, which OpenImageIO cannot write to; "
                    "choose another")  # images are written through OpenImageIO
    first = path.parts[0] if path.parts else ""
    if first.startswith("~") and not Path(first).exists() and os.path.expanduser(first) != first:
        # '-o "~/out"': only the shell expands ~, and not in quotes; a folder named ~ would be made
        # here without a word (helper-174)
        raise PsctlError(path, f"starts with {first}, which is not your home folder in quotes (only the shell "
                               f"expands it): write {os.path.expanduser(os.fspath(path))} instead")
    if path.is_symlink() and not path.exists():  # mkdir would say "File exists"
        raise PsctlError(path, f"is a broken link (to {os.readlink(path)}), not a folder: remove it or choose another")
    probe = path
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if not probe.is_dir():
        raise PsctlError(path, f"cannot create output folder: {probe} is not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        # a folder still to be made: the one it would be made in is the one to fix (a helper read
        # "capro/psctl: output folder is not writable" where capro was read-only)
        raise PsctlError(path, "output folder is not writable" if probe == path else
                         f"cannot create output folder: {probe} is not writable")
    return path


LIST_PREFIX = ".psctl-"  # an output list's name: LIST_PREFIX + command


def outputs_list(command: str) -> str:
    """The hidden file in an output folder listing what ``psctl COMMAND`` wrote there last."""
    return f"{LIST_PREFIX}{command}"


def read_small_text(path: str | os.PathLike, limit: int = 1 << 20) -> str:
    """A file psctl wrote itself (an output list, a report), read only when it is a regular file
    of at most ``limit`` bytes: a FIFO there would block the read for ever, a link to /dev/zero
    fill the memory (a hostile-input audit). Else OSError, as for a missing file. (Windows has no
    O_NONBLOCK, and no FIFOs for it to guard against: the type check after opening is enough.)"""
    import stat

    with open(path, "rb", opener=lambda p, flags: os.open(p, flags | getattr(os, "O_NONBLOCK", 0))) as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise OSError(f"{path}: not a regular file")
        data = f.read(limit + 1)
    if len(data) > limit:
        raise OSError(f"{path}: larger than {limit} bytes")
    return data.decode("utf-8")


def read_report(path: str | os.PathLike, limit: int = 64 << 20) -> dict | None:
    """A JSON report psctl wrote (report.json, depth_report.json, ...) as a dict, read as
    ``read_small_text`` reads; None where it is missing, unreadable, not JSON or not an object."""
    import json

    try:
        report = json.loads(read_small_text(path, limit))
    except (OSError, ValueError, RecursionError):  # (UnicodeDecodeError and JSONDecodeError are ValueErrors)
        return None
    return report if isinstance(report, dict) else None


def read_outputs_list(out_dir: Path, command: str) -> list[str]:
    """The files the last ``psctl COMMAND`` run wrote into ``out_dir`` (none without its list)."""
    try:
        return read_small_text(Path(out_dir) / outputs_list(command)).split()
    except (OSError, UnicodeDecodeError):
        return []


def write_outputs_list(stage: Path, names: Iterable[str], command: str) -> None:
    """Record in ``stage`` (staged with the outputs) the files this ``psctl COMMAND`` run writes."""
    (Path(stage) / outputs_list(command)).write_text("".join(f"{n}\n" for n in names), encoding="utf-8")


def replaced_notes(out_dir: Path, names: Iterable[str], command: str, listed: list[str] | None = None) -> list[str]:
    """A note naming the files of ``names`` already in ``out_dir`` that no earlier ``psctl
    COMMAND`` run there listed (a user's own ``depth.png``, say): replaced, never silently.
    ``listed``: that run's list when the caller has read it already. Also a note on earlier
    outputs that a run killed while moving its files in set aside (``.psctl-staging.*/.replaced``):
    kept there, never deleted, so the user is told where."""
    notes = [f"outputs: {d} holds files of an earlier run there, set aside by a run stopped while moving its own "
             "in (kill -9?); move back what you need and remove that folder"
             for d in sorted(Path(out_dir).glob(".psctl-staging.*/.replaced")) if d.is_dir() and any(d.iterdir())]
    if listed is None:
        listed = own_outputs(out_dir, command)
    names = list(names)
    foreign = [n for n in names if n not in listed and (Path(out_dir) / n).is_file()]
    # another command's files (psctl calibrate's light_directions.txt, then psctl lights there:
    # both default to PATH/psctl) are psctl's, not the user's; its report, left beside them, now
    # describes files that are gone, so the note says which of its files stay
    for other in (c for c in commands_listed(out_dir) if c != command):
        theirs = read_outputs_list(out_dir, other)
        mine = [n for n in foreign if n in theirs]
        if mine:
            foreign = [n for n in foreign if n not in mine]
            kept = [n for n in theirs if n not in names and os.sep not in n and (Path(out_dir) / n).is_file()]
            notes.append(f"outputs: replaced {', '.join(mine)} in {out_dir}, written there by an earlier psctl {other} "
                         "run" + (f" (its {', '.join(kept)} stay{'s' if len(kept) == 1 else ''})" if kept else ""))
    if foreign:
        notes.append(f"outputs: replaced {', '.join(foreign)} in {out_dir}, which no earlier psctl {command} run "
                     "there had listed")
    return notes


LISTING_COMMANDS = ("normals", "lights", "calibrate", "depth", "eval", "compare", "undistort")  # keep a list


def commands_listed(folder: Path) -> list[str]:
    """The psctl commands whose output lists ``folder`` holds, in LISTING_COMMANDS' order (a stray
    .psctl-foo names no command)."""
    return [c for c in LISTING_COMMANDS if (Path(folder) / outputs_list(c)).is_file()]


def _list_time(out_dir: Path, command: str) -> int | None:
    try:
        return os.stat(Path(out_dir) / outputs_list(command)).st_mtime_ns
    except OSError:
        return None


def own_outputs(out_dir: Path, command: str) -> list[str]:
    """The files ``psctl COMMAND``'s list in ``out_dir`` names that no other command's newer list
    names: a file two commands write (light_directions.txt: psctl lights and psctl calibrate, both
    into PATH/psctl by default) is its last writer's (a review: lights, calibrate, lights there
    replaced the calibrated directions without a word)."""
    listed, t = read_outputs_list(out_dir, command), _list_time(out_dir, command)
    if not listed or t is None:
        return listed
    claimed: set[str] = set()
    for other in (c for c in commands_listed(out_dir) if c != command):
        if (_list_time(out_dir, other) or 0) > t:
            claimed.update(read_outputs_list(out_dir, other))
    return [n for n in listed if n not in claimed]


def check_inputs_kept(out_dir: str | os.PathLike, names: Iterable[str], inputs: Iterable[tuple[str, object]]) -> None:
    """Refuse, before any work, a run that would write one of ``names`` over a file it reads:
    ``inputs`` are (option, path or None) pairs the user gave (--weights FILE, --normals FILE, ...).
    Inputs are never modified, also when they sit in the output folder under an output's name."""
    # realpath, not Path.resolve: a symbolic-link loop is then a path like any other (its own
    # message comes later), not a RuntimeError
    given = {os.path.realpath(p): flag for flag, p in inputs if isinstance(p, (str, os.PathLike))}
    for n in names:
        flag = given.get(os.path.realpath(Path(out_dir) / n))
        if flag:
            raise PsctlError(Path(out_dir) / n, f"is the {flag} file this run reads and would be replaced by its "
                                                f"output {n}; choose another --out or move the file")


def _machine() -> str:
    """Which machine and process namespace a working folder's process number belongs to: a short
    hash of the host name and the PID namespace (containers sharing a host name and a disk have
    their own process numbers; a review found a container's sweep deleting a live run's folder)."""
    import hashlib
    import socket

    try:
        ns = os.readlink("/proc/self/ns/pid")  # Linux; elsewhere the host name alone
    except OSError:
        ns = ""
    return hashlib.sha256(f"{socket.gethostname()}\0{ns}".encode()).hexdigest()[:10]


def _running(pid: int) -> bool:
    if os.name == "nt":  # there os.kill(pid, 0) sends Ctrl-C to the console (CTRL_C_EVENT is 0): no sweep
        return True
    try:
        os.kill(pid, 0)  # no signal sent: only whether the process exists
    except ProcessLookupError:
        return False
    except (OSError, OverflowError, ValueError):  # someone else's; or a number no process has: not ours to judge
        return True
    return True


def working_folder(folder: Path, prefix: str) -> Path:
    """A new hidden folder in ``folder`` (``prefix`` + machine-pid-random, ``_machine``) for a
    run's files until they move into place, after removing those that runs killed on this
    machine left there (``kill -9``, an out-of-memory kill: nothing of theirs ran to clean up; an
    interruption audit found them piling up). A folder is removed only when its process is gone
    and it holds no earlier outputs set aside by a commit (``.replaced``, synth's ``.earlier``):
    those are never deleted. Folders of other machines or containers (a shared disk) and older
    names are left alone."""
    import re

    machine = _machine()
    mine = re.compile(re.escape(prefix + machine) + r"-(\d{1,9})-")
    with contextlib.suppress(OSError):
        for entry in os.scandir(folder):
            m = mine.match(entry.name)
            if not m or not entry.is_dir(follow_symlinks=False) or _running(int(m.group(1))):
                continue
            aside = [Path(entry.path) / n for n in (".replaced", ".earlier")]
            if any(a.is_dir() and any(a.iterdir()) for a in aside):
                continue
            shutil.rmtree(entry.path, ignore_errors=True)
    return Path(tempfile.mkdtemp(prefix=f"{prefix}{machine}-{os.getpid()}-", dir=folder))


def input_stamp(path: str | os.PathLike) -> tuple | None:
    """What tells a file apart from one written over it or put in its place: (device, inode,
    size, modification time in ns); None when it is gone."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


LOCK_WAIT = 30.0  # seconds: a psctl commit holds a folder's lock for moments; longer is someone else's


@contextlib.contextmanager
def folder_locks(folders: Iterable[Path]) -> Iterator[None]:
    """Exclusive advisory locks (flock) on ``folders``, taken in sorted order (two runs locking
    the same folders cannot wait on each other), for the block: psctl runs moving their files into
    the same folder take turns. Taken before signals are held, so Ctrl-C still stops a run that
    waits. After 2 s of waiting a line on stderr says so; after ``LOCK_WAIT`` s (a lock held that
    long is no psctl commit: ``flock OUT command`` around psctl, say) the run goes on without it
    and says that too. Where a folder cannot be locked (no fcntl; network file systems may refuse
    flock) the block runs as it is."""
    with contextlib.ExitStack() as stack:
        for folder in sorted(set(map(Path, folders))):
            stack.enter_context(_folder_lock(folder))
        yield


@contextlib.contextmanager
def _folder_lock(folder: Path) -> Iterator[None]:
    import time

    try:
        import fcntl

        fd = os.open(folder, os.O_RDONLY)
    except (ImportError, OSError):
        yield
        return
    try:
        start = time.monotonic()
        told = False
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                waited = time.monotonic() - start
                if waited > LOCK_WAIT:
                    _say(f"psctl: {folder} is still locked after {LOCK_WAIT:g} s, longer than any psctl run holds "
                         "it; moving the outputs in without the lock")
                    break
                if waited > 2 and not told:
                    _say(f"psctl: waiting for {folder}: another process holds its lock (a psctl run moving its "
                         "outputs in?)")
                    told = True
                time.sleep(0.05)
            except OSError:  # a file system without flock: as without the lock
                break
        yield
    finally:
        os.close(fd)  # closing releases the lock


def _say(line: str) -> None:
    """A line on stderr from deep inside a run (there is no report to put it in yet)."""
    from psctl.errors import visible

    with contextlib.suppress(AttributeError, OSError, ValueError):
        print(visible(line, newlines=False), file=sys.stderr, flush=True)


def missing_folders(path: Path) -> list[Path]:
    """``path`` and those of its parents that do not exist yet, deepest first: what creating
    ``path`` creates, and what ``remove_empty`` takes away again after a failed run."""
    missing = []
    while not os.path.lexists(path) and path.parent != path:
        missing.append(path)
        path = path.parent
    return missing


def remove_empty(folders: Iterable[Path]) -> None:
    """Remove each folder, deepest first, while it is empty (a folder holding anything, or a
    failure, stops there: nothing but empty folders is ever removed)."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


class Staging:
    """Files written into a hidden folder inside ``out_dir``, then moved into ``out_dir`` together.

    ``replaces``: names of files an earlier run left in ``out_dir`` that this run supersedes
    (the caller knows they are psctl's own: ``psctl normals`` keeps a list, OUTPUTS_LIST); those
    this run does not write are removed when it commits. A callable is asked at the commit, under
    the folder's lock: a run that committed into the folder meanwhile (two psctl runs into one
    folder at once) has its list read then, not at the start. ``inputs``: files the run read,
    each with ``input_stamp`` taken when it was read; the commit stops, nothing moved, when one
    has changed since (``psctl depth`` beside a ``psctl normals`` into the same folder).
    ``commit`` is all or nothing: a file whose place is taken by a folder stops it before anything
    moves, and a failure while moving (an OSError, Ctrl-C) puts every file back. Should putting
    back fail too, the earlier files are left in the staging folder, and the error names it: they
    are never deleted.
    """

    def __init__(self, out_dir: str | os.PathLike, replaces: Iterable[str] | Callable[[], Iterable[str]] = (),
                 inputs: Iterable[tuple[Path, tuple]] = ()) -> None:
        self.out_dir = Path(out_dir)
        self.created = missing_folders(self.out_dir)  # removed again (when empty) if the run fails
        try:
            ensure_writable_dir(self.out_dir)
            self.path = working_folder(self.out_dir, ".psctl-staging.")
        except BaseException:  # (a signal here: staged_outputs never gets this object to clean up, helper-177)
            remove_empty(self.created)
            raise
        self.replaces = replaces if callable(replaces) else tuple(replaces)
        self.inputs = tuple(inputs)
        self._moved: list[str] = []  # earlier files set aside by commit (in path / ".replaced")
        self._placed: list[str] = []  # this run's files moved into out_dir by commit
        self.keep = False  # rollback could not restore everything: discard must not delete

    def _names(self) -> tuple[list[str], list[str]]:
        new = sorted(f.name for f in self.path.iterdir() if f.name != ".replaced")
        replaces = self.replaces() if callable(self.replaces) else self.replaces
        stale = [n for n in replaces if n not in new and (self.out_dir / n).is_file()]
        return new, stale

    def check(self) -> None:
        """Raise (naming the file) when a file cannot take its place: a folder or other non-file
        stands there; or when an input has changed since the run read it."""
        for path, stamp in self.inputs:
            if input_stamp(path) != stamp:
                raise PsctlError(path, "changed while this run read it (another psctl run writing there?); "
                                       "nothing was written: run again")
        for name in self._names()[0]:
            target = self.out_dir / name
            if os.path.lexists(target) and not (target.is_file() or target.is_symlink()):
                raise PsctlError(target, "is in the way of an output file (it is not a file); move it away "
                                         "or choose another --out")

    def commit(self) -> None:
        """Move the files in (the caller holds ``folder_locks`` on ``out_dir``: one commit at a
        time into a folder, each seeing the other's list)."""
        self.check()
        new, stale = self._names()
        old = self.path / ".replaced"
        old.mkdir(exist_ok=True)
        # the folder's list of psctl's files (.psctl-COMMAND) goes aside last and the new one comes in
        # first: a run killed between two renames (kill -9) leaves a list naming every psctl file
        # there, so the next run still removes the stale ones (the old list went first, and a
        # later run kept an earlier normal.exr that psctl depth then read: an interruption audit)
        listed = [n for n in new + stale if n.startswith(LIST_PREFIX)]
        try:
            for name in [n for n in new + stale if n not in listed] + listed:  # aside first, so it can come back
                if os.path.lexists(self.out_dir / name):
                    os.replace(self.out_dir / name, old / name)
                    self._moved.append(name)
            for name in [n for n in new if n in listed] + [n for n in new if n not in listed]:
                os.replace(self.path / name, self.out_dir / name)
                self._placed.append(name)
        except BaseException as e:  # OSError, and Ctrl-C between two renames
            self.rollback()
            if isinstance(e, OSError):
                raise PsctlError(self.out_dir, f"could not move the outputs into place ({e.strerror or e}); "
                                               "nothing was changed") from None
            raise

    def rollback(self) -> None:
        """Undo ``commit``: this run's files back out, the earlier ones back in. What cannot be
        put back stays in the staging folder (``keep``), and a PsctlError names it."""
        # in the reverse order of commit's: the new list goes out last and the old one comes back
        # first, so that a kill here too leaves a list naming every psctl file in the folder
        for name in reversed(self._placed):
            with contextlib.suppress(OSError):
                os.replace(self.out_dir / name, self.path / name)
        lost = []
        for name in reversed(self._moved):
            try:
                os.replace(self.path / ".replaced" / name, self.out_dir / name)
            except OSError:
                lost.append(name)
        self._placed, self._moved = [], []
        if lost:
            self.keep = True
            raise PsctlError(self.path / ".replaced", f"writing the outputs failed and {', '.join(lost)} from an "
                                                      f"earlier run could not be put back into {self.out_dir}: "
                                                      "they are here; move them back by hand")

    def discard(self, remove_created: bool = True) -> None:
        """Remove the staging folder (and what commit set aside), and ``out_dir`` and the parents
        this staging created too when nothing else is in them; nothing when ``keep``."""
        if self.keep:
            return
        shutil.rmtree(self.path, ignore_errors=True)
        if remove_created:
            remove_empty(self.created)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold Ctrl-C, SIGTERM and SIGHUP until the block ends, then hand the first one to the
    handler that was set: moving the outputs into place and removing the staging folder is not
    to be cut in two (a SIGTERM during the clean-up left the staging folder behind beside complete
    outputs, a hostile-input audit). Python runs signal handlers in the main thread only: in any
    other thread (and where handlers cannot be set) the block runs as it is."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    # not an ignored signal (nohup's SIGHUP: it would hide one that counts), nor one whose handler
    # was set outside Python (getsignal None: it could not be put back)
    sigs = [s for s in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None))
            if s is not None and signal.getsignal(s) not in (None, signal.SIG_IGN)]
    pending: list[int] = []
    before = {}
    try:
        for s in sigs:
            before[s] = signal.signal(s, lambda signum, frame: pending.append(signum))
        yield
    finally:
        failed = None
        for s, handler in before.items():  # every one back, whatever happens to one of them
            try:
                signal.signal(s, handler)
            except BaseException as e:  # noqa: BLE001 (a signal arriving now, put back after the rest)
                failed = failed or e
                signal.signal(s, handler)
        if failed is not None:
            raise failed
        if pending:  # as if it came now: the handler it would have met
            handler = before[pending[0]]
            if callable(handler):
                handler(pending[0], sys._getframe())
            elif handler == signal.SIG_DFL:
                signal.raise_signal(pending[0])


@contextlib.contextmanager
def staged_outputs(out_dir: str | os.PathLike, replaces: Iterable[str] | Callable[[], Iterable[str]] = (),
                   inputs: Iterable[tuple[Path, tuple]] = ()) -> Iterator[Path]:
    """Yield a hidden staging folder inside ``out_dir``; when the block succeeds, move every file
    written there into ``out_dir`` (``Staging``). On error nothing appears in ``out_dir`` (and
    ``out_dir`` itself is removed again if this call created it): a run gives all of its files or
    none."""
    stage = Staging(out_dir, replaces, inputs)
    try:
        yield stage.path
    except BaseException as e:
        with signals_deferred():  # removed in one piece
            stage.discard()
        if isinstance(e, PsctlError):
            raise by_final_name(e, [(stage.path, stage.out_dir)]) from None
        named = no_room(e, stage.out_dir)
        if named is not e:
            raise named from None
        raise
    # the lock first (a wait for it can be stopped: then nothing moved), then moved and cleaned up
    # in one piece
    started = False
    try:
        with folder_locks([stage.out_dir]), signals_deferred():
            started, ok = True, False
            try:
                stage.commit()
                ok = True
            finally:
                stage.discard(remove_created=not ok)
    except BaseException:
        if not started:
            with signals_deferred():
                stage.discard()
        raise


def no_room(error: BaseException, out_dir: str | os.PathLike) -> BaseException:
    """A full disk met while staging the outputs, where the system's error names no file (a write
    found short at close, as pathlib's write_text raises it): a PsctlError naming the output
    folder, else ``error`` itself."""
    if isinstance(error, OSError) and error.filename is None and error.errno in NO_ROOM:
        what = error.strerror.lower() if error.strerror else str(error)
        return PsctlError(out_dir, f"cannot write the outputs ({what}); nothing was written")
    return error


def by_final_name(error: PsctlError, stagings: "Iterable[tuple[Path, Path]]") -> PsctlError:
    """``error`` naming the output (out/normal.png) instead of its staged copy
    (out/.psctl-staging.x/normal.png), which is gone when the user reads the message;
    ``stagings``: (staging folder, output folder) pairs. ``error`` itself where it names neither."""
    if error.path is not None:
        for stage, out_dir in stagings:
            with contextlib.suppress(ValueError):
                return PsctlError(out_dir / Path(error.path).relative_to(stage),
                                  error.message.replace(str(stage), str(out_dir)))
    return error


class OutputBatch:
    """Several runs' outputs (``psctl eval --out``: one folder per object, and eval.png / eval.json in the root) that appear together
    or not at all: each run stages its files (``stage``), and they are committed only when the
    ``with`` block ends without an error, after every folder has been checked; a failure while
    committing one folder undoes the folders committed before it."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)
        self.created = missing_folders(self.root)
        self.stagings: list[Staging] = []

    def stage(self, out_dir: str | os.PathLike, replaces: Iterable[str] | Callable[[], Iterable[str]] = ()) -> Staging:
        self.stagings.append(Staging(out_dir, replaces))
        return self.stagings[-1]

    def __enter__(self) -> "OutputBatch":
        return self

    def __exit__(self, kind, value, tb) -> None:
        # every folder's lock first (a wait for one can be stopped), then committed and cleaned up
        # in one piece
        started = False
        try:
            with folder_locks([s.out_dir for s in self.stagings] if kind is None else []), signals_deferred():
                started = True
                self._finish(kind, value)
        except BaseException as e:
            if not started:  # stopped while waiting for a lock: nothing moved; discarded as after a failure
                with signals_deferred():
                    self._finish(type(e), e)
            raise

    def _finish(self, kind, value) -> None:
        ok = False
        try:
            if isinstance(value, PsctlError):
                renamed = by_final_name(value, [(s.path, s.out_dir) for s in self.stagings])
                if renamed is not value:
                    raise renamed from None
            named = no_room(value, self.root)
            if named is not value:
                raise named from None
            if kind is None:
                for s in self.stagings:
                    s.check()
                done = []
                try:
                    for s in self.stagings:
                        s.commit()
                        done.append(s)
                except BaseException:
                    kept = []
                    for s in reversed(done):
                        try:
                            s.rollback()
                        except PsctlError as e:  # what could not be put back is kept (s.keep): say where
                            kept.append(e)
                    if kept:
                        raise kept[0] from None
                    raise
                ok = True
        finally:
            for s in self.stagings:
                s.discard(remove_created=not ok)
            if not ok:  # every folder a staging created, deepest first: a folder of several
                # stagings (psctl eval -m A -m B: OUT/A holds each object's) goes once all are gone
                created = {f for s in self.stagings for f in s.created} | set(self.created)
                for folder in sorted(created, key=lambda f: len(f.parts), reverse=True):
                    remove_empty([folder])
