"""Lens distortion: ``psctl undistort`` writes a capture folder as a pinhole camera would have
seen it, so that what assumes a pinhole (``psctl calibrate --focal``, ``psctl depth --K``, point
lights) holds for photos through a real lens.

The model is OpenCV's (the numbers ``cv2.calibrateCamera`` prints): a point at normalised
coordinates (x, y) = ((u - cx) / fx, (v - cy) / fy) of the pinhole image is seen at

    r2 = x^2 + y^2,  radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
    xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

in the photo, at pixel (fx xd + cx, fy yd + cy). Undistorting needs only this forward map: each
output pixel reads the photo there (bilinear between the four nearest pixels). The output keeps
the photo's K and size (as OpenCV's ``undistort`` does by default): a barrel lens' photo (k1 < 0)
loses its rim, which lies outside the pinhole's frame; through a pincushion lens (k1 > 0) the
output's corners have no source in the photo and are left out of the written mask.

    >>> from psctl.undistort import undistort_map, remap
    >>> m = undistort_map(K, [-0.12, 0.03, 0, 0], (h, w))      # where each output pixel reads
    >>> out = remap(photo, m)                                 # [h, w, C] float
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from psctl.errors import ProgressFactory, PsctlError, check_path, check_progress

if TYPE_CHECKING:
    from psctl.io.capture import Capture

COMMAND = "undistort"
REPORT_FILE = "undistort_report.json"
PICTURE_FILE = "undistort.png"  # the shift of every pixel (psctl.io.capture's _NOT_IMAGES skips it)
K_FILE = "K.txt"  # psctl.depth.K_FILE, which psctl depth reads by default (a test holds them equal)
MASK_FILE = "mask.png"
GT_FILE = "Normal_gt.exr"  # float, NaN where there is none (psctl reads it after .mat and .png)
N_COEFFS = (4, 5, 8)  # k1 k2 p1 p2 [k3 [k4 k5 k6]], OpenCV's order
COEFF_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


MIN_VALID = 0.05  # under this share of output pixels with a source in the photos: refused, not written


def check_distortion(coeffs: "str | Iterable[float]", where: str | os.PathLike | None = None) -> np.ndarray:
    """OpenCV's coefficients k1, k2, p1, p2[, k3[, k4, k5, k6]] as float64 [8] (missing ones 0);
    text is comma- or space-separated numbers."""
    what = "--distortion" if where is None else "the distortion coefficients"
    if coeffs is None:
        raise PsctlError(where, "--distortion is required: 4, 5 or 8 numbers (k1,k2,p1,p2[,k3[,k4,k5,k6]])")
    if isinstance(coeffs, str):
        # commas and/or spaces, brackets allowed (numpy prints OpenCV's as [[k1 k2 p1 p2 k3]]); an
        # empty field (1,,2) would shift every later coefficient
        import re

        text = re.sub(r"[\[\]()]", " ", coeffs).strip()
        parts = re.split(r"\s*,\s*|\s+", text)
        try:
            if "" in parts:
                raise ValueError
            values = [float(p) for p in parts]
        except ValueError:
            raise PsctlError(where, f"{what} must be 4, 5 or 8 numbers (k1,k2,p1,p2[,k3[,k4,k5,k6]]), "
                                    f"not {coeffs!r}") from None
    else:
        try:
            values = [float(v) for v in np.asarray(coeffs, dtype=np.float64).ravel()]
        except (TypeError, ValueError):
            raise PsctlError(where, "distortion must be 4, 5 or 8 numbers (k1, k2, p1, p2[, k3[, k4, k5, k6]])") from None
    if len(values) in (12, 14):
        raise PsctlError(where, f"{len(values)} distortion coefficients: OpenCV's thin-prism (s1-s4) and tilt "
                                "(tauX, tauY) terms are not supported; psctl takes 4, 5 or 8 (k1,k2,p1,p2[,k3[,k4,k5,k6]])")
    if len(values) not in N_COEFFS:
        raise PsctlError(where, f"{what} must be 4, 5 or 8 numbers (OpenCV's k1,k2,p1,p2[,k3[,k4,k5,k6]]), "
                                f"got {len(values)}")
    if not np.isfinite(values).all():
        raise PsctlError(where, f"{what} {'contain' if where else 'contains'} NaN or infinite values")
    if max(abs(v) for v in values) > 1e6:
        raise PsctlError(where, f"{what} {'have' if where else 'has'} a coefficient above 1e6: OpenCV's "
                                "coefficients are for normalised coordinates (pixels / focal length), not pixels")
    out = np.zeros(8)
    out[:len(values)] = values
    return out


# the names OpenCV's samples and common calibration scripts store the two under (any case)
_K_KEYS = ("camera_matrix", "cameramatrix", "k", "mtx", "intrinsics", "intrinsic_matrix")
_DIST_KEYS = ("distortion_coefficients", "dist_coeffs", "distcoeffs", "d", "dist", "distortion")
# distortion_model values (ROS camera_info and others) that name this model; fisheye ones are refused
_PINHOLE_MODELS = ("plumb_bob", "rational_polynomial", "radtan", "radial-tangential", "radial_tangential", "opencv")


def read_camera(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(K [3, 3], coefficients [8]) from a calibration file as OpenCV's ``cv2.FileStorage`` writes
    it (YAML, with its ``%YAML`` line and ``!!opencv-matrix`` nodes, or JSON) or as plain YAML /
    JSON with a 3 x 3 list and a list of 4, 5 or 8 numbers, under names such as camera_matrix
    (K, mtx) and distortion_coefficients (D, dist_coeffs)."""
    return camera_file(path)[:2]


