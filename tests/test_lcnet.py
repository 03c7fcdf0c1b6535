"""LCNet, light estimation (psctl lights), sdps (LCNet + PS-FCN†) and their training.

The networks have seeded random weights (or a few training steps): what is tested here is the
architecture, the discretisation, the streaming pipeline, the files and the commands, none of
which depends on trained weights.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from psctl.errors import PsctlError
from psctl.lights import array_lights, intensity_error, lights_plot, run_lcnet, write_light_files
from psctl.models.lcnet import (LCNet, angles_to_dirs, classes_to_dirs, classes_to_ints, classification_loss,
                                decode, dirs_to_angles, dirs_to_classes, ints_to_classes,
                                resize_inputs)
from psctl.models.ps_fcn import PSFCN
from psctl.models.weights import file_sha256, load_network, read_weights, save_weights
from psctl.symmetry import SYMMETRIES, transform_dirs, transform_images, untransform_dirs
from tests.conftest import random_biases, write_capture, weights_in
from tests.test_cli import cli

REPO = Path(__file__).resolve().parents[1]

# The authors' release (SDPS-Net models/LCNet.py: mask in, 36 direction and 20 intensity classes).
OFFICIAL = {
    **{f"featExtractor.conv{i}.0.weight": s for i, s in
       enumerate([(64, 4, 3, 3), (128, 64, 3, 3), (128, 128, 3, 3), (128, 128, 3, 3), (128, 128, 3, 3),
                  (256, 128, 3, 3), (256, 256, 3, 3)], 1)},
    **{f"featExtractor.conv{i}.0.bias": (c,) for i, c in enumerate([64, 128, 128, 128, 128, 256, 256], 1)},
    "classifier.conv1.0.weight": (256, 512, 3, 3), "classifier.conv1.0.bias": (256,),
    **{f"classifier.conv{i}.0.weight": (256, 256, 3, 3) for i in (2, 3, 4)},
    **{f"classifier.conv{i}.0.bias": (256,) for i in (2, 3, 4)},
    **{f"classifier.{h}.0.0.weight": (64, 256, 1, 1) for h in ("dir_x_est", "dir_y_est", "int_est")},
    **{f"classifier.{h}.0.0.bias": (64,) for h in ("dir_x_est", "dir_y_est", "int_est")},
    "classifier.dir_x_est.1.0.weight": (36, 64, 1, 1), "classifier.dir_x_est.1.0.bias": (36,),
    "classifier.dir_y_est.1.0.weight": (36, 64, 1, 1), "classifier.dir_y_est.1.0.bias": (36,),
    "classifier.int_est.1.0.weight": (20, 64, 1, 1), "classifier.int_est.1.0.bias": (20,),
}


def lcnet(seed: int = 0, **config) -> LCNet:
    torch.manual_seed(seed)
    return LCNet(config).eval()


def psctl(*args, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "psctl.cli", *map(str, args)], capture_output=True, text=True,
                          env={**os.environ, "COLUMNS": "100", **(env or {})})


# --- architecture -----------------------------------------------------------------------------

def test_parameter_count_and_official_names():
    net = lcnet()
    assert sum(p.numel() for p in net.parameters()) == 4_409_692  # "about 4.41 M"
    assert {k: tuple(v.shape) for k, v in net.state_dict().items()} == OFFICIAL


def test_shapes_and_size_limit():
    net = lcnet()
    out = net(torch.rand(2, 5, 3, 128, 128), torch.ones(2, 1, 128, 128))
    assert {k: tuple(v.shape) for k, v in out.items()} == {"dir_x": (2, 5, 36), "dir_y": (2, 5, 36), "ints": (2, 5, 20)}
    assert net.extract(torch.rand(3, 4, 128, 128)).shape == (3, 256, 8, 8)
    with pytest.raises(ValueError, match="at most 128"):
        net(torch.rand(1, 2, 3, 256, 256), torch.ones(1, 1, 256, 256))


def test_global_feature_is_order_invariant():
    """Permuting the images permutes the per-image outputs and nothing else."""
    net = lcnet().double()
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 7, 3, 64, 64, generator=g, dtype=torch.float64)
    m = (torch.rand(1, 1, 64, 64, generator=g) > 0.2).double()
    perm = torch.randperm(7, generator=g)
    with torch.no_grad():
        a, b = net(x, m), net(x[:, perm], m)
    for k in a:
        torch.testing.assert_close(a[k][:, perm], b[k], atol=1e-10, rtol=0)


# --- discretisation ---------------------------------------------------------------------------

unit_front = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0.05, 1)).filter(
    lambda v: math.hypot(*v) > 0.1).map(lambda v: np.asarray(v) / math.hypot(*v))


@settings(max_examples=200, deadline=None)
@given(unit_front)
def test_direction_round_trip_within_half_a_bin(d):
    t = torch.tensor(d, dtype=torch.float64)
    theta, phi = dirs_to_angles(t)
    back = classes_to_dirs(*dirs_to_classes(t, 36), 36)
    theta2, phi2 = dirs_to_angles(back)
    # class centres are float32: allow its rounding on top of half a bin (2.5 degrees)
    assert abs(float(theta2 - theta)) <= 2.5 + 1e-4 and abs(float(phi2 - phi)) <= 2.5 + 1e-4
    assert abs(float(back.norm()) - 1) < 1e-6 and float(back[2]) > 0
    torch.testing.assert_close(angles_to_dirs(theta, phi), t)  # the angles describe the direction


@settings(max_examples=200, deadline=None)
@given(st.floats(0.2, 2.0))
def test_intensity_round_trip_within_half_a_bin(e):
    back = classes_to_ints(ints_to_classes(torch.tensor(e, dtype=torch.float64), 20), 20)
    assert abs(float(back) - e) <= 0.9 / 20 + 1e-6


def test_classes_decode_to_themselves():
    k = torch.arange(36)
    cx, cy = dirs_to_classes(classes_to_dirs(k, k.flip(0), 36), 36)
    assert (cx == k).all() and (cy == k.flip(0)).all()
    assert (ints_to_classes(classes_to_ints(torch.arange(20), 20), 20) == torch.arange(20)).all()
    # bin edges: (angle + 90) / 180 * K, clamped
    assert dirs_to_classes(torch.tensor([0.0, 0.0, 1.0]), 36)[0] == 18
    assert ints_to_classes(torch.tensor([0.1, 0.2, 2.0, 3.0]), 20).tolist() == [0, 0, 19, 19]
    # the ends, exactly: +-90 degrees (a light at (1, 0, 0) or (0, 1, 0)) is the last or first
    # class, never class K (cross-entropy would fail on it, decoding would give 92.5 degrees)
    from psctl.models.lcnet import angles_to_classes

    assert angles_to_classes(torch.tensor([-90.0, 90.0, -100.0, 100.0]), 36).tolist() == [0, 35, 0, 35]
    edge = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    cx, cy = dirs_to_classes(edge, 36)
    assert cx.tolist() == [35, 18, 0, 18] and cy.tolist() == [18, 35, 18, 0]


def test_resized_inputs_are_black_outside_the_mask():
    """LCNet was trained on images zeroed outside the mask after resizing (an antialiased shrink
    blurs the object's edge into the background): checked on the data, not with the function itself."""
    yy, xx = np.mgrid[:200, :200]
    disc = torch.from_numpy(((yy - 100) ** 2 + (xx - 100) ** 2 < 70 ** 2).astype(np.float32))[None, None]
    x, m = resize_inputs(torch.ones(2, 3, 200, 200), disc.expand(2, 1, 200, 200), 128)
    assert x.shape == (2, 3, 128, 128) and m.shape == (2, 1, 128, 128)
    assert set(m.unique().tolist()) == {0.0, 1.0}
    assert (x[m.expand_as(x) == 0] == 0).all() and (x[m.expand_as(x) == 1] > 0.99).all()
    assert 0.2 < float(m.mean()) < 0.5  # the disc (pi 0.35^2 = 0.38 of the frame), not all or nothing


def test_soft_argmax_decoding():
    logits = {"dir_x": torch.full((2, 36), -30.0), "dir_y": torch.full((2, 36), -30.0), "ints": torch.full((2, 20), -30.0)}
    logits["dir_x"][0, 18] = logits["dir_y"][0, 18] = logits["ints"][0, 5] = 30.0  # confident: as argmax
    for key, (i, j) in (("dir_x", (20, 21)), ("dir_y", (10, 11)), ("ints", (3, 4))):
        logits[key][1, [i, j]] = 30.0  # two equal classes: soft-argmax lands on their shared edge
    d_arg, e_arg = decode(logits)
    d_soft, e_soft = decode(logits, mode="soft")
    torch.testing.assert_close(d_soft[0], d_arg[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(e_soft[0], e_arg[0], atol=1e-5, rtol=0)
    theta, phi = dirs_to_angles(d_soft[1])
    assert float(theta) == pytest.approx(21 * 5 - 90, abs=1e-3) and float(phi) == pytest.approx(11 * 5 - 90, abs=1e-3)
    assert float(e_soft[1]) == pytest.approx(0.2 + 4 * 0.09, abs=1e-4)
    with pytest.raises(ValueError, match="decoding"):
        decode(logits, mode="median")


def test_argmax_decoding_keeps_the_heads_apart():
    """dir_x is azimuth and dir_y elevation: a light up and to the right of the view axis."""
    logits = {"dir_x": torch.full((1, 36), -30.0), "dir_y": torch.full((1, 36), -30.0), "ints": torch.full((1, 20), -30.0)}
    logits["dir_x"][0, 27] = logits["dir_y"][0, 21] = logits["ints"][0, 7] = 30.0
    for mode in ("argmax", "soft"):
        d, e = decode(logits, mode=mode)
        theta, phi = dirs_to_angles(d[0])
        assert float(theta) == pytest.approx(27.5 * 5 - 90, abs=1e-3)  # the bin centre: 47.5 degrees
        assert float(phi) == pytest.approx(21.5 * 5 - 90, abs=1e-3)  # 17.5 degrees
        assert float(d[0, 0]) > float(d[0, 1]) > 0 and float(e[0]) == pytest.approx(0.2 + 7.5 * 0.09, abs=1e-4)


def test_loss_is_cross_entropy_on_the_three_heads():
    dirs = torch.nn.functional.normalize(torch.tensor([[0.3, -0.2, 1.0], [-0.5, 0.4, 0.7]]), dim=-1)
    ints = torch.tensor([0.5, 1.7])
    uniform = {"dir_x": torch.zeros(2, 36), "dir_y": torch.zeros(2, 36), "ints": torch.zeros(2, 20)}
    total, terms = classification_loss(uniform, dirs, ints)
    assert float(total) == pytest.approx(2 * math.log(36) + math.log(20), rel=1e-6)
    cx, cy = dirs_to_classes(dirs, 36)
    right = {k: v.clone() for k, v in uniform.items()}
    right["dir_x"][torch.arange(2), cx] = right["dir_y"][torch.arange(2), cy] = 50.0
    right["ints"][torch.arange(2), ints_to_classes(ints, 20)] = 50.0
    assert float(classification_loss(right, dirs, ints)[0]) < 1e-6


# --- the light-estimation pipeline ------------------------------------------------------------

def scene(n: int = 11, h: int = 50, w: int = 70, seed: int = 0):
    rng = np.random.default_rng(seed)
    images = rng.uniform(0, 0.5, (n, h, w, 3)).astype(np.float32)
    yy, xx = np.mgrid[:h, :w]
    mask = (yy - 0.5 * h) ** 2 + (xx - 0.45 * w) ** 2 < (0.4 * h) ** 2
    return images, mask


def all_at_once(net: LCNet, images: np.ndarray, mask: np.ndarray, margin: int = 15, square: bool = False) -> dict:
    """The straightforward computation: crop, (pad to a square,) resize every image, one forward pass."""
    from psctl.arrays import bounding_box
    from psctl.lights import pad_square

    box = bounding_box(mask, margin)
    dtype = next(net.parameters()).dtype
    x = torch.from_numpy(images[:, box[0], box[1]] * mask[box][..., None]).permute(0, 3, 1, 2).to(dtype)
    m = torch.from_numpy(mask[box].astype(np.float32))[None, None].to(dtype).expand(len(images), 1, *x.shape[-2:])
    if square:
        x, m = pad_square(x), pad_square(m)
    x, m = resize_inputs(x, m, 128)
    with torch.no_grad():
        return {k: v[0].numpy() for k, v in net(x[None], m[:1]).items()}


def test_square_crop_pads_instead_of_stretching():
    """``square``: the crop is zero-padded to a square, centred, before resizing."""
    from psctl.lights import pad_square

    x = torch.ones(2, 3, 6, 10)
    y = pad_square(x)
    assert y.shape == (2, 3, 10, 10) and float(y.sum()) == float(x.sum())
    assert (y[..., :2, :] == 0).all() and (y[..., 8:, :] == 0).all() and (y[..., 2:8, :] == 1).all()
    assert pad_square(x.transpose(-1, -2)).shape == (2, 3, 10, 10)
    net = lcnet().double()
    images, mask = scene(h=24, w=40)
    ref = all_at_once(net, images, mask, square=True)
    est = array_lights(images, mask, model=net, config={"views": 1, "square": True})
    for k in ref:
        np.testing.assert_allclose(est.logits[k], ref[k], atol=1e-6, rtol=0)
    stretched = array_lights(images, mask, model=net, config={"views": 1})
    assert not np.allclose(stretched.logits["dir_x"], est.logits["dir_x"])


def test_streamed_and_chunked_equal_all_at_once():
    net = lcnet().double()
    images, mask = scene()
    ref = all_at_once(net, images, mask)
    for config in ({}, {"chunk": 3, "cache_mb": 0}, {"chunk": 4, "cache_mb": 5 * 256 * 64 * 8 / 2**20}):
        est = array_lights(images, mask, model=net, config={**config, "views": 1})
        for k in ref:
            np.testing.assert_allclose(est.logits[k], ref[k], atol=1e-6, rtol=0)  # logits are returned as float32
    assert est.info["passes"] == 3 and est.info["cached_features"] == 5  # the exposure read, pass 1, pass 2
    assert est.directions.shape == (11, 3) and est.intensities.shape == (11,)
    np.testing.assert_allclose(np.linalg.norm(est.directions, axis=1), 1, atol=1e-6)


def test_mean_fused_lcnet_streams_exactly():
    """A mean-fused LCNet (``fuse: mean``) streamed and chunked gives the all-at-once logits. The
    biases are random: with a fresh network's zero biases a wrong scale of the mean (over n - 1
    images, say) would not change the logits (a mutation audit)."""
    net = random_biases(lcnet(fuse="mean").double())
    images, mask = scene()
    ref = all_at_once(net, images, mask)
    for config in ({}, {"chunk": 3, "cache_mb": 0}, {"chunk": 4, "cache_mb": 5 * 256 * 64 * 8 / 2**20}):
        est = array_lights(images, mask, model=net, config={**config, "views": 1})
        for k in ref:
            np.testing.assert_allclose(est.logits[k], ref[k], atol=1e-6, rtol=0)


def test_pipeline_reads_each_image_once_when_the_features_fit():
    net = lcnet()
    images, mask = scene(n=6)
    calls = []

    def reader(start, box):
        calls.append(start)
        for k in range(start, len(images)):
            yield images[k][box]

    run_lcnet(net, reader, 6, mask)
    assert calls == [0]
    calls.clear()
    run_lcnet(net, reader, 6, mask, {"cache_mb": 0})
    assert calls == [0, 0, 0]  # the exposure's pass, pass 1, pass 2: nothing kept
    calls.clear()
    run_lcnet(net, reader, 6, mask, {"cache_mb": 0, "exposure_band": None})
    assert calls == [0, 0]
    with pytest.raises(PsctlError, match="expected 7 images"):
        run_lcnet(net, reader, 7, mask)


def test_exposure_guard_scales_only_captures_outside_the_band():
    """A capture far darker or brighter than LCNet's training exposures is seen at the target
    mean; one inside the band is seen as it is (identical logits with the guard off)."""
    net = lcnet()
    images, mask = scene(n=6)
    m = float(images[:, mask].mean())
    base = array_lights(images, mask, model=net, config={"views": 1, "exposure_band": (m / 2, m * 2)})
    off = array_lights(images, mask, model=net, config={"views": 1, "exposure_band": None})
    assert base.info["exposure"] == 1.0 and not [n for n in base.notes if "exposure" in n]  # (6 images: the few note)
    for k in base.logits:
        np.testing.assert_array_equal(base.logits[k], off.logits[k])
    band = {"views": 1, "exposure_band": (m / 2, m * 2), "exposure_target": m}
    bright = array_lights(images * 40, mask, model=net, config=band)
    dark = array_lights(images / 40, mask, model=net, config=band)
    for est in (bright, dark):
        assert est.info["exposure"] != 1.0 and "outside the exposures LCNet was trained on" in est.notes[0]
        for k in base.logits:  # the same images as at the target (the resized mean is within 1 %)
            np.testing.assert_allclose(est.logits[k], off.logits[k], atol=0.05 * np.abs(off.logits[k]).max())


def test_exposure_guard_reads_the_mean_inside_the_mask_only():
    """Bright background outside the mask (and LCNet without a mask channel) does not move it."""
    images, mask = scene(n=6)
    images = images * 0.1  # inside: mean 0.025, in the band
    images[:, ~mask] = 0.9
    for net in (lcnet(), lcnet(in_mask=False)):
        est = array_lights(images, mask, model=net, config={"views": 1})
        assert est.info["exposure"] == 1.0, net.config


def test_exposure_guard_without_a_mask_reads_the_lit_pixels(tmp_path):
    """No mask: the guard's mean is over the lit pixels (infer.lit_pixels), so a dark background
    beside a capture inside the band does not push it out (the frame's mean would be a third)."""
    images, mask = scene(n=6)
    images = images * 0.1
    m = float(images[:, mask].mean())
    images[:, ~mask] = np.random.default_rng(2).uniform(0, 0.001, images[:, ~mask].shape)
    assert images.mean() < m * 0.7  # the frame's mean: outside the band below
    band = {"views": 1, "exposure_band": (m * 0.7, m * 1.5)}
    est = array_lights(images, None, model=lcnet(), config=band)
    assert est.info["exposure"] == 1.0, est.notes
    # a mask that covers the frame is a mask: the frame's mean, below the band
    est = array_lights(images, np.ones_like(mask), model=lcnet(), config=band)
    assert est.info["exposure"] > 1.0 and "mean inside the mask" in est.notes[0]
    with pytest.raises(PsctlError, match="exposure_pixels"):
        array_lights(images, mask, model=lcnet(), config={"exposure_pixels": "all"})
    # and a capture that is outside it still is scaled
    est = array_lights(images / 40, None, model=lcnet(), config=band)
    assert est.info["exposure"] != 1.0 and "mean over the lit pixels" in est.notes[0]
    # a folder without mask.png, as the array API without a mask
    from psctl.io.capture import load_mask, open_capture
    from psctl.io.images import write_image
    from psctl.lights import capture_lights

    folder = tmp_path / "obj"
    folder.mkdir()
    for k, img in enumerate(images):
        write_image(folder / f"{k + 1:03d}.exr", img, "float", kind="linear")
    save_weights(tmp_path / "lcnet.pt", lcnet(), {"method": "lcnet", "train_images": 32})
    cap = open_capture(folder)
    est = capture_lights(cap, load_mask(cap), tmp_path / "lcnet.pt", band)
    assert est.info["exposure"] == 1.0, est.notes


def test_intensity_error_is_scale_invariant_and_colour_blind():
    gt = np.array([[1.0, 0.9, 0.8], [2.0, 1.8, 1.6], [0.5, 0.45, 0.4]])  # one light colour, 3 strengths
    assert intensity_error(3.0 * np.array([1.0, 2.0, 0.5]), gt) == pytest.approx(0.0, abs=1e-12)
    assert intensity_error(np.array([1.0, 1.0, 1.0]), gt) > 0.1


def test_light_files_and_plot(tmp_path):
    from psctl.io.capture import read_intensities, read_lights
    from psctl.io.images import read_image
    from psctl.lights import write_lights_plot

    d = np.array([[0.1, 0.2, 0.97], [-0.5, 0.3, 0.81], [0.0, -0.6, 0.8]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    e = np.array([0.5, 1.25, 1.9])
    write_light_files(tmp_path, d, e)
    np.testing.assert_allclose(read_lights(tmp_path / "light_directions.txt"), d, atol=1e-6)
    np.testing.assert_allclose(read_intensities(tmp_path / "light_intensities.txt"), np.repeat(e[:, None], 3, 1), atol=1e-6)
    write_lights_plot(tmp_path / "lights.png", d, e, d[::-1], light_mae=12.5)
    pixels, info = read_image(tmp_path / "lights.png")
    assert info.bits == 8 and pixels.shape[2] == 3
    # x right, y up: the light pointing down-ish (y < 0) is drawn below the centre
    canvas = lights_plot(d[2:], e[2:], radius=100)
    hot = np.argwhere(np.abs(canvas - lights_plot(d[:0], e[:0], radius=100)).sum(-1) > 0)
    centre_row = 40 + (2 * (100 + 12)) / 2  # lights_plot: 40 rows of title and colour bar name above the disk
    assert hot[:, 0].mean() > centre_row + 50
    # the legend under the disk names the rings only when there is ground truth
    with_gt, without = lights_plot(d, e, d, radius=100), lights_plot(d, e, radius=100)
    assert with_gt.shape == without.shape and (with_gt[-28:] != without[-28:]).any()
    from psctl.io.report import text_bitmap

    long = "A_LONG_OBJECT_NAME_OF_A_SYNTHETIC_SET: LIGHT DIRECTION MAE 12.34°"
    assert lights_plot(d, e, title=long, radius=100).shape[1] >= text_bitmap(long, 2).shape[1]  # the title fits
    # the intensity bar marks 1.0 (nominal) and says where intensities were clipped to its ends
    from tests.test_io import _text_at

    assert _text_at(without, "1.0", 2) and _text_at(without, "2.0", 2) and not _text_at(without, ">2.0", 2)
    clipped = lights_plot(d, np.array([0.1, 1.0, 2.5]), radius=100)
    assert _text_at(clipped, ">2.0", 2) and _text_at(clipped, "<0.2", 2)
    # coloured relative to the intensities' mean (LCNet's scale is arbitrary): three times brighter
    # lights look the same, and one of the mean intensity is drawn in the bar's 1.0 colour
    assert np.array_equal(lights_plot(d, 3 * e, radius=100), without)
    from psctl.io.report import jet

    one = lights_plot(d[:1], np.array([4.0]), radius=100)
    centre = (int(round(40 + 112 - d[0, 1] * 100)), int(round(112 + d[0, 0] * 100)))
    np.testing.assert_allclose(one[centre], jet(np.array((1.0 - 0.2) / 1.8)), atol=1e-6)
    assert _text_at(without, "ESTIMATE, COLOUR: INTENSITY / MEAN", 2)
    # the rings are labelled with their angle from the view axis (grey ink)
    grey = (np.abs(without - 0.6) < 1e-6).all(-1)
    for label in ("30°", "60°"):
        bm = text_bitmap(label, 2)
        assert any(np.array_equal(grey[y:y + bm.shape[0], x:x + bm.shape[1]] & bm, bm)
                   for y in range(grey.shape[0] - bm.shape[0]) for x in range(grey.shape[1] - bm.shape[1])), label
    # ... whole even under a rig like DiLiGenT's, whose lights covered the 30-degree label (a QA finding)
    gx, gy = np.meshgrid(np.linspace(-0.5, 0.5, 12), np.linspace(-0.45, 0.45, 8))
    rig = np.stack([gx.ravel(), gy.ravel(), np.ones(96)], 1)
    rig /= np.linalg.norm(rig, axis=1, keepdims=True)
    busy = lights_plot(rig, np.ones(96), rig, radius=100)
    grey = (np.abs(busy - 0.6) < 1e-6).all(-1)
    bm = text_bitmap("30°", 2)
    assert any(np.array_equal(grey[y:y + bm.shape[0], x:x + bm.shape[1]] & bm, bm)
               for y in range(grey.shape[0] - bm.shape[0]) for x in range(grey.shape[1] - bm.shape[1]))


# --- weights files ----------------------------------------------------------------------------

def test_weights_round_trip_and_official_checkpoint(tmp_path):
    net = lcnet(3)
    save_weights(tmp_path / "lcnet.pt", net, {"method": "lcnet", "train_images": 32})
    w = read_weights(tmp_path / "lcnet.pt")
    assert w.method == "lcnet" and w.kind == "lcnet" and w.metadata["architecture"]["size"] == 128
    loaded, _, _ = load_network("lcnet", tmp_path / "lcnet.pt")
    x = torch.rand(1, 3, 3, 128, 128)
    with torch.no_grad():
        torch.testing.assert_close(loaded(x, torch.ones(1, 1, 128, 128)), net(x, torch.ones(1, 1, 128, 128)))
    # the authors' release: {'state_dict': ..., 'model': 'LCNet'}, loaded with weights_only
    torch.save({"state_dict": net.state_dict(), "model": "LCNet"}, tmp_path / "LCNet_CVPR2019.pth.tar")
    w = read_weights(tmp_path / "LCNet_CVPR2019.pth.tar")
    assert w.official and w.method == "lcnet"
    load_network("lcnet", w.path)
    bad = dict(net.state_dict())
    bad.pop("classifier.int_est.1.0.bias")
    bad["classifier.dir_x_est.1.0.weight"] = torch.zeros(30, 64, 1, 1)
    torch.save({"state_dict": bad}, tmp_path / "bad.pth.tar")
    with pytest.raises(PsctlError, match="LCNet architecture.*missing keys: classifier.int_est.1.0.bias.*wrong shapes"):
        load_network("lcnet", tmp_path / "bad.pth.tar")
    # an LCNet file is not a normal-estimation network, and vice versa
    with pytest.raises(PsctlError, match="LCNet"):
        load_network("ps-fcn", tmp_path / "lcnet.pt")
    save_weights(tmp_path / "psfcn.pt", PSFCN(), {"method": "ps-fcn", "train_images": 32})
    with pytest.raises(PsctlError, match="cannot run as lcnet"):
        load_network("lcnet", tmp_path / "psfcn.pt")


# --- commands ---------------------------------------------------------------------------------

def test_lights_command(tmp_path, fake_weights):
    data = write_capture(tmp_path / "ballPNG", n=8, size=48)
    out = tmp_path / "out"
    proc = cli("lights", tmp_path / "ballPNG", "--weights", fake_weights / "lcnet.pt", "--out", out, "--json",
                 "--device", "cpu")
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert {"object", "n_images", "light_mae", "intensity_re", "outputs"} <= set(r)
    assert r["object"] == "ball" and r["n_images"] == 8
    assert 0 <= r["light_mae"] <= 180 and r["intensity_re"] >= 0
    assert sorted(os.listdir(out)) == [".psctl-lights", "light_directions.txt", "light_intensities.txt", "lights.png",
                                       "lights_report.json"]
    assert set(r["outputs"]) == {"light_directions", "light_intensities", "lights", "report"}
    # the folder says what made its light files: the report file is what --json printed
    assert json.loads((out / "lights_report.json").read_text()) == r
    assert r["outputs"]["report"] == str(out / "lights_report.json")
    assert r["provenance"]["weights"]["lcnet"]["sha256"] == file_sha256(fake_weights / "lcnet.pt")
    est = np.loadtxt(out / "light_directions.txt")
    from psctl.metrics import light_direction_error

    assert light_direction_error(est, data["lights"]).mean() == pytest.approx(r["light_mae"], abs=1e-5)
    assert r["views"] == 8 and r["decode"] == "soft"
    proc = cli("lights", tmp_path / "ballPNG", "--weights", fake_weights / "lcnet.pt", "--out", tmp_path / "v3",
                 "--views", "3")
    assert proc.returncode == 2 and "views" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "v3").exists()
    # never over the inputs; the capture folder keeps its own light files
    before = (tmp_path / "ballPNG" / "light_directions.txt").read_text()
    proc = cli("lights", tmp_path / "ballPNG", "--weights", fake_weights / "lcnet.pt", "--out", tmp_path / "ballPNG")
    assert proc.returncode == 2 and "never overwritten" in proc.stderr
    assert (tmp_path / "ballPNG" / "light_directions.txt").read_text() == before
    # a same-named file of the user's is replaced with a note; psctl lights' own, from a run before, silently
    from psctl.lights import run_lights

    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "lights.png").write_bytes(b"my plot")
    kw = dict(weights=fake_weights / "lcnet.pt", out=tmp_path / "mine", device="cpu", views=1, refine=False)
    notes = run_lights(tmp_path / "ballPNG", **kw)["notes"]
    assert [n for n in notes if n.startswith("outputs:")] == [
        f"outputs: replaced lights.png in {tmp_path / 'mine'}, which no earlier psctl lights run there had listed"]
    assert not any(n.startswith("outputs:") for n in run_lights(tmp_path / "ballPNG", **kw)["notes"])
    # psctl calibrate's files (it defaults to PATH/psctl too) are named as its, with the ones that stay
    # beside the new lights (its report describes the replaced ones; helper-159)
    cal = tmp_path / "cal"
    cal.mkdir()
    files = ("light_directions.txt", "lights.png", "sphere.png", "calibration_report.json")
    for n in files:
        (cal / n).write_bytes(b"calibrate's")
    (cal / ".psctl-calibrate").write_text("".join(f"{n}\n" for n in files))
    notes = run_lights(tmp_path / "ballPNG", **{**kw, "out": cal})["notes"]
    assert [n for n in notes if n.startswith("outputs:")] == [
        f"outputs: replaced light_directions.txt, lights.png in {cal}, written there by an earlier psctl calibrate "
        "run (its sphere.png, calibration_report.json stay)"], notes
    # and once more after calibrate wrote there again: the newer list owns the files both name
    # (lights, calibrate, lights replaced the calibrated directions without a word; helper-161)
    (cal / "light_directions.txt").write_bytes(b"calibrate's again")
    (cal / ".psctl-calibrate").write_text("light_directions.txt\nsphere.png\ncalibration_report.json\n")
    later = os.stat(cal / ".psctl-lights").st_mtime_ns + 10**9
    os.utime(cal / ".psctl-calibrate", ns=(later, later))
    notes = run_lights(tmp_path / "ballPNG", **{**kw, "out": cal})["notes"]
    assert [n for n in notes if n.startswith("outputs:")] == [
        f"outputs: replaced light_directions.txt in {cal}, written there by an earlier psctl calibrate run (its "
        "sphere.png, calibration_report.json stay)"], notes


def test_missing_weights_are_one_clear_line(tmp_path, capture):
    env = {"PSCTL_WEIGHTS": str(tmp_path / "none")}
    for args, needles in ((["lights", capture], ["lcnet", "psctl train lcnet", "docs/training.md"]),
                          (["normals", capture, "--method", "sdps"], ["lcnet.pt", "ps_fcn_dagger.pt", f"{tmp_path / 'none' / 'ps_fcn.pt'} and",
                                                                  "ps_fcn_n.pt", "docs/training.md"])):
        proc = cli(*args, env=env)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1
        assert all(n in proc.stderr for n in needles), proc.stderr
    (capture / "light_directions.txt").unlink()  # uncalibrated: auto means sdps
    proc = cli("normals", capture, env=env)
    assert proc.returncode == 2 and "sdps" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    # LCNet alone installed: the error named only PS-FCN† (an audit), though PS-FCN or PS-FCN+N would do
    (tmp_path / "lc").mkdir()
    save_weights(tmp_path / "lc" / "lcnet.pt", lcnet(), {"method": "lcnet", "train_images": 32})
    proc = cli("normals", capture, env={"PSCTL_WEIGHTS": str(tmp_path / "lc")})
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert all(f"{tmp_path / 'lc' / n}" in proc.stderr for n in ("ps_fcn_dagger.pt", "ps_fcn.pt", "ps_fcn_n.pt"))
    assert "needs a normals network after LCNet" in proc.stderr and "--weights FILE: psctl's PS-FCN†" in proc.stderr
    assert "a GPU is needed" in proc.stderr


def test_sdps_runs_lcnet_then_ps_fcn_dagger(tmp_path, fake_weights):
    from psctl.api import run_normals
    from psctl.eval import run_benchmark

    write_capture(tmp_path / "root" / "aPNG", n=6, size=40, seed=1)
    write_capture(tmp_path / "root" / "bPNG", n=6, size=40, seed=2)
    with weights_in(fake_weights):
        r = run_normals(tmp_path / "root" / "aPNG", method="sdps", out=tmp_path / "o", device="cpu")
        assert r["method"] == "sdps" and any("LCNet" in n and "PS-FCN†" in n for n in r["notes"])
        assert r["light_mae"] is not None and r["intensity_re"] is not None and r["mae"] is not None
        assert json.loads((tmp_path / "o" / "report.json").read_text())["light_mae"] == pytest.approx(r["light_mae"])
        res = run_benchmark("folder", root=tmp_path / "root", method="sdps", device="cpu")
        assert [o["name"] for o in res["objects"]] == ["a", "b"]
        assert res["mean_light_mae"] == pytest.approx(np.mean([o["light_mae"] for o in res["objects"]]))
        assert res["mean_intensity_re"] == pytest.approx(np.mean([o["intensity_re"] for o in res["objects"]]))
        # --weights names the PS-FCN† file; an LCNet file there is refused clearly
        with pytest.raises(PsctlError, match="LCNet"):
            run_normals(tmp_path / "root" / "aPNG", method="sdps", weights=fake_weights / "lcnet.pt", write=False)


def test_sdps_normals_write_the_lights_they_came_from(tmp_path, fake_weights, monkeypatch):
    """psctl normals -m sdps writes the lights its normals were estimated from (DiLiGenT's format,
    names of their own, never psctl lights' files in the same folder) and their picture; with an
    --images subset the images they belong to; a later run without them removes them with a note."""
    from psctl.api import run_normals
    from psctl.io.capture import holds_capture, open_capture, read_intensities, read_lights
    from psctl.io.images import read_image
    from psctl.lights import SDPS_FILES, run_lights

    write_capture(tmp_path / "aPNG", n=6, size=40, seed=1)
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    out = tmp_path / "aPNG" / "psctl"
    run_lights(tmp_path / "aPNG", device="cpu", views=1)  # psctl lights' files, in the same folder
    before = {n: (out / n).read_bytes() for n in ("light_directions.txt", "light_intensities.txt", "lights.png")}
    r = run_normals(tmp_path / "aPNG", method="sdps", device="cpu")
    assert {n: (out / n).read_bytes() for n in before} == before  # untouched
    keys = {"light_directions_estimated", "light_intensities_estimated", "lights_estimated"}
    assert keys <= set(r["outputs"]) and "light_images_estimated" not in r["outputs"]
    assert all(Path(r["outputs"][k]).name == SDPS_FILES[k.removesuffix("_estimated")] for k in keys)
    d = read_lights(out / SDPS_FILES["light_directions"])
    e = read_intensities(out / SDPS_FILES["light_intensities"])
    assert d.shape == (6, 3) and e.shape == (6, 3) and (e > 0).all()
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1, atol=1e-6)
    # the lights the report scores: its light_mae is theirs against the folder's own
    cap = open_capture(tmp_path / "aPNG")
    ang = np.degrees(np.arccos(np.clip((d * cap.lights).sum(-1) / np.linalg.norm(cap.lights, axis=-1), -1, 1)))
    assert ang.mean() == pytest.approx(r["light_mae"], abs=1e-4)
    assert read_image(out / SDPS_FILES["lights"])[0].shape[2] == 3
    assert not holds_capture(out)  # the picture is no image of a capture
    # an --images subset: the rows belong to the images listed
    r = run_normals(tmp_path / "aPNG", method="sdps", device="cpu", n_images=4, out=tmp_path / "sub")
    listed = (tmp_path / "sub" / SDPS_FILES["light_images"]).read_text().split()
    assert len(listed) == 4 and len(read_lights(tmp_path / "sub" / SDPS_FILES["light_directions"])) == 4
    assert r["outputs"]["light_images_estimated"].endswith(SDPS_FILES["light_images"])
    assert any(f"4 rows, one per image listed in {SDPS_FILES['light_images']}" in n for n in r["notes"])
    sub = open_capture(tmp_path / "aPNG").subset([cap.image_paths.index(tmp_path / "aPNG" / n) for n in listed])
    assert [p.name for p in sub.image_paths] == listed
    # a calibrated run in the same folder: sdps' files go, with a note; psctl lights' stay
    r = run_normals(tmp_path / "aPNG", method="l2")
    assert not any((out / n).exists() for n in SDPS_FILES.values())
    assert any("removed" in n and SDPS_FILES["lights"] in n for n in r["notes"])
    assert {n: (out / n).read_bytes() for n in before} == before


def test_sdps_decodes_lights_as_its_ps_fcn_dagger_was_trained(tmp_path, fake_weights):
    from psctl.api import run_normals
    from psctl.sdps import sdps_decode
    from psctl.models.ps_fcn import PSFCN

    write_capture(tmp_path / "aPNG", n=6, size=40, seed=1)
    save_weights(tmp_path / "soft.pt", PSFCN(), {"method": "ps-fcn-dagger", "train_images": 32,
                                                 "lcnet": {"decode": "soft"}})
    assert sdps_decode("ps-fcn-dagger", tmp_path / "soft.pt") == "soft"
    assert sdps_decode("ps-fcn-n", tmp_path / "soft.pt") == "soft"  # calibrated: continuous lights
    assert sdps_decode("ps-fcn") == "soft"
    with weights_in(fake_weights):
        assert sdps_decode("ps-fcn-dagger") == "argmax"  # the installed (fake) file records none
        r = run_normals(tmp_path / "aPNG", method="sdps", weights=tmp_path / "soft.pt", write=False, device="cpu")
        assert r["lcnet_decode"] == "soft" and r["lcnet_views"] == 8
        r = run_normals(tmp_path / "aPNG", method="sdps", write=False, device="cpu")
        assert r["lcnet_decode"] == "argmax"
        assert r["lcnet_views"] == 1  # bin centres, as that PS-FCN† was trained on


@pytest.mark.filterwarnings("ignore:.*only 6 images")  # (few on purpose: quick)
def test_sdps_without_ps_fcn_dagger_uses_the_installed_calibrated_network(tmp_path, fake_weights):
    """LCNet installed, PS-FCN† not: sdps runs PS-FCN+N on LCNet's lights and says so."""
    import shutil

    from psctl.api import estimate_normals, run_normals
    from psctl.infer import array_normals
    from psctl.lights import array_lights

    folder = tmp_path / "w"
    folder.mkdir()
    shutil.copy(fake_weights / "lcnet.pt", folder / "lcnet.pt")
    torch.manual_seed(2)
    save_weights(folder / "ps_fcn_n.pt", PSFCN(), {"method": "ps-fcn-n", "normalization": "per-channel",
                                                    "train_images": 32})
    data = write_capture(tmp_path / "aPNG", n=6, size=40, seed=1)
    (tmp_path / "aPNG" / "light_directions.txt").unlink()  # uncalibrated
    with weights_in(folder):
        r = run_normals(tmp_path / "aPNG", out=tmp_path / "o", device="cpu")  # auto
        assert r["method"] == "sdps" and r["second_stage"] == "ps-fcn-n"
        assert any("PS-FCN+N on those lights" in n and "not installed" in n for n in r["notes"])
        # the same as running the two stages by hand
        mask = data["mask"]
        images = data["images"]
        est = array_lights(images, mask, folder / "lcnet.pt", {"device": "cpu"})
        want = array_normals(images / est.intensities[:, None, None, None], est.directions, mask, "ps-fcn-n",
                             folder / "ps_fcn_n.pt", {"device": "cpu"}).normals
        got = estimate_normals(images, None, mask, method="sdps", device="cpu", refine=False)
        assert np.abs(got - want).max() < 1e-5
    # an explicit PS-FCN† file still wins over the installed PS-FCN+N
    with weights_in(folder):
        r = run_normals(tmp_path / "aPNG", method="sdps", weights=fake_weights / "ps_fcn_dagger.pt", write=False,
                        device="cpu")
        assert r["second_stage"] == "ps-fcn-dagger" and any("PS-FCN†" in n for n in r["notes"])


def test_sdps_prefers_ps_fcn_dagger_then_ps_fcn_then_ps_fcn_n(tmp_path):
    from psctl.api import sdps_second_stage

    folder = tmp_path / "w"
    folder.mkdir()
    with weights_in(folder):
        for name, want in (("ps_fcn_n.pt", "ps-fcn-n"), ("ps_fcn.pt", "ps-fcn"), ("ps_fcn_dagger.pt", "ps-fcn-dagger")):
            save_weights(folder / name, PSFCN(), {"method": want, "train_images": 32})
            method, note = sdps_second_stage()
            assert method == want, name
            assert ("not installed" in note) == (want != "ps-fcn-dagger")


def test_lights_help_imports_nothing_heavy():
    code = ("import sys\nfrom psctl.cli import main\nsys.argv = ['psctl', 'lights', '--help']\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\n"
            "assert not [m for m in ('torch', 'OpenImageIO', 'scipy') if m in sys.modules]\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0 and "Usage" in proc.stdout, proc.stderr


# --- training ---------------------------------------------------------------------------------

def tiny(samples: int, **train) -> dict:
    from psctl.train import load_config, merge

    cfg = load_config(REPO / "configs" / "tiny.yaml")
    return merge(cfg, {  # merge() replaces the data section whole
        "data": {**cfg["data"], "size": 32, "intensities": "random"},
        "train": {"samples": samples, "crop": 32, "batch_size": 4, "log_every": 5, "val_every": samples, **train},
        "val": {"samples": 4, "size": 32, "batch_size": 4}})


def test_tiny_lcnet_training_loss_goes_down(tmp_path):
    from psctl.train import train

    torch.set_num_threads(2)
    st = train("lcnet", tiny(160), tmp_path / "run", device="cpu")
    assert st["finished"] and st["samples"] == 160
    losses = [r["loss"] for r in map(json.loads, (tmp_path / "run" / "log.jsonl").read_text().splitlines()) if "loss" in r]
    assert np.mean(losses[-2:]) < np.mean(losses[:2]), losses
    assert min(losses) >= 0, losses  # cross-entropy: a negated loss falls too, below 0 (helper-191)
    w = read_weights(tmp_path / "run" / "best.pt")
    assert w.method == "lcnet" and w.metadata["architecture"]["size"] == 32 and w.metadata["train_images"] == 8
    assert "synthetic_val_light_mae" in w.metadata["metrics"]
    # the trained file runs in the light-estimation pipeline at the size it was trained at
    images, mask = scene(n=4)
    est = array_lights(images, mask, weights=tmp_path / "run" / "best.pt")
    assert est.info["size"] == 32 and est.directions.shape == (4, 3)


def test_tiny_ps_fcn_dagger_training_uses_the_frozen_lcnet(tmp_path):
    from psctl.train import train

    torch.set_num_threads(2)
    save_weights(tmp_path / "lc.pt", lcnet(size=32), {"method": "lcnet", "train_images": 8})
    cfg = tiny(16)
    with pytest.raises(PsctlError, match="lcnet"):  # nothing installed and no --lcnet
        with weights_in(tmp_path / "none"):
            train("ps-fcn-dagger", cfg, tmp_path / "fail", device="cpu")
    st = train("ps-fcn-dagger", cfg, tmp_path / "run", device="cpu", lcnet=tmp_path / "lc.pt")
    assert st["finished"] and st["lcnet"] == str(tmp_path / "lc.pt")
    w = read_weights(tmp_path / "run" / "best.pt")
    assert w.method == "ps-fcn-dagger" and w.metadata["normalization"] == "none"
    assert w.metadata["lcnet"]["path"] == str(tmp_path / "lc.pt")
    with pytest.raises(PsctlError, match="--lcnet is for ps-fcn-dagger"):
        train("ps-fcn", cfg, tmp_path / "other", device="cpu", lcnet=tmp_path / "lc.pt")


def test_ps_fcn_dagger_trains_on_windows_from_an_init_file(tmp_path):
    """The CPU recipe: LCNet sees the whole view, PS-FCN† (+N) trains on the stream's windows,
    starting from a calibrated network's weights; validation runs on the whole view."""
    from psctl.models.ps_fcn import PSFCN
    from psctl.train import merge, train

    torch.set_num_threads(2)
    save_weights(tmp_path / "lc.pt", lcnet(size=32), {"method": "lcnet", "train_images": 8})
    start = PSFCN()
    save_weights(tmp_path / "init.pt", start, {"method": "ps-fcn-n", "train_images": 8, "samples_seen": 123})
    base = tiny(8, lr=0.0)  # lr 0: the weights stay the init file's, which shows it was loaded
    cfg = merge(base, {"data": {**base["data"], "windows": 16}, "normalization": "per-channel",
                       "train": {**base["train"], "init": str(tmp_path / "init.pt")}})
    seen = []
    import psctl.train as T

    real = T.crop_windows
    T.crop_windows = lambda x, w, side: seen.append((x.shape[-1], side)) or real(x, w, side)
    try:
        st = train("ps-fcn-dagger", cfg, tmp_path / "run", device="cpu", lcnet=tmp_path / "lc.pt")
    finally:
        T.crop_windows = real
    assert st["finished"] and seen and all(s == (32, 16) for s in seen)
    assert [v[0] for v in st["val"]] == [0, 8]  # the init file is validated before training
    w = read_weights(tmp_path / "run" / "best.pt")
    assert w.metadata["normalization"] == "per-channel" and w.metadata["init"]["samples_seen"] == 123
    assert all(torch.equal(w.state_dict[k], v) for k, v in start.state_dict().items())
    # a file of another architecture is refused in one line
    save_weights(tmp_path / "ups.pt", PSFCN({"lights": False}), {"method": "ups-fcn", "train_images": 8})
    cfg["train"]["init"] = str(tmp_path / "ups.pt")
    with pytest.raises(PsctlError, match="train.init"):
        train("ps-fcn-dagger", cfg, tmp_path / "bad", device="cpu", lcnet=tmp_path / "lc.pt")


def test_ups_fcn_starts_from_ps_fcn_weights_without_their_light_channels(tmp_path):
    from psctl.train import merge, train

    torch.set_num_threads(2)
    start = PSFCN()
    with torch.no_grad():
        start.extractor.conv1[0].weight[:, 3:] = 7.0  # the light filters: must not survive
    save_weights(tmp_path / "ps.pt", start, {"method": "ps-fcn", "train_images": 8, "samples_seen": 45})
    base = tiny(8, lr=0.0)
    cfg = merge(base, {"train": {**base["train"], "init": str(tmp_path / "ps.pt")}})
    st = train("ups-fcn", cfg, tmp_path / "run", device="cpu")
    w = read_weights(tmp_path / "run" / "best.pt")
    assert st["finished"] and w.method == "ups-fcn" and w.metadata["architecture"]["lights"] is False
    assert w.metadata["init"]["samples_seen"] == 45 and "dropped" in w.metadata["init"]["adapted"]
    ref = start.state_dict()
    assert torch.equal(w.state_dict["extractor.conv1.0.weight"], ref["extractor.conv1.0.weight"][:, :3])
    assert all(torch.equal(w.state_dict[k], v) for k, v in ref.items() if k != "extractor.conv1.0.weight")
    # the other way (a PS-FCN run from UPS-FCN weights) has no light filters to start from: refused
    save_weights(tmp_path / "ups.pt", PSFCN({"lights": False}), {"method": "ups-fcn", "train_images": 8})
    cfg["train"]["init"] = str(tmp_path / "ups.pt")
    with pytest.raises(PsctlError, match="train.init"):
        train("ps-fcn", cfg, tmp_path / "bad", device="cpu")


def test_lcnet_resume_continues_exactly(tmp_path):
    """16 + 16 samples with a stop in between == 32 samples in one go (same batches, same Adam state)."""
    from psctl.train import merge, train

    cfg = tiny(32)
    train("lcnet", cfg, tmp_path / "a", device="cpu")
    train("lcnet", merge(cfg, {"train": {"samples": 16}}), tmp_path / "b", device="cpu")
    train("lcnet", cfg, tmp_path / "b", resume=True, device="cpu")
    wa = read_weights(tmp_path / "a" / "model.pt").state_dict
    wb = read_weights(tmp_path / "b" / "model.pt").state_dict
    assert max((wa[k] - wb[k]).abs().max().item() for k in wa) < 1e-5


# --- symmetric views --------------------------------------------------------------------------

def lambert_sphere(light: torch.Tensor, h: int = 41) -> torch.Tensor:
    """A Lambertian unit sphere filling an h x h image (row 0 at the top, x right, y up)."""
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(h, dtype=torch.float64), indexing="ij")
    x, y = (xs - (h - 1) / 2) / ((h - 1) / 2), -(ys - (h - 1) / 2) / ((h - 1) / 2)
    inside = x ** 2 + y ** 2 < 1
    n = torch.stack([x, y, (1 - x ** 2 - y ** 2).clamp_min(0).sqrt()], -1)
    return (n @ light.double()).clamp_min(0) * inside


@pytest.mark.parametrize("sym", SYMMETRIES)
def test_symmetries_move_images_and_lights_together(sym):
    """Turning / mirroring the image of a sphere equals rendering it under the turned light, and
    untransform_dirs undoes transform_dirs: the geometry LCNet's views rely on."""
    light = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64), dim=0)
    torch.testing.assert_close(transform_images(lambert_sphere(light), sym), lambert_sphere(transform_dirs(light, sym)))
    d = torch.nn.functional.normalize(torch.randn(7, 3, dtype=torch.float64), dim=-1)
    torch.testing.assert_close(untransform_dirs(transform_dirs(d, sym), sym), d)


