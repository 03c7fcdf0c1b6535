"""The synthetic data engine: renderer physics, BRDFs, shadows, the training stream, the writer."""

from __future__ import annotations

import json
import math
import shutil
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from psctl.errors import PsctlError
from psctl.synth import lights as L
from psctl.synth import materials as M
from psctl.synth import render as R
from psctl.synth.shapes import BACKGROUND, GBuffer, blobby_gbuffers, sphere_gbuffer

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"


@pytest.fixture(autouse=True)
def _one_thread():
    """Small tensors: one thread is faster and immune to other processes' load."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# --- image formation --------------------------------------------------------------------------


def test_lambertian_sphere_solved_by_l2():
    from psctl.classic import l2_normals

    sp = sphere_gbuffer(64)
    lights = L.sample_lights((1, 12), gen(1), "diligent")
    mat = M.lambertian(torch.tensor([[0.8, 0.6, 0.4]]))
    img = R.shade(sp.normals.reshape(1, 3, -1), lights, mat)[0]  # [N, 3, P], no shadows
    nl = torch.einsum("cp,nc->np", sp.normals.reshape(3, -1), lights[0])
    lit = ((nl > 0).all(0).reshape(64, 64) & sp.mask[0, 0]).numpy()  # no attached shadow anywhere
    assert lit.sum() > 1500
    images = img.reshape(12, 3, 64, 64).permute(0, 2, 3, 1).numpy()
    res = l2_normals(images, lights[0].numpy(), lit)
    gt = sp.normals[0].permute(1, 2, 0).numpy()
    err = np.degrees(np.arccos(np.clip((res.normals * gt).sum(-1), -1, 1)))[lit]
    assert err.mean() < 0.5
    # Lambert's law itself: radiance = albedo / pi * n.l
    expect = 0.8 / math.pi * nl.clamp_min(0) * sp.mask.reshape(1, -1)
    assert torch.allclose(img[:, 0], expect, atol=1e-6)


def block_scene(size: int = 48) -> GBuffer:
    """A floor (z = 0) with a tall block in the middle (z = 0.5): a guaranteed cast shadow."""
    depth = torch.zeros(1, 1, size, size)
    q = size // 2
    depth[..., q - 4:q + 4, q - 4:q + 4] = 0.5
    normals = torch.zeros(1, 3, size, size)
    normals[:, 2] = 1.0
    return GBuffer(normals, depth, torch.ones(1, 1, size, size, dtype=torch.bool), ["test"])


@pytest.mark.parametrize("method", ["march", "horizon"])
def test_cast_shadows_fall_away_from_the_light(method):
    g = block_scene()
    s = 45.0
    lights = torch.tensor([[[math.sin(math.radians(s)), 0.0, math.cos(math.radians(s))],  # from +x (right)
                            [0.0, math.sin(math.radians(s)), math.cos(math.radians(s))]]])  # from +y (up)
    if method == "march":
        vis = R.march_shadows(g.depth, lights)
    else:
        vis = R.horizon_visibility(R.horizon_map(g.depth, 32).flatten(2), lights).reshape(1, 2, 48, 48)
    q = 24
    assert vis[0, 0, q, q - 8] == 0 and vis[0, 0, q, q + 8] == 1  # light from the right: shadow on the left
    assert vis[0, 1, q + 8, q] == 0 and vis[0, 1, q - 8, q] == 1  # light from above: shadow below (rows down)
    assert vis[0, 0, q, 2] == 1 and vis[0, 1, 46, q] == 1  # beyond the shadow's length (12 px): lit


def test_cast_shadows_only_darken_and_methods_agree():
    g = blobby_gbuffers(2, 48, gen(3))
    lights = L.sample_lights((2, 16), gen(4), "hemisphere")
    mat = M.sample_materials(2, gen(5), M.load_merl())
    n = g.normals.reshape(2, 3, -1)
    plain = R.shade(n, lights, mat)
    vis = R.march_shadows(g.depth, lights).reshape(2, 16, -1)
    hz = R.horizon_visibility(R.horizon_map(g.depth, 32).flatten(2), lights)
    assert ((vis == 0) | (vis == 1)).all() and ((hz >= 0) & (hz <= 1)).all()
    for v in (vis, hz):
        shadowed = R.shade(n, lights, mat, v)
        assert (shadowed <= plain + 1e-7).all()
    lit = (torch.einsum("bcp,bnc->bnp", n, lights) > 0) & g.mask.reshape(2, 1, -1)
    assert (vis[lit] < 1).any()  # blobby shapes do cast shadows
    assert ((vis[lit] > 0.5) == (hz[lit] > 0.5)).float().mean() > 0.97
    # a convex shape casts none where the surface faces the light
    sp = sphere_gbuffer(48)
    vs = R.march_shadows(sp.depth, lights[:1])
    hs = R.horizon_visibility(R.horizon_map(sp.depth).flatten(2), lights[:1]).reshape(vs.shape)
    facing = (torch.einsum("bchw,bnc->bnhw", sp.normals, lights[:1]) > 0.05) & sp.mask
    assert (vs[facing] == 1).all() and (hs[facing] > 0.5).all()


def test_noise_and_quantisation():
    x = torch.full((4, 3, 64, 64), 0.5)
    y = R.uniform_noise(x.clone(), gen(), 0.025) - x  # in place on its argument
    assert y.abs().max() <= 0.025 and y.abs().max() > 0.02 and abs(float(y.mean())) < 1e-3
    q = R.quantize(torch.tensor([-0.1, 0.3, 1.2]), 16)
    assert q[0] == 0 and q[2] == 1 and abs(float(q[1]) * 65535 - round(0.3 * 65535)) < 1e-3


def test_capture_rounding_is_an_8_bit_camera_at_a_dark_exposure():
    """``capture``: drawn samples land on the 8-bit grid of a camera whose mean object pixel is
    the drawn value, at their own brightness; the others are untouched."""
    from psctl.synth.stream import capture_rounding

    g = torch.Generator().manual_seed(3)
    img = torch.rand(6, 4, 3, 10, 10, generator=g) * 0.4  # [b, n, 3, p] with p = 10 x 10 here
    msk = torch.ones(6, 10, 10)
    img, msk = img.flatten(3), msk.flatten(1)[:, None]  # as the stream holds them: [b, n, 3, p], [b, 1, p]
    out = capture_rounding(img, msk, gen(), {"p": 1.0, "mean": [0.02, 0.02], "bits": 8})
    for i in range(6):
        s = 0.02 / float(img[i].mean())
        codes = out[i] * s * 255
        assert torch.allclose(codes, codes.round(), atol=1e-3)  # on the 8-bit grid of that exposure
        assert len(torch.unique(codes.round())) <= 256 and (codes.round() <= 255).all()
        assert abs(float(out[i].mean()) / float(img[i].mean()) - 1) < 0.05  # brightness kept
        assert (out[i] == 0).any() and not (img[i] == 0).any()  # dark values clip to black
    same = capture_rounding(img, msk, gen(), {"p": 0.0, "mean": [0.02, 0.02], "bits": 8})
    assert torch.equal(same, img)
    low = capture_rounding(img, msk, gen(), {"p": 1.0, "mean": [0.02, 0.02], "bits": 8, "floor": True})
    s = (0.02 / img.flatten(1).mean(1))[:, None, None, None]
    torch.testing.assert_close(low, torch.floor(img * s * 255) / (255 * s))  # truncated, as DiLiGenT's crops
    assert (low <= img + 1e-7).all() and (low < out - 1e-7).any()


def test_stream_capture_option():
    from psctl.synth.stream import SynthStream

    plain = SynthStream({**SMALL}, seed=2).next_batch()
    cap = SynthStream({**SMALL, "capture": {"p": 1.0, "mean": [0.01, 0.01], "bits": 8}}, seed=2).next_batch()
    assert torch.equal(plain["normals"], cap["normals"]) and not torch.equal(plain["images"], cap["images"])
    for k in range(len(cap["images"])):  # few grey levels per sample: a dark 8-bit capture
        m = cap["masks"][k, 0].bool()
        assert len(torch.unique(cap["images"][k][:, :, m])) < 64


def test_ambient_term_lifts_shadows_by_a_times_albedo():
    """Real shadows are rarely black; the stream's ``ambient`` option adds a * kD to every image."""
    sp = sphere_gbuffer(32)
    n = sp.normals.reshape(1, 3, -1)
    lights = torch.tensor([[[0.6, 0.0, 0.8]]])
    kd = torch.tensor([[0.5, 0.4, 0.3]])
    mat = M.lambertian(kd)
    plain = R.shade(n, lights, mat)
    lifted = R.shade(n, lights, mat, ambient=torch.tensor([0.01]))
    obj = sp.mask.reshape(-1)
    dark = obj & (torch.einsum("bcp,bnc->bnp", n, lights)[0, 0] < 0)
    assert dark.any() and (plain[0, 0][:, dark] == 0).all()
    assert torch.allclose(lifted - plain, (0.01 * kd)[:, None, :, None] * obj, atol=1e-7)


def test_stream_ambient_option_leaves_no_black_shadow():
    from psctl.synth.stream import SynthStream

    cfg = {**SMALL, "noise": 0.0, "texture": 0.0, "blend": 0.0, "materials": {"lambert": 1.0}}
    for amb, black in ((0.0, True), (0.02, False)):
        b = SynthStream({**cfg, "ambient": amb}, seed=2).next_batch()
        m = b["masks"].bool()[:, None].expand_as(b["images"])
        assert ((b["images"][m] == 0).any()) == black, amb


def test_stream_interreflection_option_lights_attached_shadows():
    """With interreflections a Lambertian sample's observations where n.l < 0 are no longer all
    black on a concave G-buffer (the first mesh or blobby views have concavities), and only
    samples drawn for it change."""
    from psctl.synth.stream import SynthStream

    cfg = {**SMALL, "noise": 0.0, "texture": 0.0, "blend": 0.0, "materials": {"lambert": 1.0}, "pool": 4,
           "shadows": False}
    out = {}
    for a in (0.0, 0.9):
        out[a] = SynthStream({**cfg, "interreflection": {"p": 1.0, "albedo": [a, a]}}, seed=2).next_batch()
    b0, b1 = out[0.0], out[0.9]
    assert torch.equal(b0["normals"], b1["normals"]) and torch.equal(b0["lights"], b1["lights"])
    nl = torch.einsum("bnc,bchw->bnhw", b0["lights"], b0["normals"])
    away = (nl < -0.05) & b0["masks"].bool()  # attached shadow, [B, N, H, W]
    grey0, grey1 = b0["images"].mean(2), b1["images"].mean(2)
    assert float(grey0[away].abs().max()) == 0.0
    assert float((grey1[away] > 0).float().mean()) > 0.05
    transfer = SynthStream({**cfg, "interreflection": {"p": 1.0}}, seed=2).pool.transfer
    assert transfer is not None and float(transfer[..., 9].max()) < 1.0  # a view factor


