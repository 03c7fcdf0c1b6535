"""Light refinement (psctl.refine.refine_lights): LCNet's lights refitted against known normals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from psctl.errors import PsctlError
from psctl.lights import LightEstimate
from psctl.refine import DEFAULT_REFINE, refine_estimate, refine_lights, sample_observations
from psctl.metrics import light_direction_error
from tests.conftest import hemisphere_lights, sphere, write_capture, weights_in
from tests.test_cli import cli
from tests.test_lcnet import psctl


def rotate_randomly(dirs: np.ndarray, degrees: float, seed: int) -> np.ndarray:
    """Each direction turned by ``degrees`` about a random axis perpendicular to it."""
    rng = np.random.default_rng(seed)
    axis = np.cross(dirs, rng.normal(size=dirs.shape))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    t = np.radians(degrees)
    out = dirs * np.cos(t) + np.cross(axis, dirs) * np.sin(t)  # Rodrigues, axis . dir = 0
    return (out / np.linalg.norm(out, axis=1, keepdims=True)).astype(np.float32)


def scene(n: int = 24, size: int = 64, specular: float = 0.0, diffuse: float = 1.0, noise: float = 0.0, seed: int = 0,
          shift: float = 0.0):
    """Grey observations [n, P] of a textured sphere (Lambertian + an optional Phong lobe), with
    optional multiplicative log-normal noise; ``shift`` > 0 makes the diffuse part max(n.l - shift, 0)
    (a falloff steeper than a cosine, as cast shadows and many real surfaces give)."""
    rng = np.random.default_rng(seed)
    normals, mask = sphere(size)
    nrm = normals[mask]
    lights = hemisphere_lights(n, 40.0, seed)
    ints = rng.uniform(0.5, 1.5, n).astype(np.float32)
    albedo = rng.uniform(0.3, 1.0, len(nrm))
    cos = np.clip(nrm @ lights.T, 0, None)  # [P, n]
    diffuse = diffuse * np.clip(cos - shift, 0, None)
    refl = 2 * cos[..., None] * nrm[:, None] - lights[None]  # mirror direction of each light
    spec = np.clip(refl[..., 2], 0, None) ** 60 * (cos > 0)  # the camera looks down +z
    obs = (albedo[:, None] * diffuse + specular * spec) * ints[None]
    obs *= np.exp(noise * rng.normal(size=obs.shape))
    return obs.T.astype(np.float32), nrm, lights, ints


def test_refine_recovers_perturbed_lights_despite_highlights():
    obs, nrm, lights, ints = scene(specular=0.8)
    start = rotate_randomly(lights, 8.0, seed=1)
    start_ints = ints * np.random.default_rng(2).uniform(0.7, 1.3, len(ints))
    assert light_direction_error(start, lights).mean() == pytest.approx(8.0, abs=1e-3)
    ref = refine_lights(obs, nrm, start, start_ints)
    assert ref.weight == 1.0 and ref.quality < DEFAULT_REFINE["gate"][0]
    assert light_direction_error(ref.directions, lights).mean() < 1.0
    rel = ref.intensities / ints
    assert np.abs(rel / rel.mean() - 1).max() < 0.03  # relative intensities, up to one scale
    # the scale of the intensities passed in is kept (their geometric mean)
    assert np.exp(np.log(ref.intensities).mean()) == pytest.approx(np.exp(np.log(start_ints).mean()), rel=1e-5)


def test_astray_fits_and_badly_explained_pixels_keep_the_lights():
    obs, nrm, lights, ints = scene(specular=1.0, diffuse=0.0)  # a mirror-like material: no diffuse part
    start = rotate_randomly(lights, 8.0, seed=1)
    ref = refine_lights(obs, nrm, start, ints, {"falloff": "lambertian"})
    assert ref.weight == 0.0 and ref.status == "astray"  # the fit shrinks the lit set to a few pixels
    np.testing.assert_allclose(ref.directions, start, atol=1e-6)
    np.testing.assert_allclose(ref.intensities, ints, rtol=1e-5)
    # the shifted falloff stays near, but explains it badly: with every observation in q (the fit of
    # sessions 20-78) the gate keeps the start
    ref = refine_lights(obs, nrm, start, ints, {"dark": 0.0, "gate": (0.05, 0.15)})
    assert ref.status == "fitted" and ref.weight == 0.0 and ref.quality > 0.15
    np.testing.assert_allclose(ref.directions, start, atol=1e-6)
    # since session 79 the dark observations (most of a mirror's) are out of q too: 0.45 -> 0.09,
    # and the gate lets a quarter of the fit in. Known and documented (docs/uncalibrated.md); here
    # the blend does not move the lights further from the truth than the start
    ref = refine_lights(obs, nrm, start, ints)
    assert ref.status == "fitted" and 0.0 < ref.weight < 0.5
    assert light_direction_error(ref.directions, lights).mean() <= light_direction_error(start, lights).mean()
    # observations a Lambertian model explains badly (here: strong noise): the gate keeps LCNet's lights
    obs, nrm, lights, ints = scene(noise=0.3)
    ref = refine_lights(obs, nrm, start, ints)
    assert ref.status == "fitted" and ref.quality > DEFAULT_REFINE["gate"][1] and ref.weight == 0.0
    np.testing.assert_allclose(ref.directions, start, atol=1e-6)


def test_shifted_falloff_undoes_the_outward_bias_of_a_steep_falloff():
    obs, nrm, lights, ints = scene(shift=0.25)
    start = rotate_randomly(lights, 8.0, seed=1)
    zenith = lambda d: np.degrees(np.arccos(np.clip(d[:, 2], -1, 1)))  # noqa: E731
    lam = refine_lights(obs, nrm, start, ints, {"falloff": "lambertian", "gate": (10.0, 20.0)})
    assert (zenith(lam.directions) - zenith(lights)).mean() > 2.0  # the Lambertian fit: pulled outward
    assert light_direction_error(lam.directions, lights).mean() > 8.0  # worse than where it started
    sh = refine_lights(obs, nrm, start, ints)  # the default falloff
    assert sh.weight == 1.0 and light_direction_error(sh.directions, lights).mean() < 6.0  # the defaults: 5 steps
    # the model is exact here: without the trim, enough alternations converge to the true lights
    exact = refine_lights(obs, nrm, start, ints, {"falloff": "shifted", "trim": (0.0, 1.0), "iters": 50})
    assert light_direction_error(exact.directions, lights).mean() < 0.05
    rel = exact.intensities / ints
    assert np.abs(rel / rel.mean() - 1).max() < 1e-3  # |s| + b: the brightness where n = l
    lam = refine_lights(obs, nrm, start, ints, {"falloff": "lambertian", "trim": (0.0, 1.0), "iters": 50,
                                                "gate": (10.0, 20.0)})
    assert light_direction_error(lam.directions, lights).mean() > 8.0
    # on a Lambertian surface both falloffs agree (b would be > 0 or ~0: the Lambertian fit is kept)
    obs, nrm, lights, ints = scene()
    a = refine_lights(obs, nrm, start, ints, {"falloff": "lambertian"})
    b = refine_lights(obs, nrm, start, ints)
    assert light_direction_error(a.directions, b.directions).max() < 0.2
    with pytest.raises(PsctlError, match="falloff must be one of"):
        refine_lights(obs, nrm, start, ints, {"falloff": "cosine"})


def test_blend_between_the_gate_values():
    obs, nrm, lights, ints = scene()
    start = rotate_randomly(lights, 8.0, seed=1)
    q = refine_lights(obs, nrm, start, ints).quality
    half = refine_lights(obs, nrm, start, ints, {"gate": (q - 0.01, q + 0.01)})
    assert half.weight == pytest.approx(0.5, abs=1e-6)
    np.testing.assert_allclose(np.linalg.norm(half.directions, axis=1), 1.0, atol=1e-5)  # blended, still unit
    err = light_direction_error(half.directions, lights).mean()
    assert 2.0 < err < 6.0  # halfway between LCNet's 8 degrees and the fit's ~0


def test_refine_input_checks_and_too_few_pixels():
    obs, nrm, lights, ints = scene(size=8)  # ~40 pixels: too few to fit
    ref = refine_lights(obs, nrm, lights, ints)
    assert ref.weight == 0.0 and not np.isfinite(ref.quality) and ref.status == "too few pixels"
    with pytest.raises(PsctlError, match=r"shapes must be .*; got \[\d+, \d+\], \[\d+, 3\]"):
        refine_lights(obs[:, :-1], nrm, lights, ints)
    with pytest.raises(PsctlError, match="unknown config keys 'gates'"):  # ignored before (helper-196)
        refine_lights(obs, nrm, lights, ints, {"gates": (0.0, 1.0)})


def test_sample_observations_reads_the_sampled_pixels_once():
    normals, mask = sphere(40)
    rng = np.random.default_rng(0)
    images = rng.uniform(0, 1, (5, 40, 40, 3)).astype(np.float32)
    calls = []

    def reader(start, box):
        calls.append(start)
        for k in range(start, 5):
            yield images[k][box]

    obs, nrm = sample_observations(reader, 5, mask, normals, {"pixels": 100, "seed": 3})
    assert obs.shape == (5, 100) and nrm.shape == (100, 3) and calls == [0]
    # every sample is a mask pixel: its grey value and its normal
    ys, xs = np.nonzero(mask)
    grey = images.mean(-1)[:, ys, xs]
    for p in range(100):
        k = np.flatnonzero(np.all(normals[ys, xs] == nrm[p], axis=1))
        assert k.size == 1 and np.allclose(grey[:, k[0]], obs[:, p], atol=1e-6)
    again, _ = sample_observations(reader, 5, mask, normals, {"pixels": 100, "seed": 3})
    assert np.array_equal(obs, again)  # seeded
    obs_all, _ = sample_observations(reader, 5, mask, normals, {"pixels": 10**6})
    assert obs_all.shape == (5, int(mask.sum()))


def test_refine_estimate_says_what_it_did():
    normals, mask = sphere(48)
    lights = hemisphere_lights(12, 35.0, 0)
    images = np.clip(np.einsum("hwc,nc->nhw", normals, lights), 0, None)[..., None].repeat(3, -1) * 0.7
    est = LightEstimate(rotate_randomly(lights, 6.0, 4), np.ones(12, np.float32), {}, {"decode": "soft"}, ["lcnet: x"])

    def reader(start, box):
        for k in range(start, 12):
            yield images[k][box]

    out = refine_estimate(est, reader, 12, mask, normals)
    assert light_direction_error(out.directions, lights).mean() < 2.0  # from 6 (12 lights in a 35-degree cone)
    assert out.info["refine"]["weight"] == 1.0 and out.info["decode"] == "soft"
    assert out.notes[0] == "lcnet: x" and "refined against PS-FCN's normals" in out.notes[-1]
    flat = refine_estimate(est, reader, 12, mask, np.zeros_like(normals))  # no usable normal
    assert flat.info["refine"]["weight"] == 0.0 and "too few usable pixels" in flat.notes[-1]
    np.testing.assert_array_equal(flat.directions, est.directions)
    assert "unfitted" not in out.info["refine"] and len(out.notes) == 2
    # an image ~200x dimmer than the rest: all its observations under the dark threshold, so its
    # light is not fitted; said, by its 1-based number (helper-208: its intensity stayed 10x too bright)
    images[4] /= 200
    dim = refine_estimate(est, reader, 12, mask, normals)
    assert dim.info["refine"]["weight"] > 0 and dim.info["refine"]["unfitted"] == [5]
    assert dim.notes[-1].startswith("lights: image 5 (1-based, in the capture's order) had too few lit pixels above "
                                    "0.01 of the object's brightest for the light fit: LCNet's light kept there")


@pytest.fixture
def stand_in_networks(monkeypatch):
    """sdps' two stages replaced by stand-ins (the wiring of the refinement is tested, not the
    networks): "LCNet" gives the true lights turned by 8 degrees, the second stage the capture's
    ground-truth normals."""
    import psctl.infer
    import psctl.lights
    from psctl.io.capture import load_ground_truth

    calls = []

    def capture_lights(capture, mask, weights=None, config=None, progress=None, flag="--weights", memo=None,
                       keep_box=None):
        n = capture.n_images
        return LightEstimate(rotate_randomly(capture.lights, 8.0, 5), np.ones(n, np.float32), {},
                             {"decode": "soft", "views": 8, "device": "cpu"}, [])

    def capture_normals(capture, mask, method, weights=None, config=None, progress=None, memo=None):
        calls.append(np.array(capture.lights))
        gt = load_ground_truth(capture)
        return psctl.infer.InferResult(gt.astype(np.float32), np.zeros(mask.shape, bool), {}, [])

    monkeypatch.setattr(psctl.lights, "capture_lights", capture_lights)
    monkeypatch.setattr(psctl.infer, "capture_normals", capture_normals)
    return calls


def test_sdps_and_lights_use_the_refined_lights(tmp_path, fake_weights, stand_in_networks):
    from psctl.api import run_normals
    from psctl.lights import run_lights

    data = write_capture(tmp_path / "aPNG", n=24, size=48, seed=1)
    with weights_in(fake_weights):
        r = run_normals(tmp_path / "aPNG", method="sdps", write=False, device="cpu")
        assert r["lights_refined"]["weight"] == 1.0 and r["lights_refined"]["status"] == "fitted"
        assert r["lcnet_light_mae"] == pytest.approx(8.0, abs=1e-3) and r["light_mae"] < 2.0
        # the stand-in LCNet says all intensities are 1; the fit on the raw (grey) images gets closer
        # to the true RGB ones (the array test below checks the division exactly)
        assert r["intensity_re"] < r["lcnet_intensity_re"]
        assert len(stand_in_networks) == 2  # the second stage ran again, on the refined lights
        assert light_direction_error(stand_in_networks[1], data["lights"]).mean() == pytest.approx(r["light_mae"],
                                                                                                   abs=1e-4)
        assert any("refined against PS-FCN†'s normals" in n for n in r["notes"])
        r0 = run_normals(tmp_path / "aPNG", method="sdps", write=False, device="cpu", refine=False)
        assert r0["lights_refined"] is None and r0["light_mae"] == pytest.approx(r["lcnet_light_mae"])
        assert len(stand_in_networks) == 3

        rl = run_lights(tmp_path / "aPNG", out=tmp_path / "lights", device="cpu")
        assert rl["lights_refined"]["weight"] == 1.0 and rl["light_mae"] == pytest.approx(r["light_mae"], abs=1e-4)
        assert rl["lcnet_light_mae"] == pytest.approx(8.0, abs=1e-3)
        written = np.loadtxt(tmp_path / "lights" / "light_directions.txt")
        assert light_direction_error(written, data["lights"]).mean() == pytest.approx(rl["light_mae"], abs=1e-4)
        rl0 = run_lights(tmp_path / "aPNG", write=False, device="cpu", refine=False)
        assert rl0["lights_refined"] is None and rl0["light_mae"] == pytest.approx(8.0, abs=1e-3)


def test_lights_without_a_normals_network_says_so(tmp_path, fake_weights):
    import shutil

    from psctl.lights import run_lights

    folder = tmp_path / "w"
    folder.mkdir()
    shutil.copy(fake_weights / "lcnet.pt", folder / "lcnet.pt")
    write_capture(tmp_path / "aPNG", n=6, size=40, seed=1)
    with weights_in(folder):
        r = run_lights(tmp_path / "aPNG", write=False, device="cpu")
        assert r["lights_refined"] is None and r["light_mae"] == pytest.approx(r["lcnet_light_mae"])
        assert any("not refined" in n for n in r["notes"])


def test_cli_no_refine_flag(tmp_path, fake_weights):
    write_capture(tmp_path / "aPNG", n=6, size=40, seed=1)
    proc = psctl("lights", tmp_path / "aPNG", "--weights", fake_weights / "lcnet.pt", "--no-refine", "--json",
                 "--out", tmp_path / "o", env={"PSCTL_WEIGHTS": str(fake_weights)})
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert r["lights_refined"] is None and r["light_mae"] == pytest.approx(r["lcnet_light_mae"])


def test_falloff_option_reaches_the_fit(tmp_path, fake_weights, stand_in_networks, monkeypatch):
    from psctl.api import estimate_lights, estimate_normals, run_normals
    from psctl.errors import PsctlError
    from psctl.lights import run_lights

    data = write_capture(tmp_path / "aPNG", n=24, size=48, seed=1)
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    r = run_normals(tmp_path / "aPNG", method="sdps", write=False, device="cpu")
    assert r["lights_refined"]["falloff"] == DEFAULT_REFINE["falloff"] == "shifted"
    for fall in ("lambertian", "shifted"):
        r = run_normals(tmp_path / "aPNG", method="sdps", write=False, device="cpu", falloff=fall)
        assert r["lights_refined"]["falloff"] == fall
        rl = run_lights(tmp_path / "aPNG", write=False, device="cpu", falloff=fall)
        assert rl["lights_refined"]["falloff"] == fall
    r = run_normals(tmp_path / "aPNG", method="sdps", write=False, device="cpu", falloff="lambertian", refine=False)
    assert r["lights_refined"] is None and any("--falloff is unused without --refine" in n for n in r["notes"])
    r = run_normals(tmp_path / "aPNG", method="l2", write=False, falloff="lambertian")
    assert any("--falloff is unused (only sdps" in n for n in r["notes"])
    assert not any("--no-refine" in n for n in r["notes"])
    r = run_normals(tmp_path / "aPNG", method="l2", write=False, refine=False)
    assert any("--no-refine is unused (only sdps" in n for n in r["notes"])
    rl = run_lights(tmp_path / "aPNG", write=False, device="cpu", falloff="lambertian", refine=False)
    assert any("--falloff is unused without --refine" in n for n in rl["notes"])
    with pytest.raises(PsctlError, match="--falloff must be shifted or lambertian"):
        run_lights(tmp_path / "aPNG", write=False, device="cpu", falloff="cosine")
    for call in (lambda: estimate_normals(data["images"], data["lights"], method="l2", falloff="cosine"),
                 lambda: estimate_lights(data["images"], falloff="cosine")):
        with pytest.raises(PsctlError, match="--falloff must be"):
            call()
    for cmd in (["lights", tmp_path / "aPNG", "--out", tmp_path / "o"], ["normals", tmp_path / "aPNG", "-m", "sdps"],
                ["eval", "--benchmark", "folder", "--root", tmp_path, "-m", "sdps"]):
        proc = psctl(*cmd, "--falloff", "cosine", env={"PSCTL_WEIGHTS": str(fake_weights)})
        assert proc.returncode == 2 and "Traceback" not in proc.stderr
        assert proc.stderr.strip().splitlines() == ["error: --falloff must be shifted or lambertian, not 'cosine'"]
    assert not (tmp_path / "o").exists() and not (tmp_path / "aPNG" / "psctl").exists()


def test_sdps_runs_the_second_stage_once_when_the_gate_keeps_lcnets_lights(tmp_path, fake_weights, stand_in_networks,
                                                                           monkeypatch):
    import psctl.refine
    from psctl.api import run_normals

    write_capture(tmp_path / "aPNG", n=12, size=48, seed=1)
    monkeypatch.setitem(psctl.refine.DEFAULT_REFINE, "gate", (-2.0, -1.0))  # every fit counts as bad
    with weights_in(fake_weights):
        r = run_normals(tmp_path / "aPNG", method="sdps", write=False, device="cpu")
    assert r["lights_refined"]["weight"] == 0.0 and len(stand_in_networks) == 1
    assert r["light_mae"] == pytest.approx(r["lcnet_light_mae"])
    assert any("LCNet's lights kept" in n for n in r["notes"])


def test_array_sdps_refines_too(monkeypatch, fake_weights):
    """estimate_normals(method="sdps"): LCNet, the second stage, the fit on the raw images, the
    second stage again on the refined lights (stand-ins for both networks)."""
    import psctl.infer
    import psctl.lights
    import psctl.refine
    from psctl.api import estimate_normals
    from tests.conftest import render_lambertian

    normals, mask = sphere(48)
    lights = hemisphere_lights(24, 35.0, 0)
    ints = np.random.default_rng(0).uniform(0.5, 1.5, 24).astype(np.float32)
    images = render_lambertian(normals, mask, lights, 0.7) * ints[:, None, None, None]
    seen = []

    def array_lights(images, mask=None, weights=None, config=None, model=None, progress=None):
        return LightEstimate(rotate_randomly(lights, 8.0, 5), np.ones(24, np.float32), {}, {}, [])

    def array_normals(imgs, dirs, mask, method, weights=None, config=None, progress=None):
        seen.append((np.array(dirs), np.array(imgs)))
        return psctl.infer.InferResult(normals, np.zeros(mask.shape, bool), {}, [])

    monkeypatch.setattr(psctl.lights, "array_lights", array_lights)
    monkeypatch.setattr(psctl.infer, "array_normals", array_normals)
    with weights_in(fake_weights):
        out = estimate_normals(images, None, mask, method="sdps", device="cpu")
    assert len(seen) == 2 and np.array_equal(out, normals)
    assert light_direction_error(seen[1][0], lights).mean() < 4.0  # the second pass got the refined lights (LCNet: 8)
    # and images divided by the refined intensities: the same up to one scale in every image
    ratio = seen[1][1][:, mask].mean(-1).mean(-1) / (images[:, mask].mean(-1).mean(-1) / ints)
    assert np.ptp(ratio) < 0.2 * ratio.mean()  # (about 1.0 with LCNet's intensities of 1)
    # the caller's shading model reaches the fit (mutation review, session 39: dropping it went unseen)
    fits = []
    real = psctl.refine.refine_arrays
    monkeypatch.setattr(psctl.refine, "refine_arrays", lambda *a: fits.append(a[5]) or real(*a))  # (.., config, saturated)
    with weights_in(fake_weights):
        estimate_normals(images, None, mask, method="sdps", device="cpu", falloff="lambertian")
    assert fits and all(f is not None and f["falloff"] == "lambertian" for f in fits)


def bumps(size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Normals [H, W, 3] of a smooth, asymmetric height field (three Gaussian bumps on a tilted
    plane, orthographic), from its analytic gradient, and a disc mask [H, W]."""
    c = (np.arange(size) + 0.5) / size * 2 - 1
    x, y = np.meshgrid(c, -c)  # row 0 is the top: y up
    zx, zy = np.full_like(x, 0.2), np.full_like(x, -0.1)
    for (cx, cy, h, s) in ((-0.3, 0.2, 0.6, 0.35), (0.35, -0.1, 0.4, 0.25), (0.0, -0.45, 0.5, 0.3)):
        g = h * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
        zx, zy = zx - g * (x - cx) / (s * s), zy - g * (y - cy) / (s * s)
    n = np.stack([-zx, -zy, np.ones_like(x)], -1)  # z = f(x, y): normal (-f_x, -f_y, 1)
    mask = x**2 + y**2 < 0.85
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32), mask


