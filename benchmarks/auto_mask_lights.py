"""Would a mask made from the lit pixels rescue light estimation without a mask? (run by hand)

    psctl synth .cache/syntest_exposure --preset syntest --size 128 --lights 64 -k 4 --seed 3 -q
    python benchmarks/auto_mask_lights.py .cache/syntest_exposure [--level 0.01] [--every 4]

An experiment for a feature psctl does not have yet. Each synthetic object (every --every'th of
objects.txt) is put in front of a dark Lambertian background of albedo --level facing the camera,
plus |N(0, 0.002)| noise (as benchmarks/exposure_no_mask.py), and ``psctl.estimate_lights``
(the defaults: LCNet, 8 views, refinement with the installed PS-FCN) runs with the true mask,
with none, and with "auto": ``psctl.infer.lit_pixels`` of the summed images, holes filled
(scipy.ndimage.binary_fill_holes). Prints each object's mean light direction error (degrees)
and one JSON line of the means.

Session 62 (2026-12-01, the 2-core AVX2 EPYC VM, level 0.01, every 4th object: the four shapes in
alumina-oxide): mask 6.42, none 32.18, auto 6.42 (the auto masks: 34 pixels more and 35 fewer than
the true ones' 28,702). The same by hand on the DiLiGenT dev split's images as captured (reported
only, not a choice: estimate_lights with mask=None 3.03 9.56 6.10 5.83 9.29 = 6.76, with the
auto mask 2.06 5.81 2.51 1.87 3.39 = 3.13; psctl lights with the true masks 2.89). Not yet
tried: bright or textured backgrounds, normals, a feature's wiring (capture folders, sdps).
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="a psctl synth --preset syntest folder")
    ap.add_argument("--level", type=float, default=0.01, help="the background's albedo")
    ap.add_argument("--every", type=int, default=4, help="every K-th object of objects.txt")
    args = ap.parse_args()

    from scipy import ndimage

    import psctl
    from psctl.infer import lit_pixels
    from psctl.io.capture import load_images, load_mask, open_capture
    from psctl.metrics import light_direction_error

    warnings.simplefilter("ignore")  # the no-mask warnings, once per run
    rng = np.random.default_rng(0)
    out: dict[str, list[float]] = {}
    for name in (args.root / "objects.txt").read_text().split()[::args.every]:
        cap = open_capture(args.root / name)
        images, lights, mask = load_images(cap), cap.lights, load_mask(cap)
        back = args.level * np.clip(lights[:, 2], 0, None)[:, None, None, None] \
            + np.abs(rng.normal(0, 0.002, images.shape)).astype(np.float32)
        images[:, ~mask] = back[:, ~mask]
        auto = ndimage.binary_fill_holes(lit_pixels(images.sum((0, 3))))
        for label, m in (("mask", mask), ("none", None), ("auto", auto)):
            d, _ = psctl.estimate_lights(images, m, device="cpu")
            out.setdefault(label, []).append(float(light_direction_error(d, lights).mean()))
        print(name, {k: round(v[-1], 2) for k, v in out.items()},
              f"auto mask: {int(auto.sum())} px, true {int(mask.sum())}, extra {int((auto & ~mask).sum())}", flush=True)
    print(json.dumps({k: round(float(np.mean(v)), 2) for k, v in out.items()}))


if __name__ == "__main__":
    main()
