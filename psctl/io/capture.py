"""Capture folders (DiLiGenT style): one object per folder, or a benchmark root of several.

A capture folder holds
    images              listed in filenames.txt / names.txt, else every image file in natural order
    light_directions.txt    N x 3, optional (absent: uncalibrated)
    light_intensities.txt   N x 3 (RGB) or N x 1, optional (absent: all ones)
    mask.png            optional (absent: the whole image)
    Normal_gt.mat (key Normal_gt) / Normal_gt.png / normal.png   optional ground truth
Convention: x right, y up, z toward the camera. Pixels are linear float32, value / (2^bits - 1),
divided per channel by the image's intensity row.

``open_capture`` reads only headers and text files, so every size and count mismatch is found
before any pixel is decoded; ``iter_images`` then streams the pixels one image at a time.
"""

from __future__ import annotations

import contextlib
import os
import re
import unicodedata
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from psctl.arrays import check_lights_face_camera, lights_behind, unit_rows, unit_vectors
from psctl.errors import (ProgressFactory, PsctlError, check_bool, check_int, check_path, check_progress, few,
                          quoted_tilde)
from psctl.io.icc import ToneCurve
from psctl.io.images import (IMAGE_EXTENSIONS, RAW_SUFFIXES, ImageInfo, holds_colour, image_info, nonfinite_problem,
                              read_image, srgb_like, srgb_to_linear, to_rgb)
from psctl.io.matfile import load_variable, variable_shapes
from psctl.nearlight import NearLights

if TYPE_CHECKING:
    from psctl.io.prefetch import Prefetch

LIST_FILES = ("filenames.txt", "names.txt")
LIGHTS_FILE = "light_directions.txt"
INTENSITIES_FILE = "light_intensities.txt"
MASK_FILES = ("mask.png", "mask.tif", "mask.tiff", "mask.exr")
# an image taken with every light off (room light, sensor offset): subtracted from each image
AMBIENT_FILES = ("ambient.png", "ambient.tif", "ambient.tiff", "ambient.exr", "ambient.jpg", "ambient.jpeg")
GT_FILES = ("Normal_gt.mat", "Normal_gt.png", "normal.png", "Normal_gt.exr", "normal.exr")
# Files in a capture folder that are never input images (psctl normals' outputs; psctl eval --out's
# eval.png and compare.png; psctl synth --preview's preview.png).
_NOT_IMAGES = re.compile(r"^((mask|normal|normal_gt|error|depth|shading|lights|albedo)([._-].*)?|ambient|eval|compare|spread|sphere|undistort|preview)$",
                         re.I)

Progress = Callable[[int], None]


@dataclass(frozen=True)
class Capture:
    """A validated capture folder (headers and text files read, pixels not yet decoded)."""

    path: Path
    name: str
    image_paths: tuple[Path, ...]
    height: int
    width: int
    channels: int
    dtype: str
    bits: int
    lights: np.ndarray | None = field(repr=False)  # [N, 3] unit vectors, or None
    intensities: np.ndarray = field(repr=False)  # [N, 3]
    intensities_given: bool = False
    mask_path: Path | None = None
    gt_path: Path | None = None
    encoding: str = "auto"  # how pixel values map to radiance: one of ENCODINGS
    ambient_path: Path | None = None  # subtracted from every image (AMBIENT_FILES)
    # each image's header as open_capture read it (psctl.io.images.image_info), and the ambient
    # image's; the per-image properties below read them (empty: a Capture made without headers)
    infos: tuple[ImageInfo, ...] = field(default=(), repr=False)
    ambient_info: ImageInfo | None = field(default=None, repr=False)
    unread: tuple[str, ...] = ()  # files whose names look meant for psctl that it does not read (_unread)
    lights_path: Path | None = None  # light_directions.txt as named in the folder (any case)
    intensities_path: Path | None = None  # light_intensities.txt likewise
    list_path: Path | None = None  # the image list (filenames.txt or names.txt), when the folder has one
    near: NearLights | None = None  # point lights: iter_images divides out their falloff (psctl.nearlight)
    light_lengths: tuple[float, float] | None = None  # the light file's shortest and longest rows, where not unit
    # capture folders inside this one that hold none of its images: psctl eval --root reads them as objects
    sub_captures: tuple[str, ...] = ()

    @property
    def n_images(self) -> int:
        return len(self.image_paths)

    # each image's header fields, in image order ((): no headers)
    @property
    def orientations(self) -> tuple[int, ...]:
        """Each image's EXIF orientation (1: as stored; psctl.io.images.upright)."""
        return tuple(i.orientation for i in self.infos)

    @property
    def kinds(self) -> tuple[tuple[int, str], ...]:
        """Each image's (bits, sample type)."""
        return tuple((i.bits, i.dtype) for i in self.infos)

    @property
    def sample_kinds(self) -> tuple[str, ...]:
        """Each image's sample type as the notes name it: "8-bit", "16-bit" (integers), "16-bit signed"
        (read as value / 32767: the same codes read twice as bright as unsigned ones) or "half", "float"."""
        return tuple(f"{b}-bit" + " signed" * t.startswith("int") if t.startswith(("uint", "int")) else t
                     for b, t in self.kinds)

    @property
    def channel_counts(self) -> tuple[int, ...]:
        return tuple(i.channels for i in self.infos)

    @property
    def pages(self) -> tuple[int, ...]:
        """Each image file's subimages (a TIFF stack: psctl reads the first)."""
        return tuple(i.pages for i in self.infos)

    @property
    def layers(self) -> tuple[str, ...]:
        """Each image's layer read, of several ("Combined"; "": one or none)."""
        return tuple(i.layer for i in self.infos)

    @property
    def windowed(self) -> tuple[bool, ...]:
        """Each image's stored pixels are a window of its frame (an EXR's)."""
        return tuple(i.window is not None for i in self.infos)

    @property
    def exposures(self) -> tuple[tuple[float, float, float], ...]:
        """Each image's EXIF time (s), f-number, ISO (0: none)."""
        return tuple(i.exposure for i in self.infos)

    @property
    def profile_problems(self) -> tuple[str, ...]:
        """Why each image's embedded ICC profile gives no tone curves ("": none, or read)."""
        return tuple(i.profile_problem for i in self.infos)

    @property
    def png_tags(self) -> tuple[str, ...]:
        """What each PNG's colour chunks say its values are (ImageInfo.png_tag)."""
        return tuple(i.png_tag for i in self.infos)

    @property
    def ambient_jpeg(self) -> bool:
        return self.ambient_info is not None and self.ambient_info.format == "jpeg"

    @property
    def ambient_tone(self) -> ToneCurve | None:
        return None if self.ambient_info is None else self.ambient_info.tone

    @property
    def ambient_problem(self) -> str:
        return "" if self.ambient_info is None else self.ambient_info.profile_problem

    @property
    def ambient_png_tag(self) -> str:
        return "" if self.ambient_info is None else self.ambient_info.png_tag

    @property
    def calibrated(self) -> bool:
        return self.lights is not None

    def is_jpeg(self, k: int | Path) -> bool:
        """Whether image ``k`` (an index, or a file such as the ambient image) is JPEG data: by
        content where the header was read, whatever the name; else by name."""
        if isinstance(k, (int, np.integer)):
            return self.infos[int(k)].format == "jpeg" if self.infos else self.image_paths[int(k)].suffix.lower() in JPEG
        if self.ambient_path is not None and k == self.ambient_path:
            return self.ambient_jpeg
        return k.suffix.lower() in JPEG

    def decoding(self, k: int | Path) -> "str | ToneCurve | None":
        """How image ``k``'s stored values become linear: "srgb" (the sRGB curve), a ToneCurve (its
        embedded ICC profile's curves) or None (as stored). ``encoding`` linear: None; srgb:
        "srgb"; auto: the profile's curves where the file has a readable profile (None where they
        are linear: a linear export), else "srgb" for JPEG data (``is_jpeg``: a 16-bit PNG named
        .jpg stays linear), else None."""
        if self.encoding != "auto":
            return "srgb" if self.encoding == "srgb" else None
        if isinstance(k, (int, np.integer)):
            tone = self.infos[int(k)].tone if self.infos else None
        else:
            tone = self.ambient_tone if self.ambient_path is not None and k == self.ambient_path else None
        if tone is not None:
            return None if tone.linear else tone
        return "srgb" if self.is_jpeg(k) else None

    def is_srgb(self, k: int | Path) -> bool:
        """Whether image ``k`` is decoded with the sRGB curve (``decoding``)."""
        return isinstance(self.decoding(k), str)

    def to_linear(self, k: int | Path, values: np.ndarray) -> np.ndarray:
        """Image ``k``'s values (in [0, 1] for integer files) as linear values (``decoding``)."""
        how = self.decoding(k)
        if how is None:
            return values
        return srgb_to_linear(values) if isinstance(how, str) else how.to_linear(values)

    @property
    def turned(self) -> int:
        """How many of the images an EXIF orientation tag turns upright as they are read."""
        return sum(o != 1 for o in self.orientations)

    @property
    def srgb_images(self) -> int:
        """How many of the images are decoded from sRGB (``is_srgb``)."""
        return sum(self.is_srgb(k) for k in range(self.n_images))

    @property
    def profile_images(self) -> int:
        """How many of the images are decoded through their ICC profile's curves (``decoding``)."""
        return sum(isinstance(self.decoding(k), ToneCurve) for k in range(self.n_images))

    @property
    def input_paths(self) -> tuple[Path, ...]:
        """Every file the capture reads: images, mask, ground truth, ambient image."""
        return (*self.image_paths, *(p for p in (self.mask_path, self.gt_path, self.ambient_path) if p is not None))

    def subset(self, indices: Sequence[int]) -> "Capture":
        """The same capture restricted to some images (in the given order)."""
        idx = np.asarray(indices, dtype=np.int64)
        return replace(
            self,
            image_paths=tuple(self.image_paths[i] for i in idx),
            infos=tuple(self.infos[i] for i in idx) if self.infos else (),
            lights=None if self.lights is None else self.lights[idx],
            intensities=self.intensities[idx],
        )


# how pixel values map to radiance. Photometric stereo needs values proportional to radiance:
# DiLiGenT's PNGs and raw-converted TIFFs are linear; a camera's JPEGs carry the sRGB tone curve
# (their headers, like most PNGs', say sRGB whatever the data are, so only the kind of file or the
# user can tell, unless the file embeds an ICC profile). auto: a profile's tone curves where a file has
# one (psctl.io.icc), else JPEGs are sRGB and every other file linear.
ENCODINGS = ("auto", "linear", "srgb")
JPEG = (".jpg", ".jpeg")


def object_name(path: str | os.PathLike) -> str:
    """Folder name with a trailing ``PNG`` removed (``ballPNG`` -> ``ball``)."""
    name = Path(os.path.abspath(path)).name  # not resolved: a link to a folder is named as the link
    return name[:-3] if name.endswith("PNG") and len(name) > 3 else name


def natural_key(s: str) -> list:
    """Sort key that orders file names as people count: img2 before img10, case ignored."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", s)]


def _signed_names(names: list[str]) -> str | None:
    """Two of ``names`` named alike but for a sign ('-' or '+' after no digit) before a number in
    one (l-5.png, l6.png: a signed index, which natural order puts after the unsigned ones, or
    exp+1, exp-1, exp0; a silent mismatch with the light rows, a review), as 'A and B'; None
    where no such pair is (img-01 .. img-10 all alike; 2024-01-05_001 beside 20240106_001)."""
    groups: dict[str, dict[str, str]] = {}
    for n in names:  # a sign: '-' or '+' before a number and after no digit (not 2024-01-05, 0001-2)
        key = re.sub(r"\d+", "#", re.sub(r"(?<!\d)[-+](?=\d)", "", n.lower()))
        sign = re.search(r"(?<!\d)([-+])\d", n)
        seen = groups.setdefault(key, {})
        seen.setdefault(sign.group(1) if sign else "", n)
        if len(seen) > 1:
            a, b = seen.values()
            return f"{a} and {b}"
    return None


def _image_files(entries: list[Path]) -> list[Path]:
    """The image files among a folder's entries (``list(folder.iterdir())``), in natural order.

    The helpers here take the folder's entries rather than the folder: open_capture lists it once,
    not once per question (a listing is a round trip on a network drive)."""
    files = [
        p
        for p in entries
        if p.suffix.lower() in IMAGE_EXTENSIONS  # the name first: is_file() is a stat (a helper: 0.65 s
        and not p.name.startswith(".")            # for 50 subfolders of 2,000 files, most not images)
        and not _NOT_IMAGES.match(p.stem)
        and p.is_file()
    ]
    # the exact name breaks ties (img01 / IMG01, img1 / img01): else their order, and so their light rows,
    # would follow the folder's listing order, which differs between file systems
    return sorted(files, key=lambda p: (natural_key(p.name), p.name))


def holds_capture(path: str | os.PathLike, ignore: Iterable[str] = ()) -> bool:
    """Whether ``path`` holds someone's capture (images other than psctl's outputs, an image list,
    a mask, an ambient image or ground truth): never an output folder, where psctl's files would overwrite its
    inputs or be read as its ground truth. Light files alone do not count (psctl lights writes
    them). ``ignore``: names of files that are psctl's own there (an earlier psctl undistort's)."""
    path = Path(path)
    if not path.is_dir():
        return False
    named = {n.lower() for n in (*LIST_FILES, *MASK_FILES, "Normal_gt.mat", "Normal_gt.png", "Normal_gt.exr",
                                 *AMBIENT_FILES)}
    # any case, as open_capture matches them (_first_existing)
    ignore = set(ignore)
    entries = [p for p in path.iterdir() if p.name not in ignore]
    return any(p.name.lower() in named for p in entries) or bool(_image_files(entries))


def check_not_capture(out_dir: Path, capture: "Capture", names: Iterable[str] = (),
                      default_out: str | None = "PATH/psctl") -> None:
    """Refuse an output folder that is ``capture``'s own folder or holds a capture (``holds_capture``):
    its files are inputs (psctl lights' files would overwrite its light files, psctl normals'
    normal.png would become its ground truth); and one where an output of ``names`` is one of the
    capture's inputs (an image listed by its path in filenames.txt, named like an output).
    ``default_out``: the command's default --out, for the message (None: it has none)."""
    if os.path.realpath(out_dir) == os.path.realpath(capture.path):  # realpath: a link loop is no error here
        raise PsctlError(out_dir, "is the capture folder: its files are inputs and are never overwritten; "
                                  "choose another --out" + (f" (the default is {default_out})" if default_out else ""))
    if holds_capture(out_dir):
        raise PsctlError(out_dir, "holds a capture (images, a mask, an ambient image or ground truth), whose files are inputs; "
                                  "choose another --out")
    # realpath, not Path.resolve: a symbolic-link loop in the way is a path like any other here
    inputs = {os.path.realpath(p) for p in capture.input_paths}
    clash = [n for n in names if os.path.realpath(out_dir / n) in inputs]
    if clash:
        raise PsctlError(out_dir / clash[0], "is an input of this capture; choose another --out")