def camera_file(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, tuple[int, int] | None]:
    """``read_camera``'s (K, coefficients), and the image size (width, height) the file says it
    was calibrated at (``image_width`` and ``image_height``, as OpenCV's sample and ROS write
    them), or None."""
    import json

    import yaml

    from psctl.depth import check_intrinsics
    from psctl.errors import not_a_file
    from psctl.io.atomic import read_small_text

    path = Path(check_path("camera", path))
    if not path.is_file():
        raise PsctlError(path, not_a_file(path, "camera file is missing"))
    try:
        text = read_small_text(path).removeprefix("\ufeff")  # a byte-order mark (Notepad, PowerShell)
    except UnicodeDecodeError:
        from psctl.io.capture import _not_utf8

        raise PsctlError(path, _not_utf8(path)) from None
    except OSError as e:
        raise PsctlError(path, f"cannot read the camera file ({getattr(e, 'strerror', None) or e})") from None
    if text.lstrip().startswith("<"):
        raise PsctlError(path, "is XML; psctl reads OpenCV's YAML or JSON calibration files: save it as .yml or .json")

    class _Loader(yaml.SafeLoader):
        pass

    def _opencv(loader, suffix, node):  # !!opencv-matrix, !!opencv-nd-matrix, ...: their fields as they are
        if isinstance(node, yaml.MappingNode):
            return loader.construct_mapping(node, deep=True)
        return loader.construct_sequence(node, deep=True) if isinstance(node, yaml.SequenceNode) \
            else loader.construct_scalar(node)

    _Loader.add_multi_constructor("tag:yaml.org,2002:opencv-", _opencv)
    body = "\n".join(line for line in text.splitlines() if not line.startswith("%YAML"))  # OpenCV: %YAML:1.0 or 1.2
    try:
        try:
            data = json.loads(text)
        except ValueError:  # YAML (a flow mapping {K: ...} too)
            data = yaml.load(body, Loader=_Loader)
    except (ValueError, yaml.YAMLError) as e:
        raise PsctlError(path, f"is not valid YAML or JSON ({' '.join(str(e).split())[:160]})") from None
    if not isinstance(data, dict):
        raise PsctlError(path, "holds no named values; expected camera_matrix and distortion_coefficients")
    keys = {str(k).lower(): v for k, v in data.items()}
    spelt = {str(k).lower(): str(k) for k in data}
    # a fisheye (equidistant) calibration has 4 coefficients too, of another model
    model = str(keys.get("distortion_model", "plumb_bob")).strip().lower()
    if keys.get("fisheye_model") not in (None, 0, False, "0") or model not in _PINHOLE_MODELS:
        why = f"distortion_model {model}" if model not in _PINHOLE_MODELS else f"fisheye_model {keys['fisheye_model']}"
        raise PsctlError(path, f"is a calibration of another lens model ({why}: a fisheye's?); psctl undistort takes "
                               "OpenCV's standard model (k1, k2, p1, p2[, k3[, k4, k5, k6]]: plumb_bob, "
                               "rational_polynomial)")

    def value(n: str) -> np.ndarray:
        v, shape, channels = keys[n], (None, None), 1
        if isinstance(v, dict) and "data" in v:  # an opencv-matrix node (YAML tag or JSON type_id)
            shape = v.get("rows"), v.get("cols")
            channels = int(re.match(r"\s*(\d*)", str(v.get("dt", ""))).group(1) or 1)  # "5d": 5 channels
            v = v["data"]
        try:
            out = np.asarray(v, dtype=np.float64).ravel()
        except (TypeError, ValueError):
            raise PsctlError(path, f"{spelt[n]} is not a list of numbers") from None
        # rows x cols must be the data's count, as OpenCV's reader requires (a review: 2 x 3 over 9 numbers
        # was read as a 3 x 3 matrix)
        if shape != (None, None):
            if not all(isinstance(x, int) and not isinstance(x, bool) and x > 0 for x in shape):
                raise PsctlError(path, f"{spelt[n]}'s rows and cols must be two whole numbers, not "
                                       f"{shape[0]!r} and {shape[1]!r}")
            if shape[0] * shape[1] * channels != out.size:
                raise PsctlError(path, f"{spelt[n]} says rows: {shape[0]}, cols: {shape[1]}"
                                       f"{f' of {channels} channels' if channels > 1 else ''} but holds {out.size} "
                                       f"numbers")
        return out

    def find(names: Sequence[str], what: str) -> np.ndarray:
        found = [n for n in names if n in keys]
        if not found:
            raise PsctlError(path, f"has no {what} (looked for {', '.join(names)})")
        first = value(found[0])
        for n in found[1:]:  # two names for one thing: the file's author meant one of them
            other = value(n)
            if other.shape != first.shape or not np.array_equal(other, first):
                raise PsctlError(path, f"gives the {what} twice, as {spelt[found[0]]} and {spelt[n]}, with "
                                       "different values: keep one")
        return first

    K = find(_K_KEYS, "camera matrix")
    if K.size != 9:
        raise PsctlError(path, f"the camera matrix has {K.size} numbers, expected 9 (3 x 3)")
    size = None
    if "image_width" in keys and "image_height" in keys:
        try:
            w, h = float(keys["image_width"]), float(keys["image_height"])
        except (TypeError, ValueError):
            raise PsctlError(path, "image_width and image_height must be numbers") from None
        if not (w.is_integer() and h.is_integer() and w > 0 and h > 0):
            raise PsctlError(path, f"image_width and image_height must be positive whole numbers, not {w:g} and {h:g}")
        size = (int(w), int(h))
    return (check_intrinsics(K.reshape(3, 3), path),
            check_distortion(find(_DIST_KEYS, "distortion coefficients"), path), size)


