"""From normals to a surface: integrate a normal map into a depth map, then a mesh.

    >>> import psctl
    >>> z = psctl.integrate_normals(normals, mask)                     # [H, W] float32, NaN outside
    >>> z = psctl.integrate_normals(normals, mask, method="bilateral")  # keeps depth jumps
    >>> report = run_depth("captures/ball", method="poisson")            # files + report dict

Conventions (as everywhere in psctl): x right, y up, z toward the camera; image row 0 is the top.
The result is the surface's z coordinate, so larger values are nearer the camera.

* Orthographic (default): z in pixel units (one pixel = one unit of x and y). Its gradient is
  dz/dcol = -nx/nz and dz/drow = +ny/nz (rows go down while y goes up).
* Perspective (intrinsics K, 3 x 3, OpenCV layout: fx, fy, cx, cy in pixels, pixel centres at
  integer coordinates): the unknown is w = -log(distance) along the optical axis, whose
  gradient is a function of the normal and the pixel's ray (the log-depth form of Quéau, Durou
  and Aujol, "Normal integration: a survey", 2018, also used by BiNI). The returned
  z = -exp(-w) is the camera-frame coordinate (negative: the camera looks down -z;
  distance = -z).

Both methods minimise, over the valid pixels only, a sum over one-sided differences between
neighbouring pixels: for pixel i and each of its (up to four) 4-neighbours j,
    w_ij * (s_i * (z_j - z_i) - t_i)^2      (a forward or a backward difference)
where t_i / s_i is the slope that the normal at i predicts: s = nz, t = -nx along columns and
+ny along rows (perspective: s = f times the normal's component toward the camera along the
ray). Scaling by s keeps the residuals bounded where the surface is steep; nz is clamped at
``grazing_nz`` (slopes are computed with nz raised to at least 0.1, so none exceeds 10, ~84
degrees: rim normals are unreliable).
Each image edge (i, j) then carries c = sum of w s^2 and b = sum of w s t over its two
one-sided terms, and the normal equations are a weighted graph Laplacian L z = rhs, solved by
conjugate gradients with a small smoothed-aggregation multigrid preconditioner
(``psctl.poisson``; scipy has no sparse Cholesky, and its sparse LU is slow and memory-hungry
at millions of unknowns).

* ``poisson``: all weights 1/2: weighted least squares of the gradient field (-nx/nz, -ny/nz),
  one linear solve.
* ``bilateral`` (in the spirit of BiNI, Cao et al., ECCV 2022): iteratively reweighted least
  squares where a pixel's forward/backward weights are sigmoid(k * (backward^2 - forward^2))
  and 1 minus it, from the current depth's one-sided differences (times s). A pixel next to a
  depth jump then trusts the side without the jump, and the jump survives instead of being
  smeared into the surface. k starts high and halves each round (see ``_bilateral``).

Gauge: depth is known up to a constant per connected region (and, in perspective, up to a
scale). One pixel per connected component is pinned with a single extra equation z_p = 0
(this adds no bias: the least-squares optimum is only defined up to that constant), then
each component is shifted to zero mean (orthographic: mean z = 0; perspective: mean w = 0,
i.e. the geometric-mean distance is 1).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from psctl.arrays import as_mask, check_vector_dtype, plain, unit_vectors
from psctl.errors import ProgressFactory, PsctlError, _short, check_bool, check_path, check_progress, like_default, not_a_file
from psctl.io.normals import ALBEDO_FORMATS
from psctl.poisson import laplacian, laplacian_pattern, solve_laplacian, solve_system

if TYPE_CHECKING:
    from psctl.io.mesh import Mesh

METHODS = ("poisson", "bilateral")

DEFAULT_CONFIG = {
    "grazing_nz": 0.1,        # steeper normals count as this steep (|slope| <= 10): rims are unreliable
    "bilateral_k": 2.0,       # sigmoid sharpness (BiNI's k)
    "bilateral_iters": 50,    # at most this many reweighting rounds ...
    "bilateral_tol": 1e-3,    # ... or until the energy changes by less than this (relative)
    "bilateral_k_start": 1e4, # sharpness of the first round, halved each round down to k (see _bilateral)
    "weight_floor": 1e-6,     # keeps every edge weight > 0 so the system stays definite
    "cut_fraction": 0.05,     # bilateral: an edge left with less than this of its weight is a tear
    "cg_rtol": 1e-7,          # relative residual of the linear solve
    "cg_maxiter": 500,
    "amg_max_coarse": 400,    # coarsest multigrid level is solved densely below this size
    "amg_rebuild_iters": 20,  # bilateral: rebuild the multigrid when CG needs more iterations
    "amg_sweeps": 2,          # Jacobi sweeps before and after the coarse correction
    "amg_strength": 0.05,     # couplings weaker than this (relative) are not aggregated over
}

# (low, high, low allowed): the values each setting can take and still mean what it says
CONFIG_RANGES = {
    "grazing_nz": (0.0, 1.0, False), "bilateral_k": (0.0, math.inf, False), "bilateral_iters": (1, math.inf, True),
    "bilateral_tol": (0.0, math.inf, True), "bilateral_k_start": (0.0, math.inf, False),
    "weight_floor": (0.0, 0.5, False), "cut_fraction": (0.0, 1.0, True), "cg_rtol": (0.0, 1.0, False),
    "cg_maxiter": (1, math.inf, True), "amg_max_coarse": (1, math.inf, True), "amg_rebuild_iters": (0, math.inf, True),
    "amg_sweeps": (1, math.inf, True), "amg_strength": (0.0, 1.0, True),
}

K_FILE = "K.txt"


def depth_config(config: dict | None) -> dict:
    """DEFAULT_CONFIG with ``config``'s overrides; an unknown key or a value that is not a finite
    number of the default's kind is a one-line error."""
    if config is None:
        return dict(DEFAULT_CONFIG)
    if not isinstance(config, dict):
        raise PsctlError(None, f"config must be a dict of DEFAULT_CONFIG's keys, not {type(config).__name__}")
    unknown = sorted(set(config) - set(DEFAULT_CONFIG))
    if unknown:
        raise PsctlError(None, f"unknown depth config keys: {', '.join(map(str, unknown))} "
                               f"(known: {', '.join(DEFAULT_CONFIG)})")
    cfg = {**DEFAULT_CONFIG, **{k: like_default(f"depth config {k!r}", v, DEFAULT_CONFIG[k]) for k, v in config.items()}}
    for key, (lo, hi, closed) in CONFIG_RANGES.items():  # in range too: cg_maxiter 0 gave a flat surface, no error
        v = cfg[key]
        if not (lo <= v if closed else lo < v) or v > hi:
            raise PsctlError(None, f"depth config {key!r} must be {'at least' if closed else 'above'} {lo:g}"
                                   + (f" and at most {hi:g}" if hi != math.inf else "") + f", not {v!r}")
    return cfg


# ----------------------------------------------------------------------------------------------
# Public API
# ----------------------------------------------------------------------------------------------