def test_symmetries_are_the_group_of_the_square():
    """The 8 symmetries are distinct, and the first 1, 2 and 4 are subgroups (closed under
    composition), so views=8 gives estimates that turn with the capture."""
    d = torch.nn.functional.normalize(torch.randn(5, 3, dtype=torch.float64), dim=-1)
    images = [transform_dirs(d, s) for s in SYMMETRIES]
    assert len({tuple(np.round(i.numpy().ravel(), 9)) for i in images}) == 8
    for k in (1, 2, 4, 8):
        sub = SYMMETRIES[:k]
        keys = {tuple(np.round(transform_dirs(d, s).numpy().ravel(), 9)) for s in sub}
        for a in sub:
            for b in sub:
                assert tuple(np.round(transform_dirs(transform_dirs(d, b), a).numpy().ravel(), 9)) in keys


def test_views_average_the_turned_back_estimates():
    """views=8 is the unit mean of the 8 turned-back single-pass estimates, streamed or not."""
    net = lcnet(size=32).double()
    images, mask = scene()
    ref_dirs, ref_ints = [], []
    for sym in SYMMETRIES:
        r = array_lights(np.ascontiguousarray(transform_images(torch.from_numpy(images).permute(0, 3, 1, 2), sym)
                                              .permute(0, 2, 3, 1).numpy()),
                         np.ascontiguousarray(transform_images(torch.from_numpy(mask), sym).numpy()),
                         model=net, config={"views": 1})
        ref_dirs.append(untransform_dirs(torch.from_numpy(r.directions).double(), sym))
        ref_ints.append(r.intensities)
    ref = torch.nn.functional.normalize(torch.stack(ref_dirs).mean(0), dim=-1).numpy()
    for config in ({}, {"chunk": 3, "cache_mb": 0}):
        est = array_lights(images, mask, model=net, config=config)
        assert est.info["views"] == 8
        np.testing.assert_allclose(est.directions, ref, atol=1e-5)
        np.testing.assert_allclose(est.intensities, np.mean(ref_ints, 0), atol=1e-5)