def distort_points(x: np.ndarray, y: np.ndarray, coeffs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalised pinhole coordinates -> where the lens puts them (xd, yd), and the rational
    model's denominator (a point where it is <= 0 has no image)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = (float(c) for c in coeffs)
    r2 = x * x + y * y
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / np.where(den > 0, den, 1.0)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd, den


def _fold_radius(coeffs: np.ndarray, r_max: float) -> float:
    """The smallest radius (normalised) at which the radial map r -> r radial(r^2) stops growing:
    beyond it the lens model folds back (two pinhole radii to one photo radius) and says nothing
    true. inf when it grows up to ``r_max``."""
    r = np.linspace(0.0, r_max * 1.001 + 1e-9, 20001)
    rd, _, den = distort_points(r, np.zeros_like(r), np.r_[coeffs[:2], 0, 0, coeffs[4:]])
    bad = (np.diff(rd) <= 0) | (den[1:] <= 0)
    return float(r[1:][bad][0]) if bad.any() else float("inf")


def _jacobian(x: np.ndarray, y: np.ndarray, coeffs: np.ndarray) -> np.ndarray:
    """The determinant of the map (x, y) -> (xd, yd) (central differences): <= 0 where the whole
    model, tangential terms included, folds back or turns the image over. _fold_radius sees the
    radial part only (a QA helper: p1 = p2 = 0.5 folded 134 of a mask's 780 pixels unnoticed)."""
    e = 1e-6
    xa, ya, _ = distort_points(x + e, y, coeffs)
    xb, yb, _ = distort_points(x - e, y, coeffs)
    xc, yc, _ = distort_points(x, y + e, coeffs)
    xe, ye, _ = distort_points(x, y - e, coeffs)
    return ((xa - xb) * (yc - ye) - (xc - xe) * (ya - yb)) / (4 * e * e)


@dataclass(frozen=True)
class UndistortMap:
    """Where each output pixel reads the photo: ``x``, ``y`` float64 [H, W] (pixel centres at
    integer coordinates, OpenCV's convention) and ``valid`` bool [H, W] (inside the photo and
    inside the lens model's fold radius)."""

    x: np.ndarray
    y: np.ndarray
    valid: np.ndarray
    folded: int  # output pixels beyond the fold radius (left out of ``valid``)
    src_shape: tuple[int, int]  # the photo's (H, W)


def undistort_map(K: np.ndarray, coeffs: "np.ndarray | Iterable[float] | str", shape: tuple[int, int],
                  src_shape: tuple[int, int] | None = None) -> UndistortMap:
    """The map of an undistorted image of ``shape`` (H, W) taken with pinhole ``K`` from a photo of
    ``src_shape`` (default the same) through a lens with OpenCV's ``coeffs``."""
    from psctl.depth import check_intrinsics

    K = check_intrinsics(K)
    coeffs = check_distortion(coeffs)
    h, w = shape
    sh, sw = src_shape or shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    x, y = (u - cx) / fx, (v - cy) / fy
    xd, yd, den = distort_points(x, y, coeffs)
    xs, ys = fx * xd + cx, fy * yd + cy
    r = np.sqrt(x * x + y * y)
    fold = _fold_radius(coeffs, float(r.max()) if r.size else 0.0)
    beyond = (r >= fold) | (den <= 0) | (_jacobian(x, y, coeffs) <= 0)
    # the model is one-to-one only on the piece of the plane around the principal point where it
    # keeps its orientation: a piece of positive Jacobian cut off from it by a fold (strong
    # tangential terms: p1 0.4, p2 0.3) shows photo pixels the main piece shows too (a ghost)
    pu, pv = int(round(cx)), int(round(cy))
    if 0 <= pu < w and 0 <= pv < h and not beyond[pv, pu] and beyond.any():
        from scipy import ndimage

        pieces, _ = ndimage.label(~beyond)  # 4-connected
        beyond = pieces != pieces[pv, pu]
    inside = (xs >= -0.5) & (xs <= sw - 0.5) & (ys >= -0.5) & (ys <= sh - 0.5)
    return UndistortMap(xs, ys, inside & ~beyond, int(beyond.sum()), (int(sh), int(sw)))


def remap(image: np.ndarray, m: UndistortMap, fill: float = 0.0) -> np.ndarray:
    """Bilinear resampling of ``image`` [h, w] or [h, w, C] at ``m``'s positions -> [H, W(, C)]
    float32; ``fill`` where ``m.valid`` is False. Positions within half a pixel of the border read
    the border pixel (the photo's pixels cover their whole square)."""
    img = np.asarray(image, dtype=np.float32)
    if img.ndim not in (2, 3) or img.shape[:2] != tuple(m.src_shape):
        raise PsctlError(None, f"image of shape {img.shape} does not fit this map, made for photos of "
                               f"{m.src_shape[1]}x{m.src_shape[0]} ([H, W] or [H, W, C])")
    flat = img.reshape(img.shape[0] * img.shape[1], -1)
    sh, sw = img.shape[:2]
    xs = np.clip(m.x, 0, sw - 1)
    ys = np.clip(m.y, 0, sh - 1)
    x0 = np.minimum(np.floor(xs).astype(np.int64), max(sw - 2, 0))
    y0 = np.minimum(np.floor(ys).astype(np.int64), max(sh - 2, 0))
    x1, y1 = np.minimum(x0 + 1, sw - 1), np.minimum(y0 + 1, sh - 1)
    # weights in float32, in place: 1.6x faster than float64 on a 612 x 512 photo, 2e-7 apart
    ax, ay = (xs - x0).astype(np.float32)[..., None], (ys - y0).astype(np.float32)[..., None]
    out = flat[y0 * sw + x0]
    out += (flat[y0 * sw + x1] - out) * ax
    bottom = flat[y1 * sw + x0]
    bottom += (flat[y1 * sw + x1] - bottom) * ax
    out += (bottom - out) * ay
    out[~m.valid] = np.float32(fill)
    return out.reshape(*m.x.shape, *img.shape[2:])


def _write_dtype(dtype: str, bits: int, suffix: str) -> str:
    """write_image's dtype for an output like its input: same bit depth, float stays float."""
    if dtype in ("half",):
        return "half"
    if dtype in ("float", "double"):
        return "float"
    if suffix in (".exr",) or (bits > 16 and suffix in (".tif", ".tiff")):  # uint32 TIFF: float keeps it
        return "float"
    return "uint8" if bits <= 8 else "uint16"


# files a file manager leaves in any folder it shows: an --out holding only these counts as empty
_SYSTEM_FILES = (".DS_Store", "Thumbs.db", "desktop.ini")

# what each extension is written as (OpenImageIO picks the format by the name)
_EXT_FORMAT = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".tif": "tiff", ".tiff": "tiff", ".exr": "openexr"}


