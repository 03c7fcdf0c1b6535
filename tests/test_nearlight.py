"""Near point lights (--light-distance): the falloff is divided out exactly, and misuse is a user error."""

from __future__ import annotations

import numpy as np
import pytest

from psctl.api import run_normals
from psctl.errors import PsctlError
from psctl.io.images import write_image
from psctl.nearlight import NearLights, near_lights
from tests.conftest import write_capture
from tests.test_cli import psctl
from tests.test_cli import cli


def _falloff(light: np.ndarray, distance: float, centre: tuple[float, float], shape: tuple[int, int]) -> np.ndarray:
    """Irradiance of a point light at ``distance`` along ``light`` from ``centre``, relative to
    the centre's: D^2 / |P - X|^2 with 3-D points (x right, y up), written out independently."""
    rows, cols = np.mgrid[: shape[0], : shape[1]]
    X = np.stack([cols - centre[1], centre[0] - rows, np.zeros(shape)], -1)
    P = distance * np.asarray(light, np.float64)
    return distance**2 / ((P - X) ** 2).sum(-1)


def test_correction_undoes_the_falloff():
    near = NearLights(50.0, (10.0, 14.0))
    rows, cols = np.arange(3, 25), np.arange(30)
    for light in ([0, 0, 1], [0.6, 0, 0.8], [-0.3, 0.5, np.sqrt(1 - 0.34)]):
        fall = _falloff(np.array(light), 50.0, (10.0, 14.0), (25, 30))[3:25]
        corr = near.correction(np.array(light, np.float32), rows, cols)
        np.testing.assert_allclose(corr * fall, 1.0, rtol=1e-5)
    # brighter on the light's side, so the correction is below 1 there
    corr = near.correction(np.array([0.6, 0, 0.8]), np.array([10]), np.array([4, 14, 24]))[0]
    assert corr[1] == pytest.approx(1.0) and corr[2] < 1.0 < corr[0]


def _near_capture(folder, distance: float) -> dict:
    """The conftest sphere with each image dimmed by its point light's falloff (directions as listed)."""
    arrays = write_capture(folder, n=16, size=40)
    m = arrays["mask"]
    rows, cols = np.nonzero(m)
    centre = (rows.mean(), cols.mean())
    for k, light in enumerate(arrays["lights"]):
        img = arrays["images"][k] * _falloff(light, distance, centre, m.shape)[..., None]  # intensities included
        write_image(folder / f"{k + 1:03d}.png", 0.5 * img, "uint16", kind="linear")  # 0.5: room for the brighter side
    return arrays


def test_l2_with_the_light_distance_recovers_the_normals(tmp_path):
    write_capture(tmp_path / "distant", n=16, size=40)  # the same sphere and lights, lit from afar
    _near_capture(tmp_path / "obj", 60.0)
    base = run_normals(tmp_path / "distant", method="l2", write=False)["mae"]  # l2's own error (shadows)
    far = run_normals(tmp_path / "obj", method="l2", write=False)
    near = run_normals(tmp_path / "obj", method="l2", write=False, light_distance=60)
    assert near["light_distance"] == 60 and far["light_distance"] is None
    assert abs(near["mae"] - base) < 0.02 and far["mae"] > base + 3, (base, near["mae"], far["mae"])
    assert any("falloff" in n for n in near["notes"])


def test_estimate_normals_on_arrays_takes_the_light_distance(tmp_path):
    from psctl.api import estimate_normals
    from psctl.metrics import angular_error

    arrays = write_capture(tmp_path / "distant", n=16, size=40)
    m, lights = arrays["mask"], arrays["lights"]
    rows, cols = np.nonzero(m)
    centre = (rows.mean(), cols.mean())
    distant = np.stack([img / e for img, e in zip(arrays["images"], arrays["intensities"])])
    near_imgs = np.stack([img * _falloff(lt, 60.0, centre, m.shape)[..., None] for img, lt in zip(distant, lights)])
    gt = arrays["normals"]

    def mae(n):
        return float(angular_error(n[m], gt[m]).mean())

    base = mae(estimate_normals(distant, lights, m))
    far = mae(estimate_normals(near_imgs, lights, m))
    near = mae(estimate_normals(near_imgs, lights, m, light_distance=60))
    assert abs(near - base) < 1e-3 and far > base + 3, (base, near, far)
    with pytest.raises(PsctlError, match="ups-fcn"):
        estimate_normals(near_imgs, None, m, method="ups-fcn", light_distance=60)


