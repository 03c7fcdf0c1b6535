"""PS-FCN / PS-FCN+N / UPS-FCN: architecture, weights files, and the inference engine.

The networks have seeded random weights: what is tested here (shapes, file formats, and that
streaming, chunking, cropping and tiling give the same normals as the plain computation) does
not depend on their values.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from psctl.errors import PsctlError
from psctl.infer import all_at_once_normals, array_normals, crop_region, plan_tiles, run_network, run_views
from psctl.models import HALO, RECEPTIVE_RADIUS
from psctl.models.ps_fcn import PSFCN, normalize_observations
from psctl.models.weights import build_network, check_state_dict, read_weights, save_weights
from psctl.symmetry import SYMMETRIES, transform_dirs, transform_images, untransform_dirs, untransform_images
from tests.conftest import hemisphere_lights, random_biases, render_lambertian, sphere, write_capture

# The authors' release (models/PS_FCN.py, fuse max, no batch norm, lights in): name -> shape.
OFFICIAL = {
    "extractor.conv1.0.weight": (64, 6, 3, 3), "extractor.conv1.0.bias": (64,),
    "extractor.conv2.0.weight": (128, 64, 3, 3), "extractor.conv2.0.bias": (128,),
    "extractor.conv3.0.weight": (128, 128, 3, 3), "extractor.conv3.0.bias": (128,),
    "extractor.conv4.0.weight": (256, 128, 3, 3), "extractor.conv4.0.bias": (256,),
    "extractor.conv5.0.weight": (256, 256, 3, 3), "extractor.conv5.0.bias": (256,),
    "extractor.conv6.0.weight": (256, 128, 4, 4),
    "extractor.conv7.0.weight": (128, 128, 3, 3), "extractor.conv7.0.bias": (128,),
    "regressor.deconv1.0.weight": (128, 128, 3, 3), "regressor.deconv1.0.bias": (128,),
    "regressor.deconv2.0.weight": (128, 128, 3, 3), "regressor.deconv2.0.bias": (128,),
    "regressor.deconv3.0.weight": (128, 64, 4, 4),
    "regressor.est_normal.0.weight": (3, 64, 3, 3),
}


def model(lights: bool = True, seed: int = 0, double: bool = False) -> PSFCN:
    """Seeded random weights. double: float64, for checks of exactness (streaming, chunking,
    cropping, tiling) that float32 rounding would blur; the engine follows the model's dtype."""
    torch.manual_seed(seed)
    net = PSFCN({"lights": lights}).eval()
    return net.double() if double else net


def scene(n: int = 8, h: int = 37, w: int = 45, seed: int = 0):
    """Random non-negative images [n, h, w, 3], unit lights [n, 3], an off-centre mask."""
    rng = np.random.default_rng(seed)
    images = rng.uniform(0, 1, (n, h, w, 3)).astype(np.float32)
    lights = hemisphere_lights(n, 60, seed)
    yy, xx = np.mgrid[:h, :w]
    mask = (yy - 0.45 * h) ** 2 + (xx - 0.55 * w) ** 2 < (0.35 * min(h, w)) ** 2
    return images, lights, mask


def stream(images, lights, mask, net=None, normalization="none", q=None, **config) -> np.ndarray:
    net = net or model()
    n = len(images)

    def reader(start, box):
        for k in range(start, n):
            yield images[k][box]

    return run_network(net, reader, n, lights, mask, normalization, q, config).normals


# --- architecture ----------------------------------------------------------------------------

def n_params(net: torch.nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


def test_parameter_count():
    assert n_params(model()) == 2_210_048
    assert n_params(model(lights=False)) == 2_210_048 - 3 * 64 * 9  # UPS-FCN: no light input


def test_official_names_and_shapes():
    assert {k: tuple(v.shape) for k, v in model().state_dict().items()} == OFFICIAL


def test_forward_shapes_and_unit_normals():
    net = model()
    x = torch.rand(2, 5, 3, 16, 20)
    lights = torch.nn.functional.normalize(torch.randn(2, 5, 3), dim=-1)
    with torch.no_grad():
        out = net(x, lights)
    assert out.shape == (2, 3, 16, 20)
    assert torch.allclose(out.norm(dim=1), torch.ones(2, 16, 20), atol=1e-5)


def test_receptive_field_within_halo():
    """An output pixel depends on inputs at most RECEPTIVE_RADIUS px away (all 4 stride phases),
    and HALO covers it: the premise of exact tiling and cropping."""
    net = model()
    size, centre = 64, 28
    x = torch.rand(4, 1, 3, size, size, requires_grad=True)
    lights = torch.tensor([[[0.3, 0.2, 0.93]]]).expand(4, 1, 3)
    out = net(x, lights)
    # scene p looks at output pixel (centre + p, centre + p): every phase mod 4 in y and x
    sum(out[p, :, centre + p, centre + p].sum() for p in range(4)).backward()
    radii = []
    for p in range(4):
        ys, xs = np.nonzero(x.grad[p, 0].abs().sum(0).numpy())
        c = centre + p
        radii.append(max(c - ys.min(), ys.max() - c, c - xs.min(), xs.max() - c))
    assert max(radii) == RECEPTIVE_RADIUS
    assert HALO >= RECEPTIVE_RADIUS and HALO % 4 == 0


# --- weights files ---------------------------------------------------------------------------

def test_official_checkpoint_round_trip(tmp_path):
    net = model(seed=3)
    path = tmp_path / "PS-FCN_B_S_32.pth.tar"
    torch.save({"state_dict": net.state_dict(), "model": "PS_FCN"}, path)  # the authors' layout
    w = read_weights(path)
    assert w.official and w.lights
    loaded, run = build_network(w, "ps-fcn")
    assert run["normalization"] == "none"
    x, lights = torch.rand(1, 3, 3, 12, 16), torch.nn.functional.normalize(torch.rand(1, 3, 3), dim=-1)
    with torch.no_grad():
        assert torch.equal(loaded(x, lights), net(x, lights))
    # the same file as the +N model: the method decides, with the authors' q = 32
    assert build_network(w, "ps-fcn-n")[1] == {"normalization": "per-channel", "train_images": 32,
                                                "architecture": {"lights": True, "fuse": "max"}}
    # auto with it: PS-FCN, and the user is told why (the file cannot say whether it is +N)
    from psctl.api import resolve_method

    method, note = resolve_method("auto", True, weights=path)
    assert method == "ps-fcn" and "do not record +N" in note and "--method ps-fcn-n" in note
    # saved from nn.DataParallel: "module." prefixes are dropped
    torch.save({"state_dict": {f"module.{k}": v for k, v in net.state_dict().items()}}, tmp_path / "dp.pth.tar")
    build_network(read_weights(tmp_path / "dp.pth.tar"), "ps-fcn")


def test_official_ups_fcn_checkpoint(tmp_path):
    path = tmp_path / "UPS-FCN_B_S_32.pth.tar"
    torch.save({"state_dict": model(lights=False).state_dict(), "model": "PS_FCN"}, path)
    w = read_weights(path)
    assert not w.lights
    build_network(w, "ups-fcn")
    with pytest.raises(PsctlError, match="takes no lights"):
        build_network(w, "ps-fcn")
    # auto with it: UPS-FCN, without advice to pass --method ps-fcn-n, which takes lights (a QA helper)
    from psctl.api import resolve_method

    method, note = resolve_method("auto", False, weights=path)
    assert method == "ups-fcn" and note.endswith("running it as ups-fcn, without +N"), note


@pytest.mark.parametrize("change, expected", [
    ("rename", r"missing keys: extractor\.conv3\.0\.weight; unexpected keys: extractor\.conv3\.0\.kernel"),
    ("drop", r"missing keys: regressor\.est_normal\.0\.weight$"),
    ("shape", r"wrong shapes: extractor\.conv1\.0\.weight \[64, 4, 3, 3\] \(expected \[64, 6, 3, 3\]\)"),
])
def test_wrong_keys_fail_clearly(tmp_path, change, expected):
    sd = dict(model().state_dict())
    if change == "rename":
        sd["extractor.conv3.0.kernel"] = sd.pop("extractor.conv3.0.weight")
    elif change == "drop":
        del sd["regressor.est_normal.0.weight"]
    else:
        sd["extractor.conv1.0.weight"] = torch.zeros(64, 4, 3, 3)
    path = tmp_path / "bad.pth.tar"
    torch.save({"state_dict": sd}, path)
    with pytest.raises(PsctlError, match=expected) as err:
        build_network(read_weights(path), "ps-fcn")
    assert str(path) in str(err.value) and "does not match the PS-FCN architecture" in str(err.value)


def test_key_check_names_at_most_three(tmp_path):
    sd = {f"x{k}": torch.zeros(1) for k in range(5)}
    with pytest.raises(PsctlError, match=r"unexpected keys: x0, x1, x2 and 2 more"):
        check_state_dict(tmp_path / "f.pt", {**model().state_dict(), **sd}, model())


class Payload:  # stands for anything a malicious or careless pickle could carry
    pass


def _cut_einval(path, n, out) -> bool:
    """Whether torch itself fails with EINVAL on ``path`` cut to ``n`` bytes (written to ``out``)."""
    import errno

    out.write_bytes(path.read_bytes()[:n])
    try:
        torch.load(out, map_location="cpu", weights_only=True)
    except OSError as e:
        return e.errno == errno.EINVAL
    except Exception:  # noqa: BLE001 - another failure: not this case
        return False
    return False


def test_refuses_arbitrary_objects_and_garbage(tmp_path):
    evil = tmp_path / "evil.pth.tar"
    torch.save({"state_dict": model().state_dict(), "extra": Payload()}, evil)
    with pytest.raises(PsctlError, match="never unpickles arbitrary objects"):
        read_weights(evil)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a torch file at all")
    with pytest.raises(PsctlError, match="cannot read weights file"):
        read_weights(junk)
    whole = tmp_path / "whole.pt"  # cut inside its zip entries: torch's reader gave "[Errno 22] Invalid argument"
    torch.save({"state_dict": model().state_dict()}, whole)
    cut = next((n for n in range(2000, whole.stat().st_size, 997) if _cut_einval(whole, n, tmp_path / "cut.pt")), None)
    assert cut is not None, "no cut gave torch's EINVAL"
    (tmp_path / "cut.pt").write_bytes(whole.read_bytes()[:cut])
    with pytest.raises(PsctlError, match=r"cut.pt: cannot read weights file: damaged \(cut short\?\)"):
        read_weights(tmp_path / "cut.pt")
    # files torch.load fails on in its own ways: one message each, no warning on the way
    import pickle
    import warnings

    (tmp_path / "text.pt").write_text("hello\n")  # KeyError inside the unpickler
    (tmp_path / "empty.pt").write_bytes(b"")
    (tmp_path / "dict.pt").write_bytes(pickle.dumps({"a": 1}, protocol=4))  # torch warns about the protocol
    for name, says in (("text.pt", "the unpickler failed"), ("empty.pt", "the file is empty"),
                       ("dict.pt", "not a torch file")):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(PsctlError, match=says):
                read_weights(tmp_path / name)
    torch.save({"weights": 1}, tmp_path / "nodict.pt")
    with pytest.raises(PsctlError, match="'state_dict'"):
        read_weights(tmp_path / "nodict.pt")
    with pytest.raises(PsctlError, match="not found"):
        read_weights(tmp_path / "missing.pt")


def test_save_load_round_trip_with_metadata(tmp_path):
    net = model(seed=5)
    meta = {"method": "ps-fcn-n", "train_images": 32, "recipe": {"lr": 1e-3, "batch": 32, "steps": [1, 2]},
            "data": "psctl synth", "metrics": {"val_mae": 5.5}}
    path = save_weights(tmp_path / "ps_fcn_n.pt", net, meta)
    w = read_weights(path)
    assert not w.official
    for k, v in meta.items():
        assert w.metadata[k] == v
    assert w.metadata["normalization"] == "per-channel" and w.metadata["architecture"]["lights"] is True
    assert "date" in w.metadata
    loaded, run = build_network(w, "ps-fcn-n")
    assert run["train_images"] == 32 and run["normalization"] == "per-channel"
    for k, v in net.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v)
    with pytest.raises(PsctlError, match="holds ps-fcn-n weights, not ps-fcn"):
        build_network(w, "ps-fcn")
    # metadata must stay plain data (weights_only loading) and name a known method
    with pytest.raises(PsctlError, match="only plain data"):
        save_weights(tmp_path / "x.pt", net, {**meta, "recipe": {"path": tmp_path}})
    with pytest.raises(PsctlError, match="method"):
        save_weights(tmp_path / "x.pt", net, {**meta, "method": "ps-fcn-x"})
    with pytest.raises(PsctlError, match="train_images"):
        save_weights(tmp_path / "x.pt", net, {**meta, "train_images": 0})
    with pytest.raises(PsctlError, match="ps-fcn-n needs"):
        save_weights(tmp_path / "x.pt", net, {**meta, "normalization": "none"})
    assert not (tmp_path / "x.pt").exists()


