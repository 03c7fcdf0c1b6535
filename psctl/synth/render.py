"""Image formation: m = e * f(n, l, v) * max(n.l, 0) * visibility (+ ambient, + diffuse
interreflections), plus camera effects.

Orthographic camera, v = (0, 0, 1) everywhere, distant lights. So h = normalize(l + v) and l.h
depend only on the light, and a pixel needs just n.l, n.h and n.v: shading a batch is a few
[B, N, P] tensor operations (B samples, N lights, P pixels).

Cast shadows come from the depth map seen as a height field (z toward the camera):
  * ``march_shadows`` marches from each pixel toward each light and tests the depth map at
    growing distances (``march_distances``: every pixel up to 8, then 12 % further each step,
    so an occluder thinner than the gap can be missed; used by the folder writer);
  * ``horizon_map`` precomputes, per pixel and for K azimuths, the elevation of the horizon;
    then ``horizon_visibility`` answers any light with two look-ups (used by the training
    stream, where one G-buffer serves many samples). Both only ever darken.

Interreflections: ``interreflection_kernel`` (form factors between the pixels of a view) and
``diffuse_bounces`` follow bounces exactly (the folder writer); ``interreflection_transfer``
and ``indirect_irradiance`` store them per pixel in spherical harmonics (the stream).
"""

from __future__ import annotations

import math
import warnings

import torch
import torch.nn.functional as F
from torch import Tensor

from psctl.synth.materials import Material, lobes
from psctl.synth.shapes import BACKGROUND

VIEW = (0.0, 0.0, 1.0)


def shade(normals: Tensor, lights: Tensor, mat: Material, visibility: Tensor | None = None,
          intensities: Tensor | None = None, texture: Tensor | None = None,
          ambient: Tensor | None = None, indirect: Tensor | None = None,
          falloff: Tensor | None = None) -> Tensor:
    """Render B samples of P pixels under N lights each.

    Args:
        normals: [B, 3, P] unit normals (0 outside the object gives 0 radiance).
        lights: [B, N, 3] unit directions toward the lights, or [B, N, 3, P] one per pixel
            (near point lights, ``near_light_field``).
        mat: B materials (a blend of two: shade each, then mix, as the stream does).
        visibility: [B, N, P] in [0, 1] (cast shadows), or None.
        intensities: [B, N] light intensities e, or None for 1.
        texture: [B, 3, P] multiplier of the diffuse albedo, or None.
        ambient: [B] strength of a term ambient * kd added once per image, independent of the light
            and of ``intensities`` (the training stream passes no intensities and scales the image,
            this term included, by them afterwards: docs/synthetic.md).
        indirect: [B, N, 3, P] irradiance from interreflections (``indirect_irradiance``),
            reflected as kd / pi (times the texture).
        falloff: [B, N, P] irradiance per pixel relative to the lights' intensities (near point
            lights), or None for 1.
    Returns:
        [B, N, 3, P] linear radiance.
    """
    nz = normals[:, 2:3]  # n.v, [B, 1, P]
    if lights.dim() == 4:  # a direction per pixel: [B, N, 3, P]
        h = F.normalize(lights + lights.new_tensor(VIEW)[:, None], dim=2)
        nl = torch.einsum("bcp,bncp->bnp", normals, lights)
        nh = torch.einsum("bcp,bncp->bnp", normals, h)
        lh = (lights * h).sum(2)  # [B, N, P]
    else:
        h = F.normalize(lights + lights.new_tensor(VIEW), dim=-1)  # [B, N, 3]
        nl = torch.einsum("bcp,bnc->bnp", normals, lights)
        nh = torch.einsum("bcp,bnc->bnp", normals, h)
        lh = (lights * h).sum(-1, keepdim=True)  # [B, N, 1]
    cos = nl.clamp_min(0.0) * (nz > 0)
    if falloff is not None:
        cos = cos * falloff
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
        if ambient is not None or indirect is not None:
            alb = m["kd"][:, :, None] * (texture if texture is not None else 1.0) * (nz > 0)  # [B, 3, P]
        if ambient is not None:
            out.add_((ambient[:, None, None] * alb)[:, None])
        if indirect is not None:
            out.addcmul_((alb / math.pi)[:, None], indirect)
        return out

    return one(mat)


