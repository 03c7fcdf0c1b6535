"""LCNet's lights from few images: the DiLiGenT dev split's objects on random subsets (run by hand)

    python benchmarks/few_images_lights.py [--root ../shared/data/diligent/pmsData_crop] [--counts 1 2 4 8]
        [--subsets 6]

For each object and each count K, ``--subsets`` random subsets of K of its images (numpy seed 1,
drawn in order), ``psctl.estimate_lights`` with its defaults (LCNet, 8 views, refinement) on the
images as captured with the object's mask; the mean light direction error (degrees) over the
subset's lights. All the images once as well. Prints each object's time, then per K the mean,
median and 90th percentile over objects x subsets. Reported only (what psctl.lights.few_lights_note
quotes); nothing is chosen on it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=REPO.parent / "shared" / "data" / "diligent" / "pmsData_crop")
    ap.add_argument("--counts", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--subsets", type=int, default=6)
    args = ap.parse_args()

    import psctl
    from psctl.io.capture import find_objects, load_images, load_mask, open_capture
    from psctl.metrics import light_direction_error

    warnings.simplefilter("ignore")  # the few-images note itself, among others
    rng = np.random.default_rng(1)
    res: dict[str, list[float]] = {}
    t0 = time.time()
    for folder in find_objects(args.root):
        cap = open_capture(folder)
        images, mask = load_images(cap, as_captured=True), load_mask(cap)
        for k in [*args.counts, cap.n_images]:
            for _ in range(args.subsets if k < cap.n_images else 1):
                idx = np.sort(rng.choice(cap.n_images, k, replace=False)) if k < cap.n_images else np.arange(k)
                d, _ = psctl.estimate_lights(images[idx], mask, device="cpu")
                res.setdefault("all" if k == cap.n_images else str(k), []).append(
                    float(light_direction_error(d, cap.lights[idx]).mean()))
        print(cap.name, f"{time.time() - t0:.0f} s", flush=True)
    out = {k: {"mean": round(float(np.mean(v)), 2), "median": round(float(np.median(v)), 2),
               "p90": round(float(np.percentile(v, 90)), 2), "n": len(v)} for k, v in res.items()}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
