"""float32 vs bf16 autocast for the installed PS-FCN+N weights on the CPU (run by hand; results
in docs/performance.md). Needs ../shared/data (DiLiGenT) and a CPU with native bf16.

    python benchmarks/bench_precision.py

Per object: seconds for each precision (end to end, images read from disk), mean angular error
against the ground truth for each, and how far the bf16 normals are from the float32 ones.
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import time, json, numpy as np
from psctl.io.capture import open_capture, load_mask, load_ground_truth
from psctl.infer import capture_normals
from psctl.metrics import angular_error
out = {}
for name, path in [("ball-full-16bit", "../shared/data/diligent/pmsData/ballPNG")] + [(o, f"../shared/data/diligent/pmsData_crop/{o}PNG") for o in ["ball","cat","pot1","bear","pot2"]]:
    cap = open_capture(path); mask = load_mask(cap); gt = load_ground_truth(cap)
    r = {}
    for ac in [None, "bf16"]:
        t = time.perf_counter(); res = capture_normals(cap, mask, "ps-fcn-n", config={"autocast": ac}); dt = time.perf_counter() - t
        r[str(ac)] = (res.normals, dt)
    a, b = r["None"][0], r["bf16"][0]
    d = np.degrees(np.arccos(np.clip((a[mask]*b[mask]).sum(-1), -1, 1)))
    ea = np.degrees(np.arccos(np.clip((a[mask]*gt[mask]).sum(-1), -1, 1))).mean()
    eb = np.degrees(np.arccos(np.clip((b[mask]*gt[mask]).sum(-1), -1, 1))).mean()
    out[name] = {"fp32_s": round(r["None"][1], 2), "bf16_s": round(r["bf16"][1], 2), "fp32_mae": round(float(ea), 3), "bf16_mae": round(float(eb), 3), "fp32_vs_bf16_mean_deg": round(float(d.mean()), 3), "max_deg": round(float(d.max()), 2)}
    print(name, out[name], flush=True)