@pytest.mark.parametrize("sym", [SYMMETRIES[1], SYMMETRIES[4], SYMMETRIES[7]])  # flip x, transpose, all three
def test_eight_views_turn_with_the_capture(sym):
    """Estimating on a turned / mirrored capture gives the turned estimates (views=8)."""
    net = lcnet(size=32).double()
    images, mask = scene(h=48, w=64)
    est = array_lights(images, mask, model=net)
    t_images = transform_images(torch.from_numpy(images).permute(0, 3, 1, 2), sym).permute(0, 2, 3, 1).numpy()
    t_mask = transform_images(torch.from_numpy(mask), sym).numpy()
    t_est = array_lights(np.ascontiguousarray(t_images), np.ascontiguousarray(t_mask), model=net)
    np.testing.assert_allclose(t_est.directions, transform_dirs(torch.from_numpy(est.directions).double(), sym).numpy(),
                               atol=1e-5)
    np.testing.assert_allclose(t_est.intensities, est.intensities, atol=1e-5)


def test_views_refused_when_not_a_subgroup():
    net = lcnet(size=32).double()
    images, mask = scene()
    for bad in (3, 0, 16, "8", True):
        with pytest.raises(PsctlError, match="views"):
            array_lights(images, mask, model=net, config={"views": bad})


