"""psctl undistort: OpenCV's lens model, the bilinear remap, and the capture folder it writes."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from psctl.errors import PsctlError
from psctl.io.capture import open_capture
from psctl.io.images import image_info, read_image, write_image
from psctl.io.normals import write_normal_map
from psctl.undistort import check_distortion, read_camera, remap, shift_picture, undistort_map
from tests.conftest import hemisphere_lights, sphere
from tests.test_cli import cli

K1 = np.array([[100.0, 0, 50], [0, 200.0, 40], [0, 0, 1]])


@pytest.mark.parametrize("coeffs, pixel, expected", [
    # worked by hand from the model in psctl/undistort.py's docstring (OpenCV's):
    # (70, 40): x 0.2, y 0, r2 0.04, radial 1.004016; xd = 0.2008032 + p2 (r2 + 2 x^2) = +0.00024,
    # yd = p1 r2 = 0.00012
    ([0.1, 0.01, 0.003, 0.002], (70, 40), (70.10432, 40.024)),
    # (50, 80): x 0, y 0.2: xd = p2 r2 = 0.00008, yd = 0.2008032 + p1 (r2 + 2 y^2) = +0.00036
    ([0.1, 0.01, 0.003, 0.002], (50, 80), (50.008, 80.23264)),
    # (60, 60): x = y = 0.1, r2 0.02, radial 1.002004; xd = 0.1002004 + 2 p1 x y + p2 (r2 + 2 x^2)
    # = + 0.00006 + 0.00008, yd = 0.1002004 + p1 (r2 + 2 y^2) + 2 p2 x y = + 0.00012 + 0.00004
    ([0.1, 0.01, 0.003, 0.002], (60, 60), (60.03404, 60.07208)),
    # k3 alone: radial 1 + r2^3 = 1.000064
    ([0, 0, 0, 0, 1.0], (70, 40), (70.00128, 40.0)),
    # rational: radial 1.004016 / (1 + k4 r2) = 1.004016 / 1.02
    ([0.1, 0.01, 0, 0, 0, 0.5, 0, 0], (70, 40), (50 + 100 * 0.2 * 1.004016 / 1.02, 40.0)),
    # k5 and k6 apart (helper-166: swapped, they passed): 1 / (1 + k5 r2^2 + k6 r2^3) = 1 / (1 + 0.5 * 0.0016
    # + 2 * 0.000064) = 1 / 1.000928 (swapped: 1 / 1.003232, 0.046 px apart)
    ([0, 0, 0, 0, 0, 0, 0.5, 2.0], (70, 40), (50 + 100 * 0.2 / 1.000928, 40.0)),
])
def test_undistort_map_is_opencvs_model(coeffs, pixel, expected):
    m = undistort_map(K1, coeffs, (81, 101))
    u, v = pixel
    assert m.x[v, u] == pytest.approx(expected[0], abs=1e-9)
    assert m.y[v, u] == pytest.approx(expected[1], abs=1e-9)
    assert m.valid[v, u] and m.folded == 0


def test_undistort_writes_the_intrinsics_file_psctl_depth_reads():
    from psctl import depth, undistort

    assert undistort.K_FILE == depth.K_FILE  # two constants, so that undistort need not import depth


def test_zero_distortion_is_the_identity_and_a_fold_is_left_out():
    m = undistort_map(K1, "0,0,0,0", (81, 101))
    assert np.abs(m.x - np.arange(101)).max() < 1e-9 and np.abs(m.y - np.arange(81)[:, None]).max() < 1e-9
    assert m.valid.all()
    # k1 = -0.5: r -> r - r^3 / 2 grows up to r = sqrt(2/3) = 0.8165 only, then folds back
    K = np.array([[50.0, 0, 50], [0, 50.0, 50], [0, 0, 1]])
    m = undistort_map(K, [-0.5, 0, 0, 0], (101, 101))
    assert m.x[50, 90] == pytest.approx(50 + 50 * (0.8 - 0.5 * 0.8 ** 3)) and m.valid[50, 90]  # r 0.8
    assert m.x[50, 95] == pytest.approx(50 + 50 * (0.9 - 0.5 * 0.9 ** 3))  # r 0.9: inside the photo ...
    assert not m.valid[50, 95]  # ... but beyond the fold
    r = np.hypot(np.arange(101) - 50.0, np.arange(101)[:, None] - 50.0) / 50
    assert m.folded == int((r >= np.sqrt(2 / 3)).sum()) and not m.valid[r >= 0.8166].any()
    # tangential terms fold the map too (p1 = p2 = 0.5; the radial check saw nothing, a QA
    # helper): left out wherever the map's Jacobian is not positive, checked here by hand
    K = np.array([[50.0, 0, 15.5], [0, 50.0, 15.5], [0, 0, 1]])
    m = undistort_map(K, [0, 0, 0.5, 0.5], (32, 32))
    jx, jy = np.gradient(m.x, axis=1), np.gradient(m.y, axis=0)  # a pixel-step estimate of the determinant
    det = jx * jy - np.gradient(m.x, axis=0) * np.gradient(m.y, axis=1)
    assert m.folded > 100 and not m.valid[det < -0.05].any() and m.valid[det > 0.05].any()



def test_a_piece_cut_off_by_a_fold_is_left_out():
    """p1 0.4, p2 0.3: a corner piece where the Jacobian is positive again lies beyond the fold, and
    its pixels read photo pixels the main piece shows too (ghosts; helper 209)."""
    from scipy import ndimage

    K = np.array([[150.0, 0, 160], [0, 150.0, 120], [0, 0, 1]])
    m = undistort_map(K, [0, 0, 0.4, 0.3], (240, 320))
    assert ndimage.label(m.valid)[1] == 1
    assert not m.valid[0, 70]  # it read the photo at (205, 180), as (190, 160) does
    assert m.valid[160, 190] and abs(m.x[0, 70] - m.x[160, 190]) < 0.01 and abs(m.y[0, 70] - m.y[160, 190]) < 0.01

def test_remap_is_bilinear():
    h, w = 40, 48
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float32)
    ramp = np.stack([3 * cols + 5 * rows, cols - rows], -1)  # bilinear interpolation is exact on a ramp
    K = np.array([[40.0, 0, 23.5], [0, 40.0, 19.5], [0, 0, 1]])
    m = undistort_map(K, [0.2, 0.05, 0.001, -0.002], (h, w))
    out = remap(ramp, m, fill=-1)
    inner = m.valid & (m.x >= 0) & (m.x <= w - 1) & (m.y >= 0) & (m.y <= h - 1)
    assert inner.sum() > 0.7 * h * w and not m.valid.all()  # pincushion: the corners read outside
    np.testing.assert_allclose(out[inner, 0], (3 * m.x + 5 * m.y)[inner], atol=1e-3)
    np.testing.assert_allclose(out[inner, 1], (m.x - m.y)[inner], atol=1e-3)
    assert (out[~m.valid] == -1).all()
    edge = m.valid & ~inner  # within half a pixel of the border: the border pixel's value
    np.testing.assert_allclose(out[edge, 1], (np.clip(m.x, 0, w - 1) - np.clip(m.y, 0, h - 1))[edge], atol=1e-3)
    assert remap(ramp[..., 0], m).shape == (h, w)  # [h, w] in, [H, W] out
    for bad in (np.zeros(5), ramp[:-1]):
        with pytest.raises(PsctlError, match="does not fit this map"):
            remap(bad, m)


def test_check_distortion():
    assert check_distortion("0.1, -0.2 0.001,0").tolist() == [0.1, -0.2, 0.001, 0, 0, 0, 0, 0]
    assert check_distortion("[[-2.8e-01  9.0e-02  1.2e-03 -7.0e-04 -1.5e-02]]").tolist() == \
        [-0.28, 0.09, 0.0012, -0.0007, -0.015, 0, 0, 0]  # as numpy prints OpenCV's
    assert check_distortion([1, 2, 3, 4, 5, 6, 7, 8]).tolist() == [1, 2, 3, 4, 5, 6, 7, 8]
    for bad, words in (("1,2,3", "got 3"), ("1,,2,3,4", "4, 5 or 8 numbers"), (None, "is required"), ("a,b,c,d", "4, 5 or 8 numbers"), ("nan,0,0,0", "NaN"),
                       ([0, 0, 0, 0, 0, 0], "got 6"), ("1e7,0,0,0", "normalised coordinates")):
        with pytest.raises(PsctlError, match=words):
            check_distortion(bad)


def _digest(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


def _capture(folder, h=40, w=48):
    """Three 16-bit images, an 8-bit ambient image, mask, encoded ground truth, light files."""
    folder.mkdir()
    rng = np.random.default_rng(0)
    n, mask = sphere(max(h, w))
    n, mask = n[:h, :w], mask[:h, :w]
    names = ["b.png", "a.png", "c.png"]
    for name in names:
        write_image(folder / name, rng.random((h, w, 3)).astype(np.float32), "uint16")
    write_image(folder / "ambient.png", 0.05 * rng.random((h, w, 3)).astype(np.float32), "uint8")
    write_image(folder / "mask.png", mask.astype(np.float32), "uint8")
    write_normal_map(folder / "Normal_gt.png", n, mask, "png16")
    (folder / "filenames.txt").write_text("".join(f"{s}\n" for s in names))
    np.savetxt(folder / "light_directions.txt", hemisphere_lights(3), fmt="%.6f")
    (folder / "light_intensities.txt").write_text("1 1 1\n0.5 0.5 0.5\n2 2 2\n")
    return mask


def test_undistort_writes_a_pinhole_capture(tmp_path):
    mask = _capture(tmp_path / "obj")
    before = _digest(tmp_path / "obj")
    (tmp_path / "K.txt").write_text("40 0 23.5\n0 40 19.5\n0 0 1\n")
    # no distortion: every file as it was (pixels, bit depths, light files byte for byte)
    r = cli("undistort", tmp_path / "obj", "--out", tmp_path / "same", "--K", tmp_path / "K.txt",
            "--distortion", "0,0,0,0", "--json", check=True)
    rep = json.loads(r.stdout)
    assert rep["valid_fraction"] == 1 and rep["shift"]["max"] < 1e-6 and rep["n_images"] == 3
    for name in ("a.png", "b.png", "c.png", "ambient.png", "mask.png"):
        a, ia = read_image(tmp_path / "obj" / name)
        b, ib = read_image(tmp_path / "same" / name)
        assert ia.bits == ib.bits and np.array_equal(a, b), name
    for name in ("filenames.txt", "light_directions.txt", "light_intensities.txt"):
        assert (tmp_path / "same" / name).read_bytes() == (tmp_path / "obj" / name).read_bytes()
    out_cap, in_cap = open_capture(tmp_path / "same"), open_capture(tmp_path / "obj")
    assert [p.name for p in out_cap.image_paths] == ["b.png", "a.png", "c.png"]  # undistort.png is no input
    assert np.array_equal(out_cap.lights, in_cap.lights) and out_cap.gt_path.name == "Normal_gt.exr"
    from psctl.depth import read_intrinsics
    from psctl.io.capture import load_ground_truth

    assert np.array_equal(read_intrinsics(tmp_path / "same" / "K.txt"), read_intrinsics(tmp_path / "K.txt"))
    gt_in, gt_out = load_ground_truth(in_cap), load_ground_truth(out_cap)
    assert np.abs(gt_in - gt_out).max() < 1e-5
    # psctl info shows the K.txt that psctl depth will read (and one it cannot)
    info = json.loads(cli("info", tmp_path / "same", "--json", check=True).stdout)
    assert info["intrinsics"] == {"file": "K.txt", "fx": 40.0, "fy": 40.0, "cx": 23.5, "cy": 19.5}
    assert json.loads(cli("info", tmp_path / "obj", "--json", check=True).stdout)["intrinsics"] is None
    (tmp_path / "same" / "K.txt").write_text("40 0 23.5\n0 40 19.5\n")
    info = json.loads(cli("info", tmp_path / "same", "--json", check=True).stdout)
    assert "expected 3 rows" in info["intrinsics"]["error"]
    assert "cannot be read" in cli("info", tmp_path / "same", check=True).stdout

    # a pincushion lens: each image is the remap of its photo, the corners leave the mask
    coeffs = [0.3, 0.08, 0.002, -0.001, -0.01]
    r = cli("undistort", tmp_path / "obj", "-o", tmp_path / "und", "--K", tmp_path / "K.txt", "-d",
            ",".join(map(str, coeffs)), "--json", check=True)
    rep = json.loads(r.stdout)
    m = undistort_map(read_intrinsics(tmp_path / "K.txt"), coeffs, (40, 48))
    assert rep["valid_fraction"] == pytest.approx(m.valid.mean(), abs=1e-6) and 0.5 < m.valid.mean() < 1
    assert rep["shift"]["max"] > 3 and rep["camera"]["distortion"]["k3"] == -0.01
    photo, _ = read_image(tmp_path / "obj" / "a.png")
    got, info = read_image(tmp_path / "und" / "a.png")
    assert info.bits == 16
    diff = np.abs(got - remap(photo, m)) * 65535  # rounded to 16 bits (float32 in the test, float64 there)
    assert diff.max() <= 0.5 + 1e-3 and (diff[~m.valid] == 0).all()
    written = open_capture(tmp_path / "und")
    from psctl.io.capture import load_mask

    new_mask = load_mask(written)
    assert not new_mask[~m.valid].any() and new_mask[0, 0] == 0
    assert np.array_equal(new_mask, (remap(mask.astype(np.float32), m) >= 0.5) & m.valid)
    gt = read_image(tmp_path / "und" / "Normal_gt.exr", allow_nonfinite=True)[0]
    assert np.isnan(gt[~m.valid]).all()
    ok = np.isfinite(gt).all(-1)
    assert ok.sum() > 0.5 * mask.sum() and np.allclose(np.linalg.norm(gt[ok], axis=-1), 1, atol=1e-5)
    defined = np.linalg.norm(gt_in, axis=-1) > 0  # a normal wherever a neighbour has one: the mask's rim too
    assert np.array_equal(ok, (remap(defined.astype(np.float32), m) > 0) & m.valid)
    assert not (new_mask & ~ok).any()
    inner = (remap(defined.astype(np.float32), m) >= 1 - 1e-6) & m.valid  # all four: plain bilinear
    want = remap(gt_in, m)[inner]
    np.testing.assert_allclose(gt[inner], want / np.linalg.norm(want, axis=-1, keepdims=True), atol=1e-5)
    assert image_info(tmp_path / "und" / "undistort.png").channels == 3
    assert sorted(rep["outputs"]) == ["K", "folder", "ground_truth", "mask", "picture", "report"]
    assert _digest(tmp_path / "obj") == before  # inputs untouched
    # again into its own folder: replaced quietly
    r = cli("undistort", tmp_path / "obj", "-o", tmp_path / "und", "--K", tmp_path / "K.txt", "-d",
            ",".join(map(str, coeffs)), "--json", check=True)
    assert not any("replaced" in n for n in json.loads(r.stdout)["notes"])
    # light files added to it since (the docs' workflow) do not make it someone's capture
    (tmp_path / "und" / "extra_light_directions.txt").write_text("0 0 1\n")
    cli("undistort", tmp_path / "obj", "-o", tmp_path / "und", "--K", tmp_path / "K.txt", "-d", "0.1,0,0,0",
        check=True)
    assert (tmp_path / "und" / "extra_light_directions.txt").is_file()


def test_undistort_keeps_alpha_and_rewrites_a_list_with_folders(tmp_path):
    folder = tmp_path / "rgba"
    (folder / "sub").mkdir(parents=True)
    rng = np.random.default_rng(2)
    rgba = rng.random((24, 32, 4)).astype(np.float32)
    rgba[..., 3] = np.where(rng.random((24, 32)) < 0.5, 0.5, 1.0)
    write_image(folder / "sub" / "a.png", rgba, "uint16")
    write_image(tmp_path / "b.png", rgba[..., ::-1], "uint16")  # listed by an absolute path
    (folder / "filenames.txt").write_text(f"sub/a.png\n{tmp_path / 'b.png'}\n")
    (tmp_path / "K.txt").write_text("30 0 15.5\n0 30 11.5\n0 0 1\n")
    r = cli("undistort", folder, "-o", tmp_path / "out", "--K", tmp_path / "K.txt", "-d", "0,0,0,0", "--json",
            check=True)
    assert any("written beside each other" in n for n in json.loads(r.stdout)["notes"])
    assert (tmp_path / "out" / "filenames.txt").read_text() == "a.png\nb.png\n"
    written = open_capture(tmp_path / "out")
    assert [p.parent for p in written.image_paths] == [tmp_path / "out"] * 2  # not the photos any more
    for name, want in (("a.png", rgba), ("b.png", rgba[..., ::-1])):  # colour not divided by alpha
        got, info = read_image(tmp_path / "out" / name)
        assert info.channels == 4 and np.abs(got - want).max() <= 0.5 / 65535 + 1e-7, name
    # two images of one name cannot be written beside each other
    write_image(folder / "a.png", rgba, "uint16")
    (folder / "filenames.txt").write_text("sub/a.png\na.png\n")
    r = cli("undistort", folder, "-o", tmp_path / "new", "--K", tmp_path / "K.txt", "-d", "0,0,0,0")
    assert r.returncode == 2 and "has the name of" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "new").exists()


def test_undistort_keeps_jpegs_and_writes_a_mask_for_the_corners(tmp_path):
    folder = tmp_path / "jpg"
    folder.mkdir()
    rng = np.random.default_rng(1)
    smooth = np.kron(rng.random((6, 8, 3)), np.ones((8, 8, 1))).astype(np.float32)  # 48 x 64
    for k in range(2):
        write_image(folder / f"{k}.jpg", smooth * (0.5 + 0.5 * k), "uint8")
    (tmp_path / "K.txt").write_text("50 0 31.5\n0 50 23.5\n0 0 1\n")
    r = cli("undistort", folder, "-o", tmp_path / "out", "--K", tmp_path / "K.txt", "-d", "0,0,0,0", "--json",
            check=True)
    rep = json.loads(r.stdout)
    assert rep["mask"]["pixels"] is None and not (tmp_path / "out" / "mask.png").exists()  # no mask, none needed
    a, _ = read_image(folder / "1.jpg")
    b, info = read_image(tmp_path / "out" / "1.jpg")
    assert info.format == "jpeg" and np.abs(a - b).max() < 2 / 255  # re-encoded (quality 100, 4:4:4)
    r = cli("undistort", folder, "-o", tmp_path / "pincushion", "--K", tmp_path / "K.txt", "-d", "0.4,0,0,0",
            "--json", check=True)
    rep = json.loads(r.stdout)
    assert rep["mask"]["pixels"] < 48 * 64 and (tmp_path / "pincushion" / "mask.png").is_file()
    assert any("have no source" in n for n in rep["notes"])


def test_undistort_errors_are_one_line_and_write_nothing(tmp_path):
    _capture(tmp_path / "obj")
    K = tmp_path / "K.txt"
    K.write_text("40 0 23.5\n0 40 19.5\n0 0 1\n")
    far = tmp_path / "far.txt"
    far.write_text("40 0 5000\n0 40 5000\n0 0 1\n")
    (tmp_path / "other").mkdir()
    write_image(tmp_path / "other" / "x.png", np.zeros((4, 4, 3), np.float32), "uint8")
    d = ["-d", "0,0,0,0"]
    cases = [
        (["--K", K, "-d", "1,2,3"], "got 3"),
        (["--K", K, "-d", "-0.1,,0.001,0"], "4, 5 or 8 numbers"),
        (["--K", K, "-d", "a,b,c,d"], "4, 5 or 8 numbers"),
        (["--K", K, "-d", "nan,0,0,0"], "NaN"),
        (["--K", tmp_path / "none.txt", *d], "intrinsics file is missing"),
        (["--K", far, "-d", "0.1,0,0,0"], "no output pixel has a source"),
        # nearly none (an audit: 0.1 % of the frame kept, near-black images written, rc 0)
        (["--K", K, "-d", "1000,0,0,0"], "only 32 of 1920 output pixels (1.67 %) have a source in the photos"),
    ]
    for args, words in cases:
        r = cli("undistort", tmp_path / "obj", "-o", tmp_path / "new", *args)
        assert r.returncode == 2, (args, r.stdout, r.stderr)
        assert words in r.stderr and len(r.stderr.strip().splitlines()) == 1, (args, r.stderr)
        assert not (tmp_path / "new").exists()
    for out, words in ((tmp_path / "obj", "is the capture folder"), (tmp_path / "other", "holds a capture")):
        r = cli("undistort", tmp_path / "obj", "-o", out, "--K", K, *d)
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert "default" not in r.stderr  # --out has none here
    # only a new or empty folder, or an earlier undistort output: a psctl normals output's
    # normal.png would be read as the new capture's ground truth, other files would join it
    cli("normals", tmp_path / "obj", "-m", "l2", "-o", tmp_path / "est", check=True)
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "notes.txt").write_text("x")
    for out, words in (("est", "is not empty (error.png ...)"), ("notes", "is not empty (notes.txt)")):
        before = _digest(tmp_path / out)
        r = cli("undistort", tmp_path / "obj", "-o", tmp_path / out, "--K", K, *d)
        assert r.returncode == 2 and words in r.stderr and "not an earlier psctl undistort output" in r.stderr, r.stderr
        assert _digest(tmp_path / out) == before
    (tmp_path / "finder").mkdir()
    (tmp_path / "finder" / ".DS_Store").write_bytes(b"\0")  # empty as far as the user can see
    cli("undistort", tmp_path / "obj", "-o", tmp_path / "finder", "--K", K, *d, check=True)
    (tmp_path / "finder" / "normal.png").write_bytes((tmp_path / "est" / "normal.png").read_bytes())
    r = cli("undistort", tmp_path / "obj", "-o", tmp_path / "finder", "--K", K, *d)
    assert r.returncode == 2 and f"{tmp_path / 'finder' / 'normal.png'}: was not written by psctl undistort" in r.stderr, r.stderr
    # --K read from the folder it would be written into
    cli("undistort", tmp_path / "obj", "-o", tmp_path / "und", "--K", K, *d, check=True)
    r = cli("undistort", tmp_path / "obj", "-o", tmp_path / "und", "--K", tmp_path / "und" / "K.txt", *d)
    assert r.returncode == 2 and "is the --K file this run reads" in r.stderr
    # a capture whose images are an earlier output's (linked): never written over, nor removed as
    # that output's stale files (under other names here)
    for folder, prefix in (("linked", ""), ("renamed", "x")):
        (tmp_path / folder).mkdir()
        for name in ("a.png", "b.png", "c.png"):
            (tmp_path / folder / (prefix + name)).symlink_to(tmp_path / "und" / name)
        r = cli("undistort", tmp_path / folder, "-o", tmp_path / "und", "--K", K, "-d", "0.3,0,0,0")
        assert r.returncode == 2 and "is an input of this capture" in r.stderr, (folder, r.stderr)
        assert all((tmp_path / "und" / n).is_file() for n in ("a.png", "b.png", "c.png"))
    # what the output could not read back: a light file that does not match the images, data
    # under another format's name
    (tmp_path / "obj" / "light_intensities.txt").write_text("1 1 1\n")
    r = cli("undistort", tmp_path / "obj", "-o", tmp_path / "new", "--K", K, *d)
    assert r.returncode == 2 and "light_intensities.txt" in r.stderr and "1 intensity row but 3 images" in r.stderr
    (tmp_path / "obj" / "light_intensities.txt").unlink()
    (tmp_path / "obj" / "a.png").rename(tmp_path / "obj" / "a.tif")
    (tmp_path / "obj" / "filenames.txt").write_text("b.png\na.tif\nc.png\n")
    r = cli("undistort", tmp_path / "obj", "-o", tmp_path / "new", "--K", K, *d)
    assert r.returncode == 2 and "a.tif" in r.stderr and "holds png data under a .tif name" in r.stderr
    assert not (tmp_path / "new").exists()


# as OpenCV 5.0's cv2.FileStorage writes them (camera_matrix, distortion_coefficients), verbatim
OPENCV_YAML = """%YAML 1.2
---
image_width: 640
image_height: 480
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 812.5, 0., 319.5, 0., 810.25, 241., 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -0.28000000000000003, 0.089999999999999997,
       0.0011999999999999999, -0.00069999999999999999,
       -0.014999999999999999 ]