@dataclass
class DepthResult:
    """What ``integrate`` returns; ``depth`` is what ``integrate_normals`` returns."""

    depth: np.ndarray  # [H, W] float32 z (toward the camera), NaN where not integrated
    valid: np.ndarray  # [H, W] bool, pixels that were integrated
    n_mask: int  # pixels in the mask
    n_rejected_nan: int  # mask pixels with NaN/inf or zero-length normals
    n_rejected_facing: int  # mask pixels facing away (nz <= 0; perspective: away from the ray)
    n_components: int  # connected regions (each has its own unknown offset)
    iterations: int  # reweighting rounds (1 for poisson)
    cg_iterations: int  # conjugate-gradient iterations, all rounds together
    projection: str  # "orthographic" | "perspective"
    cut: np.ndarray | None = None  # [H, W, 2] bool, bilateral: edge to the right / to the pixel below cut by a jump
    converged: bool = True  # the (last) linear solve met cg_rtol within cg_maxiter

    @property
    def n_rejected(self) -> int:
        return self.n_rejected_nan + self.n_rejected_facing


def integrate_normals(normals: np.ndarray, mask: np.ndarray | None = None, method: str = "poisson",
                      K: np.ndarray | None = None, config: dict | None = None,
                      progress: ProgressFactory | None = None) -> np.ndarray:
    """Depth map from a normal map.

    Args:
        normals: [H, W, 3] normals, x right / y up / z toward the camera (need not be unit: any
            length; 0, or shorter than 1e-8 (than 1e-8 of the longest where that is below 1), is no normal).
        mask: [H, W] bool, the pixels to integrate (default: every pixel with a nonzero normal).
        method: "poisson" (least squares) or "bilateral" (keeps depth discontinuities).
        K: [3, 3] camera intrinsics for a perspective camera; None for orthographic.
        config: overrides of DEFAULT_CONFIG.
        progress: None or a factory (label, total) -> advance(k): poisson one step (its solve),
            bilateral one per round (advanced to its total when it converges early).
    Returns:
        [H, W] float32 z coordinate, larger = nearer the camera, NaN outside the mask and at
        rejected normals (NaN, or facing away). Orthographic: pixel units, each connected
        region shifted to mean 0. Perspective: z = -distance, each region scaled so that its
        geometric-mean distance is 1.

    Warns (PsctlWarning) where ``psctl depth`` would add a note that the depth may be wrong: a
    solve stopped at cg_maxiter before cg_rtol, most of the mask's normals facing away.
    """
    import warnings

    from psctl.errors import PsctlWarning, caller_level

    res = integrate(normals, mask, method, K, config, progress)
    level = caller_level()
    if not res.converged:
        warnings.warn("integrate_normals: the linear solve stopped at cg_maxiter before reaching cg_rtol: the depth "
                      "may be inaccurate (a larger config['cg_maxiter'] lets it finish)", PsctlWarning, stacklevel=level)
    directions = res.n_mask - res.n_rejected_nan
    if res.n_rejected_facing > directions / 2:
        rays = " along the rays of K (is K this image's?)" if K is not None else ""
        warnings.warn(f"integrate_normals: {res.n_rejected_facing} of the mask's {directions} normals face away from "
                      f"the camera{rays} and get no depth: not in psctl's convention (x right, y up, z towards the "
                      f"camera)?", PsctlWarning, stacklevel=level)
    return res.depth


def has_normal(normals: np.ndarray) -> np.ndarray:
    """[H, W] bool: the pixels of a normal map [H, W, 3] that hold a normal when there is no mask.
    Zero or NaN (as many tools write the background) is no normal; an infinite or otherwise unusable
    one stays in, to be counted as rejected. (A file's infinite components are NaN once read:
    ``read_normal_map``; so psctl depth without a mask reads them as background too.)"""
    return ~np.isnan(normals).any(axis=-1) & ~(normals == 0).all(axis=-1)


def integrate(normals: np.ndarray, mask: np.ndarray | None = None, method: str = "poisson",
              K: np.ndarray | None = None, config: dict | None = None,
              progress: ProgressFactory | None = None,
              check_facing: Callable[[int, int], None] | None = None) -> DepthResult:
    """``integrate_normals`` with the bookkeeping: rejected counts, components, iterations.
    ``check_facing(n_facing_away, n_directions)``, when given, is called with the mask's counts
    before the solve (and may raise: a map that is not normals is refused without the work)."""
    import scipy.sparse.csgraph as csgraph

    cfg = depth_config(config)
    method = str(method).lower()
    if method not in METHODS:
        raise PsctlError(None, f"unknown depth method {method!r}; choose from {', '.join(METHODS)}")
    normals = np.asarray(plain(normals))
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise PsctlError(None, f"normals must be [H, W, 3], got shape {normals.shape}")
    check_vector_dtype(normals, "normals must be unit vectors of real numbers")
    h, w = normals.shape[:2]
    if mask is None:
        # without a mask, a pixel with no normal (zero, or NaN as many tools write the background) is
        # background: a NaN background was counted as thousands of rejected "mask pixels" (a QA helper)
        mask = has_normal(normals)
        if not mask.any():
            raise PsctlError(None, "the normal map has no normal (every pixel is zero or NaN) and there is no mask")
    else:  # numbers read as estimate_normals reads them (above 0.5; 0/255 and labels work; NaN refused)
        if isinstance(mask, (str, bytes, os.PathLike)):
            as_mask(mask, (h, w))  # raises: a mask is an array here; as_mask says how to read a file
        m = np.asarray(plain(mask))
        if m.ndim < 2:
            raise PsctlError(None, f"mask must be [H, W] = [{h}, {w}] (the normal map's), got {list(m.shape)}")
        if m.shape[:2] != (h, w):
            raise PsctlError(None, f"normal map is {w}x{h} but the mask is {m.shape[1]}x{m.shape[0]}")
        mask = as_mask(m, (h, w))
    K = None if K is None else check_intrinsics(K)

    # --- per-pixel terms: gradient = t / s along columns (u) and rows (v) ------------------------
    # any length (need not be unit); "no normal" is 0, or shorter than 1e-8 (than 1e-8 of the longest
    # in the mask where that is below 1: a map scaled by 1e-9 as a whole is normals like any others)
    n, finite = unit_vectors(normals, 1e-8, within=mask)
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    if K is None:
        facing = nz  # the normal's component toward the (orthographic) camera
        su = sv = np.maximum(facing, cfg["grazing_nz"])
    else:
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        # -(n . ray) with the ray (u-cx)/fx, (v-cy)/fy, 1 in OpenCV axes (y down, z forward),
        # i.e. normal (nx, -ny, -nz): the component of the normal toward the camera along the ray.
        facing = -(nx * (u - cx) / fx - ny * (v - cy) / fy - nz)
        su = np.maximum(facing, cfg["grazing_nz"]) * fx
        sv = np.maximum(facing, cfg["grazing_nz"]) * fy
    good = mask & finite
    valid = good & (facing > 0)
    n_mask = int(mask.sum())
    n_nan = int((mask & ~finite).sum())
    n_facing = int((good & ~valid).sum())
    if check_facing is not None:
        check_facing(n_facing, n_facing + int(valid.sum()))
    if not valid.any():
        raise PsctlError(None, f"no usable normal inside the mask ({n_nan} NaN, infinite or zero, "
                               f"{n_facing} facing away from the camera)")
    tu, tv = -nx, ny  # s * dz/dcol = -nx and s * dz/drow = +ny, in both projections

    # --- graph of valid pixels: horizontal and vertical edges (i -> j = right / down) ------------
    npix = int(valid.sum())
    # 32-bit pixel indices where they fit (always, short of 2 billion pixels): the edge arrays and the
    # multigrid's coordinates are half the memory, the same numbers
    itype = np.int32 if npix < 2**31 - 1 else np.int64
    index = np.full((h, w), -1, itype)
    index[valid] = np.arange(npix, dtype=itype)
    hor = valid[:, :-1] & valid[:, 1:]
    ver = valid[:-1, :] & valid[1:, :]
    ei = np.concatenate([index[:, :-1][hor], index[:-1, :][ver]])
    ej = np.concatenate([index[:, 1:][hor], index[1:, :][ver]])
    n_hor = int(hor.sum())
    # one-sided terms: (s, t) of the edge's start pixel (its forward difference) and of its end
    # pixel (its backward difference)
    s_all = np.concatenate([su[valid], sv[valid]])  # [2P]: u-terms then v-terms, by pixel index
    t_all = np.concatenate([tu[valid], tv[valid]])
    # rows in s_all/t_all of the two one-sided terms (a vertical edge's are npix further on), 32-bit
    # where they fit: an int64 offset array made them and their sum 64-bit
    fwd = ei.astype(np.int32 if 2 * npix < 2**31 - 1 else np.int64)
    bwd = ej.astype(fwd.dtype)
    fwd[n_hor:] += npix
    bwd[n_hor:] += npix
    coords = tuple(np.asarray(a, itype) for a in np.nonzero(valid))  # (row, col) of each unknown, for the multigrid
    del index, su, sv, tu, tv, n, nx, ny, nz, facing, finite, good

    graph_n, labels = csgraph.connected_components(
        _adjacency(npix, ei, ej), directed=False) if len(ei) else (npix, np.arange(npix))
    pins = np.unique(labels, return_index=True)[1]

    progress = check_progress(progress)
    cut = None
    if method == "poisson":
        sf, sb = s_all[fwd], s_all[bwd]
        c = 0.5 * (sf * sf + sb * sb)
        b = 0.5 * (sf * t_all[fwd] + sb * t_all[bwd])
        del sf, sb, s_all, t_all, fwd, bwd
        advance = progress("integrating (poisson, one sparse solve)", 1)  # seconds at 12 MP: said, not silent
        if len(ei):  # the system, then the edges' arrays let go: 12 MP of normals peaked at 4.1 GB with them
            L, rhs = laplacian(npix, ei, ej, c, pins), np.bincount(ej, b, npix) - np.bincount(ei, b, npix)
            del c, b, ei, ej
            z, its, _, converged = solve_system(L, rhs, coords, None, cfg)
            del L, rhs
        else:
            z, its, _, converged = solve_laplacian(npix, ei, ej, c, b, pins, coords, None, cfg)
        advance(1)
        rounds, total_its = 1, its
    else:
        z, rounds, total_its, kept, converged = _bilateral(npix, ei, ej, fwd, bwd, s_all, t_all, pins, coords, cfg,
                                          progress(f"integrating (bilateral, <= {cfg['bilateral_iters']} rounds)",
                                                   cfg["bilateral_iters"]))
        # edges whose final weight is a small fraction of poisson's: the surface tears there
        cut = np.zeros((h, w, 2), bool)
        torn = kept < cfg["cut_fraction"]
        cut[:, :-1, 0][hor] = torn[:n_hor]
        cut[:-1, :, 1][ver] = torn[n_hor:]

    # --- gauge: zero mean per component, then back to z ------------------------------------------
    counts = np.bincount(labels, minlength=graph_n)
    z = z - (np.bincount(labels, z, graph_n) / counts)[labels]
    if K is not None:
        z = -np.exp(-z)
    depth = np.full((h, w), np.nan, np.float32)
    depth[valid] = z
    return DepthResult(depth, valid, n_mask, n_nan, n_facing, int(graph_n), rounds, total_its,
                       "orthographic" if K is None else "perspective", cut, bool(converged))


