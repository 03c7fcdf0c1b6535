"""Materials: BRDFs as pure tensor functions, random material batches, spatially varying maps.

Every BRDF here is isotropic and depends on the geometry only through four dot products

    nl = n.l,  nv = n.v,  nh = n.h,  lh = l.h (= v.h),   h = normalize(l + v)

so one code path shades a whole batch whatever the model. A material is "kd / pi + a specular
lobe"; the lobe is written as

    spec = c1 * S1 + c2 * S2,   S1 = F1 * D * G / (pi * nl * nv),   S2 = D * G * (1 - lh)^5 / (pi * nl * nv)

with RGB colours c1, c2 and scalar lobes S1, S2:
  * ABC (Low et al. 2012), the fits of the 100 MERL materials (table and formula in
    merl_abc.json / ../shared/data/merl/README.md):
        D = 1 / (1 + B (1 - nh))^C,  G = min(1, 2 nh nl / lh, 2 nh nv / lh) (V-groove),
        F1 = unpolarised Fresnel of a dielectric of index ior,  c1 = A (RGB),  c2 = 0.
  * GGX / Cook-Torrance (Walter et al. 2007) with separable Smith G, written in the same form
    (D -> pi/4 D_ggx, G -> G1(nl) G1(nv)):
        dielectric: F1 = Fresnel(ior), c1 = specular scale, c2 = 0
        metallic:   Schlick F = F0 + (1 - F0)(1 - lh)^5, i.e. F1 = 1, c1 = F0, c2 = 1 - F0.
  * Lambertian: c1 = c2 = 0.
All are reciprocal (symmetric in nl <-> nv) and non-negative.

A batch of B materials is a dict of tensors with leading dimension B:
    kd [B,3], c1 [B,3], c2 [B,3], abc [B] bool, b [B], c [B], alpha [B], ior [B], metal [B] bool.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from psctl.errors import PsctlError

MERL_FILE = "merl_abc_fits.json"
PACKAGED_MERL = Path(__file__).with_name("merl_abc.json")
MODELS = ("merl", "ggx", "lambert")
BLENDS = ("ramp", "checker", "irregular")

Material = dict[str, Tensor]


# --------------------------------------------------------------------------------------------
# The MERL ABC table
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MerlTable:
    """The ABC fits of the MERL materials as tensors (one row per material)."""

    names: tuple[str, ...]
    kd: Tensor  # [M, 3]
    a: Tensor  # [M, 3]
    b: Tensor  # [M]
    c: Tensor  # [M]
    ior: Tensor  # [M]
    path: Path

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise PsctlError(self.path, f"no MERL material named {name!r}") from None

    def to(self, device: str | torch.device) -> "MerlTable":
        return MerlTable(self.names, self.kd.to(device), self.a.to(device), self.b.to(device),
                         self.c.to(device), self.ior.to(device), self.path)


def find_merl_file() -> Path:
    """The ABC table to use, first found of: $PSCTL_MERL (a file or a folder holding
    merl_abc_fits.json), $PSCTL_DATA/merl/, the copy shipped in this package, and
    ../shared/data/merl/ next to the repository."""
    candidates: list[Path] = []
    if os.environ.get("PSCTL_MERL"):  # set explicitly: it must be right
        p = Path(os.environ["PSCTL_MERL"])
        p = p / MERL_FILE if p.is_dir() else p
        if not p.is_file():
            raise PsctlError(p, "PSCTL_MERL does not point to merl_abc_fits.json (or a folder holding it)")
        return p
    if os.environ.get("PSCTL_DATA"):
        candidates.append(Path(os.environ["PSCTL_DATA"]) / "merl" / MERL_FILE)
    candidates.append(PACKAGED_MERL)
    from psctl.paths import checkout_root

    root = checkout_root()
    if root is not None:  # psctl's development data sits beside its checkout
        candidates.append(root.parent / "shared" / "data" / "merl" / MERL_FILE)
    for c in candidates:
        if c.is_file():
            return c
    raise PsctlError(candidates[0], "MERL ABC table not found: set PSCTL_MERL to merl_abc_fits.json "
                                    "(or PSCTL_DATA to a folder holding merl/merl_abc_fits.json)")


def load_merl(path: str | os.PathLike | None = None, device: str | torch.device = "cpu") -> MerlTable:
    """Read the ABC table (see ``find_merl_file`` for where it is looked for)."""
    path = Path(path) if path is not None else find_merl_file()
    try:
        mats = json.loads(path.read_text(encoding="utf-8"))["materials"]
        names = tuple(mats)
        rows = [mats[n] for n in names]
        kd = torch.tensor([r["kD"] for r in rows], dtype=torch.float32)
        a = torch.tensor([r["A"] for r in rows], dtype=torch.float32)
        b = torch.tensor([float(r["B"]) for r in rows], dtype=torch.float32)
        c = torch.tensor([float(r["C"]) for r in rows], dtype=torch.float32)
        ior = torch.tensor([float(r["ior"]) for r in rows], dtype=torch.float32)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise PsctlError(path, f"not a MERL ABC table ({e.__class__.__name__}: {e})") from None
    if not names or kd.shape != (len(names), 3) or a.shape != (len(names), 3):
        raise PsctlError(path, "not a MERL ABC table (expected kD and A as RGB triples)")
    return MerlTable(names, kd, a, b, c, ior, path).to(device)


# --------------------------------------------------------------------------------------------
# BRDF evaluation
# --------------------------------------------------------------------------------------------


def fresnel_dielectric(cos_i: Tensor, ior: Tensor) -> Tensor:
    """Unpolarised Fresnel reflectance of a dielectric of real index ``ior`` (> 1) at incidence
    cosine ``cos_i`` (exact formula, e.g. Cook & Torrance 1982)."""
    c = cos_i.clamp(0.0, 1.0)
    g = (ior * ior - 1.0 + c * c).clamp_min(0.0).sqrt()
    a = (g - c) / (g + c).clamp_min(1e-12)
    b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0).clamp_min(1e-12)
    return 0.5 * a * a * (1.0 + b * b)


def _bc(x: Tensor, ndim: int) -> Tensor:
    """A per-material value [B] viewed as [B, 1, ..., 1] to broadcast against ndim-dim tensors."""
    return x.reshape(x.shape[0], *([1] * (ndim - 1)))


def lobes(mat: Material, nl: Tensor, nv: Tensor, nh: Tensor, lh: Tensor) -> tuple[Tensor, Tensor]:
    """The scalar specular lobes (S1, S2) of the module docstring.

    Args:
        mat: a material batch (fields [B] / [B, 3]).
        nl, nv, nh, lh: dot products, [B, ...] (broadcastable to each other).
    Returns:
        S1, S2 with the broadcast shape of the dot products, 0 where nl <= 0 or nv <= 0.
    """
    nd = max(t.ndim for t in (nl, nv, nh, lh))
    shape = torch.broadcast_shapes(nl.shape, nv.shape, nh.shape, lh.shape)
    nl_, nv_ = nl.clamp_min(1e-6), nv.clamp_min(1e-6)
    nh_, lh_ = nh.clamp(0.0, 1.0), lh.clamp(1e-6, 1.0)
    abc = mat["abc"]

    def part(sel: Tensor | slice | None, use_abc: bool) -> Tensor:
        # D G / (pi nl nv) for the materials in ``sel`` (all when None), one model
        def pick(t: Tensor) -> Tensor:
            return t if sel is None or t.shape[0] == 1 else t[sel]

        a, v, h, q = pick(nl_), pick(nv_), pick(nh_), pick(lh_)
        m = (lambda k: _bc(mat[k] if sel is None else mat[k][sel], nd))
        if use_abc:  # ABC: D / pi and the V-groove G
            d = torch.pow(1.0 + m("b") * (1.0 - h), -m("c")) * (1.0 / math.pi)
            g = (2.0 * h / q * torch.minimum(a, v)).clamp_max(1.0)
            return d * g / (a * v)
        # GGX: D / 4 (so that D G / (pi nl nv) equals D_ggx G / (4 nl nv)) and separable Smith G
        alpha2 = m("alpha") ** 2
        t = h * h * (alpha2 - 1.0) + 1.0
        g1a = 2.0 / (1.0 + (alpha2 / (a * a) + (1.0 - alpha2)).sqrt())  # = G1(nl)
        g1v = 2.0 / (1.0 + (alpha2 / (v * v) + (1.0 - alpha2)).sqrt())
        return alpha2 / (4.0 * math.pi * t * t) * g1a * g1v / (a * v)

    # evaluate each model only on its own materials (ABC ones first makes both parts slices)
    k = int(abc.sum())
    if k == len(abc):
        s0 = part(None, True).expand(shape)
    elif k == 0:
        s0 = part(None, False).expand(shape)
    elif bool(abc[:k].all()):
        s0 = torch.cat([part(slice(0, k), True).expand(k, *shape[1:]),
                        part(slice(k, None), False).expand(len(abc) - k, *shape[1:])])
    else:
        s0 = torch.empty(shape, device=nl.device)
        ia, ig = abc.nonzero()[:, 0], (~abc).nonzero()[:, 0]
        s0[ia] = part(ia, True).expand(len(ia), *shape[1:])
        s0[ig] = part(ig, False).expand(len(ig), *shape[1:])
    s0 = s0 * ((nl > 0) & (nv > 0))
    metal = mat["metal"]
    if not bool(metal.any()):  # S2 only matters for metals (its colour c2 is 0 otherwise)
        return s0 * fresnel_dielectric(lh_, _bc(mat["ior"], nd)), torch.zeros_like(s0)
    s1 = torch.where(_bc(metal, nd), s0, s0 * fresnel_dielectric(lh_, _bc(mat["ior"], nd)))
    return s1, s0 * (1.0 - lh_) ** 5


def brdf(mat: Material, n: Tensor, l: Tensor, v: Tensor) -> Tensor:
    """f(n, l, v) for arbitrary unit vectors (reference path, used by tests and tools).

    Args:
        mat: a material batch of B materials.
        n, l, v: [B, ..., 3] unit vectors.
    Returns:
        [B, ..., 3] RGB BRDF values (1/sr); 0 when l or v is below the surface.
    """
    h = F.normalize(l + v, dim=-1)
    nl, nv = (n * l).sum(-1), (n * v).sum(-1)
    nh, lh = (n * h).sum(-1), (l * h).sum(-1)
    s1, s2 = lobes(mat, nl, nv, nh, lh)
    nd = nl.ndim + 1
    kd, c1, c2 = (mat[k].reshape(mat[k].shape[0], *([1] * (nd - 2)), 3) for k in ("kd", "c1", "c2"))
    front = ((nl > 0) & (nv > 0)).unsqueeze(-1)
    f = kd / math.pi * front + c1 * s1.unsqueeze(-1) + c2 * s2.unsqueeze(-1)
    return f


# --------------------------------------------------------------------------------------------
# Material batches
# --------------------------------------------------------------------------------------------


def _empty(n: int, device: torch.device | str) -> Material:
    z3 = torch.zeros(n, 3, device=device)
    z = torch.zeros(n, device=device)
    return {"kd": z3.clone(), "c1": z3.clone(), "c2": z3.clone(), "abc": torch.zeros(n, dtype=torch.bool, device=device),
            "b": z.clone(), "c": z.clone(), "alpha": torch.full((n,), 0.5, device=device),
            "ior": torch.full((n,), 1.5, device=device), "metal": torch.zeros(n, dtype=torch.bool, device=device)}


def merl_materials(table: MerlTable, idx: Tensor | list[int]) -> Material:
    """Materials from rows ``idx`` of the ABC table."""
    idx = torch.as_tensor(idx, dtype=torch.long, device=table.kd.device)
    mat = _empty(len(idx), table.kd.device)
    mat.update(kd=table.kd[idx], c1=table.a[idx], abc=torch.ones(len(idx), dtype=torch.bool, device=idx.device),
               b=table.b[idx], c=table.c[idx], ior=table.ior[idx])
    return mat


def lambertian(kd: Tensor) -> Material:
    """Lambertian materials of albedo ``kd`` [B, 3] (f = kd / pi)."""
    mat = _empty(kd.shape[0], kd.device)
    mat["kd"] = kd
    return mat


def ggx(kd: Tensor, spec: Tensor, alpha: Tensor, ior: Tensor | None = None, metal: Tensor | None = None) -> Material:
    """GGX materials: diffuse ``kd`` [B,3] plus a microfacet lobe of roughness ``alpha`` [B].

    Dielectric (metal False): ``spec`` [B,3] scales a lobe with exact Fresnel of index ``ior``.
    Metallic (metal True): ``spec`` is the Schlick F0 colour.
    """
    b = kd.shape[0]
    mat = _empty(b, kd.device)
    metal = torch.zeros(b, dtype=torch.bool, device=kd.device) if metal is None else metal.bool()
    mat.update(kd=kd, alpha=alpha, metal=metal, c1=spec,
               c2=torch.where(metal[:, None], 1.0 - spec, torch.zeros_like(spec)))
    if ior is not None:
        mat["ior"] = ior
    return mat


def random_colors(n: int, gen: torch.Generator, value: tuple[float, float] = (0.1, 0.9),
                  max_saturation: float = 0.7) -> Tensor:
    """[n, 3] random RGB colours from a uniform hue, saturation in [0, max], value in range."""
    dev = gen.device
    h = torch.rand(n, generator=gen, device=dev) * 6.0
    s = torch.rand(n, generator=gen, device=dev) * max_saturation
    v = value[0] + torch.rand(n, generator=gen, device=dev) * (value[1] - value[0])
    k = (torch.tensor([5.0, 3.0, 1.0], device=dev)[None, :] + h[:, None]) % 6.0  # HSV -> RGB
    return v[:, None] * (1.0 - s[:, None] * (torch.minimum(k, 4.0 - k).clamp(0.0, 1.0)))


def sample_materials(n: int, gen: torch.Generator, table: MerlTable | None,
                     probs: dict[str, float] | None = None, merl_names: list[str] | None = None) -> Material:
    """n random materials: MERL (ABC fits), GGX (dielectric or metallic) or Lambertian.

    Args:
        probs: {"merl": p, "ggx": p, "lambert": p} (normalised here); "merl" needs ``table``.
        merl_names: restrict MERL draws to these materials (default: all).
    """
    dev = gen.device
    probs = dict(probs or {"merl": 0.5, "ggx": 0.35, "lambert": 0.15})
    bad = set(probs) - set(MODELS)
    if bad:
        raise PsctlError(None, f"unknown material model(s) {sorted(bad)}; choose from {', '.join(MODELS)}")
    if table is None:
        probs.pop("merl", None)
    w = torch.tensor([max(probs.get(m, 0.0), 0.0) for m in MODELS], device=dev)
    if w.sum() <= 0:
        raise PsctlError(None, "material probabilities are all zero")
    model = torch.multinomial(w / w.sum(), n, replacement=True, generator=gen)  # 0 merl, 1 ggx, 2 lambert

    # GGX draws for everyone (cheap), then MERL rows where chosen.
    kd = random_colors(n, gen)
    metal = torch.rand(n, generator=gen, device=dev) < 0.3
    alpha = torch.exp(torch.empty(n, device=dev).uniform_(math.log(0.03), math.log(0.6), generator=gen))
    ior = 1.3 + 0.6 * torch.rand(n, generator=gen, device=dev)
    spec_d = (0.5 + torch.rand(n, 1, generator=gen, device=dev)).expand(n, 3)
    f0 = random_colors(n, gen, value=(0.5, 1.0), max_saturation=0.5)
    kd = torch.where(metal[:, None], kd * 0.05 * torch.rand(n, 1, generator=gen, device=dev), kd)
    mat = ggx(kd, torch.where(metal[:, None], f0, spec_d), alpha, ior, metal)
    lam = model == 2
    for k in ("c1", "c2"):
        mat[k] = torch.where(lam[:, None], torch.zeros_like(mat[k]), mat[k])
    mat["metal"] = mat["metal"] & ~lam
    if table is not None:
        pool = (torch.arange(len(table.names), device=dev) if merl_names is None
                else torch.tensor([table.index(m) for m in merl_names], device=dev))
        rows = pool[torch.randint(len(pool), (n,), generator=gen, device=dev)]
        is_merl = model == 0
        merl = merl_materials(table, rows)
        for k in mat:
            sel = is_merl.reshape(n, *([1] * (mat[k].ndim - 1)))
            mat[k] = torch.where(sel, merl[k], mat[k])
    return mat


def take(mat: Material, idx: Tensor) -> Material:
    """The materials at ``idx``."""
    return {k: v[idx] for k, v in mat.items()}


# --------------------------------------------------------------------------------------------
# Spatially varying maps (in image coordinates)
# --------------------------------------------------------------------------------------------


def image_coords(h: int, w: int, device: torch.device | str = "cpu") -> tuple[Tensor, Tensor]:
    """Pixel-centre coordinates [H, W]: x in [-1, 1] left to right, y in [1, -1] top to bottom."""
    x = (torch.arange(w, device=device) + 0.5) / w * 2 - 1
    y = 1 - (torch.arange(h, device=device) + 0.5) / h * 2
    return x[None, :].expand(h, w), y[:, None].expand(h, w)


def smooth_noise(b: int, c: int, h: int, w: int, gen: torch.Generator, cells: int = 4) -> Tensor:
    """[b, c, h, w] smooth random field in [0, 1] (bicubic upsampling of a cells x cells grid)."""
    g = torch.rand(b, c, cells, cells, generator=gen, device=gen.device)
    x = F.interpolate(g, size=(h, w), mode="bicubic", align_corners=False)
    lo = x.amin(dim=(2, 3), keepdim=True)
    hi = x.amax(dim=(2, 3), keepdim=True)
    return (x - lo) / (hi - lo).clamp_min(1e-6)


def blend_weights(kinds: list[str], h: int, w: int, gen: torch.Generator) -> Tensor:
    """[B, 1, h, w] weights in [0, 1] of material A in an A/B blend, one map per kind:
    "ramp" (a soft linear gradient), "checker" (a rotated checkerboard with soft edges),
    "irregular" (thresholded smooth noise: blotches), "none" (all 1)."""
    dev = gen.device
    b = len(kinds)
    x, y = image_coords(h, w, dev)
    x, y = x[None], y[None]
    ang = torch.rand(b, 1, 1, generator=gen, device=dev) * 2 * math.pi
    xr = x * torch.cos(ang) + y * torch.sin(ang)
    yr = -x * torch.sin(ang) + y * torch.cos(ang)
    width = 1.0 + 1.5 * torch.rand(b, 1, 1, generator=gen, device=dev)
    ramp = (0.5 + xr / width).clamp(0.0, 1.0)
    period = 0.15 + 0.45 * torch.rand(b, 1, 1, generator=gen, device=dev)
    off = torch.rand(b, 2, 1, 1, generator=gen, device=dev) * 2
    checker = torch.sigmoid(30.0 * torch.sin(math.pi * (xr / period + off[:, 0])) *
                            torch.sin(math.pi * (yr / period + off[:, 1])))
    noise = 0.7 * smooth_noise(b, 1, h, w, gen, 4)[:, 0] + 0.3 * smooth_noise(b, 1, h, w, gen, 9)[:, 0]
    thr = 0.35 + 0.3 * torch.rand(b, 1, 1, generator=gen, device=dev)
    irregular = torch.sigmoid(25.0 * (noise - thr))
    out = torch.ones(b, h, w, device=dev)
    for i, k in enumerate(kinds):
        if k == "ramp":
            out[i] = ramp[i]
        elif k == "checker":
            out[i] = checker[i]
        elif k == "irregular":
            out[i] = irregular[i]
        elif k != "none":
            raise PsctlError(None, f"unknown blend map {k!r}; choose from {', '.join(BLENDS)}")
    return out[:, None]


def albedo_texture(b: int, h: int, w: int, gen: torch.Generator, strength: float = 0.6) -> Tensor:
    """[b, 3, h, w] multiplicative albedo texture around 1: smooth brightness blotches at two
    scales plus a milder colour variation."""
    dev = gen.device
    s = strength * torch.rand(b, 1, 1, 1, generator=gen, device=dev)
    cells = int(torch.randint(3, 10, (1,), generator=gen, device=dev))
    lum = 0.6 * smooth_noise(b, 1, h, w, gen, cells) + 0.4 * smooth_noise(b, 1, h, w, gen, 2 * cells + 1)
    col = smooth_noise(b, 3, h, w, gen, cells)
    return (1.0 + s * (2.0 * lum - 1.0)) * (1.0 + 0.5 * s * (2.0 * col - 1.0))
