"""How far are a rig's lights? The 1/r^2 falloff measured from images and ground-truth normals.

    python benchmarks/light_distance.py OBJ [OBJ ...] [--degree 2] [--normals METHOD] [--json]

For each image k and each pixel x lit at n.l > 0.5 away from the mirror direction (n.h below
cos 35 degrees) and neither dark nor saturated, q_k(x) = log(I_k(x) / (n(x) . l_k) / A(x)), where
A(x) is the pixel's median of I / (n . l) over the images (its albedo, and the camera's
vignetting, which are the same in every image). A point light at distance D along l_k makes
q_k grow along the image by 2 (l_k . X) / D; so per image q_k is fitted by least squares to
a + b u + c v (u, v: pixel offsets from the object's centre, v up) plus a polynomial of the
given degree in the ground-truth normal, which absorbs the BRDF's departure from Lambert's law
(a shiny material also brightens the side of the object facing the light, through its normals,
not its position). Then (b, c) = k (l_x, l_y) over the images by least squares, and D = 2 / k.

Without the normal polynomial (--degree 0) a shiny synthetic object under distant lights shows
a "distance" too; with it, psctl's renders (distant lights) give |k| near 0: run the script on
`psctl synth OUT --preset syntest --lights 96 --light-dist diligent` folders to see it. A sphere
cannot tell position from normal (its normal is a function of position): its row says so.

--normals METHOD (ps-fcn, ps-fcn-n, ensemble, l2) fits with that method's normals instead of
the ground truth's (the pixels stay those with a ground-truth normal): could a capture tell its
own lights' distance? Measured in docs/near-lights.md: no, the networks bend their normals
toward the falloff and the fit then finds a fraction of it.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def light_distance(path: str, degree: int = 2, normals: str | None = None) -> dict:
    from psctl.io.capture import load_ground_truth, load_images, load_mask, open_capture

    cap = open_capture(path)
    if cap.lights is None or cap.gt_path is None:
        raise SystemExit(f"{path}: needs light_directions.txt and ground-truth normals")
    images = load_images(cap).mean(-1)  # [N, H, W], intensities divided
    mask, n, lights = load_mask(cap), load_ground_truth(cap).astype(np.float64), cap.lights.astype(np.float64)
    ok = mask & (np.linalg.norm(n, axis=-1) > 0.5)
    if normals is not None:  # the method's own normals, distant lights assumed
        from psctl.api import run_normals

        arrays: dict = {}
        run_normals(path, method=normals, write=False, arrays=arrays)
        n = arrays["normals"].astype(np.float64)
    rows, cols = np.nonzero(ok)
    u, v = cols - cols.mean(), -(rows - rows.mean())
    nn = n[ok]  # [P, 3]
    obs = images[:, ok]  # [N, P]
    nl = lights @ nn.T
    half = lights + np.array([0.0, 0.0, 1.0])
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    nh = half @ nn.T
    valid = (nl > 0.5) & (nh < np.cos(np.radians(35))) & (obs > 0.01) & (obs < 0.95)
    ratio = np.where(valid, obs / np.maximum(nl, 1e-6), np.nan)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # pixels with no valid observation
        albedo = np.nanmedian(ratio, axis=0)
        q = np.log(ratio / albedo[None])
    feats = [np.ones(len(u)), u, v]
    for d in range(1, degree + 1):
        for c in itertools.combinations_with_replacement(range(3), d):
            feats.append(np.prod(nn[:, list(c)], axis=1))
    design = np.stack(feats, 1)
    slopes, lxy = [], []
    for k in range(len(lights)):
        s = valid[k] & np.isfinite(q[k])
        if s.sum() < 10 * design.shape[1]:
            continue
        coef, *_ = np.linalg.lstsq(design[s], q[k][s], rcond=None)
        slopes.append(coef[1:3])
        lxy.append(lights[k, :2])
    slopes, lxy = np.array(slopes), np.array(lxy)
    k = float((slopes * lxy).sum() / (lxy * lxy).sum())
    resid = slopes - k * lxy
    r2 = float(1 - (resid ** 2).sum() / ((slopes - slopes.mean(0)) ** 2).sum())
    radius = float(np.sqrt(ok.sum() / np.pi))
    # a sphere: the normal polynomial can reproduce any linear function of position
    sphere = False
    if degree >= 1:
        uv = np.stack([u, v], 1)
        fit = design[:, [0, *range(3, design.shape[1])]]
        res = uv - fit @ np.linalg.lstsq(fit, uv, rcond=None)[0]
        sphere = bool((res ** 2).sum() < 1e-3 * ((uv - uv.mean(0)) ** 2).sum())
    return {"object": cap.name, "normals": normals or "ground truth", "images": len(slopes), "k": k, "distance_px": 2 / k if k > 0 else None,
            "radius_px": radius, "r2": r2, "position_is_normal": sphere}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("objects", nargs="+")
    ap.add_argument("--degree", type=int, default=2, help="degree of the normal polynomial (0: none)")
    ap.add_argument("--normals", metavar="METHOD", help="fit with this method's normals, not the ground truth's")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    rows = [light_distance(p, args.degree, args.normals) for p in args.objects]
    if args.json:
        print(json.dumps(rows, indent=1))
        return
    for r in rows:
        d = "-" if r["distance_px"] is None else f"{r['distance_px']:.0f} px ({r['distance_px'] / r['radius_px']:.1f} radii)"
        warn = "  (a sphere: position and normal are one; not counted)" if r["position_is_normal"] else ""
        print(f"{r['object']:>24}: k {r['k']:+.2e} per px, R^2 {r['r2']:.2f}, D {d}{warn}")
    ds = [r["distance_px"] for r in rows if r["distance_px"] and not r["position_is_normal"] and r["r2"] > 0.5]
    if ds:
        print(f"median D over {len(ds)} objects with R^2 > 0.5 (spheres left out): {np.median(ds):.0f} px")


if __name__ == "__main__":
    main()
