"""Depth from normals: accuracy on analytic surfaces, signs, masks with holes and several regions,
depth jumps (bilateral), perspective, PLY round trips, and `psctl depth` end to end."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from psctl.depth import depth_mesh, depth_to_points, integrate, integrate_normals, normals_from_points
from psctl.errors import PsctlError
from psctl.io.mesh import Mesh, read_ply, write_ply
from tests.conftest import sphere, write_capture
from tests.test_cli import cli


# --- analytic surfaces ----------------------------------------------------------------------------

def surface(kind: str, n: int = 64):
    """Exact normals [n, n, 3], mask and true z of an orthographic surface (pixel units)."""
    r, c = np.mgrid[0:n, 0:n].astype(np.float64)
    x, y = c - (n - 1) / 2, (n - 1) / 2 - r  # x right, y up, row 0 at the top
    mask = x**2 + y**2 < (0.45 * n) ** 2
    if kind == "sphere":  # a cap: radius 0.5 n, seen out to 0.45 n (rim slope ~64 degrees)
        z = np.sqrt((0.5 * n) ** 2 - np.where(mask, x**2 + y**2, 0))
        zx, zy = -x / z, -y / z
    elif kind == "paraboloid":
        a = 1.0 / n
        z, zx, zy = -a * (x**2 + y**2), -2 * a * x, -2 * a * y
    elif kind == "sine":
        mask = np.ones((n, n), bool)
        amp, f = 0.05 * n, 2 * np.pi * 3 / n
        z = amp * np.sin(f * x) * np.cos(f * y)
        zx, zy = amp * f * np.cos(f * x) * np.cos(f * y), -amp * f * np.sin(f * x) * np.sin(f * y)
    else:
        raise ValueError(kind)
    normals = np.stack([-zx, -zy, np.ones_like(z)], -1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return normals.astype(np.float32), mask, z


def rel_rmse(depth: np.ndarray, z: np.ndarray, mask: np.ndarray) -> float:
    """RMSE after removing the unknown offset, as a fraction of the true depth range."""
    e = depth[mask].astype(np.float64) - z[mask]
    e -= e.mean()
    return float(np.sqrt(np.mean(e**2)) / np.ptp(z[mask]))


def perturb(normals: np.ndarray, degrees: float, seed: int = 0) -> np.ndarray:
    """Tilt every normal by exactly ``degrees`` about a random perpendicular axis."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=normals.shape)
    a -= (a * normals).sum(-1, keepdims=True) * normals
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    t = np.radians(degrees)
    return (normals * np.cos(t) + a * np.sin(t)).astype(np.float32)


@pytest.mark.parametrize("method", ["poisson", "bilateral"])
@pytest.mark.parametrize("kind", ["sphere", "paraboloid", "sine"])
def test_exact_normals_integrate_to_the_surface(kind, method):
    normals, mask, z = surface(kind)
    depth = integrate_normals(normals, mask, method=method)
    assert depth.dtype == np.float32 and depth.shape == mask.shape
    assert np.isnan(depth[~mask]).all() and np.isfinite(depth[mask]).all()
    assert rel_rmse(depth, z, mask) < 0.005  # the target: < 0.5 % of the depth range


@pytest.mark.parametrize("kind", ["sphere", "sine"])
def test_noisy_normals_degrade_gracefully(kind):
    normals, mask, z = surface(kind)
    for method in ("poisson", "bilateral"):
        err = rel_rmse(integrate_normals(perturb(normals, 5.0), mask, method=method), z, mask)
        assert err < 0.02, (method, err)


