"""Would running the networks on a shrunk capture help? (run by hand)

    python benchmarks/downsample.py --sets syntest_dl_384 syntest_dl_256_s61 --factors 1 2 3 4 [--out d.json]
    python benchmarks/downsample.py --roots ../shared/data/diligent/pmsData_crop --factors 1 2

For every object of every set and every factor k, runs PS-FCN and PS-FCN+N (the installed weights,
or --weights-a / --weights-b) on the capture shrunk by k (``downsample`` in psctl.infer: each k x k
block's mean over the mask, normals interpolated back to full size) and scores each and their unit
mean (the ensemble) at full size: mean angular error in degrees over the pixels ``psctl eval``
scores. Prints one JSON object: per set, factor and object the MAE of a, b and avg, the means, and
the object's longest mask side in pixels. Sets are folders under .cache or benchmark roots.

Decision rule, fixed on 2026-11-28 (session 41) after this script's first four objects (the
syntest_dl_384 spheres, k = 2, 3, 4) were seen and before any other object or any DiLiGenT
capture was shrunk: an automatic factor k = max(1, floor(side / T + 0.5)), side = the mask's
longest bounding-box side in pixels, becomes psctl's default (`--downsample auto`) only if, for
the T among 96, 128 and 192 with the lowest sum of the ensemble's means over syntest_dl_384 and
syntest_dl_256_s61 (`psctl synth --preset syntest --seed 61 --lights 96 --light-dist diligent
--size 256`: other materials, objects about 230 px), that mean is below full size's (k = 1) on
each of the two sets (rounded to 0.01). The 128 px sets (objects at most 116 px) keep k = 1 for
every such T, so the seven-set rules are unchanged. k = 1 on syntest_dl_384 comes from session
39's run of benchmarks/ensemble.py with the same two files (.cache/candidates39/ens_n11.json;
the same code path, as k = 1 is). The DiLiGenT dev split is reported only.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> None:
    from psctl.infer import array_normals, ensemble_normals
    from psctl.io.capture import find_objects, load_ground_truth, load_images, load_mask, object_name, open_capture
    from psctl.metrics import angular_error

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", nargs="*", default=[], help="folders under .cache")
    ap.add_argument("--roots", nargs="*", default=[], help="other benchmark roots")
    ap.add_argument("--factors", nargs="+", type=int, default=[1, 2, 3, 4])
    ap.add_argument("--weights-a")
    ap.add_argument("--weights-b")
    ap.add_argument("--out")
    args = ap.parse_args()
    roots = [(s, REPO / ".cache" / s) for s in args.sets] + [(Path(r).name, Path(r)) for r in args.roots]
    result = {"weights_a": args.weights_a, "weights_b": args.weights_b, "sets": {}}
    for set_name, root in roots:
        rows = {k: [] for k in args.factors}
        for folder in find_objects(root):
            cap = open_capture(folder)
            mask, gt = load_mask(cap), load_ground_truth(cap)
            valid = mask & (np.linalg.norm(gt, axis=-1) > 0.5)
            ys, xs = np.nonzero(mask)
            side = int(max(ys.max() - ys.min(), xs.max() - xs.min()) + 1)
            images = load_images(cap)
            for k in args.factors:
                t0 = time.perf_counter()
                res = {key: array_normals(images, cap.lights, mask, method, weights, {"device": "cpu", "downsample": k})
                       for key, method, weights in (("a", "ps-fcn", args.weights_a), ("b", "ps-fcn-n", args.weights_b))}
                res["avg"] = ensemble_normals([res["a"], res["b"]])  # what --method ensemble gives
                out = {key: r.normals.astype(np.float64) for key, r in res.items()}
                row = {"name": object_name(folder), "side": side,
                       **{key: float(angular_error(v, gt, valid).mean()) for key, v in out.items()},
                       "seconds": round(time.perf_counter() - t0, 1)}
                rows[k].append(row)
                print(set_name, k, row, file=sys.stderr, flush=True)
        result["sets"][set_name] = {str(k): {"objects": r, "mean": {key: round(float(np.mean([o[key] for o in r])), 3)
                                                                    for key in ("a", "b", "avg")}}
                                    for k, r in rows.items()}
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
