"""The documentation's examples, run: every ```python block of README.md and docs/*.md, and every
``psctl ...`` command in the ```bash / ```sh / ```console blocks of README.md, docs/*.md and
weights/README.md, so that a function, argument or option renamed in the code (or misspelt in a doc) fails here,
naming the doc file and line.

Where they run: a fresh copy of a small "world" per test (``world`` below: 32 px, 12-image
stand-ins for every folder the examples name, ``examples/bumpy_sphere``, ``./obj``, ``cap``,
``DiLiGenT/pmsData``, ...), as the current folder, with the release weights; nothing from
../shared/data and no GPU. ``/tmp/`` in a block is read as that folder's ``tmp/``, so no example
writes outside it.

How: a Python block is executed in-process, compiled under the doc's own path and line numbers
(a traceback points into the doc); a ``psctl`` command runs in-process through typer's runner
(exit status 0 wanted; ``> FILE`` gets its stdout). Commands of a shell block run in order, in one
world, as a reader would type them; lines that are not psctl commands (``pip install``, ``mkdir``)
are left out, but for ``cp`` (the test copies as it says). A fence without a language that holds a
psctl command fails ``test_untagged_blocks_hold_no_commands``: tag it ```bash so that it is run.
``psctl.PsctlWarning`` from a Python block is a failure unless SETUPS allows it:
an example that warns does not do what its text says.

Markers: a block that needs more than the world (a fragment that continues an earlier block,
a setting that would take hours) carries an HTML comment on the line above its fence, which
GitHub does not show:

    <!-- docs-test: id=NAME -->              its setup is SETUPS[NAME] below
    <!-- docs-test: skip (REASON) -->        not run (say why: needs DiLiGenT, a GPU, ...)

The id sits beside the block it belongs to, so it moves with the block when the doc is edited
(a table keyed by line numbers would not), and a reader of the doc sees that the block is tested
and where its setup is. An unknown id, or an entry of SETUPS that no doc uses, fails
``test_markers_and_setups_agree``.
"""

from __future__ import annotations

import dataclasses
import re
import shlex
import shutil
import sys
import traceback
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.conftest import REPO, write_capture

PYTHON_DOCS = ["README.md", *sorted(str(p.relative_to(REPO)) for p in (REPO / "docs").glob("*.md"))]
SHELL_DOCS = [*PYTHON_DOCS, "weights/README.md"]
SHELL_LANGS = {"bash", "sh", "shell", "console"}
MARKER = re.compile(r"^<!--\s*docs-test:\s*(?:id=(?P<id>[\w.-]+)|skip\s*\((?P<skip>[^)]*)\))\s*-->\s*$")


@dataclasses.dataclass(frozen=True)
class Setup:
    """What one marked block needs beyond the world."""

    prelude: str = ""  # Python run before a Python block (names an earlier block defined)
    replace: tuple[tuple[str, str], ...] = ()  # (doc text, what runs instead): each must be in the block
    env: tuple[tuple[str, str], ...] = ()  # environment for the block; "{world}" is the world's path
    defaults: tuple[tuple[str, str, object], ...] = ()  # (module, dict name, {key: value}) set for the block
    epilogue: str = ""  # Python run after the block: what the text says the result is for
    allow_warnings: tuple[str, ...] = ()  # PsctlWarning messages (regex) that the block may give
    known_bug: str = ""  # an error message (regex) of a reported bug: xfail while it is there, fail once gone