def test_installed_weights_found_by_method(tmp_path, monkeypatch):
    from psctl.api import estimate_normals, resolve_method

    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path))
    images, lights, mask = scene(6, 20, 24)
    with pytest.raises(PsctlError, match=r"no weights are installed for ps-fcn .*--weights FILE"):
        estimate_normals(images, lights, mask, method="ps-fcn")
    with pytest.raises(PsctlError, match=r"installed for ups-fcn .*UPS-FCN_B_S_32.pth.tar.*--method sdps$"):
        estimate_normals(images, None, mask, method="ups-fcn")  # needs no lights: sdps, not l2
    assert resolve_method("auto", True)[0] == "l2"
    save_weights(tmp_path / "ps_fcn_n.pt", model(), {"method": "ps-fcn-n", "train_images": 32})
    assert resolve_method("auto", True) == ("ps-fcn-n", None)
    (tmp_path / "ps_fcn_n.pt").rename(tmp_path / "other.pt")
    save_weights(tmp_path / "ps_fcn.pt", model(), {"method": "ps-fcn", "train_images": 32})
    assert resolve_method("auto", True) == ("ps-fcn", None)
    (tmp_path / "other.pt").rename(tmp_path / "ps_fcn_n.pt")
    assert resolve_method("auto", True) == ("ensemble", None)  # both installed: their average
    n = estimate_normals(images, lights, mask, method="auto")
    assert n.shape == (20, 24, 3)
    np.testing.assert_allclose(np.linalg.norm(n[mask], axis=-1), 1, atol=1e-5)
    assert not n[~mask].any()
    a, b = (estimate_normals(images, lights, mask, method=m) for m in ("ps-fcn", "ps-fcn-n"))
    mean = (a.astype(np.float64) + b)[mask]
    np.testing.assert_allclose(n[mask], mean / np.linalg.norm(mean, axis=-1, keepdims=True), atol=1e-5)
    assert np.abs(n - a).max() > 1e-3 and np.abs(n - b).max() > 1e-3  # two different networks


def test_ensemble_needs_both_networks_and_listed_lights(tmp_path, monkeypatch):
    from psctl.api import estimate_normals, resolve_method

    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path))
    images, lights, mask = scene(6, 20, 24)
    with pytest.raises(PsctlError, match=r"no weights are installed for ps-fcn and ps-fcn-n .*use --method l2$"):
        resolve_method("ensemble", True)
    save_weights(tmp_path / "ps_fcn.pt", model(), {"method": "ps-fcn", "train_images": 32})
    with pytest.raises(PsctlError, match=r"installed for ps-fcn-n \(looked in .*use --method ps-fcn$"):
        estimate_normals(images, lights, mask, method="ensemble")
    save_weights(tmp_path / "ps_fcn_n.pt", model(), {"method": "ps-fcn-n", "train_images": 32})
    with pytest.raises(PsctlError, match="ensemble uses the installed ps-fcn and ps-fcn-n"):
        resolve_method("ensemble", True, weights=tmp_path / "ps_fcn.pt")
    with pytest.raises(PsctlError, match="ensemble needs light directions"):
        resolve_method("ensemble", False)
    assert resolve_method("ENSEMBLE", True) == ("ensemble", None)


@pytest.mark.filterwarnings("ignore:.*only 6 images")  # (few on purpose: quick)
def test_sdps_second_stage_can_be_the_ensemble(tmp_path, monkeypatch):
    """psctl.sdps.SDPS_ENSEMBLE: with PS-FCN and PS-FCN+N installed (no PS-FCN†) sdps' second
    stage is their average; a file passed with --weights is always that network."""
    import psctl.sdps
    from psctl.api import estimate_normals
    from psctl.models.lcnet import LCNet
    from psctl.sdps import sdps_second_stage

    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path))
    save_weights(tmp_path / "lcnet.pt", LCNet(), {"method": "lcnet", "train_images": 32})
    save_weights(tmp_path / "ps_fcn.pt", model(), {"method": "ps-fcn", "train_images": 32})
    monkeypatch.setattr(psctl.sdps, "SDPS_ENSEMBLE", True)
    assert sdps_second_stage()[0] == "ps-fcn"  # one calibrated network: no average
    save_weights(tmp_path / "ps_fcn_n.pt", model(), {"method": "ps-fcn-n", "train_images": 32})
    method, note = sdps_second_stage()
    assert method == "ensemble" and "the PS-FCN/PS-FCN+N average" in note
    assert sdps_second_stage(tmp_path / "ps_fcn.pt")[0] == "ps-fcn"
    images, _, mask = scene(6, 20, 24)
    n = estimate_normals(images, None, mask, method="sdps", device="cpu")
    np.testing.assert_allclose(np.linalg.norm(n[mask], axis=-1), 1, atol=1e-5)
    from psctl.api import run_normals  # and on a capture folder (its passes share a DecodeMemo)
    from tests.conftest import write_capture

    write_capture(tmp_path / "cap", n=6, size=24)
    r = run_normals(tmp_path / "cap", method="sdps", write=False, device="cpu")
    assert r["second_stage"] == "ensemble" and np.isfinite(r["mae"])
    monkeypatch.setattr(psctl.sdps, "SDPS_ENSEMBLE", False)
    assert sdps_second_stage()[0] == "ps-fcn"


