"""A copy of a benchmark folder whose light_intensities.txt is wrong for one block of images.

    python benchmarks/miscalibrated_set.py SRC DST [--seed 51] [--block 20] [--scale 1.15 1.4]

For each object folder in SRC, DST/<object> links every file except light_intensities.txt, which
lists, for one block of `--block` consecutive images at a random start, the source intensities
divided by a factor f (log-uniform in `--scale`, and its inverse with chance 1/2): those images
are f times brighter (or darker) than listed, as DiLiGenT's bear's first 20 images are ~1.27
times brighter than its file says (benchmarks/intensity_consistency.py). A set for choosing
calibrated networks that should tolerate such files; run by hand.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("dst", type=Path)
    ap.add_argument("--seed", type=int, default=51)
    ap.add_argument("--block", type=int, default=20)
    ap.add_argument("--scale", type=float, nargs=2, default=(1.15, 1.4))
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    made = {}
    for obj in sorted(p for p in args.src.iterdir() if (p / "light_intensities.txt").exists()):
        listed = np.loadtxt(obj / "light_intensities.txt", ndmin=2)
        n = len(listed)
        if n < args.block:
            raise SystemExit(f"{obj / 'light_intensities.txt'}: {n} images, fewer than --block {args.block}")
        start = int(rng.integers(0, n - args.block + 1))
        f = math.exp(rng.uniform(math.log(args.scale[0]), math.log(args.scale[1])))
        if rng.random() < 0.5:
            f = 1 / f
        out = args.dst / obj.name
        out.mkdir(parents=True, exist_ok=False)
        for p in obj.iterdir():
            if p.name != "light_intensities.txt":
                (out / p.name).symlink_to(p.resolve())
        wrong = listed.copy()
        wrong[start:start + args.block] /= f
        np.savetxt(out / "light_intensities.txt", wrong, fmt="%.6f")
        made[obj.name] = {"start": start, "block": args.block, "brighter_than_listed": f}
    (args.dst / "miscalibration.json").write_text(json.dumps({"src": str(args.src), "seed": args.seed, "objects": made}, indent=1))
    print(f"{len(made)} objects in {args.dst}")


if __name__ == "__main__":
    main()
