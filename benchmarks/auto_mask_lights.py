"""Lights without a mask: the object found by brightness against the whole frame (run by hand)

    psctl synth .cache/syntest_exposure --preset syntest --size 128 --lights 64 -k 4 --seed 3 -q
    python benchmarks/auto_mask_lights.py .cache/syntest_exposure [--background plane --level 0.01]
    python benchmarks/auto_mask_lights.py .cache/syntest_exposure --background texture

Each synthetic object (every --every'th of objects.txt) is put in front of a background, a
Lambertian plane facing the camera lit by the same lights, plus |N(0, 0.002)| noise: "plane" of
albedo --level (0.01: dark, as a photometric stereo capture's black cloth; 0.3 or 0.8: a lit
grey or white table), or "texture" (a smooth random albedo in [0.05, 0.6]). Then
``psctl.estimate_lights`` (the defaults: LCNet, 8 views, refinement with the installed normals
network) runs with the true mask ("mask"), with mask=None ("found": psctl.lights.find_object's
object, the lit pixels with holes filled) and with a mask of the whole frame ("frame": what
mask=None meant before session 63). Prints each object's mean light direction error (degrees)
with find_object's frame fraction, contrast and overlap with the true mask, then one JSON line
of the means.

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
    args = ap.parse_args()

    from scipy import ndimage

    import psctl
    from psctl.io.capture import load_images, load_mask, open_capture
    from psctl.lights import find_object
    from psctl.metrics import light_direction_error

    warnings.simplefilter("ignore")  # the no-mask warnings, once per run
    rng = np.random.default_rng(0)
    out: dict[str, list[float]] = {}
    for name in (args.root / "objects.txt").read_text().split()[::args.every]:
        cap = open_capture(args.root / name)
        images, lights, mask = load_images(cap), cap.lights, load_mask(cap)
        if args.background == "plane":
            albedo = np.full(mask.shape, args.level, np.float32)
        else:
            t = ndimage.gaussian_filter(rng.normal(size=mask.shape), 6)
            albedo = (0.05 + 0.55 * (t - t.min()) / (t.max() - t.min())).astype(np.float32)
        shade = np.clip(lights[:, 2], 0, None)[:, None, None] * albedo[None]
        back = shade[..., None] + np.abs(rng.normal(0, 0.002, images.shape)).astype(np.float32)
        images[:, ~mask] = back[:, ~mask]
        found = find_object(images.sum((0, 3), dtype=np.float64))
        region = np.ones_like(mask) if found.mask is None else found.mask
        row = {"object": name, **{k: found.info[k] for k in ("frame_fraction", "contrast", "used")},
               "iou": round(float((region & mask).sum() / (region | mask).sum()), 3)}
        for label, m in (("mask", mask), ("found", None), ("frame", np.ones_like(mask))):
            d, _ = psctl.estimate_lights(images, m, device="cpu")
            row[label] = round(float(light_direction_error(d, lights).mean()), 2)
            out.setdefault(label, []).append(row[label])
        print(json.dumps(row), flush=True)
    print(json.dumps({"background": args.background, "level": args.level,
                      **{k: round(float(np.mean(v)), 2) for k, v in out.items()}}))


if __name__ == "__main__":
    main()
