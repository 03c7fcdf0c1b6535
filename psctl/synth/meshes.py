"""Triangle meshes (OBJ) as orthographic G-buffers, and a cache of rendered views.

``load_obj`` reads vertices and faces; ``mesh_views`` rotates a mesh and rasterises it with a
small z-buffer rasteriser written in torch (each triangle tests the pixels of its bounding box;
triangles are grouped by bounding-box size so the work stays proportional to the covered
pixels). Normals are the barycentric interpolation of area-weighted vertex normals, depth the
interpolated z.

Shapes: ``lucy`` is for training; ``bunny``, ``dragon``, ``armadillo`` (and the analytic sphere)
are test shapes only, and ``check_training_meshes`` refuses them.

Rasterising a 100k-triangle view at 128 x 128 takes about 20 ms, so where the OBJ files are
the training stream renders fresh random views. For a machine without them (the GPU machine),
render views once into a .npz under the git-ignored .cache/ folder and carry it:

    python -m psctl.synth.meshes lucy --views 256 --size 128 --out .cache/synth/lucy_views.npz
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from psctl.errors import PsctlError
from psctl.synth.shapes import BACKGROUND, GBuffer, random_rotations

TEST_SHAPES = ("sphere", "bunny", "dragon", "armadillo")


def mesh_dir() -> Path:
    """Folder of the OBJ meshes: $PSCTL_MESHES, $PSCTL_DATA/meshes, else ../shared/data/meshes
    next to the source checkout psctl runs from, or (an installed wheel) ~/.local/share/psctl/meshes.
    It may not exist (the caller decides whether that is an error)."""
    if os.environ.get("PSCTL_MESHES"):
        return Path(os.environ["PSCTL_MESHES"])
    if os.environ.get("PSCTL_DATA"):
        return Path(os.environ["PSCTL_DATA"]) / "meshes"
    from psctl.paths import checkout_root, user_data_dir

    root = checkout_root()  # psctl's development data sits beside its checkout
    return root.parent / "shared" / "data" / "meshes" if root is not None else user_data_dir() / "meshes"


def find_mesh(name: str, folder: str | os.PathLike | None = None) -> Path:
    """The OBJ file of a named mesh (``bunny`` -> <mesh_dir>/bunny.obj), or a path as given."""
    p = Path(name)
    if p.suffix.lower() == ".obj":
        if not p.is_file():
            raise PsctlError(p, "mesh file is missing")
        return p
    folder = Path(folder) if folder is not None else mesh_dir()
    p = folder / f"{name}.obj"
    if not p.is_file():
        raise PsctlError(p, f"mesh {name!r} not found: put {name}.obj there, or set PSCTL_MESHES to a folder "
                            f"that holds it (psctl ships no meshes; docs/synthetic.md, 'Meshes')")
    return p


def check_training_meshes(names: list[str] | tuple[str, ...]) -> None:
    """Refuse test shapes as training data (the paper's SynTest shapes must stay unseen)."""
    for n in names:
        if Path(n).stem.lower() in TEST_SHAPES:
            raise PsctlError(None, f"{n!r} is a test shape ({', '.join(TEST_SHAPES)}): never train on it")


def load_obj(path: str | os.PathLike) -> tuple[Tensor, Tensor]:
    """Vertices [V, 3] float32 and triangles [F, 3] int64 (polygons are fanned) of an OBJ file."""
    path = Path(path)
    try:
        text = path.read_text(errors="replace")
    except OSError as e:
        raise PsctlError(path, f"cannot read mesh ({e.strerror or e})") from None
    lines = text.splitlines()
    vlines = [ln[2:] for ln in lines if ln.startswith("v ")]
    flines = [ln[2:] for ln in lines if ln.startswith("f ")]
    try:  # fast path: x y z vertices and plain triangles
        v = np.array(" ".join(vlines).split(), dtype=np.float32).reshape(-1, 3)
        f = np.array(" ".join(flines).split(), dtype=np.int64).reshape(-1, 3)
        if not len(v) or not len(f) or any(len(ln.split()) != 3 for ln in (*vlines, *flines)):  # 3 per line
            raise ValueError
        f = np.where(f > 0, f - 1, len(v) + f)
        if f.min() < 0 or f.max() >= len(v):
            raise PsctlError(path, "face indices out of range")
        return _checked(path, v, f)
    except (ValueError, OverflowError):
        pass  # texture/normal indices, polygons, extra columns: the general parser below
    verts: list[list[float]] = []
    faces: list[list[int]] = []
    for lineno, line in enumerate(lines, 1):
        if line.startswith("v "):
            parts = line.split()[1:]
            try:
                if len(parts) < 3:
                    raise ValueError
                verts.append([float(t) for t in parts[:3]])
            except ValueError:
                raise PsctlError(path, f"line {lineno}: bad vertex {line.strip()!r} (x y z expected)") from None
        elif line.startswith("f "):
            try:
                idx = [int(t.split("/")[0]) for t in line.split()[1:]]
            except ValueError:
                raise PsctlError(path, f"line {lineno}: bad face {line.strip()!r}") from None
            idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
            if len(idx) < 3 or min(idx) < 0 or max(idx) >= len(verts):
                raise PsctlError(path, f"line {lineno}: bad face {line.strip()!r} (3 or more indices of "
                                       "vertices listed before it)")
            faces += [[idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1)]
    if not verts or not faces:
        raise PsctlError(path, "mesh has no vertices or no faces")
    return _checked(path, np.array(verts, np.float32), np.array(faces, np.int64))


def _checked(path: Path, v: np.ndarray, f: np.ndarray) -> tuple[Tensor, Tensor]:
    """What every view of a mesh needs: finite vertices, spread over some space."""
    if not np.isfinite(v).all():
        raise PsctlError(path, "mesh has NaN or infinite vertex coordinates")
    if not (v.max(0) - v.min(0)).max() > 0:
        raise PsctlError(path, "mesh has zero size (every vertex at one point)")
    tri = v[f].astype(np.float64)  # [F, 3, 3]; relative to the mesh's size, so its units do not matter
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=-1).sum()
    corners = tri.reshape(-1, 3)  # the faces' own extent: a stray unused vertex far away does not count
    if not area > 1e-12 * float((corners.max(0) - corners.min(0)).max()) ** 2:  # every view would be empty
        raise PsctlError(path, "mesh has no surface: every face has zero area (its vertices on one line)")
    return torch.from_numpy(v), torch.from_numpy(f)


