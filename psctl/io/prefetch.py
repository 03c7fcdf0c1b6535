"""Decoding a capture's images in a helper process while psctl starts its network.

Before the first image goes through a network, psctl imports torch and loads the weights (about
1 s on a laptop CPU), and decoding 96 16-bit PNGs takes about as long again on one core.
``Prefetch`` runs the decoding in a child Python process, which writes each image, cut to the
region the network reads, into shared memory: the two overlap on two cores (docs/performance.md,
"Decoding while torch imports").

The child only decodes (``read_image``, ``to_rgb``, the crop). Everything the readers do next
(intensities, ambient, saturation and black-image checks, notes) stays in this process. Whatever
the child cannot do (an unreadable file, a size that changed, a crash, a system without
``memfd_create``) only means that this process reads that image and the rest itself, as it did
before: the same values, and the same one-line errors. A process and not a thread, because psctl
silences file descriptor 2 around each decode (libpng prints its own line for a broken PNG) and a
process's threads share fd 2 (docs/performance.md, "Reading on two threads").
"""

from __future__ import annotations

import dataclasses
import json
import mmap
import os
import select
import socket
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from psctl.io.images import ImageInfo

# A decode that takes longer than this (seconds) is given up and read here instead: the largest
# EXR decodes in a few seconds; a child that hangs must not hang psctl.
TIMEOUT = 120.0
# The child says "ready" once started (Python, numpy, OpenImageIO imported); without that line
# within this many seconds, ``sys.executable`` is not a Python that can run it (an application
# embedding Python, uWSGI) and this process reads the images itself.
START_TIMEOUT = 10.0

# The child: psctl importable from the same sys.path as this process (a source checkout, a
# notebook's added paths), then the loop. Its stderr is /dev/null: a failure is read again here.
_BOOT = "import sys, json; sys.path[:] = json.loads(sys.argv[1]); from psctl.io.prefetch import _child; _child()"

_Box = tuple[slice, slice]


def _box_key(box: _Box) -> tuple[int, int, int, int]:
    return (box[0].start, box[0].stop, box[1].start, box[1].stop)


