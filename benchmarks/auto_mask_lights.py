"""Lights without a mask: the object found (by brightness, or by shading before a lit background) (run by hand)

    psctl synth .cache/syntest_exposure --preset syntest --size 128 --lights 64 -k 4 --seed 3 -q
    psctl synth .cache/syntest_dl64 --preset syntest --size 128 --lights 64 -k 4 --seed 3 \
        --light-dist diligent -q
    python benchmarks/auto_mask_lights.py .cache/syntest_exposure [--background plane --level 0.01]
    python benchmarks/auto_mask_lights.py .cache/syntest_dl64 --background texture --shadows 0.25

Each synthetic object (every --every'th of objects.txt) is put in front of a background, a
Lambertian plane facing the camera lit by the same lights, plus |N(0, 0.002)| noise: "plane" of
albedo --level (0.01: dark, as a photometric stereo capture's black cloth; 0.3 or 0.8: a lit
grey or white table), or "texture" (a smooth random albedo in [0.05, 0.6]). ``--shadows GAP``:
the object also casts shadows on it, as an object on a table does. Then
``psctl.estimate_lights`` (the defaults: LCNet, 8 views, refinement with the installed normals
network) runs with the true mask ("mask"), with mask=None ("found": psctl.masks.find_object's
object; before a lit background, by shading since session 64), with the object found by
brightness alone as its mask ("brightness": session 63's mask=None) and with a mask of the
whole frame ("frame": what mask=None meant before session 63); ``--only`` picks some. Prints
each object's mean light direction error (degrees) with find_object's frame fraction, contrast,
rule and overlap with the true mask, then one JSON line of the means.

Measured: docs/uncalibrated.md, "Without a mask".
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="a psctl synth --preset syntest folder")
    ap.add_argument("--background", choices=("plane", "texture"), default="plane")
    ap.add_argument("--level", type=float, default=0.01, help="the plane's albedo")
    ap.add_argument("--every", type=int, default=1, help="every K-th object of objects.txt")
    ap.add_argument("--shadows", type=float, default=None, metavar="GAP",
                    help="the object casts shadows on the background: a plane GAP times the object's "
                         "half-width below its rim (depth from its true normals, psctl.depth)")
    ap.add_argument("--near", type=float, default=None, metavar="D",
                    help="the background lit by point lights D pixels from the object's centroid along the "
                         "light directions (falloff and per-pixel direction; render the objects with psctl synth "
                         "--light-distance D to match)")
    ap.add_argument("--only", default="mask,found,brightness,frame", help="which runs, comma-separated")
    args = ap.parse_args()

    import psctl
    from psctl.io.capture import open_capture
    from psctl.masks import array_shading, find_object
    from psctl.metrics import light_direction_error

    warnings.simplefilter("ignore")  # the no-mask warnings, once per run
    rng = np.random.default_rng(0)
    out: dict[str, list[float]] = {}
    for name in (args.root / "objects.txt").read_text().split()[::args.every]:
        cap = open_capture(args.root / name)
        images, lights, mask = scene(cap, args.background, args.level, args.shadows, args.near, rng)
        found = find_object(*array_shading(images))
        region = np.ones_like(mask) if found.mask is None else found.mask
        row = {"object": name, **{k: found.info[k] for k in ("frame_fraction", "contrast", "by", "used")},
               "iou": round(float((region & mask).sum() / (region | mask).sum()), 3)}
        bright = find_object(images.sum((0, 3), dtype=np.float64))  # session 63's rule: brightness alone
        runs = (("mask", mask), ("found", None), ("brightness", np.ones_like(mask) if bright.mask is None else
                                                 bright.mask), ("frame", np.ones_like(mask)))
        for label, m in (r for r in runs if r[0] in args.only.split(",")):
            d, _ = psctl.estimate_lights(images, m, device="cpu")
            row[label] = round(float(light_direction_error(d, lights).mean()), 2)
            out.setdefault(label, []).append(row[label])
        print(json.dumps(row), flush=True)
    print(json.dumps({"background": args.background, "level": args.level, "shadows": args.shadows,
                      **{k: round(float(np.mean(v)), 2) for k, v in out.items()}}))


def scene(cap, background: str, level: float, shadows: float | None, near: float | None,
          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The synthetic object of ``cap`` in front of a background (see the module's docstring):
    images [N, H, W, 3] as captured, its lights [N, 3] and its true mask [H, W]."""
    from scipy import ndimage

    from psctl.io.capture import load_images, load_mask

    images, lights, mask = load_images(cap, as_captured=True), cap.lights, load_mask(cap)
    if background == "plane":
        albedo = np.full(mask.shape, level, np.float32)
    else:
        t = ndimage.gaussian_filter(rng.normal(size=mask.shape), 6)
        albedo = (0.05 + 0.55 * (t - t.min()) / (t.max() - t.min())).astype(np.float32)
    shade = (np.clip(lights[:, 2], 0, None)[:, None, None] if near is None else
             near_shading(mask, lights, near)) * albedo[None]
    if shadows is not None:
        shade = shade * cast_shadows(cap, mask, lights, shadows)
    back = shade[..., None] + np.abs(rng.normal(0, 0.002, images.shape)).astype(np.float32)
    images[:, ~mask] = back[:, ~mask]
    return images, lights, mask


def near_shading(mask: np.ndarray, lights: np.ndarray, distance: float) -> np.ndarray:
    """[N, H, W] irradiance of a plane facing the camera (at the object's centroid's depth) from point
    lights ``distance`` pixels from the centroid along ``lights``: cos / r^2, 1 / D^2 scaled to 1."""
    rows, cols = np.nonzero(mask)
    h, w = mask.shape
    x = np.arange(w)[None, :] - cols.mean()
    y = rows.mean() - np.arange(h)[:, None]  # y up
    v = distance * lights[:, :, None, None] - np.stack(np.broadcast_arrays(x, y, np.zeros_like(x)))[None]
    r = np.linalg.norm(v, axis=1)
    return (np.clip(v[:, 2], 0, None) / r * (distance / r) ** 2).astype(np.float32)


def cast_shadows(cap, mask: np.ndarray, lights: np.ndarray, gap: float) -> np.ndarray:
    """[N, H, W] visibility of a background plane under the object: the object's depth
    integrated from its true normals, the plane ``gap`` times its half-width below its lowest
    point, shadows marched toward each light (psctl.synth.render.march_shadows)."""
    import torch

    from psctl.depth import integrate_normals
    from psctl.io.capture import load_ground_truth
    from psctl.synth.render import march_shadows

    h, w = mask.shape
    depth = integrate_normals(load_ground_truth(cap), mask) * (2.0 / w)  # pixels -> image spans [-1, 1]
    obj = np.isfinite(depth) & mask
    half = 0.5 * (np.ptp(np.nonzero(obj)[1]) + 1) * (2.0 / w)
    z = np.where(obj, depth, float(depth[obj].min()) - gap * half).astype(np.float32)
    vis = march_shadows(torch.from_numpy(z)[None, None], torch.from_numpy(lights.astype(np.float32))[None])[0]
    return np.where(mask[None], 1.0, vis.numpy()).astype(np.float32)


if __name__ == "__main__":
    main()