SETUPS: dict[str, Setup] = {
    # docs/usage.md, "From Python": continues the first block (cap)
    "usage-progress": Setup(prelude='import psctl\ncap = psctl.open_capture("examples/bumpy_sphere")'),
    "usage-reuse": Setup(prelude="import psctl"),
    # white_ball: a matte sphere in the world; chrome_ball: a mirror ball
    "usage-calibrate-arrays": Setup(prelude="import psctl"),
    "usage-undistort-arrays": Setup(prelude='import numpy as np\nimport psctl\n'
                                            'images = psctl.load_images(psctl.open_capture("examples/bumpy_sphere"))'),
    # docs/depth.md: "obj" with a normal map (what `psctl normals obj` writes) and its K.txt
    "depth-python": Setup(prelude='import psctl\npsctl.run_normals("obj", method="l2")'),
    # docs/synthetic.md: the stream as documented, on a pool of 2 G-buffers at 32 px (the default
    # 64 at 128 px take 9 to 40 s to render), without mesh files, as in a fresh clone (an empty
    # mesh folder: ../shared/data/meshes is not read); the loader's first batch is what the block
    # builds it for
    "synth-stream": Setup(
        env=(("PSCTL_MESHES", "{world}/meshes"),),
        defaults=(("psctl.synth.stream", "DEFAULT_CONFIG", {"pool": 2, "size": 32, "refresh_chunk": 2}),),
        epilogue="first = next(iter(loader))\nassert first['images'].shape == batch['images'].shape\ndel loader"),
    # docs/training.md: the three calls, on a 2-step smoke recipe and the CPU, into a weights folder of
    # the world's (install_weights must never replace the checkout's weights/ps_fcn_n.pt here)
    "train-python": Setup(
        replace=(("configs/ps_fcn_n.yaml", "configs/docs_tiny.yaml"), ('device="cuda"', 'device="cpu"')),
        env=(("PSCTL_WEIGHTS", "{world}/weights"),),
        epilogue='assert (Path(r"{world}") / "weights" / "ps_fcn_n.pt").is_file()'),
    # docs/calibration.md: the outlines drawn by hand where the world's spheres are (64 px images;
    # the one beside the object: obj_sphere's, in images with a phone's EXIF, as chrome's)
    "calibrate-cli": Setup(replace=(("--circle 307.9,263.9,70.9", "--circle 31.7,32.6,25.6"),
                                    ("./obj --sphere chrome --circle 80,420,36",
                                     "./obj_sphere --sphere chrome --circle 14,46,10"))),
    # docs/synthetic.md: the three presets at 16 px, 8 lights, one material or shape each (4, 3 and
    # 1 objects), with small ellipsoids for the test meshes (psctl ships none)
    "synth-cli": Setup(
        replace=(("--preset syntest --materials 4", "--preset syntest --materials 1 --size 16 --lights 8"),
                 ("--preset dragon-svbrdf --materials 2", "--preset dragon-svbrdf --materials 1 --size 16 --lights 8"),
                 ("--preset blobby --materials 8", "--preset blobby --materials 1 --size 16 --lights 8")),
        env=(("PSCTL_MESHES", "{world}/test_meshes"),)),
    # docs/training.md: the three commands on the 2-step recipe and the CPU, installing into the world's
    "train-cli": Setup(replace=(("configs/ps_fcn_n.yaml", "configs/docs_tiny.yaml"), ("--device cuda", "--device cpu")),
                       env=(("PSCTL_WEIGHTS", "{world}/weights"),)),
    # docs/uncalibrated.md: `psctl eval` without --root reads $PSCTL_DATA/DiLiGenT/pmsData
    "uncalibrated-cli": Setup(env=(("PSCTL_DATA", "{world}/uncalibrated"),)),
    # docs/uncalibrated.md, training: LCNet's and PS-FCN†'s recipes cut to 2 samples at 16 px, on the
    # CPU; the weights folder is the world's (holding a copy of the release's lcnet.pt)
    "train-lcnet-cli": Setup(
        replace=(("configs/lcnet.yaml", "configs/docs_tiny_lcnet.yaml"),
                 ("configs/ps_fcn_dagger.yaml", "configs/docs_tiny_ps_fcn_dagger.yaml"),
                 ("--device cuda", "--device cpu")),
        env=(("PSCTL_WEIGHTS", "{world}/weights"),)),
}


# --- the blocks --------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Block:
    doc: str  # path relative to the repository
    line: int  # the opening fence's line (1-based)
    lang: str
    text: str
    marker_id: str | None = None
    skip: str | None = None

    @property
    def where(self) -> str:
        return f"{self.doc}:{self.line}"