def test_ensemble_normals_is_the_unit_mean():
    from psctl.infer import InferResult, ensemble_normals

    mask = np.zeros((2, 3), bool)
    mask[0] = True
    a = np.zeros((2, 3, 3), np.float32)
    b = np.zeros((2, 3, 3), np.float32)
    a[0] = [0, 0, 1]
    b[0, 0], b[0, 1], b[0, 2] = [1, 0, 0], [0, 0, 1], [0, 0, -1]  # 90 degrees apart, equal, opposite
    dark_a, dark_b = np.zeros((2, 3), bool), np.zeros((2, 3), bool)
    dark_a[0, 0], dark_b[0, 1] = True, True
    r = ensemble_normals([InferResult(a, dark_a, {"x": 1}, ["n1", "n2"]), InferResult(b, dark_b, {"x": 2}, ["n2", "n3"])])
    np.testing.assert_allclose(r.normals[0, 0], [np.sqrt(0.5), 0, np.sqrt(0.5)], atol=1e-6)
    np.testing.assert_allclose(r.normals[0, 1], [0, 0, 1])
    assert not r.normals[0, 2].any() and not r.normals[1].any()  # cancelled, and outside the mask
    assert np.isfinite(r.normals).all() and r.normals.dtype == np.float32
    assert r.dark.tolist() == [[True, True, False], [False, False, False]]
    assert r.notes == ["n1", "n2", "n3"] and r.info == {"members": [{"x": 1}, {"x": 2}]}
    np.testing.assert_allclose(r.spread[0], [90, 0, 180], atol=1e-4)  # the members' angle
    assert not r.spread[1].any() and r.spread.dtype == np.float32
    with pytest.raises(ValueError):
        ensemble_normals([])


def test_member_spread_is_the_largest_pairwise_angle():
    from psctl.infer import member_spread

    def tilt(deg):  # (0, 0, 1) turned about x
        t = np.radians(deg)
        return np.array([0.0, np.sin(t), np.cos(t)])

    a, b, c = (np.zeros((1, 3, 3)) for _ in range(3))
    a[0, 0], b[0, 0], c[0, 0] = tilt(0), tilt(10), tilt(-5)
    a[0, 1], b[0, 1], c[0, 1] = tilt(0), tilt(1e-4), tilt(0)  # small angles: atan2, not arccos of a dot near 1
    a[0, 2] = tilt(30)  # b and c are 0 here (outside a mask)
    np.testing.assert_allclose(member_spread([a, b])[0], [10, 1e-4, 0], rtol=1e-3, atol=1e-9)
    np.testing.assert_allclose(member_spread([a, b, c])[0], [15, 1e-4, 0], rtol=1e-3, atol=1e-9)
    assert member_spread([a]).tolist() == [[0, 0, 0]]  # one member: no spread


def test_spread_stats():
    from psctl.api import spread_stats

    spread = np.arange(20, dtype=np.float32).reshape(4, 5)
    mask = np.ones((4, 5), bool)
    mask[0, 0] = False  # spread 0 left out: 1..19 remain
    error = spread * 2
    valid = mask.copy()
    valid[3, 4] = False  # spread 19: not scored
    r = spread_stats(spread, mask, error, valid)
    assert r["mean"] == pytest.approx(10) and r["median"] == pytest.approx(10)
    assert r["p90"] == pytest.approx(np.percentile(np.arange(1, 20), 90))  # 17.2
    assert r["mae_top10"] == pytest.approx(36)  # spreads 18 (19 not scored), errors 36
    assert r["mae_rest"] == pytest.approx(np.mean(np.arange(1, 18) * 2))
    r = spread_stats(spread, mask)
    assert r["mae_top10"] is None and r["mae_rest"] is None
    flat = np.ones((4, 5), np.float32)  # ties: no pixel above the percentile, so those at it
    r = spread_stats(flat, mask, error, valid)
    assert r["p90"] == 1 and r["mae_top10"] == pytest.approx(error[valid].mean()) and r["mae_rest"] is None
    r = spread_stats(spread, np.zeros((4, 5), bool))
    assert all(v is None for v in r.values())



def test_auto_on_an_uncalibrated_folder_prefers_sdps_over_ups_fcn(tmp_path, monkeypatch):
    """Without light_directions.txt, auto takes UPS-FCN only while sdps cannot run (no LCNet, or
    no second stage); with LCNet and a calibrated network installed it is sdps, PS-FCN† or not."""
    from psctl.api import resolve_method
    from psctl.models.lcnet import LCNet

    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path))
    save_weights(tmp_path / "ups_fcn.pt", model(lights=False), {"method": "ups-fcn", "train_images": 32})
    assert resolve_method("auto", False)[0] == "ups-fcn"
    save_weights(tmp_path / "lcnet.pt", LCNet(), {"method": "lcnet", "train_images": 32})
    assert resolve_method("auto", False)[0] == "ups-fcn"  # LCNet alone: no second stage
    save_weights(tmp_path / "ps_fcn.pt", model(), {"method": "ps-fcn", "train_images": 32})
    method, note = resolve_method("auto", False)
    assert method == "sdps" and "PS-FCN" in note


def test_auto_and_sdps_choices_with_files_given(tmp_path, monkeypatch):
    """--lcnet and --weights steer auto (mutation review, session 39): each branch and its note."""
    from psctl.api import resolve_method
    from psctl.models.lcnet import LCNet
    from psctl.sdps import SDPS_NOTE

    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path / "installed"))
    (tmp_path / "installed").mkdir()
    files = tmp_path / "files"
    files.mkdir()
    lc, dag = files / "lc.pt", files / "dag.pt"
    save_weights(lc, LCNet(), {"method": "lcnet", "train_images": 32})
    save_weights(dag, model(), {"method": "ps-fcn-dagger", "train_images": 32, "lcnet": {"decode": "argmax"}})
    # nothing installed: --weights PS-FCN† without LCNet names the missing LCNet and --lcnet
    with pytest.raises(PsctlError, match=r"installed for lcnet.*--lcnet FILE"):
        resolve_method("sdps", False, weights=dag)
    # both given: nothing installed is needed, and the note names the file used
    assert resolve_method("sdps", False, dag, lc) == ("sdps", SDPS_NOTE)
    method, note = resolve_method("auto", False, weights=dag, lcnet=lc)
    assert method == "sdps" and note.startswith(f"auto: sdps (PS-FCN† weights from {dag}); ")
    inst = tmp_path / "installed"
    save_weights(inst / "ups_fcn.pt", model(lights=False), {"method": "ups-fcn", "train_images": 32})
    save_weights(inst / "ps_fcn.pt", model(), {"method": "ps-fcn", "train_images": 32})
    # UPS-FCN and PS-FCN installed, no LCNet: sdps cannot run, so ups-fcn, saying why
    method, note = resolve_method("auto", False)
    assert method == "ups-fcn" and "sdps weights are not installed" in note
    # ... but an LCNet given on the command line is used, not ignored
    assert resolve_method("auto", False, lcnet=lc)[0] == "sdps"
    # a calibrated folder with --lcnet: sdps, and the note does not claim the lights are missing
    method, note = resolve_method("auto", True, lcnet=lc)
    assert method == "sdps" and "no light_directions.txt" not in note and "--lcnet" in note
    # --weights PS-FCN with PS-FCN† installed: the note names the file, not the installed network
    save_weights(inst / "ps_fcn_dagger.pt", model(), {"method": "ps-fcn-dagger", "train_images": 32,
                                                       "lcnet": {"decode": "argmax"}})
    note = resolve_method("sdps", False, inst / "ps_fcn.pt", lc)[1]
    assert f"normals by PS-FCN on those lights (from {inst / 'ps_fcn.pt'};" in note and "not installed" not in note
    (inst / "ps_fcn_dagger.pt").unlink()
    # --weights PS-FCN† with LCNet installed: sdps, though no second stage is installed
    (inst / "ps_fcn.pt").unlink()
    save_weights(inst / "lcnet.pt", LCNet(), {"method": "lcnet", "train_images": 32})
    assert resolve_method("auto", False, weights=dag)[0] == "sdps"

# --- normalisation ---------------------------------------------------------------------------

@pytest.mark.parametrize("variant", ["per-channel", "per-pixel"])
def test_normalize_observations_sqrt_t_over_q(variant):
    x = torch.rand(2, 12, 3, 5, 6) + 0.1  # [B, N, 3, H, W]
    for q, expect in ((None, 1.0), (3, 2.0), (48, 0.5)):
        y = normalize_observations(x, variant, q)
        norm = y.square().sum(1).sqrt() if variant == "per-channel" else y.square().sum((1, 2)).sqrt()
        torch.testing.assert_close(norm, torch.full_like(norm, expect))


def test_weights_file_gives_q(tmp_path):
    """PS-FCN+N's q comes from the file's train_images (a tiny recipe trains on 8 images)."""
    from psctl.infer import array_normals

    images, lights, mask = scene(8)
    net = model()
    got = {}
    for q in (8, 32):
        w = save_weights(tmp_path / f"n{q}.pt", net, {"method": "ps-fcn-n", "train_images": q})
        got[q] = array_normals(images, lights, mask, "ps-fcn-n", w, {"device": "cpu"}).normals
        ref = stream(images, lights, mask, net, normalization="per-channel", q=q)
        np.testing.assert_allclose(got[q], ref, atol=1e-5)
    assert np.abs(got[8] - got[32]).max() > 1e-3


