"""What lens distortion costs psctl calibrate --focal, and what psctl undistort gives back (run by hand).

    python benchmarks/undistort_calibrate.py

Renders benchmarks/calibrate_sphere.py's pinhole spheres (r = 100 px, f = 1000 px, 0 / 200 / 500
px off the principal point; a mirror and a Lambertian ball; 40 lights, 16 bits), then photographs
them through a lens: each photo pixel shows the pinhole image at the point OpenCV's model
(psctl.undistort.distort_points) sends there, found by fixed-point inversion and read bilinearly.
Per case it calibrates (config focal and principal, as ``psctl calibrate --focal F --principal
X,Y``) the pinhole images, the photos as they are, and the photos after psctl.undistort
(undistort_map + remap, as ``psctl undistort``), and prints the mean (largest) direction error
in degrees against the rendered lights.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from calibrate_sphere import lights, render_pinhole  # noqa: E402
from psctl.calibrate import calibrate_lights  # noqa: E402
from psctl.errors import PsctlError  # noqa: E402
from psctl.metrics import light_direction_error  # noqa: E402
from psctl.undistort import UndistortMap, check_distortion, distort_points, remap, undistort_map  # noqa: E402

LENSES = {"barrel k1 -0.1": [-0.1, 0.0, 0.0, 0.0], "pincushion k1 0.05": [0.05, 0.0, 0.0, 0.0],
          "k1 -0.2 k2 0.05 p 1e-3": [-0.2, 0.05, 0.001, -0.001]}


def photograph(imgs: np.ndarray, mask: np.ndarray, K: np.ndarray, coeffs: list[float]
               ) -> tuple[np.ndarray, np.ndarray]:
    """The pinhole images [N, H, W, 3] (uint16) and mask as a camera with lens ``coeffs`` records them."""
    c = check_distortion(coeffs)
    h, w = mask.shape
    f, cx, cy = K[0, 0], K[0, 2], K[1, 2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    xd, yd = (u - cx) / f, (v - cy) / f
    x, y = xd.copy(), yd.copy()
    for _ in range(50):  # x = (xd - tangential(x)) / radial(x), as OpenCV's undistortPoints iterates
        px, py, _ = distort_points(x, y, c)
        x, y = x + (xd - px), y + (yd - py)
    px, py, _ = distort_points(x, y, c)
    assert max(np.abs(px - xd).max(), np.abs(py - yd).max()) * f < 1e-4, "inversion did not converge"
    xs, ys = f * x + cx, f * y + cy
    m = UndistortMap(xs, ys, (xs >= 0) & (xs <= w - 1) & (ys >= 0) & (ys <= h - 1), 0, (h, w))
    photo = np.stack([np.round(remap(img.astype(np.float32), m)).astype(imgs.dtype) for img in imgs])
    return photo, (remap(mask.astype(np.float32), m) >= 0.5) & m.valid


def main() -> None:
    gen = torch.Generator().manual_seed(0)
    d, e = lights(40, gen)
    focal, size, r = 1000.0, 256, 100.0
    sums: dict[str, float] = {}
    for off in (0.0, 200.0, 500.0):
        for material, exposure, sphere in (("ggx0.02", 4.0, "chrome"), ("lambertian", 0.9, "matte")):
            imgs, mask, principal = render_pinhole(material, size, r, focal, off, d, e, 16, exposure, gen)
            K = np.array([[focal, 0, principal[0]], [0, focal, principal[1]], [0, 0, 1]])
            cfg = {"focal": focal, "principal": principal}
            angle = math.degrees(math.atan(math.hypot(off, off / 2) / focal))
            for lens, coeffs in LENSES.items():
                photo, pmask = photograph(imgs, mask, K, coeffs)
                m = undistort_map(K, coeffs, mask.shape)
                fixed = np.stack([np.round(remap(p.astype(np.float32), m)).astype(p.dtype) for p in photo])
                fmask = (remap(pmask.astype(np.float32), m) >= 0.5) & m.valid
                shift = float(np.hypot(m.x - np.arange(size), m.y - np.arange(size)[:, None])[mask].max())
                line = []
                for label, (im, mk) in (("pinhole", (imgs, mask)), ("photo", (photo, pmask)),
                                        ("undistorted", (fixed, fmask))):
                    try:
                        res = calibrate_lights(im, sphere, mask=mk, config=cfg)
                    except PsctlError as err:
                        line.append(f"{label} refused ({err.message.split(':')[0]})")
                        continue
                    err = light_direction_error(res.directions, d.numpy())
                    sums[label] = sums.get(label, 0.0) + float(err.mean())
                    line.append(f"{label} {err.mean():6.3f} ({err.max():6.3f})")
                print(f"off-axis {off:3.0f} px ({angle:4.1f} deg)  {material:10s} {sphere:6s} {lens:24s} "
                      f"sphere moved up to {shift:5.1f} px  " + "  ".join(line), flush=True)
    print("sums of the means: " + ", ".join(f"{k} {v:.2f}" for k, v in sums.items()))


if __name__ == "__main__":
    main()
