"""In-memory inputs of the Python API, held to the rules of capture folders.

``estimate_normals``, ``estimate_lights``, ``array_normals`` and ``array_lights`` take numpy
arrays where the CLI takes files; these functions give them the same conventions (integer
pixels scaled by the largest value of their type, as image files are; light rows normalised;
a mask is what is above 0.5) and the same one-line ``PsctlError`` for what a folder would be
refused for (NaN, zero-length lights, an empty mask, all-black images).
"""

from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np

from psctl.errors import PsctlError, _short


def plain(x: object) -> object:
    """A torch tensor as a plain CPU tensor (one that requires grad, or lives on a GPU, cannot
    become a numpy array as it is; bfloat16 and float8, which numpy has no type for, as
    float32); anything else as it is."""
    if not (hasattr(x, "detach") and hasattr(x, "cpu")):
        return x
    x = x.detach().cpu()
    if str(getattr(x, "dtype", "")).startswith(("torch.bfloat16", "torch.float8")):
        x = x.float()  # exact: float32 holds every such value
    return x


def n_rows(x: object) -> int | None:
    """How many rows an array argument has (the lights': how many images they are for), where it
    has any: a 0-d array, a number or None gives None, left to the argument's own check."""
    try:
        return len(x) if np.ndim(plain(x)) >= 1 else None
    except (TypeError, ValueError):
        return None


def as_images(images: np.ndarray, n: int | None = None) -> np.ndarray:
    """[N, H, W, 3] float32 from [N, H, W, C] (C = 1, 2, 3 or 4: grey repeated, alpha dropped) or
    [N, H, W] grey. Integer arrays are divided by their type's largest value (uint8 by 255,
    uint16 by 65535), as psctl reads image files; float arrays are taken as they are (linear,
    on that scale; LCNet's exposure guard rescales captures far outside it). ``n``: the number
    of images when known (from the lights): [N, H, W] with W = 3 or 4 is then a grey stack, not
    one colour image."""
    paths = isinstance(images, (list, tuple)) and bool(images) and all(isinstance(x, (str, os.PathLike)) for x in images)
    if paths:  # file names (helper-175)
        raise PsctlError(None, "images must be a numeric [N, H, W, 3] array, not a list of file names; read them "
                               "with psctl.load_images(psctl.open_capture(folder)) or psctl.io.images.read_image")
    if images is None or isinstance(images, (str, bytes, os.PathLike)):  # (helper-172: "got dtype <U21")
        raise PsctlError(None, f"images must be a numeric [N, H, W, 3] array, not {_short(images)}"
                               + ("" if images is None else "; read a capture folder's images with "
                                                            "psctl.load_images(psctl.open_capture(path))"))
    try:
        arr = np.asarray(plain(images))
    except (TypeError, ValueError) as e:
        raise PsctlError(None, f"images must be a numeric [N, H, W, 3] array ({e})") from None
    if arr.dtype.kind not in "buf" or (arr.dtype.kind == "u" and arr.dtype.itemsize > 2):
        raise PsctlError(None, f"images must be float, uint8 or uint16 (scaled by 255 or 65535, as image "
                               f"files are), got dtype {arr.dtype}")
    if arr.ndim == 3 and arr.shape[-1] in (3, 4) and min(arr.shape[:2]) > 4 and n != arr.shape[0]:
        raise PsctlError(None, f"images of shape {arr.shape} look like one [H, W, 3] image; pass a stack "
                               "[N, H, W, 3] (grey images of width 3 or 4: [N, H, W, 1])")
    if arr.ndim == 3 and n is not None and arr.shape[0] != n == arr.shape[-1]:  # (an audit: the mask was blamed)
        raise PsctlError(None, f"images of shape {arr.shape} look like [H, W, N], the {n} images last; pass "
                               "[N, H, W] (np.moveaxis(images, -1, 0))")
    if arr.ndim == 4 and arr.shape[1] in (1, 3, 4) and arr.shape[-1] not in (1, 2, 3, 4):
        raise PsctlError(None, f"images of shape {arr.shape} look like [N, C, H, W], channels first; pass "
                               "[N, H, W, C] (np.moveaxis(images, 1, -1))")
    if arr.ndim == 3:
        arr = arr[..., None]
    if arr.ndim != 4 or arr.shape[-1] not in (1, 2, 3, 4) or min(arr.shape[:3]) < 1:
        raise PsctlError(None, f"images must be [N, H, W, 3] (or [N, H, W]) with N, H, W >= 1, got shape {arr.shape}")
    scale = float(np.iinfo(arr.dtype).max) if arr.dtype.kind in "iu" else 1.0
    with np.errstate(over="ignore"):  # float64 beyond float32's range: said below, not warned
        out = arr.astype(np.float32, copy=False)  # a float32 input is not copied (and never written to)
    if scale != 1.0:
        out /= scale
    if not np.isfinite(out).all():
        raise PsctlError(None, "images contain NaN or infinite values" if not np.isfinite(arr).all() else
                               "images hold values beyond float32's range (about 3.4e38): rescale them")
    c = out.shape[-1]
    if c in (1, 2):
        out = np.repeat(out[..., :1], 3, axis=-1)
    elif c == 4:
        out = out[..., :3]
    return np.ascontiguousarray(out)


