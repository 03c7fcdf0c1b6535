"""Image reading and writing through OpenImageIO, at the file's true bit depth.

Pillow, imageio and skimage.io silently reduce 16-bit RGB PNGs to 8 bits; DiLiGenT is 16-bit,
so everything goes through OpenImageIO. Integer pixels become linear float32 in [0, 1] as
``value / (2**bits - 1)``; float files (EXR, float TIFF) are returned as stored. Photometric
stereo needs pixel values proportional to radiance: ``srgb_to_linear`` undoes the sRGB tone curve
of camera JPEGs, and an embedded ICC profile's curves are read into ``ImageInfo.tone``
(psctl.io.icc; psctl.io.capture decides which images need which).
"""

from __future__ import annotations

import contextlib
import functools
import os
import struct
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psctl.errors import C_STDERR, PsctlError, not_a_file
from psctl.io.atomic import atomic_path, utf8_path
from psctl.io.icc import ToneCurve, read_profile

IMAGE_EXTENSIONS = (".png", ".tif", ".tiff", ".exr", ".jpg", ".jpeg")

# Camera raw files. Most are TIFF inside, and OpenImageIO without its raw plugin reads them as a TIFF:
# the embedded preview (sRGB, often smaller) or the sensor's colour mosaic as a grey picture, never
# the linear colour image photometric stereo needs, so they are refused with how to convert them.
RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".raf", ".orf", ".rw2",
                ".pef", ".srw", ".raw", ".rwl", ".3fr", ".fff", ".iiq", ".erf", ".kdc", ".dcr", ".mrw", ".mos",
                ".x3f", ".mef", ".gpr")
# TIFF photometric interpretations of sensor data (DNG's colour filter array and linear raw)
_RAW_PHOTOMETRIC = {32803: "a colour filter array", 34892: "linear raw"}
_LAB_PHOTOMETRIC = {8: "CIE L*a*b*", 9: "ICC L*a*b*", 10: "ITU L*a*b*"}
JPEG_ICC_MAX = 65519  # bytes of an ICC profile in one JPEG APP2 segment (65533 less its 14-byte header)
RAW_HINT = ("convert it to a 16-bit linear TIFF first, e.g. `dcraw -4 -T {name}` (or a raw converter with a linear "
            "profile, no tone curve and fixed white balance); docs/formats.md, 'Camera raw files'")


def _oiio():
    import OpenImageIO as oiio  # imported here: it is slow to import and only needed for files

    return oiio


@dataclass(frozen=True)
class ImageInfo:
    """What an image header says: size, channels and sample type."""

    path: Path
    width: int
    height: int
    channels: int
    dtype: str  # "uint8", "uint16", "half", "float", ...
    bits: int  # bits per sample (8, 16, 32)
    orientation: int = 1  # the EXIF Orientation tag (1-8); width and height are the upright image's
    pages: int = 1  # subimages in the file (a multi-page TIFF); psctl reads the first
    format: str = ""  # what the file holds, by its content (OpenImageIO's name: png, jpeg, tiff, openexr)
    # the stored channels read, in order (empty: all, as stored), when the file's names say which
    # are the picture: an EXR's R, G, B (and A) before its other channels, or one layer's of several
    pick: tuple[int, ...] = ()
    layer: str = ""  # the layer read ("Combined") when the file holds several named ones
    # (x, y, width, height) of the stored pixels within the frame a viewer shows (the display
    # window: width x height above), when they differ (an EXR's data window); None: the same
    window: tuple[int, int, int, int] | None = None
    color_space: str = ""  # OpenImageIO's oiio:ColorSpace for the file (its tag, or its format's default)
    names: tuple[str, ...] = ()  # the stored channels' names (an EXR's own; OpenImageIO's for other formats)
    # the tone curves of the file's embedded ICC profile (psctl.io.icc), when it has one that psctl can read
    tone: "ToneCurve | None" = None
    # the EXIF exposure: time (s), f-number, ISO; 0 where the header has no such tag
    exposure: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # why the file's embedded ICC profile gives no tone curves (psctl.io.icc.read_profile); "": none, or read
    profile_problem: str = ""
    # what a PNG's colour chunks say its values are: "sRGB", "gamma 2.2" (a gAMA chunk), "" (neither, or linear)
    png_tag: str = ""
    # a TIFF of photometric interpretation WhiteIsZero (0) wider than 8 bits: 0 is white, which
    # OpenImageIO inverts for 1- to 8-bit samples but returns as stored for 16 and 32 (read_image inverts)
    white_is_zero: bool = False


# The picture among several layers of an EXR (Blender's multilayer files: Combined; renderers'
# AOVs: beauty); one layer with colour channels, or the unnamed one, needs no name
MAIN_LAYERS = ("combined", "beauty", "rgba")


# channel names that are no picture: alpha, depth, texture coordinates (other names, as Nuke's "red" or a
# renderer's "LeR", may be colour: read as stored)
NOT_COLOUR = ("A", "ALPHA", "Z", "ZBACK", "DEPTH", "U", "V")


def holds_colour(names: "list[str] | tuple[str, ...]") -> bool:
    """Whether a file's stored channels may be a picture: False where every one is named as
    something else (NOT_COLOUR, in any layer: an EXR of a depth pass, Z; of alpha alone, A)."""
    return not names or any(name.rpartition(".")[2].upper() not in NOT_COLOUR for name in names)


def _cannot_open(path: Path, err: str) -> PsctlError:
    """The error for a file OpenImageIO did not open, in plain words where its own hide the cause
    (helper-170: 'Could not open file' for a file without read permission, 'Not a PNG file' for
    an empty one)."""
    try:
        with open(path, "rb") as f:
            empty = not f.read(1)
    except OSError as e:
        return PsctlError(path, f"cannot open image ({(e.strerror or str(e)).lower()})")
    return PsctlError(path, "is empty (0 bytes), not an image" if empty else f"cannot open image ({_clean(err)})")


