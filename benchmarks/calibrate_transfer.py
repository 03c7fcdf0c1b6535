"""Normals from lights that psctl calibrate measured on DiLiGenT's ball (run by hand).

    python benchmarks/calibrate_transfer.py BALL OBJ [OBJ ...] [--methods l2,ps-fcn-n] [--sphere chrome]

DiLiGenT photographed every object under one rig of 96 LEDs. This calibrates the rig's
directions from the ball's images (``psctl.run_calibrate``, by default from its highlights, as
from a chrome sphere) and estimates each object's normals twice: with its own listed directions
and with the ball's calibrated ones (the object's listed intensities both times). Prints, per
object and method, the mean angular error of both and the calibrated directions' error against
the object's listed ones.
"""

from __future__ import annotations

import argparse

import numpy as np

from psctl.api import estimate_normals
from psctl.calibrate import run_calibrate
from psctl.io.capture import load_ground_truth, load_images, load_mask, open_capture
from psctl.metrics import angular_error


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("ball")
    ap.add_argument("objects", nargs="+")
    ap.add_argument("--methods", default="l2,ps-fcn-n")
    ap.add_argument("--sphere", default="chrome", choices=("chrome", "matte"))
    args = ap.parse_args()
    cal = run_calibrate(args.ball, args.sphere, write=False)
    ball_dirs = np.array([i["direction"] for i in cal["images"]], np.float64)
    print(f"{args.sphere} calibration of {cal['object']}: {cal['light_mae']:.3f} degrees from its listed directions")
    for path in args.objects:
        cap = open_capture(path)
        mask, gt = load_mask(cap), load_ground_truth(cap)
        images = load_images(cap)  # divided by the object's listed intensities
        off = angular_error(ball_dirs, cap.lights)
        valid = mask & (np.linalg.norm(gt, axis=-1) > 0.5)
        for method in args.methods.split(","):
            row = []
            for lights in (cap.lights, ball_dirs):
                n = estimate_normals(images, lights.astype(np.float32), mask, method=method)
                row.append(float(angular_error(n[valid], gt[valid]).mean()))
            print(f"{cap.name:6s} {method:9s} listed {row[0]:.2f}  calibrated {row[1]:.2f}  "
                  f"(calibrated vs listed directions: mean {off.mean():.2f}, max {off.max():.2f})", flush=True)


if __name__ == "__main__":
    main()
