"""A mask wider than the object: LCNet and the light fit on the mask as given or snapped (run by hand)

    python benchmarks/mask_snap.py .cache/syntest_dl .cache/syntest_exposure [--dev ../shared/data/diligent/pmsData_crop]
    python benchmarks/mask_snap.py .cache/syntest_dl --scenes texture:0.25 [--variants snapped]

Each synthetic object (``psctl synth --preset syntest``: syntest_dl, 96 DiLiGenT-like lights;
syntest_exposure, ``--size 128 --lights 64 --seed 3``) is put before a Lambertian background lit
by the same lights plus noise (``benchmarks/auto_mask_lights.py``'s ``scene``), ``--scenes``:
"plane:ALBEDO", a plane facing the camera (0.01 dark, 0.3 lit), or "texture:GAP", a smooth random
albedo in [0.05, 0.6] on which the object casts shadows (a plane GAP times its half-width below
it). Its true mask is grown by 0, 3 and 8 px (a mask drawn around the object), and
``psctl.estimate_lights`` (its defaults: LCNet, 8 views, refinement) runs on the images as
captured with that mask as given (``psctl.masks.snap_mask`` made the identity for the call) and
snapped (as estimate_lights does since session 69; before a lit background since session 70).
Prints the mean light direction error (degrees) per set, scene, growth and variant, with the
snapped mask's overlap with the true one, then one JSON line. ``--dev``: the same on the
DiLiGenT dev split's images as captured with their masks (no background added), reported only;
``--dev-lit``: with their background (outside the true mask) replaced by a Lambertian plane facing
the camera, lit by the capture's own lights and intensities, its albedo set so that its median
is half the object's (``lit_dev``; no shadows or light from the object on it), reported only;
``--dev-objects``: some of them.

The rule, written before the first run (session 69): snapping is adopted if, on each synthetic
set before the dark plane, the mean error with the true masks (0 px) is at most 0.05 above the
mask as given and with masks grown by 3 and by 8 px below it; and before the lit plane at most
0.05 above the mask as given at every growth. The dev split does not decide.

Session 70's rule, written before its first run, for snapping by shading before a lit background
(``psctl.masks.shading_snap``, where the brightness test cannot tell): adopted if, on syntest_dl
before the texture with the object's shadows (texture:0.25) and on both sets before the lit plane
(plane:0.3), the mean error with the true masks is at most 0.05 above the mask as given, and with
masks grown by 3 and by 8 px at least 1 degree below it; the lit plane's "given" numbers are
session 69's (the same inputs; nothing but the snap changed), so only "snapped" runs there. Before
the dark plane (both sets) and on the dev split the snapped masks must be session 69's pixel for
pixel (checked apart, against its code: the lights are then the same), so no lights run there.
First run (eee90d1): the rule failed on one cell, syntest_exposure before the lit plane with the
true masks, 6.448 -> 6.526 (the four dragons' exact masks lost 2.7-5.9%: hollows that shade as
the table does); every other cell held (docs/uncalibrated.md).

Session 70's second rule, written before its run, for the guarded shading snap (a review's
findings and the first run's failure: it leaves pixels out only where they hold at least half of
the mask's edge and their albedo is within 1.5 of the surroundings', keeps at least a quarter of
the mask and the mask's cells on the frame's edge): on sets the first run did not use,
syntest_dl64 before the lit plane (plane:0.3) and syntest_exposure before the texture with the
object's shadows (texture:0.25), adopted if the mean error with the true masks is at most 0.05
above the mask as given, and with masks grown by 3 and by 8 px at least 1 degree below it.

Session 71's rule, written before its lights ran, for the shading snap's "surroundings unlike"
guard (the mask as given where over half of the cells around it are unlike their own median: no
one background). Scenes with a lit background that is not one plane under distant lights:
near:500, near:1000, near:2000 (a plane of albedo 0.3 under point lights that far, in pixels,
from the object's centroid) and cylinder:15, cylinder:25, cylinder:40 (a backdrop whose normal
turns by that many degrees either side across the frame), on syntest_dl and syntest_dl64, masks
grown by 0, 3 and 8 px. ``--masks-only`` first finds the cells where the snap without the guard
("unguarded") gives another mask (it measures no lights). The guard is dropped if, over those
cells, the unguarded mean light error is below the guarded ("snapped") one and no cell is worse by
over 0.25 degrees; else it stays. Where no cell differs it stays, and a test holds what it does.
Run (2026-12-01): 31 cells differ (cylinder:15 and near:1000 only, no true mask), 21.13 -> 6.51
degrees, every cell better (by 2.90 to 23.99): the rule held and the guard was dropped (739203a);
a review then found a flat face (a coin's, before a curved backdrop) that the snap without it cut
away, which none of these sets has, and the guard is back (docs/uncalibrated.md).
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from auto_mask_lights import scene  # noqa: E402

GROW = (0, 3, 8)


def errors(images: np.ndarray, lights: np.ndarray, mask: np.ndarray, variants: tuple[str, ...],
           masks_only: bool = False, differing: bool = False) -> dict:
    """{growth: {variant: error, "iou"}}: light errors of the mask grown, as given, snapped and
    snapped without the "surroundings unlike" guard ("unguarded": run only where its mask is not
    the snapped one's; else the snapped error). ``masks_only``: no lights, only "differs" (whether
    the unguarded mask is not the snapped one) and the two masks' pixels off the true mask.
    ``differing``: lights only where the unguarded mask differs (NaN elsewhere)."""
    from scipy import ndimage

    import psctl
    import psctl.masks
    from psctl.metrics import light_direction_error

    snap, shading = psctl.masks.snap_mask, psctl.masks.shading_snap
    loose = unguarded_snap() if "unguarded" in variants or masks_only or differing else None
    out = {}
    for g in GROW:
        grown = ndimage.binary_dilation(mask, iterations=g) if g else mask
        snapped = psctl.masks.array_snap(images, grown)[0]
        row = {}
        if loose is not None:
            psctl.masks.shading_snap = loose
            try:
                other = psctl.masks.array_snap(images, grown)[0]
            finally:
                psctl.masks.shading_snap = shading
            row["differs"] = float(not np.array_equal(other, snapped))
            row["off_snapped"], row["off_unguarded"] = float((snapped ^ mask).sum()), float((other ^ mask).sum())
        for label in () if masks_only else variants:
            if label == "unguarded" and not row["differs"]:
                row[label] = row.get("snapped", float("nan"))
                continue
            if differing and not row["differs"]:
                row[label] = float("nan")  # (left out of the means)
                continue
            # estimate_lights snaps the mask itself; "given": with snap_mask made the identity
            psctl.masks.snap_mask = (lambda edge, m: (np.asarray(m, bool), None)) if label == "given" else snap
            psctl.masks.shading_snap = loose if label == "unguarded" else shading
            try:
                d, _ = psctl.estimate_lights(images, grown, device="cpu")
            finally:
                psctl.masks.snap_mask, psctl.masks.shading_snap = snap, shading
            row[label] = float(light_direction_error(d, lights).mean())
        row["iou"] = float((snapped & mask).sum() / (snapped | mask).sum())
        out[g] = row
    return out


def lit_dev(cap, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """A dev-split object before a lit plane: images [N, H, W, 3] as captured with the pixels
    outside its mask replaced by a Lambertian plane facing the camera under the capture's lights
    (directions and intensities) plus |N(0, 0.002)| noise; its mask; the plane's albedo."""
    from psctl.io.capture import load_images, load_mask

    images, mask = load_images(cap, as_captured=True), load_mask(cap)
    shade = np.clip(cap.lights[:, 2], 0, None)[:, None] * cap.intensities  # [N, 3]
    albedo = 0.5 * float(np.median(images[:, mask])) / float(np.median(shade))
    back = albedo * shade[:, None, None, :] + np.abs(rng.normal(0, 0.002, images.shape))
    images[:, ~mask] = back.astype(np.float32)[:, ~mask]
    return images, mask, albedo