def _cpus() -> float:
    """The CPUs this process may use: its affinity, and a container's CPU quota (cgroup v2
    ``cpu.max``, v1 ``cpu.cfs_quota_us``), which the affinity does not show."""
    n = float(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    for quota_file, period_file in (("/sys/fs/cgroup/cpu.max", None),
                                    ("/sys/fs/cgroup/cpu/cpu.cfs_quota_us", "/sys/fs/cgroup/cpu/cpu.cfs_period_us")):
        try:
            with open(quota_file) as f:
                words = f.read().split()
            if period_file is not None:
                with open(period_file) as f:
                    words.append(f.read().strip())
            quota, period = words[0], float(words[1])
            if quota not in ("max", "-1") and period > 0:
                n = min(n, float(quota) / period)
        except (OSError, ValueError, IndexError):
            pass
    return n


def _usable() -> bool:
    """Whether a helper can run here: Linux's memfd, a Python to start, two CPUs to overlap on,
    and file descriptors 0-2 open. A process started with one of them closed (``2>&-``, a daemon)
    would be handed 0-2 for the ring's and pipes' own descriptors, and a C library's message on
    stderr (libgomp, libpng) would then land in the ring or among the credits."""
    if not hasattr(os, "memfd_create") or not sys.executable or getattr(sys, "frozen", False):
        return False  # no memfd (Windows, macOS); embedded or frozen: no Python to start
    if _cpus() < 2:
        return False  # one CPU: the decoding would only take turns with the import (measured: 0.3 s slower)
    try:
        for fd in (0, 1, 2):
            os.fstat(fd)
    except OSError:
        return False
    return True


class Prefetch:
    """Decode ``paths`` in order in a child process, each cut to ``box`` (two slices with
    explicit starts and stops inside the ``size`` (width, height) of the capture), into a ring
    of shared memory of at most ``budget`` bytes.

    ``take(path, box)``, called for the paths in order, returns what ``read_image`` and
    ``to_rgb`` give for that image, cut to ``box``: ([h, w, 3] float32, ImageInfo); or None,
    from which point on the caller reads the images itself: the child stopped (an image it
    could not decode or whose size changed: the caller's own read then gives the error), or
    the call is not the next path with this box. ``served`` counts the images handed over.
    Use it as a context manager, or call ``close()``: the child is killed and its memory freed.
    Where a helper cannot run or would not help (``_usable``: no ``os.memfd_create``, one CPU,
    a closed stdin, stdout or stderr) or an image is larger than ``budget``, the object starts
    nothing and every ``take`` returns None.
    """

    def __init__(self, paths: Sequence[Path], box: _Box, size: tuple[int, int], budget: int):
        self.paths = list(paths)
        self.key = _box_key(box)
        y0, y1, x0, x1 = self.key
        self.shape = (y1 - y0, x1 - x0, 3)
        self.served = 0
        self.proc: subprocess.Popen | None = None
        self.mm: mmap.mmap | None = None
        self.fd = -1
        self._buf = b""
        page = mmap.PAGESIZE  # slots on page boundaries: a used slot's pages are given back at once
        self.slot = -(-int(np.prod(self.shape)) * 4 // page) * page
        self.slots = min(len(self.paths), budget // self.slot) if self.slot else 0
        self.credits: socket.socket | None = None
        self.owed = 0  # freed slots not yet told to the child (its socket buffer was full)
        self.started = False  # the child's "ready" line read
        # the file's (inode, size, mtime ns) as the child found it before decoding the image that
        # ``take`` last returned (DecodeMemo.stamp's): a memo keeps what the file held then
        self.stamp: tuple[int, int, int] | None = None
        if self.slots < 1 or min(self.shape[:2]) < 1 or not _usable():
            return
        import psctl

        spec_fd, theirs = -1, None
        try:
            # credits on a socket, not a pipe: sent with MSG_NOSIGNAL, a child that has ended is an
            # error here and not SIGPIPE, which kills a caller that set it to SIG_DFL (``| head``);
            # never blocking: each send takes a buffer of its own, and a few hundred fill the socket
            self.credits, theirs = socket.socketpair()
            self.credits.setblocking(False)
            self.fd = os.memfd_create("psctl-prefetch")
            os.ftruncate(self.fd, self.slots * self.slot)
            self.mm = mmap.mmap(self.fd, self.slots * self.slot)
            # the list of files in a file of its own: through the pipe, thousands of names would
            # wait for the child's start (its imports), which is the time this is meant to win
            # "psctl": this process's package; the child stops if sys.path gives it another one
            spec = json.dumps({"paths": [os.fsdecode(p) for p in self.paths], "box": self.key, "size": list(size),
                               "fd": self.fd, "slots": self.slots, "slot": self.slot,
                               "psctl": os.path.realpath(psctl.__file__)}).encode()  # ASCII
            spec_fd = os.memfd_create("psctl-prefetch-spec")
            os.write(spec_fd, spec)  # tmpfs: one call writes it all
            os.lseek(spec_fd, 0, os.SEEK_SET)
            where = json.dumps([p for p in sys.path if isinstance(p, str)])
            self.proc = subprocess.Popen([sys.executable, "-c", _BOOT, where, str(spec_fd)], bufsize=0,
                                         stdin=theirs.fileno(), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                         pass_fds=(self.fd, spec_fd))
        except (OSError, ValueError):  # no memory for the ring, no process to spare: read here
            self.close()
        except BaseException:  # Ctrl-C while starting: nothing left behind
            self.close()
            raise
        finally:
            if spec_fd >= 0:
                os.close(spec_fd)
            if theirs is not None:  # the child's end: the child has its own copy
                theirs.close()

    def __enter__(self) -> "Prefetch":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the child (if still running) and free the ring. Idempotent."""
        proc, self.proc = self.proc, None
        if self.credits is not None:  # first: a child waiting for a credit then ends by itself
            self.credits.close()
            self.credits = None
        if proc is not None:
            proc.stdout.close()
            if proc.poll() is None:
                proc.kill()  # mid-decode: no need to wait for that image
            proc.wait()
        if self.mm is not None:
            self.mm.close()
            self.mm = None
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1

    def _line(self, timeout: float = TIMEOUT) -> bytes | None:
        """The child's next status line, None at its end or after ``timeout`` seconds."""
        out = self.proc.stdout.fileno()
        poll = select.poll()  # not select.select: it fails for descriptors above 1023
        poll.register(out, select.POLLIN)
        while b"\n" not in self._buf:
            chunk = os.read(out, 65536) if poll.poll(timeout * 1000) else b""
            if not chunk:
                return None
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        return line

    def take(self, path: Path, box: _Box) -> tuple[np.ndarray, ImageInfo] | None:
        k = self.served
        if self.proc is None or k >= len(self.paths) or Path(path) != self.paths[k] or _box_key(box) != self.key:
            self.close()  # out of order or another region: the caller reads from here on
            return None
        try:
            if not self.started:
                self.started = self._line(START_TIMEOUT) == b"ready"
                if not self.started:
                    raise OSError("the helper did not start")
            line = self._line()
            status = json.loads(line) if line else None
            # (JSON gave the header's tuples, pick and window, back as lists)
            info = ImageInfo(self.paths[k], **{n: tuple(v) if isinstance(v, list) else v
                                               for n, v in status["info"].items()})
            stamp = tuple(int(v) for v in status["stamp"])
        except (OSError, ValueError, TypeError, KeyError):  # no line, or not one this process wrote
            info = None
        if info is None or status.get("k") != k:
            self.close()
            return None
        off = (k % self.slots) * self.slot
        pixels = np.frombuffer(self.mm, np.float32, int(np.prod(self.shape)), off).reshape(self.shape).copy()
        if hasattr(mmap, "MADV_REMOVE"):
            self.mm.madvise(mmap.MADV_REMOVE, off, self.slot)  # the pages go back now, not at the end
        self.served += 1
        self.stamp = stamp
        if k + self.slots < len(self.paths):  # an image still to come needs this slot
            self.owed += 1
        if self.owed:
            try:
                self.owed -= self.credits.send(b"\x01" * self.owed, socket.MSG_NOSIGNAL)
            except BlockingIOError:  # the child has plenty unread: told at a later take
                pass
            except OSError:  # the child has stopped; the next take says so
                self.owed = 0
        return pixels, info


def check_prefetch_mb(mb: object) -> int:
    """The ``prefetch_mb`` setting: a whole number of MB >= 0 (0: off)."""
    from psctl.errors import PsctlError

    if isinstance(mb, bool) or not isinstance(mb, (int, np.integer)) or mb < 0:
        raise PsctlError(None, f"prefetch_mb must be a whole number of MB >= 0 (0: off), got {mb!r}")
    return int(mb)


def prefetch(paths: Sequence[Path], box: _Box | None, size: tuple[int, int], mb: object) -> Prefetch:
    """A ``Prefetch`` for a first pass over ``paths`` cut to ``box`` with a ring of ``mb`` MB (a
    network's ``prefetch_mb`` setting, checked here; 0: off), started only while torch is not
    imported: the child's decoding overlaps torch's import, and once torch is loaded there is
    nothing to overlap (``psctl eval``'s later objects: the same time either way). ``box`` None:
    off (the caller reads no region the helper could cut, e.g. an empty mask)."""
    check_prefetch_mb(mb)
    off = box is None or "torch" in sys.modules
    return Prefetch(paths, (slice(0, 0), slice(0, 0)) if box is None else box, size, 0 if off else int(mb) << 20)


def _child() -> None:
    """The helper process: decode, crop, write into the ring slot, say so on stdout; wait for a
    free slot on stdin. Any failure ends it; the parent then reads the image itself."""
    try:
        import OpenImageIO as oiio

        import psctl
        from psctl.io.images import read_image, to_rgb

        oiio.attribute("threads", 1)  # one core: the other one is the parent's
        with open(int(sys.argv[2]), "rb") as f:
            spec = json.loads(f.read())
        if os.path.realpath(psctl.__file__) != spec["psctl"]:
            raise ImportError("another psctl")  # its reading might differ: the parent reads
        y0, y1, x0, x1 = spec["box"]
        shape = (y1 - y0, x1 - x0, 3)
        slots, slot = spec["slots"], spec["slot"]
        ring = mmap.mmap(spec["fd"], slots * slot)
        os.write(1, b"ready\n")
        credits = 0
        for k, name in enumerate(spec["paths"]):
            if k >= slots:  # wait until the parent has taken the image in this slot
                if not credits:
                    credits = len(os.read(0, 65536))
                    if not credits:
                        break  # the parent has closed its end
                credits -= 1
            st = os.stat(name)  # before the read, as DecodeMemo.stamp: a later change is seen
            pixels, info = read_image(name)
            if [info.width, info.height] != spec["size"]:
                break  # the parent's own read says what is wrong
            rgb = to_rgb(pixels)[y0:y1, x0:x1]
            if rgb.shape != shape:
                break
            np.frombuffer(ring, np.float32, rgb.size, (k % slots) * slot).reshape(shape)[...] = rgb
            # (the ICC tone curve stays out: the readers take it from the Capture, and it is no JSON)
            header = {f.name: getattr(info, f.name) for f in dataclasses.fields(info) if f.name not in ("path", "tone")}
            stamp = [st.st_ino, st.st_size, st.st_mtime_ns]
            os.write(1, json.dumps({"k": k, "info": header, "stamp": stamp}).encode() + b"\n")
    except BaseException:  # noqa: BLE001 - whatever it was, the parent reads the image itself
        pass
    os._exit(0)
