"""The array API (estimate_normals, estimate_lights, array_normals, integrate_normals) holds
in-memory inputs to the rules of capture folders: one PsctlError for what a folder would be
refused for, integer pixels scaled as image files are, inputs never written to."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from psctl.api import estimate_lights, estimate_normals
from psctl.errors import PsctlError, PsctlWarning
from tests.conftest import hemisphere_lights, render_lambertian, sphere


@pytest.fixture
def data():
    normals, mask = sphere(32)
    lights = hemisphere_lights(12, seed=3)
    return render_lambertian(normals, mask, lights, 0.7), lights, mask, normals


@pytest.mark.parametrize("change,needle", [
    (lambda i, L, m: (i, np.where(np.arange(12)[:, None] == 2, np.nan, L), m), "lights[2]: NaN"),
    (lambda i, L, m: (i, np.where(np.arange(12)[:, None] == 0, np.inf, L), m), "lights[0]: NaN or infinite"),
    (lambda i, L, m: (i, np.where(np.arange(12)[:, None] == 4, 0.0, L), m), "lights[4]: zero-length"),
    (lambda i, L, m: (i, L[:5], m), "lights must be [12, 3]"),
    (lambda i, L, m: (i, [["a", "b", "c"]] * 12, m), "numeric"),
    (lambda i, L, m: (np.zeros_like(i), L, m), "all images are black"),
    (lambda i, L, m: (i[0], L, m), "look like one [H, W, 3] image"),
    (lambda i, L, m: (i, L, np.where(m, np.nan, 0.0)), "mask contains NaN"),
    (lambda i, L, m: (i, L, np.zeros_like(m)), "mask is empty"),
    (lambda i, L, m: (i.astype(str), L, m), "float, uint8 or uint16"),
    (lambda i, L, m: (i, L * np.array([1, 1, -1]), m), "every light has z <= 0"),  # as light_directions.txt
    (lambda i, L, m: (i, L.astype(complex), m), "real, numeric"),
    (lambda i, L, m: (i[:, :0], L, m[:0]), "N, H, W >= 1"),  # not "all images are black"
    (lambda i, L, m: (i.astype(np.float64) * 1e300, L, m), "beyond float32's range"),  # finite: not "NaN"
])
def test_bad_arrays_are_one_error(data, change, needle):
    import warnings

    images, lights, mask, _ = data
    i, L, m = change(images.copy(), lights.copy(), mask.copy())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's overflow / complex warnings are not the message
        with pytest.raises(PsctlError, match=needle.replace("[", r"\[").replace("]", r"\]")):
            estimate_normals(i, L, m, method="l2")


def test_light_rows_scaled_alike_are_directions(data):
    """Rows all 1e-7 long are directions like any others (they were refused as zero-length, the
    absolute floor being 1e-6; a QA helper's finding); one row 1e-7 long beside unit rows is still
    a zero written with noise."""
    images, lights, mask, _ = data
    ref = estimate_normals(images, lights, mask, method="l2")
    np.testing.assert_allclose(estimate_normals(images, lights * 1e-7, mask, method="l2"), ref, atol=1e-5)
    odd = lights.copy()
    odd[4] *= 1e-7
    with pytest.raises(PsctlError, match=r"lights\[4\]: zero-length"):
        estimate_normals(images, odd, mask, method="l2")


def test_options_are_checked_for_l2_too(data):
    images, lights, mask, _ = data
    with pytest.raises(PsctlError, match="unknown --device 'gpu'"):
        estimate_normals(images, lights, mask, method="l2", device="gpu")
    with pytest.raises(PsctlError, match="views"):
        estimate_normals(images, lights, mask, method="l2", views=3)
    for device in (0, 1):  # 0 passed as "auto", 1 failed on .lower()
        with pytest.raises(PsctlError, match="--device must be a name"):
            estimate_normals(images, lights, mask, method="l2", device=device)
    with pytest.raises(PsctlError, match="refine must be True or False, not 'no'"):
        estimate_normals(images, lights, mask, method="l2", refine="no")
    with pytest.raises(PsctlError, match="--light-distance must be a number"):
        estimate_normals(images, lights, mask, method="l2", light_distance=True)


@pytest.mark.parametrize("call,needle", [
    ("run_normals(None)", "path must be a path"),
    ("run_normals(b'folder')", "path must be a path"),
    ("run_normals(FOLDER, method='l2', out=5)", "out must be a path"),
    ("run_normals(FOLDER, weights=123)", "weights must be a path"),
    ("run_normals(FOLDER, lcnet=[1])", "lcnet must be a path"),
    ("run_normals(FOLDER, method='l2', formats=None)", "formats must be text"),
    ("run_normals(FOLDER, method='l2', formats=[1, 2])", "formats must be text"),
    ("run_lights(None)", "path must be a path"),
    ("run_lights(FOLDER, weights=3.0)", "weights must be a path"),
    ("run_benchmark('diligent', root=5)", "root must be a path"),
    ("run_benchmark(5)", "benchmark must be one of"),
    ("compare_methods('diligent', ['l2', 'ps-fcn'], root=5)", "root must be a path"),
    ("compare_methods('diligent', 'l2')", "methods must be a list"),
    ("compare_methods('diligent', ['l2', 3])", "unknown --method 3"),
    ("compare_methods('diligent', ['l2', 'ps-fcn'], out=5)", "out must be a path"),
    ("compare_methods('diligent', ['l2', 'ps-fcn'], weights=5)", "weights must be a path"),
    ("run_depth(FOLDER, normals=3)", "normals must be a path"),
    ("open_capture(7)", "path must be a path"),
    ("load_network('ps-fcn', 5)", "weights must be a path"),
    ("estimate_lights(IMAGES, weights=1)", "weights must be a path"),
    ("estimate_normals(IMAGES, LIGHTS, method='ps-fcn', weights=1)", "weights must be a path"),
])
def test_path_arguments_of_the_wrong_kind_are_one_error(data, tmp_path, call, needle):
    """Python's own TypeError ('expected str, bytes or os.PathLike object') named no argument."""
    from psctl.api import run_normals
    from psctl.depth import run_depth
    from psctl.eval import compare_methods, run_benchmark
    from psctl.io.capture import open_capture
    from psctl.lights import run_lights
    from psctl.models.weights import load_network

    images, lights, mask, _ = data
    scope = {"run_normals": run_normals, "run_depth": run_depth, "run_benchmark": run_benchmark,
             "compare_methods": compare_methods,
             "open_capture": open_capture, "run_lights": run_lights, "load_network": load_network,
             "estimate_lights": estimate_lights, "estimate_normals": estimate_normals,
             "FOLDER": str(tmp_path), "IMAGES": images, "LIGHTS": lights}
    with pytest.raises(PsctlError, match=needle):
        eval(call, globals(), scope)


def test_given_lights_are_not_dropped(data, tmp_path):
    """Methods that do not read light directions refuse them instead of ignoring them."""
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    images, lights, mask, _ = data
    save_weights(tmp_path / "u.pt", PSFCN({"lights": False}), {"method": "ups-fcn", "train_images": 32})
    with pytest.raises(PsctlError, match="lights: ups-fcn does not use given light directions"):
        estimate_normals(images, lights, mask, method="ups-fcn", weights=tmp_path / "u.pt")


def test_angular_error_and_summary_values():
    """Known angles (sign matters: a flipped normal is 180 degrees, not 0; lengths do not), and
    the report's median and within-threshold fractions by value."""
    from psctl.metrics import angular_error, summarize

    z = np.array([0.0, 0.0, 1.0])
    est = np.array([[0, 0, 2.0], [1, 0, 0], [0, 0, -1], [1, 0, 1], [0, 3, 3 * np.sqrt(3)]])
    np.testing.assert_allclose(angular_error(est, np.tile(z, (5, 1))), [0, 90, 180, 45, 30], atol=1e-9)
    s = summarize(np.array([1.0, 2.0, 20.0, 25.0, 50.0]))
    assert s["mae"] == pytest.approx(19.6) and s["median"] == 20.0
    assert s["within"] == {"11.25": 0.4, "22.5": 0.6, "30": 0.8}
    assert summarize(np.array([11.25]))["within"]["11.25"] == 0.0  # strictly below the threshold


def test_angular_error_checks_its_inputs():
    from psctl.metrics import angular_error

    normals, mask = sphere(16)
    other = normals[::-1].copy()
    ref = angular_error(normals, other, mask)
    for m in (mask.astype(int), mask.astype(np.uint8) * 255, mask.astype(float),  # numbers, not indices
              mask[..., None]):  # [H, W, 1], as integrate_normals and estimate_normals take it
        assert np.array_equal(angular_error(normals, other, m), ref)
    assert angular_error(normals, other, np.zeros_like(mask)).size == 0  # an empty selection: no error values
    for args, needle in (((normals, other[:8]), "same shape"), ((normals, other[:1]), "same shape"),
                         ((normals[..., :2], other[..., :2]), r"\[..., 3\]"),
                         ((np.full((4, 4, 3), "a"), np.zeros((4, 4, 3))), "real numbers"),
                         ((normals, other, mask[:8]), "mask must be")):
        with pytest.raises(PsctlError, match=needle):
            angular_error(*args)
    assert angular_error(normals.tolist(), other.tolist(), mask).shape == ref.shape  # lists are fine
    # any stack of vectors with a mask of its shape: [N, 3] with [N], [B, H, W, 3] with [B, H, W]
    assert np.array_equal(angular_error(normals[mask], other[mask], np.ones(int(mask.sum()), bool)), ref)
    both = angular_error(np.stack([normals, normals]), np.stack([other, other]), np.stack([mask, mask]))
    assert np.array_equal(both, np.concatenate([ref, ref]))


def test_conventions_of_the_files(data):
    images, lights, mask, normals = data
    before = images.copy(), lights.copy(), mask.copy()
    ref = estimate_normals(images, lights, mask, method="l2")
    # integer arrays are scaled by their type's largest value, as image files are
    as16 = np.round(np.clip(images, 0, 1) * 65535).astype(np.uint16)
    np.testing.assert_allclose(estimate_normals(as16, lights, mask, method="l2"), ref, atol=1e-3)
    # light rows are normalised (l2 would not mind; the networks do); numeric masks: above 0.5
    from psctl.arrays import as_lights, as_mask

    np.testing.assert_allclose(as_lights(lights * 3, 12), lights, atol=1e-6)
    assert (as_mask(np.where(mask, 1.0, 0.3), mask.shape) == mask).all()
    assert (as_mask(mask.astype(np.uint8) * 255, mask.shape) == mask).all()
    np.testing.assert_allclose(estimate_normals(images, lights * 3, mask.astype(np.float32), method="l2"), ref,
                               atol=1e-6)
    for a, b in zip(before, (images, lights, mask)):  # inputs untouched
        np.testing.assert_array_equal(a, b)


def test_lights_refuse_black_images(data):
    from psctl.lights import array_lights
    from psctl.models.lcnet import LCNet

    images, _, mask, _ = data
    with pytest.raises(PsctlError, match="all images are black"):
        array_lights(np.zeros_like(images), mask, model=LCNet(), config={"device": "cpu", "views": 1})
    with pytest.raises(PsctlError, match="all images are black"):
        estimate_lights(np.zeros_like(images), mask, device="cpu", refine=False)  # before any weights are read


def test_depth_config_is_checked():
    from psctl.depth import integrate_normals

    normals, mask = sphere(24)
    for config, needle in (({"grazing_nzz": 0.1}, "unknown depth config keys: grazing_nzz"),
                           ({"grazing_nz": "a"}, "'grazing_nz' must be a finite number"),
                           ({"cg_maxiter": 2.5}, "'cg_maxiter' must be a finite integer"),
                           ({"cg_maxiter": 10 ** 400}, "'cg_maxiter' must be a finite integer"),
                           ({"cg_maxiter": 0}, "'cg_maxiter' must be at least 1"),  # gave a flat surface
                           ({"cg_rtol": 5.0}, "'cg_rtol' must be above 0 and at most 1"),
                           ({"grazing_nz": 2.0}, "'grazing_nz' must be above 0"),
                           ({"bilateral_iters": 0}, "'bilateral_iters' must be at least 1"),  # crashed
                           ([1], "config must be a dict")):
        with pytest.raises(PsctlError, match=needle):
            integrate_normals(normals, mask, config=config)
    z = integrate_normals(normals, mask, config={"cg_maxiter": 500.0})  # a whole float is fine
    assert np.isfinite(z[mask]).all()
    for bad, needle in ((np.round((normals + 1) / 2 * 65535).astype(np.uint16), "decode RGB codes with psctl.io.normals.decode_normal_pixels"),
                        (normals.astype(complex), "complex128")):
        with pytest.raises(PsctlError, match=needle):
            integrate_normals(bad, mask)
    with pytest.raises(PsctlError, match="real 3 x 3 matrix"):
        integrate_normals(normals, mask, K=[["a"] * 3] * 3)
    with pytest.raises(PsctlError, match="not a file name"):  # a string is a file name (test_depth)
        integrate_normals(normals, mask, K="abc")
    flat = np.zeros((8, 8, 3), int) + [0, 0, 1]  # signed integers that are unit vectors are vectors
    assert np.allclose(integrate_normals(flat, None), 0.0)


def test_depth_says_when_the_solve_stopped_short():
    from psctl.depth import integrate

    normals, mask = sphere(32)
    small = {"amg_max_coarse": 10}  # CG instead of the dense solve on this small sphere
    assert integrate(normals, mask, config=small).converged
    assert not integrate(normals, mask, config={**small, "cg_maxiter": 1}).converged


def test_grey_stacks_integer_masks_and_types(data):
    images, lights, mask, _ = data
    grey = images[..., 0][:, :, :3]  # 12 grey images 32 x 3: a stack, since 12 lights are given
    out = estimate_normals(grey, lights, None, method="l2")
    assert out.shape == (32, 3, 3)
    with pytest.raises(PsctlError, match=r"\[N, H, W, 1\]"):
        estimate_lights(grey, None, device="cpu", refine=False)  # no lights: ambiguous, refused
    from psctl.arrays import as_mask

    m255 = mask.astype(np.uint8) * 255
    assert (as_mask(m255, mask.shape) == mask).all()
    assert (as_mask(np.where(mask, 200, 100).astype(np.uint8), mask.shape) == mask).all()  # 100 / 255: background
    with pytest.raises(PsctlError, match="mask is empty"):
        as_mask(np.full(mask.shape, 100, np.uint8), mask.shape)  # 100 / 255 < 0.5, as in a mask file
    with pytest.raises(PsctlError, match="float, uint8 or uint16"):
        estimate_normals((images * 65535).astype(np.int32), lights, mask, method="l2")
    # other integer types say nothing by their largest value: nonzero is the object (numpy's
    # default int64 * 255 was an empty mask), and [H, W, 1] is squeezed
    for m in (mask.astype(np.int64) * 255, mask.astype(np.int32) * 2, mask.astype(np.uint32) * 7):
        assert (as_mask(m, mask.shape) == mask).all()
    assert (as_mask(mask[..., None].astype(np.uint8), mask.shape) == mask).all()
    from psctl.depth import integrate

    n = np.zeros((*mask.shape, 3), np.float32)
    n[..., 2] = 1
    assert integrate(n, mask.astype(np.int64) * 255).n_mask == mask.sum()  # read as estimate_normals reads it
    with pytest.raises(PsctlError, match="NaN"):
        integrate(n, np.where(mask, np.nan, 0.0))


def test_recipes_given_as_dicts():
    from psctl.train import DEFAULT_CONFIG, check_recipe, merge

    cfg = check_recipe(merge(DEFAULT_CONFIG, {"train": {"betas": (0.9, 0.99), "samples": 2.5e6,
                                                         "batch_size": np.int64(8), "lr": np.float32(1e-4)}}))
    assert cfg["train"]["samples"] == 2_500_000 and isinstance(cfg["train"]["samples"], int)
    assert cfg["train"]["betas"] == [0.9, 0.99] and cfg["train"]["batch_size"] == 8


def test_settings_take_the_kind_of_their_default():
    """One check for recipe values and depth settings: whole floats become ints, numpy scalars
    count as numbers, bools are not numbers, lists keep their length."""
    from psctl.errors import like_default

    assert like_default("k", 2.5e6, 1) == 2_500_000 and type(like_default("k", 2.5e6, 1)) is int
    assert type(like_default("k", np.float32(0.5), 1.0)) is float
    assert like_default("k", np.int64(3), 1) == 3
    assert like_default("k", (1, 2), [0.9, 0.99]) == [1.0, 2.0]
    for value, default in ((True, 1), (np.nan, 1.0), ("1e-3", 1.0), ([1.0], [0.9, 0.99]), (1, True)):
        with pytest.raises(PsctlError, match="'k' must be"):
            like_default("'k'", value, default)


def test_integrate_takes_tensors_that_require_grad():
    import torch

    from psctl.depth import integrate_normals

    n = np.zeros((8, 8, 3), np.float32)
    n[..., 2] = 1
    m = np.ones((8, 8), bool)
    z = integrate_normals(torch.tensor(n, requires_grad=True), torch.tensor(m))
    assert z.shape == (8, 8) and np.isfinite(z).all()


def _ps_fcn_file(folder):
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    return save_weights(folder / "p.pt", PSFCN(), {"method": "ps-fcn", "train_images": 32})


def test_top_level_functions_name_python_arguments(data, tmp_path):
    """psctl.X words its errors for Python callers; psctl.api.X (the CLI's) keeps the flags."""
    import psctl

    images, lights, mask, _ = data
    assert {"estimate_normals", "run_normals", "integrate_normals", "PsctlError"} <= set(dir(psctl))
    assert set(psctl.__all__) == {"__version__", *psctl._LAZY}
    with pytest.raises(PsctlError, match=r"^unknown device 'gpu'; choose from"):
        psctl.estimate_normals(images, lights, mask, method="l2", device="gpu")
    with pytest.raises(PsctlError, match=r"^light_distance must be a number"):
        psctl.estimate_normals(images, lights, mask, method="l2", light_distance=True)
    with pytest.raises(PsctlError, match="unknown --device 'gpu'"):  # the module's own: the CLI's words
        estimate_normals(images, lights, mask, method="l2", device="gpu")
    assert psctl.estimate_normals.__wrapped__ is estimate_normals and psctl.PsctlError is PsctlError
    assert psctl.estimate_normals is psctl.estimate_normals  # wrapped once
    import pickle
    import warnings

    assert pickle.loads(pickle.dumps(psctl.run_normals)) is psctl.run_normals  # for process pools
    with warnings.catch_warnings(record=True) as caught:  # the warning points at the caller's line
        warnings.simplefilter("always")
        psctl.estimate_normals(images[:2], lights[:2], mask, method="ps-fcn", weights=_ps_fcn_file(tmp_path))
    assert [w.filename for w in caught if issubclass(w.category, psctl.errors.PsctlWarning)] == [__file__]


@pytest.mark.parametrize("cli,python", [
    ("use --method l2", "use method='l2'"),
    ("--device cuda: no GPU; use --device cpu or auto", "device='cuda': no GPU; use device='cpu' or auto"),
    ("pass a weights file with --weights FILE", "pass a weights file with weights=FILE"),
    ("--light-distance 1 pixels does not clear", "light_distance=1 pixels does not clear"),
    ("--light-distance needs --refine", "light_distance needs refine=True"),
    ("--images must be at least 1", "n_images must be at least 1"),
    ("--roll/--no-roll is unused; --no-refine", "roll is unused; refine=False"),
    ("--benchmark folder needs --root DIR", "benchmark='folder' needs root=DIR"),
    ("use `psctl lights`, or --normals-weights", "use psctl.estimate_lights, or normals_weights"),
    ("`psctl train lcnet --config configs/lcnet.yaml --install`", "`psctl train lcnet --config configs/lcnet.yaml --install`"),
    ("a --weightsfile", "a --weightsfile"),
    ("/data/my--weights/x.pt: --weights FILE", "/data/my--weights/x.pt: weights=FILE"),  # paths stay
    ("/tmp/a--images/b.png and light--out.txt, --no-refine/", "/tmp/a--images/b.png and light--out.txt, refine=False/"),
])
def test_python_wording(cli, python):
    from psctl.errors import python_wording

    assert python_wording(cli) == python


def test_package_functions_word_their_notes_for_python(tmp_path):
    """psctl.run_normals' notes name Python arguments; psctl.api.run_normals' (the CLI's) flags."""
    import psctl
    import psctl.api
    from tests.conftest import write_capture

    write_capture(tmp_path / "o", n=6)
    assert psctl.api.run_normals(tmp_path / "o", method="l2", seed=3, write=False)["notes"] == [
        "images: --seed is unused without --images (all images used)"]
    assert psctl.run_normals(tmp_path / "o", method="l2", seed=3, write=False)["notes"] == [
        "images: seed is unused without n_images (all images used)"]


def test_more_wrong_inputs_are_one_error(data, tmp_path):
    """Found by a review: each of these raised Python's own error from deep inside, or said
    something misleading."""
    from psctl.api import run_normals
    from psctl.depth import depth_mesh, integrate, read_intrinsics
    from psctl.infer import array_normals
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    images, lights, mask, normals = data
    for m in (np.ones(5, bool), True):
        with pytest.raises(PsctlError, match=r"mask must be \[H, W\] = \[32, 32\]"):
            integrate(normals, m)
    for m in ("mask.png", tmp_path / "mask.png"):
        with pytest.raises(PsctlError, match="not the path .*psctl.load_mask"):
            estimate_normals(images, lights, m, method="l2")
        with pytest.raises(PsctlError, match="not the path"):
            integrate(normals, m)
    for method in ("l2", "sdps", "lcnet", None, 3):
        with pytest.raises(PsctlError, match="array_normals runs ps-fcn"):
            array_normals(images, lights, mask, method)
    save_weights(tmp_path / "u.pt", PSFCN({"lights": False}), {"method": "ups-fcn", "train_images": 32})
    save_weights(tmp_path / "p.pt", PSFCN(), {"method": "ps-fcn", "train_images": 32})
    with pytest.raises(PsctlError, match="from the images alone: pass lights=None"):
        array_normals(images, lights, mask, "UPS-FCN", tmp_path / "u.pt")
    with pytest.raises(PsctlError, match=r"needs light directions \(lights=None\)"):
        array_normals(images, None, mask, "ps-fcn", tmp_path / "p.pt")
    with pytest.raises(PsctlError, match="unknown inference setting 'chunks'"):
        array_normals(images, lights, mask, "ps-fcn", tmp_path / "p.pt", {"chunks": 2})
    with pytest.raises(PsctlError, match="light-distance must be a number of pixels, not '2400'"):
        estimate_normals(images, lights, mask, method="l2", light_distance="2400")
    depth = integrate(normals, mask).depth
    for bad in (depth[0], np.zeros((4, 4), int), depth.tolist()[0]):
        with pytest.raises(PsctlError, match=r"depth must be an \[H, W\] float map"):
            depth_mesh(bad)
    with pytest.raises(PsctlError, match=r"normals must be \[H, W, 3\] = \[32, 32, 3\]"):
        depth_mesh(depth, normals=normals[:5])
    assert len(depth_mesh(depth.tolist()).faces) == len(depth_mesh(depth).faces)  # a list is an array
    with pytest.raises(PsctlError, match="path must be a path"):
        read_intrinsics(np.eye(3))
    with pytest.raises(PsctlError, match="progress must be None or a callable"):
        run_normals(tmp_path, method="l2", progress=5)


def test_a_psctl_error_survives_pickling_and_copying():
    """A ProcessPoolExecutor hands a worker's exception back pickled: PsctlError(path, message)
    failed to unpickle (its args held only the formatted line) and broke the whole pool."""
    import copy
    import pickle

    for e in (PsctlError("/data/cat", "folder does not exist"), PsctlError(None, "no file involved")):
        for back in (pickle.loads(pickle.dumps(e)), copy.copy(e), copy.deepcopy(e)):
            assert type(back) is PsctlError and str(back) == str(e)
            assert (back.path, back.message) == (e.path, e.message)


def test_angular_error_of_two_vectors_and_of_encoded_pixels():
    import psctl

    got = psctl.angular_error(np.array([0, 0, 1.0]), np.array([0, 1, 1.0]))
    assert got.shape == () and float(got) == pytest.approx(45.0)
    assert np.isnan(psctl.angular_error([0, 0, np.nan], [0, 0, 1]))
    assert float(psctl.angular_error([0, 0, 1], [0, 0, 1])) == 0.0  # integer vectors are vectors
    pixels = np.full((2, 2, 3), 128, np.uint8)  # a normal map's PNG pixels, (n + 1) / 2
    with pytest.raises(PsctlError, match="dtype uint8 .*read_normal_map.*decode_normal_pixels"):
        psctl.angular_error(pixels, pixels)


def test_the_hints_decoder_takes_raw_codes():
    """check_vector_dtype sends uint8 / uint16 pixels to decode_normal_pixels; raw codes (PIL,
    imageio) came back all in one octant, 41.5 degrees off on a sphere (helper-196)."""
    import psctl
    from psctl.io.normals import decode_normal_pixels, encode_png

    yy, xx = np.mgrid[-1:1:33j, -1:1:33j]
    inside = xx ** 2 + yy ** 2 < 0.9
    n = np.dstack([xx, -yy, np.sqrt(np.clip(1 - xx ** 2 - yy ** 2, 0, 1))]) * inside[..., None]
    for bits, dtype, tol in ((8, np.uint8, 0.5), (16, np.uint16, 0.01)):
        codes = np.round(encode_png(n, inside) * np.iinfo(dtype).max).astype(dtype)  # as a PNG holds them
        got = decode_normal_pixels(codes)
        err = psctl.angular_error(got, n, mask=inside)
        assert float(np.nanmax(err)) < tol, bits
        assert not got[~inside].any()
        # as read_image gives them (divided by the largest code): the same normals
        np.testing.assert_allclose(decode_normal_pixels(codes / np.iinfo(dtype).max), got, atol=1e-6)
    for dtype in (np.int16, np.int64, bool):  # no PNG holds these: one vector everywhere before (helper-198)
        with pytest.raises(PsctlError, match="takes a PNG's uint8 or uint16 codes"):
            decode_normal_pixels(np.ones((2, 2, 3), dtype))


def test_bfloat16_tensors_are_taken_as_float32(data):
    torch = pytest.importorskip("torch")
    import psctl

    images, lights, mask, normals = data
    half = torch.from_numpy(np.ascontiguousarray(images)).to(torch.bfloat16)
    got = psctl.estimate_normals(half, torch.from_numpy(lights).to(torch.bfloat16), mask, method="l2")
    want = psctl.estimate_normals(half.float().numpy(), torch.from_numpy(lights).to(torch.bfloat16).float().numpy(),
                                  mask, method="l2")
    np.testing.assert_array_equal(got, want)


def test_public_functions_have_resolvable_type_hints_and_python_wording():
    import inspect
    import typing
    import warnings

    import psctl
    from psctl.errors import python_wording

    for name in psctl.__all__:
        obj = getattr(psctl, name)
        if inspect.isfunction(obj):
            typing.get_type_hints(obj)  # a name imported only for type checkers raised NameError
    assert issubclass(psctl.PsctlWarning, UserWarning)
    with warnings.catch_warnings():
        warnings.simplefilter("error", psctl.PsctlWarning)  # filterable by the exported class
        with pytest.raises(psctl.PsctlWarning):
            warnings.warn("x", psctl.PsctlWarning)
    assert python_wording("use --precision float32 or bf16") == "use precision='float32' or bf16"
    assert python_wording("--albedo: ups-fcn estimates no lights") == "albedo=True: ups-fcn estimates no lights"


def test_options_a_method_does_not_use_are_a_warning(data):
    """estimate_normals took views, precision, refine, ... that the method ignores without a word
    (run_normals notes them)."""
    import warnings

    import psctl

    images, lights, mask, _ = data
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        psctl.estimate_normals(images, lights, mask, method="l2", views=8, precision="bf16", refine=False)
        psctl.estimate_normals(images, lights, mask, method="l2")
    assert [str(w.message) for w in got] == [
        "l2: views=8, precision='bf16', refine=False unused (l2 solves each pixel alone, at full size, in float64; "
        "only sdps refines lights)"]
    assert got[0].category is psctl.PsctlWarning and got[0].filename == __file__


def test_refinement_options_sdps_or_estimate_lights_do_not_use_are_a_warning(data):
    """sdps and estimate_lights with refine=False took falloff, roll and precision without a
    word (run_normals and run_lights noted them; an audit found the array API's table had drifted)."""
    import warnings

    import psctl

    images, lights, mask, _ = data
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        psctl.estimate_normals(images, None, mask, method="sdps", refine=False, falloff="lambertian", roll=False,
                               device="cpu")
        psctl.estimate_lights(images, mask, refine=False, roll=True, precision="bf16", device="cpu")
        psctl.estimate_lights(images, mask, refine=False, device="cpu")  # nothing asked that goes unused
    assert [str(w.message) for w in got if issubclass(w.category, psctl.PsctlWarning)] == [
        "sdps: falloff='lambertian', roll=False unused (sdps refines lights only with refine=True)",
        "estimate_lights: roll=True, precision='bf16' unused (the refinement's, and refine=False)"]
    assert {w.filename for w in got} == {__file__}


def test_run_normals_and_estimate_normals_share_the_unused_option_table(tmp_path):
    """The notes psctl normals prints and the array API's warnings come from one table
    (psctl.api.unused_options): each option the table names is noted by run_normals."""
    from psctl.api import run_normals, unused_note, unused_options
    from tests.conftest import write_capture

    write_capture(tmp_path / "o", n=6)
    r = run_normals(tmp_path / "o", method="l2", views=8, downsample=2, precision="bf16", refine=False,
                    falloff="lambertian", write=False)
    table = unused_options("l2", False, 8, 2, "bf16", "lambertian", None)
    assert [k for k, _ in table] == ["falloff", "refine", "views", "downsample", "precision"]
    assert [n for n in r["notes"] if "unused" in n or "one pass" in n] == [unused_note(k, w, "bf16") for k, w in table]
    assert [unused_note(k, w, "bf16") for k, w in table] == [  # the words psctl normals prints
        "lights: --falloff is unused (only sdps refines lights)",
        "lights: --no-refine is unused (only sdps refines lights)",
        "views: l2 gives the same normals in every view; one pass",
        "downsample: l2 solves each pixel alone, at full size; unused",
        "precision: l2 solves in float64; --precision bf16 unused"]
    assert unused_note("roll", "refine") == "lights: --roll/--no-roll is unused without --refine"
    assert r["precision"] == "float32"


def test_estimate_lights_says_when_no_network_refines(data, tmp_path, fake_weights):
    """With LCNet alone installed estimate_lights cannot refine: options of the refinement are
    then a warning that says why (a review found that branch untested)."""
    import shutil
    import warnings

    import psctl
    from tests.conftest import weights_in

    images, _, mask, _ = data
    (tmp_path / "lc").mkdir()
    shutil.copy(fake_weights / "lcnet.pt", tmp_path / "lc")
    with weights_in(tmp_path / "lc"), warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        psctl.estimate_lights(images, mask, falloff="lambertian", device="cpu", views=1)
        psctl.estimate_lights(images, mask, device="cpu", views=1)  # nothing asked that goes unused
    assert [str(w.message) for w in got if issubclass(w.category, psctl.PsctlWarning)] == [
        "estimate_lights: falloff='lambertian' unused (the refinement's, and no normals network is installed to "
        "refine with: PS-FCN†, PS-FCN or PS-FCN+N)"]


def test_network_calls_leave_torchs_global_generator_as_it_was(data):
    """A notebook that seeds torch got other random numbers after any network call: building the
    layers drew their initial weights from the global generator (an audit). Now it is untouched."""
    import torch

    import psctl

    images, lights, mask, _ = data
    torch.manual_seed(0)
    want = torch.rand(3)
    torch.manual_seed(0)
    psctl.estimate_normals(images, lights, mask, method="ensemble", device="cpu")
    psctl.estimate_lights(images, mask, refine=True, device="cpu", views=1)  # LCNet, then PS-FCN's refinement
    assert torch.equal(torch.rand(3), want)


def test_a_report_names_what_made_it_and_its_image_subset(tmp_path, fake_weights, monkeypatch):
    """A report could not tell which weights, image subset or versions produced it (weights are
    replaced in place; an audit): it now records them (provenance; images_used and seed)."""
    import hashlib

    from psctl.api import run_normals
    from psctl.io.capture import select_images
    from tests.conftest import write_capture

    write_capture(tmp_path / "o", n=8, size=32)
    w = _ps_fcn_file(tmp_path)
    r = run_normals(tmp_path / "o", method="ps-fcn", weights=w, n_images=5, seed=3, write=False, device="cpu")
    p = r["provenance"]
    assert p["psctl"] and p["numpy"] == np.__version__ and p["device"] == "cpu" and p["torch"]
    assert p["weights"] == {"ps-fcn": {"path": str(Path(w).resolve()),
                                       "sha256": hashlib.sha256(Path(w).read_bytes()).hexdigest()}}
    assert r["seed"] == 3 and r["selection"] == "random" and len(r["images_used"]) == 5 and all((tmp_path / "o" / n).is_file() for n in r["images_used"])
    r = run_normals(tmp_path / "o", method="l2", write=False)
    assert r["provenance"]["weights"] == {} and r["provenance"]["device"] is None and "images_used" not in r
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))  # sdps: LCNet and its second stage
    r = run_normals(tmp_path / "o", method="sdps", write=False, device="cpu", views=1, refine=False)
    assert set(r["provenance"]["weights"]) == {"lcnet", "ps-fcn-dagger"}
    assert r["provenance"]["weights"]["lcnet"]["path"] == str(fake_weights / "lcnet.pt")
    from psctl.eval import run_benchmark

    write_capture(tmp_path / "root" / "a", n=6, size=24, seed=1)
    write_capture(tmp_path / "root" / "b", n=6, size=24, seed=2)
    res = run_benchmark("folder", root=tmp_path / "root", method="ps-fcn", weights=w, n_images=4, device="cpu")
    assert [o["provenance"]["weights"]["ps-fcn"]["sha256"] for o in res["objects"]] == [p["weights"]["ps-fcn"]["sha256"]] * 2
    assert all(len(o["images_used"]) == 4 and o["seed"] is None and o["selection"] == "spread" for o in res["objects"])
    # sdps reads no light directions: a random subset, drawn with seed 0 (the report said null)
    r = run_normals(tmp_path / "o", method="sdps", write=False, device="cpu", views=1, refine=False, n_images=5)
    assert r["selection"] == "random" and r["seed"] == 0 and r["images_used"] == [
        f"{i:03d}.png" for i in select_images(8, 5, 0) + 1], r["images_used"]


