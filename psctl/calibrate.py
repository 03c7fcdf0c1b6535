"""Light calibration from a sphere photographed under the object's lights (``psctl calibrate``).

Capture rigs calibrate their lights with a sphere of known shape placed where the object goes:

- **chrome** (a mirror ball): each light shows as one small highlight. Its position on the
  sphere gives the surface normal n there, and the light's direction is the view direction
  mirrored about n: l = 2 (n . v) n - v. Directions only: a mirror's highlight is usually
  saturated, and says nothing reliable about the light's intensity.
- **matte** (a white or grey ball, as near Lambertian as can be had): each lit pixel obeys
  I = n . b with b = e * albedo * l, so a least-squares fit over the lit pixels (attached
  shadows, saturated pixels and highlights trimmed) gives the direction b / |b| and, per colour
  channel, the relative intensity.

The sphere's outline comes from mask.png (a circle fitted to its edge), from ``circle`` (x, y, r
in pixels), or, for a matte sphere without either, from the brightest value each pixel takes
over the images. Pixel coordinates: x is the column and y the row, the top-left pixel's centre
is (0, 0). The camera is taken as orthographic (view direction (0, 0, 1) at every pixel), as
psctl's methods take it; docs/calibration.md says what that costs off the optical axis.

Directions are unit vectors with x right, y up and z toward the camera (DiLiGenT's convention).
"""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Sequence

import numpy as np

from psctl.errors import ProgressFactory, PsctlError, _short, check_bool, check_path, check_progress, few, is_number
from psctl.hotpixels import HOT_RATIO

if TYPE_CHECKING:
    from psctl.io.capture import Capture

SPHERES = ("chrome", "matte")

DEFAULT_CALIBRATE = {
    # share of the radius whose pixels are used: the outermost ones mix sphere and background, and
    # their steep normals turn a small error in the outline into a large angle
    "rim": 0.97,
    # chrome: a highlight is a connected region above the level b + highlight * (peak - b), b the
    # sphere's ``base``-th percentile (the diffuse glow of a ball that is glossy rather than a
    # mirror, which would pull a lower level's centroid; find_highlight). 0.5 and 90 of highlight
    # 0.1-0.7 and base 0, 50, 90 had the lowest error summed over benchmarks/calibrate_sphere.py's
    # mirrors and glossy ball (docs/calibration.md)
    "highlight": 0.5,
    "base": 90.0,
    # matte: pixels whose fitted shading n . l is below ``lit`` times |b| are left out (the shadow's edge,
    # where the ball's surface is least Lambertian), as are residuals beyond ``trim`` robust
    # standard deviations (highlights, dust); ``iterations`` rounds of fit and trim (lit 0.2 of
    # 0.05-0.3 and trim 4 of 2-4, chosen likewise on its matte and glossy balls)
    "lit": 0.2,
    "trim": 4.0,
    "iterations": 5,
    # matte: fit a constant per image too (I = n . b + c): an offset the images keep (a black level,
    # room light, no ambient.png) otherwise tilts the fitted light (docs/calibration.md, "Offset")
    "offset": False,
    # the camera: None, orthographic (the view (0, 0, 1) everywhere, as psctl's normal estimators
    # take it); else a pinhole of this focal length in pixels, whose principal point is
    # ``principal`` ([x, y] in pixels; None: the image's centre). An off-axis sphere then sees the
    # camera, and a mirror its lights, from its own angle (docs/calibration.md, "Perspective");
    # focal "exif": the images' EXIF headers give it (psctl.io.images.exif_focal)
    "focal": None,
    "principal": None,
    "min_radius": 8.0,  # pixels: smaller spheres give directions too coarse to be worth writing
    "min_pixels": 30,  # matte: lit pixels needed to fit a light
}

# chrome: a highlight whose peak is under this many times the sphere's 90th percentile (in the median image) is
# no mirror's: benchmarks/calibrate_sphere.py's spheres gave 1.09-1.10 for matte balls, 1.61-1.68 for its
# glossy ball, 231-765 for its mirrors (median images; single ones down to 134). Clipped peaks are left out
# (overexposed balls have broad highlights, noted apart)
MATTE_LIKE = 1.3

# each setting's allowed range (inclusive); iterations and min_pixels are whole numbers
DARK_LIGHT = 0.02  # an image whose highlight or intensity is under this share of the median's: no light
_RANGES = {"rim": (0.1, 1.0), "highlight": (0.0, 0.99), "base": (0.0, 100.0), "lit": (0.0, 0.9), "trim": (0.5, 100.0),
           "iterations": (1, 100), "min_radius": (1.0, 1e6), "min_pixels": (3, 1e9)}
_FLAGS = ("offset",)  # settings that are true or false
_CAMERA = ("focal", "principal")  # None, or checked by _check_camera
EXIF = "exif"  # focal: the images' EXIF headers say it


def check_config(config: dict | None) -> dict:
    """DEFAULT_CALIBRATE with ``config``'s settings over it; an unknown key, or a value that is
    not a finite number in its range, is an error naming it."""
    if config is None:
        return dict(DEFAULT_CALIBRATE)
    if not isinstance(config, dict):
        raise PsctlError(None, f"config must be a dict of settings (DEFAULT_CALIBRATE's keys), not "
                               f"{type(config).__name__}")
    unknown = sorted(set(config) - set(DEFAULT_CALIBRATE))
    if unknown:
        raise PsctlError(None, f"config: unknown setting {unknown[0]!r}; known: {', '.join(DEFAULT_CALIBRATE)}")
    for k, v in config.items():
        if k in _CAMERA:
            continue  # checked, and parsed, below
        if k in _FLAGS:
            if not isinstance(v, (bool, np.bool_)):
                raise PsctlError(None, f"config: {k} must be true or false, not {v!r}")
            continue
        lo, hi = _RANGES[k]
        whole = k in ("iterations", "min_pixels")
        ok = is_number(v) and lo <= float(v) <= hi and (not whole or float(v).is_integer())
        if not ok:
            raise PsctlError(None, f"config: {k} must be a {'whole ' if whole else ''}number in [{lo:g}, {hi:g}], "
                                   f"not {_short(v)}")
    return {**DEFAULT_CALIBRATE, **config, **{k: _check_camera(k, config[k]) for k in _CAMERA if k in config}}


OUTPUT_FILES = {"light_directions": "light_directions.txt", "light_intensities": "light_intensities.txt",
                "lights": "lights.png", "sphere": "sphere.png"}
REPORT_FILE = "calibration_report.json"
# matte, without ``offset``: the median image's constant (over its lit mean) above which a note
# says the images keep an offset. On benchmarks/calibrate_sphere.py's balls (8 bits) no black level
# gave medians of -0.003 to -0.018, one of 0.02 of full scale (about 1.1 degrees of error) 0.023 to
# 0.045; DiLiGenT's glossy ball, whose shading falls off faster than a cosine, gives -0.13
# (docs/calibration.md, "Offset")
OFFSET_NOTE = 0.02
COMMAND = "calibrate"  # the outputs list's name (psctl.io.atomic.outputs_list)
# without a mask or --circle, the images decoded to find a matte sphere are kept, up to this many
# MB, for the pass that fits the lights (psctl.io.capture.DecodeMemo) instead of decoded again
MEMO_MB = 256


@dataclass(frozen=True)
class Circle:
    """The sphere's outline in the image: centre (x column, y row; pixel centres at whole numbers)
    and radius r in pixels. ``source``: where it came from (mask.png's name, "--circle", "images");
    ``rms``: the fitted outline's RMS distance from the circle in pixels (None when given)."""

    x: float
    y: float
    r: float
    source: str
    rms: float | None = None
    # [P, 2] (x, y): the outline points the circle was fitted to (its inliers), where it came from
    # an outline: through a pinhole the sphere's outline is an ellipse, and its cone is fitted to them
    outline: np.ndarray | None = field(default=None, repr=False, compare=False)


# --- the sphere's outline ----------------------------------------------------------------------

def _edge_points(mask: np.ndarray) -> np.ndarray:
    """[P, 2] (x, y): midpoints between each pair of 4-neighbour pixels of which one is in the
    mask and one is not. Where the mask meets the image's border there is no pair, so a sphere cut
    by the border is fitted to its own outline only."""
    pts = []
    for dy, dx in ((0, 1), (1, 0)):
        a, b = mask[: mask.shape[0] - dy, : mask.shape[1] - dx], mask[dy:, dx:]
        ys, xs = np.nonzero(a ^ b)
        pts.append(np.stack([xs + dx / 2, ys + dy / 2], 1))
    return np.concatenate(pts).astype(np.float64)


