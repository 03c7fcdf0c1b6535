"""psctl.undistort against OpenCV (run by hand, in an environment that has both).

    pip install opencv-python-headless      # not a psctl dependency
    python benchmarks/undistort_opencv.py

For three lenses (a 5-coefficient barrel lens, a 4-coefficient pincushion lens, the 8-coefficient
rational model) compares psctl.undistort.undistort_map with cv2.initUndistortRectifyMap (new
camera matrix = K, float32 maps), and psctl.undistort.remap with cv2.remap (INTER_LINEAR,
BORDER_CONSTANT) on random values in [0, 1], over the pixels both call valid. Prints the largest
differences (pixels; values).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import cv2  # noqa: E402

from psctl.undistort import remap, undistort_map  # noqa: E402

CASES = [("barrel, 5", [[800, 0, 319.5], [0, 810, 241.0], [0, 0, 1]], [-0.28, 0.09, 0.0012, -0.0007, -0.015], (480, 640)),
         ("pincushion, 4", [[1200, 0, 300], [0, 1200, 260], [0, 0, 1]], [0.15, -0.02, 0, 0.002], (512, 612)),
         ("rational, 8", [[600, 0, 330], [0, 600, 230], [0, 0, 1]], [0.8, 0.2, 0.001, 0.001, 0.01, 1.1, 0.35, 0.02],
          (480, 640))]


def main() -> None:
    print(f"OpenCV {cv2.__version__}")
    img = np.random.default_rng(0).random((512, 640, 3)).astype(np.float32)
    for name, K, d, (h, w) in CASES:
        K = np.array(K, np.float64)
        mx, my = cv2.initUndistortRectifyMap(K, np.array(d), None, K, (w, h), cv2.CV_32FC1)
        m = undistort_map(K, d, (h, w))
        v = m.valid
        src = img[:h, :w]
        ours, theirs = remap(src, m), cv2.remap(src, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        inner = v & (m.x >= 0) & (m.x <= w - 1) & (m.y >= 0) & (m.y <= h - 1)  # cv2 fades the border's half pixel
        print(f"{name:14s} valid {v.mean():.4f}  map |dx| {np.abs(m.x - mx)[v].max():.2e} |dy| "
              f"{np.abs(m.y - my)[v].max():.2e} px  remap {np.abs(ours - theirs)[inner].max():.2e}")


if __name__ == "__main__":
    main()
