"""The L2 (least squares) baseline on synthetic data, and on DiLiGenT when present."""

from __future__ import annotations

import numpy as np
import pytest

from psctl.api import estimate_normals, run_normals
from psctl.classic import l2_normals
from psctl.errors import PsctlError
from psctl.metrics import angular_error, summarize
from tests.conftest import hemisphere_lights, render_lambertian, shared_data, sphere, write_capture


def lit_everywhere(normals, mask, lights):
    """Pixels that every light reaches: no attached shadow, so Lambert's law holds exactly."""
    return mask & (np.einsum("hwc,nc->nhw", normals, lights) > 0).all(0)


def test_lambertian_sphere_without_shadows_is_exact():
    n, m = sphere(96)
    lights = hemisphere_lights(24, max_angle_deg=30)
    imgs = render_lambertian(n, m, lights, albedo=0.6)
    valid = lit_everywhere(n, m, lights)
    assert valid.sum() > 0.5 * m.sum()
    est = estimate_normals(imgs, lights, valid, method="l2")
    mae = summarize(angular_error(est, n, valid))["mae"]
    assert mae < 0.1, mae
    assert np.all(est[~valid] == 0)


def test_albedo_and_colour_do_not_matter():
    n, m = sphere(48)
    lights = hemisphere_lights(10, max_angle_deg=25, seed=3)
    valid = lit_everywhere(n, m, lights)
    rng = np.random.default_rng(0)
    albedo = rng.uniform(0.05, 1.0, m.shape + (3,)).astype(np.float32)  # per-pixel RGB albedo
    res = l2_normals(render_lambertian(n, m, lights, albedo), lights, valid)
    assert angular_error(res.normals, n, valid).max() < 0.05
    grey = albedo @ np.array([0.2989, 0.5870, 0.1140])
    assert np.allclose(res.albedo[valid], grey[valid], rtol=1e-3)


def test_streaming_equals_batch():
    n, m = sphere(32)
    lights = hemisphere_lights(8, seed=1)
    imgs = render_lambertian(n, m, lights)
    a = l2_normals(imgs, lights, m).normals
    b = l2_normals(iter(list(imgs)), lights, m).normals
    assert np.abs(a - b).max() < 1e-6


def test_dark_pixels_get_a_defined_normal_and_are_counted(capture, tmp_path):
    n, m = sphere(32)
    lights = hemisphere_lights(8, seed=2)
    imgs = render_lambertian(n, m, lights)
    imgs[:, 10:14, 10:14] = 0  # a hole of black pixels inside the mask (DiLiGenT has such)
    res = l2_normals(imgs, lights, m)
    assert np.isfinite(res.normals).all()
    assert res.dark.sum() == 16 and np.all(res.normals[res.dark] == [0, 0, 1])
    assert (res.albedo[res.dark] == 0).all() and (res.albedo[m & ~res.dark] > 0).all()
    faint = render_lambertian(n, m, lights)
    faint[:, 10:14, 10:14] *= 1e-8  # not black, but below DARK: dark, its (tiny) albedo 0 as well
    res = l2_normals(faint, lights, m)
    assert res.dark.sum() == 16 and (res.albedo[res.dark] == 0).all()
    # darkness is "at most DARK of the brightest pixel's peak": a pixel exactly at it is dark,
    # one just above it is not (a mutation audit: < instead of <= went unnoticed)
    from psctl.classic import DARK, dark_pixels

    peak = np.array([1.0, DARK, DARK * 1.001, 0.0])
    assert dark_pixels(peak).tolist() == [False, True, False, True]
    # ... the bright pixels' (their 99th percentile), not one hot pixel's: a float image with one
    # value a billion times the rest (a cosmic-ray hit) made every other pixel dark, (0, 0, 1)
    hot = render_lambertian(n, m, lights)
    hot[3, 16, 16] = 1e9
    res, clean = l2_normals(hot, lights, m), l2_normals(render_lambertian(n, m, lights), lights, m)
    assert not res.dark.any()
    others = m.copy()
    others[16, 16] = False
    assert np.abs(res.normals[others] - clean.normals[others]).max() < 1e-5
    # ... of the lit pixels: a small object on a frame that is mostly exactly 0 (no mask) too
    peak = np.concatenate([np.zeros(30000), np.full(200, 0.5), [1e9]])  # over 99 % at 0
    assert dark_pixels(peak).sum() == 30000


