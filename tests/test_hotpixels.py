"""Isolated hot pixels (psctl.hotpixels): found, set to their neighbours' level, noted; the
networks' answers then equal those of the capture without them."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from psctl.hotpixels import HOT_LEVEL, HOT_RATIO, clamp_hot_pixels, hot_pixel_notes
from tests.conftest import hemisphere_lights, render_lambertian, sphere, write_capture


def smooth(h: int = 20, w: int = 24, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(0.2, 0.3, (h, w, 3)).astype(np.float32)


def with_hot(img: np.ndarray, y: int, x: int, c: int, value: float) -> tuple[np.ndarray, float]:
    """``img`` with one value set to ``value``; returns it and the value the clamp should give
    (the brightest of the 8 neighbours in that channel)."""
    out = img.copy()
    out[y, x, c] = value
    nb = img[max(y - 1, 0): y + 2, max(x - 1, 0): x + 2, c].copy()
    nb[min(y, 1), min(x, 1)] = -np.inf  # the pixel itself
    return out, float(nb.max())


def test_one_hot_value_is_set_to_its_neighbours_max_and_nothing_else_changes():
    img = smooth()
    mean = float(img.mean())
    for y, x in ((7, 9), (0, 0), (19, 23), (0, 11)):  # inside, corners, an edge
        hot, expect = with_hot(img, y, x, 1, 2 * HOT_LEVEL * mean)
        before = hot.copy()
        out, n = clamp_hot_pixels(hot)
        assert n == 1 and out[y, x, 1] == expect
        np.testing.assert_array_equal(hot, before)  # the input is not modified
        changed = out != hot
        assert changed.sum() == 1 and changed[y, x, 1]


def test_highlights_and_moderate_values_are_kept():
    img = smooth()
    mean = float(img.mean())
    # below the level test (a bright, but not extreme, single pixel)
    low, _ = with_hot(img, 5, 5, 0, 0.5 * HOT_LEVEL * mean)
    out, n = clamp_hot_pixels(low)
    assert n == 0 and out is low
    # a 2 x 2 highlight: each pixel has a bright neighbour, so none is isolated
    blob = img.copy()
    blob[5:7, 5:7, :] = 2 * HOT_LEVEL * mean
    out, n = clamp_hot_pixels(blob)
    assert n == 0 and out is blob
    # a pixel just above the ratio test is hot; one just below is not
    nb = np.full((3, 3, 1), 1.0, np.float32)
    nb[1, 1, 0] = 1.01 * HOT_RATIO
    assert clamp_hot_pixels(nb, level=0.1)[1] == 1
    nb[1, 1, 0] = 0.99 * HOT_RATIO
    assert clamp_hot_pixels(nb, level=0.1)[1] == 0


def test_the_level_is_the_mean_inside_the_mask_and_grey_images_work():
    img = np.ones((40, 40), np.float32)  # bright around the object (a grey image)
    mask = np.zeros(img.shape, bool)
    mask[5:35, 5:35] = True
    img[mask] = 0.01  # a dark object: 900 pixels
    img[20, 20] = 20.0  # hot against the object, not against the whole image
    assert float(img.mean()) * HOT_LEVEL > 20 and float(img[mask].mean()) * HOT_LEVEL < 20
    assert clamp_hot_pixels(img)[1] == 0
    out, n = clamp_hot_pixels(img, mask)
    assert n == 1 and out.shape == img.shape and out[20, 20] == pytest.approx(0.01)
    assert clamp_hot_pixels(np.zeros((4, 4, 3), np.float32))[1] == 0  # black: no mean to compare with
    assert clamp_hot_pixels(img, np.zeros(img.shape, bool))[1] == 0  # empty mask


def test_isolated_pixel_in_shadow_is_hot():
    img = np.zeros((40, 40, 3), np.float32)
    img[:, :20] = 0.3  # lit half; the pixel sits in the shadowed half, its neighbours 0
    img[4, 27, 2] = 2 * HOT_LEVEL * float(img.mean())  # its own share of the mean: 1/16 of the level
    out, n = clamp_hot_pixels(img)
    assert n == 1 and out[4, 27, 2] == 0


def test_noise_about_zero_is_not_hot_and_a_dark_frame_still_is():
    """Float files with a subtracted black level: the level is the mean of the positive part, so
    noise about 0 does not pass it, and a hot pixel in a frame of negative mean is still found."""
    rng = np.random.default_rng(0)
    noise = rng.normal(1e-5, 0.01, (120, 130, 3)).astype(np.float32)
    assert clamp_hot_pixels(noise)[1] == 0
    dark = rng.normal(-0.005, 0.01, (120, 130, 3)).astype(np.float32)
    dark[60, 61, 2] = 1000.0
    out, n = clamp_hot_pixels(dark)
    assert n == 1 and out[60, 61, 2] == max(float(dark[59:62, 60:63, 2].ravel()[[0, 1, 2, 3, 5, 6, 7, 8]].max()), 0.0)
    huge = np.full((40, 40, 3), 1e36, np.float32)  # a float32 sum overflows here: summed again in float64
    huge[7, 7, 1] = 3.3e38  # over 300 times the mean, under float32's largest value
    assert clamp_hot_pixels(huge)[1] == 1


def test_note_lists_three_images_then_dots():
    names = [f"{k:03d}.png" for k in range(1, 7)]
    assert hot_pixel_notes({}, names) == [] and hot_pixel_notes({"hot_pixels": {}}, names) == []
    (three,) = hot_pixel_notes({"hot_pixels": {0: 2, 4: 1, 2: 1}}, names)
    assert three.startswith("images: 4 isolated hot pixel value(s) in 3 image(s) (001.png, 003.png, 005.png) set")
    (four,) = hot_pixel_notes({"hot_pixels": {0: 1, 1: 1, 2: 1, 5: 1}}, names)
    assert "in 4 image(s) (001.png, 002.png, 003.png ...)" in four and "006.png" not in four


def lambert_scene(n: int = 10, size: int = 48) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    normals, mask = sphere(size)
    lights = hemisphere_lights(n, seed=3)
    return render_lambertian(normals, mask, lights), mask, lights


def plant(images: np.ndarray, k: int, y: int, x: int, c: int) -> np.ndarray:
    """``images`` with value (k, y, x, c) far above the level, the pixel's original value made
    the brightest of its neighbours first, so that the clamp gives back the original images."""
    base = images.copy()
    base[k, y, x, c] = base[k, y - 1: y + 2, x - 1: x + 2, c].max()
    hot = base.copy()
    hot[k, y, x, c] = 1e4
    return base, hot


def test_lcnet_and_networks_answer_as_without_the_hot_pixel():
    """A max-pool fusion carries one hot value to every image's light (LCNet's global feature);
    clamped, the answers equal the clean capture's, and the note names the image."""
    from psctl.infer import array_normals
    from psctl.lights import array_lights
    from psctl.models.lcnet import LCNet
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    images, mask, lights = lambert_scene()
    base, hot = plant(images, 3, 24, 20, 1)
    torch.manual_seed(0)
    net = LCNet().double()
    ref = array_lights(base, mask, model=net, config={"views": 1})
    got = array_lights(hot, mask, model=net, config={"views": 1})
    for key in ref.logits:
        np.testing.assert_array_equal(got.logits[key], ref.logits[key])
    assert got.info["hot_pixels"] == {3: 1} and "hot_pixels" not in ref.info
    assert any("1 isolated hot pixel value(s) in 1 image(s) (image 4)" in s for s in got.notes)
    assert not any("hot pixel" in s for s in ref.notes)
    off = array_lights(hot, mask, model=net, config={"views": 1, "exposure_band": None})
    assert off.info["hot_pixels"] == {3: 1}  # without the exposure guard's pass too
    # LCNet's level is the mean over the mask too, not over its crop box (zero around the object)
    mid = base.copy()
    mid[3, 24, 20, 1] = 0.9 * HOT_LEVEL * float(base[3][mask].mean())
    assert "hot_pixels" not in array_lights(mid, mask, model=net, config={"views": 1}).info

    import tempfile

    with tempfile.TemporaryDirectory() as d:
        torch.manual_seed(1)
        w = save_weights(os.path.join(d, "n.pt"), PSFCN(), {"method": "ps-fcn-n", "train_images": 32})
        for config in ({}, {"cache_mb": 0}, {"views": 2}):  # re-read passes clamp the same way
            a = array_normals(base, lights, mask, "ps-fcn-n", w, config)
            b = array_normals(hot, lights, mask, "ps-fcn-n", w, config)
            np.testing.assert_array_equal(a.normals, b.normals)
            assert b.info["hot_pixels"] == {3: 1} and any("(image 4)" in s for s in b.notes)
        # the level is the image's mean over the mask, not over the region around it (zero there)
        region_mean = float(hot[3][:, :, 1].sum() - hot[3, 24, 20, 1]) / mask.size
        mask_mean = float(base[3][mask].mean())
        assert region_mean < 0.8 * mask_mean
        mid = base.copy()
        mid[3, 24, 20, 1] = 0.9 * HOT_LEVEL * mask_mean  # hot against the region's mean only
        c = array_normals(mid, lights, mask, "ps-fcn-n", w)
        assert "hot_pixels" not in c.info and not np.array_equal(c.normals, a.normals)