def near_field(lights: Tensor, xy: Tensor, to_src: Tensor, distance: Tensor) -> tuple[Tensor, Tensor]:
    """Point lights ``distance`` [b] pixels (inf: distant) from an object's centroid along
    ``lights`` [b, n, 3] (source frame, x right, y up), seen from pixels at ``xy`` [b, 2, P]
    (pixels from the centroid, y up, every pixel at the centroid's depth; orthographic camera,
    psctl.nearlight's model).

    Returns per-pixel directions [b, n, 3, P] in the output frame (``to_src`` [b, 2, 2] maps
    output to source directions and is orthogonal; the identity for psctl synth) and the falloff
    D^2 / |D l - X|^2 [b, n, P]."""
    x = xy / distance[:, None, None]  # X / D, 0 for distant lights
    v = lights[..., None] - torch.cat([x, torch.zeros_like(x[:, :1])], 1)[:, None]  # (D l - X) / D, D not squared
    r2 = (v * v).sum(2)
    out_xy = torch.einsum("bji,bnjp->bnip", to_src, v[:, :, :2])  # back to the output frame: to_src^T
    return torch.cat([out_xy, v[:, :, 2:]], 2) / r2.sqrt()[:, :, None], 1.0 / r2


def near_light_field(lights: Tensor, distance: float, mask: Tensor) -> tuple[Tensor, Tensor]:
    """``near_field`` for one view: point lights at ``distance`` pixels from the centroid of
    ``mask`` [H, W] along ``lights`` [N, 3] -> per-pixel directions [N, 3, H*W] and falloff [N, H*W]."""
    h, w = mask.shape
    rows, cols = torch.nonzero(mask, as_tuple=True)
    cy, cx = rows.double().mean(), cols.double().mean()
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64),
                            indexing="ij")
    xy = torch.stack([xx - cx, cy - yy]).reshape(1, 2, -1)  # x right, y up
    dirs, fall = near_field(lights.double()[None], xy, torch.eye(2, dtype=torch.float64)[None],
                            torch.tensor([float(distance)], dtype=torch.float64))
    return dirs[0].to(lights.dtype), fall[0].to(lights.dtype)


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


# --------------------------------------------------------------------------------------------
# Interreflections (one or more diffuse bounces, screen space)
# --------------------------------------------------------------------------------------------


def interreflection_offsets(max_px: float = 48.0, growth: float = 1.15) -> tuple[Tensor, Tensor]:
    """Pixel offsets sampled around a pixel and the screen area (pixels^2) each stands for.

    Every offset within 3 pixels; beyond, rings at geometrically growing radii with about
    8 pixels of arc between samples (far patches matter less: 1/r^2). Offsets landing on
    the same integer pixel are merged (areas add), and the set is made mirror-symmetric.
    Returns:
        offsets [K, 2] long (columns, rows), area [K] float.
    """
    acc: dict[tuple[int, int], float] = {}
    for dy in range(-3, 4):
        for dx in range(-3, 4):
            if 0 < dx * dx + dy * dy <= 9:
                acc[(dx, dy)] = 1.0
    r_in = 3.5
    while r_in < max_px:
        r_out = max(r_in + 1.0, r_in * growth)
        r = 0.5 * (r_in + r_out)
        m = max(8, int(math.ceil(2 * math.pi * r / 8.0)))
        area = math.pi * (r_out * r_out - r_in * r_in) / m
        for k in range(m):
            phi = 2 * math.pi * (k + 0.5 * (len(acc) % 2)) / m
            key = (round(r * math.cos(phi)), round(r * math.sin(phi)))
            acc[key] = acc.get(key, 0.0) + area
        r_in = r_out
    # mirror-symmetric in x and y (no preferred direction): each offset's area averaged over
    # its four mirror images, all of which are sampled
    sym: dict[tuple[int, int], float] = {}
    for (dx, dy) in acc:
        mirrors = {(sx * dx, sy * dy) for sx in (1, -1) for sy in (1, -1)}
        for key in mirrors:
            sym[key] = sum(acc.get(m, 0.0) for m in mirrors) / len(mirrors)
    keys = sorted(sym)
    return torch.tensor(keys, dtype=torch.long), torch.tensor([sym[k] for k in keys])