def cylinder(cap, span: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The synthetic object of ``cap`` before a curved backdrop: a Lambertian cylinder (albedo 0.3)
    whose normal turns about the vertical axis from -``span`` to +``span`` degrees across the frame,
    lit by the same lights, plus |N(0, 0.002)| noise: images [N, H, W, 3], lights [N, 3], mask."""
    from psctl.io.capture import load_images, load_mask

    images, lights, mask = load_images(cap, as_captured=True), cap.lights, load_mask(cap)
    w = mask.shape[1]
    a = np.deg2rad(((np.arange(w) + 0.5) / w * 2 - 1) * span)
    normal = np.stack([np.sin(a), np.zeros_like(a), np.cos(a)], -1)  # [W, 3], the same down each column
    shade = 0.3 * np.clip(lights @ normal.T, 0, None)[:, None, :].repeat(mask.shape[0], 1)  # [N, H, W]
    back = shade[..., None] + np.abs(rng.normal(0, 0.002, images.shape))
    images[:, ~mask] = back.astype(np.float32)[:, ~mask]
    return images, lights, mask


def unguarded_snap():
    """psctl.masks.shading_snap as if the cells around the mask always agreed on one background:
    the shading snap without its "surroundings unlike" guard, for session 71's rule (snap_mask
    takes the cut it returns)."""
    import psctl.masks

    cut = psctl.masks.shading_snap
    return lambda edge, mask: (cut(edge, mask)[0], True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", type=Path, nargs="*", help="psctl synth --preset syntest folders")
    ap.add_argument("--scenes", default="plane:0.01,plane:0.3",
                    help="comma-separated plane:ALBEDO, texture:GAP, near:DISTANCE (px) or cylinder:SPAN (degrees)")
    ap.add_argument("--variants", default="given,snapped", help="given, snapped, unguarded (comma-separated)")
    ap.add_argument("--masks-only", action="store_true", help="no lights: where the unguarded snap differs")
    ap.add_argument("--differing", action="store_true", help="lights only where the unguarded snap differs")
    ap.add_argument("--dev", type=Path, help="the DiLiGenT dev split (reported only)")
    ap.add_argument("--dev-lit", action="store_true", help="--dev before a lit plane (lit_dev)")
    ap.add_argument("--dev-objects", help="comma-separated names: only these of --dev")
    args = ap.parse_args()

    from psctl.io.capture import find_objects, load_images, load_mask, open_capture

    warnings.simplefilter("ignore")  # the notes, once per run
    variants = tuple(args.variants.split(","))
    keys = (*(() if args.masks_only else variants), "iou", *(("differs",) if args.masks_only or "unguarded" in variants else ()))
    summary = {}
    for root in args.roots:
        for sc in args.scenes.split(","):
            kind, value = sc.split(":")
            rng = np.random.default_rng(0)
            rows = []
            for name in (root / "objects.txt").read_text().split():
                if kind == "plane":
                    images, lights, mask = scene(open_capture(root / name), "plane", float(value), None, None, rng)
                elif kind == "near":
                    images, lights, mask = scene(open_capture(root / name), "plane", 0.3, None, float(value), rng)
                elif kind == "cylinder":
                    images, lights, mask = cylinder(open_capture(root / name), float(value), rng)
                else:
                    images, lights, mask = scene(open_capture(root / name), "texture", 0.0, float(value), None, rng)
                rows.append(errors(images, lights, mask, variants, args.masks_only, args.differing))
                print(name, sc, json.dumps({g: {k: round(v, 3) for k, v in r.items()} for g, r in rows[-1].items()}),
                      flush=True)
            key = f"{root.name} {sc}"
            summary[key] = {f"{g}px {v}": round(float(np.nanmean([r[g][v] for r in rows])), 3)
                            for g in GROW for v in keys if not np.isnan([r[g][v] for r in rows]).all()}
            print(key, json.dumps(summary[key]), flush=True)
    if args.dev is not None:
        rows = []
        rng = np.random.default_rng(0)
        for folder in find_objects(args.dev):
            cap = open_capture(folder)
            if args.dev_objects and cap.name not in args.dev_objects.split(","):
                continue
            if args.dev_lit:
                images, mask, albedo = lit_dev(cap, rng)
                print(cap.name, "plane albedo", round(albedo, 4), flush=True)
            else:
                images, mask = load_images(cap, as_captured=True), load_mask(cap)
            rows.append(errors(images, cap.lights, mask, variants, args.masks_only, args.differing))
            print(cap.name, json.dumps({g: {k: round(v, 3) for k, v in r.items()} for g, r in rows[-1].items()}), flush=True)
        summary["dev"] = {f"{g}px {v}": round(float(np.mean([r[g][v] for r in rows])), 3) for g in GROW for v in keys}
        print("dev", json.dumps(summary["dev"]), flush=True)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