def test_l2_needs_three_images_and_non_coplanar_lights():
    n, m = sphere(16)
    lights = hemisphere_lights(2)
    with pytest.raises(PsctlError, match="at least 3"):
        l2_normals(render_lambertian(n, m, lights), lights, m)
    flat = np.array([[0.3, 0, 0.95], [0, 0.3, 0.95], [0.3, 0.3, 0.9055], [0.6, 0.6, 0.5292]])
    flat[:, 2] = 0  # all in the x-y plane
    flat /= np.linalg.norm(flat, axis=1, keepdims=True)
    with pytest.raises(PsctlError, match="coplanar"):
        l2_normals(np.ones((4, 16, 16, 3), np.float32), flat, m)


def test_run_normals_on_generated_capture(capture):
    r = run_normals(capture, method="l2", write=False)
    # attached shadows near the limb bias least squares: about 1 degree here
    assert r["mae"] < 1.5 and r["n_images"] == 12 and r["method"] == "l2"


def test_diligent_ball_full_size_16bit(tmp_path):
    ball = shared_data("diligent", "pmsData", "ballPNG")
    r = run_normals(ball, method="l2", out=tmp_path / "out")
    assert abs(r["mae"] - 4.1) < 0.3, r["mae"]  # published L2 figure for ball
    assert {"normal_png", "normal_exr", "error", "report"} <= set(r["outputs"])


def test_diligent_dev_split_l2_near_published():
    from psctl.eval import PAPER_DILIGENT, run_benchmark

    root = shared_data("diligent", "pmsData_crop")
    res = run_benchmark("diligent", root=root, method="l2")
    assert [o["name"] for o in res["objects"]] == ["ball", "cat", "pot1", "bear", "pot2"]
    for o in res["objects"]:
        assert np.isfinite(o["mae"])
        assert abs(o["mae"] - PAPER_DILIGENT["l2"][o["name"]]) < 1.5, o


def _shiny_sphere(n_lights: int = 40):
    """A Lambertian sphere plus a sharp specular lobe, lights up to 60 degrees off the view."""
    n, m = sphere(48)
    lights = hemisphere_lights(n_lights, 60)
    half = lights + np.array([0.0, 0.0, 1.0])
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    spec = np.clip(np.einsum("hwc,nc->nhw", n, half), 0, 1) ** 200
    images = render_lambertian(n, m, lights) + 3 * spec[..., None] * m[None, ..., None]
    return images.astype(np.float32), lights, n, m


def test_trimmed_l2_drops_shadows_and_highlights():
    """Plain L2 is bent by highlights and attached shadows; the trimmed fit keeps the
    observations Lambert's law explains (measured: 7.6 vs 0.25 degrees on this sphere)."""
    from psctl.classic import trimmed_l2_normals

    images, lights, n, m = _shiny_sphere()
    plain = angular_error(l2_normals(images, lights, m).normals, n, m).mean()
    trimmed = angular_error(trimmed_l2_normals(images, lights, m).normals, n, m).mean()
    assert plain > 5 and trimmed < 0.5


def test_trimmed_range_keeps_at_least_three():
    from psctl.classic import trimmed_range

    assert trimmed_range(96, 0.55, 0.25) == (53, 72)
    assert trimmed_range(5, 0.6, 0.3) == (2, 5)
    assert trimmed_range(3, 0.6, 0.3) == (0, 3)
    assert trimmed_range(10, 0.0, 0.0) == (0, 10)
    with pytest.raises(PsctlError, match="low \\+ high < 1"):
        trimmed_range(10, 0.6, 0.4)