def test_a_weights_file_modified_during_the_run_is_flagged(tmp_path, fake_weights):
    """The digest is taken at the report: a weights file replaced while the run went on would be
    hashed as the new file, so the report says so (modified_during_run and a note) instead of
    naming it silently. The progress callback touches the file, mid-run; a file dated in the
    future (a tarball's, clock skew) is not flagged."""
    import os
    import shutil
    import time as _time

    from psctl.api import run_normals
    from psctl.lights import run_lights
    from tests.conftest import write_capture

    write_capture(tmp_path / "o", n=8, size=32)
    w = _ps_fcn_file(tmp_path)

    def touching(path):
        def progress(description, total):
            os.utime(path)  # now: after the run began
            return lambda n: None
        return progress

    later = _time.time() + 3600
    os.utime(w, (later, later))
    r = run_normals(tmp_path / "o", method="ps-fcn", weights=w, write=False, device="cpu")
    assert "modified_during_run" not in r["provenance"]["weights"]["ps-fcn"]
    assert not any(n.startswith("weights:") for n in r["notes"])
    _time.sleep(0.01)
    r = run_normals(tmp_path / "o", method="ps-fcn", weights=w, write=False, device="cpu", progress=touching(w))
    assert r["provenance"]["weights"]["ps-fcn"]["modified_during_run"] is True
    assert [n for n in r["notes"] if n.startswith("weights:")] == [
        f"weights: {Path(w).resolve()} was modified during the run; the report's sha256 is of the file as it is now, "
        "which may not be what the run read"]
    lc = tmp_path / "lcnet.pt"  # a copy: the fixture's files are shared with other tests
    shutil.copy(fake_weights / "lcnet.pt", lc)
    _time.sleep(0.01)
    r = run_lights(tmp_path / "o", weights=lc, write=False, device="cpu", views=1, refine=False,
                   progress=touching(lc))
    assert r["provenance"]["weights"]["lcnet"]["modified_during_run"] is True
    assert any(n.startswith(f"weights: {lc}") for n in r["notes"])