def _check_capture(cap: "Capture", images: list[Path]) -> bool:
    """What psctl undistort cannot write as it read it: a one-line error before any work. Returns
    whether the image list names every image bare (else it is written again with bare names)."""
    from psctl.io.images import image_info

    # (open_capture read every header; image_info only where it kept none)
    infos = dict(zip(cap.image_paths, cap.infos or ()))
    if cap.ambient_info is not None:
        infos[cap.ambient_path] = cap.ambient_info
    for p in images:
        fmt = (infos.get(p) or image_info(p)).format
        want = _EXT_FORMAT.get(p.suffix.lower())
        if want is not None and fmt and fmt != want:
            raise PsctlError(p, f"holds {fmt} data under a {p.suffix} name; it would be written as {want}: rename it")
    seen: dict[str, Path] = {}
    for p in cap.image_paths:
        if p.name.lower() in seen:
            raise PsctlError(p, f"has the name of {seen[p.name.lower()]}, listed before it: psctl undistort writes "
                                "every image beside the others in --out")
        seen[p.name.lower()] = p
    return all(p.parent == cap.path for p in cap.image_paths)


def run_undistort(path: str | os.PathLike, out: str | os.PathLike, K: "str | os.PathLike | np.ndarray | None" = None,
                  distortion: "str | Iterable[float] | None" = None, progress: "ProgressFactory | None" = None,
                  camera: str | os.PathLike | None = None) -> dict:
    """Write the capture at ``path`` into ``out`` as a pinhole camera ``K`` would have taken it,
    undoing a lens with OpenCV's ``distortion`` coefficients (or ``camera``: a calibration file
    with both, ``read_camera``); return the report (what ``psctl undistort --json`` prints).

    ``out`` (required: a new or empty folder, a file manager's .DS_Store and the like aside, or an
    earlier psctl undistort output, which is replaced; never the capture folder nor another
    capture) gets, all or none: every
    image and the ambient image under its own name, format and bit depth (the stored values
    resampled bilinearly, upright as psctl reads them, without their EXIF block); mask.png (the
    folder's mask resampled, without the pixels that have no source in the photo; written only
    when there is a mask or such pixels); Normal_gt.exr (ground truth resampled from the neighbours
    that have a normal and renormalised, NaN where none has); the light files copied as they are,
    the image list too (written again with bare names when it named images in other folders); K.txt
    (the pinhole camera: ``K``); undistort.png (how far each pixel moved) and
    undistort_report.json.

    Report: object, path, camera {K, distortion {k1 .. k6}}, size [W, H], n_images, valid_fraction (output
    pixels with a source in the photo), folded (pixels beyond the lens model's fold radius),
    shift {max, mean} (pixels, over the valid ones), mask {pixels, from}, outputs, seconds, notes.
    """
    from psctl.depth import check_intrinsics, read_intrinsics
    from psctl.io.atomic import (check_inputs_kept, check_output_dir, read_outputs_list, replaced_notes, staged_outputs,
                                 write_bytes_atomic, write_outputs_list)
    from psctl.io.capture import (GT_FILES, INTENSITIES_FILE, LIGHTS_FILE, check_not_capture, holds_capture,
                                  load_ground_truth, load_mask, open_capture, read_matrix)
    from psctl.io.images import icc_profile, read_image, write_image
    from psctl.io.report import write_json

    t0 = time.perf_counter()
    check_path("path", path)
    check_path("out", out)
    if not os.fspath(out).strip():
        raise PsctlError(None, "--out is empty; name a new folder for the undistorted capture")
    progress = check_progress(progress)
    if camera is not None:
        if K is not None or distortion is not None:
            raise PsctlError(None, "--camera gives the camera matrix and the distortion: leave out --K and "
                                   "--distortion")
        K_path: Path | None = Path(check_path("camera", camera))
        K, coeffs, calibrated_size = camera_file(camera)
    else:
        calibrated_size = None
        if K is None:
            raise PsctlError(None, "give the camera: --K FILE and --distortion k1,k2,p1,p2[,k3], or --camera FILE "
                                   "(OpenCV's calibration file)")
        if isinstance(K, (str, os.PathLike)):
            K_path = Path(K)
            K = read_intrinsics(K)
        else:
            K_path = None
            K = check_intrinsics(K)
        coeffs = check_distortion(distortion)
    cap = open_capture(path)  # light files checked as psctl normals reads them: the output must read back
    images = [*cap.image_paths, *([cap.ambient_path] if cap.ambient_path is not None else [])]
    bare = _check_capture(cap, images)
    out_dir = Path(out)
    list_file = cap.list_path
    copies = [p for p in (cap.lights_path, cap.intensities_path) if p is not None]
    names = [p.name for p in images] + [p.name for p in copies] + ([list_file.name] if list_file is not None else [])
    written = (*names, K_FILE, MASK_FILE, GT_FILE, PICTURE_FILE, REPORT_FILE)
    notes: list[str] = []
    own = set(read_outputs_list(out_dir, COMMAND))
    if own and os.path.realpath(out_dir) != os.path.realpath(cap.path):
        # an earlier psctl undistort's folder: replaced, unless it holds someone's capture files
        # besides (files added since that are not a capture's, such as light files, may stay)
        if holds_capture(out_dir, ignore=own):
            check_not_capture(out_dir, cap, written, default_out=None)
        gt_names = {g.lower() for g in GT_FILES}
        stray = sorted(p.name for p in out_dir.iterdir() if p.name.lower() in gt_names and p.name not in own)
        if stray:  # psctl normals' normal.png, say: read before Normal_gt.exr, it would score the new capture
            raise PsctlError(out_dir / stray[0], "was not written by psctl undistort and would be read as the "
                                                 "undistorted capture's ground truth: move it away or choose "
                                                 "another --out")
        for name, widths in ((LIGHTS_FILE, (3,)), (INTENSITIES_FILE, (3, 1))):
            kept = out_dir / name
            if name in written or name in own or not kept.is_file():
                continue
            # a light file added since (kept, as the docs say) must fit the new capture, or the folder
            # written would not read back (a QA helper: 3 rows kept for 6 new images, exit 0)
            rows = len(read_matrix(kept, widths, "light intensities" if name == INTENSITIES_FILE else "light directions"))
            if rows != cap.n_images:
                raise PsctlError(kept, f"was added to the earlier output and stays, but has {rows} rows for the "
                                       f"{cap.n_images} images written now (psctl normals would refuse the folder): "
                                       "remove it or choose another --out")
        if (out_dir / "psctl").is_dir():
            notes.append(f"outputs: {out_dir / 'psctl'} holds results computed from the earlier undistorted images; "
                         "run them again")
    else:
        check_not_capture(out_dir, cap, written, default_out=None)
        # a new or empty folder only (as the docs say): other files would join the capture, and a
        # normal.png (psctl normals' output) would be read as its ground truth
        others = sorted((p.name for p in out_dir.iterdir()
                         if not p.name.startswith(".psctl-staging.") and p.name not in _SYSTEM_FILES),
                        key=lambda n: (n.startswith("."), n)) if out_dir.is_dir() else []
        if others:
            raise PsctlError(out_dir, f"is not empty ({others[0]}{' ...' if len(others) > 1 else ''}) and is not "
                                      "an earlier psctl undistort output: name a new or empty folder")
    # never over a file this run reads (an image linked from an earlier output, say)
    inputs = {os.path.realpath(p) for p in (*cap.input_paths, *copies, *([list_file] if list_file else []))}
    clash = [n for n in (*written, *sorted(own)) if os.path.realpath(out_dir / n) in inputs]  # own: replaced
    if clash:
        raise PsctlError(out_dir / clash[0], "is an input of this capture; choose another --out")
    check_inputs_kept(out_dir, written, [("--camera" if camera is not None else "--K", K_path)])
    check_output_dir(out_dir)

    m = undistort_map(K, coeffs, (cap.height, cap.width))
    shift = np.hypot(m.x - np.arange(cap.width)[None, :], m.y - np.arange(cap.height)[:, None])
    if not m.valid.any():
        raise PsctlError(K_path, "with these intrinsics and --distortion no output pixel has a source in the "
                                 "photos: are fx, fy, cx and cy in this image's pixels, and the coefficients this "
                                 "lens's?")
    if m.valid.mean() < MIN_VALID:  # (a lens's undistortion keeps most of the frame: wrong units or a typo)
        raise PsctlError(K_path, f"with these intrinsics and --distortion only {int(m.valid.sum())} of {m.valid.size} "
                                 f"output pixels ({100 * m.valid.mean():.3g} %) have a source in the photos: are fx, "
                                 f"fy, cx and cy in this image's pixels, and the coefficients this lens's?")
    # the mask: the folder's, resampled, and never where the photo has nothing
    mask = m.valid
    mask_from = "the pixels with a source in the photos"
    if cap.mask_path is not None:
        mask = (remap(load_mask(cap).astype(np.float32), m) >= 0.5) & m.valid
        mask_from = f"{cap.mask_path.name}, resampled"
        if not mask.any():
            raise PsctlError(cap.mask_path, "no pixel of the mask keeps a source in the photos after undistortion: "
                                            "are the intrinsics and --distortion this camera's?")
    write_mask = cap.mask_path is not None or not m.valid.all()
    gt = load_ground_truth(cap)
    turned = [p.name for p, o in zip(cap.image_paths, cap.orientations) if o != 1]
    if turned:
        notes.append(f"images: {len(turned)} of {cap.n_images} carry an EXIF orientation ({turned[0]}...); they are "
                     "undistorted upright, as psctl reads them (and as OpenCV's imread gives them to a calibration), "
                     "and written upright")
    if any(pg > 1 for pg in cap.pages):
        notes.append("images: a multi-page TIFF's first page only is written (the one psctl reads)")
    if m.folded:
        notes.append(f"lens: {m.folded} output pixels lie where the distortion model folds back (beyond the radius "
                     "where it stops growing, or where its tangential terms fold it: outside its calibrated field); "
                     "they are left out of the mask")
    outside = int((~m.valid).sum()) - m.folded
    if outside:
        notes.append(f"{outside} of {m.valid.size} output pixels ({100 * outside / m.valid.size:.1f} %) have no "
                     "source in the photos (they fall outside the photos' frame): black, and outside mask.png")
    if calibrated_size is not None and calibrated_size != (cap.width, cap.height):
        notes.append(f"camera: {Path(camera).name} was calibrated on {calibrated_size[0]}x{calibrated_size[1]} images "
                     f"(image_width, image_height), these are {cap.width}x{cap.height}: its K is in that image's "
                     "pixels (for a crop, subtract the crop's offset from cx and cy; for a resize, scale fx, fy, cx "
                     "and cy)")
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if not (0 <= cx <= cap.width - 1 and 0 <= cy <= cap.height - 1):
        notes.append(f"K's principal point {cx:g}, {cy:g} lies outside these {cap.width}x{cap.height} images: is K "
                     "for this image size? (a cropped image's K has the crop's offset subtracted)")
    if not bare:
        notes.append(f"{list_file.name} lists images outside the folder's top level ({next(str(p) for p in cap.image_paths if p.parent != cap.path)}"
                     "...): they are written beside each other, and the list again with their bare names")
    if cap.unread:
        notes.append(f"not carried over: {', '.join(cap.unread)} (psctl does not read them)")
    if gt is not None and cap.gt_path is not None and cap.gt_path.name != GT_FILE:
        notes.append(f"ground truth: {cap.gt_path.name} is written as {GT_FILE} (float, NaN where there is none)")
    outputs_names = [*names, K_FILE, PICTURE_FILE, REPORT_FILE]
    if write_mask:
        outputs_names.append(MASK_FILE)
    if gt is not None:
        outputs_names.append(GT_FILE)
    if len(set(n.lower() for n in outputs_names)) != len(outputs_names):
        twice = next(n for n in outputs_names if [o.lower() for o in outputs_names].count(n.lower()) > 1)
        raise PsctlError(cap.path / twice, "is named like another file psctl undistort writes; rename it")
    notes += replaced_notes(out_dir, outputs_names, COMMAND)
    valid_shift = shift[m.valid]
    report = {
        "object": cap.name,
        "path": os.path.abspath(cap.path),
        "camera": {"K": [[round(float(v), 6) for v in row] for row in K],
                   "distortion": dict(zip(COEFF_NAMES, (float(c) for c in coeffs)))},
        "size": [cap.width, cap.height],
        "n_images": cap.n_images,
        "valid_fraction": round(float(m.valid.mean()), 6),
        "folded": m.folded,
        "shift": {"max": round(float(valid_shift.max()), 3), "mean": round(float(valid_shift.mean()), 3)},
        "mask": {"pixels": int(mask.sum()) if write_mask else None, "from": mask_from if write_mask else None},
        "outputs": {},
        "seconds": 0.0,
        "notes": notes,
    }
    report["outputs"] = {"folder": os.path.abspath(out_dir),
                         **{k: os.path.abspath(out_dir / v) for k, v in (("K", K_FILE), ("picture", PICTURE_FILE),
                                                                          ("report", REPORT_FILE))}}
    if write_mask:
        report["outputs"]["mask"] = os.path.abspath(out_dir / MASK_FILE)
    if gt is not None:
        report["outputs"]["ground_truth"] = os.path.abspath(out_dir / GT_FILE)

    advance = progress(f"{cap.name}: undistorting", len(images))
    with staged_outputs(out_dir, replaces=lambda: read_outputs_list(out_dir, COMMAND)) as stage:
        for p in images:
            pixels, info = read_image(p)
            # a file tagged linear (psctl synth's PNGs, EXRs) stays tagged so, a PNG tagged sRGB or a gamma so
            # (psctl reads it as stored, and its note repeats the file's word); others carry no tag
            write_image(stage / p.name, remap(pixels, m), _write_dtype(info.dtype, info.bits, p.suffix.lower()),
                        kind="linear" if "lin" in info.color_space.lower() else "data", png_tag=info.png_tag,
                        icc=icc_profile(p))  # its profile (tone curves) goes with it
            advance(1)
        for p in copies:
            write_bytes_atomic(stage / p.name, p.read_bytes())
        if list_file is not None:
            write_bytes_atomic(stage / list_file.name, list_file.read_bytes() if bare else
                               "".join(f"{p.name}\n" for p in cap.image_paths).encode("utf-8"))
        write_bytes_atomic(stage / K_FILE, "".join(" ".join(f"{float(v):.10g}" for v in row) + "\n"
                                                   for row in K).encode())
        if write_mask:
            write_image(stage / MASK_FILE, mask.astype(np.float32), "uint8", kind="data")
        if gt is not None:
            write_image(stage / GT_FILE, undistort_normals(gt, m), "float", kind="data")
        write_image(stage / PICTURE_FILE, shift_picture(shift, m.valid, cap.name), "uint8")
        write_outputs_list(stage, outputs_names, COMMAND)
        report["seconds"] = round(time.perf_counter() - t0, 3)
        write_json(stage / REPORT_FILE, report)
    report["seconds"] = round(time.perf_counter() - t0, 3)
    return report