def test_signs_follow_the_convention():
    # sphere: the centre is nearer the camera (larger z) than the rim
    normals, mask, _ = surface("sphere")
    depth = integrate_normals(normals, mask)
    n = mask.shape[0]
    assert depth[n // 2, n // 2] > np.nanmax(depth[n // 2, :8]) + 5
    # a plane facing right-ish (nx < 0) rises to the right; facing up (ny > 0) rises toward the
    # bottom of the image (row 0 is the top, y is up)
    for normal, axis in (((-0.3, 0.0, 1.0), 1), ((0.0, 0.3, 1.0), 0)):
        nm = np.broadcast_to(np.array(normal, np.float32) / np.linalg.norm(normal), (20, 30, 3))
        d = integrate_normals(nm, np.ones((20, 30), bool))
        slope = np.diff(d, axis=axis)
        np.testing.assert_allclose(slope, 0.3, atol=1e-4)


def test_holes_and_separate_regions():
    normals, mask, z = surface("paraboloid", 80)
    r, c = np.mgrid[0:80, 0:80]
    hole = (r - 40) ** 2 + (c - 40) ** 2 < 8**2
    split = np.abs(c - 20) < 2  # a vertical gap: the left cap is a separate region
    m = mask & ~hole & ~split
    res = integrate(normals, m)
    assert res.n_components == 2
    assert np.isnan(res.depth[hole]).all()
    left, right = m & (c < 20), m & (c > 20)
    for region in (left, right):  # each region is exact up to its own offset, and has mean 0
        assert rel_rmse(res.depth, z, region) < 1e-3
        assert abs(float(np.mean(res.depth[region]))) < 1e-3
    # isolated pixels are their own regions (depth 0), not a singular system
    single = np.zeros((10, 10), bool)
    single[2, 2] = single[7, 7] = True
    res = integrate(np.dstack([np.zeros((10, 10, 2)), np.ones((10, 10))]), single)
    assert res.n_components == 2 and np.all(res.depth[single] == 0)


def step_scene(n: int = 48):
    """Two planes meeting at a vertical line with a jump that varies along it (so the normals
    are not integrable across it): left z = 0.3 y, right z = -0.3 y + 10."""
    r, c = np.mgrid[0:n, 0:n].astype(np.float64)
    y = n / 2 - r
    left = c < n / 2
    z = np.where(left, 0.3 * y, -0.3 * y + 10.0)
    normals = np.stack([np.zeros_like(z), np.where(left, -0.3, 0.3), np.ones_like(z)], -1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return normals.astype(np.float32), left, z


def test_bilateral_keeps_a_depth_jump_that_poisson_smears():
    normals, left, z = step_scene()
    mask = np.ones_like(left)
    errors = {}
    for method in ("poisson", "bilateral"):
        d = integrate_normals(normals, mask, method=method)
        # the offset across the jump is unknowable from normals: compare each side's shape
        errors[method] = max(rel_rmse(d, z, left), rel_rmse(d, z, ~left))
    assert errors["poisson"] > 0.05
    assert errors["bilateral"] < errors["poisson"] / 10, errors


def test_bilateral_mesh_tears_at_the_jump_instead_of_drawing_a_wall():
    normals, left, z = step_scene()
    res = integrate(normals, np.ones_like(left), "bilateral")
    assert res.cut is not None and res.cut[..., 1].sum() == 0  # no vertical edge is torn
    torn_cols = np.nonzero(res.cut[..., 0])[1]
    assert len(torn_cols) > 30 and (torn_cols == 23).all()  # the edges between columns 23 and 24

    def max_z_span(mesh):
        zs = mesh.vertices[mesh.faces][..., 2]
        return float((zs.max(1) - zs.min(1)).max())

    assert max_z_span(depth_mesh(res.depth)) > 5  # without the tears: a wall across the jump
    assert max_z_span(depth_mesh(res.depth, cut=res.cut)) < 1
    assert integrate(normals, np.ones_like(left)).cut is None  # poisson never tears


def perspective_sphere(h=48, w=64, f=80.0):
    """Normals of a sphere seen by a pinhole camera (psctl axes), its mask (the part facing the
    camera by more than ~17 degrees), intrinsics and true distances along the optical axis."""
    K = np.array([[f, 0, w / 2 + 3.0], [0, f * 1.1, h / 2 - 2.0], [0, 0, 1.0]])
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)  # OpenCV axes
    centre, radius = np.array([0.1, -0.05, 4.0]), 1.0
    a, b, c = (ray * ray).sum(-1), -2 * ray @ centre, centre @ centre - radius**2
    disc = b * b - 4 * a * c
    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
    p = t[..., None] * ray
    n_cv = (p - centre) / radius
    facing = -(n_cv * ray).sum(-1) / np.linalg.norm(ray, axis=-1)
    mask = (disc > 0) & (facing > 0.3)
    normals = np.stack([n_cv[..., 0], -n_cv[..., 1], -n_cv[..., 2]], -1)  # OpenCV -> psctl axes
    return normals.astype(np.float32), mask, K, p[..., 2]


@pytest.mark.parametrize("method", ["poisson", "bilateral"])
def test_perspective_recovers_shape_up_to_scale(method):
    normals, mask, K, dist = perspective_sphere()
    res = integrate(normals, mask, method, K=K)
    assert res.projection == "perspective"
    est = -res.depth[mask].astype(np.float64)  # z = -distance
    assert (est > 0).all()
    est *= np.exp(np.mean(np.log(dist[mask])) - np.mean(np.log(est)))  # the unknown scale
    err = np.sqrt(np.mean((est - dist[mask]) ** 2)) / np.ptp(dist[mask])
    assert err < 0.01, err


def test_points_mesh_and_recomputed_normals():
    normals, mask, _ = surface("sphere", 32)
    depth = integrate_normals(normals, mask)
    back = normals_from_points(depth_to_points(depth))
    inner = mask & np.roll(mask, 2, 0) & np.roll(mask, -2, 0) & np.roll(mask, 2, 1) & np.roll(mask, -2, 1)
    cos = (back[inner] * normals[inner]).sum(-1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).mean() < 2.0
    mesh = depth_mesh(depth, normals=normals)
    assert len(mesh.vertices) == mask.sum()
    # faces are counter-clockwise seen from the camera: their normals point to +z
    v = mesh.vertices[mesh.faces]
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert (fn[:, 2] > 0).all()


def test_mesh_face_counts():
    depth = np.zeros((4, 5), np.float32)
    assert len(depth_mesh(depth).faces) == 2 * 3 * 4
    depth[0, 0] = np.nan  # that corner block keeps one triangle
    mesh = depth_mesh(depth)
    assert len(mesh.vertices) == 19 and len(mesh.faces) == 2 * 3 * 4 - 1


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip(tmp_path, binary):
    rng = np.random.default_rng(1)
    mesh = Mesh(vertices=rng.normal(size=(7, 3)).astype(np.float32),
                faces=rng.integers(0, 7, size=(5, 3)).astype(np.int32),
                normals=rng.normal(size=(7, 3)).astype(np.float32),
                colors=rng.integers(0, 256, size=(7, 3)).astype(np.uint8))
    path = tmp_path / "m.ply"
    write_ply(path, mesh, binary=binary, comment="test")
    back = read_ply(path)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_allclose(back.vertices, mesh.vertices, rtol=1e-6)
    np.testing.assert_allclose(back.normals, mesh.normals, rtol=1e-6)
    np.testing.assert_array_equal(back.colors, mesh.colors)
    bare = read_ply(_write(tmp_path / "bare.ply", Mesh(mesh.vertices, mesh.faces), binary))
    assert bare.normals is None and bare.colors is None


def test_an_object_name_outside_ascii_is_escaped_in_the_ply_header(tmp_path):
    """The PLY header is ASCII; `psctl depth` names the object in a comment. A folder named
    "café ☃" (tab, newline inside) gave a UnicodeEncodeError traceback."""
    import psctl
    from conftest import write_capture

    folder = tmp_path / "caf\u00e9 \u2603"
    write_capture(folder, n=8, size=24)
    report = psctl.run_depth(folder)
    head = open(report["outputs"]["mesh_ply"], "rb").read().split(b"end_header")[0]
    assert b"comment" in head and b"caf\\xe9 \\u2603" in head
    binary = read_ply(report["outputs"]["mesh_ply"])
    assert len(binary.vertices) > 0
    # binary_ply=False (not on the command line): the same mesh in ASCII
    text = psctl.run_depth(folder, out=tmp_path / "ascii", binary_ply=False)["outputs"]["mesh_ply"]
    assert b"format ascii 1.0" in open(text, "rb").read(200)
    ascii_mesh = read_ply(text)
    np.testing.assert_allclose(ascii_mesh.vertices, binary.vertices, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(ascii_mesh.faces, binary.faces)
    write_ply(tmp_path / "m.ply", Mesh(np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.int32)),
              comment="a\tb\nsecond line \u00fc")
    lines = open(tmp_path / "m.ply", "rb").read().split(b"end_header")[0].splitlines()
    assert [x for x in lines if x.startswith(b"comment")] == [b"comment a\\tb", b"comment second line \\xfc"]


def _write(path, mesh, binary):
    write_ply(path, mesh, binary=binary)
    return path


def test_rejected_normals_are_counted_not_fatal():
    normals, mask, _ = surface("sphere", 32)
    bad = normals.copy()
    bad[16, 16] = np.nan
    bad[10, 12] = (0.0, 0.0, -1.0)  # facing away
    bad[12, 10] = 0.0  # no normal inside the mask
    bad[14, 20] = (1.0, 0.0, 0.0)  # edge-on (nz = 0): no slope, rejected as facing away (nz <= 0)
    res = integrate(bad, mask)
    assert (res.n_rejected_nan, res.n_rejected_facing, res.n_rejected) == (2, 2, 4)
    assert np.isnan(res.depth[16, 16]) and np.isnan(res.depth[10, 12]) and np.isnan(res.depth[14, 20])
    assert res.valid.sum() == mask.sum() - 4


def test_normals_of_any_length_integrate_alike():
    """Normals need not be unit: a map scaled as a whole by 1e-9 or 1e300 (float64) integrates as
    the unit map does (both were refused as "NaN or zero", a QA helper's finding); one pixel
    1e-12 as long as the rest is still "no normal"."""
    import warnings

    normals, mask, _ = surface("sphere", 32)
    normals = normals.astype(np.float64)
    ref = integrate(normals, mask)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for scale in (1e-9, 1e300, 1e-300):
            res = integrate(normals * scale, mask)
            assert res.n_rejected == 0 and np.allclose(res.depth[mask], ref.depth[mask], atol=1e-9), scale
    tiny = normals.copy()
    tiny[12, 10] *= 1e-12
    assert integrate(tiny, mask).n_rejected_nan == 1
    # the floor is relative to the normals in the mask, not to those outside it
    outside = np.where(mask[..., None], normals * 1e-9, [0.0, 0.0, 1.0])
    assert integrate(outside, mask).n_rejected == 0


def test_grazing_normals_count_as_the_grazing_limit():
    """A plane at 88 degrees (slope 33 px per px) integrates as slope nx / grazing_nz: 10 with the
    default 0.1 (rims are unreliable), 33 when the limit is below its nz."""
    a = 33.0
    n = np.array([a, 0.0, 1.0]) / np.hypot(a, 1.0)
    normals = np.broadcast_to(n, (8, 12, 3)).astype(np.float32).copy()
    for grazing, slope in ((None, n[0] / 0.1), (0.01, a)):
        depth = integrate_normals(normals, config=None if grazing is None else {"grazing_nz": grazing})
        steps = np.diff(depth.astype(np.float64), axis=1)
        np.testing.assert_allclose(steps, -slope, rtol=1e-3)  # nx > 0: the surface falls to the right


@pytest.mark.parametrize("case, needle", [
    ("size", "mask is"),
    ("empty", "empty"),
    ("all_nan", "no usable normal"),
    ("method", "unknown depth method"),
    ("K", "intrinsics"),
    ("K_huge", "above 1e9 pixels"),  # squares of 1e300 overflow in the solver
    ("K_tiny", "at least 1 pixel"),  # 1e-300: a vertex at infinity in mesh.ply
])
def test_bad_arrays_raise_psctl_errors(case, needle):
    normals, mask, _ = surface("sphere", 16)
    kwargs = {}
    if case == "size":
        mask = mask[:-1]
    elif case == "empty":
        mask = np.zeros_like(mask)
    elif case == "all_nan":
        normals = np.full_like(normals, np.nan)
    elif case == "method":
        kwargs["method"] = "magic"
    elif case == "K":
        kwargs["K"] = np.eye(3) * -1
    elif case == "K_huge":
        kwargs["K"] = np.array([[1e300, 0, 8], [0, 1e300, 8], [0, 0, 1]])
    elif case == "K_tiny":
        kwargs["K"] = np.array([[1e-300, 0, 8], [0, 1.0, 8], [0, 0, 1]])
    with pytest.raises(PsctlError, match=needle):
        integrate_normals(normals, mask, **kwargs)


# --- psctl depth ------------------------------------------------------------------------------------

def psctl(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "psctl.cli", *map(str, args)], capture_output=True, text=True,
                          env={**os.environ, "COLUMNS": "200"})