def test_classifier_gradients_stay_off_padding_only_taps_under_bf16():
    """At 64 px the classifier's last conv runs on a 1 x 1 map, so only the centre tap of its
    kernel sees data. Under CPU bf16 autocast oneDNN gave the other taps non-zero (later NaN)
    gradients from the second backward on: the NaNs of the release LCNet. The classifier runs
    outside autocast; its padding-only taps must get exactly zero gradient."""
    from psctl.infer import cpu_has_bf16

    if not cpu_has_bf16():
        pytest.skip("this CPU has no native bf16: psctl trains in float32 here")
    net = lcnet(size=64).train()
    x, m = torch.rand(2, 8, 3, 64, 64), torch.ones(2, 1, 64, 64)
    for _ in range(4):
        net.zero_grad()
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = net(x, m)
        sum(v.float().logsumexp(-1).mean() for v in out.values()).backward()
        g = net.classifier.conv4[0].weight.grad.clone()
        g[:, :, 1, 1] = 0
        assert torch.count_nonzero(g) == 0


def test_lights_subset_lists_its_images(tmp_path, fake_weights):
    """psctl lights --images K: K rows, and light_images.txt says which image each row is; a later
    run over every image removes that list (its rows would no longer match)."""
    from psctl.io.capture import select_images
    from psctl.lights import run_lights

    write_capture(tmp_path / "cap", n=10, size=40)
    names = (tmp_path / "cap" / "filenames.txt").read_text().split()
    out = tmp_path / "out"
    arrays = {}
    r = run_lights(tmp_path / "cap", out=out, weights=fake_weights / "lcnet.pt", device="cpu", n_images=3,
                   refine=False, views=1, arrays=arrays)
    assert r["n_images"] == 3 and np.loadtxt(out / "light_directions.txt").shape == (3, 3)
    # arrays: what the files hold, for a Python caller (run_lights with write=False returned nothing)
    assert arrays["directions"].shape == arrays["intensities"].shape == (3, 3)
    np.testing.assert_allclose(arrays["directions"], np.loadtxt(out / "light_directions.txt"), atol=1e-6)
    np.testing.assert_allclose(arrays["intensities"], np.loadtxt(out / "light_intensities.txt"), rtol=1e-5)
    with pytest.raises(PsctlError, match="arrays must be a dict"):
        run_lights(tmp_path / "cap", write=False, weights=fake_weights / "lcnet.pt", arrays=[])
    assert (out / "light_images.txt").read_text().split() == [names[i] for i in select_images(10, 3, 0)]
    assert r["outputs"]["light_images"] == str(out / "light_images.txt")
    # the report says which images and the seed, as psctl normals' does (a QA helper's note)
    # (drawn with seed 0 without --seed: the report says so, where it said null, as for no seed at all)
    assert r["images_used"] == [names[i] for i in select_images(10, 3, 0)] and r["seed"] == 0
    assert r["selection"] == "random"
    saved = json.loads((out / "lights_report.json").read_text())
    assert saved["images_used"] == r["images_used"] and saved["seed"] == 0 and saved["selection"] == "random"
    assert any("seed 0" in n for n in r["notes"]) and any("light_images.txt" in n for n in r["notes"])
    r = run_lights(tmp_path / "cap", out=out, weights=fake_weights / "lcnet.pt", device="cpu", n_images=3, seed=5,
                   refine=False, views=1)
    assert r["seed"] == 5 and r["images_used"] == [names[i] for i in select_images(10, 3, 5)]
    r = run_lights(tmp_path / "cap", out=out, weights=fake_weights / "lcnet.pt", device="cpu", refine=False, views=1)
    assert "images_used" not in r and "seed" not in r and "selection" not in r
    assert not (out / "light_images.txt").exists() and "light_images" not in r["outputs"]
    assert any("removed light_images.txt" in n for n in r["notes"])


