"""Every accuracy number of a model-card entry for one or more weights files (run by hand).

    python benchmarks/eval_weights.py --method ps-fcn --weights runs/ps_fcn/best.pt weights/ps_fcn.pt \
        [--config configs/ps_fcn_cpu.yaml] [--sets val syntest syntest_dl dev ballpng] [--out card.json]
    python benchmarks/eval_weights.py --method ps-fcn-n --weights best.pt weights/ps_fcn_n.pt --sets rule

``--sets rule`` is the selection rule the PS-FCN and PS-FCN+N stages since session 19 were judged
by (written into their recipes before each run): the seven synthetic sets below, each mean rounded
to 0.01, summed (``rule_sum``). ``val`` then uses configs/ps_fcn_cpu.yaml unless --config says
otherwise (the recipes' "val" set, once kept as .cache/ps_fcn_n_val_hemi.yaml, is that file's).

For each file, in this order (cheapest and most important first: checkpoints are chosen on the
synthetic sets, DiLiGenT is only reported):
  val         the recipe's synthetic validation set (--config; the set `psctl train` validates on),
              float32, plus L2 on the same set
  syntest     `psctl eval --benchmark folder --root .cache/syntest` (sphere, bunny, dragon,
              armadillo; 4 MERL materials each, 100 hemisphere lights)
  syntest_dl  the same shapes under 96 DiLiGenT-like lights, 4 other materials (.cache/syntest_dl)
  truncated   syntest_dl scaled to an object mean of 0.02 and truncated to 8 bits, as DiLiGenT's
              crops (benchmarks/quantization.py --means 0.02 --floor)
  syntest_dl_ir      syntest_dl's objects with 3 bounces of diffuse interreflection (albedo 0.8)
  syntest_dl_miscal  syntest_dl with 20 consecutive images per object 1.15-1.4 times brighter or
                     darker than light_intensities.txt lists (benchmarks/miscalibrated_set.py --seed 51)
  syntest_dl_dircal  syntest_dl with every listed zenith angle 3-6 % off, then jittered
                     (benchmarks/miscalibrated_set.py --directions --seed 52)
  syntest_dl_near    syntest_dl's objects under point lights 1,000 pixels away (19-26 radii, as
                     DiLiGenT's; docs/near-lights.md), read as distant lights: robustness, not in the rule
  syntest_dl_384     syntest_dl rendered at 384 px instead of 128 (objects up to 346 px across instead of
                     116; DiLiGenT's crops: 141-407 px; training views: at most 128 px): scale, not in the rule
  dev         the DiLiGenT dev split, cropped 8-bit, all 96 images (../shared/data)
  dev_near    the same with --light-distance 2400 (DiLiGenT's lights, measured on these objects)
  ballpng     the full-size 16-bit ballPNG
Missing synthetic folders are made first with `psctl synth` (24-37 s each for the 128 px sets,
syntest_dl_384 7 minutes, on the 2-core VM beside other jobs, 2026-11-28) or
miscalibrated_set.py (seconds). Prints one JSON object (and writes it with --out): per file and set,
per-object MAE and the mean, and with all seven rule sets the rule's sum.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

DATA = REPO.parent / "shared" / "data" / "diligent"
CACHE = REPO / ".cache"
DL = ["--preset", "syntest", "--lights", "96", "--light-dist", "diligent"]
SYNTH = {  # set -> (folder, how to make it: psctl synth arguments, or a miscalibrated copy of syntest_dl)
    "syntest": (CACHE / "syntest", ["synth", "--preset", "syntest"]),
    "syntest_dl": (CACHE / "syntest_dl", ["synth", *DL]),
    "syntest_dl_ir": (CACHE / "syntest_dl_ir", ["synth", *DL, "--interreflections", "3", "--ir-albedo", "0.8"]),
    "syntest_dl_miscal": (CACHE / "syntest_dl_miscal", ["miscal", "--seed", "51"]),
    "syntest_dl_dircal": (CACHE / "syntest_dl_dircal", ["miscal", "--directions", "--seed", "52"]),
    "syntest_dl_near": (CACHE / "syntest_dl_near", ["synth", *DL, "--light-distance", "1000"]),
    "syntest_dl_384": (CACHE / "syntest_dl_384", ["synth", *DL, "--size", "384"]),
    # the uncalibrated sets (eval_lcnet.py, refine_images.py; docs/uncalibrated.md)
    "syntest_dl_dir": (CACHE / "syntest_dl_dir", ["synth", *DL, "--intensities", "directional"]),
    "syntest_dl_mix31": (CACHE / "syntest_dl_mix31", ["synth", *DL, "--seed", "31", "--intensities", "mixed"]),
    "syntest_dl_mix81": (CACHE / "syntest_dl_mix81", ["synth", *DL, "--seed", "81", "--intensities", "mixed"]),
}
RULE = ("val", "syntest", "syntest_dl", "truncated", "syntest_dl_ir", "syntest_dl_miscal", "syntest_dl_dircal")
SETS = ("val", "syntest", "syntest_dl", "truncated", "syntest_dl_ir", "syntest_dl_miscal", "syntest_dl_dircal",
        "syntest_dl_near", "syntest_dl_384", "dev", "dev_near", "ballpng")


def make_set(name: str) -> Path:
    """The synthetic folder of ``name``, made first if missing (deterministic: fixed seeds)."""
    folder, how = SYNTH[name]
    if not (folder / "objects.txt").is_file() and not (folder / "miscalibration.json").is_file():
        if how[0] == "synth":
            subprocess.run(["psctl", "synth", str(folder), *how[1:], "--quiet"], check=True)
        else:
            src = make_set("syntest_dl")
            subprocess.run([sys.executable, str(REPO / "benchmarks" / "miscalibrated_set.py"), str(src), str(folder),
                            *how[1:]], check=True)
    return folder


def truncated(method: str, weights: str) -> dict:
    """syntest_dl at object mean 0.02, truncated to 8 bits (quantization.py, as the rules ran it)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "q.json"
        subprocess.run([sys.executable, str(REPO / "benchmarks" / "quantization.py"), "--root", str(make_set("syntest_dl")),
                        "--methods", method, "--weights", weights, "--means", "0.02", "--floor", "--no-float", "--out", str(out)],
                       check=True, capture_output=True, text=True)
        q = json.loads(out.read_text())
    key = f"{method} 8bit@0.02"
    return {"objects": {k: round(v[key], 2) for k, v in q["objects"].items()}, "mean": round(q["mean"][key], 2)}