def read_exr(path) -> np.ndarray:
    # read_image rejects NaN (right for inputs); depth.exr has NaN outside the surface by design
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    try:
        return np.asarray(inp.read_image(0, 0, 0, 1, "float"))[..., 0]
    finally:
        inp.close()


def test_cli_depth_end_to_end(capture, tmp_path):
    out = tmp_path / "out"
    proc = cli("depth", capture, "--out", out, "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    for key in ("object", "method", "n_pixels", "n_rejected", "seconds", "outputs"):
        assert key in report
    assert report["method"] == "poisson" and report["projection"] == "orthographic"
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [".psctl-depth", "depth.exr", "depth.png", "mesh.ply", "shading.png", "depth_report.json"])
    assert json.loads((out / "depth_report.json").read_text())["n_pixels"] == report["n_pixels"]
    depth = read_exr(out / "depth.exr")
    from psctl.io.images import read_image

    mask = read_image(capture / "mask.png")[0][..., 0] > 0.5
    assert np.isnan(depth[~mask]).all() and np.isfinite(depth[mask]).sum() == report["n_pixels"]
    assert depth[20, 20] > np.nanmax(depth[20, :6])  # sphere centre nearer than the rim
    mesh = read_ply(out / "mesh.ply")
    assert len(mesh.vertices) == report["n_pixels"] == report["n_vertices"]
    assert len(mesh.faces) == report["n_faces"] > report["n_pixels"]
    assert mesh.normals is not None and mesh.colors is not None
    preview, info = read_image(out / "depth.png")
    assert info.dtype == "uint16" and preview.shape[2] == 2  # grey + alpha
    shading, _ = read_image(out / "shading.png")
    assert shading[..., 0][mask].std() > 0.05  # a picture, not a flat fill
    from psctl.depth import LIGHT, shade
    from psctl.io.images import linear_to_srgb

    # the sphere's centre faces the camera: its radiance, sRGB-encoded as the file's tag says
    assert abs(shading[20, 20, 0] - linear_to_srgb(shade(np.array([0.0, 0.0, 1.0]), LIGHT))) < 0.03
    # shade() by hand (helper-166: without its ambient term the test above passed, as it compares
    # with shade()): 0.08 ambient + 0.92 max(n . l, 0), the light's own direction 1, facing away 0.08
    n = np.array([[0.0, 0.0, 1.0], LIGHT, -LIGHT, [np.nan] * 3])
    np.testing.assert_allclose(shade(n)[:3], [0.08 + 0.92 * LIGHT[2], 1.0, 0.08], rtol=1e-12)
    assert np.isnan(shade(n)[3])

    # normals from a file, bilateral, perspective from PATH/K.txt
    np.save(tmp_path / "n.npy", write_capture(tmp_path / "again")["normals"])
    (capture / "K.txt").write_text("60 0 20\n0 60 20\n0 0 1\n")
    out2 = tmp_path / "out2"
    proc = cli("depth", capture, "--normals", tmp_path / "n.npy", "--method", "bilateral", "--out", out2, "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert report["projection"] == "perspective" and report["method"] == "bilateral"
    assert report["normals"].endswith("n.npy")


def _one_line_error(proc, culprit: str):
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and culprit in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("case", ["size", "empty_mask", "all_nan", "bad_K", "bad_method", "photo", "away"])
def test_cli_depth_bad_inputs(case, capture, tmp_path):
    from psctl.io.images import write_image

    normals = write_capture(tmp_path / "ref")["normals"]
    args = []
    culprit = None
    if case == "size":
        np.save(tmp_path / "small.npy", normals[:-3])
        args, culprit = ["--normals", tmp_path / "small.npy"], "small.npy"
    elif case == "empty_mask":
        write_image(capture / "mask.png", np.zeros((40, 40), np.float32), "uint8")
        culprit = "mask.png"
    elif case == "all_nan":
        np.save(tmp_path / "nan.npy", np.full_like(normals, np.nan))
        args, culprit = ["--normals", tmp_path / "nan.npy"], "nan.npy"
    elif case == "bad_K":
        (capture / "K.txt").write_text("500 0 20\n0 five 20\n0 0 1\n")
        culprit = "K.txt"
    elif case == "bad_method":
        args, culprit = ["--method", "magic"], "magic"
    elif case == "photo":  # one of the capture's images given as the normal map (an audit: a mesh of 278 px)
        args, culprit = ["--normals", capture / "001.png"], "001.png: is not a normal map"
    elif case == "away":  # most normals' z away from the camera (all of them: no usable normal, refused before)
        away = normals.copy()
        away[:28, :, 2] *= -1
        write_image(tmp_path / "away.exr", away, "float")
        args, culprit = ["--normals", tmp_path / "away.exr"], "normals face away from the camera"
    out = tmp_path / "out"
    _one_line_error(cli("depth", capture, "--out", out, *args), culprit)
    assert not out.exists() or not any(out.iterdir())  # nothing half-written


def test_run_depth_prefers_the_normal_map_psctl_wrote(capture):
    from psctl.depth import run_depth
    from psctl.io.normals import write_normal_map

    data = write_capture(capture)  # same folder again: returns its arrays
    (capture / "psctl").mkdir()
    write_normal_map(capture / "psctl" / "normal.exr", data["normals"], data["mask"], "exr")
    report = run_depth(capture, write=False)
    assert report["normals"].endswith("normal.exr") and report["outputs"] == {}
    assert report["provenance"]["weights"] == {} and report["provenance"]["psctl"]  # a given map: versions alone
    assert report["n_pixels"] == data["mask"].sum() and report["n_regions"] == 1
    (capture / "psctl" / "normal.exr").unlink()  # psctl normals -f npy: found too, not re-estimated
    write_normal_map(capture / "psctl" / "normal.npy", data["normals"], data["mask"], "npy")
    report = run_depth(capture, write=False)
    assert report["normals"].endswith("normal.npy") and not any("estimated" in n for n in report["notes"])
    (capture / "k.txt").write_text("300 0 20\n0 300 20\n0 0 1\n")  # any case, as the capture's other files
    report = run_depth(capture, write=False)
    assert report["intrinsics"].endswith("k.txt") and report["projection"] == "perspective"


def test_depth_reads_the_normals_of_its_out_folder_and_names_another_captures(tmp_path):
    """psctl normals -o N then psctl depth -o N integrates N's normals (they were passed over for
    PATH/psctl's, or estimated again); a map another capture's run wrote is passed over with a note; and a later
    psctl normals over the map depth's outputs came from says they stay (helper-159)."""
    import shutil

    from psctl.api import run_normals
    from psctl.depth import run_depth

    write_capture(tmp_path / "a", n=8, size=32, seed=1)
    write_capture(tmp_path / "b", n=8, size=32, seed=2)
    run_normals(tmp_path / "a", method="l2", out=tmp_path / "N")
    shutil.copytree(tmp_path / "N", tmp_path / "a" / "psctl")
    (tmp_path / "a" / "psctl" / "normal.exr").unlink()  # PATH/psctl holds another map: not the one read
    r = run_depth(tmp_path / "a", out=tmp_path / "N")
    assert r["normals"] == str(tmp_path / "N" / "normal.exr"), r["normals"]
    assert not any("estimated" in n or "report.json beside" in n for n in r["notes"]), r["notes"]
    # N's normals are a's, not b's: b's depth into N does not take them, and b's own PATH/psctl is empty
    b_in_n = run_depth(tmp_path / "b", out=tmp_path / "N", write=False)
    assert "estimated" in b_in_n["normals"]
    assert f"normals: {tmp_path / 'N' / 'normal.exr'} passed over: its report.json says psctl normals estimated it " \
           f"from {os.path.realpath(tmp_path / 'a')}; give it with --normals to integrate it" in b_in_n["notes"]
    for name in ("normal.exr", "normal.png"):  # touched: no longer as that run wrote them (helper-161)
        os.utime(tmp_path / "N" / name, ns=(0, 10**9))
    touched = run_depth(tmp_path / "a", out=tmp_path / "N", write=False)
    assert touched["normals"] == str(tmp_path / "a" / "psctl" / "normal.png")  # PATH/psctl's, as without -o
    assert any("passed over: no report.json there records it as written" in n
                                                     for n in touched["notes"]), touched["notes"]
    run_normals(tmp_path / "a", method="l2", out=tmp_path / "N")
    other = run_depth(tmp_path / "b", normals=tmp_path / "N" / "normal.exr", out=tmp_path / "D")
    assert any(n.startswith("normals: the report.json beside normal.exr says psctl normals estimated it from "
                            f"{os.path.realpath(tmp_path / 'a')}, not from {tmp_path / 'b'}") for n in other["notes"]), \
        other["notes"]
    again = run_normals(tmp_path / "a", method="l2", out=tmp_path / "N", formats=["npy"])  # removes normal.exr
    assert any(n.startswith("outputs: depth.exr, depth.png, mesh.ply, shading.png, depth_report.json in ") and
               "from the earlier normal.exr: run psctl depth again" in n for n in again["notes"]), again["notes"]
    assert not any("psctl depth" in n for n in run_normals(tmp_path / "a", method="l2", out=tmp_path / "N",
                                                            formats=["npy"])["notes"])  # depth read normal.exr, gone
    # a NUL byte in a report's path is no path (realpath's ValueError was a traceback; helper-161)
    run_depth(tmp_path / "a", out=tmp_path / "N")
    for name, key in (("report.json", "path"), ("depth_report.json", "normals")):
        r = json.loads((tmp_path / "N" / name).read_text())
        (tmp_path / "N" / name).write_text(json.dumps({**r, key: r[key] + "\0"}))
    assert run_depth(tmp_path / "a", normals=tmp_path / "N" / "normal.npy", write=False)["n_pixels"] > 0
    assert not any("psctl depth" in n for n in run_normals(tmp_path / "a", method="l2", out=tmp_path / "N",
                                                            formats=["npy"])["notes"])


def test_cli_depth_counts_nan_normals_in_an_exr(capture, tmp_path):
    """NaN in a float normal map marks 'no normal': counted and skipped, not a crash."""
    from psctl.io.images import write_image

    normals = write_capture(tmp_path / "again")["normals"].copy()
    normals[18:20, 18:20] = np.nan
    write_image(tmp_path / "n.exr", normals, "float")
    proc = cli("depth", capture, "--normals", tmp_path / "n.exr", "--out", tmp_path / "o", "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["n_rejected"] == 4


def test_depth_puts_the_networks_warning_in_its_notes(tmp_path, monkeypatch):
    """Without a normal map, psctl depth estimates one with --method auto; PS-FCN's warning on
    coplanar lights belongs in the report's notes, not on stderr as a Python warning."""
    import warnings

    from psctl.depth import run_depth
    from psctl.errors import PsctlWarning
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    write_capture(tmp_path / "cap", n=8, size=24)
    a = np.radians(np.linspace(-40, 40, 8))
    np.savetxt(tmp_path / "cap" / "light_directions.txt", np.stack([np.sin(a), np.zeros(8), np.cos(a)], 1))
    (tmp_path / "cap" / "Normal_gt.mat").unlink()  # not a normal map to integrate
    save_weights(tmp_path / "w" / "ps_fcn.pt", PSFCN(), {"method": "ps-fcn", "train_images": 32, "input_mean": 0.1})
    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path / "w"))
    with warnings.catch_warnings():
        warnings.simplefilter("error", PsctlWarning)
        r = run_depth(tmp_path / "cap", write=False)
    assert any("coplanar" in n and "expect large errors" in n for n in r["notes"]), r["notes"]