def doc_blocks(doc: str) -> list[Block]:
    """The fenced blocks of ``doc``, each with the docs-test marker above it, if any."""
    lines = (REPO / doc).read_text(encoding="utf-8").splitlines()
    out, k = [], 0
    while k < len(lines):
        m = re.match(r"^(\s*)(`{3,}|~{3,})\s*([\w+-]*)", lines[k])
        if not m:
            k += 1
            continue
        indent, fence, lang = m.groups()
        end = k + 1
        while end < len(lines) and not lines[end].strip().startswith(fence):
            end += 1
        body = "\n".join(s[len(indent):] if s.startswith(indent) else s for s in lines[k + 1:end])
        above = k - 1
        while above >= 0 and not lines[above].strip():
            above -= 1
        mk = MARKER.match(lines[above].strip()) if above >= 0 else None
        out.append(Block(doc, k + 1, lang.lower(), body, mk and mk["id"], mk and mk["skip"]))
        k = end + 1
    return out


def all_blocks() -> list[Block]:
    return [b for doc in dict.fromkeys(PYTHON_DOCS + SHELL_DOCS) for b in doc_blocks(doc)]


PYTHON_BLOCKS = [b for doc in PYTHON_DOCS for b in doc_blocks(doc) if b.lang in ("python", "py")]
SHELL_BLOCKS = [b for doc in SHELL_DOCS for b in doc_blocks(doc) if b.lang in SHELL_LANGS]


@dataclasses.dataclass(frozen=True)
class Command:
    line: int  # in the doc
    text: str  # the doc's line, as written
    argv: tuple[str, ...]  # psctl's arguments
    stdout_to: str | None  # `> FILE`
    tool: str = "psctl"  # or "cp" (with_cp=True)


def psctl_commands(block: Block, with_cp: bool = False) -> list[Command]:
    """The psctl commands of a shell block: each line (with its backslash continuations) split at
    &&, || and ;, the parts that start with ``psctl`` (or ``python -m psctl``, ``$ psctl``); with
    ``with_cp``, the ``cp`` commands among them too, in order."""
    out = []
    raw = block.text.splitlines()
    k = 0
    while k < len(raw):
        first, text = k, raw[k]
        while text.endswith("\\") and k + 1 < len(raw):
            k += 1
            text = text[:-1] + " " + raw[k]
        k += 1
        if block.lang == "console":
            if not text.lstrip().startswith("$ "):
                continue  # output, not a command
            text = text.lstrip()[2:]
        lex = shlex.shlex(text, posix=True, punctuation_chars=True)
        lex.whitespace_split = True
        tokens = list(lex)
        parts, cur = [], []
        for t in tokens:
            if t in ("&&", "||", ";", "&"):
                parts.append(cur)
                cur = []
            else:
                cur.append(t)
        parts.append(cur)
        for p in parts:
            tool = "psctl"
            if p[:1] == ["psctl"]:
                args = p[1:]
            elif with_cp and p[:1] == ["cp"]:
                tool, args = "cp", p[1:]
            elif p[:3] in (["python", "-m", "psctl"], ["python3", "-m", "psctl"], ["python", "-m", "psctl.cli"]):
                args = p[3:]
            else:
                continue
            where = f"{block.doc}:{block.line + 1 + first}"
            shell = [t for t in args if any(c in t for c in "|<$`*?~") or t.startswith("(")]
            if tool == "cp" and (shell or ">" in args):
                continue  # a reader's own files (README: cp /path/to/photos/*.jpg cap/): the world has them
            stdout_to = None
            if ">" in args:
                i = args.index(">")
                if len(args) != i + 2:
                    raise AssertionError(f"{where}: only a trailing `> FILE` is understood here: {text.strip()}")
                stdout_to, args = args[i + 1], args[:i]
            if shell:
                raise AssertionError(f"{where}: shell syntax this test does not run ({' '.join(shell)}): "
                                     f"{text.strip()}")
            out.append(Command(block.line + 1 + first, text.strip(), tuple(args), stdout_to, tool))
    return out


SHELL_WITH_PSCTL = [b for b in SHELL_BLOCKS if psctl_commands(b)]