def normalize_mesh(verts: Tensor) -> Tensor:
    """Centre on the bounding-box centre and scale so that the farthest vertex is at distance 1
    (so any rotation of the mesh fits in the unit ball)."""
    c = (verts.amin(0) + verts.amax(0)) / 2
    v = verts - c
    return v / v.norm(dim=1).max()


def vertex_normals(verts: Tensor, faces: Tensor) -> Tensor:
    """[V, 3] area-weighted vertex normals (outward for a consistently wound closed mesh)."""
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    fn = torch.cross(b - a, c - a, dim=1)  # length = 2 x area
    vn = torch.zeros_like(verts)
    for k in range(3):
        vn.index_add_(0, faces[:, k], fn)
    # orient outward: the signed volume of a closed outward mesh is positive
    if (a * torch.cross(b, c, dim=1)).sum() < 0:
        vn = -vn
    return F.normalize(vn, dim=1)


def rasterize(verts: Tensor, faces: Tensor, vnormals: Tensor, size: int, max_candidates: int = 2_000_000) -> tuple[Tensor, Tensor, Tensor]:
    """Z-buffer rasterisation of one mesh already in view coordinates (x, y in [-1, 1] visible,
    z toward the camera).

    Returns:
        normals [3, S, S] (0 off the mesh), depth [1, S, S] (BACKGROUND off the mesh),
        mask [1, S, S] bool.
    """
    dev = verts.device
    s = size
    u = (verts[:, 0] + 1) / 2 * s - 0.5  # pixel-centre coordinates: column
    w = (1 - verts[:, 1]) / 2 * s - 0.5  # row
    tu, tw, tz = u[faces], w[faces], verts[faces, 2]  # [F, 3]
    c0, c1 = tu.amin(1).ceil().clamp(0, s - 1), tu.amax(1).floor().clamp(0, s - 1)
    r0, r1 = tw.amin(1).ceil().clamp(0, s - 1), tw.amax(1).floor().clamp(0, s - 1)
    extent = torch.maximum(c1 - c0, r1 - r0) + 1
    area = (tu[:, 1] - tu[:, 0]) * (tw[:, 2] - tw[:, 0]) - (tw[:, 1] - tw[:, 0]) * (tu[:, 2] - tu[:, 0])
    valid = (c1 >= c0) & (r1 >= r0) & (area.abs() > 1e-12) & (tu.amax(1) >= 0) & (tu.amin(1) <= s - 1) \
        & (tw.amax(1) >= 0) & (tw.amin(1) <= s - 1)
    # depth key: quantised z in the high bits, the face index in the low 26 bits
    zq_scale = float(2**28)
    key_buf = torch.full((s * s,), -1, dtype=torch.int64, device=dev)

    def candidates(tri: Tensor, k: int):
        oy, ox = torch.meshgrid(torch.arange(k, device=dev), torch.arange(k, device=dev), indexing="ij")
        cc = c0[tri, None] + ox.reshape(1, -1)
        rr = r0[tri, None] + oy.reshape(1, -1)
        inb = (cc <= c1[tri, None]) & (rr <= r1[tri, None])
        pu, pw = tu[tri], tw[tri]
        b0 = (pu[:, 1:2] - cc) * (pw[:, 2:3] - rr) - (pw[:, 1:2] - rr) * (pu[:, 2:3] - cc)
        b1 = (pu[:, 2:3] - cc) * (pw[:, 0:1] - rr) - (pw[:, 2:3] - rr) * (pu[:, 0:1] - cc)
        b2 = (pu[:, 0:1] - cc) * (pw[:, 1:2] - rr) - (pw[:, 0:1] - rr) * (pu[:, 1:2] - cc)
        a = area[tri, None]
        b0, b1, b2 = b0 / a, b1 / a, b2 / a
        inside = inb & (b0 >= 0) & (b1 >= 0) & (b2 >= 0)
        z = b0 * tz[tri, 0:1] + b1 * tz[tri, 1:2] + b2 * tz[tri, 2:3]
        return cc, rr, inside, z

    sizes = extent[valid]
    tris = valid.nonzero()[:, 0]
    k = 1
    while tris.numel():
        sel = sizes <= k
        group, sizes, tris = tris[sel], sizes[~sel], tris[~sel]
        step = max(1, max_candidates // (k * k))
        for start in range(0, group.numel(), step):
            tri = group[start:start + step]
            cc, rr, inside, z = candidates(tri, k)
            pix = (rr * s + cc).long()[inside]
            zk = ((z[inside] + 64.0) * zq_scale).long().clamp_min(0)  # z > -64: fits in 37 bits
            key = (zk << 26) | tri[:, None].expand_as(inside)[inside]
            key_buf.scatter_reduce_(0, pix, key, reduce="amax")
        k *= 2
    hit = key_buf >= 0
    face = torch.where(hit, key_buf & ((1 << 26) - 1), torch.zeros_like(key_buf))
    # recompute barycentrics of the winning face at each covered pixel
    pix = hit.nonzero()[:, 0]
    f = face[pix]
    cc, rr = (pix % s).float(), (pix // s).float()
    pu, pw = tu[f], tw[f]
    a = area[f]
    b0 = ((pu[:, 1] - cc) * (pw[:, 2] - rr) - (pw[:, 1] - rr) * (pu[:, 2] - cc)) / a
    b1 = ((pu[:, 2] - cc) * (pw[:, 0] - rr) - (pw[:, 2] - rr) * (pu[:, 0] - cc)) / a
    b2 = 1.0 - b0 - b1
    bary = torch.stack([b0, b1, b2], 1)[..., None]  # [P, 3, 1]
    n = F.normalize((bary * vnormals[faces[f]]).sum(1), dim=1)
    z = (bary[..., 0] * tz[f]).sum(1)
    # where interpolation tilts the normal away from the camera, use the face normal
    fv = verts[faces[f]]
    fn = F.normalize(torch.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0], dim=1), dim=1)
    fn = torch.where(fn[:, 2:3] < 0, -fn, fn)
    n = torch.where(n[:, 2:3] < 0.02, fn, n)
    n[:, 2].clamp_(min=1e-3)
    n = F.normalize(n, dim=1)
    normals = torch.zeros(3, s * s, device=dev)
    normals[:, pix] = n.T
    depth = torch.full((s * s,), BACKGROUND, device=dev)
    depth[pix] = z
    return normals.reshape(3, s, s), depth.reshape(1, s, s), hit.reshape(1, s, s)