def test_engine_applies_sqrt_t_over_q():
    """+N in the engine == normalising the stack by hand (same q), then the plain network."""
    images, lights, mask = scene(8)
    masked = images * mask[None, ..., None]
    by_hand = normalize_observations(torch.from_numpy(masked).permute(0, 3, 1, 2), "per-channel", 2)
    by_hand = by_hand.permute(0, 2, 3, 1).numpy()
    net = model(double=True)
    ref = stream(by_hand, lights, mask, net)
    got = stream(images, lights, mask, net, normalization="per-channel", q=2)
    np.testing.assert_allclose(got, ref, atol=1e-5)
    other_q = stream(images, lights, mask, net, normalization="per-channel", q=32)
    assert np.abs(other_q - got).max() > 1e-3  # q matters


@pytest.mark.parametrize("variant", ["per-channel", "per-pixel"])
def test_plus_n_removes_albedo_from_lambertian_input(variant):
    normals, mask = sphere(36)
    lights = hemisphere_lights(10, 50, seed=1)
    rng = np.random.default_rng(2)
    shape = (36, 36, 3) if variant == "per-channel" else (36, 36, 1)  # per-pixel: grey albedo only
    albedo = np.broadcast_to(rng.uniform(0.05, 1.0, shape), (36, 36, 3)).astype(np.float32)
    plain = render_lambertian(normals, mask, lights, 1.0)
    painted = render_lambertian(normals, mask, lights, albedo)
    net = model()
    a = stream(plain, lights, mask, net, variant, 32)
    b = stream(painted, lights, mask, net, variant, 32)
    np.testing.assert_allclose(a, b, atol=1e-4)  # float32 rounding of the division
    # without +N the albedo does change the output (so the check above can fail)
    assert np.abs(stream(plain, lights, mask, net) - stream(painted, lights, mask, net)).max() > 1e-2


# --- the engine ------------------------------------------------------------------------------

def test_order_invariance():
    images, lights, mask = scene(9)
    p = np.random.default_rng(1).permutation(9)
    for net in (model(), model(double=True)):
        a = stream(images, lights, mask, net, "per-channel", 32, chunk=4)
        b = stream(images[p], lights[p], mask, net, "per-channel", 32, chunk=4)
        np.testing.assert_allclose(a, b, atol=1e-5)


@pytest.mark.parametrize("normalization", ["none", "per-channel", "per-pixel"])
def test_streaming_equals_all_at_once(normalization):
    """Chunked streaming on the crop == every feature map at once on the whole frame."""
    images, lights, mask = scene(5, 33, 41)
    net = model(double=True)
    ref = all_at_once_normals(net, images, lights, mask, normalization, 3)
    for chunk, cache_mb in ((1, 0), (3, 0), (7, 128)):
        got = stream(images, lights, mask, net, normalization, 3, chunk=chunk, cache_mb=cache_mb)
        np.testing.assert_allclose(got, ref, atol=1e-6)
    # float32 with channels_last (the fast path): its kernels round differently
    net = model()
    np.testing.assert_allclose(stream(images, lights, mask, net, normalization, 3),
                               all_at_once_normals(net, images, lights, mask, normalization, 3), atol=1e-4)


def test_input_mean_scales_each_capture_to_the_training_exposure():
    """Without +N: one factor per capture brings its masked mean to input_mean, so the result
    does not depend on the capture's exposure, and equals feeding pre-scaled images."""
    images, lights, mask = scene()
    net = model(double=True)

    def run(x, input_mean):
        def reader(start, box):
            for k in range(start, len(x)):
                yield x[k][box]
        return run_network(net, reader, len(x), lights, mask, "none", None, {}, None, "t", input_mean)

    base = run(images, 0.2)
    # (the images are float32 as read: the two scalings round differently)
    assert np.abs(run(images * 7.5, 0.2).normals - base.normals).max() < 1e-5
    assert np.abs(run(images * 0.01, 0.2).normals - base.normals).max() < 1e-5
    # the same as scaling by hand: the mean over the mask, all images and channels
    factor = 0.2 / images[:, mask].mean(dtype=np.float64)
    assert base.info["exposure_scale"] == pytest.approx(factor, rel=1e-5)
    by_hand = run((images * factor).astype(np.float64), None).normals
    assert np.allclose(base.normals, by_hand, atol=1e-6)
    # and it matters: without it the network sees other values
    assert not np.allclose(run(images * 7.5, None).normals, run(images, None).normals, atol=1e-3)
    assert base.info["passes"] == run(images, None).info["passes"] + 1
    with pytest.raises(PsctlError, match="black"):
        run(images * 0, 0.2)
    with pytest.raises(PsctlError, match="input_mean"):
        run(images, -1.0)


def test_no_mask_exposure_comes_from_the_lit_pixels(tmp_path):
    """Without a mask (mask=None, no mask.png) the exposure mean is over the lit pixels
    (lit_pixels: Otsu on log brightness), not the whole frame, whose dark background would halve
    the mean and double the scale (session 62: PS-FCN on the dev split's cat without its mask,
    6.08 -> 5.89 degrees). A mask that covers the frame is a mask: its mean, as before."""
    from psctl.io.images import write_image

    images, lights, mask = scene()
    rng = np.random.default_rng(3)
    images[:, ~mask] = rng.uniform(0, 0.004, images[:, ~mask].shape)  # a dark cloth, some noise
    net = model(double=True)

    def run(m, x=images, **cfg):
        def reader(start, box):
            for k in range(start, len(x)):
                yield x[k][box]
        return run_network(net, reader, len(x), lights, m, "none", None, cfg, None, "t", 0.2)

    masked = run(mask).info["exposure_scale"]
    whole = np.ones_like(mask)
    assert run(whole, exposure_pixels="lit").info["exposure_scale"] == pytest.approx(masked, rel=0.02)
    frame = 0.2 / images.mean(dtype=np.float64)  # the whole frame's mean (the rule before)
    assert frame > 1.5 * masked
    assert run(whole).info["exposure_scale"] == pytest.approx(frame, rel=1e-5)  # a frame-filling mask
    with pytest.raises(PsctlError, match="^all images are black$"):  # not ZeroDivisionError
        run(whole, images * 0, exposure_pixels="lit")
    with pytest.raises(PsctlError, match="exposure_pixels"):
        run(mask, exposure_pixels="frame")
    # the callers: mask=None in the array API, a folder without mask.png
    w = save_weights(tmp_path / "ps_fcn.pt", model(), {"method": "ps-fcn", "train_images": 32, "input_mean": 0.2})
    cfg = {"device": "cpu"}
    assert array_normals(images, lights, mask, "ps-fcn", w, cfg).info["exposure_scale"] == pytest.approx(masked, rel=1e-5)
    res = array_normals(images, lights, None, "ps-fcn", w, cfg)
    assert res.info["exposure_scale"] == pytest.approx(masked, rel=0.02)
    assert any("mean over the lit pixels: no mask" in n for n in res.notes)
    assert array_normals(images, lights, whole, "ps-fcn", w, cfg).info["exposure_scale"] == pytest.approx(frame, rel=1e-5)
    from psctl.infer import capture_normals
    from psctl.io.capture import load_mask, open_capture

    folder = tmp_path / "obj"
    folder.mkdir()
    for k, img in enumerate(images):
        write_image(folder / f"{k + 1:03d}.exr", img, "float", kind="linear")
    np.savetxt(folder / "light_directions.txt", lights)
    cap = open_capture(folder)
    got = capture_normals(cap, load_mask(cap), "ps-fcn", w, cfg).info["exposure_scale"]
    assert got == pytest.approx(masked, rel=0.02)


def test_lit_pixels_splits_object_from_background():
    from psctl.infer import lit_pixels

    rng = np.random.default_rng(0)
    b = np.concatenate([rng.uniform(1e-3, 1e-2, 600), rng.uniform(0.2, 1.0, 400)]).reshape(25, 40)
    lit = lit_pixels(b)
    assert lit.sum() == 400 and lit.reshape(-1)[600:].all()
    # unchanged by the exposure (log brightness), and by the frame's order
    assert (lit_pixels(b * 1e-6) == lit).all() and (lit_pixels(b.T) == lit.T).all()
    assert lit_pixels(np.full((4, 5), 0.3)).all()  # nothing to split: every lit pixel
    zeros = np.zeros((3, 3))
    assert not lit_pixels(zeros).any()
    zeros[1, 1] = 0.5
    assert lit_pixels(zeros).sum() == 1  # zero (unlit) pixels never count


def test_input_clip_saturates_scaled_highlights_as_training_did():
    """The training stream clips each sample at 1 after scaling it to its exposure; a dark capture
    with a bright highlight, scaled up to input_mean, must be clipped the same way."""
    images, lights, mask = scene()
    images = images * 0.05
    images[:, 10:14, 20:24] = 1.0  # highlights: far above 1 once the capture is scaled up
    net = model(double=True)

    def run(x, input_mean, input_clip):
        def reader(start, box):
            for k in range(start, len(x)):
                yield x[k][box]
        return run_network(net, reader, len(x), lights, mask, "none", None, {}, None, "t", input_mean, input_clip)

    clipped = run(images, 0.2, 1.0)
    factor = clipped.info["exposure_scale"]
    assert factor > 2
    by_hand = run(np.minimum(images.astype(np.float64) * factor, 1.0), None, None).normals
    assert np.allclose(clipped.normals, by_hand, atol=1e-6)
    assert not np.allclose(run(images, 0.2, None).normals, by_hand, atol=1e-3)
    with pytest.raises(PsctlError, match="input_clip"):
        run(images, 0.2, 0.0)