def undistort_normals(normals: np.ndarray, m: UndistortMap) -> np.ndarray:
    """[h, w, 3] unit normals (zero: none) -> [H, W, 3] float32: the bilinear mean of the four
    neighbours that have a normal, renormalised (so that the resampled mask's rim keeps one); NaN
    where none has one or there is no source."""
    n = np.asarray(normals, np.float32)
    has = (np.abs(n).sum(-1) > 0).astype(np.float32)
    v = remap(n * has[..., None], m)  # the zero vectors add nothing; renormalising divides out the weights
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    ok = (remap(has, m) > 1e-6) & m.valid & (norm[..., 0] > 1e-6)
    return np.where(ok[..., None], v / np.maximum(norm, 1e-6), np.nan).astype(np.float32)


def shift_picture(shift: np.ndarray, valid: np.ndarray, name: str) -> np.ndarray:
    """How far each output pixel's source lies from it (pixels), as a heat map with its scale."""
    from psctl.io.report import error_heatmap

    top = float(shift[valid].max()) if valid.any() else 0.0
    vmax, step = nice_scale(top)
    n = int(round(vmax / step))
    labels = {i / n: f"{round(i * step, 6):g} PX" for i in range(n + 1)}
    return error_heatmap(shift, valid, vmax, f"{name}: LENS SHIFT\nMAX {top:.1f} PX", labels=labels)


