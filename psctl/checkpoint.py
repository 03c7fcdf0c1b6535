"""A training run's checkpoint: the files of a run folder and how they are written, committed,
finished after a kill, and read back by ``--resume``.

    run/model.pt        psctl weights (release format) of the latest state
    run/optim.0.pt ...  Adam's state in parts of at most OPTIM_PART_BYTES (the GPU machine returns
                        files of under 16 MB)
    run/stream.pt       the synthetic stream's state
    run/state.json      step, samples seen, wall time, validation history, ...
    run/checkpoint.json the journal: present only while a checkpoint is being committed

Each file is written under a staged name, then one journal write commits them as a set
(``commit_checkpoint``), so that a hard kill leaves the previous checkpoint whole or a journal
that ``finish_checkpoint`` (``--resume``, or the GPU script before it returns the files)
completes. ``Stop`` turns SIGINT/SIGTERM/SIGHUP into a checkpoint at the next step, and
``no_half_run`` removes what a run that failed before its first checkpoint cannot resume from.
``psctl.train`` writes and reads checkpoints through these; what a checkpoint's recipe may
change on resume is decided there (``_resumed_state``).

This module must not import OpenImageIO: it runs on the GPU machine, which lacks it.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from psctl.errors import PsctlError
from psctl.models.weights import file_sha256, save_torch

__all__ = ["OPTIM_PART_BYTES", "OPTIM_PART", "no_half_run", "Stop", "save_optimizer", "JOURNAL", "STAGED", "TEMP_FILE",
           "commit_checkpoint", "finish_checkpoint", "load_optimizer", "adam_steps",
           "drop_lines_after_checkpoint", "check_state", "restore_checkpoint", "restore_stream"]


OPTIM_PART_BYTES = 12 * 2**20
OPTIM_PART = re.compile(r"optim\.\d+\.pt")


@contextlib.contextmanager
def folder_lock(folder: Path, busy: str) -> Iterator[None]:
    """Hold an exclusive advisory lock (flock) on ``folder``'s own descriptor, not on a file in
    it (folders' contents are checked by name, and nothing is left behind); the kernel releases
    it when the process ends, however it ends. Held elsewhere: PsctlError(folder, busy). No flock
    (Windows, some network file systems) or a folder that cannot be opened: as without."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:  # cannot be opened as a folder: the caller's own checks name it
        yield
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise PsctlError(folder, busy) from None
        except OSError:
            pass
        yield
    finally:
        os.close(fd)


def run_lock(run: Path) -> contextlib.AbstractContextManager[None]:
    """One process at a time in a run folder, for the run's whole life: a second ``psctl train
    --resume`` of the same folder while one ran finished the first one's checkpoint under it and
    stopped with a misleading "committed but not carried out" (session 79)."""
    return folder_lock(run, "is locked by another process (another psctl train of this run folder?); one run "
                            "at a time: let it finish, or stop it with Ctrl-C (it checkpoints)")


@contextlib.contextmanager
def no_half_run(run: Path, held: contextlib.ExitStack | None = None) -> Iterator[Any]:
    """Make the run folder (locked in ``held`` when this call made it), open its log (yielded)
    and close it; and if training fails (out of memory at the
    first step, a NaN loss, a second Ctrl-C, a full disk in the first checkpoint) before a
    checkpoint is whole, remove what cannot be resumed without state.json (model.pt, stream.pt,
    optim.*.pt). A validated best.pt is kept, with the log that says what it is; without one the
    log goes back to what it held before this call (an earlier stopped run's lines stay) and the
    folders this call made are removed, so that the same --out starts again."""
    made = [p for p in (run, *run.parents) if not p.exists()]  # leaf first
    run.mkdir(parents=True, exist_ok=True)
    if held is not None:  # a folder that did not exist at the run's checks: locked from now on (run_lock)
        held.enter_context(run_lock(run))
        if not made and any(run.iterdir()):  # another run made it after this one's checks (two fresh runs, one --out)
            raise PsctlError(run, "another psctl train started in this run folder while this one was setting up; "
                                  "use another --out, or --resume it once that run has stopped")
    if (run / "log.jsonl").is_file():
        _cut_partial_line(run / "log.jsonl")
    log_start = (run / "log.jsonl").stat().st_size if (run / "log.jsonl").is_file() else 0
    log = open(run / "log.jsonl", "a", encoding="utf-8", newline="\n")  # the same bytes on Windows (helper-174)
    try:
        yield log
    except BaseException:
        log.close()
        if (run / JOURNAL).exists():  # committed: --resume finishes it
            raise
        for p in run.glob(STAGED + "*"):  # a checkpoint that failed before its journal
            with contextlib.suppress(OSError):
                p.unlink()
        if not (run / "state.json").exists():
            for p in [run / "model.pt", run / "stream.pt", *run.glob("optim.*.pt")]:
                with contextlib.suppress(OSError):
                    p.unlink()
            if not (run / "best.pt").exists():
                with contextlib.suppress(OSError):
                    if log_start:
                        os.truncate(run / "log.jsonl", log_start)
                    else:
                        (run / "log.jsonl").unlink()
                for folder in made:  # the run folder, then parents it made; only while empty
                    try:
                        folder.rmdir()
                    except OSError:
                        break
        raise
    log.close()


def _cut_partial_line(log: Path) -> None:
    """End ``log`` at its last whole line: a record cut by a kill (a full disk, a lost machine)
    would otherwise have the next run's first record glued to it, a line no reader can parse (a
    review: the start after that was then refused as a foreign log)."""
    size = log.stat().st_size
    if size == 0:
        return
    with open(log, "rb") as f:
        f.seek(max(0, size - (1 << 20)))
        tail = f.read()
    if tail.endswith(b"\n"):
        return
    cut = tail.rfind(b"\n")
    if cut < 0 and size > len(tail):  # a line of over 1 MB: no record of ours; left for _run_log to refuse
        return
    os.truncate(log, size - len(tail) + cut + 1)


class Stop:
    """SIGINT/SIGTERM/SIGHUP set a flag; the loop checkpoints and leaves at the next step."""

    def __init__(self) -> None:
        self.requested = False
        self.signal: int | None = None
        self.saving = False  # a checkpoint is being written: a second signal waits for its end
        self.again = False
        self._old: dict[int, Any] = {}

    def __enter__(self) -> "Stop":
        for sig in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)):  # no SIGHUP on Windows
            if sig is None or signal.getsignal(sig) is signal.SIG_IGN:  # nohup's SIGHUP: ignored, as asked
                continue
            try:
                self._old[sig] = signal.signal(sig, self._handle)
            except ValueError:  # not in the main thread
                pass
        return self

    def _handle(self, signum, frame) -> None:
        if self.requested:  # a second Ctrl-C leaves at once, unless a checkpoint is half written
            if self.saving:
                self.again = True
                return
            raise KeyboardInterrupt
        self.requested, self.signal = True, int(signum)

    @contextlib.contextmanager
    def whole(self) -> Iterator[None]:
        """Write a checkpoint whole: a second signal during it (impatient Ctrl-C) leaves after it,
        not between the optimiser files and state.json (a folder --resume cannot use)."""
        self.saving = True
        try:
            yield
        finally:
            self.saving = False
        if self.again:
            raise KeyboardInterrupt

    def __exit__(self, *exc) -> None:
        for sig, old in self._old.items():
            if old is not None:  # None: a handler not set from Python, which cannot be put back
                signal.signal(sig, old)

    def pass_on(self) -> None:
        """After the run stopped on a signal, with the handlers put back: raise it again when the
        caller had set its own Python handler for it, which would otherwise never hear of it.
        Python's and the system's defaults are not called (Ctrl-C's KeyboardInterrupt, SIGTERM's
        exit): the run has stopped as asked, and the state it returns says why."""
        old = self._old.get(self.signal) if self.signal is not None else None
        # psctl train's own (psctl.cli): the command says how the run stopped and exits 128 + signal
        if callable(old) and old is not signal.default_int_handler and not getattr(old, "psctl_cli", False):
            signal.raise_signal(self.signal)