def test_input_mean_in_metadata(tmp_path):
    net = model()
    meta = {"method": "ps-fcn", "train_images": 32, "input_mean": 0.2236}
    w = read_weights(save_weights(tmp_path / "ps_fcn.pt", net, meta))
    assert build_network(w, "ps-fcn")[1]["input_mean"] == 0.2236
    assert build_network(w, "ps-fcn")[1]["input_clip"] == 1.0  # the stream's default sensor saturation
    w2 = read_weights(save_weights(tmp_path / "noclip.pt", net, {**meta, "recipe": {"data": {"clip": None}}}))
    assert build_network(w2, "ps-fcn")[1]["input_clip"] is None
    # random intensities: images were divided by them after the clip, so no level bounds them
    w3 = read_weights(save_weights(tmp_path / "rand.pt", net, {**meta, "recipe": {"data": {"intensities": "random"}}}))
    assert build_network(w3, "ps-fcn")[1]["input_clip"] is None
    images, lights, mask = scene(4, 16, 16)
    res = array_normals(images, lights, mask, "ps-fcn", tmp_path / "ps_fcn.pt", {"device": "cpu"})
    assert res.info["exposure_scale"] > 0 and any("scaled by" in n and "0.224" in n for n in res.notes)
    w = read_weights(save_weights(tmp_path / "old.pt", net, {"method": "ps-fcn", "train_images": 32}))
    assert build_network(w, "ps-fcn")[1]["input_mean"] is None  # files from before: images as they are
    for bad in (0, -0.1, float("nan"), "0.2", True):
        with pytest.raises(PsctlError, match="input_mean"):
            save_weights(tmp_path / "x.pt", net, {**meta, "input_mean": bad})


def test_mean_fusion_streams_too():
    images, lights, mask = scene(5)
    torch.manual_seed(0)
    net = random_biases(PSFCN({"fuse": "mean"}).eval().double())  # zero biases would hide a wrong scale
    ref = all_at_once_normals(net, images, lights, mask)
    np.testing.assert_allclose(stream(images, lights, mask, net, chunk=2), ref, atol=1e-6)
    # the check can fail: with these biases the regressor sees the fused features' scale (a mean
    # over n - 1 images is the mean x 5/4), which zero biases would hide
    f = net.extract(torch.rand(5, 3, 16, 16, dtype=torch.float64), torch.tensor(lights[:5], dtype=torch.float64))
    with torch.no_grad():
        assert (net.regress(f.mean(0, keepdim=True)) - net.regress(f.mean(0, keepdim=True) * 5 / 4)).abs().max() > 1e-3


def test_tiled_equals_untiled():
    images, lights, mask = scene(3, 70, 86)
    mask[:] = True  # the whole frame: tiles everywhere, including the image borders
    h, w = 72, 88  # the frame padded to a multiple of 4
    assert len(plan_tiles(h, w, 32, HALO)) == 9
    for net, normalization, tol in ((model(double=True), "per-channel", 1e-6), (model(), "none", 1e-4)):
        whole = stream(images, lights, mask, net, normalization, 32)
        # several groups (one pass over the images each), nothing cached: images re-read
        tiled = stream(images, lights, mask, net, normalization, 32, tile=32, group_mb=1, cache_mb=0)
        np.testing.assert_allclose(tiled, whole, atol=tol)


def test_too_small_halo_is_not_exact():
    """The tiling check can fail: with no halo the tile borders show."""
    images, lights, mask = scene(4, 64, 64)
    mask[:] = True
    net = model(double=True)
    whole = stream(images, lights, mask, net)
    assert np.abs(stream(images, lights, mask, net, tile=32, halo=0) - whole).max() > 1e-3


@pytest.mark.parametrize("h, w", [(1, 1), (5, 7), (37, 53), (64, 64), (30, 2)])
def test_any_image_size(h, w):
    rng = np.random.default_rng(h * 100 + w)
    images = rng.uniform(0, 1, (5, h, w, 3)).astype(np.float32)
    lights = hemisphere_lights(5, 40)
    mask = rng.uniform(size=(h, w)) < 0.7
    mask.flat[0] = True
    for m in (mask, np.ones((h, w), bool)):
        n = stream(images, lights, m, normalization="per-channel", q=32)
        assert n.shape == (h, w, 3) and np.isfinite(n).all()
        np.testing.assert_allclose(np.linalg.norm(n[m], axis=-1), 1, atol=1e-5)
        assert not n[~m].any()


def test_crop_region_is_aligned_and_keeps_context():
    mask = np.zeros((100, 90), bool)
    mask[41:50, 30:33] = True
    y0, y1, x0, x1 = crop_region(mask, HALO)
    assert (y0, x0) == (16, 4) and y0 % 4 == 0 and x0 % 4 == 0 and (y1 - y0) % 4 == 0 and (x1 - x0) % 4 == 0
    assert y0 <= 41 - HALO and y1 >= 50 + HALO and x0 <= 30 - HALO and x1 >= 33 + HALO


def test_bad_inputs():
    images, lights, mask = scene(3, 12, 12)
    with pytest.raises(PsctlError, match="needs light directions"):
        stream(images, None, mask)
    with pytest.raises(PsctlError, match="NaN"):
        bad = images.copy()
        bad[1, 5, 5, 0] = np.nan
        stream(bad, lights, np.ones((12, 12), bool))
    if not torch.cuda.is_available():
        with pytest.raises(PsctlError, match="no CUDA GPU"):
            stream(images, lights, mask, device="cuda")
    with pytest.raises(PsctlError, match="fp16 is for CUDA"):
        stream(images, lights, mask, device="cpu", autocast="fp16")
    with pytest.raises(PsctlError, match="unknown autocast"):
        stream(images, lights, mask, device="cpu", autocast="int8")


def test_bf16_is_refused_on_gpus_that_would_emulate_it(monkeypatch):
    """torch.cuda.is_bf16_supported() says yes on pre-Ampere GPUs, which emulate bf16 slowly: psctl
    refuses it there in one line, as on CPUs without native bf16 (no GPU needed: the query is faked)."""
    from psctl.infer import _autocast

    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda d=None: (7, 5))
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda d=None: "Tesla T4")
    with pytest.raises(PsctlError, match=r"Ampere or newer GPU \(Tesla T4 would emulate it"):
        _autocast(torch.device("cuda"), "bf16")


def test_cpu_bf16_autocast_close_to_float32():
    from psctl.infer import cpu_has_bf16

    images, lights, mask = scene(6, 24, 24)
    if not cpu_has_bf16():
        with pytest.raises(PsctlError, match="native bf16"):
            stream(images, lights, mask, device="cpu", autocast="bf16")
        pytest.skip("this CPU has no native bf16 (the refusal above is what users get)")
    a = stream(images, lights, mask, device="cpu")
    b = stream(images, lights, mask, device="cpu", autocast="bf16")
    cos = np.clip((a[mask] * b[mask]).sum(-1), -1, 1)
    assert np.degrees(np.arccos(cos)).mean() < 2.0  # random weights: loose; trained weights in docs/models.md
    np.testing.assert_allclose(np.linalg.norm(b[mask], axis=-1), 1, atol=1e-4)


def test_ups_fcn_without_lights(tmp_path):
    from psctl.api import estimate_normals

    images, _, mask = scene(4, 16, 16)
    path = save_weights(tmp_path / "ups.pt", model(lights=False), {"method": "ups-fcn", "train_images": 32})
    n = estimate_normals(images, None, mask, method="ups-fcn", weights=path)
    np.testing.assert_allclose(np.linalg.norm(n[mask], axis=-1), 1, atol=1e-5)
    with pytest.raises(PsctlError, match="needs light directions"):
        estimate_normals(images, None, mask, method="ps-fcn", weights=path)
    with pytest.raises(PsctlError, match="--weights is for the network methods"):
        estimate_normals(images, np.eye(3)[[2, 2, 2, 2]], mask, method="l2", weights=path)


def test_ups_fcn_ignores_a_folders_light_files(tmp_path):
    """UPS-FCN reads the images as captured (trained under unknown intensities), as sdps does."""
    import shutil

    from psctl.api import run_normals

    torch.manual_seed(0)
    path = save_weights(tmp_path / "ups.pt", model(lights=False), {"method": "ups-fcn", "train_images": 32})
    write_capture(tmp_path / "lit", n=6, size=24)  # intensities 0.3-0.9, listed
    shutil.copytree(tmp_path / "lit", tmp_path / "bare")
    for name in ("light_directions.txt", "light_intensities.txt"):
        (tmp_path / "bare" / name).unlink()
    runs = {k: run_normals(tmp_path / k, "ups-fcn", tmp_path / f"out_{k}", ("npy",), weights=path, device="cpu")
            for k in ("lit", "bare")}
    assert any("light_directions.txt and light_intensities.txt not used" in n for n in runs["lit"]["notes"])
    assert not any("not used" in n for n in runs["bare"]["notes"])
    np.testing.assert_array_equal(np.load(tmp_path / "out_lit" / "normal.npy"), np.load(tmp_path / "out_bare" / "normal.npy"))


# --- the command -----------------------------------------------------------------------------