@pytest.mark.parametrize("given_mask", [True, False])
def test_l2_on_arrays_clamps_a_hot_pixel_as_on_a_folder(data, given_mask):
    """estimate_normals(method="l2") left an isolated hot value in (a QA helper's finding: its
    pixel 42 degrees off, silently, where the same images as a folder gave 0.01 and a note): now
    set to its neighbours' level, with a warning naming the image."""
    import warnings

    from psctl.metrics import angular_error

    images, lights, mask, normals = data
    clean = estimate_normals(images, lights, mask, method="l2")
    y, x = np.argwhere(mask & (normals[..., 2] > 0.9))[0]
    hot = images.copy()
    hot[3, y, x] = 1000.0
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        out = estimate_normals(hot, lights, mask if given_mask else None, method="l2")
    assert angular_error(out[y:y + 1, x:x + 1], clean[y:y + 1, x:x + 1]).max() < 3  # unclamped: 40 and more
    said = [str(w.message) for w in got if issubclass(w.category, PsctlWarning)]
    assert said == ["l2: images: 3 isolated hot pixel value(s) in 1 image(s) (image 4) set to their neighbours' "
                    "level (over 300 times the image's mean and 4 times every neighbour: a sensor's hot pixel?)"]
    with warnings.catch_warnings(record=True) as got:  # the clean images: no warning, the same normals
        warnings.simplefilter("always")
        np.testing.assert_array_equal(estimate_normals(images, lights, mask, method="l2"), clean)
    assert not [w for w in got if issubclass(w.category, PsctlWarning)]


