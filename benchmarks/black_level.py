"""How a method's error moves when every pixel gains or loses a small constant (run by hand).

    python benchmarks/black_level.py --method ps-fcn --weights weights/ps_fcn.pt \
        [--objects ../shared/data/diligent/pmsData/ballPNG] [--offsets -0.00125 0 0.00125] [--json]

Real captures are rarely exactly black where no light reaches: ambient light, interreflections
and the sensor's black level leave a little (1.4 % of the lit mean on the 16-bit DiLiGenT ball;
about 0 on the 8-bit crops, whose values were truncated). A network trained on images whose
shadows are exactly 0 (plus zero-mean noise) may read that small floor as shading. For each
offset d (a fraction of the full scale, added to the raw pixels and clipped at 0, before the
division by the light intensities) this prints the mean angular error on each object.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

DATA = REPO.parent / "shared" / "data" / "diligent"


def main() -> None:
    from psctl.api import estimate_normals
    from psctl.io.capture import load_ground_truth, load_images, load_mask, open_capture
    from psctl.metrics import angular_error

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--method", default="ps-fcn")
    ap.add_argument("--weights")
    ap.add_argument("--objects", nargs="+", default=[str(DATA / "pmsData" / "ballPNG")])
    ap.add_argument("--offsets", nargs="+", type=float, default=[-0.00125, 0.0, 0.00125, 0.0025])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    rows = {}
    for folder in args.objects:
        cap = open_capture(folder)
        mask, gt = load_mask(cap), load_ground_truth(cap)
        if gt is None:
            sys.exit(f"{folder}: no ground truth")
        # raw pixels: load_images divides by the intensities, so multiply back
        imgs = load_images(cap) * cap.intensities[:, None, None, :]
        valid = mask & (np.linalg.norm(gt, axis=-1) > 0.5)
        rows[cap.name] = {}
        for d in args.offsets:
            x = np.clip(imgs + np.float32(d), 0.0, None) / cap.intensities[:, None, None, :]
            lights = None if args.method in ("sdps", "ups-fcn") else cap.lights  # those refuse given lights
            n = estimate_normals(x, lights, mask, args.method, args.weights, device="cpu")
            rows[cap.name][d] = round(float(angular_error(n, gt, valid).mean()), 2)
            if not args.json:
                print(f"{cap.name:10s} offset {d:+.5f}: {rows[cap.name][d]:.2f} deg", flush=True)
    if args.json:
        print(json.dumps({"method": args.method, "weights": args.weights, "mae": rows}, indent=1))


if __name__ == "__main__":
    main()
