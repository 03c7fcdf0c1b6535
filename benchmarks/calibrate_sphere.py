"""Accuracy of psctl calibrate's sphere calibration on rendered spheres (run by hand).

    python benchmarks/calibrate_sphere.py [--quick] [--sweep] [--bits 8|16]
    python benchmarks/calibrate_sphere.py --centroids
    python benchmarks/calibrate_sphere.py --offsets      (matte balls with a black level: config offset)
    python benchmarks/calibrate_sphere.py --perspective [--focal-error]  (spheres off a pinhole camera's axis: --focal)

Renders spheres with psctl's own shading (psctl.synth.render.shade) under known lights and
compares psctl.calibrate.calibrate_lights' directions (and, matte, intensities) with them:

- chrome: GGX mirrors of roughness 0.01-0.05 and MERL's chrome (ABC fit), exposed so that the
  highlight saturates (peak 4x full scale) or not (0.8x), and a glossy plastic ball (diffuse
  0.8, GGX roughness 0.1: a highlight over diffuse shading, as DiLiGenT's ball);
- matte: Lambertian, Lambertian with a faint GGX sheen (specular 0.04, roughness 0.3), and the
  glossy ball.

Each image is rendered at 4 x 4 samples per pixel and averaged (a sensor integrates over its
pixels; point samples would miss a mirror's sub-pixel highlight), with sensor noise, clipped and
rounded to 16 or 8 bits. Spheres of radius 100 and 30 pixels; 40 lights within 60 degrees of
the view axis, intensities uniform in [0.5, 1.5]; the outline from the rendered mask. ``--sweep``
also runs the defaults' alternatives (chrome's highlight level and base percentile; matte's lit
and trim), which chose them (docs/calibration.md). ``--centroids``: the chrome cases and two
overexposed ones (GGX 0.05 at 40x, the glossy ball at 8x), r = 100 and 30, 16 bits, with each
of find_highlight's weightings (surface, the default; even; image), and their sums. Prints one
line per case: mean and largest direction error (degrees), intensity RE.
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from psctl.calibrate import DEFAULT_CALIBRATE, calibrate_lights
from psctl.errors import PsctlError
from psctl.lights import intensity_error
from psctl.metrics import light_direction_error
from psctl.synth.materials import ggx, lambertian, load_merl, merl_materials
from psctl.synth.render import sensor_noise, shade
from psctl.synth.shapes import sphere_gbuffer

SS = 4  # samples per pixel side


def lights(n: int, gen: torch.Generator, max_zenith: float = 60.0) -> tuple[torch.Tensor, torch.Tensor]:
    cos_lo = math.cos(math.radians(max_zenith))
    z = cos_lo + (1 - cos_lo) * torch.rand(n, generator=gen)
    phi = 2 * math.pi * torch.rand(n, generator=gen)
    s = (1 - z * z).sqrt()
    d = torch.stack([s * phi.cos(), s * phi.sin(), z], 1)
    e = 0.5 + torch.rand(n, generator=gen)
    return d, e


def render(material: str, size: int, radius_px: float, d: torch.Tensor, e: torch.Tensor, bits: int,
           exposure: float, gen: torch.Generator, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """[N, size, size, 3] images and the [size, size] mask of a sphere of radius_px pixels;
    ``offset`` (of full scale) is added to every pixel before quantizing (a black level)."""
    big = size * SS
    g = sphere_gbuffer(big, radius=2 * radius_px / size)
    n = g.normals.reshape(1, 3, -1)
    mat = material_of(material)
    out = []
    for k in range(len(d)):  # one light at a time: 4 x 4 supersampled views are large
        img = shade(n, d[None, k:k + 1], mat, intensities=e[None, k:k + 1])[0, 0]  # [3, P]
        img = img.reshape(3, size, SS, size, SS).mean((2, 4))
        out.append(img.permute(1, 2, 0))
    mask = g.mask.reshape(size, SS, size, SS).float().mean((1, 3)) >= 0.5
    return expose(torch.stack(out), mask, material, bits, exposure, gen, offset)


def material_of(material: str):
    one = torch.ones(1)
    if material.startswith("ggx"):  # a mirror: dark diffuse, white specular
        mat = ggx(torch.full((1, 3), 0.02), torch.ones(1, 3), torch.tensor([float(material[3:])]), metal=torch.ones(1))
    elif material == "merl-chrome":
        table = load_merl()
        mat = merl_materials(table, [table.index("chrome")])
    elif material == "glossy":  # a shiny plastic ball (DiLiGenT's ball is one): a highlight over diffuse shading
        mat = ggx(torch.full((1, 3), 0.8), torch.full((1, 3), 0.5), 0.1 * one, ior=1.5 * one)
    elif material == "lambertian":
        mat = lambertian(torch.full((1, 3), 0.8))
    elif material == "sheen":
        mat = ggx(torch.full((1, 3), 0.8), torch.full((1, 3), 0.04), 0.3 * one, ior=1.5 * one)
    else:
        raise ValueError(material)
    return mat


def expose(imgs: torch.Tensor, mask: torch.Tensor, material: str, bits: int, exposure: float,
           gen: torch.Generator, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Rendered [N, H, W, 3] radiance to integer images: exposed, sensor noise, quantized."""
    peak = float(imgs.amax()) if material in ("lambertian", "sheen") else float(imgs.flatten(1).amax(1).median())
    # (the glossy ball, too, exposed for its highlight, as a calibration would be: its diffuse part is
    # then a quarter of the highlight's height)
    imgs = sensor_noise(imgs * (exposure / max(peak, 1e-12)), gen) + offset
    q = float(2**bits - 1)
    imgs = torch.round(imgs.clamp(0, 1) * q).to(torch.int32).numpy()
    return imgs.astype(np.uint16 if bits == 16 else np.uint8), mask.numpy()


