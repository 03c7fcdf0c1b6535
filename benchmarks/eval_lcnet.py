"""Light estimation accuracy of LCNet weight files, side by side: what chooses an LCNet checkpoint.

Not a test: run it by hand; the tables go into the model card (weights/README.md).

    python benchmarks/eval_lcnet.py weights/lcnet.pt RUN/best.pt [--sets hemi cone45 syntest syntest_dl dev]

Sets (light direction MAE in degrees and intensity relative error, argmax decoding as the
paper; soft-argmax too for the synthetic held-out sets):
  hemi        512 held-out synthetic samples (seed 2,000,003, never used for training or
              validation) of configs/lcnet_cpu.yaml's data: lights uniform over the hemisphere
  cone45      the same with lights within 45 degrees of the view axis (DiLiGenT-like rigs)
  syntest     .cache/syntest: test shapes (bunny, dragon, armadillo) x 4 MERL materials, 100
              lights over the hemisphere (benchmarks/eval_weights.py makes it)
  syntest_dl  the same shapes under 96 DiLiGenT-like lights, 4 other materials (.cache/syntest_dl)
  dev         the DiLiGenT dev split (../shared/data); reported, never used for choosing

The synthetic sets (the first four) choose; ``dev`` only reports.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_infer import machine  # noqa: E402
from bench_lights import synthetic_decoding  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DILIGENT = REPO.parent / "shared" / "data" / "diligent" / "pmsData_crop"
FOLDERS = {"syntest": REPO / ".cache" / "syntest", "syntest_dl": REPO / ".cache" / "syntest_dl", "dev": DILIGENT}
SETS = ("hemi", "cone45", "syntest", "syntest_dl", "dev")


def synthetic(weights: Path, lights: dict, samples: int, device: str) -> dict:
    """{argmax|soft: {light_mae, intensity_re}} on held-out stream samples with these light options."""
    import yaml

    from psctl.train import load_config

    cfg = copy.deepcopy(load_config(REPO / "configs" / "lcnet_cpu.yaml"))
    cfg["data"].update(lights)
    with tempfile.TemporaryDirectory(prefix="psctl-eval-lcnet-") as tmp:
        path = Path(tmp) / "recipe.yaml"
        path.write_text(yaml.safe_dump({"data": cfg["data"]}))
        return synthetic_decoding(weights, path, samples, 32, device)


def folders(weights: Path, root: Path, device: str) -> dict:
    """{object: {light_mae, intensity_re}} plus "mean" over every object of a benchmark root."""
    from psctl.io.capture import find_objects
    from psctl.lights import run_lights

    rows = {}
    for folder in find_objects(root):
        r = run_lights(folder, weights=weights, device=device, write=False)
        rows[r["object"]] = {"light_mae": r["light_mae"], "intensity_re": r["intensity_re"]}
    rows["mean"] = {k: float(np.mean([v[k] for v in rows.values()])) for k in ("light_mae", "intensity_re")}
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("weights", type=Path, nargs="+", help="LCNet weights files")
    ap.add_argument("--sets", nargs="+", default=list(SETS), choices=SETS)
    ap.add_argument("--samples", type=int, default=512, help="held-out synthetic samples per set")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args()

    out: dict = {"machine": machine(), "results": {}}
    for w in args.weights:
        res: dict = {}
        for s in args.sets:
            if s == "hemi":
                res[s] = synthetic(w, {"lights": "hemisphere", "max_zenith": None}, args.samples, args.device)["argmax"]
            elif s == "cone45":
                res[s] = synthetic(w, {"lights": "diligent", "max_zenith": None}, args.samples, args.device)["argmax"]
            else:
                if not FOLDERS[s].is_dir():
                    print(f"{s}: {FOLDERS[s]} not found, skipped", file=sys.stderr)
                    continue
                res[s] = folders(w, FOLDERS[s], args.device)
            r = res[s] if "light_mae" in res[s] else res[s]["mean"]
            print(json.dumps({"weights": str(w), "set": s, "light_mae": round(r["light_mae"], 3),
                              "intensity_re": round(r["intensity_re"], 4)}), flush=True)
        out["results"][str(w)] = res

    print("\n| weights | " + " | ".join(args.sets) + " |")
    print("|---|" + "---:|" * len(args.sets))
    for w, res in out["results"].items():
        cells = []
        for s in args.sets:
            r = res.get(s)
            r = None if r is None else (r if "light_mae" in r else r["mean"])
            cells.append("-" if r is None else f"{r['light_mae']:.2f} / {r['intensity_re']:.3f}")
        print(f"| {w} | " + " | ".join(cells) + " |")
    print("(light direction MAE degrees / intensity RE, argmax)")
    if "dev" in args.sets:
        print("\ndev split per object (light MAE):")
        for w, res in out["results"].items():
            if "dev" in res:
                print(f"  {w}: " + "  ".join(f"{k} {v['light_mae']:.2f}" for k, v in res["dev"].items()))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