def save_optimizer(run: Path, optim: torch.optim.Optimizer, stage: str = "") -> list[str]:
    """Adam state in parts of at most OPTIM_PART_BYTES (each part a weights_only-loadable file),
    written as ``run / (stage + name)``; returns the names (``optim.0.pt``, ...)."""
    from psctl.io.atomic import atomic_path

    sd = optim.state_dict()
    parts: list[dict] = [{}]
    size = 0
    for idx, st in sd["state"].items():
        nbytes = sum(v.numel() * v.element_size() for v in st.values() if torch.is_tensor(v))
        if size + nbytes > OPTIM_PART_BYTES and parts[-1]:
            parts.append({})
            size = 0
        parts[-1][idx] = {k: v.detach().cpu().clone() if torch.is_tensor(v) else v for k, v in st.items()}
        size += nbytes
    names = []
    for i, part in enumerate(parts):
        name = f"optim.{i}.pt"
        with atomic_path(run / (stage + name)) as tmp:
            save_torch({"state": part, "param_groups": sd["param_groups"] if i == 0 else []}, tmp)
        names.append(name)
    return names


# A checkpoint is several files (model.pt, stream.pt, optim.*.pt, state.json); each is written
# under its staged name (STAGED + name), then one journal write commits them as a set: a hard
# kill anywhere leaves the previous checkpoint whole, or a journal that --resume completes.
JOURNAL = "checkpoint.json"
STAGED = ".next."


