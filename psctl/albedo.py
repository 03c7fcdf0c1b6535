"""Albedo: each pixel's diffuse reflectance (RGB), from its normal, the lights and the images.

A Lambertian pixel's image under light i is m_i = rho * e_i * max(n . l_i, 0), so each image that
lights the pixel gives one estimate rho = m_i / (e_i n . l_i) (the images are read divided by
their intensities e_i). Real surfaces add highlights (too bright) and cast shadows,
interreflections and saturation (too dark or too bright), so the albedo is the **median** of these
ratios per channel, over the images that light the pixel well by its normal (``n . l_i >=
min_shading``; where none does, those with at least half the pixel's best shading) and in which
the pixel is not black (every channel at most BLACK times its brightest value among them: a cast
shadow, not evidence of a dark surface), not their least-squares mean. On a Lambertian surface every ratio
is the albedo, so the median is exact wherever lights reach; outliers are left out while they
are fewer than half of the pixel's counted images.

The albedo is on the images' scale, per unit light intensity. With intensities estimated (sdps:
one grey intensity per image) it is known up to one factor per channel: the lights' colour,
which is not estimated. Any method's normals can be used; with better normals the ratios agree
better.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from psctl.errors import NO_ROOM, PsctlError

if TYPE_CHECKING:
    from psctl.api import ProgressFactory
    from psctl.io.capture import Capture, DecodeMemo

DEFAULT_ALBEDO = {
    "min_shading": 0.2,  # n . l below this (78 degrees off the normal) counts only where nothing is brighter lit
    "budget_mb": 256,  # the ratios in memory; a larger object's go to a temporary file, their medians taken in bands
    "memo_mb": 128,  # images as the method's own pass decoded them, kept for the albedo's (psctl.io.capture.DecodeMemo)
}
BLACK = 1e-6  # an image with every channel this dark at a pixel (relative to the channel's brightest counted value) is a shadow there
PNG_PERCENTILE = 99.0  # albedo.png maps this percentile of the object's albedo (all channels) to white


@dataclass(frozen=True)
class AlbedoResult:
    """albedo [H, W, 3] float32 (0 outside the mask and where undetermined); undetermined [H, W]
    bool: object pixels without a normal (dark, or none given), that no light reaches by their
    normal (n . l <= 0 for every image), or that are black in every counted image."""
    albedo: np.ndarray
    undetermined: np.ndarray


def _median_ratios(ratios: np.ndarray, k: np.ndarray) -> np.ndarray:
    """ratios [N, P, C] (+inf where not counted), k [P, C] the number of finite ones -> [P, C]
    the median of each pixel's and channel's finite ratios, 0 where there are none. Sorted in
    place."""
    ratios.sort(axis=0)  # the uncounted (+inf) go last
    lo, hi = np.maximum((k - 1) // 2, 0), np.maximum(k // 2, 0)
    a, b = np.take_along_axis(ratios, lo[None], 0)[0], np.take_along_axis(ratios, hi[None], 0)[0]
    with np.errstate(invalid="ignore"):  # (inf - inf where nothing counts: 0 below)
        med = a + 0.5 * (b - a)  # not (a + b) / 2, which overflows float32 near its top (an audit: 3e38)
    return np.where(k > 0, med, 0.0).astype(np.float32)


def shading_floor(best: np.ndarray, min_shading: float) -> np.ndarray:
    """The least n . l that counts at pixels whose best n . l is ``best``: ``min_shading``, or
    half the best where no image reaches ``min_shading``. An image counts at a pixel where its
    n . l is at least this and above 0."""
    return np.where(best >= min_shading, min_shading, 0.5 * best)


def albedo_from_reader(read: Callable[[tuple[slice, slice]], Iterator[np.ndarray]], lights: np.ndarray,
                       normals: np.ndarray, mask: np.ndarray, config: dict | None = None,
                       progress: Callable[[int], None] | None = None,
                       median_progress: Callable[[int], Callable[[int], None]] | None = None) -> AlbedoResult:
    """The albedo of the ``mask`` pixels whose ``normals`` [H, W, 3] are nonzero, ``read(box)``
    yielding the N images cut to ``box`` (float [h, w, 3], divided by their intensities) and
    ``lights`` [N, 3] their unit directions. ``read`` is called once. The ratios are kept in
    memory when they fit ``budget_mb`` (BYTES_PER_OBSERVATION per image and pixel), else in a
    temporary file (``RatioStore``), and their medians are then taken in bands of pixels that
    fit it. ``progress(1)`` after each image read; ``median_progress(total)`` -> ``advance(pixels)``
    for the bands of the temporary file, which can take as long as the reading (not called when
    the ratios are in memory: their medians take a small part of the pass)."""
    cfg = {**DEFAULT_ALBEDO, **(config or {})}
    h, w = mask.shape
    lights = np.asarray(lights, np.float32)
    n = len(lights)
    length = np.linalg.norm(normals, axis=-1)
    has = mask & (length > 0)
    albedo = np.zeros((h, w, 3), np.float32)
    undetermined = mask & ~has
    if not has.any():
        return AlbedoResult(albedo, undetermined)
    rows, cols = np.flatnonzero(has.any(axis=1)), np.flatnonzero(has.any(axis=0))
    box = (slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1))
    sel = has[box]
    nrm = (normals[box][sel] / length[box][sel][:, None]).astype(np.float32)  # [P, 3], unit (maps read from 8 bits are not)
    npx = len(nrm)
    min_shading = float(cfg["min_shading"])
    best = np.full(npx, -np.inf, np.float32)
    for light in lights:  # each pixel's best n . l, for shading_floor, without a [P, N] array
        np.maximum(best, nrm @ light, out=best)
    floor = shading_floor(best, min_shading)
    budget = int(float(cfg["budget_mb"]) * (1 << 20))
    peak = np.zeros((npx, 3), np.float32)  # each channel's brightest counted value
    with RatioStore(n, npx, in_memory=fits_in_memory(npx, n, cfg)) as ratios:
        got = 0
        for i, img in enumerate(read(box)):
            if i >= n:
                raise PsctlError(None, f"albedo: the reader gave more than the {n} images of the lights")
            vals = img[sel]  # [P, 3]
            s = nrm @ lights[i]
            c = ((s >= floor) & (s > 0))[:, None]  # the images that count (shading_floor)
            with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # n . l <= 0: not counted
                r = vals / s[:, None]
            if (~np.isfinite(r) & c).any():
                raise PsctlError(None, "albedo: image / (n . l) passes float32's range; rescale the images")
            ratios.put(i, np.where(c, r, np.inf).astype(np.float32))
            np.maximum(peak, vals, out=peak, where=c)
            got += 1
            if progress is not None:
                progress(1)
        if got != n:
            raise PsctlError(None, f"albedo: the reader gave {got} images for {n} lights")
        med = np.zeros((npx, 3), np.float32)
        none = np.zeros(npx, bool)
        lim = BLACK * peak
        step = npx if ratios.in_memory else max(1, budget // (n * BAND_BYTES_PER_OBSERVATION))
        advance = None if ratios.in_memory or median_progress is None else median_progress(npx)
        for p0 in range(0, npx, step):
            p1 = min(p0 + step, npx)
            block = ratios.block(p0, p1)  # [N, p, 3]
            k = np.zeros((p1 - p0, 3), np.int32)  # the images each median takes
            # an image in which every channel is black at the pixel is a cast shadow there; one dark
            # channel alone is not (a dark, noisy channel of a lit surface reads 0 or less at times)
            with np.errstate(invalid="ignore", over="ignore"):  # inf * (n . l <= 0): not counted anyway
                for i in range(n):
                    r = block[i]
                    s = nrm[p0:p1] @ lights[i]  # as in the pass (one light at a time: the same rounding)
                    r[(r * s[:, None] <= lim[p0:p1]).all(axis=1)] = np.inf
                    k += np.isfinite(r)
            med[p0:p1] = _median_ratios(block, k)
            none[p0:p1] = ~k.any(axis=1)
            if advance is not None:
                advance(p1 - p0)
    out = albedo[box]
    out[sel] = med
    undetermined[box] |= _none_counted(none, sel)
    return AlbedoResult(albedo, undetermined)


def _none_counted(none: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """[h, w] bool: the ``sel`` pixels whose ``none`` [P] is True."""
    out = np.zeros(sel.shape, bool)
    out[sel] = none
    return out


# per image and pixel: the ratios (3 x float32), and a margin for the per-image temporaries
# (tracemalloc: 14.1 bytes in all on the dev split's cat, 96 images)
BYTES_PER_OBSERVATION = 12 + 3
BAND_BYTES_PER_OBSERVATION = BYTES_PER_OBSERVATION + 12  # a band read from the file: a copy beside


def fits_in_memory(n_pixels: int, n_images: int, config: dict | None = None) -> bool:
    """Whether the albedo of ``n_pixels`` object pixels under ``n_images`` images keeps its ratios
    in memory (``budget_mb``), not in a temporary file."""
    cfg = {**DEFAULT_ALBEDO, **(config or {})}
    return n_pixels * n_images * BYTES_PER_OBSERVATION <= float(cfg["budget_mb"]) * (1 << 20)


class RatioStore:
    """The ratios [N, P, 3] float32, image by image: in memory, or (``in_memory`` False) in an
    unnamed temporary file (``tempfile.TemporaryFile``: gone when closed, or when the process
    ends) whose space is reserved first, so that a full disk is one line before any image is
    read. ``put(i, [P, 3])``; ``block(p0, p1)`` -> [N, p1 - p0, 3] (in memory: a view, which the
    caller may sort)."""

    def __init__(self, n: int, npx: int, in_memory: bool):
        self.n, self.npx, self.in_memory = n, npx, in_memory
        self.array = np.empty((n, npx, 3), np.float32) if in_memory else None
        self.file = None

    def __enter__(self) -> "RatioStore":
        if not self.in_memory:
            import tempfile

            try:
                self.file = tempfile.TemporaryFile(prefix="psctl-albedo-")
                os.posix_fallocate(self.file.fileno(), 0, self.n * self.npx * 12)
            except OSError as e:
                if self.file is not None and e.errno not in NO_ROOM:
                    return self  # a file system that cannot reserve: the writes say whether there is room
                self._fail(e)
        return self

    def _fail(self, e: OSError) -> None:
        """One line for a temporary file that cannot be made or written: no room, or another cause."""
        import tempfile

        if self.file is not None:
            self.file.close()
        where = tempfile.tempdir  # set once Python found a usable folder (asking again may raise)
        size = f"{self.n * self.npx * 12 / 2**20:,.0f} MB"
        if e.errno in NO_ROOM:
            raise PsctlError(where, f"no room for the albedo's temporary ratios ({size}: {e.strerror or e}); free "
                                    f"space there, or set TMPDIR to another folder") from None
        raise PsctlError(where, f"cannot {'write' if self.file is not None else 'make'} the albedo's temporary file "
                                f"({size}: {e.strerror or e}); set TMPDIR to a writable folder") from None

    def __exit__(self, *exc: object) -> None:
        if self.file is not None:
            self.file.close()

    def put(self, i: int, ratios: np.ndarray) -> None:
        if self.array is not None:
            self.array[i] = ratios
            return
        data = memoryview(np.ascontiguousarray(ratios, np.float32)).cast("B")
        offset, done = i * self.npx * 12, 0
        try:
            while done < len(data):  # Linux writes at most about 2 GB a call
                wrote = os.pwrite(self.file.fileno(), data[done:], offset + done)
                if wrote <= 0:
                    raise OSError(errno.ENOSPC, "nothing written")
                done += wrote
        except OSError as e:
            self._fail(e)

    def block(self, p0: int, p1: int) -> np.ndarray:
        if self.array is not None:
            return self.array[:, p0:p1]
        out = np.empty((self.n, p1 - p0, 3), np.float32)
        for i in range(self.n):
            view = memoryview(out[i]).cast("B")
            offset, done = (i * self.npx + p0) * 12, 0
            while done < len(view):  # as put: at most about 2 GB a call
                got = os.preadv(self.file.fileno(), [view[done:]], offset + done)
                if got <= 0:
                    raise PsctlError(None, "albedo: the temporary ratios file was cut short")
                done += got
        return out


def capture_albedo(capture: "Capture", normals: np.ndarray, mask: np.ndarray, config: dict | None = None,
                   progress: "ProgressFactory | None" = None, memo: "DecodeMemo | None" = None) -> AlbedoResult:
    """``albedo_from_reader`` on a capture folder's images (read as the networks read them:
    divided by the capture's intensities, ambient image subtracted, near-light falloff divided
    out, isolated hot values set to their neighbours' level: ``psctl.hotpixels``), with the
    capture's lights. ``memo``: images an earlier pass decoded (``iter_images``)."""
    from psctl.io.capture import iter_images

    if capture.lights is None:
        raise PsctlError(capture.path / "light_directions.txt", "missing: the albedo needs light directions")
    cfg = {**DEFAULT_ALBEDO, **(config or {})}
    lights = capture.lights / np.linalg.norm(capture.lights, axis=1, keepdims=True)
    advance = None if progress is None else progress(f"{capture.name}: albedo", capture.n_images)
    # each image was checked against the ambient image over the method's whole box; the albedo's
    # box (the pixels with a normal) may be a smaller part, black in an image once it is subtracted
    medians = None if progress is None else (lambda total: progress(f"{capture.name}: albedo medians", total))
    from psctl.arrays import bounding_box
    from psctl.hotpixels import clamp_hot_pixels

    def read(box: tuple[slice, slice]) -> Iterator[np.ndarray]:
        # isolated hot values set to their neighbours' level, as the method's pass did (its note says
        # so): judged over the whole mask, then cut to the albedo's box (inside the mask's)
        outer = bounding_box(mask)
        inside = mask[outer]
        cut = tuple(slice(b.start - o.start, b.stop - o.start) for b, o in zip(box, outer))
        for img in iter_images(capture, outer, memo=memo, ambient_check=False):
            yield clamp_hot_pixels(img * inside[..., None], inside)[0][cut]

    return albedo_from_reader(read, lights, normals, mask, cfg, advance, medians)


