"""How well psctl.refine.mirror_ratio tells a light file with y flipped (run by hand).

    python benchmarks/mirror_check.py l2,ps-fcn OBJ [OBJ ...]

For each capture folder and method: the ratio (mirror image's curl residual over the normals')
of the normals from the lights as given and from the lights with y negated, and of the ground
truth when present. psctl normals notes ratios below psctl.refine.MIRROR_NOTE (docs/usage.md,
"A flipped light axis").
"""

from __future__ import annotations

import sys

from psctl.api import estimate_normals
from psctl.arrays import bounding_box
from psctl.io.capture import load_ground_truth, load_images, load_mask, open_capture
from psctl.refine import mirror_ratio


def main() -> None:
    if len(sys.argv) < 3 or sys.argv[1] in ("-h", "--help"):
        print(__doc__)
        sys.exit(0 if sys.argv[1:2] in (["-h"], ["--help"]) else 2)
    methods = sys.argv[1].split(",")
    for path in sys.argv[2:]:
        cap = open_capture(path)
        mask = load_mask(cap)
        box = bounding_box(mask)
        images, m = load_images(cap, box), mask[box]
        row = []
        for method in methods:
            given = estimate_normals(images, cap.lights, m, method=method, device="cpu")
            flipped = estimate_normals(images, cap.lights * [1, -1, 1], m, method=method, device="cpu")
            row.append(f"{method}: given {mirror_ratio(given, m):.2f} yflip {mirror_ratio(flipped, m):.2f}")
        gt = load_ground_truth(cap)
        if gt is not None:
            row.append(f"gt {mirror_ratio(gt[box], m):.2f}")
        print(cap.name, " | ".join(row), flush=True)


if __name__ == "__main__":
    main()
