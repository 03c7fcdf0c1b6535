"""--downsample: the networks on a shrunk capture, normals interpolated back to full size."""

from __future__ import annotations

import json

import numpy as np
import pytest

from psctl.api import run_normals
from psctl.errors import PsctlError
from psctl.eval import run_benchmark
from psctl.hotpixels import clamp_hot_pixels
from psctl.infer import block_mean, check_downsample, run_network, run_views, upsample_normals
from psctl.models import HALO
from psctl.models.weights import save_weights
from tests.conftest import write_capture
from tests.test_ps_fcn import model, scene


def reader_of(images):
    def reader(start, box):
        for k in range(start, len(images)):
            yield images[k][box]
    return reader


@pytest.mark.parametrize("grey", [False, True])
def test_block_mean_is_the_mean_over_the_mask(grey):
    rng = np.random.default_rng(1)
    h, w, k = 7, 10, 3
    img = rng.uniform(0, 1, (h, w) if grey else (h, w, 3)).astype(np.float32)
    mask = rng.uniform(size=(h, w)) < 0.6
    got = block_mean(img, mask, k)
    assert got.shape == ((3, 4) if grey else (3, 4, 3)) and got.dtype == np.float32
    for i in range(3):
        for j in range(4):
            m = mask[i * k:(i + 1) * k, j * k:(j + 1) * k]
            block = img[i * k:(i + 1) * k, j * k:(j + 1) * k]
            want = block[m].mean(0) if m.any() else np.zeros(block.shape[2:])
            np.testing.assert_allclose(got[i, j], want, rtol=1e-6, atol=1e-7)


def test_upsample_reaches_every_mask_pixel_and_only_those():
    rng = np.random.default_rng(2)
    H, W, k = 23, 31, 3
    mask = rng.uniform(size=(H, W)) < 0.3  # scattered: many blocks hold one mask pixel
    small = block_mean(mask.astype(np.float32), np.ones_like(mask), k) > 0
    n0 = np.array([0.2, -0.3, 0.9]) / np.linalg.norm([0.2, -0.3, 0.9])
    normals = np.where(small[..., None], n0, 0.0).astype(np.float32)
    up = upsample_normals(normals, mask, k)
    assert up.shape == (H, W, 3)
    np.testing.assert_allclose(up[mask], np.broadcast_to(n0, (mask.sum(), 3)), atol=1e-6)
    assert not up[~mask].any()


def test_upsample_is_bilinear_between_block_centres():
    """A field linear in the block centres' coordinates comes back linear in the pixels': the
    full-size pixel i sits at (i + 0.5) / k - 0.5 in block units (the frame's last blocks cut)."""
    k, h, w = 4, 6, 5
    yc, xc = np.mgrid[:h, :w].astype(np.float64)
    field = np.stack([0.1 * yc, -0.07 * xc, np.ones_like(yc)], -1).astype(np.float32)
    H, W = h * k - 1, w * k - 3
    up = upsample_normals(field, np.ones((H, W), bool), k)
    Y, X = np.mgrid[:H, :W].astype(np.float64)
    want = np.stack([0.1 * ((Y + 0.5) / k - 0.5), -0.07 * ((X + 0.5) / k - 0.5), np.ones_like(Y)], -1)
    want /= np.linalg.norm(want, axis=-1, keepdims=True)
    inner = (slice(k, H - 2 * k), slice(k, W - 2 * k))  # the frame's edge clamps
    np.testing.assert_allclose(up[inner], want[inner], atol=1e-6)


@pytest.mark.parametrize("normalization,views_", [("none", 1), ("per-channel", 2)])
def test_downsampled_run_is_the_network_on_the_small_capture(normalization, views_):
    """A capture made of k x k blocks (the last row and column of blocks cut by the frame) shrinks
    to the small capture exactly: the result is the network's normals on it, brought back up.
    Tiles small enough to cut the small capture, with --views and +N's two passes."""
    k = 3
    small, lights, _ = scene(4, 21, 26, seed=3)
    mask_s = np.zeros((21, 26), bool)
    mask_s[2:21, 9:26] = True  # reaches the cut blocks
    H, W = 21 * k - 1, 26 * k - 2
    full = np.repeat(np.repeat(small, k, 1), k, 2)[:, :H, :W]
    mask = np.repeat(np.repeat(mask_s, k, 0), k, 1)[:H, :W]
    net = model(double=True)
    cfg = {"views": views_, "tile": 16, "halo": HALO}
    ref = run_views(net, reader_of(small), 4, lights, mask_s, normalization, 3, cfg)
    got = run_views(net, reader_of(full), 4, lights, mask, normalization, 3, {**cfg, "downsample": k})
    np.testing.assert_allclose(got.normals, upsample_normals(ref.normals, mask, k), atol=1e-5)  # float32 block means
    assert got.normals.shape == (H, W, 3) and got.info["downsample"] == k
    assert not got.normals[~mask].any() and (np.linalg.norm(got.normals[mask], axis=-1) > 0.999).all()