def _pages_note(infos: list[ImageInfo]) -> str:
    """For a count mismatch: files holding several images (a TIFF stack) count as one."""
    stacks = [f"{i.path.name} holds {i.pages} pages" for i in infos if i.pages > 1]
    return f" ({'; '.join(stacks[:3])}: psctl reads one image per file, its first page)" if stacks else ""


def _found_note(entries: list[Path], paths: list[Path]) -> str:
    """For a count mismatch in a folder without an image list, which is often a stray file taken
    as an image (or one left out): the files not named like most (digits aside), entries named
    like images that are not files (a folder, a broken link), and how to choose the images."""
    import collections

    pattern = [re.sub(r"\d+", "#", p.name.lower()) for p in paths]
    common = collections.Counter(pattern).most_common(1)[0][0]
    odd = [p.name for p, k in zip(paths, pattern) if k != common]
    named = f"; not named like the others: {few(odd)}" if odd else ""
    skipped = sorted(p.name + (" (a broken link)" if p.is_symlink() and not p.exists() else "")
                     for p in entries if p.suffix.lower() in IMAGE_EXTENSIONS and not p.is_file())
    if skipped:
        named += f"; not files, so not read: {few(skipped)}"
    # 003.png.bak, 003.bmp or 003 beside 001.png: named like the images but not read for their
    # extension (helper-170: the count error named none of them)
    stem = common.rsplit(".", 1)[0]
    other = sorted((p.name for p in entries if p.suffix.lower() not in IMAGE_EXTENSIONS and p.is_file()
                    and (re.sub(r"\d+", "#", p.name.lower()) + ".").startswith(stem + ".")), key=natural_key)
    if other:
        named += f"; named like them but not read for their extension: {few(other)}"
    # a capture whose images are named like psctl's outputs or masks (depth_001.png) loses them
    known = {n.lower() for n in (*MASK_FILES, *AMBIENT_FILES, *GT_FILES)}  # read as what they are
    unnamed = sorted((p.name for p in entries if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
                      and p.name.lower() not in known and (p.name.startswith(".") or _NOT_IMAGES.match(p.stem))),
                     key=natural_key)
    if unnamed:
        named += (f"; left out for their names (hidden files, or names psctl gives its outputs): {len(unnamed)}, "
                  f"{few(unnamed)}")
    return f" (every image file in the folder counts{named}; list the images in filenames.txt to choose them)"