# --- the world ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def world_template(tmp_path_factory) -> Path:
    """Every folder and file the examples name, small: calibrated 32 px captures of 12 images with
    ground truth (examples/bumpy_sphere, obj, two DiLiGenT objects, two of one's own), a folder of
    JPEGs without light files (cap: sdps), 6-image ballPNG and catPNG (uncalibrated), chrome and
    matte spheres (with a phone's EXIF), intrinsics, OpenCV's calib.yml, a normal map (other.exr),
    the authors' checkpoints' layout, stand-in test meshes, the smoke recipes."""
    import torch

    from psctl.io.images import read_image, write_image
    from tests.test_calibrate import write_exif, write_sphere_folder
    from tests.test_synth import uv_sphere, write_obj

    w = tmp_path_factory.mktemp("docs_world")
    for i, name in enumerate(["examples/bumpy_sphere", "obj", "DiLiGenT/pmsData/ballPNG",
                              "DiLiGenT/pmsData/catPNG", "my_objects/a", "my_objects/b"]):
        arrays = write_capture(w / name, n=12, size=32, seed=i)
        if name == "obj":  # a normal map of its own (docs/depth.md: --normals other.exr)
            normals = np.where(arrays["mask"][..., None], arrays["normals"], 0)
            write_image(w / "other.exr", normals, "float", kind="data")
    for name in ("pmsData_crop", "DiLiGenT/pmsData_crop"):  # docs/models.md, docs/near-lights.md
        shutil.copytree(w / "DiLiGenT/pmsData", w / name)
    # docs/uncalibrated.md: 6 images each (LCNet's 8 views at 128 px per image are most of sdps'
    # time); cat alone in $PSCTL_DATA/DiLiGenT/pmsData for `psctl eval` without --root
    for i, name in enumerate(["ballPNG", "catPNG"]):
        write_capture(w / name, n=6, size=32, seed=2 + i)
    shutil.copytree(w / "catPNG", w / "uncalibrated/DiLiGenT/pmsData/catPNG")  # one object
    for name in ("light_directions.txt", "light_intensities.txt"):  # "(auto)": no light_directions.txt
        (w / "catPNG" / name).unlink()
    images = write_capture(w / "cap_png", n=12, size=32, seed=9, gt="none", mask=False, intensities=False)["images"]
    shutil.rmtree(w / "cap_png")
    (w / "cap").mkdir()
    bg = 0.02  # a dark cloth, not black: JPEG's ringing about the object stays above it
    for k, img in enumerate(images):
        write_image(w / "cap" / f"IMG_{k + 1:04d}.jpg", np.clip(img + bg, 0, 1) ** (1 / 2.2), "uint8")
    write_sphere_folder(w / "chrome", "chrome", n=12, size=64, lights_file=False)
    # docs/calibration.md: --focal exif reads the images' EXIF (a phone's 35 mm equivalent here)
    # and a chrome ball beside "the object" (none drawn), in an image that EXIF describes too
    write_sphere_folder(w / "obj_sphere", "chrome", n=12, size=64, lights_file=False, circle=(14.0, 46.0, 10.0))
    for f in [*sorted((w / "chrome").glob("0*.png")), *sorted((w / "obj_sphere").glob("0*.png"))]:
        write_exif(f, read_image(f)[0], FocalLengthIn35mmFilm=28)
    write_sphere_folder(w / "chrome_ball", "chrome", n=12, size=64, lights_file=False)
    write_sphere_folder(w / "white", "matte", n=12, size=64, lights_file=False)
    write_sphere_folder(w / "white_ball", "matte", n=12, size=64, lights_file=False)
    k_txt = "40.0 0.0 16.0\n0.0 40.0 16.0\n0.0 0.0 1.0\n"  # 3 x 3 intrinsics, pixels (docs/depth.md)
    (w / "K.txt").write_text(k_txt)
    (w / "obj" / "K.txt").write_text(k_txt)
    (w / "intrinsics.txt").write_text(k_txt)  # docs/depth.md
    # docs/calibration.md: OpenCV's calibration file (cv2.FileStorage YAML)
    (w / "calib.yml").write_text(
        "%YAML:1.0\n---\nimage_width: 32\nimage_height: 32\n"
        "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [ 40., 0., 16., 0., 40., 16., 0., 0., 1. ]\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
        "   data: [ -0.12, 0.031, 0.0004, -0.0002, 0. ]\n")
    # the smoke recipe cut to 2 steps, one validation and one 16 px G-buffer (tiny.yaml itself took
    # 12 s of this file's 25 on a quiet 2-core VM; most of what is left is torch importing dynamo for Adam)
    recipe = yaml.safe_load((REPO / "configs" / "tiny.yaml").read_text())
    recipe["data"].update(size=16, pool=1)
    recipe["train"].update(samples=8, val_every=8, log_every=1)
    recipe["val"].update(samples=4)
    (w / "configs").mkdir()
    (w / "configs" / "docs_tiny.yaml").write_text(yaml.safe_dump(recipe))
    # LCNet's and PS-FCN†'s recipes as small (docs/uncalibrated.md): their own method, loss and
    # data settings, tiny's sizes
    for method, name in (("lcnet", "lcnet"), ("ps-fcn-dagger", "ps_fcn_dagger")):
        full = yaml.safe_load((REPO / "configs" / f"{name}.yaml").read_text())
        assert full["method"] == method
        full["data"].update(size=16, pool=1, shapes={"blobby": 1.0})
        full["train"].update(batch_size=2, images_per_sample=6, crop=16, samples=2, val_every=2, log_every=1,
                             amp="none")
        full["val"].update(samples=1, size=16, images=6, batch_size=1)
        (w / "configs" / f"docs_tiny_{name}.yaml").write_text(yaml.safe_dump(full))
    (w / "weights").mkdir()
    shutil.copy(REPO / "weights" / "lcnet.pt", w / "weights")  # PS-FCN†'s frozen LCNet, as installed
    # the authors' checkpoints' layout (docs/models.md, docs/uncalibrated.md), from the release's
    # weights (NENet has PS-FCN's keys)
    for name, file, model in (("ps_fcn", "PS-FCN_B_S_32.pth.tar", "PS_FCN"),
                              ("ps_fcn_n", "PS-FCN_B_S_32_normalize.pth.tar", "PS_FCN"),
                              ("lcnet", "LCNet_CVPR2019.pth.tar", "LCNet"),
                              ("ps_fcn", "NENet_CVPR2019.pth.tar", "NENet")):
        torch.save({"state_dict": torch.load(REPO / "weights" / f"{name}.pt", map_location="cpu")["state_dict"],
                    "model": model}, w / file)
    (w / "meshes").mkdir()  # none: the synthetic stream as in a fresh clone
    # stand-ins for the test shapes (psctl synth --preset syntest, dragon-svbrdf): small ellipsoids
    verts, faces = uv_sphere(8, 16)
    (w / "test_meshes").mkdir()
    for k, name in enumerate(("bunny", "dragon", "armadillo")):
        write_obj(w / "test_meshes" / f"{name}.obj", verts * [1.0, 1.3 + 0.2 * k, 0.8], faces)
    (w / "tmp").mkdir()
    return w


