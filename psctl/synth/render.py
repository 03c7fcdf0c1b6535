"""Image formation: m = e * f(n, l, v) * max(n.l, 0) * visibility (+ ambient), plus camera effects.

Orthographic camera, v = (0, 0, 1) everywhere, distant lights. So h = normalize(l + v) and l.h
depend only on the light, and a pixel needs just n.l, n.h and n.v: shading a batch is a few
[B, N, P] tensor operations (B samples, N lights, P pixels).

Cast shadows come from the depth map seen as a height field (z toward the camera):
  * ``march_shadows`` marches from each pixel toward each light and tests the depth map
    (exact for the height field, used by the folder writer);
  * ``horizon_map`` precomputes, per pixel and for K azimuths, the elevation of the horizon;
    then ``horizon_visibility`` answers any light with two look-ups (used by the training
    stream, where one G-buffer serves many samples). Both only ever darken.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from psctl.synth.materials import Material, lobes
from psctl.synth.shapes import BACKGROUND

VIEW = (0.0, 0.0, 1.0)


def shade(normals: Tensor, lights: Tensor, mat: Material, visibility: Tensor | None = None,
          intensities: Tensor | None = None, texture: Tensor | None = None,
          mat_b: Material | None = None, weights: Tensor | None = None,
          ambient: Tensor | None = None) -> Tensor:
    """Render B samples of P pixels under N lights each.

    Args:
        normals: [B, 3, P] unit normals (0 outside the object gives 0 radiance).
        lights: [B, N, 3] unit directions toward the lights.
        mat: B materials; ``mat_b`` optional second materials blended as
            weights * f_A + (1 - weights) * f_B with ``weights`` [B, 1, P] in [0, 1].
        visibility: [B, N, P] in [0, 1] (cast shadows), or None.
        intensities: [B, N] light intensities e, or None for 1.
        texture: [B, 3, P] multiplier of the diffuse albedo, or None.
        ambient: [B] strength of a light-independent term ambient * kd (added once per image).
    Returns:
        [B, N, 3, P] linear radiance.
    """
    nz = normals[:, 2:3]  # n.v, [B, 1, P]
    h = F.normalize(lights + lights.new_tensor(VIEW), dim=-1)  # [B, N, 3]
    nl = torch.einsum("bcp,bnc->bnp", normals, lights)
    nh = torch.einsum("bcp,bnc->bnp", normals, h)
    lh = (lights * h).sum(-1, keepdim=True)  # [B, N, 1]
    cos = nl.clamp_min(0.0) * (nz > 0)
    if visibility is not None:
        cos = cos * visibility
    if intensities is not None:
        cos = cos * intensities[..., None]

    def one(m: Material) -> Tensor:
        s1, s2 = lobes(m, nl, nz, nh, lh)
        # RGB = sum of colour x scalar terms: one batched 3 x T matmul per (sample, light)
        terms, coefs = [s1 * cos], [m["c1"]]
        if bool(m["metal"].any()):
            terms.append(s2 * cos)
            coefs.append(m["c2"])
        if texture is None:
            terms.append(cos)
            coefs.append(m["kd"] / math.pi)
        out = torch.matmul(torch.stack(coefs, -1)[:, None], torch.stack(terms, 2))  # [B, N, 3, P]
        if texture is not None:
            out.addcmul_((m["kd"][:, :, None] / math.pi * texture)[:, None], cos[:, :, None])
        if ambient is not None:
            alb = m["kd"][:, :, None] * (texture if texture is not None else 1.0) * (nz > 0)  # [B, 3, P]
            out.add_((ambient[:, None, None] * alb)[:, None])
        return out

    img = one(mat)
    if mat_b is not None:
        w = weights[:, None]  # [B, 1, 1, P]
        img = w * img + (1.0 - w) * one(mat_b)
    return img


# --------------------------------------------------------------------------------------------
# Cast shadows
# --------------------------------------------------------------------------------------------


def march_distances(max_px: float, near: int = 8, growth: float = 1.12) -> list[float]:
    """Sample distances (pixels) along a shadow ray: every pixel up to ``near``, then growing
    geometrically up to ``max_px``."""
    d = [float(i) for i in range(1, near + 1)]
    while d[-1] < max_px:
        d.append(d[-1] * growth)
    return d


def march_shadows(depth: Tensor, lights: Tensor, bias_px: float = 0.5) -> Tensor:
    """Cast-shadow visibility by marching the depth map toward each light.

    Every pixel steps toward the light by the same offsets, so each step is one shifted copy of
    the depth map (bilinear: four integer shifts) compared with the ray's height.

    Args:
        depth: [B, 1, H, W] depth (world units, image spans [-1, 1]; BACKGROUND off the object).
        lights: [B, N, 3] unit directions.
        bias_px: tolerance in pixels of depth, so that a smooth surface does not shadow itself.
    Returns:
        [B, N, H, W] visibility, 1 (lit) or 0 (occluded).
    """
    b, _, hgt, wid = depth.shape
    px = 2.0 / wid
    dists = march_distances(math.hypot(hgt, wid))
    pad = int(math.ceil(dists[-1])) + 2
    vis = torch.ones(b, lights.shape[1], hgt, wid, device=depth.device)
    for i in range(b):
        z = depth[i, 0]
        obj = z > BACKGROUND / 2
        if not bool(obj.any()):
            continue
        span = float(z[obj].max() - z[obj].min())  # rays higher than this above a pixel are free
        padded = F.pad(depth[i], (pad, pad, pad, pad), value=BACKGROUND)[0]

        def shifted(ox: int, oy: int) -> Tensor:
            return padded[pad + oy:pad + oy + hgt, pad + ox:pad + ox + wid]

        for j, (lx, ly, lz) in enumerate(lights[i].tolist()):
            lxy = math.hypot(lx, ly)
            if lxy < 1e-6:  # a light along the view axis casts no shadow on a height field
                continue
            cx, cy, rise = lx / lxy, -ly / lxy, lz / lxy  # columns right, rows down
            blocked = torch.zeros(hgt, wid, dtype=torch.bool, device=depth.device)
            for d in dists:
                lift = rise * d * px
                if lift > span + bias_px * px:
                    break
                fx, fy = d * cx, d * cy
                x0, y0 = math.floor(fx), math.floor(fy)
                wx, wy = fx - x0, fy - y0
                sample = ((1 - wx) * (1 - wy)) * shifted(x0, y0) + (wx * (1 - wy)) * shifted(x0 + 1, y0) \
                    + ((1 - wx) * wy) * shifted(x0, y0 + 1) + (wx * wy) * shifted(x0 + 1, y0 + 1)
                blocked |= sample > z + (lift + bias_px * px)
            vis[i, j] = (~blocked).float()
    return vis


def horizon_map(depth: Tensor, n_dirs: int = 32, max_px: float | None = None, exact_px: float = 8.0,
                bias_px: float = 0.5) -> Tensor:
    """Horizon elevation angle (radians) per pixel and azimuth.

    Args:
        depth: [B, 1, H, W] (BACKGROUND off the object).
        n_dirs: K azimuths phi_k = 2 pi k / K, measured from +x toward +y (up).
        max_px: how far to look (default: the image diagonal).
        exact_px: up to this distance samples are bilinear at the exact offset; farther, the
            nearest pixel.
        bias_px: depth tolerance in pixels, as in ``march_shadows``.
    Returns:
        [B, K, H, W]: the largest elevation atan(dz / distance) of the depth map seen from the
        pixel toward phi_k (-pi/2 when nothing rises). A light of azimuth phi and elevation el
        above the image plane is blocked when el is below the horizon.
    """
    b, _, hgt, wid = depth.shape
    px = 2.0 / wid
    dists = march_distances(max_px if max_px is not None else math.hypot(hgt, wid))
    pad = int(math.ceil(dists[-1])) + 1
    padded = F.pad(depth, (pad, pad, pad, pad), value=BACKGROUND)[:, 0]
    z = depth[:, 0] + bias_px * px
    out = torch.empty(b, n_dirs, hgt, wid, device=depth.device)
    def shifted(ox: int, oy: int) -> Tensor:
        return padded[:, pad + oy:pad + oy + hgt, pad + ox:pad + ox + wid]

    for k in range(n_dirs):
        phi = 2 * math.pi * k / n_dirs
        cx, cy = math.cos(phi), -math.sin(phi)  # columns right, rows down
        best = torch.full_like(z, -1e9)
        seen = set()
        for d in dists:
            if d <= exact_px:
                # near the pixel the direction matters most: bilinear sample at the exact offset
                fx, fy = d * cx, d * cy
                x0, y0 = math.floor(fx), math.floor(fy)
                wx, wy = fx - x0, fy - y0
                sample = ((1 - wx) * (1 - wy)) * shifted(x0, y0) + (wx * (1 - wy)) * shifted(x0 + 1, y0) \
                    + ((1 - wx) * wy) * shifted(x0, y0 + 1) + (wx * wy) * shifted(x0 + 1, y0 + 1)
                dist = d
            else:  # farther away, the nearest pixel (direction error < atan(0.7 / d))
                ox, oy = round(d * cx), round(d * cy)
                if (ox, oy) in seen or max(abs(ox), abs(oy)) >= pad:
                    continue
                seen.add((ox, oy))
                sample, dist = shifted(ox, oy), math.hypot(ox, oy)
            torch.maximum(best, (sample - z).mul_(1.0 / (dist * px)), out=best)
        out[:, k] = torch.atan(best)
    return out


def horizon_visibility(horizon: Tensor, lights: Tensor, softness_deg: float = 1.5) -> Tensor:
    """Visibility of N lights from a horizon map.

    Args:
        horizon: [B, K, P] horizon angles (from ``horizon_map``, pixels flattened).
        lights: [B, N, 3] unit directions in the horizon map's frame.
        softness_deg: width of the lit/shadowed transition (a small penumbra, also hides the
            azimuth discretisation).
    Returns:
        [B, N, P] in [0, 1].
    """
    b, k, p = horizon.shape
    n = lights.shape[1]
    lxy = lights[..., :2].norm(dim=-1)
    el = torch.atan2(lights[..., 2], lxy)  # [B, N]
    u = torch.remainder(torch.atan2(lights[..., 1], lights[..., 0]) / (2 * math.pi) * k, k)
    k0 = u.floor().long().clamp(0, k - 1)
    frac = (u - k0)[..., None]
    h0 = torch.gather(horizon, 1, k0[..., None].expand(b, n, p))
    h1 = torch.gather(horizon, 1, ((k0 + 1) % k)[..., None].expand(b, n, p))
    hz = h0 + (h1 - h0) * frac
    return ((el[..., None] - hz) / math.radians(softness_deg) + 0.5).clamp(0.0, 1.0)


# --------------------------------------------------------------------------------------------
# Camera effects
# --------------------------------------------------------------------------------------------


def uniform_noise(images: Tensor, gen: torch.Generator, level: float = 0.025) -> Tensor:
    """Add noise uniform in [-level, level) (the paper's training augmentation), on 65536 levels:
    16-bit integer draws added in place cost a third of float draws plus arithmetic on a CPU.
    ``images`` is modified in place and returned."""
    q = torch.randint(-32768, 32768, images.shape, dtype=torch.int16, generator=gen, device=gen.device)
    return images.add_(q, alpha=level / 32768.0)


def sensor_noise(images: Tensor, gen: torch.Generator, read: float = 0.002, shot: float = 1e-4) -> Tensor:
    """Add Gaussian sensor noise of variance read^2 + shot * signal (signal in [0, 1] units)."""
    sigma = (read * read + shot * images.clamp_min(0.0)).sqrt()
    return images + sigma * torch.randn(images.shape, generator=gen, device=gen.device)


def quantize(images: Tensor, bits: int = 16) -> Tensor:
    """Clip to [0, 1] and round to ``bits`` bits, as a camera writing integer pixels does."""
    peak = float(2**bits - 1)
    return torch.round(images.clamp(0.0, 1.0) * peak) / peak