def as_mask(mask: np.ndarray | None, shape: tuple[int, int], allow_empty: bool = False) -> np.ndarray | None:
    """[H, W] bool (None stays None: the whole image; [H, W, 1] is squeezed). Numbers: above 0.5
    is the object, as in mask files; uint8 and uint16 masks above 1 (0/255, 0/65535) are first
    divided by their type's largest value, as mask files are; other integer masks above 1 (a
    label image, numpy's default int64 * 255) are the object where nonzero. Wrong shape, NaN and
    an empty mask (unless ``allow_empty``) are errors."""
    if mask is None:
        return None
    if isinstance(mask, (str, bytes, os.PathLike)):  # np.asarray would make a 0-D array of text
        raise PsctlError(None, f"mask must be an [H, W] array (or None), not the path {_short(mask)}; "
                               "read a mask file with psctl.load_mask")
    m = np.asarray(plain(mask))
    if m.ndim == 3 and m.shape[2] == 1:
        m = m[..., 0]
    if m.shape != tuple(shape):
        raise PsctlError(None, f"mask must be [H, W] = {list(shape)}, got {list(m.shape)}")
    hint = ""
    if m.dtype != bool:
        if m.dtype.kind not in "iuf":
            raise PsctlError(None, f"mask must be bool or numeric, got dtype {m.dtype}")
        if not np.isfinite(m).all():
            raise PsctlError(None, "mask contains NaN or infinite values")
        if m.dtype.kind in "iu" and m.max() > 1:
            # 0/255 or 0/65535 in an image's type: scaled as a mask file is; any other integer
            # type's largest value says nothing about the mask (int64 * 255 would be empty)
            if m.dtype in (np.uint8, np.uint16):
                top = np.iinfo(m.dtype).max
                hint = f" ({m.dtype} masks are divided by {top}, as mask files are: pass bool, or 0/{top})"
                m = m / top
            else:
                m = m != 0
        m = m > 0.5
    if not m.any() and not allow_empty:
        raise PsctlError(None, f"mask is empty (no foreground pixel){hint}")
    return m


def as_lights(lights: np.ndarray | None, n: int) -> np.ndarray | None:
    """[n, 3] float32 unit directions (rows normalised, as light_directions.txt's are); NaN,
    infinite or zero-length rows, complex numbers, a wrong shape and every light behind the object
    (z <= 0) are errors."""
    if lights is None:
        return None
    try:
        raw = np.asarray(plain(lights))
        if raw.dtype.kind == "c":  # float() would drop the imaginary part with only a warning
            raise TypeError
        arr = raw.astype(np.float64)
    except (TypeError, ValueError):
        raise PsctlError(None, f"lights must be a real, numeric [{n}, 3] array") from None
    if arr.shape != (n, 3):
        raise PsctlError(None, f"lights must be [{n}, 3] (one direction per image), got {list(arr.shape)}")
    bad = np.flatnonzero(~np.isfinite(arr).all(1))
    if bad.size:
        raise PsctlError(None, f"lights[{bad[0]}]: NaN or infinite value")  # indexed as the array (the warnings too)
    unit, bad = unit_rows(arr)
    if bad.size:
        raise PsctlError(None, f"lights[{bad[0]}]: zero-length light direction (shorter than 1e-6)")
    check_lights_face_camera(unit, None)
    return unit