@pytest.mark.parametrize("shape", ["bumps", "sphere"])
def test_integrability_roll_undoes_a_turn_about_the_view_axis(shape):
    from psctl.refine import integrability_roll, turn_about_view_axis

    normals, mask = bumps() if shape == "bumps" else sphere(64)
    t0, gain0, k = integrability_roll(normals, mask)
    assert abs(t0) < 0.2 and gain0 == pytest.approx(1.0, abs=1e-3) and k > 1000
    for turn in (-6.0, 3.0, 10.0):
        t, gain, _ = integrability_roll(turn_about_view_axis(normals, turn), mask)
        assert t == pytest.approx(-turn, abs=0.3) and gain > 1.0
    # turns about an in-plane axis are not what it measures: a 6-degree tilt gives a small roll
    tilt = np.radians(6.0)
    rx = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    assert abs(integrability_roll(normals @ rx.T, mask)[0]) < 1.5
    # the mask's edge is left out: garbage in a 2-pixel rim changes nothing
    from scipy.ndimage import binary_erosion

    rim = mask & ~binary_erosion(mask, iterations=2)
    noisy = normals.copy()
    junk = np.random.default_rng(0).normal(size=(rim.sum(), 3))
    noisy[rim] = junk / np.linalg.norm(junk, axis=1, keepdims=True)
    assert integrability_roll(noisy, mask)[0] == pytest.approx(t0, abs=1e-9)
    assert integrability_roll(normals, np.zeros_like(mask))[2] == 0