def test_cli_network_methods(tmp_path):
    folder = tmp_path / "spherePNG"
    write_capture(folder, n=6, size=24)
    weights = save_weights(tmp_path / "w.pt", model(), {"method": "ps-fcn-n", "train_images": 32})
    from tests.test_cli import cli

    def psctl(*args):  # in this process: a subprocess costs seconds of imports per call
        return cli(*args, env={"COLUMNS": "200", "PSCTL_WEIGHTS": str(tmp_path / "empty")})

    proc = psctl("normals", folder, "--method", "ps-fcn", "--out", tmp_path / "o0")
    assert proc.returncode == 2 and "no weights are installed for ps-fcn" in proc.stderr
    assert "--weights FILE" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "o0").exists()
    proc = psctl("normals", folder, "--weights", weights, "--device", "cpu", "--out", tmp_path / "o1", "--json")
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert r["method"] == "ps-fcn-n" and r["n_images"] == 6 and r["mae"] is not None
    assert sorted(os.listdir(tmp_path / "o1")) == [".psctl-normals", "error.png", "normal.exr", "normal.png",
                                                   "report.json"]
    assert r["views"] == 1
    proc = psctl("normals", folder, "--weights", weights, "--device", "cpu", "--views", "2", "--json", "--out",
                 tmp_path / "o2")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["views"] == 2
    proc = psctl("normals", folder, "--weights", weights, "--views", "6", "--out", tmp_path / "o6")
    assert proc.returncode == 2 and "views must be 1, 2, 4 or 8" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "o6").exists()


# --- symmetric views ----------------------------------------------------------------------------

def views(images, lights, mask, net, k, normalization="none", q=None, **config) -> np.ndarray:
    n = len(images)

    def reader(start, box):
        for i in range(start, n):
            yield images[i][box]

    return run_views(net, reader, n, lights, mask, normalization, q, {**config, "views": k}).normals


def test_views_average_turned_back_normals(normalization="per-channel"):  # +N: two passes through each view's reader
    """views=8: the unit mean of the network's normals on the 8 turned / mirrored captures,
    each turned back (the reader is asked for the right region of the capture in every view,
    with tiles too)."""
    images, lights, _ = scene(5, 44, 52)
    mask = np.zeros((44, 52), bool)
    mask[4:17, 29:44] = True  # off-centre and small: each view reads a different region of the capture
    net = model(double=True)
    acc = 0
    for sym in SYMMETRIES:
        n = all_at_once_normals(net, np.ascontiguousarray(transform_images(images, sym, axes=(1, 2))),
                                transform_dirs(lights, sym), np.ascontiguousarray(transform_images(mask, sym, axes=(0, 1))),
                                normalization, 3)
        acc = acc + untransform_dirs(untransform_images(n, sym, axes=(0, 1)), sym)
    ref = np.where(mask[..., None], acc / np.linalg.norm(acc, axis=-1, keepdims=True).clip(1e-12), 0)
    np.testing.assert_allclose(views(images, lights, mask, net, 8, normalization, 3), ref, atol=1e-6)
    np.testing.assert_allclose(views(images, lights, mask, net, 8, normalization, 3, tile=16, halo=HALO), ref, atol=1e-6)
    np.testing.assert_allclose(views(images, lights, mask, net, 1, normalization, 3),
                               all_at_once_normals(net, images, lights, mask, normalization, 3), atol=1e-6)


@pytest.mark.parametrize("sym", [SYMMETRIES[1], SYMMETRIES[4], SYMMETRIES[6]])
def test_eight_views_turn_with_the_capture(sym):
    images, lights, _ = scene(4, 64, 72)
    mask = np.zeros((64, 72), bool)
    mask[5:22, 40:61] = True
    net = model(double=True)
    ref = views(images, lights, mask, net, 8)
    got = views(np.ascontiguousarray(transform_images(images, sym, axes=(1, 2))), transform_dirs(lights, sym),
                np.ascontiguousarray(transform_images(mask, sym, axes=(0, 1))), net, 8)
    np.testing.assert_allclose(got, transform_dirs(transform_images(ref, sym, axes=(0, 1)), sym), atol=1e-6)


def test_views_must_be_a_subgroup():
    images, lights, mask = scene(3, 20, 20)
    with pytest.raises(PsctlError, match="views"):
        views(images, lights, mask, model(), 3)


def test_check_finite_names_the_tensor_in_every_dtype():
    """check_finite reads CPU float32/64 tensors with NumPy (helper-165: torch.isfinite took up to
    1 s on a loaded CPU) and the others with torch: a NaN or inf is found in each, integers pass."""
    import torch

    from psctl.models.weights import check_finite

    for dtype in (torch.float32, torch.float64, torch.float16, torch.bfloat16):
        state = {"ok": torch.ones(4), "n": torch.arange(3), "w": torch.zeros(2, 3, dtype=dtype)}
        check_finite(state, None)
        state["w"][1, 2] = float("inf") if dtype == torch.float32 else float("nan")
        with pytest.raises(PsctlError, match=r"^w has 1 NaN or infinite values \(of 6\)"):
            check_finite(state, None)
    t = torch.zeros(4, 6)[:, ::2]  # strided, as a view of a loaded file may be
    t[3, 1] = float("nan")
    with pytest.raises(PsctlError, match="of 12"):
        check_finite({"v": t}, None)


def test_weights_with_nan_are_refused(tmp_path):
    """A NaN in an unused kernel tap can hide behind kernels that skip zero padding (the LCNet of
    2026-11-22/23 shipped 126,208 of them): files with non-finite values are refused on load and
    never written."""
    state = {k: v.clone() for k, v in model().state_dict().items()}
    state["regressor.est_normal.0.weight"][0, 0, 0, 0] = float("nan")
    with pytest.raises(PsctlError, match=r"regressor.est_normal.0.weight has 1 NaN or infinite"):
        save_weights(tmp_path / "nan.pt", state, {"method": "ps-fcn", "train_images": 32})
    assert not (tmp_path / "nan.pt").exists()
    torch.save({"state_dict": state}, tmp_path / "authors.pth.tar")  # the authors' format, written by someone else
    with pytest.raises(PsctlError, match="NaN or infinite"):
        read_weights(tmp_path / "authors.pth.tar")


def test_loading_weights_builds_no_throwaway_network(tmp_path):
    """Loading a weights file makes each tensor once, from the file: no random initialisation and no
    meta-tensor allocation, which import torch._dynamo and sympy (2.7 s of a psctl normals run on
    the 2-core VM, session 58). In a fresh interpreter, since this one may have imported them."""
    import subprocess
    import sys

    from psctl.models.lcnet import LCNet

    save_weights(tmp_path / "p.pt", model(), {"method": "ps-fcn-n", "train_images": 32})
    lc = LCNet().eval()
    save_weights(tmp_path / "l.pt", lc.half(), {"method": "lcnet", "train_images": 32})  # stored in float16
    code = (
        "import sys, torch\n"
        "from psctl.models.weights import load_network, read_weights\n"
        "torch.manual_seed(0); before = torch.rand(3)\n"
        "torch.manual_seed(0)\n"
        "for method, f in (('ps-fcn-n', 'p.pt'), ('lcnet', 'l.pt')):\n"
        "    net, _, w = load_network(method, sys.argv[1] + '/' + f)\n"
        "    for k, t in net.state_dict().items():\n"
        "        assert t.dtype == torch.float32 and torch.equal(t, w.state_dict[k].float()), k\n"
        "        assert t.untyped_storage().data_ptr() != w.state_dict[k].untyped_storage().data_ptr(), k\n"
        "assert torch.equal(torch.rand(3), before), 'the global generator moved'\n"
        "print(sorted(m for m in ('torch._dynamo', 'sympy') if m in sys.modules))\n")
    p = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "[]"


def test_folder_and_in_memory_paths_agree(tmp_path):
    """capture_normals (images streamed from disk, divided by their intensities) and array_normals
    on load_images of the same folder give the same normals (an analysis once seemed to disagree:
    it had scored mask pixels without a ground-truth normal, see test_score_skips_pixels_without_gt)."""
    from psctl.infer import capture_normals
    from psctl.io.capture import load_images, load_mask, open_capture

    write_capture(tmp_path / "obj", n=6, size=36)
    cap = open_capture(tmp_path / "obj")
    w = save_weights(tmp_path / "ps_fcn.pt", model(), {"method": "ps-fcn", "train_images": 32, "input_mean": 0.2236})
    mask = load_mask(cap)
    a = capture_normals(cap, mask, "ps-fcn", w, {"device": "cpu"})
    b = array_normals(load_images(cap), cap.lights, mask, "ps-fcn", w, {"device": "cpu"})
    assert a.info["exposure_scale"] == b.info["exposure_scale"]
    np.testing.assert_array_equal(a.normals, b.normals)


def test_score_is_inside_the_mask_only(tmp_path):
    """Ground truth that reaches past the mask (an eroded mask, a ground-truth map of the whole
    frame) is scored inside the mask only: outside it the method gives no normal."""
    import scipy.io

    from psctl.api import run_normals
    from psctl.metrics import angular_error

    arrays = write_capture(tmp_path / "obj", n=8, size=36)
    gt = scipy.io.loadmat(tmp_path / "obj" / "Normal_gt.mat")["Normal_gt"]
    gt[~arrays["mask"]] = (0.6, 0.0, 0.8)  # a valid normal on every background pixel
    scipy.io.savemat(tmp_path / "obj" / "Normal_gt.mat", {"Normal_gt": gt})
    got: dict = {}
    r = run_normals(tmp_path / "obj", method="l2", write=False, arrays=got)
    m = arrays["mask"]
    assert r["n_evaluated_pixels"] == r["n_mask_pixels"] == int(m.sum())
    assert r["mae"] == pytest.approx(float(angular_error(got["normals"], gt, m).mean()), rel=1e-5)
    assert r["mae"] < 1.0 and r["mae_missing_as_90"] == r["mae"]
    assert (got["error"][~m] == 0).all()