@pytest.fixture
def world(world_template, tmp_path, monkeypatch) -> Path:
    w = tmp_path / "world"
    shutil.copytree(world_template, w)
    monkeypatch.chdir(w)
    return w


# --- the tests ---------------------------------------------------------------------------------

def test_the_docs_have_the_blocks_this_file_runs():
    """The extractor finds what the docs hold (an extractor that finds nothing passes everything)."""
    assert len(PYTHON_BLOCKS) >= 9, [b.where for b in PYTHON_BLOCKS]
    assert sum(len(psctl_commands(b)) for b in SHELL_BLOCKS) >= 60
    assert {"info", "normals", "lights", "depth", "eval", "calibrate", "undistort", "synth", "train"} <= {
        c.argv[0] for b in SHELL_BLOCKS for c in psctl_commands(b)}


def test_untagged_blocks_hold_no_commands():
    """A fence without a language is not run: one holding a psctl command is to be tagged ```bash."""
    untagged = [f"{b.doc}:{c.line}" for b in all_blocks() if not b.lang
                for c in psctl_commands(dataclasses.replace(b, lang="bash"))]
    assert not untagged, f"psctl commands in fences without a language (tag them ```bash): {untagged}"
    # nor in a Markdown indented code block (4 spaces, outside a fence): fence it, ```bash
    indented = []
    for doc in dict.fromkeys(PYTHON_DOCS + SHELL_DOCS):
        fence = None
        for i, line in enumerate((REPO / doc).read_text(encoding="utf-8").splitlines(), 1):
            m = re.match(r"^\s*(`{3,}|~{3,})", line)
            if m and (fence is None or line.strip().startswith(fence)):
                fence = m.group(1) if fence is None else None
            elif fence is None and re.match(r"^ {4,}(\$ )?psctl [a-z]", line):
                indented.append(f"{doc}:{i}")
    assert not indented, f"psctl commands in indented code blocks (fence them ```bash): {indented}"