def test_lights_and_sdps_on_arrays_without_a_mask_read_the_object_found(data, fake_weights):
    """mask=None: LCNet and the light fit read the object ``find_object`` finds (the array API
    took the whole frame, a QA helper: 1.75 -> 19.78 degrees on a sphere filling a quarter of a
    black frame): the lights of mask=found, and a warning that says so; none with a mask. sdps'
    second stage reads it too (since session 65), its normals on it and FOUND_GROW pixels around."""
    import warnings

    from psctl.api import _found_file_note
    from psctl.infer import FOUND_GROW, grow_mask
    from psctl.masks import find_object
    from tests.conftest import weights_in

    import psctl.lights as pl

    images, _, mask, _ = data
    found = find_object(images.sum((0, 3), dtype=np.float64))
    assert found.mask is not None and not (found.mask & ~mask).any()
    read, lcnet = [], pl.array_lights  # the masks LCNet reads
    with weights_in(fake_weights), warnings.catch_warnings(record=True) as got, pytest.MonkeyPatch.context() as mp:
        mp.setattr(pl, "array_lights", lambda im, m, *a, **k: read.append(m) or lcnet(im, m, *a, **k))
        warnings.simplefilter("always")
        none = estimate_lights(images, None, device="cpu", views=1)
        n_none = estimate_normals(images, None, None, method="sdps", device="cpu")
        assert len([w for w in got if issubclass(w.category, PsctlWarning)]) == 3
        same = estimate_lights(images, found.mask, device="cpu", views=1)
        n_found = estimate_normals(images, None, found.mask, method="sdps", device="cpu")
    for a, b in zip(none, same):
        np.testing.assert_array_equal(a, b)
    assert len(read) == 4 and all(np.array_equal(m, found.mask) for m in read)
    # LCNet, the fit and the second stage read the object; the normals cover it and FOUND_GROW
    # pixels around it (its rim), where the network answers from the object beside them
    grown = grow_mask(found.mask, FOUND_GROW)
    assert n_none.shape == mask.shape + (3,) and not n_none[~grown].any()
    assert (np.linalg.norm(n_none[grown], axis=-1) > 0.99).all()
    np.testing.assert_allclose(n_none[found.mask], n_found[found.mask], atol=1e-5)
    words = find_object(images.sum((0, 3), dtype=np.float64), reader="sdps").notes[0]
    assert words.startswith("LCNet, the light fit and the normals network read the object found")
    assert [str(w.message) for w in got if issubclass(w.category, PsctlWarning)] == [
        f"estimate_lights: mask=None: {found.notes[0]}", f"sdps: mask=None: {words}",
        f"sdps: mask=None: {_found_file_note(False)}"]
    assert {w.filename for w in got if issubclass(w.category, PsctlWarning)} == {__file__}