def _not_utf8(path: Path) -> str:
    """Why a text file did not decode: the UTF-16 hint only where the file looks like UTF-16 (a
    byte-order mark, or a zero byte in every other place), not for Latin-1 text or binary data."""
    head = path.read_bytes()[:4096]
    odd, even = head[1::2].count(0), head[0::2].count(0)  # ASCII in UTF-16: zeros at one parity only
    utf16 = head[:2] in (b"\xff\xfe", b"\xfe\xff") or (len(head) >= 4 and (
        (odd > len(head) // 4 and even < len(head) // 16) or (even > len(head) // 4 and odd < len(head) // 16)))
    if utf16:
        return "is UTF-16 text (Excel's 'Unicode text'), not UTF-8: save it as UTF-8"
    if b"\0" in head:
        return "is not UTF-8 text (binary data, or UTF-32?)"
    return "is not UTF-8 text (Latin-1 or another 8-bit encoding?): save it as UTF-8"


def _read_utf8(path: Path, what: str) -> str:
    """A text file's contents, or a one-line error naming it: not UTF-8 (``_not_utf8`` says what it
    looks like instead) or not readable (``what`` names it in the message)."""
    try:
        text = path.read_text(encoding="utf-8-sig")  # -sig: Excel's and PowerShell's byte-order mark
        if "\0" in text:  # UTF-16 without a byte-order mark decodes as UTF-8 with a zero after each letter
            raise UnicodeDecodeError("utf-8", b"", 0, 1, "a zero byte")
    except UnicodeDecodeError:
        raise PsctlError(path, _not_utf8(path)) from None
    except OSError as e:
        raise PsctlError(path, f"cannot read {what} ({e})") from None
    return text


def _read_list(path: Path, what: str = "images") -> list[str]:
    text = _read_utf8(path, "file")
    # a line's spaces around the name are layout, unless a file of that very name is there
    # (" 003.png" and "003.png" both present: the one listed, not its neighbour)
    names = [ln if ln != ln.strip() and os.path.lexists(path.parent / ln) else ln.strip()
             for ln in text.splitlines() if ln.strip() and not ln.strip().startswith("#")]
    if os.sep == "/":  # a list written on Windows (imgs\001.png) names imgs/001.png, unless a file has that very name
        names = [n.replace("\\", "/") if "\\" in n and not os.path.lexists(path.parent / n)
                 and os.path.lexists(path.parent / n.replace("\\", "/")) else n for n in names]
    if not names:
        raise PsctlError(path, f"lists no {what}")
    return names


_NUMBER = re.compile(r"[+-]?(?:(?:\d+(?:\.\d*)?|\.\d+)(?:e[+-]?\d+)?|nan|inf(?:inity)?)", re.ASCII | re.IGNORECASE)


def read_matrix(path: Path, widths: tuple[int, ...], what: str, lines: list[int] | None = None) -> np.ndarray:
    """Parse a whitespace/comma separated numeric table; each row has one of ``widths`` values.

    Errors name the file and line: malformed numbers, wrong column counts, NaN/inf. ``lines``,
    when given, receives each row's line number in the file (comments and blank lines skipped).
    """
    text = _read_utf8(path, what)
    rows: list[list[float]] = []
    row_lines: list[int] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        if re.search(r"(^|,)\s*,", line):  # "0.1,,0.2,0.9" read as 3 values would shift the next ones (helper-174)
            raise PsctlError(path, f"line {lineno}: an empty field in {line!r}")
        parts = line.replace(",", " ").split()
        # float() alone would take '1_0' as 10 and full-width digits: plain ASCII decimals only
        # (nan and inf parse, to be refused below with their own message)
        if not all(_NUMBER.fullmatch(v) for v in parts):
            # a spreadsheet's export in a European locale: "0,12;-0,01;0,99" (helper-174)
            why = "" if ";" not in line else " (semicolons are not separators: use spaces, tabs or commas" + (
                "; and psctl reads a point as the decimal mark: 0.1, not 0,1)" if re.search(r"\d,\d", line) else ")")
            raise PsctlError(path, f"line {lineno}: not a number in {line!r}{why}")
        values = [float(v) for v in parts]
        if len(values) not in widths:
            want = " or ".join(str(w) for w in widths)
            # "0,1 0,2 0,9": a decimal comma (a European locale's export), read as a separator
            comma = "." not in line and "," in line and len(line.split()) in widths and \
                all(re.fullmatch(r"[-+]?\d+(,\d+)?", v) for v in line.split())
            raise PsctlError(path, f"line {lineno}: expected {want} values, found {len(values)}" + (
                " (decimal commas? psctl reads a point as the decimal mark: 0.1, not 0,1)" if comma else ""))
        if not np.all(np.isfinite(values)):
            raise PsctlError(path, f"line {lineno}: NaN or infinite value")
        rows.append(values)
        row_lines.append(lineno)
    if not rows:
        raise PsctlError(path, f"{what} file is empty")
    odd = next((k for k, r in enumerate(rows) if len(r) != len(rows[0])), None)
    if odd is not None:
        n = len(rows[odd])
        raise PsctlError(path, f"line {row_lines[odd]}: {n} value{'s' if n != 1 else ''}, but line {row_lines[0]} "
                               f"has {len(rows[0])}: rows have different numbers of values")
    if lines is not None:
        lines.extend(row_lines)
    return np.asarray(rows, dtype=np.float64)


def _where(lines: list[int], row: int) -> str:
    """Row ``row`` (0-based) of a table for a message: its line in the file, and its row (the
    image it belongs to) where comments or blank lines make the two differ."""
    return f"line {lines[row]}" + ("" if lines[row] == row + 1 else f" (row {row + 1})")


def read_lights(path: Path) -> np.ndarray:
    """light_directions.txt -> [N, 3] float32 unit vectors (rows normalised)."""
    return read_light_rows(path)[0]


def read_light_rows(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``read_lights`` and each row's length as written ([N]: a file of directions has 1s)."""
    lines: list[int] = []
    rows = read_matrix(path, (3,), "light directions", lines)
    unit, bad = unit_rows(rows)
    if bad.size:
        raise PsctlError(path, f"{_where(lines, bad[0])}: zero-length light direction (shorter than 1e-6)")
    top = np.abs(rows).max(axis=1)  # (scaled first: rows of 1e300 have a length, their squares none)
    return unit, top * np.linalg.norm(rows / np.where(top > 0, top, 1.0)[:, None], axis=1)


UNIT_TOLERANCE = 0.02  # light rows further from unit length get a note (DiLiGenT's are within 7e-5; unit rows
# rounded to 2 decimals within about 0.009)
INTENSITY_RANGE = (1e-12, 1e12)


def read_intensities(path: Path) -> np.ndarray:
    """light_intensities.txt -> [N, 3] float32 (an N x 1 file is repeated over RGB)."""
    lines: list[int] = []
    e = read_matrix(path, (1, 3), "light intensities", lines)
    bad = np.flatnonzero((e <= 0).any(axis=1))
    if bad.size:
        raise PsctlError(path, f"{_where(lines, bad[0])}: intensities must be positive")
    lo, hi = INTENSITY_RANGE  # images are divided by these in float32: keep the results finite and nonzero
    bad = np.flatnonzero(((e < lo) | (e > hi)).any(axis=1))
    if bad.size:
        v = e[bad[0]][(e[bad[0]] < lo) | (e[bad[0]] > hi)][0]
        raise PsctlError(path, f"{_where(lines, bad[0])}: intensity {v:g} is outside [{lo:g}, {hi:g}]")
    if e.shape[1] == 1:
        e = np.repeat(e, 3, axis=1)
    return e.astype(np.float32)


def _first_existing(folder: Path, entries: list[Path], names: Sequence[str], only: str | None = None) -> Path | None:
    """The first of ``names`` in ``folder``, whatever the case of the file's name (Mask.PNG is the
    mask, Light_Directions.txt the light file). With ``only`` (what they are, for the message),
    two matching files are an error, not a silent choice (mask.png beside mask.tif). ``entries``:
    the folder's (``list(folder.iterdir())``)."""
    by_name: dict[str, list[Path]] = {}
    for p in entries:
        by_name.setdefault(p.name.lower(), []).append(p)
    hits = [p for n in dict.fromkeys(n.lower() for n in names) for p in sorted(by_name.get(n, []))]
    unique: dict[Path, Path] = {}  # Mask.png linked to mask.png is one mask
    for p in hits:
        unique.setdefault(p.resolve() if p.exists() else p, p)
    hits = list(unique.values())
    if only and len(hits) > 1:
        raise PsctlError(folder, f"holds {len(hits)} {only} ({', '.join(p.name for p in hits)}); keep one")
    if hits and not hits[0].is_file():  # a folder named mask.png is a mistake, not "no mask"
        broken = hits[0].is_symlink() and not hits[0].exists()
        raise PsctlError(hits[0], f"is a broken link (to {os.readlink(hits[0])})" if broken else "is not a file")
    return hits[0] if hits else None


# words in the names of files a capture means psctl to read: such a file that psctl does not
# read (light_intensity.txt, mask_obj.png) gets a note, since without it the run goes on silently
_LOOKS_USED = ("mask", "normal", "light", "intensit", "direction", "ambient")


def _unread(entries: list[Path], used: set[Path]) -> tuple[str, ...]:
    known = {n.lower() for n in (*LIST_FILES, LIGHTS_FILE, INTENSITIES_FILE, *MASK_FILES, *GT_FILES, *AMBIENT_FILES)}
    return tuple(sorted(p.name for p in entries if p.is_file() and p not in used
                        and p.name.lower() not in known and any(w in p.name.lower() for w in _LOOKS_USED)))


def is_capture_folder(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder that holds a capture (images, maybe light files)."""
    path = Path(path)
    return path.is_dir() and _is_capture(path, list(path.iterdir()))


def _is_capture(path: Path, entries: list[Path]) -> bool:
    listed = any(p.name.lower() in LIST_FILES and p.is_file() for p in entries)  # any case
    return listed and not (path / "objects.txt").is_file() or bool(_image_files(entries))


def find_objects(root: str | os.PathLike) -> list[Path]:
    """Object folders of a benchmark root: those in objects.txt, else capture subfolders."""
    root = Path(check_path("root", root))
    if not root.is_dir():
        raise PsctlError(root, "not a folder" if root.exists() else "folder does not exist" + quoted_tilde(root))
    listed = root / "objects.txt"
    if listed.is_file():
        names = _read_list(listed, "objects")
        folders = [root / n for n in names]
        for name, f in zip(names, folders):
            if f.is_dir() and f.resolve() == root.resolve():
                raise PsctlError(listed, f"lists {name}, the root itself; list its object folders")
            if not f.is_dir():
                why = ("is a file, not an object folder" if f.exists() else
                       f"is a broken link (to {os.readlink(f)})" if f.is_symlink() else "missing")
                raise PsctlError(f, f"listed in objects.txt but {why}")
        return folders
    folders = sorted((p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")
                      and p.name != "psctl" and is_capture_folder(p)), key=lambda p: (natural_key(p.name), p.name))
    if not folders:
        hint = "; it is one capture folder: psctl normals PATH runs it" if is_capture_folder(root) else ""
        raise PsctlError(root, f"no object folders found (expected subfolders with images, or objects.txt){hint}")
    synth = [f.name for f in folders if (f / "synth.json").is_file()]
    if synth:  # psctl synth writes objects.txt last: without it the set may be part of one
        raise PsctlError(root, f"holds psctl synth objects ({synth[0]}, ...) but no objects.txt, which psctl synth "
                               "writes when a set is complete; run psctl synth again, or list the objects in "
                               "objects.txt")
    return folders


_CAPTURE_FILES = {n.lower() for n in (LIGHTS_FILE, INTENSITIES_FILE, *MASK_FILES, *GT_FILES, *LIST_FILES)}


def _own_capture_files(root: Path, entries: list[Path]) -> list[str]:
    """The light file, intensities, mask and ground truth in a folder itself, by name."""
    return sorted((p.name for p in entries if p.name.lower() in _CAPTURE_FILES and p.is_file()), key=natural_key)


def root_notes(root: str | os.PathLike) -> list[str]:
    """What a benchmark root holds that ``find_objects`` leaves out, in words: the root's own
    images (objects.txt makes it a root) and, without objects.txt, subfolders that hold a light
    file, mask or ground truth but no image (an object whose images did not copy?)."""
    root = Path(root)
    entries = list(root.iterdir())
    notes = []
    listed = (root / "objects.txt").is_file()
    own = _image_files(entries)

    if own:  # (without objects.txt psctl normals, info and lights read them as one capture, and say so)
        notes.append(f"objects: {len(own)} image{'s' if len(own) > 1 else ''} in the root itself ({own[0].name}"
                     f"{', ...' if len(own) > 1 else ''}) not read: " + (
                         "objects.txt makes it a benchmark root of the folders it lists" if listed else
                         "the objects are its capture subfolders (psctl normals on this folder reads these images "
                         "as one capture instead)"))

    def looks_meant(folder: Path) -> bool:  # a capture file, no image
        try:
            inside = list(folder.iterdir())
        except OSError:  # unreadable: find_objects did not take it either; nothing to add here
            return False
        return not _is_capture(folder, inside) and bool(_own_capture_files(folder, inside))

    mine = [] if listed else _own_capture_files(root, entries)
    if mine:  # a capture's files beside subfolders of images: the objects do not read them
        subs = find_objects(root)  # a root without objects.txt has some (else it is no root)
        notes.append(f"objects: {', '.join(mine)} in the root itself not read: an object folder reads only its own "
                     + (f"files (if {subs[0].name} holds this capture's images, list them in filenames.txt as "
                        f"{subs[0].name}/NAME)" if len(subs) == 1 else "files (copy a shared file into each)"))
    if not listed:
        empty = sorted((p.name for p in entries if p.is_dir() and not p.name.startswith(".") and p.name != "psctl"
                        and looks_meant(p)), key=natural_key)
        if empty:
            notes.append(f"objects: skipped {few(empty)}: "
                         f"{'holds' if len(empty) == 1 else 'each holds'} capture files (lights, mask or ground "
                         f"truth) but no image")
    return notes


def is_benchmark_root(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder of capture folders (a benchmark root such as DiLiGenT's)."""
    path = Path(path)
    return path.is_dir() and _is_benchmark_root(path, list(path.iterdir()))


def _is_benchmark_root(path: Path, entries: list[Path]) -> bool:
    if (path / "objects.txt").is_file():
        return True
    return not _is_capture(path, entries) and any(p.is_dir() and is_capture_folder(p) for p in entries)


def open_capture(path: str | os.PathLike, encoding: str = "auto", light_files: bool = True,
                 intensity_file: bool = True) -> Capture:
    """Validate a capture folder without decoding pixels.

    Checks: images exist and share one size, light and intensity rows match the image count and
    are well formed, mask and ground truth (headers) have the image size. ``encoding`` (one of
    ENCODINGS): how the images' values map to radiance, applied when they are read; auto decodes a
    file with an embedded ICC profile through its tone curves (as stored when they are linear),
    else JPEGs from sRGB, and reads every other file as linear. ``light_files`` False: the folder's light
    files are not read (an uncalibrated capture; psctl calibrate, which writes new ones, when
    the old ones are damaged); ``intensity_file`` False: only light_intensities.txt is not read
    (psctl calibrate, when only that one is damaged: its directions are still compared).
    """
    if not isinstance(encoding, str) or encoding.lower() not in ENCODINGS:
        raise PsctlError(None, f"--encoding must be one of {', '.join(ENCODINGS)}, not {encoding!r}")
    encoding = encoding.lower()  # as --method and --device
    light_files, intensity_file = check_bool("light_files", light_files), check_bool("intensity_file", intensity_file)
    path = Path(check_path("path", path))
    if not path.exists():
        raise PsctlError(path, "folder does not exist" + quoted_tilde(path))
    if not path.is_dir():
        raise PsctlError(path, "not a folder (expected a capture folder of images)")
    entries = list(path.iterdir())  # listed once (see _image_files)
    if _is_benchmark_root(path, entries):
        try:
            objects = find_objects(path)
        except PsctlError:
            objects = []
        own = _own_capture_files(path, entries)
        if len(objects) == 1 and own and not _own_capture_files(objects[0], list(objects[0].iterdir())):
            # a capture whose images were put in a subfolder (one with files of its own is an object)
            sub = objects[0].name
            raise PsctlError(path, f"holds {', '.join(own)} but no image; its images seem to be in {sub}/, which "
                                   f"psctl would read as a capture of its own without them: list the images in "
                                   f"{path / LIST_FILES[0]} as {sub}/NAME, one per line, or move them up")
        if len(objects) == 1:
            raise PsctlError(path, f"is a benchmark root with one object folder, not a capture: pass {objects[0]}, or "
                                   f"use `psctl eval`")
        names = few([o.name for o in objects])
        raise PsctlError(path, f"holds {len(objects) or 'several'} object folders (a benchmark root"
                               f"{': ' + names if names else ''}); pass one object folder, or use `psctl eval`")

    list_file = _first_existing(path, entries, LIST_FILES, "image lists")
    if list_file is not None:
        image_paths = _listed_images(path, list_file)
    else:
        image_paths = _image_files(entries)
        if not image_paths:
            raise _no_images(path, entries)

    ambient_path = _first_existing(path, entries, AMBIENT_FILES, "ambient images")  # any case (ambient.JPG)
    if ambient_path is not None and list_file is not None and \
            ambient_path.resolve() in {p.resolve() for p in image_paths}:
        raise PsctlError(ambient_path, f"is the ambient image (subtracted from every image) but is also listed "
                                       f"in {list_file.name} as an input image")
    infos = [image_info(p) for p in image_paths]
    for info in infos:  # (a mask or ground-truth file may hold no colour: alpha alone, X Y Z)
        if info.names and not holds_colour(info.names):
            raise PsctlError(info.path, f"holds no colour channel, only {', '.join(info.names)}: not a photograph "
                                        f"(a depth, alpha or UV pass?)")
    first = infos[0]
    _check_one_size(infos)
    n = len(image_paths)
    found = _pages_note(infos) if list_file is not None else _found_note(entries, image_paths) + _pages_note(infos)

    lights, light_lengths = None, None
    lights_path = _first_existing(path, entries, [LIGHTS_FILE], "light direction files") if light_files else None
    if lights_path is not None:
        lights, lengths = read_light_rows(lights_path)
        if np.abs(lengths - 1).max() > UNIT_TOLERANCE:
            light_lengths = (float(lengths.min()), float(lengths.max()))
        if len(lights) != n:
            raise PsctlError(lights_path, f"{len(lights)} light row{'s' * (len(lights) != 1)} but {n} "
                                          f"image{'s' * (n != 1)}{found}")
        check_lights_face_camera(lights, lights_path)
    intensities = np.ones((n, 3), np.float32)
    intensities_path = _first_existing(path, entries, [INTENSITIES_FILE], "light intensity files") \
        if light_files and intensity_file else None
    given = intensities_path is not None
    if given:
        intensities = read_intensities(intensities_path)
        if len(intensities) != n:
            raise PsctlError(intensities_path, f"{len(intensities)} intensity row{'s' * (len(intensities) != 1)} but "
                                               f"{n} image{'s' * (n != 1)}{found}")

    mask_path = _first_existing(path, entries, MASK_FILES, "masks")
    if mask_path is not None:
        _check_size(image_info(mask_path), first)
    gt_path = _first_existing(path, entries, GT_FILES)
    try:
        if gt_path is not None and gt_path.suffix.lower() != ".mat":
            gt_info = image_info(gt_path)
            _check_size(gt_info, first)
            if gt_info.channels < 3:
                raise PsctlError(gt_path, f"ground truth needs 3 channels (nx, ny, nz), this image has "
                                          f"{gt_info.channels}")
        elif gt_path is not None:
            _check_mat_header(gt_path, first)
    except PsctlError as e:
        raise ground_truth_error(e) from None
    ambient_info = None if ambient_path is None else image_info(ambient_path)
    if ambient_info is not None:
        _check_size(ambient_info, first)
    if list_file is not None:  # a listed mask or ground truth would be read as an image
        _check_listed(image_paths, list_file, mask_path, gt_path)

    return Capture(
        path=path, name=object_name(path), image_paths=tuple(image_paths), height=first.height,
        width=first.width, channels=first.channels, dtype=first.dtype, bits=first.bits,
        lights=lights, intensities=intensities, intensities_given=given, mask_path=mask_path,
        gt_path=gt_path, encoding=encoding, ambient_path=ambient_path, light_lengths=light_lengths,
        infos=tuple(infos), ambient_info=ambient_info, lights_path=lights_path, intensities_path=intensities_path,
        list_path=list_file, sub_captures=_sub_captures(entries, image_paths),
        unread=_unread(entries, {*image_paths, *(p for p in (list_file, lights_path, intensities_path, mask_path,
                                                           gt_path, ambient_path) if p is not None)}),
    )


def _sub_captures(entries: list[Path], image_paths: list[Path]) -> tuple[str, ...]:
    """The names of the subfolders that are capture folders and hold none of ``image_paths``
    (a list's imgs/001.png makes imgs part of this capture, as links to raw/001.png make raw),
    in natural order."""
    used = {os.path.dirname(os.path.realpath(p)) for p in image_paths} | {os.path.realpath(p.parent)
                                                                            for p in image_paths}
    subs = []
    for p in entries:
        if p.name.startswith(".") or p.name == "psctl" or not p.is_dir():
            continue
        real = os.path.realpath(p)
        if any(u == real or u.startswith(real + os.sep) for u in used):
            continue
        with contextlib.suppress(OSError):  # an unreadable subfolder: not one to name
            if is_capture_folder(p):
                subs.append(p.name)
    return tuple(sorted(subs, key=natural_key))


def _link_problem(p: Path) -> str:
    """Why the symbolic link ``p`` is no file to read: broken, a loop, or a link to something else
    (helper-170: a link to /dev/zero and a loop were each "a broken link")."""
    import errno

    from psctl.errors import special_kind

    try:
        mode = os.stat(p).st_mode
    except OSError as e:
        return "is a loop of symbolic links" if e.errno == errno.ELOOP else f"is a broken link (to {os.readlink(p)})"
    return f"is a link to {os.readlink(p)}, which is {special_kind(mode)}, not a regular file"


def _listed_images(path: Path, list_file: Path) -> list[Path]:
    """The images ``list_file`` (filenames.txt) names, in its order, each there as a regular file
    and none the ground truth's .mat (checked before any header is read); else the error naming
    the first that is not."""
    image_paths = [_same_name(path / n) for n in _read_list(list_file)]
    for p in image_paths:
        if p.is_dir():
            raise PsctlError(p, f"listed in {list_file.name} but is a folder, not an image")
        if not p.is_file() and p.is_symlink():  # the entry is there, its target not a file
            raise PsctlError(p, f"listed in {list_file.name} but {_link_problem(p)}")
        if os.path.lexists(p) and not p.is_file():  # a FIFO, a socket, a device: there, but no file
            raise PsctlError(p, f"listed in {list_file.name} but is not a regular file")
        if not p.is_file():
            other = [q.name for q in p.parent.iterdir() if q.name.lower() == p.name.lower()] if p.parent.is_dir() else []
            hint = f" ({other[0]} is there: names in {list_file.name} match exactly)" if other else ""
            raise PsctlError(p, f"listed in {list_file.name} but missing{hint}")
    not_images = {n.lower() for n in GT_FILES if not n.lower().endswith(IMAGE_EXTENSIONS)}
    for p in image_paths:  # Normal_gt.mat is no image to open
        if p.name.lower() in not_images:
            raise PsctlError(p, f"is the ground truth's file name but is listed in {list_file.name} as an "
                                f"input image")
    return image_paths


def missing_lights_hint(folder: str | os.PathLike) -> str:
    """What to add to "light_directions.txt missing" where psctl lights or psctl calibrate wrote
    one into the capture's default output folder, which is never read as an input (a helper
    looked for a hint)."""
    found = Path(folder) / "psctl" / "light_directions.txt"
    try:
        there = found.is_file()
    except OSError:  # a folder psctl cannot search: no hint, and the error it adds to stands
        return ""
    return (f" ({found} is an output of psctl lights or calibrate, never read from there: copy it, and "
            f"light_intensities.txt where there is one, into {folder} to use it)") if there else ""


def _made_from(folder: Path) -> str:
    """What to run on instead of psctl's output ``folder``: the capture (or benchmark root) its
    reports name (read, not guessed from the folder's name: a review's res/psctl was no capture)."""
    from psctl.io.atomic import read_report

    for report, key in (("report.json", "path"), ("lights_report.json", "path"), ("depth_report.json", "path"),
                        ("calibration_report.json", "path"), ("eval.json", "root"), ("compare.json", "root")):
        where = (read_report(folder / report) or {}).get(key)
        if isinstance(where, str) and "\0" not in where:
            return (f"run on the capture folder it was made from, {where}" if key == "path" else
                    f"psctl eval reads the benchmark root it was made from, {where}")
    return "run on the capture folder it was made from"


def _no_images(path: Path, entries: list[Path]) -> PsctlError:
    """The error of a folder without a list in which no file is taken for an image: what it holds
    that could be (taken for a mask or an output by name, another format, camera raw) and what to do."""
    from psctl.io.atomic import commands_listed

    ran = commands_listed(path)
    if ran:  # `psctl info OBJ/psctl`: whose folder it is, not a list to write (a helper's finding)
        return PsctlError(path, f"is an output folder of psctl {' and '.join(ran)}, not a capture (no images); "
                                + _made_from(path))

    def some(names: list[str]) -> str:
        return f"{few(names)} {'is' if len(names) == 1 else 'are'}"

    files = sorted(p.name for p in entries if p.is_file() and not p.name.startswith("."))
    left_out = [n for n in files if n.lower().endswith(IMAGE_EXTENSIONS)]
    # images of other formats (.bmp, .webp): OpenImageIO may read them, once listed
    other = [n for n in files if n.lower().endswith(_OTHER_IMAGE_SUFFIXES)]
    said = ([f"{some(left_out)} taken for a mask, normals or outputs by name"] if left_out else []) + (
        [f"{some(other)} not read unless listed"] if other else [])
    hint = [f"{'; '.join(said)}: list the images in {LIST_FILES[0]}"] if said else []
    raw = [n for n in files if n.lower().endswith(RAW_SUFFIXES)]
    if raw:  # listing them would not help: say how to convert them
        them = "them to 16-bit linear TIFFs" if len(raw) > 1 else "it to a 16-bit linear TIFF"
        hint.append(f"{some(raw)} camera raw, which psctl does not decode: convert {them} first, e.g. "
                    f"`dcraw -4 -T *{Path(raw[0]).suffix}` (docs/formats.md, 'Camera raw files')")
    return PsctlError(path, f"no images found (looked for {', '.join(IMAGE_EXTENSIONS)}){''.join(f'; {h}' for h in hint)}")


def _check_one_size(infos: list[ImageInfo]) -> None:
    """Refuse images of more than one (upright) size, naming the odd one out: the first image of a
    size most images do not have."""
    sizes = [(i.width, i.height) for i in infos]
    if len(set(sizes)) > 1:
        import collections

        (common, count), = collections.Counter(sizes).most_common(1)
        if count == 1:  # no majority: the first image, and the first that differs from it
            common = sizes[0]
        ref = next(i for i in infos if (i.width, i.height) == common)
        odd = next(i for i in infos if (i.width, i.height) != common)
        others = f"the other {count} images'" if count > 1 else f"{ref.path.name}'s"
        raise PsctlError(odd.path, f"size {size_text(odd)} differs from {others} ({size_text(ref)})")


def _check_listed(image_paths: list[Path], list_file: Path, mask_path: Path | None, gt_path: Path | None) -> None:
    """Refuse a list that names an image twice, or names the mask or ground truth (used or not) as
    an image."""
    # one name twice (a copy-paste slip); two names linked to one file are the user's choice
    # (benchmarks/bench_infer.py repeats a capture so), and a set keeps 10,000 names quick
    seen: set[str] = set()
    for p in image_paths:
        key = os.path.normcase(os.path.abspath(p))
        if key in seen:
            raise PsctlError(p, f"listed twice in {list_file.name}")
        seen.add(key)
    listed = {p.resolve() for p in image_paths}
    for kind, p in (("mask", mask_path), ("ground truth", gt_path)):
        if p is not None and p.resolve() in listed:
            raise PsctlError(p, f"is the {kind} but is also listed in {list_file.name} as an input image")
    named = {n.lower() for n in (*MASK_FILES, *GT_FILES)}
    for p in image_paths:  # a second mask or ground-truth file, not the one used, is no image either
        if p.name.lower() in named:
            raise PsctlError(p, f"is named as a mask or ground truth but is listed in {list_file.name} as an input image")


def _no_normal_gt(p: Path, held: "Iterable[str]") -> PsctlError:
    """Normal_gt.mat without that variable: the error, naming the variables it holds (the normals
    may be there under another name)."""
    held = sorted(held)
    return PsctlError(p, "has no variable 'Normal_gt'" + (
        f" (it holds {few(held, 4)}; psctl reads the normals from the one named Normal_gt)" if held else ""))


def _check_mat_header(p: Path, ref: ImageInfo) -> None:
    """Normal_gt.mat's variable list (names and shapes): what load_ground_truth would refuse
    later, said when the folder is opened (psctl info too). psctl's reader of plain files first
    (it decodes the values to know a file whole, and importing scipy.io costs more); scipy, which
    reads only the headers, for the rest. The values' problems (an HDF5 file, an image's codes)
    stop only what reads the ground truth (psctl info notes them: describe_capture)."""
    shapes = variable_shapes(p)
    if shapes is None:
        import scipy.io

        try:
            shapes = {name: tuple(shape) for name, shape, _ in scipy.io.whosmat(str(p))}
        except NotImplementedError:  # MATLAB v7.3 (HDF5): not read here; only methods with ground truth need it
            return
        except Exception as e:  # scipy raises several types for bad/unsupported files
            raise PsctlError(p, f"cannot read .mat file ({' '.join(str(e).split())})") from None
    if "Normal_gt" not in shapes:
        raise _no_normal_gt(p, shapes)
    shape = shapes["Normal_gt"]
    if len(shape) != 3 or shape[2] != 3:
        raise PsctlError(p, f"Normal_gt has shape {shape}, expected H x W x 3")
    if shape[:2] != (ref.height, ref.width):
        raise PsctlError(p, f"size {shape[1]}x{shape[0]} differs from the images ({ref.width}x{ref.height})")


def _mat_ground_truth(p: Path) -> np.ndarray:
    """Normal_gt.mat's ``Normal_gt``, as stored, checked to hold real numbers that are not an
    encoded image's codes. psctl's reader of plain files first, scipy for the rest."""
    raw = load_variable(p, "Normal_gt")  # None: not a plain file (or no such variable): scipy says why
    if raw is None:
        import scipy.io

        try:
            # Normal_gt alone: scipy skips the other variables unread (a huge one would fill the memory)
            mat = scipy.io.loadmat(str(p), variable_names=["Normal_gt"])
        except NotImplementedError:  # scipy's advice (h5py) is for its own users
            raise PsctlError(p, "is a MATLAB 7.3 (HDF5) file, which psctl does not read: save it with "
                                "save(..., '-v7') or as Normal_gt.png (docs/formats.md)") from None
        except Exception as e:  # scipy raises several types for bad/unsupported files
            raise PsctlError(p, f"cannot read .mat file ({' '.join(str(e).split())})") from None
        if "Normal_gt" not in mat:
            held: list[str] = []
            with contextlib.suppress(Exception):  # (its list, for the message: scipy reads the headers alone)
                held = [name for name, *_ in scipy.io.whosmat(str(p))]
            raise _no_normal_gt(p, held)
        raw = np.asarray(mat["Normal_gt"])
    if raw.dtype.kind not in "fiu":  # a string, a cell array (object), a struct or complex numbers
        raise PsctlError(p, f"Normal_gt holds {raw.dtype} values, expected real numbers (H x W x 3 normals)")
    # whole numbers beyond 1: an image's codes ((n + 1) / 2 * 255), not vectors, which would be
    # scored as directions all in one octant (MATLAB stores a double array of -1, 0 and 1 as integers)
    if raw.dtype.kind == "u" and raw.size and int(raw.max()) > 1:
        raise PsctlError(p, f"Normal_gt holds whole numbers {int(raw.min())} .. {int(raw.max())} ({raw.dtype}): "
                            "an encoded image's values? Normal_gt.mat holds unit normals (x, y, z in -1 .. 1), "
                            "Normal_gt.png an encoded image")
    whole = raw.astype(np.int64) if raw.dtype.kind in "iu" and raw.ndim == 3 and raw.shape[-1] == 3 else None
    if whole is not None and whole.size and int(np.abs(whole).max()) <= 1:
        # whole numbers in -1 .. 1 are unit vectors only along an axis (a cube's faces); others, as
        # (1, 1, 0), are no normals: MATLAB logicals (an audit's were scored 35 degrees off, silently).
        # (Scaled ones, as int16 normals times 1000, are directions: normalised as any others)
        square = (whole ** 2).sum(-1)
        odd = int(((square != 0) & (square != 1)).sum())
        if odd:
            raise PsctlError(p, f"Normal_gt holds whole numbers ({raw.dtype}) and {odd} of its pixels are no unit "
                                "vector (as (1, 1, 0)): a logical array or a mask? Normal_gt.mat holds unit normals "
                                "(x, y, z in -1 .. 1)")
    return raw


def _check_size(info: ImageInfo, ref: ImageInfo) -> None:
    if (info.width, info.height) != (ref.width, ref.height):
        raise PsctlError(info.path, f"size {size_text(info)} differs from the images ({size_text(ref)})")


def size_text(info: ImageInfo) -> str:
    """"640x480", or for an image an EXIF orientation turns on its side (the file holds 480x640
    pixels), "640x480 upright (EXIF orientation 6; 480x640 as stored)": a size message that only
    gave the upright size contradicted every other program's view of the file."""
    if info.orientation < 5:  # 1: as stored; 2-4: mirrored or a half turn, the same size
        return f"{info.width}x{info.height}"
    return (f"{info.width}x{info.height} upright (EXIF orientation {info.orientation}; "
            f"{info.height}x{info.width} as stored)")


def as_capture(capture: "Capture | str | os.PathLike") -> Capture:
    """A Capture as it is, or the capture folder at a path opened (``open_capture``)."""
    if isinstance(capture, Capture):
        return capture
    if isinstance(capture, (str, os.PathLike)):
        return open_capture(capture)
    raise PsctlError(None, f"expected a Capture (psctl.io.capture.open_capture) or a folder, not {type(capture).__name__}")


# image formats psctl does not look for by itself, that OpenImageIO may read once listed
_OTHER_IMAGE_SUFFIXES = (".bmp", ".webp", ".gif", ".tga", ".hdr", ".dpx", ".jp2", ".j2k", ".heic", ".heif", ".psd",
                         ".pgm", ".ppm", ".pnm", ".pbm", ".sgi", ".rgb", ".iff", ".dds", ".ico", ".fits", ".cin", ".sxr")


def _same_name(p: Path) -> Path:
    """``p``, or the one file beside it whose name is the same text in another Unicode form: macOS
    stores "café" decomposed (e + combining accent, NFD), an image list typed elsewhere composed
    (NFC), and the two are different bytes on Linux (a QA helper's capture zipped on a Mac)."""
    if os.path.lexists(p) or p.name.isascii() or not p.parent.is_dir():
        return p
    want = unicodedata.normalize("NFC", p.name)
    same = [q for q in p.parent.iterdir() if unicodedata.normalize("NFC", q.name) == want]
    return same[0] if len(same) == 1 else p


def load_mask(capture: Capture | str | os.PathLike) -> np.ndarray:
    """bool [H, W]; the whole image when the folder has no mask. An empty mask is an error."""
    capture = as_capture(capture)
    if capture.mask_path is None:
        return np.ones((capture.height, capture.width), bool)
    pixels, info = read_image(capture.mask_path)
    mask = to_rgb(pixels).max(axis=-1) > 0.5  # any colour channel
    if pixels.shape[-1] in (2, 4):
        alpha = pixels[..., -1] > 0.5
        if alpha.any() and not alpha.all():  # a cut-out (white, the object opaque): transparent is background
            mask &= alpha
    if not mask.any():
        top = float(to_rgb(pixels).max())
        if 0 < top <= 0.5:  # numpy's astype(uint8) of a bool mask: 0 and 1 out of 255, all below the 0.5 cut
            if info.dtype.startswith(("uint", "int")):  # in the file's own numbers, the fix for its depth
                full = 2 ** info.bits - 1
                value = int(round(top * full))
                hint = ("a 0/1 mask? " if value == 1 else "") + f"save the object as {full}" + (
                    " (or the mask as 8-bit 0/255)" if full != 255 else " (0/255)")
                brightest = f"{value} of {full}"
            else:
                brightest, hint = f"{top:.3g}", "save the object as 1.0"
            raise PsctlError(capture.mask_path, f"mask is empty: no pixel is above half of full scale (the "
                                                f"brightest is {brightest}; {hint})")
        raise PsctlError(capture.mask_path, "mask is empty (no foreground pixel" + (
            ": no white pixel is opaque in its alpha channel)" if top > 0.5 else ")"))
    return mask


GT_HINT = "it only scores normals: move it out of the folder to run without it"


def ground_truth_error(e: PsctlError) -> PsctlError:
    """A ground-truth file's problem, with the way on: it stops every command that opens the
    folder, though only the score reads it."""
    return e if e.message.endswith(GT_HINT) else PsctlError(e.path, f"{e.message}; {GT_HINT}")


def check_ground_truth_inside(gt: np.ndarray, mask: np.ndarray, path: Path | None) -> None:
    """PsctlError naming ``path`` where ``gt`` [H, W, 3] has no normal (a vector longer than 0.5)
    on any pixel of ``mask`` [H, W]: nothing to score (psctl normals, before and after its work,
    and psctl info)."""
    if not (mask & (np.linalg.norm(gt, axis=-1) > 0.5)).any():
        raise PsctlError(path, "ground truth has no valid normal inside the mask")


def load_ground_truth(capture: Capture) -> np.ndarray | None:
    """float32 [H, W, 3] unit normals (zero where undefined), or None without ground truth."""
    p = capture.gt_path
    if p is None:
        return None
    if p.suffix.lower() == ".mat":
        raw = _mat_ground_truth(p)
        # float64, not float32: vectors beyond float32's range (1e300) or below it (1e-300) are
        # directions like any others, normalised below
        gt = raw.astype(np.float64)
        gt = np.where(np.isnan(gt).any(axis=-1, keepdims=True), 0.0, gt) if gt.ndim == 3 else gt  # NaN: no normal
        if gt.ndim != 3 or gt.shape[2] != 3:
            raise PsctlError(p, f"Normal_gt has shape {gt.shape}, expected H x W x 3")
        if gt.shape[:2] != (capture.height, capture.width):
            raise PsctlError(p, f"size {gt.shape[1]}x{gt.shape[0]} differs from the images "
                                f"({capture.width}x{capture.height})")
    else:
        from psctl.io.normals import decode_normal_pixels

        pixels, info = read_image(p, allow_nonfinite=True)  # NaN in a float map: no normal
        if info.channels < 3:
            raise PsctlError(p, f"ground truth needs 3 channels (nx, ny, nz), this image has {info.channels}")
        if info.dtype not in ("half", "float", "double") and not np.isfinite(pixels).all():
            raise PsctlError(p, nonfinite_problem(pixels, info))
        gt = decode_normal_pixels(pixels, info)
        gt = np.where(np.isfinite(gt).all(axis=-1, keepdims=True), gt, 0.0)
    if not np.isfinite(gt).all():
        bad = np.argwhere(~np.isfinite(gt))[0]  # NaN, a pixel without ground truth, was made 0 above
        raise PsctlError(p, f"ground truth contains infinite values (first at row {bad[0]}, column {bad[1]}); "
                            f"NaN marks a pixel without ground truth")
    # any length: "no normal" is 0, or shorter than 1e-6 (than 1e-6 of the longest where that is below 1)
    return unit_vectors(gt, 1e-6)[0].astype(np.float32)


def minus_ambient(rgb: np.ndarray, ambient: np.ndarray, capture: Capture, name: str,
                  check: "bool | tuple[slice, slice]" = True) -> np.ndarray:
    """Image ``name`` (linear) less the ambient image, clipped at 0; one that this turns black
    from lit is a user error naming the ambient file (shared by the reader and info --check),
    unless not ``check`` (a part of the image, which may lie in shadow); ``check`` a pair of
    slices: judged on that part of ``rgb`` only."""
    out = np.maximum(rgb - ambient, 0.0)
    seen, left = (rgb, out) if isinstance(check, bool) else (rgb[check], out[check])
    if check is not False and seen.any() and not left.any():
        raise PsctlError(capture.ambient_path, f"subtracting it leaves {name} black: is it brighter than the "
                                               f"images (taken with a light on)?")
    return out


def has_top_code(info: ImageInfo) -> bool:
    """Integer samples end at a code value, read as 1.0: there a pixel may be saturated."""
    return info.dtype.startswith(("uint", "int"))


def saturated_map(rgb: np.ndarray, level: float = 1.0) -> np.ndarray:
    """[..., C] values read from an integer file -> [...] bool: any channel at the top code value
    (or at ``level`` or above: an image's own largest value, ImageCheck.see_ceiling)."""
    top = rgb[..., 0] >= level  # channel by channel: ~7x faster than (rgb >= 1).any(-1)
    for c in range(1, rgb.shape[-1]):
        top |= rgb[..., c] >= level
    return top


def box_within(part: tuple[slice, slice], key: tuple[tuple, tuple]) -> bool:
    """``part`` (rows, columns) lies inside the box a reader kept under ``key`` ((start, stop,
    step) of its rows and of its columns); open-ended slices never do."""
    ends = (part[0].start, part[0].stop, part[1].start, part[1].stop, key[0][0], key[0][1], key[1][0], key[1][1])
    return None not in ends and key[0][0] <= ends[0] <= ends[1] <= key[0][1] and key[1][0] <= ends[2] <= ends[3] <= key[1][1]


def iter_images(capture: Capture | str | os.PathLike, box: tuple[slice, slice] | None = None,
                progress: Progress | None = None,
                clipped: Callable[[int, np.ndarray], None] | None = None,
                decoded: "Prefetch | None" = None, memo: "DecodeMemo | None" = None,
                ambient_check: "bool | tuple[slice, slice]" = True,
                ceiling: Callable[[int, np.ndarray], None] | None = None,
                rows_only: bool = False) -> Iterator[np.ndarray]:
    """Yield each image as float32 [h, w, 3] (cropped to ``box``, a pair of slices such as
    ``bounding_box`` gives), divided by its intensities, and by its light's falloff where the
    capture has ``near`` lights. ``capture``: a Capture or a folder. ``clipped(k, top)``, when
    given, gets each integer image's [h, w] bool map of pixels at the top code value (saturated),
    before anything is subtracted or divided. ``decoded`` (``psctl.io.prefetch.Prefetch``): the
    images as a helper process decoded them, where it has them; the same values as reading here.
    ``memo`` (``DecodeMemo``): images an earlier pass decoded, taken before ``decoded``'s, and
    this pass's decoded images kept in it. ``ambient_check``: an image that subtracting the
    ambient image turns black inside ``box`` is an error (False: a later pass over parts of
    images the first pass checked whole; a pair of slices: inside that part of ``box``, the
    part a caller uses of a larger box read for a later pass). ``ceiling(k, rgb)``, when given, gets each image (any
    sample type) in ``box`` as read, before anything is subtracted or divided (not to be changed:
    ``ImageCheck.see_ceiling``). ``rows_only``: decode only the rows of ``box``
    (``read_image``'s ``rows``), for a later pass over images read whole before (their NaN and
    truncation checked there)."""
    capture = as_capture(capture)
    if progress is not None and not callable(progress):  # a TypeError mid-read otherwise (a review: True)
        raise PsctlError(None, f"progress must be None or a callable advance(k), called with 1 per image, not "
                               f"{progress!r:.40}")
    if box is not None and not (isinstance(box, tuple) and len(box) == 2 and all(isinstance(b, slice) for b in box)):
        raise PsctlError(None, f"box must be (rows, columns), a pair of slices, not {box!r}")
    for part, side, name in zip(box or (), (capture.height, capture.width), ("rows", "columns")):
        ends = (part.start, part.stop)  # (an audit: slice(0.5, 10) raised numpy's TypeError, slice(20, 10) read nothing)
        if any(v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer))) for v in ends) \
                or part.step not in (None, 1):
            raise PsctlError(None, f"box: {name} must be a slice of whole numbers with step 1, not {part!r}")
        if not len(range(*part.indices(side))):
            raise PsctlError(None, f"box: {name} {part!r} holds none of the image's {side} {name}")
    ambient = None
    if capture.ambient_path is not None:  # read once a pass (or from an earlier pass's memo); linear, as the images
        got = None if memo is None or box is None else memo.take(capture.ambient_path, box)
        if got is not None:
            ambient = got[0]
        else:
            stamp = memo.stamp(capture.ambient_path) if memo is not None and box is not None else None
            pixels, info = read_image(capture.ambient_path)
            ambient = to_rgb(pixels)
            ambient = ambient if box is None else ambient[box]
            if stamp is not None:
                memo.keep(capture.ambient_path, box, ambient, info, stamp)
        ambient = capture.to_linear(capture.ambient_path, ambient)
    if capture.near is not None:
        if capture.lights is None:
            raise PsctlError(capture.path / "light_directions.txt", "missing: near lights need the listed directions")
        rows, cols = np.arange(capture.height), np.arange(capture.width)
        if box is not None:
            rows, cols = rows[box[0]], cols[box[1]]
    for k, p in enumerate(capture.image_paths):
        got = None if memo is None or box is None else memo.take(p, box)
        # not from the memo: kept there below, stamped as the file was before it is read
        # (a part decoded for a later pass is not kept: the memo keeps what whole passes read)
        stamp = memo.stamp(p) if memo is not None and box is not None and got is None and not rows_only else None
        if got is None and decoded is not None and box is not None:
            got = decoded.take(p, box)
            if got is not None and stamp is not None:
                stamp = decoded.stamp  # taken before the helper read the file, not after
        if got is not None:
            rgb, info = got  # cut to box in the helper or an earlier pass; the same size checked there
        else:
            band = range(*box[0].indices(capture.height)) if rows_only and box is not None else None
            pixels, info = read_image(p, rows=None if band is None else (band.start, band.stop))
            if (info.width, info.height) != (capture.width, capture.height):  # changed since open
                raise PsctlError(p, f"size {info.width}x{info.height} differs from the other images")
            rgb = to_rgb(pixels)
            if band is not None:
                rgb = rgb[:, box[1]]
            elif box is not None:
                rgb = rgb[box]
        if stamp is not None:
            memo.keep(p, box, rgb, info, stamp)
        if clipped is not None and has_top_code(info):
            clipped(k, saturated_map(rgb))
        if ceiling is not None:
            ceiling(k, rgb)
        rgb = capture.to_linear(k, rgb)
        if ambient is not None:
            rgb = minus_ambient(rgb, ambient, capture, p.name, ambient_check)
        with np.errstate(over="ignore"):  # checked below: a tiny intensity under huge float values
            lit = rgb / capture.intensities[k]
        if not np.isfinite(lit).all() and np.isfinite(rgb).all():  # NaN in the file: the readers' own message
            which = "light intensity" if capture.intensities_given else "estimated light intensity"
            raise PsctlError(p, f"divided by its {which} ({float(capture.intensities[k].min()):.3g}) its values "
                                "pass float32's range; rescale the images" +
                                (" or light_intensities.txt" if capture.intensities_given else ""))
        rgb = lit
        if capture.near is not None:
            rgb *= capture.near.correction(capture.lights[k], rows, cols)[..., None]
        yield np.ascontiguousarray(rgb, dtype=np.float32)
        if progress is not None:
            progress(1)


class DecodeMemo:
    """Images as decoded (``read_image``, ``to_rgb``, cut to a box), kept for later passes over
    the same capture that divide them by other intensities (sdps: the second stage on LCNet's
    lights, the light fit, the second stage on the refined lights), up to ``budget`` bytes.

    ``take(path, box)`` gives (rgb [h, w, 3], ImageInfo) when the kept box of ``path`` holds
    ``box`` (a view into it: the readers never change what they are given) and the file is as it
    was when read (``stamp``: inode, size, modification time), else None. ``keep(path, box, rgb,
    info, stamp)`` keeps a copy of a decoded image, replacing a kept one whose box the new box
    holds, while the budget allows; ``stamp`` is taken before the file is read. ``served``
    counts the images handed back."""

    def __init__(self, budget: int):
        self.budget = int(budget)
        self.used = 0
        self.served = 0
        self.kept: dict[Path, tuple[tuple[int, int, int, int], np.ndarray, ImageInfo, tuple]] = {}

    @staticmethod
    def stamp(path: str | os.PathLike) -> tuple[int, int, int] | None:
        """The file's inode, size and modification time (ns); None when it cannot be read."""
        try:
            st = os.stat(path)
        except OSError:
            return None
        return st.st_ino, st.st_size, st.st_mtime_ns

    @staticmethod
    def _key(box: tuple[slice, slice]) -> tuple[int, int, int, int] | None:
        (r, c) = box
        bounds = (r.start, r.stop, c.start, c.stop)
        if r.step not in (None, 1) or c.step not in (None, 1) or None in bounds or min(bounds) < 0:
            return None  # only boxes with explicit bounds, as bounding_box and the engine's give
        return tuple(int(b) for b in bounds)

    def take(self, path: Path, box: tuple[slice, slice]) -> tuple[np.ndarray, ImageInfo] | None:
        hit, want = self.kept.get(Path(path)), self._key(box)
        if hit is None or want is None:
            return None
        (y0, y1, x0, x1), rgb, info, stamp = hit
        if stamp != self.stamp(path):  # changed since: read again (with the size check)
            del self.kept[Path(path)]
            self.used -= rgb.nbytes
            return None
        if not self._inside(want, (y0, y1, x0, x1)):
            return None
        self.served += 1
        return rgb[want[0] - y0:want[1] - y0, want[2] - x0:want[3] - x0], info

    def holds(self, path: Path, box: tuple[slice, slice]) -> bool:
        """Whether ``take(path, box)`` would find a kept box (the file's stamp is not checked)."""
        hit, want = self.kept.get(Path(path)), self._key(box)
        return hit is not None and want is not None and self._inside(want, hit[0])

    @staticmethod
    def _inside(want: tuple[int, int, int, int], kept: tuple[int, int, int, int]) -> bool:
        """Whether box ``want`` (y0, y1, x0, x1) lies within the kept box ``kept``."""
        y0, y1, x0, x1 = kept
        return y0 <= want[0] <= want[1] <= y1 and x0 <= want[2] <= want[3] <= x1

    def keep(self, path: Path, box: tuple[slice, slice], rgb: np.ndarray, info: ImageInfo,
             stamp: tuple[int, int, int] | None) -> None:
        key, path = self._key(box), Path(path)
        if key is None or stamp is None or rgb.shape[:2] != (key[1] - key[0], key[3] - key[2]):
            return  # a box clipped by the image's edge: its slices do not say where its pixels are
        old = self.kept.get(path)
        if old is not None:
            (y0, y1, x0, x1) = old[0]
            if not (key[0] <= y0 and y1 <= key[1] and key[2] <= x0 and x1 <= key[3]):
                return  # the kept box is not inside this one: keep it
        freed = 0 if old is None else old[1].nbytes
        size = rgb.size * 4  # kept as float32
        if self.used - freed + size > self.budget:
            return
        self.kept[path] = (key, np.array(rgb, np.float32, copy=True), info, stamp)  # a copy: not a view of the whole image
        self.used += size - freed


# A run's note names the images with more of the object saturated than this: highlights of a
# glossy object stay below it (DiLiGenT's objects: at most 0.1 %); psctl info --check lists every
# image above 1 % (psctl.io.summary.SATURATED_SHARE).
CLIPPED_NOTE = 0.10
# Clipped below the top code (12-bit camera codes in a 16-bit file, a float file clipped at 1.0 or
# 0.8): over CLIPPED_NOTE of the object at the image's own largest value is noted as well, where
# the values just below it are finely spaced, CEILING_STEP of it or closer (at least 256 levels:
# not 8-bit data, nor a dim image's few codes). Unclipped images stay far below: at most 0.06 %
# of the object at their largest value on 2,564 unclipped 16-bit syntest images, 0.54 % as half-float
# EXR, 2.7 % with about 300 codes below it, 0.87 % on DiLiGenT's 8-bit crops (helper-182; clipped
# images 30-71 %). The largest value is the box's, as each command reads it: where nothing is
# clipped past the object (a camera clips the whole frame) that is the object's too.
CEILING_STEP = 1 / 256


BRIGHT_OUTLIER = 20  # an image whose mean over the object is over this many times the median image's: noted
DARK_OUTLIER = 20  # and one (not black) whose mean is under the median's over this
# 12-bit codes saved in a 16-bit file read 16 times darker: an unsigned 16-bit image with no value
# above code 4095 (and some above code 255: else 8-bit codes, the darker-image note's case) whose
# mean is under the median's over this, beside images that go above 4095, is noted as such
# (helper-180: every third image so, l2 5.21 -> 7.74 degrees without a word, 16 times being under
# DARK_OUTLIER; DiLiGenT's darkest image is 1.7 times under its median, a syntest dragon's 6.8)
TWELVE_BIT_DARKER = 8
TWELVE_BIT_TOP = 4095.5 / 65535  # (half a code above: the codes as read, float32)
EIGHT_BIT_TOP = 255.5 / 65535  # (none above it: 8-bit codes, 257 times darker, the darker-image note's case)


class ImageCheck:
    """What the readers saw of each image over the object, for notes after a run: images black
    there in every tile and pass (black only if no tile or view saw it lit: a dark tile of a large
    capture may be lit elsewhere), negative values (float files; taken as stored) and images
    with over CLIPPED_NOTE of the object saturated (integer files)."""

    def __init__(self, capture: Capture):
        self.capture = capture
        self.seen: set[int] = set()
        self.lit: set[int] = set()
        self.negative: set[int] = set()
        self.clipped: dict[int, list[int]] = {}  # image -> [object pixels at the top code value, object pixels]
        self.sums: dict[int, list[float]] = {}  # image -> [sum of its values over the object, their count]
        # image -> [its largest value read, object pixels with a channel at it, object pixels,
        # whether a value lies within CEILING_STEP below it]: mergeable over boxes and passes
        self.ceiling: dict[int, list] = {}
        self.stamps: dict[Path, tuple | None] = {}  # image file -> (inode, size, mtime) when first read

    def see_ceiling(self, k: int, rgb: np.ndarray, inside: np.ndarray) -> None:
        """Image ``k``'s values in a box as read (iter_images' ``ceiling``), ``inside`` the
        object's pixels there: its largest value, the object pixels at it and whether any value
        lies just below it, merged with other boxes' (a box whose largest is lower adds only its
        object pixels, and its largest as a value below)."""
        if not rgb.size:
            return
        top = float(rgb.max())
        near = np.count_nonzero(rgb >= top - abs(top) * CEILING_STEP) > np.count_nonzero(rgb == top)
        at = saturated_map(rgb, top)  # (nothing is above top: at it)
        at &= inside
        got, n = int(np.count_nonzero(at)), int(np.count_nonzero(inside))
        c = self.ceiling.get(k)
        if c is None:
            self.ceiling[k] = [top, got, n, near]
        elif top > c[0]:
            self.ceiling[k] = [top, got, c[2] + n, near or c[0] >= top - abs(top) * CEILING_STEP]
        else:
            c[1] += got if top == c[0] else 0
            c[2] += n
            c[3] = c[3] or (near if top == c[0] else top >= c[0] - abs(c[0]) * CEILING_STEP)

    def ceiling_reader(self, mask: np.ndarray, box: tuple[slice, slice] | None, start: int = 0
                       ) -> Callable[[int, np.ndarray], None]:
        """iter_images' ``ceiling`` callback for images read from ``start`` on, cut to ``box``."""
        m = mask if box is None else mask[box]
        return lambda k, rgb: self.see_ceiling(start + k, rgb, m)

    def see_clipped(self, k: int, top: np.ndarray, mask: np.ndarray) -> None:
        """``top``: image ``k``'s saturated-pixel flags (see iter_images), ``mask`` the object's
        pixels among them (the same shape; ``top`` is changed)."""
        c = self.clipped.setdefault(k, [0, 0])
        top &= mask
        c[0] += int(np.count_nonzero(top))
        c[1] += int(np.count_nonzero(mask))

    def clipped_reader(self, mask: np.ndarray, box: tuple[slice, slice] | None, start: int = 0
                       ) -> Callable[[int, np.ndarray], None]:
        """iter_images' ``clipped`` callback for images read from ``start`` on, cut to ``box``."""
        m = mask if box is None else mask[box]
        return lambda k, top: self.see_clipped(start + k, top, m)

    def see(self, k: int, pixels: np.ndarray, divide: np.ndarray | None = None) -> None:
        """``pixels``: image ``k``'s values over the object (any shape; [..., 3] with ``divide``, its
        intensity [3], which the brightness note divides out: summed first, no copy of them)."""
        self.seen.add(k)
        if pixels.size and pixels.max() > 0:  # an image at or below 0 everywhere is as black (noise about 0)
            self.lit.add(k)
        if pixels.size and pixels.min() < 0:
            self.negative.add(k)
        if pixels.size:
            t = self.sums.setdefault(k, [0.0, 0])
            if divide is None:
                t[0] += float(np.sum(pixels, dtype=np.float64))
            else:  # (float64 sums, then divided: values near float32's limit over a small intensity overflow)
                t[0] += float((pixels.reshape(-1, 3).sum(0, dtype=np.float64) / np.asarray(divide, np.float64)).sum())
            t[1] += pixels.size

    def reader(self, capture: Capture, mask: np.ndarray, decoded: "Prefetch | None" = None,
               memo: DecodeMemo | None = None, ambient_check: "bool | tuple[slice, slice]" = True
               ) -> Callable[[int, tuple[slice, slice]], Iterator[np.ndarray]]:
        """The network runners' reader: ``capture``'s images from ``start`` on, cut to ``box``,
        each seen by this check over ``mask`` (``capture`` may be this check's with other
        intensities: the image indices, and so the names in the notes, are the same).
        ``decoded``, ``memo``, ``ambient_check``: as ``iter_images``."""

        boxes: dict[tuple, set[int]] = {}  # this reader's boxes -> the images seen in each

        def same(k: int) -> None:
            # a file rewritten between passes (same size) was read old in some tiles and new in others
            # without a word (helper-186): each read is checked against the file as first read
            path = capture.image_paths[k]
            now = DecodeMemo.stamp(path)
            first = self.stamps.setdefault(path, now)
            if now != first:
                raise PsctlError(path, "changed on disk while psctl read it (between its passes over the images): "
                                       "run again once it is written")

        def read(start: int, box: tuple[slice, slice]) -> Iterator[np.ndarray]:
            # a large capture's later passes (one per tile group) read the same box again: what they
            # would see is seen already (its saturated map, sums and extremes over the object took a
            # third of a pass's work per image at 12 MP, helper-171); per reader, as another reader
            # of this check may read other intensities or another mask (helper-175)
            done = boxes.setdefault(tuple((b.start, b.stop, b.step) for b in box), set())
            again = done.issuperset(range(start, capture.n_images))
            for k, img in enumerate(iter_images(capture.subset(range(start, capture.n_images)), box,
                                                clipped=None if again else self.clipped_reader(mask, box, start),
                                                ceiling=None if again else self.ceiling_reader(mask, box, start),
                                                decoded=decoded, memo=memo, ambient_check=ambient_check),
                                    start):
                same(k)
                if not again:
                    self.see(k, img[mask[box]])
                    done.add(k)
                yield img

        def band(start: int, box: tuple[slice, slice]) -> Iterator[np.ndarray]:
            # part of a box this reader gave whole (every image from start on) in an earlier pass: seen
            # and checked there (ambient included); only the rows of the part are decoded
            for key, done in boxes.items():
                if box_within(box, key) and done.issuperset(range(start, capture.n_images)):
                    for k, img in enumerate(iter_images(capture.subset(range(start, capture.n_images)), box,
                                                        decoded=decoded, memo=memo, ambient_check=False,
                                                        rows_only=True), start):
                        same(k)
                        yield img
                    return
            yield from read(start, box)  # (not inside one: read as any box)

        read.band = band  # what psctl.infer.run_network's later passes call for each tile group's part
        return read

    def notes(self, named_dark: Iterable[int] = ()) -> list[str]:
        """The same words for the same images whatever the reader divided them by (sdps reads a
        capture twice and shows a note once). ``named_dark``: images another note already calls
        darker (psctl info's on mixed sample types), left out of this one's."""
        notes = []
        black = sorted(self.seen - self.lit)  # a light that did not fire looks like a shadow everywhere
        if black:
            names = few([self.capture.image_paths[i].name for i in black])
            notes.append(f"images: {len(black)} of {self.capture.n_images} black over the object ({names}): a light "
                         f"that did not fire? They count as shadow everywhere; leave them out with filenames.txt")
        if self.negative:
            idx = sorted(self.negative)
            names = few([self.capture.image_paths[i].name for i in idx])
            notes.append(f"images: {len(idx)} of {self.capture.n_images} have negative values over the object "
                         f"({names}): taken as stored (noise about a subtracted black level?)")
        # one image far brighter than the rest over the object: another scale (an audit's float TIFF of
        # 0..65535 among 0..1 images: 72 degrees off, under a note on mixed sample types alone)
        level = {k: t[0] / t[1] for k, t in self.sums.items() if t[1]}
        ref = float(np.median(list(level.values()))) if len(level) >= 3 else 0.0
        bright = sorted(k for k, v in level.items() if ref > 0 and v > BRIGHT_OUTLIER * ref)
        if bright:
            worst = max(bright, key=lambda k: level[k])
            most = (f"{level[worst] / ref:.3g} times" if len(bright) == 1 else
                    f"{few([self.capture.image_paths[i].name for i in bright])}; the brightest, "
                    f"{self.capture.image_paths[worst].name}, {level[worst] / ref:.3g} times")
            notes.append(f"images: {len(bright)} of {self.capture.n_images} {'is' if len(bright) == 1 else 'are'} over "
                         f"{BRIGHT_OUTLIER} times as bright over the object as the median image "
                         f"({self.capture.image_paths[worst].name + ', ' if len(bright) == 1 else ''}{most}): on another "
                         f"scale (a float file of 0..65535 values?) or lit far more strongly than the rest? "
                         f"{'It outweighs' if len(bright) == 1 else 'They outweigh'} the others")
        # and one far darker, not black (a light at 80 degrees still lights a sphere a third as much as a
        # frontal one): 8-bit codes in a 16-bit file read 257 times darker, as a light that barely fired
        # or a wrong intensity do (helper-163: one such image of ball's 96 took l2 from 4.49 to 4.91 degrees)
        skip = set(named_dark) | set(black)
        # 16-bit files of 12-bit codes beside full-range ones: said as such, not as a dim light below
        kinds = self.capture.kinds  # (bits, sample type)
        peaks = {k: c[0] for k, c in self.ceiling.items() if kinds[k] == (16, "uint16")}  # (1.0: the top code)
        coded = [k for k, v in peaks.items() if k not in skip and EIGHT_BIT_TOP < v <= TWELVE_BIT_TOP]
        # one far darker names the rest of its kind too: LCNet judges the images as captured, where
        # a bright light's 12-bit image can stay under the threshold (helper-187: lights named 5 of
        # 8, normals all 8)
        twelve = sorted(coded) if any(v > TWELVE_BIT_TOP for v in peaks.values()) and any(
            k in level and 0 < level[k] * TWELVE_BIT_DARKER < ref for k in coded) else []
        if twelve:
            names = few([self.capture.image_paths[i].name for i in twelve])
            one = len(twelve) == 1
            notes.append(f"images: {len(twelve)} of {self.capture.n_images} {'has' if one else 'have'} no value above "
                         f"code 4095 of 65535 ({names}) and {'reads' if one else 'some read'} over {TWELVE_BIT_DARKER} "
                         f"times darker over the object than the median image, which goes above it: 12-bit codes "
                         f"saved in a 16-bit file, which read 16 times darker? Save every image alike (e.g. the codes "
                         f"times 16)")
            skip |= set(twelve)
        dark = sorted(k for k, v in level.items() if ref > 0 and 0 < v * DARK_OUTLIER < ref and k not in skip)
        if dark:
            worst = min(dark, key=lambda k: level[k])
            names = few([self.capture.image_paths[i].name for i in dark])
            one = len(dark) == 1
            notes.append(f"images: {len(dark)} of {self.capture.n_images} {'is' if one else 'are'} over {DARK_OUTLIER} "
                         f"times darker over the object than the median image ({names}"
                         f"{'' if one else '; the darkest, ' + self.capture.image_paths[worst].name}, "
                         f"{ref / level[worst]:.3g} times): a light that barely fired or far dimmer than the rest"
                         f"{' (a wrong row in ' + INTENSITIES_FILE + '?)' if self.capture.intensities_given else ''}, "
                         f"or values of another depth saved in {'it' if one else 'them'} (8-bit codes in a 16-bit file "
                         f"read 257 times darker)? {'It reads' if one else 'They read'} as near shadow everywhere")
        share = {k: c[0] / c[1] for k, c in self.clipped.items() if c[1]}
        over = sorted(k for k, v in share.items() if v > CLIPPED_NOTE)
        if over:
            worst = max(over, key=lambda k: share[k])
            notes.append(f"images: {len(over)} of {self.capture.n_images} have over {CLIPPED_NOTE:.0%} of the object "
                         f"saturated (at the top code value; most: {self.capture.image_paths[worst].name}, "
                         f"{share[worst]:.0%}): brightness is lost there, and the normals with it; a shorter "
                         f"exposure would keep it (psctl info --check lists every image)")
        # and at a value below it (or a float file's): clipped before it was saved
        ints = [has_top_code(i) for i in self.capture.infos]
        low = {k: c[1] / c[2] for k, c in self.ceiling.items()
               if c[2] and c[0] > 0 and c[3] and not (ints[k] and c[0] >= 1.0)}
        below = sorted(k for k, v in low.items() if v > CLIPPED_NOTE)
        if below:
            worst = max(below, key=lambda k: low[k])
            bits, kind = kinds[worst]
            codes = (1 << (bits - kind.startswith("int"))) - 1  # as read_image scales them
            value = (f"code {round(self.ceiling[worst][0] * codes)} of {codes}" if ints[worst] else
                     f"{self.ceiling[worst][0]:.4g}")
            one = len(below) == 1
            notes.append(f"images: {len(below)} of {self.capture.n_images} {'has' if one else 'have'} over "
                         f"{CLIPPED_NOTE:.0%} of the object at {'its' if one else 'their'} largest value"
                         f"{', below the top code' if ints[worst] else ''} ({'' if one else 'most: '}"
                         f"{self.capture.image_paths[worst].name}{':' if one else ','} {low[worst]:.0%} at {value}): "
                         f"clipped before {'it was' if one else 'they were'} saved "
                         f"(a camera's 12-bit codes in a 16-bit file, a float file clipped at 1.0)? Brightness is "
                         f"lost there, and the normals with it")
        return notes


def load_images(capture: Capture | str | os.PathLike, box: tuple[slice, slice] | None = None,
                progress: ProgressFactory | None = None, as_captured: bool = False) -> np.ndarray:
    """All images at once: float32 [N, h, w, 3], divided by their light intensities (as
    ``iter_images``), or with ``as_captured`` not (what ``psctl.estimate_lights`` takes). ``box``:
    a crop, (rows, columns) as two slices (``bounding_box`` of the mask gives one; None: the whole
    frame); ``progress``: None or a factory (label, total) -> advance(k), as every psctl.* function
    takes (``iter_images``, lower down, takes the advance(k) itself). Prefer ``iter_images`` for
    large captures."""
    capture = as_capture(capture)
    if check_bool("as_captured", as_captured):
        capture = replace(capture, intensities=np.ones_like(capture.intensities))
    advance = check_progress(progress)(f"read {capture.name}", capture.n_images)
    out = None
    for k, img in enumerate(iter_images(capture, box, advance)):
        if out is None:
            out = np.empty((capture.n_images, *img.shape), np.float32)
        out[k] = img
    assert out is not None
    return out


READ_NOTES = ("light file:", "files:", "orientation:", "ambient:", "encoding:")  # how capture_notes' notes begin


def capture_notes(capture: Capture) -> list[str]:
    """Notes on how the images are read when it is not as stored (ambient image subtracted,
    sRGB decoded), so that a result never silently depends on it."""
    notes = []
    behind = None if capture.lights is None else lights_behind(
        capture.lights, lambda idx: f"{'row' if len(idx) == 1 else 'rows'} {', '.join(str(i + 1) for i in idx)}")
    if behind:
        notes.append(f"light file: {behind}")
    if capture.light_lengths is not None:
        lo, hi = capture.light_lengths
        notes.append(f"light file: {capture.lights_path.name if capture.lights_path else LIGHTS_FILE}'s rows are not "
                     f"unit vectors (lengths {lo:.4g} to {hi:.4g}): each is normalised, and read as a direction (the lights' "
                     f"strengths go in {INTENSITIES_FILE})")
    signed = None if capture.list_path is not None else _signed_names([p.name for p in capture.image_paths])
    if signed:
        notes.append(f"images: named with numbers that a '-' or '+' precedes in some names and not in others "
                     f"({signed}); without {LIST_FILES[0]} they are in natural order, the sign read as text (l0 .. l6, "
                     f"then l-1 .. l-5): if it is a sign, list the images in {LIST_FILES[0]} in the light file's order")
    if capture.sub_captures:  # psctl eval --root reads this folder otherwise: say which reading this is
        one = len(capture.sub_captures) == 1
        notes.append(f"files: {few(list(capture.sub_captures))} inside "
                     f"{'is a capture folder' if one else 'are capture folders'} of {'its' if one else 'their'} own, "
                     f"not read with it: psctl reads the {capture.n_images} image{'s' * (capture.n_images != 1)} of "
                     f"{capture.name} as this capture (psctl eval --benchmark folder --root on this folder reads the "
                     f"subfolders as objects instead)")
    if capture.unread:
        notes.append(f"files: not read: {', '.join(capture.unread)} (psctl reads {LIGHTS_FILE}, {INTENSITIES_FILE}, "
                     f"mask.png/.tif/.exr, Normal_gt.mat/.png/.exr, ambient.png/...; docs/formats.md)")
    stacks = [(p.name, k) for p, k in zip(capture.image_paths, capture.pages) if k > 1]
    if stacks:  # a TIFF stack of the whole capture in one file would otherwise pass as one image
        named = few([f"{n} holds {k} pages" for n, k in stacks])
        notes.append(f"images: {named}; psctl reads one image per file, its first page")
    layered = [(p.name, layer) for p, layer in zip(capture.image_paths, capture.layers) if layer]
    if layered:  # which of a multilayer EXR's layers is the picture was decided by name: say so
        read = sorted({layer for _, layer in layered})
        notes.append(f"images: {few([n for n, _ in layered])} hold several layers; psctl reads the "
                     f"{' / '.join(read)} layer's colour channels")
    windowed = [p.name for p, w in zip(capture.image_paths, capture.windowed) if w]
    if windowed:
        notes.append(f"images: {few(windowed)} store their pixels in a data window other than their "
                     f"{capture.width}x{capture.height} frame (an EXR cropped or shifted); placed in the frame, 0 outside")
    if capture.turned:
        notes.append(f"orientation: {capture.turned} of {capture.n_images} images turned upright by their EXIF "
                     f"orientation tag, as photo viewers show them (the mask and lights refer to that frame)")
    # one capture's images come from one camera setting: a mix is worth a look (psctl info)
    import collections

    kinds = collections.Counter(capture.sample_kinds)
    if len(kinds) > 1:
        odd = [k for k, _ in kinds.most_common()[1:]]  # the rarer types' files named (a helper's finding)
        names = few([p.name for p, k in zip(capture.image_paths, capture.sample_kinds) if k in odd])
        notes.append(f"images: of mixed sample types ({', '.join(f'{n} {k}' for k, n in kinds.most_common())}: {names} "
                     f"the rarer); each is read with its own full scale as 1 (psctl info --check compares their "
                     f"brightness)")
    channels = collections.Counter(capture.channel_counts)
    if len(channels) > 1:
        counts = ", ".join(f"{n} of {c} channel" + "s" * (c > 1) for c, n in channels.most_common())
        notes.append(f"images: of mixed channel counts ({counts}); grey ones (1 channel, or 2: grey and alpha) are "
                     f"read as RGB")
    if capture.ambient_path is not None:
        how = capture.decoding(capture.ambient_path)
        decoded = "" if how is None else " (decoded from sRGB)" if isinstance(how, str) else \
            f" (decoded through its ICC profile's tone curves: {how.describe()})"
        notes.append(f"ambient: {capture.ambient_path.name}{decoded} subtracted from every image")
        info = capture.ambient_info or image_info(capture.ambient_path)  # (open_capture read its header)
        if info.dtype in ("half", "float", "double"):  # (only floats go below 0)
            amb = read_image(capture.ambient_path, allow_nonfinite=True)[0]
            below = np.isfinite(amb) & (amb < 0)
            if below.any():  # subtracted, a negative ambient adds light (a dark frame's noise about 0?)
                notes.append(f"ambient: {capture.ambient_path.name} is negative in {below.any(-1).mean():.0%} of its "
                             f"pixels (down to {float(amb[below].min()):.3g}): taken as stored, so subtracting it "
                             f"adds light there")
    notes += exposure_notes(capture)
    if capture.encoding == "auto":  # (a JPEG name over other data: read as its content says, and said so)
        misnamed = [p.name for k, p in enumerate(capture.image_paths)
                    if p.suffix.lower() in JPEG and not capture.is_jpeg(k) and capture.decoding(k) is None]
        if capture.ambient_path is not None and capture.ambient_path.suffix.lower() in JPEG and \
                not capture.ambient_jpeg and capture.decoding(capture.ambient_path) is None:
            misnamed.append(capture.ambient_path.name)
        if misnamed:
            notes.append(f"encoding: {few(misnamed)}: named JPEG but "
                         f"not JPEG data, read as linear as their content's format is (--encoding srgb decodes them)")
        linear_jpegs = [p.name for k, p in enumerate(capture.image_paths)
                        if capture.is_jpeg(k) and capture.decoding(k) is None]
        if linear_jpegs:  # JPEGs are otherwise decoded from sRGB: say why these are not
            notes.append(f"encoding: {few(linear_jpegs)}: JPEG with a linear ICC profile, read as stored (--encoding "
                         f"srgb decodes them from sRGB)")
        notes += tag_notes(capture)
    profiled = [k for k in range(capture.n_images) if isinstance(capture.decoding(k), ToneCurve)]
    if profiled:  # a TIFF or PNG exported with a tone curve (Adobe RGB, ProPhoto, sRGB) says so in its profile
        kinds = sorted({capture.decoding(k).describe() for k in profiled})
        which = "all images" if len(profiled) == capture.n_images else \
            f"{len(profiled)} of {capture.n_images} images ({few([capture.image_paths[k].name for k in profiled])})"
        notes.append(f"encoding: {which} decoded to linear through their embedded ICC profile's tone curves "
                     f"({'; '.join(kinds)}) (--encoding linear reads them as stored)")
    n = capture.srgb_images
    if not n:
        return notes
    which = "all images" if n == capture.n_images else f"{n} of {capture.n_images} images"
    if capture.encoding == "srgb":
        return notes + [f"encoding: {which} decoded from sRGB to linear (--encoding srgb)"]
    named = [p.name for k, p in enumerate(capture.image_paths) if capture.is_srgb(k) and p.suffix.lower() not in JPEG]
    if named:  # JPEG data under another name (a renamed file, an export that kept the wrong extension)
        which += f" ({few(named)}: JPEG data, by their content)"
    return notes + [f"encoding: {which} are JPEG, decoded from sRGB to linear as camera JPEGs are encoded "
                    f"(--encoding linear reads them as stored)"]


def _which(capture: Capture, names: list[str]) -> str:
    """"all images", "3 of 12 images (a.png, b.png, c.png)", the ambient image by name, or both
    joined by "and"."""
    images = [n for n in names if capture.ambient_path is None or n != capture.ambient_path.name]
    which = "all images" if len(images) == capture.n_images else \
        f"{len(images)} of {capture.n_images} images ({few(images)})" if images else ""
    return " and ".join(part for part in (which, "" if len(images) == len(names) else capture.ambient_path.name) if part)


def tag_notes(capture: Capture) -> list[str]:
    """Notes (``encoding`` auto) on what the files say of their encoding that psctl does not
    follow: an ICC profile without tone curves psctl can read (read as without one), and a PNG's
    sRGB, gAMA or cICP chunk (read as stored, as linear: OpenImageIO, for one, writes an sRGB
    chunk into every PNG unless told otherwise, and DiLiGenT's PNGs, which are linear, have none)."""
    notes = []
    files = [(p, k) for k, p in enumerate(capture.image_paths)]
    files += [(capture.ambient_path, capture.ambient_path)] if capture.ambient_path is not None else []

    def problem(k):
        return capture.ambient_problem if isinstance(k, Path) else \
            capture.infos[k].profile_problem if capture.infos else ""

    def tag(k):
        return capture.ambient_png_tag if isinstance(k, Path) else capture.infos[k].png_tag if capture.infos else ""

    def verb(names, singular, plural):
        return singular if len(names) == 1 else plural

    unread = [(p.name, problem(k)) for p, k in files if problem(k)]
    if unread:  # read as a file without a profile: JPEG data from sRGB, the rest as stored
        names = [n for n, _ in unread]
        why = "; ".join(sorted({w for _, w in unread}))
        notes.append(f"encoding: {_which(capture, names)} {verb(names, 'embeds', 'embed')} an ICC profile that "
                     f"psctl cannot take tone curves from ({why}): read as a file without one is (JPEG data decoded "
                     f"from sRGB, other data as stored); --encoding linear or --encoding srgb sets how every file is read")
    tagged: dict[str, list[str]] = {}
    for p, k in files:  # a readable profile outranks the chunks (one that cannot be read does not)
        tone = capture.ambient_tone if isinstance(k, Path) else capture.infos[k].tone if capture.infos else None
        misnamed = p.suffix.lower() in JPEG and not capture.is_jpeg(k)  # (its own note says how it is read)
        if tag(k) and tone is None and not misnamed:
            tagged.setdefault("sRGB" if srgb_like(tag(k)) else tag(k), []).append(p.name)
    for t, names in tagged.items():
        which, says = _which(capture, names), verb(names, "says", "say")
        if t == "sRGB":  # (or a gamma near 2.2)
            notes.append(f"encoding: {which} {says} sRGB in PNG chunks but {verb(names, 'is', 'are')} read as stored, "
                         f"as linear (as DiLiGenT's PNGs, which say nothing; OpenImageIO, for one, tags a PNG sRGB "
                         f"unless told otherwise): if {verb(names, 'it', 'they')} came from a camera's JPEGs or an "
                         f"editor, --encoding srgb decodes every file from sRGB; --encoding linear reads every file "
                         f"as stored, without this note")
        else:
            notes.append(f"encoding: {which} {says} {t} in PNG chunks but {verb(names, 'is', 'are')} read as stored, "
                         f"as linear (psctl decodes sRGB, --encoding srgb, and ICC profiles' curves, but no other "
                         f"curve): if so encoded, convert {verb(names, 'it', 'them')} to linear first; --encoding "
                         f"linear reads every file as stored, without this note")
    return notes


# images whose EXIF exposures differ by more than this factor get a note: EXIF's values are the
# nominal ones (1/125 s for 1/128, f/11 for f/11.3: up to about 6 % in time x ISO / N^2), so a
# capture compensated in nominal steps must not get it; a third of a stop is 26 %
EXPOSURE_SPREAD = 1.12


def relative_exposures(capture: Capture) -> np.ndarray | None:
    """Each image's exposure from its EXIF header, time x ISO / f-number^2, over the images'
    median; only the factors that every image's header gives count. None when no factor is given
    by all the images, or for a single image."""
    if not capture.exposures or capture.n_images < 2:
        return None
    e = np.asarray(capture.exposures, np.float64)  # [N, 3]: time, f-number, ISO
    known = (e > 0).all(axis=0)
    if not known.any():
        return None
    t, f, iso = (np.where(known[i], e[:, i], 1.0) for i in range(3))
    rel = t * iso / f ** 2
    return rel / np.median(rel)


def exposure_notes(capture: Capture) -> list[str]:
    """A note when the images' EXIF exposures differ (a bracketed or auto-exposed capture): psctl
    reads each image as stored, so its exposure belongs in its light intensity."""
    rel = relative_exposures(capture)
    if rel is None or rel.max() / rel.min() <= EXPOSURE_SPREAD:
        return []
    e = np.asarray(capture.exposures, np.float64)
    parts = []
    for i, (what, show) in enumerate((("time", lambda v: f"1/{1 / v:.4g} s" if v < 1 else f"{v:.3g} s"),
                                      ("f-number", lambda v: f"f/{v:.3g}"), ("ISO", lambda v: f"{v:.0f}"))):
        col = e[:, i]
        if (col > 0).all() and col.max() > col.min() * 1.001:
            parts.append(f"{what} {show(col.min())} to {show(col.max())}")
    given = (f"each row of {capture.intensities_path.name if capture.intensities_path else INTENSITIES_FILE} "
             f"should include its image's exposure (intensity x exposure)") if capture.intensities_given else \
        (f"without {INTENSITIES_FILE} every light is taken as equally strong, except by sdps and psctl lights, which "
         f"estimate each image's intensity, exposure included")
    lo, hi = int(np.argmin(rel)), int(np.argmax(rel))
    return [f"images: their EXIF exposures differ ({', '.join(parts)}: {capture.image_paths[hi].name} "
            f"{rel[hi] / rel[lo]:.3g} times {capture.image_paths[lo].name}'s); psctl reads each image as stored, "
            f"so its exposure scales its light's intensity: {given} (psctl info --json: relative_exposures)"]


def select_images(n: int, k: int | None, seed: int | None, lights: np.ndarray | None = None) -> np.ndarray:
    """Indices of the images to use, sorted: all, a seeded random ``k``-subset, or ``k`` spread out.

    Without a seed the ``k`` images are spread over the light directions ``lights`` [n, 3] when
    given (``spread_lights``), else a random ``k`` with seed 0. Not the first ``k``, nor ``k``
    evenly through the list: captures list their lights in rig order, DiLiGenT's first 3-6 lights
    are nearly coplanar (condition number 4e4-1e6) and its first 12 all on one side of the rig,
    and every eighth image or so follows its grid (cropped ball, 12 images, PS-FCN: the first
    15.88, evenly spaced 9.17, spread 3.34, random with seed 0 3.36 degrees)."""
    k, seed = check_int("--images", k), check_int("--seed", seed)
    if k is not None and k < 1:
        raise PsctlError(None, f"--images must be at least 1 (got {k})")
    if seed is not None and seed < 0:
        raise PsctlError(None, f"--seed must be 0 or more (got {seed})")
    if k is None or k >= n:
        return np.arange(n)
    if seed is not None:
        return np.sort(np.random.default_rng(seed).choice(n, size=k, replace=False))
    if lights is not None:
        return spread_lights(lights, k)
    return select_images(n, k, 0)


def spread_lights(lights: np.ndarray, k: int) -> np.ndarray:
    """Sorted indices of ``k`` lights [N, 3] spread over their directions: farthest-point
    sampling by angle, from the light nearest their mean direction (deterministic)."""
    d = lights / np.maximum(np.linalg.norm(lights, axis=1, keepdims=True), 1e-12)
    c = d.sum(0)
    first = int(np.argmax(d @ (c / max(float(np.linalg.norm(c)), 1e-12))))
    picked, gap = [first], np.arccos(np.clip(d @ d[first], -1.0, 1.0))
    gap[first] = -np.inf  # never picked twice, even when lights repeat (all gaps 0)
    while len(picked) < min(k, len(d)):
        i = int(np.argmax(gap))
        picked.append(i)
        gap = np.minimum(gap, np.arccos(np.clip(d @ d[i], -1.0, 1.0)))
        gap[picked] = -np.inf
    return np.sort(np.asarray(picked, dtype=np.int64))


def selection_report(seed: int | None, by_lights: bool = False) -> dict:
    """How ``select_images`` chose a subset, for a report beside its ``images_used``: "spread"
    over the light directions (seed null), or "random" with the seed it drew with (0 where none
    was given: null there read as no seed at all)."""
    if seed is None and by_lights:
        return {"selection": "spread", "seed": None}
    return {"selection": "random", "seed": 0 if seed is None else seed}


def selection_notes(n: int, k: int | None, seed: int | None, by_lights: bool = False) -> list[str]:
    """What ``select_images`` did that a user may not expect, for the report's notes."""
    k, seed = check_int("--images", k), check_int("--seed", seed)  # before a note quotes 4.5 images
    if k is not None and k > n:
        return [f"images: --images {k} asks for more than the {n} there are; all {n} used"]
    if seed is not None and k is None:
        return ["images: --seed is unused without --images (all images used)"]
    if k is not None and k < n and seed is None:
        if by_lights:
            return [f"images: {k} of {n}, spread over the light directions (--seed S: a random {k})"]
        return [f"images: {k} of {n}, a random {k} (seed 0; --seed S for another)"]
    return []