def test_lcnet_classifier_sees_own_features_then_the_global_max():
    from psctl.models.lcnet import LCNet

    torch.manual_seed(0)
    net = LCNet({"size": 32}).double().eval()
    x = torch.rand(1, 4, 3, 32, 32, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    m = torch.ones(1, 1, 32, 32, dtype=torch.float64)
    with torch.no_grad():
        out = net(x, m)
        f = net.extract(net.network_input(x[0], m.expand(4, 1, 32, 32)))
        ref = net.classifier(torch.cat([f, f.amax(0, keepdim=True).expand_as(f)], 1))
    for k in ref:
        torch.testing.assert_close(out[k][0], ref[k])


def test_lcnet_intensity_targets_use_the_configured_range():
    from psctl.models.lcnet import classification_loss, dirs_to_classes, ints_to_classes

    cfg = {"dirs_cls": 36, "ints_cls": 10, "ints_range": [0.5, 4.0]}
    dirs = torch.nn.functional.normalize(torch.tensor([[0.3, -0.2, 1.0], [-0.5, 0.4, 0.7]]), dim=-1)
    ints = torch.tensor([0.6, 3.5])
    cx, cy = dirs_to_classes(dirs, 36)
    logits = {"dir_x": torch.zeros(2, 36), "dir_y": torch.zeros(2, 36), "ints": torch.zeros(2, 10)}
    logits["dir_x"][torch.arange(2), cx] = logits["dir_y"][torch.arange(2), cy] = 50.0
    cls = ints_to_classes(ints, 10, 0.5, 4.0)
    assert cls.tolist() == [0, 8]
    logits["ints"][torch.arange(2), cls] = 50.0
    assert float(classification_loss(logits, dirs, ints, cfg)[0]) < 1e-6


def test_intensity_relative_error_fits_the_scale_by_least_squares():
    from psctl.metrics import intensity_relative_error

    assert intensity_relative_error(np.array([1.0, 2.0, 2.0]), np.array([1.0, 2.0, 4.0])) == pytest.approx(7 / 18)


def test_lights_plot_ring_labels_hide_no_light():
    """The 30 and 60 degree labels go just outside their ring where no marker is near: at a fixed
    place the 30 degree label hid one of DiLiGenT's lights (helper-162). A DiLiGenT-like grid of 96
    lights: every dot's centre keeps its colour."""
    from psctl.io.report import jet

    x, y = np.meshgrid(np.linspace(-0.5, 0.5, 12), np.linspace(-0.42, 0.42, 8))
    d = np.stack([x.ravel(), y.ravel(), np.sqrt(1 - x.ravel() ** 2 - y.ravel() ** 2)], 1)
    canvas = lights_plot(d, np.ones(len(d)), d, radius=230)
    colour = jet(np.float32((1.0 - 0.2) / 1.8))
    top, cx = 40 + 12 + 230, 12 + 230  # lights_plot's layout: the disk's centre (rows, columns)
    for v in d:
        assert np.allclose(canvas[int(round(top - v[1] * 230)), int(round(cx + v[0] * 230))], colour, atol=1e-6), v


def test_lights_plot_rims_each_estimate():
    """jet's dark ends (the weakest and strongest lights) read as little on the dark grey disk
    (helper-162): each estimate's dot has a light rim, with no ground truth drawn too."""
    from psctl.io.report import jet

    d = np.array([[-0.3, 0.0, 0.954], [0.3, 0.0, 0.954]])
    e = np.array([0.1, 10.0])
    canvas = lights_plot(d, e, radius=230)
    top, cx = 40 + 12 + 230, 12 + 230
    for v, colour in zip(d, jet(np.float32((e / e.mean() - 0.2) / 1.8))):  # near the bar's two ends
        row, col = top - v[1] * 230, cx + v[0] * 230
        assert np.allclose(canvas[int(round(row)), int(round(col))], colour, atol=1e-6)
        for dy, dx in ((4, 0), (-4, 0), (0, 4), (0, -4)):  # the rim, 1 px outside the 3.5 px dot
            assert np.allclose(canvas[int(round(row + dy)), int(round(col + dx))], 0.8), (v, dy, dx)


def test_lights_plot_small_or_degenerate_inputs_still_draw():
    """A small disk put the ring labels left of the canvas (an IndexError), and a range of one
    intensity divided by zero: both draw now."""
    from psctl.lights import lights_plot

    d = np.array([[0.0, 0.0, 1.0]])
    for radius in (10, 30, 70):
        assert lights_plot(d, np.ones(1), radius=radius).ndim == 3
    assert lights_plot(d, np.ones(1), ints_range=(1.0, 1.0)).ndim == 3


@pytest.mark.filterwarnings("ignore:.*only 6 images")  # (few on purpose: quick)
def test_lights_precision_is_the_refinements_network(tmp_path, fake_weights, monkeypatch):
    """psctl lights --precision: the refinement's normals network runs under autocast (LCNet in
    float32); refused before any work where the CPU would emulate bf16; unused without --refine."""
    import psctl.infer
    import psctl.lights
    from psctl.api import estimate_lights
    from psctl.lights import run_lights

    write_capture(tmp_path / "aPNG", n=6, size=40, seed=1)
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    seen = []
    real = psctl.infer._autocast
    monkeypatch.setattr(psctl.infer, "_autocast", lambda d, k: (seen.append(k), real(d, k))[1])
    monkeypatch.setattr(psctl.infer, "cpu_has_bf16", lambda: False)

    def no_lcnet(*a, **k):
        raise AssertionError("LCNet ran before the precision was refused")

    with monkeypatch.context() as m:
        m.setattr(psctl.lights, "capture_lights", no_lcnet)
        with pytest.raises(PsctlError, match="would emulate it"):
            run_lights(tmp_path / "aPNG", device="cpu", views=1, precision="bf16", out=tmp_path / "no")
    assert not (tmp_path / "no").exists()
    monkeypatch.setattr(psctl.infer, "cpu_has_bf16", lambda: True)
    seen.clear()
    r = run_lights(tmp_path / "aPNG", device="cpu", views=1, precision="bf16", write=False)
    assert r["precision"] == "bf16" and seen and set(seen) == {"bf16"}
    r = run_lights(tmp_path / "aPNG", device="cpu", views=1, precision="bf16", refine=False, write=False)
    assert r["precision"] == "float32" and any("--precision is unused without --refine" in n for n in r["notes"])
    # --refine with LCNet alone installed: nothing refines, so the refinement's options go unused
    (tmp_path / "lc").mkdir()
    (tmp_path / "lc" / "lcnet.pt").write_bytes((fake_weights / "lcnet.pt").read_bytes())
    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path / "lc"))
    r = run_lights(tmp_path / "aPNG", device="cpu", views=1, precision="bf16", falloff="lambertian", write=False)
    assert r["precision"] == "float32" and [n for n in r["notes"] if "unused" in n or "not refined" in n] == [
        "lights: no normals network installed (PS-FCN† / PS-FCN / PS-FCN+N); LCNet's lights are not refined",
        "lights: --falloff is unused (no normals network is installed to refine with)",
        "lights: --precision is unused (no normals network is installed to refine with)"]
    # fp16 is for CUDA, but no network would run in it: a note, not the refusal (a review)
    r = run_lights(tmp_path / "aPNG", device="cpu", views=1, precision="fp16", write=False)
    assert "lights: --precision is unused (no normals network is installed to refine with)" in r["notes"]
    assert set(r["provenance"]["weights"]) == {"lcnet"}  # what made the lights: LCNet alone
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    r = run_lights(tmp_path / "aPNG", device="cpu", views=1, write=False)
    assert set(r["provenance"]["weights"]) == {"lcnet", "ps-fcn-dagger"}  # and the refinement's network
    seen.clear()
    from tests.conftest import render_lambertian, sphere, hemisphere_lights

    normals, mask = sphere(32)
    images = render_lambertian(normals, mask, hemisphere_lights(6, seed=2), 0.7)
    d, e = estimate_lights(images, mask, device="cpu", views=1, precision="bf16")
    assert d.shape == (6, 3) and set(seen) == {"bf16"}