def test_find_object_fills_shadows_and_gives_up_on_a_lit_frame():
    """find_object: the lit pixels with their holes filled (a part shadowed in every image is
    still the object); the whole frame (None) when nothing is lit or the region covers nearly
    all of it; a note when the unlit part is not dark (a lit background)."""
    from psctl.masks import FOUND_MAX_FRACTION, find_object

    b = np.zeros((40, 50))
    yy, xx = np.mgrid[:40, :50]
    disc = (yy - 20) ** 2 + (xx - 22) ** 2 < 15 ** 2
    b[disc] = 5.0 + 0.01 * xx[disc]
    b[(yy - 20) ** 2 + (xx - 22) ** 2 < 4 ** 2] = 0.0  # shadowed in every image
    b[~disc] = 0.02
    f = find_object(b)
    assert np.array_equal(f.mask, disc) and f.info["used"] and f.info["pixels"] == disc.sum()
    assert len(f.notes) == 1 and f.info["contrast"] < 0.01
    grey = np.where(disc, b, 2.0)  # a lit background: darker than the object, but not dark
    g = find_object(grey)
    assert g.mask is not None and any("background is not dark" in n for n in g.notes)
    assert find_object(np.zeros((8, 8))).mask is None and "nothing is lit" in find_object(np.zeros((8, 8))).notes[0]
    speck = np.full((40, 50), 0.01)
    speck[:3, :3] = 5.0  # 9 lit pixels: no object (LCNet on them would say "all images are black")
    assert find_object(speck).mask is None and "has 9 pixels" in find_object(speck).notes[0]
    frame = np.full((40, 50), 3.0)
    frame[:, :2] = 0.01  # a dark strip: the lit region covers 96% of the frame
    h = find_object(frame)
    assert h.mask is None and h.info["frame_fraction"] > FOUND_MAX_FRACTION and "covers 96%" in h.notes[0]


