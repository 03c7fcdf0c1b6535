"""Near point lights: the 1/r^2 falloff of lights at a finite distance, divided out of the images.

Photometric stereo (and every psctl network) assumes distant lights: one direction and one
intensity per image, the same at every pixel. Real rigs put point lights at a finite distance D
from the object, so over the object each image is brighter on the side facing its light, by
about 2 (l . X) / D in relative terms (X: the pixel's offset from the point where the listed
direction l holds). On DiLiGenT's development objects that gradient is measurable: D is
1,900-2,700 pixels, 16-23 object radii (`benchmarks/light_distance.py`, docs/near-lights.md), so
a light 45 degrees off the axis lights the near rim of a 120-pixel object about 7 % more than its
centre, and the far rim about 7 % less.

``NearLights`` describes such a rig with the listed directions: light k sits at ``distance``
pixels from ``centre`` (the mask's centroid by default) along direction k, and the camera is
orthographic (a pixel's offset in the image plane is its offset on the object; depth is taken
as that of the centre). psctl divides out the falloff only, and leaves the listed directions as
they are: the falloff needs D alone (where the listed directions hold moves each image's
factor by a constant, about an intensity error), the per-pixel directions also need that point,
which a benchmark does not give (docs/near-lights.md measures both).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psctl.errors import PsctlError


@dataclass(frozen=True)
class NearLights:
    """Point lights at ``distance`` pixels from ``centre`` (row, column; full-frame pixels)
    along the listed directions."""

    distance: float
    centre: tuple[float, float]

    def correction(self, light: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """What to multiply an image by to undo its light's falloff: |D l - X|^2 / D^2.

        light [3] (x right, y up, z toward the camera), rows [h], cols [w] (full-frame pixel
        indices of the region) -> float32 [h, w]; 1 at the centre, < 1 on the light's side.
        """
        d = self.distance
        x = (cols.astype(np.float64)[None, :] - self.centre[1]) / d  # x right, in units of D
        y = (self.centre[0] - rows.astype(np.float64)[:, None]) / d  # y up: rows grow downwards
        lx, ly, lz = (float(v) for v in light)
        # |l - X/D|^2 = |D l - X|^2 / D^2, without squaring D (a huge D would overflow)
        return ((lx - x) ** 2 + (ly - y) ** 2 + lz * lz).astype(np.float32)


def check_light_distance(distance: float | None) -> float | None:
    """``distance`` as a float (None stays None); a value that is not a positive number is a user
    error. Checked with the options, before any image is read (``near_lights`` also needs the
    object, which without a mask is found by reading them)."""
    if distance is None:
        return None
    try:
        # True is 1 to float(), and "2400" 2400: not what a number-valued option takes (as views, seed)
        if isinstance(distance, (bool, np.bool_, str, bytes)):
            raise TypeError
        d = float(distance)
    except (TypeError, ValueError):
        raise PsctlError(None, f"--light-distance must be a number of pixels, not {distance!r}") from None
    if not math.isfinite(d) or d <= 0:
        raise PsctlError(None, f"--light-distance must be a positive number of pixels, not {distance}")
    return d


def near_lights(distance: float | None, mask: np.ndarray, mask_path: Path | None = None,
                found: bool = False) -> NearLights | None:
    """``NearLights`` at ``distance`` pixels from the centroid of ``mask`` [H, W] (None: distant
    lights). A distance that is not a positive number, or that does not clear the object (a
    light inside it), is a user error; the latter names ``mask_path``, the file the mask came
    from (None: no file, e.g. a mask given as an array, or none at all). ``found``: ``mask`` is
    the object ``psctl.masks.find_object`` found (no mask file), which the error says."""
    d = check_light_distance(distance)
    if d is None:
        return None
    rows, cols = np.nonzero(mask)
    centre = (float(rows.mean()), float(cols.mean()))
    reach = float(np.sqrt(((rows - centre[0]) ** 2 + (cols - centre[1]) ** 2).max()))
    if d <= 2 * reach:  # the first-order picture (and any listed direction) would be meaningless
        what = ("the object found without a mask" if found else
                "the object (no mask: the whole frame)" if mask_path is None and mask.all() else "the mask")
        raise PsctlError(mask_path, f"--light-distance {d:g} pixels does not clear the object: {what} reaches "
                                    f"{reach:.0f} pixels from its centre (the distance is in image pixels, from "
                                    f"the object to the lights; it must be over twice that)")
    return NearLights(d, centre)


def near_note(near: NearLights, what: str) -> str:
    """The report's note on the lights' distance and where they sit; ``what``: what is done with it."""
    r, c = near.centre
    return (f"lights: points {near.distance:g} pixels from the object's centre (row {r:.0f}, column {c:.0f}): "
            f"{what}")