def test_few_images_get_a_note_on_lcnets_lights(tmp_path, fake_weights):
    """Under 8 images LCNet is rougher (dev split, random subsets: 15.0 degrees from 1 image, 4.9
    from 8, 2.9 from 96): a note in the folder's report, a warning from the arrays; none from 8."""
    import warnings

    import psctl
    from psctl.errors import PsctlWarning
    from psctl.lights import run_lights
    from tests.conftest import weights_in, write_capture

    write_capture(tmp_path / "fewPNG", n=7, size=32)
    write_capture(tmp_path / "enoughPNG", n=8, size=32)
    with weights_in(fake_weights):
        few = run_lights(tmp_path / "fewPNG", write=False, device="cpu", refine=False)["notes"]
        enough = run_lights(tmp_path / "enoughPNG", write=False, device="cpu", refine=False)["notes"]
        assert sum(n.startswith("lights: only 7 images: LCNet") for n in few) == 1
        assert not any("LCNet estimates each light by comparing" in n for n in enough)
        data = write_capture(tmp_path / "arrPNG", n=4, size=32)
        with warnings.catch_warnings(record=True) as got:
            warnings.simplefilter("always")
            psctl.estimate_lights(data["images"], data["mask"], device="cpu", refine=False)
        said = [str(w.message) for w in got if issubclass(w.category, PsctlWarning)]
        assert [s for s in said if "comparing the images" in s] == [
            "estimate_lights: lights: only 4 images: LCNet estimates each light by comparing the images with one "
            "another, and from few it is rougher (the DiLiGenT dev split's objects, random subsets: 15.0 degrees "
            "off on average from 1 image, 9.7 from 2, 6.3 from 4, 4.9 from 8, 2.9 from all 96)"]