def test_find_object_leaves_out_a_hole_through_the_object_and_lit_specks():
    """A hole as dark as the background around the object (a handle's, a ring's: DiLiGenT pot1 and
    pot2's were filled, given normals) is left out, with a note; a smaller or a brighter one (a
    hollow, a shadow) is still filled. Lit specks apart from the object (hot pixels: each was given
    normals 4 pixels around it) are dropped, a second object kept. The lights' reader is told when
    the object found covers much of the frame's border (a lit floor: LCNet's lights 22.8 degrees
    off in a review, 1.4 with the mask, and no word)."""
    from psctl.masks import find_object

    yy, xx = np.mgrid[:80, :100]
    r = np.hypot(yy - 40, xx - 40)
    ring = (r < 30) & (r >= 12)
    b = np.where(ring, 5.0, 0.02)
    b[(yy - 10) ** 2 + (xx - 88) ** 2 < 6 ** 2] = 4.0  # a second, small object (113 px)
    b[70, 5] = b[3, 60] = b[75, 95] = 9.0  # hot pixels
    f = find_object(b)
    second = (yy - 10) ** 2 + (xx - 88) ** 2 < 6 ** 2
    assert np.array_equal(f.mask, ring | second), (f.mask ^ (ring | second)).sum()
    assert any(f"{int((r < 12).sum())} pixels inside the object's outline" in n for n in f.notes)
    hollow = np.where(r < 12, 0.5, b)  # brighter than the background: a hollow of the object, filled
    g = find_object(hollow)
    assert g.mask[40, 40] and not any("inside the object's outline" in n for n in g.notes)
    floor = np.where(yy > 55, 3.0, b)  # a lit floor along the bottom
    assert any("covers" in n and "of the frame's border" in n for n in find_object(floor).notes)
    assert not any("frame's border" in n for n in f.notes)


def test_a_black_background_is_dark_whatever_the_objects_dim_rim():
    """A sphere before an exactly black background under oblique lights (a ring at 50 degrees): its
    rim is too dim for Otsu's lit part, so the unlit part is the black background plus that rim.
    Its mean over the lit part's was 0.17 ("the background is not dark", an audit's false note);
    the median, the background's own level, is 0."""
    from psctl.masks import find_object

    h = 32
    yy, xx = np.mgrid[:h, :h]
    nx, ny = (xx - (h - 1) / 2) / (0.45 * h), -(yy - (h - 1) / 2) / (0.45 * h)
    disc = nx ** 2 + ny ** 2 < 1
    normals = np.stack([nx, ny, np.sqrt(np.clip(1 - nx ** 2 - ny ** 2, 0, None))], -1) * disc[..., None]
    th = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    el = np.radians(50)
    lights = np.stack([np.cos(th) * np.sin(el), np.sin(th) * np.sin(el), np.full(12, np.cos(el))], -1)
    b = np.clip(np.einsum("hwc,nc->nhw", normals, lights), 0, None).sum(0)
    f = find_object(b)
    assert f.mask is not None and f.info["used"] and f.info["contrast"] == 0.0
    assert len(f.notes) == 1 and "not dark" not in f.notes[0]
    rim = disc & ~f.mask
    assert rim.sum() > 50 and b[~f.mask].mean() / b[f.mask].mean() > 0.15  # the dim rim, which the mean counted


def test_find_object_tells_a_lit_background_by_its_shading(tmp_path, fake_weights, monkeypatch):
    """Before a lit background (a textured table with the object's shadows on it) brightness cannot
    find the object; the background's one shading profile over the images can (the frame's border
    gives it): the object found by shading, for arrays and folders alike. A border that agrees on
    no profile (no plain background) leaves the brightness rule."""
    from scipy import ndimage

    from psctl.io.capture import open_capture
    from psctl.io.images import write_image
    from psctl.masks import array_shading, capture_shading, find_object
    from tests.conftest import render_lambertian

    normals, mask = sphere(48, radius=0.55)
    lights = hemisphere_lights(24, max_angle_deg=60, seed=4)
    rng = np.random.default_rng(0)
    tex = ndimage.gaussian_filter(rng.normal(size=mask.shape), 4)
    albedo = 0.2 + 0.4 * (tex - tex.min()) / np.ptp(tex)
    back = np.clip(lights[:, 2], 0, None)[:, None, None] * albedo
    yy, xx = np.mgrid[:48, :48]
    for k, lt in enumerate(lights):  # each light's shadow: the sphere's disc moved away from it
        dx, dy = -8 * lt[0] / lt[2], 8 * lt[1] / lt[2]
        back[k][((yy - 23.5 - dy) ** 2 + (xx - 23.5 - dx) ** 2 < (0.55 * 24) ** 2)] *= 0.15
    images = render_lambertian(normals, mask, lights, 0.5)
    images[:, ~mask] = back[:, ~mask][..., None]
    images += np.abs(rng.normal(0, 0.002, images.shape)).astype(np.float32)
    iou = lambda m: (m & mask).sum() / (m | mask).sum()  # noqa: E731
    by_light = find_object(images.sum((0, 3)))
    found = find_object(*array_shading(images))
    assert found.info["by"] == "shading" and found.info["used"] and iou(found.mask) > 0.95, iou(found.mask)
    assert by_light.info["by"] == "brightness" and (by_light.mask is None or iou(by_light.mask) < 0.8)
    assert any("told from it by shading" in n for n in found.notes)
    for k, img in enumerate(images):
        write_image(tmp_path / f"{k:03d}.png", img, "uint16", kind="linear")
    np.savetxt(tmp_path / "light_directions.txt", lights)
    brightness, profiles = capture_shading(open_capture(tmp_path))
    assert np.array_equal(find_object(brightness, profiles).mask, found.mask)
    monkeypatch.setenv("PSCTL_WEIGHTS", str(fake_weights))  # psctl lights and sdps read it so
    import psctl.lights
    import psctl.refine
    from psctl.api import run_normals

    fits = []
    fit = psctl.refine.refine_capture
    monkeypatch.setattr(psctl.refine, "refine_capture", lambda c, m, *a, **k: fits.append(m) or fit(c, m, *a, **k))
    report = psctl.lights.run_lights(tmp_path, write=False, device="cpu")
    assert report["found_object"] == found.info and np.array_equal(fits[-1], found.mask)
    assert run_normals(tmp_path, method="sdps", write=False, device="cpu")["found_object"] == found.info
    with pytest.warns(PsctlWarning) as caught:
        estimate_lights(images, None, device="cpu")
    said = [str(w.message) for w in caught]
    assert len(said) == 2 and "found by shading" in said[0] and "told from it by shading" in said[1], said
    dark = images.copy()  # a dark object before a white table: Otsu's lit part is the table
    dark[:, mask] *= 0.05
    dark[:, ~mask] *= 2.0
    assert find_object(dark.sum((0, 3))).mask is None  # the lit region: nearly all of the frame
    white = find_object(*array_shading(dark))
    assert white.info["by"] == "shading" and iou(white.mask) > 0.95, iou(white.mask)
    import psctl.masks

    monkeypatch.setattr(psctl.masks, "FOUND_PROFILE_SIDE", 16)  # 3 x 3 blocks: each pixel takes its cell's answer
    coarse = find_object(*array_shading(images))
    assert coarse.info["by"] == "shading" and not np.array_equal(coarse.mask, found.mask)
    # each pixel takes its block's answer (its centre pixel's): the outline within a block of the object's
    near = lambda m: ndimage.binary_dilation(m, np.ones((3, 3), bool), iterations=2)  # noqa: E731
    assert not (coarse.mask & ~near(mask)).any() and not (mask & ~near(coarse.mask)).any()
    assert np.array_equal(coarse.mask, np.kron(coarse.mask[::3, ::3], np.ones((3, 3), bool)))
    with pytest.raises(ValueError, match="profile_grid"):  # profiles of another grid: a caller's bug
        find_object(images.sum((0, 3)), array_shading(images[:, :40])[1])
    monkeypatch.undo()
    assert find_object(np.ones((40, 50))).mask is None  # a uniform frame: no contrast to speak of, no error
    noise = images.copy()  # a background of no one profile: each pixel lit at random
    noise[:, ~mask] = rng.uniform(0.1, 0.4, (len(images), int((~mask).sum()), 1))
    assert find_object(*array_shading(noise)).info["by"] == "brightness"


