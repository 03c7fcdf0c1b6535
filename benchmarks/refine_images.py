"""Does sdps' light refinement help with few images? (run by hand; docs/uncalibrated.md)

    python benchmarks/refine_images.py [--ks 8 12 16 24 32] [--dev] [--out runs/refine_images.json]

For K images per object (``--images K``, the random subset of seed 0 that psctl uses without
--seed), sdps' mean normal error with the defaults (lights refined against the first normals,
then turned by the normals' roll) and with --no-refine, on the synthetic folders that chose the
refinement and the roll: .cache/syntest, syntest_dl_dir, syntest_dl_mix31 and syntest_dl_mix81
(docs/uncalibrated.md). Why: on the cropped DiLiGenT ball with 12 images the refinement raised
the light error for three seeds out of three (LCNet 1.28 / 1.91 / 2.88 -> 2.02 / 2.37 / 3.00
degrees), while with all 96 images of the dev split it lowers it (4.04 -> 3.16).

The rule, written before the run (2026-11-26, session 25): for each K, S_K(v) = the sum over the
four folders of the mean normal error of variant v. K* = the smallest K of the grid such that
S_K(default) <= S_K(no-refine) at K and at every larger K of the grid. If K* is the smallest K of
the grid, nothing changes. If no K of the grid qualifies, the run is repeated with 48 and 64 added.
Otherwise sdps and psctl lights refine only captures of at least K*
images (DEFAULT_REFINE["min_images"]), with a note below it. ``--dev`` also measures the DiLiGenT
dev split (cropped, 8-bit) at each K: reported, never used to choose.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

FOLDERS = ("syntest", "syntest_dl_dir", "syntest_dl_mix31", "syntest_dl_mix81")
VARIANTS = {"default": True, "no-refine": False}
DEV = REPO.parent / "shared" / "data" / "diligent" / "pmsData_crop"


def main() -> None:
    from psctl.eval import run_benchmark

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ks", type=int, nargs="+", default=[8, 12, 16, 24, 32])
    ap.add_argument("--dev", action="store_true")
    ap.add_argument("--out")
    args = ap.parse_args()
    args.ks = sorted(set(args.ks))
    result: dict = {"ks": args.ks, "folders": {}, "dev": {}}
    t0 = time.perf_counter()
    sys.path.insert(0, str(REPO / "benchmarks"))
    from eval_weights import make_set  # a missing folder is made first (psctl synth, about 2 min each)

    if args.dev and not DEV.is_dir():
        raise SystemExit(f"{DEV}: not found (--dev needs ../shared/data)")
    sets = [(f, "folder", make_set(f)) for f in FOLDERS] + ([("dev", "diligent", DEV)] if args.dev else [])
    for name, kind, root in sets:
        table = result["dev"] if name == "dev" else result["folders"].setdefault(name, {})
        for k in args.ks:
            for v, refine in VARIANTS.items():
                r = run_benchmark(kind, root=root, method="sdps", n_images=k, refine=refine, device="cpu")
                table.setdefault(str(k), {})[v] = {
                    "normals": round(r["mean_mae"], 4), "light_mae": round(r["mean_light_mae"], 4),
                    "objects": {o["name"]: round(o["mae"], 3) for o in r["objects"]}}
                print(f"{name} K={k} {v}: normals {r['mean_mae']:.3f}, lights {r['mean_light_mae']:.3f} "
                      f"({time.perf_counter() - t0:.0f} s)", flush=True)
    sums = {str(k): {v: round(sum(result["folders"][f][str(k)][v]["normals"] for f in FOLDERS), 4)
                     for v in VARIANTS} for k in args.ks}
    ok = [sums[str(k)]["default"] <= sums[str(k)]["no-refine"] for k in args.ks]
    k_star = next((k for i, k in enumerate(args.ks) if all(ok[i:])), None)
    result.update(sums=sums, k_star=k_star, change=None if k_star is None else k_star != args.ks[0],
                  seconds=round(time.perf_counter() - t0))
    for k in args.ks:
        print(f"K={k}: sum default {sums[str(k)]['default']:.3f}, no-refine {sums[str(k)]['no-refine']:.3f}")
    if k_star is None:
        print("no K of the grid qualifies: by the rule, run again with 48 and 64 added (--ks ... 48 64)")
    else:
        print(f"K* = {k_star}", "(no change)" if k_star == args.ks[0] else f"-> refine only from {k_star} images")
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
