"""Make examples/bumpy_sphere/: a small synthetic capture folder to try psctl on.

A sphere with smooth bumps and dents, a two-tone albedo, Lambertian + Blinn-Phong specular
reflectance with attached shadows (no cast shadows), 24 lights spread like DiLiGenT's (within
about 50 degrees of the view direction), coloured per-light intensities, 16-bit PNG images,
mask.png and Normal_gt.mat / Normal_gt.png. Deterministic: running it again writes the same pixels
(on another CPU the ground truth's float64 values may differ in their last bits, about 1e-15). The
files' bytes need not match the committed ones: PNG and .mat compression depends on the zlib and
OpenImageIO builds (session 61's regeneration: every PNG pixel-identical, the bytes not).

    python examples/make_example.py [--out examples/bumpy_sphere] [--size 128]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import scipy.io

from psctl.io.images import write_image


def height_field(size: int, ss: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Height z(x, y) of a bumpy sphere on a supersampled grid; returns (z, mask) at size*ss."""
    n = size * ss
    c = (np.arange(n) + 0.5) / n * 2 - 1
    x, y = np.meshgrid(c, -c)  # y up: row 0 is the top
    r2 = x**2 + y**2
    radius = 0.92
    mask = r2 < radius**2
    z = np.sqrt(np.clip(radius**2 - r2, 0, None))
    rng = np.random.default_rng(7)
    for _ in range(9):  # bumps (+) and dents (-), fading to zero at the rim
        cx, cy = rng.uniform(-0.5, 0.5, 2)
        s = rng.uniform(0.08, 0.18)
        a = rng.choice([-1, 1]) * rng.uniform(0.04, 0.08)
        z = z + a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s**2)) * np.clip(1 - r2 / radius**2, 0, 1)
    return z, mask


def normals_from_height(z: np.ndarray, step: float) -> np.ndarray:
    dz_dy_rows, dz_dx = np.gradient(z, step)
    dz_dy = -dz_dy_rows  # rows go down, y goes up
    n = np.stack([-dz_dx, -dz_dy, np.ones_like(z)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def make(out: Path, size: int = 128, n_lights: int = 24, ss: int = 4) -> None:
    z, mask_ss = height_field(size, ss)
    n_ss = normals_from_height(z, 2.0 / (size * ss))
    rng = np.random.default_rng(11)
    # lights: a jittered spiral inside a 50-degree cone around the view direction
    k = np.arange(n_lights)
    theta = np.radians(50) * np.sqrt((k + 0.5) / n_lights)
    phi = k * np.pi * (3 - np.sqrt(5)) + rng.uniform(-0.2, 0.2, n_lights)
    lights = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    intensities = rng.uniform(0.7, 1.3, (n_lights, 1)) * rng.uniform(0.85, 1.15, (n_lights, 3))
    # two-tone albedo: warm left half blending to a cool right half
    xs = np.linspace(-1, 1, size * ss)[None, :].repeat(size * ss, 0)
    t = 1 / (1 + np.exp(-xs / 0.15))
    albedo = (1 - t)[..., None] * np.array([0.75, 0.55, 0.35]) + t[..., None] * np.array([0.35, 0.5, 0.7])
    view = np.array([0.0, 0.0, 1.0])

    def pool(a: np.ndarray) -> np.ndarray:  # ss x ss box filter: anti-aliasing at the rim
        h = a.shape[0] // ss
        return a.reshape(h, ss, h, ss, *a.shape[2:]).mean(axis=(1, 3))

    out.mkdir(parents=True, exist_ok=True)
    names = []
    peak = 0.0
    imgs = []
    for li, e in zip(lights, intensities):
        ndl = np.clip(n_ss @ li, 0, None)
        h = (li + view) / np.linalg.norm(li + view)
        spec = 0.35 * np.clip(n_ss @ h, 0, None) ** 40 * (ndl > 0)
        img = (albedo * ndl[..., None] + spec[..., None]) * e * mask_ss[..., None]
        imgs.append(pool(img))
        peak = max(peak, float(imgs[-1].max()))
    scale = 0.95 / peak  # expose so the brightest pixel is just below white
    for i, img in enumerate(imgs):
        name = f"{i + 1:03d}.png"
        write_image(out / name, img * scale, "uint16", kind="linear")  # PNG gAMA 1: linear radiance, not sRGB
        names.append(name)
    mask = pool(mask_ss.astype(np.float64)) > 0.999  # pixels fully inside the object
    normals = pool(n_ss)
    normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    normals[~mask] = 0
    (out / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(out / "light_directions.txt", lights, fmt="%.6f")
    # images were scaled by `scale`, so the intensities psctl divides by include it
    np.savetxt(out / "light_intensities.txt", intensities * scale, fmt="%.6f")
    write_image(out / "mask.png", mask.astype(np.float32), "uint8", kind="data")
    scipy.io.savemat(out / "Normal_gt.mat", {"Normal_gt": normals}, do_compression=True)
    # the MAT header's 116 bytes of text carry the time of writing: a fixed text keeps the file
    # the same from run to run (what the docstring promises)
    mat = (out / "Normal_gt.mat").read_bytes()
    (out / "Normal_gt.mat").write_bytes(b"MATLAB 5.0 MAT-file, written by psctl examples/make_example.py".ljust(116) + mat[116:])
    write_image(out / "Normal_gt.png", np.where(mask[..., None], (normals + 1) / 2, 0), "uint16", kind="data")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "bumpy_sphere")
    ap.add_argument("--size", type=int, default=128)
    args = ap.parse_args()
    make(args.out, args.size)
    print(f"wrote {args.out}")
