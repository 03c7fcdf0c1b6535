"""Geometry as orthographic G-buffers: the analytic sphere and procedural "blobby" shapes.

A G-buffer is what a renderer needs from geometry, per pixel: the unit normal, the depth of
the visible surface and the object mask. The camera is orthographic, looking down -z; the
image spans x, y in [-1, 1] (x right, y up, z toward the camera; row 0 is the top), so one
pixel of an S x S G-buffer is 2 / S world units wide and depth is in the same units.

Blobby shapes are signed distance functions (SDFs) rendered by sphere tracing:
a smooth union of random primitives (ellipsoids, capsules, tori, rounded boxes), a few smooth
subtractions (dents), and a displacement by random sinusoids at several scales (fine detail).
The union and the dents give concavities and creases, the low frequencies smooth parts.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

BACKGROUND = -10.0  # depth outside the mask: below any object, so it never casts a shadow

# Primitive slots of a blobby shape: ellipsoids, capsules, tori, rounded boxes, dents.
SLOTS = {"ellipsoid": 4, "capsule": 2, "torus": 1, "box": 2, "dent": 2}

BLOBBY = {
    "primitives": (2, 6),  # number of positive primitives (the first is a central ellipsoid)
    "p_capsule": 0.25, "p_torus": 0.12, "p_box": 0.3,  # chance of each non-ellipsoid slot being used
    "dents": 0.5,  # chance of each dent slot being used
    "features": 24,  # displacement sinusoids per shape
    "detail": (0.0, 2.5),  # displacement strength, drawn per shape
    "steps": 96,  # sphere-tracing iterations per level (at most)
}


def check_blobby(overrides: object, where: str = "synth stream option 'blobby'") -> dict:
    """Overrides of BLOBBY checked (known keys, kinds and ranges) and returned as a dict: a
    one-line error naming the key, not a torch error while rendering (or, with steps 0, empty
    shapes that train on nothing)."""
    from psctl.errors import PsctlError, is_number

    if overrides is None:
        return {}
    if not isinstance(overrides, dict):
        raise PsctlError(None, f"{where} must map {', '.join(BLOBBY)} to values, not {overrides!r}")
    bad = sorted(map(str, set(overrides) - set(BLOBBY)))
    if bad:
        raise PsctlError(None, f"{where}: unknown {', '.join(bad)}; choose from {', '.join(BLOBBY)}")
    positive = sum(k for kind, k in SLOTS.items() if kind != "dent")

    def whole(v: object) -> bool:
        return is_number(v) and float(v).is_integer()

    for k, v in overrides.items():
        if k == "primitives":
            ok = isinstance(v, (list, tuple)) and len(v) == 2 and all(map(whole, v)) and 1 <= v[0] <= v[1] <= positive
            want = f"[lo, hi], whole numbers with 1 <= lo <= hi <= {positive}"
        elif k == "detail":
            ok = isinstance(v, (list, tuple)) and len(v) == 2 and all(map(is_number, v)) and 0 <= v[0] <= v[1]
            want = "[lo, hi] with 0 <= lo <= hi"
        elif k in ("p_capsule", "p_torus", "p_box", "dents"):
            ok, want = is_number(v) and 0 <= v <= 1, "a chance: 0 to 1"
        elif k == "features":  # (10^6 ran past a minute per chunk: a review)
            ok, want = whole(v) and 0 <= v <= 1024, "a whole number, 0 to 1024"
        else:  # steps
            ok, want = whole(v) and v >= 1, "a whole number, 1 or more (sphere-tracing steps)"
        if not ok:
            raise PsctlError(None, f"{where}: {k} must be {want}, not {v!r}")
    return {k: (tuple(int(x) for x in v) if k == "primitives" else tuple(float(x) for x in v) if k == "detail"
                else int(v) if k in ("features", "steps") else float(v)) for k, v in overrides.items()}


@dataclass
class GBuffer:
    """Per-pixel geometry of B views.

    normals: [B, 3, H, W] float32, unit inside the mask, 0 outside.
    depth:   [B, 1, H, W] float32, z of the visible surface (world units), BACKGROUND outside.
    mask:    [B, 1, H, W] bool.
    names:   the source of each view ("sphere", "blobby", "lucy", ...).
    """

    normals: Tensor
    depth: Tensor
    mask: Tensor
    names: list[str]

    def __len__(self) -> int:
        return self.normals.shape[0]

    @property
    def size(self) -> tuple[int, int]:
        return self.normals.shape[-2], self.normals.shape[-1]

    def to(self, device: torch.device | str) -> "GBuffer":
        return GBuffer(self.normals.to(device), self.depth.to(device), self.mask.to(device), list(self.names))

    def take(self, idx: Tensor | list[int]) -> "GBuffer":
        idx = torch.as_tensor(idx, dtype=torch.long, device=self.normals.device)
        return GBuffer(self.normals[idx], self.depth[idx], self.mask[idx], [self.names[i] for i in idx.tolist()])

    @staticmethod
    def cat(items: list["GBuffer"]) -> "GBuffer":
        return GBuffer(torch.cat([g.normals for g in items]), torch.cat([g.depth for g in items]),
                       torch.cat([g.mask for g in items]), [n for g in items for n in g.names])


def pixel_xy(h: int, w: int, device: torch.device | str = "cpu") -> tuple[Tensor, Tensor]:
    """World x, y of pixel centres, [H, W] each (x grows to the right, y grows upward)."""
    x = (torch.arange(w, device=device, dtype=torch.float32) + 0.5) / w * 2 - 1
    y = 1 - (torch.arange(h, device=device, dtype=torch.float32) + 0.5) / h * 2
    return x[None, :].expand(h, w), y[:, None].expand(h, w)


def sphere_gbuffer(size: int, radius: float = 0.9, device: torch.device | str = "cpu") -> GBuffer:
    """The analytic sphere of ``radius`` centred in a size x size view."""
    x, y = pixel_xy(size, size, device)
    r2 = (x * x + y * y) / radius**2
    mask = r2 < 1.0
    nz = (1.0 - r2).clamp_min(0.0).sqrt()
    n = torch.stack([x / radius, y / radius, nz]) * mask
    depth = torch.where(mask, radius * nz, torch.full_like(nz, BACKGROUND))
    return GBuffer(n[None], depth[None, None], mask[None, None], ["sphere"])


def sphere_pinhole(width: int, height: int, focal: float, centre: tuple[float, float, float], radius: float = 1.0,
                   principal: tuple[float, float] | None = None, device: torch.device | str = "cpu"
                   ) -> tuple[Tensor, Tensor, Tensor]:
    """A sphere seen through a pinhole camera at the origin (focal length ``focal`` pixels, the
    principal point at ``principal`` (x, y) pixels, default the image's centre; x right, y up, z
    toward the camera, so the scene lies at z < 0): ray-traced per pixel centre, in float64.

    Returns normals [3, H, W] (0 off the sphere), views [3, H, W] (unit, from each pixel's surface
    point toward the camera) and mask [H, W] bool. For calibration renders where the sphere is
    off the optical axis (benchmarks/calibrate_sphere.py --perspective, tests/test_calibrate.py).
    """
    f64 = dict(dtype=torch.float64, device=device)
    px, py = ((width - 1) / 2, (height - 1) / 2) if principal is None else principal
    xs = torch.arange(width, **f64) - px
    ys = py - torch.arange(height, **f64)
    d = torch.stack([xs[None, :].expand(height, width), ys[:, None].expand(height, width),
                     torch.full((height, width), -float(focal), **f64)])
    d = d / d.norm(dim=0, keepdim=True)  # [3, H, W] unit rays from the camera
    c = torch.tensor(centre, **f64)[:, None, None]
    b = (d * c).sum(0)
    disc = b * b - (c * c).sum(0) + radius * radius
    mask = disc > 0
    t = b - disc.clamp_min(0).sqrt()  # the nearer intersection
    n = (t * d - c) / radius * mask
    return n, -d, mask


# --------------------------------------------------------------------------------------------
# Blobby SDF shapes
# --------------------------------------------------------------------------------------------


def random_rotations(shape: tuple[int, ...], gen: torch.Generator) -> Tensor:
    """[*shape, 3, 3] rotation matrices, uniform over SO(3) (normalised Gaussian quaternions)."""
    q = F.normalize(torch.randn(*shape, 4, generator=gen, device=gen.device), dim=-1)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*shape, 3, 3)


def _uniform(shape: tuple[int, ...], lo: float, hi: float, gen: torch.Generator) -> Tensor:
    return lo + (hi - lo) * torch.rand(shape, generator=gen, device=gen.device)


def _in_ball(shape: tuple[int, ...], radius: float, gen: torch.Generator) -> Tensor:
    v = F.normalize(torch.randn(*shape, 3, generator=gen, device=gen.device), dim=-1)
    return v * radius * torch.rand(*shape, 1, generator=gen, device=gen.device) ** (1 / 3)


def sample_blobby(n: int, gen: torch.Generator, config: dict | None = None) -> dict[str, Tensor]:
    """Random parameters of n blobby shapes (see BLOBBY for the knobs). Every tensor has
    leading dimension n; slot order follows SLOTS. The whole shape stays within radius ~0.9."""
    cfg = {**BLOBBY, **(config or {})}
    n_slots = sum(SLOTS.values())
    p: dict[str, Tensor] = {}
    p["center"] = _in_ball((n, n_slots), 0.5, gen)
    p["rot"] = random_rotations((n, n_slots), gen)
    p["size"] = _uniform((n, n_slots, 3), 0.15, 0.4, gen)
    p["round"] = _uniform((n, n_slots), 0.02, 0.1, gen)
    active = torch.zeros(n, n_slots, dtype=torch.bool, device=gen.device)
    # slot 0: a central body, so that every shape has one
    p["center"][:, 0] *= 0.3
    p["size"][:, 0] = _uniform((n, 3), 0.3, 0.55, gen)
    # choose how many positive primitives, then which optional slots are used
    lo, hi = cfg["primitives"]
    count = torch.randint(lo, hi + 1, (n,), generator=gen, device=gen.device)
    start = 0
    chances = {"ellipsoid": 1.0, "capsule": cfg["p_capsule"], "torus": cfg["p_torus"], "box": cfg["p_box"]}
    order = []
    for kind, k in SLOTS.items():
        if kind == "dent":
            active[:, start:start + k] = torch.rand(n, k, generator=gen, device=gen.device) < cfg["dents"]
        else:
            order += [(start + i, chances[kind]) for i in range(k)]
        start += k
    # rank optional slots by a random key (weighted by their chance) and keep the first count
    keys = torch.stack([torch.rand(n, generator=gen, device=gen.device) * c for _, c in order], 1)
    keys[:, 0] = 2.0  # the central ellipsoid always
    rank = keys.argsort(dim=1, descending=True).argsort(dim=1)
    slots = torch.tensor([s for s, _ in order], device=gen.device)
    active[:, slots] = rank < count[:, None]
    p["active"] = active
    p["k"] = _uniform((n,), 0.05, 0.2, gen)  # smooth-union radius
    # displacement: sinusoids with log-uniform frequency, slope (amplitude x frequency) ~ U(0.3, 1) x 0.045
    nf = cfg["features"]
    freq = torch.exp(_uniform((n, nf), math.log(3.0), math.log(40.0), gen))
    strength = _uniform((n, 1), *cfg["detail"], gen)
    p["w"] = F.normalize(torch.randn(n, nf, 3, generator=gen, device=gen.device), dim=-1) * freq[..., None]
    p["phase"] = _uniform((n, nf), 0.0, 2 * math.pi, gen)
    p["amp"] = 0.045 * strength / freq * _uniform((n, nf), 0.3, 1.0, gen)
    return p


def _smin(a: Tensor, b: Tensor, k: Tensor) -> Tensor:
    """Polynomial smooth minimum (Quilez); k is the blend radius."""
    h = (k - (a - b).abs()).clamp_min(0.0) / k
    return torch.minimum(a, b) - h * h * k * 0.25


def blobby_sdf(p: Tensor, s: dict[str, Tensor]) -> Tensor:
    """Signed distance (a bound, up to the displacement's Lipschitz factor) of n shapes.

    Args:
        p: [n, R, 3] points (R per shape).
        s: parameters from ``sample_blobby`` (leading dimension n).
    Returns:
        [n, R] distances (negative inside).
    """
    far = 1e3
    # local coordinates of every slot: q = (p - c) R, [n, S, R, 3]
    q = torch.einsum("nrj,nsjk->nsrk", p, s["rot"]) - torch.einsum("nsj,nsjk->nsk", s["center"], s["rot"])[:, :, None]
    size, rnd = s["size"][:, :, None], s["round"][:, :, None]
    d_all = []
    i = 0
    for kind, k in SLOTS.items():
        qk, sz = q[:, i:i + k], size[:, i:i + k]
        if kind in ("ellipsoid", "dent"):
            r = sz if kind == "ellipsoid" else sz[..., :1] * 0.6  # dents are spheres
            k0 = (qk / r).norm(dim=-1)
            k1 = (qk / (r * r)).norm(dim=-1).clamp_min(1e-6)
            d = k0 * (k0 - 1.0) / k1
        elif kind == "capsule":
            half, rad = sz[..., 0] * 0.9, sz[..., 1] * 0.5
            y = torch.maximum(torch.minimum(qk[..., 1], half), -half)
            d = torch.stack([qk[..., 0], qk[..., 1] - y, qk[..., 2]], -1).norm(dim=-1) - rad
        elif kind == "torus":
            big, small = sz[..., 0] * 0.8, sz[..., 1] * 0.3
            ring = torch.stack([qk[..., 0], qk[..., 2]], -1).norm(dim=-1) - big
            d = torch.stack([ring, qk[..., 1]], -1).norm(dim=-1) - small
        else:  # rounded box
            rr = rnd[:, i:i + k]
            b = (qk.abs() - (sz * 0.8 - rr[..., None]).clamp_min(0.01))
            d = b.clamp_min(0.0).norm(dim=-1) + b.amax(dim=-1).clamp_max(0.0) - rr
        d_all.append(torch.where(s["active"][:, i:i + k, None], d, torch.full_like(d, far)))
        i += k
    d_all = torch.cat(d_all, 1)  # [n, S, R]
    k = s["k"][:, None]
    n_pos = sum(v for kk, v in SLOTS.items() if kk != "dent")
    dist = d_all[:, 0]
    for j in range(1, n_pos):
        dist = _smin(dist, d_all[:, j], k)
    for j in range(n_pos, d_all.shape[1]):  # smooth subtraction: max(d, -dent)
        dist = -_smin(-dist, d_all[:, j], k * 0.5)
    disp = torch.sin(torch.einsum("nrj,nfj->nrf", p, s["w"]) + s["phase"][:, None]) @ s["amp"][..., None]
    return dist + disp[..., 0]


def lipschitz(s: dict[str, Tensor]) -> Tensor:
    """[n] step divisor for sphere tracing ``blobby_sdf``: 1 + 1.5 x the RMS sum of the
    displacement slopes |a w|. Not a strict bound (that is sum |a w|, reached only when every
    sinusoid peaks at once), but random phases make that rare: against strict-bound tracing
    with 600 steps it disagrees on fewer silhouette pixels, and it is 1.5x faster."""
    return 1.0 + 1.5 * ((s["amp"] * s["w"].norm(dim=-1)) ** 2).sum(-1).sqrt()


def _march(s: dict[str, Tensor], sdf, x: Tensor, y: Tensor, ids: Tensor, z: Tensor, floor: float,
           stop: Tensor, steps: int, surface: bool = False) -> tuple[Tensor, Tensor]:
    """Sphere-trace rays (one set per shape) down -z until the SDF falls below ``stop`` (with
    ``surface``: until |SDF| does, so a ray that overshot inside steps back out).

    Args:
        x, y: [Q] ray positions; ids: [n, K] the rays of each shape; z: [n, K] start heights.
        floor: rays below this height have left the object's bound.
        stop: [n, 1] stopping distance per shape (SDF units).
    Returns:
        z_stop [n, Q]: where each ray stopped (NaN: it left the bound, or was never traced),
        z_prev [n, Q]: the ray's previous position (every point of the ray above it had an
            empty ball of radius >= stop / Lipschitz around it).
    Rays still marching after ``steps`` report their current position in both.
    """
    n = z.shape[0]
    scale = (0.9 / lipschitz(s))[:, None]
    nan = float("nan")
    z_stop = torch.full((n, x.numel()), nan, device=z.device)
    z_prev = torch.full((n, x.numel()), nan, device=z.device)
    prev = z.clone()
    live = torch.ones_like(z, dtype=torch.bool)  # entries of shapes with fewer rays are padding
    for it in range(steps):
        d = sdf(torch.stack([x[ids], y[ids], z], -1), s)
        done = (d.abs() if surface else d) < stop
        prev = torch.where(done, prev, z)
        z = torch.where(done, z, z - d * scale)
        last = it == steps - 1
        if it % 8 == 7 or last:
            out = live & (done | last)
            z_stop.scatter_(1, ids, torch.where(out, z, z_stop.gather(1, ids)))
            z_prev.scatter_(1, ids, torch.where(out, prev, z_prev.gather(1, ids)))
            live = live & ~done & (z >= floor)
            if last or not live.any():
                break
            k = int(live.sum(1).max())
            order = torch.argsort((~live).to(torch.int8), dim=1, stable=True)[:, :k]
            ids, z, prev, live = (t.gather(1, order) for t in (ids, z, prev, live))
    return z_stop, z_prev


def render_sdf(s: dict[str, Tensor], size: int,
               sdf: Callable[[Tensor, dict[str, Tensor]], Tensor] = blobby_sdf, steps: int = BLOBBY["steps"],
               bound: float = 1.0, name: str = "blobby", block: int = 4) -> GBuffer:
    """Sphere-trace n SDF shapes into size x size G-buffers (orthographic, rays along -z).

    The object must lie within the ball of radius ``bound``. Steps are the SDF divided by its
    Lipschitz bound. Cone marching saves most of the work: one coarse ray per ``block`` x
    ``block`` pixels marches while its empty ball is wider than the block, so the block's rays
    start where it stopped, and skip entirely when it missed. Finished rays leave the working
    set every few steps, so the cost follows the rays still marching.
    """
    n = s["k"].shape[0]
    dev = s["k"].device
    px = 2.0 / size
    lip = lipschitz(s)[:, None]
    x, y = pixel_xy(size, size, dev)
    x, y = x.reshape(-1), y.reshape(-1)
    # coarse level: one ray per block, at the block centre
    nb = size // block
    if nb * block == size and block > 1:
        xc, yc = pixel_xy(nb, nb, dev)
        xc, yc = xc.reshape(-1), yc.reshape(-1)
        reach = (block - 1) / 2 * math.sqrt(2) * px + 1e-6  # block centre to its farthest pixel centre
        inside = ((xc * xc + yc * yc).sqrt() < bound + reach).nonzero()[:, 0]
        ids = inside[None].expand(n, -1)
        _, zc_prev = _march(s, sdf, xc, yc, ids, torch.full(ids.shape, bound, device=dev), -bound,
                                  1.2 * reach * lip, steps)
        # each pixel starts where its block's ray last had an empty ball wider than the block
        r, c = torch.arange(size, device=dev) // block, torch.arange(size, device=dev) // block
        parent = (r[:, None] * nb + c[None, :]).reshape(-1)
        start = zc_prev[:, parent]  # [n, Q]; NaN where the block's ray missed
    else:
        inside = ((x * x + y * y) < bound * bound)
        start = torch.where(inside, (bound * bound - x * x - y * y).clamp_min(0).sqrt(),
                            torch.full_like(x, float("nan")))[None].expand(n, -1)
    # fine level: pixels whose coarse ray did not miss
    todo = start.isfinite()
    k = int(todo.sum(1).max()) if todo.any() else 0
    z_hit = torch.full((n, size * size), float("nan"), device=dev)
    if k:
        order = torch.argsort((~todo).to(torch.int8), dim=1, stable=True)[:, :k]
        z0 = torch.nan_to_num(start.gather(1, order), nan=-2 * bound)  # padding: already below the floor
        z_hit, _ = _march(s, sdf, x, y, order, z0, -bound, torch.full((n, 1), 0.05 * px, device=dev), steps,
                          surface=True)
    # normals from central differences of the SDF, evaluated at the candidate hits only
    cand = z_hit.isfinite()
    normal = torch.zeros(n, 3, size * size, device=dev)
    depth = torch.full((n, size * size), BACKGROUND, device=dev)
    hit = torch.zeros(n, size * size, dtype=torch.bool, device=dev)
    k = int(cand.sum(1).max()) if cand.any() else 0
    if k:
        ids = torch.argsort((~cand).to(torch.int8), dim=1, stable=True)[:, :k]
        valid = cand.gather(1, ids)
        zz = torch.nan_to_num(z_hit.gather(1, ids), nan=0.0)
        p = torch.stack([x[ids], y[ids], zz], -1)
        # rays that ran out of steps (grazing silhouettes) count only within a quarter pixel
        valid &= sdf(p, s).abs() < 0.25 * px
        grads = []
        for axis in range(3):
            off = torch.zeros(3, device=dev)
            off[axis] = 0.5 * px
            grads.append(sdf(p + off, s) - sdf(p - off, s))
        nrm = F.normalize(torch.stack(grads, 1), dim=1)  # [n, 3, k]
        nrm[:, 2].clamp_(min=1e-3)  # the visible side faces the camera
        nrm = F.normalize(nrm, dim=1) * valid[:, None]
        # ids is a permutation prefix (no repeats); padding entries have valid False
        normal.scatter_(2, ids[:, None].expand(n, 3, k), nrm)
        depth.scatter_(1, ids, torch.where(valid, zz, torch.full_like(zz, BACKGROUND)))
        hit.scatter_(1, ids, valid)
    return GBuffer(normal.reshape(n, 3, size, size), depth.reshape(n, 1, size, size),
                   hit.reshape(n, 1, size, size), [name] * n)


def blobby_gbuffers(n: int, size: int, gen: torch.Generator, config: dict | None = None,
                    chunk: int = 8) -> GBuffer:
    """n random blobby shapes as size x size G-buffers (rendered ``chunk`` shapes at a time)."""
    cfg = {**BLOBBY, **(config or {})}
    out = []
    for start in range(0, n, chunk):
        params = sample_blobby(min(chunk, n - start), gen, cfg)
        out.append(render_sdf(params, size, steps=cfg["steps"]))
    return GBuffer.cat(out)