def test_trimmed_l2_degenerate_kept_lights_fall_back_to_all():
    """Where a pixel's kept lights are coplanar (here: three of them, in a plane through the
    view axis), it is solved on all its observations instead, never left NaN."""
    from psctl.classic import trimmed_l2_solve

    lights = np.array([[0, 0, 1], [0.5, 0, 0.866], [-0.5, 0, 0.866], [0, 0.5, 0.866], [0, -0.5, 0.866]], np.float64)
    b_true = np.array([0.1, 0.2, 0.9])
    grey = (lights @ b_true)[:, None].astype(np.float32)
    grey[3, 0], grey[4, 0] = 0.0, 5.0  # the out-of-plane lights are the darkest and brightest: dropped
    b, dark, fallback = trimmed_l2_solve(grey, lights, 0.2, 0.2)
    assert fallback[0] and not dark[0] and np.isfinite(b).all()



def test_a_flipped_light_axis_is_noted(tmp_path):
    """y down (image rows) in light_directions.txt mirrors the normals, which makes them far
    less integrable: a note says so; the file as written gets none."""
    from tests.conftest import write_capture

    data = write_capture(tmp_path / "okPNG", n=12, size=48)
    ok = run_normals(tmp_path / "okPNG", method="l2", write=False)
    assert not any("integrable" in n for n in ok["notes"])
    write_capture(tmp_path / "flipPNG", n=12, size=48)
    np.savetxt(tmp_path / "flipPNG" / "light_directions.txt", data["lights"] * [1, -1, 1], fmt="%.6f")
    flipped = run_normals(tmp_path / "flipPNG", method="l2", write=False)
    assert flipped["mae"] > 10 and any("less integrable than their mirror image" in n for n in flipped["notes"])



def test_the_mirror_note_is_for_methods_that_read_the_light_file(capture, monkeypatch):
    """UPS-FCN never reads light_directions.txt: however its normals look, no such note."""
    import psctl.refine

    monkeypatch.setattr(psctl.refine, "mirror_ratio", lambda normals, mask=None, erode=3: 0.01)
    assert any("mirror image" in n for n in run_normals(capture, method="l2", write=False)["notes"])
    ups = run_normals(capture, method="ups-fcn", write=False, device="cpu")
    assert not any("mirror image" in n for n in ups["notes"])


def test_nearly_coplanar_lights_are_refused():
    from psctl.classic import lights_problem

    def rig(tilt: float) -> np.ndarray:  # three lights in the x-z plane, one lifted out by ``tilt``
        d = np.array([[0.5, 0.0, 1.0], [-0.5, 0.0, 1.0], [0.0, tilt, 1.0]])
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    assert "coplanar" in lights_problem(rig(1e-4))
    assert lights_problem(rig(0.05)) is None
    with pytest.raises(PsctlError, match="coplanar"):
        l2_normals(np.ones((3, 4, 4, 3), np.float32), rig(1e-4))


def test_trimmed_l2_drops_the_darkest_and_keeps_three():
    from psctl.classic import trimmed_l2_solve

    lights = hemisphere_lights(4, 30.0, seed=2)
    normals, mask = sphere(24)
    b_true = normals[mask & (normals[..., 2] > 0.8)] * 0.7  # within 37 degrees of the view: lit by every light
    grey = (b_true @ lights.T).T  # [4, P], all positive
    assert grey.min() > 0
    b, dark, fallback = trimmed_l2_solve(grey, lights, low=0.25, high=0.0)  # drop 1 of 4, keep 3
    assert not fallback.any() and not dark.any()
    np.testing.assert_allclose(b, b_true, atol=1e-5)


