"""LCNet's crop: stretch the mask's bounding box to a square (the authors' code) or pad it to one.

    python benchmarks/lights_crop.py --roots .cache/syntest .cache/syntest_dl .cache/syntest_dl_dir \
        ../shared/data/diligent/pmsData_crop --out runs/lights_crop.json

For every capture folder under each root (objects.txt or subfolders): light direction error
(degrees) and intensity RE with the installed LCNet (soft, 8 views), once per crop. Images are
read once per object and both crops run on the same arrays.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    from psctl.io.capture import find_objects, load_images, load_mask, open_capture
    from psctl.lights import array_lights, light_errors

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--roots", nargs="+", required=True)
    ap.add_argument("--weights", default=None, help="LCNet file (default: the installed one)")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--out")
    args = ap.parse_args()
    result = {}
    for root in args.roots:
        rows = {}
        for folder in find_objects(root):
            cap = open_capture(folder)
            mask = load_mask(cap)
            raw = replace(cap, intensities=np.ones_like(cap.intensities))  # as captured, as `psctl lights`
            images = load_images(raw)
            row = {}
            for name, square in (("stretch", False), ("square", True)):
                t0 = time.perf_counter()
                est = array_lights(images, mask, args.weights, {"views": args.views, "square": square, "device": "cpu"})
                e = light_errors(est.directions, est.intensities, cap.lights,
                                 cap.intensities if cap.intensities_given else None)
                row[name] = {"light_mae": round(e["light_mae"], 3),
                             "intensity_re": None if e["intensity_re"] is None else round(e["intensity_re"], 4),
                             "seconds": round(time.perf_counter() - t0, 1)}
            rows[cap.name] = row
            print(root, cap.name, mask.shape, row, flush=True)
        mean = {k: {m: (round(float(np.mean([r[k][m] for r in rows.values()])), 4)
                        if all(r[k][m] is not None for r in rows.values()) else None)
                    for m in ("light_mae", "intensity_re")} for k in ("stretch", "square")}
        result[root] = {"objects": rows, "mean": mean}
        print(root, "mean", mean, flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