def test_upsample_of_an_off_centre_object_is_the_whole_frames():
    """Only the object's box is interpolated: the same as interpolating the whole frame."""
    import torch

    rng = np.random.default_rng(4)
    k, h, w = 3, 30, 40
    small = np.zeros((h, w), bool)
    small[17:26, 22:35] = rng.uniform(size=(9, 13)) < 0.8
    normals = rng.normal(size=(h, w, 3)) + [0, 0, 2]  # facing the camera, as normals do: no near-cancelling mean
    normals = np.where(small[..., None], normals / np.linalg.norm(normals, axis=-1, keepdims=True), 0).astype(np.float32)
    H, W = h * k - 2, w * k - 1
    mask = np.repeat(np.repeat(small, k, 0), k, 1)[:H, :W]
    t = torch.from_numpy(normals).permute(2, 0, 1)[None]
    whole = torch.nn.functional.interpolate(t, size=(h * k, w * k), mode="bilinear", align_corners=False)
    whole = whole[0].permute(1, 2, 0).numpy()[:H, :W].astype(np.float64)
    whole = np.where(mask[..., None], whole / np.linalg.norm(whole, axis=-1, keepdims=True).clip(1e-300), 0)
    np.testing.assert_allclose(upsample_normals(normals, mask, k), whole, atol=1e-5)  # float32 weights


def test_reader_asks_for_the_right_full_size_region():
    """Random images, an object far from the frame's origin (so the crop starts inside it), tiles:
    the same as the network on the whole frame's block means."""
    rng = np.random.default_rng(5)
    k, H, W = 3, 181, 211
    images = rng.uniform(0.1, 1, (3, H, W, 3)).astype(np.float32)
    lights = scene(3)[1]
    yy, xx = np.mgrid[:H, :W]
    mask = ((yy - 140) / 30) ** 2 + ((xx - 160) / 38) ** 2 < 1  # its crop (24 small px around it) starts at (12, 12)
    small_mask = block_mean(mask.astype(np.float32), np.ones_like(mask), k) > 0
    small = np.stack([block_mean(img, mask, k) for img in images])
    net = model(double=True)
    for cfg in ({}, {"tile": 16, "halo": HALO}):
        ref = run_views(net, reader_of(small), 3, lights, small_mask, "none", None, cfg)
        got = run_views(net, reader_of(images), 3, lights, mask, "none", None, {**cfg, "downsample": k})
        np.testing.assert_allclose(got.normals, upsample_normals(ref.normals, mask, k), atol=1e-6)


def test_dark_pixels_and_hot_pixels_are_found_at_full_size():
    """A block mean would hide a dark pixel in its block and dilute a hot one below the clamp's
    level: both are looked for before shrinking, as without it."""
    images, lights, mask = scene(4, 48, 52, seed=6)
    dark_at = np.argwhere(mask)[::37]  # scattered single pixels, black in every image
    images[:, dark_at[:, 0], dark_at[:, 1]] = 0
    net = model(double=True)
    full = run_views(net, reader_of(images), 4, lights, mask, "none", None, {})
    for k in (2, 3):
        res = run_views(net, reader_of(images), 4, lights, mask, "none", None, {"downsample": k})
        np.testing.assert_array_equal(res.dark, full.dark)
        assert res.dark.sum() == len(dark_at) and "hot_pixels" not in res.info
    hot = images.copy()
    y, x = np.argwhere(mask)[len(dark_at) * 20]
    hot[1, y, x] = 1000 * images[1][mask].mean()
    res = run_views(net, reader_of(hot), 4, lights, mask, "none", None, {"downsample": 2})
    assert res.info["hot_pixels"] == {1: 3}  # its three channels
    clamped = hot.copy()
    clamped[1] = clamp_hot_pixels(hot[1], mask)[0]  # the pixel at its neighbours' level
    want = run_views(net, reader_of(clamped), 4, lights, mask, "none", None, {"downsample": 2})
    np.testing.assert_allclose(res.normals, want.normals, atol=1e-6)
    at_full = run_views(net, reader_of(hot), 4, lights, mask, "none", None, {"downsample": 1})
    assert at_full.info["hot_pixels"] == {1: 3}  # full size finds it too


def test_a_factor_that_leaves_too_little_of_the_object_is_refused():
    images, lights, mask = scene(3, 40, 40)  # the mask is about 28 px across
    with pytest.raises(PsctlError, match=r"downsample 8 would leave the object 4 px across .* use at most 3"):
        run_views(model(), reader_of(images), 3, lights, mask, "none", None, {"downsample": 8})


def test_nan_is_refused_as_at_full_size():
    """Outside the mask too (a block mean over the mask would drop it without a word)."""
    images, lights, mask = scene(3, 40, 44)
    images[2, 0, 0] = np.nan
    assert not mask[0, 0]
    for k in (1, 2):
        with pytest.raises(PsctlError, match="image 3 contains NaN"):
            run_views(model(), reader_of(images), 3, lights, mask, "none", None, {"downsample": k})


