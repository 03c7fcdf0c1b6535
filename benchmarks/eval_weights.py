"""Every accuracy number of a model-card entry for one or more weights files (run by hand).

    python benchmarks/eval_weights.py --method ps-fcn --weights runs/ps_fcn/best.pt weights/ps_fcn.pt \
        [--config configs/ps_fcn_cpu.yaml] [--sets val syntest syntest_dl dev ballpng] [--out card.json]

For each file, in this order (cheapest and most important first: checkpoints are chosen on the
synthetic sets, DiLiGenT is only reported):
  val         the recipe's synthetic validation set (--config; the set `psctl train` validates on),
              float32, plus L2 on the same set
  syntest     `psctl eval --benchmark folder --root .cache/syntest` (sphere, bunny, dragon,
              armadillo; 4 MERL materials each, 100 hemisphere lights)
  syntest_dl  the same shapes under 96 DiLiGenT-like lights, 4 other materials (.cache/syntest_dl)
  dev         the DiLiGenT dev split, cropped 8-bit, all 96 images (../shared/data)
  ballpng     the full-size 16-bit ballPNG
Missing synthetic folders are made first with `psctl synth` (about 2 minutes each on 2 cores).
Prints one JSON object (and writes it with --out): per file and set, per-object MAE and the mean.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

DATA = REPO.parent / "shared" / "data" / "diligent"
SYNTH = {  # set -> (folder, psctl synth arguments)
    "syntest": (REPO / ".cache" / "syntest", ["--preset", "syntest"]),
    "syntest_dl": (REPO / ".cache" / "syntest_dl", ["--preset", "syntest", "--lights", "96", "--light-dist", "diligent"]),
}
SETS = ("val", "syntest", "syntest_dl", "dev", "ballpng")


def synthetic_val(config: str, method: str, paths: list[str]) -> dict:
    """MAE on the recipe's validation set: L2 and each file (the training task's own code)."""
    out = subprocess.run([sys.executable, str(REPO / "benchmarks" / "val_compare.py"), "--config", config,
                          "--method", method, "--weights", *paths], check=True, capture_output=True, text=True)
    return json.loads(out.stdout)["mae"]


def benchmark(kind: str, root: Path, method: str, weights: str) -> dict:
    from psctl.eval import run_benchmark

    r = run_benchmark(kind, root=root, method=method, weights=weights, device="cpu")
    return {"objects": {o["name"]: round(o["mae"], 2) for o in r["objects"]}, "mean": round(r["mean_mae"], 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--method", required=True, help="ps-fcn | ps-fcn-n | ups-fcn")
    ap.add_argument("--weights", nargs="+", required=True)
    ap.add_argument("--config", help="the recipe whose validation set to use (needed for 'val')")
    ap.add_argument("--sets", nargs="+", choices=SETS, default=list(SETS))
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args()

    from psctl.api import run_normals

    result: dict = {"method": args.method, "weights": {w: {} for w in args.weights}}
    t0 = time.perf_counter()
    if "val" in args.sets:
        if not args.config:
            ap.error("'val' needs --config")
        mae = synthetic_val(args.config, args.method, args.weights)
        result["val_l2"] = mae.pop("l2")
        for w in args.weights:
            result["weights"][w]["val"] = mae[w]
    for name in ("syntest", "syntest_dl"):
        if name not in args.sets:
            continue
        folder, synth_args = SYNTH[name]
        if not (folder / "objects.txt").is_file():
            subprocess.run(["psctl", "synth", str(folder), *synth_args, "--quiet"], check=True)
        for w in args.weights:
            result["weights"][w][name] = benchmark("folder", folder, args.method, w)
    if "dev" in args.sets or "ballpng" in args.sets:
        if not DATA.is_dir():
            print(f"{DATA}: not found, DiLiGenT sets skipped", file=sys.stderr)
        for w in args.weights if DATA.is_dir() else []:
            if "dev" in args.sets:
                result["weights"][w]["dev"] = benchmark("diligent", DATA / "pmsData_crop", args.method, w)
            if "ballpng" in args.sets:
                r = run_normals(DATA / "pmsData" / "ballPNG", method=args.method, weights=w, write=False, device="cpu")
                result["weights"][w]["ballpng"] = round(r["mae"], 2)
    result["seconds"] = round(time.perf_counter() - t0, 1)
    text = json.dumps(result, indent=1)
    if args.out:
        Path(args.out).write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
