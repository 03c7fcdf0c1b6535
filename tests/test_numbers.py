"""Numbers users rely on (scores, table means, published numbers, file and array conventions),
each pinned by a value derived by hand in its comment, not by running psctl. Written by
helper-158's mutation audit (session 74): each test fails with a mutant that the rest of the
suite let through (the ids in the comments are its report's)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from psctl.errors import PsctlError


def _tilt(deg):  # unit vector tilted by `deg` degrees from +z towards +x
    return np.array([np.sin(np.radians(deg)), 0.0, np.cos(np.radians(deg))])


def test_light_mae_is_the_mean_of_the_direction_errors():
    # kills M12 (lights.light_errors: mean -> median). Errors 0, 0, 30 degrees: mean 10, median 0.
    from psctl.lights import light_errors
    gt = np.tile([0.0, 0.0, 1.0], (3, 1))
    est = np.stack([_tilt(0), _tilt(0), _tilt(30)])
    r = light_errors(est, None, gt, None)
    assert r["light_mae"] == pytest.approx(10.0, abs=1e-9)
    np.testing.assert_allclose(r["direction_errors"], [0, 0, 30], atol=1e-9)


def test_intensity_error_of_an_rgb_estimate_against_grey_truth_scores_its_grey_mean():
    # kills M14 (est.mean(1) -> est[:, 0]). Row means of est are 2, 2, 2 against truth 1, 1, 1:
    # scale-invariant, so 0. Scoring the red column (1, 2, 3) instead: s = 6/14, errors 4/7, 1/7, 2/7 -> 1/3.
    from psctl.lights import intensity_error
    est = np.array([[1.0, 3.0, 2.0], [2.0, 2.0, 2.0], [3.0, 1.0, 2.0]])
    assert intensity_error(est, np.ones(3)) == pytest.approx(0.0, abs=1e-12)


def test_intensity_error_of_rgb_averages_the_channels():
    # kills L03 (mean over channels -> max). Red of image 3 is twice the others: red channel
    # s = (1+1+2)/(1+1+4) = 2/3, |s e - 1| = 1/3 each -> 1/3; green and blue 0; mean 1/9 (max would be 1/3).
    from psctl.lights import intensity_error
    est = np.array([[1.0, 1, 1], [1.0, 1, 1], [2.0, 1, 1]])
    assert intensity_error(est, np.ones((3, 3))) == pytest.approx(1 / 9, abs=1e-12)


def test_mae_missing_as_90_counts_every_mask_pixel():
    # kills M17 (api._evaluate divided by the scored pixels instead of the mask's). 4 mask pixels:
    # errors 30, 0, 0 and one without ground truth: mae (30 + 0 + 0) / 3 = 10; as the paper scores,
    # (30 + 0 + 0 + 90) / 4 = 30.
    from psctl.api import _evaluate
    mask = np.ones((1, 4), bool)
    gt = np.zeros((1, 4, 3), np.float32)
    gt[0, :3, 2] = 1
    n = np.zeros((1, 4, 3), np.float32)
    n[0, :, 2] = 1
    n[0, 0] = _tilt(30)
    _, stats, valid, _ = _evaluate(n, gt, mask, Path("Normal_gt.mat"))
    assert stats["mae"] == pytest.approx(10.0, abs=1e-4)
    assert stats["mae_missing_as_90"] == pytest.approx(30.0, abs=1e-4)
    assert valid.sum() == 3


def test_table_means_are_means_over_three_objects():
    # kills M18 and M22 (np.mean -> np.median in eval._table): with two objects the two agree,
    # as in every existing test; with 1, 2, 6 the mean is 3, the median 2.
    from psctl.eval import _table
    objs = [{"name": n, "mae": v, "median": v, "mae_missing_as_90": v, "n_images": 6, "seconds": 1.0,
             "light_mae": v, "intensity_re": v / 100, "lcnet_light_mae": v, "lcnet_intensity_re": v / 100}
            for n, v in (("a", 1.0), ("b", 2.0), ("c", 6.0))]
    r = _table("folder", Path("."), objs, ["sdps"] * 3, None)
    assert r["mean_mae"] == pytest.approx(3.0) and r["mean_mae_missing_as_90"] == pytest.approx(3.0)
    assert r["mean_light_mae"] == pytest.approx(3.0) and r["mean_intensity_re"] == pytest.approx(0.03)
    assert r["mean_lcnet_light_mae"] == pytest.approx(3.0) and r["mean_lcnet_intensity_re"] == pytest.approx(0.03)


def test_published_numbers_are_pinned():
    # kills M20, M21, M24 (one published number changed). Checked against the issues' copies of the
    # papers' tables (PS-FCN / PS-FCN+N, LCNet's lights and LCNet + PS-FCN†'s normals) and
    # DiLiGenT's own L2 baseline table: a pin guards against a slip in an edit.
    from psctl.eval import PAPER_DILIGENT, PAPER_DILIGENT_LIGHTS
    assert PAPER_DILIGENT == {
        "l2": {"ball": 4.10, "cat": 8.41, "pot1": 8.89, "bear": 8.39, "pot2": 14.65},
        "ps-fcn": {"ball": 2.8, "cat": 6.2, "pot1": 7.1, "bear": 7.6, "pot2": 7.3},
        "ps-fcn-n": {"ball": 2.7, "cat": 4.8, "pot1": 6.2, "bear": 7.7, "pot2": 7.2},
        "sdps": {"ball": 2.8, "cat": 8.1, "pot1": 8.1, "bear": 6.9, "pot2": 7.5},
    }
    assert PAPER_DILIGENT_LIGHTS == {
        "ball": {"light_mae": 3.27, "intensity_re": 0.039}, "cat": {"light_mae": 4.08, "intensity_re": 0.095},
        "pot1": {"light_mae": 5.44, "intensity_re": 0.058}, "bear": {"light_mae": 3.47, "intensity_re": 0.061},
        "pot2": {"light_mae": 2.87, "intensity_re": 0.048},
    }


def test_l2_refuses_fewer_images_than_lights():
    # kills C12 (k + 1 != len(lights) -> k + 1 > len(lights)): 3 images with 4 lights was solved with
    # the first three lights, silently.
    from psctl.classic import l2_normals
    L = np.array([[0, 0, 1.0], [0.5, 0, 0.866], [0, 0.5, 0.866], [-0.5, 0, 0.866]])
    with pytest.raises(PsctlError, match="3 images but 4 light directions"):
        l2_normals(np.ones((3, 2, 2), np.float32), L)


@pytest.mark.parametrize("solver", ["l2_normals", "trimmed_l2_normals"])
def test_l2_takes_a_0_255_mask_as_a_mask(solver):
    # kills C13 and C14 (mask.astype(bool) dropped: a uint8 mask became an integer index array,
    # IndexError). One object pixel with normal (0, 0.6, 0.8), lit Lambertian with albedo 1:
    # least squares is exact, so the normal is (0, 0.6, 0.8) and the albedo 1.
    import psctl.classic as classic
    L = np.array([[0, 0, 1.0], [0.5, 0, 0.866], [0, 0.5, 0.866], [-0.5, 0, 0.866], [0, -0.5, 0.866], [0.3, 0.3, 0.9]])
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    shade = np.clip(L @ np.array([0.0, 0.6, 0.8]), 0, None)
    imgs = np.broadcast_to(shade[:, None, None], (6, 3, 3)).astype(np.float32)
    m = np.zeros((3, 3), np.uint8)
    m[1, 1] = 255
    r = getattr(classic, solver)(imgs, L, m)
    np.testing.assert_allclose(r.normals[1, 1], [0, 0.6, 0.8], atol=1e-5)
    assert r.albedo[1, 1] == pytest.approx(1.0, abs=1e-5) and (r.normals[m == 0] == 0).all()


def test_trimmed_l2_solve_gives_dark_pixels_b_zero():
    # kills C10 (b[dark] = 0 dropped): its docstring promises b = 0 where dark.
    from psctl.classic import trimmed_l2_solve
    L = np.array([[0, 0, 1.0], [0.5, 0, 0.866], [0, 0.5, 0.866], [-0.5, 0, 0.866], [0, -0.5, 0.866]])
    grey = np.ones((5, 3))
    grey[:, 2] = 1e-9  # 1e-9 of the others: below DARK (1e-6)
    b, dark, _ = trimmed_l2_solve(grey, L)
    assert dark.tolist() == [False, False, True] and (b[2] == 0).all()


def test_read_normal_map_reads_a_mid_grey_png_background_as_no_normal(tmp_path):
    # kills N04 (the NO_NORMAL_LENGTH test dropped) at the reader itself (test_depth's run_depth test
    # kills it too, if it is run). (0.5, 0.5, 0.5) decodes to 2 v - 1 = 0 (length ~1.5e-5 after
    # 16-bit rounding): no normal, 0 -- not (1, 1, 1) / sqrt(3).
    from psctl.io.images import write_image
    from psctl.io.normals import read_normal_map
    px = np.full((4, 4, 3), 0.5)
    px[1:3, 1:3] = (np.array([0, 0.6, 0.8]) + 1) / 2
    for bits in ("uint8", "uint16"):
        write_image(tmp_path / f"n{bits}.png", px, bits, kind="data")
        n = read_normal_map(tmp_path / f"n{bits}.png")
        assert (n[0, 0] == 0).all()
        np.testing.assert_allclose(n[1, 1], [0, 0.6, 0.8], atol=0.01)


def test_a_float_normal_map_is_read_as_stored(tmp_path):
    # kills N06 (float maps normalised on read). The docstring: float images hold n as written.
    from psctl.io.images import write_image
    from psctl.io.normals import read_normal_map
    px = np.zeros((2, 2, 3), np.float32)
    px[..., 2] = 2.0
    write_image(tmp_path / "n.exr", px, "float", kind="data")
    assert (read_normal_map(tmp_path / "n.exr") == px).all()


def test_written_intensities_keep_six_decimals(tmp_path):
    # kills L02 (.6f -> .2f): 0.123456 must come back as 0.123456 (read_intensities, float32).
    from psctl.io.capture import read_intensities
    from psctl.lights import write_light_files
    p = write_light_files(tmp_path, np.array([[0, 0, 1.0], [0.6, 0, 0.8]]), np.array([1.0, 0.123456]))
    np.testing.assert_allclose(read_intensities(p["light_intensities"]), [[1, 1, 1], [0.123456] * 3], rtol=1e-6)


def test_a_nan_intensity_is_refused(tmp_path):
    # kills K02 (read_matrix's NaN/inf check dropped): light directions would still be refused (as
    # zero-length), but a NaN intensity was read and every image divided by it.
    from psctl.io.capture import read_intensities
    (tmp_path / "i.txt").write_text("1 1 1\nnan 1 1\n")
    with pytest.raises(PsctlError, match="line 2: NaN or infinite value"):
        read_intensities(tmp_path / "i.txt")


def test_the_one_sided_note_names_the_side_in_image_terms():
    # kills L01 (atan2(-my, mx): y taken as down). Lights all at +y (up, psctl's convention): "the top".
    from psctl.lights import one_sided_notes
    L = np.array([[0.0, 0.5, 0.866], [0.1, 0.5, 0.86], [-0.1, 0.5, 0.86]])
    notes = one_sided_notes(L)
    assert len(notes) == 1 and "(the top;" in notes[0]


def test_integer_image_arrays_reach_one_at_their_types_top():
    # kills R01 (divided by max + 1: 256 / 65536). Documented: uint8 / 255, uint16 / 65535.
    from psctl.arrays import as_images
    assert as_images(np.full((3, 2, 2), 255, np.uint8)).max() == 1.0
    assert as_images(np.full((3, 2, 2), 65535, np.uint16)).max() == 1.0


def test_rgba_image_arrays_drop_alpha_not_red():
    # kills R07 (out[..., 1:] instead of out[..., :3]).
    from psctl.arrays import as_images
    x = np.zeros((3, 2, 2, 4), np.float32)
    x[...] = [0.1, 0.2, 0.3, 1.0]
    np.testing.assert_array_equal(as_images(x)[0, 0, 0], np.float32([0.1, 0.2, 0.3]))


def test_a_uint16_mask_is_divided_by_65535():
    # kills R06 (uint16 masks divided by 255): 40000 / 65535 = 0.61 is object, 200 / 65535 = 0.003 is not
    # (200 / 255 = 0.78 would be).
    from psctl.arrays import as_mask
    m = np.zeros((2, 2), np.uint16)
    m[0, 0], m[1, 1] = 40000, 200
    assert as_mask(m, (2, 2)).tolist() == [[True, False], [False, False]]


def test_albedo_median_of_an_even_count_is_the_middle_two_averaged():
    # kills B01 (upper median). Normal (0, 0, 1); four lights with n . l = 1, 0.8, 0.8, 0.8 (all >= 0.2,
    # all counted); images = k * n . l for k = 1..4, so the ratios are 1, 2, 3, 4: median 2.5 (upper: 3).
    from psctl.albedo import estimate_albedo
    L = np.array([[0, 0, 1.0], [0.6, 0, 0.8], [0, 0.6, 0.8], [-0.6, 0, 0.8]])
    n = np.zeros((1, 1, 3), np.float32)
    n[0, 0] = [0, 0, 1]
    imgs = (np.arange(1.0, 5.0) * (L @ [0, 0, 1]))[:, None, None, None] * np.ones((4, 1, 1, 3))
    np.testing.assert_allclose(estimate_albedo(imgs.astype(np.float32), L, n)[0, 0], 2.5, rtol=1e-6)


def test_albedo_png_scale_is_the_99th_percentile_not_the_maximum():
    # kills B05 (max). 100 object pixels, 99 of albedo 1.0 and one of 50 (a hot pixel): 300 values,
    # 297 ones then 3 fifties; the 99th percentile (linear) sits at 0.99 * 299 = 296.01: 1 + 0.01 * 49 = 1.49.
    from psctl.albedo import albedo_png_scale
    a = np.ones((10, 10, 3), np.float32)
    a[0, 0] = 50.0
    assert albedo_png_scale(a, np.ones((10, 10), bool)) == pytest.approx(1.49, abs=1e-5)


def test_albedo_of_a_grazing_normal_is_undetermined_not_an_error():
    # kills B09 ((s > 0) dropped from the counted images). Pixel 1's normal (1, 0, 0) has n . l = 0 for
    # three lights and -0.5 for one: no light reaches it, so its albedo is 0 (it raised
    # "image / (n . l) passes float32's range" instead). Pixel 0 keeps a value.
    from psctl.albedo import estimate_albedo
    L = np.array([[0, 0, 1.0], [-0.5, 0, 0.866], [0, 0.5, 0.866], [0, -0.5, 0.866]])
    n = np.zeros((1, 2, 3), np.float32)
    n[0, 0], n[0, 1] = [0, 0, 1], [1, 0, 0]
    alb = estimate_albedo(np.full((4, 1, 2, 3), 0.5, np.float32), L, n)
    assert (alb[0, 1] == 0).all() and (alb[0, 0] > 0).all()


def test_albedo_png_scale_leaves_undetermined_zeros_out():
    # kills B06 (zeros counted). 50 object pixels at 0 (undetermined) and 50 at k / 50, k = 1..50, in
    # every channel. Without the zeros: 150 values, the 99th percentile at 0.99 * 149 = 147.51, where
    # sorted values 147..149 are all 1.0 -> 1.0. With them: 300 values, at 0.99 * 299 = 296.01, between
    # 0.98 and 1.0 -> 0.9802.
    from psctl.albedo import albedo_png_scale
    a = np.zeros((100, 1, 3), np.float32)
    a[50:, 0, :] = (np.arange(1, 51) / 50.0)[:, None]
    assert albedo_png_scale(a, np.ones((100, 1), bool)) == pytest.approx(1.0, abs=1e-6)
