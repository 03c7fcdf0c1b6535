"""Accuracy, speed and memory of normal integration (psctl.depth).

Not a test: run it by hand and copy the tables into docs/performance.md with the machine and date.

    python benchmarks/bench_depth.py                 # everything below (a few minutes on 2 cores)
    python benchmarks/bench_depth.py --skip-big      # without the 2000 x 2000 case
    python benchmarks/bench_depth.py --json out.json

Accuracy (in this process): exact normals of analytic surfaces on a 256 x 256 grid (sphere cap,
paraboloid, sinusoidal bumps), noise-free and with every normal tilted by exactly 5 degrees in
a random direction; RMSE of z after removing the unknown offset, as % of the true depth range.
Also a step (two planes meeting with a varying jump: per-side RMSE, each side's offset removed)
and a sphere seen by a perspective camera (RMSE of distance after the unknown scale).

Speed and memory (each case in a fresh process; seconds = ``psctl.depth.integrate`` only, the
input arrays already in memory; peak RSS = that process's ru_maxrss, input included):
* the full-size DiLiGenT ball (pmsData/ballPNG, 612 x 512): its mask and ground-truth normals;
* a 2000 x 2000 all-foreground map of sinusoidal bumps (4 M unknowns).
"""

from __future__ import annotations

import argparse
import datetime
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))
BALL = REPO.parent / "shared" / "data" / "diligent" / "pmsData" / "ballPNG"


# --- surfaces ------------------------------------------------------------------------------------

def surface(kind: str, n: int):
    r, c = np.mgrid[0:n, 0:n].astype(np.float64)
    x, y = c - (n - 1) / 2, (n - 1) / 2 - r
    mask = x**2 + y**2 < (0.45 * n) ** 2
    if kind == "sphere cap":
        z = np.sqrt((0.5 * n) ** 2 - np.where(mask, x**2 + y**2, 0))
        zx, zy = -x / z, -y / z
    elif kind == "paraboloid":
        a = 1.0 / n
        z, zx, zy = -a * (x**2 + y**2), -2 * a * x, -2 * a * y
    else:  # sinusoidal bumps
        mask = np.ones((n, n), bool)
        amp, f = 0.05 * n, 2 * np.pi * 3 / n
        z = amp * np.sin(f * x) * np.cos(f * y)
        zx, zy = amp * f * np.cos(f * x) * np.cos(f * y), -amp * f * np.sin(f * x) * np.sin(f * y)
    normals = np.stack([-zx, -zy, np.ones_like(z)], -1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return normals.astype(np.float32), mask, z


def perturb(normals, degrees, seed=0):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=normals.shape)
    a -= (a * normals).sum(-1, keepdims=True) * normals
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    t = np.radians(degrees)
    return (normals * np.cos(t) + a * np.sin(t)).astype(np.float32)


def rel_rmse(depth, z, mask):
    e = depth[mask].astype(np.float64) - z[mask]
    e -= e.mean()
    return float(np.sqrt(np.mean(e**2)) / np.ptp(z[mask]))


