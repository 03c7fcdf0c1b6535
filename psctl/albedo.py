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

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from psctl.errors import PsctlError

if TYPE_CHECKING:
    from psctl.api import ProgressFactory
    from psctl.io.capture import Capture, DecodeMemo

DEFAULT_ALBEDO = {
    "min_shading": 0.2,  # n . l below this (78 degrees off the normal) counts only where nothing is brighter lit
    "budget_mb": 256,  # the ratios of one band of pixels; larger objects are done in bands, each a pass over the images
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
    med = 0.5 * (np.take_along_axis(ratios, lo[None], 0)[0] + np.take_along_axis(ratios, hi[None], 0)[0])
    return np.where(k > 0, med, 0.0).astype(np.float32)


def counted_images(shading: np.ndarray, min_shading: float) -> np.ndarray:
    """shading [P, N] (n . l) -> [P, N] bool: the images that light each pixel well enough to
    count: n . l >= min_shading, or, for a pixel where no image reaches that, at least half its
    best n . l (and above 0)."""
    best = shading.max(axis=1, keepdims=True)
    return (shading >= np.where(best >= min_shading, min_shading, 0.5 * best)) & (shading > 0)


def albedo_from_reader(read: Callable[[tuple[slice, slice]], Iterator[np.ndarray]], lights: np.ndarray,
                       normals: np.ndarray, mask: np.ndarray, config: dict | None = None,
                       progress: Callable[[int], None] | None = None) -> AlbedoResult:
    """The albedo of the ``mask`` pixels whose ``normals`` [H, W, 3] are nonzero, ``read(box)``
    yielding the N images cut to ``box`` (float [h, w, 3], divided by their intensities) and
    ``lights`` [N, 3] their unit directions. Pixels are done in bands of rows whose working
    arrays (BYTES_PER_OBSERVATION per image and pixel) fit ``budget_mb``; each band reads the
    images once."""
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
    cols = np.flatnonzero(has.any(axis=0))
    x0, x1 = int(cols[0]), int(cols[-1]) + 1
    for y0, y1 in row_bands(has, n, cfg["budget_mb"]):
        box = (slice(y0, y1), slice(x0, x1))
        sel = has[box]
        nrm = (normals[box][sel] / length[box][sel][:, None]).astype(np.float32)  # [P, 3], unit (maps read from 8 bits are not)
        shading = nrm @ lights.T  # [P, N]
        counted = counted_images(shading, float(cfg["min_shading"]))
        ratios = np.empty((n, len(nrm), 3), np.float32)  # image by image: each a contiguous block
        peak = np.zeros((len(nrm), 3), np.float32)  # each channel's brightest counted value
        got = 0
        for i, img in enumerate(read(box)):
            if i >= n:
                raise PsctlError(None, f"albedo: the reader gave more than the {n} images of the lights")
            vals = img[sel]  # [P, 3]
            c = counted[:, i, None]
            with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # n . l <= 0: not counted
                r = vals / shading[:, i, None]
            if (~np.isfinite(r) & c).any():
                raise PsctlError(None, "albedo: image / (n . l) passes float32's range; rescale the images")
            ratios[i] = np.where(c, r, np.inf)
            np.maximum(peak, vals, out=peak, where=c)
            got += 1
            if progress is not None:
                progress(1)
        if got != n:
            raise PsctlError(None, f"albedo: the reader gave {got} images for {n} lights")
        # an image in which every channel is black at the pixel is a cast shadow there; one dark
        # channel alone is not (a dark, noisy channel of a lit surface reads 0 or less at times)
        lim = BLACK * peak
        k = np.zeros((len(nrm), 3), np.int32)  # the images each median takes
        with np.errstate(invalid="ignore", over="ignore"):  # inf * (n . l <= 0): not counted anyway
            for i in range(n):
                r = ratios[i]
                r[(r * shading[:, i, None] <= lim).all(axis=1)] = np.inf
                k += np.isfinite(r)
        med = _median_ratios(ratios, k)
        band = albedo[box]
        band[sel] = med
        undetermined[box] |= _none_counted(k.any(axis=1), sel)
    return AlbedoResult(albedo, undetermined)


def _none_counted(any_counted: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """[h, w] bool: the ``sel`` pixels whose ``any_counted`` [P] is False."""
    out = np.zeros(sel.shape, bool)
    out[sel] = ~any_counted
    return out


# a band's working arrays per image and pixel: the ratios (3 x float32), n . l (float32), the
# counted flags (bool) and counted_images' temporaries (bool, 2)
BYTES_PER_OBSERVATION = 12 + 4 + 1 + 2


def row_bands(has: np.ndarray, n_images: int, budget_mb: float) -> list[tuple[int, int]]:
    """[(first row, end row)] of the bands ``albedo_from_reader`` does: consecutive rows whose
    ``has`` pixels' working arrays (BYTES_PER_OBSERVATION x ``n_images`` each) fit ``budget_mb``,
    at least one row each; rows without pixels are skipped at a band's start."""
    per_row = has.sum(axis=1)
    cap = max(1, int(float(budget_mb) * (1 << 20)) // (BYTES_PER_OBSERVATION * max(n_images, 1)))
    out: list[tuple[int, int]] = []
    rows = np.flatnonzero(per_row)
    if not rows.size:
        return out
    r, stop = int(rows[0]), int(rows[-1]) + 1
    while r < stop:
        r1, count = r + 1, int(per_row[r])
        while r1 < stop and count + per_row[r1] <= cap:
            count += int(per_row[r1])
            r1 += 1
        out.append((r, r1))
        while r1 < stop and per_row[r1] == 0:
            r1 += 1
        r = r1
    return out


def capture_albedo(capture: "Capture", normals: np.ndarray, mask: np.ndarray, config: dict | None = None,
                   progress: "ProgressFactory | None" = None, memo: "DecodeMemo | None" = None) -> AlbedoResult:
    """``albedo_from_reader`` on a capture folder's images (read as the networks read them:
    divided by the capture's intensities, ambient image subtracted, near-light falloff divided
    out), with the capture's lights. ``memo``: images an earlier pass decoded (``iter_images``)."""
    from psctl.io.capture import iter_images

    if capture.lights is None:
        raise PsctlError(capture.path / "light_directions.txt", "missing: the albedo needs light directions")
    cfg = {**DEFAULT_ALBEDO, **(config or {})}
    lights = capture.lights / np.linalg.norm(capture.lights, axis=1, keepdims=True)
    has = mask & (np.linalg.norm(normals, axis=-1) > 0)
    passes = len(row_bands(has, capture.n_images, cfg["budget_mb"]))
    advance = None if progress is None or not passes else progress(f"{capture.name}: albedo", passes * capture.n_images)
    # each image was checked against the ambient image over the method's whole box: a band of a
    # few rows may lie in an image's shadow, black once the ambient image is subtracted
    return albedo_from_reader(lambda box: iter_images(capture, box, memo=memo, ambient_check=False), lights,
                              normals, mask, cfg, advance)


def estimate_albedo(images: np.ndarray, lights: np.ndarray, normals: np.ndarray, mask: np.ndarray | None = None,
                    min_shading: float = DEFAULT_ALBEDO["min_shading"]) -> np.ndarray:
    """Albedo from arrays.

    Args:
        images: [N, H, W, 3] (or [N, H, W] grey) linear images divided by their light
            intensities, as ``psctl.estimate_normals`` takes them.
        lights: [N, 3] light directions (normalised here).
        normals: [H, W, 3] unit normals (any method's; 0 where there is none).
        mask: [H, W] bool or numbers (above 0.5 is the object); None: every pixel.
        min_shading: the smallest n . l an image counts with (where no image reaches it, those
            with at least half the pixel's best n . l count).
    Returns:
        [H, W, 3] float32 albedo: per channel, the median of image / (n . l) over the counted
        images; 0 outside the mask and where no light reaches the normal.
    """
    from psctl.arrays import as_images, as_lights, as_mask, plain

    images = as_images(images, len(lights) if hasattr(lights, "__len__") else None)  # [N, H, W, 3]
    lights = as_lights(lights, images.shape[0])
    if lights is None:
        raise PsctlError(None, "lights: the albedo needs light directions")
    mask = as_mask(mask, images.shape[1:3])
    mask = np.ones(images.shape[1:3], bool) if mask is None else mask
    try:
        normals = np.asarray(plain(normals), np.float32)
    except (TypeError, ValueError):
        raise PsctlError(None, "normals must be a numeric [H, W, 3] array") from None
    if normals.shape != (*images.shape[1:3], 3):
        raise PsctlError(None, f"normals must be [H, W, 3] = {[*images.shape[1:3], 3]} (the images' size), "
                               f"got {list(normals.shape)}")
    if not np.isfinite(normals).all():
        raise PsctlError(None, "normals contain NaN or infinite values")
    try:
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