def _image_ratios(cfg: dict, err: dict, seed: int = 4):
    """Per-image ratio [B, N] of the object's summed pixels with ``intensity_error`` = err over the
    same batch without it, and both batches."""
    from psctl.synth.stream import SynthStream

    plain = SynthStream(cfg, seed=seed).next_batch()
    bad = SynthStream({**cfg, "intensity_error": err}, seed=seed).next_batch()
    m = plain["masks"].bool()[:, None].expand_as(plain["images"])  # masks [B, 1, H, W] -> [B, N, 3, H, W]
    num = torch.where(m, bad["images"], 0).flatten(2).sum(-1)
    den = torch.where(m, plain["images"], 0).flatten(2).sum(-1)
    return num / den, plain, bad


def test_stream_intensity_error_scales_a_group_of_images_and_keeps_the_listed_intensities():
    """Mis-calibrated intensities: the chosen images are brighter by the group's factor than the
    same batch without the option, the others are unchanged, and the batch's intensities (what a
    calibrated network is told) do not change."""
    cfg = {**SMALL, "noise": 0.0, "clip": None, "intensities": "random"}
    ratio, plain, err = _image_ratios(cfg, {"p": 1.0, "share": [0.5, 0.5], "scale": [1.25, 1.25]})
    assert torch.equal(plain["intensities"], err["intensities"]) and torch.equal(plain["normals"], err["normals"])
    scaled = (ratio - 1.25).abs() < 1e-4
    assert bool((scaled | ((ratio - 1.0).abs() < 1e-4)).all())
    assert 0.3 < float(scaled.float().mean()) < 0.7


def test_stream_intensity_error_one_factor_per_sample_and_some_samples_exact():
    """One factor per sample (shared by its chosen images, different between samples, inside
    `scale`), and with p = 0.5 some samples have no wrong image at all."""
    cfg = {**SMALL, "batch_size": 16, "n_images": 12, "noise": 0.0, "clip": None}
    ratio, _, _ = _image_ratios(cfg, {"p": 0.5, "share": [0.3, 0.6], "scale": [0.7, 1.4]})
    off = (ratio - 1.0).abs() > 1e-4  # [B, N]
    factors = []
    for r, o in zip(ratio, off):
        if o.any():
            f = r[o]
            assert float(f.max() - f.min()) < 1e-4 * float(f.max())  # one factor per sample
            assert 0.7 - 1e-4 <= float(f[0]) <= 1.4 + 1e-4
            factors.append(float(f[0]))
    exact = int((~off.any(1)).sum())
    assert 2 <= exact <= 14 and len(factors) >= 2
    assert max(factors) - min(factors) > 1e-3  # drawn per sample


def test_stream_intensity_error_applies_before_the_sensor_clips():
    """The error is the scene's, not the file's: a brighter image saturates at the clip like any
    other, it is not scaled past it."""
    cfg = {**SMALL, "noise": 0.0, "clip": 1.0, "exposure": (2.0, 2.0)}  # bright enough to clip
    _, plain, bad = _image_ratios(cfg, {"p": 1.0, "share": [1.0, 1.0], "scale": [1.4, 1.4]})
    assert float(plain["images"].max()) == 1.0 and float(bad["images"].max()) <= 1.0


@pytest.mark.parametrize("opts, msg", [
    ({"p": 0.5, "shares": [0, 0.4]}, "unknown key"),
    ({"p": 1.5}, "0 <= p <= 1"),
    ({"share": [0.5, 0.2]}, "share lo <= hi"),
    ({"scale": [0.0, 1.4]}, "0 < scale lo"),
    ({"scale": 1.3}, "two numbers"),
    (True, "mapping"),
])
def test_stream_rejects_bad_intensity_error_options(opts, msg):
    from psctl.synth.stream import make_config

    with pytest.raises(PsctlError, match=msg):
        make_config({"intensity_error": opts})


