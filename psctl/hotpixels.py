"""Isolated hot pixels: found in one image, set to their neighbours' level.

A sensor's hot (or stuck) pixel, or a cosmic-ray hit, is one pixel far brighter than everything
around it. The networks fuse the images by a max-pool: one such value in one image becomes the
fused feature wherever it reaches, and LCNet's global feature is a max over the whole capture,
so one hot pixel turns every estimated light. Measured (session 40, a Lambertian sphere of 32
float images at 128 x 128, mean 0.49 inside the mask, one pixel of one image set to v): sdps
2.91 degrees without, 3.05 at v = 50, 4.10 at 200, 33.5 at 1000. A pixel is taken as hot only
when it is far above its image's mean *and* far above all eight of its neighbours in the same
channel (real highlights cover several pixels). The thresholds fire on no pixel of the DiLiGenT
dev split, its full-size ball, or psctl's synthetic test sets (syntest, syntest_dl and its
variants, svbrdf: sharp rendered highlights reach 100 times the mean with neighbours ten times
darker), so captures without such pixels give the same numbers as before.
"""

from __future__ import annotations

import numpy as np

from psctl.errors import few

HOT_LEVEL = 300.0  # a candidate is above this many times the image's mean inside the mask
HOT_RATIO = 4.0  # and above this many times the brightest of its 8 neighbours (same channel)
HOT_PIXEL_WORDS = "isolated hot pixel value(s)"  # in every hot-pixel note (the array API warns on them)


def clamp_hot_pixels(img: np.ndarray, mask: np.ndarray | None = None, level: float = HOT_LEVEL,
                     ratio: float = HOT_RATIO) -> tuple[np.ndarray, int]:
    """Hot pixels set to the brightest of their 8 neighbours.

    Args:
        img: [h, w, 3] (or [h, w]) float image, linear.
        mask: [h, w] bool or 0/1 float, the pixels the mean is taken over (None: all).
        level, ratio: a value v is hot when v > level * mean and v > ratio * max(neighbours);
            neighbours outside the image do not count; the mean counts negative values as 0.
    Returns:
        (image, number of values changed); the input array itself when none is (never modified).
    """
    x = img if img.ndim == 3 else img[..., None]
    h, w, c = x.shape
    inside = np.ones(h * w, np.float32) if mask is None else (np.asarray(mask).reshape(h * w) > 0).astype(np.float32)
    count = float(inside.sum()) * c
    if count == 0 or h * w < 2:
        return img, 0
    flat = x.reshape(h * w, c).astype(np.float32, copy=False)
    if float(flat.min()) < 0:  # noise about a subtracted black level: only the signal sets the level,
        flat = np.maximum(flat, 0.0)  # else noise in a dark frame (mean ~ 0) passes the level test
    with np.errstate(over="ignore"):
        total = inside @ flat  # BLAS: no masked copy
    if not np.isfinite(total).all():  # float32 overflow (values ~1e33 and up)
        total = inside.astype(np.float64) @ flat.astype(np.float64)
    mean = float(total.sum()) / count
    if not mean > 0:  # nothing lit
        return img, 0
    if not float(x.max()) > level * mean:  # almost always: a max is ~40x cheaper than a nonzero
        return img, 0
    ys, xs, cs = np.unravel_index(np.flatnonzero(x > level * mean), x.shape)
    neighbours = np.full(len(ys), -np.inf, np.float32)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == dx == 0:
                continue
            yy, xx = ys + dy, xs + dx
            ok = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
            v = np.full(len(ys), -np.inf, np.float32)
            v[ok] = x[yy[ok], xx[ok], cs[ok]]
            np.maximum(neighbours, v, out=neighbours)
    # neighbours at or below 0 (shadow, or noise about 0): the level test alone decides
    with np.errstate(over="ignore"):  # neighbours near float32's limit: inf, and nothing above it is hot
        hot = x[ys, xs, cs] > ratio * neighbours
    if not hot.any():
        return img, 0
    out = x.copy()
    out[ys[hot], xs[hot], cs[hot]] = np.maximum(neighbours[hot], 0.0)
    return (out if img.ndim == 3 else out[..., 0]), int(hot.sum())


def hot_pixel_notes(info: dict, names: list[str]) -> list[str]:
    """The note for a run whose ``info["hot_pixels"]`` ({image index: values set}) is not empty;
    ``names``: the images' names, by index."""
    hot = info.get("hot_pixels") or {}
    if not hot:
        return []
    idx = sorted(hot)
    listed = few([names[i] for i in idx])
    return [f"images: {sum(hot.values())} {HOT_PIXEL_WORDS} in {len(idx)} image(s) ({listed}) set to "
            f"their neighbours' level (over {HOT_LEVEL:g} times the image's mean and {HOT_RATIO:g} times every "
            "neighbour: a sensor's hot pixel?)"]
