"""How close psctl's albedo (psctl.albedo) comes to the diffuse albedo a renderer used (run by hand).

    python benchmarks/albedo.py [--objects 16] [--seed 7] [--size 128] [--lights 96] [--methods gt,l2,ensemble]

Renders psctl synth's blobby objects (random MERL or GGX materials, some blended or textured,
cast shadows by depth marching) under DiLiGenT-like lights, exposes them as ``psctl synth``
does (the 99.5th percentile of the object's values at 0.9, brighter values saturate) and
quantises them to 16 bits. The true albedo is the renderer's diffuse term kd / pi per pixel,
times the exposure (what image / (n . l) gives on a Lambertian surface). For each object and
each source of normals (``gt``: the renderer's; or a psctl method's estimate from the images)
three estimates are scored:

- median: ``psctl.albedo`` (the median of image / (n . l) over well-lit images);
- least squares: sum(m s) / sum(s^2) over the images with s = n . l > 0 (the same normals);
- l2 |b|: the length of the per-channel least-squares solution b = (L^T L)^-1 L^T m (classic
  photometric stereo's albedo, which needs no normals).

Score: the relative error of the grey (channel-mean) albedo, |est - true| / true, over object
pixels whose true grey albedo is at least 2 % of the object's brightest (metallic, kd ~ 0
pixels have no diffuse albedo to find); the median over each object's pixels, then the mean and
the median over objects. Prints one line per object and a summary.
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch


def ls_albedo(images: np.ndarray, shading: np.ndarray) -> np.ndarray:
    """[N, P, 3], [N, P] -> [P, 3]: least squares over lit images."""
    s = np.clip(shading, 0, None)[..., None]
    return (images * s).sum(0) / np.maximum((s * s).sum(0), 1e-12)


def l2_albedo(images: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """[N, P, 3], [N, 3] -> [P, 3]: |b| of the per-channel least-squares normal."""
    pinv = np.linalg.pinv(lights)  # [3, N]
    b = np.einsum("kn,npc->pck", pinv, images)  # [P, 3 channels, 3 components]
    return np.linalg.norm(b, axis=-1)


def score(est: np.ndarray, true: np.ndarray) -> float:
    g_est, g_true = est.mean(-1), true.mean(-1)
    ok = (g_true >= 0.02 * g_true.max()) & (g_true > 0)
    return float(np.median(np.abs(g_est[ok] - g_true[ok]) / g_true[ok]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--objects", type=int, default=16)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--lights", type=int, default=96)
    ap.add_argument("--methods", default="gt,l2,ensemble", help="normals: gt and/or psctl methods")
    args = ap.parse_args()

    from psctl.albedo import estimate_albedo
    from psctl.api import estimate_normals
    from psctl.synth.write import diffuse_albedo, exposure_scale, preset_objects, render_object

    torch.set_grad_enabled(False)
    objs = preset_objects("blobby", seed=args.seed, size=args.size, n_lights=args.lights, k=args.objects,
                          light_dist="diligent")
    methods = args.methods.split(",")
    rows: dict[str, list[tuple[float, float, float]]] = {m: [] for m in methods}
    for obj in objs:
        imgs = render_object(obj)  # [N, 3, H, W]
        mask_t = obj.view.mask[0, 0]
        scale = exposure_scale(imgs, mask_t)
        imgs = torch.round((imgs * scale).clamp(0, 1) * 65535) / 65535
        mask = mask_t.numpy()
        h, w = mask.shape
        images = imgs.permute(0, 2, 3, 1).numpy().astype(np.float32)  # [N, H, W, 3]
        true = (diffuse_albedo(obj).reshape(3, h, w).permute(1, 2, 0).numpy() / math.pi * scale)[mask]
        lights = obj.lights.numpy().astype(np.float32)
        gt = obj.view.normals[0].permute(1, 2, 0).numpy().astype(np.float32)
        line = [obj.name, obj.meta.get("material", "")[:28]]
        if true.mean(-1).max() <= 1e-4:  # a metal: no diffuse albedo to find
            print(" | ".join(line + ["no diffuse albedo, skipped"]), flush=True)
            continue
        l2b = l2_albedo(images[:, mask], lights)
        for m in methods:
            n = gt if m == "gt" else estimate_normals(images, lights, mask, method=m, device="cpu")
            med = estimate_albedo(images, lights, n, mask)[mask]
            ls = ls_albedo(images[:, mask], np.einsum("pc,nc->np", n[mask], lights))
            r = (score(med, true), score(ls, true), score(l2b, true))
            rows[m].append(r)
            line.append(f"{m}: median {r[0]:.3f} ls {r[1]:.3f} l2|b| {r[2]:.3f}")
        print(" | ".join(line), flush=True)
    for m in methods:
        a = np.array(rows[m])
        print(f"{m} normals, {len(a)} objects: median relative error of the grey albedo, mean (median) over objects: "
              f"median {a[:, 0].mean():.3f} ({np.median(a[:, 0]):.3f}), least squares {a[:, 1].mean():.3f} "
              f"({np.median(a[:, 1]):.3f}), l2 |b| {a[:, 2].mean():.3f} ({np.median(a[:, 2]):.3f}); median best on "
              f"{int((a[:, 0] < a[:, 1]).sum())} objects vs least squares")


if __name__ == "__main__":
    main()
