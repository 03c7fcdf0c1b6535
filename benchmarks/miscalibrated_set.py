"""A copy of a benchmark folder whose light_intensities.txt (or light_directions.txt) is wrong.

    python benchmarks/miscalibrated_set.py SRC DST [--seed 51] [--block 20] [--scale 1.15 1.4]
    python benchmarks/miscalibrated_set.py SRC DST --directions [--seed 52] [--zenith 1.03 1.06] [--jitter 0.5]

For each object folder in SRC, DST/<object> links every file except light_intensities.txt, which
lists, for one block of `--block` consecutive images at a random start, the source intensities
divided by a factor f (log-uniform in `--scale`, and its inverse with chance 1/2): those images
are f times brighter (or darker) than listed, as DiLiGenT's bear's first 20 images are ~1.27
times brighter than its file says (benchmarks/intensity_consistency.py). A set for choosing
calibrated networks that should tolerate such files; run by hand.

With `--directions`, light_directions.txt is the one replaced: every listed zenith angle is the
true one times one factor per object (uniform in `--zenith`, its inverse with chance 1/2), each
direction then turned by a random angle (Gaussian per tangent component, sd `--jitter` degrees).
The default (1.0-1.8 degrees per light on syntest_dl's lights) is about the size of a 4 % zenith
scale at DiLiGenT's lights (~1.1 degrees), which moves the stage-11 PS-FCN's dev-split mean by
-0.08 (x 1.04) and +0.17 (x 0.96) degrees (docs/training.md, "Listed light directions").
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from psctl.synth.stream import turn_directions


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("dst", type=Path)
    ap.add_argument("--seed", type=int, default=51)
    ap.add_argument("--block", type=int, default=20)
    ap.add_argument("--scale", type=float, nargs=2, default=(1.15, 1.4))
    ap.add_argument("--directions", action="store_true", help="make light_directions.txt wrong instead")
    ap.add_argument("--zenith", type=float, nargs=2, default=(1.03, 1.06))
    ap.add_argument("--jitter", type=float, default=0.5)
    args = ap.parse_args()
    if args.directions:
        return wrong_directions(args)
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
        out = link_except(obj, args.dst, "light_intensities.txt")
        wrong = listed.copy()
        wrong[start:start + args.block] /= f
        np.savetxt(out / "light_intensities.txt", wrong, fmt="%.6f")
        made[obj.name] = {"start": start, "block": args.block, "brighter_than_listed": f}
    finish(args, made)


def finish(args: argparse.Namespace, made: dict) -> None:
    """miscalibration.json, and objects.txt: the links carry psctl synth's synth.json, and a folder
    of synth objects without objects.txt is refused as maybe incomplete (psctl.io.capture.find_objects)."""
    (args.dst / "miscalibration.json").write_text(json.dumps({"src": str(args.src), "seed": args.seed, "objects": made}, indent=1))
    (args.dst / "objects.txt").write_text("".join(f"{name}\n" for name in made))
    print(f"{len(made)} objects in {args.dst}")


def link_except(obj: Path, dst: Path, name: str) -> Path:
    """DST/<object>: a link to each of the object's files but ``name`` (written by the caller)."""
    out = dst / obj.name
    out.mkdir(parents=True, exist_ok=False)
    for p in obj.iterdir():
        if p.name != name:
            (out / p.name).symlink_to(p.resolve())
    return out


def wrong_directions(args: argparse.Namespace) -> None:
    rng = np.random.default_rng(args.seed)
    made = {}
    for obj in sorted(p for p in args.src.iterdir() if (p / "light_directions.txt").exists()):
        true = np.loadtxt(obj / "light_directions.txt", ndmin=2)
        f = rng.uniform(*args.zenith)
        if rng.random() < 0.5:
            f = 1 / f
        noise = rng.normal(0.0, np.radians(args.jitter), true.shape)
        # the training stream's geometry (psctl.synth.stream.turn_directions), in float64
        d = turn_directions(torch.from_numpy(true), torch.tensor(f, dtype=torch.float64), torch.from_numpy(noise)).numpy()
        out = link_except(obj, args.dst, "light_directions.txt")
        np.savetxt(out / "light_directions.txt", d, fmt="%.6f")
        ang = np.degrees(np.arccos(np.clip((d * true).sum(1), -1, 1)))
        made[obj.name] = {"zenith_factor": f, "jitter_deg": args.jitter, "mean_change_deg": float(ang.mean())}
    finish(args, made)


if __name__ == "__main__":
    main()