def synthetic_val(config: str, method: str, paths: list[str]) -> dict:
    """MAE on the recipe's validation set: L2 and each file (the training task's own code)."""
    out = subprocess.run([sys.executable, str(REPO / "benchmarks" / "val_compare.py"), "--config", config,
                          "--method", method, "--weights", *paths], check=True, capture_output=True, text=True)
    return json.loads(out.stdout)["mae"]


def benchmark(kind: str, root: Path, method: str, weights: str, light_distance: float | None = None) -> dict:
    from psctl.eval import run_benchmark

    r = run_benchmark(kind, root=root, method=method, weights=weights, device="cpu", light_distance=light_distance)
    return {"objects": {o["name"]: round(o["mae"], 2) for o in r["objects"]}, "mean": round(r["mean_mae"], 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--method", required=True, help="ps-fcn | ps-fcn-n | ups-fcn")
    ap.add_argument("--weights", nargs="+", required=True)
    ap.add_argument("--config", help="the recipe whose validation set to use (needed for 'val')")
    ap.add_argument("--sets", nargs="+", choices=(*SETS, "rule"), default=["val", "syntest", "syntest_dl", "dev", "ballpng"],
                    help="'rule': the seven sets of the selection rule (see above)")
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args()
    if "rule" in args.sets:
        args.sets = list(dict.fromkeys([*RULE, *(s for s in args.sets if s != "rule")]))
        args.config = args.config or str(REPO / "configs" / "ps_fcn_cpu.yaml")

    from psctl.api import run_normals

    result: dict = {"method": args.method, "weights": {w: {} for w in args.weights}}
    t0 = time.perf_counter()

    def done(name: str) -> None:
        """One line on stderr per set, and --out rewritten with what is measured so far ("partial":
        true until the end), so that a run stopped half-way keeps its numbers."""
        for w in args.weights:
            v = result["weights"][w].get(name)
            print(f"{name}: {w}: {v['mean'] if isinstance(v, dict) else v}", file=sys.stderr, flush=True)
        if args.out:
            Path(args.out).write_text(json.dumps({**result, "partial": True}, indent=1) + "\n")
    if "val" in args.sets:
        if not args.config:
            ap.error("'val' needs --config")
        mae = synthetic_val(args.config, args.method, args.weights)
        result["val_l2"] = mae.pop("l2")
        for w in args.weights:
            result["weights"][w]["val"] = mae[w]
        done("val")
    for name in ("syntest", "syntest_dl", "truncated", "syntest_dl_ir", "syntest_dl_miscal", "syntest_dl_dircal",
                 "syntest_dl_near", "syntest_dl_384"):
        if name not in args.sets:
            continue
        for w in args.weights:
            result["weights"][w][name] = (truncated(args.method, w) if name == "truncated"
                                          else benchmark("folder", make_set(name), args.method, w))
        done(name)
    if {"dev", "dev_near", "ballpng"} & set(args.sets):
        if not DATA.is_dir():
            print(f"{DATA}: not found, DiLiGenT sets skipped", file=sys.stderr)
        for w in args.weights if DATA.is_dir() else []:
            if "dev" in args.sets:
                result["weights"][w]["dev"] = benchmark("diligent", DATA / "pmsData_crop", args.method, w)
            if "dev_near" in args.sets:
                result["weights"][w]["dev_near"] = benchmark("diligent", DATA / "pmsData_crop", args.method, w, 2400.0)
            if "ballpng" in args.sets:
                r = run_normals(DATA / "pmsData" / "ballPNG", method=args.method, weights=w, write=False, device="cpu")
                result["weights"][w]["ballpng"] = round(r["mae"], 2)
    if all(s in args.sets for s in RULE):
        for w in args.weights:
            r = result["weights"][w]
            parts = [round(r[s] if s == "val" else r[s]["mean"], 2) for s in RULE]
            r["rule_sum"] = round(sum(parts), 2)
    result["seconds"] = round(time.perf_counter() - t0, 1)
    text = json.dumps(result, indent=1)
    if args.out:
        Path(args.out).write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