def check_intrinsics(K: np.ndarray, path: str | os.PathLike | None = None) -> np.ndarray:
    """Validate a 3 x 3 pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (pixels)."""
    if isinstance(K, (str, bytes, os.PathLike)) and path is None:  # run_depth reads files; arrays here
        raise PsctlError(None, f"K must be a 3 x 3 array here, not a file name ({_short(K)}): read the file with "
                               f"psctl.depth.read_intrinsics(PATH)")
    try:
        raw = np.asarray(plain(K))
        if raw.dtype.kind not in "iuf":  # complex would lose its imaginary part with a warning
            raise TypeError
        K = raw.astype(np.float64)
    except (TypeError, ValueError):
        raise PsctlError(path, "intrinsics must be a real 3 x 3 matrix of numbers") from None
    if K.shape != (3, 3):
        raise PsctlError(path, f"intrinsics must be a 3 x 3 matrix, got shape {K.shape}")
    if not np.isfinite(K).all():
        raise PsctlError(path, "intrinsics contain NaN or infinite values")
    if not (K[0, 0] >= 1 and K[1, 1] >= 1):  # under a pixel: a field of view of nearly 180 degrees, or a typo
        raise PsctlError(path, "intrinsics need focal lengths fx = K[0,0] and fy = K[1,1] of at least 1 pixel")
    if max(K[0, 0], K[1, 1]) > 1e9 or max(abs(K[0, 2]), abs(K[1, 2])) > 1e9:  # squares overflow in the solver
        raise PsctlError(path, "intrinsics above 1e9 pixels: a focal length that long is an orthographic "
                               "camera (leave out the intrinsics), and a principal point that far is a typo")
    if abs(K[1, 0]) > 1e-9 or not np.allclose(K[2], [0, 0, 1]):
        raise PsctlError(path, "intrinsics must have the form [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
    if abs(K[0, 1]) > 1e-6 * K[0, 0]:
        raise PsctlError(path, "skewed intrinsics (K[0,1] != 0) are not supported")
    return K


def find_intrinsics(folder: str | os.PathLike) -> Path | None:
    """The folder's K.txt, in any case as the other files of a capture (k.txt, K.TXT), or None."""
    from psctl.io.capture import _first_existing

    folder = Path(folder)
    return _first_existing(folder, list(folder.iterdir()), (K_FILE,), "intrinsics files")


def read_intrinsics(path: str | os.PathLike) -> np.ndarray:
    """K.txt: three rows of three numbers (whitespace or commas, '#' comments)."""
    from psctl.io.capture import read_matrix

    path = Path(check_path("path", path))  # an array here is a K, not a file: check_intrinsics
    if not path.is_file():
        raise PsctlError(path, not_a_file(path, "intrinsics file is missing"))
    K = read_matrix(path, (3,), "intrinsics")
    if K.shape != (3, 3):
        raise PsctlError(path, f"expected 3 rows of 3 numbers, found {K.shape[0]} rows")
    return check_intrinsics(K, path)


# ----------------------------------------------------------------------------------------------
# The pixel graph and bilateral's reweighting (the linear solve: psctl.poisson)
# ----------------------------------------------------------------------------------------------

def _adjacency(npix: int, ei: np.ndarray, ej: np.ndarray):
    import scipy.sparse as sp

    return sp.csr_matrix((np.ones(len(ei), np.int8), (ei, ej)), shape=(npix, npix))


def _bilateral(npix, ei, ej, fwd, bwd, s_all, t_all, pins, coords, cfg, advance):
    """IRLS with BiNI's one-sided weights. Returns (z, rounds, cg iterations, kept, converged),
    where kept[e] is edge e's final weight as a fraction of its poisson weight (~0 across a jump)
    and converged says whether the last round's linear solve met cg_rtol.

    Rows of s_all / t_all are (pixel, axis) pairs; ``fwd[e]`` is the row of edge e's forward
    term (its start pixel), ``bwd[e]`` the row of its backward term (its end pixel).
    """
    from scipy.special import expit

    k, floor = cfg["bilateral_k"], cfg["weight_floor"]
    # continuation: the sharpness starts at k_start and halves each round down to k. A sharp
    # sigmoid finds the jumps in the first, smeared (poisson-like) solutions within a few rounds;
    # ending at k lets smooth places that were cut by mistake knit back together.
    anneal = int(np.ceil(np.log2(max(cfg["bilateral_k_start"] / k, 1.0))))
    # Memory (12 MP of normals: 6.2 -> 3.4 GB peak; a dozen per-edge float64 arrays were alive
    # through each solve): the per-edge values (s, t and weight of each one-sided term) are gathered
    # from the per-row arrays when a step needs them, not kept; each round's matrix is filled into
    # a pattern built once (no COO arrays), c and b go once it is built, and a stale multigrid goes
    # before the next is built. Gathers copy the numbers and the products keep their operands (x w
    # is w x to the bit), so every result is the same to the bit.
    both = np.zeros(len(s_all), bool)
    both[fwd] = True
    has_b = np.zeros(len(s_all), bool)
    has_b[bwd] = True
    both &= has_b  # a pixel missing one side keeps 1/2 and 1/2: nothing to compare
    del has_b
    wt = np.full(len(s_all), 0.5)  # weight of each row's forward term; 1 - wt for the backward one
    pattern = laplacian_pattern(npix, ei, ej) if len(ei) else None  # the same graph every round
    z = amg = None
    energy = None
    rounds = total = 0
    for rounds in range(1, cfg["bilateral_iters"] + 1):
        w_fwd, sf = wt[fwd], s_all[fwd]
        c = w_fwd * sf * sf
        b = w_fwd * sf * t_all[fwd]
        del w_fwd, sf
        w_bwd, sb = 1.0 - wt[bwd], s_all[bwd]
        c += w_bwd * sb * sb
        b += w_bwd * sb * t_all[bwd]
        del w_bwd, sb
        if len(ei):
            rhs = np.bincount(ej, b, npix) - np.bincount(ei, b, npix)
            del b
            L = laplacian(npix, ei, ej, c, pins, pattern)
            del c
            z, its, amg, converged = solve_system(L, rhs, coords, z, cfg, amg, release_stale=True)
            del L, rhs
        else:
            z, its, amg, converged = solve_laplacian(npix, ei, ej, c, b, pins, coords, z, cfg, amg)
        total += its
        dz = z[ej] - z[ei]
        # one-sided depth differences, scaled by s: bounded on smooth surfaces, large at a jump
        dfe = s_all[fwd] * dz
        dbe = s_all[bwd] * dz
        del dz
        # energy: sum of w_fwd (sf dz - tf)^2 + w_bwd (sb dz - tb)^2, each term in place
        ef = dfe - t_all[fwd]
        ef **= 2
        ef *= wt[fwd]
        eb = dbe - t_all[bwd]
        eb **= 2
        eb *= 1.0 - wt[bwd]
        ef += eb
        del eb
        energy, old = float(np.sum(ef)), energy
        del ef
        df = np.zeros(len(s_all))
        df[fwd] = dfe
        db = np.zeros(len(s_all))
        db[bwd] = dbe
        del dfe, dbe
        k_round = max(k, cfg["bilateral_k_start"] * 0.5 ** (rounds - 1))
        wt = np.where(both, expit(k_round * (db * db - df * df)), 0.5).clip(floor, 1.0 - floor)
        del df, db
        advance(1)
        if rounds > anneal + 1 and abs(energy - old) <= cfg["bilateral_tol"] * max(old, 1e-300):
            advance(cfg["bilateral_iters"] - rounds)  # converged early: the bar ends full (helper-196)
            break
    del amg, pattern
    sf, sb = s_all[fwd], s_all[bwd]
    kept = (wt[fwd] * sf * sf + (1.0 - wt[bwd]) * sb * sb) / (0.5 * (sf * sf + sb * sb))
    return z, rounds, total, kept, converged


# ----------------------------------------------------------------------------------------------
# Surfaces: 3D points, mesh, shading
# ----------------------------------------------------------------------------------------------

LIGHT = np.array([-0.4, 0.5, 0.77]) / np.linalg.norm([-0.4, 0.5, 0.77])  # shading.png: upper left, front


def depth_to_points(depth: np.ndarray, K: np.ndarray | None = None) -> np.ndarray:
    """[H, W] z -> [H, W, 3] camera-frame points (x right, y up, z toward the camera).

    Orthographic: (col, -row, z), pixel units. Perspective: distance d = -z along the ray of the
    pixel (u, v), i.e. (d (u - cx) / fx, -d (v - cy) / fy, z). NaN depth gives NaN points.
    """
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    z = depth.astype(np.float32)
    if K is None:
        return np.stack([u, -v, z], axis=-1)
    d = -z
    return np.stack([d * (u - K[0, 2]) / K[0, 0], -d * (v - K[1, 2]) / K[1, 1], z], axis=-1)


def normals_from_points(points: np.ndarray) -> np.ndarray:
    """[H, W, 3] points (NaN = none) -> [H, W, 3] unit normals of the surface through them
    (central differences, one-sided at borders; NaN where a pixel has no neighbour along an axis)."""
    def derivative(axis: int) -> np.ndarray:
        p = np.moveaxis(points, axis, 0)
        nan = np.full_like(p[:1], np.nan)
        nxt = np.concatenate([p[1:], nan])
        prv = np.concatenate([nan, p[:-1]])
        d = (nxt - prv) / 2
        d = np.where(np.isnan(d), nxt - p, d)
        d = np.where(np.isnan(d), p - prv, d)
        return np.moveaxis(d, 0, axis)

    d_row, d_col = derivative(0), derivative(1)
    n = np.cross(d_row, d_col)  # rows go down, columns right: this order points n toward the camera
    with np.errstate(invalid="ignore", divide="ignore"):
        return n / np.linalg.norm(n, axis=-1, keepdims=True)


def shade(normals: np.ndarray, light: np.ndarray = LIGHT, ambient: float = 0.08) -> np.ndarray:
    """Lambertian shading of unit normals under a distant light: [H, W] in [0, 1], NaN stays NaN."""
    return ambient + (1.0 - ambient) * np.clip(normals @ light.astype(normals.dtype), 0.0, 1.0)


def depth_mesh(depth: np.ndarray, K: np.ndarray | None = None, normals: np.ndarray | None = None,
               colors: np.ndarray | None = None, cut: np.ndarray | None = None) -> "Mesh":
    """A triangle mesh with one vertex per pixel of finite depth.

    Each 2 x 2 block of pixels gives two triangles when all four have depth, one when three do,
    none when one of its edges is in ``cut`` ([H, W, 2] bool, DepthResult.cut: the surface tears
    there, so no wall is drawn across a depth jump). Triangles are counter-clockwise seen from
    the camera. ``normals`` [H, W, 3] and ``colors`` [H, W, 3] uint8 become per-vertex attributes.
    Returns psctl.io.mesh.Mesh.
    """
    from psctl.io.mesh import Mesh

    depth = np.asarray(plain(depth))
    if depth.ndim != 2 or depth.dtype.kind != "f":
        raise PsctlError(None, f"depth must be an [H, W] float map (NaN where there is none), "
                               f"got shape {list(depth.shape)} and dtype {depth.dtype}")
    h, w = depth.shape
    for name, a in (("normals", normals), ("colors", colors)):
        if a is not None and np.shape(a) != (h, w, 3):
            raise PsctlError(None, f"{name} must be [H, W, 3] = [{h}, {w}, 3], got {list(np.shape(a))}")
    if cut is not None and np.shape(cut) != (h, w, 2):
        raise PsctlError(None, f"cut must be [H, W, 2] = [{h}, {w}, 2], got {list(np.shape(cut))}")
    K = None if K is None else check_intrinsics(K)
    normals = None if normals is None else np.asarray(plain(normals))
    colors = None if colors is None else np.asarray(plain(colors))
    cut = None if cut is None else np.asarray(plain(cut), bool)
    valid = np.isfinite(depth)
    nv = int(valid.sum())  # (the faces are int32 in the end: 32-bit indices from the start where they fit)
    itype = np.int32 if nv < 2**31 - 1 else np.int64
    index = np.full((h + 1, w + 1), -1, itype)  # padded so blocks at the border see "no pixel"
    index[:h, :w][valid] = np.arange(nv, dtype=itype)
    a, b = index[:-1, :-1], index[:-1, 1:]  # top-left, top-right of each block
    c, d = index[1:, :-1], index[1:, 1:]  # bottom-left, bottom-right
    a, b, c, d = (x.ravel() for x in (a, b, c, d))
    ok = np.stack([a, b, c, d]) >= 0
    if cut is not None:  # a block with a torn edge (top, bottom, left or right) gets no triangle
        right, down = cut[..., 0], cut[..., 1]
        torn = right[:-1, :-1] | right[1:, :-1] | down[:-1, :-1] | down[:-1, 1:]
        torn = np.pad(torn, ((0, 1), (0, 1))).ravel()
        ok &= ~torn
    # (x = col, y = -row) seen from +z: a c b and b c d are counter-clockwise
    full = ok.all(axis=0)
    tris = [np.stack([a, c, b], 1)[full], np.stack([b, c, d], 1)[full]]
    three = ok.sum(axis=0) == 3
    for missing, tri in ((0, (b, c, d)), (1, (a, c, d)), (2, (a, d, b)), (3, (a, c, b))):
        sel = three & ~ok[missing]
        tris.append(np.stack(tri, 1)[sel])
    faces = np.concatenate(tris).astype(np.int32, copy=False)
    vertices = depth_to_points(depth, K)[valid]
    return Mesh(vertices=vertices, faces=faces,
                normals=None if normals is None else normals[valid].astype(np.float32),
                colors=None if colors is None else colors[valid])


def display_colors(mean_image: np.ndarray, valid: np.ndarray, scale: float | None = None) -> np.ndarray:
    """Linear mean image [H, W, 3] -> uint8 display colours (``scale`` to white, default the
    99.5th percentile of the brightest channel over ``valid``; gamma 2.2)."""
    if scale is None:
        scale = float(np.percentile(mean_image[valid].max(axis=-1), 99.5)) if valid.any() else 1.0
    rgb = np.clip(mean_image / max(scale, 1e-12), 0.0, 1.0) ** (1 / 2.2)
    return np.round(rgb * 255).astype(np.uint8)


# ----------------------------------------------------------------------------------------------
# Capture folders: psctl depth
# ----------------------------------------------------------------------------------------------

# what `psctl normals` writes into PATH/psctl/ (-f exr, npy, png16, png8), the most precise first
NORMAL_FILES = ("normal.exr", "normal.npy", "normal.png", "normal_8bit.png")
OUTPUTS = ("depth.exr", "depth.png", "mesh.ply", "shading.png", "depth_report.json")


def encoding_notes(nmap: np.ndarray, mask: np.ndarray, source: Path) -> list[str]:
    """A float map (.exr, .npy) holds the vectors themselves; one that holds a PNG's (n + 1) / 2
    instead has no negative component and lengths off 1 (0.5 to 1.5 for unit normals): it would
    integrate to a wrong surface without a word, hence a note."""
    if source.suffix.lower() not in (".exr", ".npy"):
        return []
    step = max(1, int(np.sqrt(mask.size / 200_000)))  # a sample of the map: seconds saved on 12 MP
    sub = nmap[::step, ::step]
    n = sub[mask[::step, ::step] & np.isfinite(sub).all(axis=-1)]
    n = n[(n != 0).any(axis=-1)]
    if len(n) < 16 or (n < 0).any():
        return []
    length = float(np.median(np.linalg.norm(n.astype(np.float64), axis=-1)))  # float32 squares overflow past 1e19
    if abs(length - 1) < 0.05:
        return []
    return [f"normals: no component in {source.name} is negative and their median length is {length:.2f}, not 1: "
            f"(n + 1) / 2 as in a PNG? A float map holds the vectors themselves (docs/formats.md)"]


def mirror_map_notes(nmap: np.ndarray, mask: np.ndarray, source: Path) -> list[str]:
    """A note when a given map's mirror image is far more integrable than the map (its y axis down,
    as image rows, in some tools' convention): it would integrate to a wrong surface without a word
    (a review: the bumpy sphere's map with y flipped came out saddle-like). psctl normals notes its
    own maps when it writes them (``psctl.api.mirror_notes``). On the DiLiGenT dev
    split's ground truth the ratio (``psctl.refine.mirror_ratio``) is 9.5-877,000 as given and
    0-0.105 with y flipped. A map that psctl normals wrote (its report.json beside says so)
    follows its light file: the note then names that file (a review: it said to flip the map)."""
    from psctl.refine import MIRROR_NOTE, mirror_ratio

    step = max(1, int(np.sqrt(mask.size / 1_000_000)))  # a sample of the map: 3.4 s -> 0.5 s on a 9 MP sphere
    sub = nmap[::step, ::step]
    r = mirror_ratio(np.where(np.isfinite(sub), sub, 0), mask[::step, ::step])
    if r is None or r >= MIRROR_NOTE:
        return []
    if written_by_normals(source):
        return [f"normals: {source.name} is {1 / r:.1f} times less integrable than its mirror image: psctl normals "
                f"estimated it from the capture's light_directions.txt; is an axis of that file flipped (y down, as "
                f"image rows)? Fix the file and run psctl normals again"]
    return [f"normals: {source.name} is {1 / r:.1f} times less integrable than its mirror image: is an axis flipped "
            f"(y down, as image rows, in some tools)? psctl reads x right, y up, z toward the camera "
            f"(docs/formats.md); flip it first"]


def pick_normal_file(folder: Path) -> tuple[Path | None, str | None]:
    """The normal map psctl depth reads in a psctl normals output ``folder``: the first of
    NORMAL_FILES there that the run whose report.json lies beside it wrote (``written_by_normals``;
    a note names that run's maps before it in the order that changed since), else the first there, with a note when report.json names other files (a map an earlier run
    or the user left: it was read without a word, an interruption audit); (None, None) where none is."""
    there = [folder / n for n in NORMAL_FILES if (folder / n).is_file()]
    if not there:
        return None, None
    written = _written(folder / "report.json")  # read once, not once per map
    for k, p in enumerate(there):
        if _as_written(p, written):
            passed = [q.name for q in there[:k] if q.name in written]  # that run's, changed since (helper-170)
            them = "it was" if len(passed) == 1 else "they were"
            return p, (f"normals: {p.name} read; {', '.join(passed)}, which the same psctl normals run wrote "
                       f"first, changed since, so {them} passed over (name a map with --normals)" if passed else None)
    listed = [n for n in NORMAL_FILES if n in written]
    if not listed:
        return there[0], None
    return there[0], (f"normals: {there[0].name} in {folder} is not a map the psctl normals run whose report.json is "
                      f"there wrote (it wrote {', '.join(listed)}, since changed or removed): read all the same; "
                      f"name the map with --normals")


def _written(report: Path) -> dict:
    """A psctl normals report's "written" ({file: [bytes, mtime ns]}), {} where it has none."""
    from psctl.io.atomic import read_report

    written = (read_report(report) or {}).get("written")
    return written if isinstance(written, dict) else {}


def written_by_normals(path: Path) -> bool:
    """Whether ``path`` is as the psctl normals run whose report.json lies beside it wrote it (its
    size and modification time as the report's "written" recorded them)."""
    return _as_written(path, _written(path.parent / "report.json"))


def _normals_capture(path: Path) -> str | None:
    """The capture folder (real path) the psctl normals run whose report.json lies beside ``path``
    estimated it from, where that report records ``path`` as written (else None)."""
    from psctl.io.atomic import read_report

    report = read_report(path.parent / "report.json") or {}
    made_from, written = report.get("path"), report.get("written")
    if not isinstance(made_from, str) or "\0" in made_from or not _as_written(path, written if isinstance(written, dict) else {}):
        return None  # (a NUL byte: realpath's ValueError, a review's traceback)
    return os.path.realpath(made_from)


def _as_written(path: Path, written: dict) -> bool:
    """Whether ``path``'s size and modification time are as ``written`` (a report's) records them."""
    try:
        st = path.stat()
    except OSError:
        return False
    rec = written.get(path.name)
    if not (isinstance(rec, list) and len(rec) == 2 and all(isinstance(v, int) and not isinstance(v, bool) for v in rec)):
        return False
    # the time in ns (about 1.8e18) is beyond the integers every JSON reader keeps exactly (2^53):
    # a report passed through jq 1.6 or JavaScript holds it rounded to a double, 256 ns apart
    return rec[0] == st.st_size and (rec[1] == st.st_mtime_ns or float(rec[1]) == float(st.st_mtime_ns))


def run_depth(path: str | os.PathLike, normals: str | os.PathLike | None = None, method: str = "poisson",
              out: str | os.PathLike | None = None, K: str | os.PathLike | np.ndarray | None = None,
              write: bool = True, binary_ply: bool = True, config: dict | None = None,
              progress: ProgressFactory | None = None, encoding: str = "auto") -> dict:
    """Integrate a capture folder's normal map into depth.exr, depth.png, mesh.ply, shading.png
    and depth_report.json (in ``out``, default PATH/psctl; all files or none).

    Normals: the ``normals`` file (psctl 16-bit PNG, EXR or .npy), else the first of NORMAL_FILES
    that a psctl normals run of this capture wrote in ``out``, else the first of them in
    PATH/psctl (normal.exr, normal.npy, normal.png, normal_8bit.png) that the psctl normals run
    there wrote (``pick_normal_file``), else the first of them there, else estimated from the images (``psctl normals --method auto``). Mask: the
    folder's mask, else every pixel with a nonzero normal. Intrinsics: ``K`` (a file or a 3 x 3
    array), else PATH/K.txt, else orthographic. Returns the report (what ``--json`` prints).
    The images (for estimated normals and the mesh's vertex colours) are read as
    ``psctl.io.capture.open_capture`` says for ``encoding``, ambient image subtracted.
    ``write`` False: nothing written (the report alone); ``binary_ply`` False: mesh.ply in ASCII
    (larger; for readers without binary PLY); ``config``: overrides of DEFAULT_CONFIG (the
    solver's settings, ``depth_config``); ``progress``: None or a factory (label, total) -> advance(k).
    """
    from psctl.io.atomic import check_output_dir, output_folder
    from psctl.arrays import bounding_box
    from psctl.io.capture import capture_notes, check_not_capture, iter_images, open_capture

    t0 = time.perf_counter()
    for name, value in (("path", path), ("normals", normals), ("out", out)):
        check_path(name, value, optional=name != "path")
    progress = check_progress(progress)
    method = str(method).lower()
    if method not in METHODS:
        raise PsctlError(None, f"unknown --method {method!r}; choose from {', '.join(METHODS)}")
    write, binary_ply = check_bool("write", write), check_bool("binary_ply", binary_ply)
    cfg = depth_config(config)  # a bad setting stops before any image is read
    cap = open_capture(path, encoding)
    out_dir = output_folder(out, cap.path)
    notes: list[str] = capture_notes(cap)  # the images are read for the vertex colours at least
    if write:
        from psctl.io.atomic import replaced_notes

        check_not_capture(out_dir, cap, OUTPUTS)  # inputs are never touched
        from psctl.io.atomic import check_inputs_kept

        check_inputs_kept(out_dir, OUTPUTS, (("--normals", normals), ("--K", K)))
        check_output_dir(out_dir)
        notes += replaced_notes(out_dir, OUTPUTS, "depth")  # a same-named file of the user's

    # --- intrinsics ----------------------------------------------------------------------------
    k_source = None
    if K is None:
        K = find_intrinsics(cap.path)
    if isinstance(K, (str, os.PathLike)):
        k_source = os.path.abspath(K)  # report paths are absolute (docs/formats.md)
        K = read_intrinsics(K)
    elif K is not None:
        K, k_source = check_intrinsics(K), "array"

    # --- normals and mask ----------------------------------------------------------------------
    mask = _capture_mask(cap)
    got: dict = {}  # the arrays of psctl normals' run here, when the normals are estimated
    estimated: dict | None = None  # and its report
    inputs: list = []  # (file, input_stamp): read here, to be unchanged when the outputs are written
    if normals is None:
        # psctl normals -o N then psctl depth -o N: the map that run wrote there for this capture
        # comes first (a helper found it passed over for PATH/psctl's, or estimated again)
        default = cap.path / "psctl"
        mine = out is not None and os.path.realpath(out_dir) != os.path.realpath(default)
        picked, picked_note = pick_normal_file(out_dir) if mine else (None, None)
        if picked is not None:
            made_from = _normals_capture(picked)
            if made_from != os.path.realpath(cap.path):  # passed over, with a word (a review: silently)
                notes.append(f"normals: {picked} passed over: " + (
                    "no report.json there records it as written (changed, or copied without its files' times?)"
                    if made_from is None else f"its report.json says psctl normals estimated it from {made_from}") +
                    "; give it with --normals to integrate it")
                picked = None
        if picked is None:
            picked, picked_note = pick_normal_file(default)
        normals = picked
        notes += [picked_note] if picked_note else []
    if normals is not None:
        from psctl.io.normals import read_normal_map

        from psctl.io.atomic import input_stamp

        source = Path(normals)
        # checked again as the outputs are moved into place: a psctl normals into this folder
        # meanwhile would leave this run's depth beside other normals
        inputs = [(source, input_stamp(source))]
        nmap = read_normal_map(source)
        if nmap.shape[:2] != (cap.height, cap.width):
            raise PsctlError(source, f"normal map is {nmap.shape[1]}x{nmap.shape[0]} but the capture's images "
                                     f"{'and mask ' if cap.mask_path else ''}are {cap.width}x{cap.height}")
        if mask is None:
            mask = has_normal(nmap)  # as integrate's: a NaN background too (a review: 5692 "rejected" pixels)
            if not mask.any():
                raise PsctlError(source, "normal map has no normal (every pixel is zero or NaN) and the folder has "
                                         "no mask")
            found = found_beside(source, mask.shape)
            if found is not None and (found & mask).any():  # the object, not the ring of normals around it
                mask &= found
                notes.append(f"mask: none (no mask.png): the surface is the object found ({int(mask.sum())} "
                             f"pixels, mask_found.png beside {source.name}), without the pixels around it its "
                             f"normals also cover")
        normals_source = os.path.abspath(source)
        other = _normals_capture(source)
        if other is not None and other != os.path.realpath(cap.path):  # the same size, another object?
            notes.append(f"normals: the report.json beside {source.name} says psctl normals estimated it from "
                         f"{other}, not from {os.path.abspath(cap.path)} (another capture's map? or this capture was "
                         f"moved or copied since); its mask_found.png and albedo, where used, are that run's too")
        notes += encoding_notes(nmap, mask, source) + mirror_map_notes(nmap, mask, source)
    else:  # exactly what psctl normals --method auto gives (its crop, its notes), nothing written
        from psctl.api import resolve_method, run_normals

        from psctl.albedo import fits_in_memory

        try:
            # and its albedo for the mesh's colours, where the method has lights (not ups-fcn) and
            # the albedo's arrays fit in memory: a larger object's albedo costs more than its mean
            # image (a 1200 x 1200 sphere's depth: 8.0-8.5 -> 11.2 s)
            chosen = resolve_method("auto", cap.calibrated, lights_file=cap.path / "light_directions.txt")[0]
            pixels = cap.height * cap.width if mask is None else int(mask.sum())
            estimated = run_normals(cap.path, method="auto", write=False, progress=progress, encoding=encoding,
                                    arrays=got, albedo=chosen != "ups-fcn" and fits_in_memory(pixels, cap.n_images))
        except PsctlError as e:
            raise PsctlError(e.path or cap.path, f"no normal map to integrate and cannot estimate one: "
                                                 f"{e.message} (give one with --normals)") from None
        nmap = got["normals"]
        if mask is None and got.get("found") is not None:  # the object, not the ring of normals around it
            mask = got["found"]
            notes.append(f"mask: none (no mask.png): the surface is the object found ({int(mask.sum())} pixels, "
                         f"psctl normals' mask_found.png), without the pixels around it its normals also cover")
        elif mask is None:
            mask = got["mask"]
        # its albedo notes speak of albedo maps, which depth does not write (black vertices here, below)
        notes += [n for n in estimated["notes"] if n not in notes and not n.startswith("albedo:")]
        source = cap.path
        normals_source = f"estimated (psctl normals --method auto: {estimated['method']})"
        notes.append(f"no normal map given or found in PATH/psctl: normals estimated from the images by "
                     f"{estimated['method']} (run `psctl normals` first to choose the method and keep them)")

    # --- integrate -----------------------------------------------------------------------------
    def refuse_facing_away(n_facing: int, numbers: int) -> None:
        """A given map most of whose directions face away (a visible surface faces the camera):
        refused before the solve (numbers: the mask's normals that are directions)."""
        if normals is None or n_facing <= numbers / 2:
            return
        rays = (f" along the rays of the intrinsics {Path(k_source).name if k_source != 'array' else 'given'} (are "
                f"they this image's?)") if K is not None else ""
        raise PsctlError(source, f"{n_facing} of the {numbers} normals face away from the camera{rays}: "
                                 f"not a normal map in psctl's convention (x right, y up, z towards the camera; "
                                 f"docs/formats.md), or not a normal map")

    try:
        res = integrate(nmap, mask, method, K, config, progress, check_facing=refuse_facing_away)
    except PsctlError as e:
        raise PsctlError(e.path or source, e.message) from None
    if res.n_rejected:
        notes.append(f"{res.n_rejected} mask pixels have no usable normal ({res.n_rejected_nan} NaN, infinite or zero, "
                     f"{res.n_rejected_facing} facing away from the camera): they get no depth")
    if res.n_components > 1:
        notes.append(f"{res.n_components} separate regions: each has its own unknown depth offset")
    if not res.converged:
        notes.append(f"the linear solve stopped at cg_maxiter ({cfg['cg_maxiter']}) before reaching "
                     f"cg_rtol ({cfg['cg_rtol']:g}): the depth may be inaccurate")
    t_integrate = time.perf_counter() - t0

    # --- surface products ----------------------------------------------------------------------
    valid = res.valid
    # the mesh's colours: the albedo the same psctl normals run wrote beside its normal map (the
    # surface's own colour), else the images' mean (shading and all)
    albedo = None if normals is None else albedo_beside(Path(normals), (cap.height, cap.width), notes)
    # an albedo's white is albedo.png's (albedo_png_scale), whichever file it came from: a PNG's
    # values are already over that white and clipped there, and taking the 99.5th percentile of
    # the clipped values made its colours up to 19 steps of 255 brighter than the EXR's (a QA helper)
    from psctl.albedo import albedo_png_scale

    white = None
    if albedo is not None:
        colors_source, mean_image = os.path.abspath(albedo[0]), albedo[1]
        white = 1.0 if albedo[0].suffix.lower() == ".png" else albedo_png_scale(mean_image, valid)
    elif normals is None and got.get("albedo") is not None:  # estimated here with the normals
        colors_source, mean_image = "albedo (estimated with the normals)", got["albedo"]
        white = albedo_png_scale(mean_image, valid)
        black = int((valid & (mean_image == 0).all(axis=-1)).sum())
        if black:
            notes.append(f"colours: {black} vertices have no albedo (dark in every image, or no light in front "
                         f"of their normal): black")
    else:
        colors_source = "mean image"
        box = bounding_box(valid)
        mean_image = np.zeros((cap.height, cap.width, 3), np.float32)
        advance = progress(f"{cap.name}: mean image for vertex colours", cap.n_images)
        for img in iter_images(cap, box):
            mean_image[box] += img / cap.n_images
            advance(1)
    colors = display_colors(mean_image, valid, white)
    # normals of any length, as integrate took them (1e30 or 1e-13 times unit: unit in the mesh)
    unit = np.where(valid[..., None], unit_vectors(nmap, 0.0)[0], 0.0).astype(np.float32)
    mesh = depth_mesh(res.depth, K, unit, colors, res.cut)
    recomputed = normals_from_points(depth_to_points(res.depth, K))
    shading = np.nan_to_num(shade(recomputed), nan=0.0)

    z = res.depth[valid]
    report = {
        "object": cap.name,
        "path": os.path.abspath(cap.path),
        "method": method,
        "projection": res.projection,
        "intrinsics": k_source,
        "normals": normals_source,
        "height": cap.height,
        "width": cap.width,
        "n_pixels": int(valid.sum()),
        "n_mask_pixels": res.n_mask,
        "n_rejected": res.n_rejected,
        "n_rejected_nan": res.n_rejected_nan,
        "n_rejected_facing_away": res.n_rejected_facing,
        "n_regions": res.n_components,
        "iterations": res.iterations,
        "n_torn_edges": 0 if res.cut is None else int(res.cut.sum()),
        "cg_iterations": res.cg_iterations,
        # unrounded (depth.exr's float32 values): depth.png maps back through them, and in a perspective
        # run z is about 1 with a relief of 1e-4, where 6 decimals were 77 of the PNG's grey levels
        "z_min": float(z.min()),
        "z_max": float(z.max()),
        "z_units": "pixels" if K is None else "geometric-mean distance of each region",
        "colors": colors_source,
        "n_vertices": int(len(mesh.vertices)),
        "n_faces": int(len(mesh.faces)),
        "seconds_integrate": round(t_integrate, 3),
        "seconds": round(time.perf_counter() - t0, 3),
        "outputs": {},
        "notes": notes,
    }
    from psctl.api import provenance

    # what made the result: psctl normals' own where it estimated the normals (versions, device, weights), else
    # the versions alone (a normal map's own report.json says what made it)
    report["provenance"] = estimated["provenance"] if estimated is not None else provenance({})
    if write:
        _write_outputs(out_dir, res.depth, valid, mesh, shading, report, binary_ply, t0, inputs)
    return report


# psctl normals --albedo's files, the most precise first
ALBEDO_FILES = tuple(ALBEDO_FORMATS[f] for f in ("exr", "npy", "png16", "png8"))


def found_beside(normals: Path, shape: tuple[int, int]) -> np.ndarray | None:
    """[H, W] bool, the object found without a mask (``mask_found.png``) that the psctl normals run
    which wrote the normal map ``normals`` wrote beside it: both files as that run's report.json
    recorded them ("written"), the mask of ``shape``; else None (no such run, a file replaced since)."""
    from psctl.io.images import read_image
    from psctl.masks import FOUND_FILE

    written = _written(normals.parent / "report.json")  # one read for both files
    if not (_as_written(normals, written) and _as_written(normals.parent / FOUND_FILE, written)):
        return None
    try:
        found = read_image(normals.parent / FOUND_FILE)[0]
    except (OSError, ValueError, RecursionError, AttributeError, PsctlError):
        return None
    return found[..., 0] > 0.5 if found.shape[:2] == tuple(shape) else None


def albedo_beside(normals: Path, shape: tuple[int, int], notes: list[str] | None = None
                  ) -> tuple[Path, np.ndarray] | None:
    """The albedo map that the psctl normals run which wrote the normal map ``normals`` wrote
    beside it (``--albedo``): the first of ALBEDO_FILES whose size and modification time, and the
    normal map's, are as that run's report.json recorded them ("written": a file replaced since
    is not that run's), readable as a finite [H, W, 3] map of ``shape``; a PNG is sRGB-decoded
    (linear up to its scale, which ``display_colors`` sets anyway). Returns (path, [H, W, 3]
    float32), or None; each of that run's albedo files passed over gets a note in ``notes``."""
    import json

    why = None
    try:
        from psctl.io.atomic import read_small_text

        report = json.loads(read_small_text(normals.parent / "report.json", 64 << 20))
    except FileNotFoundError:
        report, why = None, "there is no report.json beside it"
    except (OSError, ValueError, RecursionError):  # unreadable, not text, not JSON
        report, why = None, "its report.json cannot be read as JSON"
    written = report.get("written") if isinstance(report, dict) else None
    if not isinstance(written, dict):
        if notes is not None and any((normals.parent / n).is_file() for n in ALBEDO_FILES):
            why = why or ("its report.json does not record the files as written (an older psctl wrote it?)"
                          if isinstance(report, dict) else "its report.json is not a psctl report")
            notes.append(f"colours: the albedo beside {normals.name} not used: {why}; run psctl normals --albedo "
                         f"again")
        return None
    if normals.name not in written:
        return None
    if not _as_written(normals, written):
        if notes is not None and any(n in written for n in ALBEDO_FILES):
            notes.append(f"colours: {normals.name} is not as the psctl normals run that wrote it left it, by its "
                         f"report.json (replaced, or copied without its files' times); its albedo not used, the "
                         f"mesh's colours are the images' mean")
        return None
    for name in ALBEDO_FILES:
        path = normals.parent / name
        if name not in written or not path.is_file():
            continue
        why = None
        try:
            if not _as_written(path, written):
                why = ("not as the psctl normals run that wrote it left it, by its report.json (replaced, or copied "
                       "without its files' times); taken as another run's")
            elif name.endswith(".npy"):
                arr = np.load(path, allow_pickle=False)
                if arr.dtype.kind != "f":
                    why = f"holds {arr.dtype} values, not floats"
            else:
                from psctl.io.images import read_image, srgb_to_linear, to_rgb

                arr = to_rgb(read_image(path, allow_nonfinite=True)[0])
                if path.suffix == ".png":
                    arr = srgb_to_linear(arr)
        except PsctlError as e:
            why = e.message
        except (OSError, ValueError) as e:
            why = "not a NumPy array file" if "pickle" in str(e) else " ".join(str(e).split()) or type(e).__name__
        if why is None and arr.shape != (*shape, 3):
            why = f"shape {arr.shape}, not {(*shape, 3)}"
        if why is None and not np.isfinite(arr).all():
            why = "NaN or infinite values"
        if why is None:
            return path, np.asarray(arr, np.float32)
        if notes is not None:
            notes.append(f"colours: {path} not used ({why})")
    if notes is not None and any(n.startswith("colours:") for n in notes):
        notes.append("colours: the mesh's colours are the images' mean")
    return None


def _capture_mask(cap) -> np.ndarray | None:
    """The folder's mask (an all-background mask is an error), or None without a mask file."""
    from psctl.io.capture import load_mask

    return load_mask(cap) if cap.mask_path is not None else None


def depth_preview(depth: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """[H, W] z -> [H, W, 2] grey + alpha in [0, 1]: nearest point white, farthest black (a flat
    surface, every point the nearest: white), transparent where there is no depth."""
    z = depth[valid]
    lo, hi = float(z.min()), float(z.max())
    if hi > lo:
        grey = np.where(valid, (np.nan_to_num(depth, nan=lo) - lo) / (hi - lo), 0.0)
    else:
        grey = valid.astype(np.float64)
    return np.stack([grey, valid.astype(np.float32)], axis=-1).astype(np.float32)


def _write_outputs(out_dir: Path, depth: np.ndarray, valid: np.ndarray, mesh, shading: np.ndarray,
                   report: dict, binary_ply: bool, t0: float, inputs: list) -> None:
    from psctl.io.atomic import staged_outputs, write_outputs_list
    from psctl.io.images import linear_to_srgb, write_image
    from psctl.io.mesh import write_ply
    from psctl.io.report import write_json

    report["outputs"] = {name.replace(".", "_"): os.path.abspath(out_dir / name) for name in OUTPUTS}
    with staged_outputs(out_dir, inputs=inputs) as stage:
        write_outputs_list(stage, OUTPUTS, "depth")
        write_image(stage / "depth.exr", depth.astype(np.float32), "float", kind="data")
        write_image(stage / "depth.png", depth_preview(depth, valid), "uint16", kind="data")
        write_ply(stage / "mesh.ply", mesh, binary=binary_ply,
                  comment=f"psctl depth --method {report['method']} ({report['projection']}) of {report['object']}")
        # shade() is radiance: encoded with the sRGB curve so the file's sRGB tag is true
        write_image(stage / "shading.png", np.stack([linear_to_srgb(shading), valid.astype(np.float32)], -1), "uint8")
        report["seconds"] = round(time.perf_counter() - t0, 3)  # depth_report.json and the return agree
        write_json(stage / "depth_report.json", report)


def render_depth(r: dict, quiet: bool = False) -> None:
    """Print a ``run_depth`` report for people (Rich, stdout)."""
    from psctl.errors import console
    from psctl.io.summary import escape, print_notes, print_written

    con = console()
    print_notes(con, r.get("notes", []))
    con.print(f"[bold]{escape(r['object'])}[/]: {r['method']} ({r['projection']}), {r['n_pixels']} pixels, "
              f"{r['n_vertices']} vertices, {r['n_faces']} triangles, {r['seconds']:.2f} s", highlight=False,
              soft_wrap=True)
    if not quiet:
        print_written(con, r["outputs"])
