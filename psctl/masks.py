"""The object's mask for LCNet and the light fit: found without a mask file, or a given mask
snapped to the object.

    >>> from psctl.masks import find_object, snap_mask, array_edge, array_shading
    >>> found = find_object(brightness, profiles)     # no mask: the lit object, or the whole frame
    >>> mask, note = snap_mask(array_edge(images, mask), mask)   # a mask wider than the object, cut to it

Without a mask, ``find_object`` finds what the lights light: by brightness before a dark
background, by shading (``shading_object``: a plane's one profile over the images) before a lit
one. With a mask, LCNet learnt exact masks and reads the mask's edge as the object's silhouette,
so ``snap_mask`` leaves out the pixels of a wider mask that are background (by brightness before
a dark background, by shading before a lit plane), and leaves the mask as given where it cannot
tell (``unsure_note``). The calibrated networks barely mind a wider mask and read it as given.
``psctl.lights`` (``run_lights``) and ``psctl.api`` call them;
docs/uncalibrated.md ("Without a mask", "A mask wider than the object", "Before a lit
background") has the measurements behind every threshold.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from psctl.arrays import bounding_box
from psctl.errors import ProgressFactory
from psctl.infer import NO_MASK_NETWORKS_WHY, lit_pixels

if TYPE_CHECKING:
    from psctl.io.capture import Capture, DecodeMemo

__all__ = ["FOUND_FILE", "FOUND_MAX_FRACTION", "FOUND_MIN_PIXELS", "FOUND_DARK_CONTRAST", "FOUND_NORMALS_BORDER",
           "FOUND_PROFILE_ELEMENTS", "FOUND_PROFILE_SIDE", "FOUND_BORDER", "FOUND_LEVEL", "FOUND_BAND",
           "FOUND_MID", "FOUND_RELIABLE", "FOUND_HOLE_DARK", "FOUND_MIN_IMAGES", "profile_grid", "block_samples",
           "border_ring", "FOUND_REFERENCE_MAX", "unlike_background", "shading_object", "object_parts",
           "FoundObject", "for_normals", "find_object", "SNAP_QUANTILE", "SNAP_FACTOR", "SNAP_DARK",
           "SNAP_KEEP", "SNAP_MIN_OUTSIDE", "SNAP_NOTE", "SNAP_MARGIN", "SNAP_EDGE", "SNAP_ALBEDO",
           "MaskEdge", "edge_box", "snap_mask", "unsure_note", "shading_snap", "array_edge", "snappable",
           "array_snap", "capture_edge", "capture_object", "capture_shading", "array_shading",
           "NO_MASK_WHY", "NO_MASK_PREFIX", "FOUND_READERS"]


# without a mask: the object found for LCNet and the light fit, 0 / 255 as a mask.png, to look at, or
# to copy into the capture folder as mask.png (named mask_*: never read as one of its images)
FOUND_FILE = "mask_found.png"


# --- the object without a mask ---------------------------------------------------------------

# Why: LCNet's input has a mask channel and the light fit reads the mask's pixels; given the whole
# frame, both take the background for the object (synthetic objects before a dark background: 33.09
# degrees, 6.45 with the mask). The object of a photometric stereo capture is what the lights light:
# the lit pixels (psctl.infer.lit_pixels) with their holes filled (shadowed parts inside the
# outline) found it as well as the true mask there (6.30), and on the DiLiGenT dev split's images
# as captured (reported only) the lights came out 3.11 degrees off against 6.76 from the whole
# frame (2.89 with the true masks; docs/uncalibrated.md, "Without a mask"). Before a lit background (grey
# or textured planes) brightness cannot find it (15-60 degrees either way), the shading below can
# (since session 64); a found region that covers nearly the whole frame is read as the whole
# frame, as before, and a background that is not dark, where shading is not used, gets a note.
FOUND_MAX_FRACTION = 0.9  # a found object over this share of the frame: the whole frame instead
FOUND_MIN_PIXELS = 100  # one under this (a lit speck in a dark scene): the whole frame instead
FOUND_DARK_CONTRAST = 0.15  # the unlit part's median brightness over the lit part's mean, above which the
# background is not dark (dark backgrounds: 0.018-0.085 on syntest at albedo 0.01, 0.021-0.087 under
# DiLiGenT-like lights, 0.008-0.074 on the dev split; lit planes and textures, their border not lit:
# 0.245-0.864; benchmarks/auto_mask_lights.py's scenes)
FOUND_NORMALS_BORDER = 0.25  # the normals networks read the whole frame where the object found covers more
# of the frame's border ring (border_ring) than this: no background around it (a surface that fills the
# frame with a dark part, a review: 8.66 -> 40.6 degrees with its dark half left without normals)


# A lit background (a table, a wall) is brighter than the object's shadows, so brightness cannot
# split them; its shading can: a plane facing the camera under distant lights has one profile over
# the images at every pixel (its albedo and texture scale it), which the frame's border gives. Its
# cast shadows only darken it, and nearly to black: a background pixel's ratios to that profile are
# its level (lit) or near 0 (shadowed), where an object pixel's spread in between, as its normal
# turns it toward and away from each light. Chosen on psctl's synthetic objects before lit planes
# and textures with their cast shadows (benchmarks/auto_mask_lights.py, docs/uncalibrated.md).
FOUND_PROFILE_ELEMENTS = 16 << 20  # the profiles' grid: images x cells within this (64 MB of float32)
FOUND_PROFILE_SIDE = 256  # ... and its longer side at most this many cells (a pixel of each block)
FOUND_BORDER = 0.03  # the background's profile: the median over the frame's outer ring, this share of its side
FOUND_LEVEL = 0.9  # a cell's level: this quantile of its ratios (the lit images' ratio, on the background)
FOUND_BAND = (0.2, 0.8)  # ratios between these fractions of the level: neither lit background nor its shadow
FOUND_MID = 0.08  # a cell with more than this share of its images in the band is the object
FOUND_RELIABLE = 0.2  # the images the ratios use: the background's profile over this share of its peak
FOUND_MIN_IMAGES = 8  # fewer reliable images: no percentiles to speak of, shading not used


def profile_grid(n: int, height: int, width: int) -> int:
    """The block size (pixels per cell side) of ``n`` images' profiles over a height x width frame."""
    f = max(1, math.ceil(max(height, width) / FOUND_PROFILE_SIDE))
    while n * math.ceil(height / f) * math.ceil(width / f) > FOUND_PROFILE_ELEMENTS:
        f += 1
    return f


