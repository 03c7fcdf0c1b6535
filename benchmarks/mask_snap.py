"""A mask wider than the object: LCNet and the light fit on the mask as given or snapped (run by hand)

    python benchmarks/mask_snap.py .cache/syntest_dl .cache/syntest_exposure [--dev ../shared/data/diligent/pmsData_crop]

Each synthetic object (``psctl synth --preset syntest``: syntest_dl, 96 DiLiGenT-like lights;
syntest_exposure, ``--size 128 --lights 64 --seed 3``) is put before a Lambertian plane lit by
the same lights plus noise (``benchmarks/auto_mask_lights.py``'s ``scene``): dark (albedo 0.01)
and lit (0.3). Its true mask is grown by 0, 3 and 8 px (a mask drawn around the object), and
``psctl.estimate_lights`` (its defaults: LCNet, 8 views, refinement) runs on the images as
captured with that mask as given (``psctl.lights.snap_mask`` made the identity for the call) and
snapped (``snap_mask`` of the images' per-pixel peak, as estimate_lights does since session 69). Prints the mean light direction error (degrees) per set, background, growth and
variant, then one JSON line. ``--dev``: the same on the DiLiGenT dev split's images as captured
with their masks (no plane: the capture's own background), reported only.

The rule, written before the first run (session 69): snapping is adopted if, on each synthetic
set before the dark plane, the mean error with the true masks (0 px) is at most 0.05 above the
mask as given and with masks grown by 3 and by 8 px below it; and before the lit plane at most
0.05 above the mask as given at every growth. The dev split does not decide.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from auto_mask_lights import scene  # noqa: E402

GROW = (0, 3, 8)


def errors(images: np.ndarray, lights: np.ndarray, mask: np.ndarray) -> dict:
    """{growth: {"given", "snapped", "kept"}}: light errors of the mask grown, as given and snapped."""
    from scipy import ndimage

    import psctl
    import psctl.lights
    from psctl.metrics import light_direction_error

    snap = psctl.lights.snap_mask
    peak = images.max(axis=(0, 3)) if images.ndim == 4 else images.max(axis=0)
    out = {}
    for g in GROW:
        grown = ndimage.binary_dilation(mask, iterations=g) if g else mask
        snapped = snap(peak, grown)
        row = {}
        for label in ("given", "snapped"):
            # estimate_lights snaps the mask itself; "given": with snap_mask made the identity
            psctl.lights.snap_mask = snap if label == "snapped" else (lambda peak, m: np.asarray(m, bool))
            try:
                d, _ = psctl.estimate_lights(images, grown, device="cpu")
            finally:
                psctl.lights.snap_mask = snap
            row[label] = float(light_direction_error(d, lights).mean())
        row["iou"] = float((snapped & mask).sum() / (snapped | mask).sum())
        out[g] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", type=Path, nargs="+", help="psctl synth --preset syntest folders")
    ap.add_argument("--dev", type=Path, help="the DiLiGenT dev split (reported only)")
    args = ap.parse_args()

    from psctl.io.capture import find_objects, load_images, load_mask, open_capture

    warnings.simplefilter("ignore")  # the notes, once per run
    summary = {}
    for root in args.roots:
        for level in (0.01, 0.3):
            rng = np.random.default_rng(0)
            rows = []
            for name in (root / "objects.txt").read_text().split():
                images, lights, mask = scene(open_capture(root / name), "plane", level, None, None, rng)
                rows.append(errors(images, lights, mask))
                print(name, level, json.dumps({g: {k: round(v, 3) for k, v in r.items()} for g, r in rows[-1].items()}),
                      flush=True)
            key = f"{root.name} plane {level}"
            summary[key] = {f"{g}px {v}": round(float(np.mean([r[g][v] for r in rows])), 3)
                            for g in GROW for v in ("given", "snapped", "iou")}
            print(key, json.dumps(summary[key]), flush=True)
    if args.dev is not None:
        rows = []
        for folder in find_objects(args.dev):
            cap = open_capture(folder)
            rows.append(errors(load_images(cap, as_captured=True), cap.lights, load_mask(cap)))
            print(cap.name, json.dumps({g: {k: round(v, 3) for k, v in r.items()} for g, r in rows[-1].items()}), flush=True)
        summary["dev"] = {f"{g}px {v}": round(float(np.mean([r[g][v] for r in rows])), 3)
                          for g in GROW for v in ("given", "snapped", "iou")}
        print("dev", json.dumps(summary["dev"]), flush=True)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