def _circle_fit(p: np.ndarray) -> tuple[float, float, float]:
    """Least-squares circle through points [P, 2]: the algebraic fit (x^2 + y^2 + D x + E y + F = 0),
    then Gauss-Newton on the geometric distances (the algebraic fit is biased on short arcs)."""
    A = np.c_[p, np.ones(len(p))]
    D, E, F = np.linalg.lstsq(A, -(p**2).sum(1), rcond=None)[0]
    cx, cy = -D / 2, -E / 2
    r = np.sqrt(max(cx * cx + cy * cy - F, 1e-12))
    for _ in range(10):
        dx, dy = p[:, 0] - cx, p[:, 1] - cy
        d = np.maximum(np.hypot(dx, dy), 1e-12)
        J = np.stack([-dx / d, -dy / d, -np.ones_like(d)], 1)
        step = np.linalg.lstsq(J, -(d - r), rcond=None)[0]
        cx, cy, r = cx + step[0], cy + step[1], r + step[2]
        if np.abs(step).max() < 1e-6:
            break
    return float(cx), float(cy), float(abs(r))


def _check_camera(key: str, value: object) -> "float | tuple[float, float] | None":
    """The checked value of config ``focal`` (a float) or ``principal`` (x, y), or None."""
    if value is None:
        return None
    if key == "focal":
        if isinstance(value, str):
            if value.strip().lower() == EXIF:
                return EXIF
            with contextlib.suppress(ValueError):
                value = float(value)  # the command line's text
        if not is_number(value) or not 1.0 <= float(value) <= 1e7:
            raise PsctlError(None, f"--focal must be the camera's focal length in pixels (a number in [1, 1e7]) or "
                                   f"'exif' (read from the images), not {_short(value)}")
        return float(value)
    try:
        xy = [float(v) for v in (value.split(",") if isinstance(value, str) else value)]  # type: ignore[union-attr]
    except (TypeError, ValueError, OverflowError):
        xy = []
    if len(xy) != 2 or not all(np.isfinite(xy)) or max(map(abs, xy)) > 1e7:
        raise PsctlError(None, f"--principal must be the principal point as X,Y in pixels (two finite numbers, "
                               f"each within 1e7 of 0), not "
                               f"{_short(value)}")
    return xy[0], xy[1]


def camera_config(cfg: dict, shape: tuple[int, int]) -> tuple[float, float, float] | None:
    """(focal, principal x, principal y) in pixels from a checked config, or None (orthographic)."""
    if cfg["focal"] is None:
        if cfg["principal"] is not None:
            raise PsctlError(None, "--principal needs --focal (the camera's focal length in pixels)")
        return None
    if cfg["focal"] == EXIF:
        raise PsctlError(None, "focal 'exif' reads the images' files (run_calibrate, psctl calibrate); with arrays "
                               "give the focal length in pixels")
    p = cfg["principal"]
    px, py = ((shape[1] - 1) / 2, (shape[0] - 1) / 2) if p is None else p  # (checked: a pair of floats)
    return float(cfg["focal"]), float(px), float(py)


SQUARE_PIXELS = 0.005  # --K: fx and fy may differ by this fraction (their mean is the one focal length)


def camera_from_K(K: "str | os.PathLike | np.ndarray") -> tuple[float, tuple[float, float], str]:
    """(focal, (cx, cy), where from) of a 3 x 3 camera matrix (a file or an array) whose pixels are
    square: the sphere's pinhole has one focal length."""
    from psctl.depth import check_intrinsics, read_intrinsics

    path = Path(check_path("K", K)) if isinstance(K, (str, os.PathLike)) else None  # else an array
    M = read_intrinsics(path) if path is not None else check_intrinsics(K)
    fx, fy = float(M[0, 0]), float(M[1, 1])
    if abs(fx - fy) > SQUARE_PIXELS * max(fx, fy):
        raise PsctlError(path, f"fx {fx:g} and fy {fy:g} differ by over 0.5 %: psctl calibrate's pinhole has square "
                               "pixels; resample the images to square pixels first")
    if max(fx, fy) > 1e7:
        raise PsctlError(path, f"focal length {max(fx, fy):g} pixels is above 1e7; leave out --K (orthographic)")
    return (fx + fy) / 2, (float(M[0, 2]), float(M[1, 2])), f"K: {os.path.abspath(path)}" if path is not None else "K"


def exif_camera_focal(paths: Sequence[Path]) -> tuple[float, str]:
    """The focal length in pixels that every image's EXIF gives (``psctl.io.images.exif_focal``),
    and how the first image's was found; images whose focal lengths differ by over 1 % (a zoom
    turned between shots) are an error naming the first that differs."""
    from psctl.io.images import exif_focal

    f0, how = exif_focal(paths[0])
    for p in paths[1:]:
        f, _ = exif_focal(p)
        if abs(f - f0) > 0.01 * f0:
            raise PsctlError(p, f"its EXIF focal length is {f:.0f} pixels, {paths[0].name}'s {f0:.0f}: one camera "
                                "setting is needed for all the images (was the lens zoomed?); give --focal F")
    return f0, how


def _check_offset(cfg: dict, sphere: str) -> None:
    """A constant is fitted on matte spheres only: asked for on a chrome one (by --offset or the
    config), it is an error rather than silently unused."""
    if cfg["offset"] and sphere != "matte":
        raise PsctlError(None, "--offset (config offset) is for a matte sphere (a chrome sphere's highlights need no "
                               "constant)")


def fit_circle(mask: np.ndarray, source: str = "mask", where: Path | None = None,
               config: dict | None = None, camera: tuple[float, float, float] | None = None) -> Circle:
    """The circle that best fits the outline of ``mask``'s largest connected region.

    Edge points more than max(1.5 px, 3 robust standard deviations) from a first fit are left
    out and the circle fitted again (a stand or a fingerprint cutting into the outline). A
    ``PsctlError`` naming ``where`` when the region is too small, or not round: its outline
    further than max(1 px, 2 % of r) from the circle on average, or under half of it on the circle.
    With ``camera`` (focal, principal x, principal y: a pinhole), an off-axis sphere's outline is
    an ellipse: the distances, the trimming and the roundness are then the outline rays' from the
    sphere's cone (``pinhole_cone``), in pixels at the circle's scale.
    """
    from scipy import ndimage

    cfg = check_config(config)
    mask = np.asarray(mask, bool)
    labels, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    if n == 0:
        raise PsctlError(where, "holds no sphere: no pixel is set")
    if n > 1:  # the largest region: a speck of dust or a label elsewhere in the mask is not the sphere
        sizes = np.bincount(labels.ravel())[1:]
        mask = labels == 1 + int(sizes.argmax())
    mask = ndimage.binary_fill_holes(mask)  # a highlight cut out of a mask drawn by threshold
    p = _edge_points(mask)
    if len(p) < 12:
        if mask.mean() > 0.5:  # (an edge on the image's border is no outline)
            raise PsctlError(where, "has no outline inside the image (it covers the image, or all but a few pixels "
                                    "of its edge): mask only the sphere")
        raise PsctlError(where, f"the sphere is too small to fit a circle to ({int(mask.sum())} pixels)")
    cx, cy, r = _circle_fit(p)
    res = np.hypot(p[:, 0] - cx, p[:, 1] - cy) - r
    cut = max(1.5, 3 * 1.4826 * float(np.median(np.abs(res))))
    keep = np.abs(res) <= cut
    if keep.sum() >= 12 and not keep.all():
        cx, cy, r = _circle_fit(p[keep])
        res = np.hypot(p[:, 0] - cx, p[:, 1] - cy) - r
        cut = max(1.5, 3 * 1.4826 * float(np.median(np.abs(res[keep]))))
        keep = np.abs(res) <= cut
    if camera is not None:
        for _ in range(2):  # the cone on the circle's inliers, then on its own
            res = _cone_residuals(p, p[keep], camera, r)
            cut = max(1.5, 3 * 1.4826 * float(np.median(np.abs(res[keep]))))
            keep = np.abs(res) <= cut
    rms = float(np.sqrt(np.mean(res[keep] ** 2)))
    if r < cfg["min_radius"]:
        raise PsctlError(where, f"the sphere is too small: radius {r:.1f} pixels (at least {cfg['min_radius']:g})")
    if rms > max(1.0, 0.02 * r) or keep.mean() < 0.5:
        model = (f"the best circle (x {cx:.1f}, y {cy:.1f}, r {r:.1f})" if camera is None else
                 f"the best sphere's outline through the pinhole of --focal {camera[0]:g} and principal point "
                 f"{camera[1]:g},{camera[2]:g} (are they the images'?)")
        raise PsctlError(where, f"is not round: its outline lies {float(np.sqrt(np.mean(res ** 2))):.1f} pixels from "
                                f"{model} on average, {1 - keep.mean():.0%} of it further than {cut:.1f} pixels; "
                                "psctl calibrate needs the sphere's own outline (or --circle X,Y,R)")
    return Circle(cx, cy, r, source, round(rms, 4), p[keep])