def test_angular_error_normalises_vectors_of_any_length():
    z = np.array([[0.0, 0.0, 1.0]])
    tilted = np.array([[0.0, 1.0, 1.0]])
    for s in (1e-300, 1e-15, 1.0, 1e200):
        assert angular_error(z * s, z)[0] == pytest.approx(0.0, abs=1e-9)
        assert angular_error(tilted * s, z)[0] == pytest.approx(45.0)
    assert angular_error(z * 0, z)[0] == 90.0  # a zero vector has no direction: as far as can be
    assert np.isnan(angular_error(np.array([[np.nan, 0, 1.0]]), z)[0])


def test_l2_normals_are_unit_at_any_float_scale():
    """Darkness is relative (DARK): float images 1e-12 or 1e-30 times as bright give the same unit
    normals (an absolute floor on the albedo shortened them: 65 degrees at 1e-12)."""
    from psctl.api import estimate_normals
    from psctl.metrics import angular_error
    from tests.conftest import hemisphere_lights, render_lambertian, sphere

    n, m = sphere(24)
    lights = hemisphere_lights(12, seed=0)
    images = render_lambertian(n, m, lights, 0.7).astype(np.float32)
    ref = estimate_normals(images, lights, m, method="l2")
    for scale in (1e-12, 1e-30):
        got = estimate_normals(images * np.float32(scale), lights, m, method="l2")
        assert np.allclose(np.linalg.norm(got[m], axis=-1), 1, atol=1e-5)
        assert angular_error(got, ref, m).max() < 0.01


def test_l2_on_a_capture_clamps_a_hot_pixel_and_says_so(tmp_path):
    """psctl normals -m l2 clamps isolated hot pixels as the networks do (it did not: session 58's
    open item): one hot value gave its pixel a normal toward that image's light, without a word.
    The note names the file."""
    from psctl.api import run_normals
    from psctl.io.images import read_image, write_image

    for name, value in (("clean", None), ("hot", 1e4)):
        folder = tmp_path / name
        arrays = write_capture(folder, n=8, size=32, intensities=False)
        names = []
        for k, img in enumerate(arrays["images"]):
            if k == 5 and value:
                img = img.copy()
                img[16, 10, :] = value
            names.append(f"{k + 1:03d}.exr")
            write_image(folder / names[-1], img, "float")
            (folder / f"{k + 1:03d}.png").unlink()
        (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    runs = {name: run_normals(tmp_path / name, method="l2", out=tmp_path / f"{name}_out", formats=["exr"])
            for name in ("clean", "hot")}
    assert not any("hot pixel" in n for n in runs["clean"]["notes"])
    assert any("hot pixel" in n and "(006.exr)" in n for n in runs["hot"]["notes"]), runs["hot"]["notes"]
    clean, hot = (read_image(tmp_path / f"{name}_out" / "normal.exr")[0] for name in ("clean", "hot"))
    # the clamped value is its neighbours' brightest: that pixel's normal moves a degree or so, no more
    angle = np.degrees(np.arccos(np.clip((clean[16, 10] * hot[16, 10]).sum(), -1, 1)))
    assert angle < 3.0, angle
    mask = arrays["mask"].copy()
    mask[16, 10] = False
    np.testing.assert_allclose(hot[mask], clean[mask], atol=1e-6)  # and no other pixel moves
    # outside the mask a hot value changes no normal: clamped on the masked image, as the networks
    # do, it is neither counted nor noted (a review finding)
    img = read_image(tmp_path / "clean" / "006.exr")[0]
    ys, xs = np.nonzero(arrays["mask"])
    y, x = ys.min(), xs.min()  # the mask's bounding box's corner: read, but off the disc
    img[y, x, :] = 1e4
    assert not arrays["mask"][y, x]
    write_image(tmp_path / "clean" / "006.exr", img, "float")
    outside = run_normals(tmp_path / "clean", method="l2", write=False)
    assert not any("hot pixel" in n for n in outside["notes"]) and outside["mae"] == runs["clean"]["mae"]
