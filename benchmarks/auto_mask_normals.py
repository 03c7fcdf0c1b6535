"""Calibrated normals without a mask: the whole frame, or the object found (run by hand)

    psctl synth .cache/syntest_dl64 --preset syntest --size 128 --lights 64 -k 4 --seed 3 \
        --light-dist diligent -q
    python benchmarks/auto_mask_normals.py .cache/syntest_dl64 [--background plane --level 0.01]
    python benchmarks/auto_mask_normals.py .cache/syntest_dl64 --background texture --shadows 0.25

Each synthetic object is put in front of the background of ``benchmarks/auto_mask_lights.py``
(the same scenes: ``scene``), and a network method (``--method``, default the ensemble that
``psctl normals`` runs on a calibrated folder) estimates the normals with the true lights:

- mask: the true mask (what a mask.png gives);
- frame: ``mask=None``, the whole frame (psctl's rule for the networks until session 65);
- found: the object ``psctl.masks.find_object`` finds (what ``psctl lights`` reads);
- found+K: that object grown by K pixels (``--grow``) for the network's input and output;
- found>K: the network reads the found object, its normals kept on it grown by K pixels
  (``--keep``; the inference setting ``grow``: one run with the largest K, cut to each).

For each, over the true mask's pixels: ``mae`` (degrees) over the pixels the run gives a normal,
``cover`` the fraction it gives one, and ``mae90`` with the others counted at 90 degrees (a
missing normal is an error too). Prints a JSON line per object, then one with the means.

Measured (session 65, 2026-12-01, every 2nd object, four backgrounds): docs/models.md, "Without
a mask"; it chose psctl.infer.FOUND_GROW.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="a psctl synth --preset syntest folder")
    ap.add_argument("--background", choices=("plane", "texture"), default="plane")
    ap.add_argument("--level", type=float, default=0.01, help="the plane's albedo")
    ap.add_argument("--shadows", type=float, default=None, metavar="GAP", help="as auto_mask_lights.py")
    ap.add_argument("--near", type=float, default=None, metavar="D", help="as auto_mask_lights.py")
    ap.add_argument("--every", type=int, default=1, help="every K-th object of objects.txt")
    ap.add_argument("--method", default="ensemble")
    ap.add_argument("--grow", default="1,2,3,4", help="pixels to grow the found object by, comma-separated")
    ap.add_argument("--keep", default="1,2,3,4",
                    help="found>K: the network reads the found object, its normals kept on it grown by K pixels "
                         "(the inference setting grow), comma-separated")
    ap.add_argument("--only", default=None, help="which runs (mask, frame, found, found+K, found>), comma-separated")
    args = ap.parse_args()

    from auto_mask_lights import scene

    from psctl.infer import array_normals, grow_mask
    from psctl.io.capture import load_ground_truth, open_capture
    from psctl.masks import array_shading, find_object
    from psctl.metrics import angular_error

    warnings.simplefilter("ignore")  # the no-mask warnings, once per run
    rng = np.random.default_rng(0)
    keeps = [int(g) for g in args.keep.split(",") if g]
    out: dict[str, dict[str, list[float]]] = {}
    for name in (args.root / "objects.txt").read_text().split()[::args.every]:
        cap = open_capture(args.root / name)
        captured, lights, mask = scene(cap, args.background, args.level, args.shadows, args.near, rng)
        images = captured / cap.intensities[:, None, None, :].astype(np.float32)
        gt = load_ground_truth(cap)
        valid = mask & (np.linalg.norm(gt, axis=-1) > 0.5)
        found = find_object(*array_shading(captured))
        row: dict = {"object": name, "by": found.info.get("by"), "used": found.info.get("used"),
                     "iou": None if found.mask is None else
                     round(float((found.mask & mask).sum() / (found.mask | mask).sum()), 3)}

        def score(label: str, n: np.ndarray) -> None:
            given = valid & (np.linalg.norm(n, axis=-1) > 0.5)
            err = angular_error(n, gt)
            res = {"mae": float(err[given].mean()) if given.any() else float("nan"),
                   "cover": float(given.sum() / valid.sum()),
                   "mae90": float((err[given].sum() + 90.0 * (valid & ~given).sum()) / valid.sum())}
            row[label] = {k: round(v, 3) for k, v in res.items()}
            for k, v in res.items():
                out.setdefault(label, {}).setdefault(k, []).append(v)

        runs: dict[str, np.ndarray | None] = {"mask": mask, "frame": None, "found": found.mask}
        for k in (int(g) for g in args.grow.split(",") if g):
            runs[f"found+{k}"] = None if found.mask is None else grow_mask(found.mask, k)
        if keeps:
            runs["found>"] = found.mask
        for label, m in runs.items():
            if args.only and label not in args.only.split(","):
                continue
            if label == "found>" and m is not None:  # one run, its normals kept on the object grown by each K
                n_all = array_normals(images, lights, m, args.method, config={"grow": max(keeps)}).normals
                for k in keeps:
                    score(f"found>{k}", np.where(grow_mask(m, k)[..., None], n_all, 0.0))
            else:
                score(label, array_normals(images, lights, m, args.method).normals)
        print(json.dumps(row), flush=True)
    print(json.dumps({"background": args.background, "level": args.level, "shadows": args.shadows,
                      "near": args.near, "method": args.method,
                      **{lab: {k: round(float(np.mean(v)), 3) for k, v in d.items()} for lab, d in out.items()}}))


if __name__ == "__main__":
    main()