# atomic_path's temporary names (".NAME.XXXXXXXX.tmp.pt", "..next.NAME.XXXXXXXX.tmp.pt") that a
# kill left in a run folder: only psctl writes such names there
TEMP_FILE = re.compile(r"\..+\.[A-Za-z0-9_]{8}\.tmp\.(pt|json)")


def _fsync(path: Path) -> None:
    """``path``'s data (a file) or its entries (a folder) on disk; a folder that cannot be opened
    so (Windows) is left to the system."""
    try:
        # Windows: fsync is FlushFileBuffers, which needs a handle with write access (EBADF otherwise)
        fd = os.open(path, os.O_RDWR if os.name == "nt" and not path.is_dir() else os.O_RDONLY)
    except OSError:
        if path.is_dir():
            return
        raise
    try:
        os.fsync(fd)
    except OSError:
        if not path.is_dir():
            raise
    finally:
        os.close(fd)


def commit_checkpoint(run: Path, files: list[str], state: dict, remove: list[str] | tuple = ()) -> None:
    """Commit a checkpoint whose ``files`` are staged in ``run`` (``STAGED + name``): write the
    journal (each file's sha256, ``state`` for state.json, and the earlier optimiser parts
    ``remove``), then carry it out (``finish_checkpoint``)."""
    from psctl.io.atomic import write_text_atomic

    digests = {}
    for name in files:  # on disk before the journal says they are there (a lost machine, not just a kill)
        _fsync(run / (STAGED + name))
        digests[name] = file_sha256(run / (STAGED + name))
    state = {**state, "files_sha256": digests}  # kept in state.json: --resume takes only these very files
    write_text_atomic(run / JOURNAL, json.dumps({"files": digests, "state": state, "remove": list(remove)}, indent=1))
    _fsync(run / JOURNAL)
    _fsync(run)  # the journal's name too
    try:
        finish_checkpoint(run)
    except (OSError, PsctlError) as e:  # a full disk at state.json, say: the checkpoint is committed, not carried out
        why = e.message if isinstance(e, PsctlError) else (e.strerror or str(e))
        raise PsctlError(run / JOURNAL, f"the checkpoint is committed but not carried out ({why}); --resume "
                                        "finishes it") from None