def test_networks_on_arrays_warn_when_they_clamp_a_hot_pixel(data, tmp_path):
    """The networks on arrays clamped hot values with a note no one saw (estimate_normals returns
    the normals alone): now a warning, as l2's."""
    import warnings

    images, lights, mask, normals = data
    y, x = np.argwhere(mask & (normals[..., 2] > 0.9))[0]
    hot = images.copy()
    hot[3, y, x] = 1000.0
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        estimate_normals(hot, lights, mask, method="ps-fcn", weights=_ps_fcn_file(tmp_path), device="cpu")
        estimate_normals(images, lights, mask, method="ps-fcn", weights=_ps_fcn_file(tmp_path), device="cpu")
    assert [str(w.message) for w in got if issubclass(w.category, PsctlWarning)] == [
        "ps-fcn: images: 3 isolated hot pixel value(s) in 1 image(s) (image 4) set to their neighbours' level (over "
        "300 times the image's mean and 4 times every neighbour: a sensor's hot pixel?)"]


def test_networks_without_a_mask_read_the_object_found(data, tmp_path):
    """Without a mask the networks read the object find_object finds, not the whole frame (the
    background beside the object, through +N or the exposure, spoilt the outline's normals;
    docs/models.md, "Without a mask"): the normals inside it are those of mask=found, and they
    cover it and FOUND_GROW pixels around it, 0 beyond. The array API warns, psctl normals notes
    it and writes the object as mask_found.png; where nothing is found the whole frame is read,
    with the old note. l2 and runs with a mask say nothing."""
    import warnings

    from psctl.api import _found_file_note, run_normals
    from psctl.infer import FOUND_GROW, NO_MASK_NETWORKS_WHY, grow_mask
    from psctl.io.images import read_image
    from psctl.io.capture import load_mask, open_capture
    from psctl.masks import FOUND_FILE, FOUND_NORMALS_BORDER, NO_MASK_PREFIX, array_shading, find_object, for_normals
    from psctl.metrics import angular_error
    from tests.conftest import write_capture

    images, lights, mask, _ = data
    w = _ps_fcn_file(tmp_path)
    found = find_object(images.sum((0, 3), dtype=np.float64), reader="normals")
    assert found.mask is not None and found.notes[0].startswith("the networks read the object found by brightness")
    grown = grow_mask(found.mask, FOUND_GROW)
    assert grown.sum() > found.mask.sum() and not grown.all()
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        none = estimate_normals(images, lights, None, method="ps-fcn", weights=w, device="cpu")
        given = estimate_normals(images, lights, found.mask, method="ps-fcn", weights=w, device="cpu")
        estimate_normals(images, lights, None, method="l2")
    assert [str(x.message) for x in got if issubclass(x.category, PsctlWarning)] == [
        f"ps-fcn: mask=None: {found.notes[0]}", f"ps-fcn: mask=None: {_found_file_note(False)}"]
    np.testing.assert_allclose(none[found.mask], given[found.mask], atol=1e-5)  # the network read the object only
    assert (np.linalg.norm(none[grown], axis=-1) > 0.99).all() and not none[~grown].any()
    whole = estimate_normals(images, lights, np.ones_like(mask), method="ps-fcn", weights=w, device="cpu")
    assert angular_error(none[found.mask], whole[found.mask]).max() > 1  # the whole frame's differ
    flat = np.ones_like(images)  # nothing to find: the whole frame, and the old words
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        out = estimate_normals(flat, lights, None, method="ps-fcn", weights=w, device="cpu")
    said = [str(x.message) for x in got if issubclass(x.category, PsctlWarning)]
    assert len(said) == 1 and said[0].endswith(NO_MASK_NETWORKS_WHY) and (np.linalg.norm(out, axis=-1) > 0.99).all()

    write_capture(tmp_path / "with", n=6, size=24)
    write_capture(tmp_path / "without", n=6, size=24, mask=False)
    note = NO_MASK_PREFIX + _found_file_note(True)
    for folder, method, said in (("with", "ps-fcn", False), ("without", "ps-fcn", True), ("without", "l2", False)):
        out = tmp_path / "out" / folder / method
        r = run_normals(tmp_path / folder, method=method, weights=w if method != "l2" else None, out=out,
                        device="cpu")
        assert (note in r["notes"]) == said and ((out / FOUND_FILE).is_file() == said), (folder, method)
        assert (r.get("found_object") is not None) == said
    arrays: dict = {}
    r = run_normals(tmp_path / "without", method="ps-fcn", weights=w, write=False, device="cpu", arrays=arrays)
    shown = read_image(tmp_path / "out" / "without" / "ps-fcn" / FOUND_FILE)[0][..., 0] > 0.5
    assert np.array_equal(arrays["mask"], grow_mask(shown, FOUND_GROW)) and r["n_mask_pixels"] == arrays["mask"].sum()
    assert NO_MASK_PREFIX + _found_file_note(False) in r["notes"]  # (no file written: no word of one)
    assert not any("mask pixels" in n for n in r["notes"])  # no note on the authors' count: no mask of the user's
    assert r["mae_missing_as_90"] is None and r["mae"] is not None  # (nor its value: it counted the ring at 90)
    from psctl.infer import DEFAULT_INFER  # a grow set by hand: the domain written follows the normals

    given: dict = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(DEFAULT_INFER, "grow", 1)
        run_normals(tmp_path / "with", method="ps-fcn", weights=w, write=False, device="cpu", arrays=given)
    ring = grow_mask(load_mask(open_capture(tmp_path / "with")), 1)
    assert np.array_equal(given["mask"], ring) and np.array_equal(np.abs(given["normals"]).sum(-1) > 0, ring)
    with pytest.raises(PsctlError, match=r"px across \(the object found without a mask is \d+ px\)"):
        run_normals(tmp_path / "without", method="ps-fcn", weights=w, write=False, device="cpu", downsample=8)
    alb: dict = {}
    r = run_normals(tmp_path / "without", method="ps-fcn", weights=w, write=False, device="cpu", albedo=True,
                    arrays=alb)
    assert alb["albedo"][shown].any() and not alb["albedo"][~shown].any()  # the object's, not the ring's
    assert any(n.startswith(f"albedo: {r['albedo']['n_undetermined']} of {shown.sum()} object pixels") for n in r["notes"])
    # a surface that fills the frame (no background): brightness splits it, and the unlit part is not
    # dark; before a lit background the same: the networks read the whole frame (a review: 2.53 -> 16.99)
    filling, fmask = sphere(32, 2.0)
    assert fmask.all()
    bright = render_lambertian(filling, fmask, lights, 0.7)
    lit_bg = np.where(mask[None, ..., None], images, 0.3 * np.clip(lights[:, 2], 0, None)[:, None, None, None])
    half = np.full(filling.shape, 0.7, np.float32)
    half[:, 16:] = 0.05  # its right half dark: the unlit part looks like a dark background, but lies on the border
    dark_half = render_lambertian(filling, fmask, lights, half)
    assert find_object(*array_shading(dark_half)).info["border"] > FOUND_NORMALS_BORDER
    for frame, by in ((bright, "brightness"), (lit_bg, None), (dark_half, "brightness")):
        info = find_object(*array_shading(frame), reader="lights").info
        assert info["used"] and (by is None or info["by"] == by) and not for_normals(info), info
        with warnings.catch_warnings(record=True) as got:
            warnings.simplefilter("always")
            out = estimate_normals(frame, lights, None, method="ps-fcn", weights=w, device="cpu")
        said = [str(x.message) for x in got if issubclass(x.category, PsctlWarning)]
        assert len(said) == 1 and "what is left out may be part of the object" in said[0], said
        assert said[0].endswith(NO_MASK_NETWORKS_WHY) and (np.linalg.norm(out, axis=-1) > 0.99).all()
        whole = estimate_normals(frame, lights, np.ones_like(mask), method="ps-fcn", weights=w, device="cpu")
        np.testing.assert_allclose(out, whole, atol=1e-5)
        sd = find_object(*array_shading(frame), reader="sdps")  # sdps: LCNet reads it, its network the frame
        assert sd.mask is not None and sd.normals_mask is None and sd.notes[1].startswith("the normals network: ")
    # the ground truth's pixels the object found misses are scored, at 90 degrees (no normal)
    from psctl.io.images import write_image

    dark = write_capture(tmp_path / "cut", n=6, size=24, mask=False)
    for k, img in enumerate(dark["images"]):
        img[:, :9] = 0  # the sphere's left part unlit in every image: not found
        write_image(tmp_path / "cut" / f"{k + 1:03d}.png", img, "uint16", kind="linear")
    truth = np.linalg.norm(dark["normals"], axis=-1) > 0.5
    cut: dict = {}
    r = run_normals(tmp_path / "cut", method="ps-fcn", weights=w, write=False, device="cpu", arrays=cut)
    missed = truth & ~cut["mask"]
    assert missed.sum() >= 10 and r["n_evaluated_pixels"] == truth.sum()
    assert (cut["error"][missed] == 90).all() and r["mae"] > 90 * missed.sum() / truth.sum()
    assert any(n.startswith(f"scoring: {missed.sum()} pixels with a ground-truth normal lie beyond") for n in r["notes"])
    # psctl eval's picture shows those pixels too (its panel covers the pixels scored)
    import psctl.io.report as rep
    from psctl.eval import run_benchmark

    panels, panel = [], rep.object_panel
    monkeypatch = pytest.MonkeyPatch()
    monkeypatch.setattr(rep, "object_panel", lambda *a, **k: panels.append(a[4]) or panel(*a, **k))
    try:
        (tmp_path / "root").mkdir()
        (tmp_path / "root" / "cut").symlink_to(tmp_path / "cut")
        run_benchmark("folder", tmp_path / "root", "ps-fcn", weights=w, device="cpu", out=tmp_path / "ev")
    finally:
        monkeypatch.undo()
    assert len(panels) == 1 and np.array_equal(panels[0], cut["mask"] | truth)