def estimate_albedo(images: np.ndarray, lights: np.ndarray, normals: np.ndarray, mask: np.ndarray | None = None,
                    min_shading: float = DEFAULT_ALBEDO["min_shading"]) -> np.ndarray:
    """Albedo from arrays. The images are taken as given: isolated hot values are not clamped here
    (``psctl.hotpixels.clamp_hot_pixels`` does it, as ``estimate_normals`` and psctl normals do).

    Args:
        images: [N, H, W, 3] (or [N, H, W] grey) linear images divided by their light
            intensities, as ``psctl.estimate_normals`` takes them (integer arrays are divided by
            their type's maximum, as there).
        lights: [N, 3] light directions (normalised here).
        normals: [H, W, 3] unit normals (any method's; 0 or NaN where there is none).
        mask: [H, W] bool or numbers (above 0.5 is the object); None: every pixel.
        min_shading: the smallest n . l an image counts with (where no image reaches it, those
            with at least half the pixel's best n . l count).
    Returns:
        [H, W, 3] float32 albedo: per channel, the median of image / (n . l) over the counted
        images; 0 outside the mask and where no light reaches the normal.
    """
    from psctl.arrays import as_images, as_lights, as_mask, check_not_black, check_vector_dtype, n_rows, plain

    images = as_images(images, n_rows(lights))  # [N, H, W, 3]
    lights = as_lights(lights, images.shape[0])
    if lights is None:
        raise PsctlError(None, "lights: the albedo needs light directions")
    mask = as_mask(mask, images.shape[1:3])
    given_mask = mask is not None
    mask = np.ones(images.shape[1:3], bool) if mask is None else mask
    check_not_black(images, mask)  # as estimate_normals: an all-zero map would look like an answer
    try:
        raw = np.asarray(plain(normals))
    except (TypeError, ValueError):  # ragged lists
        raise PsctlError(None, "normals must be a numeric [H, W, 3] array") from None
    check_vector_dtype(raw, "normals must be real numbers (unit vectors)")
    normals = raw.astype(np.float32)
    if normals.shape != (*images.shape[1:3], 3):
        raise PsctlError(None, f"normals must be [H, W, 3] = {[*images.shape[1:3], 3]} (the images' size), "
                               f"got {list(normals.shape)}")
    if np.isinf(normals).any():
        raise PsctlError(None, "normals contain infinite values")
    # NaN marks "no normal" (read_normal_map's, as integrate_normals takes it): no albedo there
    normals = np.where(np.isnan(normals).any(axis=-1, keepdims=True), np.float32(0.0), normals)
    inside = normals[mask]
    directions = int((np.abs(inside) > 0).any(-1).sum())
    if not directions:  # an all-zero albedo would look like an answer (an audit: zero normals)
        raise PsctlError(None, f"normals: none {'inside the mask' if given_mask else 'in the frame'} is a "
                               "direction (all 0 or NaN)")
    away = int(((np.abs(inside) > 0).any(-1) & (inside[:, 2] <= 0)).sum())
    if given_mask and away > directions / 2:  # (without a mask, a background's normals could decide it)
        import warnings

        from psctl.errors import PsctlWarning, caller_level

        # a warning, not an error: a perspective camera's surface may face it along its rays with z <= 0
        # (an audit: flipped z gave medians twice the truth, a maximum of 723 against 0.8, silently)
        warnings.warn(f"estimate_albedo: {away} of the mask's {directions} normals have z <= 0, facing away from "
                      f"an orthographic camera: are they in psctl's convention (x right, y up, z towards the camera)?",
                      PsctlWarning, stacklevel=caller_level())
    try:
        if isinstance(min_shading, (str, bytes, bool, np.bool_)):  # "0.1" or True is a mistake, not a number
            raise TypeError
        min_shading = float(min_shading)
    except (TypeError, ValueError):
        raise PsctlError(None, f"min_shading must be a number in (0, 1], not {min_shading!r}") from None
    if not 0.0 < min_shading <= 1.0:
        raise PsctlError(None, f"min_shading must be in (0, 1], got {min_shading:g}")
    return albedo_from_reader(lambda box: (img[box] for img in images), lights, normals, mask,
                              {"min_shading": min_shading}).albedo


def albedo_png_scale(albedo: np.ndarray, mask: np.ndarray) -> float:
    """The value albedo.png shows as white: PNG_PERCENTILE of the object's albedo over all
    channels (1.0 for a black object)."""
    vals = albedo[mask]
    vals = vals[np.isfinite(vals) & (vals > 0)]
    if not vals.size:
        return 1.0
    return float(np.percentile(vals, PNG_PERCENTILE))