def test_network_methods_read_the_corrected_images(tmp_path):
    """ps-fcn reads the images through the same reader: its input changes with the distance."""
    torch = pytest.importorskip("torch")
    from dataclasses import replace

    from psctl.infer import capture_normals
    from psctl.io.capture import load_mask, open_capture
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    _near_capture(tmp_path / "obj", 60.0)
    torch.manual_seed(0)
    w = save_weights(tmp_path / "ps_fcn.pt", PSFCN(), {"method": "ps-fcn", "train_images": 32})
    cap = open_capture(tmp_path / "obj")
    mask = load_mask(cap)
    far = capture_normals(cap, mask, "ps-fcn", w).normals
    near = capture_normals(replace(cap, near=near_lights(60, mask)), mask, "ps-fcn", w).normals
    assert np.abs(far - near).max() > 1e-3


def test_sdps_corrects_the_falloff_along_the_estimated_lights(tmp_path, fake_weights, monkeypatch):  # noqa: F811
    """sdps: LCNet reads the images as captured; its second stage and light fit read them with
    the falloff of LCNet's lights divided out."""
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    arrays = _near_capture(tmp_path / "obj", 60.0)  # its listed lights only score sdps' estimates
    far = run_normals(tmp_path / "obj", method="sdps", write=False, device="cpu")
    seen = []  # the directions the falloff followed: LCNet's (or refined), never the listed ones
    correction = NearLights.correction
    monkeypatch.setattr(NearLights, "correction", lambda self, light, rows, cols: (
        seen.append(np.asarray(light, np.float64)), correction(self, light, rows, cols))[1])
    near = run_normals(tmp_path / "obj", method="sdps", write=False, device="cpu", light_distance=60)
    listed = arrays["lights"].astype(np.float64)
    assert seen and all(np.abs(listed - s).max(axis=1).min() > 1e-3 for s in seen)
    assert near["light_distance"] == 60 and any("as estimated" in n for n in near["notes"])
    assert near["lcnet_light_mae"] == far["lcnet_light_mae"] is not None  # LCNet saw the same images
    assert near["mae"] != far["mae"]  # the second stage did not


def test_psctl_lights_refines_on_corrected_images(tmp_path, fake_weights, monkeypatch):  # noqa: F811
    from psctl.lights import run_lights

    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))
    _near_capture(tmp_path / "obj", 60.0)
    far = run_lights(tmp_path / "obj", write=False, device="cpu")
    near = run_lights(tmp_path / "obj", write=False, device="cpu", light_distance=60)
    assert near["light_distance"] == 60 and far["light_distance"] is None
    assert near["lcnet_light_mae"] == far["lcnet_light_mae"]  # LCNet saw the same images
    assert near["lights_refined"] != far["lights_refined"]  # the light fit did not (random weights: its gate may
    # keep LCNet's lights, but its residual moves)
    (tmp_path / "obj" / "light_directions.txt").unlink()  # uncalibrated: the falloff follows LCNet's lights
    assert run_lights(tmp_path / "obj", write=False, device="cpu", light_distance=60)["light_distance"] == 60
    proc = psctl("lights", tmp_path / "obj", "--no-refine", "--light-distance", "60", "--out", tmp_path / "o",
                 env={"PSCTL_WEIGHTS": str(fake_weights)})
    assert proc.returncode == 2 and "--refine" in proc.stderr and len(proc.stderr.splitlines()) == 1
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("argv, says", [
    (["--light-distance", "-5"], "positive"),
    (["--light-distance", "nan"], "positive"),
    (["--light-distance", "20"], "mask.png: --light-distance 20 pixels does not clear the object: the mask reaches"),
    (["--light-distance", "100", "-m", "ups-fcn"], "ups-fcn"),
])
def test_light_distance_misuse_is_one_line(tmp_path, argv, says):
    write_capture(tmp_path / "obj")
    proc = cli("normals", tmp_path / "obj", "--out", tmp_path / "out", *argv)
    assert proc.returncode == 2, proc.stderr
    assert len(proc.stderr.splitlines()) == 1 and says in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "out").exists()


def test_a_huge_distance_is_distant_lights(tmp_path):
    write_capture(tmp_path / "obj")
    far = run_normals(tmp_path / "obj", method="l2", write=False)["mae"]
    assert run_normals(tmp_path / "obj", method="l2", write=False, light_distance=1e200)["mae"] == pytest.approx(far)