def render_pinhole(material: str, size: int, radius_px: float, focal: float, off_axis: float, d: torch.Tensor,
                   e: torch.Tensor, bits: int, exposure: float, gen: torch.Generator
                   ) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """render()'s sphere through a pinhole camera of ``focal`` pixels, its centre seen
    ``off_axis`` pixels right of and half as far above the principal point: a size x size crop
    around it (the principal point, returned, lies outside the crop when off_axis is large). Each
    pixel is shaded in a frame turned so that its own view is psctl's (0, 0, 1)."""
    from psctl.synth.shapes import sphere_pinhole

    at = np.array([off_axis, off_axis / 2])
    z = -focal / radius_px  # a unit sphere radius_px pixels across, nearly
    centre = (at[0] / focal * -z, at[1] / focal * -z, z)
    principal = ((size - 1) / 2 - at[0], (size - 1) / 2 + at[1])  # so that the sphere lies in the crop's middle
    big = size * SS
    n, v, m = sphere_pinhole(big, big, focal * SS, centre,
                             principal=((principal[0] + 0.5) * SS - 0.5, (principal[1] + 0.5) * SS - 0.5))
    n, v = n.reshape(3, -1).float(), v.reshape(3, -1).float()
    # the rotation taking v to z about k = v x z (Rodrigues): R x = c x + s (k x x) + (k . x)(1 - c) k
    c = v[2]
    k = torch.stack([v[1], -v[0], torch.zeros_like(c)])
    s = k.norm(dim=0)
    k = k / s.clamp_min(1e-12)

    def turn(x: torch.Tensor) -> torch.Tensor:  # [3, P] (or [3] for all pixels) -> [3, P]
        x = x.reshape(3, -1).expand(3, n.shape[1]) if x.dim() == 1 else x
        return c * x + s * torch.cross(k, x, dim=0) + (k * x).sum(0) * (1 - c) * k

    nt = turn(n) * m.reshape(1, -1)
    mat = material_of(material)
    out = []
    for j in range(len(d)):
        img = shade(nt[None], turn(d[j])[None, None], mat, intensities=e[None, j:j + 1])[0, 0]
        out.append(img.reshape(3, size, SS, size, SS).mean((2, 4)).permute(1, 2, 0))
    mask = m.reshape(size, SS, size, SS).float().mean((1, 3)) >= 0.5
    imgs, mask = expose(torch.stack(out), mask, material, bits, exposure, gen)
    return imgs, mask, principal