avg_reprojection_error: 0.20999999999999999
"""
OPENCV_JSON = """{
    "image_width": 640,
    "camera_matrix": {
        "type_id": "opencv-matrix",
        "rows": 3,
        "cols": 3,
        "dt": "d",
        "data": [ 812.5, 0.0, 319.5, 0.0, 810.25, 241.0, 0.0, 0.0, 1.0 ]
    },
    "distortion_coefficients": {
        "type_id": "opencv-matrix",
        "rows": 1,
        "cols": 5,
        "dt": "d",
        "data": [ -0.28000000000000003, 0.089999999999999997,
            0.0011999999999999999, -0.00069999999999999999,
            -0.014999999999999999 ]
    },
    "avg_reprojection_error": 0.20999999999999999
}
"""


def test_read_camera_takes_opencvs_calibration_files(tmp_path):
    K = [[812.5, 0, 319.5], [0, 810.25, 241.0], [0, 0, 1]]
    d = [-0.28, 0.09, 0.0012, -0.0007, -0.015, 0, 0, 0]
    nd = "points: !!opencv-nd-matrix\n   sizes: [ 2, 1, 2 ]\n   dt: f\n   data: [ 1., 2., 3., 4. ]\n"
    files = {"cv.yml": OPENCV_YAML, "nd.yml": OPENCV_YAML + nd,  # other OpenCV nodes beside
             "flow.yaml": "{K: [812.5, 0, 319.5, 0, 810.25, 241, 0, 0, 1], D: [-0.28, 0.09, 0.0012, -0.0007, -0.015],"
                          " distortion_model: plumb_bob}\n", "cv1.yml": OPENCV_YAML.replace("%YAML 1.2", "%YAML:1.0"),  # older OpenCV
             "cv.json": OPENCV_JSON,  # a 1 x 1 node of 5 channels, which OpenCV reads too (a review)
             "channels.yml": OPENCV_YAML.replace("rows: 1\n   cols: 5\n   dt: d", "rows: 1\n   cols: 1\n   dt: 5d"),
             "plain.yaml": "K: [[812.5, 0, 319.5], [0, 810.25, 241], [0, 0, 1]]\n"
             "D: [-0.28, 0.09, 0.0012, -0.0007, -0.015]\n",
             "bom.yml": "\ufeff" + OPENCV_YAML.replace("%YAML 1.2", "%YAML:1.0")}  # Notepad's BOM hid %YAML (helper-174)
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        got_K, got_d = read_camera(tmp_path / name)
        np.testing.assert_allclose(got_K, K)
        np.testing.assert_allclose(got_d, d, atol=1e-15)
    bad = {"nodist.yml": ("K: [[1, 0, 1], [0, 1, 1], [0, 0, 1]]\n", "has no distortion coefficients"),
           "k6.yml": ("K: [1, 0, 1, 0, 1, 1]\nD: [0, 0, 0, 0]\n", "has 6 numbers"),
           "cv.xml": ("<?xml version=\"1.0\"?>\n<opencv_storage/>\n", "is XML"),
           "broken.yml": ("K: [1, 2\n", "is not valid YAML or JSON"),
           "list.yml": ("- 1\n- 2\n", "holds no named values"),
           "fisheye.yml": (OPENCV_YAML.replace("image_width: 640", "fisheye_model: 1"), "fisheye_model 1"),
           "ros.yaml": ("distortion_model: equidistant\nK: [1, 0, 1, 0, 1, 1, 0, 0, 1]\nD: [0, 0, 0, 0]\n",
                        "distortion_model equidistant"),
           "tilt.yml": ("K: [1, 0, 1, 0, 1, 1, 0, 0, 1]\nD: [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]\n",
                        "tilt"),
           "nan.yml": ("K: [1, 0, 1, 0, 1, 1, 0, 0, 1]\nDist: [.Nan, 0, 0, 0]\n", "Dist is not a list of numbers"),
           # two names for K with different values (the first was taken without a word, a QA helper)
           # rows x cols not the data's count: OpenCV refuses it (it was read as 3 x 3, a review)
           "shape.yml": (OPENCV_YAML.replace("rows: 3", "rows: 2"), "camera_matrix says rows: 2, cols: 3 but holds 9 "
                                                                    "numbers"),
           "shape.json": (OPENCV_JSON.replace('"cols": 5', '"cols": 4'), "distortion_coefficients says rows: 1, "
                                                                         "cols: 4 but holds 5 numbers"),
           "quoted.json": (OPENCV_JSON.replace('"rows": 3', '"rows": "3"'), "camera_matrix's rows and cols must be "
                                                                           "two whole numbers, not '3' and 3"),
           "twice.yml": ("camera_matrix: [1, 0, 1, 0, 1, 1, 0, 0, 1]\nK: [2, 0, 1, 0, 2, 1, 0, 0, 1]\nD: [0, 0, 0, 0]\n",
                         "gives the camera matrix twice, as camera_matrix and K, with different values")}
    for name, (text, words) in bad.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(PsctlError, match=words) as e:
            read_camera(tmp_path / name)
        assert str(e.value.path) == str(tmp_path / name)
    (tmp_path / "utf16.yml").write_text(OPENCV_YAML, encoding="utf-16")  # Python's codec message, before
    with pytest.raises(PsctlError, match="utf16.yml: is UTF-16 text"):
        read_camera(tmp_path / "utf16.yml")
    with pytest.raises(PsctlError, match="is a folder, not a camera file$"):  # it said "is a folder; camera file is missing"
        read_camera(tmp_path)
    # the command: --camera instead of --K and --distortion; one of the two is needed
    _capture(tmp_path / "obj")
    r = cli("undistort", tmp_path / "obj", "-o", tmp_path / "out", "--camera", tmp_path / "cv.yml", "--json",
            check=True)
    rep = json.loads(r.stdout)
    assert rep["camera"]["K"] == K and rep["camera"]["distortion"]["k3"] == pytest.approx(-0.015)
    assert any("principal point 319.5, 241 lies outside these 48x40 images" in n for n in rep["notes"])
    # the size it was calibrated at (image_width, image_height: 640x480) is not these images' (a QA helper)
    assert any("cv.yml was calibrated on 640x480 images (image_width, image_height), these are 48x40" in n
               for n in rep["notes"])
    for args, words in ((["--camera", tmp_path / "cv.yml", "-d", "0,0,0,0"], "leave out --K and --distortion"),
                        ([], "give the camera"), (["--camera", tmp_path / "cv.xml"], "is XML")):
        r = cli("undistort", tmp_path / "obj", "-o", tmp_path / "new", *args)
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "new").exists()


def test_shift_picture_ticks_fall_on_round_values():
    """undistort.png's colour bar is labelled at round shifts (0, 2, 4, 6, 8 PX for a lens that shifts up to 6.1 px),
    not at thirds of the largest (a QA helper's finding: 1.3 and 2.7 PX)."""
    from psctl.undistort import nice_scale
    from tests.test_io import _text_at

    for top, want in ((0.0, (1.0, 0.25)), (1.0, (1.0, 0.25)), (1.3, (1.5, 0.5)), (3.2, (4.0, 1.0)),
                      (4.01, (6.0, 2.0)), (7.0, (8.0, 2.0)), (9.3, (10.0, 2.5)), (51.0, (60.0, 20.0)),
                      (1234.0, (1500.0, 500.0))):
        vmax, step = nice_scale(top)
        assert (vmax, step) == want and vmax >= top and vmax / step <= 4
    K = np.array([[1000.0, 0, 305.5], [0, 1000.0, 255.5], [0, 0, 1]])
    m = undistort_map(K, [-0.1, 0.02, 0, 0], (512, 612))
    shift = np.hypot(m.x - np.arange(612), m.y - np.arange(512)[:, None])
    assert 6 < shift[m.valid].max() < 8
    pic = shift_picture(shift, m.valid, "ball")
    rows = [_text_at(pic, f"{v} PX", 2) for v in (8, 6, 4, 2, 0)]
    assert all(len(r) == 1 for r in rows) and [r[0][0] for r in rows] == sorted(r[0][0] for r in rows)
    assert not _text_at(pic, "2.7 PX", 2) and not _text_at(pic, "7.0 PX", 2)


def test_shift_picture_has_room_for_its_labels():
    from psctl.io.report import BACKGROUND

    K = np.array([[1000.0, 0, 305.5], [0, 1000.0, 255.5], [0, 0, 1]])
    for coeffs in ([-0.1, 0.02, 0, 0], [0.5, 0, 0, 0]):  # top labels "8 PX" and "60 PX"
        m = undistort_map(K, coeffs, (512, 612))
        shift = np.hypot(m.x - np.arange(612), m.y - np.arange(512)[:, None])
        pic = shift_picture(shift, m.valid, "ball")
        assert np.allclose(pic[:, -2:], BACKGROUND)  # nothing cut off at the right edge


def test_a_light_file_added_to_an_earlier_output_must_fit_the_new_capture(tmp_path):
    """A light file added to an undistort output stays when the folder is written again; one that
    no longer fits the new images left a folder psctl normals refused, with exit 0 and no word (a
    QA helper, session 61). Now the run is refused, naming it, and nothing changes."""
    from psctl.undistort import run_undistort

    _capture(tmp_path / "obj")
    (tmp_path / "obj" / "light_intensities.txt").unlink()
    K = np.array([[50.0, 0, 23.5], [0, 50.0, 19.5], [0, 0, 1]])
    run_undistort(tmp_path / "obj", tmp_path / "und", K=K, distortion=(-0.1, 0, 0, 0))
    (tmp_path / "und" / "light_intensities.txt").write_text("1 1 1\n2 2 2\n")
    before = _digest(tmp_path / "und")
    with pytest.raises(PsctlError, match=r"und/light_intensities.txt: was added to the earlier output and stays, but "
                                         r"has 2 rows for the 3 images written now"):
        run_undistort(tmp_path / "obj", tmp_path / "und", K=K, distortion=(-0.2, 0, 0, 0))
    assert _digest(tmp_path / "und") == before
    (tmp_path / "und" / "light_intensities.txt").write_text("1 1 1\n2 2 2\n3 3 3\n")  # one that fits stays
    run_undistort(tmp_path / "obj", tmp_path / "und", K=K, distortion=(-0.2, 0, 0, 0))
    assert open_capture(tmp_path / "und").intensities[2, 0] == 3


def test_undistort_keeps_a_linear_colour_tag(tmp_path):
    """psctl synth's PNGs are tagged linear; undistort wrote them untagged, and viewers showed them
    as sRGB (a QA helper, session 61). A linear file stays linear; an untagged one stays untagged."""
    from psctl.undistort import run_undistort

    _capture(tmp_path / "obj")
    img = read_image(tmp_path / "obj" / "a.png")[0]
    write_image(tmp_path / "obj" / "a.png", img, "uint16", kind="linear")
    assert "lin" in image_info(tmp_path / "obj" / "a.png").color_space.lower()
    K = np.array([[50.0, 0, 23.5], [0, 50.0, 19.5], [0, 0, 1]])
    run_undistort(tmp_path / "obj", tmp_path / "und", K=K, distortion=(0, 0, 0, 0))
    assert "lin" in image_info(tmp_path / "und" / "a.png").color_space.lower()
    assert "lin" not in image_info(tmp_path / "und" / "b.png").color_space.lower()
    np.testing.assert_array_equal(read_image(tmp_path / "und" / "a.png")[0], img)  # the identity, to the bit