def test_near_lights_validates():
    mask = np.zeros((40, 40), bool)
    mask[10:30, 10:30] = True
    assert near_lights(None, mask) is None
    near = near_lights(100, mask)
    assert near.distance == 100 and near.centre == pytest.approx((19.5, 19.5))
    with pytest.raises(PsctlError, match="number"):
        near_lights("far", mask)
    with pytest.raises(PsctlError, match="the mask reaches 13 pixels") as e:  # a mask given as an array
        near_lights(20, mask)
    assert e.value.path is None
    with pytest.raises(PsctlError, match="no mask: the whole frame"):
        near_lights(20, np.ones((40, 40), bool))


# --- the renderer's near lights (psctl synth --light-distance) ------------------------------------


def test_near_light_field_matches_the_model():
    import torch

    from psctl.synth import render as R

    mask = torch.zeros(30, 40, dtype=torch.bool)
    mask[5:25, 10:30] = True  # centroid (14.5, 19.5)
    lights = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    dirs, fall = R.near_light_field(lights, 90.0, mask)
    assert dirs.shape == (2, 3, 1200) and fall.shape == (2, 1200)
    np.testing.assert_allclose(dirs.norm(dim=1).numpy(), 1.0, rtol=1e-6)
    want = np.stack([_falloff(lt.numpy(), 90.0, (14.5, 19.5), (30, 40)).reshape(-1) for lt in lights])
    np.testing.assert_allclose(fall.numpy(), want, rtol=1e-5)
    # and psctl's correction is its inverse
    corr = NearLights(90.0, (14.5, 19.5)).correction(lights[1].numpy(), np.arange(30), np.arange(40))
    np.testing.assert_allclose(corr.reshape(-1) * fall[1].numpy(), 1.0, rtol=1e-5)


def test_shade_takes_a_direction_per_pixel():
    """The same direction at every pixel gives what one direction per image gives."""
    import torch

    from psctl.synth import materials as M
    from psctl.synth import render as R

    gen = torch.Generator().manual_seed(0)
    normals = torch.nn.functional.normalize(torch.randn(1, 3, 50, generator=gen) + torch.tensor([0, 0, 2.0])[:, None],
                                            dim=1)[None, 0]
    lights = torch.nn.functional.normalize(torch.tensor([[[0.3, -0.2, 1.0], [-0.5, 0.1, 0.9]]]), dim=-1)
    mat = M.ggx(torch.tensor([[0.5, 0.4, 0.3]]), torch.tensor([[0.3, 0.3, 0.3]]), torch.tensor([0.2]))
    one = R.shade(normals, lights, mat)
    per_pixel = R.shade(normals, lights[..., None].expand(1, 2, 3, 50), mat)
    torch.testing.assert_close(per_pixel, one)
    fall = torch.rand(1, 2, 50, generator=gen) + 0.5
    torch.testing.assert_close(R.shade(normals, lights, mat, falloff=fall), one * fall[:, :, None])


def test_falloff_correction_under_full_point_light_physics(tmp_path):
    """A Lambertian sphere under point lights rendered by psctl.synth (per-pixel directions and
    falloff, 19 radii away): dividing out the falloff alone takes l2 about half the way back to its
    distant-light error (1.91 -> 3.79 -> 2.78 degrees when written); the rest is the directions."""
    import torch

    from psctl.synth import materials as M
    from psctl.synth import render as R
    from tests.conftest import hemisphere_lights, sphere

    normals, mask = sphere(48)
    lights = hemisphere_lights(24, max_angle_deg=45, seed=4)
    n = torch.from_numpy(normals).permute(2, 0, 1).reshape(1, 3, -1)
    mat = M.lambertian(torch.tensor([[0.7, 0.7, 0.7]]))
    far = R.shade(n, torch.from_numpy(lights)[None], mat)[0]
    dirs, fall = R.near_light_field(torch.from_numpy(lights), 400.0, torch.from_numpy(mask))  # 19 radii
    near = R.shade(n, dirs[None], mat, falloff=fall[None])[0]
    errors = []
    for name, imgs, d in (("far", far, None), ("near", near, None), ("near", near, 400.0)):
        folder = tmp_path / name
        folder.mkdir(exist_ok=True)
        for k, img in enumerate(imgs):
            write_image(folder / f"{k + 1:03d}.png", 0.4 * img.reshape(3, 48, 48).permute(1, 2, 0).numpy(), "uint16", kind="linear")
        np.savetxt(folder / "light_directions.txt", lights)
        write_image(folder / "mask.png", mask.astype(np.float32), "uint8")
        write_image(folder / "Normal_gt.png", np.where(mask[..., None], (normals + 1) / 2, 0), "uint16")
        errors.append(run_normals(folder, method="l2", write=False, light_distance=d)["mae"])
    base, uncorrected, corrected = errors
    assert uncorrected > base + 0.5 and corrected - base < 0.65 * (uncorrected - base), errors