def perspective(d: torch.Tensor, e: torch.Tensor, gen: torch.Generator, focal_error: bool = False) -> None:
    """Spheres off the optical axis of a pinhole camera: the orthographic model and --focal
    (``focal_error``: eight of the cases, r = 100, off the axis, the mirror and the Lambertian ball,
    with the focal length given 10 % short and long)."""
    total: dict[str, float] = {}
    cases = [(f, off, size, r, m) for f in (1000.0, 3000.0) for off in (0.0, 200.0, 500.0)
             for size, r in [(256, 100.0), (96, 30.0)]
             for m in [("ggx0.02", 4.0, "chrome"), ("glossy", 1.0, "chrome"), ("lambertian", 0.9, "matte"),
                       ("sheen", 0.9, "matte")]]
    if focal_error:
        cases = [c for c in cases if c[1] > 0 and c[3] == 100.0 and c[4][0] in ("ggx0.02", "lambertian")]
    for focal, off, size, r, (material, exposure, sphere) in cases:
        imgs, mask, principal = render_pinhole(material, size, r, focal, off, d, e, 16, exposure, gen)
        line = []
        configs = [("ortho", {}), ("focal", {"focal": focal, "principal": principal})]
        if focal_error:
            configs = [(f"focal x{k}", {"focal": k * focal, "principal": principal}) for k in (0.9, 1, 1.1)]
        for label, cfg in configs:
            try:
                res = calibrate_lights(imgs, sphere, mask=mask, config=cfg)
            except PsctlError as err:  # an outline no circle fits, orthographically
                line.append(f"{label} refused ({err.message.split(':')[0]})")
                continue
            err = light_direction_error(res.directions, d.numpy())
            total[label] = total.get(label, 0.0) + float(err.mean())
            line.append(f"{label} {err.mean():6.3f} ({err.max():6.3f})")
        angle = math.degrees(math.atan(math.hypot(off, off / 2) / focal))
        print(f"f {focal:5.0f}  off-axis {off:3.0f} px ({angle:4.1f} deg)  r {r:4.0f}  {material:10s} "
              f"{sphere:6s} " + "  ".join(line), flush=True)
    print("sums of the means (over the cases each calibrated): " + ", ".join(f"{k} {v:.2f}" for k, v in total.items()))


def centroids(d: torch.Tensor, e: torch.Tensor, gen: torch.Generator) -> None:
    import psctl.calibrate as C

    cases = [("ggx0.01", 4.0), ("ggx0.02", 4.0), ("ggx0.05", 4.0), ("ggx0.02", 0.8), ("merl-chrome", 4.0),
             ("glossy", 1.0), ("ggx0.05", 40.0), ("glossy", 8.0)]
    found, total = C.find_highlight, {}
    try:
        for size, r in [(256, 100.0), (96, 30.0)]:
            for material, exposure in cases:
                imgs, mask = render(material, size, r, d, e, 16, exposure, gen)
                for weighting in ("surface", "even", "image"):
                    C.find_highlight = lambda *a, _w=weighting, **k: found(*a, **k, weighting=_w)
                    err = light_direction_error(C.calibrate_lights(imgs, "chrome", mask=mask).directions, d.numpy())
                    total[weighting] = total.get(weighting, 0.0) + float(err.mean())
                    print(f"r {r:5.0f}  {material:12s} x{exposure:<4g} {weighting:8s} mean {err.mean():.3f}  "
                          f"max {err.max():.3f}", flush=True)
    finally:
        C.find_highlight = found
    print("sums of the means: " + ", ".join(f"{k} {v:.2f}" for k, v in total.items()))


