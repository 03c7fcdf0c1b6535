"""LCNet alone with the exposure guard as shipped against always scaling to the target (run by hand).

    python benchmarks/lcnet_exposure.py ROOT [ROOT ...]

For every object of each benchmark root: LCNet's light direction error (soft-argmax, 8 views, no
refinement) with DEFAULT_LIGHTS' guard (captures whose mean inside the mask lies outside
exposure_band are scaled to exposure_target) and with every capture scaled to exposure_target
(exposure_band collapsed to the target). The rule, written before the run (2026-11-26):
always scaling is adopted if the mean over the folder sets syntest, syntest_dl, syntest_dl_dir
and syntest_dl_ir falls by 0.05 degrees or more, and then only if sdps' normals on its three
synthetic folders (syntest, syntest_dl_dir, syntest_dl_mix31) do not get worse in sum; the
DiLiGenT dev split is reported, never used to choose.
"""

from __future__ import annotations

import sys

import numpy as np

from psctl.io.capture import find_objects
from psctl.lights import DEFAULT_LIGHTS, run_lights

VARIANTS = {"guard": {}, "always": {"exposure_band": (DEFAULT_LIGHTS["exposure_target"],) * 2}}


def main() -> None:
    import psctl.lights as lights_module

    means = {v: [] for v in VARIANTS}
    if len(sys.argv) < 2 or sys.argv[1] in ("-h", "--help"):
        print(__doc__)
        sys.exit(0 if len(sys.argv) > 1 else 2)
    for root in sys.argv[1:]:
        errs = {v: [] for v in VARIANTS}
        for folder in find_objects(root):
            row = []
            for name, override in VARIANTS.items():
                saved = dict(lights_module.DEFAULT_LIGHTS)
                lights_module.DEFAULT_LIGHTS.update(override)
                try:
                    r = run_lights(folder, refine=False, write=False, device="cpu")
                finally:
                    lights_module.DEFAULT_LIGHTS.clear()
                    lights_module.DEFAULT_LIGHTS.update(saved)
                errs[name].append(r["light_mae"])
                row.append(f"{name} {r['light_mae']:.4f}")
            print(f"  {folder.name:28s} " + "  ".join(row), flush=True)
        print(root, "  ".join(f"{k}: {np.mean(v):.6f}" for k, v in errs.items()), flush=True)
        for k, v in errs.items():
            means[k].append(float(np.mean(v)))
    # the rule's number: the mean over the roots given, unrounded
    print("mean over the roots", "  ".join(f"{k}: {np.mean(v)!r}" for k, v in means.items()),
          f"fall: {np.mean(means['guard']) - np.mean(means['always'])!r}", flush=True)


if __name__ == "__main__":
    main()
