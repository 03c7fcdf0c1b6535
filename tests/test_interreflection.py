"""Diffuse interreflections (psctl.synth.render): form factors against an exact view factor."""

import math

import numpy as np
import torch

from psctl.synth import materials as M
from psctl.synth import render as R
from psctl.synth.shapes import GBuffer, sphere_gbuffer
from psctl.synth.write import SynthObject, render_object


def v_groove(w: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    """A 90-degree V-groove along y (faces at 45 degrees, the crease farthest from the camera)."""
    px = 2 / w
    x = -1 + (torch.arange(w) + 0.5) * px
    z = x.abs()[None].expand(w, w).clone()
    s = 1 / math.sqrt(2)
    n = torch.zeros(3, w, w)
    n[0] = torch.where(x < 0, s, -s)[None].expand(w, w)
    n[2] = s
    return z[None, None], n[None]


def exact_view_factor(x0: float, grid: int = 400) -> float:
    """View factor from a point (x0 < 0, y = 0) on the groove's left face to its whole right
    face (x in (0, 1), |y| < 1), by brute-force numerical integration."""
    s2 = math.sqrt(2)
    p = np.array([x0, 0.0, -x0])
    na, nb = np.array([1.0, 0, 1]) / s2, np.array([-1.0, 0, 1]) / s2
    u = (np.arange(grid) + 0.5) / grid
    X, Y = np.meshgrid(u, -1 + 2 * u)
    d = np.stack([X, Y, X], -1) - p
    r2 = (d * d).sum(-1)
    r = np.sqrt(r2)
    g = np.clip(d @ na / r, 0, None) * np.clip(-(d @ nb) / r, 0, None) / (math.pi * r2)
    return float(g.sum() * (1 / grid) * (2 / grid) * s2)


def test_form_factors_match_the_exact_view_factor_of_a_v_groove():
    w = 64
    z, n = v_groove(w)
    K = R.interreflection_kernel(z, n)
    row_sums = (K @ torch.ones(w * w, 1)).reshape(w, w) / math.pi  # sum_q G / pi = view factor
    px = 2 / w
    for col in (0, 9, 15, 21, 27):  # more than 4 pixels from the crease (within 3, up to 15 % off)
        x0 = -1 + (col + 0.5) * px
        exact = exact_view_factor(x0)
        assert abs(float(row_sums[w // 2, col]) / exact - 1) < 0.065, (col, float(row_sums[w // 2, col]), exact)
    # symmetric faces see each other alike
    assert torch.allclose(row_sums[w // 2, :w // 2], row_sums[w // 2, w // 2:].flip(0), rtol=1e-4)


def test_convex_shapes_exchange_no_light():
    g = sphere_gbuffer(48)
    K = R.interreflection_kernel(g.depth, g.normals)
    assert K._nnz() == 0
    flat_z = torch.zeros(1, 1, 32, 32)
    flat_n = torch.zeros(1, 3, 32, 32)
    flat_n[:, 2] = 1
    assert R.interreflection_kernel(flat_z, flat_n)._nnz() == 0


def test_bounces_only_add_light_and_reach_the_face_in_attached_shadow():
    z, n = v_groove(32)
    view = GBuffer(n, z, torch.ones(1, 1, 32, 32, dtype=torch.bool), ["groove"])
    mat = M.lambertian(torch.tensor([[0.8, 0.8, 0.8]]))
    lights = torch.tensor([[0.9, 0.0, 0.436], [-0.3, 0.2, 0.933]])
    lights = lights / lights.norm(dim=1, keepdim=True)
    obj = SynthObject("groove", view, mat, lights, torch.ones(2))
    direct = render_object(obj, shadows=True)
    one = render_object(obj, shadows=True, bounces=1)
    three = render_object(obj, shadows=True, bounces=3)
    assert (one >= direct - 1e-7).all() and (three >= one - 1e-7).all()
    assert float((three - one).sum()) > 0
    gain = float((one - direct).sum() / direct.sum())
    assert 0.05 < gain < 0.8, gain  # a white groove: a noticeable, not dominant, share
    # the first light grazes the left face from the right: the right face (normal tilted to -x)
    # is in attached shadow, black without bounces and lit by the left face with them
    right = n[0, 0] < 0
    assert float(direct[0][:, right].abs().max()) == 0.0
    assert float(one[0][:, right].min()) > 0.0


def _kernel_one_offset_at_a_time(depth, normals, bias_px=0.5, min_nz=0.1):
    """The form factors as first written: one offset per Python step, all pixels at once (what
    the batched kernel must reproduce bit for bit)."""
    _, _, h, w = depth.shape
    px, z, n = 2.0 / w, depth[0, 0], normals[0]
    obj = z > -5.0  # BACKGROUND is -10
    offs, areas = R.interreflection_offsets(math.hypot(h, w))
    ii, jj = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    rows, cols, vals = [], [], []
    for (dx, dy), a in zip(offs.tolist(), areas.tolist()):
        qi, qj = ii + dy, jj + dx
        ok = obj & (qi >= 0) & (qi < h) & (qj >= 0) & (qj < w)
        qi, qj = qi.clamp(0, h - 1), qj.clamp(0, w - 1)
        ok &= obj[qi, qj]
        dz = z[qi, qj] - z
        d = torch.stack([torch.full_like(dz, dx * px), torch.full_like(dz, -dy * px), dz])
        r2 = (d * d).sum(0)
        cos_p = (n * d).sum(0) / r2.sqrt()
        nq = n[:, qi, qj]
        cos_q = -(nq * d).sum(0) / r2.sqrt()
        ok &= (cos_p > 0) & (cos_q > 0)
        for t in (0.25, 0.5, 0.75):
            si, sj = (ii + round(t * dy)).clamp(0, h - 1), (jj + round(t * dx)).clamp(0, w - 1)
            ok &= z[si, sj] <= z + t * dz + bias_px * px
        g = cos_p * cos_q * (px * px * a / nq[2].clamp_min(min_nz)) / r2
        rows.append((ii * w + jj)[ok]), cols.append((qi * w + qj)[ok]), vals.append(g[ok])
    return torch.sparse_coo_tensor(torch.stack([torch.cat(rows), torch.cat(cols)]), torch.cat(vals),
                                   (h * w, h * w), check_invariants=True).coalesce()


def test_batched_kernel_reproduces_the_one_offset_at_a_time_kernel_exactly():
    from psctl.synth.shapes import BACKGROUND, blobby_gbuffers

    assert BACKGROUND == -10.0
    g = blobby_gbuffers(2, 40, torch.Generator().manual_seed(3))
    for w in range(2):
        ref = _kernel_one_offset_at_a_time(g.depth[w:w + 1], g.normals[w:w + 1])
        got = R.interreflection_kernel(g.depth[w:w + 1], g.normals[w:w + 1]).to_sparse_coo().coalesce()
        assert ref._nnz() > 1000
        assert torch.equal(ref.indices(), got.indices())
        assert torch.equal(ref.values(), got.values())