def block_samples(image: np.ndarray, f: int) -> np.ndarray:
    """[H, W] -> [ceil(H/f), ceil(W/f)] float32: each f x f block's centre pixel (the last blocks'
    clipped to the frame). Samples, not means: a block that a cast shadow's edge crosses would
    average to a value between lit and shadowed, which is how the object's shading differs."""
    h, w = image.shape
    rows = np.minimum(np.arange(0, h, f) + f // 2, h - 1)
    cols = np.minimum(np.arange(0, w, f) + f // 2, w - 1)
    return np.asarray(image)[np.ix_(rows, cols)].astype(np.float32)  # (sampled, then converted: not the frame)


def border_ring(height: int, width: int) -> np.ndarray:
    """[height, width] bool: the frame's outer ring, FOUND_BORDER of its shorter side (at least 1 pixel)."""
    r = max(1, round(FOUND_BORDER * min(height, width)))
    ring = np.zeros((height, width), bool)
    ring[:r], ring[-r:], ring[:, :r], ring[:, -r:] = True, True, True, True
    return ring


FOUND_REFERENCE_MAX = 8192  # the background's profile: the median of at most this many of its cells (the
# frame's border ring has under 8k on find_object's grid of at most 256 cells a side: all of them)


def unlike_background(profiles: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The cells whose shading differs from the background's: ``profiles`` [N, h, w] float32 (each
    cell's grey value in each image, as captured, finite), ``reference`` [h, w] bool (cells of the
    background: the frame's border, or the pixels around a mask) -> (unlike [h, w] bool, each cell
    with over FOUND_MID of its images' ratios to the background's profile between lit and shadowed;
    level [h, w] float32, its FOUND_LEVEL quantile of them: a background cell's albedo, to scale);
    None where no reference cell is lit or fewer than FOUND_MIN_IMAGES images light the background."""
    p = profiles
    ref = np.flatnonzero(reference.ravel())
    ref = ref[::-(-len(ref) // FOUND_REFERENCE_MAX)] if len(ref) > FOUND_REFERENCE_MAX else ref  # (evenly)
    edge = p.reshape(len(p), -1)[:, ref].astype(np.float64)
    total = edge.sum(0)
    edge = edge[:, total > 0] / total[total > 0]  # each cell's profile, its albedo divided out
    if edge.shape[1] == 0:
        return None
    back = np.median(edge, axis=1)  # [N]: each image's share of the background's light
    use = back > FOUND_RELIABLE * back.max()
    if int(use.sum()) < FOUND_MIN_IMAGES:
        return None
    ratio = p[use] / back[use, None, None].astype(np.float32)
    level = np.quantile(ratio, FOUND_LEVEL, axis=0)
    between = (ratio > FOUND_BAND[0] * level) & (ratio < FOUND_BAND[1] * level)
    return between.mean(0) > FOUND_MID, level.astype(np.float32)


def shading_object(profiles: np.ndarray) -> np.ndarray | None:
    """The cells whose shading differs from the background's: ``profiles`` [N, h, w] (each cell's
    grey value in each image, as captured) -> [h, w] bool, or None where the frame's border does
    not agree on one profile (no plain background to tell the object from) or fewer than
    FOUND_MIN_IMAGES images light it."""
    from scipy import ndimage

    p = np.asarray(profiles, np.float32)  # (float32: the ratios' quantiles copy them, up to 64 MB each)
    ring = border_ring(*p.shape[1:])
    found = unlike_background(p, ring)
    if found is None:
        return None
    unlike = found[0]
    if unlike[ring].mean() > 0.5:  # the border is no one background
        return None
    # holes filled first: an object's rim may be its only part unlike the background (a face turned
    # to the camera shades as the background does), one or two cells thick where the grid is coarse
    obj = ndimage.binary_opening(ndimage.binary_fill_holes(unlike), np.ones((3, 3), bool))  # no specks
    return ndimage.binary_fill_holes(object_parts(obj))


def object_parts(region: np.ndarray, share: float = 0.1) -> np.ndarray:
    """[H, W] bool -> the connected parts of ``region`` of at least ``share`` of its largest part's
    pixels: the object's parts, not crumbs (specks of noise, a lit dust grain)."""
    from scipy import ndimage

    labels, count = ndimage.label(region)
    if count < 2:
        return np.asarray(region, bool)
    sizes = ndimage.sum(region, labels, range(1, count + 1))
    return np.isin(labels, 1 + np.nonzero(sizes >= share * sizes.max())[0])


@dataclass
class FoundObject:
    """What ``find_object`` found: ``mask`` [H, W] bool, or None for the whole frame; ``info``
    {pixels, frame_fraction, contrast, used} for the report; ``notes`` for the user, each
    after a prefix that says there was no mask (the report's "mask: none (no mask.png): ", the
    array API's warning's "mask=None: ")."""
    mask: np.ndarray | None
    info: dict
    notes: list[str]

    @property
    def normals_mask(self) -> np.ndarray | None:
        """The object the normals networks read (``psctl.api``): ``mask`` where it was found by
        brightness before a dark background (``for_normals``), else None (the whole frame)."""
        return self.mask if self.mask is not None and for_normals(self.info) else None


def for_normals(info: dict) -> bool:
    """Whether the normals networks may read an object ``find_object`` found (its ``info``):
    found by brightness before a dark background (contrast at most FOUND_DARK_CONTRAST) that
    surrounds it (it covers at most FOUND_NORMALS_BORDER of the frame's border ring). Before
    a lit one, what is left out may be the object's own: a surface that fills the frame, split by
    brightness or read as a background plane by shading (a review's 48 px relief, ensemble:
    5.02 -> 33.72 degrees with its flat part left without normals), so they read the whole frame."""
    return (info["by"] == "brightness" and info["contrast"] is not None and info["contrast"] <= FOUND_DARK_CONTRAST
            and info.get("border", 0.0) <= FOUND_NORMALS_BORDER)


FOUND_HOLE_DARK = 1.5  # a hole of the lit part whose median brightness is at most this times the unlit
# part's outside the object is the background seen through the object (a handle, a ring), not a hollow
# or a shadow inside the outline: left out (DiLiGenT pot1, pot2: 0.28-0.83; a hollow there 2.94)


def _lit_object(b: np.ndarray, lit: np.ndarray) -> tuple[np.ndarray, int]:
    """The lit pixels ``lit`` of brightness ``b`` -> (the object, the number of hole pixels left
    out). Holes are filled but those as dark as the background outside (FOUND_HOLE_DARK) and of
    FOUND_MIN_PIXELS or more; lit specks are dropped: parts under FOUND_MIN_PIXELS and a tenth of
    the largest (hot pixels, glints on the table: 16-1057 pixels on each object of the DiLiGenT
    dev split, each given normals 4 pixels around it)."""
    from scipy import ndimage

    labels, count = ndimage.label(lit)
    if count > 1:
        sizes = ndimage.sum(lit, labels, range(1, count + 1))
        small = (sizes < FOUND_MIN_PIXELS) & (sizes < 0.1 * sizes.max())
        lit = lit & ~np.isin(labels, 1 + np.flatnonzero(small))
    filled = ndimage.binary_fill_holes(lit)
    if not (~filled).any() or not (filled & ~lit).any():
        return filled, 0
    level = FOUND_HOLE_DARK * float(np.median(b[~filled]))
    labels, count = ndimage.label(filled & ~lit)
    index = range(1, count + 1)
    medians, sizes = np.asarray(ndimage.median(b, labels, index)), ndimage.sum(labels > 0, labels, index)
    through = np.isin(labels, 1 + np.flatnonzero((medians <= level) & (sizes >= FOUND_MIN_PIXELS)))  # (no pinholes)
    return filled & ~through, int(through.sum())


def find_object(brightness: np.ndarray, profiles: np.ndarray | None = None, reader: str = "lights") -> FoundObject:
    """The object of a capture without a mask, for LCNet and the light fit: ``brightness`` [H, W]
    each pixel's summed value over the images (as captured) -> the lit pixels
    (``psctl.infer.lit_pixels``, Otsu's split of log brightness) with holes filled, but holes as dark
    as the background around the object, and lit specks dropped (``_lit_object``). Where the
    unlit part is not dark (FOUND_DARK_CONTRAST: a lit background, which may be in the lit
    region) and ``profiles`` [N, h, w] are given (a pixel of each block of each image, ``profile_grid``),
    the cells whose shading differs from the background's instead (``shading_object``), when the
    frame's border agrees on one background. None (the whole frame) when the found region has
    under FOUND_MIN_PIXELS pixels or covers over FOUND_MAX_FRACTION of the frame; a note when
    the background is not dark. ``reader``: who reads the object, for the notes' words
    (``FOUND_READERS``: "lights", LCNet and the light fit; "normals", the normals networks;
    "sdps", all three)."""
    who, whole, off = FOUND_READERS[reader]
    b = np.asarray(brightness, np.float64)
    b = np.where(np.isfinite(b), b, 0.0)  # NaN (a bad pixel outside the object): dark; LCNet refuses it inside
    lit = lit_pixels(b)
    region, holes = _lit_object(b, lit)
    # rounded as the report gives it: for_normals reads the report's value, and the notes must agree with it
    # the unlit part's median: its mean counted the object's own dim rim where the background is black
    # (an exactly black one: a sphere's rim under oblique lights gave 0.13-0.17, median 0)
    contrast = round(float(np.median(b[~lit], overwrite_input=True) / b[lit].mean()), 4) if lit.any() and (~lit).any() and \
        b[lit].mean() > 0 else None
    not_dark = contrast is not None and contrast > FOUND_DARK_CONTRAST
    # a lit background: the unlit part is not dark, or the frame's border is lit (a background brighter
    # than a dark object: Otsu's lit part is the background, and its unlit part, the object, is dark;
    # or an object that fills the frame, whose border then agrees on no one profile: brightness stays)
    lit_background = not_dark or bool(lit[border_ring(*b.shape)].mean() > 0.5)
    by = "brightness"
    if lit_background and profiles is not None:
        p = np.asarray(profiles, np.float32)
        cells = shading_object(np.where(np.isfinite(p), p, np.float32(0)))
        if cells is not None:  # each pixel takes its cell's answer
            f = profile_grid(len(p), *b.shape)
            if cells.shape != (-(-b.shape[0] // f), -(-b.shape[1] // f)):
                raise ValueError(f"profiles {p.shape} are not profile_grid's cells of a {b.shape} frame")
            region, by = cells[np.arange(b.shape[0]) // f][:, np.arange(b.shape[1]) // f], "shading"
    frac = float(region.mean()) if region.size else 0.0
    used = int(region.sum()) >= FOUND_MIN_PIXELS and frac <= FOUND_MAX_FRACTION
    ring = border_ring(*b.shape)
    info = {"pixels": int(region.sum()), "frame_fraction": round(frac, 4),
            "contrast": None if contrast is None else round(contrast, 4), "by": by, "used": used,
            "border": round(float(region[ring].mean()), 4) if ring.any() else 0.0}
    how = ("the lit pixels, holes filled but those as dark as the background" if by == "brightness" else
           "the pixels whose shading over the images differs from the background's, holes filled")
    if used and reader != "lights" and not for_normals(info):
        # the normals networks read the whole frame (for_normals); sdps' LCNet and light fit the object
        lit = ("the background is lit (the object was told from it by shading)" if by == "shading" else
               f"the background is not dark (the unlit pixels' median brightness is {contrast:.2f} of the lit ones' mean)"
               if not_dark else f"the object found covers {info['border']:.0%} of the frame's border (no background "
                                f"around it)")
        why_not = (f"{lit}, and what is left out may be part of the object (a surface that fills the frame): "
                   f"{NO_MASK_NETWORKS_WHY}")
        if reader == "normals":
            return FoundObject(None, {**info, "used": False}, [why_not])
        who = "LCNet and the light fit"
        notes = [f"{who} read the object found by {by} ({how}: {info['pixels']} pixels, "
                 f"{frac:.0%} of the frame); a mask of the object is surer", f"the normals network: {why_not}"]
    elif used:
        notes = [f"{who} read the object found by {by} ({how}: {info['pixels']} pixels, "
                 f"{frac:.0%} of the frame); a mask of the object is surer"]
    else:
        part = "lit" if by == "brightness" else "found"
        why = ("nothing is lit" if by == "brightness" else "no part differs from the background") if \
            not region.any() else f"the {part} region covers {frac:.0%} of the frame" if \
            frac > FOUND_MAX_FRACTION else f"the {part} region has {int(region.sum())} pixels"
        notes = [f"no object found by {by} ({why}): {whole}"]
    if by == "shading" and used:
        notes.append("the background is lit: the object was told from it by shading, which assumes a background of "
                     "one plane under distant lights (synthetic objects before lit planes and textures, with their "
                     "shadows: lights 3.43 degrees off on average, 3.33 with their masks); give a mask of the object "
                     "where you can")
    elif not_dark:
        notes.append(f"the background is not dark (the unlit pixels' median brightness is {contrast:.2f} of the lit "
                     f"ones' mean): without a mask {off}; give a mask of the object")
    if used and by == "brightness":
        if holes:
            notes.append(f"{holes} pixels inside the object's outline are as dark as the background around it (the "
                         f"background seen through a handle or a ring?): left out of the object found; a mask.png "
                         f"is read as drawn")
        if not not_dark and info["border"] > FOUND_NORMALS_BORDER and reader != "normals":
            notes.append(f"the object found covers {info['border']:.0%} of the frame's border: it may take in a lit "
                         f"table or floor (read as the object, {off}); check {FOUND_FILE}, and give a mask of the "
                         f"object if it holds more than the object")
    return FoundObject(region if used else None, info, notes)


# --- a given mask snapped to the object ------------------------------------------------------

# A mask drawn wider than the object (by hand, or grown to be safe) moves the edge LCNet reads
# away from the object's contour, which it learnt on exact masks: on psctl's synthetic objects a
# mask 3 px wider put LCNet's lights 3.9 -> 10.5 degrees off (bunny before a dark plane, 8 px: 13.9)
# and sdps' normals 5.9 -> 17.5 (bunny in white fabric), while the normals networks did not mind (the
# ensemble within 0.25 degrees on 9 objects). A mask pixel never brighter, in any image, than the
# background around the mask is background: LCNet and the light fit read the mask without such pixels.
# Where brightness cannot tell (a lit background: a table), one whose shading over the images is the
# background's, where those pixels look like the background drawn into the mask (shading_snap; since
# session 70, docs/uncalibrated.md).
SNAP_QUANTILE = 0.99  # the background's level: this quantile of the peaks outside the mask (noise, specks)
SNAP_FACTOR = 1.5  # mask pixels whose peak is at most this times that level are background
SNAP_DARK = 0.15  # ... only where that level is under this share of the kept pixels' median peak (a dark
# background: before a lit one, a dark part of the object may be no brighter than the table)
SNAP_KEEP = 0.25  # ... and where they are at least this share of the mask (else the highlights of a
# shiny object before a lit table, say: the shading snap instead); the shading snap keeps at least this
# share too (else the mask as given: a coin's flat face around a small relief shades as the table does)
SNAP_MIN_OUTSIDE = 100  # fewer pixels outside the mask: no background to measure, the mask as given
SNAP_NOTE = 0.02  # the mask as given where the snap would leave out no more than this share of it (exact
# enough: the dev split's masks lose 0-0.8%, and bear's 0.8% cost its lights 0.36 degrees), else a note
SNAP_MARGIN = 16  # before a lit background, the shading snap's background: the pixels outside the mask
# within this many of its bounding box (their median profile, as find_object's frame border gives it)
SNAP_EDGE = 0.5  # ... which leaves out pixels only where they hold at least this share of the mask's edge
SNAP_ALBEDO = 1.5  # ... and their albedo is within this factor of the surroundings' (medians)


@dataclass
class MaskEdge:
    """What ``snap_mask`` reads of the images, in one read (``capture_edge``, ``array_edge``):
    ``peak`` [H, W] float32, each pixel's brightest value over the images and channels (as
    captured; NaN and negatives 0, inf kept); ``profiles`` [N, h, w] float32, grey samples
    (``block_samples``, a pixel of each ``grid`` x ``grid`` block) of ``box``, the mask's bounding
    box grown by SNAP_MARGIN (``edge_box``), as decoded (``snap_mask`` and ``shading_snap`` read
    non-finite values and negatives as 0)."""
    peak: np.ndarray
    profiles: np.ndarray
    box: tuple[slice, slice]
    grid: int


def edge_box(mask: np.ndarray, n: int) -> tuple[tuple[slice, slice], int]:
    """The box and grid of ``n`` images' profiles for the snap: the mask's bounding box grown by
    SNAP_MARGIN (the whole frame for an empty mask), every pixel where n x its pixels fit in
    FOUND_PROFILE_ELEMENTS, else a pixel of each f x f block."""
    box = bounding_box(mask, SNAP_MARGIN) if mask.any() else (slice(0, mask.shape[0]), slice(0, mask.shape[1]))
    bh, bw = box[0].stop - box[0].start, box[1].stop - box[1].start
    f = 1
    while n * math.ceil(bh / f) * math.ceil(bw / f) > FOUND_PROFILE_ELEMENTS:
        f += 1
    return box, f


def snap_mask(edge: MaskEdge, mask: np.ndarray) -> tuple[np.ndarray, str | None]:
    """The object within a user's mask, for LCNet and the light fit: ``edge`` (what one read of
    the images gives, ``MaskEdge``), ``mask`` [H, W] bool -> (the mask snapped or as given, the note
    that says so or None).

    Before a dark background, the mask without its pixels never brighter than SNAP_FACTOR x the
    background's level (the SNAP_QUANTILE of the peaks outside the mask), holes filled, parts under
    a tenth of the largest dropped. It is dark where that level is at most SNAP_DARK of the
    brighter pixels' median peak and those are at least SNAP_KEEP of the mask and FOUND_MIN_PIXELS.
    Before a lit one, the mask without its pixels that shade over the images as the background
    around it does (``shading_snap``, with its guards), where at least SNAP_KEEP of the mask is kept.
    The mask as given where fewer than SNAP_MIN_OUTSIDE pixels lie outside it, where neither can
    tell, where under FOUND_MIN_PIXELS would be kept, and where it would leave out no more than
    SNAP_NOTE of the mask (every snap gets a note; a mask kept as given before a background that is
    not one plane gets ``unsure_note``'s, where its edge shades as that background's middle does)."""
    from scipy import ndimage

    mask = np.asarray(mask, bool)
    if not snappable(mask):
        return mask, None
    p = np.where(np.isfinite(edge.peak), np.maximum(edge.peak, 0.0), 0.0)
    outside = p[~mask]
    level = float(np.quantile(outside, SNAP_QUANTILE))
    bright = mask & (p > SNAP_FACTOR * level)
    n = int(np.count_nonzero(bright))
    if n >= max(SNAP_KEEP * np.count_nonzero(mask), FOUND_MIN_PIXELS) and \
            level <= SNAP_DARK * float(np.median(p[bright])):
        obj, by = object_parts(ndimage.binary_fill_holes(bright) & mask), "brightness"  # (a mask's own holes stay)
    else:  # a lit background (or nothing brighter than it): its shading, where it is one background
        (obj, one), by = shading_snap(edge, mask), "shading"
        if obj is None:
            return mask, None
    total, kept = int(np.count_nonzero(mask)), int(obj.sum())
    if kept < max(FOUND_MIN_PIXELS, SNAP_KEEP * total if by == "shading" else 0) or kept >= (1.0 - SNAP_NOTE) * total:
        return mask, None
    if by == "shading" and not one:  # not one background: the mask as given (what would be cut can be a face)
        return mask, unsure_note(total - kept, total)
    why = ("are never brighter than the background around it" if by == "brightness" else
           "shade over the images as the background around it does")
    return obj, (f"{total - kept} of the mask's {total} pixels ({(total - kept) / total:.0%}) {why} (or are specks "
                 f"apart from the object): LCNet and the light fit read the mask without them (LCNet learnt exact "
                 f"masks: on a synthetic bunny one 3 px wider put its lights 3.9 -> 10.5 degrees off); --no-snap "
                 f"(snap=False) reads it as given")


def unsure_note(left: int, total: int) -> str:
    """The note for a mask left as given because the cells around it do not agree on one
    background (a curved backdrop, near lights), where ``shading_snap`` would have left out
    ``left`` of its ``total`` pixels, holding at least half of its edge, every other guard passing:
    a mask likely drawn wider than the object, as LCNet reads its edge as the object's outline (an
    exact mask of a flat face turned to the camera can get it too: the note says so)."""
    return (f"{left} of the mask's {total} pixels, most of its edge among them, shade over the images as "
            f"the middle of the background around it does, but that background is not one plane under distant "
            f"lights (a curved backdrop, near lights?), where a face turned to the camera can shade so too: the "
            f"mask is read as given. If it is wider than the object, draw it tight: LCNet reads its edge as the "
            f"object's outline (on 31 such synthetic cases with masks 3-8 px wider, lights 21 degrees off on "
            f"average)")


def shading_snap(edge: MaskEdge, mask: np.ndarray) -> tuple[np.ndarray | None, bool]:
    """The object within ``mask`` [H, W] bool where its brightness cannot tell (a lit background):
    the mask's cells whose shading differs from that of the cells around it (``unlike_background``,
    the reference being the box's cells outside the mask) and its cells on the frame's edge (the
    object may run on past it), holes filled, parts under a tenth of the largest dropped -> ([H, W]
    bool within the mask or None, whether the cells around the mask agree on one background: over
    half of them like it). ``snap_mask`` takes the cut only where they agree (before a curved
    backdrop it took a coin's flat face, docs/uncalibrated.md, "Session 71"; else ``unsure_note``).
    None (the mask as given) where the images do not light the surroundings (FOUND_MIN_IMAGES), and
    where what would be left out does not look like the background drawn into the mask: it holds
    under SNAP_EDGE of the mask's edge (a wider mask's margin runs all along it; a few patches of an
    exact mask's object that shade like the background, a dragon's hollows, do not), or its albedo
    is not the surroundings' (within SNAP_ALBEDO: a coin's flat face, which shades as the table
    does, is not the table). No opening, unlike ``shading_object``: at a pixel's grain it would cut
    an object's thin parts."""
    from scipy import ndimage

    rows, cols = edge.box
    f = edge.grid
    inner = np.asarray(mask, bool)[rows, cols]
    cells = block_samples(inner, f).astype(bool)  # whether each cell's sampled pixel is in the mask
    if np.count_nonzero(~cells) * f * f < SNAP_MIN_OUTSIDE:
        return None, True
    p = np.nan_to_num(np.asarray(edge.profiles, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    np.maximum(p, 0.0, out=p)
    found = unlike_background(p, ~cells)
    del p
    if found is None:
        return None, True
    unlike, level = found
    one = bool(unlike[~cells].mean() <= 0.5)
    h, w = mask.shape
    rim = np.zeros_like(cells)  # the cells on the frame's edge
    rim[0, :] |= rows.start == 0
    rim[-1, :] |= rows.stop == h
    rim[:, 0] |= cols.start == 0
    rim[:, -1] |= cols.stop == w
    obj = ndimage.binary_fill_holes(object_parts(ndimage.binary_fill_holes((unlike | rim) & cells)))
    out_cells = cells & ~obj
    border = cells & ~ndimage.binary_erosion(cells, border_value=1) & ~rim  # the mask's edge, in the frame
    if not out_cells.any() or not border.any() or out_cells[border].mean() < SNAP_EDGE:
        return None, one
    around, left = float(np.median(level[~cells])), float(np.median(level[out_cells]))
    if not (around > 0 and left > 0 and 1 / SNAP_ALBEDO <= left / around <= SNAP_ALBEDO):
        return None, one
    px = obj[np.arange(inner.shape[0]) // f][:, np.arange(inner.shape[1]) // f] & inner  # (a mask's own holes stay)
    out = np.zeros(mask.shape, bool)
    out[rows, cols] = px
    return out, one


def _edge(images: Iterable[np.ndarray], n: int, mask: np.ndarray,
          advance: Callable[[int], None] | None = None) -> MaskEdge:
    """``MaskEdge`` of ``n`` images [H, W, C] (or [H, W]) taken one at a time."""
    box, f = edge_box(mask, n)
    bh, bw = box[0].stop - box[0].start, box[1].stop - box[1].start
    peak = np.zeros(mask.shape, np.float32)
    profiles = np.zeros((n, -(-bh // f), -(-bw // f)), np.float32)
    for k, img in enumerate(images):
        img = img[..., None] if img.ndim == 2 else img
        np.fmax(peak, img.max(axis=-1), out=peak)  # (fmax: a NaN pixel stays 0)
        profiles[k] = block_samples(img[box].sum(-1, dtype=np.float32), f) / img.shape[-1]
        if advance is not None:
            advance(1)
    np.maximum(peak, 0.0, out=peak)
    return MaskEdge(peak, profiles, box, f)


def array_edge(images: np.ndarray, mask: np.ndarray) -> MaskEdge:
    """``capture_edge`` of in-memory images [N, H, W, 3] (or [N, H, W] grey)."""
    return _edge(images, len(images), np.asarray(mask, bool))


def snappable(mask: np.ndarray) -> bool:
    """Whether ``snap_mask`` can measure a background around ``mask`` (SNAP_MIN_OUTSIDE pixels
    outside it, and some in it): where not, the images need not be read for it."""
    mask = np.asarray(mask, bool)
    return bool(mask.any()) and np.count_nonzero(~mask) >= SNAP_MIN_OUTSIDE


def array_snap(images: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray | None, str | None]:
    """``snap_mask`` of in-memory images with ``mask`` (None: (None, None)), as a folder's mask file
    is snapped; the edge read only where the snap can measure the background."""
    if mask is None or not snappable(mask):
        return mask, None
    return snap_mask(array_edge(images, mask), mask)


def capture_edge(capture: "Capture", mask: np.ndarray, progress: "ProgressFactory | None" = None,
                 prefetch_mb: int | None = None) -> MaskEdge:
    """``MaskEdge`` of a capture's images, as captured (its light_intensities.txt not applied),
    for ``snap_mask``: one read of the images. Nothing kept in a decode memo: whole frames there
    would crowd out the crops the later passes keep. ``prefetch_mb``: the read-ahead's bound
    (``psctl.io.prefetch``; None: LCNet's, ``psctl.lights.DEFAULT_LIGHTS``)."""
    from psctl.io.capture import iter_images
    from psctl.io.prefetch import prefetch

    raw = replace(capture, intensities=np.ones_like(capture.intensities))
    box = (slice(0, capture.height), slice(0, capture.width))
    advance = (progress or (lambda d, t: (lambda k: None)))(f"{capture.name}: reading the mask's edge", capture.n_images)
    with prefetch(capture.image_paths, box, (capture.width, capture.height), _prefetch_mb(prefetch_mb)) as pf:
        return _edge(iter_images(raw, box, decoded=pf), capture.n_images, np.asarray(mask, bool), advance)


def capture_object(capture: "Capture", mask: np.ndarray, config: dict, progress: "ProgressFactory | None" = None,
                   memo: "DecodeMemo | None" = None,
                   reader: str = "lights", snap: bool = True) -> tuple[np.ndarray, dict, FoundObject | None, str | None]:
    """What LCNet and the light fit read of a capture: (mask, LCNet's config, found, the snap's
    note). With a mask file, ``mask`` snapped to the object (``snap_mask`` of one read's
    ``capture_edge``, with its note or None), ``config`` as given and None; without one, the object ``find_object``
    finds in one read of the images (``capture_shading``: brightness and profiles; ``memo``
    keeps them), with LCNet's exposure guard reading it as a mask, or where none is found the
    whole frame (``mask``), and no note here (``found.notes``). ``reader``: as ``find_object``'s.
    ``snap`` False: a mask file as given (no read). The read's read-ahead: ``config``'s
    "prefetch_mb", else LCNet's default."""
    if capture.mask_path is not None:  # (no read where snap_mask could not measure the background)
        if not snap or not snappable(mask):
            return mask, config, None, None
        snapped, note = snap_mask(capture_edge(capture, mask, progress, config.get("prefetch_mb")), mask)
        return snapped, config, None, note
    found = find_object(*capture_shading(capture, progress, memo, config.get("prefetch_mb")), reader=reader)
    if found.mask is None:
        return mask, config, found, None
    return found.mask, {**config, "exposure_pixels": "found"}, found, None  # its mean, as a mask's (words apart)


def capture_shading(capture: "Capture", progress: "ProgressFactory | None" = None,
                    memo: "DecodeMemo | None" = None, prefetch_mb: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """What ``find_object`` reads of a capture, in one read of its images: (brightness [H, W]
    float64, each pixel's sum over the images and channels as captured, its light_intensities.txt
    not applied; the profiles it tells a lit background by, [N, h, w] float32 grey, a pixel of
    each block: ``profile_grid``, ``block_samples``). ``memo`` keeps the decoded images (the whole
    frame) for the passes after, where they fit. ``prefetch_mb``: as ``capture_edge``'s."""
    from psctl.io.capture import iter_images
    from psctl.io.prefetch import prefetch

    raw = replace(capture, intensities=np.ones_like(capture.intensities))
    box = (slice(0, capture.height), slice(0, capture.width))
    advance = (progress or (lambda d, t: (lambda k: None)))(f"{capture.name}: finding the object", capture.n_images)
    with prefetch(capture.image_paths, box, (capture.width, capture.height), _prefetch_mb(prefetch_mb)) as pf:
        return _shading(iter_images(raw, box, decoded=pf, memo=memo), capture.n_images, capture.height,
                        capture.width, advance)


def _prefetch_mb(mb: int | None) -> int:
    """The read-ahead bound of a mask's read: ``mb``, or where None LCNet's (read at the call, so
    that a change to ``psctl.lights.DEFAULT_LIGHTS`` holds)."""
    if mb is not None:
        return mb
    from psctl.lights import DEFAULT_LIGHTS

    return DEFAULT_LIGHTS["prefetch_mb"]


def array_shading(images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``capture_shading`` of in-memory images [N, H, W, 3] (or [N, H, W] grey)."""
    images = images[..., None] if images.ndim == 3 else images
    return _shading(images, *images.shape[:3])


def _shading(images: Iterable[np.ndarray], n: int, h: int, w: int,
             advance: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The brightness and profiles of ``n`` images [h, w, C], taken one at a time (no float64 copy
    of them all)."""
    f = profile_grid(n, h, w)
    total = np.zeros((h, w), np.float64)
    profiles = np.zeros((n, -(-h // f), -(-w // f)), np.float32)
    for k, img in enumerate(images):
        grey = img.sum(-1, dtype=np.float64)
        total += grey
        profiles[k] = block_samples(grey, f) / img.shape[-1]
        if advance is not None:
            advance(1)
    return total, profiles


# --- notes -----------------------------------------------------------------------------------

# LCNet's input has a mask channel, and the light fit reads the mask's pixels: without one both take
# the background for the object (a QA helper's finding: no word was said)
NO_MASK_WHY = ("LCNet and the light fit take the whole frame for the object; a mask of the object makes the lights "
               "more accurate (read whole, examples/bumpy_sphere gave 6.54 degrees, 2.45 with its mask; synthetic "
               "objects before a dark background 33.0, 6.45 with theirs)")
NO_MASK_PREFIX = "mask: none (no mask.png): "  # the array API warns "mask=None: " instead
# find_object's reader -> (who reads the object, why the whole frame is worse, what a lit background may do)
_LIGHTS_OFF = "the lights may be far off (synthetic objects before a lit plane: 15-60 degrees)"
FOUND_READERS = {
    "lights": ("LCNet and the light fit", NO_MASK_WHY, _LIGHTS_OFF),
    "normals": ("the networks", NO_MASK_NETWORKS_WHY, "the object found may take in some of the background"),
    "sdps": ("LCNet, the light fit and the normals network", NO_MASK_WHY, _LIGHTS_OFF),
}