def test_the_roll_follows_the_captures_orientation():
    """A mirrored map's roll is the negative of the map's, a half-turned one's the same, and
    the mirror ratio is the same for all four (forward differences at a corner pixel made them
    depend on the orientation: the same capture's lights 5.97 / 5.27 / 5.92 degrees off as stored
    / flipped up-down / left-right, a review, session 73). On bumps turned 4 degrees, with noise."""
    from psctl.refine import integrability_roll, mirror_ratio, turn_about_view_axis

    normals, mask = bumps(80)
    turned = turn_about_view_axis(normals, 4.0) + np.random.default_rng(2).normal(0, 0.03, normals.shape)
    turned /= np.linalg.norm(turned, axis=-1, keepdims=True)
    views = {"as stored": (turned, mask, 1),
             "left-right": (np.flip(turned, 1) * [-1, 1, 1], np.flip(mask, 1), -1),
             "up-down": (np.flip(turned, 0) * [1, -1, 1], np.flip(mask, 0), -1),
             "half turn": (np.flip(turned, (0, 1)) * [-1, -1, 1], np.flip(mask, (0, 1)), 1),
             "transposed": (np.swapaxes(turned, 0, 1)[..., [1, 0, 2]] * [-1, -1, 1], mask.T, -1)}
    t0 = integrability_roll(turned, mask)[0]
    assert t0 == pytest.approx(-4.0, abs=0.5)
    r0 = mirror_ratio(turned, mask)
    for name, (n, m, sign) in views.items():
        assert integrability_roll(n, m)[0] == pytest.approx(sign * t0, abs=1e-9), name
        assert mirror_ratio(n, m) == pytest.approx(r0, rel=1e-9), name


def test_roll_estimate_turns_lights_and_normals_together():
    from psctl.refine import integrability_roll, roll_estimate, turn_about_view_axis

    normals, mask = bumps()
    lights = hemisphere_lights(12, 35.0, 0)
    est = LightEstimate(turn_about_view_axis(lights, 5.0), np.ones(12, np.float32), {}, {"refine": {"weight": 1.0}}, [])
    turned = turn_about_view_axis(normals, 5.0)
    same, n = roll_estimate(est, turned, mask, {"roll": False})
    assert same is est and n is turned
    out, n = roll_estimate(est, turned, mask, {"roll": True})
    assert out.info["refine"]["roll"]["status"] == "applied" and out.info["refine"]["weight"] == 1.0
    assert out.info["refine"]["roll"]["degrees"] == pytest.approx(-5.0, abs=0.3)
    assert light_direction_error(out.directions, lights).mean() < 0.3
    assert np.degrees(np.arccos(np.clip((n * normals).sum(-1)[mask], -1, 1))).mean() < 0.3
    assert "turned -5.0 degrees about the view axis" in out.notes[-1]
    t = integrability_roll(turned, mask)[0]
    np.testing.assert_allclose(out.directions, turn_about_view_axis(est.directions, t), atol=1e-6)
    far, n = roll_estimate(est, turned, mask, {"roll": True, "max_roll": 2.0})
    assert far.info["refine"]["roll"]["status"] == "refused" and n is turned
    np.testing.assert_array_equal(far.directions, est.directions)
    few, _ = roll_estimate(est, turned, mask & (np.arange(64)[:, None] < 8), {"roll": True})
    assert few.info["refine"]["roll"]["status"] == "too few pixels"
    still, _ = roll_estimate(est, normals, mask, {"roll": True})  # a roll of -0.04 degrees: no "+0.0" note
    assert still.info["refine"]["roll"]["status"] == "applied" and still.notes == est.notes