def mesh_views(verts: Tensor, faces: Tensor, rotations: Tensor, size: int, fill: float = 0.9,
               fit: bool = True, name: str = "mesh") -> GBuffer:
    """Render a mesh under B rotations.

    Args:
        verts, faces: a mesh (any scale; normalised here).
        rotations: [B, 3, 3]; view coordinates = R @ vertex.
        fill: with ``fit``, the silhouette's bounding box is centred and its longer side spans
            this fraction of the image; without, the normalised mesh (radius 1) is scaled by
            ``fill`` about its centre, the same scale for every rotation.
    """
    v = normalize_mesh(verts)
    vn = vertex_normals(v, faces)
    out = []
    for r in rotations:
        vr, nr = v @ r.T, vn @ r.T
        if fit:
            lo, hi = vr[:, :2].amin(0), vr[:, :2].amax(0)
            centre = torch.cat([(lo + hi) / 2, vr.new_zeros(1)])
            vr = (vr - centre) * (fill / ((hi - lo).max() / 2))
        else:
            vr = vr * fill
        n, d, m = rasterize(vr, faces, nr, size)
        out.append(GBuffer(n[None], d[None], m[None], [name]))
    return GBuffer.cat(out)


def save_views(path: str | os.PathLike, g: GBuffer) -> None:
    """Write views as a compressed .npz (normals and depth as float16, mask as bool)."""
    from psctl.io.atomic import atomic_path

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, normals=g.normals.cpu().numpy().astype(np.float16),
                                depth=g.depth.cpu().numpy().astype(np.float16), mask=g.mask.cpu().numpy(),
                                names=np.array(g.names))