def finish_checkpoint(run: Path) -> bool:
    """Carry out ``run``'s journal, if it has one: move the staged files into place, write
    state.json, remove the optimiser parts the checkpoint no longer lists, then the journal.
    Each step can be done again, so a kill half-way leaves a journal this finishes; each file is
    checked against the journal's sha256 first (a copy that dropped the hidden staged files must
    not get the journal's state.json beside the earlier checkpoint's files). Without a journal,
    staged files (a checkpoint killed before its journal) are removed; temporary files a kill
    left are removed either way. Returns whether there was a journal."""
    from psctl.io.atomic import write_text_atomic

    for p in run.iterdir() if run.is_dir() else ():
        if TEMP_FILE.fullmatch(p.name):
            with contextlib.suppress(OSError):
                p.unlink()
    journal = run / JOURNAL
    if not journal.is_file():
        for p in run.glob(STAGED + "*"):
            with contextlib.suppress(OSError):
                p.unlink()
        return False
    try:
        j = json.loads(journal.read_text(encoding="utf-8"))
        files, state, remove = j["files"], j["state"], j["remove"]
        if not (isinstance(files, dict) and isinstance(state, dict) and isinstance(remove, list)
                and all(isinstance(n, str) and "/" not in n and "\\" not in n for n in [*files, *remove])
                and all(isinstance(d, str) for d in files.values())):
            raise ValueError("not a checkpoint journal")
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as e:
        raise PsctlError(journal, f"is not a readable checkpoint journal ({e}); the checkpoint it commits cannot be "
                                  f"finished (removing it resumes the checkpoint before)") from None
    for name, digest in files.items():
        staged, final = run / (STAGED + name), run / name
        if staged.exists():
            ok = file_sha256(staged) == digest
        else:  # moved already, by the run this journal outlived, or never copied here
            ok = final.is_file() and file_sha256(final) == digest
        if not ok:
            why = (f"damaged ({STAGED + name} is not as written)" if staged.exists() else
                   f"missing ({STAGED + name} is gone and {name} is not the journal's: a copy without the hidden files?)")
            raise PsctlError(journal, f"commits a checkpoint whose {name} is {why}: the checkpoint cannot be finished "
                                      f"(removing {JOURNAL} and the {STAGED}* files resumes the one before, if its "
                                      f"files are whole)")
    for name in files:
        staged = run / (STAGED + name)
        if staged.exists():
            os.replace(staged, run / name)
    write_text_atomic(run / "state.json", json.dumps(state, indent=1))
    _fsync(run / "state.json")  # before the journal that could write it again goes
    _fsync(run)
    for stale in remove:
        if stale not in files and OPTIM_PART.fullmatch(stale):
            (run / stale).unlink(missing_ok=True)
    journal.unlink()
    return True