def test_score_skips_pixels_without_gt(tmp_path):
    """Mask pixels whose ground-truth normal is zero (73 of pot2's 35,278 in DiLiGenT's cropped
    set) are not scored: they would count 90 degrees each whatever the method answers."""
    import scipy.io

    from psctl.api import run_normals

    arrays = write_capture(tmp_path / "obj", n=8, size=36)
    full = run_normals(tmp_path / "obj", method="l2", write=False)
    gt = scipy.io.loadmat(tmp_path / "obj" / "Normal_gt.mat")["Normal_gt"]
    holes = np.argwhere(arrays["mask"])[::7]
    gt[holes[:, 0], holes[:, 1]] = 0
    scipy.io.savemat(tmp_path / "obj" / "Normal_gt.mat", {"Normal_gt": gt})
    got: dict = {}
    holed = run_normals(tmp_path / "obj", method="l2", out=tmp_path / "out", arrays=got)
    assert holed["n_mask_pixels"] == full["n_mask_pixels"] == int(arrays["mask"].sum())
    assert holed["n_evaluated_pixels"] == full["n_evaluated_pixels"] - len(holes)
    assert holed["mae"] < 1.0  # Lambertian sphere, L2: near exact on the scored pixels, no 90s
    # and as the authors' code scores, written out here on its own: both maps normalised (a zero
    # vector stays zero), the clipped dot product's angle averaged over every mask pixel
    n = holed["n_mask_pixels"]
    m = arrays["mask"]
    unit = lambda v: v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
    dots = np.clip((unit(got["normals"].astype(np.float64)) * unit(gt)).sum(-1), -1, 1)
    assert holed["mae_missing_as_90"] == pytest.approx(float(np.degrees(np.arccos(dots[m])).mean()), rel=1e-5)
    assert full["mae_missing_as_90"] == full["mae"]
    assert [x for x in holed["notes"] if x.startswith("scoring:")] == [
        f"scoring: {len(holes)} of {n} mask pixels have no ground-truth normal in Normal_gt.mat (zero or NaN) and are "
        f"not scored; at 90 degrees each, as the authors' evaluation code counts a zero normal, the MAE "
        f"would be {holed['mae_missing_as_90']:.2f} (mae_missing_as_90)"]
    assert not any(x.startswith("scoring:") for x in full["notes"])
    # the error array and error.png keep them apart from a perfect pixel: NaN, drawn grey
    err = got["error"]
    assert np.isnan(err[holes[:, 0], holes[:, 1]]).all() and np.isnan(err).sum() == len(holes)
    assert (err[~arrays["mask"]] == 0).all()
    from psctl.io.images import read_image
    from psctl.io.report import UNSCORED

    pic, _ = read_image(tmp_path / "out" / "error.png")
    k = 3  # error_heatmap: a map under 96 px tall (36 here) in whole 3 x 3 blocks, under the title's band
    top = 2 * 20 + 6  # two title lines (object and method; MAE and median) of 10 * s px, 3 * s more, s = 2
    body = pic[top:top + 36 * k:k, 4:4 + 36 * k:k]  # 2 * s px off the left edge
    grey = np.abs(body - UNSCORED).max(-1) < 1 / 255
    assert (grey == np.isnan(err)).all()
    from psctl.io.report import jet

    scored = arrays["mask"] & ~np.isnan(err)  # drawn in jet over 0..45 degrees, black outside
    np.testing.assert_allclose(body[scored], jet(err[scored] / 45), atol=1 / 255)
    assert (body[~arrays["mask"]] == 0).all()


def test_black_capture_is_an_error_for_ps_fcn_n(tmp_path):
    """PS-FCN+N normalises each pixel, so it would answer on black images; the folder is named."""
    from psctl.api import run_normals
    from psctl.io.images import write_image
    from tests.conftest import write_capture

    weights = tmp_path / "n.pt"
    save_weights(weights, model(), {"method": "ps-fcn-n", "train_images": 32})
    folder = tmp_path / "blackPNG"
    write_capture(folder, n=6)
    for k in range(6):
        write_image(folder / f"{k + 1:03d}.png", np.zeros((40, 40, 3)), "uint16")
    with pytest.raises(PsctlError, match="all images are black") as e:
        run_normals(folder, method="ps-fcn-n", weights=weights, write=False, device="cpu")
    assert e.value.path == str(folder)


def test_weights_with_inf_are_refused(tmp_path):
    from psctl.errors import PsctlError
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    state = {k: v.clone() for k, v in PSFCN().state_dict().items()}
    state["regressor.est_normal.0.weight"][0, 0, 0, 0] = float("inf")
    with pytest.raises(PsctlError, match="NaN or infinite"):
        save_weights(tmp_path / "inf.pt", state, {"method": "ps-fcn", "train_images": 32})


@pytest.mark.parametrize("method", ["l2", "ps-fcn", "ps-fcn-n"])
def test_normals_do_not_depend_on_the_captures_units(tmp_path, method):
    """A capture scaled by one factor (float images in other units, an intensity file in other
    units) gives the same normals and the same dark pixels: no absolute threshold decides."""
    from psctl.api import estimate_normals
    from psctl.metrics import angular_error

    images, lights, mask = scene(8, 24, 24)
    meta = {"method": method, "train_images": 32}
    if method == "ps-fcn":
        meta["input_mean"] = 0.2
    w = None if method == "l2" else save_weights(tmp_path / "w.pt", model(), meta)
    ref = estimate_normals(images, lights, mask, method=method, weights=w, device="cpu")
    for s in (1e-15, 1e-6, 1e6, 1e30):
        got = estimate_normals(images * np.float32(s), lights, mask, method=method, weights=w, device="cpu")
        assert np.isfinite(got).all()
        assert angular_error(got, ref, mask).max() < 0.01, s
    if method != "l2":  # denormal values: one clear error, not a crash or silent nonsense
        with pytest.raises(PsctlError, match="rescale them"):
            estimate_normals(images * np.float32(1e-39), lights, mask, method=method, weights=w, device="cpu")


def test_l2_dark_pixels_are_relative_to_the_capture():
    from psctl.classic import l2_normals

    images, lights, mask = scene(8, 24, 24)
    images[:, :, :12] *= 1e-3  # a dim half: dim, not dark
    for s in (1e-9, 1.0, 1e9):
        r = l2_normals(images * s, lights, mask)
        assert not r.dark[mask].any(), s
    dark = images.copy()
    dark[:, :, :12] = 0.0
    assert l2_normals(dark * 1e-9, lights, mask).dark[mask].sum() == (mask[:, :12]).sum()


def test_read_memo_yields_what_the_reader_does_and_reads_once_within_budget():
    """ReadMemo (the ensemble's shared reads): any (start, box) call yields exactly the reader's
    images; images kept within the budget are not read again, the rest are."""
    from psctl.infer import ReadMemo

    imgs = [np.full((4, 5, 3), k, np.float32) for k in range(6)]
    calls = []

    def reader(start, box):
        for k in range(start, 6):
            calls.append(k)
            yield imgs[k][box]

    box, other = (slice(0, 4), slice(0, 5)), (slice(1, 3), slice(0, 5))
    memo = ReadMemo(reader, 3 * imgs[0].nbytes)  # room for three
    for start in (0, 0, 2, 4, 0):
        got = list(memo(start, box))
        assert [float(g[0, 0, 0]) for g in got] == list(range(start, 6))
    assert calls[:6] == list(range(6)) and calls[6:9] == [3, 4, 5]  # the second pass read only 3..5
    assert sum(k < 3 for k in calls) == 3  # images 0..2 were read once in five passes
    calls.clear()
    got = list(memo(0, other))  # another box: its own images, out of the budget already spent
    assert calls == list(range(6)) and all(g.shape == (2, 5, 3) for g in got)
    assert memo.used == 3 * imgs[0].nbytes


def test_ensemble_reads_each_image_once(tmp_path, monkeypatch):
    """--method ensemble on a folder reads each image file once for both networks, and gives
    the unit mean of the two networks run apart (each reading the files itself)."""
    import psctl.io.capture
    from psctl.infer import capture_normals
    from psctl.io.capture import load_mask, open_capture

    write_capture(tmp_path / "cap", n=6, seed=3)
    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path))
    torch.manual_seed(0)
    save_weights(tmp_path / "ps_fcn.pt", model(), {"method": "ps-fcn", "train_images": 32})
    save_weights(tmp_path / "ps_fcn_n.pt", model(seed=1), {"method": "ps-fcn-n", "train_images": 32})
    cap = open_capture(tmp_path / "cap")
    mask = load_mask(cap)
    reads = []
    real = psctl.io.capture.read_image
    monkeypatch.setattr(psctl.io.capture, "read_image", lambda p, *a, **k: (reads.append(p), real(p, *a, **k))[1])
    ens = capture_normals(cap, mask, "ensemble", config={"device": "cpu"})
    images = [p for p in reads if p in cap.image_paths]
    assert sorted(images) == sorted(cap.image_paths)  # each once
    reads.clear()
    members = [capture_normals(cap, mask, m, config={"device": "cpu"}) for m in ("ps-fcn", "ps-fcn-n")]
    assert sum(p in cap.image_paths for p in reads) >= 2 * len(cap.image_paths)  # apart: each reads them
    mean = members[0].normals[mask].astype(np.float64) + members[1].normals[mask]
    np.testing.assert_allclose(ens.normals[mask], mean / np.linalg.norm(mean, axis=-1, keepdims=True), atol=1e-6)
    assert np.abs(members[0].normals - members[1].normals).max() > 1e-3  # two different networks
    assert ens.notes == list(dict.fromkeys(members[0].notes + members[1].notes))