def load_views(path: str | os.PathLike, device: torch.device | str = "cpu") -> GBuffer:
    """Read views written by ``save_views``."""
    path = Path(path)
    try:
        with np.load(path) as z:
            normals = torch.from_numpy(z["normals"].astype(np.float32))
            depth = torch.from_numpy(z["depth"].astype(np.float32))
            mask = torch.from_numpy(z["mask"].astype(bool))
            names = [str(n) for n in z["names"]]
    except (OSError, ValueError, KeyError) as e:
        raise PsctlError(path, f"not a psctl view cache ({e})") from None
    if normals.ndim != 4 or normals.shape[1] != 3 or depth.shape[1:] != (1, *normals.shape[2:]):
        raise PsctlError(path, "not a psctl view cache (bad array shapes)")
    normals = F.normalize(normals, dim=1) * mask
    return GBuffer(normals, depth, mask, names).to(device)


def main(argv: list[str] | None = None) -> None:
    """Render training views of a mesh into a .npz that the training stream can load."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m psctl.synth.meshes", description=main.__doc__)
    ap.add_argument("mesh", help="a training mesh name (lucy) or .obj path")
    ap.add_argument("--views", type=int, default=256)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, required=True, help="output .npz")
    a = ap.parse_args(argv)
    try:
        check_training_meshes([a.mesh])
        path = find_mesh(a.mesh)
        v, f = load_obj(path)
        rots = random_rotations((a.views,), torch.Generator().manual_seed(a.seed))
        views = GBuffer.cat([mesh_views(v, f, rots[i:i + 16], a.size, name=path.stem) for i in range(0, a.views, 16)])
        save_views(a.out, views)
    except PsctlError as e:  # a user error: one line and exit 2, as psctl's commands
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    print(f"wrote {a.views} views of {path.stem} at {a.size}px to {a.out} ({a.out.stat().st_size / 1e6:.1f} MB)")


if __name__ == "__main__":
    main()