def test_sdps_and_lights_apply_the_roll_when_it_is_on(tmp_path, fake_weights, monkeypatch):
    """With "roll" on, sdps and psctl lights read the roll from the normals of the refined lights
    and turn both; they give the same lights. Stand-ins: "LCNet" gives the true lights turned 8
    degrees about random axes, the second stage the ground-truth normals turned 6 degrees about
    the view axis (the rotation the fit cannot see)."""
    import psctl.infer
    import psctl.lights
    import psctl.refine
    from psctl.api import run_normals
    from psctl.io.capture import load_ground_truth
    from psctl.lights import run_lights
    from psctl.refine import turn_about_view_axis

    def capture_lights(capture, mask, weights=None, config=None, progress=None, flag="--weights", memo=None,
                       keep_box=None):
        return LightEstimate(rotate_randomly(capture.lights, 8.0, 5), np.ones(capture.n_images, np.float32), {},
                             {"decode": "soft", "views": 8, "device": "cpu"}, [])

    calls = []

    def capture_normals(capture, mask, method, weights=None, config=None, progress=None, memo=None):
        calls.append(1)
        gt = load_ground_truth(capture)
        return psctl.infer.InferResult(turn_about_view_axis(gt, 6.0).astype(np.float32), np.zeros(mask.shape, bool),
                                       {}, [])

    monkeypatch.setattr(psctl.lights, "capture_lights", capture_lights)
    monkeypatch.setattr(psctl.infer, "capture_normals", capture_normals)
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    write_capture(tmp_path / "aPNG", n=24, size=64, seed=1)
    monkeypatch.setitem(psctl.refine.DEFAULT_REFINE, "roll", False)
    off = run_normals(tmp_path / "aPNG", method="sdps", write=False, device="cpu")
    monkeypatch.setitem(psctl.refine.DEFAULT_REFINE, "roll", True)
    calls.clear()
    on = run_normals(tmp_path / "aPNG", method="sdps", write=False, device="cpu")
    assert len(calls) == 2  # the roll needs no third pass: the normals are turned as the lights are
    assert on["lights_refined"]["roll"]["status"] == "applied"
    assert on["lights_refined"]["roll"]["degrees"] == pytest.approx(-6.0, abs=1.0)
    # a turn about the view axis moves lights near it little: 6 sin(zenith) degrees
    assert off["light_mae"] > 1.5 and on["light_mae"] < 0.6
    assert off["mae"] > 3.0 and on["mae"] < 0.1
    calls.clear()
    lights = run_lights(tmp_path / "aPNG", write=False, device="cpu")
    assert len(calls) == 2  # psctl lights runs the second stage again on the refined lights to read the roll
    assert lights["light_mae"] == pytest.approx(on["light_mae"], abs=1e-4)
    assert lights["lights_refined"]["roll"] == on["lights_refined"]["roll"]
    r0 = run_normals(tmp_path / "aPNG", method="sdps", write=False, device="cpu", refine=False)
    assert r0["lights_refined"] is None  # --no-refine: no fit and no roll


def test_roll_option_reaches_sdps_lights_and_eval(tmp_path, fake_weights, stand_in_networks, monkeypatch):
    from psctl.api import estimate_lights, run_normals
    from psctl.lights import run_lights

    data = write_capture(tmp_path / "aPNG", n=24, size=48, seed=1)
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    for roll in (True, False):
        r = run_normals(tmp_path / "aPNG", method="sdps", write=False, device="cpu", roll=roll)
        assert ("roll" in r["lights_refined"]) is roll
        rl = run_lights(tmp_path / "aPNG", write=False, device="cpu", roll=roll)
        assert ("roll" in rl["lights_refined"]) is roll
        if roll:  # the stand-in second stage gives the ground truth: nothing to turn
            assert abs(r["lights_refined"]["roll"]["degrees"]) < 0.5
    r = run_normals(tmp_path / "aPNG", method="l2", write=False, roll=True)
    assert any("--roll/--no-roll is unused (only sdps" in n for n in r["notes"])
    rl = run_lights(tmp_path / "aPNG", write=False, device="cpu", roll=False, refine=False)
    assert any("--roll/--no-roll is unused without --refine" in n for n in rl["notes"])
    from psctl.errors import PsctlError

    with pytest.raises(PsctlError, match="roll must be True, False or None"):
        estimate_lights(data["images"], data["mask"], device="cpu", roll="no")
    # the CLI flags reach the reports (in this process, with the stand-in networks: the default is
    # on, so --no-roll is what shows that a flag got through; --roll, the default, once, to show
    # that it parses)
    env = {"PSCTL_WEIGHTS": str(fake_weights)}
    for cmd, key in ((["eval", "--benchmark", "folder", "--root", tmp_path, "-m", "sdps"], "eval"),
                     (["normals", tmp_path / "aPNG", "-m", "sdps", "--out", tmp_path / "n"], "normals"),
                     (["lights", tmp_path / "aPNG", "--out", tmp_path / "l"], "lights")):
        for flag in (("--roll", "--no-roll") if key == "eval" else ("--no-roll",)):
            proc = cli(*cmd, flag, "--json", "-q", env=env)
            assert proc.returncode == 0, proc.stderr
            out = json.loads(proc.stdout)
            refined = out["objects"][0]["lights_refined"] if key == "eval" else out["lights_refined"]
            assert ("roll" in refined) is (flag == "--roll"), (cmd, flag)


def test_array_api_applies_the_roll(monkeypatch, fake_weights):
    """estimate_normals(method="sdps") and estimate_lights with a second stage whose normals are
    the truth turned 6 degrees about the view axis (stand-ins for both networks)."""
    import psctl.infer
    import psctl.lights
    from psctl.api import estimate_lights, estimate_normals
    from psctl.refine import turn_about_view_axis
    from tests.conftest import render_lambertian

    normals, mask = bumps()
    lights = hemisphere_lights(24, 35.0, 0)
    images = render_lambertian(normals, mask, lights, 0.7)

    def array_lights(images, mask=None, weights=None, config=None, model=None, progress=None):
        return LightEstimate(rotate_randomly(lights, 8.0, 5), np.ones(24, np.float32), {}, {}, [])

    def array_normals(imgs, dirs, mask, method, weights=None, config=None, progress=None):
        return psctl.infer.InferResult(turn_about_view_axis(normals, 6.0), np.zeros(mask.shape, bool), {}, [])

    monkeypatch.setattr(psctl.lights, "array_lights", array_lights)
    monkeypatch.setattr(psctl.infer, "array_normals", array_normals)
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))

    def err(n):
        return float(np.degrees(np.arccos(np.clip((n * normals).sum(-1)[mask], -1, 1))).mean())

    on = estimate_normals(images, None, mask, method="sdps", device="cpu")  # the default
    off = estimate_normals(images, None, mask, method="sdps", device="cpu", roll=False)
    assert err(off) > 3.0 and err(on) < 0.5
    d_on, _ = estimate_lights(images, mask, device="cpu")
    d_off, _ = estimate_lights(images, mask, device="cpu", roll=False)
    assert light_direction_error(d_on, lights).mean() < light_direction_error(d_off, lights).mean() - 1.0


@pytest.mark.parametrize("weight", [0.0, 0.6])
def test_second_stage_runs_the_network_only_when_needed(weight):
    """psctl.sdps.second_stage over a stand-in Source: how often the second stage runs, and what
    comes back, for sdps (normals) and psctl lights (lights alone), with the roll on and off."""
    import psctl.infer
    from psctl.refine import turn_about_view_axis
    from psctl.sdps import Source, second_stage

    normals, mask = bumps()
    lights = hemisphere_lights(12, 35.0, 0)
    lcnet = LightEstimate(lights, np.ones(12, np.float32), {}, {}, [])
    refined = turn_about_view_axis(lights, 1.0).astype(np.float32)
    seen = []

    def run(est):  # the truth turned 4 degrees about the view axis, whatever the lights
        seen.append(est.directions)
        return psctl.infer.InferResult(turn_about_view_axis(normals, 4.0), np.zeros(mask.shape, bool), {}, ["net"])

    def refine(est, n, config):
        return LightEstimate(refined if weight else est.directions, est.intensities, {}, {"refine": {"weight": weight}},
                             [])

    source = Source(run, refine, mask)
    for roll, want_normals, passes in ((True, True, 1 + (weight > 0)), (False, True, 1 + (weight > 0)),
                                       (True, False, 1 + (weight > 0)), (False, False, 1)):
        seen.clear()
        est, net = second_stage(source, lcnet, True, {"roll": roll}, normals=want_normals)
        assert len(seen) == passes, (roll, want_normals)
        np.testing.assert_array_equal(seen[0], lights)  # the first pass gets LCNet's lights
        if passes == 2:
            np.testing.assert_array_equal(seen[1], refined)
        assert ("roll" in est.info["refine"]) is roll
        if want_normals:
            err = np.degrees(np.arccos(np.clip((net.normals * normals).sum(-1)[mask], -1, 1))).mean()
            assert (err < 0.2) if roll else (err > 1.0)  # turned back with the lights, or left (4 sin(zenith))
        else:
            assert net is None
    seen.clear()
    est, net = second_stage(source, lcnet, False, {"roll": True})  # --no-refine: one pass, LCNet's lights
    assert len(seen) == 1 and est is lcnet and "refine" not in est.info


def test_refine_blocks_of_pixels_give_the_one_block_answer(monkeypatch):
    """refine_lights works on blocks of pixels (memory); block edges must not change the fit."""
    import psctl.refine as refine_mod

    obs, nrm, lights, ints = scene(size=64, specular=0.3, noise=0.05)  # ~3,200 pixels
    obs[:, 5] = np.nan  # a dropped pixel moves the block edges against the pixel indices
    start = rotate_randomly(lights, 5.0, seed=3)
    monkeypatch.setattr(refine_mod, "_REFINE_BLOCK", 10 ** 9)
    whole = refine_lights(obs, nrm, start, ints)
    for block in (2048, 333, 7):
        monkeypatch.setattr(refine_mod, "_REFINE_BLOCK", block)
        part = refine_lights(obs, nrm, start, ints)
        assert part.status == whole.status and part.weight == whole.weight
        assert part.quality == pytest.approx(whole.quality, rel=1e-12)
        np.testing.assert_allclose(part.directions, whole.directions, atol=1e-6)
        np.testing.assert_allclose(part.intensities, whole.intensities, rtol=1e-6)
    assert whole.weight > 0 and np.isfinite(whole.quality)  # a fit that counted, not one kept as passed in