def step(n):
    r, c = np.mgrid[0:n, 0:n].astype(np.float64)
    y = (n / 2 - r)
    left = c < n / 2
    z = np.where(left, 0.3 * y, -0.3 * y + n / 5)
    normals = np.stack([np.zeros_like(z), np.where(left, -0.3, 0.3), np.ones_like(z)], -1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return normals.astype(np.float32), left, z


def perspective_sphere(h=240, w=320, f=400.0):
    K = np.array([[f, 0, w / 2 + 3.0], [0, f, h / 2 - 2.0], [0, 0, 1.0]])
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    centre = np.array([0.1, -0.05, 4.0])
    a, b, c = (ray * ray).sum(-1), -2 * ray @ centre, centre @ centre - 1.0
    disc = b * b - 4 * a * c
    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
    p = t[..., None] * ray
    n_cv = p - centre
    facing = -(n_cv * ray).sum(-1) / np.linalg.norm(ray, axis=-1)
    mask = (disc > 0) & (facing > 0.3)
    normals = np.stack([n_cv[..., 0], -n_cv[..., 1], -n_cv[..., 2]], -1)
    return normals.astype(np.float32), mask, K, p[..., 2]


# --- cases ---------------------------------------------------------------------------------------

def accuracy(n: int = 256) -> list[dict]:
    from psctl.depth import integrate

    rows = []
    for kind in ("sphere cap", "paraboloid", "sinusoidal bumps"):
        normals, mask, z = surface(kind, n)
        for noise in (0.0, 5.0):
            nm = perturb(normals, noise) if noise else normals
            for method in ("poisson", "bilateral"):
                t0 = time.perf_counter()
                res = integrate(nm, mask, method)
                rows.append({"case": kind, "noise_deg": noise, "method": method, "size": n,
                             "rmse_pct_of_range": round(100 * rel_rmse(res.depth, z, mask), 4),
                             "rounds": res.iterations, "cg_iterations": res.cg_iterations,
                             "seconds": round(time.perf_counter() - t0, 2)})
    normals, left, z = step(128)
    for method in ("poisson", "bilateral"):
        res = integrate(normals, np.ones_like(left), method)
        err = max(rel_rmse(res.depth, z, left), rel_rmse(res.depth, z, ~left))
        rows.append({"case": "step (per side)", "noise_deg": 0.0, "method": method, "size": 128,
                     "rmse_pct_of_range": round(100 * err, 4), "rounds": res.iterations,
                     "cg_iterations": res.cg_iterations})
    normals, mask, K, dist = perspective_sphere()
    for method in ("poisson", "bilateral"):
        res = integrate(normals, mask, method, K=K)
        est = -res.depth[mask].astype(np.float64)
        est *= np.exp(np.mean(np.log(dist[mask])) - np.mean(np.log(est)))
        err = np.sqrt(np.mean((est - dist[mask]) ** 2)) / np.ptp(dist[mask])
        rows.append({"case": "perspective sphere (distance)", "noise_deg": 0.0, "method": method,
                     "size": "320x240", "rmse_pct_of_range": round(100 * float(err), 4),
                     "rounds": res.iterations, "cg_iterations": res.cg_iterations})
    return rows


def child(case: str, method: str) -> None:
    """One timed case in this (fresh) process; prints a JSON line."""
    from psctl.depth import integrate

    if case == "ball":
        import scipy.io

        from psctl.io.images import read_image

        mask = read_image(BALL / "mask.png")[0][..., 0] > 0.5
        normals = scipy.io.loadmat(BALL / "Normal_gt.mat")["Normal_gt"].astype(np.float32)
    else:  # big
        n = 2000
        normals, _, _ = surface("sinusoidal bumps", n)
        mask = np.ones((n, n), bool)
    integrate(np.dstack([np.zeros((8, 8, 2), np.float32), np.ones((8, 8), np.float32)]), None, method)  # warm imports
    t0 = time.perf_counter()
    res = integrate(normals, mask, method)
    seconds = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB -> MiB
    print(json.dumps({"case": case, "method": method, "height": mask.shape[0], "width": mask.shape[1],
                      "pixels": int(res.valid.sum()), "rejected": res.n_rejected, "rounds": res.iterations,
                      "cg_iterations": res.cg_iterations, "seconds": round(seconds, 2),
                      "peak_rss_mb": round(peak, 1)}))


def run_child(case: str, method: str) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", case, method], capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(out.stderr)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--child", nargs=2, metavar=("CASE", "METHOD"), help=argparse.SUPPRESS)
    ap.add_argument("--skip-big", action="store_true", help="skip the 2000 x 2000 case")
    ap.add_argument("--big-bilateral", action="store_true", help="also run bilateral on 2000 x 2000 (slow)")
    ap.add_argument("--json", type=Path, help="write all results here")
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return

    from machine import machine

    result = {"date": datetime.date.today().isoformat(), "machine": machine(), "accuracy": accuracy(), "speed": []}
    print(f"{'case':32s} {'noise':>5s} {'method':9s} {'RMSE % range':>12s} {'rounds':>6s} {'CG':>5s}")
    for r in result["accuracy"]:
        print(f"{r['case']:32s} {r['noise_deg']:5.0f} {r['method']:9s} {r['rmse_pct_of_range']:12.4f} "
              f"{r['rounds']:6d} {r['cg_iterations']:5d}")
    cases = []
    if BALL.is_dir():
        cases += [("ball", "poisson"), ("ball", "bilateral")]
    else:
        print(f"(skipping the DiLiGenT ball: {BALL} not found)")
    if not args.skip_big:
        cases += [("big", "poisson")] + ([("big", "bilateral")] if args.big_bilateral else [])
    print(f"\n{'case':6s} {'method':9s} {'size':>10s} {'pixels':>8s} {'seconds':>8s} {'peak RSS MiB':>12s} {'rounds':>6s} {'CG':>5s}")
    for case, method in cases:
        r = run_child(case, method)
        result["speed"].append(r)
        print(f"{case:6s} {method:9s} {r['width']:>5d}x{r['height']:<4d} {r['pixels']:8d} {r['seconds']:8.2f} "
              f"{r['peak_rss_mb']:12.1f} {r['rounds']:6d} {r['cg_iterations']:5d}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