@pytest.mark.parametrize("method, where", [("lcnet", "data"), ("ups-fcn", "data"), ("lcnet", "val")])
def test_uncalibrated_training_refuses_intensity_errors(tmp_path, method, where):
    """Only PS-FCN and PS-FCN+N are told the listed intensities; the refusal comes before the run
    folder exists (also when only the validation data asks for it)."""
    from psctl.train import load_config, train

    cfg = load_config(REPO / "configs" / "tiny.yaml")
    err = {"p": 0.5}
    if where == "data":
        cfg["data"]["intensity_error"] = err
    else:
        cfg["val"]["data"] = {"intensity_error": err}
    with pytest.raises(PsctlError, match="intensity_error"):
        train(method, cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()



def test_stream_direction_error_keeps_the_images_and_lists_turned_lights():
    """Mis-calibrated directions: the images (rendered with the true lights) are the batch without
    the option, the listed lights are unit vectors above the horizon, exact for the samples that
    drew no error, and for the others off by about their zenith factor."""
    import math

    from psctl.synth.stream import SynthStream

    cfg = {**SMALL, "batch_size": 16}
    plain = SynthStream(cfg, seed=5).next_batch()
    err = SynthStream({**cfg, "direction_error": {"p": 0.5, "zenith_scale": [1.1, 1.1], "jitter": [0.0, 0.0]}},
                      seed=5).next_batch()
    assert torch.equal(plain["images"], err["images"]) and torch.equal(plain["normals"], err["normals"])
    assert torch.allclose(err["lights"].norm(dim=-1), torch.ones(()), atol=1e-5)
    assert bool((err["lights"][..., 2] > 0).all())
    zen_true = torch.acos(plain["lights"][..., 2].clamp(-1, 1))
    zen_listed = torch.acos(err["lights"][..., 2].clamp(-1, 1))
    exact = (err["lights"] - plain["lights"]).abs().amax((1, 2)) < 1e-6  # [B]
    assert 2 <= int(exact.sum()) <= 14
    off = ~exact
    want = (zen_true[off] * 1.1).clamp(max=math.radians(89.0))
    assert torch.allclose(zen_listed[off], want, atol=1e-4)
    azi = lambda d: torch.atan2(d[..., 1], d[..., 0])  # noqa: E731
    big = zen_true[off] > 0.1  # the azimuth of a light at the zenith is noise
    assert torch.allclose(azi(err["lights"][off])[big], azi(plain["lights"][off])[big], atol=1e-3)


def test_stream_direction_jitter_turns_each_light_by_about_its_sd():
    from psctl.synth.stream import SynthStream

    cfg = {**SMALL, "batch_size": 8, "n_images": 32}
    plain = SynthStream(cfg, seed=6).next_batch()
    err = SynthStream({**cfg, "direction_error": {"p": 1.0, "zenith_scale": [1.0, 1.0], "jitter": [2.0, 2.0]}},
                      seed=6).next_batch()
    ang = torch.rad2deg(torch.acos((err["lights"] * plain["lights"]).sum(-1).clamp(-1, 1)))
    # a 2-degree sd per tangent component: the angle is Rayleigh with mean 2 * sqrt(pi / 2) = 2.51
    assert 2.0 < float(ang.mean()) < 3.0 and float(ang.min()) > 0.0


@pytest.mark.parametrize("opts, msg", [
    ({"p": 0.5, "zenith": [0.9, 1.1]}, "unknown key"),
    ({"p": -0.1}, "0 <= p <= 1"),
    ({"zenith_scale": [1.1, 0.9]}, "zenith_scale lo <= hi"),
    ({"zenith_scale": [0.0, 1.1]}, "0 < zenith_scale lo"),
    ({"jitter": [0.0, 20.0]}, "jitter lo <= hi <= 10"),
    ({"jitter": "1"}, "two numbers"),
    ([0.5], "mapping"),
])
def test_stream_rejects_bad_direction_error_options(opts, msg):
    from psctl.synth.stream import make_config

    with pytest.raises(PsctlError, match=msg):
        make_config({"direction_error": opts})


def test_a_bad_stream_option_in_a_recipe_names_the_file(tmp_path):
    from psctl.train import load_config

    bad = tmp_path / "bad.yaml"
    bad.write_text("data:\n  direction_error: {p: 2}\n")
    with pytest.raises(PsctlError, match="0 <= p <= 1") as e:
        load_config(bad)
    assert e.value.path == str(bad)


@pytest.mark.parametrize("method", ["lcnet", "ups-fcn", "ps-fcn-dagger"])
def test_uncalibrated_training_refuses_direction_errors(tmp_path, method):
    from psctl.train import load_config, train

    cfg = load_config(REPO / "configs" / "tiny.yaml")
    cfg["data"]["direction_error"] = {"p": 0.5}
    with pytest.raises(PsctlError, match="direction_error"):
        train(method, cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()

# --- materials --------------------------------------------------------------------------------


def random_dirs(n: int, g: torch.Generator) -> torch.Tensor:
    v = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return torch.where(v[:, 2:] < 0, -v, v)  # upper hemisphere of z


def all_models(b: int) -> list[M.Material]:
    table = M.load_merl()
    g = gen(7)
    kd = M.random_colors(b, g)
    return [
        M.merl_materials(table, torch.arange(b) % len(table.names)),
        M.ggx(kd, torch.ones(b, 3), torch.linspace(0.02, 0.8, b), ior=torch.full((b,), 1.5)),
        M.ggx(kd * 0.05, M.random_colors(b, g, (0.5, 1.0)), torch.linspace(0.05, 0.6, b), metal=torch.ones(b)),
        M.lambertian(kd),
        M.sample_materials(b, g, table),
    ]


def test_brdfs_are_reciprocal_and_non_negative():
    b, k = 100, 64
    g = gen(2)
    n = random_dirs(b * k, g)
    # directions in n's upper hemisphere, some grazing
    l = random_dirs(b * k, g)
    v = random_dirs(b * k, g)
    frame = torch.linalg.qr(torch.randn(b * k, 3, 3, generator=g))[0]  # random frames: n = frame @ z
    n = frame[..., 2] * torch.sign(torch.linalg.det(frame))[:, None]
    to_world = lambda d: torch.einsum("pij,pj->pi", torch.stack([frame[..., 0], frame[..., 1], n], -1), d)
    l, v = to_world(l), to_world(v)
    n, l, v = (t.reshape(b, k, 3) for t in (n, l, v))
    for mat in all_models(b):
        f_lv = M.brdf(mat, n, l, v)
        f_vl = M.brdf(mat, n, v, l)
        assert torch.isfinite(f_lv).all() and (f_lv >= 0).all()
        assert torch.allclose(f_lv, f_vl, rtol=1e-4, atol=1e-6)
        below = M.brdf(mat, n, -l, v)  # light under the surface
        assert (below == 0).all()


def abc_by_hand(m: dict, i: tuple[float, float, float], o: tuple[float, float, float]) -> list[float]:
    """The README formula, term by term, in plain Python (normal = +z)."""
    h = [a + b for a, b in zip(i, o)]
    hn = math.sqrt(sum(x * x for x in h))
    h = [x / hn for x in h]
    ih = sum(a * b for a, b in zip(i, h))
    oh = sum(a * b for a, b in zip(o, h))
    g_vgroove = min(1.0, 2 * h[2] * i[2] / ih, 2 * h[2] * o[2] / oh)
    eta, c = m["ior"], ih
    g = math.sqrt(eta * eta - 1 + c * c)
    fresnel = 0.5 * ((g - c) / (g + c)) ** 2 * (1 + ((c * (g + c) - 1) / (c * (g - c) + 1)) ** 2)
    return [m["kD"][ch] / math.pi + fresnel * (m["A"][ch] / (1 + m["B"] * (1 - h[2])) ** m["C"]) * g_vgroove
            / (math.pi * i[2] * o[2]) for ch in range(3)]


@pytest.mark.parametrize("name", ["alum-bronze", "blue-acrylic", "yellow-phenolic"])
def test_abc_matches_hand_computation(name):
    params = json.loads(M.PACKAGED_MERL.read_text())["materials"][name]
    table = M.load_merl(M.PACKAGED_MERL)
    mat = M.merl_materials(table, [table.index(name)])
    for theta_i, phi_i, theta_o in ((30.0, 0.0, 20.0), (10.0, 40.0, 10.0), (60.0, 150.0, 45.0)):
        i = (math.sin(math.radians(theta_i)) * math.cos(math.radians(phi_i)),
             math.sin(math.radians(theta_i)) * math.sin(math.radians(phi_i)), math.cos(math.radians(theta_i)))
        o = (-math.sin(math.radians(theta_o)), 0.0, math.cos(math.radians(theta_o)))
        expect = abc_by_hand(params, i, o)
        got = M.brdf(mat, torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([i]), torch.tensor([o]))[0]
        assert got.tolist() == pytest.approx(expect, rel=1e-4)


def test_packaged_merl_table_equals_shared_data():
    shared = SHARED / "merl" / "merl_abc_fits.json"
    if not shared.is_file():
        pytest.skip(f"needs {shared} (the project's shared data; absent in a fresh clone)")
    ours = json.loads(M.PACKAGED_MERL.read_text())["materials"]
    theirs = json.loads(shared.read_text())["materials"]
    assert ours == theirs and len(ours) == 100


def test_merl_table_location(monkeypatch, tmp_path):
    monkeypatch.setenv("PSCTL_MERL", str(tmp_path / "nope.json"))
    with pytest.raises(PsctlError, match="PSCTL_MERL"):
        M.find_merl_file()
    (tmp_path / "merl_abc_fits.json").write_text(M.PACKAGED_MERL.read_text())
    monkeypatch.setenv("PSCTL_MERL", str(tmp_path))
    assert M.find_merl_file() == tmp_path / "merl_abc_fits.json"
    monkeypatch.delenv("PSCTL_MERL")
    assert M.find_merl_file() == M.PACKAGED_MERL
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(PsctlError, match="not a MERL ABC table"):
        M.load_merl(tmp_path / "bad.json")


def test_blend_maps_and_textures():
    w = M.blend_weights(["ramp", "checker", "irregular", "none"], 32, 32, gen())
    assert w.shape == (4, 1, 32, 32) and (w >= 0).all() and (w <= 1).all()
    for k in range(3):  # each map really mixes the two materials
        assert (w[k] < 0.1).float().mean() > 0.05 and (w[k] > 0.9).float().mean() > 0.05
    assert (w[3] == 1).all()
    t = M.albedo_texture(3, 16, 16, gen())
    assert t.shape == (3, 3, 16, 16) and (t > 0).all()


def test_lights():
    g = gen()
    for name, (lo, hi) in L.DISTRIBUTIONS.items():
        d = L.sample_lights((4, 500), g, name)
        zen = torch.rad2deg(torch.acos(d[..., 2].clamp(-1, 1)))
        assert torch.allclose(d.norm(dim=-1), torch.ones(4, 500), atol=1e-5)
        assert zen.min() >= lo - 1e-3 and zen.max() <= hi + 1e-3
        assert zen.max() > hi - 5 and zen.min() < lo + 5
    e = L.sample_intensities((1000,), g, "random")
    assert e.min() >= 0.2 and e.max() <= 2.0 and e.std() > 0.4
    assert (L.sample_intensities((5,), g, "unit") == 1).all()
    with pytest.raises(PsctlError, match="unknown light distribution 'sideways'"):
        L.sample_lights((3,), g, "sideways")


def _corr(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Pearson correlation along the last axis."""
    a, b = a - a.mean(-1, keepdim=True), b - b.mean(-1, keepdim=True)
    return (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1))


def test_directional_intensities_follow_the_lights():
    g = gen()
    lights = L.sample_lights((300, 96), g, "diligent")
    e = L.sample_intensities((300, 96), g, "directional", lights=lights)
    assert e.shape == (300, 96) and e.min() >= 0.2 and e.max() <= 2.0
    # a smooth function of direction (up to the small jitter): log e is nearly linear in l
    x = torch.cat([lights, torch.ones(300, 96, 1)], -1)
    fit = torch.linalg.lstsq(x, e.log()[..., None]).solution
    resid = (x @ fit)[..., 0] - e.log()
    unclamped = ((e > 0.2) & (e < 2.0)).all(-1)
    assert unclamped.sum() > 30
    assert resid[unclamped].abs().amax(-1).max() < 1.5 * math.log(L.DIRECTIONAL_JITTER)  # least squares, not the true a
    # each sample its own rig: strongly correlated with zenith in either sense, some with none
    c = _corr(e, lights[..., 2])
    assert (c > 0.6).any() and (c < -0.6).any() and c.abs().min() < 0.3
    # random ignores the lights; mixed is each of the two, per sample
    r = L.sample_intensities((300, 96), g, "random")
    assert _corr(r, lights[..., 2]).abs().max() < 0.45
    m = L.sample_intensities((300, 96), g, "mixed", lights=lights)
    smooth = torch.linalg.lstsq(x, m.log()[..., None]).solution
    resid_m = ((x @ smooth)[..., 0] - m.log()).abs().amax(-1)
    frac = (resid_m < 1.5 * math.log(L.DIRECTIONAL_JITTER)).float().mean()
    assert 0.15 < frac < 0.6  # directional (minus clamped ones) about half the time
    with pytest.raises(ValueError):
        L.sample_intensities((3, 4), g, "directional")  # needs the lights
    with pytest.raises(PsctlError, match="unknown intensity mode 'sometimes'"):
        L.sample_intensities((3, 4), g, "sometimes", lights=lights[:3, :4])


def test_stream_directional_intensities():
    from psctl.synth.stream import SynthStream

    b = SynthStream(SMALL, seed=1, intensities="directional", lights="diligent", crop=None, size=24).next_batch()
    e, l = b["intensities"], b["lights"]
    assert e.shape == l.shape[:2] and e.min() >= 0.2 and e.max() <= 2.0
    assert not torch.allclose(e, torch.ones_like(e))
    with pytest.raises(PsctlError, match="unknown intensities"):
        SynthStream(SMALL, seed=1, intensities="bright", crop=None, size=24)


def test_synth_folder_intensities(tmp_path):
    from psctl.synth.write import preset_objects, write_preset

    unit = preset_objects("blobby", seed=3, size=16, n_lights=12, k=2)
    dirn = preset_objects("blobby", seed=3, size=16, n_lights=12, k=2, intensities="directional")
    for a, b in zip(unit, dirn):  # the same objects and lights: only the intensities differ
        assert torch.equal(a.lights, b.lights) and a.name == b.name
        assert (a.intensities == 1).all() and not (b.intensities == 1).all()
        assert b.meta["intensities"] == "directional" and "intensities" not in a.meta
    assert not torch.equal(dirn[0].intensities, dirn[1].intensities)  # a rig per object
    with pytest.raises(PsctlError, match="unknown --intensities 'bright'"):
        preset_objects("blobby", size=16, n_lights=12, k=1, intensities="bright")
    r = write_preset(tmp_path / "set", "BLOBBY", seed=3, size=16, n_lights=12, k=2, intensities="Directional")
    assert r["intensities"] == "directional" and r["preset"] == "blobby"  # names as the command line takes them
    for o in dirn:  # the files hold the drawn intensities, one RGB row per light
        e = np.loadtxt(tmp_path / "set" / o.name / "light_intensities.txt")
        assert np.allclose(e, o.intensities.numpy()[:, None].repeat(3, 1), atol=1e-5)
    with pytest.raises(PsctlError, match="unknown --intensities 'bright'"):
        write_preset(tmp_path / "bad", "blobby", size=16, n_lights=12, k=1, intensities="bright")
    assert not (tmp_path / "bad").exists()  # refused before any folder is made


def test_lights_cone_range_is_drawn_per_sample():
    d = L.sample_lights((400, 300), gen(), "hemisphere", (40.0, 90.0))
    widest = torch.rad2deg(torch.acos(d[..., 2].clamp(-1, 1))).amax(dim=1)  # [400] per sample
    assert widest.min() >= 30 and widest.max() <= 90 + 1e-3
    # each sample fills its own cone: narrow and wide ones both occur, spread over [40, 90]
    assert (widest < 50).float().mean() > 0.1 and (widest > 80).float().mean() > 0.1
    assert abs(widest.median().item() - 65) < 6
    assert L.zenith_band("hemisphere", [40, 90]) == (0.0, 90.0)
    for bad in ([90, 40], [0, 90], [40], [40, 95]):
        with pytest.raises(PsctlError, match="max_zenith range must be|zenith band must lie in"):
            L.zenith_band("hemisphere", bad)
    from psctl.synth import stream

    with pytest.raises(PsctlError, match="zenith band must lie in"):  # the stream validates the option too
        stream.make_config(max_zenith=[95, 99])


# --- geometry ---------------------------------------------------------------------------------


def uv_sphere(n_lat: int = 24, n_lon: int = 48) -> tuple[np.ndarray, list[list[int]]]:
    verts = [[0.0, 1.0, 0.0]]
    for i in range(1, n_lat):
        t = math.pi * i / n_lat
        for j in range(n_lon):
            p = 2 * math.pi * j / n_lon
            verts.append([math.sin(t) * math.cos(p), math.cos(t), -math.sin(t) * math.sin(p)])
    verts.append([0.0, -1.0, 0.0])
    faces = []
    ring = lambda i, j: 1 + (i - 1) * n_lon + j % n_lon
    for j in range(n_lon):
        faces.append([0, ring(1, j), ring(1, j + 1)])
        faces.append([len(verts) - 1, ring(n_lat - 1, j + 1), ring(n_lat - 1, j)])
    for i in range(1, n_lat - 1):
        for j in range(n_lon):
            faces.append([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1), ring(i, j + 1)])  # quads
    return np.array(verts), faces


def write_obj(path: Path, verts: np.ndarray, faces: list[list[int]], slashes: bool = False) -> Path:
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in verts]
    for f in faces:
        lines.append("f " + " ".join(f"{i + 1}/{i + 1}" if slashes else str(i + 1) for i in f))
    path.write_text("# test mesh\n" + "\n".join(lines) + "\n")
    return path


def test_rasterised_mesh_matches_the_analytic_sphere(tmp_path):
    from psctl.synth import meshes

    verts, faces = uv_sphere()
    v, f = meshes.load_obj(write_obj(tmp_path / "ball.obj", verts, faces, slashes=True))
    assert len(v) == len(verts) and len(f) == sum(len(x) - 2 for x in faces)
    g = meshes.mesh_views(v, f, torch.eye(3)[None], 64, fill=0.9, fit=False, name="ball")
    ref = sphere_gbuffer(64, 0.9)
    inner = ref.mask & g.mask
    assert (g.mask ^ ref.mask).sum() < 0.03 * ref.mask.sum()
    cos = (g.normals * ref.normals).sum(1, keepdim=True)[inner]
    assert torch.rad2deg(torch.acos(cos.clamp(-1, 1))).mean() < 1.5
    dz = (g.depth[inner] - ref.depth[inner]).abs()  # a polyhedron: facets sag inside the sphere
    assert dz.mean() < 0.01 and dz.max() < 0.08
    assert (g.depth[~g.mask] == BACKGROUND).all()
    with pytest.raises(PsctlError, match="missing.obj: cannot read mesh"):
        meshes.load_obj(tmp_path / "missing.obj")


@pytest.mark.parametrize("text,needle", [
    ("v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", "line 2: bad vertex"),  # two coordinates
    ("v 0 0 0\nv 1 0 0 1 2\nv 0 1\nf 1 2 3\n", "line 3: bad vertex"),  # 9 numbers in all: not 3 vertices
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999999\n", "line 4: bad face"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", "line 4: bad face"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\nf 1 2 3 1\n", "line 4: bad face"),  # 6 indices in all
    ("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", "NaN or infinite"),
    ("v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n", "zero size"),
    ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "no surface"),  # a review's fuzzing: empty views, exit 0
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no vertices or no faces"),
])
def test_bad_meshes_are_one_error(tmp_path, text, needle):
    from psctl.synth import meshes

    (tmp_path / "m.obj").write_text(text)
    with pytest.raises(PsctlError, match=needle):
        meshes.load_obj(tmp_path / "m.obj")


def test_blobby_shapes_are_valid():
    g = blobby_gbuffers(3, 48, gen(11))
    assert g.names == ["blobby"] * 3
    frac = g.mask.float().mean((1, 2, 3))
    assert ((frac > 0.05) & (frac < 0.9)).all()
    norms = g.normals.norm(dim=1, keepdim=True)
    assert torch.allclose(norms[g.mask], torch.ones(1), atol=1e-4) and (norms[~g.mask] == 0).all()
    assert (g.normals[:, 2:3][g.mask] > 0).all()
    again = blobby_gbuffers(3, 48, gen(11))
    assert torch.equal(g.normals, again.normals) and torch.equal(g.mask, again.mask)


# --- the training stream ----------------------------------------------------------------------

SMALL = {"batch_size": 4, "n_images": 6, "size": 48, "crop": 16, "pool": 3, "reuse": 4, "refresh_chunk": 1,
         "shapes": {"blobby": 1.0}, "blend": 0.5, "texture": 0.5}


def test_stream_batches_are_well_formed_and_seeded():
    from psctl.synth.stream import SynthStream

    a = SynthStream(SMALL, seed=5)
    b1, b2 = a.next_batch(), a.next_batch()
    assert b1["images"].shape == (4, 6, 3, 16, 16) and b1["lights"].shape == (4, 6, 3)
    assert b1["intensities"].shape == (4, 6) and (b1["intensities"] == 1).all()
    assert b1["normals"].shape == (4, 3, 16, 16) and b1["masks"].shape == (4, 1, 16, 16)
    m = b1["masks"].bool()
    assert set(b1["masks"].unique().tolist()) <= {0.0, 1.0} and m.any()
    assert torch.allclose(b1["normals"].norm(dim=1, keepdim=True)[m], torch.ones(1), atol=1e-4)
    assert (b1["normals"].norm(dim=1, keepdim=True)[~m] == 0).all()
    assert (b1["images"] * (1 - b1["masks"][:, None]) == 0).all()
    assert torch.isfinite(b1["images"]).all() and b1["images"].max() <= 1.0 + 0.025
    assert torch.allclose(b1["lights"].norm(dim=-1), torch.ones(4, 6), atol=1e-5) and (b1["lights"][..., 2] >= 0).all()
    b = SynthStream(SMALL, seed=5)
    c1, c2 = b.next_batch(), b.next_batch()  # the pool refreshes between them (reuse 4)
    for x, y in ((b1, c1), (b2, c2)):
        for k in ("images", "lights", "intensities", "normals", "masks"):
            assert torch.equal(x[k], y[k]), k
    other = SynthStream(SMALL, seed=6).next_batch()
    assert not torch.equal(other["images"], b1["images"])
    r = SynthStream(SMALL, seed=1, intensities="random", lights="diligent", crop=None, size=24).next_batch()
    assert r["images"].shape[-2:] == (24, 24)
    assert r["intensities"].min() >= 0.2 and r["intensities"].max() <= 2.0 and r["intensities"].std() > 0
    with pytest.raises(PsctlError, match="unknown synth stream option"):
        SynthStream(SMALL, colour=True)


def test_stream_resumes_exactly_from_its_state(tmp_path):
    from psctl.synth.stream import SynthStream

    cfg = {**SMALL, "pool": 5, "reuse": 2, "refresh_chunk": 2}  # the pool turns over while we watch
    a = SynthStream(cfg, seed=3)
    for _ in range(3):
        a.next_batch()
    torch.save(a.state_dict(), tmp_path / "stream.pt")
    expect = [a.next_batch() for _ in range(3)]
    b = SynthStream(cfg, seed=99)  # a different start: everything comes from the state
    b.load_state_dict(torch.load(tmp_path / "stream.pt", weights_only=True))
    for x in expect:
        y = b.next_batch()
        for k in ("images", "lights", "normals", "masks"):
            assert torch.equal(x[k], y[k]), k
    with pytest.raises(PsctlError, match="pool"):
        SynthStream({**cfg, "pool": 4}).load_state_dict(a.state_dict())


def test_stream_crops_rotate_normals_with_the_image():
    """A centred full-view crop of a sphere is the same sphere whatever the rotation and mirror;
    a wrong sign in the normal rotation would show as a mismatch."""
    from types import SimpleNamespace

    from psctl.synth.stream import make_config, sample_crops

    sp = sphere_gbuffer(64)
    pool = SimpleNamespace(data=torch.cat([sp.normals, sp.mask.float()], 1).flatten(2).transpose(1, 2),
                           horizon=torch.zeros(1, 64 * 64, 4, dtype=torch.float16),
                           cum=sp.mask.flatten(1).float().cumsum(1), size=64, names=["sphere"], device=torch.device("cpu"))
    cfg = make_config(size=64, crop=64, scale=(64, 64))
    crops = sample_crops(pool, 8, cfg, gen(3))
    m = crops["mask"].bool() & sp.mask.reshape(1, 1, -1)
    ref = sp.normals.reshape(1, 3, -1).expand(8, -1, -1)
    ang = torch.rad2deg(torch.acos((crops["normals"] * ref).sum(1, keepdim=True).clamp(-1, 1)))
    inner = m & (ref[:, :2].norm(dim=1, keepdim=True) < 0.8)  # at the rim resampling blurs steep normals
    assert ang[inner].max() < 0.5 and ang[m].mean() < 0.5
    # lights mapped to the source frame see the same n.l there
    l_out = L.sample_lights((8, 5), gen(4))
    l_src = torch.cat([torch.einsum("bij,bnj->bni", crops["to_src"], l_out[..., :2]), l_out[..., 2:]], -1)
    to_src2 = crops["to_src"]
    x = ref[:, :2]
    n_src = torch.cat([torch.einsum("bij,bjp->bip", to_src2, x), ref[:, 2:]], 1)  # source normal at each pixel
    nl_out = torch.einsum("bcp,bnc->bnp", ref, l_out)
    nl_src = torch.einsum("bcp,bnc->bnp", n_src, l_src)
    assert torch.allclose(nl_out, nl_src, atol=1e-5)


def test_stream_never_uses_test_shapes(tmp_path, monkeypatch):
    from psctl.synth import meshes
    from psctl.synth.stream import SynthStream

    verts, faces = uv_sphere(8, 16)
    for name in ("bunny", "dragon", "armadillo", "lucy"):
        write_obj(tmp_path / f"{name}.obj", verts * [1.0, 1.6, 0.8], faces)
    cfg = {**SMALL, "shapes": {"blobby": 1.0, "mesh": 3.0}, "mesh_dir": str(tmp_path), "pool": 6, "reuse": 2}
    s = SynthStream(cfg, seed=0)
    seen = set(s.pool.names)
    for _ in range(4):
        seen |= set(s.next_batch()["shapes"])
        seen |= set(s.pool.names)
    assert "lucy" in seen and seen <= {"blobby", "lucy"}
    for bad in (["bunny"], ["lucy", "dragon"], [str(tmp_path / "armadillo.obj")], ["sphere"]):
        with pytest.raises(PsctlError, match="test shape"):
            SynthStream({**cfg, "meshes": bad})
    # a view cache made from a test shape is refused too
    views = meshes.mesh_views(*meshes.load_obj(tmp_path / "bunny.obj"), torch.eye(3)[None], 48, name="bunny")
    meshes.save_views(tmp_path / "cache.npz", views)
    (tmp_path / "empty").mkdir()
    with pytest.raises(PsctlError, match="test shape"):
        SynthStream({**cfg, "mesh_dir": str(tmp_path / "empty"), "mesh_cache": str(tmp_path / "cache.npz")})
    # without the default meshes the stream falls back to procedural shapes (or fails when asked to)
    monkeypatch.setenv("PSCTL_MESHES", str(tmp_path / "empty"))
    default = {k: v for k, v in cfg.items() if k != "mesh_dir"}
    s = SynthStream(default)
    assert set(s.pool.names) == {"blobby"} and s.notes
    from psctl.synth.stream import SynthDataset  # each DataLoader worker's stream too (it refused the
    assert set(next(iter(SynthDataset(default)))["shapes"]) == {"blobby"}  # defaults it had filled in)
    with pytest.raises(PsctlError, match="no training mesh"):
        SynthStream({**default, "require_meshes": True})
    with pytest.raises(PsctlError, match="no geometry source left: shapes gives only mesh"):
        SynthStream({**default, "shapes": {"mesh": 1.0}})
    # ones a recipe names must be there (an audit: a named folder, cache or mesh was skipped with a note)
    with pytest.raises(PsctlError, match=r"none: not found \(synth stream option 'mesh_dir' names this folder\)"):
        SynthStream({**cfg, "mesh_dir": str(tmp_path / "none")})
    with pytest.raises(PsctlError, match=r"nope.npz: not found \(synth stream option 'mesh_cache' names this file\)"):
        SynthStream({**default, "mesh_cache": str(tmp_path / "nope.npz")})
    with pytest.raises(PsctlError, match=r"teapot.obj: mesh 'teapot' not found"):
        SynthStream({**cfg, "meshes": ["teapot"]})
    with pytest.raises(PsctlError, match="'meshes' is empty but shapes gives mesh a positive weight"):
        SynthStream({**cfg, "meshes": []})
    assert "lucy" in SynthStream({**cfg, "meshes": "lucy", "pool": 16}).pool.names  # a name alone: a list of one


def test_stream_runs_without_openimageio():
    """The GPU machine has torch but no OpenImageIO: the training path must never import it."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['OpenImageIO'] = None\n"
            "import torch; torch.set_num_threads(1)\n"
            "from psctl.synth.stream import SynthStream\n"
            f"b = SynthStream({SMALL!r}, seed=0).next_batch()\n"
            "assert b['images'].shape[0] == 4 and 'OpenImageIO' in sys.modules and sys.modules['OpenImageIO'] is None\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_stream_uses_a_view_cache(tmp_path):
    from psctl.synth import meshes
    from psctl.synth.stream import SynthStream

    verts, faces = uv_sphere(8, 16)
    obj = write_obj(tmp_path / "lucy.obj", verts * [1.0, 1.8, 0.7], faces)
    views = meshes.mesh_views(*meshes.load_obj(obj), torch.eye(3)[None].repeat(2, 1, 1), 32, name="lucy")
    meshes.save_views(tmp_path / "lucy.npz", views)
    back = meshes.load_views(tmp_path / "lucy.npz")
    assert back.names == ["lucy", "lucy"] and torch.equal(back.mask, views.mask)
    assert (back.normals - views.normals).abs().max() < 2e-3
    cfg = {**SMALL, "shapes": {"mesh": 1.0}, "mesh_dir": str(tmp_path / "none"), "mesh_cache": str(tmp_path / "lucy.npz")}
    batch = SynthStream(cfg, seed=0).next_batch()
    assert set(batch["shapes"]) == {"lucy"} and batch["masks"].sum() > 0


# --- the folder writer ------------------------------------------------------------------------


def test_written_folders_round_trip_through_the_reader(tmp_path):
    from psctl.eval import run_benchmark
    from psctl.io.capture import find_objects, load_ground_truth, load_images, load_mask, open_capture
    from psctl.synth.write import exposure_scale, preset_objects, render_object, write_preset

    out = tmp_path / "set"
    rep = write_preset(out, "blobby", seed=2, size=32, n_lights=8, k=2, preview=True)
    assert rep["objects"] == ["blobby_01", "blobby_02"] and Path(rep["preview"]).is_file()
    # the contact sheet says what its columns are and which object each row is
    from psctl.io.images import read_image
    from tests.test_io import _text_at

    sheet = read_image(rep["preview"])[0]
    assert _text_at(sheet, "6 IMAGES, LIGHT LEFT TO RIGHT", 2) == [(2, 2)]  # text 14 px tall (scale 2)
    # a 20 px header, then each row: its 24 px name band (the name 2 px down, room for its tails), 32 px
    # of tiles and a 2 px gap
    assert [y for y, _ in _text_at(sheet, "blobby_01", 2)] == [22] and [y for y, _ in _text_at(sheet, "blobby_02", 2)] == [22 + 56 + 2]
    assert [p.name for p in find_objects(out)] == rep["objects"]
    objs = preset_objects("blobby", seed=2, size=32, n_lights=8, k=2)
    for folder, obj in zip(find_objects(out), objs):
        cap = open_capture(folder)
        assert cap.n_images == 8 and cap.bits == 16 and (cap.height, cap.width) == (32, 32)
        assert np.allclose(cap.lights, obj.lights.numpy(), atol=1e-5)
        mask = load_mask(cap)
        assert np.array_equal(mask, obj.view.mask[0, 0].numpy())
        gt = load_ground_truth(cap)
        assert np.allclose(gt[mask], obj.view.normals[0].permute(1, 2, 0).numpy()[mask], atol=1e-6)
        imgs = load_images(cap)
        expect = render_object(obj)
        expect = (expect * exposure_scale(expect, obj.view.mask[0, 0])).clamp(0, 1) * obj.view.mask[0]
        assert np.abs(imgs - expect.permute(0, 2, 3, 1).numpy()).max() < 1.5 / 65535
        assert json.loads((folder / "synth.json").read_text())["shape"] == "blobby"
    res = run_benchmark("folder", root=out, method="l2")
    assert [o["name"] for o in res["objects"]] == rep["objects"] and np.isfinite(res["mean_mae"])
    # writing again replaces the folders in place, leaving no temporary folder behind, and nothing
    # of the earlier set that this one does not have (its second object, its contact sheet)
    (tmp_path / "other" / "x").mkdir(parents=True)
    (tmp_path / "other" / "x" / "synth.json").write_text("{}")
    (out / "linked").symlink_to(tmp_path / "other" / "x")  # a link to someone's folder: never removed
    (tmp_path / "other" / "x" / "psctl").mkdir()  # in a linked folder: only the link goes, so no refusal
    (out / "blobby_02" / "psctl").mkdir()  # a psctl normals run's outputs: the rerun would delete them
    (out / "blobby_02" / "psctl" / "normal.png").write_bytes(b"x")
    with pytest.raises(PsctlError, match=r"blobby_02: holds psctl/, which psctl synth did not write"):
        write_preset(out, "blobby", seed=2, size=32, n_lights=8, k=1)
    shutil.rmtree(out / "blobby_02" / "psctl")
    again = write_preset(out, "blobby", seed=2, size=32, n_lights=8, k=1)
    assert sorted(p.name for p in out.iterdir()) == ["blobby_01", "linked", "objects.txt"]
    assert again["removed"] == ["blobby_02", "preview.png"] and (tmp_path / "other" / "x" / "synth.json").is_file()
    assert again["notes"] == []
    # an earlier file that cannot be deleted (chattr +i) left the working folder with no word (a
    # QA helper); rmtree here deletes nothing, as there
    import psctl.synth.write as W

    real = shutil.rmtree
    W.shutil.rmtree = lambda path, ignore_errors=False: None
    try:
        stuck = write_preset(out, "blobby", seed=2, size=32, n_lights=8, k=1)
    finally:
        W.shutil.rmtree = real
    hidden = [p for p in out.iterdir() if p.name.startswith(".psctl-synth.")]
    assert len(hidden) == 1 and stuck["notes"] == [f"outputs: {hidden[0]} could not be removed (it holds the earlier "
                                                   "set's files that could not be deleted): the new set is in place; "
                                                   "remove that folder by hand"]
    real(hidden[0])
    with pytest.raises(PsctlError, match="unknown preset"):
        write_preset(out, "teapot")


@pytest.mark.parametrize("kwargs, msg", [
    ({"seed": 2**64 - 1}, "--seed must be from 0 to 2"),
    ({"seed": -1}, "--seed must be from 0 to 2"),
    ({"size": 30000}, "needs about .* GiB of memory"),
    ({"ir_albedo": 0.5}, "give --interreflections N too"),
])
def test_synth_refuses_before_writing_anything(tmp_path, kwargs, msg):
    from psctl.synth.write import write_preset

    with pytest.raises(PsctlError, match=msg):
        write_preset(tmp_path / "o", "blobby", **{"size": 16, "n_lights": 4, "k": 1, **kwargs})
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("stop", [KeyboardInterrupt, OSError])
def test_an_interrupted_synth_run_leaves_the_earlier_set_as_it_was(tmp_path, monkeypatch, stop):
    import psctl.synth.write as W
    from psctl.io.capture import find_objects

    out = tmp_path / "o"
    W.write_preset(out, "blobby", seed=0, size=24, n_lights=6, k=2)
    before = {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    real, calls = W.write_object, []

    def second_fails(folder, obj, images):
        calls.append(obj.name)
        if len(calls) == 2:
            raise stop("stopped")
        real(folder, obj, images)

    monkeypatch.setattr(W, "write_object", second_fails)
    with pytest.raises(stop):
        W.write_preset(out, "blobby", seed=5, size=24, n_lights=6, k=3)
    after = {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    assert calls == ["blobby_01", "blobby_02"] and after == before  # nothing new, nothing hidden left
    assert sorted(p.name for p in out.iterdir()) == ["blobby_01", "blobby_02", "objects.txt"]
    calls.clear()  # a new folder (and its new parents) stopped half way: none of them is left
    with pytest.raises(stop):
        W.write_preset(tmp_path / "new" / "a" / "set", "blobby", seed=5, size=24, n_lights=6, k=3)
    assert not (tmp_path / "new").exists()
    # a failure while the new set moves in (disk full) puts the earlier one back
    monkeypatch.setattr(W, "write_object", real)
    real_replace, moves = W.os.replace, []

    def full_disk(src, dst):  # the new blobby_02 cannot move in: blobby_01 and objects.txt had moved
        if ".psctl-synth." in str(src) and ".earlier" not in str(src) and str(dst) == str(out / "blobby_02"):
            moves.append(dst)
            raise OSError(28, "No space left on device")
        real_replace(src, dst)

    monkeypatch.setattr(W.os, "replace", full_disk)
    with pytest.raises(OSError):
        W.write_preset(out, "blobby", seed=5, size=24, n_lights=6, k=3)
    monkeypatch.setattr(W.os, "replace", real_replace)
    after = {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    assert moves == [out / "blobby_02"] and after == before
    # putting the earlier set back fails too (a file held open on Windows): its files are kept in the
    # staging folder's backup, which the error names, never deleted with the staging folder
    moves.clear()

    def no_way_back(src, dst):
        if ".earlier" in str(src):
            raise PermissionError(13, "Permission denied")
        full_disk(src, dst)

    monkeypatch.setattr(W.os, "replace", no_way_back)
    with pytest.raises(PsctlError, match="so did putting the earlier one back") as e:
        W.write_preset(out, "blobby", seed=5, size=24, n_lights=6, k=3)
    monkeypatch.setattr(W.os, "replace", real_replace)
    kept = Path(e.value.path)
    assert kept.name == ".earlier" and kept.parent.parent == out
    # (each earlier file is set aside before its new one moves in: all three were)
    assert sorted(p.name for p in kept.iterdir()) == ["blobby_01", "blobby_02", "objects.txt"]
    assert {p.relative_to(kept): p.read_bytes() for p in sorted(kept.rglob("*")) if p.is_file()} == before
    for p in kept.iterdir():  # the user moves them back, as the message says
        shutil.rmtree(out / p.name, ignore_errors=True) if (out / p.name).is_dir() else None
        real_replace(p, out / p.name)
    shutil.rmtree(kept.parent)
    after = {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    assert after == before
    # object folders of psctl synth without objects.txt: part of a set, not a benchmark
    (out / "objects.txt").unlink()
    with pytest.raises(PsctlError, match="holds psctl synth objects .* but no objects.txt"):
        find_objects(out)


def test_written_lambertian_sphere_gives_l2_its_normals_back(tmp_path):
    """End to end through files: image orientation, light and normal conventions agree."""
    from psctl.api import run_normals
    from psctl.synth.write import SynthObject, render_object, write_object

    lights = L.sample_lights((20,), gen(8), "diligent")
    obj = SynthObject("ball", sphere_gbuffer(48), M.lambertian(torch.tensor([[0.7, 0.5, 0.3]])), lights,
                      torch.linspace(0.5, 1.5, 20), meta={"shape": "sphere"})
    images = render_object(obj)
    (tmp_path / "ball").mkdir()
    write_object(tmp_path / "ball", obj, (images / images.max()).clamp(0, 1))
    r = run_normals(tmp_path / "ball", method="l2", write=False)
    # the same solve in memory: only attached shadows at the rim keep L2 from 0 degrees
    from psctl.classic import l2_normals
    from psctl.metrics import angular_error

    mask = obj.view.mask[0, 0].numpy()
    mem = (images / obj.intensities[:, None, None, None]).permute(0, 2, 3, 1).numpy()
    gt = obj.view.normals[0].permute(1, 2, 0).numpy()
    mae = float(angular_error(l2_normals(mem, lights.numpy(), mask).normals, gt, mask).mean())
    assert r["n_images"] == 20 and r["mae"] < 3.0 and abs(r["mae"] - mae) < 0.05


def test_cli_synth(tmp_path):
    from tests.test_cli import cli  # in this process: a subprocess costs seconds of imports per call

    proc = cli("synth", tmp_path / "o", "--preset", "blobby",
               "--size", "24", "--lights", "6", "--materials", "1", "--json")
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert r["objects"] == ["blobby_01"] and (tmp_path / "o" / "objects.txt").is_file()
    proc = cli("synth", tmp_path / "o", "--preset", "nope")
    assert proc.returncode == 2 and "unknown preset" in proc.stderr and "Traceback" not in proc.stderr
    # --light-dist: DiLiGenT-like lights (zenith <= 45 degrees), recorded in synth.json
    proc = cli("synth", tmp_path / "d", "--preset", "blobby",
               "--size", "24", "--lights", "40", "--materials", "1", "--light-dist", "diligent", "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["light_dist"] == "diligent"
    z = np.loadtxt(tmp_path / "d" / "blobby_01" / "light_directions.txt")[:, 2]
    assert z.min() >= np.cos(np.radians(45)) - 1e-6 and z.max() > 0.97
    assert json.loads((tmp_path / "d" / "blobby_01" / "synth.json").read_text())["light_dist"] == "diligent"
    proc = cli("synth", tmp_path / "e", "--preset", "blobby",
               "--light-dist", "ring")
    assert proc.returncode == 2 and "unknown light distribution 'ring'" in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "e").exists()
    # interreflections: recorded in synth.json; a bad albedo is a one-line error and writes nothing
    proc = cli("synth", tmp_path / "i", "--preset", "blobby",
               "--size", "24", "--lights", "6", "--materials", "1", "--interreflections", "2",
               "--ir-albedo", "0.5", "--json")
    assert proc.returncode == 0, proc.stderr
    meta = json.loads((tmp_path / "i" / "blobby_01" / "synth.json").read_text())
    assert meta["interreflections"] == 2 and meta["ir_albedo"] == 0.5
    proc = cli("synth", tmp_path / "j", "--preset", "blobby",
               "--interreflections", "1", "--ir-albedo", "1.5")
    assert proc.returncode == 2 and "--ir-albedo must be in [0, 1)" in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "j").exists()
    from psctl.synth.write import write_preset  # an audit: 10^8 bounces ran for hours without a word

    with pytest.raises(PsctlError, match=r"--interreflections must be 0 to 100 \(got 100000000\)"):
        write_preset(tmp_path / "k", "blobby", size=16, n_lights=4, interreflections=10**8)
    assert not (tmp_path / "k").exists()


def test_syntest_preset_with_shared_meshes(tmp_path):
    from psctl.synth import meshes

    if not (meshes.mesh_dir() / "bunny.obj").is_file():
        pytest.skip(f"needs {meshes.mesh_dir()} (the project's shared data; absent in a fresh clone)")
    from psctl.synth.write import preset_objects

    objs = preset_objects("syntest", size=32, n_lights=4, k=1)
    assert [o.meta["shape"] for o in objs] == ["sphere", "bunny", "dragon", "armadillo"]
    assert all(o.view.mask.float().mean() > 0.1 for o in objs)


def test_stream_windows_sit_on_the_object_and_repeat_with_the_seed():
    from psctl.synth.stream import SynthStream

    cfg = {"batch_size": 6, "n_images": 4, "size": 32, "crop": 32, "pool": 4, "shapes": {"blobby": 1.0},
           "windows": 12, "seed": 5}
    a, b = SynthStream(cfg).next_batch(), SynthStream(cfg).next_batch()
    assert torch.equal(a["windows"], b["windows"]) and a["windows"].shape == (6, 2)
    for k, (r, c) in enumerate(a["windows"].tolist()):
        assert 0 <= r <= 20 and 0 <= c <= 20
        assert a["masks"][k, 0, r:r + 12, c:c + 12].sum() > 0  # the window holds object pixels
    plain = SynthStream({**cfg, "windows": None}).next_batch()
    assert "windows" not in plain and torch.equal(plain["images"], a["images"])  # same draws otherwise
    with pytest.raises(PsctlError, match="windows"):
        SynthStream({**cfg, "windows": 40})


def test_written_object_folders_follow_the_umask(tmp_path):
    """Object folders get the mode mkdir would give, not mkdtemp's 0700 (others could not read them)."""
    import os

    from psctl.synth.write import write_preset

    old = os.umask(0o022)
    try:
        write_preset(tmp_path / "set", "blobby", seed=1, size=16, n_lights=6, k=1)
    finally:
        os.umask(old)
    assert (tmp_path / "set" / "blobby_01").stat().st_mode & 0o777 == 0o755


def test_scale_law_log_draws_as_many_sides_per_octave_and_stays_in_range():
    """``scale_law: log`` draws the rescaled side log-uniformly: about half the sides of
    [32, 320] fall below its geometric mean (101), where the uniform law puts 24 %."""
    from psctl.synth.stream import rescaled_sides
    gen = torch.Generator().manual_seed(0)
    log = rescaled_sides(32.0, 320.0, "log", 20000, gen)
    uni = rescaled_sides(32.0, 320.0, "uniform", 20000, gen)
    assert float(log.min()) >= 32.0 and float(log.max()) <= 320.0
    assert abs(float((log < (32.0 * 320.0) ** 0.5).float().mean()) - 0.5) < 0.02
    assert abs(float((log < 64.0).float().mean()) - math.log(2) / math.log(10)) < 0.02
    assert abs(float((uni < (32.0 * 320.0) ** 0.5).float().mean()) - (101.19 - 32) / 288) < 0.02


def test_scale_law_is_checked():
    from psctl.synth.stream import make_config
    with pytest.raises(PsctlError, match="synth stream option 'scale_law': must be one of uniform, log"):
        make_config({"scale_law": "exp"})
    assert make_config({"scale": [32, 320], "scale_law": "log"})["scale_law"] == "log"


def test_scale_law_log_shows_more_of_the_background_in_the_crops():
    """Smaller rescaled views leave more background in a window: over [16, 160] the log law
    (median side 51) gives crops with fewer object pixels than the uniform one (median 88)."""
    from psctl.synth.stream import SynthStream

    cfg = {**SMALL, "batch_size": 64, "scale": [16, 160]}
    cover = {law: float(SynthStream({**cfg, "scale_law": law}, seed=3).next_batch()["masks"].float().mean())
             for law in ("uniform", "log")}
    assert cover["log"] < cover["uniform"] - 0.03, cover


def ggx_by_hand(kd, spec, alpha, i, o, ior=None, metal=False):
    """Walter et al.'s GGX with separable Smith G, term by term (normal = +z): dielectric with
    exact Fresnel of ``ior`` times ``spec``, or metallic with Schlick's F0 = ``spec``."""
    h = [a + b for a, b in zip(i, o)]
    hn = math.sqrt(sum(x * x for x in h))
    h = [x / hn for x in h]
    nh, lh, nl, nv = h[2], sum(a * b for a, b in zip(i, h)), i[2], o[2]
    a2 = alpha * alpha
    d = a2 / (math.pi * (nh * nh * (a2 - 1) + 1) ** 2)

    def g1(c):
        return 2 * c / (c + math.sqrt(a2 + (1 - a2) * c * c))

    if metal:
        fres = [f0 + (1 - f0) * (1 - lh) ** 5 for f0 in spec]
    else:
        g = math.sqrt(ior * ior - 1 + lh * lh)
        f = 0.5 * ((g - lh) / (g + lh)) ** 2 * (1 + ((lh * (g + lh) - 1) / (lh * (g - lh) + 1)) ** 2)
        fres = [f * s for s in spec]
    return [kd[ch] / math.pi + fres[ch] * d * g1(nl) * g1(nv) / (4 * nl * nv) for ch in range(3)]


@pytest.mark.parametrize("metal", [False, True])
def test_ggx_matches_hand_computation(metal):
    kd, spec, alpha = [0.2, 0.3, 0.4], [0.9, 0.6, 0.3], 0.25
    mat = M.ggx(torch.tensor([kd]), torch.tensor([spec]), torch.tensor([alpha]),
                ior=None if metal else torch.tensor([1.6]), metal=torch.tensor([metal]))
    for theta_i, phi_i, theta_o in ((30.0, 0.0, 20.0), (10.0, 40.0, 10.0), (60.0, 150.0, 45.0), (75.0, 180.0, 70.0)):
        i = (math.sin(math.radians(theta_i)) * math.cos(math.radians(phi_i)),
             math.sin(math.radians(theta_i)) * math.sin(math.radians(phi_i)), math.cos(math.radians(theta_i)))
        o = (-math.sin(math.radians(theta_o)), 0.0, math.cos(math.radians(theta_o)))
        expect = ggx_by_hand(kd, spec, alpha, i, o, ior=1.6, metal=metal)
        got = M.brdf(mat, torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([i]), torch.tensor([o]))[0]
        assert got.tolist() == pytest.approx(expect, rel=1e-4)


def test_shade_is_the_reference_brdf_times_the_cosine():
    """The renderer's fast path (R.shade) against M.brdf for each model, with intensities:
    radiance = e * f(n, l, v) * max(n.l, 0), v = +z."""
    b, p, n_lights = 5, 300, 4
    g = gen(7)
    normals = random_dirs(b * p, g).reshape(b, p, 3)
    normals[..., 2] = normals[..., 2].abs() + 0.05  # facing the camera
    normals = torch.nn.functional.normalize(normals, dim=-1)
    lights = L.sample_lights((b, n_lights), g, "hemisphere", 70.0)
    e = 0.5 + torch.rand(b, n_lights, generator=g)
    view = torch.tensor([0.0, 0.0, 1.0]).expand(b, n_lights, p, 3)
    nn_ = normals[:, None].expand(b, n_lights, p, 3)
    ll = lights[:, :, None].expand(b, n_lights, p, 3)

    def reference(mat):
        f = M.brdf(mat, nn_, ll, view)  # [B, N, P, 3]
        cos = (nn_ * ll).sum(-1).clamp_min(0)
        return (f * (cos * e[..., None])[..., None]).permute(0, 1, 3, 2)  # [B, N, 3, P]

    models = all_models(b)
    for mat in models:
        got = R.shade(normals.permute(0, 2, 1), lights, mat, intensities=e)
        assert torch.allclose(got, reference(mat), rtol=5e-4, atol=1e-6)  # float32 over sharp lobes


def test_sampled_lights_cover_the_whole_hemisphere_evenly():
    d = L.sample_lights((20000,), gen(3), "hemisphere")
    assert torch.allclose(d.norm(dim=-1), torch.ones(20000), atol=1e-5) and (d[:, 2] >= 0).all()
    assert abs(float(d[:, 0].mean())) < 0.02 and abs(float(d[:, 1].mean())) < 0.02
    for axis in (0, 1):
        assert 0.48 < float((d[:, axis] < 0).float().mean()) < 0.52
    assert abs(float(d[:, 2].mean()) - 0.5) < 0.02  # uniform by area: z uniform in [0, 1]


def test_quantize_rounds_to_the_nearest_code():
    x = torch.tensor([0.6, 0.4, 1.4, -2.0, 65534.6, 7e4]) / 65535
    assert (R.quantize(x) * 65535).round().tolist() == [1.0, 0.0, 1.0, 0.0, 65535.0, 65535.0]
    assert (R.quantize(torch.tensor([0.5 / 255 + 1e-4, 254.4 / 255]), bits=8) * 255).round().tolist() == [1.0, 254.0]


def test_render_object_scales_each_image_by_its_intensity_blends_included():
    """psctl synth's images follow light_intensities.txt for both materials of a blend."""
    from psctl.synth.write import SynthObject, render_object

    view = sphere_gbuffer(24)
    g = gen(5)
    lights = L.sample_lights((6,), g, "diligent")
    models = all_models(1)
    w = torch.rand(1, 1, 24, 24, generator=g)
    e = torch.tensor([0.3, 1.0, 1.7, 0.6, 2.0, 1.2])
    obj = SynthObject("blend", view, models[0], lights, e, mat_b=models[2], weights=w)
    unit = SynthObject("blend", view, models[0], lights, torch.ones(6), mat_b=models[2], weights=w)
    got, ref = render_object(obj, shadows=False), render_object(unit, shadows=False)
    assert ref.abs().sum() > 0
    assert torch.allclose(got, ref * e[:, None, None, None], rtol=1e-5, atol=1e-7)


def test_object_windows_hold_a_lone_object_pixel():
    from psctl.synth.stream import object_windows

    side, w = 32, 8
    mask = torch.zeros(3, side * side)
    for k, (r, c) in enumerate([(3, 25), (28, 2), (16, 16)]):
        mask[k, r * side + c] = 1
    win = object_windows(mask, side, w, gen())
    for k, (r, c) in enumerate([(3, 25), (28, 2), (16, 16)]):
        top, left = win[k].tolist()
        assert top <= r < top + w and left <= c < left + w


def test_random_rotations_are_rotations():
    from psctl.synth.shapes import random_rotations

    R = random_rotations((200,), gen(1))
    eye = torch.eye(3).expand(200, 3, 3)
    assert torch.allclose(R @ R.transpose(-1, -2), eye, atol=1e-5)
    assert torch.allclose(torch.linalg.det(R), torch.ones(200), atol=1e-5)


def test_blobby_normals_follow_the_depth():
    from psctl.synth.shapes import blobby_gbuffers

    gb = blobby_gbuffers(2, 48, gen(11))
    px = 2 / 48
    d = gb.depth[:, 0].double()
    m = gb.mask[:, 0]
    inner = m[:, 1:-1, 1:-1] & m[:, 2:, 1:-1] & m[:, :-2, 1:-1] & m[:, 1:-1, 2:] & m[:, 1:-1, :-2]
    dzdx = (d[:, 1:-1, 2:] - d[:, 1:-1, :-2]) / (2 * px)
    dzdy = (d[:, :-2, 1:-1] - d[:, 2:, 1:-1]) / (2 * px)  # y up: row 0 is the top
    n_fd = torch.nn.functional.normalize(torch.stack([-dzdx, -dzdy, torch.ones_like(dzdx)], 1), dim=1)
    n = gb.normals[:, :, 1:-1, 1:-1].double()
    ang = torch.rad2deg(torch.acos((n * n_fd).sum(1).clamp(-1, 1)))[inner]
    assert ang.median() < 10, float(ang.median())


def test_exposure_scale_maps_the_objects_quantile_to_the_level():
    from psctl.synth.write import EXPOSURE_LEVEL, EXPOSURE_QUANTILE, exposure_scale

    img = torch.full((2, 3, 10, 10), 5.0)  # bright background: must not count
    mask = torch.zeros(10, 10, dtype=torch.bool)
    mask[:, :5] = True
    vals = torch.linspace(0.0, 0.5, 2 * 3 * 50).reshape(2, 3, 10, 5)
    img[:, :, :, :5] = vals
    q = float(torch.quantile(vals.reshape(-1), EXPOSURE_QUANTILE))
    assert exposure_scale(img, mask) == pytest.approx(EXPOSURE_LEVEL / q, rel=1e-6)
    assert EXPOSURE_LEVEL == 0.9


def _disk_pool(size=64, radius=None, centre=None):
    yy, xx = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    if radius is None:
        mask = torch.zeros(size, size, dtype=torch.bool)
        mask[centre] = True
    else:
        mask = ((yy - size / 2 + 0.5) ** 2 + (xx - size / 2 + 0.5) ** 2) < radius ** 2
    normals = torch.zeros(3, size, size)
    normals[2] = mask.float()
    data = torch.cat([normals, mask[None].float()], 0).flatten(1).T[None]
    return types.SimpleNamespace(data=data, horizon=torch.zeros(1, size * size, 4, dtype=torch.float16),
                           cum=mask.flatten()[None].float().cumsum(1), size=size, names=["x"],
                           device=torch.device("cpu"))


def test_crop_jitter_is_centred_on_the_drawn_pixel():
    from psctl.synth.stream import make_config, sample_crops

    pool = _disk_pool(64, radius=1.2)  # a 4-pixel object at the centre
    cfg = make_config(size=64, crop=16, scale=(64, 64), rotate=False, flip=False)
    crops = sample_crops(pool, 4000, cfg, gen(2))
    m = crops["mask"].reshape(4000, 16, 16)
    cols = torch.arange(16).float()
    seen = m.sum((1, 2)) > 0
    mean_col = ((m.sum(1) * cols).sum(1) / m.sum((1, 2)).clamp_min(1))[seen].mean()
    mean_row = ((m.sum(2) * cols).sum(1) / m.sum((1, 2)).clamp_min(1))[seen].mean()
    assert abs(float(mean_col) - 7.5) < 0.5 and abs(float(mean_row) - 7.5) < 0.5


def test_rescale_draws_width_and_height_apart():
    from psctl.synth.stream import make_config, sample_crops

    pool = _disk_pool(64, radius=12)
    cfg = make_config(size=64, crop=32, scale=(32, 64), rotate=False, flip=False)
    crops = sample_crops(pool, 400, cfg, gen(3))
    m = crops["mask"].reshape(400, 32, 32)
    inside = (m[:, 0].sum(1) + m[:, -1].sum(1) + m[:, :, 0].sum(1) + m[:, :, -1].sum(1)) == 0  # not cut by the crop
    w = (m.sum(1) > 0).sum(1).float()[inside]
    h = (m.sum(2) > 0).sum(1).float()[inside]
    ratio = w / h
    assert len(ratio) > 50 and (ratio > 1.3).any() and (ratio < 1 / 1.3).any()


def test_random_intensities_are_drawn_per_sample():
    from psctl.synth.stream import SynthStream

    e = SynthStream(SMALL, seed=1, intensities="random").next_batch()["intensities"]
    assert not torch.allclose(e[0], e[1])


def test_ambient_strength_is_drawn_per_sample(monkeypatch):
    from psctl.synth import render as R
    from psctl.synth.stream import SynthStream

    seen = []
    real = R.shade

    def spy(*a, **k):
        seen.append(k.get("ambient"))
        return real(*a, **k)

    monkeypatch.setattr(R, "shade", spy)
    SynthStream({**SMALL, "batch_size": 16, "blend": 0.0}, seed=1, ambient=0.4).next_batch()
    a = seen[0]
    assert a.shape == (16,) and (a >= 0).all() and (a <= 0.4).all() and a.std() > 0.05


def test_stream_resumes_exactly_mid_refresh(tmp_path):
    from psctl.synth.stream import SynthStream

    cfg = {**SMALL, "pool": 5, "reuse": 8, "refresh_chunk": 2}  # 0.5 entries per batch: 1.0 pending at the save
    a = SynthStream(cfg, seed=3)
    for _ in range(2):
        a.next_batch()
    state = a.state_dict()
    assert 0 < state["pool"]["pending"] < 2
    expect = [a.next_batch() for _ in range(4)]
    b = SynthStream(cfg, seed=99)
    b.load_state_dict(state)
    for x in expect:
        assert torch.equal(x["images"], b.next_batch()["images"])


def test_mesh_fit_spans_the_longer_side(tmp_path):
    from psctl.synth import meshes

    v = torch.tensor([[x, y, z] for x in (-2.0, 2.0) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    f = torch.tensor([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    gb = meshes.mesh_views(v, f, torch.eye(3)[None], 64, fill=0.9)
    cols = gb.mask[0, 0].any(0).nonzero()[:, 0]
    assert abs(int(cols.max() - cols.min() + 1) - 0.9 * 64) <= 2


def test_contact_sheet_tiles_stay_small_for_large_renders():
    """--preview at --size 512 would be 3.6k px wide and 12k tall for 24 rows: each tile is shown
    at most SHEET_TILE px (every k-th pixel), under the object's name."""
    from psctl.synth.write import SHEET_IMAGES, SHEET_TILE, _sheet_row, preset_objects

    obj = preset_objects("blobby", seed=0, size=260, n_lights=8, k=1)[0]
    row = _sheet_row(torch.rand(8, 3, 260, 260), obj)
    tile = -(-260 // 3)  # every 3rd pixel: 87 <= SHEET_TILE
    assert tile <= SHEET_TILE and row.shape == (24 + tile, (SHEET_IMAGES + 1) * tile + 2 * SHEET_IMAGES, 3)


def test_contact_sheet_of_small_renders_keeps_its_text_whole(tmp_path):
    """At --size 16 a row of tiles is 124 px, narrower than the header and than long object
    names: the sheet grows to them instead of cutting them."""
    from psctl.io.images import read_image
    from psctl.synth.write import write_preset
    from tests.test_io import _text_at

    rep = write_preset(tmp_path / "s", "blobby", seed=2, size=16, n_lights=8, k=2, preview=True)
    sheet = read_image(rep["preview"])[0]
    assert _text_at(sheet, "6 IMAGES, LIGHT LEFT TO RIGHT | NORMALS", 2) == [(2, 2)]
    assert _text_at(sheet, "blobby_02", 2)  # whole: the y's tail too (helper-162's font note)


def test_synth_refuses_more_objects_than_memory_holds():
    """-k 100000000: every object's geometry is made before the first is rendered; that was an
    out-of-memory kill after hours, not a line."""
    import time

    from psctl.synth.write import preset_objects

    t = time.perf_counter()
    for preset in ("blobby", "dragon-svbrdf"):
        with pytest.raises(PsctlError, match=r"--materials 100000000 at --size 128 needs about [\d,]+ GiB"):
            preset_objects(preset, size=128, n_lights=4, k=100_000_000)
    assert time.perf_counter() - t < 5  # refused before any geometry is made


def test_the_view_renderer_refuses_a_test_shape_in_one_line_with_exit_2(tmp_path):
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "psctl.synth.meshes", "bunny", "--out", str(tmp_path / "v.npz")],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.strip().splitlines() == [
        "error: 'bunny' is a test shape (sphere, bunny, dragon, armadillo): never train on it"]
    assert not (tmp_path / "v.npz").exists()


def test_the_same_seed_writes_the_same_bytes(tmp_path, monkeypatch):
    """psctl synth with one seed twice: every file byte for byte, Normal_gt.mat included (its
    header held the time of writing: a reproducibility audit); the .mat still reads as one."""
    import scipy.io

    from psctl.io.matfile import load_variable
    from psctl.synth.write import write_preset

    import time

    write_preset(tmp_path / "a", "blobby", seed=3, size=24, n_lights=6, k=2)
    monkeypatch.setattr(time, "asctime", lambda *a: "Thu Jan  1 00:00:00 1970")  # as if written at another time
    write_preset(tmp_path / "b", "blobby", seed=3, size=24, n_lights=6, k=2)
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert any(p.name == "Normal_gt.mat" for p in files)
    differ = [p for p in files if (tmp_path / "a" / p).read_bytes() != (tmp_path / "b" / p).read_bytes()]
    assert differ == []
    mat = next(tmp_path.glob("a/*/Normal_gt.mat"))
    n = scipy.io.loadmat(mat)["Normal_gt"]
    assert n.shape == (24, 24, 3) and np.array_equal(load_variable(mat, "Normal_gt"), n)


def test_a_failed_synth_write_is_named_in_the_set_not_in_its_staging_folder(tmp_path, monkeypatch):
    """A full disk while writing: the message names out/OBJECT/FILE, not the hidden staging folder
    that is gone when the user reads it (a QA helper's finding, session 58)."""
    import psctl.synth.write as W

    real = W.write_object

    def full_disk(folder, obj, images):
        if obj.name == "blobby_02":
            raise PsctlError(folder / "Normal_gt.mat", f"cannot write {folder / 'Normal_gt.mat'} (no space left on device)")
        real(folder, obj, images)

    monkeypatch.setattr(W, "write_object", full_disk)
    out = tmp_path / "o"
    with pytest.raises(PsctlError) as e:
        W.write_preset(out, "blobby", seed=0, size=24, n_lights=6, k=2)
    assert e.value.path == str(out / "blobby_02" / "Normal_gt.mat")
    assert ".psctl-synth." not in str(e.value) and str(out / "blobby_02" / "Normal_gt.mat") in e.value.message
    assert not out.exists()


@pytest.mark.parametrize("option, value, message", [
    ("blobby", {"steps": 0}, "blobby': steps must be a whole number, 1 or more"),
    ("blobby", {"foo": 1}, "blobby': unknown foo; choose from primitives"),
    ("blobby", {"primitives": [6, 2]}, r"primitives must be \[lo, hi\], whole numbers with 1 <= lo <= hi <= 9"),
    ("blobby", {"features": -1}, "features must be a whole number, 0 to 1024"),
    ("blobby", {"features": 10**6}, "features must be a whole number, 0 to 1024"),
    ("blobby", {"p_box": 1.5}, "p_box must be a chance"),
    ("blobby", {"detail": [2, 1]}, r"detail must be \[lo, hi\] with 0 <= lo <= hi"),
    ("blobby", 5, "'blobby' must map primitives"),
    ("scale", "ab", r"'scale' must be \[lo, hi\], two whole numbers of pixels"),
    ("scale", [16], r"'scale' must be \[lo, hi\]"),
    ("windows", "x", "'windows' must be a whole number of pixels or null"),
    ("windows", 2.5, "'windows' must be a whole number"),
    ("merl_names", [], "'merl_names' is empty"),
    ("merl_names", [3], "'merl_names' must be a list of names or null"),
    ("meshes", {"lucy": 1}, "'meshes' must be a list of names"),
])
def test_stream_options_are_checked_when_the_config_is_made(option, value, message):
    """An audit of recipes: these ended in a torch or Python error mid-run (scale, windows,
    merl_names [], blobby primitives/features), were read letter by letter (a string), or with
    blobby steps 0 rendered empty shapes that trained on nothing and exited 0."""
    from psctl.synth.stream import make_config

    with pytest.raises(PsctlError, match=message):
        make_config({**SMALL, option: value})
    assert make_config({**SMALL, "blobby": {"steps": 12, "primitives": [1, 9]}})["blobby"]["primitives"] == (1, 9)
    assert make_config({**SMALL, "merl_names": "alum-bronze"})["merl_names"] == ["alum-bronze"]


def test_a_signal_in_synths_clean_up_leaves_no_hidden_folder(tmp_path):
    """SIGTERM as psctl synth removed its staging folder after moving the new set in left the
    earlier set's files in a hidden folder for good (helper-177): the move and the clean-up now
    run with signals held, and the run exits 143 after them."""
    import subprocess
    import sys

    from psctl.synth.write import write_preset

    write_preset(tmp_path / "set", "blobby", size=32, n_lights=16)
    code = f"""
import os, shutil, signal, sys
real = shutil.rmtree
def rmtree(path, *a, **k):
    if ".psctl-synth." in str(path) and os.path.isdir(os.path.join(path, ".earlier")):
        os.kill(os.getpid(), signal.SIGTERM)
    return real(path, *a, **k)
shutil.rmtree = rmtree
from psctl.cli import main
sys.argv = ["psctl", "synth", {str(tmp_path / "set")!r}, "--preset", "blobby", "--size", "32", "--lights", "16",
            "--seed", "1", "-q"]
main()
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 143, r.stderr
    assert not [p.name for p in (tmp_path / "set").iterdir() if p.name.startswith(".psctl-synth")]
    listed = (tmp_path / "set" / "objects.txt").read_text().split()
    assert listed and all((tmp_path / "set" / n / "synth.json").is_file() for n in listed)  # the new set, whole
