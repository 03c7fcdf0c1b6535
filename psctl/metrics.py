"""Error measures: angular error of normals, summary statistics, light errors."""

from __future__ import annotations

import numpy as np

from psctl.errors import PsctlError

THRESHOLDS = (11.25, 22.5, 30.0)


def angular_error(normals: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel angle in degrees between two normal maps [..., 3] of the same shape.

    Returns a float array of the pixels selected by ``mask`` (the maps' shape without the last
    axis, [H, W] for normal maps; bool, or numbers as ``psctl.arrays.as_mask`` reads them; all
    pixels when None); for two [3] vectors a 0-d array. Inputs need not be exactly unit
    length; both are normalised. Other shapes or dtypes (unsigned integers: an encoded map's
    pixels) are a ``PsctlError``.
    """
    from psctl.arrays import as_mask, check_vector_dtype, plain

    arrays = []
    for name, a in (("normals", normals), ("gt", gt)):
        a = np.asarray(plain(a))
        check_vector_dtype(a, f"angular_error: {name} must be real numbers")  # text, objects, complex, pixels
        arrays.append(a)
    normals, gt = arrays
    if normals.shape != gt.shape or normals.ndim < 1 or normals.shape[-1] != 3:
        # no broadcasting: one normal against a map is a mistake more often than a wish
        what = "be [..., 3] (x, y, z)" if normals.shape == gt.shape else "have the same shape [..., 3]"
        raise PsctlError(None, f"angular_error: normals {list(normals.shape)} and gt {list(gt.shape)} must {what}")
    if mask is not None:  # [...] of the maps' shape: numbers read as in mask files, not as indices
        m = np.asarray(plain(mask))
        if m.shape == (*normals.shape[:-1], 1):  # [H, W, 1], as the other array functions take it
            m = m[..., 0]
        if m.shape != normals.shape[:-1]:
            raise PsctlError(None, f"angular_error: mask must be {list(normals.shape[:-1])}, got {list(m.shape)}")
        try:
            m = as_mask(m.reshape(1, -1), (1, m.size), allow_empty=True).reshape(m.shape)
        except PsctlError as e:  # said as this function's, as its other errors are
            raise PsctlError(None, f"angular_error: {e.message}") from None
        normals, gt = normals[m], gt[m]
    # float64: in float32, arccos near 1 cannot resolve angles below ~0.03 degrees
    normals, gt = normals.astype(np.float64), gt.astype(np.float64)

    def unit(v: np.ndarray) -> np.ndarray:  # any non-zero length, however small; a zero vector stays 0 (90 degrees)
        top = np.abs(v).max(axis=-1, keepdims=True)  # divided first: squares of 1e-200 or 1e200 leave float64
        v = np.divide(v, top, out=np.zeros_like(v), where=top > 0)
        n = np.linalg.norm(v, axis=-1, keepdims=True)
        return np.divide(v, n, out=np.zeros_like(v), where=n > 0)

    with np.errstate(invalid="ignore"):
        a, b = unit(normals), unit(gt)
    cos = np.clip((a * b).sum(-1), -1.0, 1.0)
    deg = np.asarray(np.degrees(np.arccos(cos)))  # an array also for one pair of [3] vectors
    deg[~(np.isfinite(normals).all(-1) & np.isfinite(gt).all(-1))] = np.nan  # NaN in, NaN out
    return deg


def summarize(errors: np.ndarray) -> dict:
    """MAE, median and the fraction of pixels under 11.25 / 22.5 / 30 degrees."""
    errors = np.asarray(errors, dtype=np.float64)
    if not np.isfinite(errors).all():  # mae NaN, yet 'within' counted a NaN as not within (helper-196)
        raise PsctlError(None, f"summarize: {int((~np.isfinite(errors)).sum())} of {errors.size} errors are NaN or "
                               f"infinite; score only the pixels that have both normals")
    if errors.size == 0:
        return {"mae": None, "median": None, "within": {f"{t:g}": None for t in THRESHOLDS}}
    return {
        "mae": float(errors.mean()),
        "median": float(np.median(errors)),
        "within": {f"{t:g}": float((errors < t).mean()) for t in THRESHOLDS},
    }


def light_direction_error(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Angle in degrees between estimated and true light directions [N, 3]."""
    return angular_error(est, gt)


def intensity_relative_error(est: np.ndarray, gt: np.ndarray) -> float:
    """Scale-invariant relative error mean(|s e_i - e~_i| / e~_i), s fitted by least squares.

    Intensities are only known up to a global scale in uncalibrated photometric stereo.
    """
    est = np.asarray(est, np.float64).reshape(-1)
    gt = np.asarray(gt, np.float64).reshape(-1)
    if est.shape != gt.shape:
        raise PsctlError(None, f"intensity_relative_error: {est.size} estimates but {gt.size} true intensities")
    if not (np.isfinite(gt).all() and (gt > 0).all() and np.isfinite(est).all()):
        raise PsctlError(None, "intensity_relative_error: intensities must be finite, the true ones above 0 (the "
                               "error is relative to them)")
    s = float(est @ gt / max(est @ est, 1e-12))
    return float(np.mean(np.abs(s * est - gt) / gt))