def interreflection_kernel(depth: Tensor, normals: Tensor, max_px: float | None = None, bias_px: float = 0.5,
                           min_nz: float = 0.1) -> Tensor:
    """Form factors between the pixels of one view, for diffuse interreflections.

    E_p = sum_q G[p, q] B_q: the irradiance at pixel p from the radiance B_q leaving the
    surface at q, G = cos_p cos_q A_q / r^2 (A_q the surface area under pixel q), for q within
    ``max_px`` pixels (default: the image diagonal) that p and q face and that the height
    field does not hide (three samples along the segment). Orthographic camera, image
    spanning [-1, 1]. Checked against the exact view factor of a V-groove's face: within 6 %
    from 4.5 pixels from the crease on (64 and 128 px), 7.5 % at 3.5 px, up to 15 % at the
    crease (tests/test_interreflection.py).

    Args:
        depth: [1, 1, H, W] (BACKGROUND off the object); normals: [1, 3, H, W].
        min_nz: the area under a pixel is px^2 / max(n_z, min_nz) (grazing patches capped).
    Returns:
        sparse CSR [P, P], P = H * W.
    """
    _, _, hgt, wid = depth.shape
    px = 2.0 / wid
    z = depth[0, 0]
    obj = z > BACKGROUND / 2
    n = normals[0]
    offs, areas = interreflection_offsets(max_px if max_px is not None else math.hypot(hgt, wid))
    offs = offs.to(z.device)
    # the offsets' geometry in float64 then float32: the same values as Python scalars would give
    dxy_px = (offs.double() * px).to(z.dtype)  # [K, 2]
    area_px = (areas.double() * (px * px)).to(device=z.device, dtype=z.dtype)  # [K]
    # Offsets are taken `step` at a time: the cheap test (both pixels on the object) on [step, P_obj],
    # the rest only on the pairs that pass it. One Python step per offset launched ~40 tiny
    # kernels each, which made the kernel launch-bound on a GPU (three trainings sharing an H100
    # ran at ~30 samples/s each, i.e. ~4 s per 128 px view at 128 samples per view). On a CPU
    # smaller steps stay in cache (128 px, one thread: 0.6 s per view with 2^18 elements per
    # step, 1.0 s with 2^22 or one offset per step, when the test ran over every pixel).
    # The test reads a copy of the object mask padded by the largest offset, by flat index
    # (pixel + the offset's shift), so it needs no bounds checks; a point between two object
    # pixels is inside the image, so neither do the occlusion samples.
    pad = int(offs.abs().max()) if len(offs) else 0
    wp = wid + 2 * pad
    padded = torch.zeros(hgt + 2 * pad, wp, dtype=torch.bool, device=z.device)
    padded[pad:pad + hgt, pad:pad + wid] = obj
    padded = padded.flatten()
    src = obj.flatten().nonzero(as_tuple=True)[0]  # the object's pixels, row-major
    si0, sj0 = src // wid, src % wid
    base = (si0 + pad) * wp + (sj0 + pad)
    shift = offs[:, 1] * wp + offs[:, 0]
    zf, nf = z.flatten(), n.flatten(1)
    step = max(1, (1 << (18 if z.device.type == "cpu" else 22)) // max(1, len(src)))
    rows_all, cols_all, vals_all = [], [], []
    for k0 in range(0, len(offs), step):
        ok = padded[base[None] + shift[k0:k0 + step, None]]  # [C, P_obj]: q = p + offset on the object
        k, s = ok.nonzero(as_tuple=True)  # the pairs (p = src[s], q = p + offset k0 + k)
        k = k + k0
        i, j = si0[s], sj0[s]
        pf = src[s]
        qf = pf + offs[k, 1] * wid + offs[k, 0]
        zp = zf[pf]
        dz = zf[qf] - zp
        d = torch.stack([dxy_px[k, 0], -dxy_px[k, 1], dz])  # [3, M]
        r2 = (d * d).sum(0)
        cos_p = (nf[:, pf] * d).sum(0) / r2.sqrt()
        nq = nf[:, qf]
        cos_q = -(nq * d).sum(0) / r2.sqrt()
        keep = (cos_p > 0) & (cos_q > 0)
        for t in (0.25, 0.5, 0.75):  # the height field between p and q must stay below the segment
            si = i + torch.round(t * offs[k, 1]).long()  # round half to even, as Python's
            sj = j + torch.round(t * offs[k, 0]).long()
            keep &= zf[si * wid + sj] <= zp + t * dz + bias_px * px
        g = cos_p * cos_q * (nq[2].clamp_min(min_nz).reciprocal() * area_px[k]) / r2
        rows_all.append(pf[keep])
        cols_all.append(qf[keep])
        vals_all.append(g[keep])
    p = hgt * wid
    idx = torch.stack([torch.cat(rows_all), torch.cat(cols_all)])
    with warnings.catch_warnings():  # torch calls sparse CSR "beta"; only constructor and matmul are used
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_coo_tensor(idx, torch.cat(vals_all), (p, p), check_invariants=True).coalesce().to_sparse_csr()


def diffuse_bounces(kernel: Tensor, direct: Tensor, albedo: Tensor, bounces: int = 1,
                    receiver: Tensor | None = None) -> Tensor:
    """Radiance added by diffuse interreflections.

    Args:
        kernel: [P, P] from ``interreflection_kernel``.
        direct: [N, 3, P] radiance leaving each pixel by diffuse reflection of the lights
            (albedo / pi * e * max(n.l, 0) * visibility): the source of the first bounce. Glossy
            reflection toward other surface points is not followed (a lower bound for shiny
            materials).
        albedo: [3, P] diffuse albedo of the surface as a source of further bounces (0 off the
            object).
        bounces: how many bounces to follow.
        receiver: [3, P] the albedo that reflects the indirect light toward the camera
            (default ``albedo``; the training stream's ``interreflection`` option makes the
            surface a brighter source than its kd, and so does the writer's ``ir_albedo``).
    Returns:
        [N, 3, P]: receiver / pi * sum over bounces of the irradiance G @ B.
    """
    nl, c, p = direct.shape
    src = direct.reshape(nl * c, p).T  # [P, N*3]
    irr = torch.zeros_like(direct)
    for _ in range(bounces):
        e = (kernel @ src).T.reshape(nl, c, p)  # irradiance of this bounce
        irr += e
        src = (albedo.reshape(1, c, p) / math.pi * e).reshape(nl * c, p).T
    rec = albedo if receiver is None else receiver
    return rec.reshape(1, c, p) / math.pi * irr


# Clamped cosine in real spherical harmonics up to order 2: max(n.l, 0) ~= sum_j A_j Y_j(n) Y_j(l)
# (Ramamoorthi and Hanrahan 2001: A = pi, 2 pi / 3, pi / 4 for orders 0, 1, 2; about 2 % of
# the irradiance off, negative lobes small). It lets a G-buffer store light-independent transfer.
SH_COSINE = (math.pi,) + (2 * math.pi / 3,) * 3 + (math.pi / 4,) * 5


def sh9(d: Tensor, dim: int = -1) -> Tensor:
    """Real spherical harmonics Y_0..Y_8 of unit directions along ``dim`` (a new axis of 9 there)."""
    x, y, z = d.unbind(dim)
    c0, c1, c2, c3 = 0.282095, 0.488603, 1.092548, 0.315392
    return torch.stack([torch.full_like(x, c0), c1 * y, c1 * z, c1 * x, c2 * x * y, c2 * y * z,
                        c3 * (3 * z * z - 1), c2 * x * z, 0.546274 * (x * x - y * y)], dim)


def interreflection_transfer(kernel: Tensor, normals: Tensor, mask: Tensor) -> Tensor:
    """What a G-buffer needs to add interreflections under any distant light, per pixel.

    T_j = sum_q G[p, q] A_j Y_j(n_q) and F = sum_q G[p, q] / pi (the share of p's hemisphere
    that the surface fills), so that a unit light l lighting a Lambertian surface of albedo rho
    gives the first bounce's irradiance rho / pi * sum_j T_j Y_j(l) (cast shadows on the
    sources ignored), and all bounces about that / (1 - rho F).
    Args:
        kernel: [P, P] from ``interreflection_kernel``; normals [3, P]; mask [P] (bool).
    Returns:
        [P, 10]: T_0..T_8, F.
    """
    y = sh9(normals.T) * normals.new_tensor(SH_COSINE) * mask[:, None]  # [P, 9]
    ones = mask[:, None].to(normals.dtype)
    return torch.cat([kernel @ y, (kernel @ ones) / math.pi], 1)


def indirect_irradiance(transfer: Tensor, lights: Tensor, rho: Tensor) -> Tensor:
    """Irradiance from interreflections (all bounces, approximately) for B samples.

    Args:
        transfer: [B, 10, P] (``interreflection_transfer``, transposed, per sample).
        lights: [B, N, 3] in the transfer's frame; rho: [B, 3] the surface's diffuse albedo as
            a source of indirect light.
    Returns:
        [B, N, 3, P] (multiply by the receiving kd / pi and the light's intensity).
    """
    first = torch.einsum("bnj,bjp->bnp", sh9(lights), transfer[:, :9]).clamp_min(0.0)  # [B, N, P]
    scale = rho[:, :, None] / math.pi / (1.0 - rho.amax(1)[:, None, None] * transfer[:, 9:10]).clamp_min(0.1)
    return first[:, :, None] * scale[:, None]  # [B, N, 3, P]
