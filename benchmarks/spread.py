"""Does the ensemble's spread say where its normals are wrong?

    python benchmarks/spread.py SET_OR_OBJECT [...] [--json OUT] [--views V] [--light-distance D]

Runs ``--method ensemble`` (psctl.run_normals, nothing written) on every object of each
argument (a folder of capture folders, e.g. `.cache/syntest` from `psctl synth`, or one capture
folder; ground truth needed) and compares, per pixel scored against the ground truth, the
spread (the angle between PS-FCN's and PS-FCN+N's normals, ``psctl.infer.member_spread``) with
the ensemble's angular error. Per set: the error in spread bins (pixels pooled over its
objects, with their share), the mean error of each object's top tenth by spread against the
rest (the report's ``mae_top10`` and ``mae_rest``, averaged over objects), and the median over
objects of the Spearman rank correlation between spread and error.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

BINS = (0.0, 1.0, 2.0, 4.0, 8.0, np.inf)  # degrees of spread


def objects_of(arg: str) -> list[Path]:
    from psctl.io.capture import holds_capture

    p = Path(arg)
    if holds_capture(p):
        return [p]
    return sorted(q for q in p.iterdir() if q.is_dir() and holds_capture(q))


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.stats import spearmanr

    return float(spearmanr(a, b).correlation)


def measure(arg: str, views: int, light_distance: float | None) -> dict:
    from psctl.api import run_normals
    from psctl.io.capture import load_ground_truth, open_capture

    rows, pooled_s, pooled_e = [], [], []
    for obj in objects_of(arg):
        arrays: dict = {}
        r = run_normals(obj, method="ensemble", write=False, views=views, light_distance=light_distance,
                        arrays=arrays)
        if r["mae"] is None:
            raise SystemExit(f"{obj}: no ground truth")
        gt = load_ground_truth(open_capture(obj))
        valid = arrays["mask"] & (np.linalg.norm(gt, axis=-1) > 0.5)  # the pixels run_normals scores
        s, e = arrays["spread"][valid].astype(np.float64), arrays["error"][valid].astype(np.float64)
        pooled_s.append(s)
        pooled_e.append(e)
        sp = r["spread"]
        rows.append({"object": r["object"], "mae": r["mae"], "spread_mean": sp["mean"], "spread_p90": sp["p90"],
                     "mae_top10": sp["mae_top10"], "mae_rest": sp["mae_rest"], "rho": spearman(s, e)})
        print(json.dumps(rows[-1]), flush=True)
    s, e = np.concatenate(pooled_s), np.concatenate(pooled_e)
    bins = []
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        sel = (s >= lo) & (s < hi)
        bins.append({"spread": [lo, None if np.isinf(hi) else hi], "share": float(sel.mean()),
                     "mae": float(e[sel].mean()) if sel.any() else None})
    return {"set": arg, "objects": rows, "bins": bins, "mae": float(np.mean([o["mae"] for o in rows])),
            "mae_top10": float(np.mean([o["mae_top10"] for o in rows])),
            "mae_rest": float(np.mean([o["mae_rest"] for o in rows])),
            "rho_median": float(np.median([o["rho"] for o in rows]))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sets", nargs="+")
    ap.add_argument("--json", type=Path, help="write the results here")
    ap.add_argument("--views", type=int, default=1)
    ap.add_argument("--light-distance", type=float)
    args = ap.parse_args()
    results = [measure(a, args.views, args.light_distance) for a in args.sets]
    for res in results:
        print(f"{res['set']}: {len(res['objects'])} objects, ensemble MAE {res['mae']:.2f}; top tenth by spread "
              f"{res['mae_top10']:.2f} vs the rest {res['mae_rest']:.2f}; median Spearman {res['rho_median']:.2f}")
        for b in res["bins"]:
            lo, hi = b["spread"]
            mae = "-" if b["mae"] is None else f"{b['mae']:.2f}"
            print(f"  spread {lo:g}-{'' if hi is None else f'{hi:g}'}: {b['share']:6.1%} of pixels, error {mae}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