def test_trimming_keeps_outliers_out_of_the_fit():
    """A few pixels of one image far too bright (a highlight, a hot pixel): the default trim
    drops them from that light's fit; without trimming they pull every light off."""
    obs, nrm, lights, ints = scene()
    bad = obs.copy()
    bad[0, np.random.default_rng(4).random(obs.shape[1]) < 0.03] *= 20.0
    start = rotate_randomly(lights, 4.0, seed=5)
    gate = {"gate": (10.0, 20.0)}  # use the fit whatever its residual: compare the fits themselves
    trimmed = refine_lights(bad, nrm, start, ints, gate)
    untrimmed = refine_lights(bad, nrm, start, ints, {**gate, "trim": (0.0, 1.0)})
    assert trimmed.status == untrimmed.status == "fitted"
    kept, pulled = (light_direction_error(r.directions, lights).mean() for r in (trimmed, untrimmed))
    assert kept < 2.0 and pulled > 3.0 and pulled > 2.5 * kept


def test_eval_rows_keep_lcnets_own_light_error(tmp_path, fake_weights, stand_in_networks, monkeypatch):  # noqa: F811
    from psctl.eval import run_benchmark

    write_capture(tmp_path / "root" / "aPNG", n=24, size=48, seed=1)
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    res = run_benchmark("folder", root=tmp_path / "root", method="sdps", device="cpu")
    o = res["objects"][0]
    assert o["lcnet_light_mae"] == pytest.approx(8.0, abs=1e-3) and o["light_mae"] < 2.0
    assert res["mean_lcnet_light_mae"] == pytest.approx(8.0, abs=1e-3)


def test_refine_leaves_undetermined_rigs_alone():
    """Fewer than three lights, or coplanar ones: any light 'fits' (residual 0), so none is fitted."""
    obs, nrm, lights, ints = scene()
    two = refine_lights(obs[:2], nrm, lights[:2], ints[:2])
    assert two.status == "undetermined" and two.weight == 0.0
    np.testing.assert_array_equal(two.directions, lights[:2])
    flat = lights.copy()
    flat[:, 1] = 0.0  # all in the x-z plane
    flat /= np.linalg.norm(flat, axis=1, keepdims=True)
    assert refine_lights(obs, nrm, flat, ints).status == "undetermined"
    assert refine_lights(obs, nrm, lights, ints).status == "fitted"


def test_erode_mask_is_scipys_binary_erosion():
    """psctl.refine.erode_mask replaces scipy.ndimage.binary_erosion (its import cost every
    calibrated run 0.17 s): the same masks, borders included, for random shapes and iterations."""
    from scipy.ndimage import binary_erosion

    from psctl.refine import erode_mask

    rng = np.random.default_rng(3)
    for _ in range(200):
        h, w = (int(v) for v in rng.integers(1, 24, 2))
        m = rng.random((h, w)) < rng.uniform(0.3, 1.0)
        it = int(rng.integers(1, 5))
        assert np.array_equal(erode_mask(m, it), binary_erosion(m, iterations=it)), (h, w, it)


def test_decode_memo_serves_boxes_inside_the_kept_one(tmp_path):
    from psctl.io.capture import DecodeMemo

    rng = np.random.default_rng(0)
    a, b, c = (tmp_path / n for n in ("a.png", "b.png", "c.png"))
    for f in (a, b, c):
        f.write_bytes(b"stand-in")  # the memo looks at the files' stamps only
    info = object()  # passed through as is
    big = rng.random((10, 12, 3), dtype=np.float32)
    memo = DecodeMemo(10 * 12 * 3 * 4)
    memo.keep(a, (slice(2, 12), slice(3, 15)), big, info, DecodeMemo.stamp(a))
    orig, big[:] = big.copy(), -1.0  # the memo holds a copy: the reader's array may be reused
    big = orig
    rgb, got_info = memo.take(a, (slice(4, 8), slice(5, 9)))
    assert got_info is info and rgb.shape == (4, 4, 3)
    np.testing.assert_array_equal(rgb, big[2:6, 2:6])
    assert memo.take(a, (slice(1, 8), slice(5, 9))) is None  # not inside the kept box
    assert memo.take(b, (slice(4, 8), slice(5, 9))) is None
    assert memo.take(a, (slice(4, 8, 2), slice(5, 9))) is None  # a step: not a crop
    assert memo.served == 1 and memo.used == big.nbytes
    # the budget is full: another image is not kept; a clipped box (shape not the slices') never is,
    # nor one without a stamp (a file that cannot be looked at)
    memo.keep(b, (slice(0, 2), slice(0, 2)), big[:2, :2], info, DecodeMemo.stamp(b))
    assert memo.take(b, (slice(0, 2), slice(0, 2))) is None
    roomy = DecodeMemo(1 << 20)
    roomy.keep(c, (slice(0, 20), slice(0, 12)), big, info, DecodeMemo.stamp(c))  # 10 rows where the box says 20
    roomy.keep(b, (slice(0, 2), slice(0, 2)), big[:2, :2], info, None)
    assert roomy.take(c, (slice(0, 5), slice(0, 5))) is None and roomy.used == 0
    # a box holding the kept one replaces it; a smaller one does not
    roomy.keep(a, (slice(4, 8), slice(5, 9)), big[:4, :4], info, DecodeMemo.stamp(a))
    roomy.keep(a, (slice(2, 12), slice(3, 15)), big, info, DecodeMemo.stamp(a))
    assert roomy.used == big.nbytes and roomy.take(a, (slice(2, 4), slice(3, 4))) is not None
    roomy.keep(a, (slice(4, 8), slice(5, 9)), np.zeros((4, 4, 3), np.float32), info, DecodeMemo.stamp(a))
    np.testing.assert_array_equal(roomy.take(a, (slice(4, 8), slice(5, 9)))[0], big[2:6, 2:6])
    # kept as float32, and counted so against the budget, whatever it was given in
    exact = DecodeMemo(2 * 2 * 3 * 4)
    exact.keep(b, (slice(0, 2), slice(0, 2)), big[:2, :2].astype(np.float64), info, DecodeMemo.stamp(b))
    assert exact.used == 48 and exact.take(b, (slice(0, 2), slice(0, 2)))[0].dtype == np.float32
    # a file changed since it was read is read again, and its copy freed
    a.write_bytes(b"changed, and longer")
    assert roomy.take(a, (slice(4, 8), slice(5, 9))) is None and roomy.used == 0


@pytest.mark.parametrize("extras", ["plain", "ambient, sRGB, near lights"])
def test_sdps_passes_decode_each_image_once(tmp_path, fake_weights, monkeypatch, extras):  # noqa: F811
    """sdps' second stage, the light fit and the second stage again read the capture three times,
    each divided by other intensities: the images are decoded once (DecodeMemo, cache_mb), and
    every pass gets what it got when each decoded them itself; the memo keeps the images as
    decoded, before the ambient image, sRGB and the near lights' falloff are applied."""
    from dataclasses import replace

    import psctl.io.capture
    from psctl.io.capture import load_mask, open_capture
    from psctl.io.images import write_image
    from psctl.nearlight import NearLights
    from psctl.sdps import capture_source

    write_capture(tmp_path / "cap", n=12, size=40, seed=2)
    if extras != "plain":
        write_image(tmp_path / "cap" / "ambient.png", np.full((40, 40, 3), 0.02, np.float32), "uint16", kind="linear")
    cap = open_capture(tmp_path / "cap", encoding="linear" if extras == "plain" else "srgb")
    if extras != "plain":
        cap = replace(cap, near=NearLights(60.0, (20.0, 20.0)))
    mask = load_mask(cap)
    reads = []
    real = psctl.io.capture.read_image

    def counting(path, *a, **k):
        if path in cap.image_paths:
            reads.append(path)
        return real(path, *a, **k)

    monkeypatch.setattr(psctl.io.capture, "read_image", counting)
    est = LightEstimate(rotate_randomly(cap.lights, 5.0, 3), np.linspace(0.5, 1.5, 12, dtype=np.float32), {})
    results = {}
    for mb in (0, 64):
        reads.clear()
        source = capture_source(cap, mask, "ps-fcn-dagger", fake_weights / "ps_fcn_dagger.pt",
                                {"device": "cpu", "cache_mb": mb})
        first = source.normals(est)
        refined = source.refine(est, first.normals, {"gate": (1.0, 2.0), "max_change": 180.0})  # always applied
        assert refined.info["refine"]["weight"] == 1.0, refined.info
        again = source.normals(refined)
        results[mb] = (first.normals, refined.directions, refined.intensities, again.normals, len(reads))
    assert results[0][4] == 3 * 12  # without the memo: every pass decodes every image
    assert results[64][4] == 12
    for x, y in zip(results[0][:4], results[64][:4]):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(results[0][0], results[0][3])  # the second pass saw other lights


def _small_object_capture(folder, seed: int, cx: int):
    """12 images of 120 px, the mask a disc of radius 20 about (60, cx): LCNet's crop (margin 15)
    lies strictly inside the box the second stage reads (halo 24). Returns (capture, mask, LCNet's
    box, the second stage's box)."""
    from psctl.infer import first_read_box
    from psctl.io.capture import load_mask, open_capture
    from psctl.io.images import write_image
    from psctl.arrays import bounding_box
    from psctl.lights import DEFAULT_LIGHTS

    write_capture(folder, n=12, size=120, seed=seed)
    yy, xx = np.mgrid[:120, :120]
    write_image(folder / "mask.png", ((yy - 60) ** 2 + (xx - cx) ** 2 < 400).astype(np.float32), "uint8")
    cap = open_capture(folder)
    mask = load_mask(cap)
    lc, net = bounding_box(mask, DEFAULT_LIGHTS["margin"]), first_read_box(cap, mask)
    assert lc != net and all(n.start < c.start and c.stop < n.stop for c, n in zip(lc, net))  # two boxes: one held
    return cap, mask, lc, net