def test_synth_writes_near_lights(tmp_path):
    from psctl.synth.write import write_preset

    kw = dict(preset="blobby", seed=3, size=32, n_lights=8, k=1, shadows=False)
    write_preset(tmp_path / "far", **kw)
    write_preset(tmp_path / "near", light_distance=150.0, **kw)
    (obj,) = [p for p in (tmp_path / "near").iterdir() if p.is_dir()]
    assert '"light_distance": 150.0' in (obj / "synth.json").read_text()
    from psctl.io.images import read_image

    assert not np.array_equal(read_image(obj / "001.png")[0], read_image(tmp_path / "far" / obj.name / "001.png")[0])
    with pytest.raises(PsctlError, match="twice the image size"):
        write_preset(tmp_path / "bad", light_distance=50.0, **kw)


# --- the training stream's near lights (near_lights option) ----------------------------------------


def test_near_field_matches_the_renderer():
    """The stream's field, in the source frame with no turn, is the renderer's (psctl synth's)."""
    import torch

    from psctl.synth import render as R
    from psctl.synth.render import near_field

    mask = torch.zeros(20, 24, dtype=torch.bool)
    mask[4:16, 6:18] = True  # centroid (9.5, 11.5)
    lights = torch.nn.functional.normalize(torch.tensor([[0.3, -0.2, 1.0], [-0.5, 0.4, 0.8]]), dim=-1)
    dirs, fall = R.near_light_field(lights, 60.0, mask)
    rows, cols = torch.meshgrid(torch.arange(20.0), torch.arange(24.0), indexing="ij")
    src_xy = torch.stack([cols - 11.5, 9.5 - rows]).reshape(1, 2, -1)
    d2, f2 = near_field(lights[None], src_xy, torch.eye(2)[None], torch.tensor([60.0]))
    torch.testing.assert_close(d2[0], dirs)
    torch.testing.assert_close(f2[0], fall)
    # distant: the listed directions and no falloff; a mirrored frame turns the directions back
    flip = torch.diag(torch.tensor([-1.0, 1.0]))[None]
    d3, f3 = near_field(lights[None], src_xy, flip, torch.tensor([float("inf")]))
    torch.testing.assert_close(f3, torch.ones_like(f3))
    torch.testing.assert_close(d3[0], (lights * torch.tensor([-1.0, 1.0, 1.0]))[:, :, None].expand(2, 3, 480))


def test_stream_near_lights_option():
    import torch

    from psctl.errors import PsctlError as Err
    from psctl.synth.stream import SynthStream, make_config
    from tests.test_synth import SMALL

    cfg = {**SMALL, "noise": 0.0}
    off = SynthStream({**cfg, "near_lights": {"p": 0.0}}, seed=2).next_batch()
    far = SynthStream({**cfg, "near_lights": {"p": 1.0, "radii": [1e6, 1e6]}}, seed=2).next_batch()
    near = SynthStream({**cfg, "near_lights": {"p": 1.0, "radii": [3.0, 3.0]}}, seed=2).next_batch()
    assert torch.equal(off["lights"], near["lights"]) and torch.equal(off["normals"], near["normals"])
    torch.testing.assert_close(far["images"], off["images"], atol=1e-4, rtol=1e-4)  # a million radii: distant
    assert (near["images"] - off["images"]).abs().max() > 0.01
    with pytest.raises(Err, match="radii"):
        make_config(near_lights={"radii": [1.0, 5.0]})


def test_the_centre_is_the_masks_centroid_in_rows_and_columns():
    mask = np.zeros((100, 120), bool)
    mask[10:21, 40:81] = True  # off the frame's diagonal: rows 10-20, columns 40-80
    near = near_lights(5000.0, mask)
    assert near.centre == pytest.approx((15.0, 60.0))
    light = np.array([0.6, 0.0, 0.8])
    assert near.correction(light, np.array([15]), np.array([60]))[0, 0] == pytest.approx(1.0)
    c = near.correction(light, np.array([15]), np.array([40, 80]))[0]
    assert c[1] < 1 < c[0]  # the light is to the right (+x): the right end is nearer it
