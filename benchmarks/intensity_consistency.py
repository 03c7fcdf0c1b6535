"""How well each capture's images agree with its light_intensities.txt (run by hand; a diagnostic).

    python benchmarks/intensity_consistency.py OBJ [OBJ ...] [--dark 0.02] [--json FILE]
        [--write-fitted DIR]

A reference for intensity estimates made from the images: with the ground-truth normals and
light directions, a robust Lambertian fit of one intensity per image (grey) and one albedo per
pixel, alternated (each the median of observed / predicted over the lit, unsaturated pixels or
images), scored with the metric `psctl lights` reports (scale-invariant RE,
psctl.lights.intensity_error). A light_intensities.txt that the images agree with gives a small
RE; a large one means the file and the images disagree (or the surface is far from Lambertian
where it is lit). It is a reference, not a lower bound: an estimator that does not assume a
Lambertian surface can score lower (psctl's sdps does on bear and pot2). `--write-fitted DIR` writes, for each object, DIR/<name>PNG: links to its
files with light_intensities.txt replaced by the listed ones times the fit's per-image ratio
(an oracle: it used the ground-truth normals), to see what the fit's intensities would do to a
calibrated method (`psctl eval --benchmark folder --root DIR`). Also printed: the first 20 images' mean ratio of fitted to listed intensity
over the other images' (on DiLiGenT's bear the first 20 stand out).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from psctl.io.capture import load_ground_truth, load_mask, open_capture
from psctl.io.images import read_image, to_rgb
from psctl.lights import intensity_error


def fit_intensities(obs: np.ndarray, shading: np.ndarray, min_shading: float = 0.3, dark: float = 0.02,
                    bright: float = 0.98, rounds: int = 10) -> np.ndarray:
    """Per-image intensities [N] (mean 1) from grey observations and n.l, both [N, P]."""
    ok = (shading > min_shading) & (obs > dark) & (obs < bright)
    ratio = np.where(ok, obs / np.maximum(shading, 1e-3), np.nan)  # e_i * albedo_p where usable
    e = np.ones(len(obs))
    for _ in range(rounds):
        albedo = np.nanmedian(ratio / e[:, None], 0)
        e = np.nanmedian(ratio / albedo[None], 1)
        e = e / np.nanmean(e)
    return e


def measure(path: str, dark: float = 0.02, write_fitted: Path | None = None) -> dict:
    cap = open_capture(path)
    normals = load_ground_truth(cap)
    if not cap.calibrated or normals is None:
        raise SystemExit(f"{path}: needs light_directions.txt and ground-truth normals")
    mask = load_mask(cap) > 0
    # the raw images: psctl's readers divide by the listed intensities, which is what is tested
    grey = np.stack([to_rgb(read_image(p)[0])[mask].mean(-1) for p in cap.image_paths])  # [N, P]
    shading = cap.lights @ normals[mask].T  # [N, P]
    e = fit_intensities(grey, shading, dark=dark)
    listed = np.asarray(cap.intensities, np.float64).reshape(len(e), -1)
    ratio = e / (listed.mean(1) / listed.mean())
    if write_fitted is not None:
        out = write_fitted / f"{cap.name}PNG"
        out.mkdir(parents=True, exist_ok=True)
        src = Path(path).resolve()
        for f in src.iterdir():
            if f.name != "light_intensities.txt" and not (out / f.name).exists():
                (out / f.name).symlink_to(f)
        np.savetxt(out / "light_intensities.txt", listed * (ratio / ratio.mean())[:, None], fmt="%.6f")
    return {"object": cap.name, "n_images": len(e), "intensity_re": intensity_error(e, listed),
            "first20_over_rest": float(ratio[:20].mean() / ratio[20:].mean())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("objects", nargs="+", help="capture folders with lights, intensities and normals")
    ap.add_argument("--dark", type=float, default=0.02, help="observations below this are left out (shadow)")
    ap.add_argument("--json", type=Path, help="also write the results here")
    ap.add_argument("--write-fitted", type=Path, help="write copies of the captures with the fit's intensities here")
    args = ap.parse_args()
    rows = [measure(o, args.dark, args.write_fitted) for o in args.objects]
    print("| object | images | RE of the ground-truth-normal fit | first 20 / rest |")
    print("|---|---:|---:|---:|")
    for r in rows:
        print(f"| {r['object']} | {r['n_images']} | {r['intensity_re']:.3f} | {r['first20_over_rest']:.3f} |")
    print(f"| mean | | {np.mean([r['intensity_re'] for r in rows]):.3f} | |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