def test_no_decoding_helper_where_an_earlier_pass_kept_every_image(tmp_path, monkeypatch):
    """Without a mask the search decodes every image first (kept in a DecodeMemo): the networks'
    pass then starts no helper to decode them again (a review: it served none of them); its
    setting is checked all the same (a second review)."""
    import psctl.io.prefetch as pp
    from psctl.infer import DEFAULT_INFER, _prefetch, first_read_box
    from psctl.io.capture import DecodeMemo, iter_images, load_mask, open_capture
    from tests.conftest import write_capture

    write_capture(tmp_path / "cap", n=5, size=24)
    cap = open_capture(tmp_path / "cap")
    mask = load_mask(cap)
    started, real = [], pp.prefetch  # the helpers asked for a region (box None: none started)
    monkeypatch.setattr(pp, "prefetch", lambda paths, box, size, mb: started.append(box is not None and mb > 0)
                        or real(paths, None, size, mb))
    memo = DecodeMemo(1 << 26)
    box = first_read_box(cap, mask, {})
    for held, want in ((0, True), (4, True), (5, False)):  # images kept before the networks' pass
        list(iter_images(cap.subset(range(held)), box, memo=memo))
        started.clear()
        _prefetch(cap, mask, {}, memo)
        assert any(started) == want, held
    started.clear()
    _prefetch(cap, mask, {}, None)
    assert any(started) and DEFAULT_INFER["prefetch_mb"] > 0
    with pytest.raises(PsctlError, match="prefetch_mb must be a whole number"):
        _prefetch(cap, mask, {"prefetch_mb": -1}, memo)


def test_lcnets_changed_values_are_warnings(data, tmp_path, fake_weights):
    """estimate_lights and sdps dropped LCNet's notes of values it changed (helper-172): images on
    a 0-255 scale, which the exposure guard scales, and a clamped hot pixel warned from
    estimate_normals' l2 and networks but not there. Both are PsctlWarnings now."""
    import shutil
    import warnings

    import psctl
    from psctl.hotpixels import HOT_PIXEL_WORDS
    from psctl.lights import EXPOSURE_WORDS
    from tests.conftest import weights_in

    images, _, mask, _ = data
    (tmp_path / "lc").mkdir()
    shutil.copy(fake_weights / "lcnet.pt", tmp_path / "lc")
    shutil.copy(fake_weights / "ps_fcn_dagger.pt", tmp_path / "lc")
    hot = images.copy()
    ys, xs = np.nonzero(mask)
    hot[2, ys[len(ys) // 2], xs[len(xs) // 2]] = 1000.0
    with weights_in(tmp_path / "lc"):
        for call in (lambda x: psctl.estimate_lights(x, mask, device="cpu", views=1, refine=False),
                     lambda x: psctl.estimate_normals(x, None, mask, method="sdps", device="cpu", refine=False)):
            for x, words in ((images * 255, EXPOSURE_WORDS), (hot, HOT_PIXEL_WORDS)):
                with warnings.catch_warnings(record=True) as got:
                    warnings.simplefilter("always")
                    call(x)
                said = [str(w.message) for w in got if issubclass(w.category, psctl.PsctlWarning)]
                assert any(words in s for s in said), said
                assert all(w.filename == __file__ for w in got if words in str(w.message))  # the caller's line


def test_estimate_lights_checks_its_options_before_any_work(data, tmp_path):
    """decode, views and device were checked after LCNet's weights loaded and the mask snapped
    (helper-172: 1.6 s, then the error); with no weights installed the error is still the option's."""
    import psctl
    from tests.conftest import weights_in

    images, _, mask, _ = data
    (tmp_path / "none").mkdir()
    with weights_in(tmp_path / "none"):
        for kwargs, words in (({"decode": "mean"}, "unknown decode 'mean'"), ({"views": 3}, "views must be"),
                              ({"device": "tpu"}, "unknown device 'tpu'")):
            with pytest.raises(psctl.PsctlError, match=words):
                psctl.estimate_lights(images, mask, **kwargs)


def test_a_path_or_none_for_images_says_what_to_pass(data):
    """A folder's path as images gave "got dtype <U21" (helper-172)."""
    import psctl

    _, lights, mask, _ = data
    with pytest.raises(psctl.PsctlError, match=r"not 'cap'; read a capture folder's images with psctl.load_images"):
        psctl.estimate_normals("cap", lights, mask)
    with pytest.raises(psctl.PsctlError, match="array, not None$"):
        psctl.estimate_lights(None, mask)
    with pytest.raises(psctl.PsctlError, match="array, not a list of file names; read them with psctl.load_images"):
        psctl.estimate_normals(["a.png", "b.png", "c.png"], lights[:3], mask)


def test_report_docstrings_name_every_key():
    """run_normals' and run_lights' docstrings list the report's keys; three had been left out
    (provenance; precision, found_object: helper-196)."""
    import re

    import psctl
    from psctl.lights import run_lights

    example = Path(__file__).resolve().parents[1] / "examples" / "bumpy_sphere"
    for fn, report in ((psctl.run_normals, psctl.run_normals(example, method="l2", write=False, n_images=8)),
                       (run_lights, run_lights(example, write=False, refine=False))):
        words = set(re.findall(r"\w+", fn.__doc__))
        assert not set(report) - words, (fn.__name__, sorted(set(report) - words))


def test_metric_helpers_refuse_what_they_cannot_score():
    """helper-196: summarize gave mae NaN beside a 'within' that counted NaN as a miss,
    intensity_relative_error inf with a RuntimeWarning on a 0 and numpy's matmul error on
    mismatched lengths; angular_error's mask error lacked its prefix; formats=[] said "unknown
    formats ''"."""
    import warnings

    import psctl
    from psctl.io.normals import parse_formats
    from psctl.metrics import intensity_relative_error, summarize

    assert summarize([1.0, 3.0])["mae"] == 2.0
    with pytest.raises(PsctlError, match="summarize: 1 of 3 errors are NaN or infinite"):
        summarize([1.0, np.nan, 3.0])
    assert intensity_relative_error([1.0, 2.0], [2.0, 4.0]) == pytest.approx(0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for est, gt, needle in (([1.0, 2.0], [0.0, 4.0], "the true ones above 0"),
                                ([1.0, 2.0], [1.0, np.nan], "must be finite"),
                                ([1.0, 2.0, 3.0], [1.0, 2.0], "3 estimates but 2 true intensities")):
            with pytest.raises(PsctlError, match=needle):
                intensity_relative_error(est, gt)
    v = np.ones((2, 2, 3))
    with pytest.raises(PsctlError, match="^angular_error: mask contains NaN"):
        psctl.angular_error(v, v, mask=np.full((2, 2), np.nan))
    for spec in ("", " , "):
        with pytest.raises(PsctlError, match="no output format given; choose one or more of png16"):
            parse_formats(spec)