def test_precision_option(tmp_path, monkeypatch, capsys):
    """--precision: float32 by default; bf16 runs under autocast where the CPU has native bf16
    (normals close to float32's, report and eval.json say so) and is one line, exit 2 and nothing
    written where it would be emulated; fp16 on a CPU the same; l2 notes it unused; bad names refused."""
    import psctl.infer
    from psctl.api import estimate_normals, run_normals
    from psctl.eval import run_benchmark
    from psctl.models import check_precision

    assert check_precision("BF16") == "bf16" and check_precision("float32") == "float32"
    for bad in ("fp32", "half", None, 16):
        with pytest.raises(PsctlError, match="unknown --precision .*choose from float32, bf16, fp16$"):
            check_precision(bad)
    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path))
    save_weights(tmp_path / "ps_fcn_n.pt", model(seed=2), {"method": "ps-fcn-n", "train_images": 32})
    write_capture(tmp_path / "root" / "ballPNG", n=6, seed=4)
    cap = tmp_path / "root" / "ballPNG"
    seen = []
    real = psctl.infer._autocast
    monkeypatch.setattr(psctl.infer, "_autocast", lambda d, k: (seen.append(k), real(d, k))[1])
    monkeypatch.setattr(psctl.infer, "cpu_has_bf16", lambda: False)  # a CPU that would emulate bf16
    for p, msg in (("bf16", "would emulate it"), ("fp16", "fp16 is for CUDA")):
        with pytest.raises(PsctlError, match=msg):
            run_normals(cap, "ps-fcn-n", out=tmp_path / "no", precision=p, device="cpu")
        with pytest.raises(PsctlError, match=msg):
            estimate_normals(*scene(4, 16, 16), method="ps-fcn-n", precision=p, device="cpu")
    assert not (tmp_path / "no").exists() and None not in seen  # refused before any network ran
    import psctl.lights
    from psctl.models.lcnet import LCNet

    save_weights(tmp_path / "lcnet.pt", LCNet(), {"method": "lcnet", "train_images": 32})

    def no_lcnet(*a, **k):
        raise AssertionError("LCNet ran before the precision was refused")

    with monkeypatch.context() as m:
        m.setattr(psctl.lights, "capture_lights", no_lcnet)
        with pytest.raises(PsctlError, match="would emulate it"):  # sdps: before LCNet's minutes of work
            run_normals(cap, "sdps", out=tmp_path / "no", precision="bf16", device="cpu")
    seen.clear()
    monkeypatch.setattr(psctl.infer, "cpu_has_bf16", lambda: True)
    a = run_normals(cap, "ps-fcn-n", out=tmp_path / "a", device="cpu")
    assert a["precision"] == "float32" and set(seen) == {None}
    seen.clear()
    arrays = {}
    b = run_normals(cap, "ps-fcn-n", out=tmp_path / "b", device="cpu", precision="BF16", arrays=arrays)
    assert b["precision"] == "bf16" and set(seen) == {"bf16"}
    from psctl.io.summary import render_normals

    render_normals(b)
    assert "ps-fcn-n, bf16, 6 images" in capsys.readouterr().out  # the terminal says so too
    render_normals({**b, "views": 8, "downsample": 2})
    assert "ps-fcn-n, 8 views, 1/2 size, bf16, 6 images" in capsys.readouterr().out
    render_normals(a)
    assert "ps-fcn-n, 6 images" in capsys.readouterr().out
    assert json.loads((tmp_path / "b" / "report.json").read_text())["precision"] == "bf16"
    assert 0 < abs(b["mae"] - a["mae"]) < 2  # random weights: loose; trained ones in docs/models.md
    np.testing.assert_allclose(np.linalg.norm(arrays["normals"][arrays["mask"]], axis=-1), 1, atol=1e-4)
    seen.clear()
    images, lights, mask = scene(4, 16, 16)
    n32 = estimate_normals(images, lights, mask, method="ps-fcn-n", device="cpu")
    n16 = estimate_normals(images, lights, mask, method="ps-fcn-n", device="cpu", precision="bf16")
    assert seen[-1] == "bf16" and 0 < np.abs(n16 - n32).max() < 0.2
    seen.clear()
    sd = run_normals(cap, "sdps", write=False, device="cpu", precision="bf16")  # its second stage
    assert sd["precision"] == "bf16" and seen.count("bf16") >= 2 and None not in seen  # refined: two passes
    l2 = run_normals(cap, "l2", write=False, precision="bf16")
    assert l2["precision"] == "float32" and any("--precision bf16 unused" in n for n in l2["notes"])
    r = run_benchmark("folder", root=tmp_path / "root", method="ps-fcn-n", device="cpu", precision="bf16",
                      out=tmp_path / "ev")
    assert r["precision"] == "bf16" and json.loads((tmp_path / "ev" / "eval.json").read_text())["precision"] == "bf16"
    assert run_benchmark("folder", root=tmp_path / "root", method="l2", precision="bf16")["precision"] == "float32"


def test_later_passes_read_bands_of_rows_with_the_same_normals(tmp_path, monkeypatch):
    """A capture of several tile groups (one pass over the images each): the passes after the
    first decode only their group's rows (ImageCheck.reader's ``band``) and set the hot pixels
    the first pass clamped (helper-178). The normals are those of whole reads, bit for bit,
    for a network and for the ensemble (ReadMemo's band), a hot pixel among the images."""
    from psctl.io import capture as capture_module
    from psctl.io.capture import ImageCheck, load_mask, open_capture
    from psctl.io.images import read_image, write_image
    from psctl.infer import capture_normals

    write_capture(tmp_path / "c", n=6, size=72)
    img = read_image(tmp_path / "c" / "003.png")[0]
    img[30, 40, 1] = 1000.0  # hot: far over 300 times the image's mean (a float file holds it)
    write_image(tmp_path / "c" / "003.exr", img, "float")
    (tmp_path / "c" / "003.png").unlink()
    names = (tmp_path / "c" / "filenames.txt").read_text().replace("003.png", "003.exr")
    (tmp_path / "c" / "filenames.txt").write_text(names)
    cap = open_capture(tmp_path / "c")
    mask = load_mask(cap)
    cfg = {"device": "cpu", "tile": 32, "group_mb": 1, "cache_mb": 0, "prefetch_mb": 0}
    bands = []
    iter_images = capture_module.iter_images
    monkeypatch.setattr(capture_module, "iter_images",
                        lambda *a, **k: (bands.append(k.get("rows_only")), iter_images(*a, **k))[1])
    got = {m: capture_normals(cap, mask, m, config=cfg) for m in ("ps-fcn-n", "ensemble")}
    assert bands.count(True) >= 4, bands  # the later passes read bands
    assert any("hot" in n for n in got["ps-fcn-n"].notes), got["ps-fcn-n"].notes
    reader = ImageCheck.reader

    def whole_reads(self, *a, **k):  # the reader without its band: later passes read whole boxes again
        read = reader(self, *a, **k)
        del read.band
        return read

    monkeypatch.setattr(ImageCheck, "reader", whole_reads)
    bands.clear()
    for m, res in got.items():
        ref = capture_normals(cap, mask, m, config=cfg)
        assert res.normals.tobytes() == ref.normals.tobytes(), m
        assert res.notes == ref.notes
    assert True not in bands


def test_an_image_rewritten_between_passes_is_an_error(tmp_path, monkeypatch):
    """A file rewritten at the same size between the engine's passes was read old in some tile
    groups and new in others, without a word (helper-186: 5,716 pixels changed): now one error
    naming it, with band reads and whole reads alike."""
    from psctl.io import capture as capture_module
    from psctl.io.capture import load_mask, open_capture
    from psctl.io.images import read_image, write_image
    from psctl.infer import capture_normals

    write_capture(tmp_path / "c", n=6, size=72)
    cap = open_capture(tmp_path / "c")
    mask = load_mask(cap)
    cfg = {"device": "cpu", "tile": 32, "group_mb": 1, "cache_mb": 0, "prefetch_mb": 0}
    calls = []
    iter_images = capture_module.iter_images

    def rewrite_after_the_first_pass(*a, **k):
        calls.append(1)
        if len(calls) == 3:  # the +N pass and the first group's are done
            path = tmp_path / "c" / "003.png"
            write_image(path, read_image(path)[0] * 0.5, "uint16")
        return iter_images(*a, **k)

    monkeypatch.setattr(capture_module, "iter_images", rewrite_after_the_first_pass)
    with pytest.raises(PsctlError, match=r"003.png: changed on disk while psctl read it \(between its passes"):
        capture_normals(cap, mask, "ps-fcn-n", config=cfg)
    monkeypatch.undo()
    write_capture(tmp_path / "c", n=6, size=72)  # as it was: runs through
    assert capture_normals(open_capture(tmp_path / "c"), mask, "ps-fcn-n", config=cfg).normals.any()
