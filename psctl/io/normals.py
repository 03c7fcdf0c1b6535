"""Normal-map encodings: 16/8-bit PNG ((n + 1) / 2 per channel), float EXR, NumPy .npy; and the
albedo map's, in the same formats (``write_albedo_map``).

Convention everywhere: x right, y up, z toward the camera; row 0 is the top of the image.
Pixels outside the mask are 0 in every encoding (PNG 0 decodes to "no normal"; so does a PNG's
mid-grey, the zero vector's (n + 1) / 2, which some tools write as the background).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from psctl.errors import PsctlError, not_a_file
from psctl.io.atomic import atomic_path
from psctl.io.images import ImageInfo, linear_to_srgb, read_image, write_image

FORMATS = {"png16": "normal.png", "png8": "normal_8bit.png", "exr": "normal.exr", "npy": "normal.npy"}
ALBEDO_FORMATS = {"png16": "albedo.png", "png8": "albedo_8bit.png", "exr": "albedo.exr", "npy": "albedo.npy"}


def parse_formats(spec: str) -> list[str]:
    """"png16,exr" -> ["png16", "exr"], with a clear error for unknown names."""
    names = [s.strip().lower() for s in spec.split(",") if s.strip()]
    if not names:  # "" or [] said "unknown --format ''" (helper-196)
        raise PsctlError(None, f"no output format given; choose one or more of {', '.join(FORMATS)}")
    bad = [n for n in names if n not in FORMATS]
    if bad:
        raise PsctlError(None, f"unknown --format {','.join(bad) or spec!r}; choose from {', '.join(FORMATS)}")
    return list(dict.fromkeys(names))


def encode_png(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """[H, W, 3] unit normals -> [H, W, 3] values in [0, 1], zero outside the mask."""
    return np.where(mask[..., None], (np.asarray(normals, np.float64) + 1.0) / 2.0, 0.0)  # float64: exact rounding


# an integer map over half of whose pixels' 2 v - 1 is over 0.1 off unit length is no normal map: psctl's 8- and
# 16-bit maps and DiLiGenT's Normal_gt.png have none such; 12 of examples/bumpy_sphere's photos had 72-86%,
# two DiLiGenT images (cat 001, pot2 050) 94% and 100%
NOT_UNIT = (0.1, 0.5)


# an integer pixel whose 2 v - 1 is shorter than this is no normal: mid-grey, the zero vector's (n + 1) / 2, as
# some tools write the background (a unit normal's is within 0.01 of 1 in 8 bits); normalised, it was
# (1, 1, 1) / sqrt(3), and psctl depth without a mask put a tilted plane around the object (a review)
NO_NORMAL_LENGTH = 0.5


def decode_normal_pixels(pixels: np.ndarray, info: ImageInfo | None = None) -> np.ndarray:
    """Inverse of the encodings: integer images hold (n + 1) / 2, float images hold n.

    ``pixels``: as ``read_image`` gives them (float in [0, 1] for integer files; ``info`` says
    which files are float, and without it every float array is taken as (n + 1) / 2), or raw
    uint8 / uint16 codes in RGB order (PIL's and imageio's; OpenCV gives BGR: reverse the last
    axis first), which are divided by their type's largest value first. ``read_normal_map(path)``
    does all of this from a file.

    All-zero pixels (outside the mask) decode to 0, as do integer pixels that hold a vector
    shorter than NO_NORMAL_LENGTH (mid-grey: the zero vector).
    """
    pixels = np.asarray(pixels)
    rgb = pixels[..., :3].astype(np.float32)
    if pixels.dtype in (np.uint8, np.uint16):  # raw codes (PIL, imageio, cv2): (n + 1) / 2 * (2^bits - 1)
        rgb /= np.float32(np.iinfo(pixels.dtype).max)
    elif pixels.dtype.kind in "uib":  # int64 codes divided by int64's largest value were all one vector (helper-198)
        raise PsctlError(None, f"decode_normal_pixels takes a PNG's uint8 or uint16 codes, or read_image's floats, "
                               f"not {pixels.dtype}")
    is_float = info is not None and info.dtype in ("half", "float", "double")
    if is_float:
        return rgb
    n = rgb * 2.0 - 1.0
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    empty = (rgb == 0).all(axis=-1, keepdims=True) | (norm < NO_NORMAL_LENGTH)
    n = n / np.maximum(norm, 1e-6)
    return np.where(empty, 0.0, n).astype(np.float32)


def read_normal_map(path: str | os.PathLike) -> np.ndarray:
    """Read a normal map written by psctl (png16/png8/exr/npy) -> float32 [H, W, 3]."""
    path = Path(path)
    if not path.is_file():
        raise PsctlError(path, not_a_file(path, "normal map file is missing", "is a folder, not a normal map file"))
    if path.name.lower() in ALBEDO_FORMATS.values():  # beside normal.* in psctl normals' folder: an easy slip
        raise PsctlError(path, "is psctl normals' albedo map, not a normal map (psctl normals writes the normal "
                               f"map beside it as {' or '.join(FORMATS.values())})")
    if path.suffix.lower() == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as e:
            why = ("not a plain NumPy array file" if "allow_pickle" in str(e)  # numpy's advice is not ours
                   else ' '.join(str(e).split()))
            raise PsctlError(path, f"cannot read .npy ({why})") from None
        if arr.ndim != 3 or arr.shape[2] != 3:
            raise PsctlError(path, f"shape {arr.shape}, expected H x W x 3")
        if arr.dtype.kind != "f":  # integers would be an encoded image's pixels, read as normals
            what = {"i": "integers", "u": "integers", "c": "complex numbers", "b": "booleans"}.get(
                arr.dtype.kind, f"{arr.dtype} values")
            raise PsctlError(path, f"holds {what} ({arr.dtype}); a .npy normal map holds float unit normals "
                                   "(x right, y up, z towards the camera)")
        with np.errstate(over="ignore"):  # float64 beyond float32's range: inf, then no normal below
            nmap = arr.astype(np.float32)
    else:
        pixels, info = read_image(path, allow_nonfinite=True)
        if pixels.shape[2] < 3:
            raise PsctlError(path, "a normal map needs 3 channels")
        nmap = decode_normal_pixels(pixels, info)
        if info.dtype not in ("half", "float", "double"):  # (n + 1) / 2 of unit normals: 2 v - 1 has length 1
            stored = pixels[..., :3][::4, ::4].reshape(-1, 3).astype(np.float64)  # (a sample: seconds saved on 12 MP)
            stored = stored[(stored != 0).any(-1)]
            if len(stored):  # nor the commonest colour: a background of grey or white, not of black (a review)
                colours, counts = np.unique(stored, axis=0, return_counts=True)
                stored = stored[(stored != colours[np.argmax(counts)]).any(-1)]
            length = np.linalg.norm(2 * stored - 1, axis=-1)
            off = float(np.mean(np.abs(length - 1) > NOT_UNIT[0])) if len(length) else 0.0
            if off > NOT_UNIT[1]:
                raise PsctlError(path, f"is not a normal map: {off:.0%} of its pixels decode to vectors of a length "
                                       f"off 1 by over {NOT_UNIT[0]} (lengths {np.percentile(length, 5):.2f} to "
                                       f"{np.percentile(length, 95):.2f}), where the (n + 1) / 2 of unit normals "
                                       f"gives 1 (a photograph?)")
    # NaN = no normal (callers count them); an inf component is no direction either
    return np.where(np.isfinite(nmap).all(axis=-1, keepdims=True), nmap, np.float32(np.nan))


def write_normal_map(path: str | os.PathLike, normals: np.ndarray, mask: np.ndarray | None, fmt: str) -> None:
    """Write one encoding atomically. ``fmt`` is one of FORMATS.

    ``normals`` [H, W, 3]: unit normals. A vector more than 1e-3 off unit length is normalised
    (a PNG clips each channel of (n + 1) / 2, which would turn it), and one with no direction (NaN,
    infinite, zero) is written as 0, no normal. ``mask`` [H, W] as ``psctl.arrays.as_mask`` reads
    it (bool, or numbers above 0.5), or None for every pixel; outside it every encoding holds 0.
    """
    from psctl.arrays import as_mask, check_vector_dtype, plain, unit_vectors

    if fmt not in FORMATS:
        raise PsctlError(None, f"unknown normal-map format {fmt!r}")
    raw = np.asarray(plain(normals))
    check_vector_dtype(raw, "normals must be unit vectors of real numbers")
    if raw.ndim != 3 or raw.shape[2] != 3:
        raise PsctlError(None, f"normals must be [H, W, 3], got {list(raw.shape)}")
    keep = as_mask(mask, raw.shape[:2], allow_empty=True)
    # the length in the input's own precision (float16 in float32), summed by einsum so that no
    # [H, W, 3] temporary is made (a 12 MP float32 map: 768 MB at the peak with a float64 copy, now
    # 192 MB, by tracemalloc)
    wide = raw if raw.dtype in (np.float32, np.float64) else raw.astype(np.float32)
    with np.errstate(invalid="ignore", over="ignore"):
        off = ~(np.abs(np.sqrt(np.einsum("...i,...i->...", wide, wide)) - 1.0) <= 1e-3)
    del wide
    # unit normals are written as given (psctl's own maps stay bit for bit what they were); only
    # the others go through unit_vectors (all of a 12 MP map: 4.5 s and 1.1 GB more per format)
    normals = raw.astype(np.float32, copy=True)
    ok = ~off
    if off.any():
        unit, ok_off = unit_vectors(raw[off], 1e-6)
        normals[off] = unit
        ok[off] = ok_off
    mask = ok if keep is None else ok & keep
    normals[~mask] = 0.0
    if fmt == "png16":
        write_image(path, encode_png(normals, mask), "uint16", kind="data")
    elif fmt == "png8":
        write_image(path, encode_png(normals, mask), "uint8", kind="data")
    elif fmt == "exr":
        write_image(path, normals, "float", kind="data")
    else:
        write_npy(path, normals)


def write_albedo_map(path: str | os.PathLike, albedo: np.ndarray, mask: np.ndarray, fmt: str, scale: float) -> None:
    """Write one albedo encoding atomically. ``fmt`` is one of ALBEDO_FORMATS. EXR and .npy hold
    the albedo as estimated (linear, float32); the PNGs are pictures: albedo / ``scale``, clipped
    to [0, 1] and sRGB-encoded (tagged sRGB), so that linear = srgb_to_linear(png) * scale below
    white."""
    albedo = np.where(mask[..., None], albedo, 0.0).astype(np.float32)
    if fmt in ("png16", "png8"):
        write_image(path, linear_to_srgb(albedo / scale), "uint16" if fmt == "png16" else "uint8", kind="picture")
    elif fmt == "exr":
        write_image(path, albedo, "float", kind="linear")
    elif fmt == "npy":
        write_npy(path, albedo)
    else:
        raise PsctlError(None, f"unknown albedo-map format {fmt!r}")


def write_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    """``np.save`` atomically (a temporary name, then the rename)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, array)
