"""Which masks the snap leaves as given with the "draw it tight" note (run by hand)

    python benchmarks/snap_notes.py .cache/syntest_dl .cache/syntest_dl64 .cache/syntest_exposure

Each synthetic object of each set (``psctl synth --preset syntest`` folders) before each of
``--scenes`` (``benchmarks/mask_snap.py``'s: plane:ALBEDO, texture:GAP, near:DISTANCE,
cylinder:SPAN), its true mask grown by 0, 3 and 8 px, through ``psctl.masks.array_snap``. Prints,
per set, scene and growth, how many masks were [left as given with psctl.masks.unsure_note's
note, left as given without it, snapped]. Masks only: no lights run.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from auto_mask_lights import scene  # noqa: E402
from mask_snap import GROW, cylinder  # noqa: E402

SCENES = "near:500,near:1000,near:2000,cylinder:15,cylinder:25,cylinder:40,plane:0.3,texture:0.25,plane:0.01"


def main() -> None:
    from scipy import ndimage

    import psctl.masks
    from psctl.io.capture import open_capture

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", type=Path, nargs="+", help="psctl synth --preset syntest folders")
    ap.add_argument("--scenes", default=SCENES, help="comma-separated, as benchmarks/mask_snap.py's")
    args = ap.parse_args()
    for root in args.roots:
        for sc in args.scenes.split(","):
            kind, value = sc.split(":")
            rng = np.random.default_rng(0)  # as mask_snap.py's, so the same scenes
            counts = {g: [0, 0, 0] for g in GROW}
            for name in (root / "objects.txt").read_text().split():
                cap = open_capture(root / name)
                if kind == "plane":
                    images, _, mask = scene(cap, "plane", float(value), None, None, rng)
                elif kind == "near":
                    images, _, mask = scene(cap, "plane", 0.3, None, float(value), rng)
                elif kind == "cylinder":
                    images, _, mask = cylinder(cap, float(value), rng)
                else:
                    images, _, mask = scene(cap, "texture", 0.0, float(value), None, rng)
                for g in GROW:
                    grown = ndimage.binary_dilation(mask, iterations=g) if g else mask
                    got, note = psctl.masks.array_snap(images, grown)
                    counts[g][2 if not np.array_equal(got, grown) else 0 if note and "draw it tight" in note else 1] += 1
            print(root.name, sc, json.dumps(counts), flush=True)


if __name__ == "__main__":
    main()