def test_depth_estimates_the_normals_psctl_normals_gives(tmp_path, monkeypatch):
    """Without a normal map, psctl depth integrates what psctl normals --method auto gives (its
    crop and notes), and normals of any length give unit vertex normals in mesh.ply."""
    import warnings

    import psctl.depth as D
    from psctl.api import run_normals

    write_capture(tmp_path / "cap", n=8, size=24)
    (tmp_path / "cap" / "Normal_gt.mat").unlink()
    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path / "none"))  # auto: l2
    seen = {}
    real = D.integrate
    monkeypatch.setattr(D, "integrate", lambda n, *a, **k: seen.setdefault("n", n) is None or real(n, *a, **k))
    r = D.run_depth(tmp_path / "cap", write=False)
    got = {}
    ref = run_normals(tmp_path / "cap", method="auto", write=False, arrays=got)
    np.testing.assert_array_equal(seen["n"], got["normals"])
    assert r["normals"] == "estimated (psctl normals --method auto: l2)"
    assert [n for n in ref["notes"] if n not in r["notes"]] == []  # its notes too (auto fell back to l2)
    monkeypatch.setattr(D, "integrate", real)
    for k, scale in enumerate((1e30, 1e-13)):  # the mesh's normals unit either way (1e-13 gave 0.1 long)
        np.save(tmp_path / "n.npy", got["normals"] * np.float32(scale))
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no overflow on the way
            r = D.run_depth(tmp_path / "cap", normals=tmp_path / "n.npy", out=tmp_path / f"o{k}")
        mesh = read_ply(tmp_path / f"o{k}" / "mesh.ply")
        np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=-1), 1.0, atol=1e-5)


