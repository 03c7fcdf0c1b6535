"""Bright interreflections on the test shapes (run by hand; a diagnostic for docs/training.md).

    python benchmarks/bright_interreflections.py BOUNCES OUT [--kd-max 0.9]
    python benchmarks/bright_interreflections.py 0 .cache/ir_stress0
    python benchmarks/bright_interreflections.py 3 .cache/ir_stress3
    psctl eval --benchmark folder --root .cache/ir_stress3 -m ps-fcn --json
    python benchmarks/error_bins.py .cache/ir_stress3/bunny_nylon ...

Writes the syntest preset's bunny, dragon and armadillo objects (4 MERL materials, 96
DiLiGenT-like lights, 128 px) with each material's diffuse albedo kd scaled so that its
brightest channel is --kd-max (direct light too, unlike --ir-albedo), rendered with BOUNCES
exact diffuse bounces: what a white object's interreflections do to a method, against the same
objects without them (BOUNCES = 0).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from psctl.synth import render as R
from psctl.synth import write as W


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bounces", type=int)
    ap.add_argument("out")
    ap.add_argument("--kd-max", type=float, default=0.9)
    a = ap.parse_args()
    root = Path(a.out)
    objs = [o for o in W.preset_objects("syntest", 0, 128, 96, 4, "diligent") if not o.name.startswith("sphere")]
    root.mkdir(parents=True, exist_ok=True)
    gen = torch.Generator().manual_seed(1)
    for o in objs:
        o.mat["kd"] = o.mat["kd"] * (a.kd_max / o.mat["kd"].max())
        img = W.render_object(o, bounces=a.bounces)
        s = W.exposure_scale(img, o.view.mask[0, 0], gen)
        img = R.quantize(img * s, 16) * o.view.mask[0]
        o.meta.update(exposure=s, interreflections=a.bounces, kd_max=a.kd_max)
        (root / o.name).mkdir(exist_ok=True)
        W.write_object(root / o.name, o, img)
    (root / "objects.txt").write_text("".join(o.name + "\n" for o in objs))
    print(f"wrote {len(objs)} objects to {root}")


if __name__ == "__main__":
    main()