def test_names_that_moved_out_of_lights_and_train_are_still_found_there():
    """psctl.lights was split into lights, masks and refine, and psctl.train's checkpoint files went
    to psctl.checkpoint (2026-12-01): the docs had pointed users at psctl.lights.refine_lights and
    others, so the old names still work, as the same objects, with a DeprecationWarning (a review)."""
    import psctl.checkpoint
    import psctl.lights
    import psctl.masks
    import psctl.refine
    import psctl.train

    for old, new in ((psctl.lights, psctl.masks), (psctl.lights, psctl.refine), (psctl.train, psctl.checkpoint)):
        for name in new.__all__:
            if name in vars(old):  # imported there as well: found without a word
                continue
            with pytest.warns(DeprecationWarning, match=rf"{old.__name__}\.{name} is now {new.__name__}\.{name}"):
                assert getattr(old, name) is getattr(new, name)
    with pytest.raises(AttributeError, match="has no attribute 'lit_pixels'"):  # only the moved names
        psctl.lights.lit_pixels


def test_lights_plot_axis_names_stay_readable_beside_a_light_on_the_axis():
    """A light at the rim on an axis does not hide "+Y" or "+X" (helper-212: drawn under the
    markers at a fixed place, a light there covered them); each moves to its axis' other side."""
    def grey_pixels(canvas):
        return int((np.abs(canvas - 0.6).max(-1) < 1e-6).sum())

    empty = lights_plot(np.zeros((0, 3)), np.zeros(0), radius=100)
    for xy in ((0.07, 0.96), (0.92, -0.08)):
        d = np.array([[*xy, np.sqrt(1 - xy[0] ** 2 - xy[1] ** 2)]])
        assert grey_pixels(lights_plot(d, np.ones(1), radius=100)) == grey_pixels(empty)
