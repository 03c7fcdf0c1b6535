"""Capture-folder reader, image I/O at true bit depth, normal-map encodings."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from psctl.errors import PsctlError
from psctl.arrays import bounding_box
from psctl.io.capture import (find_objects, load_ground_truth, load_images, load_mask, object_name, read_matrix,
                              open_capture, select_images)
from psctl.io.images import image_info, read_image, write_image
from psctl.io.normals import read_normal_map, write_normal_map
from psctl.metrics import angular_error
from tests.conftest import write_capture


def test_16bit_png_read_exactly(tmp_path):
    ramp = (np.arange(65536, dtype=np.float64) / 65535).reshape(256, 256)
    rgb = np.stack([ramp, ramp[::-1], ramp.T], -1)
    write_image(tmp_path / "r.png", rgb, "uint16")
    back, info = read_image(tmp_path / "r.png")
    assert info.bits == 16 and info.dtype == "uint16"
    # every one of the 65536 levels survives: an 8-bit reader would collapse them to 256
    assert len(np.unique(back[..., 0])) == 65536
    assert np.abs(back - rgb).max() < 1e-6


def test_8bit_and_exr(tmp_path):
    x = np.linspace(0, 1, 64 * 3).reshape(8, 8, 3)
    write_image(tmp_path / "a.png", x, "uint8")
    back, info = read_image(tmp_path / "a.png")
    assert info.bits == 8 and np.abs(back - np.round(x * 255) / 255).max() < 1e-6
    hdr = x * 7.5 - 1.0  # EXR keeps values outside [0, 1] and negatives
    write_image(tmp_path / "a.exr", hdr, "float")
    back, info = read_image(tmp_path / "a.exr")
    assert info.dtype == "float" and np.abs(back - hdr).max() < 1e-6


def test_capture_reader_divides_by_intensity(capture):
    cap = open_capture(capture)
    assert cap.name == "sphere" and cap.n_images == 12 and cap.bits == 16 and cap.calibrated
    imgs = load_images(cap)
    truth = write_capture(capture.parent / "again", seed=0)  # same seed -> same arrays
    m = truth["mask"]
    # what was stored (up to 16-bit quantisation), divided by the intensity row
    stored = truth["images"]
    assert imgs.shape == stored.shape
    assert np.abs(imgs[:, m] * cap.intensities[:, None, :] - stored[:, m]).max() < 1e-4


def test_natural_order_without_filenames(tmp_path):
    folder = tmp_path / "obj"
    write_capture(folder, n=12, intensities=False, gt="none")
    (folder / "filenames.txt").unlink()
    for k in range(12):  # 001.png -> img1.png ... img12.png: natural order puts img2 before img10
        (folder / f"{k + 1:03d}.png").rename(folder / f"img{k + 1}.png")
    cap = open_capture(folder)
    assert [p.name for p in cap.image_paths] == [f"img{k + 1}.png" for k in range(12)]
    assert cap.mask_path is not None and cap.gt_path is None  # mask.png is not taken as an input image
    assert np.all(cap.intensities == 1)


def test_file_names_that_are_not_utf8_are_one_error(tmp_path):
    """Linux allows any bytes in a name; OpenImageIO's binding takes UTF-8 text only (a TypeError)."""
    import os

    from psctl.api import run_normals

    folder = tmp_path / "obj"
    write_capture(folder, n=6, intensities=False, gt="none")
    (folder / "filenames.txt").unlink()
    os.rename(folder / "002.png", os.fsencode(folder) + b"/\xff02.png")
    with pytest.raises(PsctlError, match="02.png: the path is not valid UTF-8 text"):
        load_images(open_capture(folder))
    bad_out = os.fsdecode(os.fsencode(tmp_path) + b"/\xffout")
    (folder / "\udcff02.png").rename(folder / "002.png")
    with pytest.raises(PsctlError, match="output folder's path is not valid UTF-8"):
        run_normals(folder, method="l2", out=bad_out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["obj"]


@pytest.mark.parametrize("case, needle", [
    ("grey_png", "needs 3 channels"),
    ("no_key", r"has no variable 'Normal_gt' \(it holds N; psctl reads the normals from the one named Normal_gt\)"),
    ("size", "size 20x40 differs from the images"),
    ("shape", r"Normal_gt has shape \(40, 40\)"),
    ("junk", "cannot read .mat file"),
])
def test_ground_truth_headers_are_checked_when_the_folder_opens(tmp_path, case, needle):
    """psctl info (headers only) says what psctl normals would refuse later."""
    import scipy.io

    folder = tmp_path / "obj"
    write_capture(folder, n=4, gt="png" if case == "grey_png" else "mat")
    if case == "grey_png":
        write_image(folder / "Normal_gt.png", np.full((40, 40), 0.5, np.float32), "uint16")
    elif case == "junk":
        (folder / "Normal_gt.mat").write_bytes(b"not a mat file at all" * 10)
    else:
        value = {"no_key": {"N": np.zeros((40, 40, 3))}, "size": {"Normal_gt": np.zeros((40, 20, 3))},
                 "shape": {"Normal_gt": np.zeros((40, 40))}}[case]
        scipy.io.savemat(folder / "Normal_gt.mat", value)
    with pytest.raises(PsctlError, match=needle):
        open_capture(folder)


def test_a_logical_ground_truth_is_refused(tmp_path):
    """A MATLAB logical array (scipy gives uint8 0 / 1) as Normal_gt was scored as normals, 35
    degrees off without a word (an audit): whole numbers whose vectors are not of unit length are
    refused. Whole numbers along the axes (a cube's faces, as MATLAB may store such doubles) are
    unit normals and read."""
    import scipy.io

    folder = tmp_path / "obj"
    write_capture(folder, n=4)
    rng = np.random.default_rng(0)
    scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": rng.random((40, 40, 3)) > 0.5})
    with pytest.raises(PsctlError, match=r"Normal_gt holds whole numbers \(uint8\) and \d+ of its pixels are no unit"):
        load_ground_truth(open_capture(folder))
    cube = np.zeros((40, 40, 3), np.int8)
    cube[:20, :, 2], cube[20:, :, 0] = 1, -1
    scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": cube})
    np.testing.assert_array_equal(load_ground_truth(open_capture(folder)), cube)


def test_a_matlab_v73_ground_truth_does_not_stop_what_does_not_read_it(tmp_path):
    """scipy reads no v7.3 (HDF5) file: psctl info, lights and depth open the folder anyway."""
    folder = tmp_path / "obj"
    write_capture(folder, n=4)
    (folder / "Normal_gt.mat").write_bytes(b"MATLAB 7.3 MAT-file".ljust(116) + bytes(8) + b"\x00\x02IM" + bytes(512))
    assert open_capture(folder).gt_path.name == "Normal_gt.mat"
    with pytest.raises(PsctlError, match=r"MATLAB 7.3 \(HDF5\) file, which psctl does not read"):  # where it is read
        load_ground_truth(open_capture(folder))


def test_names_txt_and_single_column_intensities(tmp_path):
    folder = tmp_path / "obj"
    write_capture(folder, n=6)
    (folder / "filenames.txt").rename(folder / "names.txt")
    np.savetxt(folder / "light_intensities.txt", np.full((6, 1), 2.0))
    cap = open_capture(folder)
    assert cap.intensities.shape == (6, 3) and np.all(cap.intensities == 2.0)


def test_ground_truth_png_and_mat_agree(tmp_path):
    a = write_capture(tmp_path / "a", gt="mat")
    write_capture(tmp_path / "b", gt="png")
    ga = load_ground_truth(open_capture(tmp_path / "a"))
    gb = load_ground_truth(open_capture(tmp_path / "b"))
    m = a["mask"]
    assert angular_error(ga, gb, m).max() < 0.01  # 16-bit PNG encoding error is tiny


def test_no_mask_means_whole_image(tmp_path):
    write_capture(tmp_path / "o", mask=False)
    assert load_mask(open_capture(tmp_path / "o")).all()


def test_open_capture_lists_the_folder_once(capture, monkeypatch):
    """Each listing is a round trip on a network drive: opening a capture lists its folder once."""
    from pathlib import Path

    listed, iterdir = [], Path.iterdir
    monkeypatch.setattr(Path, "iterdir", lambda self: (listed.append(self.name), iterdir(self))[1])
    cap = open_capture(capture)  # an image list, lights, intensities, a mask and ground truth: every lookup
    assert cap.lights_path and cap.intensities_path and cap.mask_path and cap.gt_path
    assert listed == [capture.name]


def test_object_name():
    assert object_name("/x/ballPNG") == "ball" and object_name("/x/PNG") == "PNG" and object_name("cat") == "cat"


def test_benchmark_root(tmp_path):
    write_capture(tmp_path / "root" / "aPNG", n=4)
    write_capture(tmp_path / "root" / "bPNG", n=4)
    assert [p.name for p in find_objects(tmp_path / "root")] == ["aPNG", "bPNG"]
    (tmp_path / "root" / "objects.txt").write_text("bPNG\n")
    assert [p.name for p in find_objects(tmp_path / "root")] == ["bPNG"]
    with pytest.raises(PsctlError, match="benchmark root"):
        open_capture(tmp_path / "root")


def test_select_images():
    assert list(select_images(10, None, None)) == list(range(10))
    assert list(select_images(10, 3, None)) == list(select_images(10, 3, 0))  # without lights: seed 0
    a, b = select_images(10, 4, seed=1), select_images(10, 4, seed=1)
    assert list(a) == list(b) and len(set(a)) == 4
    # pinned: a report's --images K --seed S must pick the same images in a later psctl (the
    # reports record them, docs/formats.md), and they come sorted, in the capture's order
    assert select_images(10, 4, seed=1).tolist() == [3, 4, 6, 9]
    assert select_images(96, 5, seed=7).tolist() == [55, 58, 64, 85, 86]
    assert select_images(10, 4, None).tolist() == [2, 4, 5, 7]  # no lights: seed 0


def test_bounding_box_margin_is_clipped_to_the_image():
    m = np.zeros((50, 60), bool)
    m[10:21, 2:9] = True
    assert bounding_box(m) == (slice(10, 21), slice(2, 9))
    assert bounding_box(m, margin=3) == (slice(7, 24), slice(0, 12))  # the left side stops at the frame


@pytest.mark.parametrize("fmt,name,tol", [("png16", "n.png", 0.01), ("png8", "n8.png", 0.5), ("exr", "n.exr", 1e-4),
                                          ("npy", "n.npy", 1e-5)])
def test_normal_map_round_trip(tmp_path, fmt, name, tol):
    from tests.conftest import sphere

    n, m = sphere(32)
    write_normal_map(tmp_path / name, n, m, fmt)
    back = read_normal_map(tmp_path / name)
    assert angular_error(back, n, m).max() < tol
    assert np.all(back[~m] == 0)
    np.testing.assert_allclose(np.linalg.norm(back[m], axis=-1), 1.0, atol=1e-5)  # unit, as written


def _png_chunks(path) -> list[str]:
    """The chunk types of a PNG file, read from its bytes (no image library involved)."""
    import struct

    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    kinds, i = [], 8
    while i < len(data):
        size, kind = struct.unpack(">I4s", data[i:i + 8])
        kinds.append(kind.decode())
        i += 12 + size
    return kinds


def test_data_pngs_carry_no_colour_tag_and_round_exactly(tmp_path):
    """A normal map holds numbers: tagged sRGB (OpenImageIO's default), a colour-managed reader
    would bend them. Pictures keep the sRGB tag. png16 is round((n + 1) / 2 * 65535) exactly."""
    import OpenImageIO as oiio

    rng = np.random.default_rng(0)
    n = rng.normal(size=(64, 64, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    m = np.ones((64, 64), bool)
    write_normal_map(tmp_path / "n.png", n, m, "png16")
    write_normal_map(tmp_path / "n8.png", n, m, "png8")
    write_image(tmp_path / "pic.png", np.full((4, 4, 3), 0.5, np.float32), "uint8")
    for f in ("n.png", "n8.png"):
        assert not {"sRGB", "gAMA", "cHRM", "iCCP"} & set(_png_chunks(tmp_path / f)), f
    assert "sRGB" in _png_chunks(tmp_path / "pic.png")
    inp = oiio.ImageInput.open(str(tmp_path / "n.png"))
    stored = np.asarray(inp.read_image(0, 0, 0, 3, oiio.UINT16)).reshape(64, 64, 3)
    inp.close()
    expect = np.round((n.astype(np.float64) + 1) / 2 * 65535)
    assert np.array_equal(stored, expect)


def test_12bit_tiff_full_scale_is_one(tmp_path):
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(16, 1, 1, oiio.UINT16)
    spec.attribute("oiio:BitsPerSample", 12)
    out = oiio.ImageOutput.create(str(tmp_path / "a.tif"))
    out.open(str(tmp_path / "a.tif"), spec)
    out.write_image(np.linspace(0, 1, 16, dtype=np.float32).reshape(1, 16, 1))
    out.close()
    pixels, info = read_image(tmp_path / "a.tif")
    assert info.bits == 12
    assert pixels.max() == pytest.approx(1.0) and pixels[0, 8, 0] == pytest.approx(8 / 15, abs=1e-3)


def test_grey_alpha_mask_uses_grey(tmp_path):
    folder = tmp_path / "o"
    truth = write_capture(folder)
    m = truth["mask"].astype(np.float32)
    write_image(folder / "mask.png", np.stack([m, np.ones_like(m)], -1), "uint8")  # grey + opaque alpha
    assert (load_mask(open_capture(folder)) == truth["mask"]).all()


def test_mask_threshold_and_colours(tmp_path):
    """Foreground: any colour channel above half of full scale (an anti-aliased edge of 40 %
    stays out, one of 60 % is in; a red-only or blue-only drawing counts)."""
    folder = tmp_path / "o"
    write_capture(folder, size=40)
    m = np.zeros((40, 40, 3), np.float32)
    m[5:10, 5:10] = 0.4  # grey below the threshold
    m[5:10, 20:25] = 0.6  # grey above
    m[20:25, 5:10, 0] = 1.0  # red only
    m[20:25, 20:25, 2] = 0.8  # blue only
    write_image(folder / "mask.png", m, "uint8")
    got = load_mask(open_capture(folder))
    want = np.zeros((40, 40), bool)
    want[5:10, 20:25] = want[20:25, 5:10] = want[20:25, 20:25] = True
    assert (got == want).all()


def test_light_files_with_commas_and_comments(tmp_path):
    from psctl.io.capture import read_lights

    f = tmp_path / "light_directions.txt"
    f.write_text("# x, y, z\n0,0,1\n0.6, 0 ,0.8  # a comment\n\n-0.6 0 0.8\n")
    np.testing.assert_allclose(read_lights(f), [[0, 0, 1], [0.6, 0, 0.8], [-0.6, 0, 0.8]], atol=1e-6)


def test_light_rows_that_are_not_unit_vectors_get_a_note(tmp_path):
    """Rows of other lengths (light positions? a scaled export) are normalised, as the docs say,
    and now a note says so (an audit: silently); unit rows to 4 decimals (DiLiGenT's) get none."""
    from psctl.io.capture import capture_notes

    data = write_capture(tmp_path / "c", n=6, size=16)
    lengths = np.array([1.0, 2.0, 0.5, 10.0, 1.0, 1.0])
    np.savetxt(tmp_path / "c" / "light_directions.txt", data["lights"] * lengths[:, None])
    cap = open_capture(tmp_path / "c")
    np.testing.assert_allclose(cap.lights, data["lights"], atol=1e-6)
    assert [n for n in capture_notes(cap) if n.startswith("light file:")] == [
        "light file: light_directions.txt's rows are not unit vectors (lengths 0.5 to 10): each is normalised, and "
        "read as a direction (the lights' strengths go in light_intensities.txt)"]
    np.savetxt(tmp_path / "c" / "light_directions.txt", data["lights"], fmt="%.2f")  # (rounded: within 0.01)
    assert not any("unit vectors" in n for n in capture_notes(open_capture(tmp_path / "c")))


def test_atomic_path_keeps_the_old_file_when_writing_fails(tmp_path):
    from psctl.io.atomic import atomic_path

    target = tmp_path / "w.pt"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            assert tmp != target and tmp.parent == target.parent and tmp.suffix == ".pt"
            tmp.write_bytes(b"half")
            raise RuntimeError("disk full")
    assert target.read_bytes() == b"old" and sorted(tmp_path.iterdir()) == [target]  # no temporary left
    with atomic_path(target) as tmp:
        tmp.write_bytes(b"new")
        assert target.read_bytes() == b"old"  # replaced only when the block ends
    assert target.read_bytes() == b"new" and sorted(tmp_path.iterdir()) == [target]


def _write_rgba_png(path, rgb, alpha):
    """A PNG whose colour is stored as is beside its alpha (PNG's own, unassociated)."""
    import OpenImageIO as oiio

    h, w = rgb.shape[:2]
    px = np.concatenate([rgb, np.broadcast_to(alpha, (h, w, 1))], -1).astype(np.float32)
    spec = oiio.ImageSpec(w, h, px.shape[-1], "uint16")
    spec.attribute("oiio:UnassociatedAlpha", 1)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(px) and out.close()


def test_alpha_is_ignored(tmp_path):
    """docs/formats.md: a partly or wholly transparent pixel keeps its colour (OpenImageIO would
    multiply it by alpha unless told not to)."""
    folder = tmp_path / "o"
    truth = write_capture(folder, n=6)
    img, _ = read_image(folder / "002.png")
    for a in (0.0, 0.25, 1.0):
        _write_rgba_png(folder / "002.png", img, np.full((40, 40, 1), a))
        got = load_images(open_capture(folder))[1] * open_capture(folder).intensities[1]
        np.testing.assert_allclose(got, img, atol=2e-5)
    m = truth["mask"].astype(np.float32)[..., None]
    _write_rgba_png(folder / "mask.png", np.repeat(m, 3, -1), np.full_like(m, 0.4))  # one alpha: ignored
    assert (load_mask(open_capture(folder)) == truth["mask"]).all()
    _write_rgba_png(folder / "mask.png", np.ones((40, 40, 3)), m)  # a cut-out: white, the object opaque
    assert (load_mask(open_capture(folder)) == truth["mask"]).all()


def test_info_reports_mixed_bit_depths(tmp_path):
    from psctl.io.summary import describe

    folder = tmp_path / "o"
    write_capture(folder, n=6)
    img, _ = read_image(folder / "003.png")
    write_image(folder / "003.png", img, "uint8")
    r = describe(folder)
    assert r["bit_depth"] == 16 and r["bit_depths"] == [8, 16] and r["sample_types"] == ["uint8", "uint16"]
    assert not any("darker" in n for n in describe(folder, check=True)["check"]["notes"])  # alike: no note
    # 8-bit codes saved in a 16-bit file among 8-bit images: 257 times darker, and --check says so
    # (a helper's repro on ball; the opening note promised the comparison)
    for k in range(1, 7):
        img, _ = read_image(folder / f"{k:03d}.png")
        write_image(folder / f"{k:03d}.png", img / 257 if k == 5 else img, "uint16" if k == 5 else "uint8")
    notes = describe(folder, check=True)["check"]["notes"]
    assert any(n.startswith("images: the 16-bit image (005.png) is ") and
               "times darker over the object than the 8-bit ones" in n for n in notes), notes  # (257 times its codes)


def test_select_images_refuses_a_negative_seed_and_notes_what_it_did():
    from psctl.io.capture import selection_notes

    with pytest.raises(PsctlError, match="--seed must be 0 or more"):
        select_images(10, 3, -1)
    assert "all 10 used" in selection_notes(10, 100, None)[0]
    assert "--seed is unused" in selection_notes(10, None, 4)[0]
    assert selection_notes(10, 3, 4) == [] and selection_notes(10, None, None) == []
    assert "a random 3 (seed 0" in selection_notes(10, 3, None)[0]
    assert "spread over the light directions" in selection_notes(10, 3, None, by_lights=True)[0]


def test_images_subset_spreads_over_the_lights():
    """--images K without --seed: K lights far apart, not the first K of the rig order (a DiLiGenT-like
    rig listed column by column: its first 6 lights lie in one plane, hopeless for L2)."""
    from psctl.io.capture import spread_lights

    x, y = np.meshgrid(np.linspace(-0.5, 0.5, 8), np.linspace(-0.4, 0.4, 12), indexing="ij")
    rig = np.stack([x.ravel(), y.ravel(), np.ones(96)], axis=1)  # 8 columns of 12, listed column by column
    rig /= np.linalg.norm(rig, axis=1, keepdims=True)
    cond = lambda idx: np.linalg.cond(rig[idx])
    assert cond(np.arange(6)) > 1e6  # the first 6: coplanar
    for k in (3, 6, 12):
        idx = select_images(96, k, None, rig)
        assert len(idx) == k == len(set(idx)) and list(idx) == sorted(idx) and cond(idx) < 5
        assert list(idx) == list(spread_lights(rig, k))  # deterministic
    assert list(select_images(96, 12, 3, rig)) == list(select_images(96, 12, 3))  # a seed ignores the lights
    # it starts from the light nearest the mean direction: a rig with one light on the axis keeps it
    ring = [(np.cos(a) * 0.5, np.sin(a) * 0.5, 0.8) for a in np.linspace(0, 2 * np.pi, 9)[:-1]]
    lights = np.array([*ring[:3], (0.0, 0.0, 1.0), *ring[3:]])  # the axial light is row 3
    for k in (1, 2, 5):
        assert 3 in spread_lights(lights, k).tolist()
    assert spread_lights(lights, 1).tolist() == [3]


def test_light_rows_of_any_magnitude(tmp_path):
    import warnings

    from psctl.io.capture import read_intensities, read_lights

    p = tmp_path / "light_directions.txt"
    p.write_text("1e300 0 1e300\n0 2e-3 0\n0.1 0.2 0.9\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow on the way
        lights = read_lights(p)
    np.testing.assert_allclose(lights[:2], [[0.70710677, 0, 0.70710677], [0, 1, 0]], atol=1e-6)
    p.write_text("1 0 0\n0 1e-7 0\n")
    with pytest.raises(PsctlError, match="line 2: zero-length"):
        read_lights(p)
    p.write_text("# x y z\n\n1 0 0\n0 1e-7 0  # row 2\n")  # the line in the file, and the row it is
    with pytest.raises(PsctlError, match=r"line 4 \(row 2\): zero-length"):
        read_lights(p)
    q = tmp_path / "light_intensities.txt"
    for bad in ("1e-46", "1e39", "1e300"):
        q.write_text(f"1 1 1\n1 {bad} 1\n")
        with pytest.raises(PsctlError, match="line 2: intensity"):
            read_intensities(q)
    q.write_text("# r g b\n1 1 1\n1 -1 1\n")
    with pytest.raises(PsctlError, match=r"line 3 \(row 2\): intensities must be positive"):
        read_intensities(q)


def test_load_images_as_captured_skips_the_intensities(tmp_path):
    """as_captured: the images as the files hold them (what estimate_lights takes), not divided."""
    from psctl.io.capture import load_images

    write_capture(tmp_path / "cap", n=4, size=16)
    cap = open_capture(tmp_path / "cap")
    assert not np.allclose(cap.intensities, 1)
    divided, raw = load_images(cap), load_images(cap, as_captured=True)
    np.testing.assert_allclose(divided * cap.intensities[:, None, None, :], raw, rtol=1e-5, atol=1e-7)


def test_a_stray_image_is_named_in_the_count_error(tmp_path):
    """Without filenames.txt every image file counts: the count error names the odd one out."""
    write_capture(tmp_path / "cap", n=6, size=16)
    (tmp_path / "cap" / "filenames.txt").unlink()
    write_image(tmp_path / "cap" / "thumb.png", np.zeros((16, 16, 3)), "uint8")
    with pytest.raises(PsctlError, match=r"6 light rows but 7 images .*not named like the others: thumb.png"):
        open_capture(tmp_path / "cap")


def test_files_named_like_the_images_but_not_read_are_named_in_the_count_error(tmp_path):
    """003.png.bak, 003.bmp or 003 beside 001.png are not read for their extension; the count error
    named none of them (helper-170), and names no other file (the light files, the list)."""
    write_capture(tmp_path / "cap", n=6, size=16)
    folder = tmp_path / "cap"
    (folder / "filenames.txt").unlink()
    for name in ("003.png.bak", "003.bmp", "003"):
        (folder / "003.png").rename(folder / name)
        with pytest.raises(PsctlError, match=rf"6 light rows but 5 images \(every image file in the folder counts; "
                                             rf"named like them but not read for their extension: {name}; list"):
            open_capture(folder)
        (folder / name).rename(folder / "003.png")


def test_images_left_out_for_their_names_are_named_in_the_count_error(tmp_path):
    """Images named like psctl's outputs (depth_002.png) or hidden are not read; when the count is
    then wrong the error says so, and never lists the mask or the ground truth."""
    write_capture(tmp_path / "cap", n=6, size=16, gt="png")
    folder = tmp_path / "cap"
    (folder / "filenames.txt").unlink()
    for k in (2, 3, 4, 5):
        (folder / f"{k:03d}.png").rename(folder / f"depth_{k:03d}.png")
    (folder / "006.png").rename(folder / ".006.png")
    with pytest.raises(PsctlError) as e:
        open_capture(folder)
    msg = str(e.value)
    assert "6 light rows but 1 image" in msg
    assert "left out for their names (hidden files, or names psctl gives its outputs): 5, .006.png, depth_002.png, " \
           "depth_003.png ..." in msg, msg
    assert "mask.png" not in msg and "Normal_gt" not in msg


def test_a_capture_given_as_a_benchmark_root_says_so(tmp_path):
    write_capture(tmp_path / "cap", n=4, size=16)
    with pytest.raises(PsctlError, match="no object folders found .*one capture folder: psctl normals"):
        find_objects(tmp_path / "cap")
    (tmp_path / "empty").mkdir()
    with pytest.raises(PsctlError, match=r"no object folders found \(expected subfolders with images, or objects.txt\)$"):
        find_objects(tmp_path / "empty")


@pytest.mark.parametrize("ext", ["tif", "jpg"])
def test_exif_orientation_is_applied_as_openimageio_reorients(tmp_path, ext):
    """Phone JPEGs are stored sideways with an Orientation tag: read upright, as viewers show them
    (the same pixels as OpenImageIO's own reorient), and the header's size is the upright one."""
    import OpenImageIO as oiio

    from psctl.io.images import image_info

    a = np.random.default_rng(0).random((5, 7, 3)).astype(np.float32)
    for o in range(1, 9):
        path = str(tmp_path / f"o{o}.{ext}")
        spec = oiio.ImageSpec(7, 5, 3, "uint16" if ext == "tif" else "uint8")
        spec.attribute("Orientation", o)
        out = oiio.ImageOutput.create(path)
        assert out.open(path, spec) and out.write_image(a)
        out.close()
        ref = oiio.ImageBufAlgo.reorient(oiio.ImageBuf(path)).get_pixels(oiio.FLOAT)
        mine, info = read_image(path)
        assert info.orientation == o and mine.shape == ref.shape == (*((7, 5) if o >= 5 else (5, 7)), 3)
        assert (image_info(path).height, image_info(path).width) == mine.shape[:2]
        np.testing.assert_array_equal(mine, ref)


def test_a_capture_of_turned_photos_reads_upright_with_a_note(tmp_path):
    """Images stored sideways with Orientation 6 give the normals of the upright ones, and say so."""
    import OpenImageIO as oiio

    from psctl.api import run_normals

    data = write_capture(tmp_path / "upright", n=8, size=24, intensities=False)
    turned = tmp_path / "turned"
    turned.mkdir()
    for f in ("light_directions.txt", "mask.png", "Normal_gt.mat"):
        (turned / f).write_bytes((tmp_path / "upright" / f).read_bytes())
    names = []
    for k, img in enumerate(data["images"]):
        stored = np.rot90(img, 1)  # what a camera held sideways stores; Orientation 6 turns it back
        spec = oiio.ImageSpec(stored.shape[1], stored.shape[0], 3, "uint16")
        spec.attribute("Orientation", 6)
        path = str(turned / f"{k:03d}.tif")
        out = oiio.ImageOutput.create(path)
        assert out.open(path, spec) and out.write_image(np.ascontiguousarray(stored, dtype=np.float32))
        out.close()
        names.append(f"{k:03d}.tif")
    (turned / "filenames.txt").write_text("\n".join(names) + "\n")
    a = run_normals(tmp_path / "upright", method="l2", write=False)
    b = run_normals(turned, method="l2", write=False)
    assert b["mae"] == pytest.approx(a["mae"], abs=0.05) and a["mae"] < 2
    assert any("8 of 8 images turned upright" in n for n in b["notes"])


def test_a_size_error_after_an_exif_turn_gives_both_sizes(tmp_path):
    """Every file holds 6 x 4 pixels, but the first is tagged Orientation 6 (upright: 4 x 6): the
    size error says so, not a bare 4x6 that no other program shows for the file."""
    import OpenImageIO as oiio

    folder = tmp_path / "cap"
    folder.mkdir()
    for k, o in enumerate((6, 1, 1)):
        spec = oiio.ImageSpec(6, 4, 3, "uint8")
        if o != 1:
            spec.attribute("Orientation", o)
        path = str(folder / f"{k + 1:03d}.jpg")
        out = oiio.ImageOutput.create(path)
        assert out.open(path, spec) and out.write_image(np.full((4, 6, 3), 0.5, np.float32))
        out.close()
    np.savetxt(folder / "light_directions.txt", [[0, 0, 1]] * 3)
    with pytest.raises(PsctlError) as e:
        open_capture(folder)
    # the odd one out is named (the first image here), against the size most images have
    assert str(e.value).endswith("001.jpg: size 4x6 upright (EXIF orientation 6; 6x4 as stored) differs from the "
                                 "other 2 images' (6x4)"), str(e.value)


def test_a_capture_of_mixed_sample_types_and_channels_says_so(tmp_path):
    """A folder whose images were saved at different depths, or some in grey, runs, with a note
    (psctl info showed the mix; psctl normals said nothing)."""
    from psctl.api import run_normals

    write_capture(tmp_path / "cap", n=6, size=16)
    img, _ = read_image(tmp_path / "cap" / "002.png")
    write_image(tmp_path / "cap" / "002.png", img, "uint8")
    write_image(tmp_path / "cap" / "003.png", img[..., :1], "uint16")
    notes = run_normals(tmp_path / "cap", method="l2", write=False)["notes"]
    assert "images: of mixed sample types (5 16-bit, 1 8-bit: 002.png the rarer); each is read with its own full " \
           "scale as 1 (psctl info --check compares their brightness)" in notes, notes
    assert any(n.startswith("images: of mixed channel counts (5 of 3 channels, 1 of 1 channel)") for n in notes)
    plain = run_normals(write_capture(tmp_path / "plain", n=6, size=16) and tmp_path / "plain", method="l2",
                        write=False)["notes"]
    assert not any("mixed" in n for n in plain)

    # int16 beside uint16: OpenImageIO reads signed codes over 32767, twice as bright (helper-180:
    # l2 5.73 against 5.21 degrees, without a note, as both were "16-bit")
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(16, 16, 3, "int16")
    path = str(tmp_path / "plain" / "004.tif")
    out = oiio.ImageOutput.create(path)
    assert out.open(path, spec) and out.write_image((read_image(tmp_path / "plain" / "004.png")[0] * 32767).astype(np.int16))
    out.close()
    names = (tmp_path / "plain" / "filenames.txt").read_text().replace("004.png", "004.tif")
    (tmp_path / "plain" / "filenames.txt").write_text(names)
    (tmp_path / "plain" / "004.png").unlink()
    notes = run_normals(tmp_path / "plain", method="l2", write=False)["notes"]
    assert any(n.startswith("images: of mixed sample types (5 16-bit, 1 16-bit signed: 004.tif the rarer)")
               for n in notes), notes


def _low_depth_png(path, codes, depth, colour_type=0):
    """A grey (colour type 0) PNG of 1-, 2- or 4-bit samples, written byte by byte (OpenImageIO
    writes 8 bits at least)."""
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    h, w = codes.shape
    per = 8 // depth
    rows = b""
    for row in codes:
        packed = [sum(int(v) << (8 - depth * (i + 1)) for i, v in enumerate(row[j:j + per])) for j in range(0, w, per)]
        rows += b"\x00" + bytes(packed)
    head = struct.pack(">IIBBBBB", w, h, depth, colour_type, 0, 0, 0)
    extra = chunk(b"PLTE", bytes(range(3 * 2 ** depth))) if colour_type == 3 else b""
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", head) + extra + chunk(b"IDAT", zlib.compress(rows))
                     + chunk(b"IEND", b""))


def test_a_png_of_fewer_than_8_bits_is_named_by_its_own_depth(tmp_path):
    """OpenImageIO reads a 4-bit grey PNG as 8-bit samples at full range (its values are right) and
    gives no bit depth: the mixed-types note called it "8-bit" (helper-180), and an empty mask's
    message counted its codes out of 255."""
    from psctl.api import run_normals

    codes = np.tile(np.arange(16, dtype=np.uint8), (16, 1))
    _low_depth_png(tmp_path / "g4.png", codes, 4)
    info = image_info(tmp_path / "g4.png")
    assert (info.bits, info.dtype) == (4, "uint8")
    assert np.allclose(read_image(tmp_path / "g4.png")[0][..., 0], codes / 15)
    _low_depth_png(tmp_path / "p4.png", codes, 4, colour_type=3)  # a palette's samples are 8-bit
    assert image_info(tmp_path / "p4.png").bits == 8

    write_capture(tmp_path / "cap", n=6, size=16)
    img, _ = read_image(tmp_path / "cap" / "002.png")
    _low_depth_png(tmp_path / "cap" / "002.png", np.round(img.mean(-1) * 15).astype(np.uint8), 4)
    write_image(tmp_path / "cap" / "003.png", img, "uint8")
    notes = run_normals(tmp_path / "cap", method="l2", write=False)["notes"]
    assert any(n.startswith("images: of mixed sample types (4 16-bit, 1 4-bit, 1 8-bit: 002.png, 003.png the rarer)") for n in notes), notes

    _low_depth_png(tmp_path / "cap" / "mask.png", np.ones((16, 16), np.uint8), 4)  # 0/1 codes: a bool mask
    with pytest.raises(PsctlError, match=r"the brightest is 1 of 15; a 0/1 mask\? save the object as 15"):
        run_normals(tmp_path / "cap", method="l2", write=False)


def test_twelve_bit_codes_in_a_sixteen_bit_file_beside_full_range_ones_are_noted(tmp_path):
    """Every third image saved as 12-bit codes (0..4095) in a 16-bit PNG reads 16 times darker:
    helper-180 measured l2 5.21 -> 7.74 degrees without a note (the types match, and 16 times is
    under the darker-image note's 20). Now a note names them, in psctl normals and psctl info
    --check; a capture saved wholly so, or full-range, has none."""
    from psctl.api import run_normals
    from psctl.io.capture import open_capture
    from psctl.io.summary import describe_capture

    for name, which in (("mixed", range(0, 12, 3)), ("all", range(12)), ("plain", ())):
        write_capture(tmp_path / name, n=12, size=24)
        for k in which:
            path = tmp_path / name / f"{k + 1:03d}.png"
            img = read_image(path)[0]
            write_image(path, np.round(img * 4095) / 65535, "uint16")
    words = "and some read over 8 times darker over the object than the median image, which goes above it"
    notes = run_normals(tmp_path / "mixed", method="l2", write=False)["notes"]
    hit = [n for n in notes if words in n]
    assert len(hit) == 1 and hit[0].startswith("images: 4 of 12 have no value above code 4095 of 65535 (001.png, "
                                                "004.png"), notes
    assert not any("times darker over the object than the median image" in n and "over 20" in n for n in notes)
    # one of them listed 4 times dimmer (so only 4 times darker once divided): named with the others,
    # as LCNet's reading as captured needs (helper-187: lights named 5 of 8, normals 8)
    e = np.loadtxt(tmp_path / "mixed" / "light_intensities.txt")
    np.savetxt(tmp_path / "mixed" / "light_intensities.txt", np.where(np.arange(12)[:, None] == 0, e / 4, e))
    again = [n for n in run_normals(tmp_path / "mixed", method="l2", write=False)["notes"] if words in n]
    assert again == hit, again
    np.savetxt(tmp_path / "mixed" / "light_intensities.txt", e)
    info = describe_capture(tmp_path / "mixed", check=True)
    assert any(words in n for n in info["check"]["notes"]), info["check"]["notes"]
    for name in ("all", "plain"):
        assert not any("code 4095" in n for n in run_normals(tmp_path / name, method="l2", write=False)["notes"])
    assert open_capture(tmp_path / "mixed").kinds[0] == (16, "uint16")


def test_capture_file_names_in_any_case_and_files_it_does_not_read(tmp_path):
    """Mask.PNG and Light_Directions.txt are the mask and the light file; two masks are an error;
    a file that looks meant for psctl but is not read (light_intensity.txt) gets a note."""
    from psctl.io.capture import capture_notes

    cap_dir = tmp_path / "cap"
    write_capture(cap_dir, n=6, size=16)
    (cap_dir / "mask.png").rename(cap_dir / "Mask.PNG")
    (cap_dir / "light_directions.txt").rename(cap_dir / "Light_Directions.txt")
    (cap_dir / "light_intensities.txt").rename(cap_dir / "light_intensity.txt")
    cap = open_capture(cap_dir)
    assert cap.mask_path.name == "Mask.PNG" and cap.calibrated and not cap.intensities_given
    assert cap.lights_path.name == "Light_Directions.txt" and cap.intensities_path is None  # as named (psctl info)
    assert any(n.startswith("files: not read: light_intensity.txt") for n in capture_notes(cap))
    write_image(cap_dir / "mask.tif", np.ones((16, 16)), "uint8")
    with pytest.raises(PsctlError, match=r"holds 2 masks \(Mask.PNG, mask.tif\); keep one"):
        open_capture(cap_dir)


def test_capture_text_files_with_a_byte_order_mark_and_list_mistakes(tmp_path):
    cap_dir = tmp_path / "cap"
    write_capture(cap_dir, n=6, size=16)
    for name in ("filenames.txt", "light_directions.txt"):  # Excel's "CSV UTF-8" writes a BOM
        (cap_dir / name).write_bytes(b"\xef\xbb\xbf" + (cap_dir / name).read_bytes())
    cap = open_capture(cap_dir)
    assert cap.n_images == 6 and cap.image_paths[0].name == "001.png"
    names = (cap_dir / "filenames.txt").read_text(encoding="utf-8-sig").split()
    (cap_dir / "filenames.txt").write_text("\n".join(names[:5] + ["mask.png"]) + "\n")
    with pytest.raises(PsctlError, match="is the mask but is also listed in filenames.txt"):
        open_capture(cap_dir)
    (cap_dir / "filenames.txt").write_text("\n".join(names[:5] + names[:1]) + "\n")
    with pytest.raises(PsctlError, match="001.png: listed twice in filenames.txt"):
        open_capture(cap_dir)
    (cap_dir / "filenames.txt").write_text("\n".join(names[:5] + ["./" + names[0]]) + "\n")  # the same name
    with pytest.raises(PsctlError, match="listed twice in filenames.txt"):
        open_capture(cap_dir)
    (cap_dir / "again.png").symlink_to(cap_dir / names[0])  # two names for one file: a deliberate repeat
    (cap_dir / "filenames.txt").write_text("\n".join(names[:5] + ["again.png"]) + "\n")
    assert open_capture(cap_dir).n_images == 6


def test_lights_behind_the_object(tmp_path):
    """z away from the camera in every row is an error naming the file; in some rows, a note."""
    from psctl.io.capture import capture_notes

    write_capture(tmp_path / "cap", n=6, size=16)
    f = tmp_path / "cap" / "light_directions.txt"
    rows = np.loadtxt(f)
    np.savetxt(f, rows * [1, 1, -1])
    with pytest.raises(PsctlError, match="light_directions.txt: every light has z <= 0"):
        open_capture(tmp_path / "cap")
    rows[[1, 4], 2] *= -1
    np.savetxt(f, rows)
    assert any(n.startswith("light file: 2 of 6 light directions have z <= 0") and "rows 2, 5" in n
               for n in capture_notes(open_capture(tmp_path / "cap")))


def test_ground_truth_mistakes_are_refused_or_noted(tmp_path):
    """A 1-channel Normal_gt.png is refused; ground truth with y down or z away gets a note; NaN in
    a float ground truth means no normal, as in float normal maps."""
    from psctl.api import run_normals
    from psctl.io.normals import write_normal_map

    data = write_capture(tmp_path / "cap", n=8, size=24, gt="png")
    gt_file = tmp_path / "cap" / "Normal_gt.png"
    write_image(gt_file, np.full((24, 24), 0.5), "uint16")
    with pytest.raises(PsctlError, match="Normal_gt.png: ground truth needs 3 channels"):
        run_normals(tmp_path / "cap", method="l2", write=False)
    n, m = data["normals"], data["mask"]
    for flip, needle in (([1, -1, 1], "with y flipped far better"), ([1, 1, -1], "point away from the camera")):
        write_normal_map(gt_file, n * flip, m, "png16")
        r = run_normals(tmp_path / "cap", method="l2", write=False)
        assert any(needle in note for note in r["notes"]), r["notes"]
    write_normal_map(gt_file, n, m, "png16")
    assert not any(note.startswith("ground truth") for note in run_normals(tmp_path / "cap", method="l2", write=False)["notes"])
    gt_file.unlink()
    exr = np.where(m[..., None], n, np.nan).astype(np.float32)
    write_image(tmp_path / "cap" / "Normal_gt.exr", exr, "float")
    r = run_normals(tmp_path / "cap", method="l2", write=False)
    assert r["mae"] < 2 and r["n_evaluated_pixels"] == m.sum()


def test_linked_folder_keeps_its_name_and_broken_image_links_are_named(tmp_path):
    import os

    write_capture(tmp_path / "cap_real", n=6, size=16)
    os.symlink(tmp_path / "cap_real", tmp_path / "ballPNG")
    assert open_capture(tmp_path / "ballPNG").name == "ball"  # the name the user gave, not the target's
    (tmp_path / "cap_real" / "filenames.txt").unlink()
    (tmp_path / "cap_real" / "006.png").rename(tmp_path / "elsewhere.png")
    os.symlink(tmp_path / "gone.png", tmp_path / "cap_real" / "006.png")  # a broken link: not an image
    with pytest.raises(PsctlError, match=r"6 light rows but 5 images .*not files, so not read: 006.png"):
        open_capture(tmp_path / "cap_real")


def test_tensors_that_require_grad_are_read(tmp_path):
    import torch

    from psctl.api import estimate_normals

    data = write_capture(tmp_path / "cap", n=8, size=16, intensities=False)
    imgs = torch.tensor(data["images"], requires_grad=True)
    n = estimate_normals(imgs, torch.tensor(data["lights"], requires_grad=True), torch.tensor(data["mask"]), method="l2")
    assert n.shape == (16, 16, 3)


def test_any_case_names_also_make_a_capture_and_spread_never_repeats(tmp_path):
    """Filenames.txt (images in a subfolder) is a capture's list, Mask.PNG makes a folder a capture
    (never an output folder); a spread subset of repeated lights has no image twice."""
    from psctl.io.capture import holds_capture, spread_lights

    cap = tmp_path / "cap"
    write_capture(cap / "img", n=6, size=16)
    names = (cap / "img" / "filenames.txt").read_text().split()
    (cap / "Filenames.txt").write_text("".join(f"img/{n}\n" for n in names))
    for f in ("light_directions.txt", "light_intensities.txt", "mask.png"):
        (cap / "img" / f).rename(cap / f)
    (cap / "img" / "filenames.txt").unlink()
    (cap / "img" / "Normal_gt.mat").unlink()
    assert open_capture(cap).n_images == 6
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "Mask.PNG").write_bytes((cap / "mask.png").read_bytes())
    assert holds_capture(tmp_path / "out")
    rig = np.array([[0, 0, 1], [0.3, 0, 1], [0, 0.3, 1], [-0.3, 0, 1]] * 2, float)
    assert len(set(spread_lights(rig, 6))) == 6


def test_a_tiff_stack_is_named_in_the_count_error(tmp_path):
    """A multi-page TIFF counts as one image: the count error says how many pages it holds."""
    import OpenImageIO as oiio

    cap = tmp_path / "cap"
    cap.mkdir()
    path = str(cap / "stack.tif")
    spec = oiio.ImageSpec(8, 8, 3, "uint16")
    out = oiio.ImageOutput.create(path)
    assert out.open(path, [spec] * 4)
    for i in range(4):
        if i:
            assert out.open(path, spec, "AppendSubimage")
        assert out.write_image(np.full((8, 8, 3), (i + 1) / 5, np.float32))
    out.close()
    np.savetxt(cap / "light_directions.txt", [[0, 0, 1], [0.3, 0, 1], [0, 0.3, 1], [-0.3, 0, 1]])
    with pytest.raises(PsctlError, match=r"4 light rows but 1 image .*stack.tif holds 4 pages: psctl reads one image per file"):
        open_capture(cap)
    # where the counts agree (stacks among single images), a note says which file is a stack
    from psctl.io.capture import capture_notes

    for k in range(2, 5):
        write_image(cap / f"{k:03d}.tif", np.full((8, 8, 3), k / 5, np.float32))
    (cap / "filenames.txt").write_text("stack.tif\n002.tif\n003.tif\n004.tif\n")
    c = open_capture(cap)
    assert c.pages == (4, 1, 1, 1) and c.subset([1, 0]).pages == (1, 4)
    assert [n for n in capture_notes(c) if "pages" in n] == [
        "images: stack.tif holds 4 pages; psctl reads one image per file, its first page"]
    assert not any("pages" in n for n in capture_notes(c.subset([1, 2])))


def test_more_capture_mistakes_name_their_cause(tmp_path):
    """Case in filenames.txt, images skipped by their names, UTF-16 text, a second ground-truth
    file listed as an image, NaN in a .mat ground truth (no normal), a uint16 0/255 API mask."""
    import scipy.io

    from psctl.arrays import as_mask

    cap = tmp_path / "cap"
    data = write_capture(cap, n=6, size=16)
    names = (cap / "filenames.txt").read_text().split()
    (cap / "filenames.txt").write_text("\n".join([names[0].upper(), *names[1:]]) + "\n")
    with pytest.raises(PsctlError, match=r"listed in filenames.txt but missing \(001.png is there"):
        open_capture(cap)
    (cap / "filenames.txt").write_text("\n".join(names) + "\n", encoding="utf-16")
    with pytest.raises(PsctlError, match=r"filenames.txt: is UTF-16 text \(Excel's 'Unicode text'\), not UTF-8"):
        open_capture(cap)
    (cap / "filenames.txt").write_text("\n".join(names) + "\n", encoding="utf-16-le")  # no byte-order mark
    with pytest.raises(PsctlError, match="filenames.txt: is UTF-16 text"):
        open_capture(cap)
    (cap / "filenames.txt").write_bytes(("\n".join(names) + "\ncaf\xe9.png\n").encode("latin-1"))
    with pytest.raises(PsctlError, match=r"filenames.txt: is not UTF-8 text \(Latin-1 or another"):
        open_capture(cap)
    (cap / "light_directions.txt").write_bytes(b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR\xff\xfe")
    with pytest.raises(PsctlError, match=r"light_directions.txt: is not UTF-8 text \(binary data"):
        read_matrix(cap / "light_directions.txt", (3,), "light directions")
    # rows of allowed but different widths: the first odd line is named, as every other row error is
    (cap / "light_intensities.txt").write_text("# R G B or one value\n1 1 1\n\n1 1 1\n0.5\n1 1 1\n")
    with pytest.raises(PsctlError, match=r"light_intensities.txt: line 5: 1 value, but line 2 has 3"):
        read_matrix(cap / "light_intensities.txt", (1, 3), "light intensities")
    # decimal commas (a European spreadsheet's export): said, where a row of them has a width's worth
    for row, n in (("0,1 0,2 0,97", 6), ("0,5 0 0,866", 5)):
        (cap / "light_directions.txt").write_text(row + "\n")
        with pytest.raises(PsctlError, match=rf"line 1: expected 3 values, found {n} \(decimal commas\? psctl reads a"):
            read_matrix(cap / "light_directions.txt", (3,), "light directions")
    # semicolons (a spreadsheet's CSV in a European locale) and empty fields (helper-174: read as 3 values)
    for row, words in (("0,1;0,2;0,97", r"\(semicolons are not separators: use spaces, tabs or commas; and psctl "
                                        r"reads a point as the decimal mark"),
                       ("0.1;0.2;0.97", r"\(semicolons are not separators: use spaces, tabs or commas\)$"),
                       ("0.1,,0.2,0.97", "an empty field in '0.1,,0.2,0.97'"), (",0.1,0.2,0.97", "an empty field")):
        (cap / "light_directions.txt").write_text(row + "\n")
        with pytest.raises(PsctlError, match=rf"line 1: .*{words}"):
            read_matrix(cap / "light_directions.txt", (3,), "light directions")
    (cap / "light_directions.txt").write_text("0.1, 0.2,\t0.97,\n")  # a trailing comma is no field
    assert read_matrix(cap / "light_directions.txt", (3,), "light directions").shape == (1, 3)
    (cap / "light_directions.txt").write_text("0,1,0.2,0.97,1\n")  # commas as separators: no such word
    with pytest.raises(PsctlError, match=r"line 1: expected 3 values, found 5$"):
        read_matrix(cap / "light_directions.txt", (3,), "light directions")
    lines: list[int] = []
    (cap / "light_intensities.txt").write_text("# R G B\n1 1 1\n\n2 2 2\n")
    assert read_matrix(cap / "light_intensities.txt", (1, 3), "light intensities", lines).shape == (2, 3)
    assert lines == [2, 4]
    (cap / "filenames.txt").write_text("\n".join([*names, "Normal_gt.png"]) + "\n")
    write_image(cap / "Normal_gt.png", np.zeros((16, 16, 3)), "uint16")
    np.savetxt(cap / "light_directions.txt", np.vstack([data["lights"], [[0, 0, 1]]]))
    np.savetxt(cap / "light_intensities.txt", np.ones((7, 3)))
    with pytest.raises(PsctlError, match="Normal_gt.png: is named as a mask or ground truth but is listed"):
        open_capture(cap)
    gt = np.where(data["mask"][..., None], data["normals"], np.nan)
    scipy.io.savemat(cap / "Normal_gt.mat", {"Normal_gt": gt})
    (cap / "Normal_gt.png").unlink()
    (cap / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(cap / "light_directions.txt", data["lights"])
    np.savetxt(cap / "light_intensities.txt", np.ones((6, 3)))
    from psctl.io.capture import load_ground_truth

    assert np.isfinite(load_ground_truth(open_capture(cap))).all()
    other = tmp_path / "named"
    other.mkdir()
    for k in range(3):
        write_image(other / f"lights_{k}.png", np.zeros((8, 8, 3)), "uint8")
    with pytest.raises(PsctlError, match="no images found .*lights_0.png.* are taken for a mask, normals or outputs"):
        open_capture(other)
    # images in a format psctl does not look for (a QA helper's .bmp folder): named, and how to read them
    for k in range(3):
        (other / f"lights_{k}.png").unlink()
        (other / f"{k + 1:03d}.bmp").write_bytes(b"BM")
    write_image(other / "mask.png", np.ones((8, 8)), "uint8")
    np.savetxt(other / "light_directions.txt", data["lights"][:3])
    (other / "README").write_text("my capture")  # no image: not named among them (review finding)
    (other / "Thumbs.db").write_bytes(b"")
    with pytest.raises(PsctlError, match=r"no images found \(.*\); mask.png is taken for a mask, normals or outputs "
                                         r"by name; 001.bmp, 002.bmp, 003.bmp are not read unless listed: list the "
                                         r"images in filenames.txt$"):
        open_capture(other)
    with pytest.raises(PsctlError, match=r"mask is empty .*uint16 masks are divided by 65535"):
        as_mask(np.full((4, 4), 255, np.uint16), (4, 4))
    # psctl's own output folder taken for a capture: said so, and where the capture is (helper-159)
    from psctl.api import run_normals

    run_normals(cap, method="l2")
    run_normals(cap, method="l2", out=tmp_path / "o" / "psctl")  # named psctl, in no capture: read, not guessed
    for folder in (cap / "psctl", tmp_path / "o" / "psctl"):
        with pytest.raises(PsctlError) as e:
            open_capture(folder)
        assert e.value.message == (f"is an output folder of psctl normals, not a capture (no images); run on the "
                                   f"capture folder it was made from, {cap}")
    (tmp_path / "o" / "psctl" / "report.json").unlink()
    with pytest.raises(PsctlError, match=r"not a capture \(no images\); run on the capture folder it was made from$"):
        open_capture(tmp_path / "o" / "psctl")


def test_a_broken_link_named_as_the_mask_says_so(tmp_path):
    import os

    write_capture(tmp_path / "cap", n=4, size=16)
    (tmp_path / "cap" / "mask.png").unlink()
    os.symlink(tmp_path / "gone.png", tmp_path / "cap" / "mask.png")
    with pytest.raises(PsctlError, match=r"mask.png: is a broken link \(to .*gone.png\)"):
        open_capture(tmp_path / "cap")


@pytest.mark.parametrize("method", ["l2", "ps-fcn", "sdps", "lights"])
def test_a_black_image_gets_a_note(tmp_path, method, monkeypatch):
    """One image black over the object (a light that did not fire): a note names it, once, for L2,
    the networks, sdps and psctl lights (small random networks stand in for the release weights)."""
    from psctl.api import run_normals
    from psctl.lights import run_lights
    from psctl.models.lcnet import LCNet
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    write_capture(tmp_path / "cap", n=8, size=24)
    write_image(tmp_path / "cap" / "003.png", np.zeros((24, 24, 3)), "uint16")
    weights, lcnet = tmp_path / "w.pt", tmp_path / "l.pt"
    save_weights(weights, PSFCN(), {"method": "ps-fcn", "train_images": 32})
    save_weights(lcnet, LCNet(), {"method": "lcnet", "train_images": 32})
    if method == "lights":
        r = run_lights(tmp_path / "cap", weights=lcnet, normals_weights=weights, write=False, device="cpu")
    else:
        r = run_normals(tmp_path / "cap", method=method, weights=None if method == "l2" else weights,
                        lcnet=lcnet if method == "sdps" else None, write=False, device="cpu")
    hits = [n for n in r["notes"] if n.startswith("images: 1 of 8 black over the object (003.png)")]
    assert len(hits) == 1, r["notes"]


@pytest.mark.parametrize("method", ["l2", "sdps"])
def test_negative_float_pixels_get_a_note(tmp_path, method):
    """A float image with negative values over the object (noise about a subtracted black level)
    is taken as stored, with one note naming it (sdps reads it in both stages, divided by different
    intensities: still one note)."""
    from psctl.api import run_normals
    from psctl.models.lcnet import LCNet
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    arrays = write_capture(tmp_path / "cap", n=8, size=24)
    img = arrays["images"][2] - 0.05  # the shadowed side goes below zero
    write_image(tmp_path / "cap" / "003.exr", img, "float")
    (tmp_path / "cap" / "003.png").unlink()
    names = (tmp_path / "cap" / "filenames.txt").read_text().replace("003.png", "003.exr")
    (tmp_path / "cap" / "filenames.txt").write_text(names)
    kw = {}
    if method == "sdps":
        kw = {"weights": tmp_path / "w.pt", "lcnet": tmp_path / "l.pt"}
        save_weights(kw["weights"], PSFCN(), {"method": "ps-fcn", "train_images": 32})
        save_weights(kw["lcnet"], LCNet(), {"method": "lcnet", "train_images": 32})
    r = run_normals(tmp_path / "cap", method=method, write=False, device="cpu", **kw)
    hits = [n for n in r["notes"] if "negative values" in n]
    assert hits == ["images: 1 of 8 have negative values over the object (003.exr): taken as stored "
                    "(noise about a subtracted black level?)"], r["notes"]


def test_benchmark_sheet_draws_each_objects_maps():
    from psctl.io.report import SPREAD_VMAX, benchmark_sheet, jet, object_panel, text_bitmap

    mask = np.zeros((50, 80), bool)
    mask[10:30, 20:60] = True  # 20 x 40: the panel is cropped to it (4 px margin) and scaled to 40 rows
    normals = np.zeros((50, 80, 3), np.float32)
    normals[..., 2] = 1.0
    error = np.full((50, 80), 30.0, np.float32)
    p = object_panel("cat", 1.234, normals, error, mask, vmax=45.0, height=40)
    assert p["normals"].shape == (40, round(48 * 40 / 28), 3) and p["error"].shape == p["normals"].shape
    assert np.allclose(p["normals"][20, 34], (0.5, 0.5, 1.0)) and np.allclose(p["normals"][0, 0], 0.0)  # margin: outside
    assert np.allclose(p["error"][20, 34], jet(np.float32(30 / 45)))
    q = object_panel("pot2", None, normals, None, mask, height=40)  # no ground truth: no error map
    sheet = benchmark_sheet([p, q], "L2  MEAN 1.23°")
    assert sheet.ndim == 3 and sheet.shape[2] == 3 and 0 <= sheet.min() and sheet.max() <= 1
    blue = np.isclose(sheet, (0.5, 0.5, 1.0)).all(-1)
    assert blue.sum() == 2 * (p["normals"][..., 2] == 1.0).sum()  # both normal maps, every object pixel
    red = jet(np.float32(30 / 45))
    bar = np.isclose(jet(np.linspace(1.0, 0.0, 40)), red).all(-1).sum() * 10  # the colour bar's rows of it, 10 px wide
    assert np.isclose(sheet, red).all(-1).sum() == (p["error"][..., 0] > 0).sum() + bar  # one error map, and the bar
    with pytest.raises(ValueError, match="at least one panel"):  # not a TypeError from deep inside
        benchmark_sheet([], "X")
    rows = benchmark_sheet([p, q, p], "X", per_row=2)  # two rows, each with its colour bar
    assert np.isclose(rows, (0.5, 0.5, 1.0)).all(-1).sum() == 3 * (p["normals"][..., 2] == 1.0).sum()
    assert np.isclose(rows, red).all(-1).sum() == 2 * ((p["error"][..., 0] > 0).sum() + bar)
    assert rows.shape[0] > sheet.shape[0] + 2 * 40 and rows.shape[1] < sheet.shape[1] + 2 * 40
    # the ensemble's spread: a third map under the error map, with its own colour bar (0..SPREAD_VMAX)
    r = object_panel("cat", 1.234, normals, error, mask, height=40, spread=np.full((50, 80), 6.0, np.float32))
    green = jet(np.float32(6 / SPREAD_VMAX))
    assert np.allclose(r["spread"][20, 34], green) and np.allclose(r["spread"][0, 0], 0.0) and p["spread"] is None
    three = benchmark_sheet([r, q], "L2  MEAN 1.23°")
    assert three.shape[:2] == (sheet.shape[0] + 40 + 4, sheet.shape[1])
    bar2 = np.isclose(jet(np.linspace(1.0, 0.0, 40)), green).all(-1).sum() * 10  # in each of the two bars
    assert np.isclose(three, green).all(-1).sum() == (r["spread"][..., 0] > 0).sum() + 2 * bar2
    np.testing.assert_array_equal(three[: sheet.shape[0] - 12], sheet[: sheet.shape[0] - 12])  # the rest as before
    # each bar labelled by its own scale (at eval.png's panel heights, 96 or 160 px; text scale 2)
    tall = benchmark_sheet([object_panel("cat", 1.234, normals, error, mask, height=160,
                                         spread=np.full((50, 80), 6.0, np.float32))], "X")
    assert _text_at(tall, ">45°", 2) and _text_at(tall, f">{SPREAD_VMAX:.0f}°", 2) and _text_at(tall, "MAE 1.23°", 2)
    (ey, ex), = _text_at(tall, "ERROR", 2)  # each bar named above it, so that the two read as two
    (sy, sx), = _text_at(tall, "SPREAD", 2)
    assert ex == sx and sy - ey == 160 + 4 and sx + text_bitmap("SPREAD", 2).shape[1] <= tall.shape[1]
    # an object wider than 3:1 keeps its aspect: 3 x height columns and fewer rows, centred in the row
    strip = np.zeros((40, 400), bool)
    strip[:, :] = True
    wide = object_panel("strip", 1.0, np.zeros((40, 400, 3), np.float32), np.full((40, 400), 30.0, np.float32), strip,
                        height=40)
    assert wide["normals"].shape == (round(120 * 40 / 400), 120, 3) == wide["error"].shape  # the box: the image
    both = benchmark_sheet([wide, p], "X")
    col = np.nonzero(np.isclose(both[:, 12 + 60], red).all(-1))[0]  # the strip's error map, down its middle column
    assert len(col) == wide["error"].shape[0] and col[0] - (12 + 20 + 12 + 40 + 40 + 4) == (40 - len(col)) // 2
    # an object taller than 1:3 is height / 3 wide, as tall as its aspect makes it to 3 x height, and
    # its row as tall (a 25:1 object was a 6 px sliver; helper-162)
    for rows, cols, shape in ((400, 100, (53, 13)), (1000, 40, (120, 5))):
        pole = np.ones((rows, cols), bool)
        t = object_panel("pole", 1.0, np.zeros((rows, cols, 3), np.float32), np.full((rows, cols), 30.0, np.float32),
                         pole, height=40)
        assert t["normals"].shape[:2] == t["error"].shape[:2] == shape
    mixed_rows = benchmark_sheet([t, p], "X")
    col = np.nonzero(np.isclose(mixed_rows[:, 12 + 2], red).all(-1))[0]  # the pole's error map, whole
    assert len(col) == 120 and mixed_rows.shape[0] == both.shape[0] + 2 * (120 - 40)
    # grey (a mask pixel without ground truth) is keyed at the bottom, only when some panel has it
    from psctl.io.report import UNSCORED_KEY

    holed = error.copy()
    holed[12:16, 30:40] = np.nan
    g = object_panel("cat", 1.0, normals, holed, mask, height=40)
    assert g["unscored"] and not p["unscored"] and not q["unscored"]
    keyed = benchmark_sheet([g, q], "X")
    (ky, _), = _text_at(keyed, UNSCORED_KEY, 2)
    assert keyed.shape[0] == sheet.shape[0] + 20 and ky > sheet.shape[0] - 12
    assert not _text_at(sheet, UNSCORED_KEY, 2)
    # names drawn as spelt: all of ASCII, accents dropped, "?" for what the font cannot spell
    from psctl.io.report import drawable

    assert drawable("chat_été pot#2 [a]{b}~ß 猫 Ärger") == "chat_ete pot#2 [a]{b}~ss ? Arger"
    named = benchmark_sheet([object_panel("chat_été #2", 1.0, normals, error, mask, height=40)], "données 猫")
    assert _text_at(named, "chat_ete #2", 2) and _text_at(named, "donnees ?", 2)
    assert not _text_at(named, "CHAT_ETE #2", 2)  # (as spelt: small letters, not capitals)
    # a run that mixes methods: only the row with a spread map gets the third row of maps and its bar
    mixed = benchmark_sheet([r, q, p, q], "X", per_row=2)
    assert np.isclose(mixed, green).all(-1).sum() == (r["spread"][..., 0] > 0).sum() + 2 * bar2
    plain = benchmark_sheet([p, q, p, q], "X", per_row=2)
    assert mixed.shape[0] == plain.shape[0] + 40 + 4
    # a name wider than its maps takes two lines, split after the shape and cut in the middle; names
    # cut alike (MERL's endings) are written whole: no two objects share a label (helper-162)
    kw = dict(normals=normals, error=error, mask=mask, height=40)  # maps 69 px wide: 12 characters a line
    names = ("sphere_dark-red-paint", "sphere_gold-paint", "bunny_specular-violet-phenolic",
             "bunny_specular-white-phenolic")
    long = benchmark_sheet([object_panel(n, 1.0, **kw) for n in names], "X")
    for text, times in (("sphere_", 2), ("dark-..paint", 1), ("gold-paint", 1), ("bunny_", 2),
                        ("specular-violet-phenolic", 1), ("specular-white-phenolic", 1), ("specu..nolic", 0)):
        assert len(_text_at(long, text, 2)) == times, text
    assert long.shape[0] == benchmark_sheet([object_panel("cat", 1.0, **kw)] * 4, "X").shape[0] + 20  # one more line


def test_benchmark_sheet_of_many_objects_stays_roughly_square():
    from psctl.io.report import benchmark_sheet, object_panel, sheet_layout

    assert sheet_layout(10) == (5, 160) and sheet_layout(26) == (8, 160) and sheet_layout(200) == (20, 96)
    mask = np.ones((12, 12), bool)
    normals = np.zeros((12, 12, 3), np.float32)
    normals[..., 2] = 1.0
    n = 120
    per_row, height = sheet_layout(n)
    panels = [object_panel(f"obj{i:03d}", 1.0, normals, np.zeros((12, 12), np.float32), mask, height=height)
              for i in range(n)]
    sheet = benchmark_sheet(panels, "MANY")
    assert 0.5 < sheet.shape[0] / sheet.shape[1] < 2.0, sheet.shape  # 8 rows of 16, not a strip of 24 rows of 5
    blue = np.isclose(sheet, (0.5, 0.5, 1.0)).all(-1).sum()
    assert blue == n * (panels[0]["normals"][..., 2] == 1.0).sum()  # every object's normal map is on it
    five = benchmark_sheet(panels, "MANY", per_row=5)  # an explicit per_row still rules
    assert five.shape[0] > 2.5 * sheet.shape[0]  # 24 rows instead of 8


def test_npy_normal_maps_hold_real_floats(tmp_path):
    """An integer .npy (an encoded image's pixels) or a complex, text or record one is refused;
    a component beyond float32 or infinite is no normal (NaN), like NaN itself, without warnings."""
    import warnings

    good = np.zeros((4, 5, 3))
    good[..., 2] = 1.0
    for name, arr, needle in [("u16", (good * 65535).astype(np.uint16), r"holds integers \(uint16\)"),
                              ("c", good + 1j * good, "holds complex numbers"),
                              ("s", np.full((4, 5, 3), "a"), "values"),
                              ("r", np.zeros((4, 5, 3), dtype=[("a", "f4"), ("b", "f4")]), "values")]:
        np.save(tmp_path / f"{name}.npy", arr)
        with pytest.raises(PsctlError, match=needle):
            read_normal_map(tmp_path / f"{name}.npy")
    big = good.copy()
    big[1, 2, 0], big[3, 4, 1] = 1e300, np.inf
    np.save(tmp_path / "big.npy", big)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        n = read_normal_map(tmp_path / "big.npy")
    assert n.dtype == np.float32 and np.isnan(n[1, 2]).all() and np.isnan(n[3, 4]).all()
    assert np.isfinite(n).all(-1).sum() == 18 and (n[0, 0] == (0, 0, 1)).all()


def test_empty_objects_list_says_objects(tmp_path):
    from psctl.io.capture import find_objects

    (tmp_path / "objects.txt").write_text("# nothing yet\n")
    with pytest.raises(PsctlError, match="objects.txt: lists no objects"):
        find_objects(tmp_path)


def test_networks_on_degenerate_lights_or_extreme_exposure_say_so(tmp_path):
    """PS-FCN answers on coplanar lights (l2 refuses them) with a note that its normals are a guess;
    a capture 1e30 times brighter than training is scaled by 1e-31, not reported as 'scaled by 0'."""
    from psctl.api import run_normals
    from psctl.infer import array_normals
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    arrays = write_capture(tmp_path / "cap", n=8, size=24)
    a = np.radians(np.linspace(-40, 40, 8))
    flat = np.stack([np.sin(a), np.zeros(8), np.cos(a)], 1)  # all in the x-z plane
    np.savetxt(tmp_path / "cap" / "light_directions.txt", flat)
    save_weights(tmp_path / "w.pt", PSFCN(), {"method": "ps-fcn", "train_images": 32, "input_mean": 0.1})
    r = run_normals(tmp_path / "cap", method="ps-fcn", weights=tmp_path / "w.pt", write=False, device="cpu")
    assert any("light directions are (nearly) coplanar" in n and "expect large errors" in n for n in r["notes"]), r["notes"]
    with pytest.raises(PsctlError, match="coplanar"):
        run_normals(tmp_path / "cap", method="l2", write=False)
    # the array API has no report: the same note comes as a PsctlWarning
    from psctl.api import estimate_normals
    from psctl.errors import PsctlWarning

    imgs = np.asarray(arrays["images"], np.float32)
    with pytest.warns(PsctlWarning, match="coplanar.*expect large errors"):
        estimate_normals(imgs, flat, arrays["mask"], method="ps-fcn", weights=tmp_path / "w.pt", device="cpu")
    with pytest.warns(PsctlWarning, match="only 2 image"):
        estimate_normals(imgs[:2], arrays["lights"][:2], arrays["mask"], method="ps-fcn", weights=tmp_path / "w.pt")
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", PsctlWarning)  # good lights: no warning
        estimate_normals(imgs, arrays["lights"], arrays["mask"], method="ps-fcn", weights=tmp_path / "w.pt")
    bright = np.asarray(arrays["images"], np.float32) * np.float32(1e30)
    res = array_normals(bright, arrays["lights"], arrays["mask"], "ps-fcn", weights=tmp_path / "w.pt")
    scale = res.info["exposure_scale"]
    assert 1e-33 < scale < 1e-29, scale
    assert any(f"images scaled by {scale:.4g}" in n for n in res.notes) and not any("scaled by 0 " in n for n in res.notes)


def test_run_options_of_the_wrong_kind_are_errors(tmp_path):
    """A fractional image count is not rounded behind the user's back, text is not a seed, and a
    truthy "no" does not mean write."""
    from psctl.api import run_normals
    from psctl.lights import run_lights

    write_capture(tmp_path / "cap", n=8, size=16)
    for kw, needle in (({"n_images": 4.5}, "--images must be a whole number, not 4.5"),
                       ({"n_images": "4"}, "--images must be a whole number"),
                       ({"n_images": True}, "--images must be a whole number"),
                       ({"n_images": 4, "seed": "1"}, "--seed must be a whole number"),
                       ({"write": "no"}, "write must be True or False")):
        with pytest.raises(PsctlError, match=needle):
            run_normals(tmp_path / "cap", method="l2", out=tmp_path / "out", **{"write": True, **kw})
        with pytest.raises(PsctlError, match=needle):
            run_lights(tmp_path / "cap", out=tmp_path / "out", **{"write": True, **kw})
    assert not (tmp_path / "out").exists()
    r = run_normals(tmp_path / "cap", method="l2", write=False, n_images=np.int64(4), seed=4.0)  # whole numbers
    assert r["n_images"] == 4


def test_image_errors_keep_one_copy_of_each_message():
    """OpenImageIO repeats a reader's message inside its library's: the line says it once."""
    from psctl.io.images import _clean

    msg = ("Read error: hit end of file in png reader\nPNG read error: IDAT: Read error: hit end of file in png "
           "reader\nPNG library error\nPNG library error\n")
    assert _clean(msg) == "PNG read error: IDAT: Read error: hit end of file in png reader; PNG library error"
    assert _clean(None) == "" and _clean("  one\n  line ") == "one; line"


def test_error_map_draws_the_errors(tmp_path):
    """error.png: jet over 0..45 degrees (above 45 as 45), black outside the mask, grey where NaN
    (no ground truth), the map below the title band, and the colour bar to its right."""
    from psctl.io.report import UNSCORED, jet, write_error_map

    err = np.tile(np.linspace(0, 60, 50, dtype=np.float32), (40, 1))  # 0..60 degrees left to right
    mask = np.ones((40, 50), bool)
    mask[:, :5] = False
    err[30:, 20:30] = np.nan
    write_error_map(tmp_path / "e.png", err, mask, 12.5, 10.0)
    pic, info = read_image(tmp_path / "e.png")
    k = 3  # a map under LABELLED_BAR (96) pixels tall is drawn in whole k x k blocks: 120 x 150 here
    assert info.dtype == "uint8" and pic.shape[1] > 50 * k  # room for the bar
    top = 26  # one title line of 10 * s px (9 s with tails and s of space) and 3 * s px more, at text scale s = 2
    left = 4  # 2 * s: the map's left edge in line with the title's, off the picture's
    assert (pic[top:top + 40 * k, :left] == pic[0, 0]).all()  # the background
    big = pic[top:top + 40 * k, left:left + 50 * k]
    body = big[::k, ::k]
    assert (big[1::k, 1::k] == body).all()  # whole blocks
    scored = mask & ~np.isnan(err)
    np.testing.assert_allclose(body[scored], jet(np.minimum(err[scored], 45) / 45), atol=1 / 255)
    assert (body[~mask] == 0).all() and (np.abs(body[30:, 20:30] - UNSCORED) < 1 / 255).all()
    assert np.abs(body[0, 49] - body[0, 5]).max() > 0.5  # red at 60 degrees, blue at 0
    # the grey is keyed under the map (a swatch, then its words), and only where there is grey
    from psctl.io.report import UNSCORED_KEY

    (y, x), = _text_at(pic, UNSCORED_KEY, 2)
    assert y > top + 40 * k and (np.abs(pic[y:y + 14, 4:18] - UNSCORED) < 1 / 255).all()
    write_error_map(tmp_path / "f.png", np.nan_to_num(err), mask, 12.5, 10.0)
    assert not _text_at(read_image(tmp_path / "f.png")[0], UNSCORED_KEY, 2)


def test_ground_truth_infinity_is_named_as_such(tmp_path):
    """NaN marks a pixel without ground truth (allowed); infinity is refused, by that name."""
    import scipy.io

    truth = write_capture(tmp_path / "o", n=4)
    gt = truth["normals"].astype(np.float64)
    gt[3, 5] = np.nan
    scipy.io.savemat(tmp_path / "o" / "Normal_gt.mat", {"Normal_gt": gt})
    assert load_ground_truth(open_capture(tmp_path / "o"))[3, 5].tolist() == [0.0, 0.0, 0.0]
    gt[16, 17] = [np.inf, 0.0, 1.0]
    scipy.io.savemat(tmp_path / "o" / "Normal_gt.mat", {"Normal_gt": gt})
    with pytest.raises(PsctlError, match=r"infinite values \(first at row 16, column 17\); NaN marks") as e:
        load_ground_truth(open_capture(tmp_path / "o"))
    assert "NaN or" not in str(e.value)


@pytest.mark.parametrize("fmt,name", [("png16", "n.png"), ("png8", "n8.png"), ("exr", "n.exr"), ("npy", "n.npy")])
def test_written_normal_maps_are_zero_outside_the_mask(tmp_path, fmt, name):
    from psctl.io.normals import read_normal_map, write_normal_map

    n = np.zeros((6, 8, 3), np.float32)
    n[..., 2] = 1.0
    m = np.zeros((6, 8), bool)
    m[:, :4] = True
    write_normal_map(tmp_path / name, n, m, fmt)
    back = read_normal_map(tmp_path / name)
    assert (back[~m] == 0).all() and np.allclose(back[m], [0, 0, 1], atol=0.01)


@pytest.mark.parametrize("fmt,name", [("png16", "n.png"), ("exr", "n.exr")])
def test_write_normal_map_checks_what_it_writes(tmp_path, fmt, name):
    """helper-196: non-unit vectors came back turned from a PNG (each channel clipped), a mask of
    0.3 counted as the object, None and a wrong shape raised numpy's errors, NaN became 0 through
    an undefined cast with a warning."""
    import warnings

    from psctl.io.normals import read_normal_map, write_normal_map

    true = np.array([0.314, 0.105, 0.943])
    n = np.tile((3 * true / np.linalg.norm(true)).astype(np.float32), (4, 5, 1))
    n[0, 0] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_normal_map(tmp_path / name, n, None, fmt)  # None: every pixel
    back = read_normal_map(tmp_path / name)
    assert (back[0, 0] == 0).all()  # no direction: no normal
    assert np.degrees(np.arccos(np.clip(back[1:, 1:] @ (true / np.linalg.norm(true)), -1, 1))).max() < 0.1
    write_normal_map(tmp_path / name, n, np.full((4, 5), 0.3), fmt)  # numbers: above 0.5 is the object
    assert not read_normal_map(tmp_path / name).any()
    for mask, needle in ((np.ones((5, 4), bool), r"mask must be \[H, W\] = \[4, 5\]"),
                         ("mask.png", "not the path")):
        with pytest.raises(PsctlError, match=needle):
            write_normal_map(tmp_path / name, n, mask, fmt)
    with pytest.raises(PsctlError, match=r"normals must be \[H, W, 3\], got \[4, 5\]"):
        write_normal_map(tmp_path / name, n[..., 0], None, fmt)
    with pytest.raises(PsctlError, match="read_normal_map"):  # encoded pixels are not normals
        write_normal_map(tmp_path / name, np.full((4, 5, 3), 128, np.uint8), None, fmt)


def test_exr_files_hold_no_write_time(tmp_path):
    """The same pixels give the same bytes: OpenImageIO's EXR writer stamps DateTime unless told not to."""
    import OpenImageIO as oiio

    write_image(tmp_path / "a.exr", np.random.default_rng(0).random((8, 8, 3)).astype(np.float32))
    inp = oiio.ImageInput.open(str(tmp_path / "a.exr"))
    try:
        assert "DateTime" not in [p.name for p in inp.spec().extra_attribs]
    finally:
        inp.close()


def test_no_axis_note_from_a_handful_of_pixels():
    from psctl.api import convention_notes

    rng = np.random.default_rng(1)
    gt = rng.normal(size=(10, 10, 3))
    gt[..., 2] = np.abs(gt[..., 2]) + 0.5
    gt /= np.linalg.norm(gt, axis=-1, keepdims=True)
    est = gt * [1, -1, 1]  # y flipped everywhere
    few = np.zeros((10, 10), bool)
    few[:2, :3] = True
    many = np.ones((10, 10), bool)
    mae = lambda v: float(angular_error(est, gt, v).mean())  # noqa: E731
    assert any("y flipped far better" in n for n in convention_notes(est, gt, many, mae(many), "gt"))
    assert not any("flipped" in n for n in convention_notes(est, gt, few, mae(few), "gt"))


def test_an_image_at_or_below_zero_over_the_object_counts_as_black(tmp_path):
    from psctl.api import run_normals

    arrays = write_capture(tmp_path / "cap", n=8, size=24)
    write_image(tmp_path / "cap" / "003.exr", np.where(arrays["mask"][..., None], -0.1, 0.0), "float")
    (tmp_path / "cap" / "003.png").unlink()
    names = (tmp_path / "cap" / "filenames.txt").read_text().replace("003.png", "003.exr")
    (tmp_path / "cap" / "filenames.txt").write_text(names)
    notes = run_normals(tmp_path / "cap", method="l2", write=False)["notes"]
    assert any(n.startswith("images: 1 of 8 black over the object (003.exr)") for n in notes), notes
    assert any("negative values over the object (003.exr)" in n for n in notes)


def test_small_error_maps_are_drawn_large_enough_to_read(tmp_path):
    from psctl.io.report import LABELLED_BAR, error_heatmap

    for h, w in ((1, 1), (24, 24), (8, 512), (64, 64)):
        pic = error_heatmap(np.full((h, w), 10.0, np.float32), np.ones((h, w), bool), title="MAE 10.00")
        assert pic.shape[0] >= LABELLED_BAR + 12  # the bar (and its labels) at least that tall, under the title
        assert pic.shape[1] <= 4 + 2048 + 88  # a 4 px margin, the map, the bar and its labels at text scale 2
        # the four labels a clear line apart (on a 64 px capture ">45" touched "30": a QA finding)
        # (each label's leftmost match: "0°" is also found inside "30°")
        rows = sorted(min(_text_at(pic, t, 2), key=lambda yx: yx[1])[0] for t in ("0°", "15°", "30°", ">45°"))
        assert all(b - a >= 14 + 7 for a, b in zip(rows, rows[1:])), (h, w, rows)



def _text_at(img: np.ndarray, text: str, s: int = 1) -> list[tuple[int, int]]:
    """Where ``text`` is drawn in ``img`` (white ink, exactly its bitmap): [(row, column), ...]."""
    from psctl.io.report import text_bitmap

    ink = (img >= 1.0).all(-1)
    bm = text_bitmap(text, s)
    h, w = bm.shape
    by, bx = (int(v[0]) for v in np.nonzero(bm))  # the bitmap's first ink pixel: candidates line up on it
    found = []
    for y, x in zip(*np.nonzero(ink)):
        y0, x0 = int(y) - by, int(x) - bx
        if 0 <= y0 <= ink.shape[0] - h and 0 <= x0 <= ink.shape[1] - w and np.array_equal(ink[y0:y0 + h, x0:x0 + w], bm):
            found.append((y0, x0))
    return found


def test_error_map_labels_and_title_are_the_numbers_drawn(tmp_path):
    """The pictures' text (mutation review, session 39: no test read it): the colour bar's labels
    follow vmax, the top one says ">" and sits above "0°", and the titles carry the right numbers."""
    from psctl.io.report import SPREAD_VMAX, error_heatmap, write_error_map, write_spread_map

    err, mask = np.full((60, 60), 5.0, np.float32), np.ones((60, 60), bool)
    img = error_heatmap(err, mask, vmax=12.0)
    top, zero = _text_at(img, ">12°", 2), _text_at(img, "0°", 2)  # text scale 2 at least (legible)
    assert len(top) == 1 and not _text_at(img, ">45°", 2)
    assert zero and top[0][0] < min(y for y, _ in zero)  # high values on top
    assert _text_at(img, "4°", 2) and _text_at(img, "8°", 2)  # the thirds of 12
    write_error_map(tmp_path / "e.png", err, mask, mae=12.5, median=10.0)
    e = read_image(tmp_path / "e.png")[0]
    assert _text_at(e, "MAE 12.50°  MEDIAN 10.00°", 2) == [(4, 4)] and _text_at(e, ">45°", 2)
    # with a label (run_normals': the object and the method) on a line of its own above the numbers
    write_error_map(tmp_path / "e.png", err, mask, mae=12.5, median=10.0, label="cat  ps-fcn-n")
    e = read_image(tmp_path / "e.png")[0]
    assert _text_at(e, "cat  ps-fcn-n", 2) == [(4, 4)] and _text_at(e, "MAE 12.50°  MEDIAN 10.00°", 2) == [(24, 4)]
    # the p's tails (rows 18-21) and the next line (from 24) apart (helper-167: they touched)
    assert (np.abs(e[22:24, 4:300] - e[0, 0]) < 1 / 255).all()
    write_spread_map(tmp_path / "s.png", err, mask, mean=1.25, p90=3.5, label="cat  ensemble")
    sp = read_image(tmp_path / "s.png")[0]
    assert _text_at(sp, "SPREAD MEAN 1.25°  P90 3.50°", 2) == [(24, 4)] and _text_at(sp, "cat  ensemble", 2)
    assert _text_at(sp, f">{SPREAD_VMAX:.0f}°", 2) and not _text_at(sp, ">45°", 2)
    from psctl.api import run_normals

    write_capture(tmp_path / "ballPNG", n=6, size=24)
    r = run_normals(tmp_path / "ballPNG", method="l2", out=tmp_path / "o")
    assert _text_at(read_image(r["outputs"]["error"])[0], "ball  l2", 2) == [(4, 4)]  # DiLiGenT's PNG suffix dropped, as in the report


def test_a_0_1_mask_file_says_so(tmp_path):
    """numpy's astype(uint8) of a bool mask stores 0 and 1 (out of 255): empty by the 0.5 rule,
    and the message says why instead of only 'no foreground pixel'."""
    data = write_capture(tmp_path / "cap", n=4, size=16)
    write_image(tmp_path / "cap" / "mask.png", data["mask"].astype(np.float32) / 255, "uint8")
    with pytest.raises(PsctlError, match=r"mask.png: mask is empty.*brightest is 1 of 255; a 0/1 mask\? save the "
                                         r"object as 255 \(0/255\)"):
        load_mask(open_capture(tmp_path / "cap"))
    # a 16-bit file holding 0/255 (a QA helper's finding: the hint said 'save it as 0/255')
    write_image(tmp_path / "cap" / "mask.png", data["mask"].astype(np.float32) * 255 / 65535, "uint16")
    with pytest.raises(PsctlError, match=r"brightest is 255 of 65535; save the object as 65535 \(or the mask as "
                                         r"8-bit 0/255\)\)$"):
        load_mask(open_capture(tmp_path / "cap"))
    write_image(tmp_path / "cap" / "mask.exr", data["mask"].astype(np.float32) * 0.25, "float")
    (tmp_path / "cap" / "mask.png").unlink()
    with pytest.raises(PsctlError, match=r"mask.exr: .*brightest is 0.25; save the object as 1.0\)$"):
        load_mask(open_capture(tmp_path / "cap"))
    (tmp_path / "cap" / "mask.exr").unlink()
    write_image(tmp_path / "cap" / "mask.png", np.zeros((16, 16)), "uint8")
    with pytest.raises(PsctlError, match=r"mask is empty \(no foreground pixel\)"):
        load_mask(open_capture(tmp_path / "cap"))
    rgba = np.ones((16, 16, 4))
    rgba[..., 3] = 0
    rgba[0, 0] = (0, 0, 0, 1)  # white and transparent but one opaque black pixel: a cut-out with nothing cut
    write_image(tmp_path / "cap" / "mask.png", rgba, "uint8")
    with pytest.raises(PsctlError, match=r"mask is empty \(no foreground pixel: no white pixel is opaque"):
        load_mask(open_capture(tmp_path / "cap"))


def test_images_in_a_subfolder_of_a_capture(tmp_path):
    """The light file, mask and ground truth at the top and the images in images/: not a benchmark
    root of one object (whose advice would drop the calibration) but a refusal saying how to list
    them; listed as images/NAME they are read with the top's files. info notes the unread files."""
    from psctl.io.summary import describe

    cap = tmp_path / "cap"
    write_capture(cap, n=4, size=16)
    names = (cap / "filenames.txt").read_text().split()
    (cap / "filenames.txt").unlink()
    (cap / "images").mkdir()
    for n in names:
        (cap / n).rename(cap / "images" / n)
    with pytest.raises(PsctlError, match=r"holds light_directions.txt, light_intensities.txt, mask.png, "
                                         r"Normal_gt.mat but no image; its images seem to be in images/.*filenames.txt "
                                         r"as images/NAME"):
        open_capture(cap)
    notes = describe(cap)["notes"]
    assert any("light_directions.txt" in n and "not read" in n and "as images/NAME" in n for n in notes), notes
    # an object folder with files of its own beside the root's: an ordinary one-object root
    import shutil

    shutil.copytree(cap, tmp_path / "root" / "catPNG", ignore=shutil.ignore_patterns("images"))
    for n in names:
        shutil.copy(cap / "images" / n, tmp_path / "root" / "catPNG" / n)
    shutil.copy(cap / "light_directions.txt", tmp_path / "root")
    with pytest.raises(PsctlError, match=r"is a benchmark root with one object folder, not a capture: pass .*catPNG"):
        open_capture(tmp_path / "root")
    shutil.copytree(tmp_path / "root" / "catPNG", tmp_path / "root" / "dogPNG")
    notes = describe(tmp_path / "root")["notes"]
    assert any("light_directions.txt in the root itself not read" in n and "copy a shared file into each" in n
               for n in notes), notes
    (cap / "filenames.txt").write_text("\n".join(f"images/{n}" for n in names) + "\n")
    c = open_capture(cap)
    assert c.n_images == 4 and c.calibrated and c.mask_path is not None and c.gt_path is not None


def test_a_truncated_write_is_caught_before_the_rename(tmp_path):
    """OpenImageIO's EXR writer can report success for a file cut short by a full disk: the
    read-back check refuses it, naming the output."""
    from psctl.io.images import _check_written

    write_image(tmp_path / "a.exr", np.random.default_rng(0).random((32, 32, 3)), "float")
    _check_written(tmp_path / "a.exr", tmp_path / "out.exr", (32, 32, 3))  # whole: silent
    data = (tmp_path / "a.exr").read_bytes()
    (tmp_path / "a.exr").write_bytes(data[: len(data) // 2])
    with pytest.raises(PsctlError, match=r"out.exr: written incompletely \(\d+ bytes; a full disk or a quota\?\)"):
        _check_written(tmp_path / "a.exr", tmp_path / "out.exr", (32, 32, 3))


def test_atomic_path_names_the_output_when_a_write_fails(tmp_path):
    """An OSError from writing the temporary file (no name, or the temporary name) becomes one
    PsctlError naming the final file, and nothing is left; one about another path passes as is."""
    import errno

    from psctl.io.atomic import atomic_path

    for name in (None, "tmp"):
        with pytest.raises(PsctlError, match=r"mesh.ply: cannot write \(no space left on device\)"):
            with atomic_path(tmp_path / "mesh.ply") as tmp:
                tmp.write_bytes(b"ply")
                raise OSError(errno.ENOSPC, "No space left on device", None if name is None else str(tmp))
        assert os.listdir(tmp_path) == []
    with pytest.raises(FileNotFoundError):
        with atomic_path(tmp_path / "mesh.ply"):
            raise FileNotFoundError(errno.ENOENT, "No such file or directory", str(tmp_path / "input.png"))
    assert os.listdir(tmp_path) == []


def test_a_full_disk_while_staging_names_the_output_folder(tmp_path):
    """A full disk that the system reports without a file name (pathlib's write_text finding the
    write short at close: psctl normals' list of outputs on a 64 kB tmpfs, an audit) names the
    output folder, for one run's staging and for psctl eval's batch; nothing is left; another
    error passes as is."""
    import errno

    from psctl.io.atomic import OutputBatch, staged_outputs

    full = OSError(errno.ENOSPC, "No space left on device")
    with pytest.raises(PsctlError, match=r"^.*o: cannot write the outputs \(no space left on device\); nothing was"):
        with staged_outputs(tmp_path / "o") as stage:
            (stage / "normal.png").write_bytes(b"x")
            raise full
    assert os.listdir(tmp_path) == []
    with pytest.raises(PsctlError, match=r"e: cannot write the outputs \(no space left on device\)"):
        with OutputBatch(tmp_path / "e") as batch:
            (batch.stage(tmp_path / "e" / "ball").path / "normal.png").write_bytes(b"x")
            raise full
    assert os.listdir(tmp_path) == []
    with pytest.raises(OSError, match="Input/output error"):
        with staged_outputs(tmp_path / "o"):
            raise OSError(errno.EIO, "Input/output error")
    assert os.listdir(tmp_path) == []


def test_a_pickled_npy_normal_map_is_refused_without_numpys_advice(tmp_path):
    """np.load's own message suggests allow_pickle=True (running code from the file): ours names
    the file and what it is instead."""
    np.save(tmp_path / "n.npy", np.array([{"normals": 1}], dtype=object))
    with pytest.raises(PsctlError, match=r"n.npy: cannot read .npy \(not a plain NumPy array file\)") as e:
        read_normal_map(tmp_path / "n.npy")
    assert "allow_pickle" not in str(e.value)


def test_a_run_notes_an_image_on_another_scale(tmp_path):
    """A float TIFF of 0..65535 values among 0..1 images (an audit: 72 degrees off, under the
    mixed-sample-types note alone): an image over BRIGHT_OUTLIER times the median image's
    brightness over the object is named, by l2 and the network engine alike; none otherwise."""
    from psctl.api import run_normals
    from psctl.io.capture import BRIGHT_OUTLIER

    d = write_capture(tmp_path / "c", n=8, size=32)
    assert not any("times as bright" in n for n in run_normals(tmp_path / "c", method="l2", write=False)["notes"])
    names = (tmp_path / "c" / "filenames.txt").read_text()
    for k in (2, 5):
        (tmp_path / "c" / f"{k + 1:03d}.png").unlink()
        write_image(tmp_path / "c" / f"{k + 1:03d}.tif", d["images"][k] * (65535 if k == 2 else 100), "float")
        names = names.replace(f"{k + 1:03d}.png", f"{k + 1:03d}.tif")
        (tmp_path / "c" / "filenames.txt").write_text(names)
        for method in ("l2", "ps-fcn"):
            r = run_normals(tmp_path / "c", method=method, write=False, device="cpu")
            said = [n for n in r["notes"] if "times as bright" in n]
            assert len(said) == 1 and f"over {BRIGHT_OUTLIER} times as bright over the object" in said[0], said
            assert ("1 of 8 is over" in said[0] and "(003.tif, " in said[0]) if k == 2 else \
                ("2 of 8 are over" in said[0] and "(003.tif, 006.tif; the brightest, 003.tif," in said[0]), said
    # psctl info --check judges them after their intensities, as psctl normals does (a review: it
    # named an image whose listed intensity explained it)
    from psctl.io.capture import load_mask
    from psctl.io.summary import check_pixels

    e = np.ones((8, 3))
    e[2], e[5] = 65535 * d["intensities"][2], 100 * d["intensities"][5]
    for listed, said in ((d["intensities"], True), (e, False)):
        np.savetxt(tmp_path / "c" / "light_intensities.txt", listed)
        cap = open_capture(tmp_path / "c")
        assert any("times as bright" in n for n in check_pixels(cap, load_mask(cap))["notes"]) == said


def test_a_run_notes_an_image_far_darker_than_the_rest(tmp_path):
    """8-bit codes saved in a 16-bit file among 16-bit images read 257 times darker, as a light
    that barely fired or a wrong intensity do (helper-163: no note, where the mixed-type one
    needs another sample type): an image over DARK_OUTLIER times darker than the median image
    over the object is named, by l2 and the network engine alike; a black one keeps its own
    note; psctl info --check names an image once where the mixed-type note names it."""
    from psctl.api import run_normals
    from psctl.io.capture import DARK_OUTLIER, load_mask
    from psctl.io.summary import check_pixels

    d = write_capture(tmp_path / "c", n=8, size=32)
    assert not any("darker" in n for n in run_normals(tmp_path / "c", method="l2", write=False)["notes"])
    write_image(tmp_path / "c" / "004.png", d["images"][3] / 257, "uint16", kind="linear")
    write_image(tmp_path / "c" / "007.png", d["images"][6] * 0, "uint16", kind="linear")
    for method in ("l2", "ps-fcn"):
        notes = run_normals(tmp_path / "c", method=method, write=False, device="cpu")["notes"]
        said = [n for n in notes if "darker" in n]
        assert len(said) == 1 and said[0].startswith(f"images: 1 of 8 is over {DARK_OUTLIER} times darker over the "
                                                     f"object than the median image (004.png, 2"), said
        assert any("black over the object (007.png)" in n for n in notes), notes
    cap = open_capture(tmp_path / "c")
    assert [n for n in check_pixels(cap, load_mask(cap))["notes"] if "darker" in n] == said
    # its intensity listed as 1/257: as the others
    e = np.loadtxt(tmp_path / "c" / "light_intensities.txt")
    e[3] /= 257
    np.savetxt(tmp_path / "c" / "light_intensities.txt", e)
    assert not any("darker" in n for n in run_normals(tmp_path / "c", method="l2", write=False)["notes"])
    # the others 8-bit: the mixed-type note names 004.png, the dark one does not again
    for k in (0, 1, 2, 4, 5, 7):
        write_image(tmp_path / "c" / f"{k + 1:03d}.png", d["images"][k], "uint8", kind="linear")
    np.savetxt(tmp_path / "c" / "light_intensities.txt", d["intensities"])
    cap = open_capture(tmp_path / "c")
    said = [n for n in check_pixels(cap, load_mask(cap))["notes"] if "darker" in n]
    assert len(said) == 1 and said[0].startswith("images: the 16-bit ones (004.png, 007.png) are "), said


def test_loose_images_beside_capture_folders_are_noted_both_ways(tmp_path):
    """A folder of images beside capture subfolders is one capture to psctl normals and info and a
    benchmark root to psctl eval (helper-163): each says what it left out. A list's imgs/ folder
    is part of the capture, not another one."""
    import shutil

    from psctl.io.capture import capture_notes, root_notes

    root = tmp_path / "r"
    write_capture(root / "a", n=4, size=24)
    write_capture(root / "b", n=4, size=24)
    for k in range(1, 5):
        shutil.copy(root / "a" / f"{k:03d}.png", root / f"{k:03d}.png")
    cap = open_capture(root)
    assert cap.sub_captures == ("a", "b") and cap.n_images == 4
    said = [n for n in capture_notes(cap) if "capture folders" in n]
    assert said == ["files: a, b inside are capture folders of their own, not read with it: psctl reads the 4 images "
                    "of r as this capture (psctl eval --benchmark folder --root on this folder reads the subfolders "
                    "as objects instead)"], said
    assert root_notes(root) == ["objects: 4 images in the root itself (001.png, ...) not read: the objects are its "
                                "capture subfolders (psctl normals on this folder reads these images as one capture "
                                "instead)"]
    # images listed from a subfolder: that folder is this capture's, not another one
    one = tmp_path / "one"
    write_capture(one / "imgs", n=4, size=24)
    (one / "imgs" / "light_directions.txt").rename(one / "light_directions.txt")
    (one / "filenames.txt").write_text("".join(f"imgs/{k:03d}.png\n" for k in range(1, 5)))
    assert open_capture(one).sub_captures == () and not any("capture folder" in n for n in
                                                            capture_notes(open_capture(one)))
    # the images links into raw/: raw is this capture's too (helper-167)
    linked = tmp_path / "linked"
    write_capture(linked / "raw", n=4, size=24)
    for k in range(1, 5):
        (linked / f"{k:03d}.png").symlink_to(f"raw/{k:03d}.png")
    (linked / "raw" / "light_directions.txt").rename(linked / "light_directions.txt")
    assert open_capture(linked).n_images == 4 and open_capture(linked).sub_captures == ()
    one_image = tmp_path / "one_image"  # "the 1 image", not "the 1 images" (helper-168)
    write_capture(one_image / "sub", n=4, size=24)
    shutil.copy(one_image / "sub" / "001.png", one_image / "001.png")
    assert any("psctl reads the 1 image of one_image as this capture" in n
               for n in capture_notes(open_capture(one_image)))


def _read_in_two_tiles(c, mask):
    """An ImageCheck fed as the network engine feeds it: a 24 x 24 capture read in two tiles, then
    a second pass over the first from image 2 on."""
    from psctl.io.capture import ImageCheck

    check = ImageCheck(c)
    read = check.reader(c, mask)
    box = (slice(0, 24), slice(0, 12))
    for part in (box, (slice(0, 24), slice(12, 24))):
        list(read(0, part))
    list(read(2, box))
    return check


def test_a_run_notes_heavily_saturated_images(tmp_path):
    """Images with over 10 % of the object at the top code value get a run note (l2 and the
    network engine's reader, through any number of passes); an unsaturated capture none."""
    from psctl.api import run_normals
    from psctl.io.capture import CLIPPED_NOTE

    cap = tmp_path / "cap"
    write_capture(cap, n=8, size=24)
    assert not any("saturated" in n for n in run_normals(cap, method="l2", write=False)["notes"])
    names = sorted(p.name for p in cap.glob("0*.png"))
    for name in names[:3]:  # three images 4x over: most of the lit object clips
        write_image(cap / name, np.clip(read_image(cap / name)[0] * 4, 0, 1), "uint16")
    notes = [n for n in run_normals(cap, method="l2", write=False)["notes"] if "saturated" in n]
    assert len(notes) == 1 and notes[0].startswith("images: 3 of 8 have over 10% of the object saturated"), notes
    c = open_capture(cap)
    mask = load_mask(c)
    check = _read_in_two_tiles(c, mask)
    share = {k: a / b for k, (a, b) in check.clipped.items()}
    assert sorted(k for k, v in share.items() if v > CLIPPED_NOTE) == [0, 1, 2] and share[3] == 0
    assert [n for n in check.notes() if "saturated" in n] == notes


def test_a_run_notes_images_clipped_below_the_top_code(tmp_path):
    """Over 10 % of the object at the image's own largest value, below the top code (12-bit codes
    in a 16-bit file clipped at 4095) or in a float file (clipped at 0.8), gets a note: l2, the
    network engine's reader in tiles and passes, and info --check alike; unclipped 12-bit codes,
    a dim image of a few codes (no values just below its largest) and the top-code case none."""
    from psctl.api import run_normals
    from psctl.io.capture import CLIPPED_NOTE, ImageCheck
    from psctl.io.summary import check_pixels

    def note(folder):
        return [n for n in run_normals(folder, method="l2", write=False)["notes"] if "largest value" in n]

    cap = tmp_path / "cap"
    write_capture(cap, n=8, size=24)
    names = sorted(p.name for p in cap.glob("0*.png"))
    raw = {name: read_image(cap / name)[0] for name in names}
    top = 4095 / 65535
    for name in names:  # a 12-bit camera's codes, saved as they are: nothing clipped
        write_image(cap / name, np.round(raw[name] * 4095) / 65535, "uint16")
    assert note(cap) == []
    for name in names[:3]:  # three images 4x over: clipped at code 4095
        write_image(cap / name, np.minimum(np.round(raw[name] * 4 * 4095) / 65535, top), "uint16")
    notes = note(cap)
    assert len(notes) == 1 and notes[0].startswith("images: 3 of 8 have over 10% of the object at their largest "
                                                   "value, below the top code (most: "), notes
    assert "at code 4095 of 65535" in notes[0]
    c = open_capture(cap)
    mask = load_mask(c)
    check = _read_in_two_tiles(c, mask)
    share = {k: at / n for k, (_, at, n, _) in check.ceiling.items()}
    assert sorted(k for k, v in share.items() if v > CLIPPED_NOTE) == [0, 1, 2] and share[3] < 0.01
    assert [n for n in check.notes() if "largest value" in n] == notes
    assert [n for n in check_pixels(c, mask)["notes"] if "largest value" in n] == notes
    inside = np.ones((4, 4), bool)  # boxes merged in either order: a lower largest value's pixels do not count
    flat, peak = np.full((4, 4, 3), 0.5, np.float32), np.linspace(0.1, 0.6, 48, dtype=np.float32).reshape(4, 4, 3)
    for order in ((flat, peak), (peak, flat)):
        merged = ImageCheck(c)
        for part in order:
            merged.see_ceiling(0, part, inside)
        assert merged.ceiling[0][:3] == [float(np.float32(0.6)), 1, 32]
    for name in names[:3]:  # at the top code: the saturation note's, not this one
        write_image(cap / name, np.clip(raw[name] * 4, 0, 1), "uint16")
    assert note(cap) == []
    for name in names:  # dim: a 16-bit file of codes up to 4, a fifth of the object at the largest
        write_image(cap / name, np.round(raw[name] / raw[name].max() * 4) / 65535, "uint16")
    assert note(cap) == []
    flt = tmp_path / "flt"  # a float EXR capture, one image clipped at 0.8
    write_capture(flt, n=8, size=24)
    for k, name in enumerate(names):
        img = raw[name] * 3 if k == 5 else raw[name]
        write_image(flt / name.replace(".png", ".exr"), np.minimum(img, 0.8) if k == 5 else img, "float")
        (flt / name).unlink()
    (flt / "filenames.txt").write_text("".join(n.replace(".png", ".exr") + "\n" for n in names))
    notes = note(flt)
    assert len(notes) == 1 and notes[0].startswith(f"images: 1 of 8 has over 10% of the object at its largest "
                                                   f"value ({names[5].replace('.png', '.exr')}: "), notes
    assert "% at 0.8)" in notes[0]


def test_two_images_without_lights_get_the_undetermined_note(tmp_path):
    """ups-fcn (and sdps) on fewer than 3 images: the same 'undetermined' note as a network given
    2 listed lights; 3 images none."""
    from psctl.api import run_normals
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    save_weights(tmp_path / "u.pt", PSFCN({"lights": False}), {"method": "ups-fcn", "train_images": 32})
    for n, noted in ((2, True), (3, False)):
        write_capture(tmp_path / f"c{n}", n=n, size=16)
        r = run_normals(tmp_path / f"c{n}", method="ups-fcn", weights=tmp_path / "u.pt", write=False, device="cpu")
        assert any(x.startswith(f"images: only {n}, which leaves the normals undetermined; ups-fcn")
                   for x in r["notes"]) == noted, r["notes"]
    # the array API has no report: the same note comes as a PsctlWarning, from the caller's line
    import warnings

    from psctl import estimate_normals
    from psctl.errors import PsctlWarning

    imgs = np.random.default_rng(0).uniform(0.1, 0.9, (3, 16, 16, 3)).astype(np.float32)
    with pytest.warns(PsctlWarning, match="^images: only 2, which leaves the normals undetermined; ups-fcn") as got:
        estimate_normals(imgs[:2], None, np.ones((16, 16), bool), method="ups-fcn", weights=tmp_path / "u.pt",
                         device="cpu")
    assert len(got) == 1 and got[0].filename == __file__
    with warnings.catch_warnings():
        warnings.simplefilter("error", PsctlWarning)  # (a mask: mask=None is a warning of its own)
        estimate_normals(imgs, None, np.ones((16, 16), bool), method="ups-fcn", weights=tmp_path / "u.pt",
                         device="cpu")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a file size limit (RLIMIT_FSIZE) stands in for a full disk")
@pytest.mark.parametrize("name", ["n.png", "n.exr", "n.tif"])
def test_write_image_on_a_full_disk_leaves_nothing(tmp_path, name):
    """A write cut short by a full disk (here a file size limit) raises, naming the file, and
    leaves no file: OpenImageIO's PNG writer returns success for it (only the read-back sees it)."""
    import subprocess

    code = f"""
import resource, signal, sys
import numpy as np
from psctl.io.images import write_image
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (8192, 8192))
try:
    write_image({str(tmp_path / name)!r}, np.random.default_rng(0).random((300, 300, 3)), {"float" if name.endswith("exr") else "uint16"!r})
except Exception as e:
    print(type(e).__name__, e)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout
    assert out.startswith(f"PsctlError {tmp_path / name}: ") and ("written incompletely" in out or "cannot write" in out), out
    assert os.listdir(tmp_path) == []


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a file size limit (RLIMIT_FSIZE) stands in for a full disk")
def test_save_weights_on_a_full_disk_is_one_error_naming_the_file(tmp_path):
    """torch.save's own writer fails on a full disk with a RuntimeError naming nothing; psctl
    writes through memory, so the OSError names the weights file (and nothing is left)."""
    import subprocess

    code = f"""
import resource, signal
from psctl.models.ps_fcn import PSFCN
from psctl.models.weights import save_weights
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (100000, 100000))
try:
    save_weights({str(tmp_path / "w.pt")!r}, PSFCN(), {{"method": "ps-fcn", "train_images": 32}})
except Exception as e:
    print(type(e).__name__, e)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout
    assert out.startswith(f"PsctlError {tmp_path / 'w.pt'}: cannot write (file too large"), out
    assert os.listdir(tmp_path) == []


def test_a_folder_given_as_a_normal_map_says_so(tmp_path):
    with pytest.raises(PsctlError, match="is a folder, not a normal map file"):
        read_normal_map(tmp_path)
    with pytest.raises(PsctlError, match="normal map file is missing"):
        read_normal_map(tmp_path / "n.exr")


def test_run_normals_refuses_a_batch_that_is_not_one(tmp_path):
    from psctl.api import run_normals

    write_capture(tmp_path / "cap", n=4, size=16)
    with pytest.raises(PsctlError, match="batch must be a psctl.io.atomic.OutputBatch or None, not int"):
        run_normals(tmp_path / "cap", method="l2", batch=5)
    assert not (tmp_path / "cap" / "psctl").exists()


def test_a_truncated_png_is_one_line_without_libpngs_own(tmp_path):
    """libpng prints its own line for a broken PNG on file descriptor 2, beside the error
    OpenImageIO reports; psctl keeps it off stderr: exactly one line, naming the file. (Reading
    the images on two threads was tried in session 45 and reverted: sharing fd 2's silencing
    between threads lost or misplaced other output; docs/performance.md.)"""
    import subprocess

    write_capture(tmp_path / "cap", n=8, size=64)
    bad = sorted((tmp_path / "cap").glob("*.png"))[3]
    bad.write_bytes(bad.read_bytes()[:300])
    proc = subprocess.run([sys.executable, "-m", "psctl.cli", "normals", str(tmp_path / "cap"), "-m", "l2", "-q",
                           "-o", str(tmp_path / "o")], capture_output=True, text=True)
    assert proc.returncode == 2 and "libpng" not in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and bad.name in proc.stderr
    assert not (tmp_path / "o").exists()


def test_stderr_is_silenced_for_the_command_line_only_and_put_back_across_threads(tmp_path, monkeypatch):
    """An audit embedding psctl in a service: two threads reading images each saved fd 2 and put
    it back, so one could save the other's /dev/null and leave the process's stderr there for
    good; and a library caller's other threads lost their stderr while any image was read. Now
    only the command line silences fd 2 (psctl.errors.C_STDERR), through one shared redirection."""
    import threading

    from psctl.errors import C_STDERR

    write_image(tmp_path / "a.png", np.random.default_rng(0).random((32, 32, 3), np.float32), "uint16")
    calls = []
    real_dup2 = os.dup2
    monkeypatch.setattr(os, "dup2", lambda a, b, *k: (calls.append(b), real_dup2(a, b, *k))[1])
    read_image(tmp_path / "a.png")
    assert calls == []  # a library call leaves fd 2 alone
    monkeypatch.setattr(os, "dup2", real_dup2)
    monkeypatch.setitem(C_STDERR, "silence", True)
    monkeypatch.setattr(sys, "stderr", sys.__stderr__)  # pytest's stand-in has no file descriptor
    before = os.fstat(2)

    def reads():
        for _ in range(300):
            read_image(tmp_path / "a.png")

    threads = [threading.Thread(target=reads) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    after = os.fstat(2)
    assert (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino)  # not /dev/null
    if hasattr(os, "fork"):  # a child forked while a reader holds fd 2 silenced gets it back
        from psctl.io.images import _QUIET, _quiet_stderr

        with _quiet_stderr():
            pid = os.fork()
            if pid == 0:
                st = os.fstat(2)
                os._exit(0 if (st.st_dev, st.st_ino) == (before.st_dev, before.st_ino) and _QUIET["depth"] == 0 else 1)
        assert os.waitpid(pid, 0)[1] == 0
        assert _QUIET["depth"] == 0 and (os.fstat(2).st_dev, os.fstat(2).st_ino) == (before.st_dev, before.st_ino)


def test_the_umask_is_read_without_being_changed(monkeypatch):
    """Output files get 0666 & ~umask. Reading the umask by setting it to 0 and back left a moment
    in which another thread's new files were open to everyone (an audit made 6 in 40 s); on
    Linux it is read from /proc and never set."""
    from psctl.io.atomic import current_umask

    old = os.umask(0o027)
    try:
        if os.path.exists("/proc/self/status"):
            calls = []
            real = os.umask
            monkeypatch.setattr(os, "umask", lambda m: (calls.append(m), real(m))[1])
            assert current_umask() == 0o027 and calls == []
            monkeypatch.setattr(os, "umask", real)
        monkeypatch.setattr("builtins.open", lambda *a, **k: (_ for _ in ()).throw(OSError("no /proc")))
        assert current_umask() == 0o027  # elsewhere: set and put back
        assert os.umask(0o027) == 0o027
    finally:
        os.umask(old)


def test_output_files_get_the_usual_mode(tmp_path):
    """Files are written under a temporary name (mkstemp: mode 0600) and renamed: they get 0666 &
    ~umask, as any program's new file, so that others on a shared machine can read the results."""
    from psctl.io.atomic import write_bytes_atomic, write_text_atomic
    from psctl.io.normals import write_npy
    from psctl.io.report import write_json

    old = os.umask(0o022)
    try:
        write_image(tmp_path / "a.png", np.zeros((4, 4, 3), np.float32), "uint16")
        write_image(tmp_path / "a.exr", np.zeros((4, 4, 3), np.float32), "float")
        write_npy(tmp_path / "a.npy", np.zeros((4, 4, 3), np.float32))
        write_text_atomic(tmp_path / "a.txt", "x\n")
        write_bytes_atomic(tmp_path / "a.bin", b"x")
        write_json(tmp_path / "a.json", {"x": 1})
        os.umask(0o077)
        write_text_atomic(tmp_path / "private.txt", "x\n")
    finally:
        os.umask(old)
    modes = {p.name: p.stat().st_mode & 0o777 for p in tmp_path.iterdir()}
    assert modes == {"a.png": 0o644, "a.exr": 0o644, "a.npy": 0o644, "a.txt": 0o644, "a.bin": 0o644,
                     "a.json": 0o644, "private.txt": 0o600}


def test_normal_maps_keep_axis_normals_and_their_bit_depths(tmp_path):
    """A unit normal with a component at -1 is stored as 0 in that channel (an image's (n + 1) / 2):
    only a pixel that is 0 in every channel means "no normal". And each encoding has the bit
    depth its name says (a mutation audit: either slip went unnoticed)."""
    from psctl.io.images import image_info
    from psctl.io.normals import ALBEDO_FORMATS, FORMATS, write_albedo_map

    axes = np.array([(-1, 0, 0), (0, -1, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (0.6, 0, -0.8)], np.float32)
    nmap = np.zeros((2, 4, 3), np.float32)
    nmap.reshape(-1, 3)[:6] = axes
    mask = np.zeros((2, 4), bool)
    mask.reshape(-1)[:6] = True
    bits = {"png16": 16, "png8": 8, "exr": 32}
    for fmt in FORMATS:
        write_normal_map(tmp_path / FORMATS[fmt], nmap, mask, fmt)
        back = read_normal_map(tmp_path / FORMATS[fmt])
        assert np.isfinite(back[mask]).all() and (back[~mask] == 0).all(), fmt
        assert angular_error(back[mask], axes).max() < 0.5, fmt
        if fmt in bits:
            assert image_info(tmp_path / FORMATS[fmt]).bits == bits[fmt], fmt
    for fmt in ("png16", "png8"):
        write_albedo_map(tmp_path / ALBEDO_FORMATS[fmt], np.full((2, 4, 3), 0.3, np.float32), mask, fmt, 1.0)
        assert image_info(tmp_path / ALBEDO_FORMATS[fmt]).bits == bits[fmt], fmt


def test_a_signal_while_outputs_move_into_place_waits_for_the_clean_up(tmp_path, monkeypatch):
    """SIGTERM in the clean-up after the move left the staging folder behind beside complete
    outputs (a hostile-input audit): the move and the clean-up now hold the signal, and its
    handler runs once they are done."""
    import signal

    from psctl.io.atomic import Staging, staged_outputs

    class Term(Exception):
        pass

    def on_term(signum, frame):
        raise Term

    old = signal.signal(signal.SIGTERM, on_term)
    real = Staging.discard

    def discard(self, remove_created=True):
        os.kill(os.getpid(), signal.SIGTERM)  # arrives in the middle of the clean-up
        real(self, remove_created)

    monkeypatch.setattr(Staging, "discard", discard)
    try:
        with pytest.raises(Term):
            with staged_outputs(tmp_path / "out") as stage:
                (stage / "a.txt").write_text("new")
        assert sorted(os.listdir(tmp_path / "out")) == ["a.txt"]  # in place, nothing staged left
        assert signal.getsignal(signal.SIGTERM) is on_term  # the caller's handler, back
    finally:
        signal.signal(signal.SIGTERM, old)


def test_messages_for_odd_files_say_what_they_are(tmp_path):
    """A device or FIFO named as a file was 'missing' or 'not found'; Normal_gt.mat listed as an
    image failed in the image reader; a MATLAB 7.3 file passed on scipy's advice to use h5py
    (a hostile-input audit): each now says what is wrong with it."""
    from psctl.api import run_normals
    from psctl.io.normals import read_normal_map
    from psctl.models.weights import read_weights

    os.mkfifo(tmp_path / "fifo")
    for read, missing in ((read_weights, "weights file not found"), (read_normal_map, "normal map file is missing")):
        with pytest.raises(PsctlError, match="/dev/zero: is a device, not a regular file$"):
            read("/dev/zero")
        with pytest.raises(PsctlError, match="fifo: is a FIFO, not a regular file$"):
            read(tmp_path / "fifo")
        with pytest.raises(PsctlError, match=f"nope: {missing}$"):
            read(tmp_path / "nope")
    write_capture(tmp_path / "c", n=6, size=32)
    names = (tmp_path / "c" / "filenames.txt").read_text().split()
    (tmp_path / "c" / "filenames.txt").write_text("\n".join([*names[:5], "Normal_gt.mat"]) + "\n")
    with pytest.raises(PsctlError, match="Normal_gt.mat: is the ground truth's file name but is listed in "
                                         "filenames.txt as an input image"):
        run_normals(tmp_path / "c", method="l2", write=False)
    (tmp_path / "c" / "filenames.txt").write_text("\n".join(names) + "\n")
    header = b"MATLAB 7.3 MAT-file".ljust(116, b" ") + bytes(8) + b"\x00\x02IM"  # version 0x0200: HDF5
    (tmp_path / "c" / "Normal_gt.mat").write_bytes(header + bytes(512))
    with pytest.raises(PsctlError, match=r"is a MATLAB 7.3 \(HDF5\) file, which psctl does not read: save it with "
                                         r"save\(\.\.\., '-v7'\)"):
        run_normals(tmp_path / "c", method="l2", write=False)


def test_an_encoded_normal_map_saved_as_normal_gt_mat_is_refused(tmp_path):
    """uint8 codes ((n + 1) / 2 * 255) saved in Normal_gt.mat were scored as directions, all in one
    octant (41.9 degrees on a sphere, a hostile-input audit); whole numbers -1, 0 and 1 (how
    MATLAB may store a double array of them) are still normals."""
    import scipy.io

    from psctl.io.capture import load_ground_truth

    arrays = write_capture(tmp_path / "c", n=4, size=24)
    codes = np.round((arrays["normals"] + 1) / 2 * 255).astype(np.uint8)
    scipy.io.savemat(tmp_path / "c" / "Normal_gt.mat", {"Normal_gt": codes})
    with pytest.raises(PsctlError, match=r"Normal_gt holds whole numbers \d+ \.\. 255 \(uint8\): an encoded image's"):
        load_ground_truth(open_capture(tmp_path / "c"))
    flat = np.zeros((24, 24, 3), np.int8)
    flat[..., 2] = 1
    scipy.io.savemat(tmp_path / "c" / "Normal_gt.mat", {"Normal_gt": flat})
    np.testing.assert_array_equal(load_ground_truth(open_capture(tmp_path / "c"))[..., 2], 1)


def test_info_reads_normal_gt_mat_whole_and_notes_what_normals_refuses(tmp_path):
    """psctl info (headers only) passed an HDF5 Normal_gt.mat and one of uint8 codes that psctl
    normals refuses (a QA helper, session 61; the README says the .mat is read whole to check
    it). They are notes (lights and depth read no ground truth); --check stops on them."""
    import scipy.io

    from psctl.io.summary import describe_capture

    arrays = write_capture(tmp_path / "c", n=4, size=24)
    assert describe_capture(tmp_path / "c")["notes"] == []  # a good ground truth: no note
    codes = np.round((arrays["normals"] + 1) / 2 * 255).astype(np.uint8)
    scipy.io.savemat(tmp_path / "c" / "Normal_gt.mat", {"Normal_gt": codes})
    notes = describe_capture(tmp_path / "c")["notes"]
    assert len(notes) == 1 and notes[0].startswith("Normal_gt.mat: Normal_gt holds whole numbers") and \
        notes[0].endswith("(psctl normals and eval stop on it)"), notes
    with pytest.raises(PsctlError, match="Normal_gt holds whole numbers"):
        describe_capture(tmp_path / "c", check=True)
    (tmp_path / "c" / "Normal_gt.mat").write_bytes(b"MATLAB 7.3 MAT-file".ljust(116) + bytes(8) + b"\x00\x02IM" +
                                                   bytes(512))
    assert any("MATLAB 7.3 (HDF5) file" in n for n in describe_capture(tmp_path / "c")["notes"])


def test_held_signals_skip_ignored_ones_and_reach_the_handler(tmp_path):
    """With SIGHUP ignored (nohup), a SIGHUP then a SIGTERM while outputs move into place: the
    SIGTERM still reaches its handler (a review: the ignored one was taken as the signal to pass
    on, and the real one was lost); every handler is back afterwards."""
    import signal

    from psctl.io.atomic import signals_deferred

    class Term(Exception):
        pass

    def on_term(signum, frame):
        raise Term

    old = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGHUP)}
    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with pytest.raises(Term):
            with signals_deferred():
                os.kill(os.getpid(), signal.SIGHUP)
                os.kill(os.getpid(), signal.SIGTERM)
                done = True
        assert done
        assert signal.getsignal(signal.SIGTERM) is on_term and signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def test_a_link_loop_under_an_output_name_is_no_traceback(tmp_path):
    """check_not_capture compares real paths: a symbolic-link loop where an output goes is a path
    like any other (Path.resolve raised RuntimeError on it, a review)."""
    from psctl.depth import run_depth

    write_capture(tmp_path / "c", n=6, size=32)
    from psctl.api import run_normals

    run_normals(tmp_path / "c", method="l2")
    out = tmp_path / "d"
    out.mkdir()
    os.symlink(out / "loop2", out / "loop1")
    os.symlink(out / "loop1", out / "loop2")
    os.symlink(out / "loop1", out / "depth.png")
    r = run_depth(tmp_path / "c", out=out)
    assert (out / "depth.png").is_file() and not (out / "depth.png").is_symlink() and r["outputs"]


def test_scaled_signed_whole_number_normals_are_still_normals(tmp_path):
    """Only unsigned whole numbers beyond 1 look like an image's codes; int16 normals scaled by
    1000 (one component negative or not) are directions, normalised as any others."""
    import scipy.io

    from psctl.io.capture import load_ground_truth

    write_capture(tmp_path / "c", n=4, size=24)
    gt = np.zeros((24, 24, 3), np.int16)
    gt[...] = (300, 200, 930)
    scipy.io.savemat(tmp_path / "c" / "Normal_gt.mat", {"Normal_gt": gt})
    n = load_ground_truth(open_capture(tmp_path / "c"))
    np.testing.assert_allclose(n[0, 0], np.array([300, 200, 930]) / np.linalg.norm([300, 200, 930]), rtol=1e-6)
    scipy.io.savemat(tmp_path / "c" / "Normal_gt.mat", {"Normal_gt": gt.astype(np.uint16)})
    with pytest.raises(PsctlError, match="an encoded image's values"):
        load_ground_truth(open_capture(tmp_path / "c"))


def test_a_listed_name_with_spaces_reads_that_file(tmp_path):
    """Spaces around a name in filenames.txt are layout, unless a file of that very name exists:
    " 003.png" beside "003.png" read the neighbour (a hostile-input audit)."""
    import shutil

    write_capture(tmp_path / "c", n=6, size=24)
    names = (tmp_path / "c" / "filenames.txt").read_text().split()
    shutil.copy(tmp_path / "c" / names[3], tmp_path / "c" / f" {names[2]}")  # another image, a space before
    (tmp_path / "c" / "filenames.txt").write_text("\n".join([*names[:2], f" {names[2]}", *names[3:]]) + "\n")
    assert [p.name for p in open_capture(tmp_path / "c").image_paths][2] == f" {names[2]}"
    (tmp_path / "c" / "filenames.txt").write_text("\n".join(f"  {n}\t" for n in names) + "\n")
    assert [p.name for p in open_capture(tmp_path / "c").image_paths] == names


def test_an_object_listed_as_a_broken_link_says_so(tmp_path):
    """objects.txt naming a dangling link or a link loop: "a broken link", not "missing"."""
    (tmp_path / "root").mkdir()
    os.symlink(tmp_path / "root" / "b", tmp_path / "root" / "a")
    os.symlink(tmp_path / "root" / "a", tmp_path / "root" / "b")
    (tmp_path / "root" / "objects.txt").write_text("a\n")
    with pytest.raises(PsctlError, match=r"a: listed in objects.txt but is a broken link \(to .*b\)$"):
        find_objects(tmp_path / "root")


def test_a_failed_image_write_on_a_full_disk_says_so(tmp_path, monkeypatch):
    """The EXR writer says only "File output failed" on a full disk: psctl adds the hint its PNG
    and .npy messages give, when the folder has less room than the pixels take."""
    import shutil
    from collections import namedtuple

    import psctl.io.images as images

    real = images._oiio()

    class FailingOutput:
        def open(self, *a):
            return True

        def write_image(self, *a):
            return False

        def geterror(self):
            return "File output failed"

        def close(self):
            return True

    class Oiio:
        def __getattr__(self, name):
            return getattr(real, name)

        class ImageOutput:
            @staticmethod
            def create(name):
                return FailingOutput()

    monkeypatch.setattr(images, "_oiio", lambda: Oiio())
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10 << 20, 10 << 20, 4096))
    with pytest.raises(PsctlError, match=r"n.exr: cannot write image \(File output failed; a full disk or a quota\?\)$"):
        write_image(tmp_path / "n.exr", np.zeros((64, 64, 3), np.float32), "float")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(1 << 40, 0, 1 << 40))
    with pytest.raises(PsctlError, match=r"n.exr: cannot write image \(File output failed\)$"):  # room enough: no guess
        write_image(tmp_path / "n.exr", np.zeros((64, 64, 3), np.float32), "float")
    assert not list(tmp_path.iterdir())  # nothing left behind


def test_an_interrupted_image_write_leaves_no_second_line(tmp_path):
    """Ctrl-C while a PNG is being written: the command line prints one line ('interrupted'),
    not also libpng's 'No IDATs written into file' from the writer closed half-way (an
    interruption audit); and nothing is left under the name. In a process of its own: libpng
    writes to file descriptor 2, which pytest's capture does not stand for."""
    import subprocess
    import sys

    script = (
        "import gc, numpy as np, psctl.io.images as images\n"
        "from psctl.errors import C_STDERR\n"
        "C_STDERR['silence'] = True  # as under the command line\n"
        "def interrupted(a):\n    raise KeyboardInterrupt\n"
        "images.np.ascontiguousarray = interrupted\n"
        "try:\n    images.write_image(%r, np.zeros((8, 8, 3), np.float32), 'uint16')\n"
        "except KeyboardInterrupt:\n    print('interrupted')\n"
        "gc.collect()\n" % str(tmp_path / "a.png"))
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert proc.stdout == "interrupted\n" and proc.stderr == "" and os.listdir(tmp_path) == [], proc.stderr


def _write_exr(path, pixels: np.ndarray, names=None, origin=(0, 0), frame=None) -> None:
    """A float EXR with named channels and a data window at ``origin`` in a ``frame`` (w, h)."""
    import OpenImageIO as oiio

    h, w, c = pixels.shape
    spec = oiio.ImageSpec(w, h, c, oiio.FLOAT)
    if names:
        spec.channelnames = tuple(names)
    spec.x, spec.y = origin
    spec.full_x = spec.full_y = 0
    spec.full_width, spec.full_height = frame or (w, h)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(np.ascontiguousarray(pixels, np.float32))
    out.close()


def test_pick_channels_by_name():
    from psctl.io.images import pick_channels

    assert pick_channels(["R", "G", "B"]) == ((), "", ("",))  # as stored
    assert pick_channels(["R", "G", "B", "A", "Z"]) == ((0, 1, 2, 3), "", ("",))
    assert pick_channels(["A", "B", "G", "R"]) == ((3, 2, 1, 0), "", ("",))  # EXR's alphabetical order
    assert pick_channels(["Y", "A"]) == ((), "", ("",)) and pick_channels(["X", "Y", "Z"]) == ((), "", ())
    assert pick_channels(["R", "G"]) == ((), "", ())  # a 2-channel TIFF's default names: grey and alpha
    with pytest.raises(ValueError, match="has colour channels R and G but not all of R, G and B"):
        pick_channels(["R", "G"], named=True)  # an EXR's own names
    blender = ["Albedo.R", "Albedo.G", "Albedo.B", "Combined.R", "Combined.G", "Combined.B", "Combined.A"]
    assert pick_channels(blender) == ((3, 4, 5, 6), "Combined", ("Albedo", "Combined"))
    nested = [f"ViewLayer.{n}" for n in blender]  # Blender's own names: the view layer, then the pass
    assert pick_channels(nested)[:2] == ((3, 4, 5, 6), "ViewLayer.Combined")
    assert pick_channels(["Albedo.R", "Albedo.G", "Albedo.B", "R", "G", "B"]) == ((3, 4, 5), "", ("Albedo", ""))
    assert pick_channels(["depth.Z", "diffuse.R", "diffuse.G", "diffuse.B"]) == ((1, 2, 3), "diffuse", ("diffuse",))
    with pytest.raises(ValueError, match="2 layers with colour .diffuse, specular. and none named Combined or Beauty"):
        pick_channels(["diffuse.R", "diffuse.G", "diffuse.B", "specular.R", "specular.G", "specular.B"])


def test_an_image_without_a_colour_channel_is_refused(tmp_path):
    """An EXR whose channels are all alpha, depth or UV (a depth pass, Z; alpha alone, A) was read as a
    grey photograph (an audit: the only word was the mixed channels' note, none when every image
    was such): one line naming the file and its channels. Grey (Y) images are still read."""
    from psctl.io.capture import open_capture

    arrays = write_capture(tmp_path / "c", n=6, size=24)
    grey = arrays["images"][2][..., :1]
    for names in (("Z",), ("A",), ("A", "depth.Z")):  # (as EXR stores them: sorted)
        (tmp_path / "c" / "003.png").unlink(missing_ok=True)
        _write_exr(tmp_path / "c" / "003.exr", np.repeat(grey, len(names), -1), names)
        (tmp_path / "c" / "filenames.txt").write_text(
            "".join(f"{k + 1:03d}.{'exr' if k == 2 else 'png'}\n" for k in range(6)))
        with pytest.raises(PsctlError, match=rf"003.exr: holds no colour channel, only "
                                             rf"{', '.join(names)}: not a photograph"):
            open_capture(tmp_path / "c")
    for names in (("Y",), ("L",), ("R",), ("blue", "green", "red")):  # grey; other tools' names (read as stored)
        _write_exr(tmp_path / "c" / "003.exr", np.repeat(grey, len(names), -1), names)
        assert open_capture(tmp_path / "c").n_images == 6
    # two of R, G and B were grey and alpha (helper-170: G and B read as grey G, without a word), and
    # luminance with chroma or X, Y, Z were read as stored
    for names, words in ((("B", "G"), "has colour channels G and B but not all of R, G and B"),
                         (("G", "R"), "has colour channels R and G but not"),
                         (("BY", "RY", "Y"), r"has channels (Y, BY, RY|BY, RY, Y): Y with others than A"),
                         (("X", "Y", "Z"), "has channels X, Y, Z: Y with others")):
        _write_exr(tmp_path / "c" / "003.exr", np.repeat(grey, len(names), -1), names)
        with pytest.raises(PsctlError, match=rf"003.exr: {words}"):
            open_capture(tmp_path / "c")


def test_exr_layers_and_data_windows_are_read_as_a_viewer_shows_them(tmp_path):
    """QA helper's findings: a Blender multilayer EXR (Albedo.* sorts before Combined.*) was read
    as its albedo pass, 41 degrees off; an EXR whose data window is cropped (oiiotool --trim) or
    shifted within its frame was read from the top-left corner, 27 degrees off or refused for
    its size. Now: the picture's layer, placed in the frame, with a note."""
    from psctl.api import run_normals

    arrays = write_capture(tmp_path / "png", n=8, size=32, intensities=False)
    imgs = arrays["images"]
    ys, xs = np.nonzero(imgs.max(0).max(-1) > 0)
    box = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
    assert (box[0].start, box[1].start) != (0, 0)
    for kind in ("plain", "layers", "window"):
        folder = tmp_path / kind
        folder.mkdir()
        names = []
        for k, img in enumerate(imgs):
            names.append(f"{k + 1:03d}.exr")
            if kind == "plain":
                _write_exr(folder / names[-1], img)
            elif kind == "layers":  # Blender's: the albedo pass sorts first
                albedo = np.broadcast_to([0.7, 0.6, 0.5], img.shape)
                _write_exr(folder / names[-1], np.concatenate([albedo, img, np.ones_like(img[..., :1])], -1),
                           ["Albedo.R", "Albedo.G", "Albedo.B", "Combined.R", "Combined.G", "Combined.B", "Combined.A"])
            else:  # the lit part only, at its place in the 32 x 32 frame
                _write_exr(folder / names[-1], img[box], origin=(box[1].start, box[0].start), frame=(32, 32))
        for extra in ("light_directions.txt", "mask.png", "Normal_gt.mat"):
            (folder / extra).write_bytes((tmp_path / "png" / extra).read_bytes())
        (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    pixels, info = read_image(tmp_path / "layers" / "001.exr")
    assert info.layer == "Combined" and info.channels == 4 and pixels.shape == (32, 32, 4)
    np.testing.assert_array_equal(pixels[..., :3], imgs[0])
    pixels, info = read_image(tmp_path / "window" / "001.exr")
    assert (info.width, info.height) == (32, 32) and info.window is not None
    np.testing.assert_array_equal(pixels, imgs[0])  # the crop held every lit pixel: the frame again
    runs = {kind: run_normals(tmp_path / kind, method="l2", write=False) for kind in ("plain", "layers", "window")}
    assert runs["layers"]["mae"] == runs["window"]["mae"] == runs["plain"]["mae"] < 2.0
    assert not [n for n in runs["plain"]["notes"] if n.startswith("images")]
    assert "001.exr, 002.exr, 003.exr ... hold several layers; psctl reads the Combined layer's colour channels" in \
        " ".join(runs["layers"]["notes"])
    assert any("data window other than their 32x32 frame" in n for n in runs["window"]["notes"])
    # two colour layers, neither the main one: refused, naming the file
    _write_exr(tmp_path / "layers" / "001.exr", np.concatenate([imgs[0], imgs[0]], -1),
               ["diffuse.R", "diffuse.G", "diffuse.B", "specular.R", "specular.G", "specular.B"])
    with pytest.raises(PsctlError, match=r"001\.exr.*2 layers with colour \(diffuse, specular\)"):
        run_normals(tmp_path / "layers", method="l2", write=False)


def test_listed_names_match_files_in_another_unicode_form(tmp_path):
    """A capture zipped on a Mac keeps its file names decomposed (NFD: 'e' + combining accent); an
    image list typed elsewhere has them composed (NFC). The same text: the files are found (a QA
    helper's finding: 'listed in filenames.txt but missing' beside a file that looks the same)."""
    import unicodedata

    folder = tmp_path / "cap"
    write_capture(folder, n=4, size=16)
    listed = []
    for k in range(4):
        nfc = unicodedata.normalize("NFC", f"café_{k + 1:03d}.png")
        (folder / f"{k + 1:03d}.png").rename(folder / unicodedata.normalize("NFD", nfc))
        listed.append(nfc)
    (folder / "filenames.txt").write_text("\n".join(listed) + "\n", encoding="utf-8")
    assert not (folder / listed[0]).exists()  # different bytes on this file system
    cap = open_capture(folder)
    assert [p.name for p in cap.image_paths] == [unicodedata.normalize("NFD", n) for n in listed]
    assert load_images(cap).shape == (4, 16, 16, 3)
    (folder / cap.image_paths[0].name).unlink()  # and a file really missing is still an error
    with pytest.raises(PsctlError, match="café_001.png: listed in filenames.txt but missing"):
        open_capture(folder)


def test_psctls_own_pictures_are_not_read_as_images(tmp_path):
    """psctl synth --preview writes preview.png at the root: every later run noted it as an image
    of the root not read, and copied into an object folder it was read as one of its images (a QA
    helper, session 61). Likewise psctl's other pictures."""
    from psctl.io.capture import root_notes

    write_capture(tmp_path / "root" / "a", n=4, size=16)
    (tmp_path / "root" / "objects.txt").write_text("a\n")
    for name in ("preview.png", "undistort.png", "eval.png", "sphere.png"):
        write_image(tmp_path / "root" / name, np.zeros((16, 16, 3), np.float32), "uint8")
        write_image(tmp_path / "root" / "a" / name, np.zeros((16, 16, 3), np.float32), "uint8")
    assert root_notes(tmp_path / "root") == []
    (tmp_path / "root" / "a" / "filenames.txt").unlink()  # the images found by their names
    assert open_capture(tmp_path / "root" / "a").n_images == 4


def _write_cfa_tiff(path, mosaic: np.ndarray, photometric: int = 32803, subfile: int = 0, cfa: bool = True) -> None:
    """A minimal little-endian TIFF of 16-bit sensor values with a DNG's photometric
    interpretation (32803: a colour filter array; 34892: linear raw; 1: grey; or any other, as
    0: WhiteIsZero, 8: CIE L*a*b*) and an RGGB CFA pattern (``cfa``); ``subfile``: its
    NewSubfileType (1: a reduced-resolution image, as a DNG's preview). ``mosaic``: [H, W] or [H, W, C]."""
    import struct

    h, w = mosaic.shape[:2]
    data = np.ascontiguousarray(mosaic, "<u2").tobytes()
    tags = [(254, 4, 1, subfile)] * bool(subfile) + [(256, 3, 1, w), (257, 3, 1, h), (258, 3, 1, 16), (259, 3, 1, 1), (262, 3, 1, photometric),
            (273, 4, 1, 0), (277, 3, 1, 1 if mosaic.ndim == 2 else mosaic.shape[2]), (278, 3, 1, h),
            (279, 4, 1, len(data))] + \
        [(33421, 3, 2, 2 | 2 << 16), (33422, 1, 4, int.from_bytes(bytes([0, 1, 1, 2]), "little"))] * cfa
    ifd_size = 2 + 12 * len(tags) + 4
    offset = 8 + ifd_size  # the pixels after the header and the IFD
    entries = b"".join(struct.pack("<HHII", tag, kind, count, offset if tag == 273 else value)
                       for tag, kind, count, value in tags)
    path.write_bytes(b"II*\0" + struct.pack("<I", 8) + struct.pack("<H", len(tags)) + entries + b"\0\0\0\0" + data)


def test_white_is_zero_and_lab_tiffs(tmp_path):
    """A 16-bit grey TIFF whose photometric interpretation is WhiteIsZero (0 is white): OpenImageIO
    inverts 1- to 8-bit ones but returned 16-bit ones as stored, so psctl read the capture
    inverted without a word (helper-180: l2 58.24 degrees against 5.34 for its BlackIsZero twin;
    as a mask, the background). Now read as its twin. A CIE L*a*b* TIFF was read as R, G, B: now
    one line saying so."""
    values = (np.arange(6 * 8).reshape(6, 8) * 1361 % 65536).astype(np.uint16)
    _write_cfa_tiff(tmp_path / "black.tif", values, 1, cfa=False)
    _write_cfa_tiff(tmp_path / "white.tif", 65535 - values, 0, cfa=False)
    black, white = read_image(tmp_path / "black.tif")[0], read_image(tmp_path / "white.tif")[0]
    assert black.shape == white.shape == (6, 8, 1)
    assert white.tobytes() == black.tobytes()  # bit for bit (helper-187: 1 - value was up to 3e-8 off)
    assert black.max() > 0.9 and black.min() == 0  # (not a flat picture both ways)
    disc = np.zeros((6, 8), np.uint16)
    disc[1:5, 2:6] = 65535
    _write_cfa_tiff(tmp_path / "mask.tif", 65535 - disc, 0, cfa=False)  # white object on black, stored inverted
    assert (read_image(tmp_path / "mask.tif")[0] > 0.5).sum() == 16  # as psctl's masks read it
    _write_cfa_tiff(tmp_path / "lab.tif", np.full((6, 8, 3), 1000, np.uint16), 8, cfa=False)
    with pytest.raises(PsctlError, match=r"lab.tif: holds CIE L\*a\*b\* colour \(TIFF photometric interpretation 8\), "
                                         r"which psctl would read as R, G, B; export it as RGB"):
        read_image(tmp_path / "lab.tif")
    _write_cfa_tiff(tmp_path / "rgb.tif", np.full((6, 8, 3), 1000, np.uint16), 2, cfa=False)  # the same as RGB reads
    assert read_image(tmp_path / "rgb.tif")[0].shape == (6, 8, 3)


def _strip_tiff(path, pixels: np.ndarray, compression: str = "none", rows_per_strip: int = 8, tile: int = 0,
                **attrs) -> bytes:
    """A TIFF as OpenImageIO writes it, of several strips (``rows_per_strip``) or ``tile`` x ``tile``
    tiles, and other ``attrs`` ("planarconfig", "tiff:bigtiff"); returns its bytes."""
    import OpenImageIO as oiio

    h, w, c = pixels.shape
    spec = oiio.ImageSpec(w, h, c, oiio.UINT8 if pixels.dtype == np.uint8 else oiio.UINT16)
    spec.attribute("compression", compression)
    spec.attribute("tiff:RowsPerStrip", rows_per_strip)
    spec.tile_width = spec.tile_height = tile
    for name, value in attrs.items():
        spec.attribute(name, value)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(np.ascontiguousarray(pixels)), out.geterror()
    out.close()
    return path.read_bytes()


def _tiff_entry(data: bytes, tag: int) -> tuple[int, int, list[int]]:
    """A tag of a little-endian TIFF's first IFD: where its entry is, where its values are, the values."""
    import struct

    ifd = struct.unpack_from("<I", data, 4)[0]
    for i in range(struct.unpack_from("<H", data, ifd)[0]):
        entry = ifd + 2 + 12 * i
        found, kind, count, field = struct.unpack_from("<HHII", data, entry)
        if found == tag:
            code, size = {3: ("H", 2), 4: ("I", 4)}[kind]
            where = entry + 8 if count * size <= 4 else field
            return entry, where, list(struct.unpack_from(f"<{count}{code}", data, where))
    raise KeyError(tag)


def test_a_truncated_jpeg_is_named_once(tmp_path):
    """libjpeg's message quotes the file's path, which the error already starts with (helper-190:
    'X.jpg: corrupt or truncated image (JPEG error: Premature end of JPEG file ("X.jpg"))')."""
    write_image(tmp_path / "a.jpg", np.random.default_rng(0).random((32, 32, 3), np.float32), "uint8")
    data = (tmp_path / "a.jpg").read_bytes()
    (tmp_path / "a.jpg").write_bytes(data[:len(data) // 2])
    with pytest.raises(PsctlError) as e:
        read_image(tmp_path / "a.jpg")
    assert str(e.value) == f"{tmp_path / 'a.jpg'}: corrupt or truncated image (JPEG error: Premature end of JPEG file)"


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("compression", ["none", "lzw"])
def test_a_tiff_strip_without_an_offset_is_one_line(tmp_path, bits, compression):
    """helper-190: a StripOffsets tag with fewer values than the image has strips (1 for 6) read
    as garbage without an error: libtiff fills the missing offsets with 0 and reads the file's
    header as pixels, OpenImageIO says nothing (a sphere's l2 normals 11.5 degrees off instead of
    1.0). A zero offset alone, the same. Now one line naming the file, in a whole read and in a
    band read (psctl.infer's later passes) alike; a strip past the file's end is named as such."""
    import struct

    dtype = np.uint8 if bits == 8 else np.uint16
    pixels = (np.arange(48 * 64 * 3).reshape(48, 64, 3) * 37 % (1 << bits)).astype(dtype)
    good = _strip_tiff(tmp_path / "good.tif", pixels, compression)
    entry, where, offsets = _tiff_entry(good, 273)
    assert len(offsets) == 6
    assert np.array_equal(np.rint(read_image(tmp_path / "good.tif")[0] * ((1 << bits) - 1)), pixels)
    one, zero, past = bytearray(good), bytearray(good), bytearray(good)
    struct.pack_into("<II", one, entry + 4, 1, offsets[0])  # count 1, the first strip's offset in the entry
    struct.pack_into("<I", zero, where + 4 * 3, 0)
    struct.pack_into("<I", past, where + 4 * 3, len(good) + 100)
    for data, words in ((one, "its StripOffsets tag lists 1 offset for 6 strips"),
                        (zero, "its strip 3 has offset 0, inside the TIFF header"),
                        (past, f"its strip 3 starts at byte {len(good) + 100:,}, past the file's end")):
        bad = tmp_path / "bad.tif"
        bad.write_bytes(bytes(data))
        for rows in (None, (16, 40)):
            with pytest.raises(PsctlError) as e:
                read_image(bad, rows=rows)
            assert e.value.path == str(bad) and e.value.message.startswith(f"corrupt image ({words}"), e.value.message


def test_a_repeated_strip_offsets_tag_is_read_as_libtiff_reads_it(tmp_path):
    """A StripOffsets tag listed twice (invalid TIFF): libtiff, under OpenImageIO, keeps the first
    entry, and so does the check since session 78 (helper-193). Good then zeros reads as the
    image; zeros then good is refused, as libtiff would read the header as pixels."""
    import struct

    pixels = (np.arange(48 * 64 * 3).reshape(48, 64, 3) * 37 % 65536).astype(np.uint16)
    good = _strip_tiff(tmp_path / "good.tif", pixels)
    entry, _, offsets = _tiff_entry(good, 273)
    ifd = struct.unpack_from("<I", good, 4)[0]
    n = struct.unpack_from("<H", good, ifd)[0]
    entries = [good[ifd + 2 + 12 * i: ifd + 14 + 12 * i] for i in range(n)]
    k = (entry - ifd - 2) // 12

    def with_twice(first_good: bool) -> bytes:
        zeros_at = len(good) + (len(good) % 2)  # the zero offsets' block, word-aligned, after the file
        body = bytearray(good) + bytes(len(good) % 2) + bytes(4 * len(offsets))
        dup = struct.pack("<HHII", 273, 4, len(offsets), zeros_at)
        pair = [entries[k], dup] if first_good else [dup, entries[k]]
        new_ifd = len(body) + (len(body) % 2)
        body += bytes(len(body) % 2) + struct.pack("<H", n + 1) + b"".join(entries[:k] + pair + entries[k + 1:])
        body += struct.pack("<I", 0)  # no next IFD
        struct.pack_into("<I", body, 4, new_ifd)
        return bytes(body)

    (tmp_path / "first_good.tif").write_bytes(with_twice(True))
    got = read_image(tmp_path / "first_good.tif")[0]
    assert np.array_equal(np.rint(got * 65535), pixels)
    (tmp_path / "first_zero.tif").write_bytes(with_twice(False))
    with pytest.raises(PsctlError, match="its strip 0 has offset 0, inside the TIFF header"):
        read_image(tmp_path / "first_zero.tif")

def test_tiffs_of_every_strip_and_tile_layout_still_read(tmp_path):
    """The strip check (helper-190) finds nothing wrong in what OpenImageIO writes: one strip,
    a strip a row, strips not dividing the height, tiles, separate planes, BigTIFF, compressed."""
    pixels = (np.arange(37 * 53 * 3).reshape(37, 53, 3) * 997 % 65536).astype(np.uint16)
    layouts = {"one strip": {"rows_per_strip": 64}, "a row a strip": {"rows_per_strip": 1},
               "7 rows a strip": {"rows_per_strip": 7}, "tiles": {"tile": 16},
               "planes": {"planarconfig": "separate"}, "tiled planes": {"tile": 32, "planarconfig": "separate"},
               "bigtiff": {"tiff:bigtiff": 1}, "lzw": {"compression": "lzw"}, "zip tiles": {"compression": "zip", "tile": 16}}
    for name, layout in layouts.items():
        path = tmp_path / f"{name}.tif"
        _strip_tiff(path, pixels, **layout)
        got = read_image(path)[0]
        assert np.array_equal(np.rint(got * 65535), pixels), name
        assert np.array_equal(read_image(path, rows=(5, 30))[0], got[5:30]), name


def test_a_capture_with_a_tiff_strip_without_an_offset_is_one_line(tmp_path):
    """psctl normals on TIFFs, one of which lists 1 StripOffsets value for 8 strips: before the
    fix it wrote normals 11.5 degrees off (1.0 on the good capture) and exited 0."""
    import subprocess
    import struct

    write_capture(tmp_path / "cap", n=8, size=64)
    names = []
    for png in sorted((tmp_path / "cap").glob("0*.png")):
        _strip_tiff(png.with_suffix(".tif"), np.rint(read_image(png)[0] * 65535).astype(np.uint16))
        png.unlink()
        names.append(png.with_suffix(".tif").name)
    (tmp_path / "cap" / "filenames.txt").write_text("\n".join(names) + "\n")
    bad = tmp_path / "cap" / "005.tif"
    data = bytearray(bad.read_bytes())
    entry, _, offsets = _tiff_entry(bytes(data), 273)
    struct.pack_into("<II", data, entry + 4, 1, offsets[0])
    bad.write_bytes(bytes(data))
    proc = subprocess.run([sys.executable, "-m", "psctl.cli", "normals", str(tmp_path / "cap"), "-m", "l2", "-q",
                           "-o", str(tmp_path / "o")], capture_output=True, text=True)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert f"{bad}: corrupt image (its StripOffsets tag lists 1 offset for 8 strips" in proc.stderr
    assert not (tmp_path / "o").exists()


def test_camera_raw_files_are_refused_with_how_to_convert_them(tmp_path):
    """Camera raw files: OpenImageIO (without its raw plugin) read a DNG as a grey picture of the
    sensor's colour mosaic, and most raw formats are TIFF inside (the embedded preview): now one
    line saying how to convert them, by name and, for a DNG under a TIFF name, by content."""
    from typer.testing import CliRunner

    from psctl.cli import app
    from psctl.io.capture import open_capture
    from psctl.io.images import image_info

    mosaic = (np.arange(24 * 32).reshape(24, 32) * 50 % 4000 + 64).astype(np.uint16)
    _write_cfa_tiff(tmp_path / "sensor.tif", mosaic)
    with pytest.raises(PsctlError, match=r"sensor.tif: holds camera raw sensor data \(a colour filter array, as a "
                                         r"DNG\), which psctl does not decode; convert it to a 16-bit linear TIFF "
                                         r"first, e.g. `dcraw -4 -T sensor.tif`"):
        image_info(tmp_path / "sensor.tif")
    _write_cfa_tiff(tmp_path / "linear.tif", mosaic, 34892)
    with pytest.raises(PsctlError, match=r"linear.tif: holds camera raw sensor data \(linear raw"):
        read_image(tmp_path / "linear.tif")
    _write_cfa_tiff(tmp_path / "preview.tif", mosaic, 1, subfile=1)  # a DNG's first image: its preview (a review)
    with pytest.raises(PsctlError, match=r"preview.tif: starts with a reduced-resolution preview \(TIFF "
                                         r"NewSubfileType 1\), as a DNG or a camera raw file does"):
        image_info(tmp_path / "preview.tif")
    _write_cfa_tiff(tmp_path / "grey.tif", mosaic, 1)  # the same grey TIFF as a full-size image reads
    assert image_info(tmp_path / "grey.tif").channels == 1
    write_image(tmp_path / "plain.tif", np.full((24, 32, 3), 0.5, np.float32), "uint16")  # an ordinary TIFF reads
    assert image_info(tmp_path / "plain.tif").channels == 3
    (tmp_path / "plain.tif").rename(tmp_path / "IMG_0001.CR2")  # by name, whatever it holds (CR3 is no TIFF)
    with pytest.raises(PsctlError, match=r"IMG_0001.CR2: is a camera raw file \(.CR2\), which psctl does not decode"):
        image_info(tmp_path / "IMG_0001.CR2")

    cap = tmp_path / "cap"  # a capture folder of raw files: not 'list them', but how to convert them
    write_capture(cap, n=4, size=24)
    (cap / "filenames.txt").unlink(missing_ok=True)
    for k in range(4):
        (cap / f"{k + 1:03d}.png").rename(cap / f"DSC_{k:04d}.NEF")
    with pytest.raises(PsctlError, match=r"no images found .*; DSC_0000.NEF, .* are camera raw, which psctl does not "
                                         r"decode: convert them to 16-bit linear TIFFs first, e.g. `dcraw -4 -T \*.NEF`"):
        open_capture(cap)
    (cap / "filenames.txt").write_text("".join(f"DSC_{k:04d}.NEF\n" for k in range(4)))  # listed: refused by name
    result = CliRunner().invoke(app, ["normals", str(cap), "-m", "l2", "-o", str(tmp_path / "out")])
    assert result.exit_code == 2 and "Traceback" not in result.output and not (tmp_path / "out").exists()
    assert result.output.strip().splitlines()[-1].startswith(f"error: {cap / 'DSC_0000.NEF'}: is a camera raw file")


def test_images_whose_exif_exposures_differ_get_a_note(tmp_path):
    """A bracketed or auto-exposed capture: each image's exposure scales its light's intensity,
    which psctl reads from light_intensities.txt only; a note says so (EXIF time x ISO / N^2,
    the factors every header gives). None when the exposures agree or are not all known."""
    import OpenImageIO as oiio

    from psctl.io.capture import capture_notes, open_capture, relative_exposures

    def write(folder, times, isos, intensities=True):
        data = write_capture(folder, n=len(times), size=24, bits=8, intensities=intensities)
        for k, (t, iso) in enumerate(zip(times, isos)):
            (folder / f"{k + 1:03d}.png").unlink()
            spec = oiio.ImageSpec(24, 24, 3, oiio.UINT8)
            spec.attribute("ExposureTime", t)
            spec.attribute("FNumber", 8.0)
            if iso:
                spec.attribute("Exif:PhotographicSensitivity", iso)
            out = oiio.ImageOutput.create(str(folder / f"{k + 1:03d}.jpg"))
            assert out.open(str(folder / f"{k + 1:03d}.jpg"), spec)
            out.write_image(np.round(np.clip(data["images"][k], 0, 1) * 255).astype(np.uint8))
            out.close()
        (folder / "filenames.txt").write_text("".join(f"{k + 1:03d}.jpg\n" for k in range(len(times))))
        return open_capture(folder)

    cap = write(tmp_path / "a", [1 / 60, 1 / 60, 1 / 30, 1 / 60], [200, 400, 200, 200])
    rel = relative_exposures(cap)
    np.testing.assert_allclose(rel / rel[0], [1, 2, 2, 1], rtol=1e-3)
    assert np.median(rel) == 1  # over the median image's
    assert [n for n in capture_notes(cap) if "exposures" in n] == [
        "images: their EXIF exposures differ (time 1/60 s to 1/30 s, ISO 200 to 400: 003.jpg 2 times 001.jpg's); "
        "psctl reads each image as stored, so its exposure scales its light's intensity: each row of "
        "light_intensities.txt should include its image's exposure (intensity x exposure) (psctl info --json: "
        "relative_exposures)"]
    from psctl.io.summary import describe_capture

    np.testing.assert_allclose(describe_capture(tmp_path / "a")["relative_exposures"], rel, rtol=1e-5)
    assert cap.subset([0, 3]).exposures == (cap.exposures[0], cap.exposures[3])
    assert not any("exposures" in n for n in capture_notes(cap.subset([0, 3])))  # the same: no note
    cap = write(tmp_path / "b", [1 / 60, 1 / 15, 1 / 60], [200, 200, 0], intensities=False)  # ISO not in every header
    np.testing.assert_allclose(relative_exposures(cap), [1, 4, 1], rtol=1e-3)
    assert any("(time 1/60 s to 1/15 s: 002.jpg 4 times 001.jpg's)" in n and "without light_intensities.txt every "
               "light is taken as equally strong, except by sdps" in n for n in capture_notes(cap))
    cap = write(tmp_path / "c", [1 / 60, 1 / 60, 0.0165], [200, 200, 200])  # within EXIF's rounding
    assert not any("exposures" in n for n in capture_notes(cap))
    # compensated in nominal steps: 1/60 s at ISO 100 and 1/125 s at ISO 200 (really 1/128): 4 % apart
    # by EXIF, no note (a review: it got one at a 2 % threshold)
    cap = write(tmp_path / "e", [1 / 60, 1 / 125, 1 / 60], [100, 200, 100])
    assert 1.03 < relative_exposures(cap).max() / relative_exposures(cap).min() < 1.05
    assert not any("exposures" in n for n in capture_notes(cap))
    assert relative_exposures(open_capture(write_capture(tmp_path / "d", n=4, size=24) and tmp_path / "d")) is None


def test_the_picture_font_tells_method_names_apart():
    """A QA round read "l2" on error.png and compare.png as "12" and "qa_root" as "9a_root": l and
    1 (and I) differ by at least 4 pixels however they are shifted by a pixel, and q's stem stands
    apart from its bowl's top, where 9's loop closes."""
    from psctl.io.report import _FONT

    def glyph(c):
        return np.array([[x == "#" for x in row] for row in _FONT[c]])

    def apart(a, b, k=1):
        pa, pb = np.pad(glyph(a), k), np.pad(glyph(b), k)
        return min(int((pa ^ np.roll(np.roll(pb, dy, 0), dx, 1)).sum())
                   for dy in range(-k, k + 1) for dx in range(-k, k + 1))

    assert apart("l", "1") >= 4 and apart("l", "I") >= 4 and apart("l", "|") >= 3
    q = glyph("q")  # (the old q's bowl closed into its stem at the top, as 9's loop does)
    assert q[2:, 4].all() and not q[2, 3] and not q[:2].any()  # a stem apart from the bowl's top
    # tails below the line (helper-162: in 7 rows g, p and q read as 9, P and a): 2 rows more, where
    # the text has one; the rest as before
    from psctl.io.report import text_bitmap

    assert text_bitmap("ABC pot1", 2).shape[0] == 18 and text_bitmap("ABC 01", 2).shape[0] == 14
    for c in "gjpqy":
        assert glyph(c).shape == (9, 5) and glyph(c)[7:].any() and not glyph(c)[:2, :3].any(), c
    assert all(glyph(c).shape == (7, 5) for c in "abcdefhiklmnorstuvwxz0123456789P")
    assert apart("g", "q") >= 3 and apart("p", "q") >= 4 and apart("g", "y") >= 3


def test_a_damaged_exr_header_is_one_line(tmp_path):
    """An EXR whose header holds bytes that are not UTF-8 (a channel list's type name damaged):
    OpenImageIO's message quotes them and its binding raised UnicodeDecodeError (a traceback);
    now one line naming the file, the bytes replaced, for the header's read and the pixels'."""
    from psctl.io.images import image_info

    img = np.random.default_rng(0).uniform(0, 1, (8, 8, 3)).astype(np.float32)
    for name, field in (("chl.exr", b"chlist"), ("str.exr", b"string")):
        write_image(tmp_path / name, img, "float32", kind="data")
        b = (tmp_path / name).read_bytes()
        i = b.index(field)
        (tmp_path / name).write_bytes(b[:i + 3] + b"\xfe" + b[i + 4:])
    with pytest.raises(PsctlError, match=r"chl\.exr: cannot open image \(.*\ufffd") as e:
        image_info(tmp_path / "chl.exr")
    assert "\n" not in str(e.value)
    damaged = []  # the other file's damage shows at the header's read or at the pixels'
    for read in (image_info, read_image):
        try:
            read(tmp_path / "str.exr")
        except PsctlError as err:
            damaged.append(str(err))
    assert damaged and all(m.startswith(str(tmp_path / "str.exr")) and "\n" not in m for m in damaged)


def test_a_png_page_offset_does_not_shift_its_pixels(tmp_path):
    """A PNG with an oFFs chunk (ImageMagick's -crop without +repage) is read as viewers show it:
    OpenImageIO gives its offset as the pixels' origin in a frame at 0, and psctl placed the
    pixels 4 px down and right (l2 29.7 deg instead of 0.1 on a capture-reading audit's sphere)."""
    import struct
    import zlib

    img = np.random.default_rng(1).uniform(0, 1, (12, 10, 3)).astype(np.float32)
    write_image(tmp_path / "a.png", img, "uint16", kind="linear")
    b = (tmp_path / "a.png").read_bytes()
    body = b"oFFs" + struct.pack(">iiB", 4, 4, 0)
    offs = struct.pack(">I", 9) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)
    (tmp_path / "b.png").write_bytes(b[:33] + offs + b[33:])  # after the signature and IHDR
    a, _ = read_image(tmp_path / "a.png")
    shifted, info = read_image(tmp_path / "b.png")
    assert np.array_equal(a, shifted) and info.window is None


def test_signed_image_numbers_get_a_note(tmp_path):
    """Images named l-2.png .. l3.png without filenames.txt are in natural order with the '-' read
    as text (l0 .. l3, then l-1, l-2), not as the lights' order: a note says so (a review: l2 52
    degrees off without a word); none with a list, or where every name has the '-' (img-01)."""
    from psctl.io.capture import capture_notes, open_capture
    from tests.conftest import write_capture

    for folder, names in (("signed", [f"l{k}.png" for k in range(-2, 4)]),
                          ("dashed", [f"img-{k:02d}.png" for k in range(1, 7)])):
        write_capture(tmp_path / folder, n=6, size=16)
        for k, name in enumerate(names):
            (tmp_path / folder / f"{k + 1:03d}.png").rename(tmp_path / folder / name)
        (tmp_path / folder / "filenames.txt").unlink()
    cap = open_capture(tmp_path / "signed")
    assert [p.name for p in cap.image_paths] == ["l0.png", "l1.png", "l2.png", "l3.png", "l-1.png", "l-2.png"]
    said = [n for n in capture_notes(cap) if "'-' or '+' precedes" in n]
    assert len(said) == 1 and "l0.png and l-1.png" in said[0] and "filenames.txt" in said[0]
    from psctl.io.capture import _signed_names  # '+' too; no sign after a digit (dates, copies)

    assert _signed_names(["exp+1.png", "exp+2.png", "exp-1.png"]) == "exp+1.png and exp-1.png"
    assert _signed_names(["2024-01-05_001.png", "20240106_001.png", "IMG_0001.jpg", "IMG_0001-2.jpg"]) is None
    assert not any("'-' or '+' precedes" in n for n in capture_notes(open_capture(tmp_path / "dashed")))
    (tmp_path / "signed" / "filenames.txt").write_text("".join(f"l{k}.png\n" for k in range(-2, 4)))
    assert not any("'-' or '+' precedes" in n for n in capture_notes(open_capture(tmp_path / "signed")))


@pytest.mark.parametrize("ext", ["tif", "exr"])
def test_a_cropped_data_window_is_placed_in_its_frame(tmp_path, ext):
    """A TIFF (OpenImageIO's full-size tags, as RenderMan crops) or EXR whose data window is
    smaller than its frame: the pixels at their place, 0 around (a review: with only an EXR's
    window honoured, a TIFF's failed with a reshape traceback)."""
    import OpenImageIO as oiio

    p = tmp_path / f"crop.{ext}"
    spec = oiio.ImageSpec(8, 6, 3, "float" if ext == "exr" else "uint16")
    spec.x, spec.y = 2, 1
    spec.full_x, spec.full_y, spec.full_width, spec.full_height = 0, 0, 12, 10
    out = oiio.ImageOutput.create(str(p))
    out.open(str(p), spec)
    out.write_image(np.full((6, 8, 3), 0.5, np.float32))
    out.close()
    pixels, info = read_image(p)
    assert pixels.shape == (10, 12, 3) and info.window == (2, 1, 8, 6)
    want = np.zeros((10, 12, 3), np.float32)
    want[1:7, 2:10] = 0.5
    np.testing.assert_allclose(pixels, want, atol=1e-4)


def test_names_alike_in_natural_order_keep_one_order(tmp_path):
    """img01 / IMG01 (and img1 / img01) tie in natural order; their order, and so their light rows,
    followed the folder's listing, which differs between file systems (helper-174: ext4 and tmpfs
    gave two orders). The exact name breaks the tie."""
    import random

    from psctl.io.capture import _image_files

    names = ["img01.png", "IMG01.png", "img1.png", "img2.png", "img10.png"]
    for name in names:
        (tmp_path / name).write_bytes(b"")
    entries = list(tmp_path.iterdir())
    want = [p.name for p in _image_files(entries)]
    assert want == ["IMG01.png", "img01.png", "img1.png", "img2.png", "img10.png"]
    for seed in range(5):  # whatever order the folder lists them in
        random.Random(seed).shuffle(entries)
        assert [p.name for p in _image_files(entries)] == want


def test_a_long_output_name_has_a_temporary_name_that_fits(tmp_path):
    """A 250-character output name is valid, but its temporary name was 14 characters longer
    (helper-174: psctl undistort failed on image names of 242-255 characters)."""
    from psctl.io.atomic import atomic_path

    for dst in (tmp_path / ("i" * 246 + ".png"), tmp_path / ("\U0001F600" * 62 + ".png")):  # 250 and 252 bytes
        with atomic_path(dst) as tmp:  # (a name's limit counts bytes: cut by characters, 4-byte ones failed, helper-175)
            assert len(os.fsencode(tmp.name)) < 100
            tmp.write_bytes(b"x")
        assert dst.read_bytes() == b"x"


def test_a_quoted_tilde_is_named_where_the_home_folder_holds_it(tmp_path, monkeypatch):
    """'~/cap' in quotes reaches psctl as it is (only the shell expands ~): the error says so."""
    from psctl.io.capture import open_capture

    monkeypatch.setenv("HOME", str(tmp_path))
    (tmp_path / "cap").mkdir()
    with pytest.raises(PsctlError, match=r"~/cap: folder does not exist \(a ~ in quotes is not your home folder: "):
        open_capture("~/cap")
    with pytest.raises(PsctlError, match=r"~/none: folder does not exist$"):
        open_capture("~/none")
    with pytest.raises(PsctlError, match=r"~/cap: folder does not exist \(a ~ in quotes is not your home folder"):
        find_objects("~/cap")  # psctl eval --root (helper-175)


def test_an_empty_or_unreadable_image_says_so_plainly(tmp_path, monkeypatch):
    """OpenImageIO's words hid the plainest causes (helper-170): 'Not a PNG file' for an empty file,
    'Could not open file "PATH"' (the path twice) for one without read permission."""
    import builtins
    import errno

    from psctl.io.images import _cannot_open, read_image

    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(PsctlError, match=r"empty.png: is empty \(0 bytes\), not an image$"):
        read_image(tmp_path / "empty.png")
    (tmp_path / "junk.png").write_bytes(b"not a png at all")
    with pytest.raises(PsctlError, match=r"junk.png: cannot open image \("):
        read_image(tmp_path / "junk.png")
    # no read permission (root, as on CI, reads any file: the refusal is simulated)
    write_image(tmp_path / "locked.png", np.zeros((4, 4, 3)), "uint8")
    real = builtins.open

    def refusing(path, *args, **kwargs):
        if str(path).endswith("locked.png"):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", refusing)
    e = _cannot_open(tmp_path / "locked.png", f'Could not open file "{tmp_path / "locked.png"}"')
    assert str(e) == f"{tmp_path / 'locked.png'}: cannot open image (permission denied)"


def test_image_checks_reader_sees_a_box_once(tmp_path):
    """A large capture's network passes (one per tile group) read the same box again; the check's
    saturated map, sums and extremes were worked out again each time (a third of a pass's work per
    image at 12 MP, helper-171). A box already seen is read without them; another box is seen."""
    import copy

    from psctl.io.capture import ImageCheck

    write_capture(tmp_path / "cap", n=5, size=24, bits=8)
    cap = open_capture(tmp_path / "cap")
    mask = load_mask(cap)
    chk = ImageCheck(cap)
    read = chk.reader(cap, mask)
    whole = (slice(0, 24), slice(0, 24))
    first = [x.copy() for x in read(0, whole)]
    state = copy.deepcopy((chk.sums, chk.clipped, chk.seen, chk.lit))
    again = list(read(0, whole)) + list(read(2, whole))
    assert all(np.array_equal(a, b) for a, b in zip(first + first[2:], again))  # the same images
    assert (chk.sums, chk.clipped, chk.seen, chk.lit) == state  # nothing counted twice
    list(read(0, (slice(0, 12), slice(0, 24))))  # another box: seen
    assert chk.sums != state[0]
    state = copy.deepcopy(chk.sums)
    list(chk.reader(cap, mask)(0, whole))  # another reader (other intensities, another mask): seen
    assert chk.sums != state


def test_an_output_folder_given_with_a_quoted_tilde_is_refused(tmp_path, monkeypatch):
    """-o '~/out' reaches psctl as it is and made a folder named ~ in the working folder without a
    word (helper-174); a folder ~ that is there already is the user's own choice."""
    from psctl.io.atomic import check_output_dir

    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(PsctlError, match=rf"~/out: starts with ~, which is not your home folder in quotes .*: write "
                                         rf"{tmp_path / 'home' / 'out'} instead"):
        check_output_dir("~/out")
    assert not (tmp_path / "~").exists()
    (tmp_path / "~").mkdir()
    assert str(check_output_dir("~/out")) == "~/out"


def test_a_signal_while_staging_starts_leaves_no_folder_and_no_probe(tmp_path, monkeypatch):
    """A signal after the output folder was made but before the staging folder was (helper-177):
    the folders the run made stayed, holding the write test's probe file. Now the probe has no
    name where the system allows, and the made folders go again."""
    import psctl.io.atomic as atomic

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(atomic, "working_folder", interrupted)
    with pytest.raises(KeyboardInterrupt):
        with atomic.staged_outputs(tmp_path / "a" / "b"):
            pass
    assert not (tmp_path / "a").exists()
    monkeypatch.undo()
    atomic.ensure_writable_dir(tmp_path / "c")
    assert list((tmp_path / "c").iterdir()) == []


@pytest.mark.parametrize("ext,dtype", [("png", "uint16"), ("png", "uint8"), ("tif", "float"), ("exr", "half")])
def test_read_image_rows_are_the_whole_image_cut(tmp_path, ext, dtype):
    # psctl.infer's later passes decode only a tile group's rows: the same values as reading whole
    rng = np.random.default_rng(3)
    img = rng.random((37, 23, 3)).astype(np.float32)
    p = tmp_path / f"a.{ext}"
    write_image(p, img, dtype, kind="linear")
    whole, info = read_image(p)
    for rows in ((0, 37), (0, 5), (11, 29), (36, 37)):
        part, part_info = read_image(p, rows=rows)
        assert part.shape == (rows[1] - rows[0], 23, 3) and part_info == info
        assert part.tobytes() == whole[rows[0]:rows[1]].tobytes()


def test_read_image_names_nonfinite_values(tmp_path):
    """A NaN or infinite value is one line that says what, how many, in which channel and where
    (helper-202: "image contains NaN or infinite values" alone left a NaN alpha, which psctl
    otherwise ignores, or a half-float EXR's highlight over 65504, to be hunted for)."""
    img = np.full((6, 8, 4), 0.5, np.float32)
    img[2, 5, 1] = np.nan
    img[4, 1, 1] = np.nan
    write_image(tmp_path / "g.exr", img, "float")
    with pytest.raises(PsctlError, match=r"image contains NaN values: 2 pixels \(channel G; first at row 2, column 5\)$"):
        read_image(tmp_path / "g.exr")
    img = np.full((6, 8, 4), 0.5, np.float32)
    img[0, 3, 3] = np.nan
    write_image(tmp_path / "a.exr", img, "float")
    with pytest.raises(PsctlError, match=r"NaN values: 1 pixel \(channel A; first at row 0, column 3\); only in its alpha"):
        read_image(tmp_path / "a.exr")
    write_image(tmp_path / "h.exr", np.full((6, 8, 3), np.inf, np.float32), "half")  # (1e5 as half)
    with pytest.raises(PsctlError, match=r"\+inf values: 48 pixels \(channels R, G, B; first at row 0, column 0\); "
                                         r"a half-float file holds at most 65504"):
        read_image(tmp_path / "h.exr")
    assert np.isnan(read_image(tmp_path / "g.exr", allow_nonfinite=True)[0][2, 5, 1])