def offsets(d: torch.Tensor, e: torch.Tensor, gen: torch.Generator) -> None:
    """Matte balls with a black level left in the images: the fit with and without its constant."""
    total = {}
    for size, r in [(256, 100.0), (96, 30.0)]:
        for bits in (16, 8):
            for material, exposure in [("lambertian", 0.9), ("sheen", 0.9), ("glossy", 1.0)]:
                for off in (0.0, 0.01, 0.02, 0.05):
                    imgs, mask = render(material, size, r, d, e, bits, exposure, gen, offset=off)
                    for flag in (False, True):
                        res = calibrate_lights(imgs, "matte", mask=mask, config={"offset": flag})
                        err = light_direction_error(res.directions, d.numpy())
                        re = intensity_error(res.intensities.mean(1), e.numpy())
                        key = (flag, off)
                        total[key] = total.get(key, 0.0) + float(err.mean())
                        print(f"r {r:5.0f}  {bits:2d} bit  {material:10s} offset {off:<5g} fit offset {flag!s:5s}  "
                              f"mean {err.mean():.3f}  max {err.max():.3f}  RE {re:.4f}", flush=True)
    for (flag, off), v in sorted(total.items()):
        print(f"fit offset {flag!s:5s}, offset {off:<5g}: sum of the means {v:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the defaults only, radius 100, 16 bits")
    ap.add_argument("--sweep", action="store_true", help="also the alternatives to the defaults")
    ap.add_argument("--bits", type=int, choices=(8, 16), help="only this bit depth")
    ap.add_argument("--centroids", action="store_true", help="compare find_highlight's weightings instead")
    ap.add_argument("--perspective", action="store_true", help="spheres off a pinhole camera's axis: the "
                    "orthographic model and --focal (config focal, principal) instead")
    ap.add_argument("--focal-error", action="store_true", help="with --perspective: eight cases with the focal "
                    "length 10 %% short and long")
    ap.add_argument("--offsets", action="store_true", help="matte balls with a black level: the fit with and "
                    "without its constant term (config offset) instead")
    args = ap.parse_args()
    gen = torch.Generator().manual_seed(0)
    d, e = lights(40, gen)
    if args.centroids:
        centroids(d, e, gen)
        return
    if args.offsets:
        offsets(d, e, gen)
        return
    if args.perspective:
        perspective(d, e, gen, args.focal_error)
        return
    cases = [("ggx0.01", 4.0), ("ggx0.02", 4.0), ("ggx0.05", 4.0), ("ggx0.02", 0.8), ("merl-chrome", 4.0),
             ("glossy", 1.0), ("lambertian", 0.9), ("sheen", 0.9), ("glossy", 1.0)]
    sizes = [(256, 100.0)] if args.quick else [(256, 100.0), (96, 30.0)]
    bit_depths = [args.bits] if args.bits else [16] if args.quick else [16, 8]
    print(f"defaults: {DEFAULT_CALIBRATE}")
    for size, r in sizes:
        for bits in bit_depths:
            n_glossy = 0
            for material, exposure in cases:
                imgs, mask = render(material, size, r, d, e, bits, exposure, gen)
                # the glossy ball twice: as a mirror's stand-in, then as a matte one's
                sphere = "matte" if material in ("lambertian", "sheen") or (material, n_glossy) == ("glossy", 1) \
                    else "chrome"
                n_glossy += material == "glossy"
                configs = [{}]
                if args.sweep:
                    configs += ([{"highlight": h, "base": b} for b in (0.0, 50.0, 90.0) for h in (0.1, 0.3, 0.5, 0.7)]
                                if sphere == "chrome"
                                else [{"lit": v} for v in (0.05, 0.1, 0.2, 0.3)] + [{"trim": v} for v in (2.0, 3.0, 4.0)])
                for cfg in configs:
                    res = calibrate_lights(imgs, sphere, mask=mask, config=cfg)
                    err = light_direction_error(res.directions, d.numpy())
                    re = "" if res.intensities is None else \
                        f"  RE {intensity_error(res.intensities.mean(1), e.numpy()):.4f}"
                    label = ",".join(f"{k}={v}" for k, v in cfg.items()) or "defaults"
                    print(f"r {r:5.0f}  {bits:2d} bit  {material:12s} x{exposure:<4g} {sphere:6s} {label:14s} "
                          f"mean {err.mean():.3f}  max {err.max():.3f}{re}  (circle r {res.circle.r:.2f})",
                          flush=True)


if __name__ == "__main__":
    main()