def test_downsample_one_is_full_size():
    images, lights, mask = scene(3, 30, 34)
    net = model(double=True)
    a = run_views(net, reader_of(images), 3, lights, mask, "none", None, {"downsample": 1}).normals
    b = run_network(net, reader_of(images), 3, lights, mask).normals
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("bad", [0, -2, 1.5, True, "2", None])
def test_downsample_must_be_a_whole_number(bad):
    with pytest.raises(PsctlError, match="downsample must be a whole number >= 1"):
        check_downsample(bad)


def test_folder_runs_report_the_factor(tmp_path):
    folder = tmp_path / "spherePNG"
    write_capture(folder, n=6, size=40)
    weights = save_weights(tmp_path / "w.pt", model(), {"method": "ps-fcn-n", "train_images": 32})
    r = run_normals(folder, method="ps-fcn-n", weights=weights, device="cpu", downsample=2, write=False)
    assert r["downsample"] == 2 and r["mae"] is not None
    r = run_normals(folder, method="l2", downsample=2, write=False)
    assert r["downsample"] == 1 and any("downsample: l2" in n for n in r["notes"])
    from tests.test_cli import cli  # in this process: a subprocess costs seconds of imports per call

    env = {"COLUMNS": "200"}
    proc = cli("normals", str(folder), "--weights", str(weights),
               "--downsample", "0", "--out", str(tmp_path / "o"), env=env)
    assert proc.returncode == 2 and "downsample must be a whole number" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "o").exists()
    proc = cli("eval", "--benchmark", "folder", "--root", str(tmp_path),
               "-m", "ps-fcn-n", "--weights", str(weights), "--device", "cpu", "--downsample", "2",
               "--json", "-q", env=env)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["downsample"] == 2 and out["views"] == 1
    proc = cli("normals", str(folder), "--weights", str(weights),
               "--downsample", "100", "--out", str(tmp_path / "o100"), env=env)
    assert proc.returncode == 2 and "downsample 100 would leave the object 1 px across" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "o100").exists()
    # numpy integers are accepted, and eval.json is still written (JSON has no int64)
    res = run_benchmark("folder", root=tmp_path, method="ps-fcn-n", weights=weights, device="cpu",
                        views=np.int64(2), downsample=np.int64(2), out=tmp_path / "ev")
    saved = json.loads((tmp_path / "ev" / "eval.json").read_text())
    assert saved["views"] == res["views"] == 2 and saved["downsample"] == 2


@pytest.mark.parametrize("cfg", [{}, {"views": 2, "tile": 16}, {"downsample": 3}])
def test_grow_gives_normals_beyond_the_mask_from_the_same_run(cfg):
    """The setting "grow" (the object found without a mask, psctl.api): the network reads the
    mask's pixels only, and its answer is kept also ``grow`` pixels beyond the mask: inside the
    mask the normals of grow 0, unit normals on the ring, 0 beyond; with views and downsampling
    too (downsampled: the small run grows by whole blocks, the full-size result by ``grow``, and
    the edge pixels' interpolation takes in the ring's blocks)."""
    from psctl.infer import check_grow, grow_mask

    images, lights, _ = scene(4, 50, 56, seed=5)
    mask = np.zeros((50, 56), bool)
    mask[9:42, 10:47] = True
    mask[12:15, 10:14] = False  # a notch: the ring fills it
    net = model(double=True)
    base = run_views(net, reader_of(images), 4, lights, mask, "none", 3, cfg)
    got = run_views(net, reader_of(images), 4, lights, mask, "none", 3, {**cfg, "grow": 2})
    ring = grow_mask(mask, 2)
    assert ring.sum() > mask.sum() and not ring.all() and ring[12:15, 10:14].all()
    # (downsampled: the mask's edge pixels interpolate the ring's blocks too)
    inner = mask if "downsample" not in cfg else ~grow_mask(~mask, 2 * cfg["downsample"])
    assert inner.sum() > 0.3 * mask.sum()
    np.testing.assert_allclose(got.normals[inner], base.normals[inner], atol=1e-5)  # float32 block means
    assert (np.linalg.norm(got.normals[ring], axis=-1) > 0.999).all() and not got.normals[~ring].any()
    assert got.info["grow"] == 2 and "grow" not in base.info and not got.dark[~mask].any()
    # the ring's answer ignores its own pixels: other values there change nothing
    noisy = images.copy()
    noisy[:, ring & ~mask] = 5.0
    again = run_views(net, reader_of(noisy), 4, lights, mask, "none", 3, {**cfg, "grow": 2})
    np.testing.assert_allclose(again.normals, got.normals, atol=1e-6)
    assert check_grow(0) == 0 and grow_mask(mask, 0) is mask


@pytest.mark.parametrize("bad", [-1, 1.5, True, "2", HALO + 1])
def test_grow_must_be_whole_pixels_within_the_halo(bad):
    from psctl.infer import check_grow

    with pytest.raises(PsctlError, match="grow must be a whole number of pixels"):
        check_grow(bad)
