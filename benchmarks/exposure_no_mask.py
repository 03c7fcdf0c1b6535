"""Without a mask, where should PS-FCN's exposure scale come from? (run by hand)

    psctl synth .cache/syntest_exposure --preset syntest --size 128 --lights 64 -k 4 --seed 3 -q
    python benchmarks/exposure_no_mask.py .cache/syntest_exposure [--levels 0 0.01 0.03] [--no-net] [--lights]

PS-FCN (no +N) scales every capture by one factor so that the images' mean over the object is the
mean it was trained at (``psctl.infer.run_network``). Without a mask the object is unknown. This
script puts each synthetic object in front of a dark Lambertian background facing the camera
(albedo ``level``, lit by the same lights, plus |N(0, 0.002)| sensor noise), and reports, per
level, the ratio of each rule's mean to the mean over the true mask (1 is right):

- frame: the whole frame (psctl before 2026-11-30);
- fraction F: pixels whose mean is above F x the 99th percentile of the pixels' means;
- lit: ``psctl.infer.lit_pixels`` (Otsu's threshold on log brightness), psctl's rule now.

Unless --no-net, it also runs the installed PS-FCN on each object with the mask (MAE over the
mask), without it by the lit rule, and without it by the frame rule (``lit_pixels`` replaced by
all-True, which is the old code path exactly), and prints the mean MAE of each (degrees).
With --lights, ``psctl.estimate_lights`` (LCNet, the light refinement with the installed PS-FCN;
the defaults) without the mask by each rule too, and with the mask: mean light direction error.
Prints one JSON object.

Session 62 (2026-12-01, the 2-core AVX2 EPYC VM; the folder made as above): ratio to the mask's
mean at levels 0 / 0.01 / 0.03, frame 0.445 / 0.464 / 0.501, lit 1.009 / 1.023 / 1.053 (worst
1.269); PS-FCN 4.70 with the mask, without it 4.73 / 5.06 / 5.37 by the lit rule, 6.60 / 6.82 /
6.97 by the frame's. --lights at level 0.01: 6.45 degrees with the mask, 33.02 without it by the
lit rule, 33.10 by the frame's (without a mask LCNet and the refinement fail on these objects
whatever the exposure; the no-mask note says so).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from unittest import mock

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from psctl.infer import lit_pixels  # noqa: E402


def rules(images: np.ndarray) -> dict[str, float]:
    """[N, H, W, 3] -> each rule's mean brightness."""
    pixel_mean = images.mean((0, 3))
    out = {"frame": float(images.mean())}
    for f in (0.05, 0.1, 0.2):
        out[f"fraction {f}"] = float(images[:, pixel_mean > f * np.percentile(pixel_mean, 99)].mean())
    out["lit"] = float(images[:, lit_pixels(images.sum((0, 3)))].mean())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="a psctl synth --preset syntest folder")
    ap.add_argument("--levels", type=float, nargs="+", default=[0.0, 0.01, 0.03])
    ap.add_argument("--no-net", action="store_true", help="exposure ratios only")
    ap.add_argument("--lights", action="store_true", help="also psctl.estimate_lights' light error")
    args = ap.parse_args()

    import psctl
    from psctl.io.capture import load_ground_truth, load_images, load_mask, open_capture
    from psctl.metrics import angular_error, light_direction_error

    rng = np.random.default_rng(0)
    ratios: dict[float, dict[str, list[float]]] = {}
    maes: dict[float, dict[str, list[float]]] = {}
    objects = (args.root / "objects.txt").read_text().split()
    for name in objects:
        cap = open_capture(args.root / name)
        images, lights, mask, gt = load_images(cap), cap.lights, load_mask(cap), load_ground_truth(cap)
        truth = float(images[:, mask].mean())
        for level in args.levels:
            im = images.copy()
            back = level * np.clip(lights[:, 2], 0, None)[:, None, None, None] \
                + np.abs(rng.normal(0, 0.002, im.shape)).astype(np.float32)
            im[:, ~mask] = back[:, ~mask]
            r = ratios.setdefault(level, {})
            for rule, value in rules(im).items():
                r.setdefault(rule, []).append(value / truth)
            if args.no_net:
                continue
            m = maes.setdefault(level, {})
            runs = {"mask": lambda: psctl.estimate_normals(im, lights, mask, method="ps-fcn", device="cpu"),
                    "no mask, lit": lambda: psctl.estimate_normals(im, lights, None, method="ps-fcn", device="cpu")}
            for label, run in runs.items():
                m.setdefault(label, []).append(float(angular_error(run(), gt, mask).mean()))
            with mock.patch("psctl.infer.lit_pixels", lambda b: np.ones(b.shape, bool)):
                n = psctl.estimate_normals(im, lights, None, method="ps-fcn", device="cpu")
            m.setdefault("no mask, frame", []).append(float(angular_error(n, gt, mask).mean()))
            if args.lights:
                for label, mk in (("lights, mask", mask), ("lights, no mask, lit", None)):
                    d, _ = psctl.estimate_lights(im, mk, device="cpu")
                    m.setdefault(label, []).append(float(light_direction_error(d, lights).mean()))
                with mock.patch("psctl.infer.lit_pixels", lambda b: np.ones(b.shape, bool)):
                    d, _ = psctl.estimate_lights(im, None, device="cpu")
                m.setdefault("lights, no mask, frame", []).append(float(light_direction_error(d, lights).mean()))
        print(name, file=sys.stderr)
    out = {"root": str(args.root), "objects": len(objects), "ratio_to_mask_mean": {
        str(level): {rule: {"mean": round(float(np.mean(v)), 3), "min": round(float(np.min(v)), 3),
                            "max": round(float(np.max(v)), 3)} for rule, v in r.items()}
        for level, r in ratios.items()}}
    if maes:
        out["ps_fcn_mae"] = {str(level): {k: round(float(np.mean(v)), 2) for k, v in m.items()}
                             for level, m in maes.items()}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