def test_markers_and_setups_agree():
    marked = {}
    for b in all_blocks():
        if b.marker_id:
            assert b.marker_id in SETUPS, f"{b.where}: docs-test id={b.marker_id} has no entry in SETUPS"
            assert b.marker_id not in marked, f"{b.where}: id={b.marker_id} is also {marked[b.marker_id]}'s"
            marked[b.marker_id] = b.where
    assert not set(SETUPS) - set(marked), f"SETUPS entries no doc block carries: {sorted(set(SETUPS) - set(marked))}"


def test_every_psctl_name_the_docs_mention_exists():
    """Prose names functions too (`psctl.refine.mirror_ratio`, `psctl.eval.compare_methods`): each
    dotted ``psctl.NAME`` of README.md, docs/*.md and weights/README.md must import and resolve
    (a dataclass's field counts), so a rename that the blocks above do not reach fails here."""
    import importlib

    missing = []
    seen: set[str] = set()
    for doc in [*PYTHON_DOCS, "weights/README.md"]:
        for i, line in enumerate((REPO / doc).read_text(encoding="utf-8").splitlines(), 1):
            for m in re.finditer(r"\bpsctl(?:\.[A-Za-z_]\w*)+", line):
                name = m.group(0)
                if name in seen:
                    continue
                seen.add(name)
                parts = name.split(".")
                for k in range(len(parts), 0, -1):
                    try:
                        obj = importlib.import_module(".".join(parts[:k]))
                        break
                    except ImportError:
                        continue
                for attr in parts[k:]:
                    fields = {f.name for f in dataclasses.fields(obj)} if dataclasses.is_dataclass(obj) else set()
                    if attr in fields and not hasattr(obj, attr):
                        break  # an instance field: nothing further to follow
                    if not hasattr(obj, attr):
                        missing.append(f"{doc}:{i}: {name}")
                        break
                    obj = getattr(obj, attr)
    assert len(seen) >= 50, sorted(seen)
    assert not missing, "names the docs mention that psctl does not have:\n" + "\n".join(missing)


def _setup(block: Block) -> Setup:
    if block.skip is not None:
        pytest.skip(f"{block.where}: marked docs-test: skip ({block.skip})")
    return SETUPS[block.marker_id] if block.marker_id else Setup()


def _failure(block: Block, exc: BaseException, what: str) -> str:
    """The doc line an exception came from (the innermost frame in the block), and the error."""
    line = None
    for frame in traceback.extract_tb(exc.__traceback__):
        if frame.filename == block.doc:
            line = frame.lineno
    shown = "".join(traceback.format_exception_only(type(exc), exc)).strip()
    at = f"{block.doc}:{line} (in the block at line {block.line})" if line else f"{block.where} ({what})"
    return f"{at}: {shown}"