def check_lights_face_camera(unit: np.ndarray, path: str | os.PathLike | None) -> None:
    """An error naming ``path`` (light_directions.txt; None: the array) when every light [N, 3]
    has z <= 0: behind the object, most likely an axis convention with z pointing away."""
    if (unit[:, 2] <= 0).all():
        raise PsctlError(path, ("" if path else "lights: ") + "every light has z <= 0 (behind the object); psctl "
                               "wants z toward the camera (x right, y up): negate the z column if yours points away")


def lights_behind(lights: np.ndarray, rows: Callable[[list[int]], str]) -> str | None:
    """The note on unit light directions [N, 3] of which some have z <= 0 (all: the error of
    ``check_lights_face_camera``), or None; ``rows`` names the first few ("rows 2, 5", "lights[1]")."""
    behind = [int(i) for i in np.flatnonzero(lights[:, 2] <= 0)]
    if not behind:
        return None
    named = rows(behind[:5]) + (" ..." if len(behind) > 5 else "")
    return (f"{len(behind)} of {len(lights)} light directions have z <= 0, behind the object ({named}); psctl "
            f"wants z toward the camera")


def check_vector_dtype(a: np.ndarray, what: str) -> None:
    """A PsctlError, "``what``, got dtype ...", unless ``a`` holds real numbers (floats or signed
    integers): unsigned integers (and bools) are an encoded map's pixels ((n + 1) / 2), which would
    be taken as vectors all in one octant, so the message says how to decode them."""
    if a.dtype.kind not in "fi":
        raise PsctlError(None, f"{what}, got dtype {a.dtype}"
                               + (" (read the file with psctl.io.normals.read_normal_map, or decode RGB codes "
                                  "with psctl.io.normals.decode_normal_pixels)"
                                  if a.dtype.kind in "ub" else ""))


def unit_vectors(v: np.ndarray, floor: float, within: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """[..., 3] vectors -> (unit vectors, float64, 0 where there is none; [...] bool, which have a
    direction). One has none where it is not finite, is 0, or is not longer than ``floor`` (than
    ``floor`` times the longest finite vector, among ``within`` [...] when given, where that is
    shorter than 1: a set scaled as a whole by 1e-9 keeps its directions, one 1e-9 vector among
    unit ones is a zero written with noise). Each vector is scaled to a largest |value| of 1 before
    its norm, so that neither 1e300 nor 1e-300 overflows or underflows. Light rows, normal maps to
    integrate and ground truth share this."""
    v = np.asarray(v, np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        big = np.abs(v).max(axis=-1)
        ok = np.isfinite(v).all(axis=-1) & (big > 0)
        u = np.where(ok[..., None], v / np.where(ok, big, 1.0)[..., None], 0.0)
        length = np.linalg.norm(u, axis=-1)  # 1 to sqrt(3) where ok
        full = np.where(ok, big * length, 0.0)  # inf for a vector near 1e308: long, as it is
    among = full if within is None else full[np.asarray(within, bool)]
    ok &= full > floor * min(1.0, float(among.max()) if among.size else 0.0)
    return np.where(ok[..., None], u / np.where(ok, length, 1.0)[..., None], 0.0), ok


def unit_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Finite rows [N, 3] -> (the rows normalised, float32; the indices of rows with no direction:
    ``unit_vectors`` with the floor 1e-6). light_directions.txt and the array API share this."""
    unit, ok = unit_vectors(rows, 1e-6)
    return unit.astype(np.float32), np.flatnonzero(~ok)


def check_not_black(images: np.ndarray, mask: np.ndarray | None) -> None:
    """An error when every image is black inside the mask: nothing to estimate from (a network
    would still answer, with normals or lights that mean nothing)."""
    inside = images if mask is None else images[:, mask]
    if not (inside > 0).any():
        raise PsctlError(None, "all images are black inside the mask")


def bounding_box(mask: np.ndarray, margin: int = 0) -> tuple[slice, slice]:
    """Rows/cols slices of the mask's bounding box grown by ``margin`` (clipped to the image)."""
    ys, xs = np.nonzero(mask)
    h, w = mask.shape

    def span(lo: int, hi: int, size: int) -> slice:
        return slice(max(int(lo) - margin, 0), min(int(hi) + 1 + margin, size))

    return span(ys.min(), ys.max(), h), span(xs.min(), xs.max(), w)