def _load_part(path: Path) -> Any:
    """One of a run's torch files, or a one-line error naming it (truncated, emptied, replaced)."""
    import pickle

    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:  # torch's message advises weights_only=False: not for a damaged file
        raise PsctlError(path, "is not a torch file psctl wrote: the run's checkpoint is damaged") from None
    except (OSError, RuntimeError, EOFError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise PsctlError(path, f"cannot be read ({' '.join(str(e).split())[:120] or type(e).__name__}): the run's "
                               "checkpoint is damaged") from None


def load_optimizer(run: Path, optim: torch.optim.Optimizer, names: list[str], device: torch.device) -> None:
    """Adam's state from the parts ``names`` (``save_optimizer``) in ``run``, onto ``device``."""
    if not names:  # a run whose Adam state was dropped on purpose (state.json "optim_files": []): fresh moments
        return
    state: dict = {}
    groups = None
    for name in names:
        # on the CPU: Adam's step counters must stay there (load_state_dict moves the moments to
        # the parameters' device); a CUDA step counter costs a GPU sync every iteration
        if not (run / name).is_file():
            raise PsctlError(run / name, "optimiser state listed in state.json is missing (to resume with fresh Adam "
                                         "moments, set \"optim_files\": [] there)")
        part = _load_part(run / name)
        if not (isinstance(part, dict) and isinstance(part.get("state"), dict) and "param_groups" in part):
            raise PsctlError(run / name, "is not a part of an optimiser state: the run's checkpoint is damaged")
        if set(part["state"]) & set(state):  # a part copied over another (optim.1.pt = optim.0.pt)
            raise PsctlError(run / name, "repeats another part's optimiser state: the run's checkpoint is damaged")
        state.update(part["state"])
        groups = groups or part["param_groups"]
    params = [p for g in groups or [] for p in (g.get("params", []) if isinstance(g, dict) else [])]
    if state and set(state) != set(params):  # Adam keeps state for every parameter after a step
        raise PsctlError(run / names[-1], f"the optimiser parts hold the state of {len(state)} of {len(params)} "
                                          "parameters: the run's checkpoint is damaged")
    try:
        optim.load_state_dict({"state": state, "param_groups": groups})
    except (ValueError, KeyError, TypeError, RuntimeError) as e:
        raise PsctlError(run / names[0], f"does not fit this run's network ({' '.join(str(e).split())[:120]}): "
                                         "the run's checkpoint is damaged") from None


def adam_steps(optim: torch.optim.Optimizer) -> set[int]:
    """The step counts Adam keeps per parameter (one value while every parameter gets a step)."""
    return {int(v["step"]) for v in optim.state.values() if "step" in v}


def drop_lines_after_checkpoint(log: Path, size: int, samples: int) -> None:
    """A process killed after its last checkpoint (SIGKILL, a lost machine) logged steps that the
    resume runs again: cut ``log`` back to its ``size`` at that checkpoint, but only where the
    file still is that log (a line ends there) and everything after it is lines of later steps
    (JSON records with more than ``samples``); an edited or rotated log is left as it is."""
    try:
        if not log.is_file() or log.stat().st_size <= size:
            return
        data = log.read_bytes()
        if size and data[size - 1:size] != b"\n":
            return
        for line in data[size:].splitlines():
            rec = json.loads(line)
            if not isinstance(rec, dict) or not isinstance(rec.get("samples"), int) or rec["samples"] <= samples:
                return
        os.truncate(log, size)
    except (OSError, ValueError):  # unreadable, not JSON: not psctl's lines, left alone
        return


def check_state(path: Path, saved: dict) -> None:
    """The kinds of a run state's bookkeeping values (an edited or damaged state.json is one line,
    not a TypeError deep in the loop)."""
    def number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    kinds = {"step": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
             "samples": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
             "seconds": lambda v: number(v) and v >= 0,
             "stream_seed": lambda v: isinstance(v, int) and not isinstance(v, bool),
             "best_val": lambda v: v is None or number(v),
             "best_samples": lambda v: v is None or (isinstance(v, int) and not isinstance(v, bool)),
             "val": lambda v: isinstance(v, list),
             "optim_files": lambda v: isinstance(v, list) and all(isinstance(n, str) for n in v),
             "config": lambda v: isinstance(v, dict),
             "log_bytes": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
             "loss_avg": lambda v: v is None or number(v),
             "data_notes": lambda v: isinstance(v, list) and all(isinstance(n, str) for n in v),
             "data_sources": lambda v: isinstance(v, list),
             "lcnet_sha256": lambda v: isinstance(v, str),
             "files_sha256": lambda v: isinstance(v, dict) and all(isinstance(d, str) for d in v.values()),
             "optim_step": lambda v: v is None or (isinstance(v, int) and not isinstance(v, bool) and v >= 0)}
    for key, ok in kinds.items():
        if key in saved and not ok(saved[key]):
            raise PsctlError(path, f"holds a bad {key!r} ({json.dumps(saved[key])[:40]}): the run state is damaged")


def restore_checkpoint(run: Path, st: dict, method: str, model: torch.nn.Module, optim: torch.optim.Optimizer,
                        dev: torch.device) -> None:
    """The checkpoint's weights and Adam state into ``model`` and ``optim``, each file checked to
    be this run's and of this checkpoint (``st``: state.json)."""
    from psctl.models.weights import read_weights

    w = read_weights(run / "model.pt")
    if w.method != method:  # same shapes (PS-FCN and PS-FCN+N) would load without a word
        raise PsctlError(run / "model.pt", f"holds {w.method} weights, not this {method} run's")
    try:
        model.load_state_dict(w.state_dict)
    except RuntimeError as e:  # another network's file in this run's folder
        first = " ".join(str(e).split())[:160]
        raise PsctlError(run / "model.pt", f"does not hold this {method} run's network ({first})") from None
    load_optimizer(run, optim, st["optim_files"], dev)
    # files of one checkpoint, not one from another point of the run (a folder put together
    # from parts, as the GPU workflow moves it): each says how far it got
    seen = w.metadata.get("samples_seen")
    if seen is not None and seen != st["samples"]:
        raise PsctlError(run / "model.pt", f"was saved at {seen:,} samples, state.json at {st['samples']:,}: "
                                           f"not this checkpoint's; the run cannot continue exactly")
    # (Adam's own count: a resume with fresh moments, "optim_files": [], starts it again at 0)
    steps = adam_steps(optim)
    if steps and st.get("optim_step") is not None and steps != {st["optim_step"]}:
        at = " and ".join(f"{k:,}" for k in sorted(steps))
        # (a hard kill no longer tears a checkpoint (commit_checkpoint); a folder put together by hand can)
        torn = " (parts of two checkpoints)" if len(steps) > 1 else ""
        raise PsctlError(run / st["optim_files"][0], f"holds the optimiser at step {at}{torn}, state.json at step "
                                                     f"{st['optim_step']:,}: not this checkpoint's; the run cannot "
                                                     f"continue exactly (\"optim_files\": [] in state.json continues "
                                                     f"with fresh Adam moments, not exactly)")
    _check_sha256(run, st, ["model.pt", *st["optim_files"]])
    if (run / "best.pt").exists():  # the run's answer so far: a damaged one would be named at the end as its result
        best = read_weights(run / "best.pt")  # a file that is not weights: one line naming it
        if best.method != method:
            raise PsctlError(run / "best.pt", f"holds {best.method} weights, not this {method} run's")


def restore_stream(run: Path, st: dict, stream: Any) -> None:
    """The data stream's state from the checkpoint's stream.pt, checked to be of this checkpoint."""
    if not (run / "stream.pt").is_file():
        raise PsctlError(run / "stream.pt", "is missing: the run cannot continue its data stream exactly")
    state = _load_part(run / "stream.pt")
    if isinstance(state, dict) and set(state) == {"samples", "stream"}:  # since session 49: with its count
        if state["samples"] != st["samples"]:
            raise PsctlError(run / "stream.pt", f"was saved at {state['samples']:,} samples, state.json at "
                                                f"{st['samples']:,}: not this checkpoint's; the run cannot "
                                                f"continue exactly")
        state = state["stream"]
    try:
        stream.load_state_dict(state)
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError) as e:
        raise PsctlError(run / "stream.pt", f"is not this run's stream state ({' '.join(str(e).split())[:120]})") from None
    _check_sha256(run, st, ["stream.pt"])


def _check_sha256(run: Path, st: dict, names: list[str]) -> None:
    """The very files the checkpoint wrote, after the checks that say more (damaged, another
    network, another point of the run): state.json records their sha256 (runs from before it
    have none), so another run's file saved at the same sample count is refused too."""
    digests = st.get("files_sha256") or {}
    for name in names:
        if name in digests and file_sha256(run / name) != digests[name]:
            fresh = (" (\"optim_files\": [] in state.json continues with fresh Adam moments, not exactly)"
                     if name.startswith("optim.") else "")
            raise PsctlError(run / name, "is not the file this run's last checkpoint wrote (its sha256 differs "
                                         "from state.json's): replaced, or copied from another run; the run cannot "
                                         f"continue exactly{fresh}")