def test_depth_to_points_perspective_projects_back_to_its_pixels():
    """Each point of a perspective depth map, projected with K (fx != fy, off-centre principal
    point), lands on its own pixel, at distance -z along the view axis (x right, y up)."""
    K = np.array([[800.0, 0, 30.5], [0, 500.0, 12.0], [0, 0, 1]])
    depth = -np.linspace(900, 1100, 20 * 40, dtype=np.float32).reshape(20, 40)
    p = depth_to_points(depth, K)
    d = -p[..., 2]
    rows, cols = np.mgrid[0:20, 0:40]
    np.testing.assert_allclose(K[0, 0] * p[..., 0] / d + K[0, 2], cols, atol=1e-3)
    np.testing.assert_allclose(-K[1, 1] * p[..., 1] / d + K[1, 2], rows, atol=1e-3)
    assert p[0, -1, 0] > 0 and p[0, -1, 1] > 0  # top right of the principal point: x right, y up
    o = depth_to_points(depth)  # orthographic: (col, -row, z)
    assert (o[..., 0] == cols).all() and (o[..., 1] == -rows).all() and (o[..., 2] == depth).all()


def test_depth_notes_a_replaced_file_of_the_users(tmp_path):
    from psctl.depth import run_depth
    from tests.conftest import write_capture

    write_capture(tmp_path / "obj", n=6, size=24)
    out = tmp_path / "mine"
    out.mkdir()
    (out / "depth.png").write_bytes(b"my picture")
    first = run_depth(tmp_path / "obj", method="poisson", out=out)["notes"]
    assert f"outputs: replaced depth.png in {out}, which no earlier psctl depth run there had listed" in first
    again = run_depth(tmp_path / "obj", method="poisson", out=out)["notes"]
    assert not any(n.startswith("outputs: replaced") for n in again)  # its own files from the run before