@pytest.mark.parametrize("block", PYTHON_BLOCKS, ids=lambda b: b.where)
def test_python_example(block: Block, world: Path, monkeypatch):
    import psctl

    setup = _setup(block)
    src = block.text.replace("/tmp/", f"{world}/tmp/")
    for old, new in setup.replace:
        assert old in block.text, f"{block.where}: SETUPS[{block.marker_id!r}] replaces {old!r}, no longer in the block"
        src = src.replace(old, new)
    for name, value in setup.env:
        monkeypatch.setenv(name, value.format(world=world))
    for module, attr, values in setup.defaults:
        target = getattr(__import__(module, fromlist=[attr]), attr)
        for key, value in values.items():
            assert key in target, f"SETUPS[{block.marker_id!r}]: {module}.{attr} has no {key!r}"
            monkeypatch.setitem(target, key, value)
    ns: dict = {"__name__": "__docs_example__"}
    error = None
    # the block compiled as the doc's lines, so a traceback names the doc and the line
    code = compile("\n" * block.line + src, block.doc, "exec")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", psctl.PsctlWarning)
            for pattern in setup.allow_warnings:
                warnings.filterwarnings("ignore", message=pattern, category=psctl.PsctlWarning)
            if setup.prelude:
                exec(compile(setup.prelude, f"<SETUPS[{block.marker_id!r}].prelude>", "exec"), ns)
            exec(code, ns)
            if setup.epilogue:
                exec(compile(setup.epilogue.replace("{world}", str(world)),
                             f"<SETUPS[{block.marker_id!r}].epilogue>", "exec"), {**ns, "Path": Path})
    except Exception as exc:  # noqa: BLE001 (any error of an example is the finding)
        error = exc
    if error is not None:  # (out of the except clause: the report shows this error alone)
        if setup.known_bug and re.search(setup.known_bug, str(error)):
            pytest.xfail(f"known bug ({block.where}): {str(error).strip().splitlines()[-1]}")
        pytest.fail(_failure(block, error, "the ```python block"), pytrace=False)
    if setup.known_bug:
        pytest.fail(f"{block.where}: SETUPS[{block.marker_id!r}].known_bug ({setup.known_bug!r}) no longer "
                    "happens: remove it", pytrace=False)


@pytest.mark.parametrize("block", SHELL_WITH_PSCTL, ids=lambda b: b.where)
def test_shell_example(block: Block, world: Path, monkeypatch):
    from typer.testing import CliRunner

    from psctl.cli import app

    setup = _setup(block)
    for name, value in setup.env:
        monkeypatch.setenv(name, value.format(world=world))
    text = block.text
    for old, new in setup.replace:
        assert old in block.text, f"{block.where}: SETUPS[{block.marker_id!r}] replaces {old!r}, no longer in the block"
        assert "\n" not in old + new, f"SETUPS[{block.marker_id!r}]: a replacement keeps to one line"
        text = text.replace(old, new)
    failures = []
    for cmd in psctl_commands(dataclasses.replace(block, text=text), with_cp=True):
        args = [a.replace("/tmp/", f"{world}/tmp/") for a in cmd.argv]
        if cmd.tool == "cp":
            *sources, dest = [a for a in args if not a.startswith("-")]
            for src in sources:
                (shutil.copytree if Path(src).is_dir() else shutil.copy)(src, dest)
            continue
        r = CliRunner().invoke(app, args, env={"COLUMNS": "100"})
        if r.exception is not None and not isinstance(r.exception, SystemExit):
            tb = "".join(traceback.format_exception(r.exception)).strip()
            failures.append(f"{block.doc}:{cmd.line}: `{cmd.text}` raised\n{tb}")
        elif r.exit_code != 0:
            failures.append(f"{block.doc}:{cmd.line}: `{cmd.text}` exited {r.exit_code}: {r.stderr.strip()}")
        elif cmd.stdout_to:
            (world / cmd.stdout_to).write_text(r.stdout)
    if failures:
        pytest.fail("\n".join(failures), pytrace=False)


if __name__ == "__main__":  # list what runs: python tests/test_docs_examples.py
    for b in PYTHON_BLOCKS:
        print(b.where, "python", b.marker_id or "", b.skip or "")
    for b in SHELL_WITH_PSCTL:
        for c in psctl_commands(b):
            print(f"{b.doc}:{c.line}", "psctl", *c.argv)
    sys.exit(0)