def check_circle(circle: "Circle | str | Iterable[float]",
                 min_radius: float = DEFAULT_CALIBRATE["min_radius"]) -> Circle:
    """A ``Circle`` from one, from "X,Y,R" (``--circle``) or from three numbers; its radius at least
    ``min_radius`` (the config's, as a fitted circle's)."""
    if isinstance(circle, Circle):
        values = [circle.x, circle.y, circle.r]
    else:
        try:
            values = [float(v) for v in (circle.split(",") if isinstance(circle, str) else circle)]
        except (TypeError, ValueError):
            values = []
    if len(values) != 3 or not all(np.isfinite(values)) or max(map(abs, values)) > 1e7:
        raise PsctlError(None, f"--circle must be X,Y,R (three finite numbers, each within 1e7 of 0: the centre's "
                               f"column and row and the radius, in pixels), not {circle!r}")
    if values[2] < min_radius:
        raise PsctlError(None, f"--circle's radius must be at least {min_radius:g} pixels "
                               f"(got {values[2]:g})")
    source = circle.source if isinstance(circle, Circle) else "--circle"
    return Circle(*values, source)


def circle_box(circle: Circle, shape: tuple[int, int]) -> tuple[slice, slice]:
    """The rows and columns of the image that the circle covers (one pixel of margin). A
    ``PsctlError`` when it misses the image."""
    h, w = shape
    if circle.r > np.hypot(h, w):
        raise PsctlError(None, f"--circle's radius {circle.r:g} is larger than the {w} x {h} images' diagonal: "
                               "the sphere must be in the images")
    y0, y1 = max(int(np.floor(circle.y - circle.r)) - 1, 0), min(int(np.ceil(circle.y + circle.r)) + 2, h)
    x0, x1 = max(int(np.floor(circle.x - circle.r)) - 1, 0), min(int(np.ceil(circle.x + circle.r)) + 2, w)
    if y1 - y0 < 2 or x1 - x0 < 2:
        raise PsctlError(None, f"--circle (x {circle.x:g}, y {circle.y:g}, r {circle.r:g}) lies outside the "
                               f"{w} x {h} images")
    return slice(y0, y1), slice(x0, x1)


def sphere_normals(circle: Circle, box: tuple[slice, slice], rim: float = DEFAULT_CALIBRATE["rim"]
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The sphere's normals over ``box`` of the image: ([h, w, 3] float64 unit vectors, x right,
    y up, z toward the camera; [h, w] bool, the pixels within ``rim`` * r of the centre)."""
    ys = np.arange(box[0].start, box[0].stop, dtype=np.float64)
    xs = np.arange(box[1].start, box[1].stop, dtype=np.float64)
    nx = (xs[None, :] - circle.x) / circle.r
    ny = -(ys[:, None] - circle.y) / circle.r  # rows grow downward, y up
    nx, ny = np.broadcast_arrays(nx, ny)
    rr = nx * nx + ny * ny
    inside = rr <= rim * rim
    nz = np.sqrt(np.clip(1.0 - rr, 0.0, None))
    return np.stack([nx, ny, nz], -1) * inside[..., None], inside


def _rays(p: np.ndarray, camera: tuple[float, float, float]) -> np.ndarray:
    """[P, 2] image points (x, y) -> [P, 3] unit rays from a pinhole camera into the scene."""
    f, px, py = camera
    d = np.stack([p[:, 0] - px, -(p[:, 1] - py), np.full(len(p), -f)], 1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _cone(p: np.ndarray, camera: tuple[float, float, float]) -> tuple[np.ndarray, float]:
    # every outline ray d meets the axis a at the half-angle: d . a = cos, so w = a / cos solves
    # d . w = 1 (least squares over the points)
    w = np.linalg.lstsq(_rays(p, camera), np.ones(len(p)), rcond=None)[0]
    return w / np.linalg.norm(w), float(np.arccos(min(1.0 / np.linalg.norm(w), 1.0)))


def _cone_residuals(p: np.ndarray, fit_to: np.ndarray, camera: tuple[float, float, float], r: float) -> np.ndarray:
    """Each point's ray's angle from the cone fitted to ``fit_to``, less its half-angle, in pixels
    at the circle's scale (r over the half-angle)."""
    axis, half = _cone(fit_to, camera)
    angle = np.arccos(np.clip(_rays(p, camera) @ axis, -1.0, 1.0))
    return (angle - half) * r / max(half, 1e-12)


def pinhole_cone(circle: Circle, camera: tuple[float, float, float]) -> tuple[np.ndarray, float]:
    """The cone of rays that graze the sphere, through a pinhole camera (focal, principal x,
    principal y; pixels): (its axis [3], unit, from the camera toward the sphere's centre; its
    half-angle in radians), fitted to the circle's outline points where it was fitted to an
    outline (an off-axis sphere's outline is an ellipse), else to points on the circle."""
    p = circle.outline
    if p is None or len(p) < 12:
        t = np.linspace(0, 2 * np.pi, 720, endpoint=False)
        p = np.stack([circle.x + circle.r * np.cos(t), circle.y + circle.r * np.sin(t)], 1)
    return _cone(p, camera)


