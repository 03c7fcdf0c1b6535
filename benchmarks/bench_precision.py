"""float32 vs bf16 autocast for installed network weights on the CPU (run by hand; results in
docs/performance.md). Needs ../shared/data (DiLiGenT) and a CPU with native bf16.

    python benchmarks/bench_precision.py [--method ps-fcn-n] [--weights FILE]

Per object (full-size 16-bit ball, then the cropped dev split): seconds for each precision (end
to end, images read from disk), mean angular error against the ground truth for each (over the
pixels `psctl eval` scores: mask pixels with a valid ground-truth normal), and how far the bf16
normals are from the float32 ones (mean and max degrees).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
DILIGENT = REPO.parent / "shared" / "data" / "diligent"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--method", default="ps-fcn-n")
    ap.add_argument("--weights", default=None, help="weights file (default: the installed ones)")
    args = ap.parse_args()

    from psctl.infer import capture_normals, cpu_has_bf16

    if not cpu_has_bf16():  # checked first: the float32 pass alone takes half a minute
        raise SystemExit("this CPU has no native bf16 (AVX512-BF16 or AMX): nothing to compare")
    if not DILIGENT.is_dir():
        raise SystemExit(f"{DILIGENT}: not found (needs ../shared/data)")
    from psctl.io.capture import load_ground_truth, load_mask, open_capture
    from psctl.metrics import angular_error

    objects = [("ballPNG (full size, 16-bit)", DILIGENT / "pmsData" / "ballPNG")]
    objects += [(f"{o} (crop)", DILIGENT / "pmsData_crop" / f"{o}PNG") for o in ("ball", "cat", "pot1", "bear", "pot2")]
    for name, path in objects:
        cap = open_capture(path)
        mask, gt = load_mask(cap), load_ground_truth(cap)
        valid = mask & (np.linalg.norm(gt, axis=-1) > 0.5)  # as psctl eval
        row: dict = {"object": name}
        normals = {}
        for kind in (None, "bf16"):
            t = time.perf_counter()
            normals[kind] = capture_normals(cap, mask, args.method, args.weights, {"autocast": kind}).normals
            key = kind or "fp32"
            row[f"{key}_s"] = round(time.perf_counter() - t, 2)
            row[f"{key}_mae"] = round(float(angular_error(normals[kind], gt, valid).mean()), 3)
        moved = angular_error(normals["bf16"], normals[None], mask)
        row["bf16_vs_fp32_mean_deg"] = round(float(moved.mean()), 3)
        row["bf16_vs_fp32_max_deg"] = round(float(moved.max()), 2)
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