@pytest.mark.parametrize("command", ["normals", "lights"])
def test_lcnet_and_the_passes_after_it_decode_each_image_once(tmp_path, fake_weights, monkeypatch, command):  # noqa: F811
    """`psctl normals -m sdps` and `psctl lights`: LCNet's pass decodes each image with the box the
    second stage reads (which holds LCNet's crop) and keeps it in the DecodeMemo; the second
    stage, the light fit and the second stage again take it from there (before them all, the
    mask's edge for snap_mask reads each image once, keeping nothing). The same lights and
    normals as when every pass decodes for itself."""
    import psctl.io.capture
    from psctl.infer import DEFAULT_INFER
    from psctl.lights import run_lights

    import psctl

    _small_object_capture(tmp_path / "cap", seed=2, cx=60)
    reads = []
    real = psctl.io.capture.read_image

    def counting(path, *a, **k):
        if path.parent == tmp_path / "cap" and path.name[0].isdigit():
            reads.append(path)
        return real(path, *a, **k)

    monkeypatch.setattr(psctl.io.capture, "read_image", counting)
    got = {}
    for mb in (0, 64):
        monkeypatch.setitem(DEFAULT_INFER, "cache_mb", mb)
        reads.clear()
        arrays = {}
        if command == "normals":
            rep = psctl.run_normals(tmp_path / "cap", method="sdps", lcnet=fake_weights / "lcnet.pt",
                                    weights=fake_weights / "ps_fcn_dagger.pt", device="cpu", write=False,
                                    arrays=arrays)
        else:
            rep = run_lights(tmp_path / "cap", weights=fake_weights / "lcnet.pt", device="cpu", write=False,
                             normals_weights=fake_weights / "ps_fcn_dagger.pt")
        assert rep["lights_refined"] is not None
        got[mb] = (rep["light_mae"], rep["intensity_re"], arrays.get("normals"), len(reads))
    # (with a mask file, one more read: the mask's edge for snap_mask, whole frames not kept)
    assert got[0][3] >= 4 * 12 and got[64][3] == 2 * 12, (got[0][3], got[64][3])
    assert got[0][:2] == got[64][:2]
    if command == "normals":
        np.testing.assert_array_equal(got[0][2], got[64][2])


def test_lcnet_reading_the_second_stages_box_gives_what_reading_its_own_crop_does(tmp_path, fake_weights):  # noqa: F811
    """capture_lights decoding the larger box of the pass after it (keep_box) and cutting LCNet's
    crop from it gives the lights of reading the crop itself, and checks the ambient image on the
    crop as before: an image the ambient image blacks out inside the crop, though lit outside it
    in the larger box, is the same one-line error."""
    from psctl.io.capture import DecodeMemo, open_capture
    from psctl.io.images import read_image, write_image
    from psctl.lights import capture_lights

    cap, mask, lc, net = _small_object_capture(tmp_path / "cap", seed=3, cx=57)
    weights, cfg = fake_weights / "lcnet.pt", {"device": "cpu"}
    own = capture_lights(cap, mask, weights, cfg)
    memo = DecodeMemo(64 << 20)
    cut = capture_lights(cap, mask, weights, cfg, memo=memo, keep_box=net)
    np.testing.assert_array_equal(own.directions, cut.directions)
    np.testing.assert_array_equal(own.intensities, cut.intensities)
    assert own.notes == cut.notes and memo.take(cap.image_paths[0], net) is not None

    # image 5: lit in the larger box only where the ambient image leaves it, outside the crop
    img = read_image(tmp_path / "cap" / "005.png")[0]
    amb = np.zeros_like(img)
    amb[lc] = img[lc]
    img[net[0].start:net[0].start + 3, net[1].start:net[1].start + 3] = 0.3
    write_image(tmp_path / "cap" / "005.png", img, "uint16")
    write_image(tmp_path / "cap" / "ambient.png", amb, "uint16", kind="linear")
    cap = open_capture(tmp_path / "cap")
    errors = []
    for kw in ({}, {"memo": DecodeMemo(64 << 20), "keep_box": net}):
        with pytest.raises(PsctlError) as e:
            capture_lights(cap, mask, weights, cfg, **kw)
        errors.append(str(e.value))
    assert errors[0] == errors[1] and "subtracting it leaves 005.png black" in errors[0]


def test_saturated_observations_left_out_of_the_fit():
    """NaN marks an observation not to use (refine_capture: a pixel at its integer file's top code).
    Clipped values taken as they are pull the lights; left out, the fit is as on the unclipped
    observations of the other pixels (a QA helper: 51 % saturated took sdps' lights 3.2 -> 6.5 deg)."""
    obs, nrm, lights, ints = scene()
    start = rotate_randomly(lights, 8.0, seed=1)
    top = np.quantile(obs[obs > 0], 0.7)  # 30 % of the lit observations clipped
    clipped = np.minimum(obs, top)
    marked = np.where(obs >= top, np.nan, obs).astype(np.float32)
    whole = light_direction_error(refine_lights(obs, nrm, start, ints).directions, lights).mean()  # 0.65
    as_is = light_direction_error(refine_lights(clipped, nrm, start, ints).directions, lights).mean()  # 6.05
    left_out = refine_lights(marked, nrm, start, ints)  # 0.84
    assert left_out.weight == 1.0 and light_direction_error(left_out.directions, lights).mean() < whole + 0.3
    assert as_is > whole + 3.0
    # NaN only where nothing is clipped: the same answer as without (no observation lost)
    np.testing.assert_array_equal(refine_lights(obs, nrm, start, ints).directions,
                                  refine_lights(np.where(obs > 10 * obs.max(), np.nan, obs), nrm, start, ints).directions)
    # a pixel with no usable observation at all is left out, not a NaN answer
    marked[:, :5] = np.nan
    assert np.isfinite(refine_lights(marked, nrm, start, ints).directions).all()


def test_refine_capture_marks_the_saturated_observations(tmp_path, monkeypatch):
    """refine_capture hands refine_lights NaN exactly where an integer image is at its top code
    (in any channel), and the other observations as read."""
    import psctl.refine as pr
    from psctl.io.capture import load_images, load_mask, open_capture
    from psctl.io.images import write_image

    arrays = write_capture(tmp_path / "c", n=8, size=32, bits=8, intensities=False)
    for k, img in enumerate(arrays["images"]):
        write_image(tmp_path / "c" / f"{k + 1:03d}.png", np.clip(img * 2.5, 0, 1), "uint8")  # clipped
    cap = open_capture(tmp_path / "c")
    mask = load_mask(cap)
    seen = {}

    def spy(obs, nrm, d, e, config=None):
        seen["obs"] = obs
        return pr.Refinement(d.astype(np.float32), e.astype(np.float32), 0.0, 1.0)

    monkeypatch.setattr(pr, "refine_lights", spy)
    est = LightEstimate(arrays["lights"].astype(np.float32), np.ones(8, np.float32), {})
    pr.refine_capture(cap, mask, est, arrays["normals"])
    imgs = load_images(cap)[:, mask]  # [N, P, 3], as read (intensities 1)
    top = (imgs >= 1.0).any(-1)
    assert 0.05 < top.mean() < 0.95
    obs = seen["obs"]
    assert obs.shape == top.shape and np.array_equal(np.isnan(obs), top)
    np.testing.assert_allclose(obs[~top], imgs.mean(-1)[~top], rtol=1e-6)


