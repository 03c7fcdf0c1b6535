"""Where on an object a method's error is (run by hand; a diagnostic, not a target).

    python benchmarks/error_bins.py --method ps-fcn OBJ [OBJ ...] [--weights FILE] [--json]

For each capture folder with ground truth: the mean angular error over the mask, then over the
pixels binned by how often they are dark across the images (below 5 % of the pixel's brightest
observation: shadows, attached and cast) and by the zenith angle of the ground-truth normal;
each bin as (mean error, share of the object's pixels). Comparing real objects with synthetic
ones of the same shapes' kind says whether a gap lives in the shadows, at grazing angles, or
everywhere. "attached p95": the 95th percentile, over observations in attached shadow
(ground-truth n.l < -0.1), of the observation over the pixel's brightest (intensities divided
out), which only light from elsewhere than the lamp makes nonzero.
"""

from __future__ import annotations

import argparse
import json
import tempfile

import numpy as np

from psctl.api import run_normals
from psctl.io.capture import load_ground_truth, load_images, load_mask, open_capture
from psctl.io.normals import read_normal_map
from psctl.metrics import angular_error

DARK_BINS = [(0.0, 0.1), (0.1, 0.3), (0.3, 0.5), (0.5, 1.01)]
ZENITH_BINS = [(0, 30), (30, 60), (60, 91)]


def error_bins(path: str, method: str, weights: str | None = None) -> dict:
    cap = open_capture(path)
    gt = load_ground_truth(cap)
    if gt is None:
        raise SystemExit(f"{path}: no ground truth")
    with tempfile.TemporaryDirectory() as tmp:
        run_normals(path, method=method, out=tmp + "/out", formats=("npy",), weights=weights, device="cpu")
        normals = read_normal_map(tmp + "/out/normal.npy")
    # the pixels psctl eval scores: inside the mask, with a valid ground-truth normal (pot2 has
    # 73 mask pixels without one; counting them as errors added 0.17 degrees)
    m = load_mask(cap).astype(bool) & (np.linalg.norm(gt, axis=-1) > 0.5)
    err = angular_error(normals, gt)[m]
    grey = np.asarray(load_images(cap)).mean(-1)[:, m]  # [N, P]
    dark = (grey < 0.05 * (grey.max(0) + 1e-8)).mean(0)
    zen = np.degrees(np.arccos(np.clip(gt[m][:, 2], -1, 1)))
    out: dict = {"mae": round(float(err.mean()), 2)}
    if cap.lights is not None:
        # light where no lamp reaches: observations in attached shadow (ground-truth n.l < -0.1)
        # relative to the pixel's brightest, intensities divided out (a direct-only renderer
        # gives 0; interreflections, ambient light and calibration error do not)
        rel = grey / cap.intensities.mean(1)[:, None]
        rel = rel / (rel.max(0) + 1e-8)
        att = (cap.lights @ gt[m].T) < -0.1
        out["attached p95"] = round(float(np.quantile(rel[att], 0.95)), 3) if att.any() else None
    for name, vals, bins in (("dark", dark, DARK_BINS), ("zenith", zen, ZENITH_BINS)):
        for lo, hi in bins:
            s = (vals >= lo) & (vals < hi)
            out[f"{name} {lo}-{min(hi, 1.0 if name == 'dark' else 90)}"] = (
                round(float(err[s].mean()), 2) if s.any() else None, round(float(s.mean()), 3))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("objects", nargs="+")
    ap.add_argument("--method", default="ps-fcn")
    ap.add_argument("--weights")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    rows = {}
    for path in a.objects:
        name = path.rstrip("/").split("/")[-1]
        rows[name] = error_bins(path, a.method, a.weights)
        if not a.json:
            print(name, "  ".join(f"{k}: {v}" for k, v in rows[name].items()), flush=True)
    if a.json:
        print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
