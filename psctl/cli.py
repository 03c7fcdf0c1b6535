"""The ``psctl`` command. Each command parses options, calls one library function, and prints.

User errors (PsctlError) become one line on stderr and exit code 2, never a traceback.
Heavy imports happen inside the commands so that ``psctl --help`` is instant.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import json
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Annotated, Optional

import typer

# a flag takes no value: without an empty metavar some Typer versions show "<bool>" after it,
# and `--json true` is then an error
_flag = functools.partial(typer.Option, metavar="")


def _no_flag_type(cls: type) -> type:
    """A Typer command class whose --help shows no "<bool>" (the flag takes no value; as _flag)."""

    class Command(cls):  # type: ignore[misc, valid-type]
        def get_help_option(self, ctx):  # noqa: ANN001, ANN201 (click's signature)
            opt = super().get_help_option(ctx)
            if opt is not None:
                opt.metavar = ""
            return opt

    return Command


_Command, _Group = _no_flag_type(typer.core.TyperCommand), _no_flag_type(typer.core.TyperGroup)
# newer Typers carry their own copy of click (typer._click; 0.29 does), older ones use click itself
_click = getattr(typer.core, "_click", None) or __import__("click")


def _eprint(line: str) -> None:
    """A line on stderr, or nowhere when there is none (`2>&-`: sys.stderr is None, and print
    would write it to stdout, among the results)."""
    if sys.stderr is not None:
        print(line, file=sys.stderr)


def _signal_name(number: int) -> str:
    """SIGTERM for 15; the number where this platform has no such signal (Windows has no SIGPIPE,
    which psctl train records when its reader goes away)."""
    import signal

    try:
        return signal.Signals(number).name
    except ValueError:
        return "SIGPIPE" if number == 13 else f"signal {number}"


def _reader_gone(e: BaseException) -> bool:
    """A write to a pipe whose reader went away (`| head`): BrokenPipeError, or the exit 1 that
    click and Rich raise after catching one."""
    return isinstance(e, BrokenPipeError) or (isinstance(e, SystemExit) and isinstance(e.__context__, BrokenPipeError))


def _refuse_empty(argv: list[str]) -> None:
    """An empty argument is a mistake (an unset shell variable: ``-o "$OUT"``): no psctl option
    takes one, and click would make an empty path "." (the current folder) without a word."""
    for i, a in enumerate(argv):
        flag = a[:-1] if a.startswith("-") and a.endswith("=") else None  # --out=
        if a.strip() and flag is None:
            continue
        if flag is None:
            flag = argv[i - 1] if i > 0 and argv[i - 1].startswith("-") else None
        sub = bool(argv) and not argv[0].startswith("-") and i > 0  # counted from the command's own arguments
        command = f"psctl {argv[0]}" if sub else "psctl"
        what = f"an empty value after {flag}" if flag else f"argument {i if sub else i + 1} is empty"
        _eprint(f"{command}: {what} (an unset shell variable?)")
        sys.exit(2)


def _refuse_repeated(group: "_click.Group", argv: list[str]) -> None:
    """An option that takes one value given twice with different values (``-o a -o b``, ``-m l2 -m
    ps-fcn`` to psctl normals, ``--refine --no-refine``): click keeps the last without a word, so
    the run would not be the one asked for. Options that take a list (``-f``, eval's ``-m``,
    train's ``--average``) and the same value given twice (``-q -q``) are fine."""
    cmd = group.commands.get(argv[0]) if argv else None
    ends = argv.index("--") if "--" in argv else len(argv)
    if cmd is None or {"-h", "--help"} & set(argv[:ends]):  # the help is asked for: shown, whatever else
        return
    by_flag: dict[str, tuple] = {}  # "-o" -> (param, takes a value, the value a flag sets)
    for p in cmd.params:
        # options only (typer's click has no Option class at its top to test against), of one value
        if getattr(p, "param_type_name", None) != "option" or p.multiple or p.count:
            continue
        takes = not p.is_flag
        for o in p.opts:
            by_flag[o] = (p, takes, True)
        for o in p.secondary_opts:
            by_flag[o] = (p, takes, False)
    seen: dict[str, tuple[str, object]] = {}  # param name -> (as given, value)

    def given(flag: str, value: object) -> None:
        p = by_flag[flag][0]
        if p.name in seen and seen[p.name][1] != value:
            first = seen[p.name][0]
            again = flag if by_flag[flag][1] is False else f"{flag} {value}"
            _eprint(f"psctl {argv[0]}: {'/'.join([*p.opts, *p.secondary_opts])} given twice ({first}, then {again}); "
                    f"give it once")
            sys.exit(2)
        seen.setdefault(p.name, (flag if not by_flag[flag][1] else f"{flag} {value}", value))

    i = 1
    while i < len(argv):
        a = argv[i]
        i += 1
        if a == "--":
            break
        if a.startswith("--") and "=" in a and a.split("=", 1)[0] in by_flag:
            flag, value = a.split("=", 1)
            given(flag, value)
        elif a in by_flag:
            _, takes, sets = by_flag[a]
            if takes:
                if i >= len(argv):
                    return  # click says the value is missing
                given(a, argv[i])
                i += 1
            else:
                given(a, sets)
        elif a.startswith("-") and not a.startswith("--") and len(a) > 2:  # -qn5, -o/path
            for j, c in enumerate(a[1:], 1):
                if f"-{c}" not in by_flag:
                    break  # click's to judge
                _, takes, sets = by_flag[f"-{c}"]
                if takes:
                    given(f"-{c}", a[j + 1:] or (argv[i] if i < len(argv) else None))
                    i += 0 if a[j + 1:] else 1
                    break
                given(f"-{c}", sets)


def _close_options(name: str, params: "list[_click.Parameter]") -> list[str]:
    """The options (of a command's ``params``, --help among them) spelt like ``name``, compared
    without their dashes: click compares them with, and the dashes alone make '--bogus' look like
    '--out'."""
    import difflib

    opts = [o for p in params for o in (*p.opts, *p.secondary_opts) if o.startswith("--")]
    bare = {o[2:]: o for o in opts}
    return [bare[m] for m in difflib.get_close_matches(name.lstrip("-"), list(bare), n=3)]


class _Root(_Group):
    """The root group: a command-line mistake is one line on stderr and exit code 2, as any other
    user error (Typer would print the usage and a boxed message: five lines or more)."""

    def main(self, *args, **kwargs):  # noqa: ANN002, ANN003, ANN201 (click's signature)
        argv = kwargs["args"] if "args" in kwargs else (args[0] if args else None)  # [] is a command line too
        argv = list(sys.argv[1:] if argv is None else argv)
        _refuse_empty(argv)
        _refuse_repeated(self, argv)
        kwargs["standalone_mode"] = False  # errors come back here instead of being printed
        try:
            code = super().main(*args, **kwargs)
        except _click.exceptions.ClickException as e:
            if type(e).__name__ != "NoArgsIsHelpError":  # that one has printed the help already
                ctx = getattr(e, "ctx", None)
                # some parser errors ("Option '--x' requires an argument") come without a context
                path = ctx.command_path if ctx is not None else (
                    f"psctl {argv[0]}" if argv and argv[0] in self.commands else "psctl")
                where, hint = f"{path}: ", f"; see '{path} --help'"
                if isinstance(e, _click.exceptions.NoSuchOption) and ctx is not None:
                    e.possibilities = _close_options(e.option_name, ctx.command.get_params(ctx))
                _eprint(f"{where}{e.format_message().rstrip('.')}{hint}")
            sys.exit(e.exit_code)
        except typer.Abort:  # (typer's own name: its copy of click keeps Abort elsewhere)
            _eprint("Aborted.")
            sys.exit(1)
        except SystemExit as e:
            # click and Rich answer a closed stdout (`psctl info X | head -1`) with exit 1, having
            # silenced stdout; 1 reads as a failure of psctl's own. Exit as cat and git do when their
            # reader goes away: 128 + SIGPIPE, silently
            if e.code == 1 and _reader_gone(e):
                sys.exit(141)
            raise
        # typer.Exit and Ctrl-C come back as an exit code; a finished command as None
        sys.exit(code if isinstance(code, int) else 0)


app = typer.Typer(
    cls=_Root,
    name="psctl",
    help="Photometric stereo: surface normals (and lights, depth) from images under varying light.",
    no_args_is_help=True,
    context_settings={"help_option_names": ["-h", "--help"]},  # -h as most command-line tools take it
    add_completion=False,
    pretty_exceptions_enable=False,
)

Quiet = Annotated[bool, _flag("--quiet", "-q", help="No progress bars.")]
Json = Annotated[bool, _flag("--json", help="Print one JSON object on stdout.")]
Images = Annotated[Optional[int], typer.Option("--images", "-n", help="Use K images: K spread over the light directions, or a random K with --seed (sdps and ups-fcn, which do not read lights: a random K, seed 0 unless --seed).")]
LightsImages = Annotated[Optional[int], typer.Option("--images", "-n", help="Use K images: a random K (seed 0 unless --seed; the folder's lights are what is estimated, so they choose nothing); light_images.txt names them.")]
Seed = Annotated[Optional[int], typer.Option(help="Seed for a random --images subset.")]
OutDir = Annotated[Optional[Path], typer.Option("--out", "-o", readable=False, help="Output folder (default: PATH/psctl).")]
MethodOpt = Annotated[str, typer.Option("--method", "-m", help="auto | l2 | ps-fcn | ps-fcn-n | ensemble | ups-fcn | sdps (ensemble: the average of PS-FCN's and PS-FCN+N's normals; auto: ensemble when both are installed, else the one that is, else l2; without light_directions.txt, or with --lcnet: sdps = LCNet + PS-FCN†, or + the installed PS-FCN (else PS-FCN+N) while PS-FCN† is not; ups-fcn where only its weights are installed).")]
WeightsOpt = Annotated[Optional[Path], typer.Option("--weights", "-w", readable=False, help="Network weights file: psctl's .pt or the authors' *.pth.tar (default: the installed weights: $PSCTL_WEIGHTS, else the checkout's weights/, else ~/.local/share/psctl/weights; docs/models.md). With sdps: its second stage (PS-FCN†, or a PS-FCN or PS-FCN+N file).")]
DeviceOpt = Annotated[str, typer.Option("--device", help="auto | cpu | cuda | cuda:N: where the networks run (l2 uses none).")]
RefineOpt = Annotated[bool, _flag("--refine/--no-refine", help="sdps: refine LCNet's lights against the first normals, then estimate the normals again (docs/uncalibrated.md).")]
FalloffOpt = Annotated[Optional[str], typer.Option("--falloff", help="sdps and psctl lights: the light refinement's shading model: shifted (the default) | lambertian (docs/uncalibrated.md, 'Falloff').")]
RollOpt = Annotated[Optional[bool], _flag("--roll/--no-roll", help="sdps and psctl lights: after the light refinement, turn the lights (and sdps' normals) about the view axis by the roll that makes the normals from them most integrable (default: on; docs/uncalibrated.md, 'Roll from integrability').")]
SnapOpt = Annotated[bool, _flag("--snap/--no-snap", help="sdps and psctl lights: LCNet and the light fit read mask.png snapped to the object (a mask drawn wider puts LCNet's lights far off; a note says what was left out, or where a mask read as given looks drawn wider); --no-snap: as given (an exact mask whose object has a face that shades as the background does; docs/uncalibrated.md, 'A mask wider than the object').")]
ViewsOpt = Annotated[int, typer.Option(help="Network methods: average 1, 2, 4 or 8 symmetric views (the capture turned and mirrored about the view axis; that many times the work). sdps: its normals network; its LCNet always averages 8 (psctl lights --views sets LCNet's).")]
DownsampleOpt = Annotated[int, typer.Option(help="Network methods: run on the capture shrunk by this whole factor (each K x K block's mean), normals interpolated back to full size: about 1/K^2 of the network's work, for a quick look; detail is lost (docs/models.md, 'Downsampling'). 1: full size.")]
EncodingOpt = Annotated[str, typer.Option("--encoding", help="How image values map to radiance: auto (a file with an ICC profile is decoded through its tone curves; else JPEGs are decoded from sRGB, other files read as linear) | linear (all as stored) | srgb (all decoded from sRGB).")]
LightDistanceOpt = Annotated[Optional[float], typer.Option("--light-distance", help="l2, ps-fcn, ps-fcn-n, ensemble, sdps, psctl lights' refinement: the lights are points this many image pixels from the object along the listed (sdps: estimated) directions; each image is divided by its light's falloff (docs/near-lights.md; DiLiGenT's rig: about 2400).")]
PrecisionOpt = Annotated[str, typer.Option("--precision", help="Network methods: float32 (the default) | bf16 (an Ampere or newer GPU, or a CPU with native bf16: AVX512-BF16 or AMX; on a 2-core AVX512-BF16 CPU 1.6x faster end to end, normals about 0.1 degrees from float32's on average) | fp16 (CUDA). docs/models.md, 'Precision'.")]
LcnetOpt = Annotated[Optional[Path], typer.Option("--lcnet", readable=False, help="LCNet weights for sdps: psctl's lcnet.pt or the authors' LCNet_CVPR2019.pth.tar (default: the installed weights). Given with --method auto, it selects sdps also on folders with light_directions.txt (which then only score the estimated lights).")]


def _stderr():
    from psctl.errors import console

    return console(stderr=True)


def _fail(message: str) -> None:
    from rich.markup import escape

    # escaped: a path like cap[red]x or a message quoting [fx, 0, cx] is text, not Rich markup
    from psctl.errors import visible

    # one line: a line break or an escape sequence in a file's name is written out
    _stderr().print(f"[bold red]error:[/] {escape(visible(message, newlines=False))}", highlight=False, soft_wrap=True)
    raise typer.Exit(2)


class _Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP (a scheduler's timeout, a closed terminal), raised where the program is,
    so that it unwinds as from Ctrl-C: staged outputs are discarded or put back, never half
    moved. A KeyboardInterrupt, so that whatever cleans up after Ctrl-C cleans up after it."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _raise_terminated(signum, frame) -> None:
    raise _Terminated(signum)


_raise_terminated.psctl_cli = True  # psctl.train's pass_on leaves it be: the command reports the stop itself


@contextlib.contextmanager
def _on_termination() -> Iterator[None]:
    """Python's default for SIGTERM and SIGHUP is to die at once, skipping every cleanup. Only
    the default is replaced: a signal the caller ignores (``nohup`` ignores SIGHUP) stays so."""
    import signal

    old = {}
    for name in ("SIGTERM", "SIGHUP"):
        sig = getattr(signal, name, None)  # no SIGHUP on Windows
        if sig is None or signal.getsignal(sig) is not signal.SIG_DFL:
            continue
        try:
            old[sig] = signal.signal(sig, _raise_terminated)
        except ValueError:  # not the main thread (psctl's CLI run from a thread): leave them
            pass
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _is_torch_oom(e: RuntimeError) -> bool:
    """torch's allocators raise RuntimeError (CPU: "DefaultCPUAllocator: can't allocate memory";
    CUDA: torch.OutOfMemoryError, "CUDA out of memory")."""
    import torch

    oom = getattr(torch, "OutOfMemoryError", None) or torch.cuda.OutOfMemoryError  # torch.OutOfMemoryError: 2.5+
    return isinstance(e, oom) or "can't allocate memory" in str(e) or "out of memory" in str(e)


def _out_of_memory(detail: str) -> str:
    # the allocator's own words say how much was asked for; a bug asking for terabytes shows there
    detail = " ".join(detail.split())
    if len(detail) > 160:  # cut at a word, not mid-word (an audit: "Cannot allocat")
        detail = detail[:160].rsplit(" ", 1)[0] + " ..."
    return (f"out of memory{f' ({detail})' if detail else ''}: ask for less (normals, eval: --downsample K or "
            "fewer --images; train: a smaller train.batch_size, crop or images_per_sample), or use a machine "
            "with more memory")


@contextlib.contextmanager
def _user_errors() -> Iterator[None]:
    from psctl.errors import NO_ROOM, PsctlError

    try:
        with _on_termination():
            yield
    except PsctlError as e:
        _fail(str(e))
    except OSError as e:
        if e.filename is None and e.errno in NO_ROOM:  # printing to a full disk (`> out.json`), ...
            with contextlib.suppress(OSError):
                _fail(f"cannot write the output ({e.strerror.lower() if e.strerror else e})")
            raise typer.Exit(2) from None
        if e.filename is None:  # not about a path the user gave: keep the traceback for a bug report
            raise
        # the system refused a path (too long, permission denied, disk full, ...): the user's to fix
        what = e.strerror.lower() if e.strerror else (str(e) or type(e).__name__)
        folder = _unsearchable(e.filename) if e.errno == errno.EACCES else None
        if folder is not None:  # not the file's fault: psctl may only have been looking for it
            _fail(f"{folder}: permission denied (the folder cannot be searched, so no file in it can be opened)")
        _fail(f"{e.filename}: {what}" + (f" ({e.filename2})" if e.filename2 else ""))
    except MemoryError as e:  # numpy's _ArrayMemoryError too: a capture too large for this machine's memory
        _fail(_out_of_memory(str(e)))
    except RuntimeError as e:
        if not _is_torch_oom(e):  # anything else is a bug: keep its traceback
            raise
        _fail(_out_of_memory(str(e).splitlines()[0] if str(e) else ""))
    except _Terminated as e:
        with contextlib.suppress(OSError):  # after SIGHUP the terminal may be gone
            _stderr().print("terminated")
        raise typer.Exit(128 + e.signum) from None
    except KeyboardInterrupt:
        with contextlib.suppress(OSError):
            _stderr().print("interrupted")
        raise typer.Exit(130) from None


def _unsearchable(filename: "str | bytes | int") -> str | None:
    """The outermost folder on the way to ``filename`` that this process may not search (no x
    permission), or None. Python's Path.is_file() raises on such a path, so a probe for an optional
    file (objects.txt) inside a capture folder without x would be blamed otherwise."""
    import os

    if not isinstance(filename, str):
        return None
    found, d = None, os.path.dirname(filename)
    while d and not os.access(d, os.X_OK):
        found, up = d, os.path.dirname(d)
        if up == d:
            break
        d = up
    return found


def _stderr_is_terminal() -> bool:
    """False also where there is no stderr at all: Python makes sys.stderr None when file
    descriptor 2 is closed at start (`2>&-`, some daemons), and a run must still work."""
    return sys.stderr is not None and sys.stderr.isatty()


@contextlib.contextmanager
def _progress(quiet: bool) -> Iterator[Callable[[str, int], Callable[[int], None]] | None]:
    """A progress factory for the library (see psctl.api.ProgressFactory), drawn on stderr.

    Only on a terminal: in a log or a pipe a bar is noise (and Rich leaves an empty line)."""
    if quiet or not _stderr_is_terminal():
        yield None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TimeRemainingColumn(), console=_stderr(), transient=True) as bar:
        from psctl.io.summary import escape

        def factory(description: str, total: int) -> Callable[[int], None]:
            task = bar.add_task(escape(description), total=total)  # an object's name: text, not markup
            return lambda n: bar.advance(task, n)

        yield factory


def _run(work: Callable, json_out: bool, quiet: bool, render: Callable[[dict], None]) -> None:
    """The shape of every reporting command: do the work under a progress bar, then print its
    report as one JSON object (``--json``) or for a person."""
    with _progress(quiet) as progress:
        report = work(progress)
    try:
        if json_out:
            _print_json(report)
        else:
            render(report)
    except OSError as e:  # stdout to a full disk (`> /dev/full`) or closed (`>&-`): the outputs are written
        from psctl.errors import NO_ROOM

        if e.filename is not None or e.errno not in (*NO_ROOM, errno.EBADF):
            raise
        outs = (report.get("outputs") or report.get("out")) if isinstance(report, dict) else None  # synth: "out"
        with contextlib.suppress(OSError):
            _fail(f"cannot write the report to standard output ({e.strerror.lower() if e.strerror else e})"
                  + ("; the output files were written" if outs else ""))
        raise typer.Exit(2) from None


def _print_json(obj: dict) -> None:
    if sys.stdout is None:  # started with stdout closed (`>&-`): Python then has no sys.stdout
        raise OSError(errno.EBADF, "standard output is closed")
    sys.stdout.write(json.dumps(obj, indent=2) + "\n")


@app.command(cls=_Command)
def info(path: Annotated[Path, typer.Argument(readable=False, help="A capture folder or a benchmark root.")],
         encoding: EncodingOpt = "auto",
         check: Annotated[bool, _flag("--check", help="Also decode every file: damaged images, brightness, "
                                                     "saturation, black images.")] = False,
         json_out: Json = False, quiet: Quiet = False) -> None:
    """Show what psctl detects in a folder: images, size, bit depth, lights, mask, ground truth."""
    with _user_errors():
        from psctl.io.summary import describe, render_info

        _run(lambda progress: describe(path, encoding, check=check, progress=progress), json_out, quiet, render_info)


@app.command(cls=_Command)
def normals(
    path: Annotated[Path, typer.Argument(readable=False, help="Capture folder (images, light_directions.txt, mask.png, ...).")],
    method: MethodOpt = "auto",
    out: OutDir = None,
    fmt: Annotated[list[str] | None, typer.Option("--format", "-f", show_default="png16,exr", metavar="F[,F...]",
                                                  help="Comma list of png16, png8, exr, npy; may be given more "
                                                       "than once (-f png16 -f npy).")] = None,
    images: Images = None,
    seed: Seed = None,
    weights: WeightsOpt = None,
    device: DeviceOpt = "auto",
    lcnet: LcnetOpt = None,
    views: ViewsOpt = 1,
    downsample: DownsampleOpt = 1,
    precision: PrecisionOpt = "float32",
    refine: RefineOpt = True,
    falloff: FalloffOpt = None,
    roll: RollOpt = None,
    encoding: EncodingOpt = "auto",
    light_distance: LightDistanceOpt = None,
    snap: SnapOpt = True,
    albedo: Annotated[bool, _flag("--albedo", help="Also the albedo map in each --format (albedo.png, albedo_8bit.png with png8: sRGB pictures; albedo.exr, albedo.npy: linear): per channel the median of image / (n . l) over the images that light each pixel well, from the normals and the lights (sdps: as estimated); one more pass over the images.")] = False,
    json_out: Json = False,
    quiet: Quiet = False,
) -> None:
    """Estimate a normal map: normal.png (16-bit), normal.exr, report.json, and error.png with ground truth."""
    with _user_errors():
        from psctl.api import run_normals
        from psctl.io.normals import parse_formats

        from psctl.io.summary import render_normals

        formats = parse_formats("png16,exr" if not fmt else ",".join(fmt))
        _run(lambda progress: run_normals(path, method=method, out=out, formats=formats, n_images=images, seed=seed,
                                          progress=progress, weights=weights, device=device, lcnet=lcnet,
                                          views=views, refine=refine, falloff=falloff, roll=roll, encoding=encoding,
                                          light_distance=light_distance, downsample=downsample,
                                          precision=precision, albedo=albedo, snap=snap),
             json_out, quiet, lambda r: render_normals(r, quiet=quiet))


@app.command("eval", cls=_Command)
def evaluate(
    benchmark: Annotated[str, typer.Option("--benchmark", "-b", help="diligent | folder (any folder of objects, with --root; a --root none of whose objects is named as one of DiLiGenT's is read as folder).")] = "diligent",
    root: Annotated[Optional[Path], typer.Option(readable=False, help="Benchmark root (DiLiGenT pmsData or pmsData_crop, or any folder of objects; needed with --benchmark folder). diligent without it: $PSCTL_DATA/DiLiGenT/pmsData (or diligent/pmsData), then ~/.cache/psctl/DiLiGenT/pmsData.")] = None,
    method: Annotated[Optional[list[str]], typer.Option("--method", "-m", show_default="auto", metavar="M[,M...]", help=MethodOpt.__metadata__[0].help + " Give -m more than once, or a list (-m l2,ps-fcn,ps-fcn-n), to compare methods in one table: each method's rows, then the paper's; with --out, OUT/<method>/ each and OUT/compare.png, compare.json.")] = None,
    images: Annotated[Optional[int], typer.Option("--images", "-n", help="Use K images per object (as psctl normals --images).")] = None,
    seed: Seed = None,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", readable=False, help="Also write each object's outputs to OUT/<object>/, and OUT/eval.png (every object's normal and error maps; the ensemble's spread maps too) and OUT/eval.json.")] = None,
    weights: WeightsOpt = None,
    device: DeviceOpt = "auto",
    lcnet: LcnetOpt = None,
    views: ViewsOpt = 1,
    downsample: DownsampleOpt = 1,
    precision: PrecisionOpt = "float32",
    refine: RefineOpt = True,
    falloff: FalloffOpt = None,
    roll: RollOpt = None,
    encoding: EncodingOpt = "auto",
    light_distance: LightDistanceOpt = None,
    snap: SnapOpt = True,
    albedo: Annotated[bool, _flag("--albedo", help="With --out: each object's albedo maps too, as psctl normals --albedo writes them.")] = False,
    markdown: Annotated[bool, _flag("--markdown", help="Print the table as Markdown on stdout (for a README or a paper's draft); notes go to stderr.")] = False,
    json_out: Json = False,
    quiet: Quiet = False,
) -> None:
    """Run a method over every object of a benchmark and print the paper-style error table."""
    with _user_errors():
        from psctl.eval import compare_methods, method_names, run_benchmark
        from psctl.io.summary import render_benchmark, render_benchmark_markdown, render_comparison

        if markdown and json_out:
            from psctl.errors import PsctlError

            raise PsctlError(None, "--markdown and --json each print the result on stdout; choose one")

        methods = method_names(method or ["auto"])  # -m a -m b and -m a,b alike; a name given twice runs once
        options = dict(n_images=images, seed=seed, out=out, weights=weights, device=device, lcnet=lcnet, views=views,
                       refine=refine, falloff=falloff, roll=roll, encoding=encoding, light_distance=light_distance,
                       downsample=downsample, precision=precision, albedo=albedo, snap=snap)
        if len(methods) == 1:
            _run(lambda progress: run_benchmark(benchmark, root=root, method=methods[0], progress=progress, **options),
                 json_out, quiet, render_benchmark_markdown if markdown else render_benchmark)
        else:
            _run(lambda progress: compare_methods(benchmark, methods, root=root, progress=progress, **options),
                 json_out, quiet, render_benchmark_markdown if markdown else render_comparison)


@app.command(cls=_Command)
def lights(
    path: Annotated[Path, typer.Argument(readable=False, help="Capture folder (images, mask.png; light_directions.txt is not needed).")],
    out: OutDir = None,
    weights: Annotated[Optional[Path], typer.Option("--weights", "-w", readable=False, help="LCNet weights: psctl's lcnet.pt or the authors' LCNet_CVPR2019.pth.tar (default: the installed weights).")] = None,
    decode: Annotated[str, typer.Option(help="soft (soft-argmax) | argmax (class centres, the paper).")] = "soft",
    views: Annotated[int, typer.Option(help="Symmetric views averaged: 8 (the images turned and mirrored about the view axis) | 4 | 2 | 1 (one pass, the paper).")] = 8,
    images: LightsImages = None,
    seed: Seed = None,
    device: Annotated[str, typer.Option("--device", help="auto | cpu | cuda | cuda:N: where LCNet and the refinement's normals network run.")] = "auto",
    refine: Annotated[bool, _flag("--refine/--no-refine", help="Refine LCNet's lights against the normals that the installed PS-FCN (or --normals-weights) gives from them (docs/uncalibrated.md).")] = True,
    normals_weights: Annotated[Optional[Path], typer.Option("--normals-weights", readable=False, help="With --refine: the normals network's weights (PS-FCN†, PS-FCN or PS-FCN+N; default: the installed one).")] = None,
    falloff: FalloffOpt = None,
    roll: RollOpt = None,
    encoding: EncodingOpt = "auto",
    light_distance: Annotated[Optional[float], typer.Option("--light-distance", help="With --refine: the lights are points this many image pixels from the object along the estimated directions; each image is divided by its light's falloff before the refinement's normals (docs/near-lights.md; DiLiGenT's rig: about 2400).")] = None,
    precision: Annotated[str, typer.Option("--precision", help="With --refine: the normals network's arithmetic, as psctl normals --precision (float32 | bf16 | fp16; LCNet runs in float32).")] = "float32",
    snap: SnapOpt = True,
    json_out: Json = False,
    quiet: Quiet = False,
) -> None:
    """Estimate light directions and intensities (LCNet): light_directions.txt, light_intensities.txt, lights.png, lights_report.json."""
    with _user_errors():
        from psctl.lights import render_lights, run_lights

        _run(lambda progress: run_lights(path, out=out, weights=weights, device=device, decode=decode,
                                         views=views, n_images=images, seed=seed, progress=progress,
                                         refine=refine, normals_weights=normals_weights, falloff=falloff,
                                         roll=roll, encoding=encoding, light_distance=light_distance,
                                         precision=precision, snap=snap),
             json_out, quiet, render_lights)


@app.command(cls=_Command)
def calibrate(
    path: Annotated[Path, typer.Argument(readable=False, help="Folder of images of a sphere, one per light in the object's order; mask.png: the sphere (or --circle).")],
    sphere: Annotated[str, typer.Option("--sphere", "-s", help="chrome (a mirror ball: directions from its highlights) | matte (a white Lambertian ball: directions and intensities).")],
    circle: Annotated[Optional[str], typer.Option("--circle", help="The sphere's outline as X,Y,R in pixels (the centre's column and row, the top-left pixel's centre at 0,0; the radius), instead of fitting one to mask.png.")] = None,
    offset: Annotated[bool, _flag("--offset/--no-offset", help="matte: fit a constant per image as well (I = n . l e + c): for images that keep a black level or room light and have no ambient.png (docs/calibration.md, 'Offset').")] = False,
    focal: Annotated[Optional[str], typer.Option("--focal", help="The camera's focal length in pixels, or 'exif' to read it from the images: a pinhole camera instead of an orthographic one, for a sphere away from the image's centre (docs/calibration.md, 'Perspective').")] = None,
    principal: Annotated[Optional[str], typer.Option("--principal", help="With --focal: the principal point as X,Y in pixels (default: the image's centre).")] = None,
    K: Annotated[Optional[Path], typer.Option("--K", readable=False, help="Instead of --focal and --principal: a 3x3 camera matrix file (as psctl depth reads; the K.txt psctl undistort writes).")] = None,
    out: OutDir = None,
    encoding: EncodingOpt = "auto",
    json_out: Json = False,
    quiet: Quiet = False,
) -> None:
    """Calibrate lights with a chrome or matte sphere: light_directions.txt (and, matte, light_intensities.txt), lights.png, sphere.png."""
    with _user_errors():
        from psctl.calibrate import render_calibrate, run_calibrate  # (run_calibrate checks --sphere first)

        _run(lambda progress: run_calibrate(path, sphere, out=out, circle=circle, progress=progress, encoding=encoding,
                                                   offset=offset, focal=focal, principal=principal, K=K),
             json_out, quiet, render_calibrate)


@app.command(cls=_Command)
def undistort(
    path: Annotated[Path, typer.Argument(readable=False, help="Capture folder whose photos were taken through a lens with distortion.")],
    out: Annotated[Path, typer.Option("--out", "-o", readable=False, help="New or empty folder (or an earlier undistort output, replaced) for the undistorted capture (images, mask.png, light files, K.txt).")],
    K: Annotated[Optional[Path], typer.Option("--K", readable=False, help="3x3 camera intrinsics in pixels (as psctl depth reads them; OpenCV's camera matrix).")] = None,
    distortion: Annotated[Optional[str], typer.Option("--distortion", "-d", help="OpenCV's distortion coefficients k1,k2,p1,p2[,k3[,k4,k5,k6]].")] = None,
    camera: Annotated[Optional[Path], typer.Option("--camera", readable=False, help="Instead of --K and --distortion: OpenCV's calibration file (cv2.FileStorage YAML or JSON: camera_matrix, distortion_coefficients).")] = None,
    json_out: Json = False,
    quiet: Quiet = False,
) -> None:
    """Undo lens distortion: write the capture as a pinhole camera would have taken it (docs/calibration.md, 'Lens distortion')."""
    with _user_errors():
        from psctl.undistort import render_undistort, run_undistort

        _run(lambda progress: run_undistort(path, out, K, distortion, progress=progress, camera=camera), json_out, quiet,
             render_undistort)


@app.command(cls=_Command)
def synth(
    out: Annotated[Path, typer.Argument(help="Output folder: one capture folder per object, plus objects.txt.")],
    preset: Annotated[str, typer.Option("--preset", "-p", help="syntest | dragon-svbrdf | blobby")],
    seed: Annotated[int, typer.Option(help="Random seed (shapes, materials, lights).")] = 0,
    size: Annotated[int, typer.Option(help="Image side in pixels.")] = 128,
    lights: Annotated[int, typer.Option(help="Lights (images) per object.")] = 100,
    light_dist: Annotated[str, typer.Option("--light-dist", help="Zenith band of the lights: hemisphere (0-90 degrees) | diligent (0-45, like DiLiGenT's rig) | poles (0-30) | equator (60-90).")] = "hemisphere",
    intensities: Annotated[str, typer.Option("--intensities", help="Light intensities, drawn per object: unit | random (uniform in [0.2, 2], independent per image) | directional (a smooth function of the light direction, as rigs whose LEDs dim towards the rim) | mixed.")] = "unit",
    materials: Annotated[Optional[int], typer.Option("--materials", "-k", help="K: MERL materials per shape (syntest, default 4), material pairs (dragon-svbrdf, 1), shapes (blobby, 8).")] = None,
    interreflections: Annotated[int, typer.Option("--interreflections", help="Diffuse interreflection bounces to add (0: none; at most 100; not with --light-distance).")] = 0,
    ir_albedo: Annotated[Optional[float], typer.Option("--ir-albedo", help="With --interreflections: the surface lights itself as a source of albedo A * kd / max(kd) (default: kd).")] = None,
    light_distance: Annotated[Optional[float], typer.Option("--light-distance", help="Point lights this many pixels from each object's centre along its light directions (falloff and per-pixel directions; docs/near-lights.md). Default: distant lights.")] = None,
    preview: Annotated[bool, _flag("--preview", help="Also write OUT/preview.png, a contact sheet.")] = False,
    json_out: Json = False,
    quiet: Quiet = False,
) -> None:
    """Render synthetic objects as DiLiGenT-style folders (readable by psctl normals / eval)."""
    with _user_errors():
        from psctl.synth import check_preset

        check_preset(preset)  # before the heavy imports: a typo fails at once (write_preset takes BLOBBY as blobby)
        from psctl.synth.write import render_synth, write_preset  # (preset_objects checks --light-dist before writing)

        _run(lambda progress: write_preset(out, preset, seed=seed, size=size, n_lights=lights, k=materials, light_dist=light_dist,
                                           intensities=intensities, interreflections=interreflections, ir_albedo=ir_albedo,
                                           light_distance=light_distance, preview=preview, progress=progress),
             json_out, quiet, render_synth)


@app.command(cls=_Command)
def depth(
    path: Annotated[Path, typer.Argument(readable=False, help="Capture folder. Normals: the first of PATH/psctl/normal.exr, normal.npy, normal.png, normal_8bit.png that the psctl normals run there wrote (its report.json), else the first of them there, else estimated (--method auto); with --out DIR, a map a psctl normals run of this capture wrote in DIR comes first.")],
    normals: Annotated[Optional[Path], typer.Option("--normals", readable=False, help="Normal map to integrate: psctl's 16- or 8-bit PNG, EXR or .npy.")] = None,
    method: Annotated[str, typer.Option("--method", "-m", help="poisson | bilateral (keeps depth jumps)")] = "poisson",
    out: OutDir = None,
    K: Annotated[Optional[Path], typer.Option("--K", readable=False, help="3x3 camera intrinsics (perspective) (default: PATH/K.txt if present, else orthographic).")] = None,
    encoding: EncodingOpt = "auto",
    json_out: Json = False,
    quiet: Quiet = False,
) -> None:
    """Integrate normals into a surface: depth.exr, depth.png, mesh.ply, shading.png, depth_report.json."""
    with _user_errors():
        from psctl.depth import render_depth, run_depth

        _run(lambda progress: run_depth(path, normals=normals, method=method, out=out, K=K, progress=progress,
                                        encoding=encoding),
             json_out, quiet, lambda r: render_depth(r, quiet=quiet))


@app.command(cls=_Command)
def train(
    method: Annotated[str, typer.Argument(help="ps-fcn | ps-fcn-n | ups-fcn | lcnet | ps-fcn-dagger")],
    config: Annotated[Optional[Path], typer.Option("--config", "-c", readable=False, help="Recipe YAML (see configs/; without it: the paper's schedule, 2.5 M samples from scratch).")] = None,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", readable=False, help="Run folder for a new run, new or empty (default: runs/METHOD with _ for -, e.g. runs/ps_fcn_n).")] = None,
    resume: Annotated[Optional[Path], typer.Option(readable=False, help="Continue the run in this folder.")] = None,
    device: Annotated[str, typer.Option(help="auto | cpu | cuda | cuda:N")] = "auto",
    max_minutes: Annotated[Optional[float], typer.Option(help="Checkpoint and stop after this many minutes.")] = None,
    install: Annotated[bool, _flag(help="When finished, copy the best weights to the weights folder ($PSCTL_WEIGHTS, else the checkout's weights/, else ~/.local/share/psctl/weights for an installed wheel); an installed file only with --force.")] = False,
    force: Annotated[bool, _flag("--force", help="With --install: replace the installed release file.")] = False,
    lcnet: Annotated[Optional[Path], typer.Option("--lcnet", readable=False, help="ps-fcn-dagger: the frozen LCNet's weights (default: the recipe's lcnet.weights, else weights/lcnet.pt).")] = None,
    average: Annotated[Optional[list[Path]], typer.Option("--average", metavar="FILE", readable=False, help="Instead of training: write the parameter average of these weight files (repeat the option; same method and architecture) as OUT/best.pt; with --config, measured on that recipe's validation set.")] = None,
    quiet: Quiet = False,
) -> None:
    """Train a network on the synthetic stream; resumable (checkpoints every few minutes and on Ctrl-C)."""
    with _user_errors():
        from psctl.models.weights import read_weights
        from psctl.train import average_weights, check_train_options, install_weights, train as run_training

        method, cfg = check_train_options(method, config, out, resume, device, max_minutes, install, force, lcnet,
                                          average)
        if average:
            if quiet or cfg is None:
                path = average_weights(average, out, cfg, device, method=method, recipe_name=config)
            else:  # building the validation set takes minutes on a CPU
                with _stderr().status("averaging, then measuring on the recipe's validation set"):
                    path = average_weights(average, out, cfg, device, method=method, recipe_name=config)
            if not quiet:
                metrics = read_weights(path).metadata["metrics"]
                said = "".join(f"; synthetic validation {v:.4f}" for v in metrics.values())
                _stderr().print(f"averaged {len(average)} files: weights {path}{said}", highlight=False, markup=False,
                                soft_wrap=True)
            if install:
                _stderr().print(f"installed {install_weights(out, method, replace=force)}", highlight=False, markup=False)
            return
        run_dir = resume or out or Path("runs") / method.replace("-", "_")
        con = _stderr()
        from rich.markup import escape

        gone = [False]  # stderr's reader went away (`2>&1 | head`): the first progress report stops the run

        def say(line: str) -> None:
            """A line (Rich markup) before the run folder exists: without a reader the run goes on to
            stop at its first report, with a checkpoint (exit 141), not here without one."""
            try:
                con.print(line, highlight=False, soft_wrap=True)
            except (BrokenPipeError, SystemExit) as e:
                if not _reader_gone(e):
                    raise
                gone[0] = True

        kwargs = dict(resume=resume is not None, device=device, lcnet=lcnet, recipe=config,
                      max_seconds=None if max_minutes is None else 60 * max_minutes,
                      note=None if quiet or sys.stderr is None else
                      lambda text: say(f"[yellow]note:[/] {escape(text)}"))
        if quiet or sys.stderr is None:  # no stderr (`2>&-`, a daemon): as quiet
            st = run_training(method, cfg, run_dir, **kwargs)
        elif not _stderr_is_terminal():  # a log (e.g. a remote GPU run): a plain line every 30 s
            import time

            last = [0.0]
            kwargs["started"] = lambda: say(escape(f"train {method} in {run_dir}: a line every 30 s from the first "
                                                   f"logged step (log.jsonl has every one)"))

            from psctl.train import STOP

            def log_line(rec: dict) -> str | None:
                if gone[0]:
                    return STOP
                if time.monotonic() - last[0] >= 30:
                    last[0] = time.monotonic()
                    try:
                        con.print(f"{rec['samples']:,}/{rec['total']:,} samples  loss {rec['loss']:.4f}  "
                                  f"{rec['samples_per_s']:.0f}/s  lr {rec['lr']:.2g}  {rec['seconds']:.0f} s",
                                  highlight=False, soft_wrap=True)
                    except (BrokenPipeError, SystemExit) as e:  # a closed pipe (`2>&1 | head`): stop at a
                        if not _reader_gone(e):                 # checkpoint (exit 141), not die without one
                            raise
                        return STOP
                return None

            st = run_training(method, cfg, run_dir, progress=log_line, **kwargs)
        else:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed:,} samples"),
                          TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TimeRemainingColumn(), console=con) as bar:
                task = bar.add_task(f"train {method}", total=None, info="")  # the first report sets it

                def report(rec: dict) -> None:
                    bar.update(task, completed=rec["samples"], total=rec["total"],
                               info=f"loss {rec['loss']:.4f}  {rec['samples_per_s']:.0f}/s  lr {rec['lr']:.2g}")

                st = run_training(method, cfg, run_dir, progress=report, **kwargs)
        import signal

        why = ("--max-minutes" if not st.get("signal") else
               "Ctrl-C (SIGINT)" if st["signal"] == signal.SIGINT else _signal_name(st["signal"]))
        state = "finished" if st["finished"] else f"stopped by {why} (continue with --resume {run_dir})"
        what = "light direction error" if method == "lcnet" else "MAE"
        best = Path(run_dir) / "best.pt"
        said = ("no validation yet, so no best.pt" if st["best_val"] is None else
                f"best synthetic validation {what} {st['best_val']:.2f}°; weights {best}" if best.is_file() else
                f"best synthetic validation {what} {st['best_val']:.2f}°, but {best}, which held it, is missing "
                f"(removed since)")
        con.print(f"{state}: {st['samples']:,} samples in {st['seconds'] / 60:.1f} min; {said}",
                  highlight=False, soft_wrap=True, markup=False)
        if install and st["finished"]:
            con.print(f"installed {install_weights(run_dir, method, replace=force)}", highlight=False, markup=False)
        elif install:
            con.print(f"not installed: the run stopped before its last sample (--resume {run_dir} --install "
                      f"finishes it and installs)", highlight=False, soft_wrap=True, markup=False)
        if st.get("signal"):  # Ctrl-C, SIGTERM or SIGHUP: checkpointed, but not what a finished run returns
            raise typer.Exit(128 + st["signal"])


@app.callback(invoke_without_command=True)
def _root(version: Annotated[bool, _flag("--version", help="Print the version.")] = False) -> None:
    if version:
        from psctl import __version__

        typer.echo(f"psctl {__version__}")
        raise typer.Exit()


def main(prog_name: str | None = None) -> None:
    """The ``psctl`` command (its script, ``python -m psctl`` and ``python -m psctl.cli``)."""
    from psctl.errors import C_STDERR

    C_STDERR["silence"] = True  # libpng's own lines would break the one-line errors (not for library callers)
    for stream in (sys.stdout, sys.stderr):
        # a console or a redirect in a legacy code page (Windows' cp1252, LANG=C) cannot spell every file
        # name: written as escapes, not a UnicodeEncodeError after the outputs are written
        with contextlib.suppress(AttributeError, ValueError):
            stream.reconfigure(errors="backslashreplace")
    try:
        app(prog_name=prog_name)
    finally:  # main() called in a notebook: later library calls keep their stderr
        C_STDERR["silence"] = False


if __name__ == "__main__":
    main()