def test_mesh_draws_no_wall_across_a_cut_edge():
    """A torn vertical edge (cut[..., 1]: between (r, c) and (r + 1, c)) removes the triangles
    of both blocks beside it, and only those; likewise a torn horizontal edge."""
    depth = np.zeros((4, 4), np.float32)
    full = len(depth_mesh(depth).faces)
    assert full == 2 * 3 * 3
    for axis, (r0, c0), (r1, c1) in ((1, (1, 2), (2, 2)), (0, (2, 1), (2, 2))):
        cut = np.zeros((4, 4, 2), bool)
        cut[r0, c0, axis] = True
        faces = depth_mesh(depth, cut=cut).faces
        a, b = r0 * 4 + c0, r1 * 4 + c1  # all pixels have depth: vertex = row * 4 + column
        assert not any(a in f and b in f for f in faces.tolist())
        assert len(faces) == full - 4  # the two blocks that share the edge, two triangles each


def test_display_colours_and_the_depth_preview_follow_their_conventions():
    from psctl.depth import depth_preview, display_colors

    grey = np.ones((400, 1, 3), np.float32)  # the 99.5th percentile, white, is 1
    grey[1], grey[2] = 0.5, 0.0
    c = display_colors(grey, np.ones((400, 1), bool))
    assert c[:3, 0, 0].tolist() == [255, round(255 * 0.5 ** (1 / 2.2)), 0]  # gamma 2.2 for display
    z = np.array([[0.0, 1.0, np.nan]], np.float32)  # depth z: larger is nearer the camera (docs/depth.md)
    valid = np.isfinite(z)
    prev = depth_preview(z, valid)
    assert prev[0, :, 0].tolist() == [0.0, 1.0, 0.0] and prev[0, :, 1].tolist() == [1.0, 1.0, 0.0]
    flat = depth_preview(np.array([[2.0, 2.0, np.nan]], np.float32), valid)  # every point the nearest: white
    assert flat[0, :, 0].tolist() == [1.0, 1.0, 0.0] and flat[0, :, 1].tolist() == [1.0, 1.0, 0.0]


