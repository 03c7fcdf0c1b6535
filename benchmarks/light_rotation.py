"""How much of sdps' light error is one global rotation (run by hand; a diagnostic).

    python benchmarks/light_rotation.py OBJ [OBJ ...] [--json]

For each capture folder with ground-truth lights: LCNet's lights (sdps' settings), PS-FCN's
normals from them, the refined lights (psctl.refine.refine_capture), and for both the mean
direction error before and after the best single rotation of all the lights onto the true ones
(orthogonal Procrustes, no reflection). A refit (Lambertian or shifted falloff) against normals estimated from
rotated lights cannot remove a rotation shared by all the lights (turning the normals and the
lights together leaves every n.l unchanged), so what the rotation explains is what the
refinement leaves for an absolute cue to fix.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from psctl.infer import capture_normals
from psctl.io.capture import load_mask, open_capture
from psctl.lights import capture_lights, lit_capture
from psctl.refine import refine_capture
from psctl.metrics import light_direction_error
from psctl.sdps import sdps_lcnet_config, sdps_second_stage


def best_rotation(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """R [3, 3] minimising sum |est_i R - gt_i|^2 over rotations."""
    u, _, vt = np.linalg.svd(est.T @ gt)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def measure(path: str) -> dict:
    cap = open_capture(path)
    if not cap.calibrated:
        raise SystemExit(f"{path}: no light_directions.txt to compare with")
    mask = load_mask(cap)
    second = sdps_second_stage(None)[0]
    est = capture_lights(cap, mask, None, sdps_lcnet_config(second, None, "auto"))
    net = capture_normals(lit_capture(cap, est), mask, second, None, {})
    ref = refine_capture(cap, mask, est, net.normals)
    out = {"object": cap.name, "refine_weight": ref.info["refine"]["weight"]}
    for name, d in (("lcnet", est.directions), ("refined", ref.directions)):
        r = best_rotation(d, cap.lights)
        out[name] = {"error": float(light_direction_error(d, cap.lights).mean()),
                     "after_rotation": float(light_direction_error(d @ r, cap.lights).mean()),
                     "rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("objects", nargs="+")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    rows = [measure(p) for p in args.objects]
    if args.json:
        print(json.dumps(rows, indent=1))
        return
    for r in rows:
        print(f"{r['object']:10s} " + "   ".join(
            f"{k} {r[k]['error']:5.2f} -> {r[k]['after_rotation']:5.2f} (rotation {r[k]['rotation_deg']:4.2f} deg)"
            for k in ("lcnet", "refined")) + f"   refine weight {r['refine_weight']:.2f}")


if __name__ == "__main__":
    main()