def test_cli_notes_the_hot_pixel_by_file_name(tmp_path):
    """A float capture (EXR) with one hot value: the report's notes name the file."""
    from psctl.io.images import write_image
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    folder = tmp_path / "hot"
    arrays = write_capture(folder, n=8, size=32, intensities=False)
    names = []
    for k, img in enumerate(arrays["images"]):
        if k == 5:
            img = img.copy()
            img[16, 14, 0] = 1e4
        names.append(f"{k + 1:03d}.exr")
        write_image(folder / names[-1], img, "float")
        (folder / f"{k + 1:03d}.png").unlink()
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    torch.manual_seed(0)
    w = save_weights(tmp_path / "n.pt", PSFCN(), {"method": "ps-fcn-n", "train_images": 32})
    proc = subprocess.run([sys.executable, "-m", "psctl", "normals", str(folder), "-m", "ps-fcn-n", "-w", str(w),
                           "--out", str(tmp_path / "o"), "--json"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    notes = json.loads(proc.stdout)["notes"]
    assert any("hot pixel" in s and "(006.exr)" in s for s in notes), notes
    # psctl info --check finds it too, before any estimate
    proc = subprocess.run([sys.executable, "-m", "psctl", "info", str(folder), "--check", "--json"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    notes = json.loads(proc.stdout)["check"]["notes"]
    hot = [s for s in notes if "hot pixel" in s]
    assert len(hot) == 1 and hot[0].startswith("images: 1 isolated hot pixel value(s) in 1 image(s) (006.exr)")


def test_info_check_counts_inside_the_object_only(tmp_path):
    """``check_pixels`` (psctl info --check): a hot value just outside the mask is not counted,
    one inside is (as the networks see them: zero around the object)."""
    from psctl.io.capture import as_capture, load_mask
    from psctl.io.images import write_image
    from psctl.io.summary import check_pixels

    folder = tmp_path / "c"
    arrays = write_capture(folder, n=4, size=32, intensities=False)
    m = arrays["mask"]
    ys, xs = np.nonzero(m)
    out_y, out_x = 16, int(xs[ys == 16].max()) + 1  # the first pixel right of the object on row 16
    names = []
    for k, img in enumerate(arrays["images"]):
        img = np.where(m[..., None], img, 0.05).astype(np.float32)  # a lit background
        if k == 1:
            img[16, 14, 1] = 1e4  # inside
        if k == 2:
            img[out_y, out_x, 0] = 1e4  # outside
        names.append(f"{k + 1:03d}.exr")
        write_image(folder / names[-1], img, "float")
        (folder / f"{k + 1:03d}.png").unlink()
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    cap = as_capture(folder)
    notes = check_pixels(cap, load_mask(cap))["notes"]
    hot = [s for s in notes if "hot pixel" in s]
    assert len(hot) == 1 and "1 isolated hot pixel value(s) in 1 image(s) (002.exr)" in hot[0], notes