# TIFF field types whose values the strip layout uses: SHORT, LONG, LONG8 (BigTIFF) -> struct code, size
_TIFF_INTS = {3: ("H", 2), 4: ("I", 4), 16: ("Q", 8)}


def tiff_layout_problem(path: str | os.PathLike) -> str:
    """What is wrong with where a TIFF's first image keeps its pixels, in a few words ("" when
    nothing is, or the file is no TIFF psctl can parse: OpenImageIO then judges it). libtiff reads
    a strip (or tile) that has no offset from the file's first byte: a StripOffsets tag with fewer
    values than the image has strips (helper-190: 1 for 6) is filled with zeros, and a zero offset
    (GDAL's sparse strips too) reads the TIFF header as pixels, without an error from libtiff or
    OpenImageIO. An offset at or past the file's end is named here too (libtiff's own message is
    "Read error at scanline 4294967295")."""
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            head = f.read(16)
            if len(head) < 8 or head[:2] not in (b"II", b"MM"):
                return ""
            e = "<" if head[:2] == b"II" else ">"
            magic = struct.unpack(e + "H", head[2:4])[0]
            if magic == 42:
                ifd, header, count_fmt, entry_fmt, entry_size = struct.unpack(e + "I", head[4:8])[0], 8, "H", "HHI4s", 12
            elif magic == 43 and len(head) == 16:
                ifd, header, count_fmt, entry_fmt, entry_size = struct.unpack(e + "Q", head[8:16])[0], 16, "Q", "HHQ8s", 20
            else:
                return ""
            f.seek(ifd)
            raw = f.read(struct.calcsize(e + count_fmt))
            if len(raw) < struct.calcsize(e + count_fmt):
                return ""
            n = struct.unpack(e + count_fmt, raw)[0]
            entries = f.read(min(n, 4096) * entry_size)
            tags: dict[int, list[int]] = {}
            seen: set[int] = set()
            for i in range(len(entries) // entry_size):
                tag, kind, count, field = struct.unpack(e + entry_fmt, entries[i * entry_size:(i + 1) * entry_size])
                if tag in seen:  # a repeated tag: libtiff keeps its first entry
                    continue
                seen.add(tag)
                if tag not in (256, 257, 259, 273, 277, 278, 284, 322, 323, 324) or kind not in _TIFF_INTS:
                    continue
                code, width = _TIFF_INTS[kind]
                if count > 1 << 22:  # (a damaged count: left to OpenImageIO)
                    return ""
                if count * width <= len(field):
                    data = field[:count * width]
                else:
                    f.seek(struct.unpack(e + ("I" if len(field) == 4 else "Q"), field)[0])
                    data = f.read(count * width)
                    if len(data) < count * width:
                        return ""
                tags[tag] = list(struct.unpack(f"{e}{count}{code}", data))
    except (OSError, struct.error, ValueError, OverflowError):
        return ""

    def one(tag: int, default: int) -> int:
        return tags[tag][0] if tags.get(tag) else default

    width, height, channels = one(256, 0), one(257, 0), one(277, 1)
    if width <= 0 or height <= 0 or one(259, 1) == 6:  # (old-style JPEG: libtiff finds its data by other tags)
        return ""
    planes = channels if one(284, 1) == 2 else 1
    if 322 in tags:  # tiled (libtiff's test: a TileWidth tag; the offsets in either tag)
        tw, th = one(322, 0), one(323, 0)
        if tw <= 0 or th <= 0:
            return ""
        name, unit, offsets, blocks = "TileOffsets", "tile", tags.get(324) or tags.get(273), \
            -(-width // tw) * -(-height // th) * planes
    else:
        rows = min(one(278, height), height)  # (none: the whole image, one strip)
        if rows <= 0:
            return ""
        name, unit, offsets, blocks = "StripOffsets", "strip", tags.get(273) or tags.get(324), -(-height // rows) * planes
    if not offsets:
        return ""
    if len(offsets) < blocks:
        return (f"its {name} tag lists {len(offsets)} offset{'s' * (len(offsets) != 1)} for {blocks} {unit}s: "
                f"the others would be read from the file's first bytes")
    for k, at in enumerate(offsets[:blocks]):
        if at < header:
            return f"its {unit} {k} has offset {at}, inside the TIFF header: no data stored for it"
        if at >= size:
            return f"its {unit} {k} starts at byte {at:,}, past the file's end ({size:,} bytes): truncated?"
    return ""


def pick_channels(names: list[str] | tuple[str, ...],
                  named: bool = False) -> tuple[tuple[int, ...], str, tuple[str, ...]]:
    """Which stored channels are the picture, by their names: (indices in R, G, B[, A] or Y[, A]
    order; empty: read as stored), the layer's name ("" for unprefixed channels) and the names of
    the layers that hold colour. A layer holds colour when it has R, G and B, or Y alone (with A).
    Raises ValueError when several do and none is the unprefixed one or named as MAIN_LAYERS.
    ``named``: the names are the file's own (EXR), not the reader's defaults (OpenImageIO calls a
    2-channel TIFF's channels R and G): then a layer with two of R, G and B, or Y beside other
    channels than A (luminance and chroma, or X, Y, Z), is a ValueError too, as read as stored
    it would be grey and alpha (helper-170: G and B read as grey G, B dropped, without a word)."""
    layers: dict[str, dict[str, int]] = {}
    for i, name in enumerate(names):
        layer, _, chan = name.rpartition(".")
        layers.setdefault(layer, {}).setdefault(chan.upper(), i)
    colour = {}
    for layer, chans in layers.items():
        if {"R", "G", "B"} <= set(chans):
            colour[layer] = [chans[c] for c in ("R", "G", "B", "A") if c in chans]
        elif set(chans) in ({"Y"}, {"Y", "A"}):
            colour[layer] = [chans[c] for c in ("Y", "A") if c in chans]
    if not colour:
        for layer, chans in layers.items() if named else ():
            where = f"layer {layer!r} has" if layer else "has"
            rgb = [c for c in "RGB" if c in chans]
            if len(rgb) == 2:
                raise ValueError(f"{where} colour channels {' and '.join(rgb)} but not all of R, G and B: psctl "
                                 f"cannot tell the picture's colours; export it as RGB (or grey, one channel Y)")
            if "Y" in chans and set(chans) - {"Y", "A"}:
                raise ValueError(f"{where} channels {', '.join(chans)}: Y with others than A (luminance and "
                                 f"chroma, or X, Y, Z) is not RGB, which psctl reads; export it as RGB")
        return (), "", ()
    found = tuple(colour)
    if "" in colour:
        layer = ""
    elif len(colour) == 1:
        layer = found[0]
    else:
        # by the layer's own name, the last part: Blender writes "ViewLayer.Combined.R"
        main = [name for name in found if name.rpartition(".")[2].lower() in MAIN_LAYERS]
        if len(main) != 1:
            raise ValueError(f"holds {len(found)} layers with colour ({', '.join(found)}) and none named "
                             f"{' or '.join(m.capitalize() for m in MAIN_LAYERS[:2])}: psctl cannot tell which is the "
                             f"picture; export it alone (or as unnamed R, G, B channels)")
        layer = main[0]
    pick = tuple(colour[layer])
    return (() if pick == tuple(range(len(names))) else pick), layer, found


# EXIF orientation -> how to turn the stored pixels [H, W, C] upright, as a photo viewer shows
# them (and as a user draws a mask on them): 2 mirror, 3 half turn, 4 flip, 5 transpose,
# 6 quarter turn clockwise, 7 transverse, 8 quarter turn counterclockwise
_UPRIGHT = {
    2: lambda a: a[:, ::-1],
    3: lambda a: a[::-1, ::-1],
    4: lambda a: a[::-1],
    5: lambda a: a.transpose(1, 0, 2),
    6: lambda a: np.rot90(a, -1),
    7: lambda a: a[::-1, ::-1].transpose(1, 0, 2),
    8: lambda a: np.rot90(a, 1),
}


def upright(pixels: np.ndarray, orientation: int) -> np.ndarray:
    """Stored pixels [H, W, C] turned upright by their EXIF ``orientation`` (1: as stored)."""
    turn = _UPRIGHT.get(int(orientation))
    return pixels if turn is None else np.ascontiguousarray(turn(pixels))


def _oiio_name(path: Path) -> str:
    return utf8_path(path, "the path is not valid UTF-8 text, which OpenImageIO cannot open; rename it")


def image_info(path: str | os.PathLike) -> ImageInfo:
    """Read an image's header only (cheap)."""
    oiio = _oiio()
    path = Path(path)
    if not path.is_file():
        raise PsctlError(path, not_a_file(path, "image file is missing"))
    name = _oiio_name(path)
    if path.suffix.lower() in RAW_SUFFIXES:
        raise PsctlError(path, f"is a camera raw file ({path.suffix}), which psctl does not decode; "
                               f"{RAW_HINT.format(name=path.name)}")
    with _quiet_stderr():  # libpng prints its own line for a garbage file; the error below says it
        inp = oiio.ImageInput.open(name)
        err = _geterror(oiio) if inp is None else ""
    if inp is None:
        raise _cannot_open(path, err)
    try:
        spec = inp.spec()
        sensor = _RAW_PHOTOMETRIC.get(spec.get_int_attribute("tiff:PhotometricInterpretation", 0))
        if sensor is not None:  # a DNG under another name: its pixels are the sensor's, not a picture's
            raise PsctlError(path, f"holds camera raw sensor data ({sensor}, as a DNG), which psctl does not "
                                   f"decode; {RAW_HINT.format(name=path.name)}")
        if spec.get_int_attribute("tiff:subfiletype", 0) == 1:  # NewSubfileType: a reduced-resolution image
            # first: a DNG's or a TIFF-based raw file's preview, with the sensor data further on
            raise PsctlError(path, f"starts with a reduced-resolution preview (TIFF NewSubfileType 1), as a DNG or "
                                   f"a camera raw file does: psctl would read the preview; if it is raw, "
                                   f"{RAW_HINT.format(name=path.name)}")
        dtype = str(spec.format)
        bits = spec.get_int_attribute("oiio:BitsPerSample", 0) or spec.format.size() * 8
        low_bits, png_tag = _png_header(path) if inp.format_name() == "png" else (None, "")
        bits = low_bits or bits  # (1-, 2- and 4-bit grey PNGs come as uint8, with no bit depth)
        photometric = spec.get_int_attribute("tiff:PhotometricInterpretation", -1) \
            if inp.format_name() == "tiff" else -1
        if photometric in _LAB_PHOTOMETRIC:  # OpenImageIO returns L*, a*, b* as R, G, B
            raise PsctlError(path, f"holds {_LAB_PHOTOMETRIC[photometric]} colour (TIFF photometric interpretation "
                                   f"{photometric}), which psctl would read as R, G, B; export it as RGB")
        white_is_zero = photometric == 0 and dtype != "uint8"
        if white_is_zero and not dtype.startswith("uint"):
            raise PsctlError(path, f"is a TIFF of {dtype} samples whose photometric interpretation is WhiteIsZero (0 is white): "
                                   f"psctl cannot tell its black; export it as BlackIsZero (min-is-black)")
        orientation = spec.get_int_attribute("Orientation", 1)
        orientation = orientation if orientation in _UPRIGHT else 1
        try:
            pick, layer, layers = pick_channels(list(spec.channelnames), named=inp.format_name() == "openexr")
        except ValueError as e:
            raise PsctlError(path, str(e)) from None
        # the frame a viewer shows: an EXR may store a smaller (a crop to the lit pixels) or shifted
        # data window within it, which must not shift the pixels against the mask and each other
        fw, fh = (spec.full_width, spec.full_height) if spec.full_width > 0 and spec.full_height > 0 else (
            spec.width, spec.height)
        window = (spec.x - spec.full_x, spec.y - spec.full_y, spec.width, spec.height)
        # a window that fills its frame is the frame, whatever its origin, in every format but EXR:
        # OpenImageIO reads a PNG's oFFs chunk (ImageMagick's crop without +repage) as an origin in
        # a frame at 0, and the images came out shifted by it (a capture-reading audit); a smaller
        # window (a TIFF's, DPX's or RLA's crop) is placed as an EXR's
        full = (spec.width, spec.height) == (fw, fh) and inp.format_name() != "openexr"
        window = None if window == (0, 0, fw, fh) or full else window
        w, h = (fh, fw) if orientation >= 5 else (fw, fh)
        color_space = spec.get_string_attribute("oiio:ColorSpace", "")
        pages = 1
        while pages < 10_000 and inp.seek_subimage(pages, 0):
            pages += 1
        profile = spec.getattribute("ICCProfile")
        read = None if profile is None else read_profile(bytes(np.asarray(profile, np.uint8)))
        tone, problem = (read, "") if not isinstance(read, str) else (None, read)
        exposure = (_tag_number(spec, "ExposureTime", 0.0, 1e5), _tag_number(spec, "FNumber", 0.1, 1000.0),
                    _tag_number(spec, "Exif:PhotographicSensitivity", 0.0, 1e7) or
                    _tag_number(spec, "Exif:ISOSpeedRatings", 0.0, 1e7))
        return ImageInfo(path, w, h, len(pick) or spec.nchannels, dtype, int(bits), orientation, pages,
                         inp.format_name(), pick, layer if len(layers) > 1 else "", window, color_space,
                         tuple(spec.channelnames), tone, exposure, problem,
                         png_tag, white_is_zero)
    finally:
        inp.close()


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# a cICP chunk's transfer characteristics (ITU-T H.273) -> png_colour_tag's words; 8 is linear
_CICP_TRANSFER = {1: "the BT.709 curve", 4: "gamma 2.2", 5: "gamma 2.8", 6: "the BT.709 curve", 13: "sRGB",
                  14: "the BT.709 curve", 15: "the BT.709 curve", 16: "the PQ curve (HDR)", 18: "the HLG curve (HDR)"}


def png_colour_tag(path: str | os.PathLike) -> str:
    """What a PNG file's colour chunks before its pixels say its values are: "sRGB" (an sRGB
    chunk), "gamma G" (a gAMA chunk: G 2.2 for the 0.45455 that programs write for sRGB), a cICP
    chunk's curve ("the PQ curve (HDR)", ...), or "" (none of them, or linear: a gAMA of 1, a
    cICP of 8). cICP outranks sRGB and sRGB gAMA, as the PNG standard (third edition) orders
    them. OpenImageIO's oiio:ColorSpace cannot tell: it says sRGB for a PNG without any of them
    too. (An iCCP chunk is read as the file's ICC profile: psctl.io.icc.)"""
    return _png_header(path)[1]


def _png_header(path: str | os.PathLike) -> tuple[int | None, str]:
    """A PNG's chunks before its pixels, read once: (its bits per sample where under 8, else None;
    ``png_colour_tag``'s tag). OpenImageIO reads 1-, 2- and 4-bit grey as 8-bit samples at full
    range and gives no bit depth; a palette PNG's depth is its index's (its samples are 8-bit)."""
    srgb, gamma, cicp, bits = False, 0.0, -1, None
    try:
        with open(path, "rb") as f:
            if f.read(8) != PNG_SIGNATURE:
                return None, ""
            for _ in range(10_000):  # chunks before the pixels: a few, unless the file is damaged
                head = f.read(8)
                if len(head) < 8:
                    break
                size, kind = struct.unpack(">I4s", head)
                if kind in (b"IDAT", b"IEND"):
                    break
                body = f.read(size) if kind in (b"sRGB", b"gAMA", b"cICP") and size <= 4 or \
                    kind == b"IHDR" and size == 13 else None
                if body is None:
                    f.seek(size, os.SEEK_CUR)
                f.seek(4, os.SEEK_CUR)  # the chunk's CRC
                if kind == b"IHDR" and body is not None and len(body) == 13 and body[9] != 3 and body[8] < 8:
                    bits = body[8]  # (width, height, then bit depth and colour type; 3: a palette)
                srgb |= kind == b"sRGB" and body is not None and len(body) == 1
                if kind == b"gAMA" and body is not None and len(body) == 4:
                    gamma = struct.unpack(">I", body)[0] / 100000.0
                if kind == b"cICP" and body is not None and len(body) == 4:
                    cicp = body[1]
    except OSError:
        return bits, ""
    if cicp >= 0:
        return bits, "" if cicp == 8 else _CICP_TRANSFER.get(cicp, f"transfer characteristics {cicp} (cICP)")
    if srgb:  # sRGB outranks gAMA (writers add a gAMA of 0.45455 beside it)
        return bits, "sRGB"
    if not 0.1 <= gamma <= 10.0 or abs(1.0 / gamma - 1.0) <= 0.01:  # (libpng too ignores one out of range)
        return bits, ""
    return bits, f"gamma {1.0 / gamma:.3g}"


def srgb_like(tag: str) -> bool:
    """Whether a png_colour_tag is sRGB or a gamma near sRGB's 2.2 (--encoding srgb decodes it
    within a few per cent)."""
    return tag == "sRGB" or (tag.startswith("gamma ") and 2.1 <= float(tag.split()[1]) <= 2.3)


def icc_profile(path: str | os.PathLike) -> bytes | None:
    """The ICC profile embedded in an image file (its bytes), or None."""
    oiio = _oiio()
    with _quiet_stderr():
        inp = oiio.ImageInput.open(_oiio_name(Path(path)))
    if inp is None:
        return None
    try:
        profile = inp.spec().getattribute("ICCProfile")
        return None if profile is None else bytes(np.asarray(profile, np.uint8))
    finally:
        inp.close()


# EXIF FocalPlaneResolutionUnit -> millimetres: 2 inch, 3 centimetre (the standard's two); 4
# millimetre and 5 micrometre are written by some cameras
_FOCAL_PLANE_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}
FULL_FRAME_DIAGONAL_MM = float(np.hypot(36.0, 24.0))  # what FocalLengthIn35mmFilm is relative to


def _tag_number(spec, name: str, lo: float = 0.0, hi: float = np.inf) -> float:
    """A header tag as a float in (lo, hi], else 0 (missing, text, out of range)."""
    v = spec.getattribute(name)
    try:
        v = float(v[0] if isinstance(v, (tuple, list)) else v)
    except (TypeError, ValueError, IndexError, OverflowError):
        return 0.0
    return v if np.isfinite(v) and lo < v <= hi else 0.0


def exif_focal(path: str | os.PathLike) -> tuple[float, str]:
    """The camera's focal length in this image's pixels, from its EXIF header, and how it was found.

    Two ways, as cameras write them: ``FocalLength`` (mm) times ``FocalPlaneXResolution`` (pixels
    per inch or cm of the sensor), and ``FocalLengthIn35mmFilm`` over the frame's diagonal (a
    35 mm frame's is 43.27 mm). The first is the more precise but some cameras write a focal
    plane resolution that is not the saved image's (a full-frame Canon's that gives a 23.7 mm
    sensor): where both are there and differ by over 10 %, the 35 mm equivalent is taken, and the
    first is used alone only when it gives a sensor 1-100 mm wide. ``DigitalZoomRatio`` above 1
    multiplies ``FocalLength`` (the lens's, not the crop's). EXIF describes the frame as the camera
    saved it (``PixelXDimension`` x ``PixelYDimension``, else the image's size): an image resized
    since, at the same aspect (or turned by a quarter), has its focal length scaled with it; a
    cropped one (another aspect) raises, since its principal point is no longer the image's
    centre. Raises PsctlError naming the file when the header lacks these.

    EXIF's numbers are rounded (whole millimetres, often) and nominal: expect a few percent;
    docs/calibration.md ("Perspective") measures what 10 % costs.
    """
    oiio = _oiio()
    path = Path(path)
    if not path.is_file():  # (no image_info: the header is read once, below)
        raise PsctlError(path, not_a_file(path, "image file is missing"))
    with _quiet_stderr():
        inp = oiio.ImageInput.open(_oiio_name(path))
    if inp is None:
        raise _cannot_open(path, _geterror(oiio))
    try:
        spec = inp.spec()
        w, h = spec.width, spec.height  # as stored: EXIF's dimensions are too

        number = functools.partial(_tag_number, spec)

        mm, f35 = number("Exif:FocalLength", 0.5, 5000.0), number("Exif:FocalLengthIn35mmFilm", 1.0, 5000.0)
        res, unit_tag = number("Exif:FocalPlaneXResolution"), int(number("Exif:FocalPlaneResolutionUnit", 0, 9))
        zoom = max(1.0, number("Exif:DigitalZoomRatio", 0.0, 100.0))
        w0, h0 = number("Exif:PixelXDimension", 0, 1e6), number("Exif:PixelYDimension", 0, 1e6)
    finally:
        inp.close()
    w0, h0 = (w0, h0) if w0 and h0 else (float(w), float(h))
    unit = _FOCAL_PLANE_UNIT_MM.get(unit_tag or 2)  # the standard's default unit is the inch
    plane = diag = None  # (focal in pixels of the saved frame, how)
    if mm and res and unit and 1.0 <= w0 * unit / res <= 100.0:
        px_per_mm = res / unit
        plane = (mm * zoom * px_per_mm, f"{mm:g} mm{f' x {zoom:g} digital zoom' if zoom > 1 else ''} on a sensor "
                                        f"{w0 / px_per_mm:.4g} mm wide")
    if f35:
        diag = (f35 * float(np.hypot(w0, h0)) / FULL_FRAME_DIAGONAL_MM, f"{f35:g} mm 35 mm-equivalent")
    if plane and diag and abs(plane[0] / diag[0] - 1) > 0.1:
        f, how = diag[0], (f"{diag[1]} (FocalLength over its FocalPlaneXResolution gives "
                                 f"{plane[0] / diag[0]:.3g} times that: not used)")
    elif plane or diag:
        f, how = plane or diag  # type: ignore[misc]
    elif mm and res and not unit:
        raise PsctlError(path, f"its EXIF FocalPlaneResolutionUnit ({unit_tag}) is neither inch nor cm, and it has no "
                               "FocalLengthIn35mmFilm; give --focal F in pixels")
    else:
        raise PsctlError(path, "its EXIF header has no focal length (FocalLength with FocalPlaneXResolution, or "
                               "FocalLengthIn35mmFilm); give --focal F in pixels")
    if abs((h / w) / (h0 / w0) - 1) > 0.01 and abs((h / w) / (w0 / h0) - 1) <= 0.01:
        w0, h0 = h0, w0  # the pixels were turned a quarter since, and the tags left as they were
    scale = w / w0
    if abs(h / h0 - scale) > 0.01 * scale:
        raise PsctlError(path, f"its EXIF says the camera saved {w0:.0f} x {h0:.0f} pixels, but it has {w} x {h}: "
                               f"cropped, so the lens' centre in it is unknown; if it was not resized too, give "
                               f"--focal {f:.0f} (the EXIF's, in pixels) and --principal X,Y")
    if scale != 1.0:
        how += f", scaled by {scale:.4g} from the {w0:.0f} x {h0:.0f} pixels saved"
    f *= scale
    if not 1.0 <= f <= 1e7:
        raise PsctlError(path, f"its EXIF gives a focal length of {f:.4g} pixels ({how}), which cannot be right; "
                               "give --focal F in pixels")
    return float(f), how


def read_image(path: str | os.PathLike, allow_nonfinite: bool = False,
               rows: tuple[int, int] | None = None) -> tuple[np.ndarray, ImageInfo]:
    """Read an image as float32 [H, W, C] plus its header info.

    An image with an EXIF Orientation tag (phone and camera JPEGs) is turned upright, as photo
    viewers show it: a mask drawn on it and the light directions refer to that frame. Integer images are scaled to [0, 1] by the maximum of their true bit depth, so a 16-bit
    PNG is divided by 65535 and an 8-bit one by 255. Corrupt or truncated files raise
    PsctlError naming the file, as do NaN/inf pixels unless ``allow_nonfinite`` (normal maps,
    where NaN marks "no normal" and the caller counts such pixels).

    ``rows`` (y0, y1): only those rows of the upright image, [y1 - y0, W, C], and only they are
    checked for NaN. A file of scanlines stored upright (no EXIF turn, no data window) is
    decoded down to row y1 only (a PNG's decoder still goes through the rows above, but stops
    there; the float conversion is the rows' alone); any other file is read whole and cut. For a
    later pass over an image read whole before (psctl.infer: a large capture's tile groups):
    a truncated file may decode without error above its cut.
    """
    oiio = _oiio()
    path = Path(path)
    info = image_info(path)
    problem = tiff_layout_problem(path) if info.format == "tiff" else ""
    if problem:  # read without an error, as the file's first bytes (helper-190)
        raise PsctlError(path, f"corrupt image ({problem})")
    # Without this hint OpenImageIO multiplies a PNG's or TIFF's colour by its alpha as it reads;
    # psctl ignores alpha (docs/formats.md): a photo's pixels are what they are.
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    with _quiet_stderr():
        inp = oiio.ImageInput.open(_oiio_name(path), config)
        if inp is None:
            raise _cannot_open(path, _geterror(oiio))
        try:
            # OpenImageIO converts integer samples to float by dividing by the type's maximum.
            spec = inp.spec()
            stored_channels = spec.nchannels
            band = rows is not None and info.orientation == 1 and info.window is None and spec.tile_width == 0 \
                and not spec.deep and spec.depth <= 1 and spec.height == info.height and 0 <= rows[0] < rows[1] <= spec.height
            if band:  # (y: the file's origin, as a PNG's oFFs chunk sets it; read as at 0, as read_image does)
                pixels = inp.read_scanlines(0, 0, spec.y + rows[0], spec.y + rows[1], spec.z, 0, stored_channels, "float")
            else:
                pixels = inp.read_image(0, 0, 0, stored_channels, "float")
            err = _geterror(inp)
        finally:
            inp.close()
    if pixels is None or err:
        # (libjpeg's message quotes the path the error already starts with)
        why = _clean(err).replace(f' ("{_oiio_name(path)}")', "")
        raise PsctlError(path, f"corrupt or truncated image ({why or 'the decoder gave no reason'})")
    frame = (info.width, info.height) if info.orientation >= 5 else (info.height, info.width)
    if band:
        pixels = np.asarray(pixels, dtype=np.float32).reshape(rows[1] - rows[0], frame[1], stored_channels)
    elif info.window is None:
        pixels = np.asarray(pixels, dtype=np.float32).reshape(*frame, stored_channels)
    else:  # the data window placed in the frame; outside it, 0 (as EXR viewers show it)
        x, y, w, h = info.window
        data = np.asarray(pixels, dtype=np.float32).reshape(h, w, stored_channels)
        pixels = np.zeros((*frame, stored_channels), np.float32)
        y0, x0, y1, x1 = max(y, 0), max(x, 0), min(y + h, frame[0]), min(x + w, frame[1])
        if y1 > y0 and x1 > x0:
            pixels[y0:y1, x0:x1] = data[y0 - y:y1 - y, x0 - x:x1 - x]
    if info.pick:
        pixels = pixels[..., list(info.pick)]
    if info.white_is_zero:  # grey (and alpha, not inverted): as OpenImageIO reads 8-bit WhiteIsZero
        if (info.dtype, info.bits) == ("uint16", 16):  # the codes inverted, then scaled as OpenImageIO
            # scales them (code x float32(1/65535)): bit for bit the black-is-zero twin (1 - value was 3e-8 off)
            codes = np.rint(pixels[..., 0] * np.float32(65535))
            pixels[..., 0] = (np.float32(65535) - codes) * np.float32(1 / 65535)
        else:
            pixels[..., 0] = 1.0 - pixels[..., 0]
    pixels = upright(np.ascontiguousarray(pixels), info.orientation)
    if rows is not None and not band:
        pixels = pixels[rows[0]:rows[1]]
    # Files with fewer bits than their container (12-bit TIFF in uint16) need nothing more:
    # OpenImageIO already rescales them to the container's full range.
    if not allow_nonfinite and not np.isfinite(pixels).all():
        raise PsctlError(path, nonfinite_problem(pixels, info))
    return pixels, info


def nonfinite_problem(pixels: np.ndarray, info: ImageInfo) -> str:
    """The error for an image [H, W, C] (as read_image returns it: channels picked, upright) with
    NaN or infinite values: what, how many, in which channels, the first one's place (row 0 the
    top), so that the user can find them (a NaN in an alpha channel, which psctl otherwise ignores,
    or a half-float EXR's highlight over 65504 stored as infinite, look like nothing in a viewer)."""
    bad = ~np.isfinite(pixels)
    stored = [info.names[i] for i in info.pick] if info.pick and len(info.names) > max(info.pick) else list(info.names)
    names = stored if len(stored) == pixels.shape[-1] else [str(c) for c in range(pixels.shape[-1])]
    kinds = [w for w, m in (("NaN", np.isnan(pixels)), ("+inf", np.isposinf(pixels)), ("-inf", np.isneginf(pixels)))
             if m.any()]
    chans = [names[c] for c in range(pixels.shape[-1]) if bad[..., c].any()]
    y, x = (int(v) for v in np.argwhere(bad.any(axis=-1))[0])
    n = int(bad.any(axis=-1).sum())
    alpha_only = all(c.rpartition(".")[2].upper() in ("A", "ALPHA") for c in chans)
    hint = ""
    if alpha_only:
        hint = "; only in its alpha channel, which psctl does not read as colour: fill it, or save the image without it"
    elif info.dtype == "half" and "+inf" in kinds:
        hint = "; a half-float file holds at most 65504: brighter values become infinite (save as 32-bit float)"
    return (f"image contains {' and '.join(kinds)} values: {n} pixel{'s' * (n != 1)} (channel"
            f"{'s' * (len(chans) != 1)} {', '.join(chans)}; first at row {y}, column {x}){hint}")


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """The sRGB decoding curve (IEC 61966-2-1), element-wise: an sRGB-encoded value in [0, 1]
    (a camera JPEG's pixel / 255) -> linear radiance in [0, 1]. Values above 1 follow the power
    segment and negative ones the linear segment, so float data stays finite and monotonic."""
    v = np.asarray(values, dtype=np.float32)
    return np.where(v <= 0.04045, v / 12.92, ((np.maximum(v, 0.04045) + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(values: np.ndarray) -> np.ndarray:
    """The sRGB encoding curve, inverse of ``srgb_to_linear`` on [0, 1]; values are clipped to
    [0, 1] first (for pictures)."""
    v = np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0)
    return np.where(v <= 0.0031308, v * 12.92, 1.055 * v ** (1 / 2.4) - 0.055)


def to_rgb(pixels: np.ndarray) -> np.ndarray:
    """[H, W, C] -> [H, W, 3]: grey is repeated, alpha and extra channels are dropped."""
    c = pixels.shape[-1]
    if c == 1 or c == 2:
        return np.repeat(pixels[..., :1], 3, axis=-1)
    return pixels[..., :3]


# What a PNG says its values are (OpenImageIO's colour-space names). Left to itself OpenImageIO
# tags every PNG sRGB (sRGB, gAMA and cHRM chunks), and a colour-managed reader would then bend a
# normal map's or depth map's numbers through the sRGB curve.
COLOR_TAGS = {"picture": None, "data": "Raw", "linear": "lin_rec709"}


def write_image(path: str | os.PathLike, pixels: np.ndarray, dtype: str = "uint16", kind: str = "picture",
                icc: bytes | None = None, png_tag: str = "") -> None:
    """Write [H, W] or [H, W, C] float pixels atomically.

    ``dtype`` is "uint8", "uint16" (values in [0, 1], rounded in float64) or "float"/"half"
    (stored as is). The format follows the file extension (png, tif, exr, ...). ``kind``: a
    "picture" for display (PNGs tagged sRGB), "data" (numbers: normal and depth maps, masks; no
    colour tag) or "linear" (radiance, as DiLiGenT's images: tagged linear). ``icc``: an ICC
    profile to embed (``icc_profile`` of the file the pixels came from; TIFF, PNG and JPEG keep it).
    ``png_tag``: a PNG's colour chunk as ``png_colour_tag`` gives it ("sRGB" or "gamma G"; a
    cICP curve is not written), instead of ``kind``'s (``psctl undistort``'s copies keep their own).
    """
    oiio = _oiio()
    path = Path(path)
    arr = np.asarray(pixels)
    if arr.ndim == 2:
        arr = arr[..., None]
    h, w, c = arr.shape
    if dtype in ("uint8", "uint16"):
        peak = 255 if dtype == "uint8" else 65535
        arr = np.round(np.clip(arr.astype(np.float64), 0.0, 1.0) * peak).astype(np.uint8 if dtype == "uint8" else np.uint16)
        fmt = oiio.UINT8 if dtype == "uint8" else oiio.UINT16
    elif dtype == "half":
        arr = arr.astype(np.float16)
        fmt = oiio.HALF
    else:
        arr = arr.astype(np.float32)
        fmt = oiio.FLOAT
    if kind not in COLOR_TAGS:
        raise ValueError(f"kind must be one of {', '.join(COLOR_TAGS)}, not {kind!r}")
    spec = oiio.ImageSpec(w, h, c, fmt)
    if png_tag.startswith("gamma ") and path.suffix.lower() == ".png":  # a gAMA chunk of 1 / G
        spec.attribute("oiio:ColorSpace", "GammaCorrected")
        spec.attribute("oiio:Gamma", float(png_tag.split()[1]))
    elif png_tag == "sRGB" and path.suffix.lower() == ".png":
        spec.attribute("oiio:ColorSpace", "srgb_rec709_scene")
    elif COLOR_TAGS[kind] is not None:
        spec.attribute("oiio:ColorSpace", COLOR_TAGS[kind])
    if icc and path.suffix.lower() in (".jpg", ".jpeg") and len(icc) > JPEG_ICC_MAX:
        # a JPEG holds a larger profile in several APP2 segments, which OpenImageIO 3.2 writes
        # damaged (a review: the copy's curve then read wrong or not at all)
        raise PsctlError(path, f"cannot keep its ICC profile ({len(icc):,} bytes; over {JPEG_ICC_MAX:,} bytes "
                               f"does not fit one JPEG segment, which is all psctl writes correctly)")
    if icc:
        spec.attribute("ICCProfile", oiio.TypeDesc(f"uint8[{len(icc)}]"), np.frombuffer(bytes(icc), np.uint8))
    if c in (2, 4):  # colour as given, not divided by alpha as PNG's writer would (read_image reads it so)
        spec.attribute("oiio:UnassociatedAlpha", 1)
    if path.suffix.lower() in (".jpg", ".jpeg"):  # psctl undistort's copies: as little loss as JPEG allows
        spec.attribute("Compression", "jpeg:100")
        spec.attribute("jpeg:subsampling", "4:4:4")
    if path.suffix.lower() == ".png":  # zlib level 4, not OpenImageIO's 6: a 16-bit photo (psctl undistort's,
        spec.attribute("png:compressionLevel", 4)  # synth's) writes 2.8x faster, 6 % larger; maps alike
    if path.suffix.lower() == ".exr":
        spec.attribute("compression", "zip")
        spec.attribute("DateTime", "")  # no write time in the header: the same run gives the same bytes
    _oiio_name(path)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise PsctlError(path, f"cannot write image ({_clean(_geterror(oiio))})")
        try:
            ok = out.open(str(tmp), spec) and out.write_image(np.ascontiguousarray(arr))
            err = _geterror(out)
            ok = out.close() and ok
        except BaseException:  # Ctrl-C mid-write: the writer, closed half-way, complains on fd 2
            with _quiet_stderr():  # (libpng: "No IDATs written into file") beside the one line
                out.close()
                out = None  # freed here, inside the silence
            raise
        # the first of the writer's messages (a PNG's repeats per block), named by the output
        err = _clean((err or _geterror(out)).replace(str(tmp), str(path))).split("; ")[0]
        if not ok or err.startswith("Write error"):  # libpng's: a file that lost only its end reads back
            raise PsctlError(path, f"cannot write image ({err or 'the writer gave no reason'}{_no_room(tmp, arr)})")
        # with ok, a message may be a failed write() (PNG) or harmless (TIFF's Exif block): the
        # read-back decides
        _check_written(tmp, path, arr.shape, err)


def _no_room(tmp: Path, arr: np.ndarray) -> str:
    """"; a full disk or a quota?" when the folder has less room left than the pixels take: the
    EXR writer's own message on a full disk is only "File output failed"."""
    import shutil

    try:
        free = shutil.disk_usage(tmp.parent).free
    except OSError:
        return ""
    return "; a full disk or a quota?" if free < arr.nbytes + (1 << 20) else ""


def _check_written(tmp: Path, path: Path, shape: tuple[int, ...], writer_error: str = "") -> None:
    """Read every pixel of a just-written image back (in strips). On a full disk or over a quota OpenImageIO's
    writers can report success and leave a truncated file; a normal map that cannot be read back
    must fail here, before it is renamed into place, not in the next command that reads it."""
    oiio = _oiio()
    got, err = 0, ""
    with _quiet_stderr():
        inp = oiio.ImageInput.open(str(tmp))
        if inp is None:
            err = _geterror(oiio)
        else:
            spec = inp.spec()
            if spec.tile_width:  # psctl writes scanline files; a tiled one is read whole
                back = inp.read_image(oiio.UNKNOWN)
                got = 0 if back is None else np.asarray(back).size
            else:  # in strips: memory stays small for a 12 MP map
                for y in range(spec.y, spec.y + spec.height, 256):
                    strip = inp.read_scanlines(y, min(y + 256, spec.y + spec.height), 0, 0, spec.nchannels,
                                               oiio.UNKNOWN)
                    if strip is None:
                        break
                    got += np.asarray(strip).size
            err = _geterror(inp)
            inp.close()
    if err or got != int(np.prod(shape)):
        size = tmp.stat().st_size if tmp.exists() else 0
        raise PsctlError(path, f"written incompletely ({size} bytes; a full disk or a quota?)"
                               + (f": {writer_error or _clean(err)}" if writer_error or err else ""))


_QUIET: dict = {"lock": threading.Lock(), "depth": 0, "saved": None, "fd": None}  # the readers inside, fd 2 as it was


def _quiet_after_fork() -> None:
    """A child forked while a thread of its parent was reading: that thread is not in the child,
    so put its fd 2 back now (it would stay on /dev/null) and take a fresh lock."""
    if _QUIET["depth"]:
        with contextlib.suppress(OSError):
            os.dup2(_QUIET["saved"], _QUIET["fd"])
            os.close(_QUIET["saved"])
    _QUIET.update(lock=threading.Lock(), depth=0, saved=None, fd=None)


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_quiet_after_fork)


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Swallow what C libraries print on file descriptor 2 (libpng prints "libpng error: ..."
    for truncated files even though OpenImageIO also reports it) where the command line runs
    (``psctl.errors.C_STDERR``): it promises one line. Readers in several threads share one
    redirection: the first in saves fd 2, the last out puts it back (each saving its own, one
    could save the other's /dev/null and leave it there for good)."""
    if not C_STDERR["silence"]:
        yield
        return
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        yield
        return
    with _QUIET["lock"]:
        if _QUIET["depth"] == 0:
            sys.stderr.flush()
            _QUIET["saved"], _QUIET["fd"] = os.dup(fd), fd
            sink = os.open(os.devnull, os.O_WRONLY)  # not a temporary file: /tmp may be full (or missing)
            os.dup2(sink, fd)
            os.close(sink)
        _QUIET["depth"] += 1
    try:
        yield
    finally:
        with _QUIET["lock"]:
            _QUIET["depth"] -= 1
            if _QUIET["depth"] == 0:
                os.dup2(_QUIET["saved"], _QUIET["fd"])
                os.close(_QUIET["saved"])
                _QUIET["saved"] = None


def _geterror(source) -> str:
    """``source.geterror()`` (OpenImageIO's module, an ImageInput or an ImageOutput), whatever bytes
    it holds: a damaged EXR's message quotes the file's raw bytes, which the binding decodes as
    strict UTF-8 (a UnicodeDecodeError and a traceback instead of the file's one line; 157 of 1500
    fuzzed EXR headers, a capture-reading audit)."""
    try:
        return source.geterror()
    except UnicodeDecodeError as e:
        return e.object.decode("utf-8", "replace") if isinstance(e.object, bytes) else str(e)


def _clean(msg: str | None) -> str:
    """OpenImageIO errors can span lines, and repeat themselves (a reader's message, then its
    library's with the same words inside); the CLI promises one line."""
    lines = [" ".join(ln.split()) for ln in (msg or "").splitlines() if ln.strip()]
    kept = [ln for i, ln in enumerate(lines)
            if ln not in lines[:i] and not any(ln in other and ln != other for other in lines)]
    return "; ".join(kept)[:300]
