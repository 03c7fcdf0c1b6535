"""How well each capture's images agree with its light_directions.txt (run by hand; a diagnostic).

    python benchmarks/direction_consistency.py OBJ [OBJ ...] [--pixels 20000] [--json FILE]
        [--trim LO HI] [--margin M] [--falloff lambertian|shifted] [--iters K]

With the ground-truth normals, psctl's robust light fit (psctl.refine.refine_lights, the sdps
refinement with its default falloff, "shifted" since session 20, or `--falloff lambertian`; here
always applied: no gate, no max change) is started at the listed
lights; printed per object: the fit's relative residual q, the mean angle (degrees) between the
fitted and the listed directions, the mean change of the zenith angle (fitted minus listed; + is
further from the view axis), the mean of what is not along the zenith, and the angle of the best
rotation from listed to fitted (a rig turned as a whole). On a synthetic object (exact lights)
the same numbers measure the fit's own bias; on a real one, what is beyond that is the file's
error (or the surface's departure from Lambertian where it is lit: compare q). `--trim`,
`--margin`, `--falloff` and `--iters` override the fit's (psctl.refine.DEFAULT_REFINE) to see what they do to that bias; the
last line is the mean angle over the objects the sdps gate would refine (q < its upper end).
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from psctl.io.capture import load_ground_truth, load_mask, open_capture
from psctl.io.images import read_image, to_rgb
from psctl.refine import DEFAULT_REFINE, FALLOFFS, refine_lights


def measure(path: str, pixels: int = 20000, fit: dict | None = None) -> dict:
    cap = open_capture(path)
    normals = load_ground_truth(cap)
    if not cap.calibrated or normals is None:
        raise SystemExit(f"{path}: needs light_directions.txt and ground-truth normals")
    mask = (load_mask(cap) > 0) & (np.linalg.norm(normals, axis=-1) > 0.5)
    ys, xs = np.nonzero(mask)
    pick = np.random.default_rng(0).choice(ys.size, min(pixels, ys.size), replace=False)
    ys, xs = ys[pick], xs[pick]
    grey = np.stack([to_rgb(read_image(p)[0])[ys, xs].mean(-1) for p in cap.image_paths])  # [N, P]
    listed = np.asarray(cap.lights, np.float64)
    ints = np.asarray(cap.intensities, np.float64).reshape(len(listed), -1).mean(1)
    r = refine_lights(grey, normals[ys, xs], listed, ints, {**(fit or {}), "gate": (10.0, 20.0), "max_change": 90.0})
    fit = r.directions.astype(np.float64)
    ang = np.degrees(np.arccos(np.clip((fit * listed).sum(1), -1, 1)))
    dz = np.degrees(np.arccos(np.clip(fit[:, 2], -1, 1)) - np.arccos(np.clip(listed[:, 2], -1, 1)))
    u, _, vt = np.linalg.svd(listed.T @ fit)  # Kabsch: the rotation listed -> fitted
    rot = vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
    return {"object": cap.name, "path": str(path), "n_images": len(listed), "q": round(r.quality, 4),
            "mean_angle": round(float(ang.mean()), 3), "zenith_change": round(float(dz.mean()), 3),
            "zenith_change_sd": round(float(dz.std()), 3),
            "off_zenith": round(float(np.sqrt(np.maximum(ang ** 2 - dz ** 2, 0)).mean()), 3),
            "rotation": round(float(np.degrees(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1)))), 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("objects", nargs="+")
    ap.add_argument("--pixels", type=int, default=20000)
    ap.add_argument("--json", default=None)
    ap.add_argument("--trim", type=float, nargs=2, default=None)
    ap.add_argument("--margin", type=float, default=None)
    ap.add_argument("--falloff", choices=FALLOFFS, default=None)
    ap.add_argument("--iters", type=int, default=None)
    args = ap.parse_args()
    fit = {k: getattr(args, k) for k in ("trim", "margin", "falloff", "iters") if getattr(args, k) is not None}
    rows = []
    print(f"{'object':26s} {'q':>6s} {'angle':>6s} {'zenith':>7s} {'sd':>5s} {'other':>6s} {'rot':>5s}")
    for path in args.objects:
        m = measure(path, args.pixels, fit)
        rows.append(m)
        print(f"{m['object']:26s} {m['q']:6.3f} {m['mean_angle']:6.2f} {m['zenith_change']:+7.2f} "
              f"{m['zenith_change_sd']:5.2f} {m['off_zenith']:6.2f} {m['rotation']:5.2f}")
    gated_in = [m["mean_angle"] for m in rows if m["q"] < DEFAULT_REFINE["gate"][1]]
    if gated_in:
        print(f"mean angle over the {len(gated_in)} objects with q < {DEFAULT_REFINE['gate'][1]}: "
              f"{np.mean(gated_in):.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