def test_lights_and_sdps_without_a_mask_read_the_object_found(tmp_path, fake_weights, monkeypatch):
    """Without mask.png, LCNet and the light fit read the object ``find_object`` finds (they took
    the whole frame: synthetic objects before a dark background 32.2 degrees, 6.42 with the mask
    or the found object): the lights are those of the same folder with that object as its
    mask.png, a note says so and the report gives its size. psctl lights and sdps alike; sdps'
    normals cover the object found and FOUND_GROW pixels around it."""
    from psctl.api import _found_file_note, run_normals
    from psctl.infer import FOUND_GROW, grow_mask
    from psctl.io.capture import open_capture
    from psctl.io.images import write_image
    from psctl.lights import run_lights
    from psctl.masks import NO_MASK_PREFIX, capture_shading, find_object

    arrays = write_capture(tmp_path / "bPNG", n=6, size=32, seed=1, mask=False)
    found = find_object(capture_shading(open_capture(tmp_path / "bPNG"))[0])
    m = arrays["mask"]
    assert found.mask is not None and not (found.mask & ~m).any() and found.mask.sum() > 0.9 * m.sum()
    write_capture(tmp_path / "cPNG", n=6, size=32, seed=1, mask=False)
    write_image(tmp_path / "cPNG" / "mask.png", found.mask.astype(np.float32), "uint8")
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    import psctl.refine as pr

    read = []  # the masks the light fit and the roll read (the fake network's fit may not move the lights)
    fit, roll = pr.refine_capture, pr.roll_estimate
    monkeypatch.setattr(pr, "refine_capture", lambda cap, mask, *a, **k: read.append(mask) or fit(cap, mask, *a, **k))
    monkeypatch.setattr(pr, "roll_estimate", lambda est, n, mask, *a: read.append(mask) or roll(est, n, mask, *a))
    for refine in (False, True):
        b, c = ({}, {})
        rb = run_lights(tmp_path / "bPNG", write=False, device="cpu", refine=refine, arrays=b)
        run_lights(tmp_path / "cPNG", write=False, device="cpu", refine=refine, arrays=c)
        np.testing.assert_allclose(b["directions"], c["directions"], atol=1e-6)
        np.testing.assert_allclose(b["intensities"], c["intensities"], atol=1e-6)
        assert rb["found_object"] == found.info and NO_MASK_PREFIX + found.notes[0] in rb["notes"]
    # a network trained at an exposure (input_mean) refines: its mean is the found object's, as a mask's
    # (the lit pixels' rule of a capture without a mask split the object: cat 5.80 vs 5.81 degrees)
    import torch

    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    torch.manual_seed(2)
    save_weights(tmp_path / "ps_fcn.pt", PSFCN(), {"method": "ps-fcn", "train_images": 32, "input_mean": 0.05})
    for name in ("dPNG", "ePNG"):  # a black spot on the object: in the object found (a hole), not lit
        spot = write_capture(tmp_path / name, n=6, size=32, seed=1, mask=False)["images"]
        spot[:, 13:19, 13:19] = 0
        for k, img in enumerate(spot):
            write_image(tmp_path / name / f"{k + 1:03d}.png", img, "uint16", kind="linear")
    spot = find_object(capture_shading(open_capture(tmp_path / "dPNG"))[0]).mask
    assert spot[13:19, 13:19].all()
    write_image(tmp_path / "ePNG" / "mask.png", spot.astype(np.float32), "uint8")
    import psctl.infer

    scales, infer = [], psctl.infer.capture_normals  # (a random network's refinement is refused: spied)
    monkeypatch.setattr(psctl.infer, "capture_normals",
                        lambda *a, **k: (lambda r: scales.append(r.info["exposure_scale"]) or r)(infer(*a, **k)))
    for name in ("dPNG", "ePNG"):
        run_lights(tmp_path / name, write=False, device="cpu", normals_weights=tmp_path / "ps_fcn.pt")
    assert len(scales) == 2 and scales[0] == scales[1]
    monkeypatch.setattr(psctl.infer, "capture_normals", infer)
    # psctl normals' networks too (since session 65): the found object's mean, as its mask.png's
    said = [[n for n in run_normals(tmp_path / name, method="ps-fcn", weights=tmp_path / "ps_fcn.pt", write=False,
                                    device="cpu")["notes"] if "images scaled by" in n][0] for name in ("dPNG", "ePNG")]
    assert said[0].split()[4] == said[1].split()[4] and "inside the object found without a mask" in said[0], said
    del read[4:]  # (the spot's masks)
    nb = {}
    rb = run_normals(tmp_path / "bPNG", method="sdps", write=False, device="cpu", arrays=nb)
    rc = run_normals(tmp_path / "cPNG", method="sdps", write=False, device="cpu")
    words = find_object(capture_shading(open_capture(tmp_path / "bPNG"))[0], reader="sdps").notes[0]
    assert NO_MASK_PREFIX + words in rb["notes"] and not any("no mask.png" in n for n in rc["notes"])
    assert rb["found_object"] == found.info and rc["found_object"] is None
    assert rb["light_mae"] is not None and rb["light_mae"] == rc["light_mae"] and rb["intensity_re"] == rc["intensity_re"]
    # the normals: the object and FOUND_GROW pixels around it (the second stage reads the object, since session 65)
    grown = grow_mask(found.mask, FOUND_GROW)
    assert np.array_equal(nb["mask"], grown) and not nb["normals"][~grown].any()
    assert (np.linalg.norm(nb["normals"][grown], axis=-1) > 0.99).all()
    assert NO_MASK_PREFIX + _found_file_note(False) in rb["notes"]
    assert len(read) == 8 and all(np.array_equal(r, found.mask) for r in read)  # b: found; c: its mask.png


def test_the_object_found_is_written_as_a_mask(tmp_path, fake_weights, monkeypatch):
    """Without mask.png, psctl lights and sdps write the object they found as mask_found.png (0 /
    255, as a mask.png): copied into the capture folder it is read as the mask and gives the same
    lights. A later run that reads a mask removes the earlier file."""
    import shutil

    from psctl.api import run_normals
    from psctl.io.capture import load_mask, open_capture
    from psctl.io.images import read_image
    from psctl.lights import run_lights
    from psctl.masks import FOUND_FILE, capture_shading, find_object

    write_capture(tmp_path / "bPNG", n=6, size=32, seed=1, mask=False)
    found = find_object(capture_shading(open_capture(tmp_path / "bPNG"))[0]).mask
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    r = run_lights(tmp_path / "bPNG", out=tmp_path / "out", device="cpu")
    assert r["outputs"]["mask_found"] == str(tmp_path / "out" / FOUND_FILE)
    assert any(FOUND_FILE in n for n in r["notes"])
    png = read_image(tmp_path / "out" / FOUND_FILE)
    png = png[0] if isinstance(png, tuple) else png
    assert np.array_equal(np.asarray(png).reshape(32, 32, -1)[..., 0] > 0.5, found)
    s = run_normals(tmp_path / "bPNG", method="sdps", out=tmp_path / "sd", device="cpu")
    assert s["outputs"]["mask_found"] == str(tmp_path / "sd" / FOUND_FILE) and (tmp_path / "sd" / FOUND_FILE).is_file()
    assert json.loads((tmp_path / "sd" / "report.json").read_text())["written"][FOUND_FILE]
    from psctl.io.images import png_colour_tag  # a mask is numbers, as mask.png and the normal maps: no sRGB chunk

    assert png_colour_tag(tmp_path / "out" / FOUND_FILE) == png_colour_tag(tmp_path / "sd" / FOUND_FILE) == ""
    shutil.copytree(tmp_path / "bPNG", tmp_path / "nomask")
    shutil.copy(tmp_path / "out" / FOUND_FILE, tmp_path / "bPNG" / "mask.png")  # the user takes it as the mask
    assert np.array_equal(load_mask(open_capture(tmp_path / "bPNG")), found)
    again = run_lights(tmp_path / "bPNG", out=tmp_path / "out", device="cpu")
    assert again["light_mae"] == r["light_mae"] and not (tmp_path / "out" / FOUND_FILE).exists()
    assert "mask_found" not in again["outputs"] and any(f"removed {FOUND_FILE}" in n for n in again["notes"])
    masked = run_normals(tmp_path / "bPNG", method="sdps", out=tmp_path / "sd", device="cpu")
    assert not (tmp_path / "sd" / FOUND_FILE).exists()  # removed with a note, as the other files (helper-159)
    assert any(n.startswith("outputs: removed ") and FOUND_FILE in n for n in masked["notes"]), masked["notes"]
    from psctl.io.images import write_image

    (tmp_path / "flat").mkdir()  # no mask and no object found (a lit frame): no file
    for k in range(6):
        write_image(tmp_path / "flat" / f"{k:03d}.png", np.full((32, 40, 3), 0.2 + 0.1 * k, np.float32), "uint16")
    shutil.copytree(tmp_path / "sd", tmp_path / "fl")
    (tmp_path / "sd" / FOUND_FILE).write_bytes(b"mine")  # a file of the user's: kept, and said to be replaced
    (tmp_path / "sd" / ".psctl-normals").unlink()
    flat = run_normals(tmp_path / "flat", method="sdps", out=tmp_path / "sd", device="cpu")
    assert flat["found_object"]["used"] is False and "mask_found" not in flat["outputs"]
    assert (tmp_path / "sd" / FOUND_FILE).read_bytes() == b"mine" and not any(FOUND_FILE in n for n in flat["notes"])
    s = run_normals(tmp_path / "nomask", method="sdps", out=tmp_path / "fl", device="cpu")  # an earlier run's file:
    flat = run_normals(tmp_path / "flat", method="sdps", out=tmp_path / "fl", device="cpu")  # removed, with a note
    assert not (tmp_path / "fl" / FOUND_FILE).exists()
    assert any(f"removed {FOUND_FILE}" in n and "read no object found" in n for n in flat["notes"]), flat["notes"]
    (tmp_path / "out" / FOUND_FILE).write_bytes(b"mine")  # psctl lights keeps a file of the user's too
    kept = run_lights(tmp_path / "bPNG", out=tmp_path / "out", device="cpu")
    assert (tmp_path / "out" / FOUND_FILE).read_bytes() == b"mine" and not any(FOUND_FILE in n for n in kept["notes"])
    # psctl lights and psctl normals into one folder (both default to PATH/psctl): each replaces the
    # other's mask_found.png (the same search) without calling it a file of the user's
    import functools

    sdps = functools.partial(run_normals, method="sdps")  # (the fake weights: no calibrated network)
    for first, then in ((run_lights, sdps), (sdps, run_lights)):
        shutil.rmtree(tmp_path / "both", ignore_errors=True)
        first(tmp_path / "nomask", out=tmp_path / "both", device="cpu")
        r2 = then(tmp_path / "nomask", out=tmp_path / "both", device="cpu")
        assert "mask_found" in r2["outputs"] and not any("replaced" in n for n in r2["notes"]), r2["notes"]


def test_exposure_notes_name_the_object_found(tmp_path, fake_weights, monkeypatch):
    """A dim capture without mask.png: LCNet's exposure note says its mean is the found object's,
    not "inside the mask" (there is none; session 63's wording)."""
    from psctl.io.images import write_image
    from psctl.lights import run_lights

    imgs = write_capture(tmp_path / "dimPNG", n=6, size=32, seed=1, mask=False)["images"]
    for k, img in enumerate(imgs * 0.02):  # a mean under LCNet's band (0.01)
        write_image(tmp_path / "dimPNG" / f"{k + 1:03d}.png", img, "uint16")
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    notes = run_lights(tmp_path / "dimPNG", write=False, device="cpu", refine=False)["notes"]
    lcnet = [n for n in notes if n.startswith("lcnet: the images' mean")]
    assert len(lcnet) == 1 and "inside the object found without a mask" in lcnet[0], notes


