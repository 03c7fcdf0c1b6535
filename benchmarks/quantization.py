"""How much 8-bit capture of dark images costs the network methods, on synthetic folders.

    python benchmarks/quantization.py --root .cache/syntest_dl --methods ps-fcn ps-fcn-n \
        --means 0.06 0.02 --out runs/quantization.json

The DiLiGenT dev split (cropped, 8-bit) is dark: the mean object pixel is 0.018 (pot2) to 0.073
(ball) of full scale, and 70-81 % of pot1's and pot2's observations are below 8/255. Each
synthetic object (16-bit PNG, read as float) is scaled so that its mean object pixel is m, clipped
to 1 and rounded (``--floor``: truncated) to 8 bits, then given to each method with the true lights; ``float`` is the
image as read. Mean angular error in degrees per object and over the folder.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def capture_8bit(images: np.ndarray, mask: np.ndarray, mean: float, floor: bool = False) -> np.ndarray:
    """Images [N, H, W, 3] scaled to object mean ``mean``, clipped to [0, 1], rounded (or
    truncated, as DiLiGenT's crops were made) to 8 bits."""
    scale = mean / max(float(images[:, mask].mean()), 1e-12)
    to_int = np.floor if floor else np.round
    return to_int(np.clip(images * scale, 0.0, 1.0) * 255.0) / 255.0


def main() -> None:
    from psctl.infer import array_normals
    from psctl.io.capture import find_objects, load_ground_truth, load_images, load_mask, open_capture
    from psctl.metrics import angular_error

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", required=True)
    ap.add_argument("--methods", nargs="+", default=["ps-fcn", "ps-fcn-n"])
    ap.add_argument("--weights", nargs="*", default=None, help="one file per method (default: installed)")
    ap.add_argument("--means", nargs="+", type=float, default=[0.06, 0.02])
    ap.add_argument("--floor", action="store_true", help="truncate instead of rounding (DiLiGenT's crops)")
    ap.add_argument("--no-float", action="store_true", help="skip the images as read (only the 8-bit variants)")
    ap.add_argument("--out")
    args = ap.parse_args()
    weights = args.weights or [None] * len(args.methods)
    if len(weights) != len(args.methods):  # zip would drop the methods without a file
        raise SystemExit(f"--weights: {len(weights)} files for {len(args.methods)} --methods; give one per method")
    variants = ([] if args.no_float else ["float"]) + [f"8bit@{m:g}" for m in args.means]
    rows: dict = {}
    for folder in find_objects(args.root):
        cap = open_capture(folder)
        mask, gt = load_mask(cap), load_ground_truth(cap)
        valid = mask & (np.linalg.norm(gt, axis=-1) > 0.5)
        images = load_images(cap)
        inputs = {"float": images, **{f"8bit@{m:g}": capture_8bit(images, mask, m, args.floor) for m in args.means}}
        # unrounded in the file (a selection rule rounds once), rounded to 0.001 where printed
        row = {}
        for method, w in zip(args.methods, weights):
            for v in variants:
                n = array_normals(inputs[v], cap.lights, mask, method, w, {"device": "cpu"}).normals
                row[f"{method} {v}"] = float(angular_error(n, gt, valid).mean())
        rows[cap.name] = row
        print(cap.name, {k: round(v, 3) for k, v in row.items()}, flush=True)
    mean = {k: float(np.mean([r[k] for r in rows.values()])) for k in next(iter(rows.values()))}
    print("mean", {k: round(v, 3) for k, v in mean.items()})
    if args.out:
        Path(args.out).write_text(json.dumps({"root": args.root, "objects": rows, "mean": mean}, indent=1))


if __name__ == "__main__":
    main()