def nice_scale(top: float, ticks: int = 4) -> tuple[float, float]:
    """(vmax, step): the smallest step of 1, 2, 2.5 or 5 times a power of ten that reaches ``top``
    (at least 1: a scale of 0 to 1 pixel for a lens that barely distorts) in at most ``ticks``
    steps, and vmax = that many steps. Ticks on round values (0, 1, 2, 3, 4 PX), not on thirds of
    the largest shift (1.3, 2.7 PX)."""
    top = max(float(top), 1.0)
    exponent = int(np.floor(np.log10(top / ticks)))
    for e in (exponent, exponent + 1):
        for m in (1.0, 2.0, 2.5, 5.0):
            step = m * 10.0 ** e
            n = int(np.ceil(top / step - 1e-9))
            if n <= ticks:
                return round(n * step, 9), step
    return 10.0 ** (exponent + 2), 10.0 ** (exponent + 2)  # not reached: 10^(e+1) * ticks >= top


def render_undistort(r: dict) -> None:
    """The human-readable summary of ``run_undistort``'s report (Rich, stdout)."""
    from psctl.errors import console
    from psctl.io.summary import escape, print_notes, print_written

    con = console()
    print_notes(con, r.get("notes", []))
    w, h = r["size"]
    con.print(f"[bold]{escape(r['object'])}[/]: {r['n_images']} images of {w}x{h} undistorted, pixels moved "
              f"up to [bold]{r['shift']['max']:.1f}[/] (mean {r['shift']['mean']:.2f}), "
              f"{100 * r['valid_fraction']:.1f} % with a source in the photos, {r['seconds']:.2f} s",
              highlight=False, soft_wrap=True)
    print_written(con, {k: v for k, v in r["outputs"].items() if k != "folder"})


__all__: Sequence[str] = ("read_camera", "check_distortion", "distort_points", "undistort_map", "remap", "run_undistort",
                          "undistort_normals", "UndistortMap")