def test_the_report_maps_depth_png_back_to_depth_exr(tmp_path):
    """z_min and z_max are depth.exr's own values, unrounded: in a perspective run z is about 1 with
    a relief of 1e-4, and the 6 decimals they had were up to 77 of depth.png's 65,535 grey levels (a
    QA helper's finding). Mapped back, depth.png is depth.exr within half a level."""
    import json

    from psctl.depth import run_depth
    from psctl.io.images import read_image, write_image

    h, w = 48, 64
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = 2e-4 * np.sin(u / 9.0) * np.cos(v / 7.0)  # a shallow relief (orthographic slopes of ~2e-5)
    n = np.stack([-np.gradient(z, axis=1), np.gradient(z, axis=0), np.ones_like(z)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    folder = tmp_path / "obj"
    write_capture(folder, n=3, size=8)  # any capture: the normals come from --normals
    for p in folder.iterdir():
        p.unlink()
    for k in range(3):
        write_image(folder / f"{k + 1:03d}.png", np.full((h, w, 3), 0.5, np.float32), "uint16")
    np.savetxt(folder / "K.txt", [[500.0, 0, 31.5], [0, 500.0, 23.5], [0, 0, 1]])
    np.save(tmp_path / "n.npy", n.astype(np.float32))
    r = run_depth(folder, normals=tmp_path / "n.npy", out=tmp_path / "d")
    rep = json.loads((tmp_path / "d" / "depth_report.json").read_text())
    exr = read_image(tmp_path / "d" / "depth.exr", allow_nonfinite=True)[0][..., 0]
    png = read_image(tmp_path / "d" / "depth.png")[0][..., 0]
    ok = np.isfinite(exr)
    assert rep["z_min"] == float(exr[ok].min()) and rep["z_max"] == float(exr[ok].max()) and r["z_min"] == rep["z_min"]
    back = rep["z_min"] + png * (rep["z_max"] - rep["z_min"])
    step = (rep["z_max"] - rep["z_min"]) / 65535
    assert np.abs(back[ok] - exr[ok]).max() <= 0.5 * step + 1e-12


def test_a_float_map_holding_png_encoding_gets_a_note(tmp_path):
    """(n + 1) / 2 stored in an EXR or .npy integrates to a wrong surface: a note says so; the
    vectors themselves (psctl's own maps) get none, nor does a PNG."""
    from psctl.depth import run_depth
    from psctl.io.images import write_image
    from psctl.io.normals import write_normal_map

    data = write_capture(tmp_path / "cap", n=6, size=24)
    n, m = data["normals"].astype(np.float32), data["mask"]
    write_image(tmp_path / "enc.exr", np.where(m[..., None], (n + 1) / 2, 0), "float")
    np.save(tmp_path / "enc.npy", np.where(m[..., None], (n + 1) / 2, 0).astype(np.float32))
    for f in ("enc.exr", "enc.npy"):
        notes = run_depth(tmp_path / "cap", normals=tmp_path / f, write=False)["notes"]
        assert any(f"no component in {f} is negative" in x for x in notes), notes
    for f, fmt in (("ok.exr", "exr"), ("ok.npy", "npy"), ("ok.png", "png16")):
        write_normal_map(tmp_path / f, n, m, fmt)
        notes = run_depth(tmp_path / "cap", normals=tmp_path / f, write=False)["notes"]
        assert not any("is negative" in x for x in notes), notes


def test_depth_without_a_mask_takes_a_nan_background_as_background(tmp_path):
    """A normal map with NaN outside the object (as many tools write it) and no mask: the NaN
    pixels are background, not thousands of rejected 'mask pixels' with a note saying so (a QA
    helper's finding; the depth itself was right). A NaN inside a given mask is still rejected,
    and a map of nothing but NaN is one clear error."""
    from psctl.depth import integrate

    normals, mask = sphere(24, 0.8)
    nan_bg = np.where(mask[..., None], normals, np.nan).astype(np.float32)
    zero_bg = np.where(mask[..., None], normals, 0.0).astype(np.float32)
    a, b = integrate(nan_bg, None), integrate(zero_bg, None)
    assert a.n_rejected_nan == b.n_rejected_nan == 0 and a.n_mask == b.n_mask == int(mask.sum())
    np.testing.assert_array_equal(np.isnan(a.depth), np.isnan(b.depth))
    np.testing.assert_allclose(a.depth[mask], b.depth[mask], rtol=0, atol=1e-6)
    assert integrate(nan_bg, np.ones_like(mask)).n_rejected_nan == int((~mask).sum())  # a mask says they are in
    with pytest.raises(PsctlError, match="has no normal .every pixel is zero or NaN. and there is no mask"):
        integrate(np.full_like(nan_bg, np.nan), None)


def test_integrate_normals_given_a_file_name_for_k_says_how_to_read_it(tmp_path):
    """K is an array for integrate_normals (psctl depth reads K.txt): a file name got 'intrinsics
    must be a real 3 x 3 matrix of numbers' (a QA helper); now the error names the reader."""
    normals, mask = sphere(16)
    for k in ("obj/K.txt", tmp_path / "K.txt"):
        with pytest.raises(PsctlError, match=r"^K must be a 3 x 3 array here, not a file name .*"
                                             r"psctl\.depth\.read_intrinsics\(PATH\)$"):
            integrate_normals(normals, mask, K=k)


def test_depth_without_a_mask_integrates_the_object_found_not_the_ring(tmp_path, monkeypatch):
    """Without a mask the networks' normals cover the object found and FOUND_GROW pixels around it;
    psctl depth integrates the object (its mask_found.png), not that ring (a 4-pixel skirt of
    made-up surface, its vertices black: examples/bumpy_sphere without its mask), whether it
    estimates the normals itself or reads those a psctl normals run wrote beside mask_found.png;
    a mask_found.png replaced since that run is not used."""
    import os

    import psctl.depth as D
    from psctl.api import run_normals
    from psctl.infer import FOUND_GROW, grow_mask
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    write_capture(tmp_path / "cap", n=8, size=32, mask=False)
    (tmp_path / "w").mkdir()
    import torch

    net = PSFCN()
    with torch.no_grad():  # its normals towards the camera (psctl depth refuses a map that mostly faces away)
        net.regressor.est_normal[0].weight[2] = 10 * net.regressor.est_normal[0].weight[2].abs()
    save_weights(tmp_path / "w" / "ps_fcn.pt", net, {"method": "ps-fcn", "train_images": 32})
    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path / "w"))  # auto: ps-fcn
    got: dict = {}
    run_normals(tmp_path / "cap", write=False, arrays=got)
    assert (got["normals"][got["mask"]][:, 2] > 0).mean() > 0.9
    found = got["found"]
    assert found is not None and np.array_equal(got["mask"], grow_mask(found, FOUND_GROW))
    r = D.run_depth(tmp_path / "cap", write=False)
    assert r["n_mask_pixels"] == found.sum() and any("the surface is the object found" in n for n in r["notes"])
    assert list(r["provenance"]["weights"]) == ["ps-fcn"]  # the estimate's weights file, by role
    run_normals(tmp_path / "cap")  # PATH/psctl/normal.png, mask_found.png, report.json
    r = D.run_depth(tmp_path / "cap", write=False)
    assert r["n_mask_pixels"] == found.sum() and any("mask_found.png beside" in n for n in r["notes"])
    shown = tmp_path / "cap" / "psctl" / "mask_found.png"
    st = shown.stat()
    os.utime(shown, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # replaced since (as far as its time says)
    r = D.run_depth(tmp_path / "cap", write=False)
    assert r["n_mask_pixels"] == grow_mask(found, FOUND_GROW).sum()


@pytest.mark.parametrize("perspective", [False, True])
def test_a_map_facing_away_is_refused_before_the_solve(capture, tmp_path, monkeypatch, perspective):
    """psctl depth refuses a given map most of whose normals face away before integrating it
    (a large map cost the whole solve first); perspective names the intrinsics' file."""
    import psctl.depth as depth
    from psctl.io.images import write_image

    normals = write_capture(tmp_path / "ref")["normals"]
    away = normals.copy()
    away[:28, :, 2] *= -1
    write_image(tmp_path / "away.exr", away, "float")
    if perspective:
        (capture / "K.txt").write_text("3000 0 20\n0 3000 20\n0 0 1\n")
    for solver in ("solve_laplacian", "solve_system"):  # (poisson's, from its matrix)
        monkeypatch.setattr(depth, solver, lambda *a, **k: pytest.fail("solved a map it refuses"))
    with pytest.raises(PsctlError, match="normals face away from the camera" +
                       (" along the rays of the intrinsics K.txt" if perspective else ": not a normal map")):
        depth.run_depth(capture, normals=tmp_path / "away.exr", write=False)
    seen = []

    def stop(n_facing, n_directions):
        seen.append((n_facing, n_directions))
        raise PsctlError(None, "stop")

    with pytest.raises(PsctlError, match="stop"):  # the library's hook: the mask's counts, before the solve
        depth.integrate(away, check_facing=stop)
    assert seen == [(int((away[..., 2] < 0).sum()), int((np.abs(away).sum(-1) > 0).sum()))]


def test_run_depth_without_a_mask_reads_nan_and_mid_grey_backgrounds_as_background(tmp_path):
    """Other tools write the background of a normal map as NaN (float) or mid-grey (a PNG's (n + 1) / 2
    of the zero vector). Without a mask both are background, as a zero one is: a NaN background
    was counted as thousands of rejected mask pixels, and a grey one was normalised to (1, 1, 1) /
    sqrt(3) and integrated into a tilted plane around the object (a review's findings)."""
    from psctl.depth import run_depth
    from psctl.io.images import write_image
    from psctl.io.normals import write_normal_map

    data = write_capture(tmp_path / "cap", n=6, size=32, mask=False)
    n, m = data["normals"].astype(np.float32), data["mask"]
    write_normal_map(tmp_path / "zero.exr", n, m, "exr")
    np.save(tmp_path / "nan.npy", np.where(m[..., None], n, np.nan).astype(np.float32))
    for bits in ("uint8", "uint16"):
        write_image(tmp_path / f"grey_{bits}.png", np.where(m[..., None], (n + 1) / 2, 0.5), bits, kind="data")
    ref = run_depth(tmp_path / "cap", normals=tmp_path / "zero.exr", write=False)
    assert ref["n_mask_pixels"] == int(m.sum()) and ref["n_rejected"] == 0
    for f in ("nan.npy", "grey_uint8.png", "grey_uint16.png"):
        r = run_depth(tmp_path / "cap", normals=tmp_path / f, write=False)
        assert (r["n_mask_pixels"], r["n_rejected"]) == (int(m.sum()), 0), (f, r)
        assert not any("no usable normal" in x for x in r["notes"]), r["notes"]
        assert abs(r["z_max"] - ref["z_max"]) < 0.05 * (ref["z_max"] - ref["z_min"]), (f, r["z_max"], ref["z_max"])


def test_a_given_map_with_an_axis_flipped_gets_a_note(tmp_path):
    """A normal map with y down (as image rows, some tools' convention) integrates to a wrong surface:
    a note says its mirror image is far more integrable. The map as written gets none, nor does a
    perspective sphere's (checked orthographically, it is still far more integrable than its mirror)."""
    from pathlib import Path

    from psctl.depth import mirror_map_notes, run_depth

    data = write_capture(tmp_path / "cap", n=6, size=32)
    n, m = data["normals"].astype(np.float32), data["mask"]
    np.save(tmp_path / "ok.npy", np.where(m[..., None], n, 0).astype(np.float32))
    np.save(tmp_path / "flip.npy", np.where(m[..., None], n * np.float32([1, -1, 1]), 0).astype(np.float32))
    said = lambda f: [x for x in run_depth(tmp_path / "cap", normals=tmp_path / f, write=False)["notes"]  # noqa: E731
                      if "less integrable than its mirror image" in x]
    assert said("ok.npy") == []
    assert len(said("flip.npy")) == 1 and said("flip.npy")[0].startswith("normals: flip.npy is "), said("flip.npy")
    # psctl normals' own map from a light file with y flipped: the note names the file, not the map (a review)
    from psctl.api import run_normals

    lights = np.loadtxt(tmp_path / "cap" / "light_directions.txt")
    np.savetxt(tmp_path / "cap" / "light_directions.txt", lights * [1, -1, 1])
    run_normals(tmp_path / "cap", method="l2")
    own = [x for x in run_depth(tmp_path / "cap", write=False)["notes"] if "than its mirror image" in x]
    assert len(own) == 1 and "estimated it from the capture's light_directions.txt" in own[0], own
    normals, mask, _, _ = perspective_sphere()
    assert mirror_map_notes(normals, mask, Path("p.exr")) == []
    assert mirror_map_notes(normals * np.float32([-1, 1, 1]), mask, Path("p.exr")) != []


def test_the_laplacian_solve_is_the_dense_one():
    """psctl.poisson.solve_laplacian (CG with the multigrid V-cycle, and again from a stale
    preconditioner as bilateral reuses one) gives the dense solution of the same pinned system,
    on a 50 x 50 grid of random weights cut into two components."""
    from psctl.depth import DEFAULT_CONFIG
    from psctl.poisson import laplacian, solve_laplacian

    rng = np.random.default_rng(3)
    h = w = 50
    index = np.arange(h * w).reshape(h, w)
    ei = np.concatenate([index[:, :-1].ravel(), index[:-1, :].ravel()])
    ej = np.concatenate([index[:, 1:].ravel(), index[1:, :].ravel()])
    split = (ei % w < 20) == (ej % w < 20)  # no edge across column 20: two components
    ei, ej = ei[split], ej[split]
    c, b = rng.uniform(0.01, 2.0, len(ei)), rng.normal(size=len(ei))
    pins = np.array([0, 20])
    coords = np.divmod(np.arange(h * w), w)
    cfg = {**DEFAULT_CONFIG, "cg_rtol": 1e-10}
    exact = np.linalg.solve(laplacian(h * w, ei, ej, c, pins).toarray(),
                            np.bincount(ej, b, h * w) - np.bincount(ei, b, h * w))
    z, its, amg, done = solve_laplacian(h * w, ei, ej, c, b, pins, coords, None, cfg)
    assert done and its > 0 and amg is not None and np.abs(z - exact).max() < 1e-6 * np.abs(exact).max()
    c2 = c * rng.uniform(0.5, 2.0, len(c))  # bilateral's next round: new weights, the old V-cycle first
    exact2 = np.linalg.solve(laplacian(h * w, ei, ej, c2, pins).toarray(),
                             np.bincount(ej, b, h * w) - np.bincount(ei, b, h * w))
    z2, _, _, done2 = solve_laplacian(h * w, ei, ej, c2, b, pins, coords, z, cfg, amg)
    assert done2 and np.abs(z2 - exact2).max() < 1e-6 * np.abs(exact2).max()


def test_the_laplacian_from_its_pattern_is_the_same_matrix():
    """Bilateral fills each round's matrix into a pattern built once (no COO arrays a round): the
    same data, indices and index pointers, to the bit; a graph that repeats an edge has none."""
    from psctl.poisson import laplacian, laplacian_pattern

    rng = np.random.default_rng(5)
    valid = rng.random((40, 60)) > 0.3
    npix = int(valid.sum())
    index = np.full(valid.shape, -1, np.int32)
    index[valid] = np.arange(npix)
    hor, ver = valid[:, :-1] & valid[:, 1:], valid[:-1] & valid[1:]
    ei = np.concatenate([index[:, :-1][hor], index[:-1][ver]])
    ej = np.concatenate([index[:, 1:][hor], index[1:][ver]])
    pattern = laplacian_pattern(npix, ei, ej)
    for _ in range(2):
        c = rng.uniform(1e-6, 3.0, len(ei))
        a, b = laplacian(npix, ei, ej, c, np.array([0, 7])), laplacian(npix, ei, ej, c, np.array([0, 7]), pattern)
        for name in ("data", "indices", "indptr"):
            assert getattr(a, name).dtype == getattr(b, name).dtype
            assert getattr(a, name).tobytes() == getattr(b, name).tobytes(), name
    assert laplacian_pattern(3, np.array([0, 0]), np.array([1, 1])) is None


def test_a_laplacian_without_edges_is_its_pins():
    """A graph of isolated pixels (every one pinned): np.bincount of no edges is int64, which the
    pins' float weight cannot be added to in place (helper-189: a casting error)."""
    from psctl.poisson import laplacian

    empty = np.array([], np.int32)
    L = laplacian(3, empty, empty, np.array([]), np.array([0, 1, 2]))
    assert L.dtype == np.float64 and np.allclose(L.toarray(), 1e-12 * np.eye(3))


@pytest.mark.parametrize("method", ["poisson", "bilateral"])
def test_progress_reaches_its_total(method):
    """The docstring's progress: poisson said nothing for its seconds-long solve, and bilateral's
    bar stopped short when it converged early (15 of 50 rounds; helper-196)."""
    normals, mask = sphere(48)
    seen: list[list] = []

    def factory(label, total):
        seen.append([label, total, 0])
        return lambda k: seen[-1].__setitem__(2, seen[-1][2] + k)

    res = integrate(normals, mask, method, progress=factory)
    assert len(seen) == 1 and method in seen[0][0]
    label, total, done = seen[0]
    assert done == total and total == (1 if method == "poisson" else 50)
    if method == "bilateral":
        assert res.iterations < total  # converged early, yet the bar is full
