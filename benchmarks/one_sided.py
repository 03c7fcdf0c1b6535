"""How far off are `psctl lights`' directions when the rig lights the object from one side?
(run by hand; docs/uncalibrated.md, "One-sided rigs")

    python benchmarks/one_sided.py [--out runs/one_sided] [--size 64] [--seed 5]

LCNet was trained on rigs around the view axis (cones centred on it). A QA round found lights in
one quadrant pulled toward the axis by about 12 degrees, with nothing said. This script renders
psctl's four syntest shapes (sphere, bunny, dragon, armadillo; one MERL material, the one that
`psctl synth -p syntest -k 1 --seed SEED` picks) under five rigs drawn from the DiLiGenT-like band
(zenith 0-45 degrees, `psctl.synth.lights`), unit intensities, 16-bit:

  around    32 lights, the band's first 32 draws
  half      32 lights with x > 0.05
  quadrant  32 lights with x > 0.05 and y > 0.05
  lop10     10 lights, the first draw of 10 whose lean (psctl.lights.one_sided) is 0.5-0.7
  bal10     10 lights, the first draw of 10 whose lean is under 0.15

and runs `psctl lights` (the installed LCNet, refined by the installed normals network) on each,
printing LCNet's and the refined direction error, the intensity RE, the true rig's lean and the
estimates' lean, and whether the one-sided note was given.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

RIGS = ("around", "half", "quadrant", "lop10", "bal10")


def rig_lights(rig: str, seed: int):
    import torch

    from psctl.lights import one_sided
    from psctl.synth import lights as L

    gen = torch.Generator().manual_seed(seed)
    if rig in ("lop10", "bal10"):
        lo, hi = (0.5, 0.7) if rig == "lop10" else (0.0, 0.15)
        while True:
            d = L.sample_lights((10,), gen, "diligent")
            if lo <= one_sided(d.numpy()) <= hi:
                return d
    d = L.sample_lights((400,), gen, "diligent")
    keep = {"around": torch.ones(len(d), dtype=torch.bool), "half": d[:, 0] > 0.05,
            "quadrant": (d[:, 0] > 0.05) & (d[:, 1] > 0.05)}[rig]
    return d[keep][:32]


def main() -> None:
    import numpy as np
    import torch

    from psctl.lights import one_sided, run_lights
    from psctl.synth import write as W

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="runs/one_sided")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--seed", type=int, default=5)
    a = ap.parse_args()
    out = Path(a.out)
    rows = []
    for rig in RIGS:
        lights = rig_lights(rig, a.seed + 6)
        for obj in W.preset_objects("syntest", seed=a.seed, size=a.size, n_lights=32, k=1, light_dist="diligent"):
            obj.lights, obj.intensities = lights, torch.ones(len(lights))
            images = W.render_object(obj)
            images = (images * W.exposure_scale(images, obj.view.mask[0, 0])).clamp(0, 1)
            folder = out / rig / obj.name
            folder.mkdir(parents=True, exist_ok=True)
            W.write_object(folder, obj, images)
            t = time.perf_counter()
            r = run_lights(folder, out=out / "lights" / rig / obj.name, progress=None)
            est = np.loadtxt(r["outputs"]["light_directions"])
            rows.append({"rig": rig, "object": obj.name, "n": len(lights),
                         "lcnet_light_mae": r["lcnet_light_mae"], "light_mae": r["light_mae"],
                         "intensity_re": r["intensity_re"], "lean_true": one_sided(lights.numpy()),
                         "lean_estimated": one_sided(est),
                         "noted": any("lie to one side" in n for n in r["notes"]),
                         "seconds": round(time.perf_counter() - t, 1)})
            x = rows[-1]
            print(f"{rig:9s} {obj.name:32s} LCNet {x['lcnet_light_mae']:5.2f}  refined {x['light_mae']:5.2f}  "
                  f"RE {x['intensity_re']:.3f}  lean {x['lean_true']:.2f} -> {x['lean_estimated']:.2f}  "
                  f"note {x['noted']}", flush=True)
        # a benchmark root, as psctl synth writes it: `psctl eval --benchmark folder --root OUT/RIG`
        (out / rig / "objects.txt").write_text("".join(r["object"] + "\n" for r in rows if r["rig"] == rig))
    (out / "one_sided.json").write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
