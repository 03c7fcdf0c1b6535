"""Non-learning baselines.

``l2``: Woodham's least-squares photometric stereo. Each pixel's grey observations m_k (k over
images, already divided by light intensity) are fitted as m_k = l_k . b; the normal is b / |b|
and |b| the albedo. The solution b = (L^T L)^-1 L^T m only needs the 3 x 3 matrix L^T L and the
running sum sum_k l_k m_k, so images are streamed and memory does not grow with their number.

``l2-trimmed``: the same fit per pixel on the middle of its observations only. Shadows (attached
and cast) are a pixel's darkest observations and specular highlights its brightest, and both
break m_k = l_k . b; sorting each pixel's observations and dropping the darkest ``low`` and the
brightest ``high`` shares keeps those that a Lambertian model explains. Needs every observation
of a pixel at once: [N, P] grey values. Not a psctl method: chosen on synthetic sets it beats L2
there (7.85 vs 11.80 degrees over five) but loses on the DiLiGenT dev split (10.60 vs 9.47; ball
and cat better, pot1, bear and pot2 worse), the go/no-go written before that run
(benchmarks/trim_grid.py, docs/usage.md). Kept for that benchmark and for Python users.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from psctl.errors import PsctlError

# Grey = ITU-R BT.601 luma, as MATLAB's rgb2gray (the DiLiGenT baseline code's convention).
GREY = np.array([0.2989, 0.5870, 0.1140], np.float32)
# a pixel whose brightest observation is at most this share of the bright pixels' carries no
# information: relative, so that a capture's units (its intensity file, a float image's range) do
# not decide which pixels count (an absolute 1e-6 did, session 38). "The bright pixels'": the 99th
# percentile of the pixels' peaks (the higher value), not the brightest one's, so that one hot
# pixel (a cosmic-ray hit in a float image, 1e6 times the rest) does not make every other dark
DARK = 1e-6
DARK_QUANTILE = 0.99
DEFAULT_NORMAL = np.array([0.0, 0.0, 1.0], np.float32)  # what a dark pixel gets: facing the camera


def dark_pixels(peak: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
    """Pixels whose brightest observation ``peak`` [P] is at most DARK of the bright pixels' (the
    DARK_QUANTILE quantile, its higher value, of the peaks above 0: with 100 or fewer of those, the
    brightest; all, when every pixel is 0), and with
    ``b`` [P, 3] (least squares' normal times albedo) those whose solution is (relatively) zero."""
    def tiny(v: np.ndarray, share: float) -> np.ndarray:
        lit = v[v > 0]  # of the pixels with any light: a small object on a black frame has most at 0
        ref = float(np.quantile(lit, DARK_QUANTILE, method="higher")) if lit.size else 0.0
        return v <= share * ref

    dark = tiny(np.asarray(peak, np.float64), DARK)
    return dark if b is None else dark | tiny(np.linalg.norm(b, axis=1), 1e-12)


@dataclass
class L2Result:
    normals: np.ndarray  # [H, W, 3] float32 unit vectors (0 outside the mask)
    albedo: np.ndarray  # [H, W] float32, |b|
    dark: np.ndarray  # [H, W] bool, pixels dark in every image (given DEFAULT_NORMAL)


def lights_problem(lights: np.ndarray) -> str | None:
    """Why least squares cannot solve for normals with these light directions [N, 3], or None:
    fewer than three, or (nearly) coplanar, which leaves the normal undetermined."""
    lights = np.asarray(lights, np.float64).reshape(-1, 3)
    if len(lights) < 3:
        return f"needs at least 3 images (got {len(lights)})"
    s = np.linalg.svd(lights, compute_uv=False)
    if s[-1] < 1e-3 * s[0]:
        return f"light directions are (nearly) coplanar: they cannot determine the normals (from these {len(lights)})"
    return None


def l2_result(b: np.ndarray, dark: np.ndarray, mask: np.ndarray) -> "L2Result":
    """Normal, albedo and dark maps [H, W, ...] from per-pixel solutions b [P, 3] (normal times
    albedo) and dark [P] over the pixels of ``mask``; dark pixels get DEFAULT_NORMAL."""
    albedo = np.linalg.norm(b, axis=1)
    # no absolute floor: float images 1e-12 times as bright are as valid (darkness is relative, DARK)
    n = b / np.where(albedo > 0, albedo, 1.0)[:, None]
    n[dark] = DEFAULT_NORMAL
    h, w = mask.shape
    normals = np.zeros((h, w, 3), np.float32)
    normals[mask] = n
    alb = np.zeros((h, w), np.float32)
    alb[mask] = np.where(dark, 0.0, albedo)
    dark_map = np.zeros((h, w), bool)
    dark_map[mask] = dark
    return L2Result(normals, alb, dark_map)


class L2Accumulator:
    """Streaming least squares: ``add`` one image at a time, then ``solve``."""

    def __init__(self, mask: np.ndarray):
        self.mask = mask.astype(bool)
        p = int(self.mask.sum())
        self.lhs = np.zeros((3, 3), np.float64)
        self.rhs = np.zeros((3, p), np.float64)
        self.peak = np.zeros(p, np.float32)
        self.lights: list[np.ndarray] = []

    def add(self, image: np.ndarray, light: np.ndarray) -> None:
        """image: [H, W, 3] or [H, W] linear, intensity-normalised; light: [3], used as given (a
        unit direction for such an image: a row of length 2 is read as a light twice as bright)."""
        grey = image @ GREY if image.ndim == 3 else image
        m = grey[self.mask].astype(np.float64)
        light = np.asarray(light, np.float64)
        self.lhs += np.outer(light, light)
        self.rhs += light[:, None] * m[None, :]
        np.maximum(self.peak, m, out=self.peak, casting="unsafe")
        self.lights.append(light)

    def solve(self) -> L2Result:
        problem = lights_problem(np.array(self.lights))
        if problem:
            raise PsctlError(None, f"L2: {problem}")
        b = np.linalg.solve(self.lhs, self.rhs).T  # [P, 3]
        return l2_result(b, dark_pixels(self.peak, b), self.mask)


def l2_normals(images: Iterable[np.ndarray] | np.ndarray, lights: np.ndarray,
               mask: np.ndarray | None = None) -> L2Result:
    """Least-squares normals.

    Args:
        images: [N, H, W, 3] or [N, H, W] array, or an iterable of [H, W, (3)] images.
        lights: [N, 3] light directions (x right, y up, z toward the camera), used as given: unit
            rows for images divided by their intensities, or rows of length e_j (direction times
            intensity) for images as captured. ``psctl.estimate_normals`` normalises the rows and
            divides by ``intensities`` itself.
        mask: [H, W] bool, pixels to solve (all when None).
    """
    lights = np.asarray(lights, np.float64)
    acc = None
    k = -1
    for k, img in enumerate(images):
        if acc is None:
            acc = L2Accumulator(np.ones(img.shape[:2], bool) if mask is None else mask)
        if k >= len(lights):
            raise PsctlError(None, f"more images than light directions ({len(lights)})")
        acc.add(np.asarray(img, np.float32), lights[k])
    if acc is None:
        raise PsctlError(None, "no images")
    if k + 1 != len(lights):
        raise PsctlError(None, f"{k + 1} images but {len(lights)} light directions")
    return acc.solve()


# The shares dropped per pixel, chosen on synthetic test sets only (benchmarks/trim_grid.py,
# docs/usage.md "A trimmed L2: tried, not a method"). First rule (syntest, syntest_dl, syntest_dl_ir): 0.6 / 0.3, which
# lost to L2 on the DiLiGenT dev split; second rule, adding a wrong intensity file and an 8-bit
# dark capture: 0.55 / 0.25 (mean over the five sets 7.85, L2 11.80), which lost too (10.60 vs 9.47)
DEFAULT_TRIM = {"low": 0.55, "high": 0.25}
_CHUNK = 16384  # pixels solved at once (bounds the [K, chunk, 3] temporaries)


def trimmed_range(n: int, low: float, high: float) -> tuple[int, int]:
    """(first, stop): the sorted observations kept out of ``n``; at least 3 (all when n <= 3)."""
    if not (0 <= low and 0 <= high and low + high < 1):
        raise PsctlError(None, f"trim shares must be >= 0 with low + high < 1 (got low={low}, high={high})")
    keep = min(n, max(3, int(round((1 - low - high) * n))))
    first = min(int(round(low * n)), n - keep)
    return first, first + keep


def trimmed_l2_solve(grey: np.ndarray, lights: np.ndarray, low: float = DEFAULT_TRIM["low"],
                     high: float = DEFAULT_TRIM["high"]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares per pixel on its middle observations.

    Args:
        grey: [N, P] grey observations (intensity-normalised), lights: [N, 3].
    Returns:
        b [P, 3] (normal times albedo), dark [P] bool (no light: b is 0), and fallback [P] bool:
        pixels whose kept lights were (nearly) coplanar, solved on all observations instead.
    """
    n, p = grey.shape
    lights = np.asarray(lights, np.float64)
    if lights.shape != (n, 3):
        raise PsctlError(None, f"{n} images but light directions of shape {lights.shape}")
    problem = lights_problem(lights)
    if problem:
        raise PsctlError(None, f"L2: {problem}")
    first, stop = trimmed_range(n, low, high)
    full = np.linalg.pinv(lights)  # [3, N]: the all-observation solution, for degenerate pixels
    b = np.zeros((p, 3), np.float64)
    fallback = np.zeros(p, bool)
    for a in range(0, p, _CHUNK):
        g = np.asarray(grey[:, a:a + _CHUNK], np.float64)
        idx = np.argsort(g, axis=0, kind="stable")[first:stop]  # [K, c]
        lk = lights[idx]  # [K, c, 3]
        mk = np.take_along_axis(g, idx, 0)  # [K, c]
        lhs = np.einsum("kci,kcj->cij", lk, lk)
        rhs = np.einsum("kci,kc->ci", lk, mk)
        ev = np.linalg.eigvalsh(lhs)  # ascending
        bad = ev[:, 0] < 1e-6 * ev[:, 2]
        lhs[bad] = np.eye(3)
        x = np.linalg.solve(lhs, rhs[..., None])[..., 0]
        x[bad] = (full @ g[:, bad]).T
        b[a:a + _CHUNK], fallback[a:a + _CHUNK] = x, bad
    dark = dark_pixels(grey.max(0), b)
    b[dark] = 0
    return b, dark, fallback


def trimmed_l2_normals(images: Iterable[np.ndarray] | np.ndarray, lights: np.ndarray,
                       mask: np.ndarray | None = None, low: float = DEFAULT_TRIM["low"],
                       high: float = DEFAULT_TRIM["high"]) -> L2Result:
    """Least-squares normals from each pixel's middle observations (the darkest ``low`` and
    brightest ``high`` shares dropped); arguments as ``l2_normals``."""
    lights = np.asarray(lights, np.float64)
    mask = None if mask is None else np.asarray(mask).astype(bool)  # as L2Accumulator
    grey = []
    for img in images:
        img = np.asarray(img, np.float32)
        if mask is None:
            mask = np.ones(img.shape[:2], bool)
        grey.append((img @ GREY if img.ndim == 3 else img)[mask])
    if not grey:
        raise PsctlError(None, "no images")
    if len(grey) != len(lights):
        raise PsctlError(None, f"{len(grey)} images but {len(lights)} light directions")
    b, dark, _ = trimmed_l2_solve(np.stack(grey), lights, low, high)
    return l2_result(b, dark, mask)