def test_near_lights_without_a_mask_sit_about_the_object_found(tmp_path, fake_weights, monkeypatch):
    """--light-distance without mask.png: the point lights sit about the centre of the object
    LCNet reads (the one found by brightness), as the same folder with it as mask.png would place
    them, for psctl lights and sdps alike (they were centred on the whole frame, and a distance had
    to clear the frame's corners: 40 pixels here was refused)."""
    from psctl.api import run_normals
    from psctl.infer import FOUND_GROW, grow_mask
    from psctl.io.capture import open_capture
    from psctl.io.images import write_image
    from psctl.lights import run_lights
    from psctl.masks import capture_shading, find_object
    from psctl.nearlight import near_lights

    arrays = write_capture(tmp_path / "bPNG", n=6, size=32, seed=1, mask=False)
    m = arrays["mask"]
    found = find_object(capture_shading(open_capture(tmp_path / "bPNG"))[0]).mask
    write_capture(tmp_path / "cPNG", n=6, size=32, seed=1, mask=False)
    write_image(tmp_path / "cPNG" / "mask.png", found.astype(np.float32), "uint8")
    with pytest.raises(PsctlError, match="whole frame"):  # 40 does not clear the frame's corners
        near_lights(40, np.ones_like(m))
    centre = near_lights(40, found).centre
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    import psctl.sdps as ps

    seen = []  # where the lights sit, as the second stage's capture holds them
    source = ps.capture_source
    monkeypatch.setattr(ps, "capture_source", lambda cap, *a, **k: seen.append(cap.near) or source(cap, *a, **k))
    b, c = {}, {}
    rb = run_lights(tmp_path / "bPNG", write=False, device="cpu", light_distance=40, arrays=b)
    run_lights(tmp_path / "cPNG", write=False, device="cpu", light_distance=40, arrays=c)
    np.testing.assert_allclose(b["directions"], c["directions"], atol=1e-6)
    line = f"lights: points 40 pixels from the object's centre (row {centre[0]:.0f}, column {centre[1]:.0f})"
    assert rb["light_distance"] == 40 and any(n.startswith(line) for n in rb["notes"])
    nb, nc = {}, {}
    rb = run_normals(tmp_path / "bPNG", method="sdps", write=False, device="cpu", light_distance=40, arrays=nb)
    rc = run_normals(tmp_path / "cPNG", method="sdps", write=False, device="cpu", light_distance=40, arrays=nc)
    assert rb["light_distance"] == 40 and any(n.startswith(line) for n in rb["notes"])
    assert rb["light_mae"] == rc["light_mae"] and np.array_equal(nb["mask"], grow_mask(found, FOUND_GROW))
    assert len(seen) == 4 and all(s is not None and s.centre == centre for s in seen)
    # the calibrated networks read the object found too, their lights about its centre (session 65)
    import torch

    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    torch.manual_seed(2)
    save_weights(tmp_path / "ps_fcn.pt", PSFCN(), {"method": "ps-fcn", "train_images": 32})
    pb, pc = {}, {}
    kw = {"method": "ps-fcn", "weights": tmp_path / "ps_fcn.pt", "write": False, "device": "cpu", "light_distance": 40}
    rp = run_normals(tmp_path / "bPNG", arrays=pb, **kw)
    run_normals(tmp_path / "cPNG", arrays=pc, **kw)
    assert rp["light_distance"] == 40 and any(n.startswith(line) for n in rp["notes"])
    np.testing.assert_allclose(pb["normals"][found], pc["normals"][found], atol=1e-5)
    with pytest.raises(PsctlError, match="the object found without a mask reaches"):
        run_lights(tmp_path / "bPNG", write=False, device="cpu", light_distance=10)


def test_integer_arrays_leave_their_top_code_out_of_the_fit(monkeypatch):
    """estimate_lights / estimate_normals(sdps) given uint8 or uint16 arrays mark the top code as a
    capture folder's reader does (a review finding: only the folder path did)."""
    import psctl.refine as pr
    from psctl.api import _saturated

    rng = np.random.default_rng(0)
    raw = rng.integers(0, 256, (4, 6, 5, 3)).astype(np.uint8)
    top = _saturated(raw)
    assert top is not None and np.array_equal(top, (raw == 255).any(-1)) and _saturated(raw / 255.0) is None
    assert np.array_equal(_saturated(raw.astype(np.uint16) * 257), top)  # uint16: 65535
    seen = {}

    def spy(obs, nrm, d, e, config=None):
        seen["obs"] = obs
        return pr.Refinement(d.astype(np.float32), e.astype(np.float32), 0.0, 1.0)

    monkeypatch.setattr(pr, "refine_lights", spy)
    images = raw.astype(np.float32) / 255
    normals = np.zeros((6, 5, 3), np.float32)
    normals[..., 2] = 1
    est = LightEstimate(np.tile(np.float32([0, 0, 1]), (4, 1)), np.ones(4, np.float32), {})
    pr.refine_arrays(images, None, est, normals, saturated=top)
    assert np.array_equal(np.isnan(seen["obs"]), top.reshape(4, -1))


def test_lights_and_sdps_say_when_the_estimates_lie_to_one_side(tmp_path, fake_weights, monkeypatch):
    """LCNet learnt from rigs around the view axis; lights to one side come out pulled toward it (a
    QA finding: 12 degrees, silently). A note says so when the estimates lean (psctl.lights.one_sided),
    and names the side; estimates around the axis get none."""
    import psctl.lights
    from psctl.api import run_normals
    from psctl.lights import ONE_SIDED, one_sided, one_sided_notes, run_lights

    around = hemisphere_lights(24, seed=3)
    around[:, :2] -= around[:, :2].mean(0)  # centred: no lean at all
    around /= np.linalg.norm(around, axis=1, keepdims=True)
    quadrant = np.abs(around)  # upper right: x > 0, y > 0
    left = around.copy()
    left[:, 0] = -np.abs(left[:, 0])
    assert one_sided(around) < 0.1 and one_sided(quadrant) > 0.6
    assert one_sided_notes(around) == []
    assert "(the upper right;" in one_sided_notes(quadrant)[0] and "(the left;" in one_sided_notes(left)[0]
    # the threshold: just above it a note, just below none (two unit lights in the x-z plane, at
    # x = p and x = -q: lean (p - q) / (p + q))
    for lean, said in ((ONE_SIDED + 0.01, True), (ONE_SIDED - 0.01, False)):
        q = 0.3
        p = q * (1 + lean) / (1 - lean)
        d = np.array([[p, 0, np.sqrt(1 - p * p)], [-q, 0, np.sqrt(1 - q * q)]])
        assert one_sided(d) == pytest.approx(lean, abs=1e-9)
        assert bool(one_sided_notes(d)) == said

    write_capture(tmp_path / "aPNG", n=24, size=32, seed=1)
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    for dirs, said in ((around, False), (quadrant, True)):
        def capture_lights(capture, mask, weights=None, config=None, progress=None, flag="--weights", memo=None,
                           keep_box=None, dirs=dirs):
            return LightEstimate(dirs.astype(np.float32), np.ones(len(dirs), np.float32), {},
                                 {"decode": "soft", "views": 8, "device": "cpu"}, [])

        monkeypatch.setattr(psctl.lights, "capture_lights", capture_lights)
        for r in (run_lights(tmp_path / "aPNG", write=False, device="cpu", refine=False),
                  run_normals(tmp_path / "aPNG", method="sdps", write=False, device="cpu", refine=False)):
            assert any("lie to one side of the view axis" in n for n in r["notes"]) == said


# cast-shadow zeros out of the fit and out of the gate's q, the gate scaled with them (helper-195,
# session 79: the rule written first passed on three fresh synthetic sets)

def _shadowed(seed=0, frac=0.08):
    """scene() with cast-shadow zeros: a random 8 % of the lit observations set to 0."""
    obs, nrm, lights, ints = scene(seed=seed)
    rng = np.random.default_rng(seed + 10)
    return np.where((obs > 0) & (rng.random(obs.shape) < frac), np.float32(0), obs), nrm, lights, ints


def test_without_dark_observations_gate_q_changes_nothing():
    """dark 0 is the fit of sessions 20-78: which q the gate reads is then moot."""
    obs, nrm, lights, ints = _shadowed()
    start = rotate_randomly(lights, 5.0, seed=1)
    a = refine_lights(obs, nrm, start, ints, {"dark": 0.0, "gate_q": "all"})
    b = refine_lights(obs, nrm, start, ints, {"dark": 0.0, "gate_q": "fit"})
    assert np.array_equal(a.directions, b.directions) and a.quality == b.quality


def test_dark_zeros_left_out_keep_the_fit_at_the_truth():
    obs, nrm, lights, ints = _shadowed()
    before = refine_lights(obs, nrm, lights, ints, {"gate": (1.0, 2.0), "dark": 0.0})  # ungated, zeros in
    now = refine_lights(obs, nrm, lights, ints, {"gate": (1.0, 2.0)})  # the default: zeros out
    assert DEFAULT_REFINE["dark"] > 0
    assert light_direction_error(now.directions, lights).mean() < light_direction_error(before.directions, lights).mean()


def test_gate_q_all_is_the_old_q_without_cast_shadows():
    obs, nrm, lights, ints = scene(seed=3)  # no zeros where lit (noise-free Lambertian)
    start = rotate_randomly(lights, 5.0, seed=1)
    a = refine_lights(obs, nrm, start, ints, {"dark": 0.0})
    b = refine_lights(obs, nrm, start, ints, {"gate_q": "all"})
    # only observations near or past the terminator are dark: they move the fit a little
    assert b.quality == pytest.approx(a.quality, rel=1e-3)


def test_gate_q_fit_leaves_the_shadows_out_of_q():
    obs, nrm, lights, ints = _shadowed()
    qa = refine_lights(obs, nrm, lights, ints, {"gate_q": "all"}).quality
    qf = refine_lights(obs, nrm, lights, ints).quality  # the default, "fit"
    assert DEFAULT_REFINE["gate_q"] == "fit" and qf < qa
    with pytest.raises(PsctlError, match="gate_q must be 'all' or 'fit'"):
        refine_lights(obs, nrm, lights, ints, {"gate_q": "some"})