def sphere_pinhole_geometry(circle: Circle, box: tuple[slice, slice], camera: tuple[float, float, float],
                            rim: float = DEFAULT_CALIBRATE["rim"]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``sphere_normals`` through a pinhole camera (focal, principal x, principal y; pixels): ([h,
    w, 3] normals, [h, w] bool, [h, w, 3] unit views from each surface point toward the camera).

    A unit sphere on ``pinhole_cone``'s axis at 1 / sin(half-angle) fills the cone; each pixel's
    ray meets it at its normal. ``rim``: pixels whose normal is within asin(rim) of their view (as
    rim * r from the centre is, orthographically)."""
    f, px, py = camera
    axis, half = pinhole_cone(circle, camera)
    centre = axis / max(np.sin(half), 1e-9)
    ys = np.arange(box[0].start, box[0].stop, dtype=np.float64)
    xs = np.arange(box[1].start, box[1].stop, dtype=np.float64)
    grid = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None]), -1)  # [h, w, 2] (x, y)
    d = _rays(grid.reshape(-1, 2), camera).reshape(*grid.shape[:2], 3)  # unit rays from the camera
    b = d @ centre
    disc = b * b - centre @ centre + 1.0
    n = (b - np.sqrt(np.clip(disc, 0.0, None)))[..., None] * d - centre
    view = -d
    # the sphere through this camera must cover about the circle's pixels: a focal length or a
    # principal point far from the images' own would otherwise give wrong directions silently
    disk = (xs[None, :] - circle.x) ** 2 + (ys[:, None] - circle.y) ** 2 <= circle.r**2
    ratio = float((disc > 0).sum()) / max(int(disk.sum()), 1)
    if not 0.8 <= ratio <= 1.25:
        raise PsctlError(None, f"a sphere with this outline, seen through --focal {f:g} with the principal point at "
                               f"{px:g},{py:g}, would cover {ratio:.0%} of the outline's pixels: are the focal length "
                               "(in the images' pixels) and the principal point the images'? (docs/calibration.md, "
                               "'Perspective')")
    inside = (disc > 0) & ((n * view).sum(-1) >= np.sqrt(max(1.0 - rim * rim, 0.0)))
    return n * inside[..., None], inside, view


# --- one image ---------------------------------------------------------------------------------

def mirror_direction(normal: np.ndarray, view: np.ndarray | None = None) -> np.ndarray:
    """The light direction whose mirror reflection about ``normal`` [3] reaches the camera along
    ``view`` [3] (from the surface toward the camera; None: orthographic, (0, 0, 1)):
    l = 2 (n . v) n - v."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    v = np.array([0.0, 0.0, 1.0]) if view is None else np.asarray(view, np.float64) / np.linalg.norm(view)
    return 2.0 * float(n @ v) * n - v


def find_highlight(gray: np.ndarray, inside: np.ndarray, fraction: float = DEFAULT_CALIBRATE["highlight"],
                   base: float = DEFAULT_CALIBRATE["base"], normals: np.ndarray | None = None,
                   weighting: str = "surface", views: np.ndarray | None = None,
                   frame: np.ndarray | None = None) -> dict | None:
    """The highlight inside the sphere: {"x", "y" (sub-pixel, in ``gray``'s pixels), "peak",
    "pixels" (its size), "spots" (regions above the level: more than one is a second reflection),
    "rim" (it touches the edge of ``inside`` within the image: a light far behind the sphere,
    whose highlight is partly cut off), "frame" (it touches ``frame`` [h, w] bool, the pixels on
    the image's own edge where the sphere goes on beyond it: cut off by the image),
    "frame_peak" (its brightest pixel is there, or, a clipped plateau, less than half of it shows:
    its centre is likely outside the image)}; None when the sphere is black.

    Regions above b + ``fraction`` (peak - b), b the ``base``-th percentile of the sphere's values,
    are candidates; the one with the most brightness above that level is the highlight, leaving
    out lone pixels far brighter than their neighbours where there are others (a hot pixel), and
    its level is then set again from its own peak. A
    saturated plateau as large as the sphere's top decile (b = peak) is its own level. The
    position is the centroid weighted by each pixel's height above the level (the plateau's
    centre when it is flat). With the sphere's ``normals`` [h, w, 3], also "normal": the same
    weights' mean normal, each pixel counted by the surface it covers (1 / n_z): a broad or
    clipped highlight is symmetric on the sphere, not in the image, whose centroid it pulls
    toward the sphere's centre. ``weighting`` "even" leaves out the 1 / n_z, "image" gives the
    image centroid's normal (benchmarks/calibrate_sphere.py --centroids compares them). With
    ``views`` [h, w, 3] (a pinhole camera: ``sphere_pinhole_geometry``), n . v takes n_z's place
    and "view" is the mean of its pixels' views weighted by their height above the level."""
    from scipy import ndimage

    g = np.where(inside, gray, -np.inf)
    peak = float(g.max())
    if not peak > 0:
        return None
    b = max(float(np.percentile(gray[inside], base)), 0.0) if base > 0 else 0.0
    eight = np.ones((3, 3), bool)
    # the level's peak leaves out lone pixels over HOT_RATIO times all their neighbours (hot pixels,
    # below): a stuck pixel at full scale would otherwise set a level above an unsaturated highlight,
    # which then is no candidate at all (a hot pixel of 65535 over a highlight peaking at 0.3 of it:
    # 58 degrees off without a note). A real highlight, spread by the lens, is not lone; where the
    # rest is under 1 / HOT_RATIO^2 of the peak over b (noise), the lone pixel may be a sub-pixel
    # highlight, and sets the level as before
    ring = eight.copy()
    ring[1, 1] = False
    around = ndimage.maximum_filter(g, footprint=ring, mode="constant", cval=-np.inf)
    hot = inside & (g > HOT_RATIO * np.maximum(around, 0.0))
    if hot.any():
        rest = float(np.where(hot, -np.inf, g).max())
        if rest - b > (peak - b) / HOT_RATIO**2:
            peak = rest

    def regions(level: float) -> tuple[np.ndarray, int]:
        above = g > level
        if not above.any():  # the top decile is one flat plateau at the peak
            above = g >= level
        return ndimage.label(above, structure=eight)

    first = b + fraction * (peak - b)
    labels, spots = regions(first)
    # brightness above the level (and, for flat plateaus, their size) decides, among regions that are
    # not a lone pixel over four times its brightest neighbour (a hot pixel; psctl.hotpixels' ratio)
    # where there are any: a lens spreads a real highlight over its neighbours
    index = np.arange(1, spots + 1)
    mass = ndimage.sum(np.where(labels > 0, g - first + 1e-9, 0.0), labels, index)
    size = ndimage.sum(labels > 0, labels, index)
    lone = np.zeros(spots, bool)
    where = ndimage.maximum_position(g, labels, index)
    for k in np.flatnonzero(size == 1):
        y, x = (int(v) for v in where[k])
        around = g[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2].copy()
        around[min(y, 1), min(x, 1)] = -np.inf
        lone[k] = g[y, x] > HOT_RATIO * max(float(around.max()), 0.0)
    if (~lone).any():
        mass = np.where(lone, -1.0, mass)
    best = labels == 1 + int(np.argmax(mass))
    top = float(g[best].max())  # the highlight's own peak, and its level from it
    level = b + fraction * (top - b)
    labels2, _ = regions(level)
    spot = np.isin(labels2, np.unique(labels2[best & (labels2 > 0)]))
    ys, xs = np.nonzero(spot)
    ww = gray[ys, xs] - level
    if not ww.sum() > 0:  # flat: every pixel at the level
        ww = np.ones_like(ww)
    cut = np.zeros_like(spot) if frame is None else spot & frame
    edge = spot & ~ndimage.binary_erosion(inside, structure=eight, border_value=0) & ~cut
    peak_px = spot & (g >= top)
    frame_peak = bool((cut & peak_px).any())
    if frame_peak and peak_px.sum() > 1:
        # a clipped plateau reaching the edge: its centre lies beyond it only when less than half of
        # it shows (a disc cut through its centre is half as deep as it is wide)
        py, px = np.nonzero(peak_px)
        tall, wide = int(np.ptp(py)) + 1, int(np.ptp(px)) + 1
        sides = ((frame[0].all() and peak_px[0].any()) or (frame[-1].all() and peak_px[-1].any()),
                 (frame[:, 0].all() and peak_px[:, 0].any()) or (frame[:, -1].all() and peak_px[:, -1].any()))
        frame_peak = (sides[0] and tall < wide / 2) or (sides[1] and wide < tall / 2)
    out = {"x": float((ww * xs).sum() / ww.sum()), "y": float((ww * ys).sum() / ww.sum()), "peak": top,
           "pixels": int(spot.sum()), "spots": int(spots), "rim": bool(edge.any()), "frame": bool(cut.any()),
           "frame_peak": bool(frame_peak)}
    if normals is not None:
        n = normals[ys, xs]
        if views is not None:
            if weighting == "image":
                raise ValueError("find_highlight: weighting 'image' is for an orthographic camera (views=None)")
            v = views[ys, xs]
            cos = (n * v).sum(-1)
            mv = (v * ww[:, None]).sum(0)
            out["view"] = mv / max(float(np.linalg.norm(mv)), 1e-12)
        else:
            cos = n[:, 2]
        if weighting == "image":  # the image centroid's normal (n_x, n_y are linear in x, y)
            nxy = (ww[:, None] * n[:, :2]).sum(0) / ww.sum()
            mean = np.array([nxy[0], nxy[1], np.sqrt(max(1.0 - float(nxy @ nxy), 0.0))])
        else:
            mean = (n * (ww / np.maximum(cos, 0.05) if weighting == "surface" else ww)[:, None]).sum(0)
        out["normal"] = mean / max(float(np.linalg.norm(mean)), 1e-12)
    return out


def matte_light(rgb: np.ndarray, normals: np.ndarray, usable: np.ndarray, config: dict | None = None
                ) -> dict | None:
    """Fit one light to a Lambertian sphere's image: I = max(n . b, 0) per pixel, b = e l (with
    config ``offset``: I = n . b + c on the lit pixels, c a constant of the image).

    ``rgb`` [h, w, 3] linear, ``normals`` [h, w, 3], ``usable`` [h, w] bool (inside the rim, not
    saturated). The grey values (channel mean) give the direction; each channel's intensity is
    then its least-squares scale of the fitted shading n . l (with its own constant, with
    ``offset``). Returns {"direction" [3], "intensity" [3], "pixels" (used in the last fit), "rms"
    (their residual over their mean value), "offset" (c over that mean; without ``offset``, the c
    a fit with it would give on the same pixels: a check)}, or None when fewer than
    ``min_pixels`` are lit."""
    cfg = check_config(config)
    offset = bool(cfg["offset"])
    gray = rgb.mean(-1)

    def with_constant(n: np.ndarray) -> np.ndarray:  # [P, 3] -> [P, 4]: the normals and a column of ones
        return np.concatenate([n, np.ones((len(n), 1))], 1)

    # first guess, the lit part: above ``lit`` of a bright level that a highlight does not set
    top = float(np.percentile(gray[usable], 90)) if usable.any() else 0.0
    sel = usable & (gray > cfg["lit"] * top)
    b, c = None, 0.0
    for _ in range(int(cfg["iterations"])):
        if sel.sum() < cfg["min_pixels"]:
            return None
        N, g = normals[sel], gray[sel]
        if offset:
            sol = np.linalg.lstsq(with_constant(N), g, rcond=None)[0]
            b, c = sol[:3], float(sol[3])
        else:
            b = np.linalg.lstsq(N, g, rcond=None)[0]
        e = float(np.linalg.norm(b))
        if not e > 0:
            return None
        shade = normals @ b
        res = gray - shade - c
        sigma = 1.4826 * float(np.median(np.abs(res[sel]))) + 1e-6 * top
        new = usable & (shade > cfg["lit"] * e) & (np.abs(res) <= cfg["trim"] * sigma)
        if np.array_equal(new, sel):
            break
        sel = new
    if b is None or sel.sum() < cfg["min_pixels"]:
        return None
    d = b / np.linalg.norm(b)
    s = normals[sel] @ d
    if offset:  # each channel: I_c = k_c s + o_c
        A = np.stack([s, np.ones_like(s)], 1)
        ints = np.linalg.lstsq(A, rgb[sel], rcond=None)[0][0]
    else:
        ints = (rgb[sel] * s[:, None]).sum(0) / max(float((s * s).sum()), 1e-12)
    res = gray[sel] - normals[sel] @ b - c
    mean = float(gray[sel].mean())
    if not offset:  # what a constant would have taken, on the same pixels: the note on offsets
        c = float(np.linalg.lstsq(with_constant(normals[sel]), gray[sel], rcond=None)[0][3])
    return {"direction": d, "intensity": ints, "pixels": int(sel.sum()),
            "rms": float(np.sqrt(np.mean(res**2)) / mean) if mean > 0 else None,
            "offset": c / mean if mean > 0 else None}


# --- many images ---------------------------------------------------------------------------------

@dataclass
class SphereLights:
    """What a calibration found: ``directions`` [N, 3] unit vectors, ``intensities`` [N, 3]
    (matte; scaled to a mean of 1) or None (chrome), ``circle``, and per image ``images``: for
    chrome {"highlight": [x, y] in the image's pixels, "peak", "pixels", "spots"}, for matte
    {"pixels", "rms"}. ``box``: the part of the images read (the circle's), ``brightest`` [h, w]
    each of its pixels' brightest grey value over the images (sphere.png)."""

    sphere: str
    circle: Circle
    directions: np.ndarray
    intensities: np.ndarray | None
    images: list[dict]
    box: tuple[slice, slice]
    brightest: np.ndarray = field(repr=False)
    camera: tuple[float, float, float] | None = None  # (focal, principal x, principal y), or orthographic


class _Calibrator:
    """Image by image (the folder reader streams them): each one's light, from the part of the
    image inside ``box``."""

    def __init__(self, sphere: str, circle: Circle, box: tuple[slice, slice], config: dict,
                 camera: tuple[float, float, float] | None = None, shape: tuple[int, int] | None = None):
        self.sphere, self.circle, self.box, self.cfg, self.camera = sphere, circle, box, config, camera
        h, w = box[0].stop - box[0].start, box[1].stop - box[1].start
        # the box's pixels on the image's own edge, where the sphere goes on beyond the image
        # (``shape``: the images' [H, W]; the box is cut to them): a highlight there is cut off
        self.frame = np.zeros((h, w), bool)
        if shape is not None:
            r = circle.r
            if box[0].start == 0 and circle.y - r < -0.5:
                self.frame[0] = True
            if box[0].stop == shape[0] and circle.y + r > shape[0] - 0.5:
                self.frame[-1] = True
            if box[1].start == 0 and circle.x - r < -0.5:
                self.frame[:, 0] = True
            if box[1].stop == shape[1] and circle.x + r > shape[1] - 0.5:
                self.frame[:, -1] = True
        self.names: list = []  # each image's name (a file, or "images[k]"), for what result() refuses
        self.views = None
        if camera is None:
            self.normals, self.inside = sphere_normals(circle, box, config["rim"])
        else:
            self.normals, self.inside, self.views = sphere_pinhole_geometry(circle, box, camera, config["rim"])
        if not self.inside.any():
            raise PsctlError(None, f"the sphere (x {circle.x:.1f}, y {circle.y:.1f}, r {circle.r:.1f}) has no pixel "
                                   "inside the images")
        # chrome: the sphere's pixels beyond the used part (rim), where a light far behind the sphere
        # puts its highlight; each image's brightest value there (the errors on dark images say so)
        self.outer = sphere_normals(circle, box, 1.0)[1] & ~self.inside
        self.outer_peaks: list[float] = []
        self.directions: list[np.ndarray] = []
        self.intensities: list[np.ndarray] = []
        self.images: list[dict] = []
        self.brightest: np.ndarray | None = None  # per pixel over the images: sphere.png

    def _over_base(self, gray: np.ndarray, peak: float, saturated: np.ndarray | None) -> float | None:
        """The highlight's peak over the sphere's 90th percentile (MATTE_LIKE); None where that is 0
        or the peak is clipped (a mirror's clipped highlight over a lit room's reflection can be
        near it: a review's gave 1.25)."""
        p90 = float(np.percentile(gray[self.inside], 90))
        clipped = saturated is not None and bool((saturated & self.inside & (gray >= peak)).any())
        return round(peak / p90, 3) if p90 > 0 and not clipped else None

    def add(self, rgb: np.ndarray, saturated: np.ndarray | None = None, name: Path | str | None = None) -> None:
        """``rgb`` [h, w, 3] the image inside ``box``; ``saturated`` [h, w] its clipped pixels."""
        gray = rgb.mean(-1)
        self.names.append(name)
        self.brightest = gray.copy() if self.brightest is None else np.maximum(self.brightest, gray)
        if not np.isfinite(rgb[self.inside]).all():
            raise PsctlError(name, "holds NaN or infinite values on the sphere")
        if self.sphere == "chrome":
            self.outer_peaks.append(float(gray[self.outer].max()) if self.outer.any() else 0.0)
            spot = find_highlight(gray, self.inside, self.cfg["highlight"], self.cfg["base"], self.normals,
                                  views=self.views, frame=self.frame)
            if spot is None:
                raise PsctlError(name, "is black on the sphere: there is no highlight to locate "
                                       f"({self._why_dark(self.outer_peaks[-1] > 0)})")
            if spot["frame_peak"]:  # its brightest pixel on the image's edge: the rest of it lies beyond
                raise PsctlError(name, "has its highlight at the image's edge, where the sphere goes on beyond the "
                                       "image: its centre cannot be located (frame the whole sphere)")
            x, y = spot["x"] + self.box[1].start, spot["y"] + self.box[0].start
            d = mirror_direction(spot["normal"], spot.get("view"))
            if not np.isfinite(d).all():
                raise PsctlError(name, "gives no direction: its highlight could not be located")
            self.directions.append(d)
            self.images.append({"highlight": [round(x, 3), round(y, 3)], "peak": round(spot["peak"], 6),
                                "over_base": self._over_base(gray, spot["peak"], saturated),
                                "pixels": spot["pixels"], "spots": spot["spots"], "rim": spot["rim"],
                                "frame": spot["frame"]})
        else:
            usable = self.inside if saturated is None else self.inside & ~saturated
            fit = matte_light(rgb, self.normals, usable, self.cfg)
            if fit is None:
                raise PsctlError(name, f"has too few lit pixels on the sphere to fit a light (fewer than "
                                       f"{self.cfg['min_pixels']} unsaturated ones): a light that did not fire, or "
                                       "one behind the sphere?")
            self.directions.append(fit["direction"])
            self.intensities.append(fit["intensity"])
            self.images.append({"pixels": fit["pixels"], "rms": None if fit["rms"] is None else round(fit["rms"], 5),
                                "offset": None if fit["offset"] is None else round(fit["offset"], 5)})

    def _why_dark(self, beyond: bool) -> str:
        """Why a chrome image shows no usable highlight: a light that did not fire, or one whose highlight
        lies beyond the used part of the sphere (``beyond``: it is brighter there: a light far behind
        the sphere) or outside the image (where the sphere goes on beyond it)."""
        if self.sphere == "chrome" and beyond:
            return (f"it is brighter beyond the used part of the sphere, {self.cfg['rim']:g} of its radius: a light "
                    "far behind the sphere, whose highlight lies too near its outline to be used")
        if self.sphere == "chrome" and self.frame.any():
            return "a light that did not fire, or a highlight outside the image, where the sphere goes on?"
        return "a light that did not fire?"

    def result(self) -> SphereLights:
        # a light that did not fire leaves sensor noise, not black: its highlight (or fitted
        # intensity) a small share of the others' (a QA helper's noise image gave a direction 130
        # degrees off, written without a word)
        level = np.array([i["peak"] for i in self.images] if self.sphere == "chrome" else
                         [float(np.mean(e)) for e in self.intensities], np.float64)
        ref = float(np.median(level)) if len(level) else 0.0
        dark = np.flatnonzero(level < DARK_LIGHT * ref)
        if len(dark):
            k = int(dark[0])
            what = "its highlight peaks at" if self.sphere == "chrome" else "its fitted intensity is"
            more = f" ({len(dark) - 1} more image{'s' * (len(dark) > 2)} too)" if len(dark) > 1 else ""
            beyond = (self.sphere == "chrome" and self.outer_peaks[k] > level[k]
                      and self.outer_peaks[k] >= DARK_LIGHT * ref)
            raise PsctlError(self.names[k], f"is dark on the sphere: {what} {100 * level[k] / ref:.2g} % of the "
                                            f"median image's ({self._why_dark(beyond)}){more}")
        ints = None
        if self.sphere == "matte":
            ints = np.array(self.intensities, np.float64)
            scale = float(ints.mean())
            ints = ints / scale if scale > 0 else ints
        return SphereLights(self.sphere, self.circle, np.array(self.directions, np.float64), ints, self.images,
                            self.box, self.brightest, self.camera)


def check_sphere(sphere: str) -> str:
    sphere = sphere.lower() if isinstance(sphere, str) else sphere  # as --method, --encoding: CHROME too
    if sphere not in SPHERES:
        raise PsctlError(None, f"unknown --sphere {sphere!r}; choose chrome (a mirror ball: directions) or matte "
                               "(a white Lambertian ball: directions and intensities)")
    return sphere


# the command's words -> calibrate_lights' arguments (config keys; circle a tuple; results' fields),
# before psctl's Python wording (which would say focal=F, an argument calibrate_lights has not)
_ARRAY_WORDS = (("--focal and principal point", 'config["focal"] and config["principal"]'),
                (" or 'exif' (read from the images)", ""), ("--focal", 'config["focal"]'),
                ("--principal", 'config["principal"]'), ("--circle X,Y,R", "circle=(x, y, r)"),
                ("--circle", "circle"), ("use --offset", 'use config={"offset": True}'),
                ("take ambient.png with every light off", "subtract an image taken with every light off"),
                ("sphere.png shows them", "res.brightest (each pixel's brightest value) shows them"),
                ("add mask.png (white on the sphere) or pass", "give mask or"),
                ("psctl calibrate needs", "calibrate_lights needs"))


def _array_wording(text: str) -> str:
    for cli, py in _ARRAY_WORDS:
        text = text.replace(cli, py)
    return text


def calibrate_lights(images: np.ndarray, sphere: str, mask: np.ndarray | None = None,
                     circle: "Circle | str | Iterable[float] | None" = None, config: dict | None = None
                     ) -> SphereLights:
    """Light directions (and, for a matte sphere, intensities) from images of a sphere.

    Args:
        images: [N, H, W, 3] or [N, H, W] linear images of the sphere, one per light, as captured
            (not divided by any intensities). Integer images' top code value counts as
            saturated (left out of a matte fit); float images have no saturated values.
        sphere: "chrome" or "matte".
        mask: [H, W] bool, the sphere's pixels (its outline is fitted), or
        circle: the outline as (x, y, r) in pixels (x the column, y the row, the top-left
            pixel's centre at (0, 0)). Without either, a matte sphere's outline is found in the
            images' per-pixel maximum; a chrome sphere's cannot be.
        config: overrides of DEFAULT_CALIBRATE.
    Returns:
        ``SphereLights``: directions [N, 3] (x right, y up, z toward the camera), intensities
        [N, 3] or None, the circle, per-image details.
    """
    try:
        return _calibrate_lights(images, sphere, mask, circle, config)
    except PsctlError as e:
        raise PsctlError(e.path, _array_wording(e.message)) from None


def _calibrate_lights(images, sphere, mask, circle, config) -> SphereLights:
    from psctl.arrays import as_images, as_mask, plain
    from psctl.io.capture import saturated_map

    cfg = check_config(config)
    sphere = check_sphere(sphere)
    _check_offset(cfg, sphere)
    imgs = as_images(images)
    integer = np.asarray(plain(images)).dtype.kind in "iu"  # float images have no top code: nothing is saturated
    camera = camera_config(cfg, imgs.shape[1:3])
    if mask is not None and circle is not None:
        raise PsctlError(None, "give mask or circle, not both")
    if circle is not None:
        c = check_circle(circle, cfg["min_radius"])
    elif mask is not None:
        m = as_mask(mask, imgs.shape[1:3])
        try:
            c = fit_circle(m, "mask", None, cfg, camera)
        except PsctlError as e:  # its messages' subject is the file, which an array has not: "mask is not round"
            raise PsctlError(None, ("mask " if e.message.startswith(("is ", "has ", "holds ")) else "mask: ")
                             + e.message) from None
    else:
        c = _circle_from_images(imgs.mean(-1).max(0), sphere, None, cfg, camera)
    box = _sphere_box(c, imgs.shape[1:3], camera)
    cal = _Calibrator(sphere, c, box, cfg, camera, imgs.shape[1:3])
    for k in range(len(imgs)):
        img = imgs[k][box]
        cal.add(img, saturated_map(img) if integer else None, f"images[{k}]")
    res = cal.result()
    import warnings

    from psctl.errors import PsctlWarning, caller_level, python_wording

    for note in _result_notes(res, [f"images[{k}]" for k in range(len(imgs))], bool(cfg["offset"])):
        if "light_intensities.txt is not written" in note:  # a file's: no array result has one
            continue
        # (calibrate_lights, the public function, is one frame up)
        warnings.warn(python_wording(_array_wording(note)), PsctlWarning, stacklevel=caller_level(2))
    return res


def _sphere_box(c: Circle, shape: tuple[int, int], camera: tuple[float, float, float] | None
                ) -> tuple[slice, slice]:
    """circle_box; through a pinhole, larger by 1.1 / cos(the angle off the axis): an off-axis
    sphere's outline is an ellipse longer than the fitted circle toward the principal point."""
    if camera is None:
        return circle_box(c, shape)
    f, px, py = camera
    grow = 1.1 * np.hypot(f, np.hypot(c.x - px, c.y - py)) / f
    return circle_box(Circle(c.x, c.y, min(grow * c.r, float(np.hypot(*shape))), c.source), shape)


def _no_chrome_outline(where: Path | None) -> PsctlError:
    return PsctlError(where, "a chrome sphere's outline does not show in its images (only its highlights do): "
                             "add mask.png (white on the sphere) or pass --circle X,Y,R")


def _circle_from_images(brightest: np.ndarray, sphere: str, where: Path | None, config: dict,
                        camera: tuple[float, float, float] | None = None) -> Circle:
    """A matte sphere's outline from each pixel's brightest value over the images (lit from
    somewhere by most lights, against a darker background)."""
    if sphere == "chrome":
        raise _no_chrome_outline(where)
    top = float(np.percentile(brightest, 99.5))
    if not top > 0:
        raise PsctlError(where, "the images are black: no sphere to find")
    try:
        return replace(fit_circle(brightest > 0.2 * top, "images", where, config, camera), source="images")
    except PsctlError as e:
        raise PsctlError(where, f"found no round sphere in the images' brightest values ({e.message}); add mask.png "
                                "(white on the sphere) or pass --circle X,Y,R") from None


# --- the command ---------------------------------------------------------------------------------

def run_calibrate(path: str | os.PathLike, sphere: str, out: str | os.PathLike | None = None,
                  circle: "Circle | str | Iterable[float] | None" = None, write: bool = True,
                  progress: "ProgressFactory | None" = None, encoding: str = "auto", config: dict | None = None,
                  offset: bool = False, focal: "float | str | None" = None,
                  principal: "str | Iterable[float] | None" = None,
                  K: "str | os.PathLike | np.ndarray | None" = None) -> dict:
    """Calibrate a folder of sphere images (one per light, in the object's order), write the
    light files, return the report (what ``psctl calibrate --json`` prints).

    The folder is read as ``psctl normals`` reads one (images, filenames.txt, an ambient image
    subtracted, mask.png for the outline); its own light files, when present, are only compared
    with (light_mae, intensity_re). Outputs (when ``write``, all or none) in ``out`` (default
    ``PATH/psctl``): light_directions.txt, light_intensities.txt (matte only; a chrome
    calibration removes one an earlier calibration there wrote), lights.png (the directions on
    the unit disk), sphere.png (the brightest value of each pixel over the images, the fitted
    circle and, for chrome, each highlight) and calibration_report.json.

    ``sphere``: "chrome" (directions from the highlights) or "matte" (directions and intensities
    from the shading); ``circle``: the sphere's outline (a ``Circle``, "X,Y,R" or three numbers;
    None: from mask.png, or for matte from the images); ``offset`` (matte): fit a constant per
    image too (I = n . l e + c), for a black level or room light without an ambient image;
    ``config``: overrides of DEFAULT_CALIBRATE; ``progress``: None or a factory (label, total)
    -> advance(k).

    ``focal`` (pixels, or "exif": the images' EXIF headers) and ``principal`` model a pinhole
    camera (docs/calibration.md, "Perspective"); or ``K``, a 3 x 3 camera matrix (a file as
    ``psctl depth --K`` reads, such as the K.txt psctl undistort writes, or an array) with square
    pixels (fx and fy within 0.5 %: their mean is the focal length, (cx, cy) the principal point).

    Report: object, path, sphere, n_images, circle {x, y, r, source, rms}, camera {focal,
    principal, from} (None: orthographic), light_mae and
    intensity_re (against the folder's own files, else None), direction_errors (degrees per image,
    or None), outputs, images (per image: file, direction, intensity, and for chrome highlight
    [x, y], peak, pixels, spots; for matte pixels, rms), seconds, notes.
    """
    from psctl.depth import find_intrinsics
    from psctl.io.atomic import check_output_dir, output_folder, read_outputs_list, staged_outputs
    from psctl.io.capture import (INTENSITIES_FILE, LIGHTS_FILE, DecodeMemo, check_not_capture, capture_notes,
                                  iter_images, load_mask, open_capture)

    t0 = time.perf_counter()
    for name, value in (("path", path), ("out", out)):
        check_path(name, value, optional=name != "path")
    write = check_bool("write", write)
    progress = check_progress(progress)
    sphere = check_sphere(sphere)
    cfg = check_config(config)
    if check_bool("offset", offset):
        cfg["offset"] = True
    _check_offset(cfg, sphere)
    for key, value in (("focal", focal), ("principal", principal)):  # --focal, --principal over the config
        if value is not None:
            cfg[key] = _check_camera(key, value)
    K_from = None
    if K is not None:
        if focal is not None or principal is not None:
            raise PsctlError(None, "--K gives the focal length and the principal point: leave out --focal and "
                                   "--principal")
        cfg["focal"], cfg["principal"], K_from = camera_from_K(K)
    given = None if circle is None else check_circle(circle, cfg["min_radius"])
    # the folder's own light files are only compared with: a damaged one is skipped, with a note (a
    # damaged intensity file alone still leaves the directions to compare with)
    unread, kept = [], {"light_files": True, "intensity_file": True}
    while True:
        try:
            cap = open_capture(path, encoding, **kept)
            break
        except PsctlError as e:
            name = None if e.path is None else Path(e.path).name.lower()
            if name == INTENSITIES_FILE and kept["intensity_file"]:
                kept["intensity_file"] = False
                what = "the intensities are not compared with the folder's"
            elif name in (LIGHTS_FILE, INTENSITIES_FILE) and kept["light_files"]:
                kept["light_files"] = False
                what = "these lights are not compared with the folder's"
            else:
                raise
            unread.append(f"light files: {Path(e.path).name} is not read ({e.message}); {what}")
    notes = unread + capture_notes(cap)
    focal_from = None
    if cfg["focal"] == EXIF:
        cfg["focal"], focal_from = exif_camera_focal(cap.image_paths)
        notes.append(f"camera: focal length {cfg['focal']:.0f} pixels, from the images' EXIF ({focal_from})")
    camera = camera_config(cfg, (cap.height, cap.width))
    k_file = None
    if camera is None:
        with contextlib.suppress(PsctlError):  # only for a note: two of them, or a folder of that name, are depth's business
            k_file = find_intrinsics(cap.path)  # psctl undistort's output, psctl depth's input
    if k_file is not None and k_file.is_file():
        notes.append(f"camera: {k_file} is not read by psctl calibrate, which takes the camera as orthographic "
                     f"unless told: --K {k_file} models that pinhole")
    out_dir = output_folder(out, cap.path)
    if write:
        check_not_capture(out_dir, cap, (*OUTPUT_FILES.values(), REPORT_FILE))
        check_output_dir(out_dir)
    # as captured: a calibration measures the intensities, it does not divide by any
    raw = replace(cap, intensities=np.ones_like(cap.intensities))
    memo = None
    if given is not None:
        c = given
        if cap.mask_path is not None:
            said = f"sphere: {cap.mask_path.name} is unused: --circle gives the outline"
            try:  # a --circle a few pixels off turns every light (5 px: 10-15 degrees, a QA helper's rig)
                m = fit_circle(load_mask(cap), cap.mask_path.name, cap.mask_path, cfg, camera)
                apart = max(float(np.hypot(m.x - c.x, m.y - c.y)), abs(m.r - c.r))
                if apart > max(1.0, 0.02 * c.r):
                    said += (f", and its outline (x {m.x:.1f}, y {m.y:.1f}, r {m.r:.1f}) is {apart:.1f} pixels off "
                             f"--circle's: is --circle right?")
            except PsctlError:
                pass
            notes.append(said)
    elif cap.mask_path is not None:
        c = fit_circle(load_mask(cap), cap.mask_path.name, cap.mask_path, cfg, camera)
    else:
        if sphere == "chrome":
            raise _no_chrome_outline(cap.path)
        advance = progress(f"{cap.name}: finding the sphere", cap.n_images)
        memo = DecodeMemo(MEMO_MB << 20)  # the second pass takes its crops from these, where they fit
        brightest = None
        for img in iter_images(raw, (slice(0, cap.height), slice(0, cap.width)), memo=memo):
            g = img.mean(-1)
            brightest = g if brightest is None else np.maximum(brightest, g)
            advance(1)
        c = _circle_from_images(brightest, sphere, cap.path, cfg, camera)
        notes.append(f"sphere: outline found in the images (x {c.x:.1f}, y {c.y:.1f}, r {c.r:.1f}); mask.png or "
                     "--circle X,Y,R would fix it")
    box = _sphere_box(c, (cap.height, cap.width), camera)
    if c.r < 30 and sphere == "chrome":
        notes.append(f"sphere: its radius is {c.r:.1f} pixels: each pixel of error in a highlight's place is "
                     f"{np.degrees(2 / c.r):.1f} degrees or more of direction; a larger sphere in the images is more "
                     "accurate (docs/calibration.md)")
    off = float(np.hypot(c.x - (cap.width - 1) / 2, c.y - (cap.height - 1) / 2))
    if camera is None and off > 0.1 * np.hypot(cap.width, cap.height):
        from psctl.io.images import exif_focal

        try:
            f, _ = exif_focal(cap.image_paths[0])
            by = (f"about {np.degrees(np.arctan(off / f)):.1f} degrees (atan({off:.0f} / {f:.0f}), the focal length "
                  f"in pixels that the images' EXIF gives); --focal exif models the lens")
        except PsctlError:
            by = f"about atan({off:.0f} / f) through a lens of focal length f pixels; --focal F models the lens"
        notes.append(f"sphere: its centre is {off:.0f} pixels from the image's centre; psctl takes the camera as "
                     f"orthographic, which is exact on the optical axis only: the directions can be off by {by} "
                     "(docs/calibration.md, 'Perspective')")
    if c.x - c.r < -0.5 or c.y - c.r < -0.5 or c.x + c.r > cap.width - 0.5 or c.y + c.r > cap.height - 0.5:
        notes.append("sphere: part of it lies outside the images; only the part inside is used")
    cal = _Calibrator(sphere, c, box, cfg, camera, (cap.height, cap.width))
    clipped: dict[int, np.ndarray] = {}
    advance = progress(f"{cap.name}: {sphere} sphere", cap.n_images)
    for k, img in enumerate(iter_images(raw, box, clipped=lambda k, top: clipped.__setitem__(k, top), memo=memo)):
        cal.add(img, clipped.pop(k, None), cap.image_paths[k])
        advance(1)
    res = cal.result()
    notes += _result_notes(res, [p.name for p in cap.image_paths], bool(cfg["offset"]))
    report = _report(res, cap, notes)
    if report["camera"] is not None:
        report["camera"]["from"] = K_from or ("given" if focal_from is None else f"EXIF: {focal_from}")
    if write:
        from psctl.io.atomic import replaced_notes, write_outputs_list
        from psctl.io.report import write_json

        names = [v for k, v in OUTPUT_FILES.items() if k != "light_intensities" or res.intensities is not None]
        names.append(REPORT_FILE)
        report["notes"] += replaced_notes(out_dir, names, COMMAND)
        ints = out_dir / OUTPUT_FILES["light_intensities"]
        if res.intensities is None and ints.is_file() and ints.name not in read_outputs_list(out_dir, COMMAND):
            report["notes"].append(f"outputs: {ints} is not this run's (a chrome sphere gives no intensities) and "
                                   "belongs to other lights: do not copy it with these directions")
        report["outputs"] = {k: os.path.abspath(out_dir / v) for k, v in OUTPUT_FILES.items() if v in names}
        report["outputs"]["report"] = os.path.abspath(out_dir / REPORT_FILE)
        # a chrome run after a matte one there: the earlier intensities belong to other lights' run
        with staged_outputs(out_dir, replaces=lambda: read_outputs_list(out_dir, COMMAND)) as stage:
            write_outputs_list(stage, names, COMMAND)
            write_sphere_files(stage, res, cap, report)
            report["seconds"] = round(time.perf_counter() - t0, 3)  # calibration_report.json and the return agree
            write_json(stage / REPORT_FILE, report)
    else:
        report["seconds"] = round(time.perf_counter() - t0, 3)
    return report


def _result_notes(res: SphereLights, files: list[str], offset_fitted: bool = False) -> list[str]:
    """What a calibration's result suggests went wrong (lights behind, a matte ball taken for
    chrome, an offset, ...); ``files``: each image's name (a capture's files, or images[k])."""
    notes = []

    def names(idx: list[int]) -> str:
        return few([files[i] for i in idx])

    behind = [k for k, d in enumerate(res.directions) if d[2] <= 0]
    if behind:
        notes.append(f"lights: {len(behind)} of {len(files)} point away from the camera ({names(behind)}): they "
                     "light the object's far side, which the camera does not see")
    if res.sphere == "chrome":
        second = [k for k, i in enumerate(res.images) if i["spots"] > 1]
        if second:
            notes.append(f"sphere: {len(second)} of {len(files)} images show more than one bright spot on the sphere "
                         f"({names(second)}): the brightest was taken; a reflection of a lamp or a window? "
                         "sphere.png shows them")
        cut = [k for k, i in enumerate(res.images) if i.get("frame")]
        if cut:
            notes.append(f"sphere: {len(cut)} of {len(files)} highlights reach the image's edge, where the sphere "
                         f"goes on beyond the image ({names(cut)}): partly cut off, their directions are less "
                         "accurate; frame the whole sphere")
        rim = [k for k, i in enumerate(res.images) if i["rim"]]
        if rim:
            notes.append(f"sphere: {len(rim)} of {len(files)} highlights reach the edge of the sphere's used part "
                         f"({names(rim)}): lights far behind the sphere, whose highlight is partly cut off; their "
                         "directions are less accurate")
        broad = [k for k, i in enumerate(res.images) if i["pixels"] > 0.05 * np.pi * res.circle.r ** 2]
        # (a clipped plateau over the sphere's top tenth gives 1: overexposed, which the broad note says)
        ratios = [i["over_base"] for i in res.images if i.get("over_base") is not None and i["over_base"] > 1.001]
        level = float(np.median(ratios)) if len(ratios) > len(res.images) / 2 else None
        matte_like = level is not None and level < MATTE_LIKE
        if broad and not matte_like:  # (else the note below says it of all)
            notes.append(f"sphere: {len(broad)} of {len(files)} images have a broad highlight (over 5 % of the "
                         f"sphere; {names(broad)}): is it a mirror? for a matte ball use --sphere matte")
        if matte_like:
            notes.append(f"sphere: the brightest spot is barely brighter than the sphere's brightest tenth (its peak "
                         f"{level:.2f} times their lowest value, in the median image; a mirror's is hundreds of times, "
                         f"a glossy ball's about 1.6): is the ball matte? then use --sphere matte")
        notes.append("lights: a chrome sphere gives directions only; light_intensities.txt is not written "
                     "(a matte sphere, --sphere matte, gives intensities)")
    else:
        rough = [k for k, i in enumerate(res.images) if i["rms"] is not None and i["rms"] > 0.1]
        if rough:
            notes.append(f"sphere: {len(rough)} of {len(files)} images fit a Lambertian sphere poorly (residual over "
                         f"10 % of the mean value; {names(rough)}): is the ball matte, and the images linear?")
        offsets = [i["offset"] for i in res.images if i.get("offset") is not None]
        level = float(np.median(offsets)) if offsets else 0.0
        if not offset_fitted and level > OFFSET_NOTE:
            notes.append(f"sphere: the images seem to keep an offset (a constant of {100 * level:.1f} % of the lit "
                         "sphere's mean value, in the median image): a black level or room light? It tilts the "
                         "fitted lights; take ambient.png with every light off, or use --offset "
                         "(docs/calibration.md, 'Offset')")
    return notes


def _report(res: SphereLights, cap: "Capture", notes: list[str]) -> dict:
    from psctl.lights import light_errors

    gt_ints = cap.intensities if cap.intensities_given else None
    errors = light_errors(res.directions, np.ones(len(res.directions)) if res.intensities is None else
                          res.intensities, cap.lights, gt_ints if res.intensities is not None else None)
    per = errors["direction_errors"]
    images = []
    for k, info in enumerate(res.images):
        one = {"file": cap.image_paths[k].name, "direction": [round(float(v), 8) for v in res.directions[k]],
               "intensity": None if res.intensities is None else [round(float(v), 6) for v in res.intensities[k]],
               **info}
        if per is not None:
            one["error"] = round(float(per[k]), 4)
        images.append(one)
    return {
        "object": cap.name,
        "path": os.path.abspath(cap.path),
        "sphere": res.sphere,
        "n_images": cap.n_images,
        "circle": {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(res.circle).items()
                   if k != "outline"},
        "camera": None if res.camera is None else {"focal": res.camera[0],
                                                   "principal": [round(res.camera[1], 4), round(res.camera[2], 4)]},
        "light_mae": errors["light_mae"],
        "intensity_re": errors["intensity_re"],
        "direction_errors": None if per is None else [round(float(v), 4) for v in per],
        "outputs": {},
        "images": images,
        "seconds": 0.0,
        "notes": notes,
    }


# --- files and pictures --------------------------------------------------------------------------

SPHERE_OUTLINE, HIGHLIGHT_DOT = (0.2, 0.9, 0.3), (1.0, 0.25, 0.2)  # sphere.png's marks and their key
OUTLINE_KEY, HIGHLIGHT_KEY = "FITTED OUTLINE", "HIGHLIGHT"


def sphere_picture(brightest: np.ndarray, circle: Circle, box: tuple[slice, slice],
                   highlights: list[list[float]] | None = None, title: str | None = None,
                   min_side: int = 360) -> np.ndarray:
    """[H, W, 3] in [0, 1]: each pixel's brightest value over the images (in the circle's
    ``box``; gamma 1/2.2, its 99.5th percentile white), enlarged to at least ``min_side``, with the
    fitted circle in green and each highlight (x, y in image pixels) as a red dot; a key under
    the picture names both (the highlights' only when there are any: chrome)."""
    from psctl.io.report import _stamp, text_bitmap
    from psctl.lights import _disk

    top = float(np.percentile(brightest, 99.5)) if brightest.size else 0.0
    grey = np.clip(brightest / top, 0.0, 1.0) ** (1 / 2.2) if top > 0 else np.zeros_like(brightest)
    k = max(1, int(np.ceil(min_side / max(grey.shape))))
    img = np.repeat(np.repeat(grey, k, 0), k, 1)
    s = 2  # text scale
    label = text_bitmap(title, s) if title else None
    top_px = 12 * s if title else 0  # the title and its tails (g, p, y), then s of space
    key = [(SPHERE_OUTLINE, text_bitmap(OUTLINE_KEY, s))]
    if highlights:
        key.append((HIGHLIGHT_DOT, text_bitmap(HIGHLIGHT_KEY, s)))
    key_w = sum(11 * s + bm.shape[1] + 8 * s for _, bm in key)
    canvas = np.full((top_px + img.shape[0] + 11 * s,
                      max(img.shape[1], 4 * s + (label.shape[1] if title else 0), 2 * s + key_w), 3), 0.12,
                     np.float32)
    canvas[top_px:top_px + img.shape[0], : img.shape[1]] = img[..., None]
    x = 2 * s
    for colour, bm in key:  # a swatch, its words, then the next
        y = top_px + img.shape[0] + 2 * s
        canvas[y:y + 7 * s, x:x + 7 * s] = colour
        _stamp(canvas, bm, y, x + 11 * s)  # 4 s of space: the words read as the swatch's
        x += 11 * s + bm.shape[1] + 8 * s

    def at(x: float, y: float) -> tuple[float, float]:  # image pixel centre -> canvas (row, col)
        return top_px + (y - box[0].start + 0.5) * k, (x - box[1].start + 0.5) * k

    cy, cx = at(circle.x, circle.y)
    ring = canvas[top_px:top_px + img.shape[0]]  # the outline is cut where it leaves the picture, not drawn on the key
    _disk(ring, cy - top_px, cx, circle.r * k, SPHERE_OUTLINE, ring=max(1.0, k / 2))
    for x, y in highlights or []:
        _disk(canvas, *at(x, y), max(2.0, k * 0.6), HIGHLIGHT_DOT)
    if label is not None:
        _stamp(canvas, label, 2 * s, 2 * s)
    return canvas


def write_sphere_files(folder: Path, res: SphereLights, cap: "Capture", report: dict) -> None:
    """The calibration's files into ``folder`` (a staging folder): light files, lights.png, sphere.png."""
    from psctl.io.images import write_image
    from psctl.lights import write_light_files, write_lights_plot

    folder = Path(folder)
    write_light_files(folder, res.directions, res.intensities)
    ints = None if res.intensities is None else res.intensities.mean(1)
    write_lights_plot(folder / OUTPUT_FILES["lights"], res.directions, ints, cap.lights, report["light_mae"],
                      cap.name)
    spots = [i["highlight"] for i in res.images] if res.sphere == "chrome" else None
    title = f"{cap.name}: {res.sphere.upper()} SPHERE, R {res.circle.r:.1f} PX"
    write_image(folder / OUTPUT_FILES["sphere"], sphere_picture(res.brightest, res.circle, res.box, spots, title),
                "uint8")


def render_calibrate(r: dict) -> None:
    """The human-readable summary of ``run_calibrate``'s report (Rich, stdout)."""
    from psctl.errors import console
    from psctl.io.summary import escape, print_notes, print_written

    con = console()
    print_notes(con, r.get("notes", []))
    c = r["circle"]
    line = (f"[bold]{escape(r['object'])}[/]: {r['sphere']} sphere at x {c['x']:.1f}, y {c['y']:.1f}, radius "
            f"{c['r']:.1f} px ({escape(str(c['source']))}), {r['n_images']} lights, {r['seconds']:.2f} s")
    if r["light_mae"] is not None:
        errs = r["direction_errors"]
        line += (f"\n  against the folder's light files: direction error [bold]{r['light_mae']:.2f}°[/] mean, "
                 f"{max(errs):.2f}° largest")
    if r["intensity_re"] is not None:
        line += f", intensity relative error [bold]{r['intensity_re']:.3f}[/]"
    con.print(line, highlight=False, soft_wrap=True)
    print_written(con, r["outputs"])
